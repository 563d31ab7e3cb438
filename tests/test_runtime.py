"""wrinkle_jax.runtime: process settings made before JAX starts."""

import platform
import subprocess
import sys

import pytest

from wrinkle_jax import runtime


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_retain_freed_memory_takes_effect_before_jax_is_imported():
    # in a fresh process: the setting is process-wide, and it must not import JAX itself
    code = ("import sys; from wrinkle_jax.runtime import retain_freed_memory; "
            "print(retain_freed_memory(), 'jax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["True", "False"]


def test_retain_freed_memory_without_glibc_is_false(monkeypatch):
    def no_libc(name):
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(runtime.ctypes, "CDLL", no_libc)
    assert runtime.retain_freed_memory() is False
