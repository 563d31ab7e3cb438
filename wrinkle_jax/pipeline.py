"""End-to-end enhancement of coarse garment animations: bake, tile, U-Net, merge, lift.

    coarse frames (T, V, 3) --bake--> N (H, W, 3) + mask --tile--> patches (P, S, S, 3)
      --U-Net(material)--> enhanced patches --merge (hann)--> N* (H, W, 3)
      --lift (+ body)--> detailed frames (T, V', 3)
    material "auto": coarse frames --classifier (vote over patches and time)--> material

Contract:
  * Topology-dependent setup runs once per garment in NumPy (`make_pipeline`): the raster
    plan at the enhancer's texel size, the patch origins of the non-empty patches, the
    subdivision to ~10 mm edges and the lifting topology. Every stage is a jitted function
    with static shapes, compiled once ahead of time (the ``compile`` timing); the U-Net runs
    in fixed-size batches of `PipelineConfig.batch_size` patches (the last one zero-padded),
    so nothing recompiles, whatever the frame count.
  * Frames stream in chunks of `PipelineConfig.chunk_size`: one chunk's maps, patches and
    lifted meshes are alive at a time, so memory is bounded by the chunk and the batch, not by
    the sequence length. `iter_enhance` yields one `EnhancedFrame` per frame;
    `enhance_sequence` hands each to a `writer` callback (the CLI writes files as they come)
    and, with ``keep=True``, also stacks them into arrays (a convenience for short sequences).
  * Results do not depend on the chunk size or on the batch padding (each network batch
    holds the patches of one frame only, always at the same positions). With
    `PipelineConfig.warm_start` (the CLI's setting; off by default) each frame's lift starts
    from the previous streamed frame's solution, so a lifted frame depends on the frames
    before it.
  * The stages are public pure functions of one frame (`bake_stage`, `tile_stage`,
    `network_stage`, `merge_stage`, `lift_stage`, from `wrinkle_jax.stages`); the streaming
    runs their jitted, frame-vmapped forms, and `frame_fn(pipe)` composes them into one
    jitted function ``f(params, coarse_vertices, material_id) -> FrameResult``,
    differentiable end to end (reverse mode) in the network parameters and the vertices.
  * Normal maps are float32 (H, W, 3) object-space normals in [-1, 1]: unit vectors on the
    garment texels (mask > 0), the coarse normals in the seam gutter (so bilinear sampling at
    the UV borders never reads background) and zero on the background. Vertices are meters.

Example:
    >>> import jax, numpy as np
    >>> from wrinkle_jax import enhancer, meshio, primitives
    >>> from wrinkle_jax.nn.unet import UNetConfig
    >>> g = primitives.grid_sheet(6, 6, size=(0.12, 0.12))
    >>> seq = meshio.make_sequence(np.stack([g.vertices] * 2), g)
    >>> enh = enhancer.init_enhancer(jax.random.key(0, impl="rbg"),
    ...     enhancer.EnhancerConfig(UNetConfig(width=4), patch_size=32, texel_size=0.004))
    >>> res = enhance_sequence(seq, "silk_charmeuse", enhancer=enh, lift=False)
    >>> res.normal_maps.shape[0], sorted(res.timings)[:3]
    (2, ['bake', 'classify', 'compile'])
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import lift as lift_lib
from wrinkle_jax import normalmap, patches
from wrinkle_jax.mesh import Garment
from wrinkle_jax.meshio import GarmentSequence
from wrinkle_jax.stages import (
    FrameResult,
    _bake_chunk,
    _extract_chunk,
    _frame,
    _FrameStatic,
    _lift_frame,
    _lift_frame_warm,
    _merge_chunk,
    _network_apply,
    _network_frame,
    bake_stage,
    lift_stage,
    merge_stage,
    network_stage,
    tile_stage,
)

__all__ = ["STAGES", "EnhanceResult", "EnhancedFrame", "FrameResult", "Pipeline",
           "PipelineConfig", "PipelineError", "bake_stage", "classify_material",
           "enhance_frame", "enhance_sequence", "frame_fn", "iter_enhance", "lift_stage",
           "make_pipeline", "merge_stage", "network_stage", "resolve_material", "tile_stage"]

# Per-stage timings recorded by the pipeline (seconds), in pipeline order.
STAGES = ("setup", "compile", "classify", "bake", "tile", "network", "merge", "lift", "write")


class PipelineError(ValueError):
    """Bad pipeline input (unknown material, a garment that covers no texel, ...)."""


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Static settings of the pipeline (hashable).

    Attributes:
      batch_size: patches per jitted U-Net call; a frame's last batch is zero-padded, so the
        network compiles once. Larger batches are faster per patch up to a point
        (benchmarks/bench_pipeline.py).
      chunk_size: frames baked, enhanced and merged per step (bounds memory: one chunk holds
        chunk_size * P patches of S^2 * 3 float32 twice).
      frames_per_batch: frames whose patches share one network call (their F * P patches
        cut into batches of `batch_size`; a chunk's last group is zero-padded to F frames).
        1 (default): each frame's batches hold only its own patches, so a frame's maps are
        bit-identical whatever the chunking; > 1 saves the per-frame batch padding (results
        equal up to float rounding: the network treats each patch on its own).
      stride: patch stride in texels; None for half the patch (each texel in ~4 patches).
      window: merge weights, "hann" (seam-free, default) or "uniform" (the paper's average).
      smooth: bake interpolated vertex normals (True) or flat face normals.
      lift: lift the enhanced maps to detailed meshes.
      target_edge: mean edge length of the lifted mesh, meters (the lift's weights are
        calibrated at 10 mm).
      subdivision_scheme: "midpoint" or "loop" upsampling of the coarse mesh before lifting.
      weights, solver: the lift's energy weights and solver settings (see `lift.lift`).
      warm_start: start each frame's lift from the previous streamed frame's solution,
        carried in the coarse surface's local frames (`stages._lift_warm`): fewer solver
        iterations on an animation (the CLI turns it on; benchmarks/bench_lift.py
        --sequence). A lifted frame then depends on the frames streamed before it: within
        the solver's tolerance on a smooth animation, but on an erratic map (e.g. a random
        network's) the lift can settle in another local minimum. False (default): every
        frame starts at its upsampled coarse mesh, independent of the others.
      resolve, phi: body-penetration settings (used only when a body is given).
    """

    batch_size: int = 8
    chunk_size: int = 4
    frames_per_batch: int = 1
    stride: int | None = None
    window: str = "hann"
    smooth: bool = True
    lift: bool = True
    target_edge: float = lift_lib.REFERENCE_EDGE
    subdivision_scheme: str = "midpoint"
    weights: lift_lib.LiftWeights = lift_lib.LiftWeights()
    solver: lift_lib.SolverConfig = lift_lib.SolverConfig()
    warm_start: bool = False
    resolve: lift_lib.ResolveConfig = lift_lib.ResolveConfig()
    phi: float = 5e3

    def __post_init__(self):
        if self.batch_size < 1 or self.chunk_size < 1 or self.frames_per_batch < 1:
            raise ValueError(f"batch_size, chunk_size and frames_per_batch must be >= 1, got "
                             f"{self.batch_size}, {self.chunk_size}, {self.frames_per_batch}")
        if self.window not in patches.WINDOWS:
            raise ValueError(f"unknown window {self.window!r}; expected one of "
                             f"{', '.join(patches.WINDOWS)}")


