"""Detail-only evaluation on real coarse simulations: ceilings, baselines and models.

    python -m experiments.fidelity sweep [--data data/pairs]     # unsharp settings, val split
    python -m experiments.fidelity sweep-material                 # the same per material
    python -m experiments.fidelity score [--model NAME=PATH ...] [--cells unseen|all]
    python -m experiments.fidelity report                         # results.json + README.md

`sweep` picks the unsharp mask (order 1; sigma x amount grid) with the best median detail-only
score on the VAL split of the pair data set (`experiments.make_pair_dataset`: last frames of
the training scenes), so the baseline is tuned without held-out data.

`score` draws Table 1's patches (`evaluation.cells`: first 200 frames, seed 1, every
`--frame-stride`-th frame from `--frame-offset`, 8 patches per frame among grid patches
>= 50 % covered by both meshes; the same origins as Table 1 for the frames it shares) from the
coarse and fine simulations of each cell and scores, against the fine patch of the same frame:

  identity, unsharp       the input, and the swept unsharp mask
  shipped, NAME ...       the shipped enhancer and every --model
  oracle_detail           the coarse patch's own large scale + the fine patch's exact detail
                          (`wrinkle_jax.detail`): the ceiling of a detail enhancer
  oracle_downsampled      the fine map downsampled as in the old training data (D): fine
                          large scale, no detail
  oracle_next_frame       the fine patch of the next frame (t + 1)
  oracle_energy_gain      the unsharp mask at the gain (0-4) whose 16-64 mm detail energy is
                          closest to the fine patch's: the ceiling of "the right amount"
  oracle_energy_gain_signed  the same with smoothing gains (-0.75 to -0.25) allowed too

with the detail-only score (primary; `evaluation.score_patches(detail_sigma=...)`) and, for
the non-oracle methods and oracle_detail, the paper's object-space score; plus the band RMS of
each output's detail (< 16 mm, 16-64 mm; `evaluation.band_rms`) and the 2-texel checkerboard
RMS (`evaluation.checker_rms`). Cells are cached under `experiments/results/fidelity/cells/`
method by method (models by file digest), so adding a model scores only it.

`report` pools the cells: per method the signed median and mean, the paired median difference
against unsharp with its 95 % bootstrap interval, per-cell medians, band-energy ratios to the
fine simulation's and the checkerboard level.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from wrinkle_jax import (
    MATERIALS,
    data,
    detail,
    enhancer,
    evaluation,
    material_index,
    normalmap,
    patches,
)
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import energy, gram, patchsets, suite
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.nn import vgg

OUT = suite.RESULTS / "fidelity"
SIGMA = detail.DEFAULT_SIGMA
SWEEP = [(s, a) for s in (2.0, 4.0, 8.0, 16.0) for a in (0.5, 1.0, 2.0, 3.0)]
ORACLES = ("oracle_detail", "oracle_downsampled", "oracle_next_frame", "oracle_energy_gain",
           "oracle_energy_gain_signed")
ENERGY_GAINS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)
SMOOTHING_GAINS = (-0.75, -0.5, -0.25)  # amount < 0: n + a (n - blur n) moves n towards its blur
# + every model:
OBJECT_SPACE = ("identity", "unsharp", "unsharp_card", "unsharp_material", "oracle_detail")
BASELINES = ("unsharp", "unsharp_card", "unsharp_material")


def sweep(args, vgg_params) -> dict:
    ds = data.PatchDataset(args.data, "val")
    idx = np.linspace(0, len(ds) - 1, min(args.sweep_patches, len(ds))).round().astype(int)
    b = ds.get(np.unique(idx))
    inp, tgt, mask = b["input"], b["target"], b["mask"]
    names = [f"sigma={s:g},amount={a:g}" for s, a in SWEEP]
    d_in, d_tgt, *d_outs = (np.asarray(x) for x in detail.on_reference_branch_rgb(
        inp, (tgt, *(evaluation.unsharp_mask(inp, mask, s, a, order=1) for s, a in SWEEP)),
        mask, SIGMA))
    outs = dict(zip(names, d_outs, strict=True))
    losses = gram.method_losses(vgg_params, d_in, d_tgt, mask, outs)
    res = {}
    for k in outs:
        sc = evaluation.scores_from_losses(losses["input"], losses[k])
        res[k] = float(np.median(sc["improvement_signed"][sc["valid"]]))
        print(f"unsharp {k}: median detail score {res[k]:+.1f}", flush=True)
    best = max(res, key=res.get)
    got = {"split": "val", "patches": int(len(inp)), "detail_sigma": SIGMA,
           "median_detail_score": res, "best": best, "data": suite.portable_path(args.data)}
    suite.write_json(OUT / "unsharp_sweep.json", got)
    return got


MATERIAL_AMOUNTS = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)


def sweep_per_material(args, vgg_params) -> dict:
    """The unsharp gain per material: median detail-only score of each `MATERIAL_AMOUNTS` gain
    at each `--sweep-sigmas` radius on `--sweep-patches` val patches PER MATERIAL (evenly
    spaced), written to unsharp_sweep_material.json with each material's best setting. Val
    split only."""
    ds = data.PatchDataset(args.data, "val")
    sweep = [(float(s), a) for s in args.sweep_sigmas.split(",") for a in MATERIAL_AMOUNTS]
    names = [f"sigma={s:g},amount={a:g}" for s, a in sweep]
    res, best = {}, {}
    for mid, mat in enumerate(MATERIALS):
        rows = np.flatnonzero(ds.materials == mid)
        if not len(rows):
            continue
        pick = rows[np.unique(np.linspace(0, len(rows) - 1, min(args.sweep_patches, len(rows)))
                              .round().astype(int))]
        b = ds.get(pick)
        inp, tgt, mask = b["input"], b["target"], b["mask"]
        d_in, d_tgt, *d_outs = (np.asarray(x) for x in detail.on_reference_branch_rgb(
            inp, (tgt, *(evaluation.unsharp_mask(inp, mask, s, a, order=1)
                         for s, a in sweep)), mask, SIGMA))
        outs = dict(zip(names, d_outs, strict=True))
        losses = gram.method_losses(vgg_params, d_in, d_tgt, mask, outs)
        res[mat] = {}
        for k in names:
            sc = evaluation.scores_from_losses(losses["input"], losses[k])
            v = sc["valid"]
            res[mat][k] = {"median": float(np.median(sc["improvement_signed"][v])),
                           "mean": float(np.mean(sc["improvement_signed"][v]))}
        best[mat] = max(res[mat], key=lambda k: res[mat][k]["median"])
        print(f"{mat}: best {best[mat]} median {res[mat][best[mat]]['median']:+.1f} "
              f"(amount 1: {res[mat][names[MATERIAL_AMOUNTS.index(1.0)]]['median']:+.1f})",
              flush=True)
    got = {"split": "val", "patches_per_material": int(args.sweep_patches),
           "detail_sigma": SIGMA, "unsharp_sigmas": args.sweep_sigmas, "scores": res, "best": best,
           "data": suite.portable_path(args.data)}
    suite.write_json(OUT / "unsharp_sweep_material.json", got)
    return got


def load_model(spec: str) -> enhancer.Enhancer:
    """A `--model` path, optionally ``PATH@G``: the model with residual gain G
    (`UNetConfig.residual_gain`, an inference-time amplitude chosen on validation data)."""
    path, _, gain = spec.partition("@")
    enh = enhancer.load_enhancer(path)
    return enhancer.with_unet(enh, residual_gain=float(gain)) if gain else enh


def val_models(args, vgg_params) -> dict:
    """Models against the per-material unsharp base ON THE VAL SPLIT (the training scenes'
    last frames): per material, `--sweep-patches` evenly spaced val patches, detail-only
    signed median of each `--model` and of unsharp_material, and the paired difference
    model - unsharp_material (95 % bootstrap). This is what checkpoint and recipe choices
    read; the held-out scenes are never touched here. Texel-noise models get fixed
    pseudo-random patch origins (the val patches carry none)."""
    scenes = args.val_scenes.split(",") if args.val_scenes else None
    ds = data.PatchDataset(args.data, args.split, scenes=scenes)
    settings = method_lib.material_unsharp_settings()
    models = {}
    for spec in args.model:
        name, path = spec.split("=", 1)
        models[name] = method_lib.enhancer_method(load_model(path))
    rng = np.random.default_rng(0)
    donor_rng = np.random.default_rng(0)
    scores = {k: [] for k in ["unsharp_material", *models,
                              *(TRANSPLANTS if args.transplant else ())]}
    mats = []
    bands: dict = {}  # method -> band -> per-patch RMS of the detail (and the 2-texel checker)
    picks = {}
    for mid in range(len(MATERIALS)):
        rows = np.flatnonzero(ds.materials == mid)
        picks[mid] = rows[np.unique(np.linspace(0, len(rows) - 1,
                                                min(args.sweep_patches, len(rows)))
                                    .round().astype(int))]
    for mid, mat in enumerate(MATERIALS):
        pick = picks[mid]
        if not len(pick) or mid not in settings:
            continue
        b = ds.get(pick)
        ps = patchsets.PatchSet(input=b["input"], target=b["target"], mask=b["mask"],
                              origins=rng.integers(0, 4096, (len(pick), 2)).astype(np.int32),
                              material_id=mid)
        outs = {"unsharp_material": evaluation.unsharp_mask(ps.input, ps.mask, *settings[mid],
                                                            order=1)}
        outs.update({k: f(ps) for k, f in models.items()})
        if args.transplant:
            outs.update(transplants(ds, ps, picks, mid, donor_rng))
        outs = {k: np.asarray(v, np.float32) * ps.mask for k, v in outs.items()}
        d_in, d_tgt, *d_outs = (np.asarray(x) for x in detail.on_reference_branch_rgb(
            ps.input, (ps.target, *outs.values()), ps.mask, SIGMA))
        losses = gram.method_losses(vgg_params, d_in, d_tgt, ps.mask,
                                  dict(zip(outs, d_outs, strict=True)))
        for k, d_k, img in (("target", d_tgt, ps.target),
                            *zip(outs, d_outs, outs.values(), strict=True)):
            b = evaluation.band_rms(d_k, ps.mask)
            bands.setdefault(k, {"lt16mm": [], "16_64mm": [], "checker": []})
            bands[k]["lt16mm"].append(np.asarray(b["lt16mm"]))
            bands[k]["16_64mm"].append(np.asarray(b["16_64mm"]))
            bands[k]["checker"].append(np.asarray(evaluation.checker_rms(img, ps.mask)))
        for k in outs:
            sc = evaluation.scores_from_losses(losses["input"], losses[k])
            scores[k].append(np.where(sc["valid"], sc["improvement_signed"], np.nan))
        mats += [mat] * len(pick)
    mats = np.asarray(mats)
    got = {"split": args.split, "scenes": scenes,
           "patches_per_material": int(args.sweep_patches),
           "detail_sigma": SIGMA, "models": {k: suite.portable_path(p.split("=", 1)[1])
                                             for k, p in zip(models, args.model, strict=True)},
           "methods": {}}
    cat = {k: np.concatenate(v) for k, v in scores.items()}
    fine = {b: float(np.mean(np.concatenate(v))) for b, v in bands["target"].items()}
    for k, sc in cat.items():
        v = np.isfinite(sc)
        entry = {"median": float(np.median(sc[v])), "mean": float(np.mean(sc[v])),
                 "material_medians": {m: float(np.nanmedian(sc[mats == m]))
                                      for m in dict.fromkeys(mats)}}
        if k in bands:  # mean band energy relative to the fine target's (as `summarize`)
            entry["band_ratio_to_fine"] = {
                b: float(np.mean(np.concatenate(v))) / max(fine[b], 1e-12)
                for b, v in bands[k].items()}
        if k != "unsharp_material":
            base = cat["unsharp_material"]
            entry["vs_unsharp_material"] = evaluation.paired_difference(
                np.nan_to_num(sc), np.nan_to_num(base), v & np.isfinite(base))
        got["methods"][k] = entry
        print(f"{k}: {args.split} median {entry['median']:+.1f} (mean {entry['mean']:+.1f}) "
              + ", ".join(f"{m} {x:+.1f}" for m, x in entry["material_medians"].items())
              + "; bands/fine " + ", ".join(f"{b} {x:.2f}" for b, x in
                                             entry.get("band_ratio_to_fine", {}).items()),
              flush=True)
    return got


TRANSPLANTS = ("oracle_aligned", "transplant_same_material", "transplant_same_rot90",
               "transplant_other_material")


def transplants(ds, ps, picks, mid, rng) -> dict:
    """The coarse input's large scale carrying fine detail from elsewhere (val diagnostic): its
    own target's (the aligned ceiling), another val patch's of the same material (real
    wrinkles of the right fabric, not aligned with this patch), the same turned 90 degrees (the
    detail vectors turned with it), and a patch of another material. Does the detail-only
    score reward this patch's detail, or any plausible texture of the fabric?"""
    n = len(ps.input)
    own = np.asarray(detail.to_detail_rgb(ps.target, ps.mask, SIGMA))
    flat = np.float32([0.5, 0.5, 1.0])
    own = np.where(ps.mask > 0, own, flat)
    donor = np.roll(np.arange(n), 7)

    def rot90(d):
        v = np.rot90(d, 1, axes=(1, 2)) * 2.0 - 1.0
        return (np.stack([-v[..., 1], v[..., 0], v[..., 2]], -1) + 1.0) / 2.0

    _, large, branch = detail.decompose(ps.input * 2.0 - 1.0, ps.mask, SIGMA)

    def put(d):  # detail maps (flat +z outside their garment) on the input's large scale
        return detail.from_detail_rgb(d, large, branch, ps.mask)

    other = (mid + 1 + rng.integers(0, len(MATERIALS) - 1)) % len(MATERIALS)
    b = ds.get(picks[other][:n])
    return {"oracle_aligned": put(own),
            "transplant_same_material": put(own[donor]),
            "transplant_same_rot90": put(rot90(own[donor])),
            "transplant_other_material": detail.transplant_rgb(ps.input, b["target"], ps.mask,
                                                               b["mask"], SIGMA)}


