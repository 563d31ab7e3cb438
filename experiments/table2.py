"""Paper Table 2: how close the enhancer's output patches come to FINE-SIMULATION patch statistics
without ground-truth correspondence (Chamfer distances between sets of Gram-matrix features),
against the non-learned baselines.

    python -m experiments.table2 [--model wrinkle_jax/assets/enhancer.npz] [--frames 200]
        [--frame-stride 10] [--patches-per-frame 8] [--out experiments/results/table2]

Cells, sequences and sampling are Table 1's (`experiments.table1`; same flags and defaults): 12
cells garment {flared_skirt (seen), dress, cape} x material {silk_charmeuse, denim_light} x
motion {dance (seen), walk}, seed 1, the first `--frames` frames of a fine (PD 10 mm) and a
coarse (PD 30 mm) simulation, looked up in (or simulated into) the same folders, so nothing is
simulated when Table 1 has run. Per cell, three sets of patches (paper Sec. 6):

  (a) the coarse map's patches at exactly Table 1's frames (0, k, 2k, ...; k = --frame-stride)
      and origins (same candidate grid, same seeded draw);
  (b) a method's output on (a): the model, and every baseline as an alternative (b) (identity,
      unsharp masking of order 0 and 1, bicubic and Lanczos x2 down/up, as in Table 1);
  (c) the fine map's patches at frames that correspond to NO frame of (a): midway between them,
      t + k // 2 (t - k // 2 where that is past the last frame), `--patches-per-frame` per frame
      drawn from the same candidate grid independently of (a)'s draw. Same garment, material,
      motion and stretch of the motion; all within the first `--frames` frames (no extra
      simulation). Shifting (a)'s frames by half the range instead would reuse (a)'s frame set.

All patches are cut to the texels covered by both meshes (the mask of Table 1's scores).

Features: the masked, normalized Gram matrices G_l / R_l on `evaluation.EVAL_LAYERS` (relu1_2,
relu2_1, relu3_1, relu4_1, relu5_1; `evaluation.gram.gram_matrices`, as Table 1's score), each
flattened to its upper triangle (C_l (C_l + 1) / 2 values), divided by that layer's median
vector norm over a and c of the cell (every layer then has a median norm of 1 and contributes
comparably, although relu5_1 has 63 times relu1_2's values; the scale does not depend on the
method under test), and concatenated: 305,888 values per patch (the paper: one 512 x 512 Gram).

Chamfer distance of point sets P and Q (d = Euclidean distance):
    CD(P, Q) = ( mean_{p in P} min_{q in Q} d(p, q) + mean_{q in Q} min_{p in P} d(p, q) ) / 2
C1 = CD(a, c), C2 = CD(b, c); DR = 100 |C1 - C2| / C1 (the paper's form) and the signed
DR_signed = 100 (C1 - C2) / C1 (> 0: the method's patches sit closer to the fine ones than the
input's do; < 0: further away). Two spaces:
  * embedded (the paper's): per method, the 2D spectral embedding
    (`wrinkle_jax.evaluation.spectral_embedding`: Gaussian affinity with the median
    bandwidth, symmetric normalized Laplacian) of a u b u c, scaled to unit RMS distance from
    its centroid (the raw eigenmap shrinks with the number of points; DR does not depend on
    it). C1 therefore differs slightly between methods. The embedding depends on the points
    only through their distances, so it is computed from an exact Euclidean realization of the
    distance matrix (classical MDS) rather than from the 305,888-value vectors.
  * full: the same distances in the feature space itself (a 2D embedding can distort); C1 is
    the same for every method.

Cost (2 CPU cores): the VGG passes per sampled location are (a), (c) and every method output
that differs from the input (identity reuses (a)'s): 2 + 5 = 7, as many as Table 1's (input,
target, 5 outputs), so the defaults (12 cells x 20 frames x 8 patches = 1920 locations) take
about as long as Table 1: ~35-45 min idle at 0.15-0.2 s per VGG patch pass, ~1.5-2 h with
another job on the cores. Distances and embeddings add a few seconds per cell; the Gram
features of a, c and one b set are held at a time (1.2 MB per patch: ~0.6 GB, ~1.1 GB peak).
Each finished cell's numbers and embeddings are stored under `<out>/cells/` and reused by a
rerun with the same settings (`--fresh` ignores them).

Writes `<out>/results.json` (per cell and per method: C1, C2, DR and DR_signed, embedded and
full; their means over the seen garment's cells, the unseen garments' and all; sampling,
timings, machine), `<out>/table.md` (the paper's layout for the model, then every method per
cell) and `<out>/embeddings.png` (per cell, the model's embedding: a grey, b colored, c black).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from wrinkle_jax import detail, evaluation, material_index, patches
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import gram, patchscores, patchsets, suite
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.evaluation import sets as set_lib
from wrinkle_jax.evaluation.setscores import (
    GROUPS,
    SPACES,
    c_frame_indices,
    cell_path,
    cell_record,
    group_of,
    load_cell,
    mean_scores,
    merge_records,
    save_cell,
    table_markdown,
)
from wrinkle_jax.nn import vgg

MODEL = patchscores.MODEL
# Stored cells hold derived numbers: change this text whenever the features, the distances or
# the embedding change, so that a rerun recomputes instead of reusing them.
METRIC = ("v1: upper-triangle Grams on EVAL_LAYERS / median layer norm over a+c; symmetric "
          "mean nearest-neighbour Chamfer; 2D spectral embedding at unit RMS; c at t + k//2")
# The same on detail maps (issue 21's primary representation): each map's own large scale
# rotated to +z before the Gram features, so the coarse and fine simulations' large-scale
# divergence does not count.
METRIC_DETAIL = METRIC + f"; detail maps (wrinkle_jax.detail, sigma {detail.DEFAULT_SIGMA:g})"
# Texture shape without amount: each patch's layer vector of the detail space at unit norm, so
# that the Chamfer distance no longer ranks patches by their detail energy (session 16: in the
# detail space bland patches are nearest to every set, the exact fine patches included).
METRIC_SHAPE = METRIC_DETAIL + "; each patch's layer vectors at unit norm (set_lib.unit_rows)"
METRICS = {"object": METRIC, "detail": METRIC_DETAIL, "detail_shape": METRIC_SHAPE}
FEATURES = tuple(METRICS)


def to_feature_space(space: str, a, mask_a, c, mask_c):
    """The images whose Grams are the features, and the map of method outputs to them.

    Args:
      space: "object" (the maps themselves, the paper's) or "detail" / "detail_shape"
        (`wrinkle_jax.detail`: each a and c patch on its own branch; a method's output b on
        its input's branch, as `detail.on_reference_branch_rgb` pairs them in the detail-only
        score; "detail_shape" differs only in the features, see `evaluate_cell`).
      a, mask_a: (N_a, S, S, 3) RGB-form coarse patches and their (N_a, S, S, 1) masks.
      c, mask_c: (N_c, S, S, 3) RGB-form fine patches and masks.
    Returns:
      (a', c', b_fn) with b_fn: (N_a, S, S, 3) RGB-form outputs on a -> their features' images.
    """
    if space == "object":
        return a, c, lambda b: b
    if space not in ("detail", "detail_shape"):
        raise ValueError(f"unknown feature space {space!r}; expected one of {FEATURES}")
    _, _, branch = detail.decompose(np.asarray(a) * 2.0 - 1.0, mask_a)
    a_d = np.asarray(detail.to_detail_rgb(a, mask_a, branch=branch))
    c_d = np.asarray(detail.to_detail_rgb(c, mask_c))
    return a_d, c_d, lambda b: np.asarray(detail.to_detail_rgb(b, mask_a, branch=branch))


# --------------------------------------------------------------------------------------------
# One cell
# --------------------------------------------------------------------------------------------


def evaluate_cell(fine, coarse, material: str, methods: dict[str, Callable], vgg_params,
                  sampling: patchscores.Sampling, cell_seed=(0,),
                  progress: Callable[[int, str], None] | None = None,
                  space: str = "object") -> dict:
    """Sets a, c and every method's b of one fine/coarse sequence pair, and their distances.

    Args:
      fine, coarse: `GarmentSequence`s of the same pattern, scene, material and seed (frames
        (T, V, 3) meters; T > the last frame of `c_frame_indices`).
      material: material name (to the model through `PatchSet.material_id`).
      methods: name -> (PatchSet) -> (K, S, S, 3) RGB-form outputs (the b sets).
      vgg_params: `vgg.load_vgg19()` (or a small VGG in tests).
      sampling: `evaluation.patchscores.Sampling` (a's frames and origins are exactly Table 1's).
      cell_seed: extra seed entropy for the patch draws (`evaluation.cells.Cell.patch_seed`).
      progress: called with (patches, what) after each set's features.
      space: "object", "detail" or "detail_shape": the images the Gram features are taken
        of (`to_feature_space`; "detail_shape" also puts each layer vector at unit norm).
    Returns:
      {"frame", "origin": (N_a,) int32 frames and (N_a, 2) origins of a (and every b),
       "frame_c", "origin_c": the same for c, "scales": layer -> float (`layer_scales` of a u c),
       "d2_ref": (N_a + N_c,)*2 float64 scaled squared distances of a then c,
       "d2_method": {name: (N_a, N_a + N_c + N_a) distances of b to a, c and b},
       "n_candidates": int, "timings": {"bake_s", "methods_s": {name: s}, "features_s",
       "distances_s", "vgg_passes"}}.
    """
    size = sampling.patch_size
    stride = size // 2 if sampling.grid_stride is None else sampling.grid_stride
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, sampling.texel_size)
    mask = np.asarray(patches.pad_to_patch(pair.mask, size)[0])
    cand, _ = patchsets.candidate_origins(mask, size, stride, sampling.min_coverage)
    if not len(cand):
        raise ValueError(f"no {size}x{size} patch reaches {sampling.min_coverage:.0%} coverage "
                         "by both meshes")
    mid = material_index(material)
    frames_c = c_frame_indices(sampling.frame_indices, sampling.frames, sampling.frame_stride)
    timings = {"bake_s": 0.0, "methods_s": {k: 0.0 for k in methods}, "features_s": 0.0,
               "distances_s": 0.0}
    counter: dict = {}
    # 1. Patches: a (and the methods' input) at Table 1's frames and origins; c in between.
    t0 = time.perf_counter()
    sets_ab, sets_c = [], []
    for t, tc in zip(sampling.frame_indices, frames_c, strict=True):
        sel = patchsets.choose_origins(cand, sampling.patches_per_frame,
                                       (sampling.seed, *cell_seed, t))
        sets_ab.append(patchsets.aligned_patches(pair, fine.frames[t], coarse.frames[t], sel, size,
                                          mid))
        sel_c = patchsets.choose_origins(cand, sampling.patches_per_frame,
                                         (sampling.seed, *cell_seed, t, tc))
        sets_c.append(patchsets.aligned_patches(pair, fine.frames[tc], coarse.frames[tc], sel_c,
                                                size, mid))
    timings["bake_s"] = time.perf_counter() - t0
    inp = np.concatenate([p.input for p in sets_ab])
    mask_ab = np.concatenate([p.mask for p in sets_ab])
    n_a = len(inp)

    def features(images, m, what):
        t0 = time.perf_counter()
        f = gram.set_features(vgg_params, images, m, sampling.score_batch, counter)
        if space == "detail_shape":
            f = set_lib.unit_rows(f)
        timings["features_s"] += time.perf_counter() - t0
        if progress is not None:
            progress(len(images), what)
        return f

    # 2. a u c: features, layer scales, distances.
    mask_c = np.concatenate([p.mask for p in sets_c])
    feat_a, feat_c, feat_b = to_feature_space(space, inp, mask_ab,
                                              np.concatenate([p.target for p in sets_c]), mask_c)
    ref = features(np.concatenate([feat_a, feat_c]), np.concatenate([mask_ab, mask_c]), "a + c")
    scales = set_lib.layer_scales(ref)
    t0 = time.perf_counter()
    d2_ref = set_lib.scaled_sq_dists(ref, None, scales)
    timings["distances_s"] += time.perf_counter() - t0
    # 3. Each method's b: features (identity reuses a's), distances to a, c and itself.
    d2_method = {}
    for name, fn in methods.items():
        t0 = time.perf_counter()
        out = np.concatenate([fn(p) for p in sets_ab])
        timings["methods_s"][name] += time.perf_counter() - t0
        if np.array_equal(out, inp):
            d2_method[name] = np.concatenate([d2_ref[:n_a], d2_ref[:n_a, :n_a]], axis=1)
            if progress is not None:
                progress(n_a, f"{name} (= a)")
            continue
        f_b = features(feat_b(out), mask_ab, name)
        t0 = time.perf_counter()
        d2_method[name] = np.concatenate([set_lib.scaled_sq_dists(f_b, ref, scales),
                                          set_lib.scaled_sq_dists(f_b, None, scales)], axis=1)
        timings["distances_s"] += time.perf_counter() - t0
        del f_b
    timings["vgg_passes"] = counter.get("vgg_passes", 0)
    return {"frame": np.repeat(np.asarray(sampling.frame_indices, np.int32),
                               [len(p.origins) for p in sets_ab]),
            "origin": np.concatenate([p.origins for p in sets_ab]),
            "frame_c": np.repeat(np.asarray(frames_c, np.int32),
                                 [len(p.origins) for p in sets_c]),
            "origin_c": np.concatenate([p.origins for p in sets_c]),
            "scales": scales, "d2_ref": d2_ref, "d2_method": d2_method,
            "n_candidates": int(len(cand)), "timings": timings}


# --------------------------------------------------------------------------------------------
# Figure (the numbers: `evaluation.setscores`)
# --------------------------------------------------------------------------------------------


def plot_embeddings(path: Path, cells: list[cell_lib.Cell], records: dict[str, dict],
                    ncols: int, method: str = MODEL) -> None:
    """One scatter per cell of `method`'s 2D embedding: a grey, b colored, c black."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = max(1, min(ncols, len(cells)))
    nrows = -(-len(cells) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.2 * ncols, 3.1 * nrows), squeeze=False)
    for ax, cell in zip(axes.ravel(), cells, strict=False):
        rec = records[cell.key]
        emb = rec["methods"][method]["embedding"]
        n_a, n_c = len(rec["frame"]), len(rec["frame_c"])
        n_b = len(emb) - n_a - n_c
        ax.scatter(*emb[:n_a].T, s=5, c="0.65", label="a: coarse input")
        ax.scatter(*emb[n_a:n_a + n_b].T, s=5, c="tab:red", label=f"b: {method}")
        ax.scatter(*emb[n_a + n_b:].T, s=5, c="black", label="c: fine, other frames")
        e = rec["methods"][method]["embedded"]
        ax.set_title(f"{cell.key}\nC1 {e['c1']:.3f}  C2 {e['c2']:.3f}  DR {e['dr']:.1f} "
                     f"(signed {e['dr_signed']:+.1f})", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[len(cells):]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=6, loc="best")
    fig.tight_layout()
    suite.save_figure(fig, path, dpi=90)


