"""Moved to `wrinkle_jax.evaluation` (scores, sets, flicker); this import path stays for
`wrinkle_jax.train`, which imports it, until that module is updated (issue 23)."""

from wrinkle_jax.evaluation.flicker import flicker_series, mean_angular_change, normal_angles
from wrinkle_jax.evaluation.scores import (
    ImprovementScore,
    improvement_score,
    improvement_score_from_losses,
)
from wrinkle_jax.evaluation.sets import (
    chamfer_distance,
    chamfer_from_sq_dists,
    decrease_ratio,
    spectral_embedding,
    sq_dists,
)

__all__ = ["ImprovementScore", "chamfer_distance", "chamfer_from_sq_dists", "decrease_ratio",
           "flicker_series", "improvement_score", "improvement_score_from_losses",
           "mean_angular_change", "normal_angles", "spectral_embedding", "sq_dists"]
