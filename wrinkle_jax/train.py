"""Training the enhancer: a jitted, data-parallel train step, evaluation, Orbax checkpoints that
resume exactly, JSONL metrics and a loss-curve plot.

    state = create_train_state(config, key)                   # params + Adam state + step
    step_fn = make_train_step(config, vgg_params, mesh)         # jitted, batch sharded on "data"
    state, metrics = step_fn(state, batch)                      # batch: dict of arrays

Data parallelism goes through `jax.sharding`: a `Mesh` with one axis named "data"; the batch is
split along it and the state is replicated, so the same code runs on one CPU device, on N local
devices (e.g. `XLA_FLAGS=--xla_force_host_platform_device_count=N`) and on several hosts under
`jax.distributed` (each process feeds its local slice of the batch through
`jax.make_array_from_process_local_data`).

The objective is the paper's (Sec. 4.1): `w_c * content(out, input) + w_s * style(out, target)`
on VGG19 features, with the network output masked to the garment. Optimizer: Adam with lr
1e-4 and b1 = b2 = 0.9 as in the paper (AdamW when `weight_decay` > 0).

A checkpoint holds the train state (params, optimizer state, step), the data iterator position
and the config; Orbax writes it atomically. `train(..., resume=True)` continues from the last
one and reproduces the uninterrupted run bit for bit on the same machine.

`TrainConfig`, `RECIPE` and `TrainState` are defined in `train_config`, the checkpoints, run
restore and export (`restore_run`, `averaged_params`, `export_run`, ...) in `train_runs`; both
are re-exported here.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from wrinkle_jax import detail
from wrinkle_jax import metrics as metrics_lib
from wrinkle_jax.data import BatchIterator, PatchDataset
from wrinkle_jax.fileio import atomic_write_text
from wrinkle_jax.nn import gram_bank, losses
from wrinkle_jax.numerics import safe_div

# The config and state, and the checkpoints / run restore / export, live in their own modules;
# every name stays importable from here (old import paths, run configs, pickles).
from wrinkle_jax.train_config import (  # noqa: F401
    RECIPE,
    TrainConfig,
    TrainState,
    create_train_state,
    optimizer,
)
from wrinkle_jax.train_runs import (  # noqa: F401
    _data_facts,
    _manager,
    _open_run,
    _restore_states,
    averaged_params,
    checkpoint_steps,
    export_run,
    restore_checkpoint,
    restore_run,
    save_checkpoint,
)


def _forward(config: TrainConfig, params, batch):
    """Network output in the RGB form, cut to the garment mask."""
    out = config.model().apply({"params": params}, batch["input"], batch["material"],
                               batch.get("origins"))
    return out * batch["mask"]


def loss_images(config: TrainConfig, batch: dict, out):
    """(input, output, target) in the representation the loss compares: the RGB forms
    themselves, or with `detail_sigma` their detail maps on the input's branch."""
    if config.unet.detail_sigma <= 0:
        return batch["input"], out, batch["target"]
    return detail.on_reference_branch_rgb(batch["input"], (out, batch["target"]), batch["mask"],
                                          config.unet.detail_sigma)


