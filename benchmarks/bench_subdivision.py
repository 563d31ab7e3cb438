"""Benchmark the lifted mesh's subdivision level: lift error against lift time; prints JSON.

"Model only what the scene needs": the lifted mesh should be no finer than the detail the
normal map holds. For every level L of midpoint subdivision of the demo skirt (the coarse
mesh at L = 0 up to edges of about one texel) this lifts the shipped model's enhanced maps
(cold start, default weights and solver) and reports

  * edge_texels: the lifted mesh's mean edge in texels (the model's texel size);
  * lift_ms: ms per frame of `lift.lift_from_normal_map` (jitted), timed alternately over
    the levels in one run (`timing.alternate`, so load drift hits every level alike), with
    the ratio to the finest level and the load average;
  * error_deg: how much of the map's detail the lifted surface holds: the lifted mesh is
    midpoint-subdivided to the finest level (a linear refinement, so it adds no detail) and
    the mean angle between its vertex normals and the map sampled there is taken; every
    level is thus scored on the same number of surface samples. `unlifted_error_deg` is
    the same score of the upsampled coarse mesh (no lift).

`lift.TEXELS_PER_EDGE` is chosen from this Pareto (`texel_subdivision_level`).

    python benchmarks/bench_subdivision.py [--frames 2] [--reps 3] [--max-vertices 60000]
"""

from __future__ import annotations

import argparse
import json
import platform

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import enhancer, lift, meshio, pipeline, subdivision, timing
from wrinkle_jax.cli import _demo_sequence_path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2, help="demo frames lifted per level")
    ap.add_argument("--reps", type=int, default=3, help="alternating timing rounds")
    ap.add_argument("--max-vertices", type=int, default=60000,
                    help="finest level: the last one at or under this vertex count")
    args = ap.parse_args()
    seq = meshio.load_sequence(_demo_sequence_path())
    enh = enhancer.load_enhancer()
    texel = float(enh.config.texel_size)
    frames = list(range(args.frames))
    res = pipeline.enhance_sequence(seq, seq.metadata.get("material", "silk_charmeuse"),
                                    lift=False, enhancer=enh, frames=frames)
    maps = [jnp.asarray(m) for m in res.normal_maps]
    layout = res.layout
    garment = seq.garment
    edge0 = lift.coarse_mean_edge(garment)
    levels = [0]
    while garment.num_faces * 4 ** (levels[-1] + 1) // 2 <= args.max_vertices:
        levels.append(levels[-1] + 1)
    finest = levels[-1]
    solver, weights = lift.SolverConfig(), lift.LiftWeights()
    out = dict(benchmark="subdivision", garment="demo_skirt", texel_size_m=texel,
               coarse_edge_mm=round(1e3 * edge0, 3), frames=len(frames),
               solver=solver.method, platform=platform.platform(), levels=[])
    runs, evals = {}, {}
    for level in levels:
        fine, sub = lift.upsample(garment, levels=level)
        top = lift.lift_topology(fine.faces, fine.num_vertices)
        fine = jax.tree.map(jnp.asarray, fine)
        fn = jax.jit(lift.lift_from_normal_map, static_argnames=("layout", "weights", "solver"))

        def run(fn=fn, sub=sub, fine=fine, top=top):
            return [fn(jnp.asarray(seq.frames[t]), sub, fine, top, maps[i], layout=layout,
                       weights=weights, solver=solver) for i, t in enumerate(frames)]

        runs[f"L{level}"] = run
        # The common evaluation mesh: this level refined (linearly) to the finest level.
        rest = subdivision.build(fine, finest - level, "midpoint")
        evals[level] = (fine, sub, rest, rest.garment(fine))
    t = timing.alternate(runs, reps=args.reps)
    for level in levels:
        fine, sub, rest, ev = evals[level]
        lifted = runs[f"L{level}"]()
        err, err0 = [], []
        for i, tt in enumerate(frames):
            target = lift.sample_target_normals(maps[i], ev, layout)
            p = rest.apply(lifted[i])
            p0 = rest.apply(sub.apply(jnp.asarray(seq.frames[tt])))
            err.append(float(lift.normal_angle_error(p, ev.faces, target)))
            err0.append(float(lift.normal_angle_error(p0, ev.faces, target)))
        edge = edge0 / 2**level
        out["levels"].append(dict(
            level=level, vertices=int(fine.num_vertices), edge_mm=round(1e3 * edge, 3),
            edge_texels=round(edge / texel, 2),
            lift_ms=round(1e3 * t.wall[f"L{level}"] / len(frames), 1),
            time_ratio_to_finest=round(t.ratio(f"L{level}", f"L{finest}"), 3),
            error_deg=round(float(np.mean(err)), 3),
            unlifted_error_deg=round(float(np.mean(err0)), 3)))
    out["load_average"] = [t.load_before, t.load_after]
    out["auto_level"] = lift.texel_subdivision_level(edge0, texel)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
