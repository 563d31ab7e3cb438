"""Temporal coherence: frame-to-frame change (flicker) of the enhanced normal maps against that of
the fine simulation and of the coarse input, per sequence.

    python -m experiments.temporal [--model wrinkle_jax/assets/enhancer.npz] [--frames 60]
        [--start 0] [--out experiments/results/temporal]

Sequences: Table 1's (`experiments.table1`: flared_skirt, dress, cape x silk_charmeuse,
denim_light x dance, walk; seed 1; the same files, simulated there or here if missing), or a
subset with --garments/--materials/--motions. The paper's network works frame by frame; this
checks that its details do not flicker more than real wrinkles move.

Per sequence, `--frames` CONSECUTIVE frames from `--start` (default 60 frames = 2 s at 30 fps:
59 frame pairs; the whole 200 would cost ~3x more network time) are enhanced by the streaming
pipeline without lifting (`pipeline.iter_enhance`: bake, tile with stride half a patch, U-Net,
Hann merge). For each pair of consecutive frames (t, t+1) three numbers are measured, each the
mean over a map's garment texels of the angle in degrees between the unit normals at t and t+1:

    output   the enhanced map N*, on the coarse mesh's texels (the pipeline's mask)
    coarse   the coarse map the pipeline baked (its input), same texels
    fine     the fine simulation's map of the same frames at the model's texel size

Rigid motion of the garment moves all three; the output is expected between the coarse input
and the fine simulation. Summary per sequence: mean, std, median, p95, max of each series, the
ratios output/fine and output/coarse of the means, and the added change output - coarse.

Writes `<out>/results.json` (per sequence: the series and the summary; frames, timings,
machine) and `<out>/flicker.png` (one panel per sequence: the three series over time).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import evaluation
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import suite
from wrinkle_jax.evaluation.temporal import SERIES, sequence_flicker


def summarize(res: dict) -> dict:
    """Per-series statistics and the output/fine, output/coarse ratios of the means."""
    out = {k: evaluation.series_stats(res[k]) for k in SERIES if k in res}
    mean = {k: v["mean"] for k, v in out.items()}
    out["output_over_coarse"] = mean["output"] / mean["coarse"] if mean["coarse"] > 0 else None
    out["added_over_coarse_deg"] = mean["output"] - mean["coarse"]
    if "fine" in mean:
        out["output_over_fine"] = mean["output"] / mean["fine"] if mean["fine"] > 0 else None
        out["fine_over_coarse"] = mean["fine"] / mean["coarse"] if mean["coarse"] > 0 else None
    return out


def plot(path: Path, per_sequence: dict[str, dict], frames: list[int]) -> None:
    """One panel per sequence: the coarse, output and fine series (degrees) over frame pairs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(per_sequence)
    ncols = min(4, len(names))
    nrows = -(-len(names) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.6 * ncols, 2.6 * nrows), squeeze=False,
                             sharex=True)
    x = np.asarray(frames[1:])
    style = {"coarse": ("tab:gray", "coarse input"), "output": ("tab:red", "ours (output)"),
             "fine": ("tab:blue", "fine simulation")}
    for ax, name in zip(axes.ravel(), names, strict=False):
        for k in SERIES:
            if k in per_sequence[name]["series"]:
                color, label = style[k]
                ax.plot(x, per_sequence[name]["series"][k], color=color, lw=1.0, label=label)
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_ylim(bottom=0)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("mean change (deg)", fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("frame t (pair t-1, t)", fontsize=7)
    axes[0, 0].legend(fontsize=6)
    fig.tight_layout()
    suite.save_figure(fig, path, dpi=90)


def main(argv=None) -> int:
    ap = suite.script_parser(__doc__)
    ap.add_argument("--model", default=str(enhancer_lib.DEFAULT_PATH),
                    help="enhancer .npz (default: the shipped model)")
    ap.add_argument("--frames", type=int, default=60, help="consecutive frames per sequence")
    ap.add_argument("--start", type=int, default=0, help="first frame")
    ap.add_argument("--batch-size", type=int, default=8, help="patches per network call")
    cell_lib.add_sequence_args(ap)
    ap.add_argument("--table-frames", type=int, default=200,
                    help="length of the simulations to make when missing (as table1)")
    ap.add_argument("--out", default=str(suite.RESULTS / "temporal"))
    args = ap.parse_args(argv)
    if args.frames < 2 or args.start < 0:
        ap.error("--frames must be >= 2 and --start >= 0")
    need = max(args.table_frames, args.start + args.frames)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    enh = suite.load_model_or_usage_error(ap, args.model)
    cells = cell_lib.table_cells(args.garments.split(","), args.materials.split(","),
                                 args.motions.split(","))
    sequences = {c.key: cell_lib.cell_sequences(c, need, cell_lib.TEST_SEED,
                                                (Path(args.sequences),), Path(args.sim_out))
                 for c in cells}
    frames = list(range(args.start, args.start + args.frames))
    total, done = len(cells) * len(frames), [0]
    t_start = time.perf_counter()
    per_sequence = {}
    for i, cell in enumerate(cells):
        coarse = cell_lib.load_first_frames(sequences[cell.key]["coarse"], frames[-1] + 1)
        fine = cell_lib.load_first_frames(sequences[cell.key]["fine"], frames[-1] + 1)

        def progress(k, i=i, cell=cell):
            done[0] += k
            if done[0] % 10 == 0 or done[0] == total:
                el = time.perf_counter() - t_start
                print(f"[{i + 1}/{len(cells)}] {cell.key}: {done[0]}/{total} frames, "
                      f"{el / 60:.1f} min, {suite.eta_text(done[0], total, el)}", flush=True)

        res = sequence_flicker(coarse, fine, enh, cell.material, frames, args.batch_size,
                               progress=progress)
        summ = summarize(res)
        per_sequence[cell.key] = {
            "scene": cell.scene.name, "garment": cell.garment, "motion": cell.motion,
            "material": cell.material, "kind": cell.kind,
            "coarse_file": suite.portable_path(sequences[cell.key]["coarse"]),
            "fine_file": suite.portable_path(sequences[cell.key]["fine"]),
            "patches_per_frame": res["patches_per_frame"], "texels": res["texels"],
            "summary": summ, "series": {k: res[k] for k in SERIES if k in res},
            "timings": res["timings"]}
        print(f"  {cell.key}: mean change coarse {summ['coarse']['mean']:.3f}, output "
              f"{summ['output']['mean']:.3f}, fine {summ['fine']['mean']:.3f} deg/frame",
              flush=True)
    ratios = [v["summary"]["output_over_fine"] for v in per_sequence.values()
              if v["summary"].get("output_over_fine") is not None]
    results = {
        "model": suite.portable_path(args.model), "material_given": True,
        "measure": "mean over garment texels of the angle (deg) between the unit normals of "
                   "consecutive frames; output = pipeline N* (no lift), coarse = its baked "
                   "input, fine = fine simulation baked at the model's texel size",
        "frames": frames, "fps": 30.0,
        "pipeline": {"batch_size": args.batch_size, "stride": enh.config.patch_size // 2,
                     "window": "hann", "lift": False},
        "sequences": per_sequence,
        "overall": {"output_over_fine_median": float(np.median(ratios)) if ratios else None,
                    "output_over_fine": ratios},
        "timings": {"total_s": time.perf_counter() - t_all},
        "machine": suite.machine_info(),
        "command": "python -m experiments.temporal " + " ".join(
            sys.argv[1:] if argv is None else argv),
    }
    suite.write_json(out / "results.json", results)
    plot(out / "flicker.png", per_sequence, frames)
    print(f"wrote {out / 'results.json'} and {out / 'flicker.png'} in "
          f"{(time.perf_counter() - t_all) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
