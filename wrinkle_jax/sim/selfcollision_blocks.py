"""The blocked flat build of self-collision candidates: the vertices of one hash cell are
tested against each of the cell's triangle entries in blocks of `SelfCollisionConfig.block`.

Why: every vertex of a cell reads the same entries, and the flat build (`selfcollision.
build_pairs`) reads them once per vertex: on the fine skirt's poses 7.2-7.5 M (vertex,
entry) reads per build, each a handful of row gathers, and XLA's CPU gather costs ~40 ns per
row (measured: 9.6 M rows of 10 floats in 380 ms, load 4.4-5.4). One build took 1.2-1.8 s,
the read stage 1.2-1.6 s of it. Here a slot is a (block, entry) pair: the triangle's data is
gathered once per slot and tested against the block's vertices as a dense (slots, block)
array, so the gathers drop by ~the block size while the tests stay the same.

Steps (shapes static; S = block-entry slots, G = block size, V vertices, F faces):
  * triangles put in a periodic grid by their centroid (`centroid_grid`: one argsort of F
    bucket ids, no 8 F-entry sort as in `selfcollision._cell_lists`); a vertex reads the 27
    cells around its own;
  * vertices sorted by their cell and cut into blocks of at most G vertices of one cell
    (at most V blocks, padded with -1);
  * the blocks' 27 ranges laid out in one list of S slots (slot -> range by one scatter-add
    and a cumsum, as the flat build does for vertices); entries beyond S are counted as
    (vertex, entry) reads not made;
  * the sphere test (a lower bound of the distance), the corner test and the rest exclusion
    on the dense (S, G) array; the nearest ceil(box_per_vertex x V) hits get the exact test;
    of those within the reach the nearest ceil(pairs_per_vertex x V) form the contact list
    (both bounds as in the flat build, overflow counted).
With room everywhere the contact set equals the flat build's: the 27 cells hold every
triangle that passes the sphere test, and the sphere, corner, exclusion and exact tests are
the flat build's.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import selfcollision as S


def _keep_nearest2(valid, dist, size: int, top: float, bins: int = 64):
    """`selfcollision._keep_nearest` on (N, G) arrays (row-major order within a bin)."""
    b = jnp.clip(jnp.floor(dist * (bins / top)), 0, bins - 1).astype(jnp.int32)
    hist = jnp.zeros(bins, jnp.int32).at[b].add(valid.astype(jnp.int32))
    cum = jnp.cumsum(hist)
    whole = jnp.sum(cum <= size)
    room = size - jnp.where(whole > 0, cum[jnp.maximum(whole - 1, 0)], 0)
    partial = valid & (b == whole)
    return (valid & (b < whole)) | (partial & (S.prefix_rows(partial) <= room))


def _select2(valid, dist, size: int, top: float):
    """`selfcollision._select` on (N, G) arrays: flat indices (size,) int32 (row * G + col)
    of at most `size` valid entries in row-major order, the nearest first when more are
    valid; the (size,) mask of used slots; the number left out.

    No scatter or cumsum over all N x G entries (each ~90-230 ms at 9.6 M, measured): output
    slot j finds its row by a running max over the rows' scattered offsets (N rows, `size`
    slots) and its column among the row's G entries.
    """
    num_rows, g = valid.shape
    n = valid.sum()
    keep = jax.lax.cond(n > size, lambda: _keep_nearest2(valid, dist, size, top),
                        lambda: valid)
    cnt = keep.sum(1, dtype=jnp.int32)
    off = S.prefix_sum(cnt) - cnt
    rows = jnp.arange(num_rows, dtype=jnp.int32)
    # Rows with entries have distinct offsets: mark each at its offset, carry it forward.
    mark = jnp.full(size, -1, jnp.int32).at[jnp.where(cnt > 0, off, size)].set(rows,
                                                                              mode="drop")
    row = jnp.maximum(jax.lax.cummax(mark), 0)
    rank = jnp.arange(size, dtype=jnp.int32) - off[row]
    # The column of the row's (rank + 1)-th kept entry: the columns whose inclusive count
    # is at most rank lie before it.
    inrow = jax.lax.associative_scan(jnp.add, keep[row].astype(jnp.int32), axis=1)
    col = jnp.sum(inrow <= rank[:, None], axis=1, dtype=jnp.int32)
    used = jnp.arange(size) < jnp.minimum(n, size)
    idx = jnp.where(used, row * g + jnp.minimum(col, g - 1), 0)
    return idx, used, jnp.maximum(n - size, 0)


def vertex_blocks(kv, g: int):
    """Vertices grouped by cell key kv (V,) uint32 into blocks of at most g of one cell.

    Returns vid (V, g) int32, the vertices of each block (-1 unused; blocks past the last
    are all -1), and the number of blocks (int32).
    """
    num_v = kv.shape[0]
    order = jnp.argsort(kv).astype(jnp.int32)
    sk = kv[order]
    i = jnp.arange(num_v, dtype=jnp.int32)
    new_run = jnp.concatenate([jnp.ones(1, bool), sk[1:] != sk[:-1]])
    run_start = jax.lax.cummax(jnp.where(new_run, i, 0))
    rank = i - run_start
    bid = S.prefix_sum(new_run | (rank % g == 0)) - 1
    vid = jnp.full((num_v, g), -1, jnp.int32).at[bid, rank % g].set(order)
    return vid, bid[-1] + 1


_PERIOD = 64  # cells per axis of the periodic grid (64 x the cell, ~1.7 m at PD 10 mm)


def centroid_grid(x, centre, radius, reach):
    """Triangles in a periodic grid by their centroid, and each vertex's 27 candidate ranges.

    The cell is R = the largest circumradius + reach, so a vertex p can pass the sphere test
    |p - centre| - radius < reach only for centroids within R of it per axis: in its own cell
    or one of the 26 around it. Cells are folded modulo `_PERIOD` per axis into a direct
    table of buckets (no hash: the 27 buckets around a cell are always distinct; a garment
    larger than the period only reads more), so one sort of F bucket ids and gathers replace
    the flat build's sort of 8 F entries and binary searches (XLA's CPU sort: ~130 ms for
    the fine skirt's 315 k entries, load ~5); and a 27 R^3 neighbourhood is read instead of
    the ~64 R^3 of a cell that holds a whole grown box.

    Args: x (V, 3) m; centre (F, 3) m, radius (F,) m (the triangles' centroids and
    circumradii about them); reach m.
    Returns: stri (F,) int32, triangles in bucket order; start, count (V, 27) int32, the
    vertex's ranges stri[start:start + count]; kv (V,) int32, the vertex's own bucket.
    """
    m = _PERIOD
    cell = jnp.maximum(jnp.max(radius) + reach, 1e-6)

    def bucket(g):
        g = jnp.mod(g, m)
        return g[..., 0] + m * (g[..., 1] + m * g[..., 2])

    bt = bucket(jnp.floor(centre / cell).astype(jnp.int32))
    order = jnp.argsort(bt).astype(jnp.int32)
    hist = jnp.zeros(m ** 3, jnp.int32).at[bt].add(1)
    # The table has m^3 = 262 k buckets: its running count is most of a coarse build's grid.
    first = S.prefix_sum(hist) - hist
    off = jnp.asarray(np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1],
                                           indexing="ij"), -1).reshape(27, 3), jnp.int32)
    gv = jnp.floor(x / cell).astype(jnp.int32)
    kn = bucket(gv[:, None] + off[None])                                   # (V, 27)
    return order, first[kn], hist[kn], bucket(gv)


def block_hits(x, faces, topo: S.SelfTopology, cfg: S.SelfCollisionConfig):
    """The read and sphere-test stage of `build_pairs_blocked` at positions x (V, 3) m.

    Returns hit (S, G) bool (the block vertex's sphere test passes, not a corner, not
    rest-excluded), lower (S, G) m (the distance's lower bound), t (S,) int32 the slot's
    triangle, owner (S,) int32 its block, vid (V, G) int32 the blocks' vertices, and the
    number of (vertex, entry) reads not made (int32).
    """
    num_v = x.shape[0]
    g = int(cfg.block)
    n_slots = S._budget(cfg.raw_per_vertex / g, num_v)
    reach = cfg.thickness + cfg.margin
    tri = x[faces]
    centre = tri.mean(1)
    radius = jnp.sqrt(jnp.max(jnp.sum((tri - centre[:, None]) ** 2, -1), -1))
    stri, start, count, kv = centroid_grid(x, centre, radius, reach)
    vid, nb = vertex_blocks(kv, g)
    real = jnp.arange(num_v) < nb
    head = jnp.maximum(vid[:, 0], 0)
    # A block reads its cell's 27 neighbour ranges: "parts" (V x 27, block-major).
    pcount = jnp.where(real[:, None], count[head], 0).reshape(-1)
    pstart = start[head].reshape(-1)
    ends = S.prefix_sum(pcount)
    offs = ends - pcount
    # Slot -> part: the last part starting at or before it (empty parts share offsets).
    first = jnp.zeros(n_slots, jnp.int32).at[offs].add(1, mode="drop")
    part = jnp.maximum(S.prefix_sum(first) - 1, 0)
    owner = part // 27
    slot = jnp.arange(n_slots, dtype=jnp.int32)
    read = slot < ends[-1]
    t = stri[jnp.clip(slot + (pstart - offs)[part], 0, stri.shape[0] - 1)]
    # One row per slot for the triangle (centre, circumradius, rest centre, panel, corners),
    # then one (S,) column per field; the block's vertex fields as (S, G) arrays, one per
    # field, so the tests below are plain elementwise (S, G) loops (with one (S, G, 7) row
    # array and slices of its last axis the tests alone took 463 ms on a fine skirt pose,
    # more than everything up to them takes this way, 139-230 ms).
    fdat = jnp.concatenate([centre, radius[:, None], topo.face_uv.mean(1),
                            topo.face_panel[:, None].astype(x.dtype),
                            faces.astype(x.dtype)], 1)[t]                     # (S, 10)
    f = [fdat[:, k:k + 1] for k in range(10)]
    used = vid >= 0
    vi = jnp.maximum(vid, 0)
    vfield = [x[:, 0], x[:, 1], x[:, 2], topo.uv[:, 0], topo.uv[:, 1],
              topo.panel.astype(x.dtype)]
    b = [jnp.where(used, a[vi], 0.0)[owner] for a in vfield]                  # (S, G) each
    me = jnp.where(used, vid, -1)[owner]
    d2 = (b[0] - f[0]) ** 2 + (b[1] - f[1]) ** 2 + (b[2] - f[2]) ** 2
    lower = jnp.sqrt(d2) - f[3]                                               # <= distance
    fi = me.astype(x.dtype)
    corner = (fi == f[7]) | (fi == f[8]) | (fi == f[9])
    hit = read[:, None] & (me >= 0) & (lower < reach) & ~corner
    if cfg.rest_exclusion > 0:
        dr2 = (b[3] - f[4]) ** 2 + (b[4] - f[5]) ** 2
        hit = hit & ~((b[5] == f[6]) & (dr2 < cfg.rest_exclusion ** 2))
    # (vertex, entry) reads not made: each part's unread entries times its block's vertices.
    unread = pcount - jnp.clip(n_slots - offs, 0, pcount)
    nv = jnp.repeat(used.sum(1), 27)
    return hit, lower, t, owner, vid, jnp.sum(unread * nv).astype(jnp.int32)


def build_pairs_blocked(x, faces, topo: S.SelfTopology, cfg: S.SelfCollisionConfig):
    """The contact list at positions x (V, 3) m; faces (F, 3) int32 (see the module doc).

    Bounds: ceil(raw_per_vertex x V / block) block-entry slots, ceil(box_per_vertex x V)
    exact tests, ceil(pairs_per_vertex x V) contacts. Returns (`selfcollision.Pairs`,
    overflow (3,) int32: (vertex, entry) reads not made, hits not given the exact test,
    contacts beyond the list).
    """
    num_v = x.shape[0]
    g = int(cfg.block)
    n_box = S._budget(cfg.box_per_vertex, num_v)
    n_pairs = S.max_pairs(num_v, cfg)
    reach = cfg.thickness + cfg.margin
    hit, lower, t, owner, vid, unread = block_hits(x, faces, topo, cfg)
    sel, ok, lost_box = _select2(hit, lower, n_box, reach)
    row, col = sel // g, sel % g
    bv = jnp.maximum(vid[owner[row], col], 0)
    bt = t[row]
    tt = x[faces[bt]]
    _, near, _ = S.closest_point_triangle(x[bv], tt[:, 0], tt[:, 1], tt[:, 2])
    dist = jnp.sqrt(jnp.maximum(near, 0.0))
    sel, pok, lost_pairs = S._select(ok & (dist < reach), dist, n_pairs, reach)
    pv, pt = bv[sel], bt[sel]
    h = jnp.where(pok, S._pair_thickness(topo, pv, pt, cfg), 0.0)
    overflow = jnp.stack([unread, lost_box, lost_pairs]).astype(jnp.int32)
    return S.Pairs(jnp.where(pok, pv, 0), jnp.where(pok, pt, 0), h, pok), overflow
