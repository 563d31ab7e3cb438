"""Guarded numerics: norms, divisions and normalizations that stay finite (and have finite
gradients) at zero, plus the project's tolerances in one place.

Every function here is jittable and differentiable. The trick used throughout: where the
denominator could be zero, replace it by a safe value *before* dividing (the "double where"
pattern), so neither the value nor the gradient produces NaN.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# Smallest squared length treated as non-zero (meters^2 for geometry, unitless for normals).
EPS_SQ = 1e-24
# Smallest denominator treated as non-zero in divisions.
EPS_DIV = 1e-12
# Barycentric tolerance when deciding whether a texel center lies inside a UV triangle.
BARY_EPS = 1e-7
# Degenerate-triangle threshold on twice the signed UV area, in squared pixels.
UV_AREA_EPS = 1e-12


def to_device(tree, dtype=None):
    """NumPy arrays (or a pytree of them) as device arrays, compiling nothing.

    The same arrays and dtypes as `jnp.asarray` (float64 -> float32 and int64 -> int32 unless
    jax_enable_x64), but `jnp.asarray` of a NumPy array dispatches a one-op XLA program (jax
    0.10: `stage`, or `convert_element_type` with a dtype) that compiles, 20-40 ms on a 2-core
    machine, once per shape and dtype; `jax.device_put` only copies. Set-up code (plans,
    index tables, model weights) converts with this. `dtype`: cast on the host first (JAX
    values, e.g. tracers, are cast with `jnp.asarray`).
    """
    if dtype is not None:
        tree = jax.tree.map(lambda a: jnp.asarray(a, dtype) if isinstance(a, jax.Array)
                            else np.asarray(a, dtype), tree)
    return jax.device_put(tree)


def safe_norm(x, axis=-1, keepdims=False, eps_sq=EPS_SQ):
    """Euclidean norm with a zero (not NaN) gradient at x = 0.

    Args:
      x: array (..., D).
      axis: reduction axis.
    Returns:
      (...) or (..., 1) norms; exactly 0 where |x|^2 <= eps_sq.
    """
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    ok = sq > eps_sq
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def normalize(x, axis=-1, eps_sq=EPS_SQ):
    """Unit vectors along `axis`; zero vectors stay zero with finite gradients.

    Args:
      x: array (..., D).
    Returns:
      (..., D) array of unit (or zero) vectors.
    """
    sq = jnp.sum(x * x, axis=axis, keepdims=True)
    ok = sq > eps_sq
    inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)
    return x * inv


def dot3(a, b):
    """sum_c a[..., c] * b[..., c] over a last axis of size 3, as multiply-adds.

    Why not `jnp.sum(a * b, -1)`: XLA:CPU fuses a short-axis reduction with its producers
    into a library (YNNPACK) fusion that runs several times slower than these elementwise ops
    (session 43: the capsule body query at 20k points x 14 capsules took 18.2 -> 11.0 ms with
    these forms alone). Kept separate from `safe_norm` / `normalize` so the simulator's
    arithmetic does not change with it."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def matvec3(blocks, v):
    """blocks (N, 3, 3) applied to v (N, 3) -> (N, 3), as multiply-adds: XLA:CPU runs the
    einsum `nab,nb->na` as one tiny dot per row (plus operand transposes), several times
    slower (session 43, the lift's Gauss-Newton products)."""
    return (blocks[:, :, 0] * v[:, 0:1] + blocks[:, :, 1] * v[:, 1:2]
            + blocks[:, :, 2] * v[:, 2:3])


def norm3(x, eps_sq=EPS_SQ):
    """`safe_norm` over a last axis of size 3 (no keepdims), summed by `dot3`."""
    sq = dot3(x, x)
    ok = sq > eps_sq
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def normalize3(x, eps_sq=EPS_SQ):
    """`normalize` over a last axis of size 3, summed by `dot3`."""
    sq = dot3(x, x)[..., None]
    ok = sq > eps_sq
    return x * jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def safe_div(num, den, eps=EPS_DIV, fill=0.0):
    """num / den where |den| > eps, else `fill`; gradients stay finite everywhere."""
    ok = jnp.abs(den) > eps
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fill)


def positive_div(num, den):
    """num / den where den > 0, else 0: a scale-free guard (no absolute threshold).

    For quantities that are legitimately tiny but positive (CG step sizes of energies divided
    by the vertex count, squared lengths of small triangles), where `safe_div`'s absolute
    threshold would silently zero them. Gradients stay finite.
    """
    ok = den > 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)
