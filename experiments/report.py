"""Assemble `experiments/results/REPORT.md` from the evaluation suite's stored results.

    python -m experiments.report [--results experiments/results] [--out REPORT.md path]

Nothing is recomputed: every section reads the `results.json` (or `table.json`, benchmark JSON)
that its script wrote, says which command made it and on which machine, and the speed-against-
error plots are drawn here from those numbers (`<results>/report/*.png`). A section whose
results are missing says so and gives the command that makes them, so the report is honest
about what has not been run; `--strict` makes that an error (exit status 1).

Sections: headline numbers; Table 1 (+ the wrong-material ablation); Table 2; baselines
(including the DeepWrinkles-style PatchGAN); ablations (sheet-only training, wrong material,
stride, width); temporal coherence; timing; speed against error (width, stride, lifting
solver, simulator substeps, VGG layers); commands; machines.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

from wrinkle_jax.evaluation import markdown, patchscores, suite
from wrinkle_jax.evaluation.headlines import (
    FIDELITY_METHODS,
    LADDER,
    MODEL,
    WRONG,
    card_headline,
    fidelity_headline,
    ladder_headline,
    relative_drop,
    score_text,
    ship_test_headline,
    table1_headline,
    table2_detail_headline,
    table2_headline,
)
from wrinkle_jax.fileio import git_commit

# What makes each result (relative to the project root); the report prints these.
COMMANDS = {
    "table1": "python -m experiments.table1",
    "table2": "python -m experiments.table2",
    "stride": "python -m experiments.stride",
    "temporal": "python -m experiments.temporal --frames 30",
    "timing": "python -m experiments.timing --frames 30 --model wrinkle_jax/assets/enhancer.npz",
    "reference_unet": ("python benchmarks/bench_reference.py --authors-repo PATH --skip-train "
                       "--skip-lift --rounds 5 > experiments/results/timing/reference_unet.json"),
    "reference_train": ("python benchmarks/bench_reference.py --authors-repo PATH --skip-unet "
                        "--skip-lift --train-impls im2col_bf16 winograd_bf16 --rounds 3 "
                        "> experiments/results/timing/reference_train.json"),
    "reference_avx2": ("python benchmarks/bench_reference.py --authors-repo PATH --skip-lift "
                       "--rounds 3 --train-impls im2col_f32 winograd_f32 "
                       "> experiments/results/timing/reference_s46b_avx2.json"),
    "ceiling": "python benchmarks/bench_ceiling.py > experiments/results/timing/ceiling.json",
    "lift": "python benchmarks/bench_lift.py --quick > experiments/results/lift/bench.json",
    "substeps": ("python benchmarks/bench_sim.py --quick --part substeps "
                 "> experiments/results/sim/substeps.json"),
    "layer_selection": "python -m experiments.layer_selection",
    "width": ("python -m experiments.short_runs width --widths 8,16,32 --steps 400 "
              "--minutes 1000 --tag shipped"),
    "width_old": ("python -m experiments.short_runs width --residual-base unsharp "
                  "--unsharp-sigma 8 --style-layers relu2_2,relu3_1,relu3_2 "
                  "--normalize-channels 1 --w-c 1 --relative-floor 0.01 --blur-order 0 "
                  "--residual-highpass 0 --minutes 5 --tag unsharp2 (session 2)"),
    "patchgan": "python -m experiments.patchgan",
    "sheet_only": ("python -m experiments.train_default --train-scenes sheet_balls_wind --run "
                   "outputs/sheet_only --out experiments/results/sheet_only/enhancer.npz "
                   "--steps 1666 --minutes 300 && python -m experiments.model_card --model "
                   "experiments/results/sheet_only/enhancer.npz --out "
                   "experiments/results/sheet_only"),
    "model_card": "python -m experiments.model_card",
    "fidelity": ("python -m experiments.fidelity sweep && python -m experiments.fidelity score "
                 "--model NAME=PATH"),
    "ship_test": "see experiments/results/fidelity/ship_test_s15/README.md",
    "fidelity_ladder": "see experiments/results/fidelity/README.md, session 17",
    "table2_detail": ("python -m experiments.table2 --features detail --garments dress,cape "
                      "--frame-stride 20 --out experiments/results/table2_detail --extra "
                      "run7b=experiments/results/fidelity/detail_bands_w3.npz --extra "
                      "run10=experiments/results/fidelity/detail_bank_w25.npz --oracles"),
}


class Report(markdown.Report):
    """`markdown.Report` that names this report's commands for missing results."""

    def __init__(self, results: Path):
        super().__init__(results, COMMANDS)


# --------------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------------


