"""XPBD cloth: the jittable solver; the model it runs on (pytrees and their allocation, NumPy,
once per mesh) is built in `cloth_model` and re-exported here.

Method: extended position-based dynamics (Macklin, Mueller & Chentanez 2016) with small
steps (Macklin et al. 2019: many substeps, one constraint iteration each). Per substep of
length h = 1 / (fps * substeps):

  1. v += h (g + f_aero / m);  v *= exp(-h (damping + extra_damping))
     (f_aero is evaluated once per frame by default, made stable by an exact-decay factor)
  2. p = x + h v; pinned vertices are set on their kinematic tracks
  3. constraint projection, graph-coloured Gauss-Seidel (colours precomputed in NumPy, each
     colour a vectorized gather/scatter with unique vertices; a `lax.scan` runs over padded
     runs of consecutive colours, `SimConfig.color_waste`), in this order:
       bending  C_e = sqrt(1 / (A_1 + A_2)) sum_k K_k x_k (3-vector, quadratic isometric
                bending, Bergou et al. 2006, normalized so a cylinder of radius R stores
                B / (2 R^2) per area; the rim hinges of a clamped region use their free
                face's area, `cloth_model._hinges`), compliance 1 / B. With one iteration
                per substep an interior hinge settles at B / (1 + r), r = h^2 B sum_k w_k
                K_k^2 (w: inverse masses; denim at PD 10 mm, 20 substeps: r ~0.31, 0.76 B;
                experiments/results/sim/textile/README.md)
       long-range attachments |x_i - x_pin(i)| <= geodesic rest distance (Kim, Chentanez &
                Mueller 2012), only when the garment has pins
       then `stretch_sweeps` times (colour order alternating):
         stretch limits |x_i - x_j| <= (1 + 0.5 %) rest UV distance for random same-panel
                pairs 3, 9 and 27 edges apart (multi-scale: corrects the slow global sag of
                one sweep per substep on fine meshes; never resists bending). The slack
                is the same for every fabric, and at 20 substeps the solver is softer than
                any k_s, so every fabric reaches it: a hanging strip lengthens 0.72-0.74 %
                whatever its k_s (4.3-4.9 % without the limits; textile README, session 20)
         stretch C_e = (|x_j - x_i| - L_e) / L_e, compliance 1 / (k_s A_e) (last, so the
                local strain left by the hard long-range projections is smoothed)
  4. optional self-collision (`SimConfig.self_collision`, see `selfcollision`): candidates
     rebuilt every `rebuild_every` substeps into a flat bounded contact list, vertex-triangle
     thickness constraints (closest points once per substep) projected before the body
     contacts and again after them with the body-contact vertices held, then `body_relax`
     rounds (a pass with the cloth's masses, the body again) so layers pressed on the body
     separate; optionally, at each rebuild, an intersection-contour step that shrinks
     crossings (`untangle`)
  5. collisions with the present colliders (offset = cloth thickness, Coulomb friction;
     pinned vertices are kinematic and not projected)
  6. v = (p - x) / h; x = p

Contract:
  * `build_cloth(garment, pinned, ...)` -> `ClothModel` (frozen pytree of arrays: topology,
    rest data, colours, optional wind). `fabric_params(fabric)` -> `SimParams` (scalars), so
    one compiled solver serves every material of a scene.
  * `cloth_simulator(config)` -> `(init_fn, step_fn)`:
        init_fn(model, positions (V, 3)) -> ClothState
        step_fn(model, params, state, drive0, drive1) -> ClothState   (one frame)
    `Drive` holds the kinematic inputs at a frame boundary (time, pin positions, colliders).
    The step is specialized at trace time: no pins, no wind, no spheres ... traces no code.
  * `run_frames(config, model, params, state, drives)` scans `step_fn` over frames under
    `jit`; `simulate_frames` runs it in fixed-size chunks with a progress callback.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.numerics import normalize, safe_div, safe_norm
from wrinkle_jax.sim import (
    aero,
    colliders,
    pokethrough,
    selfcollision,
    selfcollision_blocks,
    untangle,
)

# The model's pytrees and their allocation live in cloth_model; every name stays importable
# from here (old import paths, pickles).
from wrinkle_jax.sim.cloth_model import (  # noqa: F401
    GRAVITY,
    Attachments,
    BendColor,
    ClothModel,
    ClothState,
    Drive,
    LimitColor,
    SimParams,
    StretchColor,
    _geodesic_to_pins,
    _hinges,
    _nearest,
    _uv_corner_geometry,
    build_cloth,
    color_constraints,
    color_groups,
    fabric_params,
    model_summary,
    stretch_limits,
)
from wrinkle_jax.sim.selfcollision import SelfCollisionConfig


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static solver settings (hashable; a `jit` static argument).

    Attributes:
      fps: frames per second. substeps: substeps per frame. iterations: constraint sweeps
      per substep (XPBD multipliers are carried across sweeps). stretch_sweeps: stretch and
      stretch-limit sweeps per iteration (bending once), colour order alternating.
      relax: over-relaxation of the stretch sweeps. pre_collide: also resolve
      contacts before the constraint sweep (spreads a body's push; costs one collision pass).
      collision_passes: deepest-contact passes after the sweep (2 helps where colliders
      overlap). aero_per_substep: evaluate drag/lift every substep instead of once per frame
      (held constant over the frame with an exact-decay factor; 20x cheaper).
      self_collision: a `SelfCollisionConfig` (vertex-triangle thickness constraints after
      the constraint sweep, before the body contacts), or None (off: no code traced).
      color_waste: the colours of a constraint kind are projected by a `lax.scan` over runs
      of consecutive colours padded to a common size (`color_groups`); this bounds the padded
      (wasted) work per kind, as a fraction of the real work. Larger: fewer runs, a smaller
      program (faster compile), more padded work per substep. Results do not depend on it.
    """

    fps: float = 30.0
    substeps: int = 20
    iterations: int = 1
    stretch_sweeps: int = 1
    relax: float = 1.0
    pre_collide: bool = False
    collision_passes: int = 1
    aero_per_substep: bool = False
    self_collision: SelfCollisionConfig | None = None
    color_waste: float = 0.25

    @property
    def h(self) -> float:
        return 1.0 / (self.fps * self.substeps)


