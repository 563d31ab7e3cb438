"""The body push-out's coarse-grid preconditioner (`lift.resolve_coarse`): its operators are the
subdivision and the Galerkin coarse system it claims, it changes the iterations and not the
solution, and it refuses a system it was not built for."""

import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import bodies, lift, mesh, primitives, subdivision

PHI = 5e3


@pytest.fixture(scope="module")
def case():
    """A 9x9 coarse sheet subdivided twice (33x33 lifted vertices), cut 30 mm deep by a capsule."""
    coarse = primitives.grid_sheet(9, 9, size=(0.4, 0.4))
    sub = subdivision.build(coarse, 2)
    fine = jnp.asarray(sub.apply(jnp.asarray(coarse.vertices)))
    top = lift.lift_topology(np.asarray(sub.faces), fine.shape[0])
    c = np.array([0.2, 0.2, -0.04])
    body = bodies.primitive_body(capsules=(c + [-0.1, 0, 0.01], c + [0.1, 0.02, 0], 0.07))
    return coarse, sub, fine, top, body


def test_operators_are_the_subdivision_and_the_galerkin_system(case):
    coarse, sub, fine, top, _ = case
    cfg = lift.ResolveConfig(coarse_mass=0.05)
    co = lift.resolve_coarse(sub, top, PHI, cfg)
    x = np.random.default_rng(0).normal(size=(coarse.num_vertices, 3)).astype(np.float32)
    np.testing.assert_allclose(co.prolong @ jnp.asarray(x), sub.apply(jnp.asarray(x)),
                               atol=1e-6)
    y = np.random.default_rng(1).normal(size=(fine.shape[0], 3)).astype(np.float32)
    p = co.prolong.todense()
    np.testing.assert_allclose(co.restrict @ jnp.asarray(y), p.T @ y, atol=1e-4)
    lap = mesh.uniform_laplacian(np.asarray(top.faces), fine.shape[0]).todense()
    a, b = cfg.compliance * np.sqrt(PHI), cfg.compliance / np.sqrt(PHI)
    a_c = p.T @ (a * lap.T @ lap + (b + 0.05 * (1 - b)) * np.eye(len(lap))) @ p
    np.testing.assert_allclose(np.asarray(co.inverse, np.float64) @ a_c, np.eye(len(a_c)),
                               atol=2e-3)
    assert co.key == (PHI, cfg.compliance, 0.05)


def test_same_solution_fewer_iterations(case):
    _, sub, fine, top, body = case
    assert int(jnp.sum(bodies.query(body, fine).distance < 0)) > 20
    tight = dict(cg_max_iters=3000, cg_tol=1e-7)
    jac, jac_info = lift.resolve_penetration_with_info(fine, top, body, PHI,
                                                       lift.ResolveConfig(**tight))
    cfg = lift.ResolveConfig(coarse_mass=0.05, **tight)
    two, two_info = lift.resolve_penetration_with_info(
        fine, top, body, PHI, cfg, lift.resolve_coarse(sub, top, PHI, cfg))
    assert int(two_info.inside) == 0
    np.testing.assert_allclose(two, jac, atol=2e-5)  # meters; the push is ~30 mm
    assert float(jnp.max(jnp.linalg.norm(two - fine, axis=1))) > 0.02
    assert int(two_info.cg_iterations) < 0.6 * int(jac_info.cg_iterations)


def test_without_levels_the_correction_is_the_whole_fixed_system(case):
    coarse, _, _, _, body = case
    sub0 = subdivision.build(coarse, 0)
    top0 = lift.lift_topology(np.asarray(coarse.faces), coarse.num_vertices)
    cfg = lift.ResolveConfig(coarse_mass=0.05, cg_tol=1e-6)
    co = lift.resolve_coarse(sub0, top0, PHI, cfg)
    assert co.inverse.shape == (coarse.num_vertices,) * 2
    v = jnp.asarray(coarse.vertices)
    out, info = lift.resolve_penetration_with_info(v, top0, body, PHI, cfg, co)
    ref = lift.resolve_penetration(v, top0, body, PHI, lift.ResolveConfig(cg_tol=1e-6))
    np.testing.assert_allclose(out, ref, atol=5e-5)


def test_built_only_when_asked_and_small_enough_and_checked_against_its_system(case):
    _, sub, fine, top, body = case
    assert lift.resolve_coarse(sub, top, PHI, lift.ResolveConfig()) is None
    small = lift.ResolveConfig(coarse_mass=0.05, coarse_max_vertices=80)  # the sheet has 81
    assert lift.resolve_coarse(sub, top, PHI, small) is None
    co = lift.resolve_coarse(sub, top, PHI, lift.ResolveConfig(coarse_mass=0.05))
    for other_phi, other in ((2e3, lift.ResolveConfig(coarse_mass=0.05)),
                             (PHI, lift.ResolveConfig(coarse_mass=0.2)),
                             (PHI, lift.ResolveConfig(coarse_mass=0.05, compliance=0.1))):
        with pytest.raises(ValueError, match="built for"):
            lift.resolve_penetration(fine, top, body, other_phi, other, co)