def headline(rep: Report, t1, t2, timing, temporal, card=None, pg=None, sheet=None,
             fid=None) -> None:
    rep.add("## Headline numbers", "")
    rows = ship_test_headline(rep.load("ship_test", "fidelity/ship_test_s15/results.json"))
    rows += ladder_headline({k: rep.load("fidelity_ladder", f"fidelity/ladder_s17/{k}.json")
                             for k, _ in LADDER})
    rows += fidelity_headline(fid)
    rows += table2_detail_headline(rep.load("table2_detail", "table2_detail/results.json"))
    rows += table1_headline(t1)
    rows += table2_headline(t2)
    rows += card_headline(card, pg, sheet)
    if timing:
        cpu = cpu_text(timing.get("machine", {}))
        for name, r in timing_ratios(timing):
            rows.append(f"- Timing ({timing['scene']}, {timing['material']}"
                        + (f", {RECIPE_NAMES.get(name, name)}" if name else "")
                        + (f", {cpu}" if cpu else "") + "): ours "
                        f"{r['ours_ms_per_frame']:.0f} ms/frame (coarse sim + enhancement + "
                        f"lift) vs fine simulation {r['fine_ms_per_frame']:.0f} ms/frame: "
                        f"{r['speedup']:.2f}x the fine simulation's speed "
                        f"({r['speedup_no_lift']:.2f}x without lifting).")
    if temporal and temporal["overall"].get("output_over_fine_median") is not None:
        rows.append(f"- Flicker: output/fine frame-to-frame change, median over sequences "
                    f"{temporal['overall']['output_over_fine_median']:.2f}.")
    rep.add(*(rows or ["No results yet."]), "")


def fidelity_section(rep: Report, fid: dict | None) -> None:
    rep.add("## Detail-only score on real coarse simulations (the primary score)", "")
    if not fid:
        rep.add("Not run yet.", "")
        return
    rep.add("Input: the coarse simulation (PD 30 mm); target: the fine simulation (PD 10 mm) of "
            "the same frame; patches drawn as Table 1 draws them (`experiments.fidelity`). "
            "Detail-only score: the Gram improvement score (relu1_2 ... relu5_1) on detail "
            "maps, each map's own large scale (first-order masked Gaussian, sigma 8 texels = "
            "16 mm) rotated to +z (`wrinkle_jax.detail`). Object space: the paper's score on "
            "the maps themselves. Medians first (per-patch scores are heavy-tailed); the paired "
            "difference against unsharp is the median of per-patch differences with a 95 % "
            "bootstrap interval. Bands: mean RMS of the tangential detail relative to the fine "
            "simulation's (1 = the fine level); checker: 2-texel checkerboard RMS relative to "
            "the fine simulation's.", "")
    for kind, res in fid.items():
        rep.add(f"### {kind} ({', '.join(res['cells'])})", "",
                "| method | detail: median (mean) | vs unsharp (val), median diff [95 % CI] | "
                "vs unsharp (card) | vs unsharp (per-material) | object space: median (mean) "
                "| < 16 mm band | 16-64 mm band | checker |",
                "|---|---|---|---|---|---|---|---|---|")
        ms = res["methods"]
        order = [k for k in FIDELITY_METHODS if k in ms] + [
            k for k in ms if k not in FIDELITY_METHODS and k != "input"]
        for k in order:
            m = ms[k]
            det, obj = m.get("detail"), m.get("object")
            br = m.get("band_ratio_to_fine", {})
            rep.add(f"| {FIDELITY_METHODS.get(k, k)} | "
                    + (f"{det['signed_median']:+.1f} ({det['signed_mean']:+.1f})" if det
                       else "") + f" | {markdown.ci(det.get('vs_unsharp')) if det else ''} | "
                    + f"{markdown.ci(det.get('vs_unsharp_card')) if det else ''} | "
                    + f"{markdown.ci(det.get('vs_unsharp_material')) if det else ''} | "
                    + (f"{obj['signed_median']:+.1f} ({obj['signed_mean']:+.1f})" if obj
                       else "") + " | "
                    + " | ".join(f"{br[b]:.2f}" if b in br else "" for b in
                                 ("lt16mm", "16_64mm", "checker")) + " |")
        cells = {k: ms[k]["detail"]["cell_medians"] for k in order if "detail" in ms[k]}
        names = list(next(iter(cells.values()))) if cells else []
        if names:
            rep.add("", "Detail-only signed median per cell:", "",
                    "| method | " + " | ".join(names) + " |",
                    "|---|" + "---|" * len(names))
            for k, v in cells.items():
                rep.add(f"| {k} | " + " | ".join(f"{v[c]:+.1f}" for c in names) + " |")
        rep.add("")