# --------------------------------------------------------------------------------------------
# Constraint projections (JAX)
# --------------------------------------------------------------------------------------------


# Padded constraints (see `_stack_colors`) are no-ops twice over: their weights / directions
# are zero, and they name vertex V, one past the last, so their gathers clamp to a real vertex
# (finite values) and their scatters are dropped. A padded colour moves exactly the vertices
# of its real constraints, by the same amounts (up to float32 rounding of the fused code).


def _get(a, idx):
    return a.at[idx].get(mode="clip")


def project_stretch(p, w, c: StretchColor, lam, inv_k_h2, relax=1.0):
    """One Gauss-Seidel colour of strain constraints. inv_k_h2 = 1 / (k_s h^2); `relax` is
    the successive over-relaxation factor (1 = plain Gauss-Seidel)."""
    d = _get(p, c.j) - _get(p, c.i)
    n = normalize(d)
    strain = (safe_norm(d) - c.rest) / c.rest
    wi, wj = _get(w, c.i), _get(w, c.j)
    at = c.inv_area * inv_k_h2
    dlam = relax * safe_div(-(strain + at * lam), (wi + wj) / (c.rest * c.rest) + at)
    corr = n * (dlam / c.rest)[:, None]
    p = p.at[c.i].add(-wi[:, None] * corr, mode="drop").at[c.j].add(wj[:, None] * corr,
                                                                     mode="drop")
    return p, lam + dlam


def project_bend(p, w, c: BendColor, lam, inv_b_h2):
    """One colour of quadratic bending constraints (3-vector C per hinge). inv_b_h2 = 1/(B h^2)."""
    cvec = jnp.einsum("nk,nkd->nd", c.weights, _get(p, c.idx))
    wk = _get(w, c.idx)
    den = jnp.sum(wk * c.weights * c.weights, axis=1) + inv_b_h2
    dlam = -(cvec + inv_b_h2 * lam) / den[:, None]
    dx = (wk * c.weights)[..., None] * dlam[:, None, :]
    return p.at[c.idx.reshape(-1)].add(dx.reshape(-1, 3), mode="drop"), lam + dlam


def project_limits(p, w, c: LimitColor):
    """One colour of unilateral distance limits (hard, inactive unless stretched)."""
    d = _get(p, c.j) - _get(p, c.i)
    excess = jnp.maximum(safe_norm(d) - c.max_dist, 0.0)
    wi, wj = _get(w, c.i), _get(w, c.j)
    corr = normalize(d) * safe_div(excess, wi + wj)[:, None]
    return p.at[c.i].add(wi[:, None] * corr, mode="drop").at[c.j].add(-wj[:, None] * corr,
                                                                      mode="drop")


