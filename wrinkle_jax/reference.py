"""The authors' PyTorch code's conventions, in NumPy and JAX: what `benchmarks/bench_reference.py`
needs to set their code and ours side by side, without torch.

  * their training recipe (`train_DDE.py`): batch, optimizer settings, loss layers, and the
    loss weights that make our objective (`train.loss_fn`) equal to theirs
    (`authors_loss_weights`);
  * agreement measures: of two outputs (`agreement`) and of two pytrees of gradients
    (`tree_rel_rms`);
  * the lifting case (`make_lift_case`) in the arrays their loop reads, and the inputs their
    `Geometry_Opt.geo_opt` takes, built from our mesh: each vertex's opposite edges
    (`cross_edges`), the dense adjacency their Laplacian is made from (`adjacency_with_self`)
    and their vertex and flag text files;
  * issue 22's speed and error targets against a run's report (`target_summary`).

Their code is never imported here (nor copied): the benchmark loads it from a checkout.
Vertices are meters; faces (F, 3) int; speed-ups are the authors' time over ours.
"""

from __future__ import annotations

import jax
import numpy as np

from wrinkle_jax import mesh, primitives, timing

__all__ = ["AUTHORS_BATCH", "AUTHORS_C_ALPHA", "AUTHORS_LR", "AUTHORS_S_BETA",
           "AUTHORS_WEIGHT_DECAY", "CONTENT_LAYER", "STYLE_LAYERS", "adjacency_with_self",
           "agreement", "authors_loss_weights", "cross_edges", "make_lift_case",
           "speedups", "surface_rms_mm", "target_summary", "tree_rel_rms", "write_flag_text",
           "write_vertex_text"]


# -------------------------------------------------------------------------------------------------
# Their training recipe

# Their script's settings: batch 32 of 128 x 128 patches, Adam(lr 1e-4, weight decay 1e-5,
# amsgrad), BatchFeatureLoss_Model(c_alpha 1, s_beta 1e4, five style layers of weight 1):
# style on VGG19 features [:4], [:7], [:12], [:21], [:30] (relu1_2, relu2_1, relu3_1, relu4_1,
# relu5_1; max pools replaced by average pools), content on [:7] (relu2_1).
AUTHORS_BATCH = 32
AUTHORS_LR, AUTHORS_WEIGHT_DECAY = 1e-4, 1e-5
AUTHORS_C_ALPHA, AUTHORS_S_BETA = 1.0, 1e4
STYLE_LAYERS = ("relu1_2", "relu2_1", "relu3_1", "relu4_1", "relu5_1")
CONTENT_LAYER = "relu2_1"


def authors_loss_weights(batch: int, content_channels: int, content_pixels: int,
                         c_alpha: float = AUTHORS_C_ALPHA, s_beta: float = AUTHORS_S_BETA,
                         num_style_layers: int = len(STYLE_LAYERS)) -> tuple[float, float]:
    """(w_c, w_s) that make our objective equal to theirs on an all-ones mask.

    Theirs (summed over the batch): content = 1/2 sum_{n,p,c} d^2, style = sum_n sum_l
    ||dG_l||^2 / (L (2 R_l)^2) with L style layers. Ours (`train.loss_fn`,
    normalize_channels=False): the batch mean of w_c content_n + w_s style_n with
    content_n = sum_{p,c} d^2 / (C R) and style_n = sum_l ||dG_l||^2 / (4 R_l^2). Hence
    w_c = c_alpha N C R / 2 and w_s = s_beta N / L (R = pixels of the content layer, C its
    channels, N the batch).
    """
    return (c_alpha * batch * content_channels * content_pixels / 2.0,
            s_beta * batch / num_style_layers)


# -------------------------------------------------------------------------------------------------
# Agreement and speed


def speedups(t: timing.Timing, authors: str = "authors_torch") -> dict:
    """The authors' time over each of our variants' (median over the alternating rounds of
    `timing.alternate`'s per-round ratios), wall clock and process CPU: {"speedup_vs_authors_wall",
    "speedup_vs_authors_cpu"}: {variant: ratio rounded to 3 decimals}; `authors` is their
    variant's name."""
    ours = [k for k in t.wall_rounds if k != authors]
    return {f"speedup_vs_authors_{clock}": {k: round(t.ratio(authors, k, clock), 3)
                                            for k in ours} for clock in ("wall", "cpu")}


def agreement(ours: np.ndarray, theirs: np.ndarray) -> dict:
    """Errors of `ours` against `theirs` (same shape), relative to RMS(theirs)."""
    d = np.asarray(ours, np.float64) - np.asarray(theirs, np.float64)
    scale = float(np.sqrt(np.mean(np.asarray(theirs, np.float64) ** 2)))
    return {"max_abs": float(np.max(np.abs(d))),
            "max_abs_over_output_rms": float(np.max(np.abs(d)) / scale),
            "rel_rms": float(np.sqrt(np.mean(d**2)) / scale),
            "output_rms": scale}


