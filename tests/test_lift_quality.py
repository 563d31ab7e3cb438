"""The quality measure of a lift against its goal (`lift_quality`): cases with known answers."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import bodies, lift, normalmap, primitives
from wrinkle_jax import lift_quality as lq


@pytest.fixture(scope="module")
def sheet():
    """A 12 cm sheet subdivided 3 levels (2.1 mm edges), a wavy copy of it (4 mm amplitude,
    40 x 50 mm wavelengths: inside the detail bands), and the wavy copy's baked map."""
    g = primitives.grid_sheet(7, 7, size=(0.12, 0.12))
    fine, _ = lift.upsample(g, levels=3)
    flat = np.asarray(fine.vertices, np.float64)
    wavy = flat.copy()
    wavy[:, 2] += 0.004 * np.sin(2 * np.pi * flat[:, 0] / 0.04) * np.cos(
        2 * np.pi * flat[:, 1] / 0.05)
    layout = normalmap.layout_for(fine, 0.002)
    plan = lq.quality_plan(fine, layout)
    nstar = normalmap.bake(plan, jnp.asarray(wavy, jnp.float32))
    return dict(fine=fine, flat=flat, wavy=wavy, layout=layout, plan=plan, nstar=nstar)


def test_a_mesh_meets_its_own_map(sheet):
    """Re-baking the mesh a map was baked from gives that map: ~0 degrees, band ratio 1."""
    q = lq.lift_quality(sheet["wavy"], sheet["nstar"], sheet["plan"])
    assert q.texels == int(np.asarray(sheet["plan"].mask).sum())
    assert q.angle_p90_deg < 0.1 and q.angle_mean_deg < 0.05
    for band, ratio in q.band_ratio.items():
        assert q.band_rms_target[band] > 0.02  # the waves are in both bands
        assert ratio == pytest.approx(1.0, abs=1e-5)
    assert q.vs_reference_mm_rms is None and q.inside is None and q.rim_mm_rms is None


def test_the_flat_surface_misses_the_waves_by_their_slope(sheet):
    """p0 (flat) against the wavy map: the error is the waves' slope angle (the analytic
    distribution of atan|grad h|), and it carries none of the detail energy."""
    q = lq.lift_quality(sheet["flat"], sheet["nstar"], sheet["plan"])
    x, y = np.meshgrid(np.linspace(0, 0.12, 241), np.linspace(0, 0.12, 241))
    kx, ky = 2 * np.pi / 0.04, 2 * np.pi / 0.05
    gx = 0.004 * kx * np.cos(kx * x) * np.cos(ky * y)
    gy = -0.004 * ky * np.sin(kx * x) * np.sin(ky * y)
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    assert q.angle_mean_deg == pytest.approx(slope.mean(), rel=0.08)
    assert q.angle_p90_deg == pytest.approx(np.percentile(slope, 90), rel=0.08)
    assert all(r == 0.0 for r in q.band_ratio.values())


def test_lifting_a_baked_map_recovers_the_mesh(sheet):
    """Lifting p0 (flat) toward the wavy mesh's map lands close to the wavy mesh: the angle
    error falls from the waves' slope (~20 deg) to a small fraction of it, and the lifted
    surface carries most of the map's detail energy."""
    fine, flat = sheet["fine"], sheet["flat"]
    top = lift.lift_topology(fine.faces, fine.num_vertices)
    n = lift.sample_target_normals(sheet["nstar"], fine, sheet["layout"])
    p = lift.lift(jnp.asarray(flat, jnp.float32), top, n)
    before = lq.lift_quality(flat, sheet["nstar"], sheet["plan"])
    q = lq.lift_quality(p, sheet["nstar"], sheet["plan"], vertices0=flat,
                        reference=sheet["wavy"])
    assert q.angle_mean_deg < 0.15 * before.angle_mean_deg
    assert q.angle_median_deg < 2.5
    assert 0.85 < q.band_ratio["16_64mm"] < 1.1
    # The shape itself is recovered to well under the 4 mm amplitude.
    assert q.vs_reference_mm_rms < 1.0


def test_a_flat_map_is_met_by_the_subdivided_coarse_surface():
    """N* baked from p0 (the subdivided coarse frame, here a bent sheet) holds no detail:
    the lift stays at p0 (no displacement, no ragged rim) and matches the map."""
    g = primitives.grid_sheet(6, 6, size=(0.1, 0.1))
    v = np.asarray(g.vertices, np.float64).copy()
    v[:, 2] = 0.3 * v[:, 0] ** 2  # a gentle bend, smooth at the 10 mm edge scale
    g = g.replace(vertices=v.astype(np.float32))
    fine, sub = lift.upsample(g, levels=2)
    p0 = np.asarray(sub.apply(jnp.asarray(v, jnp.float32)))
    layout = normalmap.layout_for(fine, 0.002)
    plan = lq.quality_plan(fine, layout)
    nstar = normalmap.bake(plan, jnp.asarray(p0))
    top = lift.lift_topology(fine.faces, fine.num_vertices)
    n = lift.sample_target_normals(nstar, fine, layout)
    p = lift.lift(jnp.asarray(p0), top, n)
    q = lq.lift_quality(p, nstar, plan, vertices0=p0, reference=p0)
    assert q.vs_reference_mm_max < 0.05
    assert q.rim_mm_max < 0.05 and q.rim_ragged_mm_rms < 0.02 and q.interior_mm_rms < 0.05
    assert q.angle_p90_deg < 0.5