def table1_section(rep: Report, t1) -> None:
    rep.add("## Table 1: improvement score on coarse simulations", "")
    if not t1:
        rep.not_run("Table 1", "table1")
        return
    table = (rep.results / "table1" / "table.md")
    if table.exists():
        rep.add(markdown.demote(table.read_text().split("\n", 1)[1].strip(), 1), "")
    t = t1["timings"]
    rep.add(f"Run: {t['cells_s'] / 60:.1f} min of scoring, "
            f"{t['vgg_s_per_patch_pass']:.3f} s per VGG patch pass, network "
            f"{t['network_ms_per_patch']:.1f} ms/patch.", "")


def wrong_material_section(rep: Report, t1) -> None:
    rep.add("### Wrong material at inference (paper Fig. 10)", "")
    if not t1 or WRONG not in t1.get("all", {}):
        rep.not_run("the wrong-material ablation (part of Table 1)", "table1")
        return
    rep.add("The same patches; the model is told the other table material (silk_charmeuse <-> "
            "denim_light).", "",
            "| cells | right material: signed (|.|) | wrong material: signed (|.|) | "
            "signed change, points (relative, where the right score is >= 10) |",
            "|---|---|---|---|")
    for name, d in [*t1["by_kind"].items(), ("all", t1["all"])]:
        drop = relative_drop(d[MODEL], d[WRONG], "signed_mean")
        change = d[WRONG]["signed_mean"] - d[MODEL]["signed_mean"]
        rel = (f" ({-drop:+.1f} %)" if drop is not None and abs(d[MODEL]["signed_mean"]) >= 10
               else "")
        rep.add(f"| {name} | {score_text(d[MODEL])} ({score_text(d[MODEL], False)}) | "
                f"{score_text(d[WRONG])} ({score_text(d[WRONG], False)}) | {change:+.1f}{rel} |")
    rep.add("", "Per material (all garments):", "", "| true material | right | wrong |",
            "|---|---|---|")
    for ma in t1["config"]["materials"]:
        cells = [c for c in t1["cells"].values() if c["material"] == ma]
        n = sum(c["methods"][MODEL]["n"] for c in cells)
        if not n:
            continue
        right = sum(c["methods"][MODEL]["signed_mean"] * c["methods"][MODEL]["n"]
                    for c in cells) / n
        wrong = sum(c["methods"][WRONG]["signed_mean"] * c["methods"][WRONG]["n"]
                    for c in cells) / n
        rep.add(f"| {ma} | {right:+.1f} | {wrong:+.1f} |")
    rep.add("")


def table2_section(rep: Report, t2, folder: str = "table2", title: str = (
        "## Table 2: Chamfer distances of Gram features without correspondence"),
                   intro: str | None = None) -> None:
    rep.add(title, "")
    if not t2:
        rep.not_run("Table 2", folder)
        return
    if intro:
        rep.add(intro, "")
    check = patchscores.same_simulations(rep.results / "table1" / "cells",
                                         rep.results / folder / "cells")
    stale = len(check["different"]) + len(check["unrecorded"])
    if stale:
        # Table 1 and 2 read the same simulations; after a regeneration one can lag.
        rep.add(f"**Not known to be on Table 1's simulations:** {stale} of "
                f"{stale + len(check['same'])} cells: {len(check['different'])} were scored "
                f"on other simulation files than Table 1's cell of the same name, "
                f"{len(check['unrecorded'])} record no digests (scored before they were "
                f"kept); rerun `{COMMANDS[folder]}`.", "")
    table = rep.results / folder / "table.md"
    if table.exists():
        rep.add(markdown.demote(table.read_text().split("\n", 1)[1].strip(), 1), "")
    rep.image(f"{folder}/embeddings.png", "Table 2 embeddings")


def baselines_section(rep: Report, t1) -> None:
    rep.add("## Baselines", "",
            "Identity, unsharp masking (masked blur of order 0 and 1, each at the model card's "
            "best setting on training patches), bicubic and Lanczos x2 down/up-sampling are "
            "scored on the same patches as the model in Tables 1 and 2 above.", "")
    rep.add("### DeepWrinkles-style conditional PatchGAN (paper Fig. 9)", "")
    pg = rep.load("patchgan", "patchgan/results.json")
    if pg is None:
        rep.not_run("the PatchGAN baseline", "patchgan",
                    "It trains on the model's training dataset "
                    "(`python -m experiments.make_sequences` then "
                    "`python -m experiments.make_dataset`, ~80 min) for the model's 0.75 h "
                    "training budget.")
        return
    rep.add(f"Trained {pg['steps']} steps in {pg['train_s'] / 60:.1f} min on "
            f"{', '.join(pg.get('train_scenes', [])) or 'all training scenes'}; signed mean "
            f"improvement score ({pg['n_heldout']} held-out and {pg['n_seen']} training "
            "patches, the model card's sets):", "",
            "| method | unseen garments | seen garment, unseen motion | training patches |",
            "|---|---|---|---|")
    for name, row in pg["summary"].items():
        rep.add(f"| {name} | " + " | ".join(
            "-" if row.get(k) is None else f"{row[k]:+.1f}"
            for k in ("unseen garment", "seen garment, unseen motion", "training patches"))
            + " |")
    rep.add("")
    rep.image("patchgan/loss_curve.png", "PatchGAN training curves")


