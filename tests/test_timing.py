"""wrinkle_jax.timing: alternating same-run timing, checked with fake clocks of known cost."""

import jax.numpy as jnp
import pytest

from wrinkle_jax import timing


class FakeMachine:
    """Clocks advanced only by fake workloads: the k-th timed call of a job of cost c takes
    c * load[k] seconds of wall time and c seconds of CPU time; its warm-up calls cost
    `warm` (large, so a timed warm-up would show)."""

    def __init__(self, load, warmup, warm=100.0):
        self.wall = 0.0
        self.cpu = 0.0
        self.load, self.warmup, self.warm = load, warmup, warm
        self.calls = []  # (name, round or None for a warm-up)
        self.blocked = []

    def job(self, name, cost):
        def run():
            n = sum(1 for c in self.calls if c[0] == name)
            r = n - self.warmup if n >= self.warmup else None
            self.calls.append((name, r))
            self.wall += self.warm if r is None else cost * self.load[r]
            self.cpu += self.warm if r is None else cost
            return (name, r)
        return run

    def alternate(self, costs):
        return timing.alternate({k: self.job(k, c) for k, c in costs.items()},
                                reps=len(self.load), warmup=self.warmup,
                                block=self.blocked.append, wall_clock=lambda: self.wall,
                                cpu_clock=lambda: self.cpu, loadavg=lambda: 1.5)


def test_ratios_are_exact_under_drifting_load_and_medians_follow_the_load():
    load = [1.0, 7.0, 1.5, 3.0, 1.0]
    m = FakeMachine(load, warmup=1)
    t = m.alternate({"a": 2.0, "b": 1.0, "c": 0.5})
    # Per-round ratios cancel the load exactly, whatever it does between rounds.
    assert t.ratio("a", "b") == pytest.approx(2.0)
    assert t.ratio("c", "b") == pytest.approx(0.5)
    assert t.ratios("b") == pytest.approx({"a": 2.0, "b": 1.0, "c": 0.5})
    # Medians of the separate times carry the median load (1.5) ...
    assert t.wall["a"] == pytest.approx(2.0 * 1.5)
    assert t.wall_rounds["a"] == pytest.approx([2.0 * x for x in load])
    # ... the CPU clock saw the unloaded cost, and the warm-up calls (cost 100) are untimed.
    assert t.cpu == pytest.approx({"a": 2.0, "b": 1.0, "c": 0.5})
    assert t.ratio("a", "b", clock="cpu") == pytest.approx(2.0)
    assert t.reps == 5 and t.load_before == 1.5 and t.load_after == 1.5


def test_calls_alternate_after_the_warmup_and_every_result_is_blocked():
    m = FakeMachine([1.0, 1.0, 1.0], warmup=2)
    m.alternate({"a": 1.0, "b": 1.0})
    # Warm-up: each callable `warmup` times, untimed; then rounds a b a b a b.
    assert m.calls[:4] == [("a", None), ("a", None), ("b", None), ("b", None)]
    assert m.calls[4:] == [("a", 0), ("b", 0), ("a", 1), ("b", 1), ("a", 2), ("b", 2)]
    assert m.blocked == m.calls  # every result, warm-up included, went through `block`


def test_to_json_reports_ms_ratios_and_load():
    t = FakeMachine([1.0, 2.0, 1.0], warmup=1).alternate({"new": 0.004, "old": 0.008})
    j = t.to_json(baseline="old")
    assert j["median_cpu"] == {"new": 4.0, "old": 8.0}
    assert j["ratio_wall"] == {"new": 0.5, "old": 1.0}
    assert j["ratio_to"] == "old" and j["reps"] == 3
    assert j["load_avg_1m"] == {"before": 1.5, "after": 1.5}
    assert t.to_json()["ratio_to"] == "new"  # default: the first name


def test_default_block_waits_on_jax_arrays_and_bad_arguments_raise():
    t = timing.alternate({"x": lambda: jnp.ones(3) * 2}, reps=2)
    assert t.wall["x"] >= 0 and t.cpu["x"] >= 0 and len(t.wall_rounds["x"]) == 2
    with pytest.raises(ValueError):
        timing.alternate({}, reps=2)
    with pytest.raises(ValueError):
        timing.alternate({"x": lambda: 1}, reps=0)
