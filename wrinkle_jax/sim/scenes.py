"""Frozen, seeded scene configurations and `simulate`, the simulator's public entry point.

Scenes (`SCENES`; z up, the mannequin faces +y; 30 fps):

  training
    sheet_balls_wind      a 1 m sheet hanging from 6 rings, hit by two moving balls under
                          gusty wind (the paper's base data)
    skirt_dance           long flared 4-gore skirt on the mannequin dancing (samba-like)
    pleated_skirt_dance2  pleated skirt, a second dance (spins, kicks, jumps)
    shawl_dance2          rectangular shawl hanging down the back from the shoulders, dance 2
    apron_dance           apron hanging in front of the legs from the waist, dance
    circle_skirt_dance2   knee-length circle skirt (288-degree flare), dance 2
    long_shawl_dance      long wide shawl down the back to the calves, dance
    skirt_dance2          the flared skirt, dance 2
    apron_dance2          the apron, dance 2
  validation only (a garment neither training nor the held-out sets contain; checkpoint and
  recipe choices read it)
    tabard_dance2         narrow front panel hanging from the shoulders, dance 2
  test only (unseen garments and an unseen motion)
    dress_dance           sleeveless A-line dress (front/back, side + shoulder seams), dance
    cape_walk             circular cape fastened at the neck, walking (unseen motion)
    skirt_walk            the flared skirt, walking (seen garment, unseen motion)

Every scene starts with a pre-roll (body at rest, pins gliding onto the body, extra damping)
that is simulated but not returned. `simulate(...)` returns a `SimulatedSequence`: a
`GarmentSequence` (frames (T, V, 3) float32 m; UVs = pattern coordinates in meters) whose
metadata holds the material, PD, seed, solver settings and the scene config as JSON, and
whose `tracks` (pin and collider tracks per returned frame) are written by `save_simulation`
as extra arrays of the `.npz` bundle.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, __version__, material_index
from wrinkle_jax.meshio import GarmentSequence, make_sequence, save_sequence
from wrinkle_jax.sim import aero, mannequin, patterns, resume, selfcollision, xpbd
from wrinkle_jax.sim.colliders import Colliders, attach_rigid, blend_pins, to_local
from wrinkle_jax.sim.materials import fabric
from wrinkle_jax.sim.selfcollision import SelfCollisionConfig

RESOLUTIONS = {"fine": 0.010, "coarse": 0.030}  # particle distance (PD), meters

# Self-collision settings per resolution of the data set's scenes (the measurements behind
# each choice, session by session: experiments/results/sim/README.md). Thickness ~0.3-0.4 PD
# (vertex-triangle contacts only; thinner lets edges cross between contacts on coarse meshes);
# candidates rebuilt every 4 substeps with a margin covering ~2 m/s of relative motion over
# them; same-panel pairs nearer at rest than the rest exclusion are skipped, so a flat layer
# adds no candidates. Fine meshes use the blocked flat build (`selfcollision_blocks`: bounds on
# totals, the nearest kept; per-vertex bounds dropped most of the contacts that mattered) with
# the 2 nearest contacts per vertex; coarse keeps 1. Measured on skirt_dance fine: 2.03 % ->
# 0.003 % intersecting faces at ~5x the cost of a run without self-collision. Fine runs add one
# body_relax round (session 39): layers pressed on a body no longer stay pinched. The sheet's
# wool file, every 6th frame: max 0.92 -> 0.55 %, mean 0.024 -> 0.015 % (whole run); restarts
# of the sheet's ball events: denim 0.95 -> 0.29 %, knit 2.75 -> 1.79 %; skirt_dance2 silk's
# worst frames 0.13 -> 0.10 %. Two or three rounds were worse (experiments/results/sim).
SELF_COLLISION = {
    "fine": SelfCollisionConfig(thickness=0.004, margin=0.014, rebuild_every=4,
                                rest_exclusion=0.024, pairs_per_vertex=2.0,
                                raw_per_vertex=560.0, box_per_vertex=16.0, block=8,
                                body_relax=1),
    "coarse": SelfCollisionConfig(thickness=0.009, margin=0.015, rebuild_every=4,
                                  rest_exclusion=0.042, pairs_per_vertex=1.0,
                                  raw_per_vertex=400.0, box_per_vertex=16.0, block=8),
}

# The substeps per frame SELF_COLLISION was tuned at. Its margin covers the relative motion over
# one rebuild interval (4 substeps = 1/150 s at 30 fps), so `self_collision_config` keeps that
# interval in time, not in substeps, when a run uses more substeps.
SELF_COLLISION_SUBSTEPS = 20

# Solver substeps of the data set's coarse (PD 30 mm) sequences (make_sequences, the classifier's
# training and held-out sequences). At the scenes' 20 the coarse solver is softer than any
# fabric's stretch stiffness and every fabric strains alike; at 80 the knit and the heavy woven
# separate (mean log strain, experiments/results/classifier/coarse_substeps_s20.json).
DATASET_COARSE_SUBSTEPS = 80


# Seed of the test scenes' files: an unseen performance of their motion (training and
# validation scenes use seed 0).
TEST_SEED = 1


def dataset_seed(scene: str | SceneConfig) -> int:
    """The seed of a scene's files in the data set (`experiments.make_sequences`)."""
    sc = get_scene(scene) if isinstance(scene, str) else scene
    return TEST_SEED if sc.test_only else 0


