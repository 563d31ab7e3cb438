"""Paper Fig. 2 timing: coarse simulation + enhancement + lifting per frame against fine
simulation per frame, same scene, with the per-stage split.

    python -m experiments.timing [--frames 30] [--scene dress_dance]
        [--material silk_charmeuse] [--model wrinkle_jax/assets/enhancer.npz]
        [--recipes legacy,dataset] [--rounds 2] [--out experiments/results/timing]

Everything is measured on this machine in this process, nothing is estimated:

  * simulation (`scenes.simulate`, seed 1): the fine (PD 10 mm) and the coarse (PD 30 mm) run
    of the scene. Each resolution is first run once for 1 frame (the scene's pre-roll is
    simulated too), which compiles the solver; then the timed run simulates the pre-roll and
    `--frames` frames with the compiled solver. ms/frame = timed wall / simulated frames
    (pre-roll included: its frames cost the same). The meshing and model setup is reported
    separately ("setup_s"), and so is the first call's overhead over the steady rate
    ("compile_s" = first-call wall - its frames x steady ms/frame). The per-chunk rates are
    recorded to show the timed run did not compile.
  * pipeline (`pipeline.enhance_sequence` on the timed coarse frames, material given, lifting
    with the mannequin's capsules as the body, as the paper's lifting resolves
    interpenetration; the lift warm-started from the previous frame, as the CLI runs it;
    its setting was kept by the quality sweep of `benchmarks/bench_pipeline.py --lift-sweep`,
    experiments/results/lift/): the pipeline is built and compiled once ("setup_s", "compile_s"), a
    first chunk is enhanced as a warm-up, then all `--frames` frames are timed; ms/frame per
    stage (bake, tile, network, merge, lift) = stage seconds / frames.

Ratio = fine ms/frame / (coarse ms/frame + pipeline ms/frame), with and without the lift.

Two solver recipes (`--recipes`), each for both resolutions:

  * "legacy": the scene's own substeps, no self-collision -- the setting of the fine
    simulation's 172 ms/frame that issue 22's target was written against;
  * "dataset": `scenes.dataset_solver` -- what the data set's sequences (the enhancer's
    training input and target) are simulated with: coarse at 80 substeps, self-collision at
    both resolutions.

The pipeline is timed on the first recipe's coarse frames (its cost does not depend on how the
coarse input was simulated). `--rounds N` repeats every measurement N times in one process,
the recipe order reversed in every other round so that a drift of the machine's speed falls on
both alike; every round's ratio is recorded and the headline uses the median over rounds. The
top-level "coarse_sim", "fine_sim" and "ratio" are the first recipe's (the report's table).

Writes `<out>/results.json` (frames timed, ms/frame per stage and per simulation, compile and
setup seconds, ratios, vertex counts, machine) and `<out>/timing.png` (stacked bars).
The machine's other load changes the numbers: its 1-minute load average is recorded.

Run as a script, the process is set up as the `wrinkle-jax` command's
(`cli.use_command_process`: XLA's legacy CPU code generator, glibc keeping freed memory; the
same environment variables opt out), so the pipeline is timed as the command runs it, and the
legacy recipe's simulations as `wrinkle-jax simulate` runs them (the command runs only the
scenes' own recipe: `results/timing/sim_codegen_cli_s43.txt`). The data set's recipe runs in
`experiments.make_sequences` (or a notebook) under XLA's defaults and glibc's own malloc
policy, never in a `wrinkle-jax` process: since session 44 its simulations (coarse and fine)
are timed in a child process set up that way (`CHILD_RECIPES`, `child_env`; each child compiles
its solver again, warm-up excluded as in this process); earlier runs timed them here, under the
command's settings (see below). "process" in results.json and in every simulation's info
records the settings. Session 42 ran it three times (dress_dance, 4 rounds each): XLA defaults
without retained memory, no-lift 2.84x / whole 1.22x; the command's settings 3.02x / 1.28x;
retained memory with XLA's default generator 2.75x / 1.15x. Retained memory took bake 14 ->
6-9, tile 2 -> 1, merge 19 -> 12-13 ms/frame in both runs that had it; the other differences
between the runs sit within the machine's drift between runs (the fine simulation without
self-collision took 262, 263 and 300 ms/frame). Alternating processes (3 pairs,
`results/timing/sim_codegen_s42.txt`) then showed the legacy generator makes the data set's
coarse simulation 1.16x slower (212 -> 246 ms/frame, medians) and leaves its fine one as it was
(1168 / 1161): the command's settings charge our side ~34 ms/frame of coarse simulation that
XLA's default generator would not."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from wrinkle_jax import cli, runtime

# Run as a script: set up as the `wrinkle-jax` process is, before JAX starts.
PROCESS = cli.use_command_process() if __name__ == "__main__" else {}

import numpy as np  # noqa: E402

from wrinkle_jax import MATERIALS, bodies, pipeline  # noqa: E402
from wrinkle_jax import enhancer as enhancer_lib  # noqa: E402
from wrinkle_jax.evaluation import cells as cell_lib  # noqa: E402
from wrinkle_jax.evaluation import suite  # noqa: E402
from wrinkle_jax.sim import scenes  # noqa: E402

STAGES = ("bake", "tile", "network", "merge", "lift")
RECIPES = ("legacy", "dataset")
# Recipes whose simulations are timed in a child process with XLA's defaults and glibc's own
# malloc policy: the data set's recipe runs in `experiments.make_sequences` (and in a
# notebook) that way, never in a `wrinkle-jax` process.
CHILD_RECIPES = ("dataset",)


def child_env(environ=None) -> dict:
    """The environment of a child that simulates as `experiments.make_sequences` does: `environ`
    (default `os.environ`) without the command's code-generator flag, with the opt-outs of
    `cli.use_command_process` set so the child's own start-up does not make them again."""
    env = dict(os.environ if environ is None else environ)
    flags = " ".join(f for f in env.get("XLA_FLAGS", "").split() if f != cli.FAST_COMPILE_FLAG)
    if flags:
        env["XLA_FLAGS"] = flags
    else:
        env.pop("XLA_FLAGS", None)
    env["WRINKLE_JAX_XLA_DEFAULTS"] = "1"
    env[runtime.MALLOC_ENV] = "default"
    return env


