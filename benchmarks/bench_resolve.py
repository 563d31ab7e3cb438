"""The body push-out's CG budget against its converged solve; prints one JSON object.

`lift.resolve_penetration` (the paper's interpenetration step) solves one sparse SPD system per
round by PCG. On dress_dance (coarse sim, silk charmeuse, mannequin capsules) it runs one round
per frame and hits its iteration cap (300) before its tolerance (1e-5), and was about 60 % of
the lift stage's time (session 17). This measures, on the lifted frames the streaming pipeline
produces (shipped model, warm-started lift, body resolve switched off so the sweep sees the
pipeline's own input to the resolve), for each `ResolveConfig` variant:

  * CPU and wall ms per frame (all variants alternating on every frame, `timing.alternate`);
  * the vertex difference to a converged reference solve (cap 3,000, tolerance 1e-8): max and
    RMS over the vertices, mm;
  * vertices still inside the body (signed distance < 0) and the minimum signed distance, mm;
  * rounds and CG iterations.

Usage: python benchmarks/bench_resolve.py [--scenes dress_dance,cape_walk] [--frames 40]
           [--every 3] [--reps 2]
The scenes are simulated coarse (seed 1, as experiments/timing.py) for `--frames` frames;
frames `--every`-th from 10 on are measured (the first ones settle).
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import bodies, enhancer, lift, pipeline, timing
from wrinkle_jax.sim import scenes

REFERENCE = lift.ResolveConfig(cg_max_iters=3000, cg_tol=1e-8)
# Session 18: the pipeline's Jacobi default (tol 1e-3, session 17's choice) against the
# two-level preconditioner (`lift.resolve_coarse`, mass gamma) at looser tolerances; rule
# fixed before the run in experiments/results/lift/resolve_rule_s18.txt. (Session 17's
# variants, caps 20-300 and tol 1e-4, are in resolve_s17.json.)
VARIANTS = {
    "jacobi tol 1e-3 (default)": lift.ResolveConfig(cg_tol=1e-3),
    "coarse 0.05 tol 3e-3": lift.ResolveConfig(cg_tol=3e-3, coarse_mass=0.05),
    "coarse 0.05 tol 1e-2": lift.ResolveConfig(cg_tol=1e-2, coarse_mass=0.05),
    "coarse 0.2 tol 3e-3": lift.ResolveConfig(cg_tol=3e-3, coarse_mass=0.2),
    "coarse 0.2 tol 1e-2": lift.ResolveConfig(cg_tol=1e-2, coarse_mass=0.2),
    "coarse 0.05 tol 2e-2": lift.ResolveConfig(cg_tol=2e-2, coarse_mass=0.05),
}


def lifted_frames(scene: str, frames: int, every: int):
    """(lifted vertices list, body list, topology, frame indices, subdivision) of `scene`: the
    pipeline's detailed frames before any push-out (body None), the capsule body of each
    measured frame, and the lifted mesh's topology and subdivision from the coarse garment."""
    material = "silk_charmeuse"
    seq = scenes.simulate(scenes.get_scene(scene), material, "coarse", frames=frames, seed=1)
    ends = np.asarray(seq.tracks["capsule_ends"])
    radii = np.asarray(seq.tracks["capsule_radii"])
    pipe = pipeline.make_pipeline(seq.garment, enhancer.load_enhancer(),
                                  pipeline.PipelineConfig(warm_start=True), None)
    # Every frame is enhanced (the warm start follows the sequence); every `every`-th is kept.
    res = pipeline.enhance_sequence(seq, material, pipeline=pipe, keep=True)
    picks = list(range(10, len(seq), every))
    bodies_t = [bodies.primitive_body(capsules=(ends[t, :, 0], ends[t, :, 1], radii))
                for t in picks]
    return ([jnp.asarray(res.detailed_frames[t]) for t in picks], bodies_t, pipe.topology, picks,
            pipe.subdivision)


def measure(verts, bodies_t, topology, subdivision, reps: int) -> dict:
    rows = {k: {"max_mm": [], "rms_mm": [], "inside": [], "min_distance_mm": [], "rounds": [],
                "cg_iterations": [], "cpu_ms": [], "wall_ms": []} for k in VARIANTS}
    before = {"inside": [], "within_thickness": []}
    coarse = {k: lift.resolve_coarse(subdivision, topology, 5e3, c) for k, c in VARIANTS.items()}
    for v, b in zip(verts, bodies_t, strict=True):
        q = bodies.query(b, v)
        before["inside"].append(int(jnp.sum(q.distance < 0)))
        before["within_thickness"].append(int(jnp.sum(q.distance < REFERENCE.thickness)))
        ref = np.asarray(lift.resolve_penetration(v, topology, b, 5e3, REFERENCE))
        runs = {k: (lambda c=c, v=v, b=b, k=k: lift.resolve_penetration_with_info(
                    v, topology, b, 5e3, c, coarse[k])) for k, c in VARIANTS.items()}
        t = timing.alternate(runs, reps=reps)
        for k in VARIANTS:
            out, info = runs[k]()
            out = np.asarray(out)
            d = np.linalg.norm(out - ref, axis=-1) * 1e3
            r = rows[k]
            r["max_mm"].append(float(d.max()))
            r["rms_mm"].append(float(np.sqrt(np.mean(d ** 2))))
            r["inside"].append(int(info.inside))
            r["min_distance_mm"].append(float(bodies.query(b, out).distance.min()) * 1e3)
            r["rounds"].append(int(info.rounds))
            r["cg_iterations"].append(int(info.cg_iterations))
            r["cpu_ms"].append(1e3 * t.cpu[k])
            r["wall_ms"].append(1e3 * t.wall[k])
    summary = {k: {"max_mm_worst": max(r["max_mm"]), "rms_mm_mean": float(np.mean(r["rms_mm"])),
                   "inside_total": sum(r["inside"]),
                   "min_distance_mm_worst": min(r["min_distance_mm"]),
                   "cg_iterations_mean": float(np.mean(r["cg_iterations"])),
                   "cpu_ms_median": float(np.median(r["cpu_ms"])),
                   "wall_ms_median": float(np.median(r["wall_ms"]))} for k, r in rows.items()}
    return {"before": before, "per_frame": rows, "summary": summary}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="dress_dance,cape_walk")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--every", type=int, default=3)
    ap.add_argument("--reps", type=int, default=2)
    args = ap.parse_args(argv)
    out = {"benchmark": "resolve_budget", "reference": REFERENCE.__dict__,
           "variants": {k: c.__dict__ for k, c in VARIANTS.items()},
           "load_avg_1m_before": os.getloadavg()[0], "scenes": {}}
    for scene in args.scenes.split(","):
        verts, bodies_t, topology, picks, subdivision = lifted_frames(scene, args.frames,
                                                                      args.every)
        got = measure(verts, bodies_t, topology, subdivision, args.reps)
        got["frames"] = picks
        got["vertices"] = int(verts[0].shape[0])
        out["scenes"][scene] = got
    out["load_avg_1m_after"] = os.getloadavg()[0]
    out["jax"] = jax.__version__
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
