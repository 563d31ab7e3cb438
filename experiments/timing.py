"""Paper Fig. 2 timing: coarse simulation + enhancement + lifting per frame against fine
simulation per frame, same scene, with the per-stage split.

    python -m experiments.timing [--frames 30] [--scene dress_dance]
        [--material silk_charmeuse] [--model wrinkle_jax/assets/enhancer.npz]
        [--out experiments/results/timing]

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

Writes `<out>/results.json` (frames timed, ms/frame per stage and per simulation, compile and
setup seconds, ratios, vertex counts, machine) and `<out>/timing.png` (stacked bars).
The machine's other load changes the numbers: its 1-minute load average is recorded.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from wrinkle_jax import MATERIALS, bodies, pipeline
from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import suite
from wrinkle_jax.sim import scenes

STAGES = ("bake", "tile", "network", "merge", "lift")


def time_simulation(config: scenes.SceneConfig, material: str, resolution: str, frames: int,
                    seed: int = cell_lib.TEST_SEED) -> tuple[scenes.SimulatedSequence, dict]:
    """Simulate `frames` frames with a compiled solver and time it.

    Returns:
      (sequence, info): info has setup_s, first_call_s, compile_s, frames (returned),
      simulated_frames (pre-roll + frames), wall_s, ms_per_frame (steady), chunk_ms_per_frame
      (list), vertices.
    """
    t0 = time.perf_counter()
    warm = scenes.simulate(config, material, resolution, frames=1, seed=seed)
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
                          progress=progress)
    wall = time.perf_counter() - t0
    simulated = int(sum(sizes))
    ms = 1e3 * wall / max(simulated, 1)
    chunk_ms = [1e3 * (b - a) / max(n, 1) for a, b, n in zip(stamps, stamps[1:], sizes,
                                                               strict=False)]
    return seq, {"resolution": resolution, "pd_m": scenes.resolution_pd(resolution),
                 "vertices": int(seq.garment.num_vertices), "frames": frames,
                 "simulated_frames": simulated, "wall_s": wall, "ms_per_frame": ms,
                 "chunk_ms_per_frame": chunk_ms, "setup_s": setup_s,
                 "first_call_s": first_call_s,
                 "compile_s": max(first_call_s - warm_frames * ms / 1e3, 0.0)}


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
    up (one chunk) the pipeline.

    Args:
      seq: coarse `GarmentSequence` (frames (T, V, 3) meters).
      body: None, a body or a callable frame index -> body (see `pipeline.make_pipeline`).
      batch_size: patches per network call (None: the pipeline's default, as the CLI).
    Returns:
      {"frames", "ms_per_frame": {stage: ms}, "ms_per_frame_total", "setup_s", "compile_s",
       "warmup_s", "warmup_frames", "patches_per_frame", "detailed_vertices", "map_shape"}.
    """
    # As the CLI runs it: warm-started lift, a chunk's patches sharing network calls.
    batch_size = batch_size or pipeline.PipelineConfig.batch_size
    config = pipeline.PipelineConfig(batch_size=batch_size, chunk_size=chunk_size, lift=lift,
                                     frames_per_batch=chunk_size, warm_start=True)
    pipe = pipeline.make_pipeline(seq.garment, enh, config, body)
    warm = list(range(min(chunk_size, len(seq))))
    t0 = time.perf_counter()
    pipeline.enhance_sequence(seq, material, pipeline=pipe, frames=warm, keep=False)
    warmup_s = time.perf_counter() - t0
    res = pipeline.enhance_sequence(seq, material, pipeline=pipe, keep=False)
    n = len(res.frame_indices)
    per = {k: 1e3 * res.timings.get(k, 0.0) / n for k in STAGES}
    return {"frames": n, "ms_per_frame": per, "ms_per_frame_total": sum(per.values()),
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


def ratios(coarse_ms: float, fine_ms: float, stage_ms: dict) -> dict:
    """Speed-up of coarse sim + pipeline over fine sim, with and without the lift."""
    ours = coarse_ms + sum(stage_ms.values())
    no_lift = ours - stage_ms.get("lift", 0.0)
    return {"ours_ms_per_frame": ours, "ours_no_lift_ms_per_frame": no_lift,
            "fine_ms_per_frame": fine_ms, "speedup": fine_ms / ours if ours > 0 else None,
            "speedup_no_lift": fine_ms / no_lift if no_lift > 0 else None}


def plot(path: Path, results: dict) -> None:
    """Stacked bars (ms/frame): coarse sim + pipeline stages, and the fine simulation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parts = [("coarse sim", results["coarse_sim"]["ms_per_frame"])]
    parts += [(k, results["pipeline"]["ms_per_frame"][k]) for k in STAGES]
    colors = ["tab:gray", "tab:olive", "tab:cyan", "tab:red", "tab:purple", "tab:green"]
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    bottom = 0.0
    for (name, ms), color in zip(parts, colors, strict=True):
        ax.bar(0, ms, bottom=bottom, color=color, label=f"{name} {ms:.0f} ms")
        bottom += ms
    fine = results["fine_sim"]["ms_per_frame"]
    ax.bar(1, fine, color="tab:blue", label=f"fine sim {fine:.0f} ms")
    ax.set_xticks([0, 1], ["coarse sim + ours", "fine sim"])
    ax.set_ylabel("ms per frame")
    r = results["ratio"]
    verdict = (f"ours {r['speedup']:.1f}x faster" if r["speedup"] >= 1
               else f"ours {1 / r['speedup']:.1f}x slower")
    ax.set_title(f"{results['scene']} {results['material']}, {results['frames']} frames timed: "
                 f"{verdict} than the fine sim", fontsize=8)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    suite.save_figure(fig, path, dpi=100)


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
    ap.add_argument("--out", default=str(suite.RESULTS / "timing"))
    args = ap.parse_args(argv)
    if args.frames < 1:
        ap.error("--frames must be >= 1")
    try:
        enh = enhancer_lib.load_enhancer(args.model)
        config = scenes.get_scene(args.scene)
    except (enhancer_lib.EnhancerError, scenes.SceneError) as e:
        ap.error(str(e))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    load_before = suite.machine_info()["load_avg_1min"]
    print(f"coarse simulation, {args.frames} frames ...", flush=True)
    coarse, coarse_info = time_simulation(config, args.material, "coarse", args.frames)
    print(f"  {coarse_info['ms_per_frame']:.1f} ms/frame", flush=True)
    print(f"pipeline, {args.frames} frames ...", flush=True)
    body = None if args.no_body else capsule_body_fn(coarse.tracks)
    pipe_info = time_pipeline(coarse, enh, args.material, body, True, args.batch_size)
    print("  " + ", ".join(f"{k} {v:.0f}" for k, v in pipe_info["ms_per_frame"].items())
          + " ms/frame", flush=True)
    print(f"fine simulation, {args.frames} frames ...", flush=True)
    _, fine_info = time_simulation(config, args.material, "fine", args.frames)
    print(f"  {fine_info['ms_per_frame']:.1f} ms/frame", flush=True)
    results = {
        "scene": args.scene, "material": args.material, "frames": args.frames,
        "seed": cell_lib.TEST_SEED, "model": suite.portable_path(args.model),
        "model_width": enh.config.unet.width,
        "coarse_sim": coarse_info, "pipeline": pipe_info, "fine_sim": fine_info,
        "ratio": ratios(coarse_info["ms_per_frame"], fine_info["ms_per_frame"],
                        pipe_info["ms_per_frame"]),
        "note": "steady-state ms/frame; compile and setup reported separately, not included",
        "timings": {"total_s": time.perf_counter() - t_all},
        "machine": {**suite.machine_info(), "load_avg_1min_before": load_before},
        "command": "python -m experiments.timing " + " ".join(
            sys.argv[1:] if argv is None else argv),
    }
    suite.write_json(out / "results.json", results)
    plot(out / "timing.png", results)
    r = results["ratio"]
    print(f"ours {r['ours_ms_per_frame']:.0f} ms/frame "
          f"(no lift {r['ours_no_lift_ms_per_frame']:.0f}), "
          f"fine {r['fine_ms_per_frame']:.0f} ms/frame: fine / ours = {r['speedup']:.2f}x "
          f"({r['speedup_no_lift']:.2f}x without the lift)")
    print(f"wrote {out / 'results.json'} and {out / 'timing.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