def time_simulation_in_child(scene: str, material: str, resolution: str, frames: int,
                             recipe: str) -> dict:
    """`time_simulation` (with its warm-up) in a fresh process with `child_env`: its info."""
    with tempfile.TemporaryDirectory() as d:
        cmd = [sys.executable, "-m", "experiments.timing", "--scene", scene, "--material",
               material, "--frames", str(frames), "--child", f"{recipe}:{resolution}",
               "--out", d]
        subprocess.run(cmd, env=child_env(), check=True, cwd=Path(__file__).resolve().parents[1])
        info = json.loads((Path(d) / "child.json").read_text())
    return {**info, "process": "child: XLA defaults, glibc's malloc (as make_sequences)"}


def solver_settings(config: scenes.SceneConfig, resolution: str, recipe: str) -> dict:
    """`scenes.simulate` keyword arguments of a solver recipe: "legacy" (the scene's own
    substeps, no self-collision) or "dataset" (`scenes.dataset_solver`)."""
    if recipe == "legacy":
        return {}
    if recipe == "dataset":
        substeps, self_collision = scenes.dataset_solver(config, resolution)
        return {"substeps": substeps, "self_collision": self_collision}
    raise ValueError(f"unknown solver recipe {recipe!r}; choose one of {RECIPES}")


