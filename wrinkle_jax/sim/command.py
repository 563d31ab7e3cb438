"""The `wrinkle-jax simulate` sub-command (wired into `wrinkle_jax.cli` by the lead).

    wrinkle-jax simulate SCENE --material NAME [--resolution fine|coarse] [--frames N]
                         [--seed S] [--substeps K] --out PATH.npz [--no-progress]

Exit codes: 0 success, 1 failure (bad output path, runtime error), 2 bad usage (argparse).
Writes the sequence (frames, UVs in meters, metadata, pin and collider tracks) atomically and
prints a JSON report (vertices, frames, timings).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (shared by the CLI modules)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _cmd_simulate(args) -> int:
    from wrinkle_jax.mesh import GarmentError
    from wrinkle_jax.sim import scenes
    from wrinkle_jax.sim.patterns import PatternError

    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        print(f"wrinkle-jax simulate: error: {out}: the output must be an .npz file",
              file=sys.stderr)
        return 1
    if out.is_dir():
        print(f"wrinkle-jax simulate: error: {out}: is a directory", file=sys.stderr)
        return 1
    bar = None
    try:
        t0 = time.perf_counter()
        setup = scenes.setup_scene(args.scene, args.resolution,
                                   args.frames or scenes.get_scene(args.scene).frames, args.seed)
        setup_s = time.perf_counter() - t0
        progress = None
        if not args.no_progress:
            from tqdm import tqdm

            bar = tqdm(total=setup.preroll_frames + (args.frames or setup.scene.frames) - 1,
                       unit="frame", desc=f"{args.scene} {args.material} {args.resolution}",
                       file=sys.stderr)

            def progress(done, total):
                bar.update(done - bar.n)

        t0 = time.perf_counter()
        seq = scenes.simulate(setup.scene, args.material, args.resolution, args.frames,
                              args.seed, substeps=args.substeps, progress=progress, setup=setup)
        sim_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        scenes.save_simulation(out, seq)
        write_s = time.perf_counter() - t0
    except (scenes.SceneError, PatternError, GarmentError, ValueError, OSError) as e:
        print(f"wrinkle-jax simulate: error: {e}", file=sys.stderr)
        return 1
    finally:
        if bar is not None:
            bar.close()
    meta = seq.metadata
    report = {
        "output": str(out),
        "scene": meta["scene"],
        "material": meta["material"],
        "resolution": meta["resolution"],
        "pd_m": meta["pd"],
        "frames": len(seq),
        "preroll_frames": meta["preroll_frames"],
        "vertices": meta["vertices"],
        "faces": meta["faces"],
        "substeps": meta["substeps"],
        "seed": meta["seed"],
        "tracks": sorted(seq.tracks),
        "timings": {"setup_s": round(setup_s, 3), "simulate_s": round(sim_s, 3),
                    "ms_per_frame": meta["ms_per_frame"], "write_s": round(write_s, 3)},
    }
    print(json.dumps(report, indent=2))
    return 0


def add_simulate_parser(subparsers) -> argparse.ArgumentParser:
    """Register `simulate` on an argparse sub-parser collection; returns the parser."""
    from wrinkle_jax import MATERIALS
    from wrinkle_jax.sim.scenes import RESOLUTIONS, SCENES

    p = subparsers.add_parser(
        "simulate", help="simulate a cloth scene into an .npz sequence",
        description="Simulate a scene (XPBD cloth on a capsule mannequin, or a sheet with balls "
        "and wind) with one material at PD 10 mm (fine) or 30 mm (coarse). Test-only scenes: "
        + ", ".join(n for n, s in SCENES.items() if s.test_only) + ".")
    p.add_argument("scene", choices=list(SCENES), help="scene name")
    p.add_argument("--material", required=True, choices=list(MATERIALS), help="fabric")
    p.add_argument("--resolution", default="fine", choices=list(RESOLUTIONS),
                   help="fine = PD 10 mm, coarse = PD 30 mm (default: %(default)s)")
    p.add_argument("--frames", type=positive_int, default=None,
                   help="frames at 30 fps after the pre-roll (default: the scene's)")
    p.add_argument("--seed", type=int, default=0, help="motion/ball/wind seed (default: 0)")
    p.add_argument("--substeps", type=positive_int, default=None,
                   help="solver substeps per frame (default: the scene's)")
    p.add_argument("--out", required=True, help="output .npz path")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_simulate)
    return p
