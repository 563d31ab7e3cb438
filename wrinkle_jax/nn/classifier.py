"""Moved to the `wrinkle_jax.classifier` package; this import path stays for
`wrinkle_jax.pipeline` (`--material auto`), which imports it, until that module is updated."""

from wrinkle_jax.classifier import *  # noqa: F403
from wrinkle_jax.classifier import __all__  # noqa: F401