def time_simulation(config: scenes.SceneConfig, material: str, resolution: str, frames: int,
                    seed: int = cell_lib.TEST_SEED, recipe: str = "legacy",
                    warm_up: bool = True) -> tuple[scenes.SimulatedSequence, dict]:
    """Simulate `frames` frames with a compiled solver and time it.

    Args:
      recipe: solver settings (`solver_settings`). warm_up: first run 1 frame to compile the
        solver (False when an earlier call in this process compiled the same one; then
        first_call_s and compile_s are None).
    Returns:
      (sequence, info): info has recipe, substeps, self_collision, setup_s, first_call_s,
      compile_s, frames (returned), simulated_frames (pre-roll + frames), wall_s, ms_per_frame
      (steady), chunk_ms_per_frame (list), vertices.
    """
    kw = solver_settings(config, resolution, recipe)
    first_call_s = warm_frames = None
    if warm_up:
        t0 = time.perf_counter()
        warm = scenes.simulate(config, material, resolution, frames=1, seed=seed, **kw)
        first_call_s = time.perf_counter() - t0
        warm_frames = int(warm.metadata["preroll_frames"])  # pre-roll + 1 - 1 simulated frames
    t0 = time.perf_counter()
    setup = scenes.setup_scene(config, resolution, frames, seed)
    setup_s = time.perf_counter() - t0
    stamps = [time.perf_counter()]
    sizes = []

    def progress(done, total):
        stamps.append(time.perf_counter())
        sizes.append(done - sum(sizes))

    t0 = time.perf_counter()
    seq = scenes.simulate(config, material, resolution, frames=frames, seed=seed, setup=setup,
                          progress=progress, **kw)
    wall = time.perf_counter() - t0
    simulated = int(sum(sizes))
    ms = 1e3 * wall / max(simulated, 1)
    chunk_ms = [1e3 * (b - a) / max(n, 1) for a, b, n in zip(stamps, stamps[1:], sizes,
                                                               strict=False)]
    sc = kw.get("self_collision")
    return seq, {"resolution": resolution, "pd_m": scenes.resolution_pd(resolution),
                 "recipe": recipe, "substeps": kw.get("substeps", config.substeps),
                 "self_collision": sc is not None,
                 "vertices": int(seq.garment.num_vertices), "frames": frames,
                 "simulated_frames": simulated, "wall_s": wall, "ms_per_frame": ms,
                 "chunk_ms_per_frame": chunk_ms, "setup_s": setup_s,
                 "first_call_s": first_call_s,
                 "compile_s": (None if first_call_s is None
                               else max(first_call_s - warm_frames * ms / 1e3, 0.0))}


def capsule_body_fn(tracks: dict):
    """frame index -> `bodies.PrimitiveBody` of the mannequin's capsules (tracks of
    `scenes.simulate`: capsule_ends (T, C, 2, 3) m, capsule_radii (C,) m); None without."""
    if "capsule_ends" not in tracks:
        return None
    ends, radii = np.asarray(tracks["capsule_ends"]), np.asarray(tracks["capsule_radii"])

    def body(t: int):
        return bodies.primitive_body(capsules=(ends[t, :, 0], ends[t, :, 1], radii))

    return body