def dataset_solver(scene: str | SceneConfig,
                   resolution: str) -> tuple[int, SelfCollisionConfig]:
    """Solver substeps per frame and self-collision settings of the data set's sequences of
    `scene` at "fine" or "coarse" (what `experiments.make_sequences` writes by default; the
    evaluations simulate a missing sequence with the same): coarse at
    `DATASET_COARSE_SUBSTEPS`, fine at the scene's own substeps, self-collision on at both
    (`self_collision_config`). Files record them as metadata "substeps" and "self_collision".
    """
    sc = get_scene(scene) if isinstance(scene, str) else scene
    substeps = DATASET_COARSE_SUBSTEPS if resolution == "coarse" else None
    return (sc.substeps if substeps is None else substeps,
            self_collision_config(resolution, substeps, sc))


def self_collision_config(resolution: str, substeps: int | None = None,
                          scene: str | SceneConfig | None = None) -> SelfCollisionConfig:
    """`SELF_COLLISION[resolution]` for a run of `substeps` solver substeps per frame.

    Candidates are rebuilt at most as far apart in time as at `SELF_COLLISION_SUBSTEPS`:
    rebuild_every becomes the largest divisor of `substeps` (the solver needs one) not above
    rebuild_every x substeps / 20, so the margin still covers the motion between rebuilds and
    more substeps do not multiply the build cost (80 substeps: every 16).

    Args:
      resolution: "fine" or "coarse". substeps: solver substeps per frame (None: 20).
      scene: optional; a scene's `fine_self_collision` overrides the fine defaults (its
        rebuild interval counts substeps of 20 per frame, like the default's).
    Raises:
      SceneError: unknown resolution or substeps < 1.
    """
    if resolution not in SELF_COLLISION:
        raise SceneError(f"no self-collision settings for resolution {resolution!r}; "
                         f"choose one of {sorted(SELF_COLLISION)}")
    base = SELF_COLLISION[resolution]
    sc = get_scene(scene) if isinstance(scene, str) else scene
    if resolution == "fine" and sc is not None and sc.fine_self_collision:
        over = dict(sc.fine_self_collision)
        unknown = set(over) - {f.name for f in dataclasses.fields(SelfCollisionConfig)}
        if unknown:
            raise SceneError(f"scene {sc.name!r}: fine_self_collision names no setting "
                             f"{sorted(unknown)}")
        base = dataclasses.replace(base, **over)
    if substeps is None or substeps == SELF_COLLISION_SUBSTEPS:
        return base
    if substeps < 1:
        raise SceneError(f"substeps must be >= 1, got {substeps}")
    return dataclasses.replace(base, rebuild_every=rebuild_interval(
        base.rebuild_every, SELF_COLLISION_SUBSTEPS, substeps))


