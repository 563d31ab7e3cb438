"""Normal-guided lifting of an enhanced normal map to a detailed 3D mesh, and resolution of
garment-body interpenetration (the paper's Sec. 4.3), differentiable and sparse.

Pipeline of one frame:

    coarse (Vc, 3) --upsample--> fine p0 (V, 3)      (subdivision.to_edge_length, ~10 mm)
    N* (H, W, 3)  --sample_target_normals--> n (V, 3) (bilinear at the vertex UVs)
    (p0, n) --lift--> p (V, 3) --resolve_penetration(body)--> p' (V, 3)

Shapes and units: vertices are (V, 3) float32 meters; target normals (V, 3) unit vectors
(renormalized; a zero row contributes no normal of its own); faces (F, 3) int32.

The energy E, its weights, topology and solvers are in `wrinkle_jax.lift_energy` (its
module docstring states the energy, its normalization and the modelling choices);
its public names are re-exported here.

Differentiability: `lift` is a `jax.custom_vjp`. The backward pass solves the adjoint system
H lambda = g (H the exact Hessian at the solution, Hessian-vector products by `jax.jvp` of the
closed-form gradient) with CG and returns -(d grad E / d theta)^T lambda for
theta = (vertices0, target_normals): the implicit function theorem; the iterations are never
unrolled. The result is exact at a stationary point with a converged adjoint solve: tighten
`tol` / `cg_tol` and raise `adjoint_max_iters` when gradients must be accurate (the default
settings favour speed per frame; `solvers.SolverConfig` gives measured errors).

Interpenetration (`resolve_penetration`): see its docstring. Without a body nothing is traced.

How well a lift met its goal (its mesh re-baked against N*, detail bands, rim, penetrations):
`wrinkle_jax.lift_quality`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import bodies as body_lib
from wrinkle_jax import mesh, normalmap, solvers, subdivision

# The energy and its pieces, re-exported: `lift` is where users (and tests) find them.
from wrinkle_jax.lift_energy import (  # noqa: F401
    EDGE_SOFTENING,
    OBJECTIVE,
    REFERENCE_EDGE,
    LiftProblem,
    LiftTopology,
    LiftWeights,
    _gn_matvec,
    _gn_system,
    _lap,
    _lap_apply,
    _lapt_apply,
    _rows,
    energy,
    energy_grad,
    lift_topology,
    make_problem,
    make_solver,
    mean_edge,
)
from wrinkle_jax.numerics import normalize, safe_div, to_device
from wrinkle_jax.solvers import SolverConfig  # re-exported: the `solver` argument of `lift`
from wrinkle_jax.subdivision import Subdivision

# k of `texel_subdivision_level`: lifted edges of at least this many texels (measured on the
# error/time Pareto of benchmarks/bench_subdivision.py, see its JSON).
TEXELS_PER_EDGE = 3.0

# --------------------------------------------------------------------------------------------
# Diagnostics of a solve
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LiftInfo:
    """Diagnostics of a solve (a pytree of scalars).

    Attributes:
      iterations: outer iterations run. inner_iterations: CG iterations (GN) or energy
        evaluations in line searches (L-BFGS); 0 otherwise.
      energy: final E (normalized, see the module docstring).
      grad_rms: RMS of the per-vertex gradient in edge units (V * h * dE/dp).
      converged: the tolerance was met before `max_iters`.
    """

    iterations: Any
    inner_iterations: Any
    energy: Any
    grad_rms: Any
    converged: Any


# --------------------------------------------------------------------------------------------
# Upsampling and target normals
# --------------------------------------------------------------------------------------------


def texel_subdivision_level(edge: float, texel_size: float,
                            texels_per_edge: float = TEXELS_PER_EDGE, max_levels: int = 6) -> int:
    """Subdivision levels that model only the detail the normal map holds.

    Each (midpoint) level halves the edges; this returns the most levels L whose edges
    edge / 2^L are still at least `texels_per_edge` texels long, so the lifted mesh is no
    finer than the map (0 when the coarse mesh already is; at most `max_levels`). Finer
    vertices would sample the same bilinear texels again and only cost solver time.

    Args:
      edge: mean edge length of the coarse mesh, meters (`coarse_mean_edge`).
      texel_size: the map's texel edge, meters (2 mm for the shipped model).
      texels_per_edge: k, the subdivided edge length in texels (`TEXELS_PER_EDGE`: the knee
        of the error/time Pareto of benchmarks/bench_subdivision.py).
    """
    if not (edge > 0 and texel_size > 0 and texels_per_edge > 0):
        raise ValueError(f"need positive edge, texel_size and texels_per_edge, got "
                         f"{edge}, {texel_size}, {texels_per_edge}")
    ratio = edge / (texels_per_edge * texel_size)
    # The small slack keeps an exact power of two (edges of exactly k texels) at its level.
    levels = int(math.floor(math.log2(ratio) + 1e-9)) if ratio > 1.0 else 0
    return min(levels, int(max_levels))


def upsample(garment: mesh.Garment, target_edge: float = REFERENCE_EDGE,
             scheme: str = "midpoint", max_levels: int = 6, levels: int | None = None):
    """Subdivide a coarse garment until its mean edge is at most `target_edge` meters, or by
    exactly `levels` levels when given (e.g. from `texel_subdivision_level`).

    Returns:
      (fine Garment, Subdivision). Upsample further frames (V, 3) -> (V', 3) with the
      jittable `subdivision.apply(frame)` (vmap over frames).
    """
    if levels is None:
        sub = subdivision.to_edge_length(garment, target_edge, scheme, max_levels)
    else:
        if int(levels) < 0:
            raise ValueError(f"subdivision levels must be >= 0, got {levels}")
        sub = subdivision.build(garment, int(levels), scheme)
    return sub.garment(garment), sub


def coarse_mean_edge(garment: mesh.Garment) -> float:
    """Mean edge length (meters) of a garment's unique edges (NumPy)."""
    edges = mesh.unique_edges(garment.faces)
    return mesh.mean_edge_length_np(garment.vertices, edges)


def sample_target_normals(normal_map, garment: mesh.Garment, layout: normalmap.UVLayout):
    """Target normals n (V, 3) from the enhanced map N* (H, W, 3) at the vertex UVs.

    Seam vertices average their UV copies (`normalmap.sample_at_vertices`). Jittable and
    differentiable with respect to the map.
    """
    return normalmap.sample_at_vertices(normal_map, garment, layout)



def _info(state, prob: LiftProblem) -> LiftInfo:
    gauss_newton = isinstance(state, solvers.GaussNewtonState)
    g = state.grad if gauss_newton else energy_grad(state.vertices, prob)
    g = g * prob.vertices0.shape[0] * prob.edge
    inner = state.cg_iterations if gauss_newton else state.evaluations
    return LiftInfo(iterations=state.iteration, inner_iterations=inner, energy=state.energy,
                    grad_rms=jnp.sqrt(jnp.mean(g * g)), converged=state.converged)


# --------------------------------------------------------------------------------------------
# lift: the solve with an implicit-function-theorem VJP
# --------------------------------------------------------------------------------------------


def _start_point(prob: LiftProblem, start):
    """The iterate to start from: `start` (a warm start, e.g. the previous frame's solution
    carried onto this frame) when its energy is below p0's, else p0, so a poor guess (a cut
    in the sequence) never starts the solver worse off than a cold start."""
    if start is None:
        return prob.vertices0
    start = jnp.asarray(start, prob.vertices0.dtype)
    better = energy(start, prob) < energy(prob.vertices0, prob)
    return jnp.where(better, start, prob.vertices0)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5))