def loss_fn(params, batch, vgg_params, config: TrainConfig, bank=None):
    """Scalar objective and per-sample parts (content, style, total; band with
    `band_weight`; "bank" with `bank_weight`: the distance of each output's Gram features to
    the nearest fine patch of its material in `bank`, a `nn.gram_bank.GramBank`)."""
    from wrinkle_jax.nn import vgg

    inp, out, target = loss_images(config, batch, _forward(config, params, batch))
    out_f = None
    if config.bank_weight > 0:
        if bank is None:
            raise ValueError("bank_weight > 0 needs a bank (nn.gram_bank.GramBank)")
        layers = tuple(sorted(set(config.style_layers) | {config.content_layer}
                              | set(bank.layers)))
        out_f = vgg.features(vgg_params, out, layers=layers, pool=config.pool,
                             conv_impl=config.vgg_conv_impl)
    total, parts = losses.enhancer_loss(
        vgg_params, out, inp, target, batch["mask"],
        style_layers=config.style_layers, content_layer=config.content_layer,
        w_c=config.w_c, w_s=config.w_s, pool=config.pool,
        normalize_channels=config.normalize_channels, conv_impl=config.vgg_conv_impl,
        relative_floor=config.relative_floor, relative_log=config.relative_log,
        out_features=out_f)
    if config.band_weight > 0:
        band = losses.band_loss(out, target, batch["mask"])
        parts = {**parts, "band": band, "total": parts["total"] + config.band_weight * band}
        total = jnp.mean(parts["total"])
    if config.bank_weight > 0:
        x = gram_bank.feature_vectors(out_f, batch["mask"], bank)
        near = gram_bank.nearest_distance(x, batch["material"], jnp.asarray(bank.vectors),
                                          jnp.asarray(bank.material))
        parts = {**parts, "bank": near, "total": parts["total"] + config.bank_weight * near}
        total = jnp.mean(parts["total"])
    return total, parts


def data_mesh(devices=None) -> jax.sharding.Mesh:
    """A one-axis ("data") mesh over the given devices (default: all)."""
    devices = jax.devices() if devices is None else devices
    return jax.sharding.Mesh(np.asarray(devices), ("data",))


def shard_batch(batch: dict, mesh: jax.sharding.Mesh) -> dict:
    """Place a host batch (this process's slice) onto the mesh, split along "data"."""
    sharding = NamedSharding(mesh, P("data"))
    return {k: jax.make_array_from_process_local_data(sharding, np.asarray(v))
            for k, v in batch.items()}


def place_state(state, mesh: jax.sharding.Mesh | None = None):
    """`state` (a `TrainState`, or any pytree of arrays) replicated on `mesh` (default: all
    devices), as the train step returns it.

    Place a state before its first step: its avals then carry the mesh like the step's
    output, so the second step reuses the first one's program. A state placed otherwise is
    another input type to jit and the step compiles again (about 50 s for the authors' width-64
    recipe in the Winograd form, session 27).
    """
    mesh = data_mesh() if mesh is None else mesh
    return jax.device_put(state, NamedSharding(mesh, P()))


def make_train_step(config: TrainConfig, vgg_params, mesh: jax.sharding.Mesh | None = None,
                    bank=None):
    """The jitted `(state, batch) -> (state, metrics)` step, data parallel over `mesh`
    (`bank`: see `loss_fn`). Pass it a state placed by `place_state` and a batch from
    `shard_batch` on the same mesh, or its second call compiles again."""
    mesh = data_mesh() if mesh is None else mesh
    tx = optimizer(config)
    replicated = NamedSharding(mesh, P())
    vgg_params = place_state(vgg_params, mesh)  # replicated, like the state
    if bank is not None:
        bank = dataclasses.replace(bank, vectors=place_state(bank.vectors, mesh),
                                   material=place_state(bank.material, mesh))

    def step(state: TrainState, batch: dict):
        (loss, parts), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, batch, vgg_params, config, bank)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        out = {"loss": loss, "content": jnp.mean(parts["content"]),
               "style": jnp.mean(parts["style"]), "grad_norm": optax.tree.norm(grads),
               **{k: jnp.mean(parts[k]) for k in ("band", "bank") if k in parts}}
        return TrainState(state.step + 1, params, opt_state), out

    batch_sharding = NamedSharding(mesh, P("data"))
    return jax.jit(step, in_shardings=(replicated, batch_sharding),
                   out_shardings=(replicated, replicated), donate_argnums=(0,))