def _card_row(res: dict, name: str = "model") -> list[str]:
    """Signed means of a model card result: unseen garments, seen garment (held out), seen."""
    m = res["methods"][name]
    kinds = m["heldout"]["by_kind"]
    vals = [kinds.get("unseen garment", {}), kinds.get("seen garment", {}), m["seen"]["all"]]
    return ["-" if not v.get("n") else f"{v['signed_mean']:+.1f}" for v in vals]


def ablations_section(rep: Report, t1, stride) -> None:
    rep.add("## Ablations", "")
    rep.add("### Training on the sheet only vs all training scenes (paper Fig. 8)", "")
    sheet = rep.load("sheet_only", "sheet_only/results.json")
    card = rep.load("model_card", "model_card/results.json")
    if sheet is None or card is None:
        rep.not_run("the sheet-only ablation", "sheet_only",
                    "Same recipe and budget as the shipped model, trained on the sheet scene's "
                    "patches only, scored on the model card's patches.")
    else:
        rep.add("Signed mean improvement score on the model card's patches:", "",
                "| trained on | unseen garments | seen garment, unseen motion | "
                "training patches |", "|---|---|---|---|",
                "| all training scenes (shipped model) | " + " | ".join(_card_row(card)) + " |",
                "| sheet only | " + " | ".join(_card_row(sheet)) + " |", "")
    wrong_material_section(rep, t1)
    rep.add("### Patch stride (seams against time)", "")
    if not stride:
        rep.not_run("the stride ablation", "stride")
    else:
        table = rep.results / "stride" / "table.md"
        if table.exists():
            rep.add(markdown.demote(table.read_text().split("\n", 1)[1].strip(), 2), "")
        rep.image("stride/pareto.png", "stride: time against score and seams")
    rep.add("### Network width", "",
            "See the width Pareto plot under speed against error.", "")


def temporal_section(rep: Report, temporal) -> None:
    rep.add("## Temporal coherence (flicker)", "")
    if not temporal:
        rep.not_run("the flicker study", "temporal")
        return
    rep.add(f"Mean angle (degrees) between the unit normals of consecutive frames over the "
            f"garment texels, frames {temporal['frames'][0]}-{temporal['frames'][-1]} "
            f"({temporal['fps']:g} fps); output = the pipeline's N* (no lift), coarse = its "
            "input, fine = the fine simulation.", "",
            "| sequence | coarse | output | fine | output / fine | output - coarse |",
            "|---|---|---|---|---|---|")
    for key, s in temporal["sequences"].items():
        sm = s["summary"]
        ratio = sm.get("output_over_fine")
        added = sm.get("added_over_coarse_deg")
        rep.add(f"| {key} | {sm['coarse']['mean']:.3f} | {sm['output']['mean']:.3f} | "
                f"{sm['fine']['mean']:.3f} | {'-' if ratio is None else f'{ratio:.2f}'} | "
                f"{'-' if added is None else f'{added:+.3f}'} |")
    rep.add("")
    rep.image("temporal/flicker.png", "flicker per sequence")


RECIPE_NAMES = {"legacy": "solvers without self-collision, the scenes' substeps",
                "dataset": "the data set's solvers (self-collision; coarse at 80 substeps)"}


def timing_ratios(timing) -> list[tuple[str, dict]]:
    """(recipe, ratio) per solver recipe of a timing result; ("", ratio) for results written
    before the recipes existed."""
    summary = timing.get("summary")
    if not summary:
        return [("", timing["ratio"])]
    return [(name, s["ratio"]) for name, s in summary["recipes"].items()]


def cpu_text(machine: dict, extra: str = "") -> str:
    """"<model> (<flags><extra>)" of a recorded machine (`suite.machine_info` or
    `hostcpu.describe`), or "" where it has no CPU model (runs before session 46)."""
    if not machine.get("cpu_model"):
        return ""
    flags = ", ".join(machine.get("cpu_flags", [])) or "no recorded flags"
    return f"{machine['cpu_model']} ({flags}{extra})"


