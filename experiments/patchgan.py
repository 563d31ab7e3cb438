"""Train the DeepWrinkles-style conditional PatchGAN baseline (`wrinkle_jax.nn.patchgan`) on the
enhancer's training patches for the enhancer's wall-clock budget, then score it against the
shipped model on the model card's patches (paper Fig. 9).

    python -m experiments.patchgan [--data data/patches] [--minutes 45]
        [--run outputs/patchgan] [--out experiments/results/patchgan] [--fresh]
        [--width W] [--disc-width W] [--plain-unet] [--lr 2e-4] [--batch 8]

Training: `data.PatchDataset(<data>, "train")` in the enhancer's batch order (BatchIterator,
seed 0, batch 8 or `--batch`); one D and one G update per step (`patchgan.make_gan_step`) until
`--minutes` of wall time (the shipped model trained 0.75 h on this machine class: see
`wrinkle_jax/assets/MODEL_CARD.md`) or `--steps`. Metrics go to `<run>/metrics.jsonl`; a
checkpoint (`<run>/state.npz` + `state.json`: iterator position, config) is written every
`--checkpoint-every` steps and at the end, and a rerun resumes from it (the budget counts
this run's time only; `--fresh` starts over). The generator is exported as an enhancer file
(`<out>/patchgan.npz`, one material "any", ~1 MB) that every evaluation script can load.

Scoring (`experiments.model_card`'s sets): the first `--n` (480) held-out patches (unseen
garments, seen garment in an unseen motion) and `--n-seen` (160) training patches, improvement
score on `evaluation.EVAL_LAYERS` with shared input/target Gram matrices
(`evaluation.gram.method_losses`): identity, unsharp masking (order 1 at the model card's best
setting), the shipped model (or `--model`), and the PatchGAN.

Writes `<out>/results.json` (config, steps, wall time, scores by kind/scene/material, ms per
patch), `<out>/table.md` and `<out>/loss_curve.png`.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, data, enhancer, evaluation
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import gram, patchsets, suite
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.fileio import atomic_write_bytes, atomic_write_text
from wrinkle_jax.nn import patchgan, vgg
from wrinkle_jax.nn.unet import UNetConfig

ROOT = Path(__file__).resolve().parents[1]
GAN = "patchgan"


def save_state(run: Path, state: patchgan.GANState, iterator: data.IteratorState,
               config: patchgan.GANConfig, elapsed_s: float) -> None:
    """Checkpoint: the state's leaves (.npz, in tree order) and a JSON sidecar (iterator,
    config, step, time); the sidecar is written last, so it never names a missing state."""
    buf = io.BytesIO()
    np.savez(buf, *[np.asarray(x) for x in jax.tree.leaves(jax.device_get(state))])
    atomic_write_bytes(run / "state.npz", buf.getvalue())
    atomic_write_text(run / "state.json", json.dumps(
        {"step": int(state.step), "iterator": dataclasses.asdict(iterator),
         "config": config.to_json(), "train_s": elapsed_s}))


def load_state(run: Path, template: patchgan.GANState, config: patchgan.GANConfig):
    """(state, iterator state, train seconds so far) from `run`, or None (none / other config)."""
    try:
        meta = json.loads((run / "state.json").read_text())
        if patchgan.GANConfig.from_json(meta["config"]) != config:
            return None
        leaves, tree = jax.tree_util.tree_flatten(template)
        with np.load(run / "state.npz") as z:
            arrays = [z[f"arr_{i}"] for i in range(len(leaves))]
        if any(a.shape != np.shape(t) for a, t in zip(arrays, leaves, strict=True)):
            return None
    except (OSError, ValueError, KeyError):
        return None
    state = jax.tree_util.tree_unflatten(tree, [jnp.asarray(a, np.asarray(t).dtype)
                                                for a, t in zip(arrays, leaves, strict=True)])
    return state, data.IteratorState(**meta["iterator"]), float(meta.get("train_s", 0.0))


def train(config: patchgan.GANConfig, data_root: Path, run: Path, minutes: float,
          max_steps: int | None = None, checkpoint_every: int = 200, fresh: bool = False,
          log=print, train_scenes: tuple[str, ...] | None = None) -> dict:
    """Train (or resume) until `minutes` of this run's wall time or `max_steps` total steps
    (on `train_scenes` only, if given).

    Returns {"state", "steps", "train_s" (all runs), "this_run_s"}.
    """
    run.mkdir(parents=True, exist_ok=True)
    train_set = data.PatchDataset(data_root, "train", scenes=train_scenes)
    iterator = data.BatchIterator(train_set, config.batch_size, seed=config.seed)
    state = patchgan.create_gan_state(config, jax.random.key(config.seed, impl="rbg"),
                                      train_set.patch_size)
    before = 0.0
    metrics_path = run / "metrics.jsonl"
    loaded = None if fresh else load_state(run, state, config)
    if loaded is not None:
        state, iterator.state, before = loaded
        keep = [ln for ln in (metrics_path.read_text().splitlines()
                              if metrics_path.exists() else [])
                if ln and json.loads(ln)["step"] <= int(state.step)]
        atomic_write_text(metrics_path, "".join(k + "\n" for k in keep))
        log(f"resuming at step {int(state.step)} ({before / 60:.1f} min trained)")
    elif metrics_path.exists():
        metrics_path.unlink()
    step_fn = patchgan.make_gan_step(config)
    t_start = time.perf_counter()
    limit = 60.0 * minutes
    with open(metrics_path, "a") as f:
        while max_steps is None or int(state.step) < max_steps:
            batch = {k: jnp.asarray(v) for k, v in next(iterator).items()
                     if k in ("input", "target", "mask")}
            t0 = time.perf_counter()
            state, m = step_fn(state, batch)
            m = {k: float(v) for k, v in jax.device_get(m).items()}
            step = int(state.step)
            m.update(step=step, step_s=time.perf_counter() - t0)
            f.write(json.dumps(m) + "\n")
            elapsed = time.perf_counter() - t_start
            done = elapsed > limit or (max_steps is not None and step >= max_steps)
            if step % checkpoint_every == 0 or done:
                f.flush()
                save_state(run, state, iterator.state, config, before + elapsed)
            if step % 50 == 0:
                log(f"step {step}: d {m['d_loss']:.3f} (real {m['d_real']:.2f}, fake "
                    f"{m['d_fake']:.2f}), g adv {m['g_adv']:.3f} l1 {m['g_l1']:.4f}, "
                    f"{elapsed / 60:.1f} min")
            if done:
                break
    this_run = time.perf_counter() - t_start
    return {"state": state, "steps": int(state.step), "train_s": before + this_run,
            "this_run_s": this_run}


def plot_curves(metrics_path: Path, out_png: Path) -> None:
    """D loss, G's adversarial and L1 terms and D's real/fake probabilities per step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(ln) for ln in metrics_path.read_text().splitlines() if ln]
    if not rows:
        return
    step = np.array([r["step"] for r in rows])

    def smooth(k):
        x = np.array([r[k] for r in rows])
        w = max(1, len(x) // 50)
        return np.convolve(x, np.ones(w) / w, mode="same")

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    axes[0].plot(step, smooth("d_loss"), label="D loss")
    axes[0].plot(step, smooth("g_adv"), label="G adversarial")
    axes[1].plot(step, smooth("g_l1"), color="tab:green")
    axes[1].set_title("G masked L1 (RGB form)", fontsize=10)
    axes[2].plot(step, smooth("d_real"), label="D(real)")
    axes[2].plot(step, smooth("d_fake"), label="D(fake)")
    for ax in axes:
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    suite.save_figure(fig, out_png, dpi=100)


def score(vgg_params, batch: dict, outs: dict[str, np.ndarray]) -> dict:
    """Per method: summaries overall, by kind (seen/unseen garment), scene and material."""
    kind = np.array(["unseen garment" if s in cell_lib.UNSEEN_GARMENT else "seen garment"
                     for s in batch["scene"]])
    mat = np.array([MATERIALS[m] for m in batch["material"]])
    losses = gram.method_losses(vgg_params, batch["input"], batch["target"], batch["mask"], outs)
    res = {}
    for name in outs:
        sc = evaluation.scores_from_losses(losses["input"], losses[name])
        res[name] = {"all": evaluation.summarize(sc)["all"],
                     "by_kind": evaluation.summarize(sc, kind),
                     "by_scene": evaluation.summarize(sc, batch["scene"]),
                     "by_material": evaluation.summarize(sc, mat)}
    return res


def table_markdown(res: dict) -> str:
    def cell(d):
        return (f"{d['signed_mean']:+.1f} ({d['improvement_mean']:.1f} ± "
                f"{d['improvement_std']:.1f})") if d.get("n") else "-"

    lines = [f"# PatchGAN baseline vs the model ({res['steps']} GAN steps in "
             f"{res['train_s'] / 60:.1f} min)", "",
             "Improvement score: signed mean (paper's |.| mean ± std).", "",
             "| method | unseen garments | seen garment, unseen motion | training patches | "
             "ms/patch |", "|---|---|---|---|---|"]
    for name, r in res["scores"].items():
        k = r["heldout"]["by_kind"]
        ms = res["ms_per_patch"].get(name)
        lines.append(f"| {name} | {cell(k.get('unseen garment', {}))} | "
                     f"{cell(k.get('seen garment', {}))} | {cell(r['seen']['all'])} | "
                     f"{'-' if ms is None else f'{ms:.1f}'} |")
    lines += ["", "Held-out patches by scene (signed mean):", "",
              "| scene | " + " | ".join(res["scores"]) + " |",
              "|---|" + "---|" * len(res["scores"])]
    scenes = [s for s in res["scores"][GAN]["heldout"]["by_scene"] if s != "all"]
    for s in scenes:
        lines.append(f"| {s} | " + " | ".join(
            f"{r['heldout']['by_scene'][s]['signed_mean']:+.1f}" for r in res["scores"].values())
            + " |")
    return "\n".join(lines) + "\n"


def config_from_args(args: argparse.Namespace) -> patchgan.GANConfig:
    """The GAN configuration of the command line: the defaults give `patchgan.GANConfig()`
    (the shipped model's generator U-Net) with only `--width` applied."""
    net = (UNetConfig(width=args.width, residual=True) if args.plain_unet
           else dataclasses.replace(patchgan.GANConfig().unet, width=args.width))
    return patchgan.GANConfig(unet=net, l1_weight=args.l1_weight, disc_width=args.disc_width,
                              learning_rate=args.lr, batch_size=args.batch)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--run", default=str(ROOT / "outputs" / "patchgan"))
    ap.add_argument("--out", default=str(suite.RESULTS / "patchgan"))
    ap.add_argument("--model", default=str(enhancer.DEFAULT_PATH), help="model to compare with")
    ap.add_argument("--minutes", type=float, default=45.0, help="training wall-clock budget")
    ap.add_argument("--steps", type=int, default=None, help="stop at this many steps")
    ap.add_argument("--checkpoint-every", type=int, default=200)
    ap.add_argument("--n", type=int, default=480, help="held-out patches scored")
    ap.add_argument("--n-seen", type=int, default=160, help="training patches scored")
    ap.add_argument("--l1-weight", type=float, default=patchgan.GANConfig.l1_weight)
    ap.add_argument("--width", type=int, default=patchgan.GANConfig().unet.width,
                    help="generator width (default: the shipped model's)")
    ap.add_argument("--disc-width", type=int, default=patchgan.GANConfig.disc_width)
    ap.add_argument("--plain-unet", action="store_true",
                    help="generator: a plain residual U-Net (the input as its base, no unsharp "
                         "base or high-pass) instead of the shipped model's")
    ap.add_argument("--lr", type=float, default=patchgan.GANConfig.learning_rate,
                    help="Adam learning rate of G and D")
    ap.add_argument("--batch", type=int, default=patchgan.GANConfig.batch_size,
                    help="patches per step")
    ap.add_argument("--train-scenes", default=None,
                    help="train on these scenes only (comma-separated; the paper's Fig. 9 "
                         "trained both networks on the long skirt: skirt_dance)")
    ap.add_argument("--fresh", action="store_true")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    scenes = tuple(args.train_scenes.split(",")) if args.train_scenes else None
    out, run = Path(args.out), Path(args.run)
    out.mkdir(parents=True, exist_ok=True)
    config = config_from_args(args)
    got = train(config, Path(args.data), run, args.minutes, args.steps,
                args.checkpoint_every, args.fresh, log=lambda s: print(s, flush=True),
                train_scenes=scenes)
    ds = data.PatchDataset(args.data, "train", scenes=scenes)
    entry = ds.entries[0]
    ecfg = config.enhancer_config(ds.patch_size, entry["texel_size"],
                                  entry["config"]["coarse_pd"])
    gan_path = enhancer.save_enhancer(out / "patchgan.npz", got["state"].g_params, ecfg, meta={
        "baseline": "DeepWrinkles-style conditional PatchGAN (wrinkle_jax.nn.patchgan)",
        "gan_config": config.to_json(), "steps": got["steps"],
        "train_minutes": round(got["train_s"] / 60, 2), "data": suite.portable_path(args.data),
        "train_scenes": sorted({e["scene"] for e in ds.entries})})
    gan = enhancer.load_enhancer(gan_path)
    model = enhancer.load_enhancer(args.model)
    plot_curves(run / "metrics.jsonl", out / "loss_curve.png")
    sigma, amount, src = method_lib.unsharp_setting(order=1)
    vgg_params = vgg.load_vgg19()
    held = patchsets.take(data.PatchDataset(args.data, "heldout"), args.n)
    seen = patchsets.take(ds, args.n_seen)
    scores, ms = {}, {}
    for split, batch in (("heldout", held), ("seen", seen)):
        outs = {"identity": evaluation.identity(batch["input"], batch["mask"]),
                f"unsharp order 1 (sigma={sigma:g},amount={amount:g})":
                    evaluation.unsharp_mask(batch["input"], batch["mask"], sigma, amount, 1)}
        outs["model"], ms["model"] = method_lib.run_model(model, batch)
        outs[GAN], ms[GAN] = method_lib.run_model(
            gan, {**batch, "material": np.zeros_like(batch["material"])})
        for name, r in score(vgg_params, batch, outs).items():
            scores.setdefault(name, {})[split] = r
        print(split, {k: round(v[split]["all"]["signed_mean"], 1) for k, v in scores.items()},
              flush=True)
    res = {"config": config.to_json(), "data": suite.portable_path(args.data),
           "steps": got["steps"],
           "train_scenes": sorted({e["scene"] for e in ds.entries}),
           "train_s": got["train_s"], "minutes_budget": args.minutes,
           "model": suite.portable_path(args.model),
           "model_meta": {k: v for k, v in model.meta.items()
                          if not isinstance(v, dict | list)},
           "unsharp": {"sigma": sigma, "amount": amount, "source": src},
           "n_heldout": len(held["input"]), "n_seen": len(seen["input"]),
           "scores": scores, "ms_per_patch": ms, "weights": suite.portable_path(gan_path),
           "machine": suite.machine_info(),
           "command": "python -m experiments.patchgan " + " ".join(
               sys.argv[1:] if argv is None else argv)}
    res["summary"] = {name: {"unseen garment": r["heldout"]["by_kind"].get(
        "unseen garment", {}).get("signed_mean"), "seen garment, unseen motion":
        r["heldout"]["by_kind"].get("seen garment", {}).get("signed_mean"),
        "training patches": r["seen"]["all"].get("signed_mean")}
        for name, r in scores.items()}
    suite.write_json(out / "results.json", res)
    (out / "table.md").write_text(table_markdown(res))
    print(table_markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
