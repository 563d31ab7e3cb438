"""Sets of patches without correspondence (paper Table 2).

:func:`chamfer_distance` of feature point sets, :func:`decrease_ratio` DR = 100 |C1 - C2| / C1
(and its signed form), and the Laplacian-eigenmap :func:`spectral_embedding` the paper plots
them in; Table 2's sets as features (`upper_triangle` of Gram matrices, per-layer
`layer_scales`), and the comparison of one method's set b with the sets a and c
(`compare_sets`: C1 = CD(a, c), C2 = CD(b, c), DR, embedded and in full space). NumPy (float64),
for reporting.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

__all__ = ["SET_A", "SET_B", "SET_C", "chamfer_distance", "chamfer_from_sq_dists",
           "chamfer_scores", "compare_sets", "decrease_ratio", "layer_scales",
           "points_from_sq_dists", "scaled_features", "scaled_sq_dists", "spectral_embedding",
           "sq_dists", "union_sq_dists", "unit_rms", "unit_rows", "upper_triangle"]

SET_A, SET_B, SET_C = 0, 1, 2  # labels: coarse input, a method's output, fine (other frames)


def _sq_norms(x) -> np.ndarray:
    """(N, D) -> (N,) float64 squared row norms."""
    x = np.asarray(x)
    return np.einsum("ij,ij->i", x, x, dtype=np.float64)


def sq_dists(x, y=None) -> np.ndarray:
    """Pairwise squared Euclidean distances of (n, d) and (m, d) points: (n, m) float64, as
    |x|^2 + |y|^2 - 2 x.y in float64, clipped at 0 (y None: x with itself, zero diagonal)."""
    x64 = np.asarray(x, np.float64)
    y64 = x64 if y is None else np.asarray(y, np.float64)
    d2 = _sq_norms(x64)[:, None] + _sq_norms(y64)[None, :] - 2.0 * (x64 @ y64.T)
    d2 = np.maximum(d2, 0.0)
    if y is None:
        np.fill_diagonal(d2, 0.0)
    return d2


def chamfer_from_sq_dists(d2) -> float:
    """Symmetric Chamfer distance from the (n, m) squared distances between two point sets:
    (mean_i min_j d_ij + mean_j min_i d_ij) / 2 with d = sqrt(d2); NaN if a set is empty."""
    d2 = np.asarray(d2, np.float64)
    if d2.ndim != 2:
        raise ValueError(f"expected an (n, m) matrix, got shape {d2.shape}")
    if 0 in d2.shape:
        return float("nan")
    d = np.sqrt(np.maximum(d2, 0.0))
    return 0.5 * float(d.min(axis=1).mean() + d.min(axis=0).mean())


def chamfer_distance(x, y) -> float:
    """Symmetric Chamfer distance of (n, d) and (m, d) point sets: the mean distance from a point
    to the nearest point of the other set, averaged over both directions (not squared).

    >>> chamfer_distance([[0.0, 0.0]], [[3.0, 4.0], [0.0, 1.0]])  # (1 + (5 + 1) / 2) / 2
    2.0
    """
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1]:
        raise ValueError(f"expected (n, d) and (m, d) points, got {x.shape} and {y.shape}")
    if not len(x) or not len(y):
        return float("nan")
    if len(x) * len(y) * x.shape[1] <= 2**25:
        # Exact differences (not the |x|^2 + |y|^2 - 2 x.y expansion): no cancellation.
        return chamfer_from_sq_dists(((x[:, None, :] - y[None, :, :]) ** 2).sum(-1))
    return chamfer_from_sq_dists(sq_dists(x, y))


def decrease_ratio(c1: float, c2: float, signed: bool = False) -> float:
    """The paper's DR = 100 |C1 - C2| / C1, or signed 100 (C1 - C2) / C1 (> 0 when C2 < C1);
    NaN unless C1 is positive and finite."""
    c1, c2 = float(c1), float(c2)
    if not (np.isfinite(c1) and c1 > 0.0):
        return float("nan")
    dr = 100.0 * (c1 - c2) / c1
    return dr if signed else abs(dr)


def spectral_embedding(x, dim: int = 2) -> np.ndarray:
    """(n, d) points -> (n, dim) Laplacian-eigenmap coordinates (float64): Gaussian affinity
    with the median squared distance as bandwidth, symmetric normalized Laplacian, the `dim`
    eigenvectors after the trivial one, divided by sqrt(degree)."""
    x = np.asarray(x, np.float64)
    d2 = sq_dists(x)
    sigma2 = np.median(d2[np.triu_indices(len(x), 1)])
    w = np.exp(-d2 / max(sigma2, 1e-30))
    deg = w.sum(1)
    lap_sym = w / np.sqrt(deg[:, None] * deg[None, :])
    _, vecs = np.linalg.eigh(lap_sym)
    # The largest eigenvalue of D^-1/2 W D^-1/2 is the trivial one; take the next `dim`.
    return vecs[:, -1 - dim:-1][:, ::-1] / np.sqrt(deg)[:, None]


# Features, distances, Chamfer distance
# --------------------------------------------------------------------------------------------


def upper_triangle(grams: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Flatten every layer's symmetric Gram matrices to their upper triangles.

    Args:
      grams: layer -> (N, C_l, C_l).
    Returns:
      layer -> (N, C_l (C_l + 1) / 2) float32, the row-major upper triangle with the diagonal
      (same key order).
    """
    out = {}
    for name, g in grams.items():
        g = np.asarray(g)
        if g.ndim != 3 or g.shape[1] != g.shape[2]:
            raise ValueError(f"{name}: expected (N, C, C) Gram matrices, got shape {g.shape}")
        rows, cols = np.triu_indices(g.shape[1])
        out[name] = np.ascontiguousarray(g[:, rows, cols], dtype=np.float32)
    return out