def unsharp_best() -> tuple[float, float]:
    best = json.loads((OUT / "unsharp_sweep.json").read_text())["best"]
    kv = dict(p.split("=") for p in best.split(","))
    return float(kv["sigma"]), float(kv["amount"])


def _cell_file(cell: cell_lib.Cell, root: Path = OUT) -> Path:
    return root / "cells" / f"{cell.scene.name}__{cell.material}.npz"


def _load_cell(path: Path) -> dict:
    if not path.exists():
        return {}
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["json"]))


def _frames_digest(*frame_sets) -> str:
    """sha1 of the float32 vertex positions of the given (T, V, 3) frame stacks."""
    h = hashlib.sha1()
    for f in frame_sets:
        h.update(np.ascontiguousarray(np.asarray(f, np.float32)).tobytes())
    return h.hexdigest()


def score_cell(cell: cell_lib.Cell, methods: dict, sources: dict, vgg_params, args) -> dict:
    """Scores of `methods` (name -> callable(PatchSet, extras) -> outputs) on one cell, merged
    into the cached ones (a method is recomputed only when its source changed)."""
    path = _cell_file(cell, Path(args.score_dir))
    cached = _load_cell(path)
    frames = list(range(args.frame_offset, args.frames - 1, args.frame_stride))
    seqs = cell_lib.cell_sequences(cell, args.frames, log=lambda m: print(m, flush=True))
    fine = cell_lib.load_first_frames(seqs["fine"], args.frames)  # t + 1 <= the last frame
    coarse = cell_lib.load_first_frames(seqs["coarse"], args.frames)
    # The simulations themselves are part of the fingerprint: a re-simulated cell (another
    # machine's floating point diverges chaotically) invalidates every cached method, since
    # the input's and the methods' losses must come from the same patches.
    fp = {"frames": frames, "patches_per_frame": args.patches, "sigma": SIGMA,
          "simulations": _frames_digest(fine.frames, coarse.frames)}
    if not args.object_space:  # a detail-only cache is never mixed with a full one
        fp["object_space"] = False
    if cached.get("fingerprint") != fp:
        cached = {}
    todo = {k: f for k, f in methods.items()
            if k not in cached.get("methods", {}) or cached["sources"].get(k) != sources[k]}
    if not todo and cached:
        return cached
    size = 128
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, normalmap.DEFAULT_TEXEL_SIZE)
    mask_full = np.asarray(patches.pad_to_patch(pair.mask, size)[0])
    cand, _ = patchsets.candidate_origins(mask_full, size, size // 2, 0.5)
    mid = material_index(cell.material)
    got = {k: {"detail": [], "object": [], "lt16mm": [], "16_64mm": [], "checker": []}
           for k in [*todo, "input", "target"]}
    for t in frames:
        sel = patchsets.choose_origins(cand, args.patches, (0, *cell.patch_seed, t))
        ps = patchsets.aligned_patches(pair, fine.frames[t], coarse.frames[t], sel, size, mid)
        extras = {"next": patchsets.aligned_patches(pair, fine.frames[t + 1], coarse.frames[t], sel,
                                                    size, mid).target,
                  "fine_map": fine.frames[t], "pair": pair}
        outs = {k: np.asarray(f(ps, extras), np.float32) * ps.mask for k, f in todo.items()}
        imgs = {"target": ps.target, **outs}
        d = dict(zip(["input", *imgs], (np.asarray(x) for x in detail.on_reference_branch_rgb(
            ps.input, tuple(imgs.values()), ps.mask, SIGMA)), strict=True))
        det = gram.method_losses(vgg_params, d["input"], d["target"], ps.mask,
                                 {k: d[k] for k in outs})
        obj_names = [k for k in outs if k in OBJECT_SPACE or k not in ORACLES]
        obj = gram.method_losses(vgg_params, ps.input, ps.target, ps.mask,
                                 {k: outs[k] for k in obj_names}) if args.object_space else {}
        for k in [*outs, "input", "target"]:
            bands = evaluation.band_rms(d[k], ps.mask)
            img = {"input": ps.input, "target": ps.target, **outs}[k]
            got[k]["lt16mm"] += bands["lt16mm"].tolist()
            got[k]["16_64mm"] += bands["16_64mm"].tolist()
            got[k]["checker"] += evaluation.checker_rms(img, ps.mask).tolist()
        got["input"]["detail"] += det["input"].tolist()
        got["input"]["object"] += obj["input"].tolist() if obj else []
        for k in outs:
            got[k]["detail"] += det[k].tolist()
            got[k]["object"] += obj[k].tolist() if k in obj else []
        print(f"  {cell.key} frame {t}: " + ", ".join(
            f"{k} {np.median(100 * (1 - det[k] / det['input'])):+.0f}" for k in outs),
            flush=True)
    result = {"cell": cell.key, "kind": cell.kind, "fingerprint": fp,
              "sources": {**cached.get("sources", {}), **{k: sources[k] for k in todo}},
              "loss_input": {"detail": got["input"]["detail"], "object": got["input"]["object"]},
              "bands": {k: {b: got[k][b] for b in ("lt16mm", "16_64mm", "checker")}
                        for k in ("input", "target")},
              "methods": {**cached.get("methods", {}), **{k: got[k] for k in todo}}}
    if cached.get("bands"):  # keep the stored input/target bands (same patches)
        result["bands"] = cached["bands"]
    path.parent.mkdir(parents=True, exist_ok=True)
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, json=np.asarray(json.dumps(result)))
    from wrinkle_jax.fileio import atomic_write_bytes

    atomic_write_bytes(path, buf.getvalue())
    return result