def rebuild_interval(rebuild_every: int, substeps: int, new_substeps: int) -> int:
    """`rebuild_every` substeps at `substeps` per frame, kept in time at `new_substeps`: the
    largest divisor of new_substeps (the solver needs one) not above that, at least 1."""
    ideal = rebuild_every * new_substeps // substeps
    return max([d for d in range(1, ideal + 1) if new_substeps % d == 0], default=1)


class SceneError(ValueError):
    """Unknown scene, material or resolution, or invalid simulation arguments."""


@dataclasses.dataclass(frozen=True)
class WindSpec:
    """Mean wind (m/s) and gust/turbulence levels (see `aero.make_wind`)."""

    mean: tuple = (0.0, 1.5, 0.0)
    gustiness: float = 0.6
    swing: float = 0.35
    turbulence: float = 0.3


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """A scene (static, hashable).

    Attributes:
      name: scene id.
      garment: key of `patterns.GARMENTS`.
      motion: mannequin motion (`mannequin.MOTIONS`), or None for no body.
      pins: "rings" (sheet), or a pattern landmark ("waist", "shoulders", "neck"); where its
        vertices attach is the pattern's `pin_targets` (in place if it has none).
      attach_to: mannequin frame the pins follow ("pelvis", "chest") or None (static).
      balls: number of moving balls (0 = none; the solver then traces no sphere code).
      wind: WindSpec or None (still air; air drag is always on).
      preroll_s: simulated, unreturned seconds before t = 0.
      attach_s: seconds over which the pins glide onto their targets.
      preroll_damping: extra velocity damping during the pre-roll, 1/s.
      substeps: solver substeps per frame (30 fps). stretch_sweeps: stretch sweeps per substep.
      frames: default number of returned frames.
      test_only: never used for training (held-out evaluation).
      val_only: never used for training; the validation garment that checkpoint and recipe
        choices read (so held-out scenes need not).
      fine_self_collision: (name, value) pairs overriding `SELF_COLLISION["fine"]` where the
        motion needs more than the default (`self_collision_config`), e.g. the walk's shins
        kick the flared skirt's hem faster than the 14 mm margin covers in 4 substeps, so
        skirt_walk rebuilds every 2 (and projects the self-contacts 3 times after the body
        contacts). () = the default.
    """

    name: str
    garment: str
    motion: str | None
    pins: str
    attach_to: str | None
    balls: int = 0
    wind: WindSpec | None = None
    preroll_s: float = 1.5
    attach_s: float = 0.7
    preroll_damping: float = 3.0
    substeps: int = 20
    stretch_sweeps: int = 2
    frames: int = 300
    test_only: bool = False
    val_only: bool = False
    description: str = ""
    fine_self_collision: tuple[tuple[str, float], ...] = ()

    def to_json(self) -> str:
        d = dataclasses.asdict(self)
        if not d["val_only"]:  # keeps the JSON (and stored simulations' match) of older scenes
            del d["val_only"]
        # A solver setting, recorded with the others in a file's "self_collision" metadata
        # (and matched there, `evaluation.cells`); kept out of the scene's identity so the
        # coarse files, which it does not touch, still match.
        del d["fine_self_collision"]
        return json.dumps(d, sort_keys=True)


