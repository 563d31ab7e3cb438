"""Tests for `wrinkle_jax.pipeline`: end to end on a tiny garment with a tiny random enhancer.

Every test uses the same garment, model and (patch) batch shape, so the stages compile once
for the module (jit caches are shared by every pipeline in the process).
"""

from __future__ import annotations

import dataclasses
import tracemalloc
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import bodies, lift, meshio, normalmap, pipeline, primitives

BATCH = 4


def _frames(garment, count: int) -> np.ndarray:
    """(T, V, 3) a sheet with a travelling ripple (meters)."""
    v = np.asarray(garment.vertices)
    t = np.arange(count, dtype=np.float32)[:, None]
    z = 0.01 * np.sin(40.0 * v[None, :, 0] + 0.7 * t)
    return (v[None] + np.stack([0 * z, 0 * z, z], -1)).astype(np.float32)


@pytest.fixture(scope="module")
def garment():
    return primitives.grid_sheet(6, 6, size=(0.16, 0.12))


# `model` is the session's tiny enhancer (tests/conftest.py, built once per worker): a width-4
# residual U-Net on 32 px patches of 4 mm texels. Residual, so that zeroing its output layer
# makes an identity network of the same shapes (one compile for both).


@pytest.fixture(scope="module")
def seq(garment):
    return meshio.make_sequence(_frames(garment, 4), garment)


@pytest.fixture(scope="module")
def result(seq, model):
    return pipeline.enhance_sequence(seq, "wool_melton", enhancer=model, batch_size=BATCH,
                                     chunk_size=4)


