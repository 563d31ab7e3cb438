"""The `wrinkle-jax train-enhancer` sub-command (`wrinkle_jax.cli`): train (or resume) the
enhancer with the shipped recipe and the recipe flags (`wrinkle_jax.recipe`), and export a
run as a model file. `cli` re-exports every name here (old import paths keep working).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def train_config(args):
    """The `train.TrainConfig` of a parsed `train-enhancer` command line: the recipe flags
    (`recipe.config_from_args`, as `experiments.train_default` reads them) plus the seed and
    the evaluation and checkpoint intervals, which only this command sets."""
    import dataclasses

    from wrinkle_jax import recipe

    extra = {"seed": args.seed, "eval_every": args.eval_every,
             "checkpoint_every": args.checkpoint_every}
    return dataclasses.replace(recipe.config_from_args(args),
                               **{k: v for k, v in extra.items() if v is not None})


def _cmd_train_enhancer(args) -> int:
    from wrinkle_jax import recipe, train
    from wrinkle_jax.validate import UsageError

    if args.export_only and not args.export:
        raise UsageError("--export-only needs --export PATH")
    t0 = time.time()
    if not args.export_only:
        if args.data is None:
            raise UsageError("--data is required to train (--export-only --export PATH "
                             "exports an existing run)")
        if not Path(args.data, "index").is_dir():
            print(f"wrinkle-jax train-enhancer: error: {args.data}: not a patch data set "
                  "(no index/ folder; build one with wrinkle_jax.data.build_dataset)",
                  file=sys.stderr)
            return 1
        try:
            # JSON lines on stdout: the chosen --material-gains (if any), then the last metrics.
            result = recipe.train_from_args(train_config(args), args, Path(args.data),
                                            Path(args.out), resume=args.resume, progress=True)
        except recipe.RecipeError as e:
            raise UsageError(str(e)) from None
        print(json.dumps({k: v for k, v in result["last"].items()}, indent=2))
    if args.export:
        # The data facts the run recorded (data.json), so --export-only needs no --data.
        path = train.export_run(args.out, args.export, None,
                                None if args.export_only else round(time.time() - t0, 1),
                                steps=recipe.export_steps(args))
        print(json.dumps({"exported": str(path), "bytes": path.stat().st_size}))
    return 0