SCENES = {s.name: s for s in (
    SceneConfig("sheet_balls_wind", "sheet", None, "rings", None, balls=2, wind=WindSpec(),
                preroll_s=1.0, attach_s=0.0, preroll_damping=2.0,
                description="1 m sheet hanging from 6 rings, two moving balls, gusty wind"),
    SceneConfig("skirt_dance", "flared_skirt", "dance", "waist", "pelvis",
                description="long flared 4-gore skirt, samba-like dance"),
    # Session 32: three post-body passes (as skirt_dance2, by the same rule): knit_terry
    # continuation of frames 96-130, 0.45 % -> 0.40 % intersecting faces at the worst frame.
    SceneConfig("pleated_skirt_dance2", "pleated_skirt", "dance2", "waist", "pelvis",
                fine_self_collision=(("post_passes", 3),),
                description="pleated skirt (16 pleats), modern dance with spins and kicks"),
    SceneConfig("shawl_dance2", "shawl", "dance2", "top", "chest",
                description="shawl hanging down the back from the shoulders, dance 2"),
    SceneConfig("apron_dance", "apron", "dance", "top", "pelvis",
                description="apron hanging in front of the legs from the waist, dance"),
    # Session 13: more garments and garment/motion pairs for the enhancer's training set.
    SceneConfig("circle_skirt_dance2", "circle_skirt", "dance2", "waist", "pelvis",
                description="knee-length circle skirt (288-degree flare, 6 gores), dance 2"),
    SceneConfig("long_shawl_dance", "long_shawl", "dance", "top", "chest",
                description="long wide shawl down the back to the calves, dance"),
    # Session 25: rebuilt every 2 substeps at PD 10 mm, by the rule written before its
    # screen (results/sim/self_collision_rule_s25.txt): at every 4, knit_terry intersected on
    # 0.38 % of faces over 300 frames, 3.6 % in one frame.
    # Session 32: three passes of the self-contacts after the body contacts instead of one
    # (results/sim/self_collision_rule_s32.txt): a knit_terry continuation of frames 36-70,
    # 2.21 % -> 0.66 % intersecting faces at the worst frame.
    # Session 37: rest exclusion 14 mm instead of 24 (results/sim/README.md): 72 % of an
    # episode's crossed pairs were folds through themselves 14-18 mm apart in the pattern,
    # which the 24 mm exclusion kept out of the contacts; knit_terry every 6th frame over
    # frames 0-594, max 1.05 % -> 0.23 % (mean 0.19 -> 0.03); fine cost 1.26x per frame.
    SceneConfig("skirt_dance2", "flared_skirt", "dance2", "waist", "pelvis",
                fine_self_collision=(("rebuild_every", 2), ("post_passes", 3),
                                     ("rest_exclusion", 0.014)),
                description="long flared 4-gore skirt, dance 2"),
    SceneConfig("apron_dance2", "apron", "dance2", "top", "pelvis",
                description="apron hanging in front of the legs from the waist, dance 2"),
    SceneConfig("tabard_dance2", "tabard", "dance2", "top", "chest", val_only=True,
                description="VAL: narrow front panel from the shoulders (unseen garment), "
                            "dance 2"),
    SceneConfig("dress_dance", "dress", "dance", "shoulders", "chest", test_only=True,
                description="TEST: sleeveless A-line dress (unseen garment), dance"),
    SceneConfig("cape_walk", "cape", "walk", "neck", "chest", preroll_s=2.0, test_only=True,
                description="TEST: circular cape (unseen garment), walk (unseen motion)"),
    # Session 25: rebuilt every 2 substeps at PD 10 mm. At every 4, silk and wool both
    # intersected on 0.84 % of faces (a 300-frame file each); frames 0-120, silk: 0.95 % ->
    # 0.074 % at 1.4-1.6x the cost, while larger candidate bounds did not help (1.34 %) and
    # two projection passes helped less (0.54 %); the whole re-simulated silk file: 0.26 %
    # (experiments/results/sim/README.md).
    # Session 32: three post-body passes, as skirt_dance2: the shins press the hem into
    # itself, and a crossing, once made, is kept. Continuations of the stored files at the
    # worst frames: denim_light 1.86 % -> 0.31 %, silk_charmeuse 3.05 % -> 0.27 %.
    SceneConfig("skirt_walk", "flared_skirt", "walk", "waist", "pelvis", test_only=True,
                fine_self_collision=(("rebuild_every", 2), ("post_passes", 3)),
                description="TEST: flared skirt, walk (unseen motion)"),
)}
TRAINING_SCENES = tuple(n for n, s in SCENES.items() if not (s.test_only or s.val_only))
VAL_SCENES = tuple(n for n, s in SCENES.items() if s.val_only)
TEST_SCENES = tuple(n for n, s in SCENES.items() if s.test_only)


def get_scene(name: str) -> SceneConfig:
    try:
        return SCENES[name]
    except KeyError:
        raise SceneError(f"unknown scene {name!r}; expected one of {', '.join(SCENES)}") from None


