"""Patch-stride ablation: seams and score against time of the full enhancement pass (bake, tile,
U-Net, Hann merge) at tile strides 32, 64 (the default, half a patch) and 96 texels.

    python -m experiments.stride [--model wrinkle_jax/assets/enhancer.npz] [--strides 32,64,96]
        [--frame-every 5] [--out experiments/results/stride]

Data: Table 1's cells and sequences (`experiments.table1`; simulated there, or here if
missing) and Table 1's patches at a subset of its frames: every `--frame-every`-th scored
frame (defaults: frames 0, 50, 100, 150 of 0, 10, ..., 190), with the same seeded draw, so the
"patch" row below is Table 1's model on exactly these patches.

Per cell and stride, `pipeline.make_pipeline` runs on the coarse mesh baked on the SHARED
fine/coarse grid (`evaluation.patchsets.aligned_pair`; `layout=`), so the merged map N* can be
cut at the same cloth as the fine map:

  score   the improvement score (|.| and signed) of N* cut at Table 1's patch origins (and to
          the texels both meshes cover), fine map as target, coarse map as input: what the
          merge keeps of the network's patch-level gain. "patch" = the network on the patch
          itself (no tiling, no merge; Table 1's "model").
  seams   the mean angle (degrees) between the normals of neighbouring garment texels ACROSS a
          tile border (between texel x-1 and x where a tile starts at x or ends at x-1, rows
          and columns) divided by the mean angle between neighbours elsewhere; 1 = the tile
          borders are invisible. The coarse map's ratio at the same positions is the control
          (its borders are not special).
  time    ms per frame of tile + network + merge (the stages stride changes; bake is
          reported too), compile excluded; patches per frame.

Cost: the network runs (128 / stride)^2 times as often as without overlap (~4x at 32 vs 64);
with the defaults (12 cells x 4 frames, 8 patches per frame scored by 5 VGG passes) ~15 min
on 2 idle cores.

Writes `<out>/results.json`, `<out>/table.md` and `<out>/pareto.png` (ms per frame against
signed score and against the seam ratio, one point per stride).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import evaluation, material_index, normalmap, patches, pipeline
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import gram, patchscores, patchsets, suite
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.evaluation import seams as seam_lib
from wrinkle_jax.nn import vgg

PATCH = "patch"


def evaluate_cell(fine, coarse, material: str, enh: enhancer_lib.Enhancer, strides, vgg_params,
                  sampling: patchscores.Sampling, frames: list[int], cell_seed=(0,),
                  batch_size: int = 8) -> dict:
    """Scores, seam sums and timings of every stride (and the patch-level model) on one cell.

    Args:
      fine, coarse: `GarmentSequence`s of one Table 1 cell (frames (T, V, 3) meters).
      material: its material; enh: the model; strides: tile strides (texels, <= patch size).
      vgg_params: VGG19 (or a tiny VGG in tests); sampling: Table 1's `Sampling`.
      frames: frame indices (each drawn as Table 1 draws it with `cell_seed`).
    Returns:
      {"loss_input": (N,), "loss": {name: (N,)}, "seams": {stride: (4,) sums},
       "seams_coarse": {stride: (4,)}, "timings": {stride: {stage: s}},
       "patches_per_frame": {stride: int}, "frames": frames}.
    """
    size = sampling.patch_size
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, sampling.texel_size)
    both = np.asarray(patches.pad_to_patch(pair.mask, size)[0])
    grid = size // 2 if sampling.grid_stride is None else sampling.grid_stride
    cand, _ = patchsets.candidate_origins(both, size, grid, sampling.min_coverage)
    if not len(cand):
        raise ValueError("no candidate patch")
    mid = material_index(material)
    pipes = {s: pipeline.make_pipeline(
        coarse.garment, enh, pipeline.PipelineConfig(batch_size=batch_size, stride=s,
                                                     lift=False, chunk_size=len(frames)),
        layout=pair.layout) for s in strides}
    maps, timings, per_frame = {}, {}, {}
    for s, pipe in pipes.items():
        t, counts = {}, {}
        maps[s] = {f.index: f.normal_map for f in pipeline.iter_enhance(
            pipe, coarse.frames, pipe.enhancer.config.material_id(material), frames, t, counts)}
        timings[s], per_frame[s] = t, pipe.num_patches
    patch_model = method_lib.enhancer_method(enh, batch_size=batch_size)
    coarse_mask = np.asarray(pipes[strides[0]].mask)[..., 0] > 0
    seams = {s: np.zeros(4) for s in strides}
    seams_coarse = {s: np.zeros(4) for s in strides}
    loss_in, loss = [], {k: [] for k in (PATCH, *strides)}
    for t in frames:
        sel = patchsets.choose_origins(cand, sampling.patches_per_frame,
                                       (sampling.seed, *cell_seed, t))
        ps = patchsets.aligned_patches(pair, fine.frames[t], coarse.frames[t], sel, size, mid)
        outs = {PATCH: patch_model(ps)}
        base = np.asarray(patchsets.bake_map(pair.coarse, coarse.frames[t]))
        for s in strides:
            rgb = normalmap.to_rgb(patches.pad_to_patch(maps[s][t], size)[0])
            outs[s] = patchsets.cut(np.asarray(rgb), sel, size) * ps.mask
            org = pipes[s].origins
            seams[s] += seam_lib.seam_sums(maps[s][t], coarse_mask, org, size)
            seams_coarse[s] += seam_lib.seam_sums(base, coarse_mask, org, size)
        got = gram.method_losses(vgg_params, ps.input, ps.target, ps.mask, outs,
                                 batch_size=sampling.score_batch)
        loss_in.append(got["input"])
        for k in loss:
            loss[k].append(got[k])
    return {"loss_input": np.concatenate(loss_in),
            "loss": {k: np.concatenate(v) for k, v in loss.items()},
            "seams": seams, "seams_coarse": seams_coarse, "timings": timings,
            "patches_per_frame": per_frame, "frames": list(frames)}


def summarize(results: dict[str, dict], strides) -> dict:
    """Pooled over cells: per stride the score summary, seam ratios, ms per frame per stage and
    patches per frame; the patch-level model's score."""
    out = {}
    loss_in = np.concatenate([r["loss_input"] for r in results.values()])
    for name in (PATCH, *strides):
        sc = evaluation.scores_from_losses(loss_in, np.concatenate([r["loss"][name]
                                                                    for r in results.values()]))
        row = {"score": patchscores.summary(sc)}
        if name != PATCH:
            n_frames = sum(len(r["frames"]) for r in results.values())
            stages = {}
            for r in results.values():
                for k, v in r["timings"][name].items():
                    stages[k] = stages.get(k, 0.0) + v
            ms = {k: 1e3 * v / n_frames for k, v in stages.items()}
            row.update(
                stride=int(name), ms_per_frame=ms,
                ms_tile_network_merge=sum(ms.get(k, 0.0) for k in ("tile", "network", "merge")),
                patches_per_frame=float(np.mean([r["patches_per_frame"][name]
                                                 for r in results.values()])),
                seam_ratio=seam_lib.seam_ratio(sum(r["seams"][name] for r in results.values())),
                seam_ratio_coarse=seam_lib.seam_ratio(sum(r["seams_coarse"][name]
                                                          for r in results.values())))
        out[str(name)] = row
    return out