def tree_rel_rms(ours, theirs, floor: float = 1e-4) -> dict:
    """Relative RMS error of pytree `ours` against `theirs` (same structure): over all leaves
    together ("all"), and the worst leaf among those whose norm is at least `floor` times the
    largest leaf norm ("worst_leaf", "worst_leaf_name"; the decoder biases feed an instance
    norm, so their gradient is zero analytically and rounding noise on both sides)."""
    pairs = [(jax.tree_util.keystr(path), np.asarray(a, np.float64).ravel(),
              np.asarray(b, np.float64).ravel())
             for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(ours),
                                     jax.tree.leaves(theirs), strict=True)]
    norms = {name: np.linalg.norm(b) for name, _, b in pairs}
    top = max(norms.values())
    per = {name: float(np.linalg.norm(a - b) / norms[name]) for name, a, b in pairs
           if norms[name] >= floor * top > 0}
    num = np.sqrt(sum(np.sum((a - b) ** 2) for _, a, b in pairs))
    worst = max(per, key=per.get)
    return {"all": float(num / np.sqrt(sum(n**2 for n in norms.values()))),
            "worst_leaf": per[worst], "worst_leaf_name": worst}


# -------------------------------------------------------------------------------------------------
# Lifting: the case, and their inputs built from our mesh


def make_lift_case(cells: int) -> dict:
    """`primitives.wrinkled_sheet_case` (the case `bench_lift` times) in the arrays their loop
    reads: {"p0": (V, 3) float32 upsampled coarse vertices, "faces": (F, 3) int32,
    "normals", "ideal": (V, 3) float32, "num_coarse": Vc (the first Vc fine vertices are the
    coarse ones)}; `cells` a multiple of 4 (exact 10 mm edges)."""
    if cells % 4:
        raise ValueError(f"cells must be a multiple of 4, got {cells}")
    case = primitives.wrinkled_sheet_case(cells)
    return {"p0": np.asarray(case["fine"].vertices, np.float32),
            "faces": np.asarray(case["fine"].faces, np.int32),
            "normals": case["normals"], "ideal": case["ideal"],
            "num_coarse": int(case["coarse"].num_vertices)}


def cross_edges(faces: np.ndarray, num_vertices: int):
    """Every vertex's opposite edges, one per incident face, grouped by vertex (the input of
    their `Loss_NormalCrossVert`).

    Returns:
      (edge_0, edge_1, counts): (R,) int64 endpoints of the R = 3F edges, vertex 0's first,
      and (V,) int64 edges per vertex (sum = R).
    """
    f = np.asarray(faces, np.int64)
    owner = f.reshape(-1)  # corner k of face i owns the edge (corner k+1, corner k+2)
    e0 = np.roll(f, -1, axis=1).reshape(-1)
    e1 = np.roll(f, -2, axis=1).reshape(-1)
    order = np.argsort(owner, kind="stable")
    return e0[order], e1[order], np.bincount(owner, minlength=num_vertices).astype(np.int64)


def adjacency_with_self(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(V, V) int dense one-ring adjacency with ones on the diagonal: what their
    `DataIO.readAdjFile` returns for the mesh (their Laplacian is built from it)."""
    adj = np.eye(num_vertices, dtype=np.int64)
    e = mesh.unique_edges(faces).astype(np.int64)
    adj[e[:, 0], e[:, 1]] = 1
    adj[e[:, 1], e[:, 0]] = 1
    return adj


def write_vertex_text(path: str, array: np.ndarray):
    """Rows of three numbers, one vertex per line (their vertex/normal text format)."""
    np.savetxt(path, np.asarray(array, np.float64), fmt="%.9g")


def write_flag_text(path: str, flags: np.ndarray):
    """Their per-vertex flag format: the count, then one integer per line."""
    with open(path, "w") as f:
        f.write(f"{len(flags)}\n")
        f.writelines(f"{int(v)}\n" for v in flags)


def surface_rms_mm(p, ideal) -> float:
    """RMS distance in mm between (V, 3) vertex arrays `p` and `ideal` (meters)."""
    return float(1e3 * np.sqrt(np.mean(np.sum((np.asarray(p) - np.asarray(ideal)) ** 2, 1))))


# -------------------------------------------------------------------------------------------------
# Targets


def target_summary(report: dict) -> dict:
    """Issue 22's targets against what a side-by-side run measured (wall-clock ratios).

    Args:
      report: `benchmarks/bench_reference.py`'s JSON, with any of "unet", "train", "lift"
        (their "speedup_vs_authors_wall": variant -> the authors' time / ours).
    Returns:
      the best speed-ups (x the authors'), the relative errors and whether each goal is met:
      U-Net inference >= 3x (and the fastest form), each bfloat16 form's relative RMS error
      <= 1 %, training step >= 4x,
      lifting at the default settings >= 100x.
    """
    out = {}
    if "unet" in report:
        u = report["unet"]
        speed = u["speedup_vs_authors_wall"]
        best = max(speed, key=speed.get)
        out["unet_inference_x_authors_best"] = speed[best]
        out["unet_inference_best_form"] = best.removeprefix("ours_")
        out["unet_inference_goal_3x_met"] = speed[best] >= 3.0
        for form, agreement in u["agreement_vs_authors"].items():
            if form.endswith("bf16"):  # the error bound is on the bfloat16 forms
                out[f"{form}_rel_rms_vs_authors"] = agreement["rel_rms"]
                out[f"{form}_error_goal_1pct_met"] = agreement["rel_rms"] <= 0.01
    if "train" in report:
        tr = report["train"]
        best = max(tr["speedup_vs_authors_wall"].values())
        out["train_step_x_authors_best"] = best
        out["train_step_goal_4x_met"] = best >= 4.0
        out["train_grad_rel_rms_vs_authors"] = {
            k: v["grad_rel_rms_vs_authors"]["all"] for k, v in tr["agreement"].items()}
    if "lift" in report:
        x = report["lift"]["speedup_vs_authors_wall"]["ours_default"]
        out["lift_default_x_authors"] = x
        out["lift_goal_100x_met"] = x >= 100.0
    return out
