"""benchmarks/bench_ceiling.py's arithmetic: the ceilings it prints from a timing run, on
synthetic times (the benchmark itself is timed in `make bench`)."""

import importlib.util
import json
from pathlib import Path

import pytest

from wrinkle_jax import roofline, timing


@pytest.fixture(scope="module")
def ceiling():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_ceiling.py"
    spec = importlib.util.spec_from_file_location("bench_ceiling", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _dot(m, k, n):
    return roofline.Dot((m, k), (k, n), (m, n), (1, 0), (1, 0), "bf16", "bf16", "f32", (1,),
                        (0,))


def test_summary_ceilings_follow_from_the_times(ceiling):
    m, k, n = ceiling.PEAK_SHAPE
    peak_s = 2 * m * k * n / 400e9  # a 400 GFLOP/s machine, best round
    rounds = {"peak_bf16": [peak_s * 1.1, peak_s], "peak_f32": [2 * peak_s, 2 * peak_s],
              "f_program": [0.30, 0.20], "f_dots": [0.10, 0.10]}
    t = timing.Timing(rounds, rounds, 2, 1.0, 1.0)
    dots = [_dot(1000, 1000, 1000)] * 4  # 8 GFLOP
    got = ceiling.summarize(t, {"f": (None, dots)}, {"f": 2.0}, 3.0)
    assert got["peak_gflops_per_s"] == {"peak_bf16": 400.0, "peak_f32": 200.0}
    r = got["forms"]["f"]
    assert r["dot_gflop"] == 8.0 and r["dots_share"] == 0.1 / 0.25
    assert r["ceiling_gain_dots"] == 2.5  # median of the per-round ratios 3 and 2
    assert r["ceiling_gain_peak"] == pytest.approx(0.25 / (8 / 400))
    assert r["ceiling_speedup_vs_authors_dots"] == 5.0
    assert r["ceiling_speedup_vs_authors_peak"] == pytest.approx(2.0 * 12.5, abs=0.01)
    # no stored ratio for a form: no ceiling against the authors
    assert "ceiling_speedup_vs_authors_dots" not in ceiling.summarize(
        t, {"f": (None, dots)}, {}, 3.0)["forms"]["f"]


def test_stored_speedups_read_bench_reference_output(ceiling, tmp_path):
    p = tmp_path / "ref.json"
    p.write_text(json.dumps({"unet": {"speedup_vs_authors_wall": {"ours_winograd_bf16": 2.0}}}))
    assert ceiling.stored_speedups(str(p), "unet") == {"winograd_bf16": 2.0}
    assert ceiling.stored_speedups(str(p), "train") == {}
    assert ceiling.stored_speedups(str(tmp_path / "missing.json"), "unet") == {}
