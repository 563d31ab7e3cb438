"""Tests for `wrinkle_jax.character` on the real MakeHuman assets.

The assets are fetched through `assets_fetch.fetch_makehuman()` (idempotent: no download once
cached); the tests are skipped only when that download fails (no network)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import assets_fetch, character, meshio


@pytest.fixture(scope="module")
def char():
    try:
        path = assets_fetch.fetch_makehuman()
    except assets_fetch.AssetDownloadError as e:
        pytest.skip(f"MakeHuman assets unavailable (download failed: {e})")
    return character.load_character(path)


@pytest.fixture(scope="module")
def anim(char):
    return char.walk_cycle()


@pytest.fixture(scope="module")
def walk(char, anim):
    """Jitted pose stage: frame -> (pose, world)."""
    return jax.jit(lambda t: character.evaluate_walk(anim, char.skeleton, t))


def _tail(world, skel, name):
    i = skel.index(name)
    return world[i, :3, 3] + world[i, :3, 1] * skel.lengths[i]


# --------------------------------------------------------------------------------------------
# Mesh, rig and weights
# --------------------------------------------------------------------------------------------


def test_rest_pose_reproduces_base_obj(char):
    obj = meshio.load_obj(char.asset_dir / "3dobjs" / "base.obj")
    v = np.asarray(obj.vertices, np.float64)
    expected = 0.1 * np.stack([v[:, 0], -v[:, 2], v[:, 1]], 1)  # decimeters, Y up -> m, Z up
    skel = char.skeleton
    mats = character.skinning_matrices(skel, character.forward_kinematics(
        skel, character.rest_pose(skel)))
    posed = jax.jit(character.skin)(jnp.asarray(char.base.mesh.vertices), char.weights, mats)
    np.testing.assert_allclose(np.asarray(posed), expected, atol=2e-6)
    # Parts keep their map back to base.obj, and their faces are the group's faces.
    for part in (char.body, *char.garments.values()):
        np.testing.assert_allclose(part.garment.vertices, expected[part.vertex_ids], atol=1e-6)
        gid = char.base.group_names.index(part.name)
        group_faces = np.asarray(char.base.mesh.faces)[np.asarray(char.base.mesh.panels) == gid]
        np.testing.assert_array_equal(part.vertex_ids[np.asarray(part.garment.faces)],
                                      group_faces)
    assert char.body.garment.num_vertices == 13380
    assert -0.85 < char.ground_height < -0.75  # soles, ~1.67 m tall character


def test_helpers_have_valid_uvs_and_a_fallback(char):
    for name in character.GARMENT_GROUPS:
        part = char.garments[name]
        rep = part.uv_report
        assert rep["ok"] and rep["uv_source"] == "obj", rep
        assert rep["flipped_faces"] == 0 and rep["overlap_fraction"] < 0.005
        # UVs rescaled to meters of cloth: UV area == surface area.
        from wrinkle_jax.mesh import global_uv_scale

        assert global_uv_scale(part.garment) == pytest.approx(1.0, rel=1e-4)
    # The documented fallback gives a valid layout for the tube-like skirt.
    skirt = char.garments["helper-skirt"].garment
    uvs, uv_faces = character.cylindrical_uvs(skirt)
    assert character.check_uv_layout(skirt.replace(uvs=uvs, uv_faces=uv_faces))["ok"]
    # A broken layout (half the triangles mirrored) is detected.
    uv = np.asarray(skirt.uvs).copy()
    bad = skirt.replace(uvs=np.concatenate([uv, uv * [-1.0, 1.0]]),
                        uv_faces=np.where(np.arange(skirt.num_faces)[:, None] % 2 == 0,
                                          skirt.uv_faces, np.asarray(skirt.uv_faces) + len(uv)))
    rep = character.check_uv_layout(bad)
    assert not rep["ok"] and rep["flipped_faces"] > 0


def test_broken_helper_uvs_fall_back_to_cylindrical(char):
    base = char.base
    gid = base.group_names.index("helper-skirt")
    uv_faces = np.asarray(base.mesh.uv_faces).copy()
    uv_faces[np.asarray(base.mesh.panels) == gid] = 0  # every corner on one UV point
    broken = character.BaseMesh(base.mesh.replace(uv_faces=uv_faces), base.group_names,
                                base.source)
    part = character.extract_part(broken, "helper-skirt")
    assert part.uv_report["uv_source"] == "cylindrical" and part.uv_report["ok"]
    assert "degenerate" in " ".join(part.uv_report["obj_problems"])
    with pytest.raises(character.CharacterError, match="no group"):
        character.extract_part(base, "helper-cape")


def test_weights_sum_to_one(char):
    w = np.asarray(char.weights.weights)
    ids = np.asarray(char.weights.bone_ids)
    assert w.shape == (char.base.mesh.num_vertices, ids.shape[1])
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-5)
    assert (w >= 0).all() and ids.min() >= 0 and ids.max() < char.skeleton.num_bones
    assert np.all(np.diff(w, axis=1) <= 1e-7)  # sorted, padding last
    for part in char.garments.values():
        pw = char.part_weights(part)
        np.testing.assert_allclose(np.asarray(pw.weights).sum(1), 1.0, atol=1e-5)
        # Helper garments are skinned to the legs and trunk, never to helper IK bones.
        used = {char.skeleton.names[b] for b in np.unique(np.asarray(pw.bone_ids)[
            np.asarray(pw.weights) > 0])}
        assert not any(n.endswith("_ik") for n in used)
        assert {"upperleg02.L", "upperleg02.R"} <= used


def test_bone_rest_matrix_follows_blender_conventions():
    m = character.bone_rest_matrix([0.1, 0.2, 0.3], [0.1, 0.2, 0.8], 0.0)
    r = m[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r[:, 1], [0, 0, 1], atol=1e-12)  # y from head to tail
    np.testing.assert_allclose(r[:, 0], [1, 0, 0], atol=1e-12)  # smallest rotation from Y
    np.testing.assert_allclose(m[:3, 3], [0.1, 0.2, 0.3])
    rolled = character.bone_rest_matrix([0, 0, 0], [0, 0, 1], np.pi / 2)[:3, :3]
    np.testing.assert_allclose(rolled[:, 0], [0, 1, 0], atol=1e-12)  # x turned about y
    down_y = character.bone_rest_matrix([0, 0, 0], [0, -1, 0], 0.0)[:3, :3]
    np.testing.assert_allclose(down_y, np.diag([-1.0, -1.0, 1.0]), atol=1e-12)


def test_skeleton_joints_are_placed_on_the_mesh(char):
    skel = char.skeleton
    assert skel.num_bones == 163 + 8  # rig.default plus the 8 IK helpers
    parents = np.asarray(skel.parents)
    assert np.all(parents < np.arange(skel.num_bones))  # parents first
    # foot.L's head is the ankle (joint cube), its IK target sits on it.
    np.testing.assert_allclose(skel.heads[skel.index("left_foot_ik")],
                               skel.heads[skel.index("foot.L")])
    np.testing.assert_allclose(skel.heads[skel.index("left_knee_ik")],
                               skel.tails[skel.index("upperleg02.L")], atol=1e-6)
    # Left/right symmetry of the base mesh carries over to the joints.
    for name in ("upperleg01", "lowerarm02", "foot"):
        l, r = skel.heads[skel.index(name + ".L")], skel.heads[skel.index(name + ".R")]
        np.testing.assert_allclose(l * [-1, 1, 1], r, atol=1e-4)


# --------------------------------------------------------------------------------------------
# Forward kinematics and skinning
# --------------------------------------------------------------------------------------------


def _random_pose(skel, seed=0, scale=0.3):
    rng = np.random.default_rng(seed)
    rot = character.euler_xyz_to_matrix(jnp.asarray(rng.normal(0, scale, (skel.num_bones, 3))))
    loc = jnp.asarray(rng.normal(0, 0.01, (skel.num_bones, 3)), jnp.float32)
    return character.Pose(rot.astype(jnp.float32), loc)


def test_forward_kinematics_matches_a_recursive_reference(char):
    skel = char.skeleton
    pose = _random_pose(skel)
    world = np.asarray(jax.jit(character.forward_kinematics)(skel, pose))
    rel = np.asarray(skel.rest_rel, np.float64)
    ref = np.zeros_like(rel)
    for b, p in enumerate(skel.parents):  # parents first
        basis = np.eye(4)
        basis[:3, :3], basis[:3, 3] = np.asarray(pose.rotations[b]), np.asarray(pose.locations[b])
        ref[b] = (ref[p] if p >= 0 else np.eye(4)) @ rel[b] @ basis
    np.testing.assert_allclose(world, ref, atol=2e-5)


def test_identity_pose_leaves_every_vertex_in_place(char):
    skel = char.skeleton
    mats = character.skinning_matrices(skel, character.forward_kinematics(
        skel, character.rest_pose(skel)))
    np.testing.assert_allclose(np.asarray(mats), np.broadcast_to(np.eye(4)[:3], mats.shape),
                               atol=1e-6)
    for part in (char.body, *char.garments.values()):
        out = jax.jit(character.skin)(jnp.asarray(part.garment.vertices),
                                      char.part_weights(part), mats)
        np.testing.assert_allclose(np.asarray(out), part.garment.vertices, atol=2e-6)


def test_rotating_one_bone_moves_only_vertices_it_weights(char):
    skel = char.skeleton
    bone = "lowerarm01.L"
    pose = character.pose_from_angles(skel, {bone: ((1.0, 0.3, 0.2), 0.8)})
    mats = character.skinning_matrices(skel, character.forward_kinematics(skel, pose))
    moved = np.linalg.norm(np.asarray(character.skin(
        jnp.asarray(char.base.mesh.vertices), char.weights, mats)) - char.base.mesh.vertices,
        axis=1) > 1e-5
    # The bone and its descendants (children follow their parent).
    subtree = {skel.index(bone)}
    for b, p in enumerate(skel.parents):
        if p in subtree:
            subtree.add(b)
    ids, w = np.asarray(char.weights.bone_ids), np.asarray(char.weights.weights)
    weighted = (np.isin(ids, list(subtree)) & (w > 0)).any(1)
    assert moved.sum() > 100
    assert not (moved & ~weighted).any()
    strong = (w * (ids == skel.index(bone))).sum(1) > 0.2
    assert moved[strong].all()


def test_capsules_contain_most_of_their_bone_vertices(char, walk):
    skel, body = char.skeleton, char.body
    bw = char.part_weights(body)
    caps = character.fit_capsules(skel, body.garment.vertices, bw)
    assert len(caps.names) == len(character.BODY_CAPSULE_BONES)
    dominant = np.asarray(bw.bone_ids)[:, 0]
    cap_of_bone = np.full(skel.num_bones, -1)
    cap_of_bone[np.asarray(caps.bone_ids)] = np.arange(len(caps.names))
    own = cap_of_bone[dominant]  # capsule of each vertex's dominant bone (-1: none)
    sel = own >= 0

    def contained(verts, ends):
        """Per capsule, the fraction of its bone's vertices inside it."""
        a, b = np.asarray(ends)[own[sel], 0], np.asarray(ends)[own[sel], 1]
        p = verts[sel]
        t = np.clip(np.sum((p - a) * (b - a), 1) / np.sum((b - a) ** 2, 1), 0, 1)
        inside = np.linalg.norm(p - a - t[:, None] * (b - a), axis=1) <= \
            np.asarray(caps.radii)[own[sel]] + 1e-6
        return np.bincount(own[sel], inside) / np.bincount(own[sel])

    mats0 = character.skinning_matrices(skel, character.forward_kinematics(
        skel, character.rest_pose(skel)))
    rest = contained(np.asarray(body.garment.vertices), character.pose_capsules(caps, mats0))
    assert rest.min() >= 0.75  # fitted with coverage 0.8
    _, world = walk(12.0)
    mats = character.skinning_matrices(skel, world)
    verts = np.asarray(character.skin(jnp.asarray(body.garment.vertices), bw, mats))
    ends = character.pose_capsules(caps, mats)
    posed = contained(verts, ends)
    assert np.median(posed) >= 0.75 and posed.min() >= 0.5
    # Posed capsules stay on their bones: the thigh capsule ends near the posed knee.
    knee = np.asarray(_tail(np.asarray(world), skel, "upperleg02.L"))
    assert np.linalg.norm(np.asarray(ends)[caps.names.index("upperleg02.L"), 1] - knee) < 0.1
    # Signed distance: -radius on the axis, the gap outside; the union takes the nearest.
    c = caps.names.index("head")
    a, b = np.asarray(ends)[c]
    out = b + 0.3 * (b - a) / np.linalg.norm(b - a) + np.array([0.05, 0.0, 0.0])
    d = np.asarray(jax.jit(character.capsule_distance)(jnp.asarray([0.5 * (a + b), out]),
                                                        ends[c:c + 1], caps.radii[c:c + 1]))
    r = float(caps.radii[c])
    np.testing.assert_allclose(d, [-r, np.linalg.norm(out - b) - r], atol=1e-5)
    union = character.capsule_distance(jnp.asarray([0.5 * (a + b)]), ends, caps.radii)
    assert float(union[0]) <= d[0] + 1e-6


