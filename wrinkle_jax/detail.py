"""The detail representation of a normal map: each map's own large scale rotated to +z.

A coarse and a fine simulation of the same frame disagree at large scale (median 12 degrees at
>= 30 mm on the held-out garments, more than the wrinkle detail itself), so a patch score or a
style loss on object-space normals mostly measures that divergence. The detail representation
removes it: the large-scale normal field of a map is its masked, first-order Gaussian low-pass

    L = normalize(masked_blur(n, mask, sigma, order=1))        (sharpen.masked_blur)

and each texel's normal is rotated by the rotation R(L) that takes L to +z:

    d = R(L) n           (to_detail)        n = R(L)^T d       (from_detail)

so a flat (or smoothly curved) panel becomes d = +z everywhere whatever its orientation, and
only detail finer than about sigma (wrinkles, folds, facets) remains. `R` is the minimal
rotation to +z, which is smooth except at L = -z; each patch therefore picks a *branch*: +1
uses R_+(L) (pole at -z), -1 uses R_+(S L) S with S = diag(1, -1, -1) (the 180 degree turn
about x; pole at +z). `branch_of` picks, per patch, the branch whose pole is furthest from the
patch's mean large-scale normal. Maps compared with each other (input, output and target of
one patch) must share a branch, so that their tangent frames twist alike; the branch is
chosen from one reference map (the input) and passed to the others.

Everything is jittable and differentiable (the branch is a float sign, selected with `where`).
Shapes: n, d (N, H, W, 3) unit vectors in [-1, 1]; mask (N, H, W, 1) in {0, 1}; L (N, H, W, 3);
branch (N,) float32 in {-1, +1}. Texels outside the mask are returned as 0.

Example:
    >>> import numpy as np
    >>> n = np.zeros((1, 32, 32, 3), np.float32); n[..., 0] = 1.0   # a panel facing +x
    >>> mask = np.ones((1, 32, 32, 1), np.float32)
    >>> d = to_detail_rgb((n + 1) / 2, mask, sigma=4.0)               # RGB form
    >>> bool(np.allclose(np.asarray(d)[..., 2], 1.0, atol=1e-5))      # now faces +z
    True
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from wrinkle_jax import sharpen

__all__ = ["BAND_SIGMAS", "DEFAULT_SIGMA", "band_rms", "band_rms_pair", "branch_of",
           "decompose", "from_detail", "from_detail_rgb", "large_scale",
           "on_reference_branch_rgb", "to_detail", "to_detail_rgb", "transplant_rgb"]

# Low-pass radius in texels (2 mm texels: 16 mm): the wrinkle band (16-64 mm) stays in the
# detail, the coarse/fine large-scale divergence (>= 30 mm) leaves it. Chosen by measurement
# (experiments/results/fidelity/).
DEFAULT_SIGMA = 8.0

# Band edges of the detail spectrum (2 mm texels): wavelengths below 16 mm (fine creases and
# facet ripples) and 16-64 mm (the wrinkle band). A Gaussian of radius s texels halves the
# power at wavelength pi s / sqrt(ln(2) / 2) ~ 5.3 s texels, hence radii 1.5 and 6.
BAND_SIGMAS = {"lt16mm": (0.0, 1.5), "16_64mm": (1.5, 6.0)}

# Band-passes are unreliable near the mask's border: only texels this far inside count.
_BAND_INSET = 6

# 1 + cos(angle to the pole) below which the rotation is regularized (within ~2.6 degrees of
# the pole; `branch_of` keeps real patches far from it).
_POLE_GUARD = 1e-3


@functools.partial(jax.jit, static_argnames=("sigma",))
def large_scale(n, mask, sigma: float = DEFAULT_SIGMA, weights=None):
    """(N, H, W, 3) normals -> (N, H, W, 3) unit large-scale normals (0 outside the mask);
    `weights`: optional ``sharpen.blur_weights(mask, sigma, 1)``, computed once per mask."""
    low = sharpen.masked_blur(n, mask, sigma, order=1, weights=weights)
    norm = jnp.sqrt(jnp.sum(low * low, axis=-1, keepdims=True) + 1e-12)
    return low / norm * (mask > 0)


def branch_of(large, mask):
    """(N,) float32: +1 where the patch's mean large-scale normal has z >= 0, else -1."""
    m = (mask > 0).astype(jnp.float32)
    mean_z = jnp.sum(large[..., 2:3] * m, axis=(1, 2, 3))
    return jnp.where(mean_z >= 0, 1.0, -1.0).astype(jnp.float32)


