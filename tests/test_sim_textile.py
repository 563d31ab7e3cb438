"""Tests for sim.textile: the projected-area routine on analytic shapes, the Cusick drape
coefficient limits and monotonicity, the cantilever bending length's Peirce scaling
c ∝ (B / W)^(1/3), and the exact invariance of the settled shape under a common scale of
density and stiffnesses. Small specimens at coarse PD with few substeps (one compilation per
mesh, reused across fabrics; the cantilever test runs the data set's 20 substeps at PD 10 mm)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wrinkle_jax.sim import materials, patterns, textile

FAST = textile.SettleConfig(substeps=8, max_frames=240, v_tol=2e-3)


def _fan(n: int, r: float, center=(0.0, 0.0), rot: float = 0.0):
    """A regular n-gon of circumradius r as a triangle fan: positions (n + 1, 3), faces."""
    a = rot + 2 * math.pi * np.arange(n) / n
    pts = np.c_[np.r_[center[0], center[0] + r * np.cos(a)],
                np.r_[center[1], center[1] + r * np.sin(a)], np.zeros(n + 1)]
    faces = np.array([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)])
    return pts, faces


@pytest.mark.parametrize("n, rot", [(4, 0.3), (7, 0.0), (64, 0.1)])
def test_projected_area_of_polygons_within_the_raster_bound(n, rot):
    r, cell = 0.1, 5e-4
    x, f = _fan(n, r, rot=rot)
    exact = 0.5 * n * r * r * math.sin(2 * math.pi / n)
    perimeter = 2 * n * r * math.sin(math.pi / n)
    got = textile.projected_area(x, f, cell)
    assert abs(got - exact) <= perimeter * cell  # the stated bound (one cell along the outline)
    assert abs(got - exact) / exact < 0.01


def test_projected_area_is_a_union_and_ignores_height():
    x, f = _fan(32, 0.08)
    a = textile.projected_area(x, f)
    # The same disc twice (one copy lifted and shifted by 0.05 m in x): union, not sum.
    x2 = np.r_[x, x + [0.05, 0.0, 0.3]]
    f2 = np.r_[f, f + len(x)]
    both = textile.projected_area(x2, f2)
    assert a < both < 2 * a
    # Two discs of radius r with centres d apart: lens overlap area is analytic.
    r, d = 0.08, 0.05
    lens = 2 * r * r * math.acos(d / (2 * r)) - 0.5 * d * math.sqrt(4 * r * r - d * d)
    assert both == pytest.approx(2 * a - lens * (a / (math.pi * r * r)), rel=0.01)
    # Folding a specimen up (z) does not change its shadow; tilting shrinks it by cos.
    tilt = x.copy()
    tilt[:, 2] = tilt[:, 0] * math.tan(math.radians(60))
    tilt[:, 0] *= math.cos(math.radians(60))
    assert textile.projected_area(tilt, f) == pytest.approx(0.5 * a, rel=0.01)


def test_peirce_closed_form_and_interpolation():
    # At the 41.5 degree incline Peirce's empirical f(theta) is 0.509, which the instrument
    # rounds to 1/2 (a numerical heavy-elastica solve gives overhang = 2.000 c at 41.5 deg).
    assert textile.peirce_c(0.05, textile.PEIRCE_ANGLE) == pytest.approx(0.0255, rel=2e-3)
    # Angles of a Peirce cantilever with c = 0.02 m recovered by the interpolation.
    lengths = np.geomspace(0.02, 0.08, 7)
    target = 0.02

    def angle(l):  # invert peirce_c in theta by bisection
        lo, hi = 1e-4, math.pi / 2 - 1e-4
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if textile.peirce_c(l, mid) > target else (lo, mid)
        return 0.5 * (lo + hi)

    got = textile.bending_length(lengths, [angle(v) for v in lengths])
    # The crossing is at l = target / f(41.5 deg); the test reports l / 2.
    f = textile.peirce_c(1.0, textile.PEIRCE_ANGLE)
    assert got == pytest.approx(0.5 * target / f, rel=0.005)
    assert math.isnan(textile.bending_length([0.01, 0.02], [0.1, 0.2]))  # not bracketed


def _loop_grid_faces(idx):
    """The strips' grid triangles as first written (a double loop over the cells of an
    (I + 1, J + 1) index grid, diagonal a-c on even cells, b-d on odd ones)."""
    faces = []
    for i in range(idx.shape[0] - 1):
        for j in range(idx.shape[1] - 1):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            faces += [(a, b, c), (a, c, d)] if (i + j) % 2 == 0 else [(a, b, d), (b, c, d)]
    return np.asarray(faces, np.int32)


@pytest.mark.parametrize("pd", [0.01, 0.03, 0.2])
def test_strip_meshes_keep_their_grid_triangles(pd):
    m = textile.hanging_strip_mesh(pd, length=0.31, width=0.07)
    nx, nz = max(1, round(0.07 / pd)), max(1, round(0.31 / pd))
    idx = np.arange((nx + 1) * (nz + 1)).reshape(nx + 1, nz + 1)
    assert m.garment.faces.dtype == np.int32
    np.testing.assert_array_equal(m.garment.faces, _loop_grid_faces(idx))
    np.testing.assert_array_equal(m.clamped, idx[:, 0])
    overhangs, width = [0.05, 0.12], 0.025
    s = textile.cantilever_strips(overhangs, pd, width)
    ny, n_p = max(1, round(width / pd)), max(1, round(0.03 / pd))
    faces, panels, base = [], [], 0
    for k, length in enumerate(overhangs):
        nx = n_p + 1 + max(1, round(length / pd))
        idx = np.arange(nx * (ny + 1)).reshape(nx, ny + 1) + base
        faces.append(_loop_grid_faces(idx))
        panels.append(np.repeat(2 * k + (np.arange(nx - 1) >= n_p), 2 * ny))
        base += idx.size
    np.testing.assert_array_equal(s.garment.faces, np.concatenate(faces))
    np.testing.assert_array_equal(s.garment.uv_faces, np.concatenate(faces))
    np.testing.assert_array_equal(s.garment.panels, np.concatenate(panels))


def test_drape_mesh_clamps_exactly_the_support_disc():
    mesh = patterns.mesh_pattern(textile.drape_pattern(0.12, 0.06), 0.03)
    x = np.asarray(mesh.garment.vertices)
    pinned = textile.clamped_vertices(mesh)
    rho = np.hypot(x[:, 0], x[:, 1])
    assert rho[pinned].max() == pytest.approx(0.06, abs=1e-6)
    free = np.setdiff1d(np.arange(len(x)), pinned)
    assert rho[free].min() > 0.06 + 1e-3
    assert rho.max() == pytest.approx(0.12, abs=1e-6)
    # The flat specimen's DC is 1 up to the polygonal outline and the raster.
    dc = textile.drape_coefficient(x, np.asarray(mesh.garment.faces), 0.12, 0.06)
    assert 0.95 < dc <= 1.01


def test_drape_coefficient_limits_and_monotone_in_bending():
    base = materials.fabric("denim_light")
    dcs = {}
    for scale in (1e-3, 1.0, 1e3):
        r = textile.cusick_drape(base.replace(bending=base.bending * scale), 0.03, radius=0.12,
                                 support=0.06, cfg=FAST, cell=1e-3)
        assert r["settled"], r["max_speed_m_s"]
        dcs[scale] = r["dc"]
    # Nearly rigid: the specimen stays almost flat. Limp: it hangs nearly straight down.
    assert dcs[1e3] > 0.85
    assert dcs[1e-3] < 0.3
    assert dcs[1e-3] < dcs[1.0] < dcs[1e3]


def test_cantilever_follows_peirce_cube_root_and_weight_scaling():
    # Peirce's c ∝ B^(1/3) holds while the XPBD step does not cap bending: with one
    # iteration an interior hinge settles at B / (1 + r), r = h^2 B sum_k w_k K_k^2, and r
    # grows with B. Melton's clamp-rim hinges (normalised by the free face, so r doubles
    # there) reach r = 1.5 at B and 4.5 at 3 B with the data set's 20 substeps: the exponent
    # then measures 0.28 (0.13 with 8 substeps); 40 substeps (r / 4) give 0.317.
    cfg = textile.SettleConfig(max_frames=240, substeps=40)
    base = materials.fabric("wool_melton")
    overhangs = np.geomspace(0.02, 0.1, 8)
    c = {}
    for scale in (1.0, 3.0):
        r = textile.cantilever(base.replace(bending=base.bending * scale), 0.01, overhangs,
                               cfg=cfg)
        assert r["settled"]
        c[scale] = r["bending_length_m"]
    exponent = math.log(c[3.0] / c[1.0]) / math.log(3.0)
    assert exponent == pytest.approx(1.0 / 3.0, abs=0.05)
    # Dividing the weight per area by 3 acts like multiplying B by 3 (c depends on B / W) ...
    light = textile.cantilever(base.replace(density=base.density / 3.0), 0.01, overhangs,
                               cfg=cfg)
    assert light["bending_length_m"] == pytest.approx(c[3.0], rel=0.05)
    # ... and scaling mass, bending and stretch together leaves the settled shape unchanged
    # (XPBD sees only stiffness / mass: same trajectory up to rounding).
    s = 3.0
    heavy = base.replace(density=base.density * s, bending=base.bending * s,
                         stretch=base.stretch * s)
    r = textile.cantilever(heavy, 0.01, overhangs, cfg=cfg)
    np.testing.assert_allclose(r["angles_deg"], textile.cantilever(base, 0.01, overhangs,
                                                                   cfg=cfg)["angles_deg"],
                               atol=0.05)


@pytest.mark.parametrize("deg", [0.0, 45.0, 90.0])
def test_membrane_uniaxial_stiffness_is_a_third_of_k_s_on_jittered_meshes(deg):
    # The edge membrane sum_e k_s A_e C_e^2 / 2 under uniaxial strain (lateral strain free)
    # stores ~k_s / 3 per area, not k_s: what the measured stiffnesses are compared with.
    g = patterns.mesh_pattern(patterns.sheet_pattern(0.4, 0.4), 0.03, seed=1).garment
    e, nu = textile.membrane_uniaxial_stiffness(g, math.radians(deg))
    assert e == pytest.approx(textile.MEMBRANE_UNIAXIAL, abs=0.015)
    assert -0.37 < nu < -0.29
    # A square grid with alternating diagonals, along its rows: vertical edges (1/3 of the
    # weight) carry eps, diagonals eps / 2 (lateral strain -1/5): energy 0.4 k_s eps^2 / 2.
    e, nu = textile.membrane_uniaxial_stiffness(textile.hanging_strip_mesh(0.01).garment, 0.0)
    assert e == pytest.approx(0.4, abs=0.005) and nu == pytest.approx(-0.2, abs=0.005)


def test_stretch_comparison_uses_the_uniaxial_stiffness_and_the_rule():
    terry = textile.stretch_comparison("knit_terry", 400.0)
    vals = [v for pair in textile.STRETCH_REFERENCE["knit_terry"].values() for v in pair]
    assert terry["median_N_m"] == pytest.approx(float(np.median(vals)))
    assert terry["ratio"] == pytest.approx(textile.MEMBRANE_UNIAXIAL * 400.0 / np.median(vals))
    assert terry["ratio"] < textile.STRETCH_RATIO_RULE and terry["proposed_N_m"] is None
    stiff = textile.stretch_comparison("knit_terry", 1e4)  # 50 x the median: proposed
    assert stiff["proposed_N_m"] == pytest.approx(np.median(vals) / textile.MEMBRANE_UNIAXIAL,
                                                  rel=0.03)
    assert textile.stretch_comparison("silk_chiffon", 1500.0) is None


def test_hanging_strip_lengthens_more_when_softer_and_limits_cap_it():
    cfg = textile.SettleConfig(substeps=8, max_frames=240)
    f = materials.fabric("knit_terry")
    soft = textile.hanging_strip(f.replace(stretch=20.0), 0.05, cfg=cfg, limit_spans=False)
    stiff = textile.hanging_strip(f.replace(stretch=2e4), 0.05, cfg=cfg, limit_spans=False)
    capped = textile.hanging_strip(f.replace(stretch=20.0), 0.05, cfg=cfg, limit_spans=True)
    assert soft["settled"] and stiff["settled"] and capped["settled"]
    assert soft["mean_strain"] > 2 * stiff["mean_strain"] > 0
    assert capped["mean_strain"] < soft["mean_strain"]
    assert soft["nominal_strain"] == pytest.approx(f.density * 9.81 * 0.5 / 40.0)
