"""Process settings that must be made before JAX starts (import this before `jax`: it
imports nothing but the standard library)."""

from __future__ import annotations

import ctypes
import os

# The environment variable that opts a process out of `use_retained_memory`.
MALLOC_ENV = "WRINKLE_JAX_MALLOC"


def retain_freed_memory() -> bool:
    """glibc `mallopt`: one arena, no mmap'd blocks, no trimming, so freed memory stays in the
    heap and XLA's per-call temporaries do not page-fault again. Call it before JAX (or torch)
    starts; True when glibc took all three settings (False without glibc)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_max, m_arena_max = -1, -4, -8
    return bool(libc.mallopt(m_arena_max, 1) and libc.mallopt(m_mmap_max, 0)
                and libc.mallopt(m_trim_threshold, 2**31 - 1))


def use_retained_memory(environ=None) -> bool:
    """`retain_freed_memory` unless `environ` (default `os.environ`) sets WRINKLE_JAX_MALLOC to
    "default" (glibc's own policy). The `wrinkle-jax` process, and the scripts that time what it
    runs, call it at start: without it, XLA's per-call temporaries above glibc's mmap threshold
    (128 kB, raised as blocks are freed, to 32 MB at most) are mapped afresh, and page-faulted,
    on every call -- measured in `make demo` (3 alternating pairs): bake 8-11 -> 6-7, tile 2 -> 1,
    merge 18-20 -> 13 ms/frame; a (131072, 27) @ (27, 64) float32 dot 13.6 -> 2.4 ms. Freed
    memory then stays with the process until it exits. True when the setting was made."""
    environ = os.environ if environ is None else environ
    if environ.get(MALLOC_ENV, "retain") == "default":
        return False
    return retain_freed_memory()