def build_methods(args) -> tuple[dict, dict]:
    s, a = unsharp_best()
    methods = {
        "identity": lambda p, e: p.input,
        "unsharp": lambda p, e: evaluation.unsharp_mask(p.input, p.mask, s, a, order=1),
    }
    sources = {"identity": "identity", "unsharp": f"order=1,sigma={s:g},amount={a:g}"}
    # The shipped recipe's unsharp setting (the model card's object-space sweep), as a second
    # baseline: the val sweep's stronger gain over-sharpens the held-out denim.
    s1, a1, _ = method_lib.unsharp_setting(order=1)
    methods["unsharp_card"] = lambda p, e: evaluation.unsharp_mask(p.input, p.mask, s1, a1,
                                                                   order=1)
    sources["unsharp_card"] = f"order=1,sigma={s1:g},amount={a1:g}"
    # Per-material gains from the val sweep (sweep-material): the base a material-conditioned
    # model starts from, so "model minus its own base" is measured, not assumed.
    settings = method_lib.material_unsharp_settings()
    if settings:
        methods["unsharp_material"] = lambda p, e: evaluation.unsharp_mask(
            p.input, p.mask, *settings[p.material_id], order=1)
        sources["unsharp_material"] = "order=1," + ";".join(
            f"{MATERIALS[i]}:sigma={s:g},amount={a:g}" for i, (s, a) in sorted(settings.items()))
    models = {"shipped": str(enhancer.DEFAULT_PATH)}
    for spec in args.model:
        name, path = spec.split("=", 1)
        models[name] = path
    for name, path in models.items():
        enh = load_model(path)
        methods[name] = (lambda fn: (lambda p, e: fn(p)))(method_lib.enhancer_method(enh))
        file, _, gain = path.partition("@")
        sources[name] = suite.file_digest(file) + (f"@{gain}" if gain else "")
    if args.ceilings:
        def oracle_detail(p, e):
            d_in, large, branch = detail.decompose(p.input * 2.0 - 1.0, p.mask, SIGMA)
            d_f = detail.to_detail_rgb(p.target, p.mask, SIGMA, branch)
            return detail.from_detail_rgb(d_f, large, branch, p.mask)

        def oracle_down(p, e):
            fmap = patchsets.bake_map(e["pair"].fine, e["fine_map"])
            m = np.asarray(e["pair"].mask)
            down = normalmap.downsample_like_coarse(fmap, m, 0.03 / normalmap.DEFAULT_TEXEL_SIZE)
            img = normalmap.to_rgb(patches.pad_to_patch(np.asarray(down), 128)[0])
            return patchsets.cut(np.asarray(img), p.origins, 128)

        def oracle_energy_gain(p, e, gains=ENERGY_GAINS):
            # Per patch, the unsharp gain whose 16-64 mm detail energy is closest to the
            # fine target's (experiments.energy_oracle): the right AMOUNT of detail, known.
            sigma = settings[p.material_id][0] if settings else s
            sw = energy.gain_sweep(p.input, p.target, p.mask, sigma, gains, SIGMA)
            pick = energy.matched_gain_choice(sw["band_out"], sw["band_target"])
            return np.stack(sw["outputs"], 1)[np.arange(len(pick)), pick]

        methods.update({"oracle_detail": oracle_detail, "oracle_downsampled": oracle_down,
                        "oracle_next_frame": lambda p, e: e["next"],
                        "oracle_energy_gain": oracle_energy_gain,
                        "oracle_energy_gain_signed": lambda p, e: oracle_energy_gain(
                            p, e, SMOOTHING_GAINS + ENERGY_GAINS)})
        sources.update({k: k for k in ORACLES})
    return methods, sources