def _flip(v, branch):
    """S v with S = diag(1, s, s), s = branch (per patch)."""
    s = branch.reshape((-1, 1, 1, 1))
    return jnp.concatenate([v[..., :1], v[..., 1:] * s], axis=-1)


def _rotate_to_z(a, v, transpose: bool = False):
    """R(a) v (or R(a)^T v): R the minimal rotation taking unit a to +z (pole at a = -z).

    R = [[1 - k ax^2, -k ax ay, -ax], [-k ax ay, 1 - k ay^2, -ay], [ax, ay, az]],
    k = 1 / (1 + az).
    """
    ax, ay, az = a[..., 0:1], a[..., 1:2], a[..., 2:3]
    k = 1.0 / jnp.maximum(1.0 + az, _POLE_GUARD)
    vx, vy, vz = v[..., 0:1], v[..., 1:2], v[..., 2:3]
    if not transpose:
        x = (1 - k * ax * ax) * vx - k * ax * ay * vy - ax * vz
        y = -k * ax * ay * vx + (1 - k * ay * ay) * vy - ay * vz
        z = ax * vx + ay * vy + az * vz
    else:
        x = (1 - k * ax * ax) * vx - k * ax * ay * vy + ax * vz
        y = -k * ax * ay * vx + (1 - k * ay * ay) * vy + ay * vz
        z = -ax * vx - ay * vy + az * vz
    return jnp.concatenate([x, y, z], axis=-1)


def to_detail(n, large, branch):
    """Object-space normals -> detail normals: R_b(L) n (see the module docstring)."""
    return _rotate_to_z(_flip(large, branch), _flip(n, branch))


def from_detail(d, large, branch):
    """Detail normals -> object-space normals: R_b(L)^T d, the inverse of `to_detail`."""
    return _flip(_rotate_to_z(_flip(large, branch), d, transpose=True), branch)


@functools.partial(jax.jit, static_argnames=("sigma",))
def decompose(n, mask, sigma: float = DEFAULT_SIGMA, branch=None, weights=None):
    """Split normals into (detail d, large scale L, branch); `branch` None picks it from L;
    `weights`: as `large_scale`'s."""
    large = large_scale(n, mask, sigma, weights)
    branch = branch_of(large, mask) if branch is None else jnp.asarray(branch, jnp.float32)
    return to_detail(n, large, branch) * (mask > 0), large, branch


def _unit_rgb(n, mask):
    norm = jnp.sqrt(jnp.sum(n * n, axis=-1, keepdims=True) + 1e-12)
    return ((n / norm + 1.0) * 0.5) * (mask > 0)


@functools.partial(jax.jit, static_argnames=("sigma",))
def to_detail_rgb(x, mask, sigma: float = DEFAULT_SIGMA, branch=None):
    """RGB-form patches (N, H, W, 3) in [0, 1] -> RGB form of their detail maps.

    Args:
      x: RGB form ((n + 1) / 2) of normal-map patches, 0 outside the mask.
      mask: (N, H, W, 1) garment mask.
      sigma: low-pass radius in texels.
      branch: (N,) branches to use (e.g. those of the input when `x` is an output or a
        target); None picks each patch's own (`branch_of`).
    Returns:
      (N, H, W, 3) RGB form of unit detail normals inside the mask, 0 outside (float32, or
      float64 for float64 input).
    """
    x = jnp.asarray(x, jnp.result_type(x, jnp.float32))  # float64 stays float64 (gradchecks)
    mask = jnp.asarray(mask, x.dtype)
    d, _, _ = decompose(x * 2.0 - 1.0, mask, sigma, branch)
    return _unit_rgb(d, mask)


def on_reference_branch_rgb(reference, others, mask, sigma: float = DEFAULT_SIGMA):
    """Detail maps (RGB form) of `reference` and of each of `others`, all on the reference's
    branch (e.g. input, output and target of one patch, branch from the input), each with its
    own large scale removed; the reference is decomposed once.

    Returns:
      (reference detail, *others' details), each (N, H, W, 3) RGB form, 0 outside the mask.
    """
    x = jnp.asarray(reference, jnp.result_type(reference, jnp.float32))
    mask = jnp.asarray(mask, x.dtype)
    d, _, branch = decompose(x * 2.0 - 1.0, mask, sigma)
    return (_unit_rgb(d, mask), *(to_detail_rgb(o, mask, sigma, branch) for o in others))


