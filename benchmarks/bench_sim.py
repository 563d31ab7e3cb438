"""Simulator benchmark: ms per frame (30 fps) per scene at PD 10 and 30 mm, speed against
error over substep counts (constraint violation, energy drift, penetration depth), and the
skirts' self-intersections; with --self-collision, ms/frame with and without it per scene
(the data set's setting of the scene, `scenes.self_collision_config`; before session 35 the
resolution's `scenes.SELF_COLLISION` without the scene's own changes; with --variants also
changed settings; the runs advance in alternating chunks) and their ratio to the run without.

    python benchmarks/bench_sim.py [--quick] [--part speed|substeps|intersect|all]
                                   [--scenes a,b] [--data data/sequences] [--self-collision]
                                   [--variants "poke_repair=0.5;thickness=0.006"]

Prints one JSON document. Timings exclude compilation (a warm-up chunk runs first). On a
shared CPU the numbers are upper bounds; `load_avg` is reported alongside.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import colliders as C
from wrinkle_jax.sim import materials as M
from wrinkle_jax.sim import patterns as P
from wrinkle_jax.sim import scenes, selfcollision, xpbd


def bench_speed(scene_names, resolutions, frames: int, material: str = "silk_charmeuse",
                self_collision: tuple = (None,)):
    """ms/frame per scene, resolution and self-collision setting (None = off).

    The settings of one scene and resolution advance chunk by chunk in alternation (the
    order flipped every chunk), so each sees the same machine load; their ratio to the
    first (off) setting is `ratio_to_off`.
    """
    rows = []
    for name in scene_names:
        for res in resolutions:
            setup = scenes.setup_scene(name, res, frames)
            # "default": the data set's setting of this scene (`scenes.self_collision_config`);
            # "default:name=value,...": it with those settings replaced.
            data_set = scenes.self_collision_config(res, setup.scene.substeps, name)
            settings = [sc if sc is None else selfcollision.with_settings(
                            data_set, sc.partition(":")[2]) for sc in self_collision]
            group = _speed_rows(setup, name, res, frames, material, settings)
            for row, sc in zip(group, settings, strict=True):
                if sc is not None and settings[0] is None:
                    row["ratio_to_off"] = round(row["ms_per_frame"] / group[0]["ms_per_frame"],
                                                2)
                row["load_avg"] = [round(a, 2) for a in os.getloadavg()]
                print(json.dumps(row), file=sys.stderr, flush=True)  # progress
            rows += group
    return rows


def _speed_rows(setup, name, res, frames, material, settings):
    params = xpbd.fabric_params(M.fabric(material))
    configs = [xpbd.SimConfig(substeps=setup.scene.substeps,
                              stretch_sweeps=setup.scene.stretch_sweeps, self_collision=sc)
               for sc in settings]
    chunk = 10
    states, compile_s = [], []
    warm = xpbd.slice_drives(setup.drives, 0, chunk + 1)
    for config in configs:
        init_fn, _ = xpbd.cloth_simulator(config)
        t0 = time.perf_counter()
        state, xs = xpbd.run_frames(config, setup.model, params,
                                    init_fn(setup.model, setup.mesh.garment.vertices), warm)
        xs.block_until_ready()
        compile_s.append(time.perf_counter() - t0)
        states.append(state)
    secs = [0.0] * len(configs)
    n = 0
    stop = min(chunk + frames, setup.drives.time.shape[0] - 1)
    for k, start in enumerate(range(chunk, stop, chunk)):
        part = xpbd.slice_drives(setup.drives, start, start + chunk + 1)
        order = range(len(configs)) if k % 2 == 0 else reversed(range(len(configs)))
        for i in order:
            t0 = time.perf_counter()
            states[i], xs = xpbd.run_frames(configs[i], setup.model, params, states[i], part)
            xs.block_until_ready()
            secs[i] += time.perf_counter() - t0
        n += chunk
    return [{"scene": name, "resolution": res, "pd_mm": setup.mesh.pd * 1e3,
             "vertices": setup.mesh.garment.num_vertices,
             "faces": setup.mesh.garment.num_faces,
             "substeps": config.substeps, "stretch_sweeps": config.stretch_sweeps,
             "self_collision": None if sc is None else dataclasses.asdict(sc),
             "self_overflow": None if sc is None else np.asarray(state.self_overflow).tolist(),
             "ms_per_frame": round(1e3 * dt / max(n, 1), 1),
             "compile_plus_first_chunk_s": round(c, 2)}
            for config, sc, state, dt, c in zip(configs, settings, states, secs, compile_s,
                                                strict=True)]


def _energies(xs, vs, model, params):
    """Kinetic and gravitational energy (J) of the free vertices per frame."""
    m = np.asarray(params.density * model.vertex_area * model.free)
    g = -float(params.gravity[2])
    ke = np.array([0.5 * np.sum(m * np.sum(v * v, -1)) for v in vs])
    pe = np.array([np.sum(m * g * x[:, 2]) for x in xs])
    return ke, pe


def bench_substeps(substep_list, pd: float, frames: int):
    """A sheet pinned along one edge swings down from horizontal (no damping, no air), then a
    ball rises through it: strain, energy drift and penetration per substep count."""
    pat = P.sheet_pattern(0.5, 0.5, top=1.0)
    mesh = P.mesh_pattern(pat, pd)
    g = mesh.garment
    top = mesh.landmark_vertices(pat, "top")
    x0 = np.asarray(g.vertices).copy()
    x0[:, 1], x0[:, 2] = x0[:, 2] - 1.0, 1.0
    model = xpbd.build_cloth(g, top, use_aero=False)
    fab = M.fabric("denim_light").replace(damping=0.0)
    params = xpbd.fabric_params(fab)
    n = frames + 1
    centers = np.stack([np.zeros(n), np.full(n, -0.25),
                        np.linspace(0.2, 1.1, n)], 1)[:, None].astype(np.float32)
    col = C.Colliders(sphere_centers=jnp.asarray(centers), sphere_radii=jnp.full((n, 1), 0.1))
    pins = np.broadcast_to(x0[top], (n,) + x0[top].shape)
    rows = []
    for sub in substep_list:
        config = xpbd.SimConfig(substeps=sub)
        init_fn, step_fn = xpbd.cloth_simulator(config)
        step = jax.jit(step_fn)
        results = {}
        for label, colliders in (("swing", C.Colliders()), ("ball", col)):
            drives = xpbd.Drive(time=jnp.arange(n, dtype=jnp.float32) / 30, pins=jnp.asarray(pins),
                                colliders=colliders, extra_damping=jnp.zeros(n))
            state = init_fn(model, x0)
            d = [jax.tree_util.tree_map(lambda a, k=k: a[k], drives) for k in range(n)]
            state = step(model, params, state, d[0], d[1])  # compile
            state = init_fn(model, x0)
            xs, vs = [x0], [np.zeros_like(x0)]
            t0 = time.perf_counter()
            for k in range(frames):
                state = step(model, params, state, d[k], d[k + 1])
                xs.append(np.asarray(state.x))
                vs.append(np.asarray(state.v))
            results[label] = (time.perf_counter() - t0, xs, vs)
        dt, xs, vs = results["swing"]
        strain = np.concatenate([np.abs(np.asarray(xpbd.edge_strain(model, jnp.asarray(x))))
                                 for x in xs[1:]])
        ke, pe = _energies(xs, vs, model, params)
        energy = ke + pe
        scale = max(pe[0] - pe.min(), 1e-12)  # potential energy released by the swing
        _, bx, _ = results["ball"]
        pen = [float(-C.signed_distance(jnp.asarray(bx[k + 1]),
                                        C.frame_colliders(col, k + 1)).min())
               for k in range(frames)]
        rows.append({
            "substeps": sub, "ms_per_frame": round(1e3 * dt / frames, 2),
            "strain_p99": float(np.percentile(strain, 99)),
            "strain_mean": float(strain.mean()),
            # (KE + PE) change relative to the released potential energy: negative = the
            # numerical dissipation of one-sweep XPBD (no physical damping in this run).
            "energy_drift_rel": float((energy[-1] - energy[0]) / scale),
            "energy_drift_max_rel": float(np.abs(energy - energy[0]).max() / scale),
            "max_penetration_m": max(max(pen), 0.0),
        })
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)  # progress
    return rows


def bench_intersections(data: str, every: int, frames: int):
    """Self-intersections (non-adjacent triangle pairs) of the skirts per frame: from the
    generated sequences in `data` when present, else from fresh coarse runs."""
    from pathlib import Path

    from wrinkle_jax import meshio
    from wrinkle_jax.sim import intersect

    rows = []
    for name in ("skirt_dance", "pleated_skirt_dance2", "skirt_walk", "dress_dance",
                 "cape_walk"):
        found = sorted(Path(data).glob(f"{name}/*.npz"))
        runs = [(p.stem, meshio.load_sequence(p)) for p in found]
        if not runs:
            runs = [(f"silk_charmeuse_coarse_fresh{frames}",
                     scenes.simulate(name, "silk_charmeuse", "coarse", frames=frames))]
        for label, seq in runs:
            t0 = time.perf_counter()
            st = intersect.self_intersection_stats(seq.frames, seq.garment.faces, every)
            rows.append({"scene": name, "run": label, "faces": seq.garment.num_faces,
                         "measured_frames": len(st["frames"]),
                         "frames_with_intersections": st["frames_with_intersections"],
                         "mean_pairs": round(st["mean_pairs"], 1), "max_pairs": st["max_pairs"],
                         "mean_face_fraction": round(st["mean_face_fraction"], 5),
                         "s_per_frame": round((time.perf_counter() - t0) / len(st["frames"]), 3)})
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)  # progress
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse only, few frames")
    ap.add_argument("--part", default="all", choices=["speed", "substeps", "intersect", "all"])
    ap.add_argument("--data", default="data/sequences", help="sequences for --part intersect")
    ap.add_argument("--scenes", default=",".join(scenes.SCENES))
    ap.add_argument("--self-collision", action="store_true",
                    help="--part speed: also time each scene with self-collision "
                         "(the data set's setting of each scene; ratio_to_off per row)")
    ap.add_argument("--variants", default="",
                    help="with --self-collision: also time these changes of that setting, "
                         "';'-separated 'name=value,...' (e.g. 'poke_repair=0.5'), alternating "
                         "with the others")
    args = ap.parse_args(argv)
    out = {"jax": jax.__version__, "devices": [str(d) for d in jax.devices()],
           "cpu_count": os.cpu_count(), "load_avg_start": os.getloadavg()}
    names = [s for s in args.scenes.split(",") if s]
    if args.part in ("speed", "all"):
        out["speed"] = bench_speed(names, ["coarse"] if args.quick else ["coarse", "fine"],
                                   frames=10 if args.quick else 30,
                                   self_collision=(None, "default", *(
                                       f"default:{v}" for v in args.variants.split(";") if v))
                                   if args.self_collision else (None,))
    if args.part in ("substeps", "all"):
        out["substeps"] = bench_substeps([5, 10, 20] if args.quick else [5, 10, 20, 40, 80],
                                         pd=0.03 if args.quick else 0.02,
                                         frames=15 if args.quick else 45)
        out["substeps_setup"] = ("0.5 m denim sheet pinned on one edge, released horizontal, "
                                 "no damping/air; 'ball' run: a 0.1 m ball rises through it")
    if args.part in ("intersect", "all"):
        out["self_intersections"] = bench_intersections(args.data, every=10 if args.quick else 5,
                                                        frames=60 if args.quick else 150)
    out["load_avg_end"] = os.getloadavg()
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
