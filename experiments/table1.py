"""Paper Table 1: improvement score of the enhancer on COARSE SIMULATIONS, fine simulations as
ground truth, against the non-learned baselines on the same patches.

    python -m experiments.table1 [--model wrinkle_jax/assets/enhancer.npz] [--frames 200]
        [--frame-stride 10] [--patches-per-frame 8] [--out experiments/results/table1]

Cells (12): garment {flared_skirt (seen in training), dress, cape (unseen)} x material
{silk_charmeuse, denim_light} x motion {dance (seen), walk (unseen)}, seed 1 (training used
seed 0, so even the seen cell is an unseen performance). Scenes: skirt_dance, skirt_walk,
dress_dance, cape_walk from `wrinkle_jax.sim.scenes`; dress_walk and cape_dance are the dress
and cape scenes with the motion replaced (`evaluation.cells.scene_for`). Each cell uses the first
`--frames` frames of a fine (PD 10 mm) and a coarse (PD 30 mm) simulation: files of
`data/sequences` (the 300-frame test sequences) are reused when their scene config, material,
seed and solver settings match (`scenes.dataset_solver`: coarse at 80 substeps, self-collision
on); missing ones (skirt_dance seed 1, dress_walk, cape_dance, and files of older recipes) are
simulated with those settings into `data/table1_sequences/` first (resumable, atomic writes;
with self-collision the fine simulation costs ~4x what it did without).

Patches (paper: patch level): both meshes are baked on ONE pixel grid at the model's texel
size (`evaluation.patchsets.shared_layout`: the fine mesh's meters-per-UV, the union of the UV
bounds), so a patch origin is the same cloth in both maps. Candidate patches are the model-size
patches of a grid (stride half a patch) in which the texels covered by BOTH meshes make up at least
`--min-coverage` (0.5); in every `--frame-stride`-th frame, `--patches-per-frame` of them are
drawn at random (seeded by cell and frame). Input N = the coarse map, target N_hat = the fine
map of the same frame, both cut to that mask.

Methods, on the same patches: identity (score 0 by definition); unsharp masking with masked
blur of order 0 and of order 1, each with the best (sigma, amount) of the model card's sweep on
training patches (`experiments/results/model_card/results.json`, else sigma 8 amount 1);
bicubic and Lanczos x2
down/up-sampling; the model (run on the patch itself, material given); and the wrong-material
ablation (paper Fig. 10): the model told the other table material (silk_charmeuse <->
denim_light; `evaluation.methods.wrong_material`; off with --no-wrong-material).

Score: `wrinkle_jax.evaluation`'s improvement score on EVAL_LAYERS (relu1_2 ... relu5_1), the
paper's |.| form and the signed form (negative = further from the target's style than the
input). The Gram matrices of the input and the target are computed once per patch and shared
by the methods (`evaluation.gram.method_losses`, equal to `evaluation.score_patches`).

Cost (2 CPU cores): a VGG19 pass to relu5_1 costs ~0.15-0.2 s per 128x128 patch on an idle
machine and ~0.4-0.5 s with another job on the cores; a patch needs 2 + 6 passes (input,
target, and every method except identity: two unsharp orders, bicubic, Lanczos, the model with
the right and the wrong material), so the defaults (12 cells x 20 frames x 8 patches = 1920
patches) take ~40-50 min idle. The ETA
is printed as it goes. Each finished cell is
stored under `<out>/cells/` and reused by a rerun with the same settings (`--fresh` ignores it).

Writes `<out>/results.json` (per cell and per cell kind: n, mean and std of both scores and
medians, per method; sampling, timings, machine), `<out>/table.md` (laid out like the paper's
Table 1, plus the method comparison) and `<out>/scores.npz` (per-patch losses and scores).
"""

from __future__ import annotations

import dataclasses
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

from wrinkle_jax import evaluation
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import patchscores, suite
from wrinkle_jax.fileio import atomic_write_bytes
from wrinkle_jax.nn import vgg

SUMMARY_KINDS = ("seen garment, seen motion", "seen garment, unseen motion", "unseen garment")


