"""Coarse garment sequences by linear blend skinning: the MakeHuman helper garments (skirt,
tights) carried by the character's walk cycle.

For each garment, writes `<out>/makehuman_walk_<garment>.npz` (`meshio.save_sequence`): the
garment frames (T, V, 3) meters with its UVs, plus extra arrays

    body_frames     (T, Vb, 3) float32  posed body (group `body` of base.obj), meters
    body_faces      (Fb, 3) int32
    capsule_ends    (T, C, 2, 3) float32 posed capsule segments, meters
    capsule_radii   (C,) float32, meters
    capsule_bones   (C,) str
    base_vertex_ids (V,) int32  garment vertex -> base.obj vertex
    times           (T,) float32 animation frame of each output frame

and a preview PNG of a few frames of the skinned skirt over the body, plus a JSON report with
timings (pose stage and skinning stage, compile and run separately). Both go to
`outputs/character/` (git-ignored); `--refresh-results` writes them over the committed
`experiments/results/character/` instead.

    python -m experiments.make_lbs_sequences [--frames 100] [--out data/lbs] [--tiny]
                                             [--refresh-results]

The assets are fetched on first use (`wrinkle-jax assets fetch makehuman`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import character
from wrinkle_jax.assets_fetch import fetch_makehuman
from wrinkle_jax.fileio import atomic_write_bytes, atomic_write_text
from wrinkle_jax.meshio import make_sequence, save_sequence

ROOT = Path(__file__).resolve().parents[1]


@dataclasses.dataclass(frozen=True)
class LBSConfig:
    """What to generate.

    Attributes:
      num_frames: output frames per sequence.
      fps: output frame rate.
      anim_fps: frame rate of the walk cycle's keys (Blender's default 24; the 40-frame cycle
        then lasts 1.67 s, so 100 frames at 30 fps hold two full strides).
      garments: helper groups to skin.
      walk: walk cycle file stem (None: the first one).
      out_dir: where the .npz sequences go (git-ignored).
      preview: the preview PNG, relative to the repository; its folder also receives
        lbs_report.json (None: neither).
      preview_frames: how many frames the preview shows.
    """

    num_frames: int = 100
    fps: float = 30.0
    anim_fps: float = 24.0
    garments: tuple[str, ...] = character.GARMENT_GROUPS
    walk: str | None = None
    out_dir: str = "data/lbs"
    preview: str | None = "outputs/character/walk_skirt_lbs.png"
    preview_frames: int = 4


# The committed preview and report (`--refresh-results`).
RESULTS_PREVIEW = "experiments/results/character/walk_skirt_lbs.png"
TINY = LBSConfig(num_frames=6, garments=("helper-skirt",), out_dir="data/lbs/tiny",
                 preview=None)


def make_sequences(cfg: LBSConfig = LBSConfig()) -> dict:
    """Generate the sequences (and preview); returns a report with paths and timings."""
    timings: dict = {}
    t0 = time.perf_counter()
    fetch_makehuman()
    timings["fetch_check_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    char = character.load_character()
    anim = char.walk_cycle(cfg.walk)
    skel = char.skeleton
    body = char.body
    body_w = char.part_weights(body)
    caps = character.fit_capsules(skel, body.garment.vertices, body_w)
    timings["load_s"] = time.perf_counter() - t0

    times = anim.start + np.arange(cfg.num_frames, dtype=np.float32) * (cfg.anim_fps / cfg.fps)
    pose_stage = jax.jit(lambda t: character.walk_skinning_matrices(anim, skel, t))
    skin_stage = jax.jit(character.skin_frames)
    caps_stage = jax.jit(jax.vmap(character.pose_capsules, in_axes=(None, 0)))

    mats = _timed(timings, "pose", pose_stage, jnp.asarray(times))
    body_frames = _timed(timings, "skin_body", skin_stage, jnp.asarray(body.garment.vertices),
                         body_w, mats)
    cap_ends = np.asarray(caps_stage(caps, mats))
    extras = dict(body_frames=np.asarray(body_frames, np.float32),
                  body_faces=np.asarray(body.garment.faces, np.int32),
                  capsule_ends=cap_ends.astype(np.float32),
                  capsule_radii=np.asarray(caps.radii, np.float32),
                  capsule_bones=np.asarray(caps.names), times=times)
    out_dir = ROOT / cfg.out_dir
    outputs, garment_frames = {}, {}
    for name in cfg.garments:
        part = char.garments.get(name) or character.extract_part(char.base, name)
        frames = _timed(timings, f"skin_{name}", skin_stage,
                        jnp.asarray(part.garment.vertices), char.part_weights(part), mats)
        frames = np.asarray(frames, np.float32)
        garment_frames[name] = frames
        seq = make_sequence(frames, part.garment.replace(vertices=frames[0]), fps=cfg.fps,
                            metadata={"name": f"makehuman_walk_{name}", "garment": name,
                                      "animation": anim.name, "anim_fps": cfg.anim_fps,
                                      "source": "experiments/make_lbs_sequences.py",
                                      "frame": "meters, Z up, character faces -Y",
                                      "uv": part.uv_report},
                            source=name)
        path = out_dir / f"makehuman_walk_{name.removeprefix('helper-')}.npz"
        save_sequence(path, seq, base_vertex_ids=part.vertex_ids, **extras)
        outputs[name] = _display(path)
        inside = np.asarray(jax.vmap(character.capsule_distance, in_axes=(0, 0, None))(
            jnp.asarray(frames), jnp.asarray(cap_ends), caps.radii) < 0)
        timings[f"{name}_inside_capsules_fraction"] = float(inside.mean())
    report = {"frames": cfg.num_frames, "fps": cfg.fps, "anim_fps": cfg.anim_fps,
              "walk": anim.name, "bones": skel.num_bones, "capsules": len(caps.names),
              "body_vertices": body.garment.num_vertices,
              "garments": {n: {"vertices": int(f.shape[1]), "path": outputs[n]}
                           for n, f in garment_frames.items()},
              "timings": timings}
    if cfg.preview and "helper-skirt" in garment_frames:
        t0 = time.perf_counter()
        png = ROOT / cfg.preview
        picks = np.linspace(0, cfg.num_frames - 1, cfg.preview_frames).round().astype(int)
        skirt = char.garments["helper-skirt"].garment
        render_preview(png, extras["body_frames"][picks], extras["body_faces"],
                       garment_frames["helper-skirt"][picks], np.asarray(skirt.faces),
                       titles=[f"frame {i}" for i in picks])
        report["preview"] = _display(png)
        report["preview_kib"] = round(png.stat().st_size / 1024, 1)
        timings["preview_s"] = time.perf_counter() - t0
        atomic_write_text(png.with_name("lbs_report.json"), json.dumps(report, indent=2))
    return report


def _display(path: Path) -> str:
    """A path relative to the repository when inside it."""
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def _timed(timings: dict, name: str, fn, *args):
    """Run a jitted stage twice: the first call's time is compile + run, the second run."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    timings[f"{name}_compile_and_run_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    timings[f"{name}_run_s"] = time.perf_counter() - t0
    return out