# --------------------------------------------------------------------------------------------
# Keyframes, walk cycle and IK
# --------------------------------------------------------------------------------------------


def test_interpolated_curves_pass_through_their_keys(anim):
    curves = anim.curves
    times, values, n = (np.asarray(a) for a in (curves.times, curves.values, curves.num_keys))
    valid = np.arange(times.shape[1])[None] < n[:, None]
    key_times = np.unique(times[valid])
    at = np.asarray(jax.jit(jax.vmap(character.evaluate_curves, in_axes=(None, 0)))(
        curves, jnp.asarray(key_times)))  # (U, C)
    rows = np.searchsorted(key_times, times[valid])
    cols = np.nonzero(valid)[0]
    np.testing.assert_allclose(at[rows, cols], values[valid], atol=1e-5)
    # Between keys the curves move (they are not stuck at a key value).
    mid = np.asarray(character.evaluate_curves(curves, 2.5))
    assert np.abs(mid - values[:, 0]).max() > 1e-3


def test_bezier_and_auto_clamped_handles():
    # Handles a third of the way along a straight line: the Bezier curve is that line.
    lin = character.make_curves([[
        {"frame": 0.0, "value": 0.0, "handle_right": [2.0, 1.0], "handle_left": [-2.0, -1.0]},
        {"frame": 6.0, "value": 3.0, "handle_left": [4.0, 2.0], "handle_right": [8.0, 4.0]}]])
    for t in (0.0, 1.5, 3.0, 4.5, 6.0):
        assert float(character.evaluate_curves(lin, t)[0]) == pytest.approx(t / 2, abs=1e-5)
    assert float(character.evaluate_curves(lin, 9.0)[0]) == pytest.approx(3.0)  # constant
    # Auto-clamped: no overshoot between keys, flat at extrema and ends.
    t = np.array([0.0, 5.0, 10.0, 20.0])
    v = np.array([0.0, 1.0, 1.2, -1.0])
    curves = character.make_curves([[{"frame": a, "value": b} for a, b in zip(t, v,
                                                                                strict=True)]])
    s = np.linspace(0, 20, 81)
    vals = np.asarray(jax.vmap(lambda x: character.evaluate_curves(curves, x))(s))[:, 0]
    assert vals.max() <= 1.2 + 1e-5 and vals.min() >= -1.0 - 1e-5
    left, right = character.auto_clamped_handles(t, v)
    assert left[2, 1] == right[2, 1] == 1.2 and right[0, 1] == 0.0
    np.testing.assert_allclose(right[:, 0] - t, np.r_[np.diff(t), 10.0] / 3)