def make_eval_step(config: TrainConfig, vgg_params):
    """Jitted `(params, batch) -> per-sample content, style, improvement score, valid` and,
    for detail models, the output's band RMS relative to the target's (`band_<name>`).

    The improvement score uses the training style loss (same layers and normalization):
    100 |L(input) - L(output)| / L(input), with L the style loss against the target.
    """
    from wrinkle_jax.nn import vgg

    layers = tuple(sorted(set(config.style_layers) | {config.content_layer}))

    def eval_fn(params, batch):
        inp, out, target = loss_images(config, batch, _forward(config, params, batch))
        n = out.shape[0]
        feats = vgg.features(vgg_params, jnp.concatenate([inp, out, target]),
                             layers=layers, pool=config.pool, conv_impl=config.vgg_conv_impl)
        f_in, f_out, f_tgt = ({k: v[i * n:(i + 1) * n] for k, v in feats.items()}
                              for i in range(3))
        mask = batch["mask"]

        def style(f):
            return losses.style_loss(f, f_tgt, mask, config.style_layers,
                                     normalize_channels=config.normalize_channels)

        loss_in, loss_out = style(f_in), style(f_out)
        # Losses scale with the VGG weights and layer choice; only an exact (to float32
        # rounding) match of input and target makes the score undefined.
        eps = 1e-6 * jnp.maximum(jnp.max(loss_in), 1e-30)
        score = metrics_lib.improvement_score_from_losses(loss_in, loss_out, eps=eps)
        content = losses.content_loss(f_out, f_in, mask, config.content_layer)
        bands = {}
        if config.unet.detail_sigma > 0:
            bands = {f"band_{k}": safe_div(o, t)
                     for k, (o, t) in detail.band_rms_pair(out, target, mask).items()}
        return {"content": content, "style": loss_out, "input_style": loss_in,
                "improvement": score.score, "improvement_signed": score.signed_score,
                "valid": score.valid, **bands}

    return jax.jit(eval_fn)


# Jitted steps of earlier `train` calls, reused by later calls in the same process (a resumed
# run, a study's variants): building a step anew re-traces and re-compiles it, seconds of CPU
# each call. Keyed on what the step closes over -- the frozen config, the VGG parameters'
# identity and the mesh; each entry holds its VGG pytree, so that while the entry lives no
# other object can take its id(). (VGG parameters mutated in place would be missed: they are
# treated as immutable, like every parameter pytree here.) A few entries only: each keeps
# compiled programs and, for the real VGG19, 80 MB of weights alive.
_STEP_CACHE: dict[tuple, tuple[Any, Any]] = {}
_STEP_CACHE_SIZE = 4
# Settings only the training loop reads (cadences, budget, data order, batch size -- a shape,
# which jit specializes on by itself); the key and the built steps see them at their
# defaults, so e.g. a run cut at 2 steps and its resumption to 4 share one program.
_LOOP_ONLY = ("batch_size", "steps", "seed", "eval_every", "eval_batches", "checkpoint_every",
              "keep_checkpoints")


def cached_step(kind: str, config: TrainConfig, vgg_params,
                mesh: jax.sharding.Mesh | None = None, bank=None):
    """`make_train_step(config, vgg_params, mesh)` (kind "train") or `make_eval_step(config,
    vgg_params)` (kind "eval"), built once per (config, VGG params object, mesh) and then
    returned again (least recently used entries are dropped past `_STEP_CACHE_SIZE`); configs
    that differ only in loop settings (`_LOOP_ONLY`) share their steps."""
    if kind not in ("train", "eval"):
        raise ValueError(f"kind: 'train' or 'eval', got {kind!r}")
    mesh = data_mesh() if mesh is None and kind == "train" else mesh
    config = dataclasses.replace(
        config, **{f: TrainConfig.__dataclass_fields__[f].default for f in _LOOP_ONLY})
    key = (kind, config, id(vgg_params), mesh, id(bank))
    hit = _STEP_CACHE.pop(key, None)
    if hit is None:
        fn = (make_train_step(config, vgg_params, mesh, bank) if kind == "train"
              else make_eval_step(config, vgg_params))
        hit = ((vgg_params, bank), fn)
    _STEP_CACHE[key] = hit  # (re)inserted last: dicts keep insertion order, oldest first
    while len(_STEP_CACHE) > _STEP_CACHE_SIZE:
        del _STEP_CACHE[next(iter(_STEP_CACHE))]
    return hit[1]


