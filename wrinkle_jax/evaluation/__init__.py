"""Evaluation: scores, baselines, set and temporal metrics, aligned patch sets.

Modules (by concept):

    scores      the paper's improvement score and the detail-only `score_patches`
    stats       summaries: per-group means, bootstrap intervals, paired differences
    baselines   identity, unsharp masking, down/up-sampling (NumPy/OpenCV, masked)
    bands       band energies of detail maps, the 2-texel checkerboard artefact
    energy      local band-energy maps, coarse in-plane stretches, energy-matched gains
    sets        sets of patches without correspondence (paper Table 2): Chamfer, DR, embedding
    flicker     frame-to-frame angular change of normal maps
    seams       how much sharper normals turn across the tile borders of a merged map
    patchsets   coarse and fine maps on one pixel grid, aligned patch sets
    gram        several methods scored on the same patches with shared Gram matrices
    methods     the model, other model files and the baselines as methods on patch sets
    patchscores Table 1's scoring of a cell's patches, its cell files, the tables' setup
    setscores   Table 2's cell records (set distances), their files, means and table
    temporal    flicker of an enhanced sequence (streamed through the pipeline)
    cells       the evaluation cells (garment x material x motion) and their simulations
    suite       the evaluation scripts' folders, results files and argument parsers
    markdown    the evaluation report's line collector (missing results, machines)
    headlines   the evaluation report's headline rows, from the stored results

The names of `scores`, `stats`, `baselines`, `bands`, `sets` and `flicker` are re-exported
here (`evaluation.score_patches`, `evaluation.unsharp_mask`, `evaluation.chamfer_distance`,
...). The other modules are imported as submodules (most need the baking, network or
simulation stack): `from wrinkle_jax.evaluation import patchsets`.

Conventions: patches are in the RGB form of normal maps ((n + 1) / 2, in [0, 1]), NHWC
float32, with an (N, S, S, 1) float32 {0, 1} mask; normal maps are (H, W, 3) unit vectors.
"""

from wrinkle_jax.evaluation.bands import BAND_SIGMAS, band_rms, checker_rms
from wrinkle_jax.evaluation.baselines import identity, resample, unsharp_mask
from wrinkle_jax.evaluation.flicker import flicker_series, mean_angular_change, normal_angles
from wrinkle_jax.evaluation.scores import (
    EVAL_LAYERS,
    ImprovementScore,
    detail_triplet,
    improvement_score,
    improvement_score_from_losses,
    score_patches,
    scores_from_losses,
)
from wrinkle_jax.evaluation.sets import (
    chamfer_distance,
    chamfer_from_sq_dists,
    decrease_ratio,
    spectral_embedding,
    sq_dists,
)
from wrinkle_jax.evaluation.stats import bootstrap_ci, paired_difference, series_stats, summarize

__all__ = ["BAND_SIGMAS", "EVAL_LAYERS", "ImprovementScore", "band_rms", "bootstrap_ci",
           "chamfer_distance", "chamfer_from_sq_dists", "checker_rms", "decrease_ratio",
           "detail_triplet", "flicker_series", "identity", "improvement_score",
           "improvement_score_from_losses", "mean_angular_change", "normal_angles",
           "paired_difference", "resample", "score_patches", "scores_from_losses", "series_stats",
           "spectral_embedding", "sq_dists", "summarize", "unsharp_mask"]