@dataclasses.dataclass(frozen=True)
class EnhancedFrame:
    """One enhanced frame, as streamed by `iter_enhance`.

    Attributes:
      index: frame index in the input sequence.
      coarse: (V, 3) float32 coarse vertices, meters.
      normal_map: (H, W, 3) float32 enhanced map N* (see the module docstring).
      detailed: (V', 3) float32 lifted vertices, meters (topology `Pipeline.fine_garment`),
        or None without lifting.
    """

    index: int
    coarse: np.ndarray
    normal_map: np.ndarray
    detailed: np.ndarray | None


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


@dataclasses.dataclass(frozen=True)
class EnhanceResult:
    """What `enhance_sequence` returns.

    Attributes:
      material: material name used. scores: per-material vote scores (name -> float) when the
        material was classified, else None.
      frame_indices: input frame index of every enhanced frame (in order).
      normal_maps: (T, H, W, 3) float32 enhanced maps, or None with ``keep=False``.
      detailed_frames: (T, V', 3) float32 lifted vertices (meters), or None (no lift or
        ``keep=False``).
      mask: (H, W, 1) float32 garment texels. layout: the maps' `normalmap.UVLayout`.
      fine_garment: topology and UVs of the detailed frames (None without lifting).
      patches: counts: per_frame, network (patches run), padding (zero patches added to fill
        batches), batches, batch_size, stride, patch_size.
      timings: seconds per stage (`STAGES`) and "total", the wall time of the call (setup and
        compile are part of it only when the call built its pipeline).
      peak_buffered_frames: most frames held by the pipeline at once (at most chunk_size).
      lift_iterations: the lift's solver iterations summed over the frames (counted with
        `PipelineConfig.warm_start` only; else 0).
    """

    material: str
    scores: dict | None
    frame_indices: tuple[int, ...]
    normal_maps: np.ndarray | None
    detailed_frames: np.ndarray | None
    mask: np.ndarray
    layout: normalmap.UVLayout
    fine_garment: Garment | None
    patches: dict
    timings: dict
    peak_buffered_frames: int
    lift_iterations: int = 0