def time_pipeline(seq, enh: enhancer_lib.Enhancer, material: str, body=None, lift: bool = True,
                  batch_size: int | None = None, chunk_size: int = 4) -> dict:
    """Time the pipeline stages on every frame of `seq` after building, compiling and warming
    up (one chunk) the pipeline. As the CLI, the lift overlaps the next chunk's stages
    (`overlap_lift`): the stages' times then add up to more than the wall time, which is
    "wall_ms_per_frame" (the streaming loop, material given).

    Args:
      seq: coarse `GarmentSequence` (frames (T, V, 3) meters).
      body: None, a body or a callable frame index -> body (see `pipeline.make_pipeline`).
      batch_size: patches per network call (None: the pipeline's default, as the CLI).
    Returns:
      {"frames", "ms_per_frame": {stage: ms}, "ms_per_frame_total", "wall_ms_per_frame",
       "setup_s", "compile_s", "warmup_s", "warmup_frames", "patches_per_frame",
       "detailed_vertices", "map_shape", ...}.
    """
    # As the CLI runs it: warm-started lift, a chunk's patches sharing network calls.
    batch_size = batch_size or pipeline.PipelineConfig.batch_size
    config = pipeline.PipelineConfig(batch_size=batch_size, chunk_size=chunk_size, lift=lift,
                                     frames_per_batch=chunk_size, warm_start=True,
                                     overlap_lift=lift)
    pipe = pipeline.make_pipeline(seq.garment, enh, config, body)
    warm = list(range(min(chunk_size, len(seq))))
    t0 = time.perf_counter()
    pipeline.enhance_sequence(seq, material, pipeline=pipe, frames=warm, keep=False)
    warmup_s = time.perf_counter() - t0
    res = pipeline.enhance_sequence(seq, material, pipeline=pipe, keep=False)
    n = len(res.frame_indices)
    per = {k: 1e3 * res.timings.get(k, 0.0) / n for k in STAGES}
    wall = 1e3 * (res.timings["total"] - res.timings["classify"]) / n
    return {"frames": n, "ms_per_frame": per, "ms_per_frame_total": sum(per.values()),
            "wall_ms_per_frame": wall, "overlap_lift": config.overlap_lift,
            "setup_s": pipe.timings["setup"], "compile_s": pipe.timings["compile"],
            "warmup_s": warmup_s, "warmup_frames": len(warm),
            "patches_per_frame": pipe.num_patches, "batch_size": batch_size,
            "chunk_size": chunk_size, "frames_per_batch": chunk_size, "lift": lift,
            "body": body is not None,
            "lift_warm_start": True, "lift_max_iters": config.solver.max_iters,
            "lift_iterations_per_frame": res.lift_iterations / n,
            "detailed_vertices": (None if pipe.fine_garment is None
                                  else int(pipe.fine_garment.num_vertices)),
            "map_shape": list(pipe.shape)}


def ratios(coarse_ms: float, fine_ms: float, stage_ms: dict, wall_ms: float | None = None,
           no_lift_wall_ms: float | None = None) -> dict:
    """Speed-up of coarse sim + pipeline over fine sim, with and without the lift: the
    pipeline's wall times when given (the lift overlapping, and a run without it), else the
    sum of `stage_ms` (without the lift: minus its stage)."""
    ours = coarse_ms + (sum(stage_ms.values()) if wall_ms is None else wall_ms)
    no_lift = (ours - stage_ms.get("lift", 0.0) if no_lift_wall_ms is None
               else coarse_ms + no_lift_wall_ms)
    return {"ours_ms_per_frame": ours, "ours_no_lift_ms_per_frame": no_lift,
            "fine_ms_per_frame": fine_ms, "speedup": fine_ms / ours if ours > 0 else None,
            "speedup_no_lift": fine_ms / no_lift if no_lift > 0 else None}