def test_walk_cycle_format(anim, char):
    skel = char.skeleton
    animated = {skel.names[b] for b, _, _ in anim.target}
    assert {"root", "left_foot_ik", "right_hand_ik", "spine03"} <= animated
    assert anim.start == 0.0 and anim.end == 40.0 and anim.quaternion_bones == ()
    # The root carries the walk forward (-Y), horizontally.
    travel = np.asarray(skel.rest)[skel.index("root"), :3, :3] @ np.asarray(
        anim.cycle_offset)[skel.index("root")]
    assert travel[1] < -0.6 and abs(travel[2]) < 1e-6


def test_walk_ik_reaches_targets_and_bends_knees_forward(char, walk):
    skel = char.skeleton
    for t in (0.0, 7.0, 13.5, 33.0, 61.0):
        pose, world = walk(t)
        world = np.asarray(world)
        for side in ("left", "right"):
            s = side[0].upper()
            ankle = _tail(world, skel, f"lowerleg02.{s}")
            goal = world[skel.index(f"{side}_foot_ik"), :3, 3]
            assert np.linalg.norm(ankle - goal) < 2e-3, (t, side)
            # The knee lies in front of the hip-ankle line (character faces -Y).
            hip = world[skel.index(f"upperleg01.{s}"), :3, 3]
            knee = _tail(world, skel, f"upperleg02.{s}")
            assert knee[1] <= 0.5 * (hip[1] + ankle[1]) + 0.01
            # The foot copies the IK target's rotation.
            np.testing.assert_allclose(world[skel.index(f"foot.{s}"), :3, :3],
                                       world[skel.index(f"{side}_foot_ik"), :3, :3], atol=1e-5)
            wrist = world[skel.index(f"wrist.{s}"), :3, 3]
            hand_goal = world[skel.index(f"{side}_hand_ik"), :3, 3]
            assert np.linalg.norm(wrist - hand_goal) < 2e-3
        assert np.isfinite(np.asarray(pose.rotations)).all()


