"""wrinkle_jax.runtime: process settings made before JAX starts."""

import os
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


def test_use_retained_memory_follows_the_environment(monkeypatch):
    calls = []
    monkeypatch.setattr(runtime, "retain_freed_memory", lambda: calls.append(1) or True)
    assert runtime.use_retained_memory({runtime.MALLOC_ENV: "default"}) is False
    assert calls == []  # opted out: glibc's policy untouched
    assert runtime.use_retained_memory({}) is True
    assert runtime.use_retained_memory({runtime.MALLOC_ENV: "retain"}) is True
    assert calls == [1, 1]


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_only_the_wrinkle_jax_process_retains_freed_memory():
    # main() without arguments is the command's own process: it makes the setting, before JAX
    # starts; main(argv) is a caller's (a notebook, a test) and leaves that process alone.
    code = ("import sys\n"
            "from wrinkle_jax import cli, runtime\n"
            "made = []\n"
            "runtime.retain_freed_memory = lambda: made.append(1) or True\n"
            "sys.argv = ['wrinkle-jax', '--version']\n"
            "for argv in (['--version'], None):\n"
            "    try:\n"
            "        cli.main(argv)\n"
            "    except SystemExit:\n"
            "        pass\n"
            "    print('made', len(made), 'jax' in sys.modules)\n")
    env = {k: v for k, v in os.environ.items() if k != runtime.MALLOC_ENV}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env=env).stdout.splitlines()
    assert [line for line in out if line.startswith("made")] == ["made 0 False",
                                                                 "made 1 False"]
