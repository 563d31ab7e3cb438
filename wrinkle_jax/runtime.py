"""Process settings that must be made before JAX starts (import this before `jax`: it
imports nothing but the standard library)."""

from __future__ import annotations

import ctypes


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
