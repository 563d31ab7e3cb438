"""Tests for sim.xpbd and sim.aero: analytic free fall, settling, strain, colouring, the
bending stencil and aerodynamic drag (contacts: test_sim_colliders.py)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax.sim import colliders as C
from wrinkle_jax.sim import materials as M
from wrinkle_jax.sim import patterns as P
from wrinkle_jax.sim import xpbd as X


def _sheet(size=0.3, pd=0.03, z=1.0, horizontal=False, seed=0):
    pat = P.sheet_pattern(size, size, top=z)
    if horizontal:
        pat = P.Pattern("table", pat.panels, (), lambda i, p: np.stack(
            [p[:, 0] - size / 2, p[:, 1] - size / 2, np.full(len(p), z)], 1), {})
    return pat, P.mesh_pattern(pat, pd, seed=seed)


def _drives(frames, pins=None, colliders=None):
    n = frames + 1
    return X.Drive(time=jnp.arange(n, dtype=jnp.float32) / 30.0,
                   pins=None if pins is None else jnp.asarray(pins),
                   colliders=colliders or C.Colliders(),
                   extra_damping=jnp.zeros(n, jnp.float32))


def _run(model, params, x0, drives, config=None):
    config = config or X.SimConfig()
    init_fn, _ = X.cloth_simulator(config)
    return X.simulate_frames(config, model, params, init_fn(model, x0), drives)


def test_free_fall_matches_analytic():
    _, m = _sheet()
    g = m.garment
    model = X.build_cloth(g, None, use_aero=False)
    params = dataclasses.replace(X.fabric_params(M.fabric("denim_light")), damping=jnp.float32(0))
    frames = 30
    _, xs = _run(model, params, g.vertices, _drives(frames))
    t = frames / 30.0
    drop = float(np.mean(np.asarray(g.vertices)[:, 2] - xs[-1][:, 2]))
    assert drop == pytest.approx(0.5 * 9.81 * t * t, rel=0.01)
    # A rigid translation: no deformation.
    assert float(jnp.abs(X.edge_strain(model, jnp.asarray(xs[-1]))).max()) < 1e-3


def test_pinned_sheet_settles_and_stays_finite():
    # The edge-strain test's sheet and solver settings: the pinned solver compiles once for
    # both (its mesh, pins and config are the program; the fabric and start are arguments).
    pat, m = _sheet(0.4, 0.02, z=1.0)
    g = m.garment
    top = m.landmark_vertices(pat, "top")
    x0 = np.asarray(g.vertices).copy()
    # Start swung up to horizontal (rotated about the top edge, isometric).
    dz = x0[:, 2] - 1.0
    x0[:, 1], x0[:, 2] = dz, 1.0
    model = X.build_cloth(g, top)
    params = X.fabric_params(M.fabric("wool_melton"))
    frames = 100  # x 20 substeps = 2,000 substeps
    pins = np.broadcast_to(x0[top], (frames + 1,) + x0[top].shape)
    _, xs = _run(model, params, x0, _drives(frames, pins), X.SimConfig(stretch_sweeps=2))
    assert np.isfinite(xs).all()
    v = np.diff(xs, axis=0) * 30.0
    ke = np.array([float(X.kinetic_energy(params, model, jnp.asarray(vi))) for vi in v])
    assert ke.max() > 1e-3
    assert ke[-10:].max() < 0.02 * ke.max()
    assert xs[-1][:, 2].min() < 1.0 - 0.25  # it hangs down


def test_edge_strain_small_for_stiff_fabric():
    pat, m = _sheet(0.4, 0.02, z=1.0)
    g = m.garment
    top = m.landmark_vertices(pat, "top")
    model = X.build_cloth(g, top)
    params = X.fabric_params(M.fabric("denim_light"))
    frames = 30
    x0 = np.asarray(g.vertices)
    pins = np.broadcast_to(x0[top], (frames + 1,) + x0[top].shape)
    _, xs = _run(model, params, x0, _drives(frames, pins), X.SimConfig(stretch_sweeps=2))
    strain = np.abs(np.asarray(X.edge_strain(model, jnp.asarray(xs[-1]))))
    assert np.percentile(strain, 99) < 0.03
    assert strain.mean() < 0.01


def test_coloring_is_valid():
    _, m = _sheet(0.3, 0.03)
    model = X.build_cloth(m.garment, None)
    for groups, get in ((model.stretch, lambda c: np.stack([c.i, c.j], 1)),
                        (model.bend, lambda c: np.asarray(c.idx)),
                        (model.limits, lambda c: np.stack([c.i, c.j], 1))):
        total = 0
        for c in groups:
            idx = np.asarray(get(c)).reshape(-1)
            assert len(np.unique(idx)) == len(idx)  # no vertex twice in a colour
            total += len(get(c))
        assert total > 0
    s = X.model_summary(model)
    assert s["stretch_colors"] <= 12 and s["bend_colors"] <= 25


def test_bending_stencil_vanishes_on_flat_and_scales():
    # sum_k K_k x_k = 0 for any affine (flat) configuration; a cylinder of radius R stores
    # B / (2 R^2) per unit area (the cylindrical bend that defines B).
    _, m = _sheet(0.3, 0.02)
    g = m.garment
    hidx, w, _ = X._hinges(g)
    uv = np.asarray(g.uvs, np.float64)
    v2uv = np.zeros(g.num_vertices, np.int64)
    v2uv[np.asarray(g.faces).reshape(-1)] = np.asarray(g.uv_faces).reshape(-1)
    flat = np.concatenate([uv[v2uv], np.zeros((g.num_vertices, 1))], 1)
    flat = flat @ np.array([[0.8, 0.6, 0.0], [-0.6, 0.8, 0.0], [0.0, 0.0, 1.0]]) + 0.3
    res = np.einsum("nk,nkd->nd", w, flat[hidx])
    assert np.abs(res).max() < 1e-6
    radius = 0.2
    p = uv[v2uv]
    cyl = np.stack([radius * np.sin(p[:, 0] / radius), p[:, 1],
                    radius * (1 - np.cos(p[:, 0] / radius))], 1)
    energy = 0.5 * np.sum(np.einsum("nk,nkd->nd", w, cyl[hidx]) ** 2)  # B = 1
    area = 0.3 * 0.3
    interior = 0.5 * area / radius ** 2  # B/2 * (1/R)^2 * A
    assert energy == pytest.approx(interior, rel=0.05)


def test_aero_drag_opposes_motion():
    from wrinkle_jax.sim import aero

    _, m = _sheet(0.2, 0.05, horizontal=True)
    g = m.garment
    x = jnp.asarray(g.vertices)
    v = jnp.zeros_like(x).at[:, 2].set(-1.0)  # falling flat
    f = aero.aero_forces(x, v, jnp.asarray(g.faces), None, 1.2, 0.3)
    total = np.asarray(f).sum(0)
    assert total[2] == pytest.approx(0.5 * 1.2 * 1.2 * 0.04, rel=1e-3)  # 1/2 rho C_d A u^2
    wind = aero.make_wind(jax.random.PRNGKey(0))
    w1 = aero.wind_velocity(wind, x, 0.5)
    w2 = aero.wind_velocity(aero.make_wind(jax.random.PRNGKey(0)), x, 0.5)
    np.testing.assert_array_equal(np.asarray(w1), np.asarray(w2))
    assert float(jnp.mean(w1[:, 1])) > 0.3
