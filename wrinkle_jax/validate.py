"""Up-front checks of command-line input: units and scale, degenerate faces, the texel/patch/
lift budget and frame ranges. Everything here is NumPy on the coarse mesh (milliseconds) and
runs before any rasterization or compilation, so a wrong unit or a huge garment fails in a
second with a message naming the file, the likely cause and the fix, instead of running for
minutes or allocating gigabytes.

Errors:
  * `InputError` (a `GarmentError`): the input file is wrong (exit code 1).
  * `UsageError`: a flag is wrong, e.g. `--frames` (exit code 2).
Checks that only warn return their warnings as strings (the caller prints and reports them).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from wrinkle_jax.mesh import GarmentError

# Multipliers that bring a mesh's coordinates to meters (`--units`).
UNIT_SCALES = {"m": 1.0, "cm": 0.01, "mm": 0.001}
# Bounding-box diagonal of a plausible garment, meters (a glove to a long cape or a tent-sized
# sheet); outside it the coordinates are almost surely in another unit.
PLAUSIBLE_EXTENT_M = (0.1, 5.0)
# Budget of one run, checked before rasterizing: normal-map texels, patches per frame and
# vertices of the lifted mesh (the ~10 mm subdivision). The bundled demo skirt needs 0.35 M
# texels, 32 patches per frame at stride 64 and ~25 k lifted vertices.
MAX_MAP_TEXELS = 4096 * 4096
MAX_PATCHES_PER_FRAME = 4096
MAX_LIFT_VERTICES = 1_000_000
# A face is degenerate when its area is below DEGENERATE_AREA_FRACTION of the median face area
# (zero-area faces included) or when it is a sliver (its smallest altitude is below
# SLIVER_RATIO of its longest edge). Up to DEGENERATE_MAX_FRACTION of the faces only warn.
DEGENERATE_AREA_FRACTION = 1e-6
SLIVER_RATIO = 1e-3
DEGENERATE_MAX_FRACTION = 0.01


class InputError(GarmentError):
    """The input garment is unusable as given (wrong unit, degenerate, over budget)."""


class UsageError(ValueError):
    """A command-line flag is wrong (exit code 2)."""


def unit_scale(units: str | None, scale: float | None) -> float:
    """The factor that converts the input's coordinates to meters.

    Args:
      units: "m", "cm", "mm" or None; scale: an explicit factor or None (not both).
    Raises:
      UsageError: both given, an unknown unit, or a factor that is not a positive number.
    """
    if units is not None and scale is not None:
        raise UsageError("give either --units or --scale, not both")
    if units is not None:
        if units not in UNIT_SCALES:
            raise UsageError(f"--units must be one of {', '.join(UNIT_SCALES)}, got {units!r}")
        return UNIT_SCALES[units]
    if scale is None:
        return 1.0
    if not (math.isfinite(scale) and scale > 0):
        raise UsageError(f"--scale must be a positive number, got {scale}")
    return float(scale)


def face_areas(vertices, faces) -> np.ndarray:
    """(F,) float64 triangle areas, m^2, of (V, 3) vertices and (F, 3) int faces."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return 0.5 * np.linalg.norm(cross, axis=1)


def _edge_lengths(vertices, faces) -> np.ndarray:
    """(F, 3) float64 lengths of each face's three edges (0-1, 1-2, 2-0), meters."""
    v = np.asarray(vertices, np.float64)
    p = v[np.asarray(faces, np.int64)]
    return np.linalg.norm(p - np.roll(p, -1, axis=1), axis=2)


def _unit_hint(diagonal: float) -> str:
    """The likely unit of a garment `diagonal` (in file units) across, and the fix."""
    lo, hi = PLAUSIBLE_EXTENT_M
    names = {"mm": "millimetres", "cm": "centimetres"}
    fits = [(abs(math.log10(diagonal * f)), u, f) for u, f in UNIT_SCALES.items()
            if u in names and lo <= diagonal * f <= hi]
    if fits and diagonal > hi:
        guesses = " or ".join(f"{names[u]} (--units {u})" for _, u, _ in sorted(fits))
        return f"it is probably in {guesses}; or pass --scale S to convert it to meters"
    factor = 10.0 ** round(math.log10(1.0 / max(diagonal, 1e-30)))
    return f"if it is not in meters, pass --scale S to convert it (e.g. --scale {factor:g})"


