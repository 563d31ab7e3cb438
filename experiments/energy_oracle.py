"""How much of the detail-only score is "the right amount of detail per patch", and can the
coarse input tell that amount? (Issue 21 diagnostic; validation data only.)

    python -m experiments.energy_oracle gains [--split valgarment] [--patches 32]
    python -m experiments.energy_oracle strain
    python -m experiments.energy_oracle history

`gains` scores the order-1 unsharp mask (sigma 16 texels) at several gains on `--patches`
patches per material of `--split` (default: the validation garment), and compares, per patch:
each fixed gain; the per-material gain of the val sweep (`unsharp_sweep_material.json`, the
baseline every model is paired against); the best gain per patch (an oracle); the gain whose
16-64 mm detail energy is closest to the FINE TARGET's (`energy.matched_gain_choice`: an
oracle that knows only the amount of detail); and the gain matched to a PREDICTED target
energy, from a per-material log-linear fit of the target's 16-64 mm RMS on the input's
16-64 mm and < 16 mm RMS, fitted on `--fit-split` (the training scenes' last frames).

`strain` asks, texel by texel on whole frames of training and validation scenes, whether the
coarse mesh's in-plane stretches (`energy.principal_stretches` against the pattern) predict
the fine simulation's local 16-64 mm energy beyond the coarse map's own band energies
(`energy.local_band_energy`, 16-texel average): R^2 of a per-material log-linear fit on the
training scenes, evaluated on the validation garment, with and without the stretches.

`history` adds the coarse sequence's past (its 16-64 mm energy 3, 10 and 30 frames back, the
peak over the last second, the local angular change of the coarse normals from t-1) to the
same fits, and, as a reference of how persistent the fine detail is, the fine map's own energy
1 and 10 frames back (oracles: no method has them).

Writes `experiments/results/fidelity/energy_oracle_{gains,strain,history}.json`.
"""

from __future__ import annotations

import json
import time

import numpy as np

from wrinkle_jax import MATERIALS, data, detail, evaluation, meshio
from wrinkle_jax.evaluation import energy, gram, patchsets, suite
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.nn import vgg

OUT = suite.RESULTS / "fidelity"
GAINS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)
SIGMA = detail.DEFAULT_SIGMA
UNSHARP_SIGMA = 16.0
_TRAIN_F, _VAL_F = (90, 180, 270), (40, 80, 120)
STRAIN_JOBS = (  # (scene, material, frames): training scenes, then the validation garment
    ("skirt_dance", "silk_charmeuse", _TRAIN_F), ("skirt_dance", "denim_light", _TRAIN_F),
    ("shawl_dance2", "silk_charmeuse", _TRAIN_F), ("shawl_dance2", "denim_light", _TRAIN_F),
    ("pleated_skirt_dance2", "silk_charmeuse", _TRAIN_F), ("apron_dance", "wool_melton", _TRAIN_F),
    ("circle_skirt_dance2", "silk_charmeuse", _TRAIN_F),
    ("tabard_dance2", "silk_charmeuse", _VAL_F), ("tabard_dance2", "denim_light", _VAL_F),
    ("tabard_dance2", "wool_melton", _VAL_F))
VAL_SCENE = "tabard_dance2"


def _picks(ds, per: int) -> dict[int, np.ndarray]:
    """Evenly spaced patch rows per material id (as experiments.fidelity's val)."""
    out = {}
    for mid in range(len(MATERIALS)):
        rows = np.flatnonzero(ds.materials == mid)
        if len(rows):
            out[mid] = rows[np.unique(np.linspace(0, len(rows) - 1, min(per, len(rows)))
                                      .round().astype(int))]
    return out


def _log_features(b_in: dict, mat: np.ndarray) -> np.ndarray:
    cols = [np.log(np.maximum(b_in["16_64mm"], 1e-9)), np.log(np.maximum(b_in["lt16mm"], 1e-9))]
    return np.stack(cols + [(mat == m).astype(float) for m in range(len(MATERIALS))], 1)