def from_detail_rgb(d_rgb, large, branch, mask):
    """RGB-form detail patches -> RGB-form object-space patches on the large scale `large`.

    Args:
      d_rgb: (N, H, W, 3) RGB form of detail normals (need not be unit: renormalized).
      large, branch: from `decompose` of the map whose large scale is kept.
      mask: (N, H, W, 1).
    """
    d = jnp.asarray(d_rgb, jnp.result_type(d_rgb, jnp.float32)) * 2.0 - 1.0
    return _unit_rgb(from_detail(d, large, branch), mask)


@functools.partial(jax.jit, static_argnames=("sigma",))
def transplant_rgb(x, donor, mask, donor_mask, sigma: float = DEFAULT_SIGMA):
    """`x`'s large scale carrying `donor`'s detail (RGB forms): what a map would look like with
    another map's wrinkles, e.g. the fine target's own detail on the coarse input (the
    aligned ceiling) or another patch's (texture statistics without alignment).

    Args:
      x, donor: (N, H, W, 3) RGB-form patches; mask, donor_mask: (N, H, W, 1) their masks.
      sigma: low-pass radius in texels.
    Returns:
      (N, H, W, 3) RGB form inside `mask`, 0 outside; where the donor has no garment its
      detail is flat (+z), so only `x`'s large scale shows.
    """
    x = jnp.asarray(x, jnp.result_type(x, jnp.float32))
    mask = jnp.asarray(mask, x.dtype)
    _, large, branch = decompose(x * 2.0 - 1.0, mask, sigma)
    d = to_detail_rgb(donor, donor_mask, sigma)
    flat = jnp.asarray([0.5, 0.5, 1.0], x.dtype)
    d = jnp.where(jnp.asarray(donor_mask) > 0, d, flat)
    return from_detail_rgb(d, large, branch, mask)


def band_rms(detail_rgb, mask, bands=BAND_SIGMAS, eps: float = 0.0):
    """Per-patch RMS of the tangential detail (x, y of the detail normals) in each band.

    The jittable, differentiable form of `evaluation.bands.band_rms` (its NumPy/OpenCV
    reference; same masked Gaussians, same border inset), for losses.

    Args:
      detail_rgb: (N, H, W, 3) RGB-form detail maps; mask: (N, H, W, 1) in {0, 1}.
      bands: name -> (inner, outer) Gaussian radii in texels; the band is
        G_inner(d) - G_outer(d) (masked normalized convolution; inner 0 = d itself).
      eps: added to the mean square before the root (> 0 keeps the gradient finite for a
        patch with no energy in a band).
    Returns:
      name -> (N,) RMS over texels at least 6 texels inside the mask (0 if there are none).
    """
    x = jnp.asarray(detail_rgb)[..., :2] * 2.0 - 1.0
    m = jnp.asarray(mask, x.dtype)
    # Erosion by a (2 inset + 1)^2 square; outside the image counts as inside (as OpenCV's
    # default border for erode).
    w = 2 * _BAND_INSET + 1
    inner = jax.lax.reduce_window(m, jnp.inf, jax.lax.min, (1, w, w, 1), (1, 1, 1, 1),
                                  "SAME") > 0
    count = jnp.sum(inner, axis=(1, 2, 3))
    radii = sorted({r for pair in bands.values() for r in pair if r > 0})
    blurred = {0.0: x, **{r: sharpen.masked_blur(x, m, r, order=0) for r in radii}}
    out = {}
    for name, (a, b) in bands.items():
        sq = jnp.sum(jnp.square(blurred[a] - blurred[b]), axis=-1, keepdims=True)
        ms = jnp.sum(sq * inner, axis=(1, 2, 3)) / jnp.maximum(count, 1)
        out[name] = jnp.sqrt(ms + eps) * (count > 0)
    return out


def band_rms_pair(a, b, mask, bands=BAND_SIGMAS, eps: float = 0.0):
    """`band_rms` of two detail maps on one mask (e.g. an output and its target) in one call:
    name -> ((N,) RMS of `a`, (N,) RMS of `b`)."""
    n = a.shape[0]
    both = band_rms(jnp.concatenate([a, b]), jnp.concatenate([mask, mask]), bands, eps)
    return {k: (v[:n], v[n:]) for k, v in both.items()}