def resolution_pd(resolution: str | float) -> float:
    """PD in meters of "fine" (10 mm), "coarse" (30 mm) or an explicit number of meters."""
    if isinstance(resolution, str):
        try:
            return RESOLUTIONS[resolution]
        except KeyError:
            raise SceneError(f"unknown resolution {resolution!r}; expected fine or coarse") \
                from None
    pd = float(resolution)
    if not 0.002 <= pd <= 0.2:
        raise SceneError(f"particle distance {pd} m is outside [0.002, 0.2]")
    return pd


@dataclasses.dataclass(frozen=True)
class SimulatedSequence(GarmentSequence):
    """A `GarmentSequence` plus kinematic tracks per returned frame (NumPy arrays):
    pins (T, P, 3), pin_vertices (P,), sphere_centers (T, S, 3), sphere_radii (S,),
    capsule_ends (T, C, 2, 3), capsule_radii (C,) (absent kinds omitted)."""

    tracks: dict = dataclasses.field(default_factory=dict)


def save_simulation(path, seq: SimulatedSequence) -> None:
    """Write a simulated sequence and its tracks as one `.npz` (atomically)."""
    save_sequence(path, seq, **seq.tracks)


# --------------------------------------------------------------------------------------------
# Scene assembly (NumPy)
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class SceneSetup:
    """Everything `simulate` needs: the mesh, the model and the drives (T_total + 1 frames)."""

    scene: SceneConfig
    mesh: patterns.PatternMesh
    model: xpbd.ClothModel
    drives: xpbd.Drive
    pin_vertices: np.ndarray
    preroll_frames: int


def _ball_tracks(times: np.ndarray, count: int, seed: int):
    """Two balls (r = 0.12 m) pushing into the sheet from either side, seeded paths."""
    rng = np.random.default_rng(seed + 7)
    tp = np.maximum(times, 0.0)
    centers = []
    for b in range(count):
        side = -1.0 if b % 2 == 0 else 1.0
        f = rng.uniform(0.3, 0.5)
        push = np.maximum(np.sin(2 * np.pi * f * tp + rng.uniform(0, 2 * np.pi)), 0.0) ** 2
        x = rng.uniform(-0.25, 0.25) + 0.2 * np.sin(2 * np.pi * rng.uniform(0.1, 0.3) * tp
                                                     + rng.uniform(0, 2 * np.pi))
        z = rng.uniform(0.9, 1.3) + 0.15 * np.sin(2 * np.pi * rng.uniform(0.1, 0.3) * tp
                                                   + rng.uniform(0, 2 * np.pi))
        y = side * (0.45 - 0.55 * push)
        centers.append(np.stack([x, y, z], -1))
    return np.stack(centers, 1).astype(np.float32), np.full(count, 0.12, np.float32)


def _pins(scene: SceneConfig, pattern, mesh, frames, n_pre: int, attach_frames: int):
    """Pinned vertices (P,) and their tracks (T, P, 3)."""
    g = mesh.garment
    x0 = np.asarray(g.vertices, np.float64)
    if scene.pins == "rings":
        top = mesh.landmark_vertices(pattern, "top")
        xs = x0[top, 0]
        rings = np.linspace(xs.min(), xs.max(), 6)
        pins = np.unique(top[np.argmin(np.abs(xs[None] - rings[:, None]), axis=1)])
        n = len(frames["time"])
        return pins, np.broadcast_to(x0[pins], (n,) + x0[pins].shape).astype(np.float32)
    pins = mesh.landmark_vertices(pattern, scene.pins)
    p0 = x0[pins]
    # The pattern says where its landmark attaches (skirt waists close onto the waistband,
    # the cape's inner arc onto a ring around the neck); others (dress shoulders, panel
    # tops) stay where the drape put them.
    to_target = pattern.pin_targets.get(scene.pins)
    target = p0 if to_target is None else to_target(p0)
    body_frames = frames[scene.attach_to]
    local = to_local(target, body_frames[0])
    world = attach_rigid(local, body_frames)
    return pins, blend_pins(p0, world, attach_frames)


