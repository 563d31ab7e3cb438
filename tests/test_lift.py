"""Tests for wrinkle_jax.lift: energy, solvers, implicit gradients, interpenetration."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from wrinkle_jax import bodies, mesh, normalmap, primitives, solvers
from wrinkle_jax import lift as L

# One fast-solver configuration shared by most tests (jit caches compile it once per shape).
GN = L.SolverConfig(method="gauss_newton", max_iters=50, tol=1e-9, cg_tol=1e-6, cg_max_iters=200)


@jax.jit
def _energy(p, v0, top, nrm):
    return L.energy(p, L.make_problem(v0, top, nrm))


def _height_field_case(n=40, size=0.4, amp=0.01, wavelength=0.2):
    """Flat grid + normals of h = amp sin(kx) sin(ky) at the grid's xy (analytic)."""
    g = primitives.grid_sheet(n, n, size=(size, size))
    k = 2 * np.pi / wavelength
    x, y = g.vertices[:, 0].astype(np.float64), g.vertices[:, 1].astype(np.float64)
    h = amp * np.sin(k * x) * np.sin(k * y)
    hx = amp * k * np.cos(k * x) * np.sin(k * y)
    hy = amp * k * np.sin(k * x) * np.cos(k * y)
    nrm = np.stack([-hx, -hy, np.ones_like(x)], 1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return g, h, nrm.astype(np.float32)


@pytest.fixture(scope="module")
def case():
    g, h, nrm = _height_field_case()
    return g, h, nrm, L.lift_topology(g.faces, g.num_vertices)


def _wavy_problem(n=10, seed=0, noise=0.02, dtype=jnp.float32):
    g = primitives.grid_sheet(n, n, size=(0.01 * n, 0.01 * n), jitter=0.2, seed=seed)
    v0 = jnp.asarray(g.vertices, dtype)
    v0 = v0.at[:, 2].set(0.01 * jnp.sin(40 * v0[:, 0]))
    rng = np.random.default_rng(seed)
    bumped = v0.at[:, 2].add(0.005 * jnp.sin(60 * v0[:, 1]))
    nrm = mesh.vertex_normals(bumped, jnp.asarray(g.faces))
    nrm = nrm + noise * jnp.asarray(rng.normal(size=v0.shape), dtype)
    return g, v0, nrm, L.lift_topology(g.faces, g.num_vertices)


# ---------------------------------------------------------------- structure


def test_topology_laplacian_matches_mesh():
    g = primitives.grid_sheet(7, 5, size=(0.07, 0.05), jitter=0.3)
    top = L.lift_topology(g.faces, g.num_vertices)
    dense = mesh.uniform_laplacian(g.faces, g.num_vertices).todense()
    x = np.random.default_rng(0).normal(size=(g.num_vertices, 3)).astype(np.float32)
    np.testing.assert_allclose(L._lap_apply(top, jnp.asarray(x)), dense @ x, atol=1e-5)
    np.testing.assert_allclose(L._lapt_apply(top, jnp.asarray(x)), dense.T @ x, atol=1e-5)
    np.testing.assert_allclose(top.ltl_diag, np.diag(dense.T @ dense), rtol=1e-6)
    # The same products over the first M slots plus the overflow rows' other slots.
    degree = np.asarray(top.valid).sum(1).astype(int)
    for m in (3, 5):
        rows = np.nonzero(degree > m)[0]
        assert 0 < rows.size < degree.size
        split = dataclasses.replace(top, main_slots=m, overflow_rows=jnp.asarray(rows, jnp.int32))
        np.testing.assert_allclose(L._lap_apply(split, jnp.asarray(x)), dense @ x, atol=1e-5)
        np.testing.assert_allclose(L._lapt_apply(split, jnp.asarray(x)), dense.T @ x, atol=1e-5)


def test_energy_gradient_and_gauss_newton_product_match_autodiff():
    g, v0, nrm, top = _wavy_problem(seed=1, noise=0.1)
    prob = jax.jit(L.make_problem)(v0, top, nrm)
    # NumPy draws for test input (an op-by-op jax.random draw compiles a threefry program for
    # every new shape, ~0.4 s of CPU each).
    rng = np.random.default_rng(0)
    p = v0 + 0.002 * jnp.asarray(rng.normal(size=v0.shape), jnp.float32)
    auto = jax.jit(jax.grad(L.energy))(p, prob)
    np.testing.assert_allclose(jax.jit(L.energy_grad)(p, prob), auto, rtol=1e-4,
                               atol=1e-5 * float(jnp.abs(auto).max()))

    def residuals(q):
        r = L._rows(q, prob)
        return jnp.concatenate([jnp.sqrt(prob.c_normal) * r.r_f.reshape(-1),
                                jnp.sqrt(prob.c_lap) * L._lap(q, prob).reshape(-1),
                                jnp.sqrt(prob.c_data) * (q - prob.vertices0).reshape(-1)])

    @jax.jit
    def gauss_newton_product(q, w):  # 2 J^T J w from autodiff of the residual vector
        _, jvp = jax.linearize(residuals, q)
        return 2.0 * jax.linear_transpose(jvp, q)(jvp(w))[0]

    v = jnp.asarray(rng.normal(size=v0.shape), jnp.float32)
    ref = gauss_newton_product(p, v)
    product = jax.jit(lambda q, w, pr: L._gn_matvec(L._gn_system(L._rows(q, pr), pr), pr, w))
    np.testing.assert_allclose(product(p, v, prob), ref, rtol=1e-4,
                               atol=1e-5 * float(jnp.abs(ref).max()))
    # The one-ring split: the first M slots of every row, the rest only for the overflow rows
    # (scatter-added). This grid has too many high-valence rows to split (every slot runs for
    # every row); force splits at 4 and 6 slots.
    degree = np.asarray(top.valid).sum(1).astype(int)
    assert top.main_slots == degree.max() and top.overflow_rows.shape == (0,)
    for m in (4, 6):
        rows = jnp.asarray(np.nonzero(degree > m)[0], jnp.int32)
        split = dataclasses.replace(prob, topology=dataclasses.replace(
            top, main_slots=m, overflow_rows=rows))
        assert L._gn_system(L._rows(p, split), split).overflow[0].shape[0] > 0
        np.testing.assert_allclose(product(p, v, split), ref, rtol=1e-4,
                                   atol=1e-5 * float(jnp.abs(ref).max()))


def test_slot_split_keeps_the_few_high_valence_rows_apart():
    from wrinkle_jax.lift_energy import _slot_split

    degree = np.array([6] * 1000 + [7] * 10 + [8] * 5 + [3] * 20)
    m, rows = _slot_split(degree)
    assert m == 6 and rows.tolist() == list(range(1000, 1015))
    # Slot work V M + 4 E (K - M): 10 of 110 rows above 6 split (660 + 40 < 770); 40 of 140
    # do not (840 + 160 > 980), and neither do half the rows two slots above the rest.
    m, rows = _slot_split(np.array([6] * 100 + [7] * 10))
    assert m == 6 and rows.tolist() == list(range(100, 110))
    m, rows = _slot_split(np.array([6] * 100 + [7] * 40))
    assert m == 7 and rows.size == 0
    assert _slot_split(np.array([6] * 50 + [8] * 50))[0] == 8
    assert _slot_split(np.array([6] * 50))[0] == 6


def test_block_inverse_in_closed_form_matches_lu():
    """The Gauss-Newton preconditioner's 3 x 3 inverses (adjugate / determinant) against
    NumPy's LU inverse in float64, on SPD blocks with condition numbers up to 1e3 (the lift's
    diagonal blocks: up to ~60): accurate to a few float32 ulps times the condition number,
    symmetric bit for bit and positive definite, and applied as each block's solve."""
    rng = np.random.default_rng(3)
    q = np.linalg.qr(rng.normal(size=(300, 3, 3)))[0]
    eig = np.exp(rng.uniform(0, np.log(1e3), (300, 3))) * 1e4  # the lift's blocks are ~1e4
    a = np.einsum("nij,nj,nkj->nik", q, eig, q)
    blocks = jnp.asarray(0.5 * (a + np.swapaxes(a, 1, 2)), jnp.float32)
    inv = np.asarray(jax.jit(solvers.inverse3)(blocks), np.float64)
    want = np.linalg.inv(np.asarray(blocks, np.float64))
    cond = np.linalg.cond(np.asarray(blocks, np.float64))
    err = np.abs(inv - want).max((1, 2)) / np.abs(want).max((1, 2))
    assert (err <= 1e-5 * cond).all(), float((err / cond).max())  # measured: <= 4e-6 cond
    np.testing.assert_array_equal(inv, np.swapaxes(inv, 1, 2))
    assert (np.linalg.eigvalsh(inv) > 0).all()
    r = rng.normal(size=(300, 3)).astype(np.float32)
    got = np.asarray(jax.jit(lambda b, r: solvers.block_inverse(b)(r))(blocks, jnp.asarray(r)))
    applied = np.einsum("nab,nb->na", inv, r)
    np.testing.assert_allclose(got, applied, rtol=1e-5, atol=1e-6 * float(np.abs(applied).max()))


def test_configs_are_hashable_and_validated():
    assert hash(L.LiftWeights()) == hash(L.LiftWeights())
    assert hash(L.SolverConfig()) == hash(L.SolverConfig())
    with pytest.raises(ValueError, match="method"):
        L.SolverConfig(method="newton")
    with pytest.raises(ValueError, match="laplacian_of"):
        L.LiftWeights(laplacian_of="edges")


# ---------------------------------------------------------------- lifting quality


def test_flat_grid_lifts_to_the_height_field(case):
    g, h, nrm, top = case
    p, info = L.lift_with_info(g.vertices, top, nrm, solver=GN)
    # Stationary (GN's tol=1e-9 is below float32 resolution, so it may end "stuck" instead).
    assert float(info.grad_rms) < 1e-4
    z = np.asarray(p[:, 2], np.float64)
    zc, hc = z - z.mean(), h - h.mean()
    assert np.corrcoef(zc, hc)[0, 1] > 0.99
    assert np.sqrt(np.mean((zc - hc) ** 2)) < 0.1 * 0.01  # < 10 % of the amplitude
    # Border vertices have one-sided normals; the bound holds with and without them.
    interior = ~mesh.boundary_vertices(g.faces, g.num_vertices)
    assert float(L.normal_angle_error(p, g.faces, nrm)) < 5.0
    assert float(L.normal_angle_error(p, g.faces, nrm, interior)) < 5.0


@pytest.mark.parametrize("which", ["jittered_sheet", "skirt"])
def test_coarse_normals_leave_the_mesh_in_place(which, skirt):
    g = primitives.grid_sheet(12, 10, size=(0.12, 0.1), jitter=0.3) if which != "skirt" else skirt
    top = L.lift_topology(g.faces, g.num_vertices)
    nrm = mesh.vertex_normals(jnp.asarray(g.vertices), jnp.asarray(g.faces))
    p = L.lift(g.vertices, top, nrm)
    assert float(jnp.abs(p - g.vertices).max()) < 1e-4


def test_degenerate_geometry_stays_finite():
    g = primitives.grid_sheet(8, 8, size=(0.08, 0.08))
    v = np.asarray(g.vertices).copy()
    v[10] = v[11]  # a zero-length edge (and two degenerate triangles)
    v[20] = 0.5 * (v[19] + v[21])  # collinear corners: zero-area triangles
    top = L.lift_topology(g.faces, g.num_vertices)
    nrm = np.tile(np.array([[0.1, 0.0, 1.0]], np.float32), (g.num_vertices, 1))
    nrm[3] = 0.0  # a vertex without a target normal
    v, nrm = jnp.asarray(v), jnp.asarray(nrm)
    w = jnp.asarray(np.random.default_rng(0).normal(size=v.shape), jnp.float32)
    loss = jax.jit(jax.value_and_grad(lambda a, b: jnp.sum(w * L.lift(a, top, b, solver=GN)),
                                      (0, 1)))
    value, (gv, gn) = loss(v, nrm)
    assert np.isfinite(float(value))
    assert np.isfinite(np.asarray(gv)).all() and np.isfinite(np.asarray(gn)).all()
    e, ge = jax.jit(jax.value_and_grad(_energy))(v, v, top, nrm)
    assert np.isfinite(float(e)) and np.isfinite(np.asarray(ge)).all()


def test_solvers_reach_the_same_minimum():
    g, v0, nrm, top = _wavy_problem(n=8, seed=2)
    energies = {}
    # The paper's Adam needs a small learning rate to settle (a fixed step hovers otherwise).
    for cfg in (GN, L.SolverConfig(method="lbfgs", max_iters=2000, tol=1e-10),
                L.SolverConfig(method="adam", max_iters=4000, tol=1e-9, learning_rate=0.005,
                               patience=50)):
        _, info = L.lift_with_info(v0, top, nrm, solver=cfg)
        energies[cfg.method] = float(info.energy)
    ref = energies["gauss_newton"]
    for method, e in energies.items():
        assert abs(e - ref) <= 1e-3 * ref, (method, energies)


def test_plain_gradient_descent_descends():
    g, v0, nrm, top = _wavy_problem(n=8, seed=2)
    e0 = float(_energy(v0, v0, top, nrm))
    _, info = L.lift_with_info(v0, top, nrm, solver=L.SolverConfig(method="gd", max_iters=500,
                                                                   learning_rate=0.02))
    assert float(info.energy) < 0.5 * e0


def test_reference_adam_lowers_the_energy(case):
    g, _, nrm, top = case
    p0 = jnp.asarray(g.vertices)
    e0 = float(_energy(p0, p0, top, nrm))
    _, info = L.lift_with_info(p0, top, nrm, solver=L.SolverConfig(method="adam", max_iters=60,
                                                                   tol=1e-3))
    assert float(info.energy) < 0.5 * e0


def test_lift_vmaps_over_frames():
    g, v0, nrm, top = _wavy_problem(n=8)
    frames = jnp.stack([v0, v0.at[:, 2].add(0.003)])
    normals = jnp.stack([nrm, nrm])
    batched = jax.jit(jax.vmap(lambda a, b: L.lift(a, top, b, solver=GN)))(frames, normals)
    # The per-frame reference is `lift` unbatched (`lift` returns lift_with_info's vertices);
    # lift_with_info at these shapes is already compiled by test_solvers_reach_the_same_minimum.
    one, _ = L.lift_with_info(frames[1], top, nrm, solver=GN)
    np.testing.assert_allclose(batched[1], one, atol=1e-5)


# ---------------------------------------------------------------- differentiability


def test_implicit_gradient_matches_finite_differences(enable_x64):
    g, v0, nrm, top = _wavy_problem(n=8, dtype=jnp.float64)
    cfg = L.SolverConfig(max_iters=100, tol=1e-14, cg_max_iters=500, cg_tol=1e-10,
                         adjoint_tol=1e-12, adjoint_max_iters=2000)
    rng = np.random.default_rng(0)
    w = jnp.asarray(rng.normal(size=v0.shape))

    @jax.jit
    def loss(a, b):
        return jnp.sum(w * L.lift(a, top, b, solver=cfg))

    grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(v0, nrm)
    assert grads[0].dtype == jnp.float64
    for arg, grad in enumerate(grads):
        d = jnp.asarray(rng.normal(size=v0.shape))
        eps = 1e-6
        plus = [v0, nrm]
        minus = [v0, nrm]
        plus[arg] = plus[arg] + eps * d
        minus[arg] = minus[arg] - eps * d
        fd = float(loss(*plus) - loss(*minus)) / (2 * eps)
        an = float(jnp.sum(grad * d))
        assert abs(fd - an) <= 1e-3 * abs(fd), (arg, fd, an)


def test_gradient_reaches_the_normal_map_and_coarse_vertices():
    coarse = primitives.grid_sheet(4, 4, size=(0.08, 0.08),
                                   height_fn=lambda x, y: 0.02 * np.sin(20 * x))
    fine, sub = L.upsample(coarse, 0.01)
    assert sub.levels == 2 and fine.num_vertices == 17 * 17
    plan = normalmap.make_plan(fine, texel_size=0.004)
    nmap = normalmap.bake(plan, jnp.asarray(fine.vertices))

    @jax.jit
    def agreement(m, v):  # sampled map vs the mesh's own vertex normals
        n_at_v = L.sample_target_normals(m, fine, plan.layout)
        return jnp.mean(jnp.sum(n_at_v * mesh.vertex_normals(v, fine.faces), -1))

    assert float(agreement(nmap, jnp.asarray(fine.vertices))) > 0.99
    top = L.lift_topology(fine.faces, fine.num_vertices)
    w = jnp.asarray(np.random.default_rng(0).normal(size=(fine.num_vertices, 3)), jnp.float32)

    @jax.jit
    def loss(cv, m):
        return jnp.sum(w * L.lift_from_normal_map(cv, sub, fine, top, m, plan.layout))

    gc, gm = jax.grad(loss, argnums=(0, 1))(jnp.asarray(coarse.vertices), nmap)
    assert gc.shape == coarse.vertices.shape and gm.shape == nmap.shape
    assert np.isfinite(np.asarray(gc)).all() and np.isfinite(np.asarray(gm)).all()
    assert float(jnp.abs(gm).max()) > 0 and float(jnp.abs(gc).max()) > 0


# ---------------------------------------------------------------- interpenetration


@pytest.fixture(scope="module")
def sheet60():
    g = primitives.grid_sheet(50, 50, size=(0.5, 0.5))
    return g, L.lift_topology(g.faces, g.num_vertices)


def _body(kind):
    center = np.array([0.25, 0.25, -0.05])
    if kind == "sphere":
        return bodies.primitive_body(spheres=(center, 0.1))
    if kind == "capsule":
        return bodies.primitive_body(capsules=(center + [-0.12, 0, 0.01], center + [0.12, 0.02, 0],
                                               0.07))
    if kind == "icosphere":
        ico = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
        return bodies.mesh_body(ico.vertices + center, ico.faces)
    box = trimesh.creation.box(extents=(0.16, 0.12, 0.16))
    return bodies.mesh_body(box.vertices + center, box.faces)


@pytest.mark.parametrize("kind", ["sphere", "capsule", "icosphere", "box"])
def test_resolve_pushes_the_sheet_out_of_the_body(kind, sheet60):
    g, top = sheet60
    body = _body(kind)
    v = jnp.asarray(g.vertices)
    d0 = np.asarray(bodies.query(body, v).distance)
    assert (d0 < 0).sum() > 50
    p, info = L.resolve_penetration_with_info(v, top, body)
    d1 = np.asarray(bodies.query(body, p).distance)
    assert (d1 < 0).sum() == 0 and int(info.inside) == 0
    move = np.linalg.norm(np.asarray(p - v), axis=1)
    assert move[d0 > 0.2].max() < 2e-3  # far from the body: barely moves
    assert move[d0 > 0.12].max() < 1e-2


def test_resolve_without_body_is_the_identity(sheet60):
    g, top = sheet60
    v = jnp.asarray(g.vertices)
    assert L.resolve_penetration(v, top, None) is v
    # Nothing is traced: the jaxpr of a pipeline with body=None has no resolve in it.
    jaxpr = jax.make_jaxpr(lambda x: L.resolve_penetration(x, top, None))(v)
    assert len(jaxpr.jaxpr.eqns) == 0
