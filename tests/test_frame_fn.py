"""`pipeline.frame_fn`: the whole pipeline of one frame, differentiated end to end.

The gradient test runs in float64 (`jax_enable_x64`, switched on for the test only) on a tiny
garment with a tiny *smooth* network: the U-Net computes in float32 whatever its inputs and its
ReLUs and small-patch instance norms make central differences of it meaningless, while the
pipeline's own gradient plumbing (bake, padding, tiling, batching, merge, lift) is what this
tests. The U-Net's gradients are tested in tests/test_unet.py.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import enhancer, lift, pipeline, primitives
from wrinkle_jax.nn import unet


@pytest.fixture
def x64():
    """float64 for the duration of one test, then the previous setting again."""
    old = bool(jax.config.jax_enable_x64)
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", old)


class SmoothNet(nn.Module):
    """A tiny smooth material-conditioned patch network in the input's dtype:
    out = 0.8 x + 0.2 sigmoid(conv(tanh(conv(x))) + embedding[material]), in (0, 1) for x in
    [0, 1] (the pipeline's clip to [0, 1] never binds, so there is no kink)."""

    num_materials: int = 5

    @nn.compact
    def __call__(self, x, material, origins=None):
        h = jnp.tanh(nn.Conv(3, (3, 3), padding=1, param_dtype=x.dtype)(x))
        emb = self.param("embedding", nn.initializers.normal(0.5), (self.num_materials, 3),
                         x.dtype)
        y = nn.Conv(3, (3, 3), padding=1, param_dtype=x.dtype)(h) + emb[material][:, None, None]
        return 0.8 * x + 0.2 * jax.nn.sigmoid(y)


def _rel(a, b):
    return float(abs(a - b) / max(abs(a), abs(b)))


def test_frame_fn_gradients_match_central_differences_in_float64(x64):
    # A 4x4-cell sheet with a bump (75 mm x 50 mm, 12-19 mm edges): a 33x38-texel map, 16-texel
    # patches (stride 8, 12 of them, batches of 5: the last batch is zero-padded) and one
    # level of subdivision to the lift's 10 mm edges (81 vertices).
    g = primitives.grid_sheet(4, 4, size=(0.075, 0.05))
    v0 = np.asarray(g.vertices, np.float64)
    v0[:, 2] += 0.006 * np.sin(60.0 * v0[:, 0] + 30.0 * v0[:, 1])
    net = SmoothNet()
    # One program (op by op, each float64 threefry draw compiles on its own); same values.
    params = jax.jit(net.init)(jax.random.key(1), jnp.zeros((1, 16, 16, 3)),
                               jnp.zeros((1,), int))
    model = enhancer.Enhancer(net, params["params"], enhancer.EnhancerConfig(
        unet.UNetConfig(width=1), patch_size=16, texel_size=0.004), {})
    # A converged solve: the lift's implicit gradient is exact at a stationary point.
    solver = lift.SolverConfig(max_iters=60, tol=1e-15, cg_tol=1e-10, cg_max_iters=400,
                               adjoint_tol=1e-12, adjoint_max_iters=2000)
    pipe = pipeline.make_pipeline(g, model, pipeline.PipelineConfig(batch_size=5,
                                                                    solver=solver),
                                  compile=False)
    assert pipe.num_patches % 5 and pipe.fine_garment.num_vertices > g.num_vertices
    f = pipeline.frame_fn(pipe)
    rng = np.random.default_rng(0)
    w_map = jnp.asarray(rng.normal(size=(*pipe.shape, 3)))
    w_mesh = jnp.asarray(rng.normal(size=(pipe.fine_garment.num_vertices, 3)))

    def functionals(p, v):
        """Two scalars: a random projection of N* and one of the lifted vertices (in cm)."""
        r = f(p, v, 3)
        return jnp.stack([jnp.sum(w_map * r.normal_map), 100.0 * jnp.sum(w_mesh * r.detailed)])

    p0 = model.params
    v = jnp.asarray(v0)
    out = functionals(p0, v)
    assert out.dtype == jnp.float64
    jac_p, jac_v = jax.jacrev(functionals, argnums=(0, 1))(p0, v)
    dv = jnp.asarray(rng.normal(size=v0.shape)) * 1e-3  # meters
    dp = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape)) * 0.1, p0)
    ad_v = np.asarray(jnp.einsum("kvc,vc->k", jac_v, dv))
    ad_p = np.asarray(sum(jnp.tensordot(a, b, b.ndim) for a, b in
                          zip(jax.tree.leaves(jac_p), jax.tree.leaves(dp), strict=True)))
    fun = functionals  # f itself is jitted: no second compile of the chain
    errors = {}
    for h in (1e-2, 3e-3):
        fd_v = (fun(p0, v + h * dv) - fun(p0, v - h * dv)) / (2 * h)
        p_plus, p_minus = (jax.tree.map(lambda a, b, s=s: a + s * b, p0, dp) for s in (h, -h))
        fd_p = (fun(p_plus, v) - fun(p_minus, v)) / (2 * h)
        errors[h] = [_rel(a, b) for a, b in zip(np.r_[ad_v, ad_p], np.r_[fd_v, fd_p],
                                                strict=True)]
    print("directional derivatives (map/v, mesh/v, map/params, mesh/params):",
          ad_v, ad_p, "relative errors by step:", errors)
    assert np.all(np.abs(np.r_[ad_v, ad_p]) > 1e-3)  # the directions do move the outputs
    best = np.min(list(errors.values()), axis=0)
    assert np.all(best < 1e-4), errors
