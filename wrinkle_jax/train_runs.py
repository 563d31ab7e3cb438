"""Training runs on disk: Orbax checkpoints that resume exactly (train state, data iterator
position and config), restoring a run folder written by `train.train` (`restore_run`,
`checkpoint_steps`, `averaged_params`) and exporting it as an enhancer model file
(`export_run`). `train` re-exports every name here (old import paths keep working).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import numpy as np

from wrinkle_jax.data import IteratorState, PatchDataset
from wrinkle_jax.train_config import TrainConfig, TrainState, create_train_state


def _manager(directory: Path, config: TrainConfig):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=config.keep_checkpoints, create=True)
    return ocp.CheckpointManager(directory.absolute(), options=options)


def save_checkpoint(manager, state: TrainState, iterator: IteratorState, config: TrainConfig):
    import orbax.checkpoint as ocp

    step = int(state.step)
    meta = {"step": step, "iterator": dataclasses.asdict(iterator), "config": config.to_json()}
    manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                               meta=ocp.args.JsonSave(meta)))
    manager.wait_until_finished()


def restore_checkpoint(manager, template: TrainState, config: TrainConfig, step=None):
    """Restore (state, iterator state) from `step` (default: the latest).

    Raises:
      ValueError: when the checkpoint's config differs from `config` in anything but the
        step budget and the logging/checkpoint cadence.
    """
    import orbax.checkpoint as ocp

    step = manager.latest_step() if step is None else step
    if step is None:
        raise FileNotFoundError(f"{manager.directory}: no checkpoint to resume from")
    abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, template)
    got = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                        meta=ocp.args.JsonRestore()))
    saved = TrainConfig.from_json(got["meta"]["config"]).to_json()
    want = config.to_json()
    free = ("steps", "eval_every", "eval_batches", "checkpoint_every", "keep_checkpoints",
            "conv_impl")
    diff = {k for k in want if k not in free and saved[k] != want[k]}
    if diff:
        raise ValueError(f"{manager.directory}: checkpoint was trained with a different "
                         f"config ({', '.join(sorted(diff))})")
    return got["state"], IteratorState(**got["meta"]["iterator"])


def _open_run(run_dir: str | os.PathLike):
    """(config, checkpoint manager) of a run folder written by `train`."""
    run = Path(run_dir)
    if not (run / "config.json").is_file():
        raise FileNotFoundError(f"{run}: no training run here (no config.json), so no checkpoint")
    cfg = TrainConfig.from_json(json.loads((run / "config.json").read_text()))
    return cfg, _manager(run / "checkpoints", cfg)


def _restore_states(run_dir: str | os.PathLike, steps: Sequence[int | None]):
    """(config, [train state at each of `steps`]) (None: the last checkpoint); the run's
    config, manager and state template are built once."""
    cfg, manager = _open_run(run_dir)
    # Only the shapes are needed: tracing the init is far cheaper than running it at 128 px.
    template = jax.eval_shape(lambda: create_train_state(cfg, jax.random.key(0, impl="rbg")))
    return cfg, [restore_checkpoint(manager, template, cfg, s)[0] for s in steps]


def restore_run(run_dir: str | os.PathLike, step: int | None = None
                ) -> tuple[TrainConfig, TrainState]:
    """The config and the train state of a run folder written by `train` (its
    ``config.json`` and ``checkpoints/``), at its last checkpoint or at `step`."""
    cfg, (state,) = _restore_states(run_dir, [step])
    return cfg, state


def checkpoint_steps(run_dir: str | os.PathLike) -> list[int]:
    """The steps of a run folder's kept checkpoints, ascending."""
    return sorted(int(s) for s in _open_run(run_dir)[1].all_steps())


def averaged_params(run_dir: str | os.PathLike, steps: Sequence[int]):
    """(config, the parameter mean over the run's checkpoints at `steps`) (float32 leaves).

    Weight averaging of checkpoints along one run (they share an architecture and lie in one
    basin, so the mean is a network too): it smooths the last steps' noise, a common
    regulariser for generalisation to unseen inputs. One step returns that checkpoint."""
    if not steps:
        raise ValueError("averaged_params needs at least one step")
    cfg, states = _restore_states(run_dir, [int(s) for s in steps])
    params = jax.tree_util.tree_map(
        lambda *x: np.mean(np.stack([np.asarray(v, np.float32) for v in x]), 0),
        *[st.params for st in states])
    return cfg, params


def _data_facts(ds: PatchDataset) -> dict:
    """What a model file records about the patch data set it was trained on."""
    entry = ds.entries[0]
    return {"patch_size": ds.patch_size, "texel_size": entry["texel_size"],
            "coarse_pd": entry["config"]["coarse_pd"], "train_patches": len(ds),
            "train_sequences": [e["sequence"] for e in ds.entries],
            "train_scenes": sorted({e["scene"] for e in ds.entries})}


def export_run(run_dir: str | os.PathLike, out_path: str | os.PathLike,
               data_root: str | os.PathLike | None = None, wall_s: float | None = None,
               train_scenes: tuple[str, ...] | None = None,
               steps: Sequence[int] | None = None) -> Path:
    """Write a run's last checkpoint as an enhancer model file (`enhancer.save_enhancer`,
    float16, loadable by `wrinkle_jax.load_enhancer`) with the training facts in its metadata;
    returns `out_path`.

    Args:
      data_root: None: the data facts the run recorded (``data.json``, written by `train`);
        or the patch data set the run trained on, read again (needed for runs from before
        ``data.json`` existed), restricted to `train_scenes` if given.
      wall_s: seconds of wall time to record (``meta["wall_seconds_this_call"]``).
      steps: None: the last checkpoint; else the checkpoints at these steps, their parameters
        averaged (`averaged_params`; one step = that checkpoint), recorded in
        ``meta["checkpoint_steps"]``.

    Raises:
      FileNotFoundError: naming the folder, if it holds no run, no checkpoint, or (without
        `data_root`) no ``data.json``.
    """
    from wrinkle_jax import MATERIALS, enhancer

    run = Path(run_dir)
    if steps is None:
        cfg, state = restore_run(run)
        params, last_step = state.params, int(state.step)
    else:
        (cfg, params), last_step = averaged_params(run, steps), int(max(steps))
    if data_root is not None:
        facts = _data_facts(PatchDataset(data_root, "train", scenes=train_scenes))
    elif (run / "data.json").is_file():
        facts = json.loads((run / "data.json").read_text())
    else:
        raise FileNotFoundError(f"{run}: no data.json (a run written before it was recorded): "
                                "give the data set it trained on")
    econf = enhancer.EnhancerConfig(unet=cfg.unet, materials=MATERIALS,
                                    patch_size=facts["patch_size"],
                                    texel_size=facts["texel_size"], coarse_pd=facts["coarse_pd"])
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if x]
    train_s = float(sum(r.get("step_s", 0.0) for r in rows if r["kind"] == "train"))
    evals = [r for r in rows if r["kind"] == "eval"]
    meta = {"train_config": cfg.to_json(),
            "steps": last_step,
            "checkpoint_steps": None if steps is None else [int(x) for x in steps],
            "train_step_seconds": round(train_s, 1), "wall_seconds_this_call": wall_s,
            "train_patches": facts["train_patches"], "train_sequences": facts["train_sequences"],
            "train_scenes": facts["train_scenes"], "last_eval": evals[-1] if evals else None,
            "exported": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())}
    return enhancer.save_enhancer(out_path, jax.device_get(params), econf, meta)
