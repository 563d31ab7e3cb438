"""wrinkle-jax: plausible fine wrinkles for coarse garment animations, in JAX.

Reimplements and extends *Deep Detail Enhancement for Any Garment* (Zhang et al., EG 2021):
bake a coarse garment to a UV normal map, enhance overlapping patches with a material-conditioned
U-Net, merge them, and lift the enhanced map back to a detailed mesh.
"""

__version__ = "0.1.0"

# Materials, in the fixed index order used by every model and data set.
MATERIALS = ("silk_charmeuse", "wool_melton", "knit_terry", "silk_chiffon", "denim_light")


def material_index(name: str) -> int:
    """Index of a material name in `MATERIALS`; raises ValueError naming the valid choices."""
    try:
        return MATERIALS.index(name)
    except ValueError:
        choices = ", ".join(MATERIALS)
        raise ValueError(f"unknown material {name!r}; expected one of {choices}") from None


def load_enhancer(path=None, conv_impl: str | None = None):
    """Load an enhancer model file; None loads the shipped default model.

    The same as `wrinkle_jax.enhancer.load_enhancer` (imported on first call, so importing
    the package stays light). Returns an `Enhancer` (model, params, config, meta); `conv_impl`
    None picks the U-Net's form by width (`enhancer.inference_conv_impl`).

    Raises:
      enhancer.EnhancerError: naming the file, if it is missing or not an enhancer file.
    """
    from wrinkle_jax.enhancer import load_enhancer as _load

    return _load(path, conv_impl=conv_impl)
