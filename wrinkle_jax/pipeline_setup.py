"""The pipeline's per-garment setup: its settings (`PipelineConfig`), the prepared state
(`Pipeline`) and `make_pipeline`, which builds it once per garment in NumPy and compiles every
stage ahead of time for its fixed shapes. `wrinkle_jax.pipeline` re-exports the public names
and runs the frames (streaming `iter_enhance`, `enhance_sequence`, and `frame_fn`).

Topology-dependent setup runs once per garment: the raster plan at the enhancer's texel size,
the origins of the non-empty patches, the subdivision of the lifted mesh and its lifting
topology. Every stage is a jitted function with static shapes, compiled once (the
``compile`` timing), so nothing recompiles, whatever the frame count.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import lift as lift_lib
from wrinkle_jax import normalmap, patches
from wrinkle_jax.mesh import Garment
from wrinkle_jax.nn import unet
from wrinkle_jax.numerics import to_device
from wrinkle_jax.stages import (
    _bake_chunk,
    _extract_chunk,
    _lift_frame,
    _lift_frame_warm,
    _merge_chunk,
    _network_apply,
    _network_frame,
    batch_blur_weights,
)

# Per-stage timings recorded by the pipeline (seconds), in pipeline order.
STAGES = ("setup", "compile", "classify", "bake", "tile", "network", "merge", "lift", "write")


class PipelineError(ValueError):
    """Bad pipeline input (unknown material, a garment that covers no texel, ...)."""


# The pipeline's lift: Gauss-Newton capped at 3 iterations per frame. Sweep
# (experiments/results/lift/lift_sweep_{demo,dress_dance}_s16.json, shipped model's maps, 12
# frames, lift_quality against N*): against the solver's own stop (cap 20; 8 iterations/frame
# warm on the demo, 4 on dress_dance) cap 3 changes the mean angle to N* by +0.004 deg of 1.58
# (demo, warm; +0.007 cold) and -0.006 of 2.43 (dress_dance), band ratios by < 0.002, no body
# penetrations, 0.6-0.8 mm RMS from the converged mesh, at 3/8 of the demo's iterations.
LIFT_SOLVER = lift_lib.SolverConfig(max_iters=3)

# The pipeline's body push-out: PCG with the two-level preconditioner (`lift.resolve_coarse`,
# mass 0.2) stopped at a relative residual of 3e-3. Rule fixed before the run
# (experiments/results/lift/resolve_rule_s18.txt; session 17's rule, resolve_rule_s17.txt, had
# chosen Jacobi at 1e-3 over the 1e-5 default), measured by benchmarks/bench_resolve.py
# (resolve_s18.json: dress_dance and cape_walk, 10 lifted frames each, load 3.8-5.0): 39-40
# CG iterations instead of 144, 127 vs 203 ms CPU per frame (pooled median), at most 0.49 mm
# from a converged solve (Jacobi at 1e-3: 0.27 mm), no vertex inside the body, the same
# minimum clearance. The error sits in the smooth far field and scales with the push: on a
# sheet cut 32 mm deep by a capsule (tests/test_pipeline_resolve.py) it is 1.9 mm (6 %;
# Jacobi at 1e-3: 2.8 mm).
LIFT_RESOLVE = lift_lib.ResolveConfig(cg_tol=3e-3, coarse_mass=0.2)


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Static settings of the pipeline (hashable).

    Attributes:
      batch_size: patches per jitted U-Net call; a frame's last batch is zero-padded, so the
        network compiles once. 4 (default) was the fastest of 2, 4, 8 and 16 per frame on
        three garments (benchmarks/bench_batch.py, experiments/results/timing/batch_s18.json:
        0.82-0.88x batch 8's CPU, batch 16 1.09-1.30x; bit-identical maps): smaller calls
        keep the convolutions' working set in cache, and less of the last batch is padding.
        Those runs page-faulted large temporaries afresh every call; with freed memory
        retained, as the command now runs (session 42, 4 frames per call: batch_fpb4_s42a/b.json),
        batches 4 and 8 were within 1 % pooled and 16 was 3 % and 8 % slower; the rule's pick
        flipped (16 at its 3 % edge, then 8), so the default stays.
      chunk_size: frames baked, enhanced and merged per step (bounds memory: one chunk holds
        chunk_size * P patches of S^2 * 3 float32 twice).
      frames_per_batch: frames whose patches share one network call (their F * P patches
        cut into batches of `batch_size`; a chunk's last group is zero-padded to F frames).
        1 (default): each frame's batches hold only its own patches, so a frame's maps are
        bit-identical whatever the chunking; > 1 saves the per-frame batch padding (results
        equal up to float rounding: the network treats each patch on its own).
      stride: patch stride in texels; None for `default_stride` (three quarters of the
        patch).
      window: merge weights, "hann" (seam-free, default) or "uniform" (the paper's average).
      smooth: bake interpolated vertex normals (True) or flat face normals.
      lift: lift the enhanced maps to detailed meshes.
      target_edge: mean edge length of the lifted mesh, meters (the lift's weights are
        calibrated at 10 mm).
      subdivision_scheme: "midpoint" or "loop" upsampling of the coarse mesh before lifting.
      subdivision: how many levels the coarse mesh is subdivided before lifting: None
        (default: until the mean edge is at most `target_edge`), "auto" (no finer than the
        map's detail: edges of at least `lift.TEXELS_PER_EDGE` texels of the model's texel
        size, `lift.texel_subdivision_level`), or an int >= 0 (exactly that many levels).
      weights, solver: the lift's energy weights and solver settings (see `lift.lift`);
        `solver` defaults to `LIFT_SOLVER` (3 Gauss-Newton iterations per frame, ~0.7 mm from
        a converged solve): pass a tighter one when gradients through the lift must be exact.
      warm_start: start each frame's lift from the previous streamed frame's solution,
        carried in the coarse surface's local frames (`stages._lift_warm`): fewer solver
        iterations on an animation (the CLI turns it on; benchmarks/bench_lift.py
        --sequence). A lifted frame then depends on the frames streamed before it: within
        the solver's tolerance on a smooth animation, but on an erratic map (e.g. a random
        network's) the lift can settle in another local minimum. False (default): every
        frame starts at its upsampled coarse mesh, independent of the others.
      resolve, phi: body-penetration settings (used only when a body is given); `resolve`
        defaults to `LIFT_RESOLVE` (two-level PCG to a 3e-3 residual, <= 0.5 mm from a
        converged solve); pass `lift.ResolveConfig()` for the converged one.
      overlap_lift: lift a chunk's frames in a worker thread while the next chunk is baked,
        enhanced and merged (`pipeline.iter_enhance`; the CLI turns it on). The frames are
        the same; two chunks are alive at once, and a chunk's frames are yielded once the
        next chunk's maps are done. The lift runs on about one core and the network on
        little more, so on two cores the two overlap: dress_dance's network + lift took
        ~0.8x their sequential wall time (session 45, scratch measurement, 4 pairs).
    """

    batch_size: int = 4
    chunk_size: int = 4
    frames_per_batch: int = 1
    stride: int | None = None
    window: str = "hann"
    smooth: bool = True
    lift: bool = True
    target_edge: float = lift_lib.REFERENCE_EDGE
    subdivision_scheme: str = "midpoint"
    subdivision: int | str | None = None
    weights: lift_lib.LiftWeights = lift_lib.LiftWeights()
    solver: lift_lib.SolverConfig = LIFT_SOLVER
    warm_start: bool = False
    resolve: lift_lib.ResolveConfig = LIFT_RESOLVE
    phi: float = 5e3
    overlap_lift: bool = False

    def __post_init__(self):
        if self.batch_size < 1 or self.chunk_size < 1 or self.frames_per_batch < 1:
            raise ValueError(f"batch_size, chunk_size and frames_per_batch must be >= 1, got "
                             f"{self.batch_size}, {self.chunk_size}, {self.frames_per_batch}")
        sub = self.subdivision
        if not (sub is None or sub == "auto"
                or (isinstance(sub, int) and not isinstance(sub, bool) and sub >= 0)):
            raise ValueError(f"subdivision must be None, 'auto' or an int >= 0, got {sub!r}")
        if self.window not in patches.WINDOWS:
            raise ValueError(f"unknown window {self.window!r}; expected one of "
                             f"{', '.join(patches.WINDOWS)}")