def check_scale(vertices, faces, source: str) -> dict:
    """Check that a garment's size is plausible in meters.

    Args:
      vertices: (V, 3) positions as they will be used (after --units/--scale), meters.
      faces: (F, 3) int triangles.
      source: the file named in messages.
    Returns:
      {"diagonal_m": bounding-box diagonal, "median_edge_m": median edge length}.
    Raises:
      InputError: the diagonal is outside `PLAUSIBLE_EXTENT_M`; the message names the size, the
        median edge, the likely unit and the flag that fixes it.
    """
    v = np.asarray(vertices, np.float64)
    diagonal = float(np.linalg.norm(v.max(0) - v.min(0)))
    edges = _edge_lengths(v, faces)
    median_edge = float(np.median(edges))
    lo, hi = PLAUSIBLE_EXTENT_M
    if not lo <= diagonal <= hi:
        size = "small" if diagonal < lo else "large"
        raise InputError(
            f"{source}: the garment is {diagonal:.4g} units across (median edge "
            f"{median_edge:.3g}), too {size} for a garment in meters (expected {lo:g} to "
            f"{hi:g} m); {_unit_hint(diagonal)}")
    return {"diagonal_m": diagonal, "median_edge_m": median_edge}


def check_faces(vertices, faces, uvs, uv_faces, source: str) -> list[str]:
    """Zero-area and sliver triangles, in 3D and in the UV layout.

    Args:
      vertices: (V, 3) meters; faces: (F, 3) int; uvs: (T, 2); uv_faces: (F, 3) int.
    Returns:
      warnings (one string each) when at most `DEGENERATE_MAX_FRACTION` of the faces are
      degenerate (they bake no texel and crack the lifted mesh locally).
    Raises:
      InputError: the garment has no 3D area (all vertices on a point or a line), its UV
        layout has no area, or more than `DEGENERATE_MAX_FRACTION` of the faces are degenerate.
    """
    f = np.asarray(faces, np.int64)
    area = face_areas(vertices, f)
    if not area.sum() > 0:
        raise InputError(f"{source}: the garment has zero 3D area (all vertices lie on one "
                         f"point or line)")
    uv = np.asarray(uvs, np.float64)
    uf = np.asarray(uv_faces, np.int64)
    e1, e2 = uv[uf[:, 1]] - uv[uf[:, 0]], uv[uf[:, 2]] - uv[uf[:, 0]]
    uv_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    if not uv_area.sum() > 0:
        raise InputError(f"{source}: the UV layout has zero area (all UVs lie on one point or "
                         f"line); a UV layout is required")
    longest = _edge_lengths(vertices, f).max(1)
    # Smallest altitude = 2 * area / longest edge.
    sliver = 2.0 * area < SLIVER_RATIO * longest * longest
    tiny = area <= DEGENERATE_AREA_FRACTION * np.median(area)
    bad3 = tiny | sliver
    bad_uv = uv_area <= DEGENERATE_AREA_FRACTION * np.median(uv_area)
    n = len(f)
    problems = []
    for count, what in ((int(bad3.sum()), "zero-area or sliver faces in 3D"),
                        (int((bad_uv & ~bad3).sum()), "zero-area faces in the UV layout")):
        if count:
            first = int(np.flatnonzero(bad3 if "3D" in what else bad_uv & ~bad3)[0])
            problems.append((count, f"{count} of {n} {what} (first: face {first + 1})"))
    total = sum(c for c, _ in problems)
    if total > DEGENERATE_MAX_FRACTION * n:
        raise InputError(f"{source}: {'; '.join(m for _, m in problems)}: more than "
                         f"{DEGENERATE_MAX_FRACTION:.0%} of the faces are degenerate; remove "
                         f"or fix them (e.g. merge by distance) before enhancing")
    return [f"{source}: {m}; they bake no texel and may crack the lifted mesh"
            for _, m in problems]


