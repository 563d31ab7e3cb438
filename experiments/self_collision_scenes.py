"""Self-collision in the data-set scenes: intersecting faces and cost, off against on.

    python -m experiments.self_collision_scenes [--scenes a,b] [--resolutions fine,coarse]
        [--frames 90] [--every 6] [--material silk_charmeuse] [--thickness MM] [--margin MM]
        [--rebuild-every N] [--max-raw R] [--max-contacts K] [--max-box B]
        [--rest-exclusion MM] [--pairs-per-vertex P] [--raw-per-vertex R]
        [--box-per-vertex B] [--block G] [--passes N] [--post-passes N] [--out PATH]
        [--log PATH]

For each scene of `sim.scenes` and resolution, simulates the pre-roll and the first `--frames`
frames of the motion twice in one process, with self-collision off and on (the same frames,
mesh and drives), advancing the two runs chunk by chunk in alternation so both see the same
machine load. Every `--every`-th returned frame is checked by the independent `sim.intersect`:
the fraction of faces in an intersecting non-adjacent pair (mean, max, frames with any), and
the intersecting pair count. Also reports the candidate overflow and ms/frame of each run
(compilation excluded: the first chunk is not timed) with the load average.

The settings when on: `--thickness` etc. override the resolution's default
(`scenes.SELF_COLLISION[resolution]`). Rows are appended to `--log` as they finish (JSON
lines) and the table is written to `--out` (default
experiments/results/sim/self_collision_scenes.json, rewritten after every row; its rows of
other scenes and resolutions are kept, so the scenes can be run one at a time).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from wrinkle_jax.fileio import atomic_write_text
from wrinkle_jax.sim import intersect, scenes, xpbd
from wrinkle_jax.sim import materials as M

ROOT = Path(__file__).resolve().parents[1]


def face_stats(frames, faces) -> dict:
    """Intersecting-face fraction per measured frame (frames (T, V, 3), faces (F, 3))."""
    frac, pairs = [], []
    for x in frames:
        p = intersect.intersecting_pairs(x, faces)
        pairs.append(int(len(p)))
        frac.append(len(np.unique(p)) / len(faces))
    frac_a = np.asarray(frac)
    return {"face_fraction_mean": round(float(frac_a.mean()), 5),
            "face_fraction_max": round(float(frac_a.max()), 5),
            "frames_with_any": round(float(np.mean(frac_a > 0)), 3),
            "pairs_mean": round(float(np.mean(pairs)), 1), "pairs_max": int(max(pairs)),
            "face_fraction": [round(f, 5) for f in frac]}


def run_pair(setup, material, sc, chunk):
    """Simulate the setup's drives with self-collision off and on, alternating chunks.

    Returns: frames (T, V, 3) of each run (returned frames only), ms/frame of each run after
    the first chunk, and the final overflow [cell entries, box hits or contacts, flat-list
    contacts] of the 'on' run.
    """
    params = xpbd.fabric_params(M.fabric(material))
    sub, sweeps = setup.scene.substeps, setup.scene.stretch_sweeps
    configs = [xpbd.SimConfig(substeps=sub, stretch_sweeps=sweeps, self_collision=s)
               for s in (None, sc)]
    states = []
    for cfg in configs:
        init_fn, _ = xpbd.cloth_simulator(cfg)
        states.append(init_fn(setup.model, setup.mesh.garment.vertices))
    total = setup.drives.time.shape[0] - 1
    outs = [[], []]
    secs = [0.0, 0.0]
    timed = 0
    done = 0
    while done < total:
        n = min(chunk, total - done)
        part = xpbd.slice_drives(setup.drives, done, done + chunk + 1)
        order = (0, 1) if (done // chunk) % 2 == 0 else (1, 0)
        for i in order:
            t0 = time.perf_counter()
            states[i], xs = xpbd.run_frames(configs[i], setup.model, params, states[i], part,
                                            jnp.int32(n))
            xs = np.asarray(xs[:n])  # blocks
            if done > 0:
                secs[i] += time.perf_counter() - t0
            outs[i].append(xs)
            print(f"  {setup.scene.name} {'on' if i else 'off'} frames {done + n}/{total} "
                  f"{time.perf_counter() - t0:.1f} s load {os.getloadavg()[0]:.1f}",
                  file=sys.stderr, flush=True)
        if done > 0:
            timed += n
        done += n
    keep = setup.preroll_frames - 1
    frames = [np.concatenate(o)[keep:] for o in outs]
    ms = [round(1e3 * s / max(timed, 1), 1) for s in secs]
    return frames, ms, np.asarray(states[1].self_overflow).tolist()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(scenes.SCENES))
    ap.add_argument("--resolutions", default="fine,coarse")
    ap.add_argument("--material", default="silk_charmeuse")
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--every", type=int, default=6)
    ap.add_argument("--chunk", type=int, default=15)
    ap.add_argument("--thickness", type=float, help="mm")
    ap.add_argument("--margin", type=float, help="mm")
    ap.add_argument("--rebuild-every", type=int)
    ap.add_argument("--max-raw", type=int)
    ap.add_argument("--max-contacts", type=int)
    ap.add_argument("--max-box", type=int)
    ap.add_argument("--rest-exclusion", type=float, help="mm")
    ap.add_argument("--pairs-per-vertex", type=float)
    ap.add_argument("--raw-per-vertex", type=float, help="> 0: the flat build (build_pairs)")
    ap.add_argument("--box-per-vertex", type=float)
    ap.add_argument("--block", type=int, help="> 0: the blocked flat build (selfcollision_blocks)")
    ap.add_argument("--passes", type=int, help="projection passes before the body contacts")
    ap.add_argument("--post-passes", type=int, help="passes after the body contacts")
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "sim"
                                         / "self_collision_scenes.json"))
    ap.add_argument("--log", default=None, help="JSON lines, one per row (default OUT.log)")
    args = ap.parse_args(argv)
    log = Path(args.log or Path(args.out).with_suffix(".log"))
    over = {k: v for k, v in (("thickness", args.thickness and args.thickness * 1e-3),
                              ("margin", args.margin and args.margin * 1e-3),
                              ("rebuild_every", args.rebuild_every),
                              ("max_raw", args.max_raw),
                              ("max_contacts", args.max_contacts),
                              ("max_box", args.max_box),
                              ("rest_exclusion", None if args.rest_exclusion is None
                               else args.rest_exclusion * 1e-3),
                              ("pairs_per_vertex", args.pairs_per_vertex),
                              ("raw_per_vertex", args.raw_per_vertex),
                              ("box_per_vertex", args.box_per_vertex),
                              ("block", args.block),
                              ("passes", args.passes),
                              ("post_passes", args.post_passes)) if v is not None}
    # Rows of other scenes / resolutions already in --out are kept (runs can be split).
    out = Path(args.out)
    rows = json.loads(out.read_text())["rows"] if out.exists() else []
    for name in [s for s in args.scenes.split(",") if s]:
        seed = 1 if scenes.get_scene(name).test_only else 0
        for res in [r for r in args.resolutions.split(",") if r]:
            sc = dataclasses.replace(scenes.SELF_COLLISION[res], **over)
            load0 = os.getloadavg()
            t0 = time.perf_counter()
            setup = scenes.setup_scene(name, res, args.frames, seed)
            (off, on), ms, overflow = run_pair(setup, args.material, sc, args.chunk)
            faces = np.asarray(setup.mesh.garment.faces)
            idx = list(range(0, args.frames, args.every))
            row = {"scene": name, "resolution": res, "material": args.material, "seed": seed,
                   "faces": int(len(faces)), "frames": args.frames, "measured_frames": idx,
                   "self_collision": dataclasses.asdict(sc),
                   "off": {"ms_per_frame": ms[0], **face_stats(off[idx], faces)},
                   "on": {"ms_per_frame": ms[1], "overflow": overflow,
                          **face_stats(on[idx], faces)},
                   "cost_ratio": round(ms[1] / max(ms[0], 1e-9), 2),
                   "load_avg": [round(a, 2) for a in load0],
                   "load_avg_end": [round(a, 2) for a in os.getloadavg()],
                   "wall_s": round(time.perf_counter() - t0, 1)}
            rows = [r for r in rows if (r["scene"], r["resolution"]) != (name, res)] + [row]
            brief = {k: v for k, v in row.items() if k != "measured_frames"}
            for k in ("off", "on"):
                brief[k] = {a: b for a, b in row[k].items() if a != "face_fraction"}
            with log.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(json.dumps(brief), flush=True)
            atomic_write_text(out, json.dumps({"rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
