"""wrinkle_jax.evaluation.headlines: the report's headline rows from stored results (pure
text; no JAX)."""

import pytest

from wrinkle_jax.evaluation import headlines


def test_score_text_and_relative_drop():
    d = {"n": 3, "signed_mean": -4.25, "improvement_mean": 7.04}
    assert headlines.score_text(d) == "-4.2" and headlines.score_text(d, False) == "7.0"
    assert headlines.score_text({"n": 0}) == "-" and headlines.score_text(None) == "-"
    right, wrong = {"signed_mean": 40.0}, {"signed_mean": 38.0}
    assert headlines.relative_drop(right, wrong, "signed_mean") == pytest.approx(5.0)
    assert headlines.relative_drop({"signed_mean": -40.0}, wrong, "signed_mean") == (
        pytest.approx(-195.0))  # relative to |right|: a gain from a negative score is negative
    assert headlines.relative_drop({"signed_mean": 0.0}, wrong, "signed_mean") is None
    assert headlines.relative_drop({}, wrong, "signed_mean") is None


def test_ladder_headline_lists_each_rung_of_the_named_model():
    def rung(med, lo, hi):
        return {"methods": {"run7b": {"vs_unsharp_material": {
            "n": 160, "median_diff": med, "median_diff_ci": [lo, hi]}}}}

    rows = headlines.ladder_headline({"val_seen7b": rung(13.5, 9.1, 17.2),
                                      "val_newmotion": None,
                                      "val_newgarment": rung(21.9, 12.9, 33.2)})
    assert len(rows) == 1
    assert "later frames of its training garments +13.5 [+9.1, +17.2]" in rows[0]
    assert "two garments it never saw +21.9 [+12.9, +33.2]" in rows[0]
    assert "motion" not in rows[0].split("two garments")[0]  # the missing rung is left out
    assert headlines.ladder_headline({}) == []
    assert headlines.ladder_headline({"val_seen7b": rung(1, 0, 2)}, model="other") == []


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
        methods[headlines.VALIDATED] = model(40.0)
    rows = headlines.fidelity_headline({"unseen garment": {"methods": methods}})
    assert len(rows) == 2 and "shipped enhancer" in rows[0] and "**+31.0**" in rows[0]
    assert "weak" not in rows[1]
    if present:  # the validated candidate, not the better-scoring "other"
        assert "**+40.0**" in rows[1] and "validated" in rows[1]
    else:
        assert "**+50.0**" in rows[1] and "post hoc" in rows[1]


def test_report_ship_test_headline_states_the_paired_differences_of_the_stored_candidate():
    def pd(med, lo, hi):
        return {"n": 640, "median_diff": med, "median_diff_ci": [lo, hi]}

    ship = {"unseen garment": {"methods": {
        "identity": {"detail": {"n": 640}},
        "unsharp_material": {"detail": {"vs_unsharp_card": pd(18.5, 15.5, 21.2)}},
        "run7b": {"detail": {"n": 640, "vs_unsharp_material": pd(0.7, -2.9, 2.8),
                             "vs_unsharp_card": pd(10.6, 7.1, 15.8)}}}}}
    rows = headlines.ship_test_headline(ship)
    assert len(rows) == 1  # one row per model, none for the baselines
    assert "(run7b)" in rows[0] and "640 new held-out patches" in rows[0]
    assert "+0.7 [-2.9, +2.8]" in rows[0] and "+10.6 [+7.1, +15.8]" in rows[0]
    assert "+18.5 [+15.5, +21.2]" in rows[0]
    assert headlines.ship_test_headline(None) == [] and headlines.ship_test_headline({}) == []
    ship["unseen garment"]["methods"]["shipped"] = {"detail": {
        "n": 640, "signed_median": 30.0, "vs_unsharp_material": pd(-9.0, -12.0, -6.0),
        "vs_unsharp_card": pd(-1.0, -3.0, 1.0)}}
    rows = headlines.ship_test_headline(ship)
    assert len(rows) == 2 and "(run7b)" in rows[0]  # the shipped model is reported apart
    assert "median +30.0" in rows[1] and "-9.0 [-12.0, -6.0]" in rows[1]


