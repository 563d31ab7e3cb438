"""wrinkle_jax.evaluation.markdown: the report's line collector, and experiments.report's
validation-ladder headline."""

import json

import pytest

from experiments import report
from wrinkle_jax.evaluation import markdown


def test_report_loads_once_and_names_the_command_of_a_missing_result(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "results.json").write_text(json.dumps(
        {"x": 1, "command": "python -m make_a", "machine": {"cpu_count": 2}}))
    (tmp_path / "bad.json").write_text("{not json")
    rep = markdown.Report(tmp_path, {"a": "cmd a", "b": "python -m make_b", "bad": "cmd bad"})
    got = rep.load("a", "a/results.json")
    assert got == {"x": 1, "command": "python -m make_a", "machine": {"cpu_count": 2}}
    (tmp_path / "a" / "results.json").write_text(json.dumps({"x": 2}))
    assert rep.load("a", "a/results.json")["x"] == 1  # read once per report
    assert rep.commands["a"] == "python -m make_a" and rep.machines["a"] == {"cpu_count": 2}
    assert rep.load("b", "b/results.json") is None
    assert rep.load("bad", "bad.json") is None
    assert rep.missing[0] == ("b", "python -m make_b")
    assert rep.missing[1][0] == "bad" and "unreadable" in rep.missing[1][1]
    rep.not_run("thing B", "b")
    assert rep.lines[-2] == "**Not run yet**: thing B. Command: `python -m make_b`."
    rep.image("a/missing.png", "x")  # no file: no line
    assert rep.lines[-1] == ""


def test_demote_and_ci():
    assert markdown.demote("# A\n## B\ntext # no", 2) == "### A\n#### B\ntext # no"
    d = {"n": 10, "median_diff": 1.26, "median_diff_ci": [-0.5, 3.0]}
    assert markdown.ci(d) == "+1.3 [-0.5, +3.0]"
    assert markdown.ci({"n": 0}) == "" and markdown.ci(None) == ""


def test_ladder_headline_lists_each_rung_of_the_named_model():
    def rung(med, lo, hi):
        return {"methods": {"run7b": {"vs_unsharp_material": {
            "n": 160, "median_diff": med, "median_diff_ci": [lo, hi]}}}}

    rows = report.ladder_headline({"val_seen7b": rung(13.5, 9.1, 17.2),
                                   "val_newmotion": None,
                                   "val_newgarment": rung(21.9, 12.9, 33.2)})
    assert len(rows) == 1
    assert "later frames of its training garments +13.5 [+9.1, +17.2]" in rows[0]
    assert "two garments it never saw +21.9 [+12.9, +33.2]" in rows[0]
    assert "motion" not in rows[0].split("two garments")[0]  # the missing rung is left out
    assert report.ladder_headline({}) == []
    assert report.ladder_headline({"val_seen7b": rung(1, 0, 2)}, model="other") == []


@pytest.mark.parametrize("present", [True, False])
def test_fidelity_headline_names_the_validated_candidate_else_says_post_hoc(present):
    def model(med):
        return {"detail": {"n": 8, "signed_median": med, "signed_mean": med,
                           "vs_unsharp_card": {"n": 8, "median_diff": med - 30,
                                               "median_diff_ci": [0.0, 1.0]}}}

    methods = {"unsharp": {"detail": {"signed_median": 20.0}},
               "unsharp_card": {"detail": {"signed_median": 30.0}},
               "shipped": model(31.0), "other": model(50.0), "weak": model(35.0)}
    if present:
        methods[report.VALIDATED] = model(40.0)
    rows = report.fidelity_headline({"unseen garment": {"methods": methods}})
    assert len(rows) == 2 and "shipped enhancer" in rows[0] and "**+31.0**" in rows[0]
    assert "weak" not in rows[1]
    if present:  # the validated candidate, not the better-scoring "other"
        assert "**+40.0**" in rows[1] and "validated" in rows[1]
    else:
        assert "**+50.0**" in rows[1] and "post hoc" in rows[1]