def fit_energy(args) -> np.ndarray:
    """Least-squares coefficients of log target 16-64 mm RMS on `_log_features` (fit split)."""
    ds = data.PatchDataset(args.data, args.fit_split)
    feats, target = [], []
    for mid, pick in _picks(ds, args.fit_patches).items():
        b = ds.get(pick)
        d_in, d_tgt = (np.asarray(x) for x in detail.on_reference_branch_rgb(
            b["input"], (b["target"],), b["mask"], SIGMA))
        bi, bt = evaluation.band_rms(d_in, b["mask"]), evaluation.band_rms(d_tgt, b["mask"])
        ok = (bi["16_64mm"] > 0) & (bi["lt16mm"] > 0) & (bt["16_64mm"] > 0)
        feats.append(_log_features({k: v[ok] for k, v in bi.items()}, np.full(ok.sum(), mid)))
        target.append(np.log(bt["16_64mm"][ok]))
    x, y = np.concatenate(feats), np.concatenate(target)
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ coef
    print(f"energy fit on {args.fit_split}: n {len(y)}, R^2 {1 - resid.var() / y.var():.3f}, "
          f"residual sd {resid.std():.3f} (log)", flush=True)
    return coef


def gains(args, vgg_params) -> dict:
    coef = fit_energy(args)
    mat_gain = {m: amount for m, (_, amount) in method_lib.material_unsharp_settings().items()}
    ds = data.PatchDataset(args.data, args.split)
    scores, band_out, b_tgt, b_in, mats = [], [], [], {"16_64mm": [], "lt16mm": []}, []
    t0 = time.perf_counter()
    for mid, pick in _picks(ds, args.patches).items():
        b = ds.get(pick)
        sw = energy.gain_sweep(b["input"], b["target"], b["mask"], UNSHARP_SIGMA, GAINS, SIGMA)
        d_in, d_tgt, *d_outs = sw["details"]
        names = [f"gain={g:g}" for g in GAINS]
        losses = gram.method_losses(vgg_params, d_in, d_tgt, b["mask"],
                                  dict(zip(names, d_outs, strict=True)))
        sc = [evaluation.scores_from_losses(losses["input"], losses[k]) for k in names]
        scores.append(np.stack([np.where(s["valid"], s["improvement_signed"], np.nan)
                                for s in sc], 1))
        band_out.append(sw["band_out"])
        b_tgt.append(sw["band_target"])
        for k, v in evaluation.band_rms(d_in, b["mask"]).items():
            b_in[k].append(v)
        mats.append(np.full(len(pick), mid))
        print(f"{MATERIALS[mid]}: {len(pick)} patches at {time.perf_counter() - t0:.0f} s",
              flush=True)
    s = np.concatenate(scores)
    valid = np.isfinite(s).all(1)
    s = np.where(np.isfinite(s), s, -np.inf)
    band_out, b_tgt, mats = np.concatenate(band_out), np.concatenate(b_tgt), np.concatenate(mats)
    b_in = {k: np.concatenate(v) for k, v in b_in.items()}
    rows = np.arange(len(s))
    base = s[rows, [GAINS.index(mat_gain[m]) for m in mats]]
    predicted = np.exp(_log_features(b_in, mats) @ coef)
    chosen = {
        **{f"gain={g:g}": s[:, j] for j, g in enumerate(GAINS)},
        "per_material_gain": base,
        "oracle_best_gain": s.max(1),
        "oracle_energy_matched": s[rows, energy.matched_gain_choice(band_out, b_tgt)],
        "predicted_energy_matched": s[rows, energy.matched_gain_choice(band_out, predicted)],
    }
    got = {"split": args.split, "patches_per_material": args.patches, "gains": GAINS,
           "unsharp_sigma": UNSHARP_SIGMA, "detail_sigma": SIGMA, "fit_split": args.fit_split,
           "fit_coef": coef.tolist(), "n_valid": int(valid.sum()),
           "predicted_vs_target_log_sd": float(np.std(np.log(predicted[valid])
                                                      - np.log(np.maximum(b_tgt[valid], 1e-9)))),
           "methods": {}}
    for k, v in chosen.items():
        got["methods"][k] = {
            "median": float(np.median(v[valid])), "mean": float(np.mean(v[valid])),
            "material_medians": {MATERIALS[m]: float(np.median(v[valid & (mats == m)]))
                                 for m in np.unique(mats)},
            "vs_per_material_gain": evaluation.paired_difference(v, base, valid)}
        print(f"{k}: median {got['methods'][k]['median']:+.1f} "
              f"(mean {got['methods'][k]['mean']:+.1f})", flush=True)
    return got


