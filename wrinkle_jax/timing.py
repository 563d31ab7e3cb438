"""Same-run ratio timing: alternate several callables so that load drifts hit all alike.

On a shared machine the absolute time of a call moves with the load; the ratio of two
variants timed in one run, interleaved (A B C A B C ...), moves much less. `alternate` is the
one helper the benchmarks use for this:

    t = alternate({"new": f, "old": g}, reps=5)
    t.wall["new"], t.cpu["new"]          # median seconds per call
    t.ratio("new", "old")                # median over rounds of new / old (wall clock)

Every callable takes no argument; its result is passed to `block` (default
`jax.block_until_ready`) inside the timed interval, so asynchronous dispatch is not mistaken
for speed. Each is called `warmup` times first (compilation, caches), untimed.

Ratios are the median over rounds of the per-round ratio (each round times every callable
once, back to back): a round shares its load, so a slow round inflates both terms alike.
Medians of the separate times are reported beside them.
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import time
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["Timing", "alternate", "load_average"]


def load_average() -> float | None:
    """The 1-minute load average, or None where the OS does not report it."""
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def _block(x):
    import jax

    return jax.block_until_ready(x)


@dataclasses.dataclass(frozen=True)
class Timing:
    """What `alternate` measured.

    Attributes:
      wall_rounds, cpu_rounds: name -> the per-round seconds, in round order (wall clock;
        process CPU time of all threads, the steadier number under load).
      reps: timed rounds. load_before, load_after: 1-minute load average around the run.
    """

    wall_rounds: dict
    cpu_rounds: dict
    reps: int
    load_before: float | None
    load_after: float | None

    @property
    def wall(self) -> dict:
        """name -> median wall seconds per call."""
        return {k: statistics.median(v) for k, v in self.wall_rounds.items()}

    @property
    def cpu(self) -> dict:
        """name -> median CPU seconds per call."""
        return {k: statistics.median(v) for k, v in self.cpu_rounds.items()}

    def ratio(self, a: str, b: str, clock: str = "wall") -> float:
        """Median over rounds of time(a) / time(b) (`clock` "wall" or "cpu"); inf when b took
        no measurable time in a round."""
        rounds = self.wall_rounds if clock == "wall" else self.cpu_rounds
        return statistics.median(x / y if y > 0 else float("inf")
                                 for x, y in zip(rounds[a], rounds[b], strict=True))

    def ratios(self, baseline: str, clock: str = "wall") -> dict:
        """name -> `ratio(name, baseline)` for every timed name."""
        return {k: self.ratio(k, baseline, clock) for k in self.wall}

    def to_json(self, baseline: str | None = None, scale: float = 1e3,
                digits: int = 3) -> dict:
        """A JSON-ready summary: medians (times `scale`: ms by default), ratios to `baseline`
        (the first name by default), reps and the load average."""
        baseline = next(iter(self.wall)) if baseline is None else baseline
        r = lambda v: round(v, digits)  # noqa: E731
        return {
            "median_wall": {k: r(scale * v) for k, v in self.wall.items()},
            "median_cpu": {k: r(scale * v) for k, v in self.cpu.items()},
            "ratio_to": baseline,
            "ratio_wall": {k: r(v) for k, v in self.ratios(baseline, "wall").items()},
            "ratio_cpu": {k: r(v) for k, v in self.ratios(baseline, "cpu").items()},
            "reps": self.reps,
            "load_avg_1m": {"before": self.load_before, "after": self.load_after},
        }


def alternate(runs: Mapping[str, Callable[[], Any]], reps: int = 5, *, warmup: int = 1,
              block: Callable[[Any], Any] = _block,
              wall_clock: Callable[[], float] = time.perf_counter,
              cpu_clock: Callable[[], float] = time.process_time,
              loadavg: Callable[[], float | None] = load_average) -> Timing:
    """Time zero-argument callables alternately: `warmup` untimed calls each, then `reps`
    rounds, each calling every callable once in the mapping's order.

    Args:
      runs: name -> callable; its result goes through `block` inside the timed interval.
      reps: timed rounds (>= 1).
      warmup: untimed calls of each callable before the first round.
      block: waits for a result (default `jax.block_until_ready`).
      wall_clock, cpu_clock, loadavg: injectable for tests (defaults: `time.perf_counter`,
        `time.process_time`, the 1-minute load average).
    Returns:
      Timing (seconds).
    """
    if reps < 1 or not runs:
        raise ValueError(f"need reps >= 1 and at least one callable, got {reps}, {len(runs)}")
    load_before = loadavg()
    for fn in runs.values():
        for _ in range(warmup):
            block(fn())
    wall = {k: [] for k in runs}
    cpu = {k: [] for k in runs}
    for _ in range(reps):
        for k, fn in runs.items():
            c0, t0 = cpu_clock(), wall_clock()
            block(fn())
            wall[k].append(wall_clock() - t0)
            cpu[k].append(cpu_clock() - c0)
    return Timing(wall_rounds=wall, cpu_rounds=cpu, reps=reps, load_before=load_before,
                  load_after=loadavg())