def _solve(vertices0, topology, target_normals, start, weights, solver):
    prob = make_problem(vertices0, topology, target_normals, weights)
    state = solvers.run(make_solver(solver), prob, _start_point(prob, start), solver.max_iters)
    return state.vertices, _info(state, prob)


def _solve_fwd(vertices0, topology, target_normals, start, weights, solver):
    out = _solve(vertices0, topology, target_normals, start, weights, solver)
    return out, (out[0], vertices0, topology, target_normals)


def _solve_bwd(weights, solver, res, cotangents):
    p, vertices0, topology, target_normals = res
    g_p = cotangents[0]

    def grad_at(p_, v0, n):
        return energy_grad(p_, make_problem(v0, topology, n, weights))

    prob = make_problem(vertices0, topology, target_normals, weights)
    hvp = lambda v: jax.jvp(lambda x: grad_at(x, vertices0, target_normals), (p,), (v,))[1]  # noqa: E731
    precond = solvers.block_inverse(_gn_system(_rows(p, prob), prob).diag)
    lam = solvers.pcg(hvp, g_p, precond, solver.adjoint_tol, solver.adjoint_max_iters).x
    _, vjp = jax.vjp(lambda v0, n: grad_at(p, v0, n), vertices0, target_normals)
    ct_v0, ct_n = vjp(-lam)
    # The minimizer does not depend on where the solver started (implicit function theorem).
    return ct_v0, None, ct_n, None


