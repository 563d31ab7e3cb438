"""Reading and writing files the pipeline depends on.

`torch_pickle` reads PyTorch checkpoints (legacy and zip serializations) without torch and
without executing anything the file names.
"""

from wrinkle_jax.io.torch_pickle import CheckpointError, UnsafeCheckpointError
from wrinkle_jax.io.torch_pickle import load as load_torch_checkpoint

__all__ = ["CheckpointError", "UnsafeCheckpointError", "load_torch_checkpoint"]
