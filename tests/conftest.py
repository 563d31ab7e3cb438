"""Shared test fixtures: analytic garments and a float64 context for gradient checks."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from wrinkle_jax import data, primitives
from wrinkle_jax.meshio import make_sequence, save_sequence


def x64():
    """Context manager enabling float64 (for finite-difference gradient checks)."""
    if hasattr(jax, "enable_x64"):
        return jax.enable_x64(True)
    from jax.experimental import enable_x64  # older JAX

    return enable_x64()


@pytest.fixture
def enable_x64():
    with x64():
        yield


@pytest.fixture(scope="session")
def sheet():
    return primitives.grid_sheet(12, 10, size=(0.6, 0.5))


@pytest.fixture(scope="session")
def cube():
    return primitives.uv_cube(size=0.4, n=6)


@pytest.fixture(scope="session")
def skirt():
    return primitives.flared_skirt(n_theta=32, n_s=8)



@pytest.fixture(scope="session")
def tiny_patch_root(tmp_path_factory):
    """A tiny patch dataset (32x32 patches, 4 mm texels): a "sheet" and a "cape" sequence of 4
    frames of a travelling fold with fine ripples, silk_chiffon; both splits non-empty."""
    src = tmp_path_factory.mktemp("seq")
    g = primitives.grid_sheet(40, 40, size=(0.25, 0.25))
    xy = g.vertices[:, :2]
    paths = []
    for name, garment in (("sheet", "sheet"), ("cape", "cape")):
        frames = [np.c_[xy, 0.015 * np.sin(15 * xy[:, 1] + t)
                        + 0.002 * np.sin(120 * xy[:, 0] + t)] for t in range(4)]
        seq = make_sequence(np.asarray(frames, np.float32), g,
                            metadata={"material": "silk_chiffon", "garment": garment})
        save_sequence(src / f"{name}.npz", seq)
        paths.append(src / f"{name}.npz")
    root = tmp_path_factory.mktemp("patches")
    cfg = data.PatchDataConfig(texel_size=0.004, patch_size=32, crops_per_frame=2,
                               min_coverage=0.5, shard_size=8)
    data.build_dataset(paths, root, cfg)
    return root
