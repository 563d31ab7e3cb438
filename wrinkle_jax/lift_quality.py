"""How well a lift met its goal: the lifted mesh's own normal map against the map it followed.

The lift deforms the upsampled coarse frame p0 so that its normals follow the enhanced map N*
(`wrinkle_jax.lift`). Its solver settings (iteration cap, warm start, subdivision level) trade
time against how closely it gets there, so the measure of a lift is taken where its goal is:

  * re-bake the lifted mesh with the same UV charts onto N*'s pixels (`normalmap.bake`,
    smooth vertex normals) and compare texel by texel, inside the garment mask: the angle
    between the re-baked normal and N* (median, mean, 90th percentile, degrees);
  * the detail-band energy of both maps (`detail.band_rms` on their detail representations,
    N*'s branch for both): RMS of the tangential detail per band, and the ratio lifted / N*
    (1 = the lifted surface carries N*'s wrinkle energy; < 1 = it smoothed it away);
  * the vertex difference to a reference solution (e.g. the same lift run to convergence),
    mm RMS and max; the number of vertices inside a body (signed distance < 0), when a body
    is given; and the displacement from p0 on the mesh's boundary rim (mm RMS and max, and its
    raggedness: the RMS difference between a rim vertex's displacement and the mean of its
    rim neighbours'), since a map with strong detail at a chart edge can leave a ragged rim.

A map baked from a mesh measures ~0 degrees against that mesh, whatever its shape; a map baked
from p0 itself (no detail) is met by p0 (zero displacement).

Shapes and units: vertices (V, 3) float32 meters; maps (H, W, 3) unit normals; angles in
degrees; distances in millimetres in the results.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import bodies as body_lib
from wrinkle_jax import detail, mesh, normalmap

__all__ = ["LiftQuality", "RimTopology", "lift_quality", "quality_plan", "rim_topology"]


@dataclasses.dataclass(frozen=True)
class LiftQuality:
    """The quality of one lifted frame (plain floats; None where not measured).

    Attributes:
      angle_median_deg, angle_mean_deg, angle_p90_deg: angle between the re-baked lifted
        normals and N* over the garment texels, degrees.
      texels: garment texels compared.
      band_rms_lifted, band_rms_target: band name (`detail.BAND_SIGMAS`) -> RMS of the
        tangential detail of the re-baked map and of N* (unit-normal components).
      band_ratio: band name -> lifted / target (0 when the target has no energy there).
      vs_reference_mm_rms, vs_reference_mm_max: distance to a reference solution, mm.
      inside: vertices with negative signed distance to the body (None without a body).
      rim_mm_rms, rim_mm_max: |lifted - p0| over the boundary vertices, mm.
      rim_ragged_mm_rms: RMS of |d_i - mean of d over i's rim neighbours| on the rim, mm.
      interior_mm_rms: |lifted - p0| RMS over the other vertices, mm (for scale).
    """

    angle_median_deg: float
    angle_mean_deg: float
    angle_p90_deg: float
    texels: int
    band_rms_lifted: dict
    band_rms_target: dict
    band_ratio: dict
    vs_reference_mm_rms: float | None = None
    vs_reference_mm_max: float | None = None
    inside: int | None = None
    rim_mm_rms: float | None = None
    rim_mm_max: float | None = None
    rim_ragged_mm_rms: float | None = None
    interior_mm_rms: float | None = None

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class RimTopology:
    """The boundary rim of a mesh (NumPy, built once per topology by `rim_topology`).

    Attributes:
      on_rim: (V,) bool, vertex on a boundary edge.
      edges: (E, 2) int boundary edges (vertex pairs).
      degree: (V,) int rim neighbours of every vertex (0 off the rim).
    """

    on_rim: np.ndarray
    edges: np.ndarray
    degree: np.ndarray


def rim_topology(faces, num_vertices: int) -> RimTopology:
    """The boundary edges (used by one face only) of a triangle mesh and their vertices."""
    edges, counts = mesh.edge_face_counts(np.asarray(faces))
    rim = edges[counts == 1].astype(np.int64)
    degree = np.bincount(rim.reshape(-1), minlength=num_vertices)
    return RimTopology(degree > 0, rim, degree)


def quality_plan(fine_garment: mesh.Garment, layout: normalmap.UVLayout) -> normalmap.RasterPlan:
    """The raster plan that re-bakes a lifted mesh onto N*'s pixels (the fine mesh's own UV
    triangles, N*'s `layout`); built once per topology, in NumPy."""
    return normalmap.make_plan(fine_garment, layout=layout)


