"""Tests for experiments.self_collision_cull_study on two parallel sheets whose gap closes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments import self_collision_cull_study as study


def _sheets(path, gaps):
    n, h = 12, 0.01
    g = np.stack(np.meshgrid(np.arange(n) * h, np.arange(n) * h, indexing="ij"), -1)
    g = g.reshape(-1, 2)
    idx = np.arange(n * n).reshape(n, n)
    quads = [(idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1])
             for i in range(n - 1) for j in range(n - 1)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int32)
    faces = np.concatenate([f, f + n * n])
    uvs = np.concatenate([g, g + [1.0, 0.0]]).astype(np.float32)  # the panels apart at rest
    frames = np.stack([np.concatenate([np.c_[g, np.zeros(n * n)], np.c_[g, np.full(n * n, z)]])
                       for z in gaps]).astype(np.float32)
    np.savez(path, frames=frames, faces=faces, uvs=uvs, uv_faces=faces,
             panels=np.repeat(np.arange(2, dtype=np.int32), len(f)))


def test_two_sheets_closing_in(tmp_path):
    seq, out = tmp_path / "s.npz", tmp_path / "o.json"
    _sheets(seq, [0.008, 0.005])  # 8 mm apart, then 5 mm: near (< 6 mm) only at t + 1
    assert study.main([str(seq), "--poses", "0", "--cluster-faces", "60", "--out", str(out)]) == 0
    row = json.loads(out.read_text())["poses"][0]
    assert row["within_thickness_plus_2mm"] == 0
    assert row["within_reach"] >= 2 * 144  # every vertex sees the other sheet within 18 mm
    assert row["near_at_t+1"] >= 2 * 144
    assert row["approach_per_frame_m"]["max"] == pytest.approx(0.003, abs=2e-5)
    assert row["approach_per_frame_m"]["p50"] == pytest.approx(0.003, abs=2e-5)
    # the sheets' clusters are not rest-adjacent: the cull keeps them, nothing is missed
    assert row["reach_pairs_covered"] == 1.0 and row["near_pairs_missed"] == 0
    assert row["cluster_pairs_kept"] >= 1


def test_a_flat_sheet_culls_its_own_clusters(tmp_path):
    seq, out = tmp_path / "s.npz", tmp_path / "o.json"
    _sheets(seq, [0.5, 0.5])  # the second sheet far away
    study.main([str(seq), "--poses", "0", "--cluster-faces", "60", "--out", str(out)])
    row = json.loads(out.read_text())["poses"][0]
    assert row["within_thickness_plus_2mm"] == 0 and row["near_at_t+1"] == 0
    assert row["approach_per_frame_m"] is None
    # flat: every rest-adjacent pair of clusters has a zero normal cone and is culled
    assert row["adjacent_culled_by_cone"] == row["of_which_rest_adjacent"] > 0
    assert row["clusters_tested_against_themselves"] == 0