_solve.defvjp(_solve_fwd, _solve_bwd)


@functools.partial(jax.jit, static_argnames=("weights", "solver"))
def lift_with_info(vertices0, topology: LiftTopology, target_normals,
                   weights: LiftWeights = LiftWeights(), solver: SolverConfig = SolverConfig(),  # noqa: B008
                   start=None):
    """`lift` that also returns a `LiftInfo` (iterations, energy, convergence); `start`: see
    `lift`."""
    return _solve(jnp.asarray(vertices0), topology, jnp.asarray(target_normals), start,
                  weights, solver)


@functools.partial(jax.jit, static_argnames=("weights", "solver"))
def lift(vertices0, topology: LiftTopology, target_normals,
         weights: LiftWeights = LiftWeights(), solver: SolverConfig = SolverConfig(),  # noqa: B008
         start=None):
    """Deform the upsampled coarse mesh so its edges follow the target normals.

    Args:
      vertices0: (V, 3) float meters, the upsampled coarse frame p0.
      topology: `lift_topology(faces, V)`, built once per mesh.
      target_normals: (V, 3) target normals (renormalized; zero rows have no normal term).
      weights: LiftWeights (static). solver: SolverConfig (static).
      start: None (start at p0), or (V, 3) meters, a warm start (e.g. the previous frame's
        solution carried onto this one); used only when its energy is below p0's. The
        minimizer, and so the gradient, does not depend on it; the iterate the solver stops
        at does, within its tolerance.
    Returns:
      (V, 3) lifted vertices, meters. Differentiable with respect to vertices0 and
      target_normals through the implicit function theorem (custom VJP; reverse mode only).

    Example:
      >>> from wrinkle_jax import mesh, primitives
      >>> g = primitives.grid_sheet(20, 20, size=(0.2, 0.2))
      >>> top = lift_topology(g.faces, g.num_vertices)
      >>> p = lift(g.vertices, top, mesh.vertex_normals(g.vertices, g.faces))
    """
    return lift_with_info(vertices0, topology, target_normals, weights, solver, start)[0]


def lift_from_normal_map(coarse_vertices, subdivision: Subdivision,
                         fine_garment: mesh.Garment, topology: LiftTopology, normal_map,
                         layout: normalmap.UVLayout,
                         weights: LiftWeights = LiftWeights(),  # noqa: B008
                         solver: SolverConfig = SolverConfig()):  # noqa: B008
    """One frame end to end: upsample the coarse frame, sample N*, lift (jittable with
    weights/solver/layout static; differentiable in coarse_vertices and normal_map).

    Args:
      coarse_vertices: (Vc, 3) meters. subdivision, fine_garment: from `upsample`.
      normal_map: (H, W, 3) enhanced map N*. layout: its UVLayout.
    Returns:
      (V, 3) lifted fine vertices, meters.
    """
    p0 = subdivision.apply(coarse_vertices)
    n = sample_target_normals(normal_map, fine_garment, layout)
    return _solve(p0, topology, n, None, weights, solver)[0]