def _load_scene(scene: str, material: str):
    """Fine and coarse training-set sequences of one scene and material, their aligned pair,
    and the texel selection (every 12th texel, >= 12 texels inside both meshes)."""
    import cv2

    root = suite.ROOT / "data" / "sequences" / scene
    fine = meshio.load_sequence(root / f"{material}_fine_s0.npz")
    coarse = meshio.load_sequence(root / f"{material}_coarse_s0.npz")
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, 0.002)
    keep = cv2.erode(pair.mask[..., 0], np.ones((25, 25), np.uint8)) > 0
    grid = np.zeros_like(keep)
    grid[::12, ::12] = True
    return fine, coarse, pair, np.nonzero(keep & grid)


def _bands(plan, frame, m) -> dict:
    """Local 16-64 mm and < 16 mm energies (H, W) of one frame's detail map, and its unit
    normals (H, W, 3)."""
    n = patchsets.bake_map(plan, frame)
    d = np.asarray(detail.to_detail_rgb(((n + 1.0) / 2.0 * m)[None], m[None], SIGMA))[0]
    return {b: energy.local_band_energy(d, m, b) for b in ("16_64mm", "lt16mm")} | {"n": n}


def _present_row(fine, coarse, pair, sel, f):
    """Frame f's columns per sampled texel (fine 16-64 mm energy, coarse 16-64 / < 16 mm
    energies, s_min, s_max; (N, 5)) and the coarse frame's `_bands`."""
    m = pair.mask
    fb, cb = _bands(pair.fine, fine.frames[f], m), _bands(pair.coarse, coarse.frames[f], m)
    st = energy.principal_stretches(coarse.frames[f], coarse.garment)
    smin, smax = (energy.masked_smooth(energy.face_values_to_texels(pair.coarse, st[:, i]),
                                       m, 16.0) for i in (0, 1))
    return np.stack([fb["16_64mm"][sel], cb["16_64mm"][sel], cb["lt16mm"][sel], smin[sel],
                     smax[sel]], 1), cb


def _texel_rows(scene: str, material: str, frames):
    """Per sampled texel: fine 16-64 mm energy, coarse 16-64 / < 16 mm energies, s_min,
    s_max (`_present_row`), frames stacked."""
    loaded = _load_scene(scene, material)
    return np.concatenate([_present_row(*loaded, f)[0] for f in frames])


HISTORY_LAGS = (3, 10, 30)  # frames (30 fps) back for the coarse map's past band energy
HISTORY_COLS = ("coarse 16-64 mm at t-3", "coarse 16-64 mm at t-10", "coarse 16-64 mm at t-30",
                "coarse max 16-64 mm over t-30..t", "coarse normal change t-1 -> t (deg)",
                "fine 16-64 mm at t-1 (oracle)", "fine 16-64 mm at t-10 (oracle)")


def _history_rows(scene: str, material: str, frames):
    """`_texel_rows` plus the coarse sequence's past, per sampled texel (HISTORY_COLS, all
    positive: energies, the max over every 5th frame of the last 30, and the local mean angle
    between the coarse normals of t-1 and t, 16-texel average) and two fine-past oracles."""
    fine, coarse, pair, sel = _load_scene(scene, material)
    m = pair.mask
    out = []
    for f in frames:
        present, cb = _present_row(fine, coarse, pair, sel, f)
        past = {lag: _bands(pair.coarse, coarse.frames[f - lag], m) for lag in
                sorted({*HISTORY_LAGS, *range(5, 31, 5), 1})}
        peak = np.max([past[k]["16_64mm"] for k in range(5, 31, 5)] + [cb["16_64mm"]], 0)
        cosang = np.clip(np.sum(cb["n"] * past[1]["n"], -1), -1.0, 1.0)
        turn = energy.masked_smooth(np.degrees(np.arccos(cosang)), m, 16.0)
        fine_past = [_bands(pair.fine, fine.frames[f - lag], m)["16_64mm"] for lag in (1, 10)]
        cols = [past[lag]["16_64mm"] for lag in HISTORY_LAGS] + [peak, turn, *fine_past]
        out.append(np.concatenate([present, np.stack([c[sel] for c in cols], 1)], 1))
    return np.concatenate(out)


def _gather(row_fn):
    """`row_fn(scene, material, frames)` over STRAIN_JOBS: stacked rows, and per row its scene
    name and material id."""
    rows, scene_of, mat_of = [], [], []
    for scene, mat, frames in STRAIN_JOBS:
        r = row_fn(scene, mat, frames)
        rows.append(r)
        scene_of += [scene] * len(r)
        mat_of += [MATERIALS.index(mat)] * len(r)
        print(f"{scene}/{mat}: {len(r)} texels", flush=True)
    return np.concatenate(rows), np.asarray(scene_of), np.asarray(mat_of)