def enhance_batch(config: TrainConfig, params, batch: dict, batch_size: int = 16) -> np.ndarray:
    """A training run's network (`config.model()`, its `conv_impl`) on a batch of patches.

    Args:
      params: the run's parameters (e.g. `restore_run(run)[1].params`).
      batch: "input" (N, S, S, 3) RGB-form patches in [0, 1], "material" (N,) int ids,
        "mask" (N, S, S, 1) {0, 1} (a `data.PatchDataset.get` batch).
    Returns:
      (N, S, S, 3) float32 RGB form: the output clipped to [0, 1], renormalized to unit normals
      inside the mask, 0 outside (`enhancer.enhance_patches`, jitted chunks of `batch_size`).
    """
    from wrinkle_jax import enhancer  # enhancer is not needed to train; keep the import local

    model = config.model()
    fn = jax.jit(lambda p, x, m: jnp.clip(model.apply({"params": p}, x, m), 0.0, 1.0))
    return enhancer.enhance_patches(fn, params, batch["input"], batch["material"],
                                    batch["mask"], batch_size)


# --------------------------------------------------------------------------------------------
# The loop
# --------------------------------------------------------------------------------------------


def evaluate(eval_step, params, batches: list[dict]) -> dict:
    """Mean content, style and improvement score over fixed held-out batches."""
    parts = [jax.device_get(eval_step(params, b)) for b in batches]
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    valid = cat["valid"].astype(bool)
    return {"heldout_content": float(cat["content"].mean()),
            "heldout_style": float(cat["style"].mean()),
            "heldout_input_style": float(cat["input_style"].mean()),
            "heldout_improvement": float(cat["improvement"][valid].mean()) if valid.any()
            else float("nan"),
            # The paper's score takes |.|, so an output that overshoots the target's style by
            # as much as the input misses it also scores 100; the signed form is negative
            # when the output is further from the target than the input.
            "heldout_improvement_signed": float(cat["improvement_signed"][valid].mean())
            if valid.any() else float("nan"),
            # Per-patch scores are heavy-tailed; the evaluation leads with the median.
            "heldout_improvement_signed_median":
                float(np.median(cat["improvement_signed"][valid])) if valid.any()
                else float("nan"),
            "heldout_improvement_valid": float(valid.mean()),
            # Output band energy / the target's (median over patches; 1 = the fine level).
            **{f"heldout_{k}_median": float(np.median(v[valid])) if valid.any()
               else float("nan") for k, v in cat.items() if k.startswith("band_")}}