# --------------------------------------------------------------------------------------------
# Diagnostics
# --------------------------------------------------------------------------------------------


def normal_angle_error(vertices, faces, target_normals, mask=None):
    """Mean angle (degrees) between the mesh's vertex normals and the target normals.

    Args:
      vertices: (V, 3). faces: (F, 3). target_normals: (V, 3) (zero rows are ignored).
      mask: optional (V,) bool/float, vertices to include (e.g. excluding a border ring).
    """
    vn = mesh.vertex_normals(vertices, faces)
    t = normalize(target_normals)
    cos = jnp.clip(jnp.sum(vn * t, -1), -1.0, 1.0)
    w = (jnp.sum(t * t, -1) > 0).astype(vertices.dtype)
    if mask is not None:
        w = w * jnp.asarray(mask, vertices.dtype)
    return jnp.degrees(safe_div(jnp.sum(w * jnp.arccos(cos)), jnp.sum(w)))


# --------------------------------------------------------------------------------------------
# Interpenetration
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ResolveConfig:
    """Settings of `resolve_penetration` (hashable; a static argument).

    Attributes:
      thickness: clearance epsilon in meters: vertices with signed distance < thickness are
        constrained and pushed to the offset surface at distance `thickness`.
      compliance: kappa, the weight of (smoothness + anchor) relative to the constraints;
        small values make the constraints nearly hard.
      max_rounds: bound on project-and-solve rounds.
      cg_max_iters, cg_tol: per-round conjugate-gradient budget.
      coarse_mass: gamma of the two-level preconditioner (see `resolve_coarse`), or None for
        Jacobi alone. It takes effect only where a `ResolveCoarse` built for this config is
        passed (the pipeline builds one per garment).
      coarse_max_vertices: `resolve_coarse` builds nothing (Jacobi alone) above this many
        coarse vertices: its dense inverse costs Vc^2 floats and Vc^3 setup.
    """

    thickness: float = 2e-3
    compliance: float = 0.05
    max_rounds: int = 8
    cg_max_iters: int = 300
    cg_tol: float = 1e-5
    coarse_mass: float | None = None
    coarse_max_vertices: int = 3000


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ResolveCoarse:
    """The coarse-grid correction of the push-out's PCG (a pytree; `resolve_coarse` builds it).

    Attributes:
      prolong: (V, Vc) `mesh.RowTable` P, the subdivision from the coarse garment.
      restrict: (Vc, V) `mesh.RowTable`, P^T (row tables: gathers, no scatter-adds in the
        CG loop).
      inverse: (Vc, Vc) float32, A_c^-1 (see `resolve_coarse`).
      key: static (phi, compliance, coarse_mass) it was built for.
    """

    prolong: mesh.RowTable
    restrict: mesh.RowTable
    inverse: Any
    key: tuple = dataclasses.field(metadata=dict(static=True))


def _coo(op: mesh.SparseOperator):
    return (np.asarray(op.rows, np.int64), np.asarray(op.cols, np.int64),
            np.asarray(op.values, np.float64))


