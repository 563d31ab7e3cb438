"""Benchmark mesh bodies per pose (issue 22, item 3); prints JSON.

Two cases, each timed with `wrinkle_jax.timing.alternate` (interleaved rounds, median wall and
CPU milliseconds, the 1-minute load average before and after):

  * `torus`: a bent torus (1,536 triangles: a thin tube whose halves nearly touch), where the
    previous form (`bodies_grid.grid_mesh_body`, NumPy) still builds: old against new in one
    alternating run, build (per pose) and query (`--points` random points around the body),
    with ratios new / old; both forms' distances against the exact signed distance (brute
    force over every triangle, sign from the winding number); and the query again on points
    near the surface (vertices jittered by 5 mm: what a garment lift asks).
  * `makehuman` (when the assets are fetched: `wrinkle-jax assets fetch makehuman`): the
    skinned MakeHuman body (26,756 triangles) on walk-cycle poses; the template once, then
    per pose the jitted build and the query of the LBS skirt helper subdivided to the lifted
    sizes (level 2: 11k, level 3: 44k vertices), with how many points took the exact
    fallback. The previous form is not run by default (it raised BodyError after 68 s on the
    rest pose: "1997 grid cells near the surface need more than 128 candidate triangles");
    `--old-makehuman` runs it once on the first pose and reports its time and outcome.

    python benchmarks/bench_bodies.py [--reps 3] [--points 11088] [--no-makehuman]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import bodies, bodies_grid, timing


def bend(v, angle=2.4):
    """Roll the x axis onto a circle (the torus curls up on itself by `angle` radians)."""
    r = 0.2 / angle
    x, z = v[:, 0] + 0.1, v[:, 2]
    a = x / r
    return np.stack([r * np.sin(a) - z * np.sin(a) - 0.1, v[:, 1],
                     r * (1 - np.cos(a)) + z * np.cos(a)], 1).astype(np.float32)


def exact_signed_distance(vertices, faces, points, chunk: int = 500) -> np.ndarray:
    """Signed distance by brute force, independent of both query forms: the nearest point of
    every triangle (`closest_point_on_triangle`) and the sign from the generalized winding
    number (solid angles / 4 pi, inside where |w| > 1/2). O(points x triangles)."""
    tri = jnp.asarray(np.asarray(vertices)[np.asarray(faces)], jnp.float32)

    @jax.jit
    def run(p):
        cp, _ = bodies.closest_point_on_triangle(p[:, None], tri[None, :, 0], tri[None, :, 1],
                                                 tri[None, :, 2])
        d = jnp.sqrt(jnp.min(jnp.sum((p[:, None] - cp) ** 2, -1), 1))
        a, b, c = (tri[None, :, k] - p[:, None] for k in range(3))
        la, lb, lc = (jnp.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = jnp.sum(a * jnp.cross(b, c), -1)
        den = (la * lb * lc + jnp.sum(a * b, -1) * lc + jnp.sum(b * c, -1) * la
               + jnp.sum(c * a, -1) * lb)
        w = jnp.sum(2 * jnp.arctan2(det, den), 1) / (4 * jnp.pi)
        return jnp.where(jnp.abs(w) > 0.5, -d, d)

    pts = jnp.asarray(points, jnp.float32)
    return np.concatenate([np.asarray(run(pts[i:i + chunk]))
                           for i in range(0, len(pts), chunk)])


def _errors(d: np.ndarray, exact: np.ndarray) -> dict:
    e = np.abs(d - exact)
    near = np.abs(exact) < 0.02
    return {"max_abs_error_m": float(e.max()),
            "max_abs_error_within_2cm_m": float(e[near].max()) if near.any() else 0.0,
            "exact_distance_at_worst_m": float(exact[e.argmax()]),
            "sign_errors": int(((d < 0) != (exact < 0)).sum())}


def torus_case(reps: int, n_points: int) -> dict:
    import trimesh

    t = trimesh.creation.torus(major_radius=0.08, minor_radius=0.015, major_sections=48,
                               minor_sections=16)
    rest, faces = np.asarray(t.vertices), np.asarray(t.faces)
    posed = bend(rest)
    rng = np.random.default_rng(0)
    pts = rng.uniform(posed.min(0) - 0.03, posed.max(0) + 0.03, (n_points, 3))
    pts = jnp.asarray(pts, jnp.float32)
    t0 = time.perf_counter()
    tpl = bodies.mesh_template(rest, faces)
    template_s = time.perf_counter() - t0
    old_body = bodies_grid.grid_mesh_body(posed, faces)
    new_body = bodies.pose_mesh_body(tpl, posed)
    old_q, new_q = jax.jit(bodies_grid.grid_query), jax.jit(bodies.query)
    build = timing.alternate({"new": lambda: bodies.pose_mesh_body(tpl, posed),
                              "old": lambda: bodies_grid.grid_mesh_body(posed, faces)},
                             reps=reps)
    query = timing.alternate({"new": lambda: new_q(new_body, pts),
                              "old": lambda: old_q(old_body, pts)}, reps=reps)
    d_new = np.asarray(new_q(new_body, pts).distance)
    d_old = np.asarray(old_q(old_body, pts).distance)
    exact = exact_signed_distance(posed, faces, pts)
    # Points near the surface (what a garment lift queries): surface vertices jittered by
    # 5 mm (normal distribution per axis).
    near = jnp.asarray(posed[rng.integers(0, len(posed), n_points)]
                       + rng.normal(0.0, 0.005, (n_points, 3)), jnp.float32)
    query_near = timing.alternate({"new": lambda: new_q(new_body, near),
                                   "old": lambda: old_q(old_body, near)}, reps=reps)
    exact_near = exact_signed_distance(posed, faces, near)
    return {"triangles": len(faces), "points": n_points, "template_ms": round(1e3 * template_s),
            "build": build.to_json("old"), "query": query.to_json("old"),
            "new_query_paths": bodies.mesh_query_stats(new_body, pts),
            "max_abs_distance_difference_m": float(np.abs(d_new - d_old).max()),
            "sign_disagreements": int(((d_new < 0) != (d_old < 0)).sum()),
            "against_exact": {"new": _errors(d_new, exact), "old": _errors(d_old, exact)},
            "near_surface": {
                "query": query_near.to_json("old"),
                "new_query_paths": bodies.mesh_query_stats(new_body, near),
                "against_exact": {
                    "new": _errors(np.asarray(new_q(new_body, near).distance), exact_near),
                    "old": _errors(np.asarray(old_q(old_body, near).distance), exact_near)}}}


def makehuman_case(reps: int, old: bool) -> dict | None:
    from wrinkle_jax import assets_fetch, character
    from wrinkle_jax import lift as lift_lib

    if assets_fetch.makehuman_path(required=False) is None:
        return None
    char = character.load_character()
    anim, skel = char.walk_cycle(None), char.skeleton
    body, skirt = char.body, char.garments["helper-skirt"]
    times = anim.start + np.arange(4, dtype=np.float32) * 3.0
    mats = jax.jit(lambda t: character.walk_skinning_matrices(anim, skel, t))(
        jnp.asarray(times))
    skin = jax.jit(character.skin_frames)
    poses = np.asarray(skin(jnp.asarray(body.garment.vertices), char.part_weights(body), mats))
    skirt_frames = skin(jnp.asarray(skirt.garment.vertices), char.part_weights(skirt), mats)
    faces = np.asarray(body.garment.faces)
    t0 = time.perf_counter()
    tpl = bodies.mesh_template(np.asarray(body.garment.vertices), faces)
    out = {"triangles": len(faces), "template_ms": round(1e3 * (time.perf_counter() - t0)),
           "capacities": {"table_size": tpl.table_size, "entry_capacity": tpl.entry_capacity,
                          "cell_capacity": tpl.cell_capacity,
                          "cell_size_m": round(float(tpl.cell_size), 5),
                          "clusters": int(tpl.clusters.shape[0])}}
    state = {"i": 0}

    def build():  # a different pose every call, as per frame
        state["i"] = (state["i"] + 1) % len(poses)
        return bodies.pose_mesh_body(tpl, poses[state["i"]])

    out["build"] = timing.alternate({"new": build}, reps=reps).to_json()
    q = jax.jit(bodies.query)
    body1 = bodies.pose_mesh_body(tpl, poses[1])
    for levels in (2, 3):
        _, sub = lift_lib.upsample(skirt.garment, levels=levels)
        pts = sub.apply(skirt_frames[1])
        t = timing.alternate({"new": lambda p=pts: q(body1, p)}, reps=reps)
        out[f"query_{pts.shape[0]}"] = {**t.to_json(),
                                        "paths": bodies.mesh_query_stats(body1, pts)}
    if old:
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            bodies_grid.grid_mesh_body(poses[0], faces)
            outcome = "built"
        except bodies.BodyError as e:
            outcome = f"BodyError: {e}"
        out["old_build_once"] = {"wall_s": round(time.perf_counter() - t0, 1),
                                 "cpu_s": round(time.process_time() - c0, 1),
                                 "outcome": outcome, "load_avg_1m": timing.load_average()}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--points", type=int, default=11088)
    ap.add_argument("--no-makehuman", action="store_true")
    ap.add_argument("--old-makehuman", action="store_true")
    args = ap.parse_args(argv)
    res = {"benchmark": "bodies", "machine": platform.machine(), "jax": jax.__version__,
           "torus": torus_case(args.reps, args.points)}
    if not args.no_makehuman:
        res["makehuman"] = makehuman_case(args.reps, args.old_makehuman)
    json.dump(res, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
