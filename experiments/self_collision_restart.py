"""Where a stored fine run self-intersects, would other solver settings have avoided it?

    python -m experiments.self_collision_restart --scene skirt_walk --material denim_light \
        --start 190 --stop 226 [--variants "recorded;post_passes=3;substeps=40"] [--every 2] \
        [--jitter 1e-6 --repeats 3] [--out PATH]

Continues a data-set file (`data/sequences/<scene>/<material>_<resolution>_s<seed>.npz`) from
its frame `--start` to `--stop` once per variant (`sim.scenes.resimulate`: the stored positions
and a finite-difference velocity, so "recorded", the file's own settings, is the reference the
others are compared with, not the stored frames) and counts the intersecting faces every
`--every` frames (`sim.intersect`). A variant is "recorded" or `name=value[,name=value]` over
`SelfCollisionConfig` fields and `substeps` (a substep count keeps the rebuild interval in time,
as `scenes.self_collision_config` does). Prints one JSON line per variant and writes them all to
`--out` (default: none).

A cloth run is chaotic: two continuations that differ by far less than any setting does can
still peak differently. `--jitter SIGMA --repeats K` runs each variant K times from start frames
moved by Gaussian noise of SIGMA m per coordinate (seeds 1..K, `jitter_start`), so the spread of
the peaks under one setting is measured beside the differences between settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from wrinkle_jax import meshio
from wrinkle_jax.evaluation import cells, suite
from wrinkle_jax.sim import intersect, scenes, selfcollision
from wrinkle_jax.sim.selfcollision import SelfCollisionConfig

ROOT = Path(__file__).resolve().parents[1]


def variant_settings(text: str, recorded: dict, substeps: int) -> tuple[SelfCollisionConfig, int]:
    """("recorded" | "name=value,...") -> (self-collision config, substeps)."""
    cfg = selfcollision.recorded_config(recorded)
    if text == "recorded":
        return cfg, substeps
    rest = []
    for item in text.split(","):
        name, _, value = item.partition("=")
        if name == "substeps":
            n = int(value)  # the rebuild interval kept in time, as the data set's settings
            every = scenes.rebuild_interval(cfg.rebuild_every, substeps, n)
            cfg, substeps = dataclasses.replace(cfg, rebuild_every=every), n
        else:
            rest.append(item)
    try:
        return selfcollision.with_settings(cfg, ",".join(rest)), substeps
    except ValueError as e:
        raise SystemExit(f"{e}; or substeps") from None


def jitter_start(seq: meshio.GarmentSequence, start: int, sigma: float,
                 seed: int) -> meshio.GarmentSequence:
    """seq with its stored frames start - 1 and start (what `scenes.resimulate` starts from:
    positions and velocity) moved by independent N(0, sigma^2) m per coordinate; sigma 0 or
    seed 0: seq itself. The input is left alone (the frames are copied)."""
    if sigma <= 0 or seed == 0:
        return seq
    noise = np.random.default_rng(seed).normal(0.0, sigma, (2, *seq.frames.shape[1:]))
    frames = np.array(seq.frames)  # (T, V, 3) float32
    frames[start - 1:start + 1] += noise.astype(np.float32)
    return dataclasses.replace(seq, frames=frames)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--scene", required=True, choices=sorted(scenes.SCENES))
    ap.add_argument("--material", required=True)
    ap.add_argument("--resolution", choices=("fine", "coarse"), default="fine")
    ap.add_argument("--start", type=int, required=True)
    ap.add_argument("--stop", type=int, required=True)
    ap.add_argument("--variants", default="recorded;post_passes=3")
    ap.add_argument("--every", type=int, default=2)
    ap.add_argument("--jitter", type=float, default=0.0,
                    help="m: Gaussian noise on the start frames (with --repeats)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="runs per variant; with --jitter, seeds 1..K")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    seed = scenes.dataset_seed(args.scene)
    path = cells.sequence_file(args.sequences, args.scene, args.material, args.resolution, seed)
    seq = meshio.load_sequence(path)
    meta = seq.metadata
    if meta.get("self_collision") is None:
        raise SystemExit(f"{path} was simulated without self-collision")
    setup = scenes.setup_scene(args.scene, args.resolution, seq.frames.shape[0], seed)
    faces = np.asarray(seq.garment.faces)
    rows = []
    runs = [(text, rep) for text in args.variants.split(";")
            for rep in (range(1, args.repeats + 1) if args.jitter > 0 else [0])]
    for text, rep in runs:
        cfg, substeps = variant_settings(text, meta["self_collision"], int(meta["substeps"]))
        t0 = time.perf_counter()
        xs, final = scenes.resimulate(jitter_start(seq, args.start, args.jitter, rep), args.start,
                                      args.stop, cfg, substeps, setup=setup, return_state=True)
        wall = time.perf_counter() - t0
        frames = list(range(args.start + 1, args.stop + 1, args.every))
        pct = [100.0 * len(np.unique(intersect.intersecting_pairs(xs[k - args.start - 1], faces)))
               / len(faces) for k in frames]
        row = {"file": str(path.relative_to(path.parents[2])), "variant": text,
               "substeps": substeps, "self_collision": dataclasses.asdict(cfg),
               "jitter_m": args.jitter if rep else 0.0, "jitter_seed": rep,
               "wall_s_with_compile": round(wall, 1), "frames": frames,
               "face_pct": [round(p, 3) for p in pct],
               "max_face_pct": round(max(pct), 3), "mean_face_pct": round(float(np.mean(pct)), 3),
               "self_overflow": np.asarray(final.self_overflow).tolist()}
        print(json.dumps(row), flush=True)
        rows.append(row)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        command = {**vars(args), "sequences": suite.portable_path(args.sequences)}
        Path(args.out).write_text(json.dumps({"command": command, "rows": rows}, indent=1))
    return rows


if __name__ == "__main__":
    main()