def summarize(cells: list[dict]) -> dict:
    out = {}
    kinds = {"unseen garment": [c for c in cells if c["kind"] == "unseen garment"],
             "seen garment": [c for c in cells if c["kind"] != "unseen garment"]}
    for kind, cs in kinds.items():
        if not cs:
            continue
        names = [k for k in cs[0]["methods"] if all(k in c["methods"] for c in cs)]
        res = {"cells": [c["cell"] for c in cs], "methods": {}}
        for space in ("detail", "object"):
            li = np.concatenate([c["loss_input"][space] for c in cs])
            if not len(li):  # scored with --object-space 0
                continue
            scores = {}
            for k in names:
                lo = np.concatenate([c["methods"][k][space] for c in cs])
                if len(lo) != len(li):
                    continue
                scores[k] = evaluation.scores_from_losses(li, lo)
            for k, sc in scores.items():
                v = sc["valid"]
                entry = res["methods"].setdefault(k, {})
                entry[space] = {"n": int(v.sum()),
                                "signed_median": float(np.median(sc["improvement_signed"][v])),
                                "signed_mean": float(np.mean(sc["improvement_signed"][v])),
                                "abs_mean": float(np.mean(sc["improvement"][v]))}
                for base in BASELINES:
                    if base in scores and k != base:
                        key = "vs_unsharp" if base == "unsharp" else f"vs_{base}"
                        entry[space][key] = evaluation.paired_difference(
                            sc["improvement_signed"], scores[base]["improvement_signed"],
                            v & scores[base]["valid"])
                per_cell, start = {}, 0
                for c in cs:
                    n = len(c["loss_input"][space])
                    sl = slice(start, start + n)
                    per_cell[c["cell"]] = float(np.median(sc["improvement_signed"][sl][v[sl]]))
                    start += n
                entry[space]["cell_medians"] = per_cell
        tgt = {b: np.concatenate([c["bands"]["target"][b] for c in cs])
               for b in ("lt16mm", "16_64mm", "checker")}
        res["fine_bands"] = {b: float(np.mean(v)) for b, v in tgt.items()}
        for k in ["input", *names]:
            src = [c["bands"]["input"] if k == "input" else c["methods"][k] for c in cs]
            e = res["methods"].setdefault(k, {})
            e["bands"] = {b: float(np.mean(np.concatenate([s[b] for s in src])))
                          for b in ("lt16mm", "16_64mm", "checker")}
            e["band_ratio_to_fine"] = {b: e["bands"][b] / max(res["fine_bands"][b], 1e-12)
                                       for b in ("lt16mm", "16_64mm", "checker")}
        out[kind] = res
    return out