def plot(path: Path, results: dict) -> None:
    """Stacked bars (ms/frame): coarse sim + pipeline stages, and the fine simulation, one pair
    per solver recipe (`results["summary"]`; without it, the top-level recipe only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = results.get("summary")
    if summary:
        pairs = [(name, s["coarse_ms_per_frame"], s["fine_ms_per_frame"], s["ratio"])
                 for name, s in summary["recipes"].items()]
    else:
        pairs = [("", results["coarse_sim"]["ms_per_frame"],
                  results["fine_sim"]["ms_per_frame"], results["ratio"])]
    stage_ms = results["pipeline"]["ms_per_frame"]
    colors = ["tab:gray", "tab:olive", "tab:cyan", "tab:red", "tab:purple", "tab:green"]
    fig, ax = plt.subplots(figsize=(2.2 + 1.9 * len(pairs), 3.6))
    ticks, labels = [], []
    for i, (name, coarse, fine, r) in enumerate(pairs):
        x = 2.6 * i
        parts = [("coarse sim", coarse)] + [(k, stage_ms[k]) for k in STAGES]
        bottom = 0.0
        for (part, ms), color in zip(parts, colors, strict=True):
            # The stages are shared by the recipes: labelled once; the coarse sims per recipe.
            label = (f"{part} {ms:.0f} ms" + (f" ({name})" if name else "")
                     if part == "coarse sim" else f"{part} {ms:.0f} ms" if i == 0 else None)
            ax.bar(x, ms, bottom=bottom, color=color, label=label)
            bottom += ms
        ax.bar(x + 1, fine, color="tab:blue", label=f"fine sim {fine:.0f} ms"
               + (f" ({name})" if name else ""))
        ax.text(x + 0.5, max(bottom, fine) * 1.02, f"{r['speedup']:.2f}x", ha="center",
                fontsize=7)
        ticks += [x, x + 1]
        labels += [f"ours\n{name}".strip(), f"fine\n{name}".strip()]
    ax.set_xticks(ticks, labels, fontsize=7)
    ax.set_ylabel("ms per frame")
    ax.set_title(f"{results['scene']} {results['material']}, {results['frames']} frames: "
                 "fine / ours above each pair", fontsize=8)
    ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    suite.save_figure(fig, path, dpi=100)


def summarize(rounds: list[dict], recipes: tuple[str, ...]) -> dict:
    """Medians over rounds of `measure_round` results.

    Returns:
      {"pipeline_ms_per_frame": {stage: median ms}, "recipes": {recipe: {"coarse_ms_per_frame",
       "fine_ms_per_frame", "ratio" (`ratios` of the medians), "speedup_per_round",
       "speedup_no_lift_per_round"}}}.
    """
    stage_ms = {k: float(np.median([r["pipeline"]["ms_per_frame"][k] for r in rounds]))
                for k in STAGES}
    wall = float(np.median([r["pipeline"]["wall_ms_per_frame"] for r in rounds]))
    no_lift = float(np.median([r["pipeline_no_lift"]["wall_ms_per_frame"] for r in rounds]))
    out = {}
    for name in recipes:
        coarse = float(np.median([r["recipes"][name]["coarse_sim"]["ms_per_frame"]
                                  for r in rounds]))
        fine = float(np.median([r["recipes"][name]["fine_sim"]["ms_per_frame"] for r in rounds]))
        out[name] = {"coarse_ms_per_frame": coarse, "fine_ms_per_frame": fine,
                     "ratio": ratios(coarse, fine, stage_ms, wall, no_lift),
                     "speedup_per_round": [r["recipes"][name]["ratio"]["speedup"]
                                           for r in rounds],
                     "speedup_no_lift_per_round": [r["recipes"][name]["ratio"]["speedup_no_lift"]
                                                   for r in rounds]}
    return {"pipeline_ms_per_frame": stage_ms, "pipeline_wall_ms_per_frame": wall,
            "pipeline_no_lift_wall_ms_per_frame": no_lift, "recipes": out}


def simulate_timed(config: scenes.SceneConfig, material: str, resolution: str, frames: int,
                   recipe: str, warm_up: bool) -> dict:
    """One timed simulation: in this process, or in a child for `CHILD_RECIPES`; the info of
    `time_simulation`, with the sequence under "sequence" when simulated here."""
    if recipe in CHILD_RECIPES:
        return time_simulation_in_child(config.name, material, resolution, frames, recipe)
    seq, info = time_simulation(config, material, resolution, frames, recipe=recipe,
                                warm_up=warm_up)
    return {**info, "process": "this process", "sequence": seq}


def measure_round(config: scenes.SceneConfig, material: str, frames: int,
                  recipes: tuple[str, ...], order: tuple[str, ...], enh: enhancer_lib.Enhancer,
                  use_body: bool, batch_size: int | None, warm_up: bool) -> dict:
    """One round: the coarse simulation of every recipe (in `order`), the pipeline on the
    coarse frames of `recipes[0]`, then the fine simulations (in `order`)."""
    rec = {"order": list(order), "load_avg_1min_before": suite.machine_info()["load_avg_1min"],
           "recipes": {name: {} for name in recipes}}
    first = None
    for name in order:
        print(f"  coarse simulation ({name}), {frames} frames ...", flush=True)
        info = simulate_timed(config, material, "coarse", frames, name, warm_up)
        seq = info.pop("sequence", None)
        print(f"    {info['ms_per_frame']:.1f} ms/frame", flush=True)
        rec["recipes"][name]["coarse_sim"] = info
        first = seq if name == recipes[0] else first
    if first is None:  # the first recipe was simulated in a child: its frames, untimed
        first, _ = time_simulation(config, material, "coarse", frames, recipe=recipes[0],
                                   warm_up=False)
    print(f"  pipeline on the {recipes[0]} coarse frames ...", flush=True)
    body = capsule_body_fn(first.tracks) if use_body else None
    rec["pipeline"] = time_pipeline(first, enh, material, body, True, batch_size)
    print("    " + ", ".join(f"{k} {v:.0f}" for k, v in rec["pipeline"]["ms_per_frame"].items())
          + f" ms/frame; wall {rec['pipeline']['wall_ms_per_frame']:.0f}", flush=True)
    print("  pipeline without the lift (--no-lift) ...", flush=True)
    rec["pipeline_no_lift"] = time_pipeline(first, enh, material, None, False, batch_size)
    print(f"    wall {rec['pipeline_no_lift']['wall_ms_per_frame']:.0f} ms/frame", flush=True)
    for name in order:
        print(f"  fine simulation ({name}), {frames} frames ...", flush=True)
        info = simulate_timed(config, material, "fine", frames, name, warm_up)
        info.pop("sequence", None)
        print(f"    {info['ms_per_frame']:.1f} ms/frame", flush=True)
        r = rec["recipes"][name]
        r["fine_sim"] = info
        r["ratio"] = ratios(r["coarse_sim"]["ms_per_frame"], info["ms_per_frame"],
                            rec["pipeline"]["ms_per_frame"],
                            rec["pipeline"]["wall_ms_per_frame"],
                            rec["pipeline_no_lift"]["wall_ms_per_frame"])
    rec["load_avg_1min_after"] = suite.machine_info()["load_avg_1min"]
    return rec


def parse_recipes(text: str) -> tuple[str, ...]:
    """"legacy,dataset" -> ("legacy", "dataset"); ValueError on unknown or repeated names."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in RECIPES]
    if not names or bad or len(set(names)) != len(names):
        raise ValueError(f"--recipes: a comma-separated subset of {RECIPES}, got {text!r}")
    return names