def unit_rows(flat: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Every layer's (N, D_l) feature rows divided by their Euclidean norms (rows of norm 0
    stay 0): the texture's shape without its amount (same key order, float32)."""
    out = {}
    for name, x in flat.items():
        x = np.asarray(x, np.float64)
        norm = np.linalg.norm(x, axis=1, keepdims=True)
        out[name] = np.where(norm > 0, x / np.where(norm > 0, norm, 1.0), 0.0).astype(np.float32)
    return out


def layer_scales(flat: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Per layer, the median Euclidean norm of its (N, D_l) feature vectors: the divisor that
    gives the layer a median norm of 1 (1.0 where that median is 0 or not finite)."""
    out = {}
    for name, x in flat.items():
        med = float(np.median(np.linalg.norm(np.asarray(x, np.float64), axis=1)))
        out[name] = med if med > 0.0 and np.isfinite(med) else 1.0
    return out


def scaled_features(flat: Mapping[str, np.ndarray], scales: Mapping[str, float]) -> np.ndarray:
    """The layers' (N, D_l) blocks, each divided by its scale, concatenated in key order:
    (N, sum_l D_l) float64."""
    return np.concatenate([np.asarray(x, np.float64) / scales[k] for k, x in flat.items()],
                          axis=1)


def scaled_sq_dists(fx: Mapping[str, np.ndarray], fy: Mapping[str, np.ndarray] | None,
                    scales: Mapping[str, float]) -> np.ndarray:
    """`sq_dists(scaled_features(fx), scaled_features(fy))`, one layer at a time (no
    concatenated float64 copies); fy None: fx with itself."""
    if fy is not None and set(fx) != set(fy):
        raise ValueError(f"different layers: {sorted(fx)} and {sorted(fy)}")
    return sum(sq_dists(fx[k], None if fy is None else fy[k]) / scales[k] ** 2 for k in fx)


def chamfer_scores(c1: float, c2: float) -> dict:
    """{"c1", "c2", "dr" (paper's |.|), "dr_signed"} as floats."""
    return {"c1": float(c1), "c2": float(c2), "dr": decrease_ratio(c1, c2),
            "dr_signed": decrease_ratio(c1, c2, signed=True)}


def points_from_sq_dists(d2) -> np.ndarray:
    """A Euclidean realization of a squared-distance matrix (classical MDS).

    Args:
      d2: (n, n) squared Euclidean distances between n points (symmetric, zero diagonal).
    Returns:
      (n, k) float64 points whose pairwise squared distances are d2 up to rounding (k: the
      number of eigenvalues of -J d2 J / 2 above 1e-12 of the largest; J the centering).
    """
    d2 = np.asarray(d2, np.float64)
    n = len(d2)
    centering = np.eye(n) - 1.0 / n
    b = -0.5 * centering @ d2 @ centering
    vals, vecs = np.linalg.eigh(0.5 * (b + b.T))
    if not vals[-1] > 0.0:
        return np.zeros((n, 1))
    keep = vals > 1e-12 * vals[-1]
    return vecs[:, keep] * np.sqrt(vals[keep])


def unit_rms(points) -> np.ndarray:
    """(n, d) points centered and scaled to unit root-mean-square distance from their centroid
    (float64; only centered when they all coincide)."""
    p = np.asarray(points, np.float64)
    p = p - p.mean(axis=0)
    rms = float(np.sqrt((p * p).sum(axis=1).mean()))
    return p / rms if rms > 0.0 else p


def compare_sets(d2, labels) -> dict:
    """C1 = CD(a, c), C2 = CD(b, c) and DR of one method in one cell, embedded and in full space.

    Args:
      d2: (n, n) squared feature distances of the union of the sets a, b and c (any order).
      labels: (n,) int, `SET_A`, `SET_B` or `SET_C` per row of d2.
    Returns:
      {"embedded": chamfer_scores(...) in the unit-RMS 2D spectral embedding of the union,
       "full": chamfer_scores(...) from d2 itself, "embedding": (n, 2) float64}.
    """
    d2 = np.asarray(d2, np.float64)
    labels = np.asarray(labels)
    if d2.shape != (len(labels), len(labels)):
        raise ValueError(f"{d2.shape} distances for {len(labels)} labels")
    a, b, c = (labels == s for s in (SET_A, SET_B, SET_C))
    if not (a.any() and b.any() and c.any()):
        raise ValueError("each of the sets a, b and c needs at least one point")
    emb = unit_rms(spectral_embedding(points_from_sq_dists(d2), dim=2))
    return {"embedded": chamfer_scores(chamfer_distance(emb[a], emb[c]),
                                       chamfer_distance(emb[b], emb[c])),
            "full": chamfer_scores(chamfer_from_sq_dists(d2[np.ix_(a, c)]),
                                   chamfer_from_sq_dists(d2[np.ix_(b, c)])),
            "embedding": emb}


# --------------------------------------------------------------------------------------------
# One cell


def union_sq_dists(d2_ref: np.ndarray, d2_b: np.ndarray, n_a: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The squared distances of a u b u c (rows in that order) and their labels, from
    `evaluate_cell`'s a-then-c block and one method's b block."""
    n_c, n_b = len(d2_ref) - n_a, len(d2_b)
    if d2_b.shape != (n_b, n_a + n_c + n_b):
        raise ValueError(f"b block {d2_b.shape} does not match {n_a} a and {n_c} c points")
    a, b, c = slice(0, n_a), slice(n_a, n_a + n_b), slice(n_a + n_b, n_a + n_b + n_c)
    d2 = np.empty((n_a + n_b + n_c,) * 2)
    d2[a, a], d2[a, c] = d2_ref[:n_a, :n_a], d2_ref[:n_a, n_a:]
    d2[c, a], d2[c, c] = d2_ref[n_a:, :n_a], d2_ref[n_a:, n_a:]
    d2[b, a], d2[b, c], d2[b, b] = d2_b[:, :n_a], d2_b[:, n_a:n_a + n_c], d2_b[:, n_a + n_c:]
    d2[a, b], d2[c, b] = d2[b, a].T, d2[b, c].T
    return d2, np.repeat([SET_A, SET_B, SET_C], [n_a, n_b, n_c])
