"""Sets of patches without correspondence (paper Table 2).

:func:`chamfer_distance` of feature point sets, :func:`decrease_ratio` DR = 100 |C1 - C2| / C1
(and its signed form), and the Laplacian-eigenmap :func:`spectral_embedding` the paper plots
them in. NumPy (float64), for reporting.
"""

from __future__ import annotations

import numpy as np

__all__ = ["chamfer_distance", "chamfer_from_sq_dists", "decrease_ratio", "spectral_embedding",
           "sq_dists"]


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