def test_end_to_end_shapes_finite_unit_normals_and_timings(result, seq, model):
    res = result
    plan = normalmap.make_plan(seq.garment, texel_size=model.config.texel_size)
    h, w = plan.shape
    assert res.material == "wool_melton" and res.scores is None
    assert res.frame_indices == (0, 1, 2, 3)
    assert res.normal_maps.shape == (4, h, w, 3) and res.mask.shape == (h, w, 1)
    fine = res.fine_garment
    assert res.detailed_frames.shape == (4, fine.num_vertices, 3)
    assert fine.num_vertices > seq.garment.num_vertices  # upsampled to ~10 mm edges
    assert np.isfinite(res.normal_maps).all() and np.isfinite(res.detailed_frames).all()
    inside = res.mask[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(res.normal_maps[:, inside], axis=-1), 1.0,
                               atol=1e-5)
    assert not res.normal_maps[:, ~inside & ~(np.asarray(plan.index_map) < plan.texel_pixel.size)
                               ].any()  # background (outside mask and gutter) is zero
    # The random network changes the map (the lift then follows random normals).
    coarse = np.asarray(normalmap.bake_frames(plan, seq.frames))
    assert np.abs(res.normal_maps - coarse)[:, inside].max() > 1e-2
    for stage in pipeline.STAGES + ("total",):
        assert stage in res.timings and res.timings[stage] >= 0.0
    for stage in ("bake", "network", "merge", "lift"):
        assert res.timings[stage] > 0.0
    p = res.patches
    assert p["per_frame"] > 0 and p["network"] == 4 * p["per_frame"]
    nb = -(-p["per_frame"] // BATCH)
    assert p["batches"] == 4 * nb and p["padding"] == 4 * (nb * BATCH - p["per_frame"])
    assert p["stride"] == 24 and p["patch_size"] == 32  # the default: 3/4 of the patch
    assert res.peak_buffered_frames == 4


def test_identity_network_keeps_the_coarse_map_and_mesh(seq, model, result):
    """A residual U-Net whose output layer is zero returns its input: N* is the coarse map on
    the garment and the lifted mesh stays at the upsampled coarse mesh."""
    params = {**model.params, "out": jax.tree.map(jnp.zeros_like, model.params["out"])}
    ident = model._replace(params=params)
    config = model.config
    res = pipeline.enhance_sequence(seq, "silk_chiffon", enhancer=ident, batch_size=BATCH,
                                    frames=[0, 3])
    plan = normalmap.make_plan(seq.garment, texel_size=config.texel_size)
    coarse = np.asarray(normalmap.bake_frames(plan, seq.frames[[0, 3]]))
    inside = res.mask[..., 0] > 0
    np.testing.assert_allclose(res.normal_maps[:, inside], coarse[:, inside], atol=1e-5)
    _, sub = lift.upsample(seq.garment)
    p0 = np.asarray(jax.vmap(sub.apply)(seq.frames[[0, 3]]))
    assert np.abs(res.detailed_frames - p0).max() < 2e-3  # meters


def test_streaming_chunk_size_and_repeat_do_not_change_results(result, seq, model):
    one = pipeline.enhance_sequence(seq, "wool_melton", enhancer=model, batch_size=BATCH,
                                    chunk_size=1)
    np.testing.assert_array_equal(one.normal_maps, result.normal_maps)
    np.testing.assert_array_equal(one.detailed_frames, result.detailed_frames)
    assert one.peak_buffered_frames == 1
    # A chunk of 3 over 4 frames pads the last chunk; a frame subset in another order.
    sub = pipeline.enhance_sequence(seq, "wool_melton", enhancer=model, batch_size=BATCH,
                                    chunk_size=3, frames=[3, 1], lift=False)
    assert sub.frame_indices == (3, 1) and sub.detailed_frames is None
    np.testing.assert_array_equal(sub.normal_maps, result.normal_maps[[3, 1]])


def _assert_same_maps_up_to_batch_blocking(a, b):
    """Normal maps of one sequence enhanced with different network batch sizes: XLA's float32
    GEMM blocking changes with the batch and moves the network's output by ~1e-5, which a few
    texels amplify (on session 37's fresh machine 353 of 30,912 values off by more than 3e-5,
    at most 1.9e-3; the machine before gave 2e-6 everywhere). A wrong or misplaced patch moves
    whole patches by far more."""
    off = np.abs(np.asarray(a) - np.asarray(b))
    assert (off > 3e-5).mean() < 0.02 and off.max() < 0.01


def test_batch_padding_gives_the_same_maps(result, seq, model):
    per_frame = result.patches["per_frame"]
    batch = next(b for b in (3, 5, 6, 7) if per_frame % b)  # forces zero-padded batches
    padded = pipeline.enhance_sequence(seq, "wool_melton", enhancer=model, batch_size=batch,
                                       lift=False)
    assert padded.patches["padding"] > 0
    _assert_same_maps_up_to_batch_blocking(padded.normal_maps, result.normal_maps)


def test_enhance_frame_matches_the_sequence(result, seq, model):
    frame = pipeline.enhance_frame(seq.frames[2], seq.garment, "wool_melton", enhancer=model,
                                   batch_size=BATCH)
    assert frame.index == 0
    np.testing.assert_array_equal(frame.normal_map, result.normal_maps[2])
    np.testing.assert_array_equal(frame.detailed, result.detailed_frames[2])
    np.testing.assert_array_equal(frame.coarse, seq.frames[2])


def test_frame_fn_is_the_streamed_frame(result, seq, model):
    """One jitted function of (params, coarse vertices, material) computes what the streaming
    pipeline computes for that frame (same stages, padding and batches)."""
    pipe = pipeline.make_pipeline(seq.garment, model, pipeline.PipelineConfig(batch_size=BATCH),
                                  compile=False)
    f = pipeline.frame_fn(pipe)
    out = f(model.params, jnp.asarray(seq.frames[2]), model.config.material_id("wool_melton"))
    assert isinstance(out, pipeline.FrameResult)
    np.testing.assert_allclose(out.normal_map, result.normal_maps[2], atol=1e-6)
    np.testing.assert_allclose(out.detailed, result.detailed_frames[2], atol=1e-6)
    np.testing.assert_array_equal(out.mask, result.mask)


def test_material_auto_uses_the_injected_classifier(seq, model):
    calls = []

    def classify(frames, garment, key):
        calls.append(frames.shape)
        return SimpleNamespace(material="knit_terry", scores={"knit_terry": 0.7,
                                                               "silk_chiffon": 0.3})

    res = pipeline.enhance_sequence(seq, "auto", enhancer=model, batch_size=BATCH, lift=False,
                                    classify_fn=classify, frames=[0, 2])
    assert calls == [(2, seq.garment.num_vertices, 3)]
    assert res.material == "knit_terry" and res.scores == {"knit_terry": 0.7,
                                                           "silk_chiffon": 0.3}
    assert res.timings["classify"] > 0

    with pytest.raises(pipeline.PipelineError, match="unknown material 'felt'"):
        pipeline.resolve_material("felt", model.config.materials)
    with pytest.raises(pipeline.PipelineError, match="does not know"):
        pipeline.resolve_material("auto", ("silk_charmeuse",), seq.frames, seq.garment,
                                  lambda f, g, k: SimpleNamespace(material="denim", scores={}))


def test_material_auto_without_a_classifier_is_a_clear_error(seq, monkeypatch, tmp_path):
    from wrinkle_jax.classifier import calibrated, synthesis_model

    monkeypatch.setattr(calibrated, "MOTION_PATH", tmp_path / "none.npz")  # nothing ships
    monkeypatch.setattr(synthesis_model, "SYNTHESIS_PATH", tmp_path / "none_s.npz")
    with pytest.raises(pipeline.PipelineError, match="no material classifier is available"):
        pipeline.resolve_material("auto", ("silk_charmeuse",), seq.frames, seq.garment)
    # With a model, frames alone still cannot be classified: the motion is read against the
    # body, which a GarmentSequence does not carry.
    monkeypatch.setattr(calibrated, "load", lambda path=None: object())
    with pytest.raises(pipeline.PipelineError, match="capsule_ends"):
        pipeline.resolve_material("auto", ("silk_charmeuse",), seq.frames, seq.garment)


def test_memory_does_not_grow_with_the_sequence_length(garment, model):
    """Live device bytes at every write, and the host peak, for 10 vs 40 frames."""

    def run(count, leak=False):
        s = meshio.make_sequence(_frames(garment, count), garment)
        live, kept = [], []

        def writer(frame):
            live.append(sum(a.nbytes for a in jax.live_arrays()))
            if leak:
                kept.append(frame)

        tracemalloc.start()
        res = pipeline.enhance_sequence(s, "silk_charmeuse", enhancer=model, batch_size=BATCH,
                                        lift=False, keep=False, writer=writer)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert res.normal_maps is None and len(live) == count
        return max(live), peak, res

    run(4)  # warm up: the first run also allocates compile-time and cache objects
    live10, host10, res10 = run(10)
    live40, host40, res40 = run(40)
    one_map = int(np.prod(res10.mask.shape[:2])) * 3 * 4
    assert live40 <= live10 + one_map, (live10, live40)
    assert host40 <= host10 + 4 * one_map + (1 << 16), (host10, host40)
    assert res10.peak_buffered_frames == res40.peak_buffered_frames == 4
    # Control: a writer that keeps every frame does show up in the host measurement.
    _, host40_leak, _ = run(40, leak=True)
    assert host40_leak > host10 + 30 * one_map, (host10, host40_leak)


def test_no_lift_and_body(seq, model, result):
    fine = result.fine_garment
    # A ball pushed up into the middle of the sheet: the lifted garment must end outside.
    center = np.asarray(seq.frames[0]).mean(0) - np.array([0.0, 0.0, 0.02], np.float32)
    body = bodies.primitive_body(spheres=(center[None], np.array([0.03], np.float32)))
    res = pipeline.enhance_sequence(seq, "wool_melton", enhancer=model, batch_size=BATCH,
                                    body=body, frames=[0])
    assert res.detailed_frames.shape == (1, fine.num_vertices, 3)
    before = bodies.query(body, result.detailed_frames[0]).distance
    after = bodies.query(body, res.detailed_frames[0]).distance
    assert float(before.min()) < -1e-3 and float(after.min()) >= -1e-4


def test_config_validation():
    with pytest.raises(ValueError, match="batch_size"):
        pipeline.PipelineConfig(batch_size=0)
    with pytest.raises(ValueError, match="window"):
        pipeline.PipelineConfig(window="gauss")
    assert dataclasses.replace(pipeline.PipelineConfig(), stride=8).stride == 8


def test_map_smaller_than_a_patch_is_padded(model):
    g = primitives.grid_sheet(3, 3, size=(0.06, 0.05))
    s = meshio.make_sequence(_frames(g, 2), g)
    res = pipeline.enhance_sequence(s, "denim_light", enhancer=model, batch_size=BATCH,
                                    lift=False)
    h, w = res.mask.shape[:2]
    assert h < 32 and w < 32 and res.normal_maps.shape == (2, h, w, 3)
    assert res.patches["per_frame"] == 1
    inside = res.mask[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(res.normal_maps[:, inside], axis=-1), 1.0,
                               atol=1e-5)


def test_a_given_layout_bakes_onto_its_pixels_and_must_match_the_texel_size(seq, model):
    """With `layout`, N* lives on that layout's grid (here 20 texels of margin instead of 8):
    the identity network returns the coarse map baked on it."""
    params = {**model.params, "out": jax.tree.map(jnp.zeros_like, model.params["out"])}
    ident = model._replace(params=params)
    layout = normalmap.layout_for(seq.garment, model.config.texel_size, margin=20)
    pipe = pipeline.make_pipeline(seq.garment, ident, pipeline.PipelineConfig(
        batch_size=BATCH, lift=False), layout=layout)
    assert pipe.shape == (layout.height, layout.width)
    got = np.stack([f.normal_map for f in pipeline.iter_enhance(pipe, seq.frames, 0, [1, 2])])
    plan = normalmap.make_plan(seq.garment, layout=layout)
    want = np.asarray(normalmap.bake_frames(plan, seq.frames[[1, 2]]))
    inside = np.asarray(plan.mask)[..., 0] > 0
    assert got.shape == (2, layout.height, layout.width, 3)
    np.testing.assert_allclose(got[:, inside], want[:, inside], atol=1e-5)
    own = normalmap.layout_for(seq.garment, model.config.texel_size)
    assert (layout.height, layout.width) == (own.height + 24, own.width + 24)
    wrong = normalmap.layout_for(seq.garment, 2 * model.config.texel_size)
    with pytest.raises(pipeline.PipelineError, match="texel size"):
        pipeline.make_pipeline(seq.garment, ident, pipeline.PipelineConfig(lift=False),
                               layout=wrong)


def test_warm_started_lift_carries_the_previous_frame(seq, model):
    """With `warm_start`, a repeated frame starts from its own previous solution (carried
    through the local frames), so the lift keeps descending the same energy across frames
    instead of repeating the same solve. (On this random network's map the solver does not
    converge within the pipeline's iteration cap: every cold start stops at the same
    unconverged mesh.)"""
    frames = np.repeat(seq.frames[1:2], 3, axis=0)
    runs = {}
    for warm in (False, True):
        pipe = pipeline.make_pipeline(
            seq.garment, model, pipeline.PipelineConfig(batch_size=BATCH, warm_start=warm),
            compile=False)
        counts, iters, meshes = {}, [], []
        for frame in pipeline.iter_enhance(pipe, frames, model.config.material_id("wool_melton"),
                                           counts=counts):
            iters.append(counts["lift_iterations"] - sum(iters))
            meshes.append(frame.detailed)
        runs[warm] = (iters, meshes, frame.normal_map)
    (cold_iters, cold, nmap), (warm_iters, warm, _) = runs[False], runs[True]
    assert cold_iters == [0, 0, 0]  # counted with warm starts only
    cap = pipe.config.solver.max_iters
    assert warm_iters[0] == cap and min(warm_iters[1:]) >= 1  # the first frame: a cold start
    np.testing.assert_array_equal(cold[2], cold[0])
    # The energy of the one problem all frames share goes down frame after frame. One
    # program (op by op, each of the problem's primitives compiles on its own).
    @jax.jit
    def energies(coarse, nmap, meshes):
        p0 = pipe.subdivision.apply(coarse)
        targets = lift.sample_target_normals(nmap, pipe.fine_garment, pipe.plan.layout)
        prob = lift.make_problem(p0, pipe.topology, targets)
        return jax.vmap(lambda m: lift.energy(m, prob))(meshes)

    e = [float(x) for x in energies(jnp.asarray(frames[0]), jnp.asarray(nmap),
                                    jnp.asarray(np.stack(warm)))]
    assert e[1] < e[0] * (1 - 1e-4) and e[2] <= e[1], e
    repeated = meshio.make_sequence(frames, seq.garment)
    res = pipeline.enhance_sequence(repeated, "wool_melton", enhancer=model,
                                    config=pipeline.PipelineConfig(batch_size=BATCH,
                                                                   warm_start=True))
    assert res.lift_iterations == sum(warm_iters)
    np.testing.assert_array_equal(res.detailed_frames[2], warm[2])


def test_overlapped_lift_gives_the_same_frames_in_order(seq, model, monkeypatch):
    """`overlap_lift`: chunk k lifted in a worker thread while chunk k + 1 is enhanced. Same
    frames bit for bit (warm-started, so the lift's order matters), in the order asked, two
    chunks alive at once; a worker error reaches the caller; closing the generator early
    leaves no worker running."""
    import threading

    order = [0, 1, 2, 3, 2]  # chunks of 2: the last one padded
    runs = {}
    for overlap in (False, True):
        config = pipeline.PipelineConfig(batch_size=BATCH, chunk_size=2, warm_start=True,
                                         overlap_lift=overlap)
        runs[overlap] = pipeline.enhance_sequence(seq, "wool_melton", enhancer=model,
                                                  config=config, frames=order)
    seq_run, ovl = runs[False], runs[True]
    assert ovl.frame_indices == tuple(order)
    np.testing.assert_array_equal(ovl.normal_maps, seq_run.normal_maps)
    np.testing.assert_array_equal(ovl.detailed_frames, seq_run.detailed_frames)
    assert ovl.lift_iterations == seq_run.lift_iterations > 0
    assert (seq_run.peak_buffered_frames, ovl.peak_buffered_frames) == (2, 4)
    assert ovl.timings["lift"] > 0.0

    config = pipeline.PipelineConfig(batch_size=BATCH, chunk_size=2, warm_start=True,
                                     overlap_lift=True)
    pipe = pipeline.make_pipeline(seq.garment, model, config, compile=False)
    material = model.config.material_id("wool_melton")
    frames = pipeline.iter_enhance(pipe, seq.frames, material, order)
    assert next(frames).index == 0
    frames.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("wrinkle-jax-lift")]

    calls = []
    real = pipeline._lift_frame_warm

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("lift failed")
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "_lift_frame_warm", failing)
    got = []
    with pytest.raises(RuntimeError, match="lift failed"):
        for frame in pipeline.iter_enhance(pipe, seq.frames, material, order):
            got.append(frame.index)
    assert got == [0, 1]


