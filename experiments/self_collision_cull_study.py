"""Where the fine self-collision candidates come from, on stored poses (issue 24's cost; a
study, no solver change): would a rest-space cluster cull with normal cones, or a smaller
margin, shrink the candidate build?

    nice -n 10 python -m experiments.self_collision_cull_study \
        data/sequences/skirt_dance/silk_charmeuse_fine_s0.npz --poses 100,300,500 \
        --out experiments/results/sim/self_collision_cull_study_s24_skirt.json

Per pose t (settings of `scenes.SELF_COLLISION["fine"]`: thickness 4 mm, margin 14 mm, rest
exclusion 24 mm):
  * the candidate funnel of the blocked build's definition: (vertex, triangle) pairs passing
    the sphere test (|x - centroid| - circumradius < reach), after the rest exclusion and the
    incident-vertex test, within the reach (exact distance, `selfcollision.
    closest_point_triangle`), within thickness + 2 mm;
  * a cluster cull: each panel's triangles split by k-means on their rest centroids into
    clusters of ~`--cluster-faces`; cluster pairs whose bounding spheres (+ reach) overlap
    are kept, except rest-adjacent pairs (sharing a vertex) whose union's normal cone is
    narrower than 90 degrees (a near-flat connected patch cannot touch itself; Volino and
    Magnenat-Thalmann's criterion without its contour test), and a cluster is tested
    against itself only when its own cone reaches 90 degrees. Reported: the vertex-triangle
    tests the surviving pairs need and the share of the reach / near pairs they cover;
  * the approach of the pairs that are near at t + 1 (distance at t minus distance at t + 1,
    per 1/30 s frame): the margin must cover it over one rebuild interval (1/150 s).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from wrinkle_jax.fileio import atomic_write_text
from wrinkle_jax.sim import scenes
from wrinkle_jax.sim.selfcollision import closest_point_triangle

CFG = scenes.SELF_COLLISION["fine"]


def distances(x, faces, vi, fi):
    """Exact vertex-triangle distances (N,) m of pairs (vi, fi) at positions x (V, 3)."""
    t = jnp.asarray(x[faces[fi]], jnp.float32)
    _, d2, _ = closest_point_triangle(jnp.asarray(x[vi], jnp.float32), t[:, 0], t[:, 1], t[:, 2])
    return np.sqrt(np.asarray(d2, np.float64))


def candidate_pairs(x, faces, rest, reach):
    """(vi, fi) passing the sphere test, not incident, not rest-excluded; and the count before
    the rest exclusion."""
    tri = x[faces]
    cen = tri.mean(1)
    circ = np.sqrt(((tri - cen[:, None]) ** 2).sum(-1).max(1))
    lists = cKDTree(x).query_ball_point(cen, circ.max() + reach)
    fi = np.repeat(np.arange(len(faces)), [len(p) for p in lists])
    vi = np.concatenate(lists).astype(np.int64)
    keep = np.linalg.norm(x[vi] - cen[fi], axis=1) - circ[fi] < reach
    keep &= ~(faces[fi] == vi[:, None]).any(1)
    fi, vi = fi[keep], vi[keep]
    vuv, vpanel, cen_uv, panels = rest
    own = (panels[fi] == vpanel[vi]) & (((vuv[vi] - cen_uv[fi]) ** 2).sum(1)
                                        < CFG.rest_exclusion ** 2)
    return vi[~own], fi[~own], len(fi)


def rest_clusters(cen_uv, panels, size, seed=0):
    """Cluster id (F,) per face: k-means (15 Lloyd steps) on rest centroids within a panel."""
    rng = np.random.default_rng(seed)
    lab_all = np.zeros(len(panels), np.int64)
    n = 0
    for p in np.unique(panels):
        idx = np.where(panels == p)[0]
        k = max(1, round(len(idx) / size))
        c = cen_uv[idx[rng.choice(len(idx), k, replace=False)]].copy()
        for _ in range(15):
            lab = cKDTree(c).query(cen_uv[idx])[1]
            for j in range(k):
                if (lab == j).any():
                    c[j] = cen_uv[idx[lab == j]].mean(0)
        lab_all[idx] = lab + n
        n += k
    return lab_all, n


def cone_deg(normals):
    m = normals.sum(0)
    m /= max(np.linalg.norm(m), 1e-30)
    return float(np.degrees(np.arccos(np.clip((normals @ m).min(), -1.0, 1.0))))


def cluster_cull(x, faces, fclus, n, vown, vi, fi, near, reach):
    cl_faces = [np.where(fclus == c)[0] for c in range(n)]
    cl_verts = [np.unique(faces[f]) for f in cl_faces]
    adj = set()
    owners = {}
    for c, vs in enumerate(cl_verts):
        for v in vs:
            owners.setdefault(int(v), []).append(c)
    for cs in owners.values():
        adj.update((a, b) for a in cs for b in cs if a < b)
    tri = x[faces]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    ctr = np.array([x[vs].mean(0) for vs in cl_verts])
    rad = np.array([np.linalg.norm(x[vs] - ctr[c], axis=1).max()
                    for c, vs in enumerate(cl_verts)])
    cand = cKDTree(ctr).query_pairs(2 * rad.max() + reach, output_type="ndarray")
    cand = cand[np.linalg.norm(ctr[cand[:, 0]] - ctr[cand[:, 1]], axis=1)
                < rad[cand[:, 0]] + rad[cand[:, 1]] + reach]
    keep, adjacent, culled = [], 0, 0
    for a, b in cand.tolist():
        if (a, b) in adj:
            adjacent += 1
            if cone_deg(nrm[np.concatenate([cl_faces[a], cl_faces[b]])]) < 90.0:
                culled += 1
                continue
        keep.append((a, b))
    keep = np.array(keep, np.int64).reshape(-1, 2)
    selfk = [c for c in range(n) if cone_deg(nrm[cl_faces[c]]) >= 90.0]
    nv = np.bincount(vown, minlength=n)
    nf = np.bincount(fclus, minlength=n)
    tests = int((nv[keep[:, 0]] * nf[keep[:, 1]] + nv[keep[:, 1]] * nf[keep[:, 0]]).sum()
                + sum(int(nv[c] * nf[c]) for c in selfk))
    ok = {(a, b) for a, b in keep.tolist()} | {(b, a) for a, b in keep.tolist()}
    ok |= {(c, c) for c in selfk}
    cov = np.array([(int(a), int(b)) in ok for a, b in zip(vown[vi], fclus[fi], strict=True)],
                   bool)
    return {"cluster_pairs_overlapping": int(len(cand)), "of_which_rest_adjacent": adjacent,
            "adjacent_culled_by_cone": culled, "cluster_pairs_kept": int(len(keep)),
            "clusters_tested_against_themselves": len(selfk),
            "vertex_triangle_tests_after_cull": tests,
            "reach_pairs_covered": float(cov.mean()) if len(cov) else 1.0,
            "near_pairs_missed": int((~cov[near]).sum())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--poses", default="100,300,500")
    ap.add_argument("--cluster-faces", type=int, default=64)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    z = np.load(args.sequence)
    faces, panels = z["faces"].astype(np.int64), z["panels"]
    face_uv = z["uvs"][z["uv_faces"]].astype(np.float64)
    cen_uv = face_uv.mean(1)
    V = z["frames"].shape[1]
    vuv = np.zeros((V, 2))
    vpanel = np.zeros(V, np.int64)
    vuv[faces.reshape(-1)] = face_uv.reshape(-1, 2)
    vpanel[faces.reshape(-1)] = np.repeat(panels, 3)
    rest = (vuv, vpanel, cen_uv, panels)
    fclus, n = rest_clusters(cen_uv, panels, args.cluster_faces)
    vown = np.zeros(V, np.int64)
    vown[faces.reshape(-1)] = np.repeat(fclus, 3)
    reach = CFG.thickness + CFG.margin
    out = {"sequence": args.sequence, "vertices": V, "faces": len(faces), "clusters": n,
           "settings": {"thickness": CFG.thickness, "margin": CFG.margin,
                        "rest_exclusion": CFG.rest_exclusion, "near": CFG.thickness + 0.002},
           "poses": []}
    for t in (int(p) for p in args.poses.split(",")):
        x = z["frames"][t].astype(np.float64)
        vi, fi, before = candidate_pairs(x, faces, rest, reach)
        d = distances(x, faces, vi, fi)
        inr = d < reach
        near = d[inr] < CFG.thickness + 0.002
        row = {"pose": t, "sphere_pairs_before_rest_exclusion": int(before),
               "after_rest_exclusion": int(len(vi)), "within_reach": int(inr.sum()),
               "within_thickness_plus_2mm": int(near.sum())}
        row |= cluster_cull(x, faces, fclus, n, vown, vi[inr], fi[inr], near, reach)
        # approach of the pairs near at t + 1 over the frame before
        x1 = z["frames"][t + 1].astype(np.float64)
        v1, f1, _ = candidate_pairs(x1, faces, rest, CFG.thickness + 0.002)
        d1 = distances(x1, faces, v1, f1)
        m = d1 < CFG.thickness + 0.002
        app = distances(x, faces, v1[m], f1[m]) - d1[m]
        row["near_at_t+1"] = int(m.sum())
        row["approach_per_frame_m"] = ({f"p{q}": float(np.percentile(app, q))
                                        for q in (50, 99, 99.9)} | {"max": float(app.max())}
                                       if len(app) else None)
        row["max_vertex_speed_m_s"] = float(np.linalg.norm(x1 - x, axis=1).max() * 30.0)
        out["poses"].append(row)
        print(json.dumps(row), flush=True)
    atomic_write_text(Path(args.out), json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
