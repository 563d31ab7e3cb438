"""Tests for sim.xpbd and sim.aero: analytic free fall, settling, strain, colouring, the
bending stencil and aerodynamic drag (contacts: test_sim_colliders.py)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sim_fixtures import drives as _drives  # tests/ is on sys.path
from sim_fixtures import run as _run
from sim_fixtures import sheet as _sheet

from wrinkle_jax.sim import materials as M
from wrinkle_jax.sim import xpbd as X


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


def test_color_groups_fewest_runs_within_budget():
    import itertools

    rng = np.random.default_rng(3)
    cases = [[5, 5, 5], [9, 7, 3, 1], [1, 100, 1], [7]] + [
        list(rng.integers(1, 60, size=rng.integers(1, 8))) for _ in range(30)]
    for sizes in cases:
        for waste in (0.0, 0.1, 0.4, 10.0):
            runs = X.color_groups(sizes, waste)
            # Consecutive runs covering every colour once, in order.
            assert [a for a, _ in runs] == [0] + [b for _, b in runs[:-1]]
            assert runs[-1][1] == len(sizes) and all(a < b for a, b in runs)
            cost = sum(max(sizes[a:b]) * (b - a) for a, b in runs)
            assert cost <= (1 + waste) * sum(sizes) + 1e-9
            # No partition with fewer runs fits the budget (brute force over cut sets).
            n = len(sizes)
            for k in range(1, len(runs)):
                for cuts in itertools.combinations(range(1, n), k - 1):
                    edges = (0,) + cuts + (n,)
                    c = sum(max(sizes[a:b]) * (b - a)
                            for a, b in zip(edges[:-1], edges[1:], strict=True))
                    assert c > (1 + waste) * sum(sizes)
    assert X.color_groups([5, 5, 5], 0.0) == [(0, 3)]
    assert X.color_groups([4, 2], 0.0) == [(0, 1), (1, 2)]
    assert X.color_groups([], 0.1) == []


def test_padded_color_scan_matches_colour_loop():
    # The solver scans padded runs of colours; the reference projects colour by colour in
    # Python. Padded constraints must be no-ops: vertices of no constraint stay bit-identical
    # and every vertex matches the reference to float32 rounding (the loop and the unrolled
    # code may fuse differently, e.g. into fused multiply-adds).
    pat, m = _sheet(0.3, 0.03)
    g = m.garment
    model = X.build_cloth(g, m.landmark_vertices(pat, "top"))
    nv = g.num_vertices
    p0 = jnp.asarray(g.vertices) + 0.01 * jax.random.normal(jax.random.PRNGKey(1), (nv, 3))
    w = model.free / (0.2 * model.vertex_area)
    # Leave the last vertex (the clamp target of padded gathers) out of every constraint.
    keep = nv - 1

    def drop_last(c, names):
        idx = np.asarray(getattr(c, names[0]))
        ok = ~np.any(np.stack([np.asarray(getattr(c, k)).reshape(len(idx), -1) == keep
                               for k in names], 0), axis=(0, 2))
        return type(c)(**{f.name: jnp.asarray(np.asarray(getattr(c, f.name))[ok])
                          for f in dataclasses.fields(c)})

    kinds = {
        "bend": ([drop_last(c, ["idx"]) for c in model.bend],
                 lambda q, c, lam: X.project_bend(q, w, c, lam, 3.0),
                 lambda c: jnp.zeros(c.weights.shape[:-1] + (3,))),
        "stretch": ([drop_last(c, ["i", "j"]) for c in model.stretch],
                    lambda q, c, lam: X.project_stretch(q, w, c, lam, 2.0, 1.1),
                    lambda c: jnp.zeros(c.rest.shape)),
        "limits": ([drop_last(c, ["i", "j"]) for c in model.limits],
                   lambda q, c, lam: (X.project_limits(q, w, c), lam), lambda c: None),
    }
    # The solver sweeps stretch colours in both orders, the others forward only.
    for (name, (colors, project, zeros)), reverse in zip(
            list(kinds.items()) + [("stretch", kinds["stretch"])], (False,) * 3 + (True,),
            strict=True):
        sizes = [len(c.rest if name == "stretch" else c.weights if name == "bend"
                     else c.max_dist) for c in colors]
        assert len(set(sizes)) > 2, name  # unequal colours: the runs below are padded
        touched = np.zeros(nv, bool)
        for c in colors:
            for f in ("i", "j", "idx"):
                if hasattr(c, f):
                    touched[np.asarray(getattr(c, f)).reshape(-1)] = True
        assert not touched[keep]
        # One run of every colour (padded to the largest) and one run per colour (no padding).
        # Counted on shapes (eval_shape): run eagerly, every pad and stack of every colour
        # would compile its own program (4 s of the test's CPU).
        def runs(waste, colors=tuple(colors)):
            return jax.eval_shape(lambda: X._stack_colors(colors, nv, waste))

        assert len(runs(100.0)) == 1 and len(runs(0.0)) > 2

        @jax.jit
        def both(q, colors=tuple(colors), project=project, zeros=zeros, reverse=reverse):
            ref = q
            for c in (reversed(colors) if reverse else colors):
                ref, _ = project(ref, c, zeros(c))
            outs = []
            for waste in (0.0, 100.0):
                runs = X._stack_colors(colors, nv, waste)
                outs.append(X._sweep(q, runs, [zeros(r) for r in runs], project, reverse)[0])
            return ref, outs

        ref, outs = both(p0)
        ref = np.asarray(ref)
        assert np.abs(ref - np.asarray(p0)).max() > 1e-3, name  # it did project
        for out in map(np.asarray, outs):
            np.testing.assert_array_equal(out[~touched], np.asarray(p0)[~touched])
            # |p| < 2 m: float32 rounding is 2^-22 m per operation; a few operations differ.
            np.testing.assert_allclose(out, ref, rtol=0, atol=4 * 2.0 ** -22, err_msg=name)