# --------------------------------------------------------------------------------------------
# Setup
# --------------------------------------------------------------------------------------------


def _body_for(body, index: int):
    return body(index) if callable(body) else body


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
    stride = size // 2 if config.stride is None else int(config.stride)
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
    fine = sub = top = None
    if config.lift:
        fine, sub = lift_lib.upsample(garment, config.target_edge, config.subdivision_scheme)
        top = lift_lib.lift_topology(fine.faces, fine.num_vertices)
        fine = jax.tree.map(jnp.asarray, fine)  # device arrays: arguments, not constants
    timings["setup"] = time.perf_counter() - t0
    pipe = Pipeline(enh, dataclasses.replace(config, stride=stride), garment, plan, mask,
                    origins, tuple(padded.shape[:2]), fine, sub, top, body, timings)
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
                         origins=_noise_origins(pipe)).compile()
    _merge_chunk.lower(spec((c, p, size, size, 3), f32), pipe.origins, _padded_mask(pipe),
                       spec((c, hp, wp, 3), f32), window=cfg.window, shape=pipe.shape).compile()
    if cfg.lift:
        body = _body_for(pipe.body, 0)
        coarse, nmap = spec((pipe.garment.num_vertices, 3), f32), spec((*pipe.shape, 3), f32)
        if cfg.warm_start:
            _lift_frame_warm.lower(coarse, nmap, _no_offsets(pipe), pipe.subdivision,
                                   pipe.fine_garment, pipe.topology, body,
                                   **_lift_static(pipe)).compile()
        else:
            _lift_frame.lower(coarse, nmap, pipe.subdivision, pipe.fine_garment, pipe.topology,
                              body, **_lift_static(pipe)).compile()
    return time.perf_counter() - t0


def _noise_origins(pipe: Pipeline):
    """The patch origins of one network call (`frames_per_call` frames) for models with
    texel noise (fixed to the cloth), else None."""
    if not pipe.enhancer.config.unet.noise_channels:
        return None
    return jnp.asarray(np.tile(pipe.origins, (pipe.frames_per_call, 1)))


def _padded_mask(pipe: Pipeline):
    return jnp.asarray(patches.pad_to_patch(pipe.mask, pipe.enhancer.config.patch_size)[0])


def _no_offsets(pipe: Pipeline):
    """Zero carried lift offsets (V', 3): a cold start."""
    return jnp.zeros((pipe.fine_garment.num_vertices, 3), jnp.float32)


def _lift_static(pipe: Pipeline) -> dict:
    cfg = pipe.config
    return dict(layout=pipe.plan.layout, weights=cfg.weights, solver=cfg.solver,
                resolve=cfg.resolve, phi=float(cfg.phi))


# --------------------------------------------------------------------------------------------
# Streaming
# --------------------------------------------------------------------------------------------


def _add(timings: dict, stage: str, t0: float) -> float:
    now = time.perf_counter()
    timings[stage] = timings.get(stage, 0.0) + now - t0
    return now