def test_report_table2_detail_headline_gives_means_medians_and_the_oracles_as_ceilings():
    def cell(group, model, oracle):
        def m(e, f):
            return {"embedded": {"dr_signed": e}, "full": {"dr_signed": f}}
        return {"group": group, "methods": {"identity": m(0.0, 0.0), "model": m(*model),
                                            "oracle fine": m(*oracle)}}

    t2d = {"methods": ["identity", "model", "oracle fine"],
           "by_group": {"unseen garment": {"model": {}}},
           "cells": {"a": cell("unseen garment", (10.0, -2.0), (40.0, 1.0)),
                     "b": cell("unseen garment", (-100.0, -4.0), (20.0, 3.0)),
                     "c": cell("unseen garment", (30.0, 0.0), (30.0, 5.0)),
                     "d": cell("seen garment", (99.0, 99.0), (99.0, 99.0))}}
    rows = headlines.table2_detail_headline(t2d)
    assert len(rows) == 1 and "3 unseen-garment cells" in rows[0]
    assert "model -20.0 (+10.0) / -2.0 (-2.0)" in rows[0]  # mean (median) over cells
    head, ceilings = rows[0].split("Ceilings")
    assert "oracle fine" not in head and "identity" not in head
    assert "oracle fine +30.0 (+30.0) / +3.0 (+3.0)" in ceilings
    assert headlines.table2_detail_headline(None) == []


def test_table1_headline_names_the_best_baseline_by_each_form_and_the_wrong_material_cost():
    s = lambda signed, absolute, n=10: {"n": n, "signed_mean": signed,  # noqa: E731
                                        "improvement_mean": absolute}
    kind = {headlines.MODEL: s(20.0, 30.0), headlines.WRONG: s(5.0, 25.0),
            "identity": s(0.0, 0.0), "unsharp": s(22.0, 28.0), "bicubic": s(0.5, 31.0),
            "patchgan": s(-3.0, 35.0)}
    t1 = {"by_kind": {"unseen garment": kind},
          "all": {headlines.MODEL: s(40.0, 45.0), headlines.WRONG: s(38.0, 44.0)}}
    rows = headlines.table1_headline(t1)
    assert rows[0] == ("- Table 1, unseen garments (10 patches): model signed mean +20.0 "
                       "(paper's |.| form 30.0); best baseline by signed mean unsharp +22.0 "
                       "(|.| 28.0), by |.| patchgan 35.0 (signed -3.0).")
    assert rows[1] == "- Table 1, unseen garments: PatchGAN signed mean -3.0 (|.| 35.0)."
    assert rows[2] == ("- Wrong material at inference (all cells): signed mean +40.0 -> +38.0 "
                       "(+2.0 points lost; 5.0 % drop; the paper saw about a 5 % drop).")
    # Near 0 a relative drop is not stated.
    t1["all"] = {headlines.MODEL: s(4.0, 9.0), headlines.WRONG: s(3.0, 9.0)}
    assert "meaningless" in headlines.table1_headline(t1)[2]
    assert headlines.table1_headline(None) == []
    # With paired differences stored, the robust row leads.
    kind[headlines.MODEL]["signed_median"] = 12.34
    d = {"n": 10, "median_diff": 0.4, "median_diff_ci": (-0.04, 0.7), "mean_diff": -2.1}
    t1["paired_vs_unsharp"] = {"unseen garment": {headlines.MODEL: {"unsharp": d}}}
    rows = headlines.table1_headline(t1)
    assert rows[0] == ("- **Table 1, unseen garments** (10 patches): model signed median +12.3; "
                       "paired median difference (95 % bootstrap) against unsharp +0.4 "
                       "[-0.0, +0.7] (mean -2.1).")
    assert rows[1].startswith("- Table 1, unseen garments (10 patches): model signed mean")


def test_table2_headline_gives_the_models_unseen_garment_row_or_nothing():
    m = {"embedded": {"c1": 0.1234, "c2": 0.5, "dr": 14.8, "dr_signed": -2.04},
         "full": {"dr": 0.8, "dr_signed": 0.75}}
    t2 = {"by_group": {"unseen garment": {headlines.MODEL: m}}}
    assert headlines.table2_headline(t2) == [
        "- Table 2, unseen garments (model, mean over cells): embedded C1 0.123, C2 0.500, "
        "DR 14.8 (signed -2.0); full space DR 0.8 (signed +0.8)."]
    assert headlines.table2_headline({"by_group": {}}) == []
    assert headlines.table2_headline(None) == []
