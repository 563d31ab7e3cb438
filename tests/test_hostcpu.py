import json

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import hostcpu
from wrinkle_jax.nn import unet, vgg

# Abbreviated /proc/cpuinfo of two processors each (fields as the kernel prints them).
SAPPHIRE = """processor\t: 0
vendor_id\t: GenuineIntel
model name\t: Intel(R) Xeon(R) Platinum 8481C CPU @ 2.70GHz
flags\t\t: fpu sse2 avx avx2 fma avx512f avx512_vnni avx512_bf16 amx_bf16 amx_tile

processor\t: 1
model name\t: something else
flags\t\t: fpu
"""
MILAN = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC
flags\t\t: fpu sse2 avx fma avx2 sha_ni

processor\t: 1
model name\t: AMD EPYC
flags\t\t: fpu sse2 avx fma avx2 sha_ni
"""
GRAVITON = """processor\t: 0
BogoMIPS\t: 243.75
Features\t: fp asimd evtstrm aes sve bf16 i8mm
CPU implementer\t: 0x41
"""


def test_flags_and_model_are_read_from_the_first_processor():
    info = hostcpu._cpuinfo_fields(SAPPHIRE)
    assert hostcpu.cpu_model(info).startswith("Intel(R) Xeon(R) Platinum 8481C")
    assert {"avx512_bf16", "amx_bf16", "avx2"} <= hostcpu.cpu_flags(info)
    assert "something" not in hostcpu.cpu_model(info)
    assert hostcpu.cpu_flags(hostcpu._cpuinfo_fields(GRAVITON)) >= {"bf16", "sve"}
    assert hostcpu.cpu_flags({}) == frozenset()


def test_bf16_dots_only_on_x86_bf16_units_unless_forced():
    env = {}
    assert hostcpu.native_bf16_dots(env, hostcpu._cpuinfo_fields(SAPPHIRE))
    assert not hostcpu.native_bf16_dots(env, hostcpu._cpuinfo_fields(MILAN))
    # ARM's "bf16" feature is not an XLA:CPU fast path we measured: float32 there
    assert not hostcpu.native_bf16_dots(env, hostcpu._cpuinfo_fields(GRAVITON))
    assert not hostcpu.native_bf16_dots(env, {})  # unknown CPU: the exact form
    avx512_only = {"flags": "avx2 avx512f avx512_vnni"}
    assert not hostcpu.native_bf16_dots(env, avx512_only)
    assert hostcpu.native_bf16_dots({hostcpu.BF16_ENV: "1"}, hostcpu._cpuinfo_fields(MILAN))
    assert not hostcpu.native_bf16_dots({hostcpu.BF16_ENV: "0"},
                                        hostcpu._cpuinfo_fields(SAPPHIRE))


def test_auto_resolves_to_the_hosts_fast_form_and_leaves_forms_alone():
    assert hostcpu.fast_conv_impl(environ={hostcpu.BF16_ENV: "1"}) == "im2col_bf16"
    assert hostcpu.fast_conv_impl(environ={hostcpu.BF16_ENV: "0"}) == "im2col_f32"
    assert hostcpu.resolve_conv_impl("auto", environ={hostcpu.BF16_ENV: "0"}) == "im2col_f32"
    for impl in unet.CONV_IMPLS:
        assert hostcpu.resolve_conv_impl(impl, 64, {hostcpu.BF16_ENV: "0"}) == impl
    assert set(unet.CONV_IMPLS) == set(vgg.CONV_IMPLS)  # a config's form serves both
    # by width: Winograd from 32 in float32; bfloat16 hosts keep the im2col form
    no, yes = {hostcpu.BF16_ENV: "0"}, {hostcpu.BF16_ENV: "1"}
    assert [hostcpu.fast_conv_impl(w, no) for w in (None, 16, 31, 32, 64)] == (
        ["im2col_f32"] * 3 + ["winograd_f32"] * 2)
    assert {hostcpu.fast_conv_impl(w, yes) for w in (None, 16, 64)} == {"im2col_bf16"}
    assert hostcpu.resolve_conv_impl("auto", 64, no) == "winograd_f32"
    assert unet.UNetConfig(width=64).module(5, "auto").conv_impl == hostcpu.fast_conv_impl(64)


def test_describe_is_json_and_agrees_with_the_detection():
    d = json.loads(json.dumps(hostcpu.describe()))
    assert d["native_bf16_dots"] == hostcpu.native_bf16_dots()
    assert d["fast_conv_impl"] == {"width_16": hostcpu.fast_conv_impl(16),
                                   "width_64": hostcpu.fast_conv_impl(64)}
    assert set(d["cpu_flags"]) <= set(hostcpu.cpu_flags())


def test_vgg_float32_im2col_matches_xla_and_auto_runs(monkeypatch):
    """VGG's float32 im2col form is the XLA convolution to float32 rounding; "auto" runs it
    where the host has no bfloat16 dots."""
    params = vgg.init_vgg19(jax.random.PRNGKey(0), num_convs=3)
    x = jax.random.uniform(jax.random.PRNGKey(1), (2, 32, 32, 3))
    f = jax.jit(vgg.features, static_argnames=("layers", "conv_impl"))
    ref = f(params, x, layers=("relu2_1",), conv_impl="xla")["relu2_1"]
    got = f(params, x, layers=("relu2_1",), conv_impl="im2col_f32")["relu2_1"]
    scale = float(jnp.sqrt(jnp.mean(ref**2)))
    assert scale > 0 and float(jnp.max(jnp.abs(got - ref))) < 1e-5 * max(scale, 1.0)
    monkeypatch.setenv(hostcpu.BF16_ENV, "0")
    auto = f(params, x, layers=("relu2_1",), conv_impl="auto")["relu2_1"]
    np.testing.assert_array_equal(np.asarray(auto), np.asarray(got))
    wino = f(params, x, layers=("relu2_1",), conv_impl="winograd_f32")["relu2_1"]
    assert float(jnp.max(jnp.abs(wino - ref))) < 1e-4 * max(scale, 1.0)
    bf16 = f(params, x, layers=("relu2_1",), conv_impl="im2col_bf16")["relu2_1"]
    assert float(jnp.max(jnp.abs(bf16 - ref))) > 10 * float(jnp.max(jnp.abs(got - ref)))
