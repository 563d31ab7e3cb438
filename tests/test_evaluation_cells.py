"""Tests for the evaluation cells: scenes, sequences, resumable runs
(`wrinkle_jax.evaluation.cells`)."""

from __future__ import annotations

import pytest

from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.sim import scenes, selfcollision


def test_run_cells_reuses_by_source_adds_missing_methods_and_upgrades_legacy_files(tmp_path):
    cells = cell_lib.table_cells(["dress"], ["silk_charmeuse"], ["dance", "walk"])
    a, b = cells
    store = {  # a: legacy file with m1 only; b: current file with m1 from another source
        a.key: {"loss": {"m1": 1}, "sources": {"m1": "m1"}, "legacy": True, "timings": {}},
        b.key: {"loss": {"m1": 1, "m2": 2}, "sources": {"m1": "old", "m2": "m2"},
                "legacy": False, "timings": {"cell_s": 5.0}}}
    saved, evaluated = {}, []

    def evaluate(cell, names, progress):
        evaluated.append((cell.key, list(names)))
        if progress is not None:
            progress(1, "step")
        return {"loss": {n: 10 for n in names}, "timings": {}}

    def merge(old, new, order):
        if new.get("bad"):
            raise ValueError
        return {**old, "loss": {**old["loss"], **new["loss"]}, "timings": dict(old["timings"])}

    common = dict(path_of=lambda c: tmp_path / c.key.replace("/", "_"),
                  fingerprint_of=lambda c: {}, load=lambda p, f: next(
                      v for k, v in store.items() if k.replace("/", "_") == p.name),
                  save=lambda p, r, f, src: saved.__setitem__(p.name, (r, src)),
                  evaluate=evaluate, merge=merge, field="loss", units=lambda n: 1, unit="x",
                  log=lambda m: None)
    got = cell_lib.run_cells(cells, {"m1": None}, None, **common)
    assert evaluated == [(b.key, ["m1"])]  # b's m1 came from another source
    assert got[a.key]["loss"] == {"m1": 1} and got[b.key]["loss"] == {"m1": 10}
    name_a = a.key.replace("/", "_")
    assert saved[name_a][1] == {"m1": "m1"}  # the legacy file was rewritten with its sources
    evaluated.clear()
    got = cell_lib.run_cells(cells, {"m1": None, "m3": None}, {"m1": "m1", "m3": "s3"}, **common)
    assert (a.key, ["m3"]) in evaluated and got[a.key]["loss"] == {"m1": 1, "m3": 10}
    assert saved[name_a][1] == {"m1": "m1", "m3": "s3"}
    evaluated.clear()
    cell_lib.run_cells(cells, {"m1": None}, None, **common, fresh=True)
    assert evaluated == [(a.key, ["m1"]), (b.key, ["m1"])]
    # Patches that no longer match the stored ones: every method is evaluated again.
    evaluated.clear()

    def refuse(old, new, order):
        raise ValueError("different patches")

    cell_lib.run_cells(cells[:1], {"m1": None, "m4": None}, None, **{**common, "merge": refuse})
    assert evaluated == [(a.key, ["m4"]), (a.key, ["m1", "m4"])]


def test_scene_for_reuses_existing_scenes_and_derives_new_ones():
    assert cell_lib.scene_for("dress", "dance") is scenes.SCENES["dress_dance"]
    assert cell_lib.scene_for("flared_skirt", "walk") is scenes.SCENES["skirt_walk"]
    cape = cell_lib.scene_for("cape", "dance")
    base = scenes.SCENES["cape_walk"]
    assert cape.name == "cape_dance" and cape.motion == "dance"
    assert (cape.pins, cape.attach_to, cape.preroll_s) == (base.pins, base.attach_to, 2.0)
    kinds = {c.key: c.kind for c in cell_lib.table_cells()}
    assert len(kinds) == 12
    assert kinds["skirt_dance/denim_light"] == "seen garment, seen motion"
    assert kinds["skirt_walk/denim_light"] == "seen garment, unseen motion"
    assert kinds["cape_dance/silk_charmeuse"] == "unseen garment"


def test_find_or_simulate_reuses_only_files_of_the_data_sets_solver_settings(tmp_path,
                                                                            monkeypatch):
    import dataclasses

    from evaluation_fixtures import write_cell_files

    from wrinkle_jax import meshio

    write_cell_files(tmp_path, "dress", "dance", "silk_charmeuse")
    sc = cell_lib.scene_for("dress", "dance")
    for res in ("fine", "coarse"):
        p, info = cell_lib.find_or_simulate(sc, "silk_charmeuse", res, cell_lib.TEST_SEED, 3,
                                            [tmp_path], tmp_path / "new")
        assert info["source"] == "reused" and p.parent.parent == tmp_path
    # The same coarse file at the scenes' own 20 substeps, or without self-collision: not the
    # data set's recipe, so it must not be reused.
    path = cell_lib.sequence_file(tmp_path, sc.name, "silk_charmeuse", "coarse",
                                  cell_lib.TEST_SEED)
    solver = scenes.dataset_solver(sc, "coarse")
    seq = meshio.load_sequence(path)
    assert cell_lib.stored_matches(path, sc, "silk_charmeuse", cell_lib.TEST_SEED, 3, solver)
    for change in ({"substeps": 20}, {"self_collision": None},
                   {"self_collision": dataclasses.asdict(scenes.SELF_COLLISION["coarse"])}):
        meshio.save_sequence(path, meshio.make_sequence(
            seq.frames, seq.garment, metadata={**seq.metadata, **change}))
        assert not cell_lib.stored_matches(path, sc, "silk_charmeuse", cell_lib.TEST_SEED, 3,
                                           solver), change
        # Without settings to check (the old rule) the file still matches.
        assert cell_lib.stored_matches(path, sc, "silk_charmeuse", cell_lib.TEST_SEED, 3)
    # A setting added after the file was written takes its default (the old behaviour), so the
    # file still matches while the default is what the data set uses; a setting the config
    # lacks, or one missing whose default differs, does not.
    rec = dataclasses.asdict(solver[1])
    assert rec["post_passes"] == 1 and rec["block"] != 0  # the coarse recipe: default, not
    for recorded, same in (({k: v for k, v in rec.items() if k != "post_passes"}, True),
                           ({k: v for k, v in rec.items() if k != "block"}, False),
                           ({**rec, "no_such_setting": 1}, False)):
        meshio.save_sequence(path, meshio.make_sequence(
            seq.frames, seq.garment, metadata={**seq.metadata, "self_collision": recorded}))
        assert cell_lib.stored_matches(path, sc, "silk_charmeuse", cell_lib.TEST_SEED, 3,
                                       solver) is same, recorded
    assert selfcollision.recorded_config(None) is None
    with pytest.raises(ValueError, match="no_such_setting"):
        selfcollision.recorded_config({**rec, "no_such_setting": 1})
    # find_or_simulate then simulates anew, with the data set's settings.
    calls = []

    class Done(Exception):
        pass

    def fake_simulate(*args, **kwargs):
        calls.append(kwargs)
        raise Done

    monkeypatch.setattr(cell_lib.scenes, "simulate", fake_simulate)
    try:
        cell_lib.find_or_simulate(sc, "silk_charmeuse", "coarse", cell_lib.TEST_SEED, 3,
                                  [tmp_path], tmp_path / "new", log=lambda m: None)
    except Done:
        pass
    assert len(calls) == 1
    assert (calls[0]["substeps"], calls[0]["self_collision"]) == solver

