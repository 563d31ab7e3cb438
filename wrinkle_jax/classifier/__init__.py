"""Material classifiers: from motion (issue 25, the default of `wrinkle-jax classify` and
`--material auto`) and from normal-map patches (paper Sec. 4.2, Fig. 6; at chance here).

Motion (`motion`, `calibrated`; imported as submodules)::

    frames (T, V, 3) + body track (capsules or pins) --windows of 32 frames, stride 16-->
      motion features per window (kinematic, spectral, hem lag, stretch, curvature)
      --logistic regression--> window log p --mean over windows / temperature--> p (M,)
      --answer if max p >= threshold and the features look like the training sims--> or abstain

Temperature, threshold and the feature choice are fitted on cross-validation folds that leave
out one garment (all of its scenes) at a time (`folds`, imported as a submodule).

The rest of this docstring describes the patch classifier.

Modules (by concept): `config` (ClassifierConfig, feature specs), `features` (VGG features
per patch), `model` (the MLP, prediction), `voting` (Fig. 6), `sequences` (crops of a
sequence, `classify_sequence`), `fit` (training on cached features), `files` (model files),
`training` (the feature cache built from sequences) and `cli` (the `wrinkle-jax classify` and
`train-classifier` sub-commands). The names below are re-exported here; `training` and `cli`
are imported as submodules.

Pipeline, for a coarse garment sequence of unknown fabric::

    frames (T, V, 3) --bake at config.texel_size--> normal maps (H, W, 3) + mask
      --random valid crops (>= min_coverage garment texels), spread over time--> (P, S, S, 3)
      --VGG19 features (config.feature)--> (P, D) --4 fully connected layers--> (P, M) logits
      --sigmoid, normalized to sum 1--> per-patch probabilities
      --vote: per-material histogram of patch probabilities (Fig. 6)--> material + scores

Contract:
  * Patches are the RGB form ``(n + 1) / 2`` of coarse normal maps, multiplied by the mask
    (background 0), exactly like the enhancer's inputs (`wrinkle_jax.data`).
  * ``config.feature`` names a VGG layer and a reduction, ``"<layer>:<reduce>"``:
    ``grid4`` averages the layer to a 4 x 4 grid and flattens it (``relu5_4:grid4`` is the
    paper's pool5, 4 x 4 x 512 = 8,192 values with average pooling), ``stats`` takes the
    per-channel mean and standard deviation over the garment texels (2 C values; a
    translation-invariant texture statistic, like the Gram matrices of the style loss).
    Features go through ``log1p`` (VGG activations are heavy-tailed) and are standardized by
    the training set's mean and std (stored with the model).
  * The MLP is four Dense layers (three hidden ReLU layers with dropout, then M outputs);
    probabilities are ``sigmoid(z) / sum(sigmoid(z))`` and the loss is the cross-entropy
    ``-log p[label]`` (paper).
  * Classification is a pure function of the key: same key, same answer.
  * Measured (experiments/results/classifier/README.md): on this project's simulated data the
    classifier is at chance on held-out scenes for every feature tried (the five fabrics give
    nearly the same coarse geometry at PD 30 mm), so no trained model ships yet and
    `load_classifier()` raises ClassifierError until one does. The default feature and sizes
    are the cheapest candidate of equal (chance-level) accuracy, not a validated choice.
  * The shipped model (``wrinkle_jax/assets/classifier.npz``) is a plain ``.npz`` (no
    pickle): ``params/<module>/<leaf>`` float16, ``norm/mean`` and ``norm/std`` float32,
    ``config.json`` and ``meta.json`` as uint8 bytes. The VGG19 weights are not in it; they come
    from `wrinkle_jax.nn.vgg.load_vgg19` (``meta["vgg"]`` records which).

Example:
    >>> import jax, numpy as np
    >>> from wrinkle_jax.nn import vgg
    >>> tiny = vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8),
    ...                       num_convs=4, spec=vgg.VGGSpec("custom", "REFLECT"))
    >>> cfg = ClassifierConfig(feature="relu2_1:stats", hidden=(16, 16, 16), patch_size=32)
    >>> clf = init_classifier(jax.random.key(1, impl="rbg"), cfg, tiny)
    >>> probs = predict_patches(clf, np.full((2, 32, 32, 3), 0.5, np.float32),
    ...                         np.ones((2, 32, 32, 1), np.float32))
    >>> probs.shape
    (2, 5)
"""

from wrinkle_jax.classifier.config import (
    GRID,
    REDUCTIONS,
    ClassifierConfig,
    ClassifierError,
    feature_dim,
)
from wrinkle_jax.classifier.features import feature_stats, patch_features
from wrinkle_jax.classifier.files import DEFAULT_PATH, load_classifier, save_classifier
from wrinkle_jax.classifier.fit import train_classifier
from wrinkle_jax.classifier.model import (
    Classifier,
    MaterialMLP,
    cross_entropy,
    init_classifier,
    predict_from_features,
    predict_patches,
    probabilities,
)
from wrinkle_jax.classifier.sequences import (
    classify_sequence,
    sample_patches,
    to_patch_frame,
    valid_origin_count,
)
from wrinkle_jax.classifier.voting import Classification, classify_patches, vote

__all__ = [
    "DEFAULT_PATH",
    "GRID",
    "REDUCTIONS",
    "Classification",
    "Classifier",
    "ClassifierConfig",
    "ClassifierError",
    "MaterialMLP",
    "classify_patches",
    "classify_sequence",
    "cross_entropy",
    "feature_dim",
    "feature_stats",
    "init_classifier",
    "load_classifier",
    "patch_features",
    "predict_from_features",
    "predict_patches",
    "probabilities",
    "sample_patches",
    "save_classifier",
    "to_patch_frame",
    "train_classifier",
    "valid_origin_count",
    "vote",
]