def _fmt(d: dict, signed: bool = False) -> str:
    if not d.get("n"):
        return "-"
    if signed:
        return f"{d['signed_mean']:+.1f} ± {d['signed_std']:.1f}"
    return f"{d['improvement_mean']:.1f} ± {d['improvement_std']:.1f}"


def table_markdown(results: dict) -> str:
    """table.md: the paper's layout (rows material x motion, columns garments) for the model,
    in the paper's |.| form and signed; then every method by cell kind."""
    cells = results["cells"]
    garments = results["config"]["garments"]
    lines = [f"# Table 1: improvement score on coarse simulations (model `{results['model']}`)",
             "",
             f"{results['sampling_text']}", ""]
    for signed in (False, True):
        title = ("signed score (100 = target style, 0 = input unchanged, < 0 = worse)" if signed
                 else "paper's |.| form, mean ± std over patches")
        lines += [f"## Model, {title}", "",
                  "| material | motion | " + " | ".join(
                      f"{g} ({'seen' if g == cell_lib.SEEN_GARMENT else 'unseen'})"
                      for g in garments) + " |",
                  "|---|---|" + "---|" * len(garments)]
        for ma in results["config"]["materials"]:
            for mo in results["config"]["motions"]:
                row = [ma, f"{mo} ({'seen' if mo == cell_lib.SEEN_MOTION else 'unseen'})"]
                for g in garments:
                    key = cell_lib.Cell(g, mo, ma).key
                    row.append(_fmt(cells[key]["methods"][patchscores.MODEL], signed)
                               if key in cells else "-")
                lines.append("| " + " | ".join(row) + " |")
        lines.append("")
    lines += ["## All methods by cell kind: |.| mean ± std (signed mean ± std), n patches", "",
              "| method | " + " | ".join(results["by_kind"]) + " | all |",
              "|---|" + "---|" * (len(results["by_kind"]) + 1)]
    for name in results["methods"]:
        row = [name]
        for d in [*results["by_kind"].values(), results["all"]]:
            s = d[name]
            row.append(f"{_fmt(s)} ({_fmt(s, True)}), n={s.get('n', 0)}" if s.get("n")
                       else "-")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    ap = suite.script_parser(__doc__)
    patchscores.add_cell_args(ap, suite.RESULTS / "table1")
    ap.add_argument("--no-wrong-material", action="store_true",
                    help="skip the wrong-material ablation (the model told the other material)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    st = patchscores.setup_from_args(ap, args, wrong_material=not args.no_wrong_material)
    sampling, cells, sequences, methods = st.sampling, st.cells, st.sequences, st.methods
    sources, unsharp_src, net_timings = st.sources, st.unsharp_text, st.net_timings
    sim_s = st.sim_s
    vgg_params = vgg.load_vgg19()
    n_patches_max = len(cells) * len(sampling.frame_indices) * sampling.patches_per_frame
    print(f"{len(cells)} cells x {len(sampling.frame_indices)} frames x "
          f"<= {sampling.patches_per_frame} patches = <= {n_patches_max} patches, "
          f"{len(methods)} methods", flush=True)
    fingerprint_of = st.fingerprint_of

    results_by_cell = patchscores.run(cells, sequences, methods, vgg_params, sampling, out,
                                      fingerprint_of, args.fresh,
                                      log=lambda m: print(m, flush=True), sources=sources)
    # 3. Summaries.
    cells_out, kinds = {}, {k: [] for k in SUMMARY_KINDS}
    for cell in cells:
        r = results_by_cell[cell.key]
        sc = patchscores.cell_scores(r)
        kinds[cell.kind].append(r)
        cells_out[cell.key] = {
            "scene": cell.scene.name, "garment": cell.garment, "motion": cell.motion,
            "material": cell.material, "kind": cell.kind, "n_patches": int(len(r["frame"])),
            "n_candidates_per_frame": r["n_candidates"],
            "frames_scored": sorted(set(r["frame"].tolist())),
            "fine": suite.portable_path(sequences[cell.key]["fine"]),
            "coarse": suite.portable_path(sequences[cell.key]["coarse"]),
            "sequence_source": {res: sequences[cell.key][f"{res}_info"]["source"]
                                for res in ("fine", "coarse")},
            "methods": {k: patchscores.summary(v) for k, v in sc.items()}, "timings": r["timings"]}
    pooled = {k: patchscores.pooled_scores(v) for k, v in kinds.items() if v}
    pooled["all"] = patchscores.pooled_scores(list(results_by_cell.values()))
    by_kind = {k: {m: patchscores.summary(s) for m, s in p.items()}
               for k, p in pooled.items() if k != "all"}
    everything = {m: patchscores.summary(s) for m, s in pooled["all"].items()}
    # The robust summary: every other method against the unsharp baselines, patch by patch.
    refs = [m for m in pooled["all"] if m.startswith("unsharp")]
    paired = {k: patchscores.paired_against(p, [m for m in p if m not in refs + ["identity"]],
                                            refs) for k, p in pooled.items()}
    cell_t = [c["timings"] for c in cells_out.values()]
    n_all = sum(c["n_patches"] for c in cells_out.values())
    score_s = sum(t["score_s"] for t in cell_t)
    passes = sum(t["vgg_passes"] for t in cell_t) * sampling.score_batch
    sampling_text = (
        f"Sampling: first {sampling.frames} frames of each sequence "
        f"(seed {cell_lib.TEST_SEED}); frames "
        f"{patchscores.frames_text(sampling.frame_indices)} "
        f"({len(sampling.frame_indices)} frames); "
        f"{sampling.patches_per_frame} random {sampling.patch_size}x{sampling.patch_size} "
        f"patches per frame ({sampling.texel_size * 1e3:g} mm texels) among the grid patches "
        f"with >= {sampling.min_coverage:.0%} of texels covered by both the coarse and the fine "
        f"mesh. Input: coarse simulation (PD 30 mm); target: fine simulation (PD 10 mm) of the "
        f"same frame. Unsharp: {unsharp_src}.")
    results = {
        **st.record(args.model),
        "score": "evaluation.score_patches equivalent on " + ", ".join(evaluation.EVAL_LAYERS),
        "sampling": dataclasses.asdict(sampling), "sampling_text": sampling_text,
        "config": {"garments": args.garments.split(","), "materials": args.materials.split(","),
                   "motions": args.motions.split(","), "seed": cell_lib.TEST_SEED,
                   "scenes": {c.key: json.loads(c.scene.to_json()) for c in cells}},
        "cells": cells_out, "by_kind": by_kind, "all": everything,
        "paired_vs_unsharp": paired,
        "timings": {
            "note": "per-cell timings are from the run that scored the cell (see cells.*.timings)",
            "cells_s": sum(t.get("cell_s", 0.0) for t in cell_t),
            "score_s": score_s, "vgg_patch_passes": passes,
            "vgg_s_per_patch_pass": score_s / passes if passes else None,
            "network_ms_per_patch": (1e3 * sum(t["methods_s"].get(patchscores.MODEL, 0.0)
                                               for t in cell_t)
                                     / n_all if n_all else None),
            "network_compile_s": net_timings.get("compile_s"),
            "sequences_s": sim_s, "this_run_s": time.perf_counter() - t_all},
        "machine": suite.machine_info(),
        "command": "python -m experiments.table1 " + " ".join(
            sys.argv[1:] if argv is None else argv),
    }
    suite.write_json(out / "results.json", results)
    (out / "table.md").write_text(table_markdown(results))
    flat = {}
    for key, r in results_by_cell.items():
        tag = key.replace("/", "__")
        flat[f"{tag}/frame"], flat[f"{tag}/origin"] = r["frame"], r["origin"]
        for m, s in patchscores.cell_scores(r).items():
            for f in ("loss_output", "improvement_signed", "valid"):
                flat[f"{tag}/{m}/{f}"] = s[f]
        flat[f"{tag}/loss_input"] = r["loss_input"]
    buf = io.BytesIO()
    np.savez_compressed(buf, **flat)
    atomic_write_bytes(out / "scores.npz", buf.getvalue())
    print(table_markdown(results))
    print(f"wrote {out / 'results.json'}, {out / 'table.md'}, {out / 'scores.npz'} "
          f"in {(time.perf_counter() - t_all) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
