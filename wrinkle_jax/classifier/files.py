"""Classifier model files: a plain `.npz` (no pickle), the shipped default at `DEFAULT_PATH`."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import modelfile
from wrinkle_jax.classifier.config import ClassifierConfig, ClassifierError, feature_dim
from wrinkle_jax.classifier.model import Classifier, _model
from wrinkle_jax.nn import vgg

DEFAULT_PATH = Path(__file__).resolve().parents[1] / "assets" / "classifier.npz"
_FORMAT = "wrinkle-jax-classifier/1"


def save_classifier(path: str | os.PathLike, classifier: Classifier, meta: dict | None = None,
                    dtype=np.float16) -> Path:
    """Write the MLP parameters (float16), standardization and config to `path` atomically.

    The VGG weights are not written (``meta["vgg"]`` should say which were used).
    """
    path = Path(path)
    arrays = modelfile.cast_params(classifier.params, dtype, path, ClassifierError)
    for k, v in classifier.norm.items():
        arrays[f"norm/{k}"] = np.asarray(v, np.float32)
    return modelfile.write(path, arrays, classifier.config.to_json(),
                           {**classifier.meta, **(meta or {})}, _FORMAT)


def load_classifier(path: str | os.PathLike | None = None, vgg_params=None) -> Classifier:
    """Load a classifier file (default: the shipped ``wrinkle_jax/assets/classifier.npz``).

    Args:
      path: an ``.npz`` written by `save_classifier`; None for `DEFAULT_PATH`.
      vgg_params: the VGG19 to compute features with (default: `vgg.load_vgg19()`, the
        weights the shipped model was trained with).
    Raises:
      ClassifierError: naming the file, if it is missing, not a classifier file, or its
        parameters do not match its config and the VGG.
    """
    path = Path(DEFAULT_PATH if path is None else path)
    if not path.is_file():
        hint = (" (the shipped model is trained by "
                "`python -m experiments.classifier_report --ship`)" if path == DEFAULT_PATH
                else "")
        raise ClassifierError(f"{path}: no such classifier file{hint}")
    files, config, meta = modelfile.read(path, "classifier", _FORMAT, ClassifierError)
    try:
        config = ClassifierConfig.from_json(config)
    except (TypeError, ValueError, KeyError) as e:
        raise ClassifierError(f"{path}: not a readable classifier file ({e})") from None
    vgg_params = vgg.load_vgg19() if vgg_params is None else vgg_params
    flat = modelfile.float32_params(files)
    norm = {k[len("norm/"):]: jnp.asarray(v, jnp.float32) for k, v in files.items()
            if k.startswith("norm/")}
    try:
        d = feature_dim(vgg_params, config.feature, config.patch_size)
    except ValueError as e:
        raise ClassifierError(f"{path}: {e}") from None
    want = jax.eval_shape(lambda: _model(config).init(jax.random.key(0, impl="rbg"),
                                                      jnp.zeros((1, d)))["params"])
    want_shapes = modelfile.flatten(want, lambda s: tuple(s.shape))
    got_shapes = {k: v.shape for k, v in flat.items()}
    if want_shapes != got_shapes or set(norm) != {"mean", "std"} or any(
            v.shape != (d,) for v in norm.values()):
        raise ClassifierError(f"{path}: parameters do not match the config ({config.feature}, "
                              f"hidden {config.hidden}, {d} features with this VGG)")
    if not all(np.all(np.isfinite(v)) for v in flat.values()):
        raise ClassifierError(f"{path}: non-finite parameters")
    params = jax.tree.map(jnp.asarray, modelfile.unflatten(flat))
    return Classifier(config, params, norm, vgg_params, meta)
