"""Scoring enhanced patches against ground truth, and the non-learned baselines.

All functions take patches in the RGB form of normal maps ((n + 1) / 2, in [0, 1]) with a UV
mask, as stored by `wrinkle_jax.data`:

    inp, out, target: (N, H, W, 3) float32;  mask: (N, H, W, 1) float32 in {0, 1}.

`score_patches` is the paper's improvement score (Sec. 6) on a FIXED set of VGG layers
(`EVAL_LAYERS`, independent of the layers a model was trained with, so that models trained with
different losses are compared on one yardstick), plus its signed form (negative when the output
is further from the target's style than the input is). With `detail_sigma` set, the same score
is taken on the detail representation (`wrinkle_jax.detail`: each map's own large scale rotated
to +z, the branch chosen from the input), the project's primary, detail-only score: it ignores
where coarse and fine simulations diverge at large scale. `paired_difference` gives the robust
summary the reports lead with (median of paired differences with a bootstrap interval).
Baselines (`identity`, `unsharp_mask`, `resample`) are NumPy/OpenCV, masked (background never
bleeds into the garment) and return unit normals inside the mask.
"""

from __future__ import annotations

import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import detail, metrics
from wrinkle_jax.nn import losses, vgg

__all__ = ["BAND_SIGMAS", "EVAL_LAYERS", "band_rms", "bootstrap_ci", "checker_rms",
           "detail_triplet", "identity", "paired_difference", "resample", "score_patches",
           "scores_from_losses", "summarize", "unsharp_mask"]

EVAL_LAYERS = vgg.DEFAULT_LAYERS  # relu1_2, relu2_1, relu3_1, relu4_1, relu5_1 (Gatys)


def _normals(rgb):
    return np.asarray(rgb, np.float64) * 2.0 - 1.0


def _to_rgb_masked(n, mask):
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    unit = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), 0.0)
    return (((unit + 1.0) * 0.5) * mask).astype(np.float32)


def identity(inp, mask):
    """The input unchanged (improvement score 0 by definition)."""
    return np.asarray(inp, np.float32) * np.asarray(mask, np.float32)


