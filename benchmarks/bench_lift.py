"""Benchmark the normal-guided lifting solvers; prints JSON.

Problem (analytic, at the pipeline's 10 mm fine resolution): a coarse sheet (40 mm grid,
smooth drape z0 = 3 cm sin(2 pi x / 0.8 m) cos(2 pi y / 1.1 m)) is upsampled twice by midpoint
subdivision to 10 mm; the target normals are those of z0 plus wrinkles of 3-5 mm amplitude: two
wave trains (10 and 13 cm wavelength, crossing directions) blended smoothly over the sheet.
Sizes: ~2k, 10k and 40k vertices (0.45, 1 and 2 m squares: same resolution, more cloth, so
the weights mean the same).

For each size and solver: per-frame time of the jitted `lift` (median of repeats, compile time
separately), iterations, final energy and mean normal angle error (degrees, all vertices,
between the lifted mesh's area-weighted vertex normals and the targets). Solvers:
  * reference: Adam, learning rate 1 mm (0.1 edge), early stop when the energy changes by less
    than `--ref-tol` relatively (calibrated so it stops after ~50 iterations at 10k, like the
    authors' PyTorch solver: ~0.33 s/iteration, ~15 s/frame, 52 iterations, dense 0.37 GiB
    Laplacian at 10k on this machine class);
  * fast: Gauss-Newton / Levenberg-Marquardt with matrix-free PCG (default settings), and the
    smallest GN iteration count whose energy and angle error are both at most the
    reference's ("gn_matched");
  * L-BFGS (optax) for comparison.
Then a speed-against-error curve at 10k (cumulative time, energy and angle error after every
iteration, from the (init, step) API jitted once), and a memory estimate (bytes of the largest
arrays, per vertex, against the dense V x V Laplacian).

Then, with --sequence (alone): the pipeline's lift on the demo skirt's first 8 enhanced frames,
cold and warm-started from the previous frame, for Gauss-Newton budgets (iterations,
tolerance): ms/frame against the distance to a converged solve (`sequence_pareto`).

    python benchmarks/bench_lift.py [--quick] | [--sequence [--frames N]]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import lift as L
from wrinkle_jax import primitives

AUTHORS_S_PER_FRAME_10K = 15.0
AUTHORS_S_PER_ITER_10K = 0.33


def make_case(cells: int):
    """Upsampled coarse sheet (p0), target normals and the ideal wrinkled surface
    (`primitives.wrinkled_sheet_case`)."""
    case = primitives.wrinkled_sheet_case(cells)
    fine = case["fine"]
    return (fine, jnp.asarray(fine.vertices), jnp.asarray(case["normals"]),
            jnp.asarray(case["ideal"]))


def _timed(fn, reps: int):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return out, first, statistics.median(times), min(times)


def run_solver(v0, top, nrm, faces, cfg: L.SolverConfig, reps: int) -> dict:
    (p, info), first, med, best = _timed(lambda: L.lift_with_info(v0, top, nrm, solver=cfg),
                                         reps)
    return {
        "config": {"method": cfg.method, "max_iters": cfg.max_iters, "tol": cfg.tol,
                   **({"cg_max_iters": cfg.cg_max_iters, "cg_tol": cfg.cg_tol}
                      if cfg.method == "gauss_newton" else {}),
                   **({"learning_rate": cfg.learning_rate, "patience": cfg.patience}
                      if cfg.method in ("adam", "gd") else {})},
        "seconds_per_frame": round(med, 4),
        "seconds_per_frame_min": round(best, 4),
        "compile_plus_first_run_s": round(first, 2),
        "iterations": int(info.iterations),
        "inner_iterations": int(info.inner_iterations),
        "converged": bool(info.converged),
        "energy": round(float(info.energy), 6),
        "angle_error_deg": round(float(L.normal_angle_error(p, faces, nrm)), 3),
    }


CURVE_COLUMNS = ["iteration", "seconds", "energy", "angle_error_deg"]


def curve(v0, top, nrm, faces, cfg: L.SolverConfig, iters: int) -> list:
    """[iteration, cumulative seconds, energy, angle error] after each iteration (one
    compile; the problem assembly is not timed)."""
    prob = jax.jit(L.make_problem)(v0, top, nrm)
    solver = L.make_solver(cfg)
    init = jax.jit(solver.init)
    step = jax.jit(solver.step)
    err = jax.jit(L.normal_angle_error)
    # Compile (two steps: some optimizer states change weak types after the first update).
    jax.block_until_ready(step(prob, step(prob, init(prob, v0))))
    points = []
    t0 = time.perf_counter()
    state = jax.block_until_ready(init(prob, v0))
    elapsed = time.perf_counter() - t0
    for i in range(iters):
        t0 = time.perf_counter()
        state = jax.block_until_ready(step(prob, state))
        elapsed += time.perf_counter() - t0
        points.append([i + 1, round(elapsed, 4), round(float(state.energy), 6),
                       round(float(err(state.vertices, faces, nrm)), 3)])
    return points


def _first_reaching(points: list, energy: float, angle: float):
    for it, sec, e, a in points:
        if e <= energy and a <= angle:
            return {"iteration": it, "seconds": sec}
    return None


def memory_estimate(v: int, top: L.LiftTopology) -> dict:
    k = int(top.neighbors.shape[1])
    f32 = 4
    arrays = {
        "topology_tables (neighbors, valid, L, L^T on the one-ring)": 4 * v * k * f32,
        "gn_blocks_M (V, K, 3, 3)": v * k * 9 * f32,
        "per_slot_rows (g_f, g_b: V, K, 3)": 2 * v * k * 3 * f32,
        "cg_vectors (x, r, z, p, Ap: V, 3)": 5 * v * 3 * f32,
    }
    total = sum(arrays.values())
    return {"vertices": v, "ring_width_K": k, "bytes": arrays, "total_bytes": total,
            "bytes_per_vertex": round(total / v, 1),
            "dense_laplacian_bytes_for_comparison": v * v * f32}


def bench_size(cells: int, reps: int, ref_tol: float, ref_patience: int, gn_probe: int):
    fine, v0, nrm, ideal = make_case(cells)
    faces = jnp.asarray(fine.faces)
    t0 = time.perf_counter()
    top = L.lift_topology(fine.faces, fine.num_vertices)
    topo_s = time.perf_counter() - t0
    ref = run_solver(v0, top, nrm, faces,
                     L.SolverConfig(method="adam", max_iters=1000, tol=ref_tol,
                                    patience=ref_patience), reps)
    gn = run_solver(v0, top, nrm, faces, L.SolverConfig(), reps)
    lbfgs = run_solver(v0, top, nrm, faces, L.SolverConfig(method="lbfgs", max_iters=200,
                                                           tol=1e-5), reps)
    matched = None
    for it in range(1, gn_probe + 1):  # fewest GN iterations matching the reference
        r = run_solver(v0, top, nrm, faces, L.SolverConfig(max_iters=it, tol=0.0), reps)
        if r["energy"] <= ref["energy"] and r["angle_error_deg"] <= ref["angle_error_deg"]:
            matched = r
            break
    prob = L.make_problem(v0, top, nrm)
    out = {
        "vertices": fine.num_vertices,
        "edge_mm": round(1e3 * float(prob.edge), 2),
        "topology_build_s": round(topo_s, 3),
        "start": {"energy": round(float(L.energy(v0, prob)), 6),
                  "angle_error_deg": round(float(L.normal_angle_error(v0, faces, nrm)), 3)},
        "ideal_wrinkled_surface": {
            "energy": round(float(L.energy(ideal, prob)), 6),
            "angle_error_deg": round(float(L.normal_angle_error(ideal, faces, nrm)), 3)},
        "reference_adam": ref,
        "gauss_newton": gn,
        "gn_matched": matched,
        "lbfgs": lbfgs,
        "speedup": {
            "gn_default_vs_reference": round(ref["seconds_per_frame"] / gn["seconds_per_frame"], 1),
            **({"gn_matched_vs_reference": round(ref["seconds_per_frame"]
                                                 / matched["seconds_per_frame"], 1)}
               if matched else {}),
        },
        "memory": memory_estimate(fine.num_vertices, top),
    }
    if fine.num_vertices == 10201:
        out["speedup"]["gn_default_vs_authors_15s"] = round(
            AUTHORS_S_PER_FRAME_10K / gn["seconds_per_frame"], 1)
        if matched:
            out["speedup"]["gn_matched_vs_authors_15s"] = round(
                AUTHORS_S_PER_FRAME_10K / matched["seconds_per_frame"], 1)
        out["speedup"]["reference_adam_vs_authors_15s"] = round(
            AUTHORS_S_PER_FRAME_10K / ref["seconds_per_frame"], 1)
    return out, (v0, top, nrm, faces)


# ---------------------------------------------------------------------------------------------
# The demo sequence: warm start and solver budget (the pipeline's lift stage, per frame)

SEQUENCE_SOLVERS = {  # name -> SolverConfig: iteration budgets and the default
    "gn_it2": L.SolverConfig(max_iters=2),
    "gn_it4": L.SolverConfig(max_iters=4),
    "gn_default": L.SolverConfig(),
}
SEQUENCE_REFERENCE = L.SolverConfig(max_iters=40, tol=1e-7, cg_tol=1e-4, cg_max_iters=100)


def sequence_pareto(frames: int) -> dict:
    """Lift the demo skirt's enhanced maps frame by frame, cold and warm-started, for every
    solver budget of `SEQUENCE_SOLVERS`: ms/frame, iterations, and the error against a
    tightly converged solve of each frame (RMS and max vertex distance, mm; energy excess,
    relative) and against the targets (mean normal angle, degrees).

    The configurations alternate frame by frame (frame t for every configuration, then
    t + 1), so the load of this shared machine hits all alike; each carries its own warm
    state. The first frame of a warm run is a cold start and is included.
    """
    from wrinkle_jax import enhancer, meshio, pipeline, stages, timing
    from wrinkle_jax.cli import _demo_sequence_path

    seq = meshio.load_sequence(_demo_sequence_path())
    model = enhancer.load_enhancer()
    sel = list(range(min(frames, len(seq))))
    material = seq.metadata.get("material") or "silk_charmeuse"
    maps = pipeline.enhance_sequence(seq, material, enhancer=model, lift=False,
                                     frames=sel).normal_maps
    pipe = pipeline.make_pipeline(seq.garment, model, pipeline.PipelineConfig(), compile=False)
    static = dict(layout=pipe.plan.layout, weights=pipe.config.weights,
                  resolve=pipe.config.resolve, phi=float(pipe.config.phi))
    nv = pipe.fine_garment.num_vertices
    faces = pipe.fine_garment.faces

    def lift(t, local, solver):
        return stages._lift_frame_warm(jnp.asarray(seq.frames[t]), jnp.asarray(maps[t]), local,
                                       pipe.subdivision, pipe.fine_garment, pipe.topology,
                                       None, solver=solver, **static)

    zeros = jnp.zeros((nv, 3), jnp.float32)
    ref = [lift(t, zeros, SEQUENCE_REFERENCE) for t in sel]
    print("reference solves done", file=sys.stderr, flush=True)
    targets = [L.sample_target_normals(jnp.asarray(m), pipe.fine_garment, pipe.plan.layout)
               for m in maps]
    runs = [(name, warm) for name in SEQUENCE_SOLVERS for warm in (False, True)]
    carried = {r: zeros for r in runs}
    rows = {r: {"ms": [], "iterations": [], "rms_mm": [], "max_mm": [], "energy_excess": [],
                "angle_deg": []} for r in runs}
    for r in runs:  # compile and run once (frame 0, cold) before anything is timed
        jax.block_until_ready(lift(0, zeros, SEQUENCE_SOLVERS[r[0]]))
    load_before = timing.load_average()
    for t in sel:
        print(f"frame {t}", file=sys.stderr, flush=True)
        for r in runs:
            t0 = time.perf_counter()
            p, local, info = jax.block_until_ready(lift(t, carried[r], SEQUENCE_SOLVERS[r[0]]))
            ms = 1e3 * (time.perf_counter() - t0)
            if r[1]:
                carried[r] = local
            d = np.linalg.norm(np.asarray(p) - np.asarray(ref[t][0]), axis=1) * 1e3
            e_ref = float(ref[t][2].energy)
            row = rows[r]
            row["ms"].append(ms)
            row["iterations"].append(int(info.iterations))
            row["rms_mm"].append(float(np.sqrt(np.mean(d * d))))
            row["max_mm"].append(float(d.max()))
            row["energy_excess"].append((float(info.energy) - e_ref) / max(abs(e_ref), 1e-30))
            row["angle_deg"].append(float(L.normal_angle_error(p, faces, targets[t])))
    out = {}
    for (name, warm), row in rows.items():
        cfg = SEQUENCE_SOLVERS[name]
        out[f"{name}_{'warm' if warm else 'cold'}"] = {
            "max_iters": cfg.max_iters, "tol": cfg.tol, "warm_start": warm,
            "ms_per_frame_median": round(statistics.median(row["ms"]), 1),
            "ms_per_frame_mean": round(float(np.mean(row["ms"])), 1),
            "iterations_mean": round(float(np.mean(row["iterations"])), 2),
            "rms_to_converged_mm_mean": round(float(np.mean(row["rms_mm"])), 4),
            "max_to_converged_mm_max": round(float(np.max(row["max_mm"])), 3),
            "energy_excess_mean": float(f"{np.mean(row['energy_excess']):.3g}"),
            "angle_error_deg_mean": round(float(np.mean(row["angle_deg"])), 3),
        }
    return {"garment": "demo_skirt", "frames": len(sel), "fine_vertices": nv,
            "reference": {"max_iters": SEQUENCE_REFERENCE.max_iters,
                          "tol": SEQUENCE_REFERENCE.tol,
                          "iterations_mean": float(np.mean([int(r[2].iterations)
                                                            for r in ref])),
                          "angle_error_deg_mean": round(float(np.mean(
                              [L.normal_angle_error(r[0], faces, n)
                               for r, n in zip(ref, targets, strict=True)])), 3)},
            "load_avg_1m": {"before": load_before, "after": timing.load_average()},
            "runs": out}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2k and 10k only, fewer repeats")
    ap.add_argument("--ref-tol", type=float, default=2e-2,
                    help="relative improvement the reference Adam's early stop waits for")
    ap.add_argument("--ref-patience", type=int, default=3,
                    help="iterations without that improvement before the reference stops")
    ap.add_argument("--sequence", action="store_true",
                    help="only the demo sequence: warm start and solver budget per frame")
    ap.add_argument("--frames", type=int, default=8, help="demo frames (--sequence)")
    args = ap.parse_args()
    if args.sequence:
        print(json.dumps({"benchmark": "lift_sequence", **sequence_pareto(args.frames)},
                         indent=1))
        return
    reps = 3 if args.quick else 5
    sizes = (45, 100) if args.quick else (45, 100, 200)
    results, case10k = {}, None
    for cells in sizes:
        res, case = bench_size(cells, reps, args.ref_tol, args.ref_patience, gn_probe=4)
        results[f"{res['vertices']}"] = res
        if cells == 100:
            case10k = case
    curves, summary = {}, {}
    if case10k is not None:
        n_adam, n_gn, n_lbfgs = (100, 4, 60) if args.quick else (150, 8, 100)
        curves = {
            "vertices": 10201,
            "columns": CURVE_COLUMNS,
            "adam_lr0.1": curve(*case10k, L.SolverConfig(method="adam"), n_adam),
            "gauss_newton": curve(*case10k, L.SolverConfig(), n_gn),
            "lbfgs": curve(*case10k, L.SolverConfig(method="lbfgs"), n_lbfgs),
        }
        ref = results["10201"]["reference_adam"]
        matched = results["10201"]["gn_matched"]
        summary = {
            "reference_final": {k: ref[k] for k in ("seconds_per_frame", "iterations",
                                                     "energy", "angle_error_deg")},
            "time_to_reference_error_from_curves": {
                name: _first_reaching(curves[name], ref["energy"], ref["angle_error_deg"])
                for name in ("adam_lr0.1", "gauss_newton", "lbfgs")},
            "gn_per_frame_at_reference_error_s": matched and matched["seconds_per_frame"],
            "gn_speedup_at_reference_error": matched and round(
                ref["seconds_per_frame"] / matched["seconds_per_frame"], 1),
            "gn_speedup_vs_authors_15s": matched and round(
                AUTHORS_S_PER_FRAME_10K / matched["seconds_per_frame"], 1),
        }
        for name in ("adam_lr0.1", "lbfgs"):  # keep every 5th point of the long curves
            curves[name] = curves[name][::5] + curves[name][-1:]
    text = json.dumps({
        "benchmark": "lift",
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                    "jax": jax.__version__, "backend": jax.default_backend(),
                    "load_average_1min": round(os.getloadavg()[0], 2)},
        "authors_reference_10k": {"seconds_per_iteration": AUTHORS_S_PER_ITER_10K,
                                  "seconds_per_frame": AUTHORS_S_PER_FRAME_10K,
                                  "iterations": 52, "dense_laplacian_gib": 0.37},
        "weights": {"eta": L.LiftWeights().eta, "omega": L.LiftWeights().omega,
                    "laplacian_of": L.LiftWeights().laplacian_of,
                    "chord_correction": L.LiftWeights().chord_correction,
                    "normal_at": L.LiftWeights().normal_at},
        "summary_10k": summary,
        "sizes": results,
        "speed_vs_error_10k": curves,
    }, indent=1)
    # Keep innermost number lists (curve points) on one line.
    print(re.sub(r"\[\s+([^\[\]{}]+?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]",
                 text))


if __name__ == "__main__":
    main()
