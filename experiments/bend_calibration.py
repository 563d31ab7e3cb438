"""Why simulated cantilevers were short: the bending calibration, split into the discrete
energy, the clamped boundary and the XPBD solver (issue 24 item 2).

    PYTHONPATH=. python experiments/bend_calibration.py [--out DIR/bend_calibration.json] [--quick]

(a) Cylinder energy: the meshes the textile scenes and the data set use (pattern-mesher
    jittered sheets and the Cusick specimen at PD 10 and 30 mm, the structured cantilever
    strips 25 and 100 mm wide) are bent into exact cylinders of radius R = 10 PD and 30 PD
    with the axis at 0, 30, 45, 60, 90 degrees to the x axis. Ratio = sum_e 1/2 |C_e|^2
    (B = 1, the weights `cloth_model._hinges` builds) / (continuum B / (2 R^2) x area), with
    the area the hinges cover (sum_e (A_1 + A_2) / 3) and the whole area.
(b) Static minimum: the cantilever's settled shape as the minimum of the simulator's own
    discrete energy (stretch sum_e k_s A_e strain^2 / 2 + bending sum_h B |C_h|^2 / 2 +
    gravity; float64 Newton with an eigenvalue-modified dense Hessian, to |grad| < 1e-12 N or
    the float64 floor), one strip per overhang (1.2-2.4 x nominal c), interpolated as in
    `textile.cantilever`. Free strips, and "beam" strips whose columns move rigidly in x-z
    (no lateral freedom), at several PD; with the interior normalisation on the clamp line
    (weights built without pins, the old calibration) and with the clamped-boundary one.
(c) The XPBD one-iteration ratio r = h^2 B sum_k w_k K_k^2 per hinge on the PD 10 mm strips
    (30 fps x 20 substeps): an interior hinge (uniform gravity prediction, load carried by the
    stretch sweeps that follow) settles at B / (1 + r) with one iteration per substep.
(d) Which data-set scenes the clamp-rim normalisation touches: hinges whose weights change
    when the scene's pins are passed, per scene at PD 10 and 30 mm.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from wrinkle_jax.sim import cloth_model as CM  # noqa: E402
from wrinkle_jax.sim import materials as M  # noqa: E402
from wrinkle_jax.sim import patterns as P  # noqa: E402
from wrinkle_jax.sim import textile as T  # noqa: E402


def flat(g):
    """(V, 2) rest coordinates of a flat garment in its own plane, x along the world x axis
    (panels of a seamed pattern have separate UV frames, so UVs cannot be used directly)."""
    x = np.asarray(g.vertices, np.float64)
    x = x - x.mean(0)
    _, _, vt = np.linalg.svd(x, full_matrices=False)
    p = x @ vt[:2].T
    ex = vt[:2] @ np.array([1.0, 0.0, 0.0])
    ex /= np.linalg.norm(ex)
    return p @ np.array([[ex[0], ex[1]], [-ex[1], ex[0]]]).T


def cylinder(p, radius, axis_deg):
    a = math.radians(axis_deg)
    ax, perp = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    t, s = p @ ax, p @ perp - (p @ perp).mean()
    return (t[:, None] * np.r_[ax, 0.0] + (radius * np.sin(s / radius))[:, None] * np.r_[perp, 0]
            + (radius * (1 - np.cos(s / radius)))[:, None] * np.array([0.0, 0.0, 1.0]))


def cylinder_ratio(g, radius, axis_deg):
    """(energy / hinge-area reference, energy / whole-area reference), B = 1."""
    hidx, w, _ = CM._hinges(g)
    _, area = CM._uv_corner_geometry(g)
    x = cylinder(flat(g), radius, axis_deg)
    energy = 0.5 * np.sum(np.einsum("nk,nkd->nd", w, x[hidx]) ** 2)
    face = {tuple(sorted(t)): a for t, a in zip(np.asarray(g.faces).tolist(), area, strict=True)}
    h_area = sum(face[tuple(sorted(h[:3]))] + face[tuple(sorted((h[0], h[1], h[3])))]
                 for h in hidx.tolist())
    ref = 0.5 / radius ** 2
    return energy / (h_area / 3.0 * ref), energy / (area.sum() * ref)


def part_a():
    meshes = {}
    for pd in (0.01, 0.03):
        for seed in (0, 1):
            meshes[f"sheet_jitter pd={pd} seed={seed}"] = P.mesh_pattern(
                P.sheet_pattern(0.6, 0.6), pd, seed=seed).garment
        meshes[f"cusick pd={pd}"] = P.mesh_pattern(T.drape_pattern(), pd).garment
        meshes[f"strip25 pd={pd}"] = T.cantilever_strips([0.16], pd).garment
        meshes[f"strip100 pd={pd}"] = T.cantilever_strips([0.16], pd, width=0.1).garment
    out = {}
    for name, g in meshes.items():
        pd = float(name.split("pd=")[1].split()[0])
        row = {}
        for k in (10, 30):
            r = {a: cylinder_ratio(g, k * pd, a) for a in (0, 30, 45, 60, 90)}
            row[f"R={k}pd hinge-area"] = {str(a): round(v[0], 4) for a, v in r.items()}
            row[f"R={k}pd whole-area"] = {str(a): round(v[1], 4) for a, v in r.items()}
        out[name] = row
        print(name, json.dumps(row["R=10pd whole-area"]), flush=True)
    return out


def static_minimum(g, pinned, fab, clamp: bool, beam: bool):
    """Positions (V, 3) minimising the discrete energy with `pinned` at rest; |grad| max."""
    x0 = np.asarray(g.vertices, np.float64)
    n = g.num_vertices
    faces = np.asarray(g.faces, np.int64)
    uv, area = CM._uv_corner_geometry(g)
    vertex_area = np.bincount(faces.reshape(-1), np.repeat(area / 3.0, 3), minlength=n)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    euv = np.concatenate([uv[:, [0, 1]], uv[:, [1, 2]], uv[:, [2, 0]]])
    key = np.minimum(e[:, 0], e[:, 1]) * n + np.maximum(e[:, 0], e[:, 1])
    uniq, first, inv = np.unique(key, return_index=True, return_inverse=True)
    edges = e[first]
    rest = np.linalg.norm(euv[first, 1] - euv[first, 0], axis=1)
    e_area = np.bincount(inv, np.tile(area / 3.0, 3), minlength=len(uniq))
    hidx, hw, _ = CM._hinges(g, pinned if clamp else None)
    free = np.setdiff1d(np.arange(n), pinned)
    weight = fab.density * vertex_area * 9.81
    z_ref = x0[pinned, 2].mean()  # gravity relative to the clamp: keeps float64 resolution
    cols, col_of = np.unique(np.round(x0[free, 0], 9), return_inverse=True)

    def positions(q):
        if beam:  # columns move rigidly in x-z, y stays at rest
            q = q.reshape(-1, 2)
            q = jnp.stack([q[col_of, 0], jnp.asarray(x0[free, 1]), q[col_of, 1]], 1)
        return jnp.asarray(x0).at[free].set(q.reshape(-1, 3))

    def energy(q):
        x = positions(q)
        d = x[edges[:, 1]] - x[edges[:, 0]]
        strain = (jnp.sqrt(jnp.sum(d * d, 1)) - rest) / rest
        c = jnp.einsum("nk,nkd->nd", hw, x[hidx])
        return (0.5 * fab.stretch * jnp.sum(e_area * strain ** 2) + 0.5 * fab.bending
                * jnp.sum(c ** 2) + jnp.sum(weight * (x[:, 2] - z_ref)))

    e_f, g_f, h_f = jax.jit(energy), jax.jit(jax.grad(energy)), jax.jit(jax.hessian(energy))
    q = (np.stack([cols, np.full(len(cols), x0[0, 2])], 1) if beam else x0[free]).reshape(-1)
    gn = math.inf
    for _ in range(300):
        gr, hess = np.asarray(g_f(q)), np.asarray(h_f(q))
        gn = float(np.abs(gr).max())
        if gn < 1e-12:
            break
        lam, vec = np.linalg.eigh(hess)
        lam = np.maximum(np.abs(lam), 1e-8 * np.abs(lam).max())
        step = -(vec @ ((vec.T @ gr) / lam))
        e0, t = float(e_f(q)), 1.0
        while float(e_f(q + t * step)) > e0 and t > 1e-8:
            t *= 0.5
        if t <= 1e-8:
            break
        q = q + t * step
    return np.asarray(positions(q)), gn


def static_c(fab, pd, clamp, beam, width=0.025):
    nominal = M.fold_length(fab)
    overhangs = [float(v) for v in nominal * np.geomspace(1.2, 2.4, 7)]
    angles, worst = [], 0.0
    for l in overhangs:
        s = T.cantilever_strips([l], pd, width)
        x, gn = static_minimum(s.garment, s.clamped, fab, clamp, beam)
        worst = max(worst, gn)
        angles.append(T.chord_angle(x, s.tips[0], s.z_edge))
    c = T.bending_length(overhangs, angles)
    return {"c_mm": round(c * 1e3, 3), "c_over_nominal": round(c / nominal, 4),
            "max_abs_grad": worst}


def part_b(quick: bool):
    out = []
    for name in ("denim_light", "silk_chiffon"):
        fab = M.fabric(name)
        for clamp in (False, True):
            for beam, pds in ((True, (0.01, 0.005) if quick else (0.01, 0.005, 0.0025)),
                              (False, (0.01,) if quick else (0.01, 0.005))):
                for pd in pds:
                    t0 = time.perf_counter()
                    r = {"fabric": name, "pd_mm": pd * 1e3, "clamp_normalisation": clamp,
                         "strip": "beam" if beam else "free",
                         "nominal_c_mm": round(M.fold_length(fab) * 1e3, 3),
                         **static_c(fab, pd, clamp, beam),
                         "wall_s": round(time.perf_counter() - t0, 1)}
                    out.append(r)
                    print(json.dumps(r), flush=True)
    return out


def part_c():
    s = T.cantilever_strips(list(T.OVERHANGS), 0.01)
    g = s.garment
    hidx, hw, _ = CM._hinges(g, s.clamped)
    _, area = CM._uv_corner_geometry(g)
    va = np.bincount(np.asarray(g.faces).reshape(-1), np.repeat(area / 3, 3),
                     minlength=g.num_vertices)
    pin = np.zeros(g.num_vertices, bool)
    pin[s.clamped] = True
    act = ~pin[hidx].all(1)
    h = 1.0 / (30 * 20)
    out = {}
    for name, f in M.FABRICS.items():
        w = np.where(pin, 0.0, 1.0 / (f.density * va))
        r = (h * h * f.bending * (w[hidx] * hw ** 2).sum(1))[act]
        med = float(np.median(r))
        out[name] = {"r_median": round(med, 4), "r_max": round(float(r.max()), 4),
                     "B_eff_over_B_at_median": round(1 / (1 + med), 4)}
    print(json.dumps(out), flush=True)
    return out


def part_d():
    from wrinkle_jax.sim import scenes

    out = {}
    for name, sc in scenes.SCENES.items():
        pattern = P.make_pattern(sc.garment)
        for pd in (0.01, 0.03):
            mesh = P.mesh_pattern(pattern, pd, seed=0)
            # "rings" pins a subset of the top edge; the whole edge bounds what can change.
            pins = mesh.landmark_vertices(pattern, "top" if sc.pins == "rings" else sc.pins)
            _, w0, _ = CM._hinges(mesh.garment)
            _, w1, _ = CM._hinges(mesh.garment, pins)
            out[f"{name} pd={pd}"] = {"hinges": len(w0), "pins": len(pins),
                                      "changed": int((np.abs(w0 - w1).sum(1) > 0).sum())}
    print(json.dumps(out), flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="experiments/results/sim/textile/bend_calibration.json")
    ap.add_argument("--quick", action="store_true", help="fewer PDs in part (b)")
    ap.add_argument("--parts", default="abcd", help="which parts to (re)compute; the others "
                    "are kept from an existing output file")
    args = ap.parse_args(argv)
    parts = {"a": ("a_cylinder_energy_ratio", part_a), "c": ("c_xpbd_bias_pd10", part_c),
             "d": ("d_scene_hinges_changed", part_d),
             "b": ("b_static_minimum", lambda: part_b(args.quick))}
    try:
        with open(args.out) as fh:
            doc = json.load(fh)
    except FileNotFoundError:
        doc = {}
    for k in "acdb":
        if k in args.parts:
            key, fn = parts[k]
            doc[key] = fn()
    with open(args.out, "w") as fh:
        json.dump(doc, fh, indent=1)


if __name__ == "__main__":
    main()
