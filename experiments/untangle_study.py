"""Would a history-free untangling step undo the stored episodes? A study on single frames.

    python -m experiments.untangle_study --scene sheet_balls_wind --material knit_terry \
        --frame 378 [--step 0.0005] [--shrink] [--iterations 200] [--out PATH]

Takes one stored fine frame that self-intersects and descends the total length of its
intersection curves (intersection-contour minimisation, Volino & Magnenat-Thalmann 2006): each
pair of crossing triangles contributes the distance between its two edge-triangle crossing
points; the gradient of the sum (autodiff, float64) is taken per vertex, and every vertex on a
curve moves `--step` m along its own descent direction. The intersecting pairs are found again
after every step (`sim.intersect`, the independent checker). Nothing else acts: no cloth
constraints, no body, so the edge strain it leaves says how much the cloth solver would have to
absorb if such a step ran inside it. With --shrink the step is halved (down to 1/16 of
`--step`) whenever the contour length did not fall over the previous step. Prints a JSON line
every 10 steps and at the end: pairs (and how many have the two crossings the length reads;
the others, touching or coplanar, are left), faces %, vertices moved (max, 99th percentile, count
> 1 mm), edge strain (max, count > 10 %), the step.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import mesh, meshio
from wrinkle_jax.evaluation import cells
from wrinkle_jax.sim import intersect, scenes

ROOT = Path(__file__).resolve().parents[1]


def crossing_pairs(x: np.ndarray, faces: np.ndarray, pairs: np.ndarray):
    """For each intersecting face pair with exactly two edge-triangle crossings (the general
    case), the crossing edges (K, 2, 2) and the triangles they cross (K, 2, 3), vertex ids;
    per pair the crossings in order (the first face's edges through the second, then the
    second's through the first; edges in corner order)."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    tri = x[faces]
    hits = np.zeros((len(pairs), 2, 3), bool)  # (pair, which face's edges, edge)
    for d in range(2):
        src, dst = tri[pairs[:, d]], tri[pairs[:, 1 - d]]
        for m in range(3):
            hits[:, d, m] = intersect.segment_hits_triangle(
                src[:, m], src[:, (m + 1) % 3], dst[:, 0], dst[:, 1], dst[:, 2])
    two = hits.sum(axis=(1, 2)) == 2
    k, d, m = np.nonzero(hits & two[:, None, None])  # row-major: each pair's two together
    src, dst = pairs[k, d], pairs[k, 1 - d]
    edges = np.stack([faces[src, m], faces[src, (m + 1) % 3]], axis=1)
    return edges.reshape(-1, 2, 2), faces[dst].reshape(-1, 2, 3)


def contour_length(x, edges, tris):
    """Total length (m) of the intersection segments: per pair, the distance between the
    points where its two crossing edges meet the planes of the triangles they cross."""
    a, b = x[edges[..., 0]], x[edges[..., 1]]
    p, q, r = x[tris[..., 0]], x[tris[..., 1]], x[tris[..., 2]]
    n = jnp.cross(q - p, r - p)
    s = jnp.sum((p - a) * n, -1) / jnp.sum((b - a) * n, -1)
    hit = a + s[..., None] * (b - a)
    return jnp.sum(jnp.sqrt(jnp.sum((hit[:, 0] - hit[:, 1]) ** 2, -1) + 1e-30))


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--scene", required=True, choices=sorted(scenes.SCENES))
    ap.add_argument("--material", required=True)
    ap.add_argument("--frame", type=int, required=True)
    ap.add_argument("--step", type=float, default=0.0005, help="m per vertex per step")
    ap.add_argument("--shrink", action="store_true",
                    help="halve the step when the contour length did not fall")
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    path = cells.sequence_file(args.sequences, args.scene, args.material, "fine",
                               scenes.dataset_seed(args.scene))
    seq = meshio.load_sequence(path)
    faces = np.asarray(seq.garment.faces, np.int64)
    x0 = np.asarray(seq.frames[args.frame], np.float64)
    x = x0.copy()
    edges = mesh.unique_edges(faces)
    rest = np.linalg.norm(x0[edges[:, 0]] - x0[edges[:, 1]], axis=1)
    grad = jax.jit(jax.grad(contour_length))
    rows, t0 = [], time.perf_counter()
    step, last = args.step, np.inf
    for it in range(args.iterations + 1):
        pairs = intersect.intersecting_pairs(x, faces)
        e, t = crossing_pairs(x, faces, pairs)
        if it % 10 == 0 or len(pairs) == 0 or it == args.iterations:
            moved = np.linalg.norm(x - x0, axis=1)
            strain = np.abs(np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / rest - 1)
            row = {"step": it, "pairs": int(len(pairs)), "pairs_with_two_crossings": len(e),
                   "faces_pct": round(100 * len(np.unique(pairs)) / len(faces), 3),
                   "moved_max_mm": round(1e3 * moved.max(), 2),
                   "moved_p99_mm": round(1e3 * float(np.percentile(moved[moved > 0], 99))
                                         if (moved > 0).any() else 0.0, 2),
                   "moved_over_1mm": int((moved > 1e-3).sum()),
                   "strain_max": round(float(strain.max()), 3),
                   "edges_over_10pct": int((strain > 0.1).sum()), "edges": int(len(edges)),
                   "step_mm": round(1e3 * step, 4),
                   "wall_s": round(time.perf_counter() - t0, 1)}
            print(json.dumps(row), flush=True)
            rows.append(row)
        if len(pairs) == 0 or it == args.iterations:
            break
        length = float(contour_length(jnp.asarray(x), jnp.asarray(e), jnp.asarray(t)))
        if args.shrink and it > 0 and length >= last:
            step = max(step / 2, args.step / 16)
        last = length
        g = np.asarray(grad(jnp.asarray(x), jnp.asarray(e), jnp.asarray(t)))
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        x = x - step * np.where(norm > 0, g / np.maximum(norm, 1e-300), 0.0)
    if args.out:
        Path(args.out).write_text(json.dumps(
            {"command": {k: v for k, v in vars(args).items() if k != "sequences"},
             "file": str(path.relative_to(path.parents[2])), "rows": rows}, indent=1) + "\n")
    return rows


if __name__ == "__main__":
    main()
