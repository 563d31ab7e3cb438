"""Aerodynamics: a seeded, gusty, turbulent wind field and per-triangle drag and lift.

Contract (JAX, jittable):
  * `make_wind(key, ...)` draws a `WindField` (a frozen pytree of small arrays) from an
    explicit PRNG key: a mean wind, slow gusts modulating its speed and direction, and a few
    travelling Fourier modes of turbulence.
  * `wind_velocity(wind, points (N, 3) m, t s) -> (N, 3) m/s`.
  * `aero_forces(x, v, faces, air_velocity, ...) -> (V, 3) N`: per triangle, with the
    relative air velocity u = w - v_face, unit normal n, area A and u_n = u . n,

        F = 1/2 rho A [ C_d |u_n| u_n n  +  C_l |u| u_n l ],  l = unit(n - (n . u^) u^)

    (pressure drag along the normal; lift perpendicular to the relative flow, zero for flow
    along or across the cloth), split equally over the three corners. With zero wind this is
    still-air drag, which is what slows a light skirt's swing. The solver evaluates it once
    per frame by default, with the exact-decay factor of `stable_dt` keeping it stable.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.mesh import face_cross
from wrinkle_jax.numerics import normalize, safe_div, safe_norm

AIR_DENSITY = 1.2  # kg/m^3 at 20 C, sea level


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class WindField:
    """Wind parameters (all arrays; see `make_wind`).

    Attributes:
      mean: (3,) mean wind velocity, m/s.
      gust_amp, gust_freq, gust_phase: (G,) relative speed modulation, Hz, radians.
      swing_amp, swing_freq, swing_phase: (G,) direction swing about z, radians, Hz, radians.
      mode_k: (M, 3) turbulence wave vectors, 1/m; mode_freq (M,) Hz; mode_phase (M,);
      mode_amp: (M, 3) turbulence velocity amplitudes, m/s.
    """

    mean: Any
    gust_amp: Any
    gust_freq: Any
    gust_phase: Any
    swing_amp: Any
    swing_freq: Any
    swing_phase: Any
    mode_k: Any
    mode_freq: Any
    mode_phase: Any
    mode_amp: Any


def make_wind(key, mean_velocity=(0.0, 2.0, 0.0), gustiness: float = 0.5,
              swing: float = 0.35, turbulence: float = 0.3, num_gusts: int = 3,
              num_modes: int = 8) -> WindField:
    """Draw a gusty wind from `key`.

    Args:
      key: jax.random key.
      mean_velocity: (3,) mean wind, m/s.
      gustiness: relative speed modulation amplitude (sum over gusts), 0.5 = +-50 %.
      swing: direction swing amplitude about z, radians.
      turbulence: turbulent velocity amplitude relative to the mean speed.
      num_gusts, num_modes: number of gust sinusoids and turbulence modes.
    """
    ks = jax.random.split(key, 8)
    mean = jnp.asarray(mean_velocity, jnp.float32)
    speed = jnp.linalg.norm(mean)
    g = num_gusts
    amp = jax.random.dirichlet(ks[0], jnp.ones(g)) * gustiness
    wave_len = jax.random.uniform(ks[5], (num_modes,), minval=0.3, maxval=2.0)  # meters
    kdir = normalize(jax.random.normal(ks[6], (num_modes, 3)))
    return WindField(
        mean=mean,
        gust_amp=amp.astype(jnp.float32),
        gust_freq=jax.random.uniform(ks[1], (g,), minval=0.1, maxval=0.8),
        gust_phase=jax.random.uniform(ks[2], (g,), maxval=2 * jnp.pi),
        swing_amp=(jax.random.dirichlet(ks[3], jnp.ones(g)) * swing).astype(jnp.float32),
        swing_freq=jax.random.uniform(ks[4], (g,), minval=0.05, maxval=0.4),
        swing_phase=jax.random.uniform(ks[7], (g,), maxval=2 * jnp.pi),
        mode_k=kdir * (2 * jnp.pi / wave_len)[:, None],
        mode_freq=jax.random.uniform(jax.random.fold_in(key, 1), (num_modes,), minval=0.3,
                                     maxval=2.0),
        mode_phase=jax.random.uniform(jax.random.fold_in(key, 2), (num_modes,),
                                      maxval=2 * jnp.pi),
        mode_amp=turbulence * speed / jnp.sqrt(num_modes)
        * jax.random.normal(jax.random.fold_in(key, 3), (num_modes, 3)),
    )


def wind_velocity(wind: WindField, points, t):
    """Wind velocity (N, 3) m/s at points (N, 3) m and time t (s)."""
    tau = 2 * jnp.pi * t
    gust = 1.0 + jnp.sum(wind.gust_amp * jnp.sin(tau * wind.gust_freq + wind.gust_phase))
    ang = jnp.sum(wind.swing_amp * jnp.sin(tau * wind.swing_freq + wind.swing_phase))
    c, s = jnp.cos(ang), jnp.sin(ang)
    m = wind.mean
    mean = jnp.maximum(gust, 0.0) * jnp.stack([c * m[0] - s * m[1], s * m[0] + c * m[1], m[2]])
    phase = points @ wind.mode_k.T - tau * wind.mode_freq + wind.mode_phase  # (N, M)
    return mean[None] + jnp.sin(phase) @ wind.mode_amp


def aero_forces(x, v, faces, air_velocity, drag, lift, rho=AIR_DENSITY, vertex_faces=None,
                stable_dt=None, areal_density=None):
    """Aerodynamic forces on the vertices (V, 3), newtons.

    Args:
      x, v: (V, 3) positions (m) and velocities (m/s).
      faces: (F, 3) int.
      air_velocity: (F, 3) air velocity at the face centroids (m/s), or None for still air.
      drag, lift: coefficients; rho: air density, kg/m^3.
      vertex_faces: optional (V, D) incident faces padded with F (see `incident_faces`):
        gathers instead of a scatter-add (faster on CPU).
      stable_dt: optional time step (s) over which the force will be held constant; the
        force is then scaled by 1 / (1 + c dt), c = rho (C_d |u_n| + C_l |u|) / (2 rho_A),
        the exact velocity decay of quadratic drag du/dt = -c u, so a long step never
        reverses the relative flow (needs `areal_density`, kg/m^2).
    """
    cr = face_cross(x, faces)
    area = 0.5 * safe_norm(cr)
    n = normalize(cr)
    u = -jnp.mean(v[faces], axis=1)
    if air_velocity is not None:
        u = u + air_velocity
    un = jnp.sum(u * n, -1)
    speed = safe_norm(u)
    l_dir = normalize(n - safe_div(un, speed * speed)[:, None] * u)
    f = 0.5 * rho * area[:, None] * (drag * (jnp.abs(un) * un)[:, None] * n
                                     + lift * (speed * un)[:, None] * l_dir)
    if stable_dt is not None:
        c = 0.5 * rho * (drag * jnp.abs(un) + lift * speed) / areal_density
        f = f / (1.0 + c * stable_dt)[:, None]
    if vertex_faces is not None:
        f = jnp.concatenate([f / 3.0, jnp.zeros((1, 3), f.dtype)])
        return jnp.sum(f[vertex_faces], axis=1)
    return jax.ops.segment_sum(jnp.repeat(f / 3.0, 3, axis=0), faces.reshape(-1),
                               num_segments=x.shape[0])


def incident_faces(faces, num_vertices: int) -> np.ndarray:
    """(V, D) int32 faces incident to each vertex, padded with F (NumPy, once per mesh)."""
    f = np.asarray(faces, np.int64)
    v = f.reshape(-1)
    fid = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(v, kind="stable")
    v, fid = v[order], fid[order]
    count = np.bincount(v, minlength=num_vertices)
    start = np.r_[0, np.cumsum(count)[:-1]]
    slot = np.arange(len(v)) - start[v]
    out = np.full((num_vertices, max(int(count.max()), 1)), len(f), np.int32)
    out[v, slot] = fid
    return out
