"""Which contacts a candidate build keeps: of the vertex-triangle pairs closer than the
thickness in stored poses, the share each self-collision setting puts in its contact list.

    python -m experiments.self_collision_candidates [--data data/sequences]
        [--scene skirt_dance] [--material silk_charmeuse] [--resolution fine]
        [--frames 30,100,160,220,280]

Static (no simulation): the poses are a stored data-set sequence (simulated without
self-collision, so its layers touch and cross). The reference is the flat build without rest
exclusion and with room for 40 contacts per vertex (nearest kept, so every pair closer than
the thickness is in it); each setting's list is compared with its violated pairs
(distance < the pair's target thickness). Prints one line per frame and setting.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.meshio import load_sequence
from wrinkle_jax.sim import scenes
from wrinkle_jax.sim import selfcollision as S

ROOT = Path(__file__).resolve().parents[1]


def settings(base: S.SelfCollisionConfig) -> dict:
    """Named settings: the per-vertex build of sessions 15 and 16, and the flat build."""
    r = dataclasses.replace
    return {
        "session 16 (per-vertex 512/64/16, 2 per vertex, exclusion 24 mm)":
            r(base, raw_per_vertex=0.0, max_raw=512, max_box=64, max_contacts=16,
              pairs_per_vertex=2.0),
        "session 16 without the rest exclusion":
            r(base, raw_per_vertex=0.0, max_raw=512, max_box=64, max_contacts=16,
              pairs_per_vertex=2.0, rest_exclusion=0.0),
        "session 15 (per-vertex 256/48/16, V x K list, no exclusion, margin 12 mm)":
            r(base, raw_per_vertex=0.0, max_raw=256, max_box=48, max_contacts=16,
              pairs_per_vertex=0.0, rest_exclusion=0.0, margin=0.012),
        "flat 450/32/4, exclusion 24 mm":
            r(base, raw_per_vertex=450.0, box_per_vertex=32.0, pairs_per_vertex=4.0),
        "flat 450/32/4, no exclusion":
            r(base, raw_per_vertex=450.0, box_per_vertex=32.0, pairs_per_vertex=4.0,
              rest_exclusion=0.0),
    }


def contact_list(faces, topo, cfg):
    """A jitted x -> (vertex, tri, valid) of the setting's contact list."""
    def build(x):
        if cfg.raw_per_vertex > 0:
            p, _ = S.build_pairs(x, faces, topo, cfg)
        else:
            p, _ = S.flatten(S.build_candidates(x, faces, topo, cfg),
                             S.max_pairs(x.shape[0], cfg))
        return p.vertex, p.tri, p.valid
    return jax.jit(build)


def as_set(vertex, tri, valid) -> set:
    v, t, ok = (np.asarray(a) for a in (vertex, tri, valid))
    return set(zip(v[ok].tolist(), t[ok].tolist(), strict=True))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--scene", default="skirt_dance")
    ap.add_argument("--material", default="silk_charmeuse")
    ap.add_argument("--resolution", default="fine")
    ap.add_argument("--frames", default="30,100,160,220,280")
    args = ap.parse_args(argv)
    seq = load_sequence(Path(args.data) / args.scene
                        / f"{args.material}_{args.resolution}_s0.npz")
    frames = np.asarray(seq.frames)
    model = scenes.setup_scene(args.scene, args.resolution, 1).model
    faces, topo = model.faces, model.self_topo
    if frames.shape[1] != int(model.vertex_area.shape[0]):
        raise SystemExit("the stored sequence's mesh differs from the scene's")
    base = scenes.SELF_COLLISION[args.resolution]
    ref_cfg = dataclasses.replace(base, rest_exclusion=0.0, raw_per_vertex=800.0,
                                  box_per_vertex=64.0, pairs_per_vertex=40.0)
    ref_build = jax.jit(lambda x: S.build_pairs(x, faces, topo, ref_cfg))
    builds = {k: contact_list(faces, topo, c) for k, c in settings(base).items()}
    closest = jax.jit(S.closest_point_triangle)
    uv, panel = np.asarray(topo.uv), np.asarray(topo.panel)
    centre = np.asarray(topo.face_uv).mean(1)
    for i in [int(a) for a in args.frames.split(",")]:
        x = jnp.asarray(frames[i])
        ref, over = ref_build(x)
        ok = np.asarray(ref.valid)
        v, t = np.asarray(ref.vertex)[ok], np.asarray(ref.tri)[ok]
        tri = frames[i][np.asarray(faces)[t]]
        _, d2, _ = closest(x[v], *(jnp.asarray(tri[:, k]) for k in range(3)))
        hit = np.sqrt(np.asarray(d2)) < np.asarray(ref.thickness)[ok]
        violated = set(zip(v[hit].tolist(), t[hit].tolist(), strict=True))
        own = np.asarray(topo.face_panel)[t] == panel[v]
        rest = np.linalg.norm(uv[v] - centre[t], axis=1)
        excluded = int((hit & own & (rest < base.rest_exclusion)).sum())
        print(f"frame {i}: pairs within the reach {ok.sum()} (reference overflow "
              f"{np.asarray(over).tolist()}), closer than the thickness {len(violated)}, "
              f"of them inside the rest exclusion {excluded}; load {os.getloadavg()[0]:.1f}")
        for name, build in builds.items():
            kept = as_set(*build(x))
            n = len(violated & kept)
            print(f"   {name}: {n}/{len(violated)} ({100 * n / max(len(violated), 1):.1f} %) "
                  f"kept, list {len(kept)}", flush=True)


if __name__ == "__main__":
    main()
