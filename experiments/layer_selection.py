"""Style-layer selection by the paper's method (Sec. 4.1, Fig. 4): which VGG19 layers tell coarse
from fine normal-map patches, and what each costs in a training step.

    python -m experiments.layer_selection [--data data/patches] [--n 300]

For every candidate layer: masked, pixel-count-normalized Gram matrices of `n` coarse-looking
input patches and of `n` fine target patches from the training split (`data/patches`, built by
`experiments.make_dataset`), a 2D spectral embedding of all 2n Gram matrices (Gaussian affinity
with the median-distance bandwidth, symmetric normalized Laplacian), and two separation scores:

  * knn_2d: leave-one-out 7-nearest-neighbour accuracy of coarse-vs-fine in the 2D embedding
    (0.5 = the sets overlap, 1 = fully separated) -- what the paper's figure shows;
  * knn_full: the same in the full Gram space (no embedding loss);
  * paired_ratio: median |G(coarse crop i) - G(fine crop i)| / median |G(fine crop i) -
    G(fine crop j)|: the detail difference of the same crop relative to the variation between
    crops (what a paired style loss sees; the unpaired sets are dominated by the latter).

Cost: wall time of one VGG forward + backward (to the images) down to that layer for a batch of
8 patches of 128^2, `conv_impl="im2col_bf16"` as in training. Writes
`experiments/results/layer_selection/{table.json,table.md,embeddings.png}`.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import data, evaluation
from wrinkle_jax.evaluation.suite import portable_path
from wrinkle_jax.nn import losses, vgg

ROOT = Path(__file__).resolve().parents[1]
CANDIDATES = ("relu1_1", "relu1_2", "relu2_1", "relu2_2", "relu3_1", "relu3_2", "relu3_4",
              "relu4_1", "relu4_2", "relu4_4", "relu5_1")


def knn_accuracy(x: np.ndarray, labels: np.ndarray, k: int = 7) -> float:
    """Leave-one-out k-NN accuracy (majority vote)."""
    sq = (x * x).sum(1)
    d2 = sq[:, None] + sq[None, :] - 2.0 * x @ x.T
    np.fill_diagonal(d2, np.inf)
    nn = np.argsort(d2, axis=1)[:, :k]
    votes = labels[nn].mean(1)
    return float(((votes > 0.5) == labels.astype(bool)).mean())


def grams(vgg_params, images, mask, layers, batch=16):
    """dict layer -> (N, C*(C+1)/2) float32 upper triangles of normalized masked Grams."""
    pyramid = {}

    @jax.jit
    def run(x, m):
        f = vgg.features(vgg_params, x, layers=layers, conv_impl="im2col_bf16")
        out = {}
        for name in layers:
            lvl = vgg.layer_level(name)
            mm = losses.mask_pyramid(m, lvl + 1)[lvl]
            g = losses.gram(f[name], mm, normalize=True)
            iu = jnp.triu_indices(g.shape[-1])
            out[name] = g[:, iu[0], iu[1]]
        return out

    for s in range(0, len(images), batch):
        got = run(jnp.asarray(images[s:s + batch]), jnp.asarray(mask[s:s + batch]))
        for k, v in got.items():
            pyramid.setdefault(k, []).append(np.asarray(v))
    return {k: np.concatenate(v) for k, v in pyramid.items()}


def step_cost(vgg_params, layer, reps=3) -> float:
    """ms of VGG forward + backward to the input down to `layer`, batch 8 of 128^2."""
    x = jnp.asarray(np.random.default_rng(0).uniform(size=(8, 128, 128, 3)), jnp.float32)

    @jax.jit
    def g(x):
        def e(x):
            return jnp.mean(vgg.features(vgg_params, x, layers=(layer,),
                                         conv_impl="im2col_bf16")[layer] ** 2)
        return jax.grad(e)(x)

    g(x).block_until_ready()
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        g(x).block_until_ready()
        best = min(best, time.perf_counter() - t0)
    return 1e3 * best


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "layer_selection"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ds = data.PatchDataset(args.data, "train")
    rng = np.random.default_rng(args.seed)
    # Coarse and fine patches from different random crops: the sets, not the pairs, are compared.
    ia, ib = np.split(rng.choice(len(ds), 2 * args.n, replace=False), 2)
    a, b = ds.get(np.sort(ia)), ds.get(np.sort(ib))
    params = vgg.load_vgg19()
    t0 = time.time()
    ga = grams(params, a["input"], a["mask"], CANDIDATES)
    ga_t = grams(params, a["target"], a["mask"], CANDIDATES)
    gb = grams(params, b["target"], b["mask"], CANDIDATES)
    gram_s = time.time() - t0
    labels = np.r_[np.zeros(args.n), np.ones(args.n)]
    rows, embs = [], {}
    for name in CANDIDATES:
        x = np.concatenate([ga[name], gb[name]]).astype(np.float64)
        x = x / (np.linalg.norm(x, axis=1, keepdims=True).mean() + 1e-30)
        emb = evaluation.spectral_embedding(x)
        embs[name] = emb
        # Paired: how far the coarse and fine versions of the SAME crop are apart, relative
        # to how far the fine versions of two different crops are (content variation).
        paired = np.linalg.norm(ga[name] - ga_t[name], axis=1)
        across = np.linalg.norm(ga_t[name] - gb[name], axis=1)
        rows.append({"layer": name, "knn_2d": knn_accuracy(emb, labels),
                     "knn_full": knn_accuracy(x, labels),
                     "paired_ratio": round(float(np.median(paired) / np.median(across)), 4),
                     "step_ms_to_layer": round(step_cost(params, name), 1)})
        print(json.dumps(rows[-1]), flush=True)
    result = {"n_per_set": args.n, "data": portable_path(args.data),
              "gram_seconds": round(gram_s, 1), "rows": rows}
    (out / "table.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = ["| layer | kNN acc. (2D embedding) | kNN acc. (Gram space) | paired ratio "
             "| VGG fwd+bwd ms |", "|---|---|---|---|---|"]
    lines += [f"| {r['layer']} | {r['knn_2d']:.3f} | {r['knn_full']:.3f} | "
              f"{r['paired_ratio']:.3f} | {r['step_ms_to_layer']:.0f} |" for r in rows]
    (out / "table.md").write_text("\n".join(lines) + "\n")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cols = 4
    nrow = -(-len(CANDIDATES) // cols)
    fig, axes = plt.subplots(nrow, cols, figsize=(3.2 * cols, 3.0 * nrow))
    for ax, r in zip(axes.ravel(), rows, strict=False):
        e = embs[r["layer"]]
        ax.scatter(*e[:args.n].T, s=3, c="tab:blue", label="coarse (downsampled)")
        ax.scatter(*e[args.n:].T, s=3, c="tab:red", label="fine")
        ax.set_title(f"{r['layer']}  kNN {r['knn_2d']:.2f}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[len(rows):]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(out / "embeddings.png", dpi=90)
    print((out / "table.md").read_text())


if __name__ == "__main__":
    main()