def history(args) -> dict:
    """Does the coarse sequence's past tell the fine local 16-64 mm energy beyond the present
    frame? Per-material log-linear fits on the training scenes, R^2 on the validation garment."""
    a, scene_of, mat_of = _gather(_history_rows)
    ok = (a > 0).all(1)
    la = np.log(np.where(ok[:, None], a, 1.0))
    dummies = [(mat_of == m).astype(float) for m in np.unique(mat_of)]
    sets = {"present (coarse bands)": [1, 2], "present + stretches": [1, 2, 3, 4],
            "present + stretches + coarse past": [1, 2, 3, 4, 5, 6, 7, 8, 9],
            "coarse past only": [5, 6, 7, 8, 9],
            "oracle: fine at t-1": [10], "oracle: fine at t-10": [11]}
    train, val = ok & (scene_of != VAL_SCENE), ok & (scene_of == VAL_SCENE)
    got = {"jobs": [[s, m, list(f)] for s, m, f in STRAIN_JOBS], "n_train": int(train.sum()),
           "n_val": int(val.sum()), "columns": ["fine 16-64 mm (target)", "coarse 16-64 mm",
                                                "coarse < 16 mm", "s_min", "s_max",
                                                *HISTORY_COLS],
           "fits": {}}
    for name, cols in sets.items():
        x = np.stack([la[:, c] for c in cols] + dummies, 1)
        coef, *_ = np.linalg.lstsq(x[train], la[train, 0], rcond=None)
        r_tr, r_val = la[train, 0] - x[train] @ coef, la[val, 0] - x[val] @ coef
        got["fits"][name] = {"train_r2": float(1 - r_tr.var() / la[train, 0].var()),
                             "val_r2": float(1 - r_val.var() / la[val, 0].var()),
                             "val_resid_sd_log": float(r_val.std()), "coef": coef.tolist()}
        print(name, json.dumps({k: round(v, 3) for k, v in got["fits"][name].items()
                                if k != "coef"}), flush=True)
    return got


def strain(args) -> dict:
    a, scene_of, mat_of = _gather(_texel_rows)
    ok = (a[:, :3] > 0).all(1) & (a[:, 3:] > 0).all(1)
    y = np.log(np.where(ok, a[:, 0], 1.0))

    def design(k, with_strain):
        cols = [np.log(a[k, 1]), np.log(a[k, 2])]
        cols += [(mat_of[k] == m).astype(float) for m in np.unique(mat_of)]
        if with_strain:
            cols += [np.log(a[k, 3]), np.log(a[k, 4])]
        return np.stack(cols, 1)

    train = ok & (scene_of != VAL_SCENE)
    val = ok & (scene_of == VAL_SCENE)
    pct = [5, 25, 50, 75, 95]
    got = {"jobs": [[s, m, list(f)] for s, m, f in STRAIN_JOBS], "n_train": int(train.sum()),
           "n_val": int(val.sum()),
           "s_min_percentiles_5_25_50_75_95": np.percentile(a[train, 3], pct).tolist(),
           "s_max_percentiles_5_25_50_75_95": np.percentile(a[train, 4], pct).tolist(),
           "fits": {}}
    for with_strain in (False, True):
        coef, *_ = np.linalg.lstsq(design(train, with_strain), y[train], rcond=None)
        r_tr = y[train] - design(train, with_strain) @ coef
        r_val = y[val] - design(val, with_strain) @ coef
        key = "with_stretches" if with_strain else "band_energies_only"
        got["fits"][key] = {"train_r2": float(1 - r_tr.var() / y[train].var()),
                            "val_r2": float(1 - r_val.var() / y[val].var()),
                            "val_resid_sd_log": float(r_val.std()), "coef": coef.tolist()}
        print(key, json.dumps(got["fits"][key]), flush=True)
    return got


def main(argv=None) -> int:
    ap = suite.script_parser(__doc__)
    ap.add_argument("command", choices=("gains", "strain", "history"))
    ap.add_argument("--data", default=str(suite.ROOT / "data" / "pairs"))
    ap.add_argument("--split", default="valgarment")
    ap.add_argument("--patches", type=int, default=32)
    ap.add_argument("--fit-split", default="val")
    ap.add_argument("--fit-patches", type=int, default=64)
    args = ap.parse_args(argv)
    if args.command == "gains":
        got = gains(args, vgg.load_vgg19())
    else:
        got = strain(args) if args.command == "strain" else history(args)
    suite.write_json(OUT / f"energy_oracle_{args.command}.json", got)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
