"""The pipeline sub-commands of `wrinkle-jax` (`wrinkle_jax.cli`): `enhance` (bake, enhance,
merge, lift, previews, report), `bake` (16-bit normal-map PNGs), and the two runs behind
`demo` (`_run_enhance` with the shipped model, `bake_sequence_to_pngs` without one).

Every check of the input runs before any compile (`wrinkle_jax.validate`); output folders
appear only when complete (`wrinkle_jax.outdir`). Heavy modules (JAX, the pipeline) are
imported inside the functions, so building the command line stays cheap. `cli` re-exports
every name here (old import paths keep working).
"""

from __future__ import annotations

import functools
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


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


def _classify_auto(input_path: Path, materials) -> tuple:
    """`--material auto`: the default classifier's material (the shipped synthesis classifier
    if any, else the motion classifier), or a UsageError naming --material when it abstains
    (never a silent default). Returns (material, MotionClassification, the classifier's kind:
    "synthesis" or "motion")."""
    from wrinkle_jax.classifier import ClassifierError
    from wrinkle_jax.classifier.cli import classify_default
    from wrinkle_jax.validate import UsageError

    names = ", ".join(materials)
    try:
        kind, result = classify_default(input_path)
    except ClassifierError as e:
        raise UsageError(f"--material auto: {e}; pass --material NAME (one of {names})") from None
    if result.abstained:
        raise UsageError(f"--material auto: the material classifier abstained ({result.reason}); "
                         f"pass --material NAME (one of {names})")
    if result.material not in materials:
        raise UsageError(f"--material auto: the classifier chose {result.material!r}, which the "
                         f"model does not know; pass --material NAME (one of {names})")
    return result.material, result, kind


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
            input_path, args, enh.config.texel_size, size,
            args.stride or pipeline.default_stride(size),
            not args.no_lift, template, pipeline.PipelineConfig().target_edge)
        load_s = time.perf_counter() - t0
        material, material_source = validate.choose_material(
            args.material, seq.metadata.get("material"), enh.config.materials,
            display_path(input_path))
        classification = None
        if material == "auto":
            material, classification, classifier_kind = _classify_auto(input_path,
                                                                       enh.config.materials)
        body = _load_body(Path(args.body)) if getattr(args, "body", None) else None
        # Warm-started lift: the same error as cold starts on the demo at ~0.6x the lift time
        # (benchmarks/bench_lift.py --sequence); frames are streamed in order. A chunk's
        # patches share network calls: ~0.9x the network's CPU time per frame at batch 16
        # (benchmarks/bench_pipeline.py --network-sweep); batch 4 then takes 0.90-0.95x
        # batch 8's CPU and batch 16 1.04-1.08x (bench_batch.py --frames-per-batch 4).
        batch = args.batch or pipeline.PipelineConfig.batch_size
        config = pipeline.PipelineConfig(batch_size=batch, chunk_size=args.chunk,
                                         frames_per_batch=args.chunk, stride=args.stride,
                                         lift=not args.no_lift, warm_start=True,
                                         overlap_lift=True)
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
            if classification is not None:
                report["material_scores"] = classification.scores
                report["material_classification"] = {"classifier": classifier_kind,
                                                     **classification.to_json()}
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
    write_obj = meshio.ObjWriter(fine) if fine is not None and fmt != "ply" else None

    def write(frame: pipeline.EnhancedFrame) -> None:
        t = frame.index
        normalmap.save_normal_map_png(maps_dir / f"normal_map_{t:05d}.png", frame.normal_map,
                                      pipe.mask)
        if frame.detailed is not None:
            if fmt == "ply":
                meshio.save_ply(mesh_dir / f"frame_{t:05d}.ply", frame.detailed, fine.faces)
            else:
                write_obj(mesh_dir / f"frame_{t:05d}.obj", frame.detailed)
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


def _print_report(report: dict, args, cmd: str, out: Path) -> None:
    """The report as JSON on stdout with --json; otherwise a one-screen summary on stderr."""
    from wrinkle_jax.outdir import summary

    if getattr(args, "json", False):
        print(json.dumps(report, indent=2))
    else:
        print(summary(report, cmd, out), file=sys.stderr)
