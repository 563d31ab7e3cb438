"""Simulate the coarse held-out sequences the motion classifier is scored on (resumable).

    nice -n 5 python -m experiments.classifier_sequences [--out data/classifier_sequences]
        [--frames 300] [--seed 1] [--cells dress_dance,cape_walk,skirt_walk,dress_walk,cape_dance]
        [--substeps 80] [--self-collision on|off]

Writes `<out>/<scene>/<material>_coarse_s<seed>.npz` (`scenes.save_simulation`) for every
material of every cell: PD 30 mm, simulated as the data set's coarse sequences are
(`scenes.DATASET_COARSE_SUBSTEPS` substeps, `scenes.self_collision_config`; the settings are in
each file's metadata, and `experiments.classifier_motion` refuses a mix). `dress_walk` and
`cape_dance` are the dress and cape with the motion replaced (`evaluation.cells.scene_for`).
Existing files are skipped, and so are files another run is simulating (each is claimed
first, as in `experiments.make_sequences`); one mesh and solver model per scene serve all five
materials. These garments and motions are never used to choose features or models (the
classifier is selected by leave-one-garment-out cross-validation on the training scenes);
they only score the final choice.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from wrinkle_jax import MATERIALS
from wrinkle_jax.evaluation import cells
from wrinkle_jax.fileio import claim_output
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]
CELLS = ("dress_dance", "cape_walk", "skirt_walk", "dress_walk", "cape_dance")
_GARMENT = {"dress": "dress", "cape": "cape", "skirt": "flared_skirt"}


def scene_config(cell: str) -> scenes.SceneConfig:
    """The scene of a "<garment>_<motion>" cell name (an existing scene or a derived one)."""
    if cell in scenes.SCENES:
        return scenes.get_scene(cell)
    short, motion = cell.split("_", 1)
    return cells.scene_for(_GARMENT[short], motion)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "data" / "classifier_sequences"))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cells", default=",".join(CELLS))
    ap.add_argument("--substeps", type=int, default=scenes.DATASET_COARSE_SUBSTEPS)
    ap.add_argument("--self-collision", choices=("on", "off"), default="on")
    args = ap.parse_args(argv)
    contacts = (scenes.self_collision_config("coarse", args.substeps)
                if args.self_collision == "on" else None)
    out = Path(args.out)
    for cell in args.cells.split(","):
        sc = scene_config(cell)
        todo = [m for m in MATERIALS
                if not (out / sc.name / f"{m}_coarse_s{args.seed}.npz").exists()]
        if not todo:
            continue
        setup = scenes.setup_scene(sc, "coarse", args.frames, args.seed)
        for mat in todo:
            path = out / sc.name / f"{mat}_coarse_s{args.seed}.npz"
            # Claimed, so two runs (one per core) can share the list.
            with claim_output(out, path) as mine:
                if not mine or path.exists():
                    print(f"skip {path} ({'exists' if mine else 'another run has it'})",
                          flush=True)
                    continue
                t0 = time.perf_counter()
                seq = scenes.simulate(sc, mat, "coarse", frames=args.frames, seed=args.seed,
                                      setup=setup, substeps=args.substeps,
                                      self_collision=contacts)
                path.parent.mkdir(parents=True, exist_ok=True)
                scenes.save_simulation(path, seq)
            print(f"{path} {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
