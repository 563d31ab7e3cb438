"""Shared pieces of the evaluation tests (tests/ is on sys.path): a tiny VGG, a tiny enhancer
analytic sheet sequences (a travelling fold, optional fine ripples) and the cell files
that the evaluation scripts read; meters."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from wrinkle_jax import enhancer, meshio, primitives
from wrinkle_jax.evaluation import cells
from wrinkle_jax.nn import unet, vgg
from wrinkle_jax.sim import scenes

SIZE = (0.3, 0.2)  # sheet, meters
TEXEL = 0.004
PATCH = 32
FOLD = 0.3  # wavelength of the fold, meters


def tiny_vgg_params():
    return vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8), num_convs=16,
                          spec=vgg.VGGSpec("custom", "REFLECT"))


def tiny_model():
    config = enhancer.EnhancerConfig(unet.UNetConfig(width=4, residual=True), patch_size=PATCH,
                                     texel_size=TEXEL)
    return enhancer.init_enhancer(jax.random.key(0, impl="rbg"), config)


def fold_height(x, y, t, ripple):
    """Travelling fold (2 cm amplitude, 30 cm wavelength) plus optional fine ripples (m)."""
    return (0.02 * np.sin(2 * np.pi * x / FOLD + 0.5 * t)
            + ripple * np.sin(2 * np.pi * y / 0.02))


def sheet_sequence(nx, ny, frames, ripple=0.0, metadata=None):
    g = primitives.grid_sheet(nx, ny, size=SIZE)
    v = np.asarray(g.vertices)
    out = np.stack([np.c_[v[:, :2], fold_height(v[:, 0], v[:, 1], t, ripple)]
                    for t in range(frames)]).astype(np.float32)
    return meshio.make_sequence(out, g, metadata=metadata)


def sheet_pair(frames=3):
    """(fine 5 mm grid with ripples, coarse 30 mm grid) of the same sheet and fold."""
    return (sheet_sequence(60, 40, frames, ripple=0.002), sheet_sequence(10, 7, frames))


def write_cell_files(root, garment, motion, material, frames=3):
    """Tiny fine/coarse sheet files that `evaluation.cells.cell_sequences` accepts for a cell."""
    sc = cells.scene_for(garment, motion)
    fine, coarse = sheet_pair(frames)
    for res, seq in (("fine", fine), ("coarse", coarse)):
        substeps, self_collision = scenes.dataset_solver(sc, res)  # as the data set's files
        meta = {"scene_config": sc.to_json(), "material": material, "seed": cells.TEST_SEED,
                "substeps": substeps, "self_collision": dataclasses.asdict(self_collision)}
        seq = meshio.make_sequence(seq.frames, seq.garment, metadata=meta)
        path = cells.sequence_file(root, sc.name, material, res, cells.TEST_SEED)
        meshio.save_sequence(path, seq)