# --------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------


def run(cells: list[cell_lib.Cell], sequences: dict, methods: dict, vgg_params,
        sampling: patchscores.Sampling, out: Path,
        fingerprint_of: Callable[[cell_lib.Cell], dict],
        fresh: bool = False, log: Callable[[str], None] = print,
        sources: dict[str, str] | None = None, space: str = "object") -> dict[str, dict]:
    """Evaluate (or reload from `<out>/cells/`) every cell, printing progress and an ETA.

    As `evaluation.patchscores.run`, stored cells are reused method by method
    (`evaluation.cells.run_cells`); a new method costs the features of a and c again (2 VGG
    passes per location) plus its own b.

    Returns:
      cell key -> `cell_record` restricted to `methods` (timings also hold "cell_s").
    """
    per_loc = len(sampling.frame_indices) * sampling.patches_per_frame

    def evaluate(cell, names, progress):
        fine = cell_lib.load_first_frames(sequences[cell.key]["fine"], sampling.frames)
        coarse = cell_lib.load_first_frames(sequences[cell.key]["coarse"], sampling.frames)
        rec = cell_record(evaluate_cell(fine, coarse, cell.material,
                                        {k: methods[k] for k in names}, vgg_params, sampling,
                                        cell.patch_seed, progress, space))
        sig = {k: (round(v["embedded"]["dr_signed"], 1), round(v["full"]["dr_signed"], 1))
               for k, v in rec["methods"].items()}
        log(f"{cell.key}: signed DR (embedded, full) {sig}")
        return rec

    return cell_lib.run_cells(cells, methods, sources, path_of=lambda c: cell_path(out, c),
                              fingerprint_of=fingerprint_of, load=load_cell, save=save_cell,
                              evaluate=evaluate, merge=merge_records, field="methods",
                              units=lambda names: per_loc * (2 + len(names)),
                              unit="patch features", fresh=fresh, log=log)