def _masked_blur(n, m, sigma, order: int = 1):
    """Masked Gaussian blur of (H, W, 3) normals with (H, W) weights (OpenCV, float64).

    order 0: normalized convolution (local mean); order 1: the centre value of the weighted
    local least-squares plane (`wrinkle_jax.sharpen.masked_blur` documents why).
    """
    k = int(2 * np.ceil(3 * sigma) + 1)
    if order == 0:
        num = cv2.GaussianBlur(n * m[..., None], (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
        den = cv2.GaussianBlur(m, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
        return num / np.maximum(den, 1e-8)[..., None]
    g = cv2.getGaussianKernel(k, sigma).ravel()
    d = np.arange(k) - (k - 1) // 2
    g1, g2 = g * d, g * d * d

    def filt(img, ky, kx):  # correlation: sum_de ky[d] kx[e] img[i+d, j+e], zero outside
        return cv2.sepFilter2D(img, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT)

    w = np.maximum(filt(m, g, g), 1e-8)
    nm = n * m[..., None]
    v = filt(nm, g, g) / w[..., None]
    uy, ux = filt(m, g1, g) / w, filt(m, g, g1) / w
    ridge = 1e-3 * sigma**2
    cyy = filt(m, g2, g) / w - uy * uy + ridge
    cxx = filt(m, g, g2) / w - ux * ux + ridge
    cxy = filt(m, g1, g1) / w - uy * ux
    sy = filt(nm, g1, g) / w[..., None] - uy[..., None] * v
    sx = filt(nm, g, g1) / w[..., None] - ux[..., None] * v
    det = (cyy * cxx - cxy * cxy)[..., None]
    by = (cxx[..., None] * sy - cxy[..., None] * sx) / det
    bx = (cyy[..., None] * sx - cxy[..., None] * sy) / det
    return v - by * uy[..., None] - bx * ux[..., None]


def unsharp_mask(inp, mask, sigma: float = 2.0, amount: float = 1.0, order: int = 1):
    """Unsharp masking of the normal field: n + amount (n - blur_sigma(n)), renormalized.

    Args:
      sigma: Gaussian blur radius in texels; amount: sharpening gain (0 = identity);
      order: masked blur order, 1 (local plane: tilted flat panels stay unchanged) or 0
        (normalized convolution, the classic form, which sharpens every mask border).
    """
    inp, mask = np.asarray(inp), np.asarray(mask, np.float32)
    out = np.empty(inp.shape, np.float32)
    for i in range(len(inp)):
        n, m = _normals(inp[i]), mask[i, ..., 0].astype(np.float64)
        out[i] = _to_rgb_masked(n + amount * (n - _masked_blur(n, m, sigma, order)), mask[i])
    return out


def resample(inp, mask, factor: float = 2.0, down=cv2.INTER_AREA, up=cv2.INTER_CUBIC):
    """Down-sample by `factor` and up-sample back (bicubic by default; `up=cv2.INTER_LANCZOS4`
    for Lanczos) -- the image-super-resolution baseline applied to the coarse map, masked."""
    inp, mask = np.asarray(inp), np.asarray(mask, np.float32)
    n_, h, w, _ = inp.shape
    sh, sw = max(1, round(h / factor)), max(1, round(w / factor))
    out = np.empty(inp.shape, np.float32)
    for i in range(n_):
        n, m = _normals(inp[i]), mask[i, ..., 0].astype(np.float64)
        small_n = cv2.resize(n * m[..., None], (sw, sh), interpolation=down)
        small_m = cv2.resize(m, (sw, sh), interpolation=down)
        small = small_n / np.maximum(small_m, 1e-8)[..., None] * (small_m > 1e-8)[..., None]
        big_n = cv2.resize(small, (w, h), interpolation=up)
        big_m = cv2.resize((small_m > 1e-8).astype(np.float64), (w, h), interpolation=up)
        out[i] = _to_rgb_masked(big_n / np.maximum(big_m, 1e-8)[..., None], mask[i])
    return out


_SCORE_CACHE: dict = {}


def _score_fn(layers, pool):
    key = (layers, pool)
    if key not in _SCORE_CACHE:
        def fn(vgg_params, inp, out, target, mask):
            n = inp.shape[0]
            feats = vgg.features(vgg_params, jnp.concatenate([inp, out, target]),
                                 layers=layers, pool=pool)
            f_in, f_out, f_tgt = ({k: v[i * n:(i + 1) * n] for k, v in feats.items()}
                                  for i in range(3))
            return (losses.style_loss(f_in, f_tgt, mask, layers),
                    losses.style_loss(f_out, f_tgt, mask, layers))
        _SCORE_CACHE[key] = jax.jit(fn)
    return _SCORE_CACHE[key]


@functools.partial(jax.jit, static_argnames="sigma")
def _detail_triplet(inp, out, target, mask, sigma):
    return detail.on_reference_branch_rgb(inp, (out, target), mask, sigma)


def detail_triplet(inp, out, target, mask, sigma: float = detail.DEFAULT_SIGMA):
    """Detail maps (RGB form) of input, output and target patches, all on the INPUT's branch
    (`wrinkle_jax.detail`), each with its own large scale removed. (N, S, S, 3) float32 each."""
    got = _detail_triplet(*(jnp.asarray(np.asarray(a), jnp.float32)
                            for a in (inp, out, target, mask)), float(sigma))
    return tuple(np.asarray(g) for g in got)


def score_patches(vgg_params, inp, out, target, mask, layers=EVAL_LAYERS, pool="avg",
                  batch_size: int = 16, detail_sigma: float | None = None
                  ) -> dict[str, np.ndarray]:
    """Per-patch style losses and improvement scores (float32 XLA convolutions: exact).

    Args:
      detail_sigma: None for the paper's object-space score; a low-pass radius in texels
        (e.g. `detail.DEFAULT_SIGMA`) for the detail-only score (`detail_triplet`).
    Returns:
      dict of (N,) arrays: loss_input, loss_output, improvement (the paper's |.| form, %),
      improvement_signed (%), valid (bool: the input's loss is not ~0).
    """
    fn = _score_fn(tuple(layers), pool)
    n = len(inp)
    if detail_sigma is not None:
        inp, out, target = detail_triplet(inp, out, target, mask, detail_sigma)
    parts = []
    for s in range(0, n, batch_size):
        sl = slice(s, min(s + batch_size, n))
        idx = np.resize(np.arange(sl.start, sl.stop), batch_size)  # fixed shape: one compile
        got = fn(vgg_params, *(jnp.asarray(np.asarray(a)[idx], jnp.float32)
                               for a in (inp, out, target, mask)))
        parts.append([np.asarray(g)[:sl.stop - sl.start] for g in got])
    return scores_from_losses(np.concatenate([p[0] for p in parts]),
                              np.concatenate([p[1] for p in parts]))


def scores_from_losses(loss_input, loss_output) -> dict[str, np.ndarray]:
    """Improvement scores of a set of patches from their (N,) input and output style losses.

    eps = 1e-6 of the set's largest input loss (only an exact match of input and target makes a
    patch's score undefined). Returns dict of (N,) arrays: loss_input, loss_output, improvement
    (paper |.| form, %), improvement_signed (%), valid (bool).
    """
    loss_input = np.asarray(loss_input, np.float32)
    loss_output = np.asarray(loss_output, np.float32)
    eps = 1e-6 * max(float(loss_input.max(initial=0.0)), 1e-30)
    sc = metrics.improvement_score_from_losses(jnp.asarray(loss_input), jnp.asarray(loss_output),
                                               eps=eps)
    return {"loss_input": loss_input, "loss_output": loss_output,
            "improvement": np.asarray(sc.score), "improvement_signed": np.asarray(sc.signed_score),
            "valid": np.asarray(sc.valid)}


def summarize(scores: dict[str, np.ndarray], groups: np.ndarray | None = None) -> dict:
    """Mean and standard deviation of the scores over valid patches, overall and per group."""
    def stats(sel):
        v = scores["valid"] & sel
        if not v.any():
            return {"n": 0}
        imp, sgn = scores["improvement"][v], scores["improvement_signed"][v]
        return {"n": int(v.sum()), "improvement_mean": float(imp.mean()),
                "improvement_std": float(imp.std()), "signed_mean": float(sgn.mean()),
                "signed_std": float(sgn.std()),
                "loss_ratio_median": float(np.median(scores["loss_output"][v]
                                                     / scores["loss_input"][v]))}
    out = {"all": stats(np.ones_like(scores["valid"]))}
    if groups is not None:
        groups = np.asarray(groups)
        for g in sorted(set(groups.tolist())):
            out[str(g)] = stats(groups == g)
    return out


def bootstrap_ci(x, stat=np.median, n_boot: int = 2000, level: float = 0.95, seed: int = 0
                 ) -> tuple[float, float]:
    """Percentile bootstrap interval of `stat` over the (N,) sample `x` (seeded)."""
    x = np.asarray(x, np.float64)
    if len(x) == 0:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(x), size=(n_boot, len(x)))
    boots = stat(x[idx], axis=1)
    lo, hi = np.quantile(boots, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def paired_difference(a, b, valid=None, n_boot: int = 2000, seed: int = 0) -> dict:
    """Robust paired comparison of two methods' per-patch scores on the same patches.

    Args:
      a, b: (N,) scores (e.g. signed improvement) of method A and of the reference B.
      valid: optional (N,) bool; only these patches count.
    Returns:
      {"n", "median_a", "median_b", "mean_a", "mean_b", "median_diff" (median of a - b),
       "median_diff_ci" (95 % bootstrap), "mean_diff", "mean_diff_ci", "win_rate" (a > b)}.
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if valid is not None:
        a, b = a[np.asarray(valid, bool)], b[np.asarray(valid, bool)]
    d = a - b
    if not len(d):
        return {"n": 0}
    return {"n": int(len(d)), "median_a": float(np.median(a)), "median_b": float(np.median(b)),
            "mean_a": float(a.mean()), "mean_b": float(b.mean()),
            "median_diff": float(np.median(d)),
            "median_diff_ci": bootstrap_ci(d, np.median, n_boot, seed=seed),
            "mean_diff": float(d.mean()),
            "mean_diff_ci": bootstrap_ci(d, np.mean, n_boot, seed=seed),
            "win_rate": float((d > 0).mean())}


# Band edges of the detail spectrum (2 mm texels): wavelengths below 16 mm (fine creases and
# facet ripples) and 16-64 mm (the wrinkle band). A Gaussian of radius s texels halves the
# power at wavelength pi s / sqrt(ln(2) / 2) ~ 5.3 s texels, hence radii 1.5 and 6.
BAND_SIGMAS = {"lt16mm": (0.0, 1.5), "16_64mm": (1.5, 6.0)}


def _masked_gauss(x, m, sigma):
    if sigma <= 0:
        return x
    k = int(2 * np.ceil(3 * sigma) + 1)
    num = cv2.GaussianBlur(x * m[..., None], (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(m, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    return num / np.maximum(den, 1e-8)[..., None]


def band_rms(detail_rgb, mask, bands=BAND_SIGMAS) -> dict[str, np.ndarray]:
    """Per-patch RMS of the tangential detail (x, y of the detail normals) in each band.

    Args:
      detail_rgb: (N, S, S, 3) RGB-form detail maps (`detail_triplet`); mask (N, S, S, 1).
      bands: name -> (inner, outer) Gaussian radii in texels; the band is
        G_inner(d) - G_outer(d) (masked normalized convolution; inner 0 = d itself).
    Returns:
      name -> (N,) float32 RMS over texels at least 6 texels inside the mask (band-passes
      are unreliable at the border).
    """
    x = np.asarray(detail_rgb, np.float64)[..., :2] * 2.0 - 1.0
    m = np.asarray(mask, np.float64)[..., 0]
    out = {k: np.zeros(len(x), np.float32) for k in bands}
    for i in range(len(x)):
        inner = cv2.erode(m[i], np.ones((13, 13), np.uint8)) > 0
        for name, (a, b) in bands.items():
            band = _masked_gauss(x[i], m[i], a) - _masked_gauss(x[i], m[i], b)
            out[name][i] = np.sqrt(np.mean(np.sum(band[inner] ** 2, -1))) if inner.any() else 0
    return out


def checker_rms(rgb, mask) -> np.ndarray:
    """(N,) RMS of the 2-texel checkerboard component (the Nyquist frequency of the texel grid,
    the transposed-conv artefact) of the normals' x, y: the 2x2 kernel [[1, -1], [-1, 1]] / 4
    over 2x2 blocks fully inside the mask."""
    x = np.asarray(rgb, np.float64)[..., :2] * 2.0 - 1.0
    m = np.asarray(mask, np.float64)[..., 0]
    c = (x[:, :-1, :-1] - x[:, 1:, :-1] - x[:, :-1, 1:] + x[:, 1:, 1:]) / 4.0
    ok = (m[:, :-1, :-1] * m[:, 1:, :-1] * m[:, :-1, 1:] * m[:, 1:, 1:]) > 0
    sq = np.sum(c * c, -1) * ok
    return np.sqrt(sq.sum((1, 2)) / np.maximum(ok.sum((1, 2)), 1)).astype(np.float32)
