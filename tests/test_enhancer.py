import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import enhancer, hostcpu, sharpen
from wrinkle_jax.nn import unet

KEY = jax.random.key(0, impl="rbg")
SMALL = enhancer.EnhancerConfig(unet.UNetConfig(width=4), patch_size=32)


@pytest.fixture(scope="module")
def small():
    return enhancer.init_enhancer(KEY, SMALL, conv_impl="im2col_f32")


def test_round_trip_float32_is_exact(small, tmp_path):
    path = enhancer.save_enhancer(tmp_path / "m.npz", small.params, SMALL, {"steps": 7},
                                  dtype=np.float32)
    got = enhancer.load_enhancer(path, conv_impl="im2col_f32")
    assert got.config == SMALL and got.meta["steps"] == 7
    for a, b in zip(jax.tree.leaves(small.params), jax.tree.leaves(got.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_float16_storage_changes_outputs_little(small, tmp_path):
    path = enhancer.save_enhancer(tmp_path / "m.npz", small.params, SMALL)
    got = enhancer.load_enhancer(path, conv_impl="im2col_f32")
    x = np.random.default_rng(0).uniform(size=(3, 32, 32, 3)).astype(np.float32)
    mat = np.array([0, 2, 4])
    apply = enhancer.make_apply(small, clip=False)
    a, b = np.asarray(apply(small.params, x, mat)), np.asarray(apply(got.params, x, mat))
    assert np.linalg.norm(a - b) / np.linalg.norm(a) < 2e-3
    assert not np.array_equal(a, b)  # float16 really rounded


def test_materials_condition_the_output(small):
    apply = enhancer.make_apply(small)
    x = np.random.default_rng(1).uniform(size=(1, 32, 32, 3)).astype(np.float32)
    outs = [np.asarray(apply(small.params, x, np.array([m]))) for m in range(5)]
    assert all(o.min() >= 0 and o.max() <= 1 for o in outs)
    # CIN tables start equal (scale 1, shift 0), so perturb one material's tables.
    params = jax.tree.map(lambda v: v, small.params)
    params["cin1"]["scale"] = params["cin1"]["scale"].at[3].mul(2.0)
    o3 = np.asarray(apply(params, x, np.array([3])))
    o2 = np.asarray(apply(params, x, np.array([2])))
    np.testing.assert_allclose(o2, outs[2], atol=1e-6)
    assert np.abs(o3 - outs[3]).max() > 1e-4


def test_material_names(small):
    assert SMALL.material_id("denim_light") == SMALL.materials.index("denim_light")
    with pytest.raises(ValueError, match="leather"):
        SMALL.material_id("leather")


def test_bad_files_name_the_problem(small, tmp_path):
    with pytest.raises(enhancer.EnhancerError, match="no such enhancer file"):
        enhancer.load_enhancer(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(enhancer.EnhancerError, match="junk.npz"):
        enhancer.load_enhancer(junk)
    # Parameters of another width under this config.
    path = enhancer.save_enhancer(tmp_path / "w.npz", small.params, SMALL)
    with np.load(path) as z:
        files = dict(z)
    cfg = json.loads(bytes(files["config.json"]).decode())
    cfg["width"] = 8
    files["config.json"] = np.frombuffer(json.dumps(cfg).encode(), np.uint8)
    np.savez(tmp_path / "mismatch.npz", **files)
    with pytest.raises(enhancer.EnhancerError, match="do not match"):
        enhancer.load_enhancer(tmp_path / "mismatch.npz")


def test_non_finite_after_cast_is_refused(small, tmp_path):
    params = jax.tree.map(lambda v: v, small.params)
    params["out"]["bias"] = params["out"]["bias"] + 1e6
    with pytest.raises(enhancer.EnhancerError, match="float16"):
        enhancer.save_enhancer(tmp_path / "big.npz", params, SMALL)


def test_unsharp_base_round_trips_with_its_gains(tmp_path):
    conf = enhancer.EnhancerConfig(unet.UNetConfig(width=4, residual=True,
                                                   residual_base="unsharp", unsharp_sigma=2.0,
                                                   unsharp_amount=1.5), patch_size=32)
    enh = enhancer.init_enhancer(KEY, conf, conv_impl="im2col_f32")
    params = {**enh.params, "unsharp_amount": enh.params["unsharp_amount"].at[1].set(0.25)}
    path = enhancer.save_enhancer(tmp_path / "m.npz", params, conf, dtype=np.float32)
    got = enhancer.load_enhancer(path, conv_impl="im2col_f32")
    assert got.config == conf
    np.testing.assert_array_equal(np.asarray(got.params["unsharp_amount"]),
                                  [1.5, 0.25, 1.5, 1.5, 1.5])
    # A file whose config says "input" base but carries gains (or vice versa) is refused.
    bad = enhancer.save_enhancer(tmp_path / "bad.npz", params,
                                 enhancer.EnhancerConfig(unet.UNetConfig(width=4, residual=True),
                                                         patch_size=32),
                                 dtype=np.float32)
    with pytest.raises(enhancer.EnhancerError, match="do not match"):
        enhancer.load_enhancer(bad)


def test_residual_gain_scales_the_residual_and_round_trips(tmp_path):
    """base + g * residual: gain 0 is the model's own unsharp base, 0.5 the midpoint of base
    and full output (before the detail representation, here off, and the clip)."""
    conf = enhancer.EnhancerConfig(unet.UNetConfig(width=4, residual=True,
                                                   residual_base="unsharp", unsharp_sigma=2.0,
                                                   residual_highpass=2.0), patch_size=32)
    enh = enhancer.init_enhancer(KEY, conf, conv_impl="im2col_f32")
    params = jax.tree.map(lambda x: x + 0.05, enh.params)  # a non-zero residual
    x = jnp.asarray(np.random.default_rng(0).uniform(0.2, 0.8, (2, 32, 32, 3)), jnp.float32)
    m = jnp.array([0, 3])
    # Jitted, one program per gain (op-by-op dispatch of the im2col U-Net compiles each of
    # its many slices and dots separately).
    out = {g: np.asarray(jax.jit(enhancer.with_unet(enh, residual_gain=g).model.apply)(
        {"params": params}, x, m)) for g in (0.0, 0.5, 1.0)}
    base = np.asarray(sharpen.unsharp_rgb(x, 2.0, params["unsharp_amount"][m],
                                          jnp.ones((2, 32, 32, 1)), 1))
    np.testing.assert_allclose(out[0.0], base, atol=1e-5)
    np.testing.assert_allclose(out[0.5], (out[0.0] + out[1.0]) / 2, atol=1e-5)
    assert np.abs(out[1.0] - out[0.0]).max() > 1e-2
    half = enhancer.with_unet(enh, residual_gain=0.5)
    assert half.model.conv_impl == "im2col_f32" and enh.config.unet.residual_gain == 1.0
    path = enhancer.save_enhancer(tmp_path / "g.npz", params, half.config, dtype=np.float32)
    assert enhancer.load_enhancer(path).config.unet.residual_gain == 0.5


def test_files_without_blur_order_keep_the_order0_blur():
    """Model files and run configs written before `blur_order` existed were trained with the
    order-0 (local mean) blur; reading them must not silently switch to the new default."""
    from wrinkle_jax import train

    d = enhancer.EnhancerConfig(unet.UNetConfig(residual=True, residual_base="unsharp")).to_json()
    assert d.pop("blur_order") == 1
    assert enhancer.EnhancerConfig.from_json(d).unet.blur_order == 0
    t = train.TrainConfig().to_json()
    t.pop("blur_order")
    assert train.TrainConfig.from_json(t).unet.blur_order == 0
    one = train.TrainConfig(unet.UNetConfig(blur_order=1))
    assert train.TrainConfig.from_json(one.to_json()).unet.blur_order == 1


def test_shipped_model_loads_and_enhances():
    """The default model ships in the package (a fresh clone has it): it loads, is the recipe
    its model card describes, and sharpens folds on a 128x128 patch."""
    import jax.numpy as jnp

    enh = enhancer.load_enhancer()
    c = enh.config
    assert c.unet == unet.RECIPE_UNET and c.patch_size == 128
    assert enh.meta["steps"] > 0 and enh.meta["train_patches"] > 0
    assert enhancer.DEFAULT_PATH.stat().st_size < 10 * 2**20
    y, x = np.mgrid[0:128, 0:128] / 128.0
    g = 0.4 * np.sin(2 * np.pi * 3 * x)
    nrm = np.stack([-g, np.zeros_like(g), np.ones_like(g)], -1)
    patch = ((nrm / np.linalg.norm(nrm, axis=-1, keepdims=True) + 1) / 2)[None].astype(np.float32)
    out = np.asarray(enhancer.make_apply(enh)(enh.params, jnp.asarray(patch),
                                              jnp.array([c.material_id("silk_charmeuse")])))
    assert out.shape == patch.shape and np.all(np.isfinite(out))
    assert np.all((out >= 0) & (out <= 1))
    # Sharpening: the x-component's swing across the folds grows.
    assert np.ptp(out[0, 40:90, 40:90, 0]) > 1.05 * np.ptp(patch[0, 40:90, 40:90, 0])


def test_enhance_patches_unit_normals_in_the_mask_independent_of_batching(small):
    rng = np.random.default_rng(0)
    size = small.config.patch_size
    x = rng.uniform(0.2, 0.8, (5, size, size, 3)).astype(np.float32)
    mask = np.zeros((5, size, size, 1), np.float32)
    mask[:, : size // 2] = 1
    mats = np.array([0, 1, 2, 3, 4])
    apply = enhancer.make_apply(small)
    timings = {}
    got = enhancer.enhance_patches(apply, small.params, x, mats, mask, batch_size=2,
                                   timings=timings)
    assert got.shape == x.shape and timings["network_patches"] == 5
    inside = mask[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(got[inside] * 2 - 1, axis=-1), 1.0, atol=1e-5)
    assert not got[~inside].any()
    # one call for all five patches gives the same result; and so does the plain apply
    np.testing.assert_allclose(
        enhancer.enhance_patches(apply, small.params, x, mats, mask, batch_size=8), got,
        atol=1e-6)
    ref = np.asarray(apply(small.params, x, mats)) * 2 - 1
    ref = (ref / np.linalg.norm(ref, axis=-1, keepdims=True) + 1) / 2 * mask
    np.testing.assert_allclose(got, ref, atol=1e-5)
    # a scalar material is broadcast
    one = enhancer.enhance_patches(apply, small.params, x[:2], 3, mask[:2], batch_size=2)
    np.testing.assert_allclose(
        one, enhancer.enhance_patches(apply, small.params, x[:2], [3, 3], mask[:2], 2), atol=0)


def _shipped_model_files():
    from pathlib import Path

    results = Path(__file__).resolve().parents[1] / "experiments" / "results"
    return [enhancer.DEFAULT_PATH, *sorted((results / "fidelity").glob("*.npz")),
            results / "patchgan" / "patchgan.npz", results / "sheet_only" / "enhancer.npz"]


@pytest.mark.parametrize("path", _shipped_model_files(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_shipped_model_files_and_their_run_configs_still_read(path):
    """Every model file in the repository was written with the flat config (before
    `UNetConfig` was nested): it loads (parameters matching its config), its config and the
    training config in its metadata read back to the same JSON, and files written now keep
    that form."""
    from wrinkle_jax import train
    from wrinkle_jax.nn import patchgan

    assert path.is_file()
    with np.load(path) as z:
        raw = json.loads(bytes(z["config.json"]).decode())
        meta = json.loads(bytes(z["meta.json"]).decode())
    enh = enhancer.load_enhancer(path, conv_impl="im2col_f32")
    again = json.loads(json.dumps(enh.config.to_json()))
    assert {k: again[k] for k in raw} == raw
    assert enh.config.unet.width == raw["width"] and enh.config.unet.residual == raw["residual"]
    assert set(again) - set(raw) <= {f for f in unet.UNetConfig().to_json()}
    for key, cls in (("train_config", train.TrainConfig), ("gan_config", patchgan.GANConfig)):
        if key in meta:
            cfg = cls.from_json(meta[key])
            back = json.loads(json.dumps(cfg.to_json()))
            assert {k: back[k] for k in meta[key]} == meta[key]
            assert cfg.unet == enh.config.unet  # the run trained what the file holds
    assert "train_config" in meta or "gan_config" in meta


def test_config_json_is_flat_and_round_trips():
    net = unet.UNetConfig(width=8, residual=True, residual_base="unsharp", detail_sigma=8.0,
                          noise_channels=4, noise_scale=4, upsample="bilinear")
    conf = enhancer.EnhancerConfig(net, materials=("a", "b"), patch_size=64)
    d = json.loads(json.dumps(conf.to_json()))
    assert d["width"] == 8 and d["upsample"] == "bilinear" and "unet" not in d
    assert enhancer.EnhancerConfig.from_json(d) == conf
    with pytest.raises(ValueError, match="unknown enhancer config fields.*colour"):
        enhancer.EnhancerConfig.from_json({**d, "colour": 1})


def test_default_form_by_cpu_and_width_and_the_winograd_form_on_the_shipped_model(monkeypatch):
    """Loaded models pick their form by the CPU (float32 without bfloat16 dot units) and the
    width (Winograd from 32); on the shipped width-16 model the Winograd form (two layers
    qualify) stays within the bfloat16 forms' error of the exact float32 form, and differs from
    the im2col form (so it is really in use)."""
    monkeypatch.setenv(hostcpu.BF16_ENV, "0")
    assert enhancer.load_enhancer().model.conv_impl == "im2col_f32"
    no_bf16 = enhancer.load_enhancer().config
    wide = dataclasses.replace(no_bf16, unet=dataclasses.replace(no_bf16.unet, width=32))
    assert wide.model().conv_impl == "winograd_f32"
    monkeypatch.setenv(hostcpu.BF16_ENV, "1")
    enh = enhancer.load_enhancer()
    assert enh.config.unet.width == 16 and enh.model.conv_impl == "im2col_bf16"
    assert wide.model().conv_impl == "winograd_bf16" and wide.model("xla").conv_impl == "xla"
    assert wide.model("auto").conv_impl == "im2col_bf16"  # "auto" is the host's im2col form
    y, x = np.mgrid[0:128, 0:128] / 128.0
    n = np.stack([0.3 * np.sin(40 * x + 3 * y), 0.2 * np.cos(25 * y), np.ones_like(x)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    rgb = jnp.asarray(np.stack([(n + 1) / 2, (n[:, ::-1] + 1) / 2]), jnp.float32)
    m = jnp.array([0, 3])
    outs = {impl: np.asarray(jax.jit(enh.config.model(impl).apply)({"params": enh.params}, rgb,
                                                                   m))
            for impl in ("winograd_bf16", "im2col_bf16", "im2col_f32", "winograd_f32")}
    exact = outs["im2col_f32"]
    for impl in ("winograd_bf16", "im2col_bf16"):
        assert np.sqrt(np.mean((outs[impl] - exact) ** 2) / np.mean(exact**2)) < 1e-3
    assert np.any(outs["winograd_bf16"] != outs["im2col_bf16"])
    # float32 Winograd: its transforms' rounding only, and really in use
    wino = outs["winograd_f32"]
    assert np.sqrt(np.mean((wino - exact) ** 2) / np.mean(exact**2)) < 1e-5
    assert np.any(wino != exact)