def timing_section(rep: Report, timing) -> None:
    rep.add("## Timing (paper Fig. 2)", "")
    if not timing:
        rep.not_run("the timing study", "timing")
        return
    p = timing["pipeline"]
    summary = timing.get("summary")
    rounds = timing.get("rounds", 1)
    cpu = cpu_text(timing.get("machine", {}))
    rep.add(f"{timing['scene']}, {timing['material']}, {timing['frames']} frames, model width "
            f"{timing.get('model_width')}" + (f", on {cpu}" if cpu else "")
            + "; steady state, compile and setup excluded"
            + (f"; medians of {rounds} rounds in one process, the recipe order alternating"
               if rounds > 1 else "") + ".", "")
    recipes = list(summary["recipes"]) if summary else [""]
    head = "| stage | " + " | ".join(f"ms per frame, {n}" if n else "ms per frame"
                                      for n in recipes) + " |"
    rep.add(head, "|---|" + "---|" * len(recipes))
    coarse = [summary["recipes"][n]["coarse_ms_per_frame"] for n in recipes] if summary else [
        timing["coarse_sim"]["ms_per_frame"]]
    rep.add(f"| coarse simulation (PD {timing['coarse_sim']['pd_m'] * 1e3:g} mm, "
            f"{timing['coarse_sim']['vertices']} vertices) | "
            + " | ".join(f"{c:.1f}" for c in coarse) + " |")
    overlap = p.get("overlap_lift")
    for stage, ms in p["ms_per_frame"].items():
        name = f"{stage} (overlaps the next chunk's stages)" if overlap and stage == "lift" \
            else stage
        rep.add(f"| {name} | " + " | ".join(f"{ms:.1f}" for _ in recipes) + " |")
    if p.get("wall_ms_per_frame") is not None:
        rep.add("| pipeline, wall | " + " | ".join(
            f"{p['wall_ms_per_frame']:.1f}" for _ in recipes) + " |")
    if p.get("no_lift_wall_ms_per_frame") is not None:
        rep.add("| pipeline without the lift (a run of its own), wall | " + " | ".join(
            f"{p['no_lift_wall_ms_per_frame']:.1f}" for _ in recipes) + " |")
    ratios = dict(timing_ratios(timing))
    rep.add("| **ours, total** | " + " | ".join(
        f"**{ratios[n]['ours_ms_per_frame']:.0f}**" for n in recipes) + " |",
        f"| fine simulation (PD {timing['fine_sim']['pd_m'] * 1e3:g} mm, "
        f"{timing['fine_sim']['vertices']} vertices) | "
        + " | ".join(f"{ratios[n]['fine_ms_per_frame']:.0f}" for n in recipes) + " |", "")
    for n in recipes:
        r = ratios[n]
        rounds_txt = ""
        if summary:
            per = summary["recipes"][n]["speedup_per_round"]
            rounds_txt = "; rounds " + ", ".join(f"{x:.2f}x" for x in per)
        rep.add((f"With {RECIPE_NAMES.get(n, n)}: ours" if n else "Ours")
                + f" runs at {r['speedup']:.2f}x the fine simulation's speed "
                f"({r['speedup_no_lift']:.2f}x without lifting; {p['patches_per_frame']} "
                f"patches per frame{rounds_txt}).", "")
    if timing.get("context"):  # what a reader needs beside the numbers, written with the run
        rep.add(timing["context"], "")
    rep.image("timing/timing.png", "per-stage timing")


