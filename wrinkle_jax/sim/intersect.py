"""Self-intersection measurement: how many pairs of non-adjacent triangles intersect.

The independent checker of the solver's optional self-collision (`sim.selfcollision`): it
uses none of the solver's code. (The solver's untangling step borrows `grid_pairs` to list
faces near in the pattern; the checker's broad phase is only a superset filter.)

Method (NumPy, per frame): a spatial hash with cells as large as the longest edge puts each
triangle at its centroid's cell, so two triangles that touch are in the same or neighbouring
cells. Candidate pairs from the 27 neighbouring cells are filtered by bounding-box overlap and
by sharing no vertex (adjacent triangles always touch), then tested exactly: two triangles
intersect iff an edge of one crosses the other (segment-triangle tests, Moller-Trumbore).
Coplanar overlaps are not counted.
"""

from __future__ import annotations

import itertools

import numpy as np


def segment_hits_triangle(p, q, a, b, c, eps: float = 1e-12) -> np.ndarray:
    """(N,) bool: segment p-q crosses triangle a-b-c (all (N, 3) float64)."""
    d = q - p
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > eps
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p - a
    u = inv * np.einsum("ij,ij->i", s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, qv)
    t = inv * np.einsum("ij,ij->i", e2, qv)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def grid_pairs(points: np.ndarray, cell: float) -> np.ndarray:
    """Pairs (K, 2) int64, i < j, of the points (N, D) in the same or adjacent cells of a grid
    `cell` wide: every pair closer than `cell` is among them (a superset; NumPy)."""
    g = np.floor((points - points.min(0)) / cell).astype(np.int64) + 1
    dims = g.max(0) + 2
    stride = np.cumprod(np.concatenate([dims[1:], [1]])[::-1])[::-1]  # mixed-radix key
    key = g @ stride
    order = np.argsort(key, kind="stable")
    skey = key[order]
    out = []
    for offset in itertools.product((-1, 0, 1), repeat=points.shape[1]):
        q = key + int(np.dot(offset, stride))
        lo = np.searchsorted(skey, q, "left")
        hi = np.searchsorted(skey, q, "right")
        n = hi - lo
        if n.sum() == 0:
            continue
        i = np.repeat(np.arange(len(points)), n)
        j = order[np.repeat(lo, n) + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))]
        keep = i < j
        out.append(np.stack([i[keep], j[keep]], 1))
    return np.concatenate(out) if out else np.zeros((0, 2), np.int64)


def intersecting_pairs(vertices, faces, chunk: int = 1 << 20) -> np.ndarray:
    """Pairs (K, 2) of non-adjacent faces that intersect in this frame.

    Args:
      vertices: (V, 3) float, meters. faces: (F, 3) int.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    tri = v[f]
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max()
    pairs = grid_pairs(tri.mean(1), max(float(edge), 1e-9))
    lo, hi = tri.min(1), tri.max(1)
    hits = []
    for s in range(0, len(pairs), chunk):
        i, j = pairs[s:s + chunk, 0], pairs[s:s + chunk, 1]
        ok = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
        shared = (f[i][:, :, None] == f[j][:, None, :]).any(axis=(1, 2))
        i, j = i[ok & ~shared], j[ok & ~shared]
        a, b = tri[i], tri[j]
        hit = np.zeros(len(i), bool)
        for k in range(3):
            hit |= segment_hits_triangle(a[:, k], a[:, (k + 1) % 3], b[:, 0], b[:, 1], b[:, 2])
            hit |= segment_hits_triangle(b[:, k], b[:, (k + 1) % 3], a[:, 0], a[:, 1], a[:, 2])
        hits.append(np.stack([i[hit], j[hit]], 1))
    return np.concatenate(hits) if hits else np.zeros((0, 2), np.int64)


def self_intersection_stats(frames, faces, every: int = 1) -> dict:
    """Per-frame counts of intersecting non-adjacent triangle pairs over a sequence.

    Args:
      frames: (T, V, 3) positions; faces: (F, 3); every: measure every n-th frame.
    Returns:
      dict with the measured frame indices, counts, the fraction of frames with any
      intersection, the mean and max count, and the fraction of faces involved: per frame,
      their mean and the worst frame's (the issue's target is per frame).
    """
    idx = list(range(0, len(frames), max(every, 1)))
    counts, involved = [], []
    for t in idx:
        p = intersecting_pairs(frames[t], faces)
        counts.append(int(len(p)))
        involved.append(len(np.unique(p)) / len(faces))
    counts_a = np.asarray(counts)
    return {
        "frames": idx,
        "counts": counts,
        "frames_with_intersections": float(np.mean(counts_a > 0)) if len(idx) else 0.0,
        "mean_pairs": float(counts_a.mean()) if len(idx) else 0.0,
        "max_pairs": int(counts_a.max()) if len(idx) else 0,
        "mean_face_fraction": float(np.mean(involved)) if len(idx) else 0.0,
        "max_face_fraction": float(np.max(involved)) if len(idx) else 0.0,
        "face_fractions": [float(a) for a in involved],
    }
