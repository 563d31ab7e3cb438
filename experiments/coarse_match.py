"""Which downsampling makes a fine normal map look like a real coarse simulation's?

    python -m experiments.coarse_match [--frames 60,120,180] [--out FILE.json]

The enhancer trains on fine maps downsampled to look coarse (paper Sec. 5); at test time it sees
real coarse (PD 30 mm) simulations. This compares, on the same scene, motion and frames
(skirt_dance, silk_charmeuse, seed 0), the detail statistics of the real coarse map with those
of the fine map downsampled by several factors (texels of 2 mm): mean |first difference| and
mean |second difference| of the unit-normal field inside the garment. The coarse simulation is
run here if `data/sequences/skirt_dance/silk_charmeuse_coarse_s0.npz` does not exist (~40 s).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from wrinkle_jax import meshio, normalmap
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]
FACTORS = (1, 3, 5, 8, 10, 15, 20)


def detail(n, mask) -> tuple[float, float]:
    """Mean |n(x+1) - n(x)| over both axes and mean |n(x+1) - 2 n(x) + n(x-1)| along x."""
    m = np.asarray(mask[..., 0]) > 0.5
    n = np.asarray(n)
    dx = np.linalg.norm(n[:, 1:] - n[:, :-1], axis=-1)
    dy = np.linalg.norm(n[1:] - n[:-1], axis=-1)
    d2 = np.linalg.norm(n[:, 2:] - 2 * n[:, 1:-1] + n[:, :-2], axis=-1)
    first = np.r_[dx[m[:, 1:] & m[:, :-1]], dy[m[1:] & m[:-1]]].mean()
    second = d2[m[:, 2:] & m[:, 1:-1] & m[:, :-2]].mean()
    return float(first), float(second)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="60,120,180")
    ap.add_argument("--texel", type=float, default=normalmap.DEFAULT_TEXEL_SIZE)
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "coarse_match.json"))
    args = ap.parse_args(argv)
    frames = [int(f) for f in args.frames.split(",")]
    seq_dir = ROOT / "data" / "sequences" / "skirt_dance"
    fine = meshio.load_sequence(seq_dir / "silk_charmeuse_fine_s0.npz")
    coarse_path = seq_dir / "silk_charmeuse_coarse_s0.npz"
    if not coarse_path.exists():
        sim = scenes.simulate("skirt_dance", "silk_charmeuse", "coarse", max(frames) + 1, seed=0)
        scenes.save_simulation(coarse_path, sim)
    coarse = meshio.load_sequence(coarse_path)
    pf = normalmap.make_plan(fine.garment, texel_size=args.texel)
    pc = normalmap.make_plan(coarse.garment, texel_size=args.texel)
    rows = {"coarse_pd30": [], "fine_pd10": [], **{f"fine_ds{f}": [] for f in FACTORS}}
    for t in frames:
        nf = normalmap.bake(pf, jnp.asarray(fine.frames[t]))
        rows["coarse_pd30"].append(detail(normalmap.bake(pc, jnp.asarray(coarse.frames[t])),
                                          pc.mask))
        rows["fine_pd10"].append(detail(nf, pf.mask))
        for f in FACTORS:
            rows[f"fine_ds{f}"].append(detail(
                normalmap.downsample_like_coarse(nf, pf.mask, float(f)), pf.mask))
    table = {k: dict(zip(("first_diff", "second_diff"), np.mean(v, axis=0).round(5).tolist(),
                         strict=True)) for k, v in rows.items()}
    ref = np.array(list(table["coarse_pd30"].values()))
    best = min(FACTORS, key=lambda f: float(np.abs(
        np.log(np.array(list(table[f"fine_ds{f}"].values())) / ref)).sum()))
    out = {"scene": "skirt_dance", "material": "silk_charmeuse", "frames": frames,
           "texel_size_m": args.texel, "detail": table, "best_factor": best,
           "best_factor_texel_m": best * args.texel}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