def test_frames_per_batch_shares_network_calls_and_keeps_the_maps(result, seq, model):
    """Patches of several frames in one network call (the chunk's last group zero-padded to
    whole frames) give the per-frame maps up to float rounding; the counts follow."""
    per_frame = result.patches["per_frame"]
    batch = next(b for b in (3, 5, 6, 7) if per_frame % b)  # per-frame batches are padded
    one = pipeline.enhance_sequence(seq, "wool_melton", enhancer=model, config=pipeline.
                                    PipelineConfig(batch_size=batch, chunk_size=3, lift=False))
    shared = pipeline.enhance_sequence(seq, "wool_melton", enhancer=model, config=pipeline.
                                       PipelineConfig(batch_size=batch, chunk_size=3,
                                                      frames_per_batch=2, lift=False))
    np.testing.assert_allclose(shared.normal_maps, one.normal_maps, atol=3e-5)
    _assert_same_maps_up_to_batch_blocking(shared.normal_maps, result.normal_maps)
    # 4 frames in chunks of 3 (+1): groups of 2, 1 (padded to 2) and 1 (padded to 2).
    calls, per_call = 3, -(-2 * per_frame // batch)
    assert shared.patches["batches"] == calls * per_call
    assert shared.patches["padding"] == calls * per_call * batch - 4 * per_frame
    assert shared.patches["network"] == one.patches["network"] == 4 * per_frame
    with pytest.raises(ValueError, match="frames_per_batch"):
        pipeline.PipelineConfig(frames_per_batch=0)


def test_blur_weights_computed_once_give_the_in_network_blurs_maps(seq, monkeypatch):
    """A model with the shipped blur layout (unsharp base and high-passed residual, two radii):
    the pipeline computes the blurs' mask-only weights once per garment, and its maps equal
    those of the in-network blurs, two frames per network call and through `frame_fn`."""
    from wrinkle_jax import enhancer
    from wrinkle_jax.nn import unet

    cfg = enhancer.EnhancerConfig(
        unet.UNetConfig(width=4, residual=True, residual_base="unsharp", unsharp_sigma=4.0,
                        residual_highpass=2.0), patch_size=32, texel_size=0.004)
    enh = enhancer.init_enhancer(jax.random.key(1, impl="rbg"), cfg)
    material = cfg.material_id("wool_melton")

    def maps(pipe):
        return np.stack([f.normal_map for f in pipeline.iter_enhance(pipe, seq.frames,
                                                                     material)])

    # Two frames per network call (weights tiled over both frames' patches); frame_fn runs
    # one frame's patches (weights for one frame).
    config = pipeline.PipelineConfig(batch_size=3, chunk_size=4, lift=False, frames_per_batch=2)
    pipe = pipeline.make_pipeline(seq.garment, enh, config, compile=False)
    assert set(pipe.blur_weights) == {"highpass", "unsharp"}
    assert pipe.blur_weights["highpass"].shape[0] == pipe.batches_per_call
    got = maps(pipe)
    want = maps(dataclasses.replace(pipe, blur_weights=None))
    np.testing.assert_allclose(got, want, atol=2e-6)
    coarse = np.asarray(normalmap.bake_frames(pipe.plan, seq.frames))
    assert np.abs(got - coarse).max() > 1e-2  # the blurs' output is in the maps
    out = pipeline.frame_fn(pipe)(enh.params, jnp.asarray(seq.frames[1]), material)
    np.testing.assert_allclose(out.normal_map, want[1], atol=2e-6)
    # A copy with another batch size does not use weights laid out for the original's.
    other = dataclasses.replace(pipe, config=dataclasses.replace(config, batch_size=2))
    assert pipeline._call_blur_weights(pipe) is pipe.blur_weights
    assert pipeline._call_blur_weights(other) is None
    # One frame per call: frame_fn uses the pipeline's weights as they are (computed once).
    one = pipeline.make_pipeline(seq.garment, enh, dataclasses.replace(config, frames_per_batch=1),
                                 compile=False)
    monkeypatch.setattr(pipeline, "_network_blur_weights", None)  # not computed again
    out = pipeline.frame_fn(one)(enh.params, jnp.asarray(seq.frames[1]), material)
    np.testing.assert_allclose(out.normal_map, want[1], atol=2e-6)
