"""Shared test fixtures: analytic garments and a float64 context for gradient checks."""

from __future__ import annotations

import jax
import pytest

from wrinkle_jax import primitives


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