def reference_section(rep: Report, unet_run, train_run,
                      title: str = "### Beside the authors' code") -> None:
    """Our U-Net forms beside the authors' PyTorch code (`benchmarks/bench_reference.py`):
    speed-ups (their wall time / ours, medians of per-round ratios) and errors against theirs;
    the runs' CPU when they recorded it (the fast forms depend on it: `wrinkle_jax.hostcpu`)."""
    rep.add(title, "")
    if not unet_run and not train_run:
        rep.not_run("the side-by-side runs with the authors' network", "reference_unet")
        return
    rep.add("Same weights, their PyTorch (CPU) and our forms in one process, alternating; "
            "inference: width 64, batch 8 of 128 x 128 patches; training step: their recipe, "
            "batch 32. Errors: relative RMS against their output / parameter gradient.", "")
    rep.add("| form | inference, x their speed | output error | training step, x their speed "
            "| gradient error |", "|---|---|---|---|---|")
    u = (unet_run or {}).get("unet", {})
    t = (train_run or {}).get("train", {})
    forms = list(dict.fromkeys(
        [k.removeprefix("ours_") for k in u.get("speedup_vs_authors_wall", {})]
        + [k.removeprefix("ours_") for k in t.get("speedup_vs_authors_wall", {})]))

    def cell(d, key, fmt):
        return fmt.format(d[key]) if key in d else "-"

    for form in forms:
        err = u.get("agreement_vs_authors", {}).get(form, {})
        grad = t.get("agreement", {}).get(form, {}).get("grad_rel_rms_vs_authors", {})
        infer = cell(u.get("speedup_vs_authors_wall", {}), "ours_" + form, "{:.2f}x")
        step = cell(t.get("speedup_vs_authors_wall", {}), "ours_" + form, "{:.2f}x")
        rep.add(f"| {form} | {infer} | {cell(err, 'rel_rms', '{:.2%}')} | {step} "
                f"| {cell(grad, 'all', '{:.2%}')} |")
    loads = [r["timing"]["load_avg_1m"] for r in (u, t) if r and "timing" in r]
    # One run may serve both parts (a file with "unet" and "train"): its CPU and context once.
    runs = [r for r in (unet_run, train_run) if r]
    runs = runs[:1] if len(runs) == 2 and runs[0] is runs[1] else runs
    hosts = dict.fromkeys(
        cpu_text(h, f"; bfloat16 dot units: {'yes' if h['native_bf16_dots'] else 'no'}")
        for h in (r["host_cpu"] for r in runs if "host_cpu" in r))
    cpu = "".join(f" CPU: {text}." for text in hosts)
    rep.add("", "Targets (issue 22): inference >= 3x, training step >= 4x, bfloat16 output "
            "error <= 1 %. 1-minute load before/after: "
            + "; ".join(f"{x['before']}/{x['after']}" for x in loads) + "." + cpu, "")
    for run in runs:
        if run.get("context"):
            rep.add(run["context"], "")


def ceiling_section(rep: Report, run) -> None:
    """How far each convolution form can go: every dot of the compiled program replayed alone
    (`benchmarks/bench_ceiling.py`), and the ceilings on the speed-up against the authors' code
    that follow from the stored side-by-side ratios."""
    rep.add("### GEMM ceilings of these forms", "")
    if not run:
        rep.not_run("the GEMM ceilings", "ceiling")
        return
    parts = [(p, run[p]) for p in ("infer", "train", "shipped") if p in run]
    peak = parts[0][1]["peak_gflops_per_s"] if parts else {}
    rep.add("Each program's matrix products (read from its optimized HLO) replayed alone at "
            "their exact shapes, dtypes and layouts, as often as it runs them, alternating with "
            f"the program (width {run['width']}; bfloat16 GEMM peak through XLA "
            f"{peak.get('peak_bf16', '-')} GFLOP/s, float32 {peak.get('peak_f32', '-')}). "
            "Ceiling = stored speed-up x program time / dots time (or / the dots' FLOPs at the "
            "peak rate): what the same decomposition reaches if nothing but its products cost "
            "time.", "")
    rep.add("| part | form | program ms | dots ms (share) | dots GFLOP/s | x their speed now "
            "| ceiling: dots / at peak | target |", "|---|---|---|---|---|---|---|---|")
    for part, res in parts:
        name = {"infer": f"inference (batch {res['batch']})",
                "train": f"training step (batch {res['batch']})",
                "shipped": f"shipped model (pipeline batch {res['batch']})"}[part]
        for form, r in res["forms"].items():
            now = r.get("stored_speedup_vs_authors")
            if now:
                vs = (f"{now:.2f}x | {r['ceiling_speedup_vs_authors_dots']:.2f}x / "
                      f"{r['ceiling_speedup_vs_authors_peak']:.2f}x | {r['target']:.0f}x")
            else:
                vs = "- | - | -"
            rep.add(f"| {name} | {form} | {r['program_ms']:,.1f} | {r['dots_ms']:,.1f} "
                    f"({r['dots_share']:.0%}) | {r['dots_gflops_per_s']:.0f} | {vs} |")
    loads = [res["timing"]["load_avg_1m"] for _, res in parts]
    rep.add("", "A share near 100 % means the program is its products (replayed one by one "
            "they pay a dispatch each, so the share can exceed 100 %). The first two parts "
            "use the authors' layout at width 64; the shipped model (width 16) has no "
            "side-by-side run. 1-minute load before/after: "
            + "; ".join(f"{x['before']}/{x['after']}" for x in loads) + ".", "")


# --------------------------------------------------------------------------------------------
# Speed against error
# --------------------------------------------------------------------------------------------


