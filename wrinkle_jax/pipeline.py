"""End-to-end enhancement of coarse garment animations: bake, tile, U-Net, merge, lift.

    coarse frames (T, V, 3) --bake--> N (H, W, 3) + mask --tile--> patches (P, S, S, 3)
      --U-Net(material)--> enhanced patches --merge (hann)--> N* (H, W, 3)
      --lift (+ body)--> detailed frames (T, V', 3)
    material "auto": coarse frames --classifier (vote over patches and time)--> material

Contract:
  * Topology-dependent setup runs once per garment in NumPy (`make_pipeline`, defined with
    `PipelineConfig` and `Pipeline` in `wrinkle_jax.pipeline_setup`, re-exported here): the
    raster plan at the enhancer's texel size, the patch origins of the non-empty patches, the
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

import concurrent.futures
import dataclasses
import functools
import time
from collections.abc import Callable, Iterator, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import normalmap
from wrinkle_jax.mesh import Garment
from wrinkle_jax.meshio import GarmentSequence
from wrinkle_jax.numerics import to_device

# The per-garment setup, re-exported: `pipeline` is where users (and benchmarks) find it.
from wrinkle_jax.pipeline_setup import (  # noqa: F401
    STAGES,
    Pipeline,
    PipelineConfig,
    PipelineError,
    _body_for,
    _call_blur_weights,
    _compile,
    _lift_static,
    _network_blur_weights,
    _no_offsets,
    _noise_origins,
    _padded_mask,
    default_stride,
    make_pipeline,
)
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
           "default_stride", "enhance_frame", "enhance_sequence", "frame_fn", "iter_enhance",
           "lift_stage", "make_pipeline", "merge_stage", "network_stage", "resolve_material",
           "tile_stage"]


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
# Streaming
# --------------------------------------------------------------------------------------------


def _add(timings: dict, stage: str, t0: float) -> float:
    now = time.perf_counter()
    timings[stage] = timings.get(stage, 0.0) + now - t0
    return now


@functools.partial(jax.jit, static_argnames=("frames", "count"))
def _network_groups(inputs, frames: int, count: int):
    """The first `count` frames of `inputs` (T, P, S, S, C) cut into groups of `frames`
    frames, each flattened to (frames * P, S, S, C), the last one zero-padded to whole frames:
    the network calls' inputs, as one jitted program (slicing, padding and reshaping them
    eagerly compiled one XLA program per op)."""
    x = inputs[:count]
    calls = -(-count // frames)
    if calls * frames > count:  # whole frames of zeros: the compiled shape
        x = jnp.pad(x, ((0, calls * frames - count),) + ((0, 0),) * (x.ndim - 1))
    x = x.reshape(calls, frames * x.shape[1], *x.shape[2:])
    return tuple(x[i] for i in range(calls))


@functools.partial(jax.jit, static_argnames=("patches", "count", "total"))
def _network_join(outs, patches: int, count: int, total: int):
    """The network calls' outputs (each (F * P, S, S, C)) back to frames: the first `count`
    frames, zero-padded to `total` frames, (total, P, S, S, C) (one jitted program)."""
    x = jnp.concatenate(outs).reshape(-1, patches, *outs[0].shape[1:])[:count]
    return jnp.pad(x, ((0, total - count),) + ((0, 0),) * (x.ndim - 1))


def _run_network(pipe: Pipeline, inputs, material_id: int, counts: dict,
                 frames: int | None = None):
    """U-Net over the patches of n frames, (n, P, S, S, 3) -> same shape, RGB form.

    One `network_stage` call per group of `frames_per_call` frames (their patches
    concatenated, then cut into fixed-size batches; the last group zero-padded to whole
    frames, so the call compiles once). With one frame per call every batch holds patches of
    a single frame at fixed positions, so a patch's result never depends on its neighbours in
    the chunk. Models with texel noise get each patch's origin, so the noise is fixed to the
    cloth. `frames`: only the first `frames` of the n frames are real (default all); the
    others are not run and come back as zeros (a chunk's padding).
    """
    apply = _network_apply(pipe.enhancer)
    b, p, f = pipe.config.batch_size, pipe.num_patches, pipe.frames_per_call
    total = inputs.shape[0]
    n = total if frames is None else int(frames)
    material = to_device(np.int32(material_id))
    origins = _noise_origins(pipe)
    outs = [_network_frame(apply, pipe.enhancer.params, group, material, batch_size=b,
                           origins=origins, blur_weights=_call_blur_weights(pipe))
            for group in _network_groups(inputs, frames=f, count=n)]
    calls = -(-n // f)
    counts["network"] += n * p
    counts["padding"] += calls * pipe.batches_per_call * b - n * p
    counts["batches"] += calls * pipe.batches_per_call
    return _network_join(tuple(outs), patches=p, count=n, total=total)


def iter_enhance(pipe: Pipeline, frames, material_id: int, indices: Sequence[int] | None = None,
                 timings: dict | None = None, counts: dict | None = None
                 ) -> Iterator[EnhancedFrame]:
    """Enhance frames chunk by chunk, yielding one `EnhancedFrame` per frame, in order.

    With `PipelineConfig.overlap_lift` a worker thread lifts chunk k while this thread bakes,
    enhances and merges chunk k + 1 (two chunks alive at once); the frames, and their order,
    are the same as without it.

    Args:
      pipe: from `make_pipeline`.
      frames: (T, V, 3) float32 coarse vertices, meters (NumPy, may be a memmap: only one
        chunk is read at a time).
      material_id: index into `pipe.enhancer.config.materials`.
      indices: frame indices to enhance (default all), in the order given.
      timings: dict accumulating seconds per stage (bake, tile, network, merge, lift; with
        `overlap_lift` the lift's seconds overlap the others').
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
    chunks = _map_chunks(pipe, frames, material_id, indices, timings, counts)
    if not cfg.lift:
        for idx, coarse, enhanced in chunks:
            for j, t in enumerate(idx):
                yield EnhancedFrame(int(t), coarse[j], enhanced[j], None)
        return
    lift_static = _lift_static(pipe)
    # The lift's warm start: the previous frame's offsets in its local frames (zeros: cold).
    state = {"carried": _no_offsets(pipe) if cfg.warm_start else None}

    def lift_one(t: int, coarse, enhanced) -> EnhancedFrame:
        t0 = time.perf_counter()
        args = (pipe.subdivision, pipe.fine_garment, pipe.topology, _body_for(pipe.body, t),
                pipe.resolve_coarse)
        if cfg.warm_start:
            detailed, state["carried"], info = _lift_frame_warm(
                to_device(coarse), to_device(enhanced), state["carried"], *args, **lift_static)
            counts["lift_iterations"] += int(info.iterations)
        else:
            # The very computation `frame_fn` runs (bit for bit: a lift that stops short of
            # convergence amplifies rounding differences).
            detailed = _lift_frame(to_device(coarse), to_device(enhanced), *args, **lift_static)
        detailed = np.array(detailed)
        _add(timings, "lift", t0)
        return EnhancedFrame(int(t), coarse, enhanced, detailed)

    if not cfg.overlap_lift:
        for idx, coarse, enhanced in chunks:
            for j, t in enumerate(idx):
                yield lift_one(t, coarse[j], enhanced[j])
        return

    def lift_chunk(chunk) -> list[EnhancedFrame]:
        idx, coarse, enhanced = chunk
        return [lift_one(t, coarse[j], enhanced[j]) for j, t in enumerate(idx)]

    # One chunk in the worker at a time (the warm start is sequential): its result is taken
    # before the next chunk is submitted, and its frames are yielded (written, by the CLI)
    # while the worker lifts that next chunk. Leaving early (an error, a closed generator)
    # waits for the chunk in flight.
    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="wrinkle-jax-lift") as pool:
        pending = None
        for chunk in chunks:
            counts["peak_buffered_frames"] = max(
                counts["peak_buffered_frames"],
                len(chunk[0]) + (0 if pending is None else cfg.chunk_size))
            done = None if pending is None else pending.result()
            pending = pool.submit(lift_chunk, chunk)
            if done is not None:
                yield from done
        if pending is not None:
            yield from pending.result()