def main(argv=None) -> int:
    ap = suite.script_parser(__doc__)
    ap.add_argument("command", choices=("sweep", "sweep-material", "val", "score", "report"))
    ap.add_argument("--data", default=str(suite.ROOT / "data" / "pairs"))
    ap.add_argument("--sweep-patches", type=int, default=96)
    ap.add_argument("--sweep-sigmas", default="16",
                    help="sweep-material: comma-separated unsharp radii (texels)")
    ap.add_argument("--model", action="append", default=[], metavar="NAME=PATH[@GAIN]",
                    help="a model file; @GAIN scales its residual (UNetConfig.residual_gain)")
    ap.add_argument("--cells", default="unseen", choices=("unseen", "all"))
    ap.add_argument("--scenes", default=None,
                    help="comma-separated scene names to keep (e.g. dress_dance,cape_walk)")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--frame-stride", type=int, default=40)
    ap.add_argument("--frame-offset", type=int, default=20,
                    help="first scored frame (frame 0 is the settled start pose, where coarse "
                         "and fine detail are both near zero and every ratio degenerates)")
    ap.add_argument("--patches", type=int, default=8)
    ap.add_argument("--ceilings", type=int, default=1)
    ap.add_argument("--object-space", type=int, default=1,
                    help="score: 0 skips the paper's object-space score (half the VGG passes)")
    ap.add_argument("--baselines", default=None,
                    help="score: comma-separated non-model methods to keep (e.g. "
                         "identity,unsharp_card,unsharp_material); default all")
    ap.add_argument("--score-dir", default=str(OUT),
                    help="score/report: where the per-cell caches (cells/) and results.json "
                         "live; another folder keeps a differently drawn patch set apart from "
                         "the report's")
    ap.add_argument("--val-out", default=None, help="val: write the JSON here")
    ap.add_argument("--split", default="val", choices=("val", "valgarment", "train"),
                    help="val: the pair data's split (val = last frames of the training scenes; "
                         "valgarment = the validation-only garment, a proxy for unseen ones; "
                         "train = the training patches themselves: the gain where it was "
                         "learned)")
    ap.add_argument("--val-scenes", default=None,
                    help="val: only these scenes of the split (comma-separated), e.g. the "
                         "training scenes a model saw against those it did not")
    ap.add_argument("--transplant", type=int, default=0,
                    help="val: also score the coarse input carrying fine detail from its own "
                         "target / other patches (`transplants`)")
    args = ap.parse_args(argv)
    if args.command == "report":
        root = Path(args.score_dir)
        cells = [_load_cell(p) for p in sorted((root / "cells").glob("*.npz"))]
        summary = summarize([c for c in cells if c])
        suite.write_json(root / "results.json", summary)
        print(json.dumps({k: {m: {s: v[s]["signed_median"] for s in ("detail", "object")
                                  if s in v} for m, v in r["methods"].items()}
                          for k, r in summary.items()}, indent=1))
        return 0
    vgg_params = vgg.load_vgg19()
    if args.command == "sweep-material":
        print(json.dumps(sweep_per_material(args, vgg_params)["best"]))
        return 0
    if args.command == "sweep":
        print(json.dumps(sweep(args, vgg_params)["best"]))
        return 0
    if args.command == "val":
        got = val_models(args, vgg_params)
        if args.val_out:
            suite.write_json(Path(args.val_out), got)
        return 0
    methods, sources = build_methods(args)
    if args.baselines is not None:  # the models given with --model are always scored
        keep_b = set(args.baselines.split(","))
        methods = {k: f for k, f in methods.items()
                   if k in keep_b or k in dict(m.split("=", 1) for m in args.model)}
    keep = set(args.scenes.split(",")) if args.scenes else None
    cells = [c for c in cell_lib.table_cells()
             if (args.cells == "all" or c.kind == "unseen garment")
             and (keep is None or c.scene.name in keep)]
    t0 = time.perf_counter()
    for cell in cells:
        score_cell(cell, methods, sources, vgg_params, args)
        print(f"{cell.key} done at {time.perf_counter() - t0:.0f} s", flush=True)
    return main(["report", "--score-dir", args.score_dir])


if __name__ == "__main__":
    raise SystemExit(main())