def project_attachments(p, a: Attachments, pin_idx):
    """Keep each attached vertex within its rest geodesic distance of its pin."""
    d = p[a.vertex] - p[pin_idx[a.slot]]
    excess = jnp.maximum(safe_norm(d) - a.max_dist, 0.0)
    return p.at[a.vertex].add(-normalize(d) * excess[:, None])


def _stack_colors(colors: tuple, num_vertices: int, max_waste: float) -> list:
    """Runs of consecutive colours (`color_groups`), each stacked along a new leading axis and
    padded to its largest colour with no-op constraints on vertex `num_vertices` (one past
    the last; rest length 1, zero weights). Traced once per step; shapes are static."""
    if not colors:
        return []
    sizes = [jax.tree_util.tree_leaves(c)[0].shape[0] for c in colors]
    fills = {"i": num_vertices, "j": num_vertices, "idx": num_vertices, "rest": 1.0,
             "inv_area": 0.0, "weights": 0.0, "max_dist": 1.0}
    out = []
    for a, b in color_groups(sizes, max_waste):
        n = max(sizes[a:b])

        def pad(name, arr, n=n):
            arr = jnp.asarray(arr)
            width = [(0, n - arr.shape[0])] + [(0, 0)] * (arr.ndim - 1)
            return jnp.pad(arr, width, constant_values=fills[name])

        fields = [f.name for f in dataclasses.fields(colors[a])]
        out.append(type(colors[a])(**{
            f: jnp.stack([pad(f, getattr(c, f)) for c in colors[a:b]]) for f in fields}))
    return out


def _sweep(p, runs, lams, project, reverse=False):
    """One Gauss-Seidel sweep over stacked colour runs (`_stack_colors`): `project(p, colour,
    lam) -> (p, lam)` applied colour by colour in order (or in reverse order), a `lax.scan`
    per run so the traced program holds one projection per run, not per colour.
    lams: per run (colours, n, ...) multipliers, or None entries for stateless constraints."""
    new = list(lams)
    order = range(len(runs))
    for r in (reversed(order) if reverse else order):
        def body(q, inputs):
            c, lam = inputs
            return project(q, c, lam)
        p, new[r] = jax.lax.scan(body, p, (runs[r], lams[r]), reverse=reverse)
    return p, new


# --------------------------------------------------------------------------------------------
# The solver
# --------------------------------------------------------------------------------------------


