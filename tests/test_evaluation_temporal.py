"""Tests for frame-to-frame flicker of normal maps and of an enhanced sequence
(`wrinkle_jax.evaluation.flicker`, `.temporal`)."""

from __future__ import annotations

import numpy as np
import pytest
from evaluation_fixtures import SIZE, TEXEL, sheet_sequence  # tests/ is on sys.path

from experiments import temporal
from wrinkle_jax import evaluation, meshio, normalmap, primitives
from wrinkle_jax.evaluation import patchsets
from wrinkle_jax.evaluation import temporal as temporal_lib


def _rotating_sheet(frames, degrees_per_frame, nx=12, ny=8):
    """A flat sheet turning rigidly about the x axis: every normal turns by the same angle."""
    g = primitives.grid_sheet(nx, ny, size=SIZE)
    v = np.asarray(g.vertices)
    out = []
    for t in range(frames):
        a = np.radians(degrees_per_frame * t)
        rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        out.append(v @ rot.T)
    return meshio.make_sequence(np.asarray(out, np.float32), g)


def test_flicker_of_a_rigid_rotation_is_its_angle_and_of_a_static_map_zero():
    seq = _rotating_sheet(4, 3.0)
    plan = normalmap.make_plan(seq.garment, texel_size=TEXEL)
    maps = np.stack([patchsets.bake_map(plan, f) for f in seq.frames])
    np.testing.assert_allclose(evaluation.flicker_series(maps, plan.mask), 3.0, atol=1e-3)
    np.testing.assert_allclose(evaluation.flicker_series(maps[[1, 1, 1]], plan.mask), 0.0,
                               atol=1e-4)
    assert evaluation.mean_angular_change(maps[0], maps[1], np.zeros_like(plan.mask)) == 0.0


def test_sequence_flicker_static_is_zero_and_rotation_moves_coarse_and_fine(model):
    static = sheet_sequence(10, 7, 1)
    static = meshio.make_sequence(np.repeat(static.frames, 3, 0), static.garment)
    res = temporal_lib.sequence_flicker(static, static, model, "wool_melton", [0, 1, 2],
                                    batch_size=4)
    for k in temporal_lib.SERIES:
        np.testing.assert_allclose(res[k], 0.0, atol=1e-3)
    assert res["patches_per_frame"] > 0 and res["timings"]["network"] > 0
    coarse, fine = _rotating_sheet(3, 2.0), _rotating_sheet(3, 2.0, nx=40, ny=30)
    res = temporal_lib.sequence_flicker(coarse, fine, model, "wool_melton", [0, 1, 2], batch_size=4)
    np.testing.assert_allclose(res["coarse"], 2.0, atol=1e-3)
    np.testing.assert_allclose(res["fine"], 2.0, atol=1e-3)
    assert res["output"].shape == (2,) and np.isfinite(res["output"]).all()
    s = temporal.summarize(res)
    assert s["output_over_fine"] == pytest.approx(res["output"].mean() / 2.0, rel=1e-3)
    with pytest.raises(ValueError, match="consecutive"):
        temporal_lib.sequence_flicker(coarse, fine, model, "wool_melton", [0, 2])