def setup_scene(scene: str | SceneConfig, resolution: str | float, frames: int, seed: int = 0,
                mesh_seed: int = 0, fps: float = 30.0) -> SceneSetup:
    """Mesh the garment and build the solver model and kinematic drives (NumPy, once).

    Args:
      scene: name or config. resolution: "fine", "coarse" or a PD in meters.
      frames: returned frames (the pre-roll is added). seed: motion, balls and wind.
      mesh_seed: lattice jitter of the mesh (kept fixed so every material and seed of a scene
        shares one mesh and UV layout).
    """
    sc = get_scene(scene) if isinstance(scene, str) else scene
    if frames < 1:
        raise SceneError(f"frames must be >= 1, got {frames}")
    pd = resolution_pd(resolution)
    pattern = patterns.make_pattern(sc.garment)
    mesh = patterns.mesh_pattern(pattern, pd, seed=mesh_seed)
    n_pre = max(1, int(round(sc.preroll_s * fps)))
    times = (np.arange(n_pre + frames) - n_pre) / fps  # frame boundaries
    kin: dict = {"time": times}
    col = Colliders()
    if sc.motion is not None:
        ends, radii, body_frames = mannequin.body_tracks(sc.motion, times, seed)
        kin.update(body_frames)
        col = col.replace(capsule_ends=jnp.asarray(ends),
                          capsule_radii=jnp.asarray(np.broadcast_to(radii, ends.shape[:2])))
    if sc.balls:
        centers, radii = _ball_tracks(times, sc.balls, seed)
        col = col.replace(sphere_centers=jnp.asarray(centers),
                          sphere_radii=jnp.asarray(np.broadcast_to(radii, centers.shape[:2])))
    pins, pin_track = _pins(sc, pattern, mesh, kin, n_pre, int(round(sc.attach_s * fps)))
    wind = None
    if sc.wind is not None:
        wind = aero.make_wind(jax.random.fold_in(jax.random.PRNGKey(seed), 17), sc.wind.mean,
                              sc.wind.gustiness, sc.wind.swing, sc.wind.turbulence)
    model = xpbd.build_cloth(mesh.garment, pins, wind=wind, use_aero=True)
    damping = np.where(np.arange(len(times)) < n_pre, sc.preroll_damping, 0.0)
    drives = xpbd.Drive(time=jnp.asarray(times, jnp.float32), pins=jnp.asarray(pin_track),
                        colliders=col, extra_damping=jnp.asarray(damping, jnp.float32))
    return SceneSetup(sc, mesh, model, drives, pins, n_pre)


