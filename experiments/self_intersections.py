"""How often the simulated garments self-intersect.

    python -m experiments.self_intersections [--every 30] [--material silk_charmeuse]
        [--resolution fine|coarse] [--scenes NAME ...] [--out PATH]

For each scene's generated sequence of one material and resolution (`data/sequences`, from
`experiments.make_sequences`; the training scenes' coarse ones from
`experiments.make_coarse_training_sequences`; the validation scene's and the test scenes'
from `make_sequences`), counts intersecting non-adjacent triangle pairs
every `--every` frames (`sim.intersect.self_intersection_stats`), and records the solver
settings from each file's metadata (substeps, self-collision). `--scenes` measures only those
(e.g. the files a regeneration has just written; default: every training, validation and test
scene). Writes
`experiments/results/sim/self_intersections.json` (fine; `--out` for another) and prints a table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from wrinkle_jax import meshio
from wrinkle_jax.evaluation import cells, suite
from wrinkle_jax.sim import intersect, scenes

ROOT = Path(__file__).resolve().parents[1]
ALL_SCENES = scenes.TRAINING_SCENES + scenes.VAL_SCENES + scenes.TEST_SCENES


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--material", default="silk_charmeuse")
    ap.add_argument("--every", type=int, default=30)
    ap.add_argument("--resolution", choices=("fine", "coarse"), default="fine")
    ap.add_argument("--scenes", nargs="+", choices=ALL_SCENES, default=list(ALL_SCENES))
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "sim"
                                         / "self_intersections.json"))
    args = ap.parse_args(argv)
    rows = {}
    for name in args.scenes:
        path = cells.sequence_file(args.sequences, name, args.material, args.resolution,
                                   scenes.dataset_seed(name))
        if not path.exists():
            print(f"{name}: {path} missing, skipped")
            continue
        seq = meshio.load_sequence(path)
        st = intersect.self_intersection_stats(np.asarray(seq.frames), seq.garment.faces,
                                               every=args.every)
        meta = seq.metadata
        rows[name] = {"faces": int(len(seq.garment.faces)), "num_frames": len(seq),
                      "substeps": meta.get("substeps"),
                      "self_collision": meta.get("self_collision") is not None,
                      "generator": meta.get("generator"), **st}
        print(f"{name:22s} faces {rows[name]['faces']:6d}  frames with any "
              f"{st['frames_with_intersections']:.0%}  mean pairs {st['mean_pairs']:.0f}  "
              f"max {st['max_pairs']}  faces involved {100 * st['mean_face_fraction']:.2f}% "
              f"(worst frame {100 * st['max_face_fraction']:.2f}%)",
              flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"material": args.material, "every": args.every,
                                          "resolution": args.resolution,
                                          "sequences": suite.portable_path(args.sequences),
                                          "scenes": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