def main(argv=None) -> int:
    ap = suite.script_parser(__doc__)
    patchscores.add_cell_args(ap, suite.RESULTS / "table2", frame_stride_help=(
        "set a uses every k-th frame, set c the frames midway between (k >= 2)"))
    ap.add_argument("--features", default="object", choices=FEATURES,
                    help="object: Grams of the maps (the paper's); detail: of their detail maps "
                         "(issue 21's primary representation); detail_shape: the detail "
                         "maps' Gram vectors at unit norm (amount removed); use another --out")
    ap.add_argument("--oracles", action="store_true",
                    help="also score the ceilings that read the fine simulation of the scored "
                         "frame (`evaluation.methods.oracle_methods`)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    if args.frame_stride < 2:
        ap.error("--frame-stride must be >= 2 (set c uses the frames between the scored ones)")
    try:
        frames_c = c_frame_indices(range(0, args.frames, args.frame_stride), args.frames,
                                   args.frame_stride)
    except ValueError as e:
        ap.error(str(e))
    st = patchscores.setup_from_args(ap, args, min_frame_stride=2)
    sampling, cells, sequences, methods = st.sampling, st.cells, st.sequences, st.methods
    sources, unsharp_src, net_timings = st.sources, st.unsharp_text, st.net_timings
    sim_s = st.sim_s
    if args.oracles:
        oracles = method_lib.oracle_methods()
        methods.update(oracles)
        sources.update({k: k for k in oracles})
    vgg_params = vgg.load_vgg19()
    n_max = len(cells) * len(sampling.frame_indices) * sampling.patches_per_frame
    print(f"{len(cells)} cells x {len(sampling.frame_indices)} frames x "
          f"<= {sampling.patches_per_frame} patches = <= {n_max} patches per set (a, c, and b "
          f"for each of {len(methods)} methods)", flush=True)

    def fingerprint_of(cell):
        return st.fingerprint_of(cell, metric=METRICS[args.features])

    records = run(cells, sequences, methods, vgg_params, sampling, out, fingerprint_of,
                  args.fresh, log=lambda m: print(m, flush=True), sources=sources,
                  space=args.features)

    # 3. Summaries.
    cells_out, groups = {}, {g: [] for g in GROUPS}
    for cell in cells:
        r = records[cell.key]
        groups[group_of(cell)].append(r)
        cells_out[cell.key] = {
            "scene": cell.scene.name, "garment": cell.garment, "motion": cell.motion,
            "material": cell.material, "kind": cell.kind, "group": group_of(cell),
            "n_a": int(len(r["frame"])), "n_c": int(len(r["frame_c"])),
            "n_candidates_per_frame": r["n_candidates"],
            "frames_a": sorted(set(r["frame"].tolist())),
            "frames_c": sorted(set(r["frame_c"].tolist())),
            "fine": suite.portable_path(sequences[cell.key]["fine"]),
            "coarse": suite.portable_path(sequences[cell.key]["coarse"]),
            "sequence_source": {res: sequences[cell.key][f"{res}_info"]["source"]
                                for res in ("fine", "coarse")},
            "layer_scales": r["scales"],
            "methods": {k: {s: v[s] for s in SPACES} for k, v in r["methods"].items()},
            "timings": r["timings"]}
    by_group = {g: mean_scores(v) for g, v in groups.items() if v}
    cell_t = [c["timings"] for c in cells_out.values()]
    n_all = sum(c["n_a"] for c in cells_out.values())
    features_s = sum(t["features_s"] for t in cell_t)
    passes = sum(t["vgg_passes"] for t in cell_t) * sampling.score_batch
    sampling_text = (
        f"Sampling: first {sampling.frames} frames of each sequence (seed {cell_lib.TEST_SEED}). "
        f"(a) coarse simulation (PD 30 mm) at Table 1's frames "
        f"{patchscores.frames_text(sampling.frame_indices)} and patches: "
        f"{sampling.patches_per_frame} random {sampling.patch_size}x{sampling.patch_size} "
        f"patches per frame ({sampling.texel_size * 1e3:g} mm texels) among the grid patches "
        f"with >= {sampling.min_coverage:.0%} of texels covered by both meshes. (b) each "
        f"method's output on (a). (c) fine simulation (PD 10 mm) at the non-corresponding "
        f"frames {patchscores.frames_text(frames_c)}, as many patches per frame, drawn "
        f"independently. Features: upper-triangle normalized Gram matrices on "
        f"{', '.join(evaluation.EVAL_LAYERS)}, each layer divided by its median norm over a "
        f"and c. Unsharp: {unsharp_src}.")
    results = {
        **st.record(args.model),
        "sets": {"a": "coarse-map patches at Table 1's frames and origins",
                 "b": "a method's output on a (every method in turn)",
                 "c": "fine-map patches at frames t + stride // 2 (t - stride // 2 past the "
                      "end), origins drawn independently"},
        "features": "upper triangles of evaluation.gram.gram_matrices on "
                    + ", ".join(evaluation.EVAL_LAYERS)
                    + ", each layer divided by its median vector norm over a u c, concatenated",
        "chamfer": "CD(P, Q) = (mean_p min_q |p - q| + mean_q min_p |p - q|) / 2; C1 = CD(a, c), "
                   "C2 = CD(b, c), dr = 100 |C1 - C2| / C1, dr_signed = 100 (C1 - C2) / C1; "
                   "embedded: 2D spectral embedding of a u b u c at unit RMS radius; full: "
                   "feature space",
        "metric_version": METRICS[args.features],
        "feature_space": args.features,
        "sampling": dataclasses.asdict(sampling), "frames_c": frames_c,
        "sampling_text": sampling_text,
        "config": {"garments": args.garments.split(","), "materials": args.materials.split(","),
                   "motions": args.motions.split(","), "seed": cell_lib.TEST_SEED,
                   "scenes": {c.key: json.loads(c.scene.to_json()) for c in cells}},
        "cells": cells_out, "by_group": by_group, "all": mean_scores(list(records.values())),
        "timings": {
            "note": "per-cell timings are from the run that computed the cell "
                    "(see cells.*.timings)",
            "cells_s": sum(t.get("cell_s", 0.0) for t in cell_t),
            "features_s": features_s, "vgg_patch_passes": passes,
            "vgg_s_per_patch_pass": features_s / passes if passes else None,
            "distances_s": sum(t["distances_s"] for t in cell_t),
            "compare_s": sum(t["compare_s"] for t in cell_t),
            "network_ms_per_patch": (1e3 * sum(t["methods_s"].get(MODEL, 0.0) for t in cell_t)
                                     / n_all if n_all else None),
            "network_compile_s": net_timings.get("compile_s"),
            "sequences_s": sim_s, "this_run_s": time.perf_counter() - t_all},
        "machine": suite.machine_info(),
        "command": "python -m experiments.table2 " + " ".join(
            sys.argv[1:] if argv is None else argv),
    }
    suite.write_json(out / "results.json", results)
    table = table_markdown(results)
    (out / "table.md").write_text(table)
    plot_embeddings(out / "embeddings.png", cells, records, ncols=len(results["config"]
                                                                      ["garments"]))
    print(table)
    print(f"wrote {out / 'results.json'}, {out / 'table.md'}, {out / 'embeddings.png'} "
          f"in {(time.perf_counter() - t_all) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