def test_rim_terms_on_a_known_displacement(sheet):
    """Lift the rim alone by 1 mm: rim RMS = max = 1 mm and interior 0; alternate the push
    along the rim (a ragged rim): raggedness = the step between neighbours."""
    flat, plan = sheet["flat"], sheet["plan"]
    rim = lq.rim_topology(np.asarray(plan.faces), len(flat))
    moved = flat.copy()
    moved[rim.on_rim, 2] += 1e-3
    q = lq.lift_quality(moved, sheet["nstar"], plan, vertices0=flat, rim=rim)
    assert q.rim_mm_rms == pytest.approx(1.0, abs=1e-4)
    assert q.rim_mm_max == pytest.approx(1.0, abs=1e-4)
    assert q.rim_ragged_mm_rms == pytest.approx(0.0, abs=1e-4)
    assert q.interior_mm_rms == pytest.approx(0.0, abs=1e-9)
    # Every other vertex along the bottom edge (y = 0) up by 1 mm: on that edge's inner
    # vertices, each pushed vertex's rim neighbours are not pushed (step 1 mm) and vice versa
    # (step 1 mm to the mean of two pushed neighbours).
    ragged = flat.copy()
    bottom = np.flatnonzero(np.abs(flat[:, 1]) < 1e-6)
    bottom = bottom[np.argsort(flat[bottom, 0])]
    ragged[bottom[::2], 2] += 1e-3
    q = lq.lift_quality(ragged, sheet["nstar"], plan, vertices0=flat, rim=rim)
    assert q.rim_ragged_mm_rms > 0.3  # a smooth 1 mm lift of the rim scored 0


def test_reference_distance_and_penetrations(sheet):
    """Distance to a reference shifted by 2 mm is 2 mm; the count inside a sphere is the
    count of vertices within its radius."""
    flat, plan = sheet["flat"], sheet["plan"]
    shifted = flat + np.array([0.0, 0.0, 0.002])
    center = np.array([0.06, 0.06, -0.03])
    body = bodies.primitive_body(spheres=(center, 0.05))
    q = lq.lift_quality(flat, sheet["nstar"], plan, reference=shifted, body=body)
    assert q.vs_reference_mm_rms == pytest.approx(2.0, abs=1e-4)
    assert q.vs_reference_mm_max == pytest.approx(2.0, abs=1e-4)
    expected = int(np.sum(np.linalg.norm(flat - center, axis=1) < 0.05))
    assert expected > 10 and q.inside == expected


def test_empty_map_is_an_error(sheet):
    with pytest.raises(ValueError, match="no garment texel"):
        lq.lift_quality(sheet["flat"], jnp.zeros_like(sheet["nstar"]), sheet["plan"])


def _bench_pipeline():
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "bench_pipeline.py"
    spec = importlib.util.spec_from_file_location("bench_pipeline", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # not __main__: parses no arguments
    return mod


def _setting(ms, angle, p90=None, band=None, inside=None):
    angle = np.asarray(angle, float)
    p90 = 2 * angle if p90 is None else np.asarray(p90, float)
    band = np.full_like(angle, 0.9) if band is None else np.asarray(band, float)
    return {"lift_ms_per_frame": ms, "per_frame": {
        "angle_mean_deg": list(angle), "angle_p90_deg": list(p90),
        "band_ratio_16_64mm": list(band),
        "inside": [None] * len(angle) if inside is None else list(inside)}}


def test_choose_lift_rule_on_known_sweeps():
    """The lift choice rule (`bench_pipeline.choose_lift`): noise = |mean(D - T)| + 2 SE of
    the default's paired difference with its cold twin; a cheaper setting within that noise
    (or better) on every scene wins, one outside it on any scene is rejected, the band ratio
    counts both ways."""
    b = _bench_pipeline()
    d, t = b.CHOICE_DEFAULT, b.CHOICE_TWIN
    base = np.array([1.0, 1.2, 1.1, 1.3])
    # D - T = (0.01, 0.03, 0.01, 0.03): mean 0.02, sample SD sqrt(4e-4 / 3) = 0.01155,
    # SE = SD / 2 -> angle noise 0.02 + 0.01155 = 0.0315.
    twin = base - np.array([0.01, 0.03, 0.01, 0.03])
    scene = {d: _setting(100, base), t: _setting(120, twin),
             "within": _setting(40, base + 0.03),           # worse by 0.03 <= 0.0315
             "outside": _setting(10, base + 0.035),         # worse by 0.035 > 0.0315
             "better": _setting(60, base - 0.5),            # better: one-sided
             "band_off": _setting(5, base, band=np.full(4, 0.7))}  # band moved by 0.2
    sweeps = [{"scene": "a", "settings": scene}, {"scene": "b", "settings": scene}]
    out = b.choose_lift(sweeps)
    v = out["verdicts"]
    assert v["_noise_a"]["angle_mean_deg"] == pytest.approx(0.02 + np.sqrt(4e-4 / 3), abs=1e-4)
    assert v["within"]["qualifies"] and v["better"]["qualifies"]
    assert not v["outside"]["qualifies"] and not v["band_off"]["qualifies"]
    assert out["chosen"] == "within"  # the cheapest qualifying on the last scene
    # Outside the noise on one scene only is enough to reject it.
    other = dict(scene, within=_setting(40, base + 0.2))
    out = b.choose_lift([{"scene": "a", "settings": scene}, {"scene": "b", "settings": other}])
    assert not out["verdicts"]["within"]["qualifies"] and out["chosen"] == "better"