def cloth_simulator(config: SimConfig) -> tuple[Callable, Callable]:
    """The (init_fn, step_fn) pair of an XPBD cloth solver (see the module docstring)."""
    n_sub = int(config.substeps)
    h = config.h
    dt = 1.0 / config.fps
    sc = config.self_collision
    if sc is not None and (sc.rebuild_every < 1 or n_sub % sc.rebuild_every):
        raise ValueError(f"self_collision.rebuild_every={sc.rebuild_every} must divide "
                         f"substeps={n_sub}")
    if sc is not None and sc.untangle < 0:
        raise ValueError(f"self_collision.untangle={sc.untangle} must be >= 0")
    if sc is not None and not 0.0 <= sc.poke_repair < 1.0:
        raise ValueError(f"self_collision.poke_repair={sc.poke_repair} must be in [0, 1)")

    # Dropped-candidate counts: the build's three, and crossed pairs beyond the untangling
    # step's list when it is on.
    n_over = 3 if sc is None or sc.untangle == 0 else 4

    def init_fn(model: ClothModel, positions) -> ClothState:
        x = jnp.asarray(positions, jnp.float32)
        del model
        return ClothState(x=x, v=jnp.zeros_like(x),
                          self_overflow=None if sc is None else jnp.zeros(n_over, jnp.int32))

    def step_fn(model: ClothModel, params: SimParams, state: ClothState, drive0: Drive,
                drive1: Drive) -> ClothState:
        free = model.free
        w = free / (params.density * model.vertex_area)
        inv_k_h2 = 1.0 / (params.stretch * h * h)
        inv_b_h2 = 1.0 / (params.bending * h * h)
        damp = jnp.exp(-h * (params.damping + drive0.extra_damping))

        def aero_acc(x, v, t, span):
            air = None
            if model.wind is not None:
                air = aero.wind_velocity(model.wind, jnp.mean(x[model.faces], axis=1), t)
            f = aero.aero_forces(x, v, model.faces, air, params.drag, params.lift,
                                 vertex_faces=model.vertex_faces, stable_dt=span,
                                 areal_density=params.density)
            return f * w[:, None]

        gravity = params.gravity[None] * free[:, None]
        frame_acc = gravity
        if model.aero is not None and not config.aero_per_substep:
            frame_acc = gravity + aero_acc(state.x, state.v, drive0.time, dt)

        if sc is not None and model.self_topo is None:
            raise ValueError("self-collision needs a model built with self_topo (build_cloth)")

        def rebuild(x):
            if sc.raw_per_vertex > 0 and sc.block > 0:  # cell vertices in blocks
                return selfcollision_blocks.build_pairs_blocked(x, model.faces,
                                                                model.self_topo, sc)
            if sc.raw_per_vertex > 0:  # bounds on totals, the nearest kept (see build_pairs)
                return selfcollision.build_pairs(x, model.faces, model.self_topo, sc)
            # Per-vertex candidates, then one flat bounded list: the projections then touch
            # only the contacts that exist (0.009-3 per vertex measured), not V x K slots.
            cand = selfcollision.build_candidates(x, model.faces, model.self_topo, sc)
            pairs, lost = selfcollision.flatten(cand, n_pairs)
            return pairs, jnp.concatenate([cand.overflow, lost[None]])

        # Colours stacked into padded runs once per step (static shapes). The loops over
        # colours, stretch sweeps and iterations are XLA loops, so the compiled program does
        # not grow with their counts (unrolled, it took 12-15 s to compile per garment).
        nv = model.vertex_area.shape[0]
        n_pairs = 0 if sc is None else selfcollision.max_pairs(nv, sc)
        bend_runs = _stack_colors(model.bend, nv, config.color_waste)
        stretch_runs = _stack_colors(model.stretch, nv, config.color_waste)
        limit_runs = _stack_colors(model.limits, nv, config.color_waste)

        def bend_one(q, c, lam):
            return project_bend(q, w, c, lam, inv_b_h2)

        def stretch_one(q, c, lam):
            return project_stretch(q, w, c, lam, inv_k_h2, config.relax)

        def limit_one(q, c, lam):
            return project_limits(q, w, c), lam

        def stretch_sweep(q, lam_s, reverse):
            q, _ = _sweep(q, limit_runs, [None] * len(limit_runs), limit_one)
            return _sweep(q, stretch_runs, lam_s, stretch_one, reverse)

        def one_iteration(q, lam_b, lam_s):
            q, lam_b = _sweep(q, bend_runs, lam_b, bend_one)
            # Stretch converges slowest on fine meshes: extra (cheap) stretch-only sweeps.
            # Long-range corrections first, local stretch last: the hard long-range
            # projections leave local strain noise that the stretch sweep then smooths.
            if model.attach is not None:
                q = project_attachments(q, model.attach, model.pin_idx)
            # Sweeps alternate the colour order (symmetric Gauss-Seidel): pairs in a loop.
            def pair(_, carry):
                q, lam_s = carry
                q, lam_s = stretch_sweep(q, lam_s, False)
                return stretch_sweep(q, lam_s, True)

            pairs = config.stretch_sweeps // 2
            if pairs == 1:
                q, lam_s = pair(0, (q, lam_s))
            elif pairs > 1:
                q, lam_s = jax.lax.fori_loop(0, pairs, pair, (q, lam_s))
            if config.stretch_sweeps % 2:
                q, lam_s = stretch_sweep(q, lam_s, False)
            return q, lam_b, lam_s

        def constraint_iterations(q):
            # XPBD multipliers start at zero every substep and carry across iterations.
            lam_b = [jnp.zeros(r.weights.shape[:2] + (3,)) for r in bend_runs]
            lam_s = [jnp.zeros(r.rest.shape) for r in stretch_runs]
            if config.iterations == 1:
                return one_iteration(q, lam_b, lam_s)[0]
            return jax.lax.fori_loop(0, config.iterations,
                                     lambda _, c: one_iteration(*c), (q, lam_b, lam_s))[0]

        def rebuild_sides(x):
            cand, lost = rebuild(x)
            if sc.untangle > 0:  # shrink the crossings; their contacts off until the next one
                x, keep, _, crossed_lost = untangle.untangle_contacts(
                    x, free, model.faces, model.self_topo.vertex_faces, cand.vertex, cand.tri,
                    cand.valid, sc.untangle, untangle.max_crossed(nv, sc.untangle_pairs),
                    model.self_topo.near_faces, model.self_topo.poke.ring, sc.untangle_smooth)
                cand = dataclasses.replace(cand, valid=keep)
                lost = jnp.concatenate([lost, crossed_lost[None]])
            sides = None
            if sc.poke_repair > 0:  # poked-through vertices, decided until the next rebuild
                sides = pokethrough.repair_sides(x, model.faces, model.self_topo.poke,
                                                 cand.vertex, cand.tri, sc.poke_repair)
            return x, cand, sides, lost

        def substep(carry, k):
            x, v, cand, sides, overflow = carry
            if sc is not None:
                # Candidates from the substep's start positions; the margin covers the motion
                # until the next rebuild.
                # The untangling step (if on) moves x itself; v is kept (no impulse).
                if sc.rebuild_every == 1:
                    x, cand, sides, lost = rebuild_sides(x)
                else:
                    fresh = k % sc.rebuild_every == 0
                    x, cand, sides, lost = jax.lax.cond(
                        fresh, rebuild_sides,
                        lambda y: (y, cand, sides, jnp.zeros(n_over, jnp.int32)), x)
                overflow = saturating_add(overflow, lost)
                # Closest points and directions at the substep's start: fixed over the
                # substep, so computed once for both projection stages.
                frame = selfcollision.contact_frame(x, model.faces, cand, sides)
            s0 = k / n_sub
            s1 = (k + 1) / n_sub
            acc = frame_acc
            if model.aero is not None and config.aero_per_substep:
                acc = gravity + aero_acc(x, v, drive0.time + s0 * dt, h)
            v = (v + h * acc) * damp
            p = x + h * v
            if model.pin_idx is not None:
                p = p.at[model.pin_idx].set(drive0.pins + s1 * (drive1.pins - drive0.pins))
            c0 = colliders.lerp_colliders(drive0.colliders, drive1.colliders, s0)
            c1 = colliders.lerp_colliders(drive0.colliders, drive1.colliders, s1)

            def body_contacts(q, friction, passes):
                """The colliders' contacts applied to the free vertices, and (V,) which
                vertices they moved."""
                moved = colliders.collide(q, x, c0, c1, params.offset, friction, passes=passes)
                return jnp.where(free[:, None] > 0, moved, q), jnp.any(moved != q, axis=-1)

            # Contacts before the constraint sweep too: a moving body's push then spreads
            # through the cloth in the same substep instead of stretching the contact ring.
            if config.pre_collide:
                p, _ = body_contacts(p, params.friction, 1)
            p = constraint_iterations(p)
            if sc is not None:
                # After the cloth constraints (they would undo it).
                for _ in range(sc.passes):
                    p, _ = selfcollision.project_pairs(p, w, cand, frame)
            p, held = body_contacts(p, params.friction, config.collision_passes)
            if sc is not None:
                # A layer pressed between the body and another layer: the body contact pushed
                # it out into that layer. Those vertices are now held (inverse mass 0), so the
                # outer layer gives way instead of pushing them back into the body.
                w_held = jnp.where(held, 0.0, w)
                for _ in range(sc.post_passes):
                    p, _ = selfcollision.project_pairs(p, w_held, cand, frame)
                # Layers pressed on the body (both held above): the pair separates with the
                # cloth's masses, the body pushes the inner layer back out (no friction: it
                # was applied once this substep).
                for _ in range(sc.body_relax):
                    p, _ = selfcollision.project_pairs(p, w, cand, frame)
                    p, _ = body_contacts(p, None, config.collision_passes)
            return (p, (p - x) / h, cand, sides, overflow), None

        cand0 = sides0 = None
        if sc is not None:  # rebuilt at k = 0
            m = selfcollision.max_pairs(state.x.shape[0], sc)
            cand0 = selfcollision.Pairs(jnp.zeros(m, jnp.int32), jnp.zeros(m, jnp.int32),
                                        jnp.zeros(m, jnp.float32), jnp.zeros(m, bool))
            if sc.poke_repair > 0:
                sides0 = jnp.zeros(m, jnp.float32)
        (x, v, _, _, overflow), _ = jax.lax.scan(
            substep, (state.x, state.v, cand0, sides0, state.self_overflow), jnp.arange(n_sub))
        return ClothState(x=x, v=v, self_overflow=overflow)

    return init_fn, step_fn