def pareto_section(rep: Report, stride) -> None:
    rep.add("## Speed against error", "")
    out = rep.results / "report"
    # Width.
    rep.add("### Network width", "")
    shipped = (rep.results / "width_shipped_study" / "results.json").exists()
    width = (rep.load("width", "width_shipped_study/results.json") if shipped
             else rep.load("width_old", "width_unsharp2_study/results.json"))
    if width:
        pts = [(k, v["infer_ms_per_patch"], v["heldout"]["all"]["signed_mean"],
                v["heldout"]["all"]["n"], v["steps"],
                v["heldout"]["all"]["signed_std"] / max(v["heldout"]["all"]["n"], 1) ** 0.5)
               for k, v in width.items() if "heldout" in v]
        budget = ("equal step budget, the shipped recipe" if shipped
                  else "5-min training budget each")
        markdown.plot(out / "pareto_width.png",
              lambda ax: markdown.label_points(ax, [p[1] for p in pts], [p[2] for p in pts],
                                       [p[0] for p in pts]),
              "inference ms per 128x128 patch", "held-out signed score", f"width ({budget})")
        # Unpaired standard error of each mean (every width scores the same patches, so the
        # gaps between widths are less noisy than this).
        rep.add("| model | ms/patch | held-out signed score ± s.e. | n | steps |",
                "|---|---|---|---|---|",
                *[f"| {k} | {ms:.1f} | {s:+.1f} ± {se:.1f} | {n} | {st} |"
                  for k, ms, s, n, st, se in pts], "")
        if not shipped:
            rep.add("Caveat: a session-2 study (5-minute training budget per width, order-0 "
                    "unsharp base at sigma 8), not the shipped recipe; the study at the shipped "
                    f"recipe is `{COMMANDS['width']}`.", "")
        rep.image("report/pareto_width.png", "width Pareto")
    else:
        rep.not_run("the width study", "width")
    rep.add("### Patch stride", "")
    if stride:
        rep.add("Plotted by the stride ablation above (`stride/pareto.png`).", "")
    else:
        rep.not_run("the stride ablation", "stride")
    # Lifting solver.
    rep.add("### Lifting solver (iterations / tolerance)", "")
    lift = rep.load("lift", "lift/bench.json")
    if lift and lift.get("speed_vs_error_10k"):
        curves = lift["speed_vs_error_10k"]
        cols = curves["columns"]
        tc, ac = cols.index("seconds"), cols.index("angle_error_deg")

        def draw(ax):
            for name in ("gauss_newton", "adam_lr0.1", "lbfgs"):
                pts = curves.get(name) or []
                ax.plot([p[tc] * 1e3 for p in pts], [p[ac] for p in pts], "o-", ms=3,
                        label=name)
            ax.set_xscale("log")
            ax.legend(fontsize=8)

        markdown.plot(out / "pareto_lift.png", draw, "ms per frame (cumulative over iterations)",
              "mean normal angle error (deg)", f"lifting, {curves['vertices']} vertices")
        s = lift.get("summary_10k", {})
        ref = s.get("reference_final", {})
        rep.add(f"Reference (Adam, the authors' solver): {ref.get('seconds_per_frame', 0):.2f} "
                f"s/frame, {ref.get('angle_error_deg', 0):.2f} deg; Gauss-Newton reaches that "
                f"error in {s.get('gn_per_frame_at_reference_error_s') or float('nan'):.3f} "
                f"s/frame ({s.get('gn_speedup_at_reference_error')}x).", "")
        rep.image("report/pareto_lift.png", "lifting solver Pareto")
    else:
        rep.not_run("the lifting benchmark's speed-against-error curves", "lift")
    # Simulator substeps.
    rep.add("### Simulator substeps", "")
    sub = rep.load("substeps", "sim/substeps.json")
    rows = (sub or {}).get("substeps") or []
    if rows:
        keys = [k for k in ("strain_p99", "strain_mean") if k in rows[0]]
        ykey = keys[0] if keys else None
        if ykey and "ms_per_frame" in rows[0]:
            markdown.plot(out / "pareto_substeps.png",
                  lambda ax: markdown.label_points(ax, [r["ms_per_frame"] for r in rows],
                                           [r[ykey] for r in rows],
                                           [str(r["substeps"]) for r in rows]),
                  "ms per frame", ykey, "simulator substeps")
            rep.image("report/pareto_substeps.png", "substeps Pareto")
        rep.add("```", json.dumps(rows, indent=1)[:2500], "```", "")
    else:
        rep.not_run("the simulator substep sweep", "substeps")
    # VGG layers.
    rep.add("### VGG layers (training cost against discriminative power)", "")
    ls = rep.load("layer_selection", "layer_selection/table.json")
    if ls:
        rows = ls["rows"]
        markdown.plot(out / "pareto_vgg_layers.png",
              lambda ax: markdown.label_points(ax, [r["step_ms_to_layer"] for r in rows],
                                       [r["knn_full"] for r in rows],
                                       [r["layer"] for r in rows]),
              "VGG19 forward+backward to the layer, ms per batch step",
              "kNN material accuracy of the layer's Grams", "VGG layers")
        rep.add(f"From `layer_selection/table.md` ({ls['n_per_set']} patches per set): the "
                "cost of running VGG19 up to a layer in a training step against how well "
                "that layer's Gram matrices separate materials.", "")
        rep.image("report/pareto_vgg_layers.png", "VGG layer Pareto")
    else:
        rep.not_run("the VGG layer study", "layer_selection")


