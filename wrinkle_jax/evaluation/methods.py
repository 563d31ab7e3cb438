"""Methods scored on aligned patch sets: the model, other model files, the baselines.

A method maps a `patchsets.PatchSet` to (K, S, S, 3) RGB-form outputs, unit normals inside
the mask and zero outside.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, detail, material_index
from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax.evaluation import baselines
from wrinkle_jax.evaluation.cells import TABLE_MATERIALS
from wrinkle_jax.evaluation.patchsets import PatchSet
from wrinkle_jax.evaluation.suite import MODEL_CARD_RESULTS, RESULTS, file_digest, portable_path

__all__ = ["DEFAULT_UNSHARP", "MATERIAL_SWEEP_RESULTS", "baseline_methods", "enhancer_method",
           "material_unsharp_settings", "model_methods", "oracle_methods", "run_model",
           "unsharp_setting", "wrong_material"]

# Unsharp masking when no sweep result exists (the model card's sweep best on training patches).
DEFAULT_UNSHARP = (8.0, 1.0)


def unsharp_setting(path: Path = MODEL_CARD_RESULTS, order: int = 1
                    ) -> tuple[float, float, str]:
    """(sigma texels, amount, source) of the unsharp-mask baseline with masked-blur `order`:
    the best entry of that order in the model card's "unsharp_sweep" (mean signed improvement
    on training patches; keys without "order=" are order 0, from before it existed) if that
    file has one, else `DEFAULT_UNSHARP`."""
    try:
        sweep = json.loads(Path(path).read_text())["unsharp_sweep"]
        parsed = {key: dict(part.split("=") for part in key.split(",")) for key in sweep}
        mine = [key for key, kv in parsed.items() if int(kv.get("order", 0)) == order]
        best = max(mine, key=sweep.get)
        kv = parsed[best]
        return (float(kv["sigma"]), float(kv["amount"]),
                f"{portable_path(path)}: unsharp_sweep best {best}")
    except (OSError, KeyError, ValueError, json.JSONDecodeError):
        s, a = DEFAULT_UNSHARP
        return s, a, (f"default order={order},sigma={s:g},amount={a:g} "
                      f"(no sweep in {portable_path(path)})")


# The per-material unsharp sweep on the val split (`python -m experiments.fidelity
# sweep-material`): the base every material-conditioned model is paired against.
MATERIAL_SWEEP_RESULTS = RESULTS / "fidelity" / "unsharp_sweep_material.json"


def material_unsharp_settings(path: Path = MATERIAL_SWEEP_RESULTS
                              ) -> dict[int, tuple[float, float]]:
    """Per-material (sigma texels, amount) of the val sweep's best entries, by material id;
    empty when the sweep has not been run."""
    path = Path(path)
    if not path.exists():
        return {}
    best = json.loads(path.read_text())["best"]
    return {MATERIALS.index(m): tuple(float(dict(q.split("=") for q in k.split(","))[x])
                                      for x in ("sigma", "amount"))
            for m, k in best.items()}


def enhancer_method(enh: enhancer_lib.Enhancer, batch_size: int = 16,
                    timings: dict | None = None,
                    material_of: Callable[[int], int] | None = None
                    ) -> Callable[[PatchSet], np.ndarray]:
    """The model as a method: (PatchSet) -> (K, S, S, 3) RGB-form outputs, unit normals inside
    the mask and zero outside (as the baselines).

    `material_of` maps the patch set's `material_id` to the id the model is told (default:
    itself); the wrong-material ablation (paper Fig. 10) passes another material's id.

    One jitted apply with a fixed batch shape (the last batch padded), compiled here (seconds
    in `timings["compile_s"]`), so calls time the network only; `timings` accumulates
    "network_s" and "network_patches".
    """
    apply = enhancer_lib.make_apply(enh)
    timings = {} if timings is None else timings
    size = enh.config.patch_size
    noise = bool(enh.config.unet.noise_channels)  # texel-noise models read the patch origins
    t0 = time.perf_counter()
    apply(enh.params, jnp.zeros((batch_size, size, size, 3), jnp.float32),
          jnp.zeros((batch_size,), jnp.int32),
          *((jnp.zeros((batch_size, 2), jnp.int32),) if noise else ())).block_until_ready()
    timings["compile_s"] = time.perf_counter() - t0

    def run(p: PatchSet) -> np.ndarray:
        mid = p.material_id if material_of is None else material_of(p.material_id)
        return enhancer_lib.enhance_patches(apply, enh.params, p.input, mid, p.mask,
                                            batch_size, timings,
                                            origins=p.origins if noise else None)

    return run


def wrong_material(material_id: int, materials=TABLE_MATERIALS) -> int:
    """The id (in `wrinkle_jax.MATERIALS`) of the table material that is not `material_id`'s:
    silk_charmeuse <-> denim_light, the lightest and stiffest of the table's materials. A
    material outside `materials` maps to the first of them."""
    ids = [material_index(m) for m in materials]
    others = [i for i in ids if i != material_id]
    if not others:
        raise ValueError("need at least two distinct materials")
    return others[0]


def baseline_methods(settings: dict[int, tuple[float, float]]
                     ) -> dict[str, Callable[[PatchSet], np.ndarray]]:
    """The non-learned methods, each (PatchSet) -> (K, S, S, 3) outputs (RGB form, masked).

    settings: masked-blur order -> (sigma, amount) of an unsharp-mask baseline (one entry per
    order, e.g. from `unsharp_setting`).
    """
    def unsharp(order, sigma, amount):
        return lambda p: baselines.unsharp_mask(p.input, p.mask, sigma, amount, order)

    return {
        "identity": lambda p: baselines.identity(p.input, p.mask),
        **{f"unsharp order {o} (sigma={s:g},amount={a:g})": unsharp(o, s, a)
           for o, (s, a) in sorted(settings.items())},
        "bicubic x2 down/up": lambda p: baselines.resample(p.input, p.mask, 2.0),
        "lanczos x2 down/up": lambda p: baselines.resample(p.input, p.mask, 2.0,
                                                            up=cv2.INTER_LANCZOS4),
    }



def oracle_methods() -> dict[str, Callable[[PatchSet], np.ndarray]]:
    """Ceilings that read the fine simulation of the scored frame (no method can): each
    (PatchSet) -> (K, S, S, 3) RGB-form outputs, masked.

    "oracle fine": the aligned fine patch itself (fine large scale and detail);
    "oracle coarse + fine detail": the coarse patch's large scale carrying its aligned fine
    patch's detail (`detail.transplant_rgb`), what a perfect detail enhancer would output.
    """
    def fine(p):
        return baselines.identity(p.target, p.mask)

    def transplant(p):
        return np.asarray(detail.transplant_rgb(p.input, p.target, p.mask, p.mask), np.float32)

    return {"oracle fine": fine, "oracle coarse + fine detail": transplant}


def model_methods(specs: list[str], batch_size: int) -> tuple[dict, dict]:
    """Extra models as methods, from "NAME=PATH" specs (e.g. a trained baseline).

    A one-material model (e.g. the PatchGAN baseline's "any") is told material 0; others the
    patch set's material by name. Returns (methods, sources): name -> method, and name -> a
    source string (file digest) that identifies its outputs.
    """
    methods, sources = {}, {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"expected NAME=PATH, got {spec!r}")
        enh = enhancer_lib.load_enhancer(path)
        if len(enh.config.materials) == 1:
            def material_of(_):
                return 0
        else:
            def material_of(i, enh=enh):
                return enh.config.material_id(MATERIALS[i])
        methods[name] = enhancer_method(enh, batch_size=batch_size, material_of=material_of)
        sources[name] = f"model {file_digest(path)}"
    return methods, sources


def run_model(enh: enhancer_lib.Enhancer, batch: dict, size: int = 16) -> tuple[np.ndarray, float]:
    """The model's unit-normal outputs on a batch of patches and its ms per patch (compile
    excluded)."""
    apply = enhancer_lib.make_apply(enh)
    n0 = min(size, len(batch["input"]))
    enhancer_lib.enhance_patches(apply, enh.params, batch["input"][:n0], batch["material"][:n0],
                             batch["mask"][:n0], size)  # compile outside the timing
    timings: dict = {}
    out = enhancer_lib.enhance_patches(apply, enh.params, batch["input"], batch["material"],
                                   batch["mask"], size, timings)
    return out, 1e3 * timings["network_s"] / max(len(out), 1)