@functools.partial(jax.jit, static_argnames=("sigma",))
def _map_terms(plan: normalmap.RasterPlan, lifted, normal_map, sigma: float):
    """Per-texel angles (H, W) degrees, the compared texels (H, W) bool and the band RMS of
    the re-baked map and of N* (their detail maps on N*'s branch)."""
    baked = normalmap.bake(plan, lifted, True)
    target = jnp.asarray(normal_map, baked.dtype)
    # Garment texels only (not the seam gutter), where N* holds a normal.
    valid = (plan.mask[..., 0] > 0) & (jnp.sum(target * target, -1) > 0.25)
    cos = jnp.clip(jnp.sum(baked * target, -1), -1.0, 1.0)
    angles = jnp.degrees(jnp.arccos(cos))
    m = valid[None, ..., None].astype(baked.dtype)
    rgb = lambda n: normalmap.to_rgb(n)[None] * m  # noqa: E731
    d_target, d_lifted = detail.on_reference_branch_rgb(rgb(target), [rgb(baked)], m, sigma)
    bands = detail.band_rms_pair(d_lifted, d_target, m)
    return angles, valid, {k: (a[0], b[0]) for k, (a, b) in bands.items()}


def lift_quality(lifted, normal_map, plan: normalmap.RasterPlan, *, vertices0=None,
                 reference=None, body=None, rim: RimTopology | None = None,
                 sigma: float = detail.DEFAULT_SIGMA) -> LiftQuality:
    """Measure one lifted frame against the map it was lifted from (see the module docstring).

    Args:
      lifted: (V, 3) lifted vertices, meters (after any body push-out: what is delivered).
      normal_map: (H, W, 3) N*, the enhanced map the lift followed.
      plan: `quality_plan(fine_garment, layout)` of the lifted mesh on N*'s layout.
      vertices0: (V, 3) the upsampled coarse frame p0 the lift started from (for the rim
        terms; None skips them).
      reference: (V, 3) another solution of the same frame (e.g. the converged lift) to
        measure the distance to; None skips it.
      body: a `bodies` body (meters) to count penetrating vertices; None skips it.
      rim: `rim_topology` of the lifted mesh (built from `plan.faces` when None).
      sigma: the detail representation's low-pass radius, texels (`detail.DEFAULT_SIGMA`).
    Returns:
      LiftQuality.
    """
    lifted = jnp.asarray(lifted, jnp.float32)
    angles, valid, bands = _map_terms(plan, lifted, jnp.asarray(normal_map), float(sigma))
    a = np.asarray(angles)[np.asarray(valid)]
    if a.size == 0:
        raise ValueError("lift_quality: no garment texel carries a normal of N*")
    band_l = {k: float(v[0]) for k, v in bands.items()}
    band_t = {k: float(v[1]) for k, v in bands.items()}
    out = dict(angle_median_deg=float(np.median(a)), angle_mean_deg=float(a.mean()),
               angle_p90_deg=float(np.percentile(a, 90)), texels=int(a.size),
               band_rms_lifted=band_l, band_rms_target=band_t,
               band_ratio={k: band_l[k] / band_t[k] if band_t[k] > 0 else 0.0 for k in band_t})
    p = np.asarray(lifted, np.float64)
    if reference is not None:
        d = 1e3 * np.linalg.norm(p - np.asarray(reference, np.float64), axis=-1)
        out.update(vs_reference_mm_rms=float(np.sqrt(np.mean(d * d))),
                   vs_reference_mm_max=float(d.max()))
    if body is not None:
        out["inside"] = int(jnp.sum(body_lib.query(body, lifted).distance < 0))
    if vertices0 is not None:
        rim = rim_topology(np.asarray(plan.faces), len(p)) if rim is None else rim
        disp = 1e3 * (p - np.asarray(vertices0, np.float64))
        norm = np.linalg.norm(disp, axis=-1)
        on = rim.on_rim
        if on.any():
            # Mean displacement of each rim vertex's rim neighbours: a smooth rim moves like
            # its neighbours, a ragged one does not.
            acc = np.zeros_like(disp)
            np.add.at(acc, rim.edges[:, 0], disp[rim.edges[:, 1]])
            np.add.at(acc, rim.edges[:, 1], disp[rim.edges[:, 0]])
            mean_nb = acc[on] / rim.degree[on][:, None]
            ragged = np.linalg.norm(disp[on] - mean_nb, axis=-1)
            out.update(rim_mm_rms=float(np.sqrt(np.mean(norm[on] ** 2))),
                       rim_mm_max=float(norm[on].max()),
                       rim_ragged_mm_rms=float(np.sqrt(np.mean(ragged ** 2))))
        if (~on).any():
            out["interior_mm_rms"] = float(np.sqrt(np.mean(norm[~on] ** 2)))
    return LiftQuality(**out)