def _run_network(pipe: Pipeline, inputs, material_id: int, counts: dict):
    """U-Net over the patches of n frames, (n, P, S, S, 3) -> same shape, RGB form.

    One `network_stage` call per group of `frames_per_call` frames (their patches
    concatenated, then cut into fixed-size batches; the last group zero-padded to whole
    frames, so the call compiles once). With one frame per call every batch holds patches of
    a single frame at fixed positions, so a patch's result never depends on its neighbours in
    the chunk. Models with texel noise get each patch's origin, so the noise is fixed to the
    cloth.
    """
    apply = _network_apply(pipe.enhancer)
    b, p, f = pipe.config.batch_size, pipe.num_patches, pipe.frames_per_call
    n = inputs.shape[0]
    material = jnp.asarray(material_id, jnp.int32)
    origins = _noise_origins(pipe)
    outs = []
    for g in range(0, n, f):
        group = inputs[g:g + f]
        k = group.shape[0]
        if k < f:  # whole frames of zeros: the compiled shape
            group = jnp.pad(group, ((0, f - k),) + ((0, 0),) * 4)
        out = _network_frame(apply, pipe.enhancer.params, group.reshape(f * p, *group.shape[2:]),
                             material, batch_size=b, origins=origins)
        outs.append(out.reshape(group.shape)[:k])
    calls = -(-n // f)
    counts["network"] += n * p
    counts["padding"] += calls * pipe.batches_per_call * b - n * p
    counts["batches"] += calls * pipe.batches_per_call
    return outs[0] if len(outs) == 1 else jnp.concatenate(outs)


def iter_enhance(pipe: Pipeline, frames, material_id: int, indices: Sequence[int] | None = None,
                 timings: dict | None = None, counts: dict | None = None
                 ) -> Iterator[EnhancedFrame]:
    """Enhance frames chunk by chunk, yielding one `EnhancedFrame` per frame, in order.

    Args:
      pipe: from `make_pipeline`.
      frames: (T, V, 3) float32 coarse vertices, meters (NumPy, may be a memmap: only one
        chunk is read at a time).
      material_id: index into `pipe.enhancer.config.materials`.
      indices: frame indices to enhance (default all), in the order given.
      timings: dict accumulating seconds per stage (bake, tile, network, merge, lift).
      counts: dict accumulating patch counts (network, padding, batches), the most frames
        alive at once (peak_buffered_frames) and the lift's solver iterations
        (lift_iterations; counted with warm_start only).
    """
    timings = {} if timings is None else timings
    counts = {} if counts is None else counts
    for k in ("network", "padding", "batches", "peak_buffered_frames", "lift_iterations"):
        counts.setdefault(k, 0)
    cfg = pipe.config
    indices = list(range(len(frames)) if indices is None else indices)
    mask = _padded_mask(pipe)
    origins = jnp.asarray(pipe.origins)
    size = pipe.enhancer.config.patch_size
    lift_static = _lift_static(pipe)
    # The lift's warm start: the previous frame's offsets in its local frames (zeros: cold).
    carried = _no_offsets(pipe) if cfg.lift and cfg.warm_start else None
    for start in range(0, len(indices), cfg.chunk_size):
        idx = indices[start:start + cfg.chunk_size]
        n = len(idx)
        # Frames whose maps, patches or meshes are alive at once: one chunk.
        counts["peak_buffered_frames"] = max(counts["peak_buffered_frames"], n)
        # Fixed chunk shape (the last chunk repeats its last frame) so the bake compiles once.
        padded_idx = idx + [idx[-1]] * (cfg.chunk_size - n)
        t0 = time.perf_counter()
        coarse = np.asarray(frames[np.asarray(padded_idx)], np.float32)
        # Static arguments by keyword, exactly as in `_compile` (the jit cache key differs
        # between positional and keyword static arguments).
        maps, rgb = _bake_chunk(pipe.plan, jnp.asarray(coarse), mask, smooth=cfg.smooth,
                                padded_shape=pipe.padded_shape)
        rgb.block_until_ready()
        t0 = _add(timings, "bake", t0)
        tiles = _extract_chunk(rgb, origins, size=size)
        tiles.block_until_ready()
        del rgb
        t0 = _add(timings, "tile", t0)
        out = _run_network(pipe, tiles[:n], material_id, counts)
        out.block_until_ready()
        del tiles
        t0 = _add(timings, "network", t0)
        if n < cfg.chunk_size:  # keep the merge's compiled shape
            out = jnp.pad(out, ((0, cfg.chunk_size - n),) + ((0, 0),) * 4)
        enhanced = _merge_chunk(out, origins, mask, maps, window=cfg.window, shape=pipe.shape)
        enhanced = np.array(enhanced)  # host-owned (writable) copy; the device chunk is freed
        del out, maps
        t0 = _add(timings, "merge", t0)
        for j, t in enumerate(idx):
            detailed = None
            if cfg.lift:
                t0 = time.perf_counter()
                args = (pipe.subdivision, pipe.fine_garment, pipe.topology,
                        _body_for(pipe.body, t))
                if cfg.warm_start:
                    detailed, carried, info = _lift_frame_warm(
                        jnp.asarray(coarse[j]), jnp.asarray(enhanced[j]), carried, *args,
                        **lift_static)
                    counts["lift_iterations"] += int(info.iterations)
                else:
                    # The very computation `frame_fn` runs (bit for bit: a lift that stops
                    # short of convergence amplifies rounding differences).
                    detailed = _lift_frame(jnp.asarray(coarse[j]), jnp.asarray(enhanced[j]),
                                           *args, **lift_static)
                detailed = np.array(detailed)
                _add(timings, "lift", t0)
            yield EnhancedFrame(int(t), coarse[j], enhanced[j], detailed)


# --------------------------------------------------------------------------------------------
# One frame as one differentiable function
# --------------------------------------------------------------------------------------------


def frame_fn(pipe: Pipeline, body=None) -> Callable[..., FrameResult]:
    """The whole pipeline of one frame as one pure, jittable, differentiable function.

        f = frame_fn(pipe)
        f(params, coarse_vertices, material_id) -> FrameResult(normal_map, mask, detailed)

    bake -> tile -> U-Net -> merge -> lift with the pipeline's setup and settings (the same
    stage functions, padding, batching, merge window and lifting as `iter_enhance`, so for
    ``params = pipe.enhancer.params`` it computes the streamed results, up to float rounding).

    Args of f:
      params: the enhancer's parameter pytree (any values of `pipe.enhancer.params`' shapes).
      coarse_vertices: (Vc, 3) float coarse frame, meters (float64 under jax_enable_x64).
      material_id: int or int32 scalar, a row of the model's material tables
        (`pipe.enhancer.config.material_id(name)`); not differentiable.
    Returns of f: FrameResult; `detailed` is None when `pipe.config.lift` is False.

    Differentiable end to end in reverse mode (`jax.grad`, `jax.vjp`) with respect to params
    and coarse_vertices: through the bake, the U-Net, the merge and the lift (implicit
    function theorem, exact at a converged solve: build the pipeline with a tighter
    `PipelineConfig.solver` when gradients must be accurate). f is jitted (one compile per
    pipeline shape, shared by pipelines of the same shapes and settings) and can be traced
    inside a caller's jit or grad.

    Args:
      pipe: from `make_pipeline` (``compile=False`` is enough; f compiles on first call).
      body: None (default, also when the pipeline has one), or a `bodies` body, meters, the
        lifted mesh is pushed out of (forward only: the penetration resolution is not
        differentiable in reverse mode).
    """
    cfg = pipe.config
    lift = None
    if cfg.lift:
        lift = tuple(sorted(_lift_static(pipe).items()))
    static = _FrameStatic(apply=_network_apply(pipe.enhancer), smooth=cfg.smooth,
                          padded_shape=pipe.padded_shape, shape=pipe.shape,
                          size=pipe.enhancer.config.patch_size, batch_size=cfg.batch_size,
                          window=cfg.window, noise=bool(pipe.enhancer.config.unet.noise_channels),
                          lift=lift)
    setup = dict(plan=pipe.plan, padded_mask=_padded_mask(pipe),
                 origins=jnp.asarray(pipe.origins), mask=jnp.asarray(pipe.mask),
                 subdivision=pipe.subdivision, fine_garment=pipe.fine_garment,
                 topology=pipe.topology, body=body)

    def f(params, coarse_vertices, material_id) -> FrameResult:
        return _frame(setup, params, coarse_vertices, material_id, static=static)

    return f


# --------------------------------------------------------------------------------------------
# Material
# --------------------------------------------------------------------------------------------


def classify_material(frames, garment: Garment, key):
    """The default material classifier: `wrinkle_jax.nn.classifier` with its shipped weights.

    Returns the classifier's result (``.material`` name and ``.scores`` name -> float).

    Raises:
      PipelineError: the classifier module or its weights are not available.
    """
    try:
        from wrinkle_jax.nn import classifier
    except ImportError as e:
        raise PipelineError(f"material 'auto' needs the material classifier "
                            f"(wrinkle_jax.nn.classifier), which is not available ({e}); "
                            f"pass a material name instead") from None
    try:
        model = classifier.load_classifier()
    except (OSError, ValueError) as e:
        raise PipelineError(f"material 'auto': cannot load the material classifier ({e}); "
                            f"pass a material name instead") from None
    return classifier.classify_sequence(model, frames, garment, key)


def resolve_material(material: str, materials: Sequence[str], frames=None,
                     garment: Garment | None = None, classify_fn: Callable | None = None,
                     key=None) -> tuple[str, dict | None]:
    """The material to enhance with: `material` itself, or the classifier's vote for "auto".

    Args:
      material: a name in `materials` or "auto".
      materials: the names the enhancer knows (its CIN table order).
      frames: (T, V, 3) coarse frames, meters; garment: their topology (for "auto").
      classify_fn: ``(frames, garment, key) -> result with .material and .scores``; default
        `classify_material`.
      key: PRNG key of the classifier's patch sampling (default: rbg key 0).
    Returns:
      (name, scores): scores is the classifier's name -> float dict, None for a given name.
    Raises:
      PipelineError: unknown material name, or the classifier chose a material the enhancer
        does not know.
    """
    materials = tuple(materials)
    if material != "auto":
        if material not in materials:
            raise PipelineError(f"unknown material {material!r}; expected 'auto' or one of "
                                f"{', '.join(materials)}")
        return material, None
    classify = classify_material if classify_fn is None else classify_fn
    key = jax.random.key(0, impl="rbg") if key is None else key
    result = classify(frames, garment, key)
    name = str(result.material)
    if name not in materials:
        raise PipelineError(f"the classifier chose {name!r}, which the enhancer does not know "
                            f"({', '.join(materials)})")
    scores = {str(k): float(v) for k, v in dict(result.scores).items()}
    return name, scores


# --------------------------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------------------------


def enhance_sequence(sequence: GarmentSequence, material: str = "auto", *, lift: bool = True,
                     body=None, enhancer: enhancer_lib.Enhancer | None = None,
                     batch_size: int = 8, chunk_size: int = 4, stride: int | None = None,
                     frames: Sequence[int] | None = None, config: PipelineConfig | None = None,
                     classify_fn: Callable | None = None, key=None,
                     writer: Callable[[EnhancedFrame], None] | None = None, keep: bool = True,
                     progress: Callable[[int], None] | None = None,
                     pipeline: Pipeline | None = None) -> EnhanceResult:
    """Enhance a coarse garment sequence end to end.

    Args:
      sequence: the coarse animation (frames (T, V, 3) meters, garment with UVs).
      material: a material name of the enhancer, or "auto" to classify it from the motion.
      lift: lift the enhanced maps to detailed meshes (`config.lift` when a config is given).
      body: None, a body of `wrinkle_jax.bodies` or a callable frame index -> body; the
        lifted garment is pushed out of it.
      enhancer: the model; None loads the shipped default.
      batch_size, chunk_size, stride: see `PipelineConfig` (ignored when `config` is given).
      frames: input frame indices to enhance (default all).
      config: a full PipelineConfig (overrides lift/batch_size/chunk_size/stride).
      classify_fn: ``(frames, garment, key) -> .material, .scores`` for "auto" (default: the
        shipped classifier, `classify_material`).
      key: PRNG key of the classifier.
      writer: called with every `EnhancedFrame` as soon as it is ready (timed as "write").
      keep: also return the stacked maps and detailed frames (memory grows with T; use
        ``keep=False`` with a writer for long sequences).
      progress: called with the number of frames finished after each frame.
      pipeline: a prepared `make_pipeline` for this garment, reused across calls (its
        enhancer, config and body then replace the arguments above).
    Returns:
      EnhanceResult.
    Raises:
      PipelineError: unknown material, empty frame selection, a garment without texels.
    """
    t_start = time.perf_counter()
    if config is None:
        config = PipelineConfig(batch_size=batch_size, chunk_size=chunk_size, stride=stride,
                                lift=lift)
    indices = list(range(len(sequence)) if frames is None else frames)
    if not indices:
        raise PipelineError("no frame selected")
    bad = [t for t in indices if not 0 <= int(t) < len(sequence)]
    if bad:
        raise PipelineError(f"frame {bad[0]} is out of range (the sequence has "
                            f"{len(sequence)} frames)")
    if pipeline is None:
        pipeline = make_pipeline(sequence.garment, enhancer, config, body)
    enh = pipeline.enhancer
    timings = {"setup": pipeline.timings.get("setup", 0.0),
               "compile": pipeline.timings.get("compile", 0.0)}
    # Validate a given name before any work; classify "auto" on the selected frames.
    t0 = time.perf_counter()
    name, scores = resolve_material(
        material, enh.config.materials,
        np.asarray(sequence.frames[np.asarray(indices)]) if material == "auto" else None,
        sequence.garment, classify_fn, key)
    timings["classify"] = time.perf_counter() - t0
    material_id = enh.config.material_id(name)

    counts: dict = {}
    maps, detailed = [], []
    done = 0
    for frame in iter_enhance(pipeline, sequence.frames, material_id, indices, timings, counts):
        if writer is not None:
            t0 = time.perf_counter()
            writer(frame)
            _add(timings, "write", t0)
        if keep:
            maps.append(frame.normal_map)
            if frame.detailed is not None:
                detailed.append(frame.detailed)
        done += 1
        if progress is not None:
            progress(done)
    for stage in STAGES:
        timings.setdefault(stage, 0.0)
    timings["total"] = time.perf_counter() - t_start
    return EnhanceResult(
        material=name, scores=scores, frame_indices=tuple(int(t) for t in indices),
        normal_maps=np.stack(maps) if keep else None,
        detailed_frames=np.stack(detailed) if keep and detailed else None,
        mask=pipeline.mask, layout=pipeline.plan.layout, fine_garment=pipeline.fine_garment,
        patches=dict(per_frame=pipeline.num_patches, network=counts["network"],
                     padding=counts["padding"], batches=counts["batches"],
                     batch_size=pipeline.config.batch_size, stride=pipeline.config.stride,
                     patch_size=enh.config.patch_size),
        timings=timings, peak_buffered_frames=counts["peak_buffered_frames"],
        lift_iterations=counts["lift_iterations"])


def enhance_frame(vertices, garment: Garment, material: str, **kwargs) -> EnhancedFrame:
    """Enhance one frame: `enhance_sequence` on a one-frame sequence.

    Args:
      vertices: (V, 3) float32 coarse vertices, meters.
      garment: topology and UVs.
      material: a material name, or "auto" (classified from this single frame).
      **kwargs: the keyword arguments of `enhance_sequence` (lift, body, enhancer, ...).
    Returns:
      EnhancedFrame (index 0).
    Raises:
      GarmentError: non-finite or mis-shaped vertices.
    """
    from wrinkle_jax.meshio import make_sequence

    seq = make_sequence(np.asarray(vertices, np.float32)[None], garment, source="<frame>")
    kept = []
    kwargs = {**kwargs, "keep": False}
    user_writer = kwargs.pop("writer", None)

    def keep_one(frame: EnhancedFrame):
        kept.append(frame)
        if user_writer is not None:
            user_writer(frame)

    enhance_sequence(seq, material, writer=keep_one, **kwargs)
    return kept[0]