def _product(a, b, b_rows: int):
    """COO (rows, cols, values) of A @ B from COO A and B (duplicates allowed; NumPy)."""
    ar, ac, av = a
    order = np.argsort(b[0], kind="stable")
    br, bc, bv = (x[order] for x in b)
    start = np.searchsorted(br, np.arange(b_rows + 1))
    count = start[ac + 1] - start[ac]
    first = np.repeat(start[ac], count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    return np.repeat(ar, count), bc[first + offset], np.repeat(av, count) * bv[first + offset]


def _gram(q, rows: int, cols: int) -> np.ndarray:
    """Dense Q^T Q (cols, cols) from COO Q (rows x cols): sums over pairs within each row."""
    qr, qc, qv = q
    t = _product((qc, qr, qv), q, rows)  # Q^T Q in COO, with duplicates
    return np.bincount(t[0] * cols + t[1], t[2], minlength=cols * cols).reshape(cols, cols)


def resolve_coarse(subdivision: Subdivision, topology: LiftTopology, phi: float = 5e3,
                   config: ResolveConfig = ResolveConfig()) -> ResolveCoarse | None:  # noqa: B008
    """Precompute the push-out's coarse-grid correction for one garment (NumPy, once).

    The push-out system A d = r (see `resolve_penetration`), A = C + a L^T L + b (I - C), has
    a nearly free low-frequency part (only the weak anchor b and the few constrained vertices
    hold it), which Jacobi-preconditioned CG resolves slowly. The correction adds the
    Galerkin coarse solve P A_c^-1 P^T to the Jacobi preconditioner, with P the subdivision
    from the coarse garment and A_c = P^T (a L^T L + b I + gamma (1 - b) I) P: A with every
    vertex's constraint weight replaced by gamma = `config.coarse_mass`, so A_c is fixed per
    garment and inverted once (the true C changes every frame; a per-frame Cholesky of A_c
    cut the iterations further, 144 -> 22 on dress_dance, but XLA's triangular solves cost
    15 ms each). The result is still a symmetric positive definite preconditioner.

    Args:
      subdivision: `Subdivision` from the coarse garment to the lifted mesh.
      topology: `lift_topology` of the lifted mesh. phi: the push-out's phi.
      config: ResolveConfig; nothing is built (None) when `config.coarse_mass` is None or the
        coarse garment has more than `config.coarse_max_vertices` vertices.
    Returns:
      ResolveCoarse, or None.
    """
    if config.coarse_mass is None:
        return None
    n = topology.num_vertices
    ops = list(subdivision.vertex_ops)
    cols = ops[0].shape[1] if ops else n
    if cols > config.coarse_max_vertices:
        return None
    p = (np.arange(n), np.arange(n), np.ones(n))
    if ops:
        p = _coo(ops[0])
        for op in ops[1:]:
            p = _product(_coo(op), p, op.shape[1])
    # L as the push-out applies it: the topology's one-ring table (no second edge scan).
    valid = np.asarray(topology.valid) > 0
    rows = np.concatenate([np.nonzero(valid)[0], np.arange(n)])
    lap = (rows, np.concatenate([np.asarray(topology.neighbors)[valid], np.arange(n)]),
           np.concatenate([np.asarray(topology.lap_off, np.float64)[valid],
                           np.asarray(topology.lap_diag, np.float64)]))
    a = config.compliance * math.sqrt(phi)
    b = config.compliance / math.sqrt(phi)
    a_c = (a * _gram(_product(lap, p, n), n, cols)
           + (b + config.coarse_mass * (1.0 - b)) * _gram(p, n, cols))
    r, c, v = (np.asarray(x) for x in p)
    prolong = mesh.sparse_operator(r, c, v, (n, cols))
    restrict = mesh.sparse_operator(c, r, v, (cols, n))
    return ResolveCoarse(mesh.row_table(prolong), mesh.row_table(restrict),
                         to_device(np.linalg.inv(a_c), np.float32),
                         (float(phi), config.compliance, config.coarse_mass))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ResolveInfo:
    """rounds run, vertices still inside (signed distance < 0), total CG iterations."""

    rounds: Any
    inside: Any
    cg_iterations: Any


def resolve_penetration_with_info(vertices, topology: LiftTopology, body, phi: float = 5e3,
                                  config: ResolveConfig = ResolveConfig(),  # noqa: B008
                                  coarse: ResolveCoarse | None = None):
    """`resolve_penetration` that also returns a `ResolveInfo` (None when body is None)."""
    if body is None:  # no body: the term does not exist and nothing is traced
        return vertices, None
    if coarse is not None and coarse.key != (float(phi), config.compliance, config.coarse_mass):
        raise ValueError(f"this ResolveCoarse was built for (phi, compliance, coarse_mass) = "
                         f"{coarse.key}, not {(float(phi), config.compliance, config.coarse_mass)}")
    return _resolve(jnp.asarray(vertices), topology, body, float(phi), config, coarse)


def resolve_penetration(vertices, topology: LiftTopology, body, phi: float = 5e3,
                        config: ResolveConfig = ResolveConfig(),  # noqa: B008
                        coarse: ResolveCoarse | None = None):
    """Push garment vertices out of a body and let their neighbourhood follow smoothly.

    The paper's objective, sum_{p in C} |p* - p|^2 + phi sum_p |grad p|^2, is solved in
    rounds. Each round: C = {vertices with signed distance < thickness}; every p in C gets
    the target p* = its nearest body-surface point + thickness * outward normal; then the
    displacement d = p_new - p minimizes

        sum_{i in C} |d_i - (p*_i - p_i)|^2
          + kappa * [ sqrt(phi) sum_i |(L d)_i|^2 + sum_{i not in C} |d_i|^2 / sqrt(phi) ],

    a linear SPD system solved matrix-free by PCG (O(V)). |grad p|^2 is interpreted as the
    smoothness of the *displacement*, measured with the same uniform Laplacian as the lift
    (a smoothness of positions would shrink the garment), and the weak anchor on the free
    vertices removes the smoothness term's affine null space, without which the whole
    garment would translate to satisfy the constraints. The two weights make phi a length:
    the push decays over about phi^(1/4) edges (8.4 edges, ~84 mm at 10 mm edges, for the
    paper's phi = 5e3), while kappa alone sets how hard the constraints are. Rounds repeat
    until no vertex is inside (signed distance < 0) or `config.max_rounds`.

    Args:
      vertices: (V, 3) meters. topology: LiftTopology of the garment.
      body: `bodies.PrimitiveBody`, `bodies.MeshBody` or None (returns `vertices` unchanged
        without tracing anything).
      phi: smoothness weight (static).
      config: ResolveConfig (static).
      coarse: None (Jacobi-preconditioned CG), or `resolve_coarse(subdivision, topology, phi,
        config)`: the same system with a coarse-grid correction in the preconditioner (fewer
        iterations for the same tolerance).
    Returns:
      (V, 3) vertices, meters. Not differentiable in reverse mode (a while loop).
    """
    return resolve_penetration_with_info(vertices, topology, body, phi, config, coarse)[0]


@functools.partial(jax.jit, static_argnames=("phi", "config"))
def _resolve(vertices, topology: LiftTopology, body, phi: float, config: ResolveConfig,
             coarse: ResolveCoarse | None = None):
    dt = vertices.dtype
    a = config.compliance * np.sqrt(phi)
    b = config.compliance / np.sqrt(phi)
    eps = config.thickness
    ltl = topology.ltl_diag.astype(dt)

    def lap_t_lap(v):
        return _lapt_apply(topology, _lap_apply(topology, v))

    def count_inside(q):
        return jnp.sum(q.distance < 0).astype(jnp.int32)

    def round_(s):
        p, q, k, cg_total = s
        c = (q.distance < eps).astype(dt)[:, None]
        target = c * (q.closest + eps * q.normal - p)
        matvec = lambda v: c * v + a * lap_t_lap(v) + b * (1.0 - c) * v  # noqa: E731
        diag = c + a * ltl[:, None] + b * (1.0 - c)
        if coarse is None:
            precond = lambda r: r / diag  # noqa: E731
        else:
            inv = coarse.inverse.astype(dt)
            precond = lambda r: r / diag + coarse.prolong @ (  # noqa: E731
                inv @ (coarse.restrict @ r))
        sol = solvers.pcg(matvec, target, precond, config.cg_tol, config.cg_max_iters)
        p = p + sol.x
        return p, body_lib.query(body, p), k + 1, cg_total + sol.iterations

    q0 = body_lib.query(body, vertices)
    zero = jnp.asarray(0, jnp.int32)
    p, q, rounds, cg_total = jax.lax.while_loop(
        lambda s: (s[2] < config.max_rounds) & (count_inside(s[1]) > 0), round_,
        (vertices, q0, zero, zero))
    return p, ResolveInfo(rounds, count_inside(q), cg_total)
