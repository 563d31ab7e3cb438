"""Real coarse-input / fine-target patch pairs of the TRAINING scenes (resumable).

    python -m experiments.make_sequences --only sheet_balls_wind,skirt_dance,pleated_skirt_dance2,\
shawl_dance2,apron_dance,tabard_dance2 --train-frames 300   # fine (+ coarse val scene), seed 0
    python -m experiments.make_coarse_training_sequences --frames 300   # coarse, seed 0
    python -m experiments.make_pair_dataset [--sequences data/sequences] [--out data/pairs]

For every training scene and material, the coarse (PD 30 mm) and the fine (PD 10 mm) simulation
of the same motion are baked on one grid (`wrinkle_jax.evaluation.patchsets`) and cut at the
same random origins (`data.build_pair_sequence`): input = the real coarse map, target = the fine
map. The last `--val-fraction` of each sequence's frames form the "val" split, which the trainer
evaluates on and recipe choices read; the held-out garments and motions are not in this data
set at all. The validation-only scenes (`scenes.VAL_SCENES`: a garment outside both training
and the held-out sets) are written whole as the "valgarment" split, which checkpoint choices
read as a proxy for unseen garments. No dihedral augmentation: flipping the pixel grid of an
object-space normal map makes a field no surface has, and the detail loss compares the
statistics of real maps.
Each index entry records the two files it was cut from (name and SHA-256), and a rerun cuts
again every cell whose files changed (a scene simulated again) or that records none; `--check`
only lists them. Progress goes to `<out>/make_pair_dataset.log`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from wrinkle_jax import MATERIALS, data, meshio
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--out", default=str(ROOT / "data" / "pairs"))
    ap.add_argument("--frame-stride", type=int, default=3)
    ap.add_argument("--crops", type=int, default=8)
    ap.add_argument("--min-coverage", type=float, default=0.3)
    ap.add_argument("--patch-size", type=int, default=data.PatchDataConfig.patch_size)
    ap.add_argument("--texel-size", type=float, default=data.PatchDataConfig.texel_size,
                    help="meters of cloth per texel")
    ap.add_argument("--val-fraction", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--check", action="store_true",
                    help="list the cells that are missing or stale and exit 1 if any; cut none")
    args = ap.parse_args(argv)
    seq_root, out = Path(args.sequences), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    config = data.PatchDataConfig(texel_size=args.texel_size, patch_size=args.patch_size,
                                  crops_per_frame=args.crops, min_coverage=args.min_coverage,
                                  frame_stride=args.frame_stride, augment=False, seed=args.seed)
    with open(out / "make_pair_dataset.log", "a", buffering=1) as log:
        def say(msg):
            log.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}\n")
            print(msg, flush=True)

        missing = todo = 0
        for scene in scenes.TRAINING_SCENES + scenes.VAL_SCENES:
            for mat in MATERIALS:
                name = f"{scene}__{mat}"
                names = [name]
                if args.val_fraction > 0 and scene in scenes.TRAINING_SCENES:
                    names.append(f"{name}__val")
                fine_p = seq_root / scene / f"{mat}_fine_s{args.seed}.npz"
                coarse_p = seq_root / scene / f"{mat}_coarse_s{args.seed}.npz"
                if not (fine_p.exists() and coarse_p.exists()):
                    kept = any((out / "index" / f"{n}.json").exists() for n in names)
                    say(f"missing {fine_p.name if not fine_p.exists() else coarse_p.name} "
                        f"of {scene}; skipped" + ("; its existing cell is kept, unverified"
                                                  if kept else ""))
                    missing += 1
                    continue
                sources = data.pair_sources(fine_p, coarse_p)
                why = data.pair_cell_stale(out, names, sources, config, args.val_fraction)
                if why is None:
                    continue
                todo += 1
                if args.check:
                    say(f"{name}: to cut ({why})")
                    continue
                # Drop the old entries first: a cut stopped half-way leaves no entry that
                # points at overwritten shards.
                for n in names:
                    (out / "index" / f"{n}.json").unlink(missing_ok=True)
                t0 = time.perf_counter()
                entries = data.build_pair_sequence(
                    meshio.load_sequence(fine_p), meshio.load_sequence(coarse_p), name, out,
                    config, val_fraction=args.val_fraction, sources=sources)
                n = {e["split"]: sum(len(s["frames"]) for s in e["shards"]) for e in entries}
                say(f"{name}: {n} patches in {time.perf_counter() - t0:.0f} s ({why})")
        if args.check:
            say(f"check: {todo} cells to cut, {missing} without their simulations")
    return 1 if missing or (args.check and todo) else 0


if __name__ == "__main__":
    raise SystemExit(main())
