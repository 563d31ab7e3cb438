"""Motion features of a coarse garment sequence, per time window (issue 25).

One frame's normal map of a 30 mm coarse simulation says almost nothing about the fabric (the
five fabrics' coarse runs differ by 1-2 cm RMS; experiments/results/classifier/README.md). What
physics still leaves at coarse scale is in the motion: mass per area (how inertia and air drag
make the cloth lag and swing behind the body), stretch under its own weight, and drape at the
5-10 cm scale. This module turns a window of W frames into a fixed-length vector of such
measurements, grouped in families so each can be scored alone:

  * ``kinematic``: speeds and accelerations of the cloth relative to the body (log means and
    90th percentiles), and their ratios to the body's own speed and acceleration;
  * ``spectral``: the temporal power spectrum of the cloth's motion relative to the body,
    as fractions of the power in fixed frequency bands, and its centroid (Hz);
  * ``lag``: how far (s) and how strongly the lowest cloth (the hem) follows the body's
    velocity (normalized cross-correlation over lags);
  * ``stretch``: edge lengths against their rest lengths (the UV layout, meters):
    log-strain statistics over edges and over time;
  * ``curvature``: dihedral angles between neighbouring faces (fold sharpness) and how fast
    they change;
  * ``sag``: log-strain of hanging (near-vertical) sides against horizontal and diagonal
    ones, and of the top third against the bottom third (the weight a side carries);
  * ``rigidity``: motion of each vertex in the frame of its nearest body capsule (zero for a
    garment that rides its bones, as skinned input does);
  * ``gravity``: the log strain of hanging sides regressed on their height above the hem
    (meters): cloth hanging under its own weight strains as mass per area x g / stretch
    stiffness x the length below, so the slope is a material constant that the garment's
    size and cut do not set (the other stretch statistics mix both);
  * ``drape``: statistics of the baked coarse normal map at the 3-15 cm fold scale
    (`wrinkle_jax.classifier.drape`: band energies and their rates of change, fold
    wavelength, hang); computed only when `sequence_features` is given a raster plan
    (`drape.make_plan`), zeros otherwise.

Conventions: positions in meters, z up (gravity along -z, as in `wrinkle_jax.sim`), time in
seconds. Every feature is a function of distances, speeds, heights and times only, so it is
invariant to a translation of body and cloth together and to a rotation about the vertical
axis (tests/test_classifier_motion.py). All functions are pure NumPy (features are cheap: a
300-frame, 2k-vertex sequence takes well under a second), computed once per window.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from wrinkle_jax import mesh
from wrinkle_jax.classifier import drape

FAMILIES = ("kinematic", "spectral", "lag", "stretch", "curvature", "sag", "rigidity",
            "gravity", "drape")
# Band edges (Hz) of the spectral family: below the body's stride rate, around it, the first
# harmonics and the fast flutter a light fabric adds.
BANDS_HZ = (0.0, 1.0, 2.0, 3.5, 6.0, 10.0, 16.0)
_EPS = 1e-9


@dataclasses.dataclass(frozen=True)
class Topology:
    """What the features need of a garment's topology, computed once (NumPy).

    Attributes:
      edge_faces: (E, 2) int, the two faces of each interior edge (for dihedral angles).
      edge_verts: (E, 2) int, the vertices of that edge.
      corner_edges: (3F, 2) int, the vertex pairs of every face's three sides.
      rest_lengths: (3F,) float, rest length of each side in meters (from the UV layout),
        or None when the garment has no UVs in meters.
      faces: (F, 3) int.
    """

    edge_faces: np.ndarray
    edge_verts: np.ndarray
    corner_edges: np.ndarray
    rest_lengths: np.ndarray | None
    faces: np.ndarray

    def __hash__(self):
        return id(self)


def make_topology(faces, uvs=None, uv_faces=None) -> Topology:
    """Edges, face pairs and rest lengths of a triangle mesh.

    Args:
      faces: (F, 3) int vertex indices.
      uvs: (U, 2) float UV coordinates in meters of cloth (the simulator's layout), optional.
      uv_faces: (F, 3) int UV indices per face corner (default: `faces`).
    Returns:
      Topology. Sides whose UV length is below 0.1 mm get rest length NaN (ignored).
    """
    f = np.asarray(faces, np.int64)
    sides = mesh.face_sides(f)
    rest = None
    if uvs is not None:
        uf = f if uv_faces is None else np.asarray(uv_faces, np.int64)
        uv = np.asarray(uvs, np.float64)
        us = mesh.face_sides(uf)
        rest = np.linalg.norm(uv[us[:, 0]] - uv[us[:, 1]], axis=-1)
        rest = np.where(rest > 1e-4, rest, np.nan)
    a, b = mesh.shared_sides(f)
    return Topology(edge_faces=np.stack([a // 3, b // 3], axis=1),
                    edge_verts=np.sort(sides[a], axis=1), corner_edges=sides,
                    rest_lengths=rest, faces=f)


def body_reference(capsule_ends) -> np.ndarray:
    """The body's reference point per frame: the mean of its capsule end points.

    Args:
      capsule_ends: (T, C, 2, 3) meters.
    Returns:
      (T, 3) meters.
    """
    c = np.asarray(capsule_ends, np.float64)
    return c.reshape(c.shape[0], -1, 3).mean(axis=1)


def reference_track(arrays) -> np.ndarray | None:
    """The reference point per frame of a sequence's arrays (a dict-like of `.npz` arrays).

    The body's capsules (`body_reference`) when present; else the mean of the pinned points
    (``pins`` (T, P, 3): a sheet held in the wind has no body, its pins drive it); else None.
    Returns (T, 3) meters or None.
    """
    if "capsule_ends" in arrays:
        return body_reference(arrays["capsule_ends"])
    if "pins" in arrays and np.asarray(arrays["pins"]).size:
        return np.asarray(arrays["pins"], np.float64).mean(axis=1)
    return None


def power_spectrum(signal, fps: float):
    """Power spectrum of a real signal along time, Hann-windowed, mean removed.

    Args:
      signal: (W, ...) float, time first (any trailing shape is summed over).
      fps: samples per second.
    Returns:
      (freqs (W // 2 + 1,) Hz, power (W // 2 + 1,) summed over the trailing axes).
    """
    x = np.asarray(signal, np.float64)
    w = x.shape[0]
    x = x - x.mean(axis=0, keepdims=True)
    hann = np.hanning(w).reshape((w,) + (1,) * (x.ndim - 1))
    spec = np.abs(np.fft.rfft(x * hann, axis=0)) ** 2
    return np.fft.rfftfreq(w, 1.0 / fps), spec.reshape(spec.shape[0], -1).sum(axis=1)


def band_fractions(freqs, power, bands=BANDS_HZ) -> np.ndarray:
    """Share of the power (excluding 0 Hz) in each band [bands[i], bands[i + 1]); (B,)."""
    f, p = np.asarray(freqs), np.asarray(power)
    keep = f > 0
    f, p = f[keep], p[keep]
    total = p.sum() + _EPS
    return np.array([p[(f >= lo) & (f < hi)].sum() / total
                     for lo, hi in zip(bands[:-1], bands[1:], strict=True)])


def _kinematic(x_rel, ref, fps):
    v = np.diff(x_rel, axis=0) * fps
    a = np.diff(x_rel, n=2, axis=0) * fps ** 2
    vb = np.linalg.norm(np.diff(ref, axis=0) * fps, axis=-1)
    ab = np.linalg.norm(np.diff(ref, n=2, axis=0) * fps ** 2, axis=-1)
    sv, sa = np.linalg.norm(v, axis=-1), np.linalg.norm(a, axis=-1)
    # Deformation alone: the cloth's own mean motion removed, so a garment that rides
    # stiffly with the body scores low whatever the body does.
    d = x_rel - x_rel.mean(axis=1, keepdims=True)
    sd = np.linalg.norm(np.diff(d, axis=0) * fps, axis=-1)
    lg = np.log
    return np.array([lg(sv.mean() + 1e-4), lg(np.percentile(sv, 90) + 1e-4),
                     lg(sa.mean() + 1e-3), lg(np.percentile(sa, 90) + 1e-3),
                     lg((sa.mean() + 1e-3) / (sv.mean() + 1e-4)),
                     lg((sv.mean() + 1e-4) / (vb.mean() + 1e-2)),
                     lg((sa.mean() + 1e-3) / (ab.mean() + 1e-1)),
                     lg(sd.mean() + 1e-4)])


def _spectral(x_rel, fps):
    freqs, power = power_spectrum(x_rel, fps)
    frac = band_fractions(freqs, power)
    centroid = float((freqs * power)[1:].sum() / (power[1:].sum() + _EPS))
    return np.concatenate([np.log(frac + 1e-4), [centroid]])


def _hem(x0, frac=0.2):
    z = x0[:, 2]
    return z <= np.quantile(z, frac)


def _lag(x, ref, fps, max_lag_s=0.5):
    """Lag (s) and peak correlation of the hem's horizontal velocity behind the body's."""
    hem = _hem(x[0])
    vh = np.diff(x[:, hem].mean(axis=1), axis=0)[:, :2] * fps
    vb = np.diff(ref, axis=0)[:, :2] * fps
    vh = vh - vh.mean(0)
    vb = vb - vb.mean(0)
    n = len(vb)
    lags = range(0, max(1, min(int(max_lag_s * fps), n // 2)) + 1)
    corr = []
    for k in lags:
        a, b = vb[:n - k], vh[k:]
        corr.append(float((a * b).sum() / (np.sqrt((a * a).sum() * (b * b).sum()) + _EPS)))
    corr = np.array(corr)
    best = int(np.argmax(corr))
    hem_rel = x[:, hem].mean(axis=1) - ref
    swing = np.linalg.norm(hem_rel[:, :2] - hem_rel[:, :2].mean(0), axis=-1).mean()
    drop = (x[:, hem, 2].mean(axis=1) - ref[:, 2]).mean()
    return np.array([best / fps, corr[best], corr[0], np.log(swing + 1e-4), drop])


def _sides(x, topo):
    """The window's triangle sides that have a rest length, shared by the stretch, sag and
    gravity families: vectors d (W, S, 3), lengths (W, S), log strain (W, S) and midpoint
    heights (W, S), meters; None when the garment has no rest lengths."""
    if topo.rest_lengths is None:
        return None
    ce = topo.corner_edges
    ok = np.isfinite(topo.rest_lengths)
    d = x[:, ce[ok, 0]] - x[:, ce[ok, 1]]
    length = np.linalg.norm(d, axis=-1)
    strain = np.log(length / topo.rest_lengths[ok] + _EPS)
    height = 0.5 * (x[:, ce[ok, 0], 2] + x[:, ce[ok, 1], 2])
    return d, length, strain, height


def _stretch(sides):
    if sides is None:
        return np.zeros(6)
    s = sides[2]                                                               # log strain
    per_edge = s.mean(axis=0)
    return np.array([per_edge.mean(), np.median(per_edge), np.percentile(per_edge, 90),
                     np.percentile(per_edge, 10), per_edge.std(), s.std(axis=0).mean()])


def _sag(sides):
    """Strain of sides by their 3D direction: hanging (vertical) sides carry the weight below
    them, so their stretch against the horizontal sides' is mass per area x g / stiffness."""
    if sides is None:
        return np.zeros(6)
    d, length, s, height = sides
    up = np.abs(d[..., 2]) / (length + _EPS)                                   # |cos| to z
    vert, horiz = up > 0.8, up < 0.3
    diag = ~(vert | horiz)
    lo, hi = np.quantile(height, [1 / 3, 2 / 3], axis=1, keepdims=True)

    def mean(mask):
        return float((s * mask).sum() / max(mask.sum(), 1))

    return np.array([mean(vert), mean(horiz), mean(diag), mean(vert) - mean(horiz),
                     mean(vert & (height >= hi)), mean(vert & (height <= lo))])


def _gravity(x, sides, hem_quantile=0.02):
    """Least-squares line of hanging sides' log strain against their midpoint's height above
    the hem (the `hem_quantile` of the frame's heights), over the window: [slope (1/m),
    intercept, correlation]. A strip hanging under gravity has strain rho g h / k at height h
    above its free end (the weight below), so the slope reads rho g / k; the intercept holds
    what does not grow with the weight (the solver's floor, the body's pull)."""
    if sides is None:
        return np.zeros(3)
    d, length, strain, height = sides
    vert = np.abs(d[..., 2]) > 0.8 * length
    if vert.sum() < 3:
        return np.zeros(3)
    s = strain[vert]
    hem = np.quantile(x[..., 2], hem_quantile, axis=1)[:, None]               # (W, 1)
    h = (height - hem)[vert]
    hc, sc = h - h.mean(), s - s.mean()
    var = (hc * hc).mean()
    slope = (hc * sc).mean() / (var + _EPS)
    corr = (hc * sc).mean() / np.sqrt(var * (sc * sc).mean() + _EPS ** 2)
    return np.array([slope, s.mean() - slope * h.mean(), corr])


def dihedral_angles(x, topo: Topology) -> np.ndarray:
    """Unsigned angles (radians) between the normals of the two faces of each interior edge.

    Args:
      x: (..., V, 3) positions, meters.
    Returns:
      (..., E) angles in [0, pi]; 0 for a flat pair.
    """
    f = topo.faces
    p0, p1, p2 = x[..., f[:, 0], :], x[..., f[:, 1], :], x[..., f[:, 2], :]
    n = np.cross(p1 - p0, p2 - p0)
    na, nb = n[..., topo.edge_faces[:, 0], :], n[..., topo.edge_faces[:, 1], :]
    # atan2 of |na x nb| and na . nb: accurate near 0 where arccos of a dot product is not,
    # and the face areas cancel (no normalization to guard for degenerate faces).
    return np.arctan2(np.linalg.norm(np.cross(na, nb), axis=-1), (na * nb).sum(-1))


def _curvature(x, topo, fps):
    th = dihedral_angles(x, topo)                                              # (W, E)
    dth = np.abs(np.diff(th, axis=0)) * fps
    return np.array([th.mean(), np.percentile(th, 90), th.std(axis=0).mean(),
                     np.log(dth.mean() + 1e-4), np.log(np.percentile(dth, 90) + 1e-4)])


FAMILY_DIMS = {"kinematic": 8, "spectral": len(BANDS_HZ), "lag": 5, "stretch": 6,
               "curvature": 5, "sag": 6, "rigidity": 3, "gravity": 3,
               "drape": drape.DIM}


def family_slices() -> dict:
    """Family name -> slice of the full feature vector (in `FAMILIES` order)."""
    out, i = {}, 0
    for name in FAMILIES:
        out[name] = slice(i, i + FAMILY_DIMS[name])
        i += FAMILY_DIMS[name]
    return out


FEATURE_DIM = sum(FAMILY_DIMS.values())


def _rigidity(x, caps, ref, fps):
    """How much the cloth moves in the frame of the body part it hangs from: each vertex is
    given its nearest capsule at the window's first frame and followed in that capsule's
    frame. Skinned (LBS) cloth rides its bones, so this motion is ~0 away from the joints;
    simulated cloth swings and lags. Zeros when there are no capsules (a pinned sheet)."""
    if caps is None:
        return np.zeros(3)
    rot, org = _capsule_frames(caps, ref)
    bone = _nearest_capsule(x[0], caps[0])
    local = np.einsum("tvij,tvj->tvi", rot[:, bone], x - org[:, bone])          # (W, V, 3)
    nonrigid = np.linalg.norm(np.diff(local, axis=0), axis=-1) * fps
    rel = np.linalg.norm(np.diff(x - ref[:, None], axis=0), axis=-1) * fps
    return np.array([np.log(nonrigid.mean() + 1e-4), np.log(np.percentile(nonrigid, 90) + 1e-4),
                     np.log((nonrigid.mean() + 1e-4) / (rel.mean() + 1e-4))])


def window_features(frames, ref, topo: Topology, fps: float, capsules=None,
                    drape_features=None) -> np.ndarray:
    """The feature vector of one window of frames.

    Args:
      frames: (W, V, 3) garment positions, meters, W >= 8.
      ref: (W, 3) the body's reference point per frame (`body_reference`), meters.
      topo: `make_topology` of the garment.
      fps: frames per second.
      capsules: (W, C, 2, 3) the body's capsules, meters (the ``rigidity`` family), or None.
      drape_features: (drape.DIM,) the window's ``drape`` family (`drape.window_features`;
        it needs the baked normal maps, see `sequence_features`), or None for zeros.
    Returns:
      (FEATURE_DIM,) float64, families in `FAMILIES` order (`family_slices`).
    """
    x = np.asarray(frames, np.float64)
    r = np.asarray(ref, np.float64)
    if x.ndim != 3 or x.shape[0] < 8 or r.shape != (x.shape[0], 3):
        raise ValueError(f"window_features needs (W >= 8, V, 3) frames and (W, 3) ref, got "
                         f"{x.shape} and {r.shape}")
    x_rel = x - r[:, None, :]
    sides = _sides(x, topo)
    return np.concatenate([_kinematic(x_rel, r, fps), _spectral(x_rel, fps),
                           _lag(x, r, fps), _stretch(sides), _curvature(x, topo, fps),
                           _sag(sides),
                           _rigidity(x, None if capsules is None else
                                     np.asarray(capsules, np.float64), r, fps),
                           _gravity(x, sides),
                           np.zeros(drape.DIM) if drape_features is None else
                           np.asarray(drape_features, np.float64).reshape(drape.DIM)])


def window_starts(num_frames: int, window: int, stride: int) -> np.ndarray:
    """Start frames of the windows of `window` frames every `stride` frames; (N,) int."""
    if num_frames < window:
        return np.zeros(0, np.int64)
    return np.arange(0, num_frames - window + 1, stride)


def sequence_features(frames, ref, topo: Topology, fps: float, window: int = 32,
                      stride: int = 16, capsules=None, drape_plan=None) -> np.ndarray:
    """Features of every window of a sequence: (N, FEATURE_DIM), N = len(window_starts).
    capsules: (T, C, 2, 3) or None (see `window_features`); drape_plan: the garment's
    `drape.make_plan`, or None (the ``drape`` family is then zero)."""
    starts = window_starts(len(frames), window, stride)
    if len(starts) == 0:
        raise ValueError(f"the sequence has {len(frames)} frames, fewer than one window "
                         f"({window})")
    dw = [None] * len(starts)
    if drape_plan is not None:
        dw = drape.window_features(drape.sequence_stats(drape_plan, frames, fps), starts,
                                   window)
    return np.stack([window_features(frames[s:s + window], ref[s:s + window], topo, fps,
                                     None if capsules is None else capsules[s:s + window], d)
                     for s, d in zip(starts, dw, strict=True)])


def _capsule_frames(capsule_ends, ref):
    """(T, C, 3, 3) orthonormal frames (rows: axis, side, third) and (T, C, 3) origins."""
    c = np.asarray(capsule_ends, np.float64)
    a, b = c[:, :, 0], c[:, :, 1]
    e1 = b - a
    ln = np.linalg.norm(e1, axis=-1, keepdims=True)
    # A zero-length capsule (a sphere, e.g. the head) has no axis: use the vertical.
    e1 = np.where(ln > 1e-6, e1 / np.maximum(ln, 1e-12), np.array([0.0, 0.0, 1.0]))
    # The side direction points from the capsule to the body's reference point, so the frame
    # turns with the body; a capsule in line with that point falls back to a fixed axis.
    s = ref[:, None, :] - 0.5 * (a + b)
    s = s - (s * e1).sum(-1, keepdims=True) * e1
    n = np.linalg.norm(s, axis=-1, keepdims=True)
    fz, fx = np.cross(e1, np.array([0.0, 0.0, 1.0])), np.cross(e1, np.array([1.0, 0.0, 0.0]))
    fallback = np.where(np.linalg.norm(fz, axis=-1, keepdims=True) > 1e-3, fz, fx)
    fallback = fallback / np.linalg.norm(fallback, axis=-1, keepdims=True)
    s = np.where(n > 1e-6, s / np.maximum(n, 1e-12), fallback)
    e3 = np.cross(e1, s)
    return np.stack([e1, s, e3], axis=-2), a


def _nearest_capsule(x0, caps0) -> np.ndarray:
    """(V,) index of the capsule axis segment nearest to each vertex; caps0 (C, 2, 3)."""
    a0, b0 = caps0[:, 0], caps0[:, 1]
    ab = b0 - a0
    t = np.clip(((x0[:, None] - a0) * ab).sum(-1) / ((ab * ab).sum(-1) + 1e-12), 0.0, 1.0)
    return np.argmin(np.linalg.norm(x0[:, None] - (a0 + t[..., None] * ab), axis=-1), axis=1)


def follow_body_rigidly(rest_vertices, capsule_ends) -> np.ndarray:
    """A skinned garment without dynamics: every vertex rides rigidly on its nearest capsule.

    The stand-in for linear-blend-skinned input (one bone per vertex): the cloth moves exactly
    with the body and never swings, stretches or folds on its own.

    Args:
      rest_vertices: (V, 3) the garment at frame 0, meters.
      capsule_ends: (T, C, 2, 3) the body's capsules per frame, meters.
    Returns:
      (T, V, 3) float32 frames, meters; frame 0 equals `rest_vertices`.
    """
    x0 = np.asarray(rest_vertices, np.float64)
    c = np.asarray(capsule_ends, np.float64)
    ref = body_reference(c)
    rot, org = _capsule_frames(c, ref)
    bone = _nearest_capsule(x0, c[0])
    local = np.einsum("vij,vj->vi", rot[0, bone], x0 - org[0, bone])
    return np.einsum("tvji,vj->tvi", rot[:, bone], local).astype(np.float32) + \
        org[:, bone].astype(np.float32)
