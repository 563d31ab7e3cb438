"""Self-collision on the small contact scenes: intersecting triangle pairs per frame (by the
independent `sim.intersect`) and ms/frame with and without self-collision, plus the long
folded-sheet check (300 frames by default).

    python experiments/self_collision.py [--frames 300] [--pd 0.02] [--out PATH]

Writes one JSON document (default experiments/results/sim/self_collision.json).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import contact_scenes as CS
from wrinkle_jax.sim import intersect, xpbd
from wrinkle_jax.sim import materials as M
from wrinkle_jax.sim.selfcollision import SelfCollisionConfig

# Thickness ~0.3 x PD closes the edge-edge gaps between vertex-triangle contacts on these
# meshes (no edge-edge constraints in the solver).
SELF = SelfCollisionConfig(thickness=0.006, margin=0.006, max_raw=256, max_contacts=16)


def run(scene, self_collision, material="silk_charmeuse", chunk=30):
    """Positions (T, V, 3), ms/frame after the first (compiling) chunk, and the overflow."""
    config = xpbd.SimConfig(self_collision=self_collision)
    params = xpbd.fabric_params(M.fabric(material))
    init_fn, _ = xpbd.cloth_simulator(config)
    state = init_fn(scene.model, scene.x0)
    first = xpbd.slice_drives(scene.drives, 0, chunk + 1)
    # num_valid given as in simulate_frames, so the timed chunks reuse this compilation.
    state, xs0 = xpbd.run_frames(config, scene.model, params, state, first, jnp.int32(chunk))
    rest = xpbd.slice_drives(scene.drives, chunk, scene.drives.time.shape[0])
    t0 = time.perf_counter()
    state, xs = xpbd.simulate_frames(config, scene.model, params, state, rest, chunk)
    ms = 1e3 * (time.perf_counter() - t0) / max(len(xs), 1)
    overflow = None if state.self_overflow is None else np.asarray(state.self_overflow).tolist()
    return np.concatenate([np.asarray(xs0), xs]), ms, overflow


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--pd", type=float, default=0.02)
    ap.add_argument("--every", type=int, default=5, help="measure every n-th frame")
    ap.add_argument("--out", default="experiments/results/sim/self_collision.json")
    args = ap.parse_args(argv)
    scenes = {"two_sheets": lambda f: CS.two_sheets(pd=args.pd, frames=f, size=0.2),
              "folded_sheet": lambda f: CS.folded_sheet(pd=args.pd, frames=f, length=0.4,
                                                        width=0.2)}
    rows = []
    for name, make in scenes.items():
        frames = 60 if name == "two_sheets" else args.frames
        scene = make(frames)
        for sc in (None, SELF):
            xs, ms, overflow = run(scene, sc)
            st = intersect.self_intersection_stats(xs, np.asarray(scene.model.faces), args.every)
            rows.append({"scene": name, "pd": args.pd, "frames": frames,
                         "vertices": int(scene.x0.shape[0]),
                         "self_collision": None if sc is None else dataclasses.asdict(sc),
                         "ms_per_frame": round(ms, 1), "overflow": overflow,
                         "frames_with_intersections": st["frames_with_intersections"],
                         "mean_pairs": st["mean_pairs"], "max_pairs": st["max_pairs"],
                         "last_pairs": st["counts"][-1]})
            print(json.dumps(rows[-1]), flush=True)
    out = {"load_avg": os.getloadavg(), "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(args.out).with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=2))
    tmp.replace(args.out)


if __name__ == "__main__":
    main()
