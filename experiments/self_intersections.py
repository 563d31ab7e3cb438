"""How often the simulated garments self-intersect (the simulator has no self-collision).

    python -m experiments.self_intersections [--every 30] [--material silk_charmeuse]

For each scene's generated FINE sequence of one material (`data/sequences`, from
`experiments.make_sequences`), counts intersecting non-adjacent triangle pairs every `--every`
frames (`sim.intersect.self_intersection_stats`). Writes
`experiments/results/sim/self_intersections.json` and prints a table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from wrinkle_jax import meshio
from wrinkle_jax.sim import intersect, scenes

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--material", default="silk_charmeuse")
    ap.add_argument("--every", type=int, default=30)
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "sim"
                                         / "self_intersections.json"))
    args = ap.parse_args(argv)
    rows = {}
    for name in scenes.TRAINING_SCENES + scenes.TEST_SCENES:
        seed = 0 if name in scenes.TRAINING_SCENES else 1
        path = Path(args.sequences) / name / f"{args.material}_fine_s{seed}.npz"
        if not path.exists():
            print(f"{name}: {path} missing, skipped")
            continue
        seq = meshio.load_sequence(path)
        st = intersect.self_intersection_stats(np.asarray(seq.frames), seq.garment.faces,
                                               every=args.every)
        rows[name] = {"faces": int(len(seq.garment.faces)), **st}
        print(f"{name:22s} faces {rows[name]['faces']:6d}  frames with any "
              f"{st['frames_with_intersections']:.0%}  mean pairs {st['mean_pairs']:.0f}  "
              f"max {st['max_pairs']}  faces involved {100 * st['mean_face_fraction']:.2f}%",
              flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"material": args.material, "every": args.every,
                                          "scenes": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