def render_preview(path, body_frames, body_faces, garment_frames, garment_faces, titles=(),
                   view_dir=(1.0, -0.6, 0.0),
                   title="MakeHuman walk cycle: LBS skirt helper over the skinned body") -> None:
    """Flat-shaded orthographic renders (painter's algorithm), one panel per frame.

    Args:
      body_frames: (N, Vb, 3); garment_frames: (N, Vg, 3) meters; faces index them.
      view_dir: direction from the model towards the camera (character frame).
    """
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    view = np.asarray(view_dir, np.float64)
    view /= np.linalg.norm(view)
    right = np.cross((0.0, 0.0, 1.0), view)
    right /= np.linalg.norm(right)
    up = np.cross(view, right)
    light = view + np.array([0.3, 0.0, 0.8])
    light /= np.linalg.norm(light)
    n = len(body_frames)
    fig, axes = plt.subplots(1, n, figsize=(1.9 * n, 4.4), dpi=100)
    for k, ax in enumerate(np.atleast_1d(axes)):
        polys, colors, depth = [], [], []
        for verts, faces, rgb in ((body_frames[k], body_faces, (0.80, 0.78, 0.74)),
                                  (garment_frames[k], garment_faces, (0.20, 0.45, 0.85))):
            p = np.asarray(verts, np.float64)[faces]  # (F, 3, 3)
            nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            shade = 0.25 + 0.75 * np.abs(nrm @ light)  # two-sided: helpers are open
            polys.append(np.stack([p @ right, p @ up], -1))
            colors.append(shade[:, None] * np.asarray(rgb))
            depth.append((p @ view).mean(1))
        order = np.argsort(np.concatenate(depth))  # far first
        rgb = np.concatenate(colors)[order]
        # Edges drawn in the face colour close the hairline gaps between flat polygons.
        pc = PolyCollection(np.concatenate(polys)[order], facecolors=rgb, edgecolors=rgb,
                            linewidths=0.3, antialiased=False)
        ax.add_collection(pc)
        xy = np.concatenate(polys).reshape(-1, 2)
        c = 0.5 * (xy.min(0) + xy.max(0))
        h = 0.5 * (xy.max(0) - xy.min(0)) + 0.02
        ax.set_xlim(c[0] - max(h[0], 0.42 * h[1]), c[0] + max(h[0], 0.42 * h[1]))
        ax.set_ylim(c[1] - h[1], c[1] + h[1])
        ax.set_aspect("equal")
        ax.axis("off")
        if k < len(titles):
            ax.set_title(titles[k], fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=LBSConfig.num_frames)
    ap.add_argument("--out", default=None,
                    help=f"output folder, relative to the repository (default {LBSConfig.out_dir}"
                         f", {TINY.out_dir} with --tiny)")
    ap.add_argument("--tiny", action="store_true", help="a 6-frame skirt-only smoke run")
    ap.add_argument("--refresh-results", action="store_true",
                    help=f"write the preview and report over the committed {RESULTS_PREVIEW} "
                         f"(default: {LBSConfig.preview})")
    args = ap.parse_args(argv)
    cfg = TINY if args.tiny else LBSConfig(num_frames=args.frames)
    if args.refresh_results and not args.tiny:
        cfg = dataclasses.replace(cfg, preview=RESULTS_PREVIEW)
    if args.out:
        cfg = dataclasses.replace(cfg, out_dir=args.out)
    print(json.dumps(make_sequences(cfg), indent=2))


if __name__ == "__main__":
    main()
