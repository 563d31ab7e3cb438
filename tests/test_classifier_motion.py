"""Motion features and the calibrated, abstaining classifier (issue 25)."""

import dataclasses

import numpy as np
import pytest

from wrinkle_jax.classifier import calibrated as cal
from wrinkle_jax.classifier import motion


def _grid(n=6, pitch=0.05):
    """A flat n x n sheet hanging in the xz-plane: vertices (n*n, 3), faces, UVs in meters."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    uv = np.stack([i.ravel(), j.ravel()], -1) * pitch
    verts = np.stack([uv[:, 0], np.zeros(n * n), 1.0 - uv[:, 1]], -1)
    idx = (i * n + j)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([idx, idx + n, idx + 1], -1),
                            np.stack([idx + 1, idx + n, idx + n + 1], -1)])
    return verts, faces, uv


def _scene(seed=0, frames=40, fps=30.0):
    """A sheet swinging and flapping behind a body that walks and turns (random, smooth)."""
    rng = np.random.default_rng(seed)
    verts, faces, uv = _grid()
    t = np.arange(frames) / fps
    body = np.stack([0.8 * t, 0.1 * np.sin(2 * np.pi * t), 0.9 + 0.02 * np.sin(4 * np.pi * t)],
                    -1)
    caps = np.zeros((frames, 3, 2, 3))
    caps[:, :, 0] = body[:, None] + rng.normal(0, 0.1, (3, 3))
    caps[:, :, 1] = caps[:, :, 0] + np.array([0.0, 0.0, 0.3])
    low = (1.0 - verts[:, 2])[None, :, None]
    wave = np.stack([np.sin(2 * np.pi * 1.7 * t[:, None] + verts[None, :, 0] * 5),
                     np.cos(2 * np.pi * 3.1 * t[:, None] + verts[None, :, 2] * 3),
                     0.3 * np.sin(2 * np.pi * 2.3 * t[:, None])[:, [0] * len(verts)]], -1)
    frames_ = verts[None] + body[:, None] - body[0] + 0.2 * low * wave
    return frames_, caps, faces, uv, fps


def _yaw_shift(x, angle, shift):
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return x @ rot.T + shift


def test_features_invariant_to_rigid_motion_of_body_and_cloth():
    frames, caps, faces, uv, fps = _scene()
    topo = motion.make_topology(faces, uv)
    f0 = motion.window_features(frames[:32], motion.body_reference(caps[:32]), topo, fps,
                                caps[:32])
    shift = np.array([3.0, -2.0, 0.7])
    moved_caps = _yaw_shift(caps[:32], 1.1, shift)
    f1 = motion.window_features(_yaw_shift(frames[:32], 1.1, shift),
                                motion.body_reference(moved_caps), topo, fps, moved_caps)
    assert f0.shape == (motion.FEATURE_DIM,)
    np.testing.assert_allclose(f1, f0, rtol=1e-6, atol=1e-6)
    # ... and NOT invariant to moving the cloth alone (the features do see the motion).
    moved = frames[:32] + np.linspace(0, 0.3, 32)[:, None, None] * np.array([1.0, 0, 0])
    f2 = motion.window_features(moved, motion.body_reference(caps[:32]), topo, fps, caps[:32])
    assert np.max(np.abs(f2 - f0)) > 0.05


def test_spectrum_peak_of_damped_oscillator():
    fps, f0 = 30.0, 4.0
    t = np.arange(128) / fps
    x = np.exp(-0.3 * t) * np.sin(2 * np.pi * f0 * t)
    freqs, power = motion.power_spectrum(x[:, None, None], fps)
    assert abs(freqs[np.argmax(power)] - f0) <= fps / 128  # within one frequency bin
    frac = motion.band_fractions(freqs, power)
    assert frac.sum() == pytest.approx(1.0, abs=1e-6)
    assert np.argmax(frac) == 3  # the 3.5-6 Hz band


def test_stretch_of_uniformly_scaled_sheet():
    verts, faces, uv = _grid()
    topo = motion.make_topology(faces, uv)
    frames = np.repeat(verts[None], 10, 0) * 1.05
    ref = np.zeros((10, 3))
    f = motion.window_features(frames, ref, topo, 30.0)[motion.family_slices()["stretch"]]
    # log strain log(1.05) on every side, no spread over edges or time.
    np.testing.assert_allclose(f[:4], np.log(1.05), atol=1e-6)
    np.testing.assert_allclose(f[4:], 0.0, atol=1e-6)
    # Stretch only the hanging direction (z) by 3 %: vertical sides strain, horizontal not.
    sag = np.repeat(verts[None], 10, 0) * np.array([1.0, 1.0, 1.03])
    g = motion.window_features(sag, ref, topo, 30.0)[motion.family_slices()["sag"]]
    assert g[0] == pytest.approx(np.log(1.03), abs=1e-6)        # vertical sides
    assert g[1] == pytest.approx(0.0, abs=1e-6)                 # horizontal sides
    assert 0.0 < g[2] < np.log(1.03)                            # diagonals: in between
    assert g[3] == pytest.approx(np.log(1.03), abs=1e-6)        # vertical - horizontal


def test_gravity_slope_of_a_strip_hanging_under_its_own_weight():
    # Rest height v above the free end; strain a + b v, as weight g rho v / k would give:
    # deformed height Z(v) = v (1 + a) + b v^2 / 2. Each vertical side's strain is exactly
    # a + b v_mid, so the fit must return the slope b (per meter) and the intercept a.
    a, b = 1e-3, 6e-3
    verts, faces, uv = _grid(n=8, pitch=0.04)
    v = verts[:, 2] - verts[:, 2].min()
    hung = verts.copy()
    hung[:, 2] = v * (1 + a) + 0.5 * b * v * v
    frames = np.repeat(hung[None], 10, 0)
    topo = motion.make_topology(faces, uv)
    g = motion.window_features(frames, np.zeros((10, 3)), topo, 30.0)
    slope, icpt, corr = g[motion.family_slices()["gravity"]]
    assert slope == pytest.approx(b, rel=0.02)
    assert icpt == pytest.approx(a, abs=2e-5)
    assert corr > 0.99
    # A stiffer fabric (a tenth of the slope) reads a tenth; a uniform stretch reads none.
    hung[:, 2] = v * (1 + a) + 0.05 * b * v * v
    g = motion.window_features(np.repeat(hung[None], 10, 0), np.zeros((10, 3)), topo, 30.0)
    assert g[motion.family_slices()["gravity"]][0] == pytest.approx(0.1 * b, rel=0.02)
    g = motion.window_features(np.repeat(verts[None] * 1.01, 10, 0), np.zeros((10, 3)), topo,
                               30.0)
    assert g[motion.family_slices()["gravity"]][0] == pytest.approx(0.0, abs=1e-6)


def test_dihedral_angle_of_folded_pair():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    faces = np.array([[0, 1, 2], [2, 1, 3]])
    topo = motion.make_topology(faces)
    assert len(topo.edge_faces) == 1
    assert motion.dihedral_angles(verts, topo)[0] == pytest.approx(0.0, abs=1e-6)
    folded = verts.copy()
    folded[3] = [0.5, 0.5, np.sqrt(0.5)]  # lift vertex 3 about the shared edge by 90 degrees
    assert motion.dihedral_angles(folded, topo)[0] == pytest.approx(np.pi / 2, abs=1e-5)


def test_follow_body_rigidly_keeps_shape():
    frames, caps, faces, uv, _ = _scene(frames=12)
    skinned = motion.follow_body_rigidly(frames[0], caps)
    np.testing.assert_allclose(skinned[0], frames[0], atol=1e-6)
    # Rigid per capsule: the distances between vertices riding on one capsule never change.
    d0 = np.linalg.norm(skinned[0, :, None] - skinned[0, None], axis=-1)
    d9 = np.linalg.norm(skinned[9, :, None] - skinned[9, None], axis=-1)
    c = caps[0]
    ab = c[:, 1] - c[:, 0]
    t = np.clip(((frames[0][:, None] - c[:, 0]) * ab).sum(-1) / (ab * ab).sum(-1), 0, 1)
    bone = np.argmin(np.linalg.norm(frames[0][:, None] - (c[:, 0] + t[..., None] * ab), axis=-1),
                     1)
    same = bone[:, None] == bone[None]
    np.testing.assert_allclose(d9[same], d0[same], atol=1e-5)
    # The rigidity family sees it: no motion in the capsules' frames (the 1e-4 m/s floor),
    # while the swinging original moves in them.
    topo = motion.make_topology(faces, uv)
    sl = motion.family_slices()["rigidity"]
    ref = motion.body_reference(caps)
    rigid = motion.window_features(skinned, ref, topo, 30.0, caps)[sl]
    swing = motion.window_features(frames, ref, topo, 30.0, caps)[sl]
    assert rigid[0] < np.log(2e-4) and swing[0] > np.log(1e-2)


def _blobs(seed, n=60, scale=1.0):
    """Window features of 5 classes separated along 3 of the columns, 3 'scenes' each."""
    rng = np.random.default_rng(seed)
    x = rng.normal(0, 1, (5 * n, motion.FEATURE_DIM))
    y = np.repeat(np.arange(5), n)
    x[:, :3] += scale * np.eye(5, 3)[y] * 3.0
    return x, y


def test_logistic_fit_learns_and_temperature_calibrates():
    x, y = _blobs(0, n=150)  # 150 windows per class: enough for all FEATURE_DIM columns
    model = cal.fit(x, y, cal.MotionConfig(l2=1e-3))
    xt, yt = _blobs(1)
    lp = cal.window_log_probs(model, xt)
    assert np.mean(lp.argmax(1) == yt) > 0.6
    # An overconfident model (logits x 8) has a higher NLL; the fitted temperature undoes it.
    over = lp * 8.0
    t = cal.fit_temperature(over, yt)
    assert t > 2.0
    p_over, p_cal = cal.sequence_probs(over, 1.0), cal.sequence_probs(over, t)
    assert cal.nll(p_cal, yt) < cal.nll(p_over, yt) - 0.1
    assert cal.reliability(p_cal, yt)[3] < cal.reliability(p_over, yt)[3]


def test_reliability_and_threshold():
    probs = np.array([[0.9, 0.1], [0.9, 0.1], [0.6, 0.4], [0.6, 0.4]])
    labels = np.array([0, 0, 0, 1])
    counts, conf, acc, ece = cal.reliability(probs, labels, bins=10)
    assert counts[9] == 2 and counts[6] == 2
    assert acc[9] == 1.0 and acc[6] == 0.5
    assert ece == pytest.approx(0.5 * 0.1 + 0.5 * 0.1)
    assert cal.choose_threshold([0.9, 0.9, 0.6, 0.6], [1, 1, 1, 0], 0.9, min_answers=2) == 0.9
    assert cal.choose_threshold([0.9, 0.6], [0, 0], 0.9, min_answers=1) == 1.0


def test_abstains_on_constant_input_and_round_trips(tmp_path):
    x, y = _blobs(2)
    model = cal.fit(x, y, cal.MotionConfig(families=("kinematic", "spectral")))
    model = model._replace(temperature=1.0, threshold=0.5, novelty_limit=4.0)
    good = cal.classify_features(model, x[y == 2][:8])
    assert not good.abstained and good.material == "knit_terry"
    # A sequence whose windows never move (all features constant, far from the data) abstains.
    const = np.full((8, motion.FEATURE_DIM), 25.0)
    r = cal.classify_features(model, const)
    assert r.abstained and r.material is None and "unlike" in r.reason
    path = cal.save(tmp_path / "m.npz", model)
    back = cal.load(path)
    assert back.config == model.config and back.threshold == 0.5
    r2 = cal.classify_features(back, x[y == 2][:8])
    assert r2.material == good.material
    assert r2.confidence == pytest.approx(good.confidence, rel=1e-4)
    with pytest.raises(cal.ClassifierError):
        cal.load(tmp_path / "missing.npz")


def test_clip_bounds_the_logits_of_an_input_unlike_the_training_data():
    x, y = _blobs(3, n=30)
    cfg = cal.MotionConfig(steps=50, clip=2.0)
    model = cal.fit(x, y, cfg)
    at_edge = model.mean + 2.0 * model.std                      # +2 sd on every used feature
    far = model.mean + 50.0 * model.std
    lp_edge = cal.window_log_probs(model, at_edge[None])
    np.testing.assert_allclose(cal.window_log_probs(model, far[None]), lp_edge, atol=1e-9)
    unclipped = model._replace(config=dataclasses.replace(cfg, clip=0.0))
    assert np.abs(cal.window_log_probs(unclipped, far[None]) - lp_edge).max() > 1.0
    # inside the range nothing changes; the novelty guard still sees the far input
    inside = model.mean + np.array([[-1.9], [0.0], [1.0]]) * model.std     # within 2 sd
    np.testing.assert_allclose(cal.window_log_probs(model, inside),
                               cal.window_log_probs(unclipped, inside), atol=1e-12)
    assert cal.novelty(model, far[None]) > 100 * cal.novelty(model, inside)


def test_group_answer_when_the_material_is_unsure():
    cfg = cal.MotionConfig(families=("lag",))
    d = len(cfg.columns())
    p = np.array([0.45, 0.04, 0.03, 0.45, 0.03])  # the two silks, MATERIALS order
    model = cal.MotionClassifier(np.zeros((d, 5)), np.log(p), np.zeros(d), np.ones(d), 1.0,
                                 0.6, np.inf, cfg, group_threshold=0.8)
    r = cal.classify_features(model, np.zeros((3, motion.FEATURE_DIM)))
    assert r.abstained and r.material is None and "low confidence" in r.reason
    assert r.group == "light_silk" and r.group_confidence == pytest.approx(0.9)
    assert sum(r.group_scores.values()) == pytest.approx(1.0)
    # Above the group threshold only: a stricter one abstains at group level too.
    r2 = cal.classify_features(model._replace(group_threshold=0.95),
                               np.zeros((3, motion.FEATURE_DIM)))
    assert r2.group is None
