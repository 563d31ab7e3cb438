"""Summaries of per-patch scores: means per group, bootstrap intervals, paired differences.

`paired_difference` gives the robust summary the reports lead with (median of paired
differences with a bootstrap interval). NumPy, float64.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bootstrap_ci", "paired_difference", "series_stats", "summarize"]


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


def series_stats(x: np.ndarray) -> dict:
    """mean, std, median, p95, max of a 1-D series (JSON-ready floats)."""
    x = np.asarray(x, np.float64)
    if not len(x):
        return {"n": 0}
    return {"n": int(len(x)), "mean": float(x.mean()), "std": float(x.std()),
            "median": float(np.median(x)), "p95": float(np.percentile(x, 95)),
            "max": float(x.max())}
