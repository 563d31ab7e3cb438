"""The pipeline's body push-out setting (`pipeline_setup.LIFT_RESOLVE`: the two-level
preconditioner at a 3e-3 residual) on a hard case: a subdivided sheet cut through by a capsule
(a 32 mm push, far deeper than the lifted garments' few mm). It must leave nothing inside and
spend fewer CG iterations than a converged solve; its error, in the smooth far field, scales
with the push: 1.9 mm here (6 %), <= 0.49 mm on the benchmark's scenes
(benchmarks/bench_resolve.py, resolve_s18.json)."""

import jax.numpy as jnp
import numpy as np

from wrinkle_jax import bodies, lift, pipeline, primitives, subdivision
from wrinkle_jax.pipeline_setup import LIFT_RESOLVE


def test_pipeline_resolve_default_is_the_cheap_two_level_solve_and_stays_close_to_converged():
    assert pipeline.PipelineConfig().resolve == LIFT_RESOLVE
    assert LIFT_RESOLVE.coarse_mass is not None
    coarse = primitives.grid_sheet(13, 13, size=(0.5, 0.5))
    sub = subdivision.build(coarse, 2)
    v = jnp.asarray(sub.apply(jnp.asarray(coarse.vertices)))
    top = lift.lift_topology(np.asarray(sub.faces), v.shape[0])
    c = np.array([0.25, 0.25, -0.05])
    body = bodies.primitive_body(capsules=(c + [-0.12, 0, 0.01], c + [0.12, 0.02, 0], 0.07))
    assert int(jnp.sum(bodies.query(body, v).distance < 0)) > 50
    co = lift.resolve_coarse(sub, top, 5e3, LIFT_RESOLVE)
    fast, info = lift.resolve_penetration_with_info(v, top, body, 5e3, LIFT_RESOLVE, co)
    ref, ref_info = lift.resolve_penetration_with_info(
        v, top, body, 5e3, lift.ResolveConfig(cg_max_iters=3000, cg_tol=1e-8))
    assert int(info.inside) == 0
    assert float(jnp.min(bodies.query(body, fast).distance)) >= 0.0
    diff = np.linalg.norm(np.asarray(fast - ref), axis=1)
    push = np.linalg.norm(np.asarray(ref - v), axis=1).max()
    assert push > 0.02
    assert diff.max() < 0.1 * push  # measured 1.9 of 32 mm
    assert diff.max() > 1e-5        # it is not the converged solve itself
    assert int(info.cg_iterations) < 0.2 * int(ref_info.cg_iterations)  # measured 80 of 1,443


def test_pipeline_builds_the_coarse_correction_for_its_lifted_mesh():
    coarse = primitives.grid_sheet(6, 6, size=(0.12, 0.12))
    pipe = pipeline.make_pipeline(coarse, config=pipeline.PipelineConfig(subdivision=1),
                                  compile=False)
    co = pipe.resolve_coarse
    assert co is not None and co.key == (5e3, LIFT_RESOLVE.compliance, LIFT_RESOLVE.coarse_mass)
    assert co.prolong.shape == (pipe.fine_garment.num_vertices, coarse.num_vertices)
    off = pipeline.make_pipeline(coarse, config=pipeline.PipelineConfig(lift=False),
                                 compile=False)
    assert off.resolve_coarse is None