def simulate(scene: str | SceneConfig, material: str, resolution: str | float = "fine",
             frames: int | None = None, seed: int = 0, substeps: int | None = None,
             iterations: int = 1, progress: Callable[[int, int], None] | None = None,
             chunk: int = 30, setup: SceneSetup | None = None,
             self_collision: xpbd.SelfCollisionConfig | None = None,
             checkpoint: str | os.PathLike | None = None,
             checkpoint_every_s: float = 300.0) -> SimulatedSequence:
    """Simulate a scene with one material at one resolution.

    Args:
      scene: a name in `SCENES` or a SceneConfig.
      material: a name in `wrinkle_jax.MATERIALS`.
      resolution: "fine" (PD 10 mm), "coarse" (PD 30 mm) or a PD in meters.
      frames: returned frames at 30 fps (default: the scene's).
      seed: seeds the motion, balls and wind (same seed -> bit-identical result).
      substeps, iterations: solver settings (default: the scene's substeps, 1 sweep).
      progress: optional callback(done_frames, total_frames) including the pre-roll.
      chunk: frames per jitted call.
      setup: a prebuilt `setup_scene(...)` (to reuse a mesh and model across materials).
      self_collision: a `SelfCollisionConfig`, or None (off, the default). Its settings and
        the dropped-candidate counts (`self_overflow`) are recorded in the metadata.
      checkpoint: optional path (`resume`): the state and frames are written there every
        `checkpoint_every_s` seconds of simulation; a call with the same settings resumes
        from it (bit-identical to an uninterrupted run; the metadata's `resumed_at_frame`
        says where), and it is deleted when the simulation completes.
    Returns:
      SimulatedSequence (see the module docstring).

    Example:
      >>> seq = simulate("sheet_balls_wind", "silk_chiffon", "coarse", frames=2)  # doctest: +SKIP
      >>> seq.frames.shape[0]
      2
    """
    sc = get_scene(scene) if isinstance(scene, str) else scene
    if material not in MATERIALS:
        material_index(material)  # raises a ValueError naming the choices
    frames = sc.frames if frames is None else int(frames)
    if setup is None:
        setup = setup_scene(sc, resolution, frames, seed)
    config = xpbd.SimConfig(fps=30.0, substeps=sc.substeps if substeps is None else substeps,
                            iterations=iterations, stretch_sweeps=sc.stretch_sweeps,
                            self_collision=self_collision)
    fab = fabric(material)
    params = xpbd.fabric_params(fab)
    init_fn, _ = xpbd.cloth_simulator(config)
    state = init_fn(setup.model, setup.mesh.garment.vertices)
    total = setup.preroll_frames + frames - 1
    key = json.dumps({"scene": sc.to_json(), "material": material, "resolution": resolution,
                      "frames": frames, "seed": int(seed), "substeps": config.substeps,
                      "iterations": iterations, "chunk": int(chunk),
                      "stretch_sweeps": config.stretch_sweeps, "generator": __version__,
                      "self_collision": selfcollision.key_settings(self_collision)},
                     sort_keys=True)
    got = resume.load(checkpoint, key) if checkpoint is not None else None
    start, prior, wall0 = 0, [], 0.0
    if got is not None:
        start, saved, frames_done, wall0 = got
        state = jax.tree_util.tree_map(jnp.asarray, saved)
        prior = [frames_done]
    writer = (None if checkpoint is None
              else resume.Writer(checkpoint, key, checkpoint_every_s, prior, wall0))
    done = [start]

    def tick(n):
        done[0] += n
        if progress is not None:
            progress(done[0], total)

    if start and progress is not None:
        progress(start, total)
    t0 = time.perf_counter()
    final, xs = xpbd.simulate_frames(config, setup.model, params, state, setup.drives, chunk,
                                     tick, start=start, on_chunk=writer)
    wall = wall0 + time.perf_counter() - t0
    if prior:
        xs = np.concatenate(prior + [xs])
    out = xs[setup.preroll_frames - 1:]
    g = setup.mesh.garment
    keep = np.arange(setup.preroll_frames, setup.preroll_frames + frames)
    c = setup.drives.colliders
    tracks = {"pins": np.asarray(setup.drives.pins)[keep],
              "pin_vertices": setup.pin_vertices.astype(np.int32),
              "times": np.asarray(setup.drives.time)[keep]}
    if c.sphere_centers is not None:
        tracks["sphere_centers"] = np.asarray(c.sphere_centers)[keep]
        tracks["sphere_radii"] = np.asarray(c.sphere_radii)[0]
    if c.capsule_ends is not None:
        tracks["capsule_ends"] = np.asarray(c.capsule_ends)[keep]
        tracks["capsule_radii"] = np.asarray(c.capsule_radii)[0]
    pd = setup.mesh.pd
    meta = {
        "generator": f"wrinkle_jax.sim {__version__}",
        "scene": sc.name,
        "scene_config": sc.to_json(),
        "test_only": sc.test_only,
        "material": material,
        "material_index": material_index(material),
        "fabric": dataclasses.asdict(fab),
        "resolution": resolution if isinstance(resolution, str) else "custom",
        "pd": pd,
        "pd_mm": round(pd * 1e3, 3),
        "seed": int(seed),
        "fps": 30.0,
        "substeps": config.substeps,
        "iterations": config.iterations,
        "stretch_sweeps": config.stretch_sweeps,
        "preroll_frames": setup.preroll_frames,
        "self_collision": None if self_collision is None
        else dataclasses.asdict(self_collision),
        "self_overflow": None if final.self_overflow is None
        else np.asarray(final.self_overflow).tolist(),
        "uv_units": "meters",
        "vertices": g.num_vertices,
        "faces": g.num_faces,
        "resumed_at_frame": int(start),
        "wall_s": round(wall, 3),
        "ms_per_frame": round(1e3 * wall / max(total, 1), 3),
    }
    seq = make_sequence(out, g, 30.0, meta, source=f"simulate({sc.name}, {material})")
    if checkpoint is not None and os.path.exists(checkpoint):
        os.unlink(checkpoint)
    return SimulatedSequence(seq.frames, seq.garment, seq.fps, seq.metadata, tracks)


