"""Generate the simulated training and test sequences (resumable, background-friendly).

    nohup nice -n 10 python -m experiments.make_sequences [--out data/sequences] \
        [--train-frames 600] [--test-frames 300] [--tiny] [--only SCENE,...] \
        [--self-collision on|off] [--coarse-substeps N] > /dev/null 2>&1 &
    python -m experiments.make_sequences --status      # written / checkpointed / left, hours
    python -m experiments.make_sequences --previews experiments/results/sim

Writes `<out>/<scene>/<material>_<resolution>_s<seed>.npz` (`scenes.save_simulation`: frames
(T, V, 3) m, UVs in meters, metadata with material / PD / scene config JSON, pin and collider
tracks) for:

  * training scenes (`scenes.TRAINING_SCENES`: sheet_balls_wind, skirt_dance,
    pleated_skirt_dance2, shawl_dance2, apron_dance, circle_skirt_dance2, long_shawl_dance,
    skirt_dance2, apron_dance2): all five materials, fine (PD 10 mm), seed 0 (the same
    motion for every material, as in the paper);
  * validation-only scenes (tabard_dance2): all five materials, fine AND coarse, seed 0;
  * test-only scenes (dress_dance, cape_walk, skirt_walk): all five materials, fine AND coarse
    (PD 30 mm), seed 1.

Self-collision (`--self-collision`, default on since issue 24): each resolution simulates with
`scenes.self_collision_config(resolution, substeps, scene)` (`scenes.SELF_COLLISION`'s settings
at the job's substeps, with the scene's fine overrides; recorded in every file's metadata, with
the dropped-candidate counts).

Coarse substeps (`--coarse-substeps N`, default `scenes.DATASET_COARSE_SUBSTEPS` = 80; the
scenes' own is 20): the coarse (PD 30 mm) jobs' solver substeps per frame. At 20 the coarse
solver is softer than any fabric's stretch stiffness, so every fabric strains alike; at 80 terry
and melton separate (`experiments/coarse_substeps.py`,
experiments/results/classifier/README.md). Self-collision candidates are then rebuilt at the
same interval in time (`scenes.self_collision_config`). Fine jobs always use the scene's.
Recorded in the manifest; a folder that already holds coarse files refuses another value (fine
files do not depend on it, so a folder of fine files can take any).

Several runs may share one folder, e.g. one per core: each job is claimed first (an flock on
`<out>/.partial/<scene>/<file>.lock`, dropped by the kernel if its process dies), so a run
skips the job another is simulating. Files already present are skipped (also those another
run writes while this one runs), each file is written atomically (temporary file +
rename), the file being simulated is checkpointed every `--checkpoint-every` seconds under
`<out>/.partial/` (`scenes.simulate(checkpoint=...)`; the next run resumes it bit-identically,
so a killed session loses minutes, not hours), and progress goes to `<out>/make_sequences.log`
(one line per chunk of frames and per file, with ms/frame and an ETA) and `<out>/manifest.json`
(rewritten after every file). One mesh, model and compiled solver per scene and resolution serve
all five materials. A run that resumes another must use the same code: the log's start line and
the manifest record the git commit and the self-collision setting, and a start refuses a folder
whose manifest names other settings (use a new --out for a new simulator version).

Sizing: 85 files (the nine training scenes fine, the validation scene and the three test
scenes fine and coarse), roughly 5 GB. With self-collision the fine files cost 0.45-3 s per
frame on the 2-core CPU (the 11.5k-vertex scenes ~0.9 s, the fine skirts 1.6-2.9 s; sessions
26-29) and the coarse ones at 80 substeps ~0.11 s, about 8 hours of one core in all; two runs
side by side (one per core, sharing the folder through the job claims) take about half.
`--status` prices what is left from the files already written.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from wrinkle_jax import MATERIALS
from wrinkle_jax.fileio import NPZ_READ_ERRORS, atomic_write_text, claim_output, git_commit
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]

# Measured ms/frame (fine, coarse) used for the ETA only.
EST_MS = {"sheet_balls_wind": (125, 8), "skirt_dance": (210, 15), "pleated_skirt_dance2": (130, 10),
          "shawl_dance2": (100, 8), "apron_dance": (60, 6), "tabard_dance2": (70, 6),
          "dress_dance": (135, 8), "cape_walk": (131, 8), "skirt_walk": (235, 15),
          "circle_skirt_dance2": (220, 12), "long_shawl_dance": (160, 10),
          "skirt_dance2": (230, 15), "apron_dance2": (60, 6)}


def plan(train_frames: int, test_frames: int, val_frames: int = 150) -> list[dict]:
    """The jobs: one per (scene, resolution, material), grouped by scene and resolution."""
    groups = ((scenes.TRAINING_SCENES, ("fine",), train_frames),
              (scenes.VAL_SCENES, ("fine", "coarse"), val_frames),
              (scenes.TEST_SCENES, ("fine", "coarse"), test_frames))
    return [{"scene": name, "resolution": res, "material": mat,
             "seed": scenes.dataset_seed(name), "frames": frames}
            for names, resolutions, frames in groups
            for name in names for res in resolutions for mat in MATERIALS]


def self_collision_for(resolution: str, setting: str, substeps: int | None = None,
                       scene: str | None = None):
    """The `SelfCollisionConfig` a job of `scene` at `resolution` simulates with at `substeps`
    per frame: `scenes.self_collision_config`'s for "on" (the same rebuild interval in time
    at any substeps; the scene's own fine overrides, `SceneConfig.fine_self_collision`),
    None for "off"."""
    if setting not in ("on", "off"):
        raise ValueError(f"self-collision setting must be 'on' or 'off', got {setting!r}")
    if setting == "off":
        return None
    return scenes.self_collision_config(resolution, substeps, scene)


def substeps_for(resolution: str, coarse_substeps: int | None) -> int | None:
    """The solver substeps a job of `resolution` simulates with: `coarse_substeps` for coarse
    jobs when given, else None (the scene's own)."""
    if coarse_substeps is not None and coarse_substeps < 1:
        raise ValueError(f"coarse substeps must be >= 1, got {coarse_substeps}")
    return coarse_substeps if resolution == "coarse" else None


def select(jobs: list[dict], only: str | None) -> list[dict]:
    """The jobs of the comma-separated scenes `only` (all jobs when None), in plan order.

    Raises:
      ValueError: `only` names a scene that does not exist.
    """
    if not only:
        return jobs
    keep = set(only.split(","))
    unknown = keep - set(scenes.SCENES)
    if unknown:
        raise ValueError(f"unknown scenes: {sorted(unknown)}")
    return [j for j in jobs if j["scene"] in keep]


def job_path(out: Path, job: dict) -> Path:
    return out / job["scene"] / f"{job['material']}_{job['resolution']}_s{job['seed']}.npz"


def partial_path(out: Path, job: dict) -> Path:
    """Where a job's checkpoint lives while it runs (`scenes.simulate(checkpoint=...)`): under
    `<out>/.partial/`, out of the way of globs over the data set's files."""
    rel = job_path(out, job).relative_to(out)
    return out / ".partial" / rel.parent / (rel.name + ".partial")


def estimate_s(job: dict) -> float:
    sc = scenes.get_scene(job["scene"])
    ms = EST_MS.get(job["scene"], (200, 15))[0 if job["resolution"] == "fine" else 1]
    return ms * (job["frames"] + sc.preroll_s * 30) / 1e3


def job_status(out: Path, jobs: list[dict]) -> list[dict]:
    """Where each job stands, and what the rest costs at the rates of the files written.

    Per job: "state" ("done", "partial" with a checkpoint, or "todo"), "frames_left" (pre-roll
    included) and "ms_per_frame": the file's own rate when done (its metadata), else the
    fastest written file's of the same scene and resolution, else `EST_MS` times the median
    over scenes of that resolution of (fastest written rate / `EST_MS`) (the estimates predate
    self-collision and the coarse substeps), and "source" saying which. Rates are wall time as
    the files were written; the fastest is the one least slowed by other work on the machine,
    so the hours are closer to an idle machine's than to a busy one's."""
    import numpy as np

    measured: dict[tuple, list[float]] = {}
    rows = []
    for job in jobs:
        sc = scenes.get_scene(job["scene"])
        total = job["frames"] + int(round(sc.preroll_s * 30)) - 1
        row = dict(job, state="todo", frames_left=total, ms_per_frame=None, source=None)
        path, partial = job_path(out, job), partial_path(out, job)
        try:
            if path.exists():
                with np.load(path, allow_pickle=False) as z:
                    ms = float(json.loads(str(z["metadata"]))["ms_per_frame"])
                row.update(state="done", frames_left=0, ms_per_frame=ms, source="file")
                measured.setdefault((job["scene"], job["resolution"]), []).append(ms)
            elif partial.exists():
                with np.load(partial, allow_pickle=False) as z:
                    done = int(z["done"])
                row.update(state="partial", frames_left=max(total - done, 0))
        except NPZ_READ_ERRORS:  # being replaced right now, or damaged: counted as not done
            pass
        rows.append(row)
    scale = {}
    for res, i in (("fine", 0), ("coarse", 1)):
        ratios = [min(v) / EST_MS[sc][i] for (sc, r), v in measured.items()
                  if r == res and sc in EST_MS]
        if ratios:
            scale[res] = float(np.median(ratios))
    for row in rows:
        if row["state"] == "done":
            continue
        key, res = (row["scene"], row["resolution"]), row["resolution"]
        if key in measured:
            row.update(ms_per_frame=min(measured[key]), source="scene")
        elif res in scale and row["scene"] in EST_MS:
            est = EST_MS[row["scene"]][0 if res == "fine" else 1]
            row.update(ms_per_frame=est * scale[res], source=f"estimate x {scale[res]:.1f}")
    return rows


def _hours_left(rows: list[dict]) -> float:
    """Hours of simulation the rows' frames left cost at their rates (no rate: not counted)."""
    return sum(r["frames_left"] * (r["ms_per_frame"] or 0.0) for r in rows) / 3.6e6


def status_summary(rows: list[dict]) -> str:
    """One line: files written, and hours of simulation left at `job_status`'s rates."""
    left = [r for r in rows if r["state"] != "done"]
    hours = _hours_left(left)
    unknown = sum(r["ms_per_frame"] is None for r in left)
    return (f"{len(rows) - len(left)} of {len(rows)} files written; {hours:.1f} hours of "
            f"simulation left at the fastest written rates (one process; two on two cores "
            f"take about half){f', {unknown} jobs without a rate' if unknown else ''}")


def status_text(rows: list[dict]) -> str:
    """A table per scene and resolution (files done / partial / to do, hours left) and the
    total, for `--status`."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["resolution"]), []).append(r)
    lines = ["| scene | resolution | done | partial | to do | ms/frame (source) | hours left |",
             "|---|---|---|---|---|---|---|"]
    for (scene, res), rs in groups.items():
        left = [r for r in rs if r["state"] != "done"]
        rate = next((r for r in left if r["ms_per_frame"] is not None), None)
        hours = _hours_left(left)
        counts = [sum(r["state"] == s for r in rs) for s in ("done", "partial", "todo")]
        rate_text = f"{rate['ms_per_frame']:.0f} ({rate['source']})" if rate else "-"
        lines.append(f"| {scene} | {res} | {counts[0]} | {counts[1]} | {counts[2]} | "
                     f"{rate_text} | {hours:.2f} |")
    lines.append(f"\n{status_summary(rows)}")
    return "\n".join(lines)


def make_previews(out: Path, data: Path, frame: int = 90, material: str = "silk_charmeuse",
                  only: str | None = None, texel: float = 0.004) -> list[str]:
    """Fine-vs-coarse preview PNGs per scene (3D views and baked normal maps at frame `frame`).

    Uses the generated fine/coarse files when present (same seed and frame), otherwise runs a
    short simulation of `frame + 1` frames with the data set's solver (`scenes.dataset_solver`).
    `only`: comma-separated scene names (default all).
    """
    import jax.numpy as jnp
    import numpy as np

    from wrinkle_jax import meshio, normalmap
    from wrinkle_jax.sim import preview

    paths = []
    keep = set(only.split(",")) if only else set(scenes.SCENES)
    for name, sc in scenes.SCENES.items():
        if name not in keep:
            continue
        seed = scenes.dataset_seed(sc)
        seqs = {}
        for res in ("fine", "coarse"):
            p = data / name / f"{material}_{res}_s{seed}.npz"
            seq = meshio.load_sequence(p) if p.exists() else None
            if seq is None or len(seq) <= frame:
                # The data set's solver, so the preview shows what its file would hold.
                substeps, contacts = scenes.dataset_solver(name, res)
                seq = scenes.simulate(name, material, res, frames=frame + 1, seed=seed,
                                      substeps=substeps, self_collision=contacts)
                tracks = seq.tracks
            else:
                with np.load(p) as z:
                    tracks = {k: z[k] for k in ("capsule_ends", "capsule_radii",
                                                "sphere_centers", "sphere_radii") if k in z}
            seqs[res] = (seq, tracks)
        layout = normalmap.layout_for(seqs["fine"][0].garment, texel, margin=4,
                                      meters_per_uv=1.0)
        panels, titles = [], []
        for res in ("fine", "coarse"):
            seq, tr = seqs[res]

            def view(ax, seq=seq, tr=tr):
                preview.render_frame(
                    ax, seq.frames[frame], seq.garment.faces, azim=25, elev=12,
                    capsules=tr["capsule_ends"][frame] if "capsule_ends" in tr else None,
                    capsule_radii=tr.get("capsule_radii"),
                    spheres=tr["sphere_centers"][frame] if "sphere_centers" in tr else None,
                    sphere_radii=tr.get("sphere_radii"))

            panels.append(view)
            titles.append(f"{res} PD {seq.metadata.get('pd_mm', '?')} mm, "
                          f"{seq.garment.num_vertices} v")
        for res in ("fine", "coarse"):
            seq, _ = seqs[res]
            plan = normalmap.make_plan(seq.garment, layout=layout)
            rgb = np.asarray(normalmap.to_rgb(normalmap.bake(plan, jnp.asarray(seq.frames[frame]))))
            rgb = np.where(np.asarray(plan.mask) > 0, rgb, 1.0)

            def image(ax, rgb=rgb):
                ax.imshow(rgb, interpolation="nearest")
                ax.axis("off")

            panels.append(image)
            titles.append(f"normal map ({res}, {texel * 1e3:.0f} mm texels)")
        path = out / f"{name}.png"
        preview.save_comparison(path, panels, titles, dpi=55, ncols=4)
        paths.append(str(path))
    return paths


def run_job(job: dict, out: Path, setup, args, log) -> tuple:
    """Simulate one job (resuming its checkpoint under `<out>/.partial/`) and write its file;
    returns (sequence, wall seconds)."""
    last = [time.perf_counter()]

    def progress(done, total):
        now = time.perf_counter()
        if now - last[0] > 60 or done == total:
            last[0] = now
            log(f"  {job['scene']} {job['material']} {job['resolution']}: "
                f"frame {done}/{total}")

    t0 = time.perf_counter()
    substeps = substeps_for(job["resolution"], args.coarse_substeps)
    partial = partial_path(out, job)
    if partial.exists():
        log(f"  {job['scene']} {job['material']} {job['resolution']}: "
            f"resuming from {partial.relative_to(out)}")
    seq = scenes.simulate(job["scene"], job["material"], job["resolution"], job["frames"],
                          job["seed"], progress=progress, setup=setup, substeps=substeps,
                          self_collision=self_collision_for(
                              job["resolution"], args.self_collision, substeps, job["scene"]),
                          checkpoint=partial, checkpoint_every_s=args.checkpoint_every)
    scenes.save_simulation(job_path(out, job), seq)
    return seq, time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--train-frames", type=int, default=600)
    ap.add_argument("--test-frames", type=int, default=300)
    ap.add_argument("--val-frames", type=int, default=150)
    ap.add_argument("--tiny", action="store_true", help="3 frames each, coarse only (smoke test)")
    ap.add_argument("--only", default=None,
                    help="comma-separated scene names (e.g. the sheet and the test scenes first, "
                         "so a sheet-only run can start early); the manifest still lists all")
    ap.add_argument("--self-collision", choices=("on", "off"), default="on",
                    help="simulate with scenes.SELF_COLLISION per resolution (default on)")
    ap.add_argument("--coarse-substeps", type=int, default=scenes.DATASET_COARSE_SUBSTEPS,
                    metavar="N", help="solver substeps per frame of the coarse jobs (default "
                    "%(default)s: scenes.DATASET_COARSE_SUBSTEPS)")
    ap.add_argument("--checkpoint-every", type=float, default=300.0, metavar="S",
                    help="seconds between checkpoints of the running file (resumed by the "
                         "next run; default 300)")
    ap.add_argument("--status", action="store_true",
                    help="print what is written, checkpointed and left (with hours left at the "
                         "written files' rates), and exit")
    ap.add_argument("--previews", default=None, metavar="DIR",
                    help="only write fine-vs-coarse preview PNGs into DIR (from --out data)")
    args = ap.parse_args(argv)
    if args.previews:
        for p in make_previews(Path(args.previews), Path(args.out), only=args.only):
            print(p)
        return 0
    out = Path(args.out)
    if args.status:
        try:
            print(status_text(job_status(out, select(plan(args.train_frames, args.test_frames,
                                                          args.val_frames), args.only))))
        except ValueError as e:
            ap.error(str(e))
        return 0
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "make_sequences.log"
    jobs = plan(args.train_frames, args.test_frames, args.val_frames)
    if args.tiny:
        tiny = {}
        for j in jobs:
            if j["material"] == MATERIALS[0]:
                t = dict(j, frames=3, resolution="coarse")
                tiny[job_path(out, t)] = t
        jobs = list(tiny.values())
    try:
        selected = select(jobs, args.only)
    except ValueError as e:
        ap.error(str(e))

    def log(msg: str) -> None:
        line = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}"
        with open(log_path, "a", encoding="utf-8") as fh:
            fh.write(line + "\n")

    manifest_path = out / "manifest.json"
    try:
        substeps_for("coarse", args.coarse_substeps)
    except ValueError as e:
        ap.error(str(e))
    version = {"self_collision": args.self_collision, "coarse_substeps": args.coarse_substeps,
               "commit": git_commit(ROOT) or "unknown"}
    if manifest_path.exists():
        stored = json.loads(manifest_path.read_text())
        old = stored.get("version")
        coarse_done = any(e.get("resolution") == "coarse" for e in stored.get("done", []))
        if old is not None and old["self_collision"] != version["self_collision"]:
            ap.error(f"{out} holds sequences simulated with self-collision "
                     f"{old['self_collision']}; use another --out")
        # Manifests from before the option hold no entry: the scenes' own substeps (None). Fine
        # files do not depend on it, so only a folder that holds coarse files is guarded.
        if (old is not None and coarse_done
                and old.get("coarse_substeps") != version["coarse_substeps"]):
            ap.error(f"{out} holds coarse sequences simulated with substeps "
                     f"{old.get('coarse_substeps') or 'of the scene'}; use another --out")
        if old is not None and old["commit"] != version["commit"]:
            log(f"note: resuming files written at commit {old['commit']} at {version['commit']}")
    todo = [j for j in selected if not job_path(out, j).exists()]
    log(f"start ({version}): {len(selected)} jobs, {len(selected) - len(todo)} already done, "
        f"{status_summary(job_status(out, selected))}")
    t_start = time.perf_counter()
    done_est = 0.0
    total_est = sum(estimate_s(j) for j in todo)
    setup_key, setup = None, None
    failures = 0
    for k, job in enumerate(todo):
        path = job_path(out, job)
        # A claim per job: several runs may share the plan (e.g. a second one with --only,
        # or two full runs), and none starts a file another is simulating.
        with claim_output(out, path) as mine:
            if not mine:
                log(f"  {job['scene']} {job['material']} {job['resolution']}: running in "
                    f"another process, skipped")
                continue
            if path.exists():  # written meanwhile by another run
                log(f"  {job['scene']} {job['material']} {job['resolution']}: written by "
                    f"another run, skipped")
                continue
            key = (job["scene"], job["resolution"], job["frames"], job["seed"])
            try:
                if key != setup_key:
                    setup = scenes.setup_scene(job["scene"], job["resolution"], job["frames"],
                                               job["seed"])
                    setup_key = key
                seq, wall = run_job(job, out, setup, args, log)
            except Exception as e:  # log and go on with the next job; rerun to retry
                failures += 1
                log(f"FAILED {path.name} ({job['scene']}): {type(e).__name__}: {e}")
                continue
        done_est += estimate_s(job)
        elapsed = time.perf_counter() - t_start
        eta = elapsed / max(done_est, 1e-9) * (total_est - done_est)
        log(f"wrote {path.relative_to(out)} ({seq.frames.shape[1]} vertices, {len(seq)} frames, "
            f"{path.stat().st_size / 2**20:.1f} MiB) in {wall:.0f} s "
            f"({seq.metadata['ms_per_frame']:.0f} ms/frame); {k + 1}/{len(todo)} done, "
            f"ETA {eta / 60:.0f} min")
        entries = []
        for j in jobs:
            p = job_path(out, j)
            if p.exists():
                entries.append(dict(j, path=str(p.relative_to(out)), bytes=p.stat().st_size))
        atomic_write_text(manifest_path, json.dumps({"jobs": len(jobs), "version": version,
                                                     "done": entries}, indent=1))
    log(f"finished: {len(todo) - failures} written, {failures} failed, "
        f"{(time.perf_counter() - t_start) / 60:.1f} min")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