def test_walk_is_continuous_across_cycles(char, walk):
    skel = char.skeleton
    names = ("root", "foot.L", "foot.R", "wrist.L", "head")
    ids = [skel.index(n) for n in names]
    heads = [np.asarray(walk(t)[1])[ids, :3, 3] for t in (39.95, 40.0, 40.05)]
    assert np.abs(heads[1] - heads[0]).max() < 0.01 and np.abs(heads[2] - heads[1]).max() < 0.01
    # After one cycle the root has advanced by the stride and is back at the same height.
    r0, r1 = (np.asarray(walk(t)[1])[skel.index("root"), :3, 3] for t in (3.0, 43.0))
    assert r1[1] - r0[1] < -0.6 and abs(r1[2] - r0[2]) < 1e-4


def test_lbs_frame_is_finite_with_garment_topology(char, walk):
    skel = char.skeleton
    mats = character.skinning_matrices(skel, walk(17.0)[1])
    body = np.asarray(character.skin(jnp.asarray(char.body.garment.vertices),
                                     char.part_weights(char.body), mats))
    for part in char.garments.values():
        g = part.garment
        frame = np.asarray(character.skin(jnp.asarray(g.vertices), char.part_weights(part),
                                          mats))
        assert frame.shape == (g.num_vertices, 3) and np.isfinite(frame).all()
        seq = meshio.make_sequence(frame[None], g.replace(vertices=frame), source=part.name)
        np.testing.assert_array_equal(seq.garment.faces, g.faces)
        # No exploded triangles. LBS does distort a few edges: the skirt's seam between the
        # legs, the tights' crotch and toes (expected of coarse skinned input).
        e = np.asarray(g.faces)[:, :2]
        ratio = np.linalg.norm(frame[e[:, 0]] - frame[e[:, 1]], axis=1) / np.linalg.norm(
            np.asarray(g.vertices)[e[:, 0]] - np.asarray(g.vertices)[e[:, 1]], axis=1)
        assert ratio.max() < 6.0 and np.mean((ratio < 0.5) | (ratio > 2.0)) < 0.02
        # The garment travels with the body.
        assert np.linalg.norm(frame.mean(0)[:2] - body.mean(0)[:2]) < 0.1


