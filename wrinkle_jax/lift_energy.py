"""The lifting energy of `wrinkle_jax.lift` (the paper's Sec. 4.3): its weights, the sparse
one-ring topology it is evaluated on, its closed-form value, gradient and Gauss-Newton
model, bundled as the `solvers.Objective` `OBJECTIVE`. `wrinkle_jax.lift` re-exports the
public names; the solve, its implicit gradient and the body resolution live there.

Shapes and units: vertices are (V, 3) float32 meters; target normals (V, 3) unit vectors
(renormalized; a zero row contributes no normal of its own); faces (F, 3) int32.

Lifting energy (paper, Sec. 4.3), with our normalization:

    E(p) = 1/V * [ sum_p sum_{q in ring(p)} (m_pq . (q - p) / |q - p|_eps - c_pq)^2
                   + eta   * s^2 * sum_p |L (p - b)|^2
                   + omega * s^2 * sum_p |p - p0|^2 ],      s = h_ref / h.

Normalization (why the paper's weights are the defaults and mean the same everywhere):
  * h is the mean edge length of p0 and h_ref = 10 mm (the paper's fine particle distance):
    every length is measured as if the mesh had been scaled to 10 mm edges, and the sum is
    divided by V. E is thus the paper's energy (in meters, at its own 10 mm resolution) per
    vertex, so eta = 5e3 and omega = 8 keep their meaning for any vertex count and any
    length unit. (Refining one garment shifts the per-vertex balance, as for any discrete
    Laplacian energy; the pipeline lifts at ~10 mm by default, where the weights are
    calibrated; `PipelineConfig.subdivision="auto"` may pick coarser edges.)
    The normal term is dimensionless; an energy of 0.01 is a mean squared sine of 0.01/6 per
    one-ring pair.
  * |e|_eps = sqrt(|e|^2 + (1e-2 h)^2): a softened edge length, so zero-length edges and
    degenerate triangles give finite values and gradients (the relative change on normal
    edges is 5e-5).

Modelling choices (each can be switched back to the paper's literal term in `LiftWeights`):
  * L is the uniform ("umbrella") Laplacian of `mesh.uniform_laplacian`: it depends on
    topology only, so its term is exactly quadratic (Gauss-Newton is exact on it), it is
    finite on degenerate triangles (cotangent weights are not), and on the regular meshes
    made by subdivision it is the cotangent operator up to scale. The paper applies it to
    positions (b = 0, `laplacian_of="position"`); by default we apply it to the displacement
    from p0 (b = p0): the paper's form also pulls open boundaries inward and flattens the
    coarse curvature (L p0 != 0 there; it moves a flat 0.2 m sheet by 19 mm with perfect
    targets), while the displacement form leaves p0 stationary.
  * m_pq is the normal the pair is measured against. The paper uses m_pq = n_p
    (`normal_at="vertex"`). By default we use the edge's mean normal normalize(n_p + n_q)
    for both directions (`normal_at="edge"`): the chord of a circular arc is exactly
    perpendicular to it, while with n_p the chord is off by half the bend angle, a bias of
    order |e| * curvature that the minimizer removes by distorting the wrinkles. On the
    benchmark's 10 cm wrinkles at 10 mm edges the paper's form converges to a surface 2.3 mm
    RMS from the true one with a growing normal error, the edge form to 0.65 mm with the
    error flat over the iterations.
  * c_pq = the same chord term evaluated on p0 with p0's own vertex normals
    (`chord_correction=True`, default; 0 in the paper): it makes "target normals = the coarse
    mesh's normals" an exact fixed point on curved meshes too (the uncorrected term moves a
    20 cm cylinder by 1.3 mm and a coarse skirt by 15 cm). It is zero on flat regions.

Solvers (`SolverConfig.method`): the generic (init, step) drivers of `wrinkle_jax.solvers`,
iterated by `lax.while_loop`. This module supplies what is specific to E, bundled as the
`solvers.Objective` `OBJECTIVE` (closed-form value and gradient, the Gauss-Newton model, the
change of variables u = (p - p0) / h of the first-order solvers); `make_solver(config)` binds it.
  * "adam" (the paper's code: Adam, learning rate 0.1 edge = 1 mm at 10 mm edges, early
    stop after `patience` iterations without a `tol` relative improvement) and "gd" (plain
    gradient descent on the per-vertex energy in edge units) - the references;
  * "gauss_newton" (fast, default): Levenberg-Marquardt on the residual form of E with
    matrix-free preconditioned conjugate gradients. J^T J v is evaluated from each one-ring
    slot's rank-2 block, kept factored, by gathers over the padded one-ring (no scatter, no
    dense matrix); the preconditioner is the exact 3x3 block diagonal of J^T J, inverted in
    closed form;
  * "lbfgs": `optax.lbfgs` with its zoom line search.
Everything is O(V) memory: padded one-ring tables (V, K) and per-slot factors (V, K, 3).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import mesh, solvers
from wrinkle_jax.numerics import dot3, matvec3, normalize, safe_div, safe_norm, to_device
from wrinkle_jax.solvers import SolverConfig

REFERENCE_EDGE = 0.01  # meters: the paper's fine particle distance, where weights are calibrated
EDGE_SOFTENING = 1e-2  # |e|_eps = sqrt(|e|^2 + (EDGE_SOFTENING * h)^2)


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LiftWeights:
    """Weights of the lifting energy (hashable; a static argument).

    Attributes:
      eta: Laplacian smoothness weight (paper: 5e3).
      omega: weight of the distance to the upsampled coarse positions (paper: 8).
      laplacian_of: "displacement" (L (p - p0), default) or "position" (L p, the paper's).
      chord_correction: subtract the coarse mesh's own chord term n0_p . (q0 - p0)/|q0 - p0|
        from each residual (default True; False is the paper's energy), see the module doc.
      normal_at: "edge" (default: both directions of edge pq use the mean normal
        normalize(n_p + n_q), to which the chord of a circular arc is exactly perpendicular)
        or "vertex" (the paper: pair p -> q uses n_p), see the module doc.
      reference_edge: h_ref in meters; lengths are scaled by h_ref / h.
    """

    eta: float = 5e3
    omega: float = 8.0
    laplacian_of: str = "displacement"
    chord_correction: bool = True
    normal_at: str = "edge"
    reference_edge: float = REFERENCE_EDGE

    def __post_init__(self):
        if self.laplacian_of not in ("displacement", "position"):
            raise ValueError(f"laplacian_of must be 'displacement' or 'position', "
                             f"got {self.laplacian_of!r}")
        if self.normal_at not in ("vertex", "edge"):
            raise ValueError(f"normal_at must be 'vertex' or 'edge', got {self.normal_at!r}")
        if not (self.eta >= 0 and self.omega > 0):
            raise ValueError(f"need eta >= 0 and omega > 0, got {self.eta}, {self.omega}")


# --------------------------------------------------------------------------------------------
# Topology (NumPy, once per mesh)
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LiftTopology:
    """Sparse structure of the lifting problem, built once per mesh by `lift_topology`.

    Every sparse product is a gather over the padded one-ring table: on CPU that is several
    times faster than a scatter-add, and it has static shapes. The Laplacian L (from
    `mesh.uniform_laplacian`, one-ring support) is stored on the same table, so one gather
    of v[neighbors] serves both the normal term and L v.

    Attributes:
      faces: (F, 3) int32 triangles (for the vertex normals of p0).
      neighbors: (V, K) int32 one-ring (padding repeats the vertex itself).
      valid: (V, K) float32, 1 on real neighbours.
      lap_off: (V, K) float32, L[i, neighbors[i, k]]. lap_diag: (V,) float32, L[i, i].
      lapt_off: (V, K) float32, L^T[i, neighbors[i, k]] = L[neighbors[i, k], i].
      ltl_diag: (V,) float32, diagonal of L^T L (for preconditioners).
      overflow_rows: (E,) int32, the vertices with more than `main_slots` neighbours.
      main_slots: static M <= K (`_slot_split`): the Gauss-Newton product runs its slot loops
        over the first M slots of every row (valid neighbours come first) and adds the other
        K - M slots of the E overflow rows only. A subdivided mesh has a few vertices of
        valence 7-8 and nearly all others of valence <= 6 (dress_dance at 10 mm: 49 of
        20,308): there one product took 1.77 ms over 8 slots and 0.58 ms split (session 44).
        0: no split.
    """

    faces: Any
    neighbors: Any
    valid: Any
    lap_off: Any
    lap_diag: Any
    lapt_off: Any
    ltl_diag: Any
    overflow_rows: Any = None
    main_slots: int = dataclasses.field(default=0, metadata=dict(static=True))

    @property
    def num_vertices(self) -> int:
        return int(self.neighbors.shape[0])


def lift_topology(faces, num_vertices: int) -> LiftTopology:
    """Precompute the one-ring table and the uniform Laplacian on it (NumPy, once per mesh).

    Args:
      faces: (F, 3) int triangles. num_vertices: V.
    Returns:
      LiftTopology with device arrays.
    """
    n = int(num_vertices)
    nbr, valid = mesh.one_ring_padded(faces, n)
    lap = mesh.uniform_laplacian(faces, n)
    r, c = np.asarray(lap.rows, np.int64), np.asarray(lap.cols, np.int64)
    v = np.asarray(lap.values, np.float64)
    diag = np.bincount(r[r == c], v[r == c], minlength=n)
    # Locate every off-diagonal entry (r, c) in row r of the neighbour table.
    slot_key = np.where(valid, np.arange(n)[:, None] * n + nbr, -1).reshape(-1)
    order = np.argsort(slot_key)
    off = r != c
    key = r[off] * n + c[off]
    pos = np.searchsorted(slot_key, key, sorter=order)
    slot = order[np.clip(pos, 0, len(order) - 1)]
    if not (slot_key[slot] == key).all():
        raise mesh.GarmentError("the Laplacian has entries outside the one-ring")
    lap_off = np.zeros(nbr.size)
    np.add.at(lap_off, slot, v[off])
    lap_off = lap_off.reshape(nbr.shape)
    # L^T at slot (i, k) is L[j, i] with j = neighbors[i, k]: the same lookup, transposed.
    tkey = nbr.reshape(-1) * n + np.repeat(np.arange(n), nbr.shape[1])
    tpos = np.searchsorted(slot_key, tkey, sorter=order)
    tslot = order[np.clip(tpos, 0, len(order) - 1)]
    lapt_off = np.where(valid.reshape(-1) & (slot_key[tslot] == tkey),
                        lap_off.reshape(-1)[tslot], 0.0).reshape(nbr.shape)
    ltl_diag = diag**2 + np.bincount(c[off], v[off] ** 2, minlength=n)  # sum_m L_mi^2
    main, overflow = _slot_split(valid.sum(1))
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    return LiftTopology(**to_device(dict(
        faces=np.asarray(faces, np.int32), neighbors=np.asarray(nbr), valid=f32(valid),
        lap_off=f32(lap_off), lap_diag=f32(diag), lapt_off=f32(lapt_off),
        ltl_diag=f32(ltl_diag), overflow_rows=overflow)), main_slots=main)


def _slot_split(degree: np.ndarray, overflow_cost: float = 4.0) -> tuple[int, np.ndarray]:
    """(M, rows): the main slot count M and the vertices with more than M neighbours ((E,)
    int32), M chosen to minimize the product's slot work V M + overflow_cost E (K - M), K the
    largest degree; ties keep fewer overflow rows (M = K: no rows, no split).

    An overflow slot (gathered and scatter-added for its row only) cost 2.3-3.4x a main slot
    on the 10k-vertex reference sheet (session 45: one product with M = 6 and E = 288 ->
    5,000 overflow rows 0.45 -> 0.61 ms with XLA's defaults, 0.32 -> 0.49 ms with the
    command's settings); 4 leaves a margin. That sheet (288 of 10,201 vertices of valence 8)
    splits at 6 slots, in the same time as unsplit (0.45 / 0.32 ms) once L v is
    `_materialized`; on dress_dance's 20,308 vertices the split product took 0.63 ms against
    1.2 ms (defaults) and 2.5 ms (command) over all 8 slots. (Before `_materialized`, the
    overflow rows' scatter-add was what kept XLA from recomputing L v: the sheet's product
    went 1.38 -> 0.41 ms when first split.)"""
    degree = np.asarray(degree)
    k = int(degree.max()) if degree.size else 0
    best, best_cost = k, float(degree.size * k)
    for m in range(k - 1, 0, -1):
        e = int(np.count_nonzero(degree > m))
        cost = degree.size * m + overflow_cost * e * (k - m)
        if cost < best_cost:
            best, best_cost = m, cost
    return best, np.nonzero(degree > best)[0].astype(np.int32)


# The products over the one-ring below are written as unrolled multiply-adds over the K slots
# and the 3 components, not as einsums or reductions: XLA:CPU runs a batched dot of tiny
# blocks as one small call per vertex (plus operand transposes), and reduces a short middle
# axis slowly, while a chain of elementwise multiply-adds becomes one fused loop. Measured
# (session 43, 20k vertices): the Gauss-Newton product 2.49 -> 1.16 ms with the CLI's XLA
# settings, 2.64 -> 2.18 ms with XLA's defaults; with the closed-form 3 x 3 preconditioner
# (`solvers.inverse3`), dress_dance's lift stage (body included) ~535 -> ~455 ms per frame
# (3 alternating process pairs; XLA's defaults: ~575 -> ~510), the lifted vertices within
# 17 um of the einsum form's (rounding: the default solve stops after 3 iterations). Keeping
# the normal term's blocks factored (`_GNSystem`) then took one Gauss-Newton step (system and
# 25 products) 0.87x (XLA's defaults: 0.79x) in one process, alternating.


def _sum_slots(x):
    """sum_k x[:, k] of (V, K, ...) as K - 1 adds (see above)."""
    out = x[:, 0]
    for k in range(1, x.shape[1]):
        out = out + x[:, k]
    return out


def _ring_apply(off, diag, x, x_nbr):
    """y_i = sum_k off[i, k] x[neighbors[i, k]] + diag[i] x_i, given x_nbr = x[neighbors]."""
    off = off.astype(x.dtype)
    y = diag.astype(x.dtype)[:, None] * x
    for k in range(off.shape[1]):
        y = y + off[:, k:k + 1] * x_nbr[:, k]
    return y


def _materialized(top: LiftTopology, y):
    """y (V, ...) computed into a buffer of its own before anything gathers from it (or
    reduces it: `energy`).

    XLA:CPU fuses a cheap producer into a gather that reads it, recomputing it for every
    gathered slot: L v (itself a one-ring gather) gathered again for L^T L v was recomputed
    6-8 times per row. `lax.optimization_barrier` does not stop that on CPU (it is removed
    before fusion); a scatter-add, which is not fused into its consumers, does: here one of
    zeros into one row. One Gauss-Newton product on dress_dance's mesh with an unsplit 6-slot
    table: 1.32 -> 0.82 ms (session 45; split tables already had the overflow rows'
    scatter-add there, which is why splitting them looked 3x faster)."""
    return y.at[top.neighbors[:1, 0]].add(jnp.zeros((1,) + y.shape[1:], y.dtype))


def _split(top: LiftTopology):
    """(M, rows): the slots every row runs (`LiftTopology.main_slots`, K when unset) and the
    overflow rows (E,) whose other K - M slots are added apart, or None without a split."""
    k = top.neighbors.shape[1]
    m = top.main_slots or k
    return m, (top.overflow_rows if m < k and top.overflow_rows.shape[0] else None)


def _split_apply(top: LiftTopology, off, x):
    """y_i = sum_k off[i, k] x[neighbors[i, k]] + lap_diag[i] x_i for x (V, 3), over the
    first `main_slots` slots of every row plus the other slots of the overflow rows
    (scatter-added), as the Gauss-Newton product does. y is `_materialized` (the overflow
    rows' scatter-add does it when there are some)."""
    m, r = _split(top)
    y = _ring_apply(off[:, :m], top.lap_diag, x, x[top.neighbors[:, :m]])
    if r is not None:
        return y.at[r].add(_sum_slots(off[r, m:][..., None].astype(x.dtype)
                                      * x[top.neighbors[r, m:]]))
    return _materialized(top, y)


def _lap_apply(top: LiftTopology, x):
    """L x for x (V, 3)."""
    return _split_apply(top, top.lap_off, x)


def _lapt_apply(top: LiftTopology, y):
    """L^T y for y (V, 3)."""
    return _split_apply(top, top.lapt_off, y)


# --------------------------------------------------------------------------------------------
# The energy
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LiftProblem:
    """One lifting problem (a pytree): data, topology and the derived constants.

    Attributes:
      vertices0: (V, 3) upsampled coarse positions p0, meters.
      normals: (V, 3) unit target normals (zero rows: no target).
      base: (V, 3) the point the Laplacian term is measured from (p0 or zeros).
      topology: LiftTopology.
      edge: () mean edge length h of p0, meters.
      c_normal, c_lap, c_data: () term coefficients 1/V, eta s^2/V, omega s^2/V.
      eps_sq: () squared edge softening, meters^2.
      chord_f, chord_b: (V, K) chord terms of p0 with its own normals n0, for the pairs
        i -> j and j -> i of each slot (None without chord correction).
    """

    vertices0: Any
    normals: Any
    base: Any
    topology: LiftTopology
    edge: Any
    c_normal: Any
    c_lap: Any
    c_data: Any
    eps_sq: Any
    chord_f: Any = None
    chord_b: Any = None
    edge_normals: bool = dataclasses.field(default=False, metadata=dict(static=True))


def mean_edge(vertices, topology: LiftTopology):
    """Mean edge length (meters) over the one-ring table (each edge counted twice)."""
    e = vertices[topology.neighbors] - vertices[:, None, :]
    w = topology.valid.astype(vertices.dtype)
    return safe_div(jnp.sum(w * safe_norm(e)), jnp.sum(w))


def make_problem(vertices0, topology: LiftTopology, target_normals,
                 weights: LiftWeights = LiftWeights()) -> LiftProblem:
    """Assemble a LiftProblem (jittable; differentiable in vertices0 and target_normals)."""
    v0 = jnp.asarray(vertices0)
    n = normalize(jnp.asarray(target_normals, v0.dtype))
    nv = v0.shape[0]
    h = mean_edge(v0, topology)
    h = jnp.where(h > 0, h, jnp.asarray(weights.reference_edge, v0.dtype))
    s2 = (weights.reference_edge / h) ** 2
    base = v0 if weights.laplacian_of == "displacement" else jnp.zeros_like(v0)
    eps_sq = jnp.maximum((EDGE_SOFTENING * h) ** 2, 1e-30).astype(v0.dtype)
    chord_f = chord_b = None
    if weights.chord_correction:
        # The chord term of p0 with its own normals: subtracting it makes (p0, n0) an exact
        # zero of the normal term on curved meshes (chords are not tangent to the surface).
        n0 = mesh.vertex_normals(v0, topology.faces)
        n0_i, n0_j = _pair_normals(n0, topology, weights.normal_at == "edge")
        e0 = v0[topology.neighbors] - v0[:, None, :]
        w_inv = topology.valid.astype(v0.dtype) * jax.lax.rsqrt(dot3(e0, e0) + eps_sq)
        chord_f = w_inv * dot3(n0_i, e0)
        chord_b = -w_inv * dot3(n0_j, e0)
    return LiftProblem(
        vertices0=v0, normals=n, base=base, topology=topology, edge=h,
        c_normal=jnp.asarray(1.0 / nv, v0.dtype), c_lap=weights.eta * s2 / nv,
        c_data=weights.omega * s2 / nv, eps_sq=eps_sq, chord_f=chord_f, chord_b=chord_b,
        edge_normals=weights.normal_at == "edge",
    )


def _pair_normals(normals, topology: LiftTopology, edge: bool):
    """Normals (V, K, 3) used by the pairs i -> j and j -> i of every one-ring slot."""
    n_i = jnp.broadcast_to(normals[:, None, :], topology.neighbors.shape + (3,))
    n_j = normals[topology.neighbors]
    if edge:
        n_i = n_j = normalize(n_i + n_j)
    return n_i, n_j


class _Rows(NamedTuple):
    """Per one-ring slot (i, k), j = neighbors[i, k], e = p_j - p_i:
    r_f = n_i.e/|e| (pair i->j), r_b = n_j.(p_i - p_j)/|e| (pair j->i), and their gradients
    with respect to p_j and p_i respectively: g_f, g_b (V, K, 3). Padding slots are zero."""

    r_f: Any
    r_b: Any
    g_f: Any
    g_b: Any


def _rows(p, prob: LiftProblem) -> _Rows:
    top = prob.topology
    w = top.valid.astype(p.dtype)
    e = p[top.neighbors] - p[:, None, :]
    inv = jax.lax.rsqrt(dot3(e, e) + prob.eps_sq)  # 1 / |e|_eps, finite always
    n_i, n_j = _pair_normals(prob.normals, top, prob.edge_normals)
    a = dot3(n_i, e)
    b = dot3(n_j, e)
    # d(n.e/|e|_eps)/de = (n - (n.e) e / |e|_eps^2) / |e|_eps
    g_f = (w * inv)[..., None] * (n_i - (a * inv * inv)[..., None] * e)
    g_b = (w * inv)[..., None] * (n_j - (b * inv * inv)[..., None] * e)
    r_f, r_b = w * a * inv, -w * b * inv
    if prob.chord_f is not None:
        r_f, r_b = r_f - prob.chord_f, r_b - prob.chord_b
    return _Rows(r_f, r_b, g_f, g_b)


def _lap(p, prob: LiftProblem):
    return _lap_apply(prob.topology, p - prob.base)


def energy(vertices, prob: LiftProblem):
    """The normalized lifting energy E (a scalar) at vertices (V, 3) (jittable).

    Uses gathers only; `jax.grad` of it is the reference for the analytic gradient.
    """
    rows = _rows(vertices, prob)
    lp = _lap(vertices, prob)
    d = vertices - prob.vertices0
    # Summed per vertex first (multiply-adds), then one reduction over V: XLA:CPU ran the three
    # full reductions fused with their producers 1.8x slower (demo skirt, session 44). Not in
    # `_value_and_grad`, where the same form measured slower. The per-vertex sums are
    # `_materialized`: fused into the reduction they ran on one thread, 4.6 -> 0.8 ms per
    # evaluation on dress_dance's 20,308 vertices (session 45).
    per_vertex = (prob.c_normal * _sum_slots(rows.r_f * rows.r_f) + prob.c_lap * dot3(lp, lp)
                  + prob.c_data * dot3(d, d))
    return jnp.sum(_materialized(prob.topology, per_vertex))


def _value_and_grad(p, prob: LiftProblem):
    """E and dE/dp (V, 3) in closed form, gathers only (no scatter-add)."""
    top = prob.topology
    rows = _rows(p, prob)
    lp = _lap(p, prob)
    d = p - prob.vertices0
    value = (prob.c_normal * jnp.sum(rows.r_f ** 2) + prob.c_lap * jnp.sum(lp * lp)
             + prob.c_data * jnp.sum(d * d))
    g_n = _sum_slots(rows.r_b[..., None] * rows.g_b - rows.r_f[..., None] * rows.g_f)
    g_l = _lapt_apply(top, lp)
    grad = 2.0 * (prob.c_normal * g_n + prob.c_lap * g_l + prob.c_data * d)
    return value, grad


def energy_grad(vertices, prob: LiftProblem):
    """dE/dp (V, 3), closed form (equal to `jax.grad(energy)`, without scatter-adds)."""
    return _value_and_grad(vertices, prob)[1]


class _GNSystem(NamedTuple):
    """The Gauss-Newton Hessian of E at a point, assembled for fast products:
    H v = -sum_k M[:, k] v[neighbors[:, k]] + S v + 2 c_lap (L^T L) v, with the normal term's
    per-slot blocks M[:, k] = g_f g_f^T + g_b g_b^T kept factored (g_f, g_b, scaled by
    sqrt(2 c_normal)): a product reads 6 numbers per slot instead of 9 and the (V, K, 3, 3)
    blocks are never stored. S (V, 3, 3) = sum_k M[:, k] + 2 c_data I; `diag` (V, 3, 3) is the
    exact block diagonal of H. The one-ring is split as `LiftTopology.main_slots` says:
    `ring` holds the first M slots of every row, `overflow` the other K - M slots of the
    overflow rows (None when there are none).

    Attributes:
      g_f, g_b: (V, M, 3). s, diag: (V, 3, 3).
      ring: (neighbors, lap_off), each (V, M).
      overflow: None, or (rows (E,), neighbors, lap_off (E, K - M), g_f, g_b
        (E, K - M, 3)).
    """

    g_f: Any
    g_b: Any
    s: Any
    diag: Any
    ring: Any
    overflow: Any


def _gn_system(rows: _Rows, prob: LiftProblem) -> _GNSystem:
    top = prob.topology
    scale = jnp.sqrt(2.0 * prob.c_normal)
    g_f, g_b = scale * rows.g_f, scale * rows.g_b
    m = g_f[..., :, None] * g_f[..., None, :] + g_b[..., :, None] * g_b[..., None, :]
    eye = jnp.eye(3, dtype=m.dtype)
    s = _sum_slots(m) + 2.0 * prob.c_data * eye
    diag = s + (2.0 * prob.c_lap * top.ltl_diag.astype(m.dtype))[:, None, None] * eye
    k, r = _split(top)
    ring = (top.neighbors[:, :k], top.lap_off[:, :k])
    overflow = None if r is None else (
        r, top.neighbors[r, k:], top.lap_off[r, k:], g_f[r, k:], g_b[r, k:])
    return _GNSystem(g_f[:, :k], g_b[:, :k], s, diag, ring, overflow)


def _slot_terms(g_f, g_b, v_nbr):
    """sum_k g_f (g_f . v_k) + g_b (g_b . v_k) over the slots of (N, S, 3) factors."""
    out = None
    for k in range(v_nbr.shape[1]):
        a, b, v_k = g_f[:, k], g_b[:, k], v_nbr[:, k]
        t = a * dot3(a, v_k)[:, None] + b * dot3(b, v_k)[:, None]
        out = t if out is None else out + t
    return out


def _gn_matvec(sys: _GNSystem, prob: LiftProblem, v):
    """H v for the Gauss-Newton Hessian H = 2 J^T J (matching E); gathers only, plus
    scatter-adds of the few overflow rows."""
    nbr, lap_off = sys.ring
    diag = prob.topology.lap_diag
    v_nbr = v[nbr]  # one gather serves the normal term and L v
    out = matvec3(sys.s, v) - _slot_terms(sys.g_f, sys.g_b, v_nbr)
    lv = _ring_apply(lap_off, diag, v, v_nbr)
    if sys.overflow is not None:
        rows, x_nbr, x_lap, x_gf, x_gb = sys.overflow
        v_x = v[x_nbr]
        out = out.at[rows].add(-_slot_terms(x_gf, x_gb, v_x))
        lv = lv.at[rows].add(_sum_slots(x_lap[..., None].astype(v.dtype) * v_x))
    else:
        lv = _materialized(prob.topology, lv)
    ltl = _split_apply(prob.topology, prob.topology.lapt_off, lv)
    return out + 2.0 * prob.c_lap * ltl


# --------------------------------------------------------------------------------------------
# The lifting energy as a `solvers.Objective`
# --------------------------------------------------------------------------------------------


def _gauss_newton_model(prob: LiftProblem, p) -> solvers.GaussNewtonModel:
    """The Gauss-Newton model of E at p: H = 2 J^T J from per-slot factors (gathers only)."""
    system = _gn_system(_rows(p, prob), prob)

    def damped(lam):  # H + lam D, D = the block diagonal of H (assembled once)
        damped_system = system._replace(s=system.s + lam * system.diag)
        return lambda v: _gn_matvec(damped_system, prob, v)

    return solvers.GaussNewtonModel(matvec=lambda v: _gn_matvec(system, prob, v),
                                    damped=damped, diag=system.diag)


def _scaling(prob: LiftProblem) -> solvers.Scaling:
    """First-order solvers iterate on u = (p - p0) / h and minimize V * E (the per-vertex
    energy summed): learning rates are in mean-edge lengths."""
    return solvers.Scaling(origin=prob.vertices0, length=prob.edge,
                           weight=prob.vertices0.shape[0])


OBJECTIVE = solvers.Objective(
    value=lambda prob, p: energy(p, prob),
    value_and_grad=lambda prob, p: _value_and_grad(p, prob),
    gauss_newton=_gauss_newton_model,
    scaling=_scaling,
)
"""The lifting energy E(prob, p) with its closed-form gradient and Gauss-Newton model."""


def make_solver(config: SolverConfig) -> solvers.Solver:
    """The (init, step) pair of `config.method` on the lifting energy: init(prob, p0) and
    step(prob, state) take a `LiftProblem`; states carry `vertices` (V, 3) and `energy`."""
    return solvers.make_solver(config, OBJECTIVE)
