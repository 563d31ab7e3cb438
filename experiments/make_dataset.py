"""Build the enhancer's patch data set from the simulated sequences (resumable, background).

    nohup nice -n 5 python -m experiments.make_dataset [--sequences data/sequences] \
        [--out data/patches] [--wait] > /dev/null 2>&1 &

Training patches come from the FINE simulations of the training scenes (sheet_balls_wind,
skirt_dance, pleated_skirt_dance2; all five materials; seed 0); held-out patches from the FINE
simulations of the test-only scenes (dress_dance and cape_walk: unseen garments; skirt_walk:
unseen motion; seed 1). As in the paper, the network input is the fine map downsampled to
texels of the coarse particle distance (30 mm / 2 mm = 15; `data.PatchDataConfig.coarse_pd`),
so input and target align.
`wrinkle_jax.data` assigns the split from each sequence's metadata (test-only scenes and the
held-out garments/motion are "heldout"), so held-out data cannot reach training.

Sizing: training sequences use every `--train-stride`-th frame (default 6: 100 of 600 frames,
8 crops each -> 800 patches per sequence, ~12k patches, ~2.7 GB of uint16); held-out sequences
every `--heldout-stride`-th (default 10). Sequences already built are skipped; with `--wait`
the script polls for sequences the simulator has not written yet. Progress goes to
`<out>/make_dataset.log`.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from wrinkle_jax import MATERIALS, data, meshio
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]


def sources(seq_root: Path) -> list[tuple[Path, str]]:
    """(path, role) for every sequence the data set wants, training first."""
    out = []
    for name in scenes.TRAINING_SCENES:
        out += [(seq_root / name / f"{m}_fine_s0.npz", "train") for m in MATERIALS]
    for name in scenes.TEST_SCENES:
        out += [(seq_root / name / f"{m}_fine_s1.npz", "heldout") for m in MATERIALS]
    return out


def unique_name(path: Path) -> str:
    # Files are named by material only; the data set names a sequence by scene and material.
    return f"{path.parent.name}__{path.stem}"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--out", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--train-stride", type=int, default=6)
    ap.add_argument("--heldout-stride", type=int, default=10)
    ap.add_argument("--crops", type=int, default=8)
    ap.add_argument("--wait", action="store_true", help="poll for sequences not written yet")
    ap.add_argument("--only", default=None, help="comma-separated scene names")
    args = ap.parse_args(argv)
    seq_root, out = Path(args.sequences), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = open(out / "make_dataset.log", "a", buffering=1)

    def say(msg):
        log.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}\n")

    base = data.PatchDataConfig(crops_per_frame=args.crops)
    configs = {"train": dataclasses.replace(base, frame_stride=args.train_stride),
               "heldout": dataclasses.replace(base, frame_stride=args.heldout_stride)}
    todo = sources(seq_root)
    if args.only:
        keep = set(args.only.split(","))
        todo = [(p, r) for p, r in todo if p.parent.name in keep]
    say(f"start: {len(todo)} sequences -> {out}")
    while todo:
        waiting = []
        for path, role in todo:
            name = unique_name(path)
            if (out / "index" / f"{name}.json").exists():
                continue
            if not path.exists():
                waiting.append((path, role))
                continue
            t0 = time.time()
            seq = meshio.load_sequence(path)
            entry = data.build_sequence(seq, name, out, configs[role])
            n = sum(len(s["frames"]) for s in entry["shards"])
            say(f"built {name} ({entry['split']}, {n} patches) in {time.time() - t0:.0f} s")
            if entry["split"] != role:
                say(f"WARNING: {name} was expected in {role} but landed in {entry['split']}")
        todo = waiting
        if todo and not args.wait:
            say(f"missing {len(todo)} sequences (run again or pass --wait): "
                + ", ".join(unique_name(p) for p, _ in todo))
            break
        if todo:
            time.sleep(60)
    say("done" if not todo else "stopped")


if __name__ == "__main__":
    main()
