"""Coarse (PD 30 mm) simulations of the TRAINING scenes, for the material classifier and the
real coarse/fine pair data set (`experiments.make_pair_dataset`).

    nice -n 10 python -m experiments.make_coarse_training_sequences [--out data/sequences] \
        [--frames 300] [--scenes sheet_balls_wind ...] [--substeps 80] [--self-collision on|off]

The classifier sees coarse normal maps at test time; `experiments.make_sequences` only
simulates the training scenes at fine resolution. This writes
`<out>/<scene>/<material>_coarse_s0.npz` for every training scene and material (seed 0: the
same motion as the fine training sequences), one at a time, skipping files that exist and
files another run is simulating (each is claimed first, as in `experiments.make_sequences`, so
two runs can share the list); each file is written atomically. At the data set's coarse
settings (80 substeps, self-collision) a coarse frame costs ~0.11-0.16 s (the test scenes'
coarse files, session 28), so the 45 sequences of 300 frames take about half an hour of one
core. 300 frames is what the earlier data sets had (sessions 21-27) and what the README's data
commands run: the pair data set pairs the first min(coarse, fine) frames, so its size and the
stored training runs stay comparable although the fine training files now hold 600 frames.
The test scenes are never touched here.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from wrinkle_jax import MATERIALS
from wrinkle_jax.fileio import claim_output
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenes", nargs="+", default=list(scenes.TRAINING_SCENES))
    ap.add_argument("--substeps", type=int, default=scenes.DATASET_COARSE_SUBSTEPS)
    ap.add_argument("--self-collision", choices=("on", "off"), default="on")
    args = ap.parse_args(argv)
    contacts = (scenes.self_collision_config("coarse", args.substeps)
                if args.self_collision == "on" else None)
    out = Path(args.out)
    for name in args.scenes:
        if scenes.get_scene(name).test_only:
            raise SystemExit(f"{name} is a test scene; it must not be used for training")
        setup = None
        for mat in MATERIALS:
            path = out / name / f"{mat}_coarse_s{args.seed}.npz"
            # Claimed, so two runs (one per core) can share the list.
            with claim_output(out, path) as mine:
                if not mine:
                    print(f"skip {path} (another process is simulating it)", flush=True)
                    continue
                if path.exists():
                    print(f"skip {path} (exists)", flush=True)
                    continue
                t0 = time.perf_counter()
                if setup is None:  # one mesh, model and compiled solver per scene
                    setup = scenes.setup_scene(name, "coarse", args.frames, args.seed)
                seq = scenes.simulate(setup.scene, mat, "coarse", args.frames, args.seed,
                                      setup=setup, substeps=args.substeps,
                                      self_collision=contacts)
                path.parent.mkdir(parents=True, exist_ok=True)
                scenes.save_simulation(path, seq)
            print(f"wrote {path} ({seq.garment.num_vertices} vertices, {len(seq)} frames) in "
                  f"{time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