def saturating_add(total, count):
    """total + count for non-negative int32 counts, held at the int32 maximum instead of
    wrapping round to negative numbers (a fine skirt drops ~1e5 contacts per substep, so a
    whole run's count passes 2^31; `simulate_frames` sums per chunk on the host instead)."""
    top = jnp.iinfo(jnp.int32).max
    return jnp.where(total > top - count, top, total + count)


@functools.partial(jax.jit, static_argnames="config")
def run_frames(config: SimConfig, model: ClothModel, params: SimParams, state: ClothState,
               drives: Drive, num_valid=None):
    """Advance len(drives) - 1 frames (drives carry a leading frame axis of T + 1).

    Args:
      num_valid: optional traced int: frames at index >= num_valid leave the state unchanged
        (padding of a fixed-size chunk).
    Returns:
      (final ClothState, positions (T, V, 3) float32 at the end of each frame).
    """
    _, step_fn = cloth_simulator(config)
    d0 = jax.tree_util.tree_map(lambda a: a[:-1], drives)
    d1 = jax.tree_util.tree_map(lambda a: a[1:], drives)
    count = d0.time.shape[0]
    valid = jnp.arange(count) < (count if num_valid is None else num_valid)

    def frame(s, inputs):
        a, b, ok = inputs
        new = step_fn(model, params, s, a, b)
        s = jax.tree_util.tree_map(lambda n, o: jnp.where(ok, n, o), new, s)
        return s, s.x

    return jax.lax.scan(frame, state, (d0, d1, valid))


