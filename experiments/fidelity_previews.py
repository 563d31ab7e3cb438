"""Previews a person can judge: coarse simulation | ours | fine simulation, one frame per cell.

    python -m experiments.fidelity_previews [--model PATH] [--frame 120] \
        [--out experiments/results/fidelity/previews]

For dress_dance and cape_walk in silk_charmeuse and denim_light (Table 1's held-out
simulations: seed 1, --frames 200; simulated into data/table1_sequences/ when missing), writes
per cell

  <scene>__<material>__meshes.png   coarse mesh | ours (the enhanced map lifted to a detailed
                                    mesh by the pipeline) | fine mesh; one camera fitted to the
                                    coarse frame, 3 panels of --panel pixels
  <scene>__<material>__normals.png  coarse map | enhanced map | fine map: the same --crop
                                    texels (2 mm each) of all three, upscaled nearest to --panel

and index.json (cells, frame, model, panel sizes, crops; project-relative paths).

The coarse and fine meshes are baked on one grid (`aligned.aligned_pair`) and the pipeline is
built on that same layout (`pipeline.make_pipeline(layout=...)`), so the enhanced map needs no
resampling: the crop is the same texels, i.e. the same cloth, in every map
(`wrinkle_jax.compare`). The crop is the window of most garment texels nearest the garment's
centroid.
"""

from __future__ import annotations

import time
from pathlib import Path

from wrinkle_jax import compare, enhancer, render
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import suite

OUT = suite.RESULTS / "fidelity" / "previews"
SCENES = {"dress_dance": ("dress", "dance"), "cape_walk": ("cape", "walk")}


def cells(scenes: list[str], materials: list[str]) -> list[cell_lib.Cell]:
    """The preview cells, scene by scene, then material."""
    bad = [s for s in scenes if s not in SCENES]
    if bad:
        raise ValueError(f"unknown scene {bad[0]!r}; expected one of {', '.join(SCENES)}")
    return [cell_lib.Cell(*SCENES[s], m) for s in scenes for m in materials]


def _load_index(path: Path) -> dict:
    import json

    try:
        return {c["cell"]: c for c in json.loads(path.read_text())["cells"]}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def main(argv=None) -> dict:
    ap = suite.script_parser(__doc__)
    ap.add_argument("--model", default=None, help="enhancer .npz (default: the shipped model)")
    ap.add_argument("--frame", type=int, default=120, help="frame index of every cell")
    ap.add_argument("--frames", type=int, default=200,
                    help="frames of the simulations (Table 1's: a simulation made here is the "
                         "suite's; a longer stored one is reused)")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--materials", default=",".join(cell_lib.TABLE_MATERIALS))
    ap.add_argument("--panel", type=int, default=512, help="pixels per panel side")
    ap.add_argument("--crop", type=int, default=256, help="normal-map crop side, texels")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--sequences", default=str(suite.SEQUENCES),
                    help="folder of existing simulations to reuse")
    ap.add_argument("--sim-out", default=str(suite.TABLE1_SEQUENCES),
                    help="folder for the simulations made here (shared by the suite)")
    args = ap.parse_args(argv)
    frames = args.frames
    if not 0 <= args.frame < frames:
        ap.error(f"--frame {args.frame} must be in [0, --frames {frames})")
    try:
        todo = cells(args.scenes.split(","), args.materials.split(","))
    except ValueError as e:
        ap.error(str(e))
    model_path = Path(enhancer.DEFAULT_PATH if args.model is None else args.model)
    enh = suite.load_model_or_usage_error(ap, model_path)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    index_path = out / "index.json"
    entries = _load_index(index_path)
    for i, cell in enumerate(todo):
        t0 = time.perf_counter()
        seqs = cell_lib.cell_sequences(cell, frames, reuse_roots=(Path(args.sequences),),
                                       out_root=Path(args.sim_out),
                                       log=lambda m: print(m, flush=True))
        fine = cell_lib.load_first_frames(seqs["fine"], frames)
        coarse = cell_lib.load_first_frames(seqs["coarse"], frames)
        t1 = time.perf_counter()
        mesh_labels = (f"coarse simulation (frame {args.frame})", *compare.MESH_LABELS[1:])
        map_labels = (f"coarse map ({args.crop}x{args.crop} texels of "
                      f"{enh.config.texel_size * 1e3:g} mm)", *compare.MAP_LABELS[1:])
        prev = compare.fidelity_previews(
            coarse.garment, coarse.frames[args.frame], fine.garment, fine.frames[args.frame],
            enh, cell.material, panel=args.panel, crop=args.crop, mesh_labels=mesh_labels,
            map_labels=map_labels)
        stem = f"{cell.scene.name}__{cell.material}"
        files = {"meshes": out / f"{stem}__meshes.png", "normals": out / f"{stem}__normals.png"}
        render.write_png(files["meshes"], prev.meshes)
        render.write_png(files["normals"], prev.normals)
        seconds = time.perf_counter() - t0
        entries[cell.key] = {
            "cell": cell.key, "scene": cell.scene.name, "material": cell.material,
            "kind": cell.kind, "frame": args.frame,
            "sequences": {k: suite.portable_path(seqs[k]) for k in ("coarse", "fine")},
            "meshes": {"file": suite.portable_path(files["meshes"]),
                       "size": list(prev.meshes.shape[:2]), "panels": 3,
                       "panel_size": [args.panel, args.panel],
                       "labels": list(mesh_labels),
                       "vertices": prev.vertex_counts},
            "normals": {"file": suite.portable_path(files["normals"]),
                        "size": list(prev.normals.shape[:2]), "panels": 3,
                        "panel_size": [args.panel, args.panel],
                        "labels": list(map_labels),
                        "crop_origin_texels": list(prev.crop_origin),
                        "crop_texels": prev.crop, "texel_size_m": prev.texel_size,
                        "map_size_texels": [prev.layout.height, prev.layout.width]},
            "seconds": {"sequences": round(t1 - t0, 2),  # load (or simulate) and load
                        "previews": round(seconds - (t1 - t0), 2)},
        }
        print(f"[{i + 1}/{len(todo)}] {cell.key} frame {args.frame}: {files['meshes']}, "
              f"{files['normals']} ({seconds:.0f} s)", flush=True)
    index = {"frame": args.frame, "model": suite.portable_path(model_path),
             "model_digest": suite.file_digest(model_path), "panel": args.panel,
             "crop_texels": args.crop, "cells": list(entries.values())}
    suite.write_json(index_path, index)
    return index


if __name__ == "__main__":
    main()