def table_markdown(res: dict) -> str:
    lines = [f"# Patch stride: score, seams and time (model `{res['model']}`)", "",
             res["sampling_text"], "",
             "| stride | patches/frame | tile+network+merge ms/frame | |.| score | signed score "
             "| seam ratio (coarse control) |", "|---|---|---|---|---|---|"]
    for name, row in res["pooled"].items():
        s = row["score"]
        score = f"{s['improvement_mean']:.1f} ± {s['improvement_std']:.1f}"
        signed = f"{s['signed_mean']:+.1f} ± {s['signed_std']:.1f}"
        if name == PATCH:
            lines.append(f"| patch level (no tiling, Table 1's model) | - | - | {score} | "
                         f"{signed} | - |")
        else:
            lines.append(f"| {name} | {row['patches_per_frame']:.1f} | "
                         f"{row['ms_tile_network_merge']:.0f} | {score} | {signed} | "
                         f"{row['seam_ratio']:.3f} ({row['seam_ratio_coarse']:.3f}) |")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for k, r in res["pooled"].items() if k != PATCH]
    ms = [r["ms_tile_network_merge"] for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, key, label in ((axes[0], "signed", "signed improvement score (higher is better)"),
                           (axes[1], "seam", "seam ratio (1 = invisible borders)")):
        ys = [r["score"]["signed_mean"] if key == "signed" else r["seam_ratio"] for r in rows]
        ax.plot(ms, ys, "o-")
        for r, x, y in zip(rows, ms, ys, strict=True):
            ax.annotate(f"stride {r['stride']}", (x, y), textcoords="offset points",
                        xytext=(4, 4), fontsize=8)
        if key == "signed":
            ax.axhline(res["pooled"][PATCH]["score"]["signed_mean"], color="grey", ls="--",
                       label="patch level (no merge)")
            ax.legend(fontsize=8)
        ax.set_xlabel("tile + network + merge, ms per frame")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    suite.save_figure(fig, path, dpi=110)


def main(argv=None) -> int:
    ap = suite.script_parser(__doc__)
    ap.add_argument("--model", default=str(enhancer_lib.DEFAULT_PATH))
    ap.add_argument("--strides", default="32,64,96")
    ap.add_argument("--frame-every", type=int, default=5,
                    help="use every k-th of Table 1's scored frames")
    ap.add_argument("--frames", type=int, default=200, help="Table 1's --frames")
    ap.add_argument("--frame-stride", type=int, default=10, help="Table 1's --frame-stride")
    ap.add_argument("--patches-per-frame", type=int, default=8)
    cell_lib.add_sequence_args(ap)
    ap.add_argument("--out", default=str(suite.RESULTS / "stride"))
    args = ap.parse_args(argv)
    enh = suite.load_model_or_usage_error(ap, args.model)
    size = enh.config.patch_size
    try:
        strides = [int(s) for s in args.strides.split(",")]
    except ValueError:
        ap.error("--strides: comma-separated integers")
    if any(not 1 <= s <= size for s in strides):
        ap.error(f"strides must be in 1..{size}")
    if args.frame_every < 1:
        ap.error("--frame-every must be >= 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    sampling = patchscores.Sampling(frames=args.frames, frame_stride=args.frame_stride,
                               patches_per_frame=args.patches_per_frame, patch_size=size,
                               texel_size=enh.config.texel_size,
                               score_batch=min(args.patches_per_frame, 16))
    frames = sampling.frame_indices[::args.frame_every]
    cells = cell_lib.table_cells(args.garments.split(","), args.materials.split(","),
                                 args.motions.split(","))
    vgg_params = vgg.load_vgg19()
    results = {}
    for i, cell in enumerate(cells):
        seqs = cell_lib.cell_sequences(cell, args.frames, cell_lib.TEST_SEED,
                                       (Path(args.sequences),), Path(args.sim_out))
        fine = cell_lib.load_first_frames(seqs["fine"], args.frames)
        coarse = cell_lib.load_first_frames(seqs["coarse"], args.frames)
        t0 = time.perf_counter()
        results[cell.key] = evaluate_cell(fine, coarse, cell.material, enh, strides,
                                          vgg_params, sampling, frames, cell.patch_seed)
        elapsed = time.perf_counter() - t_all
        print(f"[{i + 1}/{len(cells)}] {cell.key}: {time.perf_counter() - t0:.0f} s, "
              f"{suite.eta_text(i + 1, len(cells), elapsed)}", flush=True)
    pooled = summarize(results, strides)
    per_cell = {k: summarize({k: r}, strides) for k, r in results.items()}
    res = {
        "model": suite.portable_path(args.model), "strides": strides, "frames": frames,
        "sampling": dataclasses.asdict(sampling),
        "sampling_text": (
            f"Table 1's cells ({len(cells)}), frames {', '.join(map(str, frames))} of each, "
            f"{sampling.patches_per_frame} of Table 1's patches per frame "
            f"({sum(len(r['loss_input']) for r in results.values())} patches); score: "
            f"{', '.join(evaluation.EVAL_LAYERS)}; timings on this machine, compile "
            "excluded."),
        "pooled": pooled, "cells": per_cell, "machine": suite.machine_info(),
        "run_s": time.perf_counter() - t_all,
        "command": "python -m experiments.stride " + " ".join(
            sys.argv[1:] if argv is None else argv)}
    suite.write_json(out / "results.json", res)
    (out / "table.md").write_text(table_markdown(res))
    plot(res, out / "pareto.png")
    print(table_markdown(res))
    print(f"wrote {out} in {(time.perf_counter() - t_all) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