def machines_section(rep: Report) -> None:
    rep.add("## Commands and machines", "", "| result | command | machine |", "|---|---|---|")
    for name, cmd in rep.commands.items():
        m = rep.machines.get(name)
        cpu = f"{cpu_text(m)}, " if m and m.get("cpu_model") else ""
        mtext = (f"{m.get('cpu_count')} CPUs, {cpu}{m.get('platform')}, jax {m.get('jax')}, "
                 f"load {m.get('load_avg_1min')}" if m else "-")
        rep.add(f"| {name} | `{cmd}` | {mtext} |")
    rep.add("", "Regenerate this report: `python -m experiments.report`.", "")
    if rep.missing:
        rep.add("## Not run yet", "", *[f"- {n}: " + (f"`{c}`" if c != "no script yet" else c)
                                        for n, c in rep.missing], "")


def build(results: Path) -> Report:
    """Read every stored result under `results` and lay out the report."""
    rep = Report(results)
    t1 = rep.load("table1", "table1/results.json")
    t2 = rep.load("table2", "table2/results.json")
    stride = rep.load("stride", "stride/results.json")
    temporal = rep.load("temporal", "temporal/results.json")
    timing = rep.load("timing", "timing/results.json")
    rep.add("# wrinkle-jax evaluation report", "",
            f"Generated {datetime.date.today().isoformat()} by `python -m experiments.report` "
            f"from the stored results under `experiments/results/` (commit "
            f"{git_commit(suite.ROOT) or 'unknown'}). Scores: the improvement score on the Gram "
            "matrices of relu1_2 ... relu5_1 (100 = the fine simulation's style, 0 = the "
            "coarse input's, < 0 = further away; the paper's form takes |.|, which counts "
            "overshoot as improvement).", "")
    fid = rep.load("fidelity", "fidelity/results.json")
    headline(rep, t1, t2, timing, temporal, card=rep.load("model_card", "model_card/results.json"),
             pg=rep.load("patchgan", "patchgan/results.json"),
             sheet=rep.load("sheet_only", "sheet_only/results.json"), fid=fid)
    fidelity_section(rep, fid)
    table1_section(rep, t1)
    table2_section(rep, t2)
    table2_section(rep, rep.load("table2_detail", "table2_detail/results.json"), "table2_detail",
                   "## Table 2 on detail features (issue 21's representation)",
                   "The same sets and distances as Table 2, on detail maps: each coarse (a) and "
                   "fine (c) patch's own large scale rotated to +z, each method's output (b) on "
                   "its input's branch (`python -m experiments.table2 --features detail`).")
    baselines_section(rep, t1)
    ablations_section(rep, t1, stride)
    temporal_section(rep, temporal)
    timing_section(rep, timing)
    reference_section(rep, rep.load("reference_unet", "timing/reference_unet.json"),
                      rep.load("reference_train", "timing/reference_train.json"))
    avx2 = rep.load("reference_avx2", "timing/reference_s46b_avx2.json")
    if avx2:
        reference_section(rep, avx2, avx2, "### Beside the authors' code on a CPU without "
                                           "bfloat16 dot units")
    ceiling_section(rep, rep.load("ceiling", "timing/ceiling.json"))
    pareto_section(rep, stride)
    machines_section(rep)
    return rep


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default=str(suite.RESULTS))
    ap.add_argument("--out", default=None, help="default: <results>/REPORT.md")
    ap.add_argument("--strict", action="store_true", help="fail if any result is missing")
    args = ap.parse_args(argv)
    results = Path(args.results)
    rep = build(results)
    out = Path(args.out) if args.out else results / "REPORT.md"
    out.write_text("\n".join(rep.lines).rstrip() + "\n")
    print(f"wrote {out} ({len(rep.lines)} lines); missing: "
          f"{', '.join(n for n, _ in rep.missing) or 'nothing'}")
    if args.strict and rep.missing:
        print("missing results: " + "; ".join(f"{n} ({c})" for n, c in rep.missing),
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