def check_budget(garment, texel_size: float, patch_size: int | None, stride: int | None,
                 lift: bool, target_edge: float, source: str) -> dict:
    """Map size, patches per frame and lifted vertices, estimated before any rasterization.

    Args:
      garment: the coarse garment (meters, with UVs); texel_size: meters per texel;
      patch_size, stride: the enhancer's patch size and the tile stride, texels (None: no
        patches, e.g. a bake);
      lift: whether the lift runs; target_edge: its mean edge length, meters.
    Returns:
      {"map_shape": (H, W), "patches_per_frame": upper bound (0 without patches),
      "lift_vertices": estimate (0 without lift)}, plus "warning" when the garment is smaller
      than one patch (a likely unit mistake, but a glove can be that small).
    Raises:
      InputError: over `MAX_MAP_TEXELS`, `MAX_PATCHES_PER_FRAME` or `MAX_LIFT_VERTICES`; the
        message gives the numbers and the fixes (units, --texel-size).
    """
    from wrinkle_jax.normalmap import layout_for

    if not texel_size > 0:
        raise UsageError(f"--texel-size must be positive, got {texel_size}")
    # layout_for refuses maps over 16384^2 itself; catch that as a budget error too.
    try:
        layout = layout_for(garment, texel_size)
        h, w = layout.shape
    except ValueError as e:
        raise InputError(f"{source}: {e}; is the garment in meters (--units, --scale)?"
                         ) from None
    rows = cols = 0
    if patch_size:
        rows = -(-max(h - patch_size, 0) // stride) + 1
        cols = -(-max(w - patch_size, 0) // stride) + 1
    area = float(face_areas(garment.vertices, garment.faces).sum())
    # A regular triangle mesh with edge e has ~ 2 / (sqrt(3) e^2) vertices per m^2.
    lift_vertices = int(2.0 * area / (math.sqrt(3.0) * target_edge ** 2)) if lift else 0
    over = []
    if h * w > MAX_MAP_TEXELS:
        over.append(f"a {h}x{w}-texel normal map ({h * w / 1e6:.1f} M texels, limit "
                    f"{MAX_MAP_TEXELS / 1e6:.1f} M)")
    if rows * cols > MAX_PATCHES_PER_FRAME:
        over.append(f"up to {rows * cols} patches per frame (limit {MAX_PATCHES_PER_FRAME})")
    if lift_vertices > MAX_LIFT_VERTICES:
        over.append(f"~{lift_vertices / 1e6:.1f} M lifted vertices at {target_edge * 1e3:g} mm "
                    f"edges (limit {MAX_LIFT_VERTICES / 1e6:.1f} M)")
    if over:
        raise InputError(f"{source}: {area:.3g} m^2 of cloth at {texel_size * 1e3:g} mm per "
                         f"texel needs {' and '.join(over)}; is the garment in meters (--units, "
                         f"--scale)? Otherwise use a larger --texel-size or --no-lift")
    budget = {"map_shape": (h, w), "patches_per_frame": rows * cols,
              "lift_vertices": lift_vertices}
    inner = (h - 2 * layout.margin, w - 2 * layout.margin)
    if patch_size and max(inner) < patch_size:
        budget["warning"] = (f"{source}: the garment covers only {inner[0]}x{inner[1]} texels "
                             f"at {texel_size * 1e3:g} mm, less than one {patch_size}-texel patch "
                             f"({patch_size * texel_size:g} m); if it is not in meters, pass "
                             f"--units or --scale")
    return budget


_FRAMES = re.compile(r"^\s*(-?\d+)?\s*(?::\s*(-?\d+)?\s*(?::\s*(-?\d+)?\s*)?)?$")


def parse_frames(spec: str | None, n: int) -> range:
    """Frame indices selected by `spec`, with Python slice semantics, in a sequence of `n`.

    "A:B" is frames A..B-1, "A:B:S" every S-th, "A" one frame, "-3:" the last three, ":-1" all
    but the last; None or "" is all frames. Unlike a Python slice, bounds are never clipped.

    Raises:
      UsageError: malformed spec, a step of 0, a bound outside the sequence (an index
        outside [-n, n-1], a stop outside [-n, n]) or an empty selection.
    """
    if spec is None or not spec.strip():
        return range(n)
    m = _FRAMES.match(spec)
    if not m or not any(m.groups()):
        raise UsageError(f"--frames must look like A:B, A:B:S or A (Python slice, negative "
                         f"counts from the end), got {spec!r}")
    a, b, s = (None if x is None else int(x) for x in m.groups())
    if ":" not in spec:
        if not -n <= a < n:
            raise UsageError(f"--frames {spec}: frame {a} is outside the {n}-frame sequence "
                             f"(valid: 0 to {n - 1}, or -{n} to -1)")
        return range(a % n, a % n + 1)
    if s == 0:
        raise UsageError(f"--frames {spec}: the step must not be 0")
    for name, x in (("start", a), ("stop", b)):
        if x is not None and not -n <= x <= n:
            raise UsageError(f"--frames {spec}: {name} {x} is outside the {n}-frame sequence "
                             f"(valid: -{n} to {n}); ranges are never clipped")
    r = range(n)[slice(a, b, s)]
    if len(r) == 0:
        raise UsageError(f"--frames {spec} selects no frame of the {n}-frame sequence")
    return r


def load_checked(input_path: Path, args, texel_size: float, patch_size: int | None = None,
                 stride: int | None = None, lift: bool = False, template=None,
                 lift_edge: float = 0.01):
    """Load a sequence, convert it to meters (--units/--scale) and run every up-front check:
    size, degenerate faces, texel/patch/lift budget (`lift_edge` meters), --frames.

    Args:
      input_path: anything `meshio.load_sequence` reads; args: a namespace with `frames` and
        optionally `units`, `scale`; texel_size: meters per texel; patch_size, stride: texels
        (None: no patch budget); lift: whether the lift runs; template: a PC2's template OBJ.

    Returns:
      (sequence in meters, selected frame indices, warnings, budget dict).
    Raises:
      GarmentError (incl. InputError): bad input; UsageError: bad flags.
    """
    from wrinkle_jax import meshio

    factor = unit_scale(getattr(args, "units", None), getattr(args, "scale", None))
    seq = meshio.load_sequence(input_path, template=template)
    if factor != 1.0:
        g = seq.garment
        f32 = np.float32(factor)
        seq = meshio.make_sequence(np.asarray(seq.frames, np.float32) * f32,
                                   g.replace(vertices=np.asarray(g.vertices) * f32), seq.fps,
                                   {**seq.metadata, "unit_scale": factor}, str(input_path))
    g = seq.garment
    src = str(input_path)
    warnings = check_faces(g.vertices, g.faces, g.uvs, g.uv_faces, src)
    check_scale(g.vertices, g.faces, src if factor == 1.0 else f"{src} (scaled by {factor:g})")
    sel = list(parse_frames(args.frames, len(seq)))
    budget = check_budget(g, texel_size, patch_size, stride or patch_size, lift, lift_edge, src)
    if budget.get("warning"):
        warnings.append(budget.pop("warning"))
    return seq, sel, warnings, budget


def choose_material(flag: str | None, stored, materials, source: str) -> tuple[str, str]:
    """(material or "auto", its source: "flag", "stored" or "classified").

    Raises:
      UsageError: an unknown name; no flag and no known stored material; "auto"
        without a classifier.
    """
    names = ", ".join(materials)
    if flag is None:
        if stored in materials:
            return stored, "stored"
        what = f"stores the unknown material {stored!r}" if stored else "stores no material"
        raise UsageError(f"{source} {what}; pass --material NAME (one of {names})")
    if flag == "auto":
        from wrinkle_jax.classifier import calibrated, synthesis_model
        from wrinkle_jax.outdir import display_path

        # "auto" is the shipped synthesis classifier, else the motion classifier (issue 25);
        # cli_pipeline runs it on the input and stops naming --material when it abstains.
        if not (synthesis_model.shipped() or Path(calibrated.MOTION_PATH).is_file()):
            raise UsageError(f"--material auto: no material classifier is available (none "
                             f"ships at {display_path(synthesis_model.SYNTHESIS_PATH)} or "
                             f"{display_path(calibrated.MOTION_PATH)}); pass "
                             f"--material NAME (one of {names})")
        return "auto", "classified"
    if flag not in materials:
        raise UsageError(f"unknown material {flag!r}; expected auto or one of {names}")
    return flag, "flag"
