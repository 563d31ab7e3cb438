"""Where every scene's pins go: the pinned vertices and their attachment targets are a
property of the pattern (`Pattern.pin_targets`), not of the garment's name."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wrinkle_jax.sim import patterns, scenes


def _on_waist_ellipse(t: np.ndarray) -> np.ndarray:
    """Normalized ellipse radius of target points (P, 3): 1 on the waistband."""
    rx, ry = patterns.WAIST_RADII
    return np.hypot(t[:, 0] / rx, t[:, 1] / ry)


def _waist_ellipse_same_azimuth(p0, t):
    np.testing.assert_allclose(_on_waist_ellipse(t), 1.0, atol=1e-12)
    # Each vertex goes to the ellipse point whose parameter is its own azimuth.
    rx, ry = patterns.WAIST_RADII
    np.testing.assert_allclose(np.arctan2(t[:, 1] / ry, t[:, 0] / rx),
                               np.arctan2(p0[:, 1], p0[:, 0]), atol=1e-12)
    np.testing.assert_array_equal(t[:, 2], patterns.WAIST_Z)


def _pleated_waist(p0, t):
    # On the wavy ring around the waistband: never inside the ellipse, within its pleat depth.
    _, a = patterns.wavy_ring(1.8, 1.0, 16, *patterns.WAIST_RADII)
    r = _on_waist_ellipse(t)
    # (1e-6: the ring is a dense polyline, whose chords cut in by ~1e-7.)
    assert r.min() >= 1.0 - 1e-6 and r.max() <= 1.0 + 2 * a + 1e-6 and r.max() > 1.01
    np.testing.assert_array_equal(t[:, 2], patterns.WAIST_Z)


def _cape_neck(p0, t):
    np.testing.assert_allclose(np.hypot(t[:, 0], t[:, 1]), patterns.CAPE_NECK_RADIUS,
                               atol=1e-12)
    np.testing.assert_array_equal(t[:, 2], patterns.CAPE_NECK_Z)


def _in_place(p0, t):
    np.testing.assert_array_equal(t, p0)


# How each garment's pinned landmark attaches (the behaviour the data sets were made with). A
# new garment in a scene must be added here with the property its pins must have.
EXPECTED = {
    "flared_skirt": _waist_ellipse_same_azimuth,
    "circle_skirt": _waist_ellipse_same_azimuth,
    "pleated_skirt": _pleated_waist,
    "cape": _cape_neck,
    "dress": _in_place,
    "shawl": _in_place,
    "long_shawl": _in_place,
    "apron": _in_place,
    "tabard": _in_place,
}

LANDMARK_SCENES = [n for n, s in scenes.SCENES.items() if s.pins != "rings"]


@pytest.mark.parametrize("name", LANDMARK_SCENES)
def test_every_scene_pins_its_landmark_onto_its_target(name):
    """`_pins` pins the scene's landmark vertices and, with the body frame at rest, glides them
    onto the pattern's targets, which have the property the garment's pins always had."""
    sc = scenes.get_scene(name)
    assert sc.garment in EXPECTED, f"add {sc.garment}'s pin property to EXPECTED"
    pattern = patterns.make_pattern(sc.garment)
    mesh = patterns.mesh_pattern(pattern, scenes.resolution_pd("coarse"))
    frames = 12
    rest = np.broadcast_to(np.eye(3, 4), (frames, 3, 4)).copy()
    kin = {"time": np.arange(frames) / 30.0, sc.attach_to: rest}
    pins, track = scenes._pins(sc, pattern, mesh, kin, 2, 5)
    np.testing.assert_array_equal(pins, mesh.landmark_vertices(pattern, sc.pins))
    assert len(pins) >= 8 and track.shape == (frames, len(pins), 3)
    p0 = np.asarray(mesh.garment.vertices, np.float64)[pins]
    np.testing.assert_allclose(track[0], p0, atol=1e-6)  # starts where the drape put them
    to_target = pattern.pin_targets.get(sc.pins)
    target = p0 if to_target is None else to_target(p0)
    EXPECTED[sc.garment](p0, target)
    np.testing.assert_allclose(track[-1], target, atol=1e-6)  # attached after 5 frames


def test_rings_pin_six_points_of_the_top_edge():
    sc = scenes.get_scene("sheet_balls_wind")
    pattern = patterns.make_pattern(sc.garment)
    mesh = patterns.mesh_pattern(pattern, scenes.resolution_pd("coarse"))
    pins, track = scenes._pins(sc, pattern, mesh, {"time": np.arange(4) / 30.0}, 1, 0)
    assert len(pins) == 6 and set(pins) <= set(mesh.landmark_vertices(pattern, "top"))
    np.testing.assert_array_equal(track, np.broadcast_to(
        np.asarray(mesh.garment.vertices, np.float32)[pins], track.shape))


def test_a_waist_is_never_pinned_in_place():
    """Every garment with a waist, and any new skirt the skirt builders make under another
    name, closes its waist onto the waistband (the pinning does not depend on the name)."""
    made = {n: f() for n, f in patterns.GARMENTS.items()}
    made["new_skirt"] = patterns.flared_skirt_pattern(0.5, 1.2 * math.pi, 5, name="new_skirt")
    made["wide_pleats"] = patterns.pleated_skirt_pattern(width=2.0, pleats=20)
    for name, pattern in made.items():
        if "waist" not in pattern.landmarks:
            continue
        assert "waist" in pattern.pin_targets, name
        mesh = patterns.mesh_pattern(pattern, 0.05)
        p0 = np.asarray(mesh.garment.vertices, np.float64)[mesh.landmark_vertices(pattern,
                                                                                  "waist")]
        t = pattern.pin_targets["waist"](p0)
        np.testing.assert_array_equal(t[:, 2], patterns.WAIST_Z)
        r = _on_waist_ellipse(t)
        assert r.min() >= 1.0 - 1e-6 and r.max() < 1.5, name
    p0 = np.array([[0.3, -0.2, 1.2], [-0.1, 0.4, 1.1]])
    _waist_ellipse_same_azimuth(p0, made["new_skirt"].pin_targets["waist"](p0))


def test_pleated_targets_follow_the_patterns_own_pleats():
    """A pleated skirt with other pleats gets the targets of its own ring, not the default's."""
    wide = patterns.pleated_skirt_pattern(width=2.0, pleats=20)
    mesh = patterns.mesh_pattern(wide, 0.03)
    p0 = np.asarray(mesh.garment.vertices, np.float64)[mesh.landmark_vertices(wide, "waist")]
    np.testing.assert_array_equal(wide.pin_targets["waist"](p0)[:, :2],
                                  patterns.pleated_waist_targets(p0[:, :2], 2.0, 20))