def resimulate(seq: GarmentSequence, start: int, stop: int,
               self_collision: SelfCollisionConfig | None | str = "recorded",
               substeps: int | None = None, scene: SceneConfig | None = None,
               setup: SceneSetup | None = None, return_state: bool = False):
    """Simulate a stored sequence's frames start+1 .. stop again from its frame `start`,
    with the recorded or other solver settings (to see what a setting changes where a
    stored run went wrong, without simulating the frames before it).

    The state at `start` is the stored positions and the velocity (x[start] - x[start - 1])
    * fps: the solver's own velocity (the last substep's) is not stored, so even with the
    recorded settings the continuation is close to the stored frames, not equal to them.
    Compare a setting against a continuation with the recorded ones.

    Args:
      seq: a sequence written by `simulate` (its metadata: material, resolution or pd, seed,
        substeps, self_collision, preroll_frames, scene_config).
      start: 1 <= start < stop <= T - 1 (stored frame indices).
      self_collision: "recorded" (the file's), None (off) or a `SelfCollisionConfig`.
      substeps: solver substeps per frame (None: the recorded).
      scene: the scene config, for scenes outside `SCENES` (default: by the recorded name;
        its JSON must match the recorded one). setup: a prebuilt `setup_scene(...)` of the
        recorded resolution, frame count and seed.
      return_state: also return the final `xpbd.ClothState` (its `self_overflow`: the
        dropped-candidate counts over the continuation).
    Returns:
      (stop - start, V, 3) float32 positions of frames start+1 .. stop, m; with return_state,
      (positions, final state).
    Raises:
      SceneError: frames out of range, or a scene that no longer matches the file's.
    """
    meta = seq.metadata
    frames = np.asarray(seq.frames)
    total = frames.shape[0]
    if not 1 <= start < stop <= total - 1:
        raise SceneError(f"need 1 <= start < stop <= {total - 1}, got start {start}, stop {stop}")
    sc = get_scene(meta["scene"]) if scene is None else scene
    if sc.to_json() != meta["scene_config"]:
        raise SceneError(f"scene {sc.name!r} differs from the one this file was simulated with")
    res = meta["resolution"] if meta["resolution"] in RESOLUTIONS else float(meta["pd"])
    if setup is None:
        setup = setup_scene(sc, res, total, int(meta["seed"]))
    if setup.preroll_frames != int(meta["preroll_frames"]):
        raise SceneError("the setup's pre-roll differs from the file's")
    if isinstance(self_collision, str):
        if self_collision != "recorded":
            raise SceneError("self_collision: 'recorded', None or a config, "
                             f"got {self_collision!r}")
        self_collision = selfcollision.recorded_config(meta.get("self_collision"))
    config = xpbd.SimConfig(fps=float(seq.fps),
                            substeps=int(meta["substeps"]) if substeps is None else substeps,
                            iterations=int(meta.get("iterations", 1)),
                            stretch_sweeps=sc.stretch_sweeps, self_collision=self_collision)
    init_fn, _ = xpbd.cloth_simulator(config)
    state = init_fn(setup.model, frames[start]).replace(
        v=jnp.asarray((frames[start] - frames[start - 1]) * float(seq.fps)))
    # Stored frame k is the state after preroll_frames + k simulated frames.
    pre = setup.preroll_frames
    drives = xpbd.slice_drives(setup.drives, 0, pre + stop + 1)
    final, xs = xpbd.simulate_frames(config, setup.model,
                                     xpbd.fabric_params(fabric(meta["material"])),
                                     state, drives, chunk=stop - start, start=pre + start)
    return (xs, final) if return_state else xs
