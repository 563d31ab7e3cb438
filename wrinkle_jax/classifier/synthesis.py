"""Material by analysis-by-synthesis (issue 25): re-simulate the input garment with each known
fabric, driven by the input's own body and pin tracks, and compare motion features.

    input sequence (frames (T, V, 3), mesh + UV pattern, pins (T, P, 3), capsules (T, C, 2, 3))
      --build_cloth(mesh, pins)-->  a solver model of the INPUT garment (rest = its UV layout)
      --for each fabric m: settle from frame 0, then simulate frames 0..N-1 on the input's
        tracks-->  syntheses S_m (N, V, 3)
      --motion features per window (same windows, same body motion)-->  d_m = weighted mean
        squared difference of input and S_m features --> p_m = softmax(-d_m / T)

Why: the motion features (`motion`) are offset by the garment's cut and the dance more than by
the fabric, and 10 training garments cannot teach that offset away. A synthesis on the same mesh
and the same motion carries the same offset, so comparing the input with each synthesis
cancels it (tested: a shift added to both does not change the distance).

What an input must carry: the garment mesh with its UV pattern in meters (`uv_units`), the
pinned vertices and their track, and the body's capsules per frame (the simulator's `.npz`
files do). Wind is not in the files: the synthesis runs in still air (air drag on).

Cost: `num_fabrics x (settle + N)` coarse frames per classified sequence: 5 x 76 frames at 80
substeps without self-collision took a median 16 s per sequence (20 substeps: 4 s) on two
shared CPU cores (experiments/results/classifier/README.md, session 23).

What it needs to work (measured there): the synthesis must strain like the input. With the
synthesis at 20 substeps and the inputs at 80, leave-one-garment-out CV fell from 0.98 to 0.72;
the held-out inputs (same simulator, same fabrics) scored 0.76.

Conventions: meters, seconds, z up. Pure NumPy/JAX; the solver is `wrinkle_jax.sim.xpbd`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier import calibrated, motion
from wrinkle_jax.mesh import Garment
from wrinkle_jax.sim import selfcollision, xpbd
from wrinkle_jax.sim.colliders import Colliders
from wrinkle_jax.sim.materials import Fabric, fabric
from wrinkle_jax.sim.selfcollision import SelfCollisionConfig


class SynthesisError(ValueError):
    """The input cannot be re-simulated (no pins, no body track, too few frames)."""


@dataclasses.dataclass(frozen=True)
class SynthesisConfig:
    """Static settings of a synthesis (hashable).

    Attributes:
      frames: synthesized frames N (frame 0 = the end of the settle), at the input's fps.
      settle_frames: frames simulated before frame 0 with the body and pins frozen at the
        input's frame 0 and extra damping, starting from the input's frame 0 at rest (so each
        fabric hangs in its own drape before the motion starts; 0: start exactly there).
      settle_damping: extra velocity damping during the settle, 1/s.
      substeps: solver substeps per frame. stretch_sweeps: stretch sweeps per substep.
      self_collision: a `SelfCollisionConfig` or None (off).
      chunk: frames per jitted call.
    """

    frames: int = 64
    settle_frames: int = 12
    settle_damping: float = 3.0
    substeps: int = 20
    stretch_sweeps: int = 2
    self_collision: SelfCollisionConfig | None = None
    chunk: int = 38

    def sim_config(self, fps: float) -> xpbd.SimConfig:
        return xpbd.SimConfig(fps=fps, substeps=self.substeps, iterations=1,
                              stretch_sweeps=self.stretch_sweeps,
                              self_collision=self.self_collision)


def config_from_metadata(metadata: Mapping, **changes) -> SynthesisConfig:
    """The solver settings a simulated file records (metadata "substeps", "stretch_sweeps",
    "self_collision"), as a `SynthesisConfig` (other fields from `changes`)."""
    sc = metadata.get("self_collision")
    base = SynthesisConfig(substeps=int(metadata.get("substeps", 20)),
                           stretch_sweeps=int(metadata.get("stretch_sweeps", 2)),
                           self_collision=None if not sc else selfcollision.recorded_config(sc))
    return dataclasses.replace(base, **changes)


def check_input(arrays: Mapping) -> str:
    """'' when `arrays` (a dict of a sequence `.npz`'s arrays) can be re-simulated, else the
    reason (no pin track, no UV pattern, ...)."""
    for key in ("frames", "faces", "uvs", "uv_faces"):
        if key not in arrays:
            return f"the input has no {key!r}"
    if "pins" not in arrays or "pin_vertices" not in arrays or not np.size(arrays["pins"]):
        return "the input has no pin track (pins, pin_vertices): nothing holds the garment up"
    meta = arrays.get("metadata")
    if meta is not None:
        units = json.loads(str(meta)).get("uv_units") if not isinstance(meta, dict) \
            else meta.get("uv_units")
        if units not in (None, "meters"):
            return f"the UVs are in {units!r}, not a sewing pattern in meters"
    return ""


def input_garment(arrays: Mapping) -> Garment:
    """The input's garment at frame 0 (vertices (V, 3) m; UVs = its pattern in meters)."""
    panels = arrays.get("panels")
    return Garment(np.asarray(arrays["frames"][0], np.float32),
                   np.asarray(arrays["faces"], np.int32), np.asarray(arrays["uvs"], np.float32),
                   np.asarray(arrays["uv_faces"], np.int32),
                   None if panels is None else np.asarray(panels, np.int32))


def build_model(arrays: Mapping) -> xpbd.ClothModel:
    """The solver model of the input garment: rest = its UV pattern, its pins, still air."""
    why = check_input(arrays)
    if why:
        raise SynthesisError(why)
    return xpbd.build_cloth(input_garment(arrays), np.asarray(arrays["pin_vertices"]),
                            wind=None, use_aero=True)


def input_drives(arrays: Mapping, frames: int, settle_frames: int,
                 settle_damping: float) -> xpbd.Drive:
    """Drives at settle_frames + frames boundaries: the input's frame 0 repeated over the
    settle (extra damping), then its frames 0..frames-1 (pins, capsules, spheres).

    Returns an `xpbd.Drive` with a leading axis of settle_frames + frames.
    """
    total = int(arrays["frames"].shape[0])
    if frames > total:
        raise SynthesisError(f"the input has {total} frames, fewer than {frames}")
    idx = np.r_[np.zeros(settle_frames, np.int64), np.arange(frames)]
    fps = float(arrays.get("fps", 30.0))
    t0 = float(np.asarray(arrays["times"])[0]) if "times" in arrays else 0.0
    time = t0 + (np.arange(len(idx)) - settle_frames) / fps
    col = Colliders()
    if "capsule_ends" in arrays:
        ends = np.asarray(arrays["capsule_ends"], np.float32)[idx]
        radii = np.broadcast_to(np.asarray(arrays["capsule_radii"], np.float32),
                                ends.shape[:2])
        col = col.replace(capsule_ends=jnp.asarray(ends), capsule_radii=jnp.asarray(radii))
    if "sphere_centers" in arrays:
        c = np.asarray(arrays["sphere_centers"], np.float32)[idx]
        r = np.broadcast_to(np.asarray(arrays["sphere_radii"], np.float32), c.shape[:2])
        col = col.replace(sphere_centers=jnp.asarray(c), sphere_radii=jnp.asarray(r))
    damping = np.where(np.arange(len(idx)) < settle_frames, settle_damping, 0.0)
    return xpbd.Drive(time=jnp.asarray(time, jnp.float32),
                      pins=jnp.asarray(np.asarray(arrays["pins"], np.float32)[idx]),
                      colliders=col, extra_damping=jnp.asarray(damping, jnp.float32))


def scaled_fabric(fab: Fabric | str, density: float = 1.0, stiffness: float = 1.0) -> Fabric:
    """A fabric with its mass per area x `density` and its stretch and bending stiffness x
    `stiffness` (the model-mismatch tests)."""
    f = fabric(fab) if isinstance(fab, str) else fab
    return f.replace(density=f.density * density, stretch=f.stretch * stiffness,
                     bending=f.bending * stiffness)


def synthesize(arrays: Mapping, fab: Fabric | str, config: SynthesisConfig = SynthesisConfig(),
               model: xpbd.ClothModel | None = None, start=None) -> np.ndarray:
    """Re-simulate the input garment with fabric `fab` on the input's own tracks.

    Args:
      arrays: a simulated sequence's arrays (`.npz`: frames (T, V, 3) m, faces, uvs (meters),
        uv_faces, panels, pins (T, P, 3), pin_vertices (P,), capsule_ends (T, C, 2, 3),
        capsule_radii (C,), optional sphere_centers/radii, times, fps).
      fab: a `Fabric` or a name in `wrinkle_jax.MATERIALS`.
      config: `SynthesisConfig`.
      model: `build_model(arrays)` (built when None; pass it to reuse across fabrics).
      start: optional (positions (V, 3), velocities (V, 3)) to start from instead of the
        input's frame 0 at rest (tests; with settle_frames 0 and the input's own fabric and
        solver this reproduces the input).
    Returns:
      (config.frames, V, 3) float32 synthesized frames, meters; frame k is at the time of the
      input's frame k.
    """
    f = fabric(fab) if isinstance(fab, str) else fab
    model = build_model(arrays) if model is None else model
    fps = float(arrays.get("fps", 30.0))
    cfg = config.sim_config(fps)
    drives = input_drives(arrays, config.frames, config.settle_frames, config.settle_damping)
    init_fn, _ = xpbd.cloth_simulator(cfg)
    if start is None:
        state = init_fn(model, np.asarray(arrays["frames"][0], np.float32))
    else:
        state = init_fn(model, np.asarray(start[0], np.float32))
        state = dataclasses.replace(state, v=jnp.asarray(start[1], jnp.float32))
    _, xs = xpbd.simulate_frames(cfg, model, xpbd.fabric_params(f), state, drives,
                                 config.chunk)
    x0 = np.asarray(state.x)[None] if config.settle_frames == 0 else \
        xs[config.settle_frames - 1:config.settle_frames]
    return np.concatenate([x0, xs[config.settle_frames:]])[:config.frames]


def synthesize_all(arrays: Mapping, config: SynthesisConfig = SynthesisConfig(),
                   fabrics: Mapping[str, Fabric] | None = None) -> dict[str, np.ndarray]:
    """`synthesize` with every fabric (default: `MATERIALS` in order): name -> (N, V, 3)."""
    model = build_model(arrays)
    fabrics = {m: fabric(m) for m in MATERIALS} if fabrics is None else fabrics
    return {m: synthesize(arrays, f, config, model) for m, f in fabrics.items()}


# --------------------------------------------------------------------------------------------
# Comparing an input with its syntheses
# --------------------------------------------------------------------------------------------


def window_features(arrays: Mapping, frames: np.ndarray, window: int = 32,
                    stride: int = 16, drape_plan=None) -> np.ndarray:
    """Motion features (`motion.sequence_features`) of `frames` (N, V, 3) driven by the
    input's tracks (its frames 0..N-1): (W, motion.FEATURE_DIM) per window."""
    n = len(frames)
    topo = motion.make_topology(arrays["faces"], arrays["uvs"], arrays["uv_faces"])
    ref = motion.reference_track(arrays)[:n]
    caps = arrays.get("capsule_ends")
    return motion.sequence_features(np.asarray(frames), ref, topo,
                                    float(arrays.get("fps", 30.0)), window, stride,
                                    None if caps is None else np.asarray(caps)[:n],
                                    drape_plan=drape_plan)


def feature_mask(families) -> np.ndarray:
    """(motion.FEATURE_DIM,) bool: the columns of the given families."""
    sl = motion.family_slices()
    mask = np.zeros(motion.FEATURE_DIM, bool)
    for f in families:
        mask[sl[f]] = True
    return mask


def differences(input_features, synth_features) -> np.ndarray:
    """Input minus synthesis features per window and fabric.

    Args:
      input_features: (W, D) the input's window features.
      synth_features: (M, W, D) each fabric's synthesis' window features (same windows).
    Returns:
      (M, W, D) float64.
    """
    x = np.asarray(input_features, np.float64)
    s = np.asarray(synth_features, np.float64)
    if s.shape[1:] != x.shape:
        raise ValueError(f"window features {x.shape} and syntheses {s.shape} do not align")
    return x[None] - s


def mean_squares(diffs, scale, agg: str = "window") -> np.ndarray:
    """(M, D) squared scaled differences per fabric and feature: agg "window" averages the
    squares over windows (mean_w (diff / scale)^2), "mean" squares the mean over windows
    ((mean_w diff / scale)^2: window noise averages out first)."""
    z = np.asarray(diffs, np.float64) / np.asarray(scale, np.float64)
    if agg == "window":
        return (z ** 2).mean(axis=1)
    if agg == "mean":
        return z.mean(axis=1) ** 2
    raise ValueError(f"agg must be 'window' or 'mean', got {agg!r}")


def distances(diffs, scale, weights=None, agg: str = "window") -> np.ndarray:
    """Scaled squared difference per fabric: the study's and the shipped classifier's distance.

    Args:
      diffs: (M, W, D) `differences`.
      scale: (D,) positive per-feature scales (a typical between-fabric difference).
      weights: (D,) non-negative feature weights from `fit_weights` (0 drops a feature; not
        normalized: their size acts as an inverse temperature), or None: the mean over features.
      agg: see `mean_squares`.
    Returns:
      (M,) d_m = sum_j w_j q_mj (or mean_j q_mj), q = `mean_squares(diffs, scale, agg)`.
    """
    q = mean_squares(diffs, scale, agg)
    return q.mean(-1) if weights is None else q @ np.asarray(weights, np.float64)


@functools.partial(jax.jit, static_argnames="steps")
def _fit_weights(q, y, l2, steps: int):
    def loss(u):
        w = jax.nn.softplus(u)
        ll = jax.nn.log_softmax(-(q @ w), axis=-1)[jnp.arange(y.shape[0]), y]
        return -ll.mean() + l2 * jnp.sum(w ** 2)

    u = calibrated.lbfgs_minimize(loss, jnp.full(q.shape[-1], -2.0), steps)
    return jax.nn.softplus(u)


def fit_weights(q, labels, l2: float = 0.1, steps: int = 200) -> np.ndarray:
    """Non-negative feature weights w (D,) of the distance d_m = q_m . w, fitted by a
    conditional logit (softmax(-d) over fabrics, cross-entropy + l2 |w|^2, L-BFGS).

    Args:
      q: (S, M, D) `mean_squares` of S training inputs. labels: (S,) true fabric indices.
    Returns:
      (D,) float64 weights (their overall size is an inverse temperature; calibrate after).
    """
    w = _fit_weights(jnp.asarray(q, jnp.float32), jnp.asarray(labels, jnp.int32),
                     jnp.float32(l2), int(steps))
    return np.asarray(w, np.float64)


def difference_scale(diffs_list, floor: float = 1e-6) -> np.ndarray:
    """(D,) per-feature scale: the RMS over sequences, fabrics and windows of the differences
    `diffs_list` (a list of (M, W, D)) of TRAINING inputs (floored)."""
    z = np.concatenate([np.asarray(d, np.float64).reshape(-1, np.shape(d)[-1])
                        for d in diffs_list])
    return np.maximum(np.sqrt((z ** 2).mean(axis=0)), floor)


def scores_to_probs(dist, temperature: float) -> np.ndarray:
    """softmax(-d / T): (..., M) probabilities from (..., M) distances."""
    z = -np.asarray(dist, np.float64) / temperature
    z = z - z.max(axis=-1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=-1, keepdims=True)