def slice_drives(drives: Drive, start: int, stop: int) -> Drive:
    """Frames [start, stop) of stacked drives, padded by repeating the last frame."""
    n = jax.tree_util.tree_leaves(drives)[0].shape[0]
    return _take_frames(drives, np.minimum(np.arange(start, stop), n - 1))


@jax.jit
def _take_frames(drives: Drive, idx):
    # One program per drive layout; eagerly, each leaf's gather would compile on its own.
    return jax.tree_util.tree_map(lambda a: a[idx], drives)


def simulate_frames(config: SimConfig, model: ClothModel, params: SimParams,
                    state: ClothState, drives: Drive, chunk: int = 30,
                    progress: Callable[[int], None] | None = None, start: int = 0,
                    on_chunk: Callable[[int, ClothState, np.ndarray], None] | None = None):
    """Run all frames of `drives` (T + 1 boundaries -> T frames) in jitted chunks.

    Chunks have a fixed length (the last one padded), so the solver compiles once.
    Args:
      start: frames already simulated, `state` being the state after them (a resumed run;
        a multiple of `chunk` keeps the chunks, and so the result, those of a whole run).
      on_chunk: optional callback(frames done, state, this call's chunks so far: a list of
        (n, V, 3) positions, not copied) after each chunk, before `progress` (checkpoints:
        `resume.Writer`).
    Returns:
      (final ClothState, positions (T - start, V, 3) NumPy float32). With self-collision the
      final state's (and `on_chunk`'s) `self_overflow` is an int64 NumPy array: the counts
      are summed per chunk on the host, since a whole run's passes the int32 range.
    """
    total = jax.tree_util.tree_leaves(drives)[0].shape[0] - 1
    out = []
    done = int(start)
    over = None
    if state.self_overflow is not None:
        over = np.asarray(state.self_overflow, np.int64)
        zero = jnp.zeros(over.shape, jnp.int32)
        state = state.replace(self_overflow=zero)
    while done < total:
        n = min(chunk, total - done)
        part = slice_drives(drives, done, done + chunk + 1)
        state, xs = run_frames(config, model, params, state, part, jnp.int32(n))
        out.append(np.asarray(xs[:n]))
        done += n
        if over is not None:
            over = over + np.asarray(state.self_overflow, np.int64)
            state = state.replace(self_overflow=zero)
        if on_chunk is not None:
            on_chunk(done, state if over is None else state.replace(self_overflow=over), out)
        if progress is not None:
            progress(n)
    if over is not None:
        state = state.replace(self_overflow=over)
    return state, np.concatenate(out) if out else np.zeros((0,) + state.x.shape, np.float32)


def kinetic_energy(params: SimParams, model: ClothModel, v):
    """Kinetic energy (J) of free vertices."""
    m = params.density * model.vertex_area * model.free
    return 0.5 * jnp.sum(m * jnp.sum(v * v, -1))


@jax.jit
def edge_strain(model: ClothModel, x):
    """Strain (|x_j - x_i| - L) / L of every edge constraint, concatenated over colours."""
    return jnp.concatenate([(safe_norm(x[c.j] - x[c.i]) - c.rest) / c.rest
                            for c in model.stretch])