@dataclasses.dataclass(frozen=True)
class Pipeline:
    """Everything the per-frame work needs, prepared once per garment by `make_pipeline`.

    Attributes:
      enhancer: the model. config: PipelineConfig.
      garment: the coarse garment (topology and UVs).
      plan: raster plan at `enhancer.config.texel_size`; `mask` (H, W, 1) float32 its garment
        texels (NumPy).
      origins: (P, 2) int32 origins of the patches that touch the mask (padded-map pixels).
      padded_shape: (Hp, Wp) map size the patches live on (>= one patch, bottom/right zeros).
      fine_garment, subdivision, topology: the lifted mesh's topology (None without lifting).
      body: a `bodies` body, a callable frame index -> body, or None.
      timings: seconds spent in setup and compilation.
      resolve_coarse: `lift.resolve_coarse` of the lifted mesh for `config.resolve` (the body
        push-out's coarse-grid preconditioner), or None.
      blur_weights: the mask-only part of the model's blurs for one network call's patches
        (`stages.batch_blur_weights`, `frames_per_call` frames; 0.4 MB per patch for the
        shipped model), or None: the patches sit at fixed texels, so their masks, and these,
        are the same every frame.
    """

    enhancer: enhancer_lib.Enhancer
    config: PipelineConfig
    garment: Garment
    plan: normalmap.RasterPlan
    mask: np.ndarray
    origins: np.ndarray
    padded_shape: tuple[int, int]
    fine_garment: Garment | None
    subdivision: Any
    topology: lift_lib.LiftTopology | None
    body: Any
    timings: dict
    resolve_coarse: Any = None
    blur_weights: Any = None

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the normal maps."""
        return self.plan.shape

    @property
    def num_patches(self) -> int:
        """Patches enhanced per frame."""
        return int(self.origins.shape[0])

    @property
    def frames_per_call(self) -> int:
        """Frames whose patches go through one network call (at most a chunk)."""
        return min(self.config.frames_per_batch, self.config.chunk_size)

    @property
    def batches_per_frame(self) -> int:
        return -(-self.num_patches // self.config.batch_size)

    @property
    def batches_per_call(self) -> int:
        return -(-self.frames_per_call * self.num_patches // self.config.batch_size)



# --------------------------------------------------------------------------------------------
# Setup
# --------------------------------------------------------------------------------------------


def _body_for(body, index: int):
    return body(index) if callable(body) else body


def default_stride(patch_size: int) -> int:
    """The tiling stride used when none is given: three quarters of the patch (96 texels for
    128). Each interior texel lies in 1-4 patches and the Hann merge still has overlap at every
    patch edge. The stride study (`experiments/results/stride/`: 384 patches of Table 1's
    cells) scored it as half the patch (|.| 60.9 vs 61.3, signed -9.6 vs -9.5, seam ratio
    1.007 vs 0.987, within the coarse control's 0.99-1.01) at 53.5 instead of 100.7 patches
    and 398 instead of 715 ms per frame for tiling, network and merge."""
    return 3 * int(patch_size) // 4


def make_pipeline(garment: Garment, enhancer: enhancer_lib.Enhancer | None = None,
                  config: PipelineConfig = PipelineConfig(), body=None,  # noqa: B008
                  compile: bool = True, layout: normalmap.UVLayout | None = None) -> Pipeline:
    """Prepare the per-garment setup and compile every stage (NumPy setup, AOT compile).

    Args:
      garment: the coarse garment (topology, UVs; its vertices set the texel scale).
      enhancer: the model; None loads the shipped default (`enhancer.load_enhancer`).
      config: PipelineConfig.
      body: None, a `bodies.PrimitiveBody`/`bodies.MeshBody` (meters, the garment's frame), or
        a callable ``frame_index -> body`` for an animated body (bodies of the same structure
        share one compile).
      compile: compile the stages now (the "compile" timing); False compiles on first use.
      layout: bake onto this UV layout instead of the garment's own (e.g.
        `evaluation`-style comparisons with a fine mesh baked on the same pixels); its texel
        size must be the model's.
    Raises:
      PipelineError: the garment covers no texel at the model's texel size, or `layout` has
        another texel size.
      enhancer.EnhancerError: no model given and the shipped one is missing or unreadable.
    """
    enh = enhancer_lib.load_enhancer() if enhancer is None else enhancer
    size = int(enh.config.patch_size)
    stride = default_stride(size) if config.stride is None else int(config.stride)
    timings = {}
    t0 = time.perf_counter()
    if layout is not None and not np.isclose(layout.texel_size, enh.config.texel_size,
                                             rtol=1e-6):
        raise PipelineError(f"layout texel size {layout.texel_size} m differs from the "
                            f"model's {enh.config.texel_size} m")
    plan = normalmap.make_plan(garment, texel_size=enh.config.texel_size, layout=layout)
    mask = np.asarray(plan.mask)
    if not mask.any():
        raise PipelineError(f"the garment covers no texel at texel size "
                            f"{enh.config.texel_size} m (is its UV layout degenerate?)")
    padded, _ = patches.pad_to_patch(mask, size)
    origins = patches.tile(padded, size=size, stride=stride)
    fine = sub = top = coarse_pc = None
    if config.lift:
        levels = config.subdivision
        if levels == "auto":
            levels = lift_lib.texel_subdivision_level(lift_lib.coarse_mean_edge(garment),
                                                      enh.config.texel_size)
        fine, sub = lift_lib.upsample(garment, config.target_edge, config.subdivision_scheme,
                                      levels=levels)
        top = lift_lib.lift_topology(fine.faces, fine.num_vertices)
        coarse_pc = lift_lib.resolve_coarse(sub, top, config.phi, config.resolve)
        fine = to_device(fine)  # device arrays: arguments, not constants
    frames = min(config.frames_per_batch, config.chunk_size)  # Pipeline.frames_per_call
    blur_w = _network_blur_weights(enh, padded, np.tile(origins, (frames, 1)), config.batch_size)
    timings["setup"] = time.perf_counter() - t0
    pipe = Pipeline(enh, dataclasses.replace(config, stride=stride), garment, plan, mask,
                    origins, tuple(padded.shape[:2]), fine, sub, top, body, timings, coarse_pc,
                    blur_w)
    timings["compile"] = _compile(pipe) if compile else 0.0
    return pipe


def _compile(pipe: Pipeline) -> float:
    """Compile every stage for the pipeline's fixed shapes; returns the seconds it took."""
    t0 = time.perf_counter()
    cfg, enh = pipe.config, pipe.enhancer
    c, size, p = cfg.chunk_size, enh.config.patch_size, pipe.num_patches
    hp, wp = pipe.padded_shape
    f32 = jnp.float32
    spec = jax.ShapeDtypeStruct
    _bake_chunk.lower(pipe.plan, spec((c, pipe.garment.num_vertices, 3), f32),
                      _padded_mask(pipe), smooth=cfg.smooth,
                      padded_shape=pipe.padded_shape).compile()
    _extract_chunk.lower(spec((c, hp, wp, 3), f32), pipe.origins, size=size).compile()
    _network_frame.lower(_network_apply(enh), enh.params,
                         spec((pipe.frames_per_call * p, size, size, 3), f32),
                         spec((), jnp.int32), batch_size=cfg.batch_size,
                         origins=_noise_origins(pipe),
                         blur_weights=_call_blur_weights(pipe)).compile()
    _merge_chunk.lower(spec((c, p, size, size, 3), f32), pipe.origins, _padded_mask(pipe),
                       spec((c, hp, wp, 3), f32), window=cfg.window, shape=pipe.shape).compile()
    if cfg.lift:
        body = _body_for(pipe.body, 0)
        coarse, nmap = spec((pipe.garment.num_vertices, 3), f32), spec((*pipe.shape, 3), f32)
        if cfg.warm_start:
            _lift_frame_warm.lower(coarse, nmap, _no_offsets(pipe), pipe.subdivision,
                                   pipe.fine_garment, pipe.topology, body, pipe.resolve_coarse,
                                   **_lift_static(pipe)).compile()
        else:
            _lift_frame.lower(coarse, nmap, pipe.subdivision, pipe.fine_garment, pipe.topology,
                              body, pipe.resolve_coarse, **_lift_static(pipe)).compile()
    return time.perf_counter() - t0


def _noise_origins(pipe: Pipeline):
    """The patch origins of one network call (`frames_per_call` frames) for models with
    texel noise (fixed to the cloth), else None."""
    if not pipe.enhancer.config.unet.noise_channels:
        return None
    return to_device(np.tile(pipe.origins, (pipe.frames_per_call, 1)))


def _network_blur_weights(enh: enhancer_lib.Enhancer, padded_mask, origins, batch_size: int):
    """`stages.batch_blur_weights` of the patches at `origins` ((P, 2)) of an (Hp, Wp, 1)
    padded garment mask, for `network_stage` with `batch_size`; None for models without
    blurs (or that are not a `CINUNet`: nothing is passed to them)."""
    if not isinstance(enh.model, unet.CINUNet):
        return None
    weights = batch_blur_weights(enh.model.config, padded_mask, np.asarray(origins, np.int32),
                                 size=int(enh.config.patch_size), batch_size=batch_size)
    return weights or None


def _call_blur_weights(pipe: Pipeline):
    """`pipe.blur_weights` when they fit its network calls (batches per call and batch size),
    else None (the network then blurs the masks itself: the same maps). They do not fit a
    pipeline copied with another batch size or frames per call (`dataclasses.replace`)."""
    w = pipe.blur_weights
    if not w:
        return None
    leaf = next(iter(w.values()))  # (batches, K, S, batch size, S)
    if leaf.shape[0] != pipe.batches_per_call or leaf.shape[3] != pipe.config.batch_size:
        return None
    return w


def _padded_mask(pipe: Pipeline):
    return to_device(patches.pad_to_patch(pipe.mask, pipe.enhancer.config.patch_size)[0])


def _no_offsets(pipe: Pipeline):
    """Zero carried lift offsets (V', 3): a cold start."""
    return to_device(np.zeros((pipe.fine_garment.num_vertices, 3), np.float32))


def _lift_static(pipe: Pipeline) -> dict:
    cfg = pipe.config
    return dict(layout=pipe.plan.layout, weights=cfg.weights, solver=cfg.solver,
                resolve=cfg.resolve, phi=float(cfg.phi))