def plot_curves(metrics_path: Path, out_png: Path) -> None:
    """Loss curves (train total/style, held-out style and improvement) from the JSONL log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(line) for line in metrics_path.read_text().splitlines() if line]
    train = [r for r in rows if r["kind"] == "train"]
    held = [r for r in rows if r["kind"] == "eval"]
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.6))
    if train:
        steps = np.array([r["step"] for r in train])
        style = np.array([r["style"] for r in train])
        axes[0].semilogy(steps, style, lw=0.6, alpha=0.35, label="per step")
        k = min(50, len(style))  # trailing mean: single batches of 8 patches are noisy
        smooth = np.convolve(style, np.ones(k) / k, mode="valid")
        axes[0].semilogy(steps[k - 1:], smooth, lw=1.5, label=f"mean of {k} steps")
        axes[0].legend()
    if held:
        hs = [r["step"] for r in held]
        axes[1].semilogy(hs, [r["heldout_style"] for r in held], "o-", label="output")
        axes[1].semilogy(hs, [r["heldout_input_style"] for r in held], "--", label="input")
        axes[1].legend()
        axes[2].plot(hs, [r["heldout_improvement"] for r in held], "o-", label="paper |.| form")
        if "heldout_improvement_signed" in held[0]:
            axes[2].plot(hs, [r["heldout_improvement_signed"] for r in held], "s-",
                         label="signed")
        axes[2].legend()
    titles = ("train style term (the objective's units)", "held-out style loss (absolute)",
              "held-out improvement score (%)")
    for ax, title in zip(axes, titles, strict=True):
        ax.set_xlabel("step")
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    from wrinkle_jax.fileio import atomic_write_bytes

    atomic_write_bytes(out_png, buf.getvalue())


def training_bank(config: TrainConfig, dataset: PatchDataset, vgg_params,
                  path: str | os.PathLike | None = None) -> gram_bank.GramBank:
    """The fine-target bank of the `bank_weight` term: `config.bank_size` random training
    patches per material (seeded by `config.seed`), their targets in the loss's
    representation (`loss_images`), Gram features on `config.style_layers`. Loaded from `path`
    if it exists (a resumed run keeps its bank), else built and saved there."""
    if path is not None and Path(path).exists():
        return gram_bank.load_bank(path)
    rng = np.random.default_rng([config.seed, 7])
    rows = []
    for m in np.unique(dataset.materials):
        idx = np.flatnonzero(dataset.materials == m)
        rows.append(np.sort(rng.choice(idx, min(config.bank_size, len(idx)), replace=False)))
    idx = np.concatenate(rows)
    images, masks = [], []
    for i in range(0, len(idx), 64):
        batch = dataset.get(idx[i:i + 64])
        _, target, _ = loss_images(config, batch, batch["target"])
        images.append(np.asarray(target))
        masks.append(np.asarray(batch["mask"]))
    bank = gram_bank.build_bank(vgg_params, np.concatenate(images), np.concatenate(masks),
                                dataset.materials[idx], config.style_layers,
                                conv_impl=config.vgg_conv_impl)
    if path is not None:
        gram_bank.save_bank(path, bank)
    return bank


def train(config: TrainConfig, data_root: str | os.PathLike, out_dir: str | os.PathLike,
          resume: bool = False, vgg_params=None, progress: bool = True,
          time_limit_s: float | None = None, init_params=None,
          train_scenes: tuple[str, ...] | None = None, eval_split: str = "heldout") -> dict:
    """Train (or resume training) the enhancer; returns the last metrics.

    Writes `out_dir/checkpoints/<step>/`, `out_dir/metrics.jsonl` (one JSON object per logged
    train step and per evaluation), `out_dir/loss_curve.png`, `out_dir/config.json` and
    `out_dir/data.json` (the data set's root, patch and texel size, coarse particle distance and
    training sequences, which `export_run` writes into the model file).

    Args:
      time_limit_s: stop (with an evaluation and a checkpoint) after the first step that ends
        past this many seconds of wall time, counted from the first step -- for
        equal-wall-clock comparisons and session budgets; `--resume` continues later.
      init_params: warm-start parameters (a CINUNet pytree of this config's shapes) for a fresh
        run, e.g. the shipped model's; ignored when resuming from a checkpoint.
      train_scenes: train on these scenes' patches only (e.g. the sheet-only ablation); the
        held-out evaluation keeps every held-out scene.
      eval_split: the split the periodic evaluation reads ("heldout"; "val": frames of the
        training scenes set aside; or "valgarment": the validation-only garment, so that
        recipe and checkpoint choices never see held-out data).
    """
    from tqdm import tqdm

    from wrinkle_jax.nn import vgg

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    vgg_params = vgg.load_vgg19() if vgg_params is None else vgg_params
    train_set = PatchDataset(data_root, "train", scenes=train_scenes)
    held_set = PatchDataset(data_root, eval_split)
    mesh = data_mesh()
    if config.batch_size % mesh.size:
        raise ValueError(f"batch_size {config.batch_size} is not divisible by {mesh.size} devices")
    iterator = BatchIterator(train_set, config.batch_size, seed=config.seed,
                             origins=config.unet.noise_channels > 0)
    manager = _manager(out_dir / "checkpoints", config)
    # rbg keys: threefry initialization compiles ~8x slower on CPU (see unet.init_params).
    key = jax.random.key(config.seed, impl="rbg")
    state = create_train_state(config, key, train_set.patch_size)
    if init_params is not None:
        # Copies: the train step donates its state, which must not delete the caller's arrays.
        params = jax.tree.map(lambda p, q: jnp.array(q, p.dtype, copy=True).reshape(p.shape),
                              state.params, init_params)
        state = TrainState(state.step, params, optimizer(config).init(params))
    metrics_path = out_dir / "metrics.jsonl"
    if resume and manager.latest_step() is not None:
        state, iterator.state = restore_checkpoint(manager, state, config)
        # Drop log lines past the checkpoint so the log matches the resumed run.
        if metrics_path.exists():
            keep = [line for line in metrics_path.read_text().splitlines()
                    if line and json.loads(line)["step"] <= int(state.step)]
            atomic_write_text(metrics_path, "".join(k + "\n" for k in keep))
    elif metrics_path.exists():
        metrics_path.unlink()
    atomic_write_text(out_dir / "config.json", json.dumps(config.to_json(), indent=2))
    atomic_write_text(out_dir / "data.json", json.dumps(
        {"data_root": str(Path(data_root).absolute()),
         "train_scenes_selected": None if train_scenes is None else list(train_scenes),
         "eval_split": eval_split, **_data_facts(train_set)}, indent=1))

    # One placement for every start (fresh, warm-started or restored): the step returns its
    # state replicated on the mesh, and a state placed otherwise is another input type to
    # jit (its avals carry the mesh), so the step and the eval step would compile again.
    state = place_state(state, mesh)
    bank = (training_bank(config, train_set, vgg_params, out_dir / "bank.npz")
            if config.bank_weight > 0 else None)
    # Reused across calls (a resume compiles nothing new; see `cached_step`).
    step_fn = cached_step("train", config, vgg_params, mesh, bank)
    eval_step = cached_step("eval", config, vgg_params)
    # Fixed held-out patches spread over the whole split (all held-out sequences), not its head.
    n_eval = min(len(held_set), config.eval_batches * config.batch_size)
    held_idx = np.unique(np.linspace(0, len(held_set) - 1, n_eval).round().astype(int))
    held_batches = [held_set.get(held_idx[i:i + config.batch_size])
                    for i in range(0, len(held_idx), config.batch_size)]
    start = int(state.step)
    last: dict = {}
    t_start = time.perf_counter()
    with open(metrics_path, "a") as log, tqdm(total=config.steps, initial=start,
                                              disable=not progress, desc="train") as bar:
        for step in range(start, config.steps):
            batch = shard_batch(next(iterator), mesh)
            t0 = time.perf_counter()
            state, m = step_fn(state, batch)
            m = {k: float(v) for k, v in jax.device_get(m).items()}
            m.update(kind="train", step=step + 1, step_s=time.perf_counter() - t0)
            log.write(json.dumps(m) + "\n")
            last = m
            done = step + 1
            out_of_time = (time_limit_s is not None
                           and time.perf_counter() - t_start > time_limit_s)
            final = done == config.steps or out_of_time
            if held_batches and (done % config.eval_every == 0 or final):
                e = evaluate(eval_step, state.params, held_batches)
                e.update(kind="eval", step=done)
                log.write(json.dumps(e) + "\n")
                last = {**last, **e}
                bar.set_postfix(style=f"{m['style']:.3g}", held=f"{e['heldout_style']:.3g}")
            log.flush()
            if done % config.checkpoint_every == 0 or final:
                save_checkpoint(manager, state, iterator.state, config)
            bar.update(1)
            if out_of_time:
                break
    if metrics_path.stat().st_size:
        plot_curves(metrics_path, out_dir / "loss_curve.png")
    return {"state": state, "last": last}
