"""What the host CPU offers that decides which convolution form is fast: bfloat16 dot units.

Why: the U-Net's and VGG's fast forms (`nn.fastconv`) round the dot operands to bfloat16
because XLA:CPU runs a bfloat16 dot with float32 accumulation on AVX512-BF16 (or AMX) units at
several times the float32 rate. A CPU without those units has XLA emulate the bfloat16 dot, and
the same form is then slower than float32. Measured on an AVX2-only AMD EPYC (session 46, 2
cores, the shipped width-16 model, batch 32 of 128 x 128 patches, 3 alternating rounds):
forward 14.0-14.5 ms/patch in "im2col_bf16" against 9.9-11.6 in "im2col_f32" (XLA's own
convolutions 12.0-13.1). At width 64 (`benchmarks/bench_reference.py`, beside the authors'
PyTorch network, 3 alternating rounds): inference 30.6 ms/patch in "winograd_f32", 45.3 in
"winograd_bf16", 56.9 in "im2col_f32", 80.2 in "im2col_bf16" (theirs 59.6); their training
step (batch 32) 14.2 s in "winograd_f32" against 30.8 s in "im2col_f32" (theirs 34.4 s). So
the fast form is chosen per host and width (`fast_conv_impl`; "auto" in configs).

Only the standard library: nothing here starts JAX.

Example:
  >>> isinstance(native_bf16_dots(), bool)
  True
"""

from __future__ import annotations

import functools
import os
import platform

__all__ = ["AUTO", "BF16_ENV", "BF16_FLAGS", "WINOGRAD_MIN_WIDTH", "cpu_flags", "cpu_model",
           "describe", "fast_conv_impl", "native_bf16_dots", "resolve_conv_impl"]

# x86 CPU flags (Linux /proc/cpuinfo names) of units that run bfloat16 dots natively.
BF16_FLAGS = ("avx512_bf16", "amx_bf16")
# "1" or "0" overrides the detection (e.g. to time both forms on one machine).
BF16_ENV = "WRINKLE_JAX_BF16"
# The convolution-form name that means "the fast form of this host" (`resolve_conv_impl`).
AUTO = "auto"
# U-Nets at least this wide run Winograd forms where those are chosen for speed (narrower ones
# have too few layers with enough channels: `nn.winograd.use_winograd`).
WINOGRAD_MIN_WIDTH = 32
# Flags worth recording beside a timing: they decide which code XLA:CPU can emit.
_RECORDED = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_tile")


def _cpuinfo_fields(text: str) -> dict[str, str]:
    """The first processor block of /proc/cpuinfo's text as {field: value}."""
    out: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            if out:
                break
            continue
        key, _, value = line.partition(":")
        out.setdefault(key.strip(), value.strip())
    return out


@functools.lru_cache(maxsize=1)
def _cpuinfo() -> dict[str, str]:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            return _cpuinfo_fields(f.read())
    except OSError:  # not Linux
        return {}


def cpu_flags(cpuinfo: dict[str, str] | None = None) -> frozenset[str]:
    """The CPU's feature flags ("flags" on x86 Linux, "Features" on ARM Linux); empty where
    /proc/cpuinfo does not exist. `cpuinfo`: fields as `_cpuinfo_fields` reads them (tests)."""
    info = _cpuinfo() if cpuinfo is None else cpuinfo
    return frozenset((info.get("flags") or info.get("Features") or "").split())


def cpu_model(cpuinfo: dict[str, str] | None = None) -> str | None:
    """The CPU's model name, or None where it cannot be read."""
    info = _cpuinfo() if cpuinfo is None else cpuinfo
    return info.get("model name") or platform.processor() or None


def native_bf16_dots(environ=None, cpuinfo: dict[str, str] | None = None) -> bool:
    """True when the CPU runs bfloat16 dots natively (an x86 flag of `BF16_FLAGS`), or when
    `environ` (default `os.environ`) sets WRINKLE_JAX_BF16=1; WRINKLE_JAX_BF16=0 says False.
    Unknown CPUs (no flags readable, other architectures) say False: the float32 forms are
    exact to float32 rounding and never the emulated slow path."""
    environ = os.environ if environ is None else environ
    forced = environ.get(BF16_ENV, "").strip()
    if forced in ("0", "1"):
        return forced == "1"
    return any(f in cpu_flags(cpuinfo) for f in BF16_FLAGS)


def fast_conv_impl(width: int | None = None, environ=None) -> str:
    """The fast convolution form of this host (`nn.unet`, `nn.vgg`) for a U-Net of `width`
    (None: unknown). Where `native_bf16_dots`: "im2col_bf16" (the Winograd bfloat16 form adds
    error; `enhancer.inference_conv_impl` opts into it for loaded models). Elsewhere the float32
    forms, exact and faster there (see the module docstring): "winograd_f32" from
    `WINOGRAD_MIN_WIDTH`, else "im2col_f32"."""
    if native_bf16_dots(environ):
        return "im2col_bf16"
    wide = width is not None and width >= WINOGRAD_MIN_WIDTH
    return "winograd_f32" if wide else "im2col_f32"


def resolve_conv_impl(name: str, width: int | None = None, environ=None) -> str:
    """`name`, or `fast_conv_impl(width)` for `AUTO`: configs say "auto" so that they stay
    portable between hosts, and the module built from them runs a concrete form."""
    return fast_conv_impl(width, environ) if name == AUTO else name


def describe() -> dict:
    """JSON-ready: the CPU model, the recorded flags it has, `native_bf16_dots` and the fast
    forms at widths 16 and 64."""
    flags = cpu_flags()
    return {"cpu_model": cpu_model(), "cpu_flags": [f for f in _RECORDED if f in flags],
            "native_bf16_dots": native_bf16_dots(),
            "fast_conv_impl": {f"width_{w}": fast_conv_impl(w) for w in (16, 64)}}
