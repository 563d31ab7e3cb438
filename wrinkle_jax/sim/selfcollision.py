"""Cloth self-collision for the XPBD solver: a spatial hash and vertex-triangle proximity
constraints with a thickness (jittable, static shapes).

Method (Bridson, Fedkiw & Anderson 2002 proximity; Mueller et al. 2007 PBD constraints):

  candidates (rebuilt every `rebuild_every` substeps, at the substep's start positions x):
    * every triangle's box, grown by reach = thickness + margin, is entered in the (at most 8)
      cells of a uniform grid it overlaps; the cell size is the largest grown box extent, so a
      vertex inside a grown box always lies in one of that box's cells. Cells are hashed to
      uint32 keys and the entries sorted by key (one sort of 8 F keys).
    * each vertex reads up to `max_raw` entries of its own cell (two binary searches), keeps
      the first `max_box` triangles whose grown box holds it and that do not contain it (a
      cheap test), of those the ones closer than the reach (the exact test, the dear part), and
      compacts them into at most `max_contacts` slots. A pair closer than the thickness in
      the rest (pattern) shape gets 0.9 x its rest distance as its thickness. With
      `rest_exclusion`, pairs of one panel whose rest centroid distance is below it are
      skipped at the box test: a flat layer's own neighbours (2.7 per vertex at PD 30 mm,
      30 at PD 10 mm, measured on the skirt's rest pose) never become active yet filled the
      lists and the exact tests.
    * the per-vertex slots are moved into one flat list of at most `pairs_per_vertex` x V
      contacts (`flatten`), which the projections run over.
    * or the flat build (`build_pairs`, `raw_per_vertex` > 0; the fine default in session
      17): the same cells, but every bound is a total over the mesh (a fold fills a few
      vertices' lists while most have none), and where one is exceeded the nearest
      candidates are kept. On
      the skirt's fine poses the per-vertex bounds above kept only 6-11 % of the pairs
      closer than the thickness (they drop in cell and vertex order); the flat build 97-100 %.
    * or the blocked flat build (`selfcollision_blocks`, `block` > 0; the default of both
      resolutions since session 18): the flat build's contacts, from a centroid grid read in
      the 27 cells around a vertex, a cell's vertices tested in blocks against each triangle.
    * nothing is dropped silently: cell entries beyond `max_raw`, box hits beyond `max_box`
      and close triangles beyond `max_contacts` are counted (`Candidates.overflow`,
      accumulated in the solver state).
  projection (every substep, closest points computed once by `contact_frame`: after the
  cloth constraints, and again after the body contacts with the vertices the body moved held
  fixed, so a layer pressed between the body and another layer pushes that layer out instead
  of being pushed back into the body):
    for candidate (v, t), the closest point of t to the vertex at the substep's start
    (barycentrics b, clamped to t) and the unit direction d from it to the vertex are fixed;
        C = d . (p_v - sum_i b_i p_i) - thickness >= 0
    is projected with zero compliance (XPBD with alpha = 0 is PBD). Over the face d is the
    normal on the start side, so a vertex that passed through during the substep is sent
    back, not on. All contacts are solved together (Jacobi) and each vertex's correction is
    divided by its number of active contacts (Macklin et al. 2014), so it does not overshoot.
    No participant of a contact moves further than its violation (a kinematic vertex against
    a triangle whose closest point sits on kinematic corners would otherwise throw the free
    corner by c / b; see `project_pairs`).
    With `poke_repair` > 0 (`pokethrough`), a contact whose vertex lies on the other side of
    the layer than most of its one-ring (a poke-through) is directed back to the ring's side.
  not modelled: edge-edge proximity. Two edges can cross while every vertex keeps the
  thickness from every triangle; measured on coarse meshes (PD 30 mm, thickness 4 mm) this
  is the remaining failure, and a thickness of ~0.3 PD closes it on the test scenes.

Shapes: V vertices, F faces, K = max_contacts, R = max_raw, B = max_box, M = flat contacts.
Units: meters.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.numerics import normalize, safe_div, safe_norm, to_device
from wrinkle_jax.sim import aero, pokethrough, untangle

# The settings live in their own module, re-exported here (callers use either).
from wrinkle_jax.sim.selfcollision_config import (  # noqa: F401
    ADDED_SETTINGS,
    SelfCollisionConfig,
    key_settings,
    recorded_config,
    with_settings,
)

_SENTINEL = np.uint32(0xFFFFFFFF)  # key of unused cell entries (sorted last, never queried)
_PRIMES = (np.uint32(73856093), np.uint32(19349663), np.uint32(83492791))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SelfTopology:
    """Rest (pattern) geometry that bounds the thickness of nearby pairs.

    Attributes: uv (V, 2) m, a rest position per vertex (on a seam: one of its panels);
    panel (V,) int32, that panel; face_uv (F, 3, 2) m; face_panel (F,) int32; poke, the
    one-ring and face adjacency the poke-through repair reads (`pokethrough.PokeTopology`;
    None: no repair possible); vertex_faces (V, D) int32, incident faces padded with F (what
    `untangle` pairs a contact's triangle with; None: no untangling possible); near_faces
    (P, 2) int32, the pairs of faces of one panel, sharing no vertex, whose rest centroids lie
    closer than 2.4 median rest edges (`untangle.near_face_pairs`: what `rest_exclusion`
    keeps out of the contacts, which `untangle` tests on its own).
    """

    uv: Any
    panel: Any
    face_uv: Any
    face_panel: Any
    poke: Any = None
    vertex_faces: Any = None
    near_faces: Any = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Candidates:
    """Candidate triangles per vertex: tri (V, K) int32 (0 where unused), valid (V, K) bool,
    thickness (V, K) m (the pair's target distance), overflow (2,) int32: [cell entries not
    read (max_raw), triangles dropped untested (beyond max_box box hits) or close but beyond
    max_contacts]."""

    tri: Any
    valid: Any
    thickness: Any
    overflow: Any


def self_topology(garment) -> SelfTopology:
    """Rest geometry of a garment for self-collision (NumPy, once per mesh)."""
    faces = np.asarray(garment.faces)
    uv_faces = np.asarray(garment.uv_faces)
    uvs = np.asarray(garment.uvs, np.float32)
    panels = (np.zeros(len(faces), np.int32) if garment.panels is None
              else np.asarray(garment.panels, np.int32))
    vuv = np.zeros((garment.num_vertices, 2), np.float32)
    vpanel = np.zeros(garment.num_vertices, np.int32)
    vuv[faces.reshape(-1)] = uvs[uv_faces.reshape(-1)]
    vpanel[faces.reshape(-1)] = np.repeat(panels, 3)
    return SelfTopology(jnp.asarray(vuv), jnp.asarray(vpanel), jnp.asarray(uvs[uv_faces]),
                        jnp.asarray(panels),
                        pokethrough.poke_topology(faces, garment.num_vertices),
                        to_device(aero.incident_faces(faces, garment.num_vertices)),
                        to_device(untangle.near_face_pairs(faces, uvs[uv_faces], panels)))


def empty_candidates(num_vertices: int, cfg: SelfCollisionConfig) -> Candidates:
    """No candidates (a placeholder of the right shapes)."""
    k = (num_vertices, cfg.max_contacts)
    return Candidates(jnp.zeros(k, jnp.int32), jnp.zeros(k, bool), jnp.zeros(k, jnp.float32),
                      jnp.zeros(2, jnp.int32))


def _hash(g):
    """uint32 key of integer cells g (..., 3) int32; never the sentinel."""
    # A wrapping linear form, not the usual XOR: XOR of the products maps (i, j, k) and
    # (-i, -j, k) to one key, merging cells on opposite sides of the origin. Keys are only
    # sorted (no table); a rare collision only adds entries that the exact tests drop.
    u = g.astype(jnp.uint32)
    k = u[..., 0] * _PRIMES[0] + u[..., 1] * _PRIMES[1] + u[..., 2] * _PRIMES[2]
    return jnp.minimum(k, _SENTINEL - np.uint32(1))


def _cell_lists(x, tri, reach):
    """Triangles (F, 3, 3) entered in a uniform grid by their boxes grown by `reach`; per
    vertex of x (V, 3), where its own cell's entries lie in the sorted list.

    Returns: lo, hi (F, 3) grown boxes; stri (8F,) int32 triangle of each sorted entry;
    start (V,) and count (V,) int32, the vertex's cell entries stri[start:start + count].
    """
    lo = tri.min(1) - reach
    hi = tri.max(1) + reach
    # One cell holds the largest grown box, so every box overlaps at most 2 cells per axis.
    cell = jnp.maximum(jnp.max(hi - lo), 1e-6)
    glo = jnp.floor(lo / cell).astype(jnp.int32)
    ghi = jnp.floor(hi / cell).astype(jnp.int32)
    off = jnp.asarray(np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1)
                      .reshape(8, 3), jnp.int32)
    g = glo[:, None, :] + off[None]
    used = jnp.all(g <= ghi[:, None, :], axis=-1)
    keys = jnp.where(used, _hash(g), _SENTINEL).reshape(-1)
    order = jnp.argsort(keys)
    skeys = keys[order]
    stri = (order // 8).astype(jnp.int32)
    # Each vertex reads its own cell: [start, stop) in the sorted entries.
    kv = _hash(jnp.floor(x / cell).astype(jnp.int32))
    start = jnp.searchsorted(skeys, kv, side="left")
    count = jnp.searchsorted(skeys, kv, side="right") - start
    return lo, hi, stri, start.astype(jnp.int32), count.astype(jnp.int32)


def build_candidates(x, faces, topo: SelfTopology, cfg: SelfCollisionConfig) -> Candidates:
    """Candidate triangles of every vertex at positions x (V, 3) m; faces (F, 3) int32."""
    num_v = x.shape[0]
    reach = cfg.thickness + cfg.margin
    tri = x[faces]
    lo, hi, stri, start, count = _cell_lists(x, tri, reach)
    slot = jnp.arange(cfg.max_raw)
    read = slot[None] < count[:, None]
    t = stri[jnp.minimum(start[:, None] + slot[None], stri.shape[0] - 1)]        # (V, R)
    inside = jnp.all((lo[t] <= x[:, None]) & (x[:, None] <= hi[t]), axis=-1)
    touches = jnp.any(faces[t] == jnp.arange(num_v)[:, None, None], axis=-1)
    # Two stages, because the exact distance (three segment tests and a projection) costs far
    # more than the box test: the box test over all R entries, then the exact test only on
    # the first `max_box` that pass it.
    box = read & inside & ~touches
    if cfg.rest_exclusion > 0:
        # The pattern distance from the vertex to the triangle's centroid bounds the rest
        # distance from above, so only pairs closer than `rest_exclusion` at rest are dropped.
        centre = topo.face_uv.mean(1)                                      # (F, 2)
        dr = topo.uv[:, None] - centre[t]                                  # (V, R, 2)
        own = topo.face_panel[t] == topo.panel[:, None]
        box = box & ~(own & (jnp.sum(dr * dr, -1) < cfg.rest_exclusion ** 2))
    tb, okb = _compact(t, box, cfg.max_box)                                # (V, B)
    # The box test keeps every same-layer triangle around a vertex; the exact distance does
    # not (in a flat sheet they are >= ~0.8 PD away, beyond the reach).
    tt = tri[tb]
    _, near, _ = closest_point_triangle(x[:, None], tt[..., 0, :], tt[..., 1, :], tt[..., 2, :])
    keep = okb & (near < reach * reach)
    out_t, valid = _compact(tb, keep, cfg.max_contacts)                   # (V, K)
    out_h = jnp.where(valid, _pair_thickness(topo, jnp.arange(num_v)[:, None], out_t, cfg),
                      0.0)
    n_box = box.sum(1)
    dropped = (jnp.maximum(n_box - cfg.max_box, 0)
               + jnp.maximum(keep.sum(1) - cfg.max_contacts, 0))
    overflow = jnp.stack([jnp.maximum(count - cfg.max_raw, 0).sum(),
                          dropped.sum()]).astype(jnp.int32)
    return Candidates(out_t, valid, out_h, overflow)


def _pair_thickness(topo: SelfTopology, v, t, cfg: SelfCollisionConfig):
    """Target distance (m) of vertex v and triangle t (int arrays of one shape)."""
    # A pair closer at rest than the thickness (a vertex and a triangle two rings away on a
    # fine or irregular mesh) is only kept at 0.9 x its rest distance: no force in the rest
    # shape, yet a tight fold still cannot close through it.
    fu = topo.face_uv[t]
    fu = jnp.concatenate([fu, jnp.zeros(fu.shape[:-1] + (1,), fu.dtype)], -1)
    vu = topo.uv[v]
    vu = jnp.concatenate([vu, jnp.zeros(vu.shape[:-1] + (1,), vu.dtype)], -1)
    _, rest2, _ = closest_point_triangle(vu, fu[..., 0, :], fu[..., 1, :], fu[..., 2, :])
    same = topo.face_panel[t] == topo.panel[v]
    return jnp.where(same, jnp.minimum(cfg.thickness, 0.9 * jnp.sqrt(rest2)), cfg.thickness)


def prefix_rows(m):
    """Inclusive running count (N, G) int32 of m (N, G) in row-major order.

    A cumsum over the rows' totals and a log-depth scan within rows: XLA's CPU cumsum is a
    sequential loop (~7 ns per entry measured at 0.26-1.2 M entries, session 27; ~25 ns under
    load), the scan within rows vectorizes.
    """
    m = m.astype(jnp.int32)
    inrow = jax.lax.associative_scan(jnp.add, m, axis=1)
    tot = inrow[:, -1]
    return inrow + (jnp.cumsum(tot) - tot)[:, None]


def prefix_sum(v, width: int = 256):
    """`jnp.cumsum` of an integer or bool vector v (N,) as int32, the same values: rows of
    `width` through `prefix_rows` (measured 1.5-2x faster at 35 k-1.2 M entries, session 27).
    Short vectors use the plain cumsum."""
    n = v.shape[0]
    if n < 16 * width:
        return jnp.cumsum(v.astype(jnp.int32))
    rows = -(-n // width)
    p = jnp.pad(v.astype(jnp.int32), (0, rows * width - n)).reshape(rows, width)
    return prefix_rows(p).reshape(-1)[:n]


def _budget(per_vertex: float, num_vertices: int) -> int:
    return max(1, int(np.ceil(per_vertex * num_vertices)))


def _keep_nearest(valid, dist, size: int, top: float, bins: int = 64):
    """At most `size` of the valid entries (N,) bool, the nearest by dist (N,) first.

    Ranked by bins of width top / bins (dist < 0 in the first, >= top in the last; within
    the bin that does not fit whole, in order), so no sort: one histogram and two cumsums.
    Returns the (N,) bool mask of the kept entries.
    """
    b = jnp.clip(jnp.floor(dist * (bins / top)), 0, bins - 1).astype(jnp.int32)
    hist = jnp.zeros(bins, jnp.int32).at[b].add(valid.astype(jnp.int32))
    cum = jnp.cumsum(hist)
    whole = jnp.sum(cum <= size)                     # the first `whole` bins fit entirely
    room = size - jnp.where(whole > 0, cum[jnp.maximum(whole - 1, 0)], 0)
    partial = valid & (b == whole)
    return (valid & (b < whole)) | (partial & (prefix_sum(partial) <= room))


def _select(valid, dist, size: int, top: float):
    """Indices (size,) int32 of at most `size` valid entries of (N,), the nearest by dist
    first when more are valid (`_keep_nearest`), in order; the (size,) bool mask of used
    slots; and the number of valid entries left out (int32)."""
    n = valid.sum()
    # The ranking costs a histogram over all N entries: only when the bound is exceeded.
    keep = jax.lax.cond(n > size, lambda: _keep_nearest(valid, dist, size, top),
                        lambda: valid)
    pos = jnp.where(keep, prefix_sum(keep) - 1, size)
    idx = jnp.zeros(size, jnp.int32).at[pos].set(jnp.arange(valid.shape[0], dtype=jnp.int32),
                                                  mode="drop")
    return idx, jnp.arange(size) < jnp.minimum(n, size), jnp.maximum(n - size, 0)


def build_pairs(x, faces, topo: SelfTopology, cfg: SelfCollisionConfig) -> tuple[Pairs, Any]:
    """The flat build: the contact list at positions x (V, 3) m; faces (F, 3) int32.

    Every bound is a total over the mesh, not per vertex (a fold fills a few vertices' lists
    while most vertices have none):
      * all vertices' cell entries are read into one list of ceil(raw_per_vertex x V) slots,
        each vertex its whole cell (no per-vertex padding);
      * the sphere test (|x - centroid| - circumradius < reach, a lower bound of the
        distance, so nothing within the reach is lost; tighter than the grown box) keeps at
        most ceil(box_per_vertex x V) triangles for the exact distance, the nearest by that
        bound first;
      * of those within the reach, at most ceil(pairs_per_vertex x V) contacts, the nearest
        first (a budget cut leaves far pairs out, never the touching ones).
    Returns: the contacts (`Pairs`, in vertex order within each distance bin) and overflow
    (3,) int32: cell entries not read, triangles not given the exact test, contacts beyond
    the list.
    """
    num_v = x.shape[0]
    n_raw = _budget(cfg.raw_per_vertex, num_v)
    n_box = _budget(cfg.box_per_vertex, num_v)
    n_pairs = max_pairs(num_v, cfg)
    reach = cfg.thickness + cfg.margin
    tri = x[faces]
    _, _, stri, start, count = _cell_lists(x, tri, reach)
    ends = prefix_sum(count)
    offs = ends - count
    # The vertex of each slot: the number of vertices whose slots start at or before it,
    # minus one (a vertex with an empty cell starts where the next one does, so the last
    # of them, the owner, is counted last). One scatter-add of V and one cumsum, no search.
    first = jnp.zeros(n_raw, jnp.int32).at[offs].add(1, mode="drop")
    owner = jnp.maximum(prefix_sum(first) - 1, 0)
    slot = jnp.arange(n_raw, dtype=jnp.int32)
    read = slot < ends[-1]
    t = stri[jnp.clip(slot + (start - offs)[owner], 0, stri.shape[0] - 1)]
    # Per-entry data as one row gather per side (separate gathers of each field cost ~2x).
    centre = tri.mean(1)                                                  # (F, 3)
    radius = jnp.sqrt(jnp.max(jnp.sum((tri - centre[:, None]) ** 2, -1), -1))
    fdat = jnp.concatenate([centre, radius[:, None], topo.face_uv.mean(1),
                            topo.face_panel[:, None].astype(x.dtype)], 1)[t]   # (N, 7)
    vdat = jnp.concatenate([x, topo.uv, topo.panel[:, None].astype(x.dtype)], 1)[owner]
    lower = safe_norm(vdat[:, :3] - fdat[:, :3]) - fdat[:, 3]            # <= distance, m
    hit = read & (lower < reach) & ~jnp.any(faces[t] == owner[:, None], -1)
    if cfg.rest_exclusion > 0:
        dr = vdat[:, 3:5] - fdat[:, 4:6]
        own = vdat[:, 5] == fdat[:, 6]
        hit = hit & ~(own & (jnp.sum(dr * dr, -1) < cfg.rest_exclusion ** 2))
    sel, ok, lost_box = _select(hit, lower, n_box, reach)
    bv, bt = owner[sel], t[sel]
    tt = tri[bt]
    _, near, _ = closest_point_triangle(x[bv], tt[:, 0], tt[:, 1], tt[:, 2])
    dist = jnp.sqrt(jnp.maximum(near, 0.0))
    sel, pok, lost_pairs = _select(ok & (dist < reach), dist, n_pairs, reach)
    pv, pt = bv[sel], bt[sel]
    h = jnp.where(pok, _pair_thickness(topo, pv, pt, cfg), 0.0)
    overflow = jnp.stack([jnp.maximum(ends[-1] - n_raw, 0), lost_box,
                          lost_pairs]).astype(jnp.int32)
    return Pairs(jnp.where(pok, pv, 0), jnp.where(pok, pt, 0), h, pok), overflow


def _compact(t, keep, size: int):
    """The entries of t (V, N) where keep (V, N) bool, moved to the front in order, at most
    `size` per row: (V, size) int32 (0 where unused) and the (V, size) bool mask."""
    pos = jnp.where(keep, jnp.cumsum(keep, axis=1) - 1, size)  # out of range -> dropped
    rows = jnp.broadcast_to(jnp.arange(t.shape[0])[:, None], pos.shape)
    out = jnp.zeros((t.shape[0], size), jnp.int32).at[rows, pos].set(t, mode="drop")
    valid = jnp.arange(size)[None] < keep.sum(1)[:, None]
    return out, valid


def _segment_closest(p, a, b):
    """Parameter t (...) of the point of segment a-b closest to p, and the squared distance."""
    ab = b - a
    t = jnp.clip(safe_div(jnp.sum((p - a) * ab, -1), jnp.sum(ab * ab, -1)), 0.0, 1.0)
    d = p - a - t[..., None] * ab
    return t, jnp.sum(d * d, -1)


def closest_point_triangle(p, a, b, c):
    """Closest point of triangles a, b, c to points p (all (..., 3) m).

    Returns:
      barycentrics (..., 3) of the closest point, the squared distance (...) m^2, and the
      unit normal (..., 3) of the triangle (guarded when degenerate).
    """
    n = normalize(jnp.cross(b - a, c - a))
    h = jnp.sum((p - a) * n, -1)
    bary = _barycentric(p - h[..., None] * n, a, b, c)
    inside = jnp.all(bary >= 0, -1)
    t0, d0 = _segment_closest(p, a, b)
    t1, d1 = _segment_closest(p, b, c)
    t2, d2 = _segment_closest(p, c, a)
    z = jnp.zeros_like(t0)
    b0 = jnp.stack([1 - t0, t0, z], -1)
    b1 = jnp.stack([z, 1 - t1, t1], -1)
    b2 = jnp.stack([t2, z, 1 - t2], -1)
    use0 = (d0 <= d1) & (d0 <= d2)
    use1 = ~use0 & (d1 <= d2)
    edge_b = jnp.where(use0[..., None], b0, jnp.where(use1[..., None], b1, b2))
    edge_d = jnp.minimum(jnp.minimum(d0, d1), d2)
    return (jnp.where(inside[..., None], bary, edge_b), jnp.where(inside, h * h, edge_d), n)


def _barycentric(q, a, b, c):
    """Barycentric coordinates (..., 3) of q in triangle a, b, c (guarded when degenerate)."""
    e0, e1, e2 = b - a, c - a, q - a
    d00 = jnp.sum(e0 * e0, -1)
    d01 = jnp.sum(e0 * e1, -1)
    d11 = jnp.sum(e1 * e1, -1)
    d20 = jnp.sum(e2 * e0, -1)
    d21 = jnp.sum(e2 * e1, -1)
    den = d00 * d11 - d01 * d01
    bv = safe_div(d11 * d20 - d01 * d21, den)
    bw = safe_div(d00 * d21 - d01 * d20, den)
    return jnp.stack([1.0 - bv - bw, bv, bw], -1)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Pairs:
    """A flat, bounded contact list: vertex (M,) int32, tri (M,) int32, thickness (M,) m,
    valid (M,) bool (unused slots name vertex 0 and triangle 0 and are never active)."""

    vertex: Any
    tri: Any
    thickness: Any
    valid: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ContactFrame:
    """Per contact, what stays fixed over a substep (from its start positions): idx (M, 3)
    triangle vertices, bary (M, 3) closest-point barycentrics, d (M, 3) unit direction from
    the closest point to the vertex."""

    idx: Any
    bary: Any
    d: Any


def max_pairs(num_vertices: int, cfg: SelfCollisionConfig) -> int:
    """Static length M of the flat contact list (see `pairs_per_vertex`)."""
    if cfg.pairs_per_vertex <= 0:
        return num_vertices * cfg.max_contacts
    return max(1, int(np.ceil(cfg.pairs_per_vertex * num_vertices)))


def flatten(cand: Candidates, size: int) -> tuple[Pairs, Any]:
    """The valid (vertex, triangle) slots of cand moved into a flat list of `size`, in
    vertex order; returns the list and the number of valid slots that did not fit (int32)."""
    num_v, k = cand.tri.shape
    valid = cand.valid.reshape(-1)
    pos = jnp.where(valid, prefix_sum(valid) - 1, size)      # out of range -> dropped
    vert = jnp.repeat(jnp.arange(num_v, dtype=jnp.int32), k)

    def put(a, fill):
        return jnp.full((size,), fill, a.dtype).at[pos].set(a, mode="drop")

    n = valid.sum()
    pairs = Pairs(put(vert, 0), put(cand.tri.reshape(-1), 0),
                  put(cand.thickness.reshape(-1), 0.0), jnp.arange(size) < n)
    return pairs, jnp.maximum(n - size, 0).astype(jnp.int32)


def contact_frame(x, faces, pairs: Pairs, sides=None) -> ContactFrame:
    """Closest points and directions of the contacts at the substep's start positions x
    (V, 3) m (computed once per substep, shared by every projection pass). sides: optional
    (M,) from `pokethrough.repair_sides`; where nonzero, the direction is the triangle's
    normal times it (a poked-through vertex sent back to its one-ring's side)."""
    idx = faces[pairs.tri]                                                # (M, 3)
    xt = x[idx]
    xv = x[pairs.vertex]
    bary, d2, n = closest_point_triangle(xv, xt[:, 0], xt[:, 1], xt[:, 2])
    off = xv - jnp.einsum("mc,mcd->md", bary, xt)
    side = jnp.where(jnp.sum(off * n, -1) >= 0, 1.0, -1.0)[:, None] * n
    # Exactly on the surface the direction is undefined: fall back to the normal.
    d = jnp.where((d2 > 1e-12)[:, None], normalize(off), side)
    if sides is not None:
        d = jnp.where((sides != 0)[:, None], sides[:, None] * n, d)
    return ContactFrame(idx, bary, d)


def project_pairs(p, w, pairs: Pairs, frame: ContactFrame):
    """One Jacobi pass over a flat contact list (see `project_self` for the constraint).

    Args: p (V, 3) predicted positions, m; w (V,) inverse masses (0 = kinematic).
    Returns: (V, 3) corrected positions, and the number of active contacts (int32).
    """
    idx, bary, d = frame.idx, frame.bary, frame.d
    vert = pairs.vertex
    c = jnp.sum(d * (p[vert] - jnp.einsum("mc,mcd->md", bary, p[idx])), -1) - pairs.thickness
    active = pairs.valid & (c < 0)
    wt = w[idx]
    wv = w[vert]
    # The PBD step moves the vertex by w_v dlam and triangle vertex i by w_i b_i dlam, with
    # dlam = -c / (w_v + sum_i w_i b_i^2). When every movable participant has a tiny weight
    # (a kinematic vertex against a triangle whose closest point sits on kinematic vertices,
    # b_free -> 0) that is -c / b_free: measured on cape_walk coarse, the two ends of the
    # pinned neckline meet at one point, and pin 119 against triangle (137 pinned, 138
    # pinned, 139 free) at b = (0, 0.998, 0.002) threw vertex 139 by 0.35 m in one pass and
    # 9 m in a frame. No participant is moved further than the violation: the denominator
    # is at least max(w_v, w_i b_i), which leaves every ordinary contact unchanged (there
    # the sum already exceeds it, e.g. 4/3 w against w at the centroid).
    den = jnp.maximum(wv + jnp.sum(wt * bary * bary, -1),
                      jnp.maximum(wv, jnp.max(wt * bary, -1)))
    dlam = jnp.where(active, safe_div(-c, den), 0.0)                      # (M,), m
    dirn = dlam[:, None] * d                                               # (M, 3)
    act = active.astype(p.dtype)
    num_v = p.shape[0]
    delta = (jnp.zeros_like(p).at[vert].add(wv[:, None] * dirn)
             .at[idx.reshape(-1)].add((-(wt * bary)[..., None] * dirn[:, None]).reshape(-1, 3)))
    cnt = (jnp.zeros(num_v, p.dtype).at[vert].add(act)
           .at[idx.reshape(-1)].add(jnp.repeat(act, 3)))
    return p + delta / jnp.maximum(cnt, 1.0)[:, None], active.sum().astype(jnp.int32)


def project_self(p, x, w, faces, cand: Candidates, cfg: SelfCollisionConfig):
    """One Jacobi pass of vertex-triangle thickness constraints.

    Per candidate, the closest point of the triangle to the vertex at the substep's start
    (barycentrics b, clamped to the triangle) and the direction d from it to the vertex are
    fixed; then C = d . (p_v - sum_i b_i p_i) - thickness >= 0. In the face region d is the
    normal on the vertex's start side, so a vertex that passed through the face during the
    substep is sent back, not on; over an edge or corner d points away from it, so a vertex
    above a convex ridge (which projects into neither face, and may lie below the extended
    plane of either) is pushed away from the ridge, never through it.

    Args:
      p: (V, 3) predicted positions, m. x: (V, 3) start-of-substep positions.
      w: (V,) inverse masses (0 = kinematic). faces: (F, 3) int32.
    Returns:
      (V, 3) corrected positions, and the number of active contacts (int32 scalar).
    """
    del cfg
    pairs, _ = flatten(cand, cand.tri.size)  # every slot: nothing dropped
    return project_pairs(p, w, pairs, contact_frame(x, faces, pairs))
