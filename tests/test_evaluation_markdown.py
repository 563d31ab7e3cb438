"""wrinkle_jax.evaluation.markdown: the report's line collector."""

import json

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