def test_lbs_is_jittable_and_vmap_equals_loop(char, anim, walk):
    skel = char.skeleton
    part = char.garments["helper-skirt"]
    weights = char.part_weights(part)
    verts = jnp.asarray(part.garment.vertices)
    times = jnp.asarray([0.0, 9.5, 41.0])
    mats = jax.jit(lambda t: character.walk_skinning_matrices(anim, skel, t))(times)
    frames = jax.jit(character.skin_frames)(verts, weights, mats)
    skin1 = jax.jit(character.skin)
    for k, t in enumerate(np.asarray(times)):
        m = character.skinning_matrices(skel, walk(t)[1])
        np.testing.assert_allclose(np.asarray(mats[k]), np.asarray(m), atol=2e-5)
        np.testing.assert_allclose(np.asarray(frames[k]), np.asarray(skin1(verts, weights, m)),
                                   atol=2e-5)


def test_procedural_gait_pose(char):
    skel = char.skeleton
    fk = jax.jit(lambda phase: character.forward_kinematics(
        skel, character.gait_pose(skel, phase)))
    w0, w1 = np.asarray(fk(np.pi / 2)), np.asarray(fk(-np.pi / 2))
    rest = np.asarray(skel.rest)
    knee = skel.index("lowerleg01.L")
    # Left thigh forward (-Y) at phase pi/2, backward at -pi/2.
    assert w0[knee, 1, 3] < rest[knee, 1, 3] - 0.05 < w1[knee, 1, 3] - 0.05
    # Bones outside the driven chains stay at rest.
    for name in ("pelvis.L", "root", "left_foot_ik"):
        np.testing.assert_allclose(w0[skel.index(name)], rest[skel.index(name)], atol=1e-5)
