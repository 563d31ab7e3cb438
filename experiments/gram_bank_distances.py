"""How far real patches are from a run's fine-target Gram bank (`nn.gram_bank`).

For random patches of the training scenes and of the validation garment (never the held-out
ones), the distance of the coarse input's and of the fine target's detail Gram features to the
nearest bank row of the same material: is the set-level term's minimum where the fine
patches are?

    python -m experiments.gram_bank_distances --run outputs/fidelity_run10 \
        --out experiments/results/fidelity/run10_bank/bank_distances.json
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import data, train
from wrinkle_jax.evaluation import suite
from wrinkle_jax.nn import gram_bank, vgg


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True, help="a training run directory with bank.npz")
    ap.add_argument("--data", default="data/pairs")
    ap.add_argument("--patches", type=int, default=64, help="per split (a multiple of 8)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    cfg = train.TrainConfig.from_json(json.load(open(f"{args.run}/config.json")))
    facts = json.load(open(f"{args.run}/data.json"))
    bank = gram_bank.load_bank(f"{args.run}/bank.npz")
    vgg_params = vgg.load_vgg19()

    @jax.jit
    def nearest(images, mask, material):
        f = vgg.features(vgg_params, images, layers=bank.layers, conv_impl=cfg.vgg_conv_impl)
        return gram_bank.nearest_distance(gram_bank.feature_vectors(f, mask, bank), material,
                                          jnp.asarray(bank.vectors), jnp.asarray(bank.material))

    out = {"run": args.run, "bank_rows": len(bank.vectors), "layers": list(bank.layers),
           "note": "nearest same-material bank distance (nn.gram_bank), median and mean over "
                   "random patches; detail maps on the input's branch (train.loss_images)"}
    for split in ("train", "valgarment"):
        scenes = facts.get("train_scenes_selected") if split == "train" else None
        ds = data.PatchDataset(args.data, split, scenes=scenes)
        idx = np.sort(np.random.default_rng(args.seed).choice(len(ds), args.patches, False))
        got: dict[str, list] = {"input": [], "target": []}
        for i in range(0, len(idx), 8):
            b = ds.get(idx[i:i + 8])
            inp, _, tgt = train.loss_images(cfg, b, b["target"])
            got["input"].append(np.asarray(nearest(inp, b["mask"], b["material"])))
            got["target"].append(np.asarray(nearest(tgt, b["mask"], b["material"])))
        cat = {k: np.concatenate(v) for k, v in got.items()}
        out[split] = {k: {"median": float(np.median(v)), "mean": float(np.mean(v)),
                          "n": int(len(v))} for k, v in cat.items()}
        out[split]["target_farther_than_input"] = float(np.mean(cat["target"] > cat["input"]))
        print(split, json.dumps(out[split]), flush=True)
    suite.write_json(args.out, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
