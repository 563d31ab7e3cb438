"""Tests for the methods scored on aligned patches (`wrinkle_jax.evaluation.methods`)."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from evaluation_fixtures import PATCH, TEXEL, sheet_pair  # tests/ is on sys.path

from wrinkle_jax import material_index, patches
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.evaluation import patchsets


def test_unsharp_setting_reads_the_sweep_best_or_falls_back(tmp_path):
    p = tmp_path / "results.json"
    p.write_text(json.dumps({"unsharp_sweep": {"sigma=2,amount=1": 3.0,
                                               "sigma=12,amount=1.5": 7.5,
                                               "sigma=8,amount=4": -60.0}}))
    # Keys without "order=" predate the order-1 blur: they are order 0.
    assert method_lib.unsharp_setting(p, order=0)[:2] == (12.0, 1.5)
    assert method_lib.unsharp_setting(p, order=1)[:2] == method_lib.DEFAULT_UNSHARP
    p.write_text(json.dumps({"unsharp_sweep": {"order=0,sigma=8,amount=1.5": 9.0,
                                               "order=1,sigma=12,amount=1": 8.0,
                                               "order=1,sigma=16,amount=2": 5.0}}))
    assert method_lib.unsharp_setting(p, order=0)[:2] == (8.0, 1.5)
    assert method_lib.unsharp_setting(p, order=1)[:2] == (12.0, 1.0)
    assert method_lib.unsharp_setting(tmp_path / "missing.json")[:2] == method_lib.DEFAULT_UNSHARP
    names = list(method_lib.baseline_methods({0: (8.0, 1.5), 1: (12.0, 1.0)}))
    assert names[1:3] == ["unsharp order 0 (sigma=8,amount=1.5)",
                          "unsharp order 1 (sigma=12,amount=1)"]


def test_model_method_outputs_unit_normals_inside_the_mask_only(model):
    fine, coarse = sheet_pair(1)
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, TEXEL)
    mask = np.asarray(patches.pad_to_patch(pair.mask, PATCH)[0])
    origins, _ = patchsets.candidate_origins(mask, PATCH, PATCH // 2, 0.1)
    ps = patchsets.aligned_patches(pair, fine.frames[0], coarse.frames[0], origins[:3], PATCH, 4)
    timings = {}
    out = method_lib.enhancer_method(model, batch_size=2, timings=timings)(ps)
    inside = ps.mask[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(out[inside] * 2 - 1, axis=-1), 1.0, atol=1e-5)
    assert not out[~inside].any()
    assert timings["network_patches"] == 3 and timings["compile_s"] > 0


def test_wrong_material_swaps_the_table_materials_and_the_method_tells_the_model_so(model):
    silk, denim = material_index("silk_charmeuse"), material_index("denim_light")
    assert method_lib.wrong_material(silk) == denim and method_lib.wrong_material(denim) == silk
    assert method_lib.wrong_material(material_index("wool_melton")) == silk
    with pytest.raises(ValueError):
        method_lib.wrong_material(silk, materials=("silk_charmeuse",))
    # Give every material its own CIN parameters, so the material id changes the output.
    # NumPy draws: op by op, jax.random would compile a program for every leaf shape.
    rng = np.random.default_rng(3)
    params = jax.tree.map(
        lambda x: jnp.asarray(np.asarray(x) + 0.3 * rng.standard_normal(x.shape), x.dtype),
        model.params)
    noisy = model._replace(params=params)
    fine, coarse = sheet_pair(1)
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, TEXEL)
    mask = np.asarray(patches.pad_to_patch(pair.mask, PATCH)[0])
    origins, _ = patchsets.candidate_origins(mask, PATCH, PATCH // 2, 0.1)
    ps = patchsets.aligned_patches(pair, fine.frames[0], coarse.frames[0], origins[:2], PATCH, silk)
    wrong = method_lib.enhancer_method(noisy, batch_size=2,
                                       material_of=method_lib.wrong_material)(ps)
    right = method_lib.enhancer_method(noisy, batch_size=2)
    np.testing.assert_allclose(wrong, right(dataclasses.replace(ps, material_id=denim)),
                               atol=1e-6)
    assert np.abs(wrong - right(ps)).max() > 1e-3


def test_material_unsharp_settings_reads_the_sweep_and_is_empty_without_it(tmp_path):
    import json

    from wrinkle_jax import MATERIALS
    from wrinkle_jax.evaluation import methods as method_lib

    p = tmp_path / "sweep.json"
    assert method_lib.material_unsharp_settings(p) == {}
    p.write_text(json.dumps({"best": {"denim_light": "sigma=16,amount=0.5",
                                      "silk_charmeuse": "amount=2,sigma=8"}}))
    got = method_lib.material_unsharp_settings(p)
    assert got == {MATERIALS.index("denim_light"): (16.0, 0.5),
                   MATERIALS.index("silk_charmeuse"): (8.0, 2.0)}


def test_oracles_return_the_fine_patch_and_the_coarse_large_scale_with_its_detail():
    fine, coarse = sheet_pair(1)
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, TEXEL)
    mask = np.asarray(patches.pad_to_patch(pair.mask, PATCH)[0])
    origins, _ = patchsets.candidate_origins(mask, PATCH, PATCH // 2, 0.1)
    ps = patchsets.aligned_patches(pair, fine.frames[0], coarse.frames[0], origins[:3], PATCH, 4)
    oracles = method_lib.oracle_methods()
    np.testing.assert_array_equal(oracles["oracle fine"](ps), ps.target * ps.mask)
    out = oracles["oracle coarse + fine detail"](ps)
    inside = ps.mask[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(out[inside] * 2 - 1, axis=-1), 1.0, atol=1e-5)
    assert not out[~inside].any()
    # It is neither map: the coarse large scale with the fine detail...
    assert np.abs(out - ps.target)[inside].max() > 1e-3
    assert np.abs(out - ps.input)[inside].max() > 1e-3
    # ...and a patch carrying its own detail is returned unchanged.
    same = dataclasses.replace(ps, input=ps.target)
    np.testing.assert_allclose(oracles["oracle coarse + fine detail"](same), ps.target * ps.mask,
                               atol=2e-4)
