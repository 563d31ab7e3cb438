"""Self-collision's added cost per frame, split into candidate builds and per-substep work,
and the builds per frame of the on-motion rebuild (`rebuild_every = 0`).

    python -m experiments.self_collision_frame_cost [--scene skirt_dance] [--resolution fine]
        [--frames 10] [--chunk 2] [--rebuild 4,20,0] [--margin MM] [--out PATH]

Simulates the pre-roll with the resolution's default (`scenes.SELF_COLLISION`), then from that
state `--frames` frames once per setting: off, and the default with each `rebuild_every` of
`--rebuild` (4 = today's default, 20 = one build per frame, 0 = on motion); the settings
advance in alternating chunks in one process, so they see the same load (the first chunk,
compiling, is not timed). Per setting: wall and CPU (process) ms per frame, builds per frame.
With builds b_4 = 5 and b_20 = 1 per frame, one build costs (t_4 - t_20) / 4 and the
per-substep work (contact frames and projections) t_20 - t_off - one build.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import materials as M
from wrinkle_jax.sim import scenes, xpbd


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="skirt_dance")
    ap.add_argument("--resolution", default="fine")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--chunk", type=int, default=2)
    ap.add_argument("--rebuild", default="4,20,0")
    ap.add_argument("--margin", type=float, help="mm (all settings)")
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    seed = 1 if scenes.get_scene(args.scene).test_only else 0
    setup = scenes.setup_scene(args.scene, args.resolution, args.frames + args.chunk, seed)
    base = scenes.SELF_COLLISION[args.resolution]
    if args.margin is not None:
        base = dataclasses.replace(base, margin=args.margin * 1e-3)
    params = xpbd.fabric_params(M.fabric("silk_charmeuse"))
    sub, sweeps = setup.scene.substeps, setup.scene.stretch_sweeps
    names = ["off"] + [f"rebuild_every={r}" for r in args.rebuild.split(",")]
    scs = [None] + [dataclasses.replace(base, rebuild_every=int(r))
                    for r in args.rebuild.split(",")]
    configs = [xpbd.SimConfig(substeps=sub, stretch_sweeps=sweeps, self_collision=s)
               for s in scs]
    # The pre-roll once, with the default on.
    n_pre = setup.preroll_frames
    pre = xpbd.slice_drives(setup.drives, 0, n_pre + 1)
    state0 = xpbd.cloth_simulator(configs[1])[0](setup.model, setup.mesh.garment.vertices)
    state0, _ = xpbd.run_frames(configs[1], setup.model, params, state0, pre)
    x0, v0 = state0.x, state0.v
    states = []
    for cfg in configs:
        s = xpbd.cloth_simulator(cfg)[0](setup.model, x0)
        states.append(s.replace(v=v0))
    wall = np.zeros(len(configs))
    cpu = np.zeros(len(configs))
    builds0 = [None] * len(configs)
    timed = 0
    loads = [os.getloadavg()[0]]
    for c, start in enumerate(range(n_pre, n_pre + args.frames + args.chunk, args.chunk)):
        part = xpbd.slice_drives(setup.drives, start, start + args.chunk + 1)
        order = range(len(configs)) if c % 2 == 0 else reversed(range(len(configs)))
        for i in order:
            t0, p0 = time.perf_counter(), time.process_time()
            states[i], xs = xpbd.run_frames(configs[i], setup.model, params, states[i], part,
                                            jnp.int32(args.chunk))
            np.asarray(xs)  # blocks
            if c > 0:
                wall[i] += time.perf_counter() - t0
                cpu[i] += time.process_time() - p0
            elif states[i].self_overflow is not None and len(states[i].self_overflow) == 4:
                builds0[i] = int(states[i].self_overflow[3])
        if c > 0:
            timed += args.chunk
        loads.append(os.getloadavg()[0])
        print(f"chunk {c}: load {loads[-1]:.1f}", flush=True)
    rows = []
    for i, name in enumerate(names):
        row = {"setting": name, "ms_per_frame": round(1e3 * wall[i] / timed, 1),
               "cpu_ms_per_frame": round(1e3 * cpu[i] / timed, 1)}
        if scs[i] is not None:
            over = np.asarray(states[i].self_overflow).tolist()
            row["overflow"] = over
            r = scs[i].rebuild_every
            row["builds_per_frame"] = (round((over[3] - builds0[i]) / timed, 2) if r == 0
                                       else sub // r)
        rows.append(row)
    out = {"scene": args.scene, "resolution": args.resolution, "frames_timed": timed,
           "start_frame": n_pre, "margin": base.margin, "load": [round(a, 2) for a in loads],
           "rows": rows}
    by = {r["setting"]: r for r in rows}
    if "rebuild_every=4" in by and "rebuild_every=20" in by:
        for k in ("ms_per_frame", "cpu_ms_per_frame"):
            build = (by["rebuild_every=4"][k] - by["rebuild_every=20"][k]) / 4
            out[f"one_build_{k}"] = round(build, 1)
            out[f"per_substep_work_{k}"] = round(by["rebuild_every=20"][k] - by["off"][k]
                                                 - build, 1)
    print(json.dumps(out), flush=True)
    if args.out:
        with open(args.out, "a") as fh:
            fh.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
