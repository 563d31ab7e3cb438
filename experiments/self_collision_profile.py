"""Where self-collision's time goes: one candidate build and one substep's projection,
stage by stage, on poses of a scene simulated without self-collision.

    python -m experiments.self_collision_profile [--scene skirt_dance] [--resolution fine]
        [--frames 40] [--poses 40,80] [--repeat 5] [--block G] [--raw-per-vertex R]
        [--box-per-vertex B] [--pairs-per-vertex P]

Simulates the pre-roll and `--frames` frames without self-collision (its layers touch and
cross), then at each pose in `--poses` (frame indices, pre-roll included) times jitted stages
with `block_until_ready`, the minimum of `--repeat` calls after a compiling one: the flat
build (`selfcollision.build_pairs`, session 17's fine default) whole, and the blocked build
(`scenes.SELF_COLLISION[resolution]`, or with the bounds given) whole and by stage: grid
and reads plus sphere tests (`block_hits`), the bounded selection (`_select2`); then the
substep's stages on the blocked build's contacts (`contact_frame`, one `project_pairs`
pass). The load average is printed beside every pose (the machine is shared).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import materials as M
from wrinkle_jax.sim import scenes, xpbd
from wrinkle_jax.sim import selfcollision as S
from wrinkle_jax.sim import selfcollision_blocks as SB


def best_ms(fn, *args, repeat: int = 5):
    """Minimum wall time (ms) of `repeat` calls after a first (compiling) one; the result."""
    out = jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return 1e3 * min(times), out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="skirt_dance")
    ap.add_argument("--resolution", default="fine")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--poses", default="40,80")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--block", type=int)
    ap.add_argument("--raw-per-vertex", type=float)
    ap.add_argument("--box-per-vertex", type=float)
    ap.add_argument("--pairs-per-vertex", type=float)
    args = ap.parse_args(argv)
    setup = scenes.setup_scene(args.scene, args.resolution, args.frames)
    config = xpbd.SimConfig(substeps=setup.scene.substeps,
                            stretch_sweeps=setup.scene.stretch_sweeps)
    params = xpbd.fabric_params(M.fabric("silk_charmeuse"))
    state = xpbd.cloth_simulator(config)[0](setup.model, setup.mesh.garment.vertices)
    _, xs = xpbd.simulate_frames(config, setup.model, params, state, setup.drives)
    faces, topo = setup.model.faces, setup.model.self_topo
    over = {k: getattr(args, k) for k in ("block", "raw_per_vertex", "box_per_vertex",
                                          "pairs_per_vertex") if getattr(args, k) is not None}
    cfg = dataclasses.replace(scenes.SELF_COLLISION[args.resolution], **over)
    if cfg.block < 1 or cfg.raw_per_vertex <= 0:
        raise SystemExit("the blocked build needs --block >= 1 and --raw-per-vertex > 0")
    flat = dataclasses.replace(cfg, block=0, raw_per_vertex=480.0, box_per_vertex=32.0)
    num_v = xs.shape[1]
    n_box = S._budget(cfg.box_per_vertex, num_v)
    reach = cfg.thickness + cfg.margin
    stages = {
        "flat build (session 17)": jax.jit(lambda x: S.build_pairs(x, faces, topo, flat)),
        "blocked build": jax.jit(lambda x: SB.build_pairs_blocked(x, faces, topo, cfg)),
        "  grid + reads + sphere tests": jax.jit(lambda x: SB.block_hits(x, faces, topo, cfg)),
    }
    select = jax.jit(lambda hit, low: SB._select2(hit, low, n_box, reach))
    frame = jax.jit(lambda x, pairs: S.contact_frame(x, faces, pairs))
    project = jax.jit(lambda x, w, pairs, fr: S.project_pairs(x, w, pairs, fr))
    w = setup.model.free / (params.density * setup.model.vertex_area)
    print(f"{args.scene} {args.resolution}: V {num_v}, F {faces.shape[0]}, setting {cfg}")
    for i in [int(a) for a in args.poses.split(",")]:
        x = jnp.asarray(xs[i])
        print(f"pose {i} (load {os.getloadavg()[0]:.1f})")
        out = {}
        for name, fn in stages.items():
            ms, out[name] = best_ms(fn, x, repeat=args.repeat)
            print(f"  {name}: {ms:.0f} ms", flush=True)
        hit, low, *_, unread = out["  grid + reads + sphere tests"]
        ms, _ = best_ms(select, hit, low, repeat=args.repeat)
        print(f"  bounded selection of {int(hit.sum())} sphere hits ({hit.size} tested "
              f"entries, {int(unread)} reads not made): {ms:.0f} ms")
        pairs, over = out["blocked build"]
        flat_pairs, flat_over = out["flat build (session 17)"]
        print(f"  contacts {int(pairs.valid.sum())} of {pairs.valid.shape[0]} slots, overflow "
              f"{np.asarray(over).tolist()} (flat build: {int(flat_pairs.valid.sum())}, "
              f"{np.asarray(flat_over).tolist()})")
        ms, fr = best_ms(frame, x, pairs, repeat=args.repeat)
        print(f"  substep: contact_frame {ms:.1f} ms", end="")
        ms, _ = best_ms(project, x, w, pairs, fr, repeat=args.repeat)
        print(f", one project_pairs pass {ms:.1f} ms (load {os.getloadavg()[0]:.1f})",
              flush=True)


if __name__ == "__main__":
    main()