def main(argv=None) -> int:
    ap = suite.script_parser(__doc__)
    ap.add_argument("--frames", type=int, default=30, help="frames timed (after the pre-roll)")
    ap.add_argument("--scene", default="dress_dance", help="a scene of wrinkle_jax.sim.scenes")
    ap.add_argument("--material", default="silk_charmeuse", choices=MATERIALS)
    ap.add_argument("--model", default=str(enhancer_lib.DEFAULT_PATH),
                    help="enhancer .npz (default: the shipped model)")
    ap.add_argument("--batch-size", type=int, default=None,
                    help="patches per network call (default: the pipeline's, as the CLI)")
    ap.add_argument("--no-body", action="store_true",
                    help="lift without the body (no interpenetration resolution)")
    ap.add_argument("--recipes", default=",".join(RECIPES),
                    help="solver recipes, comma-separated; the first is the report's table")
    ap.add_argument("--rounds", type=int, default=2,
                    help="repeat every measurement, the recipe order reversed every other round")
    ap.add_argument("--out", default=str(suite.RESULTS / "timing"))
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)  # RECIPE:RESOLUTION
    args = ap.parse_args(argv)
    if args.frames < 1 or args.rounds < 1:
        ap.error("--frames and --rounds must be >= 1")
    try:
        recipes = parse_recipes(args.recipes)
        # A child (`--child`) only simulates: it does not load the model.
        enh = None if args.child else enhancer_lib.load_enhancer(args.model)
        config = scenes.get_scene(args.scene)
    except (ValueError, enhancer_lib.EnhancerError, scenes.SceneError) as e:
        ap.error(str(e))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.child:  # time_simulation_in_child's process: one simulation, info to child.json
        recipe, resolution = args.child.split(":")
        _, info = time_simulation(config, args.material, resolution, args.frames, recipe=recipe)
        info["xla_flags"] = os.environ.get("XLA_FLAGS", "")
        suite.write_json(out / "child.json", info)
        return 0
    t_all = time.perf_counter()
    load_before = suite.machine_info()["load_avg_1min"]
    rounds = []
    for i in range(args.rounds):
        order = recipes if i % 2 == 0 else recipes[::-1]
        print(f"round {i + 1}/{args.rounds}, order {', '.join(order)}", flush=True)
        rounds.append(measure_round(config, args.material, args.frames, recipes, order, enh,
                                    not args.no_body, args.batch_size, warm_up=i == 0))
    summary = summarize(rounds, recipes)
    head = summary["recipes"][recipes[0]]
    first = rounds[0]["recipes"][recipes[0]]
    pipe_info = {**rounds[0]["pipeline"], "ms_per_frame": summary["pipeline_ms_per_frame"],
                 "ms_per_frame_total": sum(summary["pipeline_ms_per_frame"].values()),
                 "wall_ms_per_frame": summary["pipeline_wall_ms_per_frame"],
                 "no_lift_wall_ms_per_frame": summary["pipeline_no_lift_wall_ms_per_frame"]}
    results = {
        "scene": args.scene, "material": args.material, "frames": args.frames,
        "seed": cell_lib.TEST_SEED, "model": suite.portable_path(args.model),
        "model_width": enh.config.unet.width, "rounds": args.rounds,
        "recipes": list(recipes),
        "coarse_sim": {**first["coarse_sim"], "ms_per_frame": head["coarse_ms_per_frame"]},
        "pipeline": pipe_info,
        "fine_sim": {**first["fine_sim"], "ms_per_frame": head["fine_ms_per_frame"]},
        "ratio": head["ratio"], "summary": summary, "per_round": rounds,
        "note": ("steady-state ms/frame, medians over rounds; compile and setup reported "
                 "separately (first round), not included"),
        "timings": {"total_s": time.perf_counter() - t_all},
        "machine": {**suite.machine_info(), "load_avg_1min_before": load_before},
        "process": {**PROCESS, "xla_flags": os.environ.get("XLA_FLAGS", ""),
                    "child_recipes": [r for r in recipes if r in CHILD_RECIPES]},
        "command": "python -m experiments.timing " + " ".join(
            sys.argv[1:] if argv is None else argv),
    }
    suite.write_json(out / "results.json", results)
    plot(out / "timing.png", results)
    for name in recipes:
        s = summary["recipes"][name]
        r = s["ratio"]
        print(f"{name}: ours {r['ours_ms_per_frame']:.0f} ms/frame "
              f"(no lift {r['ours_no_lift_ms_per_frame']:.0f}), "
              f"fine {r['fine_ms_per_frame']:.0f} ms/frame: fine / ours = {r['speedup']:.2f}x "
              f"({r['speedup_no_lift']:.2f}x without the lift; per round "
              + ", ".join(f"{x:.2f}" for x in s["speedup_per_round"]) + ")")
    print(f"wrote {out / 'results.json'} and {out / 'timing.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
