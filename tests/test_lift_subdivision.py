"""The lifted mesh's subdivision level chosen from the texel size (`lift.texel_subdivision_level`,
`PipelineConfig.subdivision`)."""

from __future__ import annotations

import numpy as np
import pytest

from wrinkle_jax import enhancer, lift, mesh, pipeline, primitives, subdivision
from wrinkle_jax.nn.unet import UNetConfig


@pytest.mark.parametrize("edge, texel, k, expected", [
    (0.040, 0.002, 4.0, 2),    # 40 mm -> 10 mm (5 texels); one more level would be 2.5
    (0.032, 0.002, 4.0, 2),    # exactly k texels after 2 levels: kept at 2, not 1
    (0.0319, 0.002, 4.0, 1),   # just under: 2 levels would go below k texels
    (0.001, 0.002, 4.0, 0),    # very fine input (finer than a texel): never subdivided
    (0.008, 0.002, 4.0, 0),    # already exactly k texels
    (10.0, 0.002, 4.0, 6),     # very coarse (10 m edges): capped at max_levels
    (0.020, 0.001, 2.5, 3),    # 20 mm / 2.5 mm = 8 = 2^3
])
def test_level_on_known_edge_lengths(edge, texel, k, expected):
    assert lift.texel_subdivision_level(edge, texel, k) == expected


def test_level_is_the_finest_not_below_k_texels():
    """For any edge, L is the largest level whose edges stay >= k texels (or 0 / the cap)."""
    rng = np.random.default_rng(0)
    texel, k, cap = 0.002, 3.0, 5
    for edge in 10 ** rng.uniform(-3.5, 0.5, 200):
        level = lift.texel_subdivision_level(float(edge), texel, k, max_levels=cap)
        assert 0 <= level <= cap
        if level > 0:
            assert edge / 2**level >= k * texel * (1 - 1e-9)
        if level < cap:
            assert edge / 2 ** (level + 1) < k * texel


def test_level_rejects_nonpositive_input():
    for bad in [(0.0, 0.002), (0.01, 0.0), (-1.0, 0.002)]:
        with pytest.raises(ValueError):
            lift.texel_subdivision_level(*bad)


def _edge_lengths(g):
    e = mesh.unique_edges(g.faces)
    v = np.asarray(g.vertices, np.float64)
    lengths = np.sort(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1))
    return lengths[np.r_[True, np.diff(lengths) > 1e-6]]  # distinct lengths (float32 noise merged)


def test_upsample_with_levels_halves_every_edge():
    """Midpoint levels: every edge of level L is an edge length of the coarse mesh / 2^L (the
    mean over unique edges shifts slightly, as the inner edges weight the lengths anew)."""
    g = primitives.grid_sheet(5, 4, size=(0.2, 0.15))
    coarse = _edge_lengths(g)
    for level in (0, 1, 2):
        fine, sub = lift.upsample(g, levels=level)
        assert sub.levels == level
        np.testing.assert_allclose(_edge_lengths(fine), coarse / 2**level, rtol=0, atol=1e-6)
    with pytest.raises(ValueError):
        lift.upsample(g, levels=-1)


def _unapplied_enhancer(texel):
    """A model with no parameters: the setup (compile=False) reads only its config."""
    config = enhancer.EnhancerConfig(UNetConfig(width=2), patch_size=32, texel_size=texel)
    return enhancer.Enhancer(model=None, params={}, config=config, meta={})


@pytest.mark.parametrize("texel", [0.002, 0.05])
def test_pipeline_auto_picks_the_level_from_the_models_texel(texel):
    g = primitives.grid_sheet(4, 4, size=(0.12, 0.12))  # 30 mm cells, ~34 mm mean edge
    enh = _unapplied_enhancer(texel)
    edge = lift.coarse_mean_edge(g)
    expected = lift.texel_subdivision_level(edge, texel)
    k = lift.TEXELS_PER_EDGE * texel
    if texel == 0.05:  # texels larger than the edges: the coarse mesh is already fine enough
        assert expected == 0
    else:  # the finest level whose edges are still >= k texels
        assert expected >= 1 and edge / 2**expected >= k > edge / 2 ** (expected + 1)
    pipe = pipeline.make_pipeline(g, enh, pipeline.PipelineConfig(subdivision="auto"),
                                  compile=False)
    assert pipe.subdivision.levels == expected
    assert pipe.fine_garment.num_vertices == subdivision.build(g, expected).garment(g).num_vertices
    # An explicit level is used as given, whatever the texel size.
    pipe3 = pipeline.make_pipeline(g, enh, pipeline.PipelineConfig(subdivision=3), compile=False)
    assert pipe3.subdivision.levels == 3


@pytest.mark.parametrize("bad", [-1, "fine", 1.5, True])
def test_pipeline_config_rejects_bad_subdivision(bad):
    with pytest.raises(ValueError):
        pipeline.PipelineConfig(subdivision=bad)