def _map_chunks(pipe: Pipeline, frames, material_id: int, indices: list, timings: dict,
                counts: dict) -> Iterator[tuple]:
    """(idx, coarse (n, V, 3), enhanced maps (n, H, W, 3)) per chunk of `indices`, NumPy:
    baked, cut into patches, enhanced and merged (the stages before the lift)."""
    cfg = pipe.config
    mask = _padded_mask(pipe)
    origins = to_device(pipe.origins)
    size = pipe.enhancer.config.patch_size
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
        maps, rgb = _bake_chunk(pipe.plan, to_device(coarse), mask, smooth=cfg.smooth,
                                padded_shape=pipe.padded_shape)
        rgb.block_until_ready()
        t0 = _add(timings, "bake", t0)
        tiles = _extract_chunk(rgb, origins, size=size)
        tiles.block_until_ready()
        del rgb
        t0 = _add(timings, "tile", t0)
        # The chunk's padding frames are not enhanced: zeros (the merge's compiled shape).
        out = _run_network(pipe, tiles, material_id, counts, frames=n)
        out.block_until_ready()
        del tiles
        t0 = _add(timings, "network", t0)
        enhanced = _merge_chunk(out, origins, mask, maps, window=cfg.window, shape=pipe.shape)
        enhanced = np.array(enhanced)  # host-owned (writable) copy; the device chunk is freed
        del out, maps
        _add(timings, "merge", t0)
        yield idx, coarse, enhanced


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
    `PipelineConfig.solver`, and a larger `adjoint_max_iters`, when gradients must be
    accurate; `solvers.SolverConfig` gives the measured errors). f is jitted (one compile per
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
    padded_mask = _padded_mask(pipe)
    # f runs one frame's patches: `pipe.blur_weights` serve it when laid out for one frame;
    # for several frames per call (or a copy with another batch size) they are recomputed.
    blur_weights = _call_blur_weights(pipe) if pipe.frames_per_call == 1 else None
    if blur_weights is None:
        blur_weights = _network_blur_weights(pipe.enhancer, padded_mask, pipe.origins,
                                             cfg.batch_size)
    setup = dict(plan=pipe.plan, padded_mask=padded_mask, blur_weights=blur_weights,
                 origins=to_device(pipe.origins), mask=to_device(pipe.mask),
                 subdivision=pipe.subdivision, fine_garment=pipe.fine_garment,
                 topology=pipe.topology, body=body, resolve_coarse=pipe.resolve_coarse)

    def f(params, coarse_vertices, material_id) -> FrameResult:
        return _frame(setup, params, coarse_vertices, material_id, static=static)

    return f


# --------------------------------------------------------------------------------------------
# Material
# --------------------------------------------------------------------------------------------


def classify_material(frames, garment: Garment, key):
    """The default classifier for material "auto": the shipped classifiers (the synthesis one,
    `wrinkle_jax.classifier.synthesis_model`, or the motion one, `...calibrated`) read the
    cloth's motion against the body and its pin track, which a `GarmentSequence` does not
    carry, so the library cannot run them from frames alone.

    Raises:
      PipelineError, always: naming why (no shipped motion classifier, or no body track) and
      what to do instead (a material name, `classify_fn`, or the CLI's `classify` /
      `enhance --material auto` on an `.npz` that holds the body's capsules).
    """
    from wrinkle_jax.classifier import ClassifierError, calibrated, synthesis_model

    if not synthesis_model.shipped():
        try:
            calibrated.load()
        except ClassifierError as e:
            raise PipelineError(f"material 'auto': no material classifier is available ({e}); "
                                f"pass a material name instead") from None
    raise PipelineError("material 'auto': the material classifiers need the body's motion "
                        "(capsule_ends) and the pin track, which a GarmentSequence does not "
                        "carry; pass a material name, a classify_fn, or run `wrinkle-jax "
                        "classify` on the .npz sequence with its capsules")


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
