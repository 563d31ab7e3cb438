"""Safe, torch-free reader for PyTorch checkpoints (``.pth`` / ``.pt`` files).

Contract:
  ``load(path) -> dict[str, np.ndarray]`` reads a checkpoint written by ``torch.save`` without
  importing torch and without executing anything the file names. Nested containers are
  flattened with dotted keys: ``{"state_dict": {"conv.weight": t}}`` becomes
  ``{"state_dict.conv.weight": array}``; list/tuple items use their index as key. Tensors become
  NumPy arrays that own their memory, in C order, with the tensor's logical shape (storage
  offsets and strides are applied), in native byte order. Python ``int``/``float``/``bool``
  leaves become 0-d arrays; any other leaf (strings, ``None``) is dropped.

Both serializations are read:

* **legacy** (``torch.save(..., _use_new_zipfile_serialization=False)``, torch < 1.6):
  five consecutive pickles and raw data -- magic number ``0x1950a86a20f9469cfc6c``, protocol
  version ``1001``, a sys-info dict (endianness), the object (storages referenced by persistent
  ids ``('storage', storage_type, key, location, numel[, view_metadata])``), the list of storage
  keys; then, for each key in that order, the element count as an int64 followed by the raw
  storage bytes.
* **zip** (torch >= 1.6): an archive with ``<prefix>/data.pkl`` (persistent ids
  ``('storage', storage_type, key, location, numel)``) and one entry ``<prefix>/data/<key>``
  per storage, plus an optional ``<prefix>/byteorder``.

Storage dtypes: float32, float64, float16, bfloat16 (as ``ml_dtypes.bfloat16``), int64, int32,
int16, int8, uint8 and bool, in the legacy typed form (``torch.FloatStorage``) and the newer
``torch.UntypedStorage`` + explicit dtype form (``torch._utils._rebuild_tensor_v3``).

Safety: every pickle is first scanned opcode by opcode (without executing it); a global that is
not on a short allow-list (``collections.OrderedDict``, the ``torch._utils._rebuild_*`` tensor
and parameter builders, the ``torch.*Storage`` types and ``torch`` dtypes) raises
:class:`UnsafeCheckpointError` before any object is built. The unpickler's ``find_class``
enforces the same list again at load time, and it maps every allowed name to an inert
placeholder defined here -- nothing from torch (or anywhere else) is imported or called.
Strided views are bounds-checked against their storage before being materialized.

Corrupt, truncated or unsupported files raise :class:`CheckpointError` whose message starts
with the file name.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import pickletools
import struct
import zipfile
from dataclasses import dataclass
from typing import Any

import ml_dtypes
import numpy as np

__all__ = ["CheckpointError", "UnsafeCheckpointError", "load", "LEGACY_MAGIC_NUMBER"]

LEGACY_MAGIC_NUMBER = 0x1950A86A20F9469CFC6C
LEGACY_PROTOCOL_VERSION = 1001


class CheckpointError(ValueError):
    """A checkpoint file is corrupt, truncated or in an unsupported layout."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint's pickle names a global outside the allow-list (it is never executed)."""


# ---------------------------------------------------------------------------------------------
# Inert placeholders for the names a checkpoint may use.


class _Inert:
    """Base of the placeholders: a pickle's BUILD opcode must not rewrite them after the
    builders below have validated them (frozen dataclasses alone do not stop BUILD)."""

    def __setstate__(self, state):
        raise pickle.UnpicklingError(f"refusing to set state on {type(self).__name__}")



@dataclass(frozen=True)
class _StorageType(_Inert):
    """Stands in for ``torch.FloatStorage`` & co.; only carries the element dtype."""

    name: str
    dtype: np.dtype


@dataclass(frozen=True)
class _DType(_Inert):
    """Stands in for ``torch.float32`` & co. (used by ``_rebuild_tensor_v3``)."""

    name: str
    dtype: np.dtype


@dataclass(frozen=True)
class _StorageRef(_Inert):
    """A storage referenced by a persistent id; its bytes are read after unpickling.

    ``offset`` and ``numel`` are in elements of ``dtype`` and select a view of the root storage
    ``key`` (legacy storage views); for ordinary storages ``offset == 0``.
    """

    key: str
    dtype: np.dtype
    offset: int
    numel: int


@dataclass(frozen=True)
class _TensorRef(_Inert):
    """A tensor whose storage bytes are not known yet (materialized after unpickling)."""

    storage: _StorageRef
    offset: int
    shape: tuple
    stride: tuple
    dtype: np.dtype  # element dtype (may differ from an untyped storage's uint8)


_STORAGE_DTYPES = {
    "FloatStorage": np.dtype(np.float32),
    "DoubleStorage": np.dtype(np.float64),
    "HalfStorage": np.dtype(np.float16),
    "BFloat16Storage": np.dtype(ml_dtypes.bfloat16),
    "LongStorage": np.dtype(np.int64),
    "IntStorage": np.dtype(np.int32),
    "ShortStorage": np.dtype(np.int16),
    "CharStorage": np.dtype(np.int8),
    "ByteStorage": np.dtype(np.uint8),
    "BoolStorage": np.dtype(np.bool_),
    "UntypedStorage": np.dtype(np.uint8),
}

_TORCH_DTYPES = {
    "float32": np.float32,
    "float": np.float32,
    "float64": np.float64,
    "double": np.float64,
    "float16": np.float16,
    "half": np.float16,
    "bfloat16": ml_dtypes.bfloat16,
    "int64": np.int64,
    "long": np.int64,
    "int32": np.int32,
    "int": np.int32,
    "int16": np.int16,
    "short": np.int16,
    "int8": np.int8,
    "uint8": np.uint8,
    "bool": np.bool_,
}


def _as_shape(value, what):
    if not isinstance(value, tuple | list) or not all(
        isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value
    ):
        raise ValueError(f"tensor {what} must be a tuple of non-negative ints, got {value!r}")
    return tuple(value)


def _rebuild_tensor(storage, storage_offset, size, stride):
    """Placeholder for ``torch._utils._rebuild_tensor``."""
    if not isinstance(storage, _StorageRef):
        raise ValueError(f"tensor storage must come from a persistent id, got {type(storage)}")
    if not isinstance(storage_offset, int) or storage_offset < 0:
        raise ValueError(f"bad storage offset {storage_offset!r}")
    shape = _as_shape(size, "size")
    strides = _as_shape(stride, "stride")
    if len(shape) != len(strides):
        raise ValueError(f"size {shape} and stride {strides} have different lengths")
    return _TensorRef(storage, storage_offset, shape, strides, storage.dtype)


def _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad=False,
                       backward_hooks=None, metadata=None):
    """Placeholder for ``torch._utils._rebuild_tensor_v2`` (hooks and metadata ignored)."""
    return _rebuild_tensor(storage, storage_offset, size, stride)


def _rebuild_tensor_v3(storage, storage_offset, size, stride, requires_grad=False,
                       backward_hooks=None, dtype=None, metadata=None):
    """Placeholder for ``torch._utils._rebuild_tensor_v3`` (untyped storage + explicit dtype)."""
    ref = _rebuild_tensor(storage, storage_offset, size, stride)
    if dtype is None:
        return ref
    if not isinstance(dtype, _DType):
        raise ValueError(f"tensor dtype must be a torch dtype, got {dtype!r}")
    return _TensorRef(ref.storage, ref.offset, ref.shape, ref.stride, dtype.dtype)


def _rebuild_parameter(data, requires_grad=False, backward_hooks=None, state=None):
    """Placeholder for ``torch._utils._rebuild_parameter[_with_state]``: a parameter is its data."""
    if not isinstance(data, _TensorRef):
        raise ValueError(f"parameter data must be a tensor, got {type(data)}")
    return data


class _Builder(_Inert):
    """Callable wrapper handed to the unpickler instead of the function itself, so that a BUILD
    opcode cannot set attributes (e.g. ``__defaults__``) on our module's functions."""

    __slots__ = ("_fn",)

    def __init__(self, fn):
        object.__setattr__(self, "_fn", fn)

    def __setattr__(self, name, value):
        raise AttributeError(f"{type(self).__name__} is read-only")

    def __call__(self, *args):
        return self._fn(*args)


_ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch._utils", "_rebuild_tensor"): _Builder(_rebuild_tensor),
    ("torch._utils", "_rebuild_tensor_v2"): _Builder(_rebuild_tensor_v2),
    ("torch._utils", "_rebuild_tensor_v3"): _Builder(_rebuild_tensor_v3),
    ("torch._utils", "_rebuild_parameter"): _Builder(_rebuild_parameter),
    ("torch._utils", "_rebuild_parameter_with_state"): _Builder(_rebuild_parameter),
}
for _name, _dt in _STORAGE_DTYPES.items():
    _ALLOWED_GLOBALS[("torch", _name)] = _StorageType(_name, _dt)
_ALLOWED_GLOBALS[("torch.storage", "UntypedStorage")] = _StorageType(
    "UntypedStorage", _STORAGE_DTYPES["UntypedStorage"]
)
for _name, _dt in _TORCH_DTYPES.items():
    _ALLOWED_GLOBALS[("torch", _name)] = _DType(_name, np.dtype(_dt))
del _name, _dt


# ---------------------------------------------------------------------------------------------
# Pickle scanning and restricted unpickling.

_STRING_PUSH_OPS = frozenset({
    "SHORT_BINUNICODE", "BINUNICODE", "BINUNICODE8", "UNICODE",
    "STRING", "BINSTRING", "SHORT_BINSTRING",
})
_GET_OPS = frozenset({"GET", "BINGET", "LONG_BINGET"})
_PUT_OPS = frozenset({"PUT", "BINPUT", "LONG_BINPUT"})
# Opcodes that resolve globals through a registry we do not control.
_FORBIDDEN_OPS = frozenset({"EXT1", "EXT2", "EXT4"})
_UNKNOWN = object()


def _check_global(module, name, where):
    if (module, name) not in _ALLOWED_GLOBALS:
        raise UnsafeCheckpointError(
            f"{where}: refusing to load global {module}.{name} (not on the allow-list of "
            "tensor-building names); the file was not executed"
        )


def _scan_pickle(stream, where):
    """Check every global a pickle names, without executing it.

    Reads one pickle (up to and including STOP) from `stream`, leaving the stream just after
    it. GLOBAL/INST carry their names inline; STACK_GLOBAL takes them from the two preceding
    pushes, which are tracked through the memo. A STACK_GLOBAL whose names cannot be resolved
    statically is rejected (a normal pickler never produces one).
    """
    memo: dict[int, Any] = {}
    last = [_UNKNOWN, _UNKNOWN]  # values pushed by the two latest stack-changing opcodes
    try:
        for opcode, arg, pos in pickletools.genops(stream):
            name = opcode.name
            if name in _FORBIDDEN_OPS:
                raise UnsafeCheckpointError(f"{where}: refusing opcode {name} at byte {pos}")
            if name in ("GLOBAL", "INST"):
                module, _, qualname = str(arg).partition(" ")
                _check_global(module, qualname, where)
            elif name == "STACK_GLOBAL":
                module, qualname = last
                if not (isinstance(module, str) and isinstance(qualname, str)):
                    raise UnsafeCheckpointError(
                        f"{where}: STACK_GLOBAL at byte {pos} with names that cannot be checked"
                    )
                _check_global(module, qualname, where)
            if name == "MEMOIZE":
                memo[len(memo)] = last[1]
            elif name in _PUT_OPS:
                memo[arg] = last[1]
            elif name in _STRING_PUSH_OPS:
                last = [last[1], arg if isinstance(arg, str) else _UNKNOWN]
            elif name in _GET_OPS:
                last = [last[1], memo.get(arg, _UNKNOWN)]
            else:
                last = [last[1], _UNKNOWN]
    except UnsafeCheckpointError:
        raise
    except (ValueError, EOFError, struct.error) as err:
        raise CheckpointError(f"{where}: corrupt or truncated pickle ({err})") from None


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler whose globals come only from the allow-list and whose storages are refs."""

    def __init__(self, file, where):
        super().__init__(file)
        self._where = where
        self.storages: dict[str, _StorageRef] = {}

    def find_class(self, module, name):
        _check_global(module, name, self._where)
        return _ALLOWED_GLOBALS[(module, name)]

    def persistent_load(self, pid):
        # ('storage', storage_type, key, location, numel[, view_metadata])
        if not (isinstance(pid, tuple) and len(pid) in (5, 6) and pid[0] == "storage"):
            raise pickle.UnpicklingError(f"unsupported persistent id {pid!r}")
        storage_type, key, numel = pid[1], str(pid[2]), pid[4]
        if not isinstance(storage_type, _StorageType):
            raise pickle.UnpicklingError(f"persistent id has no storage type: {pid!r}")
        if not isinstance(numel, int) or numel < 0:
            raise pickle.UnpicklingError(f"bad storage size in persistent id {pid!r}")
        root = _StorageRef(key, storage_type.dtype, 0, numel)
        previous = self.storages.setdefault(key, root)
        if previous.dtype != root.dtype or previous.numel != root.numel:
            raise pickle.UnpicklingError(f"storage {key!r} declared twice with different types")
        view = pid[5] if len(pid) == 6 else None
        if view is None:
            return root
        # Legacy storage view: (view_key, offset, view_size), in elements of the root storage.
        _, offset, size = view
        if not (isinstance(offset, int) and isinstance(size, int) and offset >= 0 and size >= 0
                and offset + size <= numel):
            raise pickle.UnpicklingError(f"storage view {view!r} out of range of {numel} elements")
        return _StorageRef(key, storage_type.dtype, offset, size)


def _unpickle(stream, where):
    """Scan, then load, one pickle from a seekable binary stream. Returns (object, storages)."""
    start = stream.tell()
    _scan_pickle(stream, where)
    stream.seek(start)
    unpickler = _RestrictedUnpickler(stream, where)
    try:
        obj = unpickler.load()
    except UnsafeCheckpointError:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, KeyError, IndexError,
            AttributeError, struct.error) as err:
        raise CheckpointError(f"{where}: corrupt checkpoint pickle ({err})") from None
    return obj, unpickler.storages


# ---------------------------------------------------------------------------------------------
# Materialization.


def _materialize(ref: _TensorRef, raw: dict[str, np.ndarray], big_endian: bool, where: str):
    """Build the array for one tensor from its storage's raw bytes (bounds-checked)."""
    storage = ref.storage
    # Re-validate: the bounds check below relies on non-negative integer geometry.
    try:
        _as_shape(ref.shape, "size")
        _as_shape(ref.stride, "stride")
        _as_shape((ref.offset, storage.offset, storage.numel), "offset")
        buf = raw[storage.key]
    except (ValueError, KeyError) as err:
        raise CheckpointError(f"{where}: malformed tensor ({err})") from None
    itemsize = storage.dtype.itemsize
    # The storage's own element range, in bytes; the tensor may reinterpret it (v3 dtypes).
    lo = storage.offset * itemsize
    hi = (storage.offset + storage.numel) * itemsize
    data = buf[lo:hi]
    dtype = ref.dtype.newbyteorder(">") if big_endian and ref.dtype.itemsize > 1 else ref.dtype
    if data.size % dtype.itemsize:
        raise CheckpointError(
            f"{where}: storage {storage.key!r} of {data.size} bytes is not a whole number of "
            f"{dtype} elements"
        )
    elems = data.view(dtype)
    if 0 in ref.shape:
        return np.zeros(ref.shape, ref.dtype)
    last = ref.offset + sum((n - 1) * s for n, s in zip(ref.shape, ref.stride, strict=True))
    if last >= elems.size:
        raise CheckpointError(
            f"{where}: tensor (shape {ref.shape}, stride {ref.stride}, offset {ref.offset}) "
            f"reads past the end of storage {storage.key!r} ({elems.size} elements)"
        )
    view = np.lib.stride_tricks.as_strided(
        elems[ref.offset:],
        shape=ref.shape,
        strides=tuple(s * dtype.itemsize for s in ref.stride),
        writeable=False,
    )
    # A copy that owns its memory, in native byte order.
    return np.array(view, dtype=ref.dtype, order="C", copy=True)


def _flatten(obj, prefix, out, raw, big_endian, where):
    if isinstance(obj, _TensorRef):
        out[prefix] = _materialize(obj, raw, big_endian, where)
    elif isinstance(obj, dict):
        for key, value in obj.items():
            _flatten(value, f"{prefix}.{key}" if prefix else str(key), out, raw, big_endian, where)
    elif isinstance(obj, list | tuple):
        for i, value in enumerate(obj):
            _flatten(value, f"{prefix}.{i}" if prefix else str(i), out, raw, big_endian, where)
    elif isinstance(obj, bool | int | float):
        out[prefix] = np.asarray(obj)
    # Strings, None and other leaves carry no array data and are dropped.


# ---------------------------------------------------------------------------------------------
# The two container formats.


def _read_legacy(path: str, where: str):
    with open(path, "rb") as f:
        magic, _ = _unpickle(f, where)
        if magic != LEGACY_MAGIC_NUMBER:
            raise CheckpointError(f"{where}: not a PyTorch checkpoint (bad magic number)")
        version, _ = _unpickle(f, where)
        if version != LEGACY_PROTOCOL_VERSION:
            raise CheckpointError(f"{where}: unsupported legacy protocol version {version!r}")
        sys_info, _ = _unpickle(f, where)
        big_endian = not (isinstance(sys_info, dict) and sys_info.get("little_endian", True))
        obj, storages = _unpickle(f, where)
        keys, _ = _unpickle(f, where)
        if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
            raise CheckpointError(f"{where}: storage key list is malformed")
        missing = set(storages) - set(keys)
        if missing:
            raise CheckpointError(f"{where}: storages {sorted(missing)} have no data section")
        count_fmt = ">q" if big_endian else "<q"
        file_size = os.fstat(f.fileno()).st_size
        raw: dict[str, np.ndarray] = {}
        for key in keys:
            header = f.read(8)
            if len(header) < 8:
                raise CheckpointError(f"{where}: truncated in the data of storage {key!r}")
            (numel,) = struct.unpack(count_fmt, header)
            ref = storages.get(key)
            if ref is None:
                raise CheckpointError(f"{where}: data section holds unreferenced storage {key!r}")
            # The element count in the file must agree with the pickle's persistent id.
            if numel != ref.numel:
                raise CheckpointError(
                    f"{where}: storage {key!r} has {numel} elements in the data section but "
                    f"{ref.numel} in the pickle"
                )
            nbytes = numel * ref.dtype.itemsize
            # Check against the file size first: never allocate what a header merely claims.
            data = f.read(nbytes) if nbytes <= file_size - f.tell() else b""
            if len(data) < nbytes:
                raise CheckpointError(
                    f"{where}: truncated: storage {key!r} needs {nbytes} bytes, found {len(data)}"
                )
            raw[key] = np.frombuffer(data, np.uint8)
    return obj, raw, big_endian


def _read_zip(path: str, where: str):
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as err:
        raise CheckpointError(f"{where}: corrupt zip checkpoint ({err})") from None
    with archive:
        pickles = [n for n in archive.namelist() if n.endswith("data.pkl") and n.count("/") == 1]
        if len(pickles) != 1:
            raise CheckpointError(
                f"{where}: zip checkpoint must hold exactly one '<prefix>/data.pkl', "
                f"found {pickles}"
            )
        prefix = pickles[0][: -len("data.pkl")]
        try:
            big_endian = False
            if prefix + "byteorder" in archive.namelist():
                big_endian = archive.read(prefix + "byteorder").strip() == b"big"
            obj, storages = _unpickle(io.BytesIO(archive.read(pickles[0])), where)
            raw: dict[str, np.ndarray] = {}
            for key, ref in storages.items():
                entry = f"{prefix}data/{key}"
                need = ref.numel * ref.dtype.itemsize
                try:
                    # Read only what the pickle declares (bounded memory for odd entries).
                    with archive.open(entry) as member:
                        data = member.read(need)
                except KeyError:
                    raise CheckpointError(f"{where}: missing storage entry {entry!r}") from None
                if len(data) < need:
                    raise CheckpointError(
                        f"{where}: storage entry {entry!r} has {len(data)} bytes, needs {need}"
                    )
                raw[key] = np.frombuffer(data, np.uint8)
        except (zipfile.BadZipFile, EOFError, OSError, zipfile.LargeZipFile) as err:
            raise CheckpointError(f"{where}: corrupt zip checkpoint ({err})") from None
    return obj, raw, big_endian


def load(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a PyTorch checkpoint safely, without torch.

    Args:
      path: a ``.pth``/``.pt`` file in the legacy or the zip serialization.

    Returns:
      dict mapping dotted keys (e.g. ``"features.0.weight"``) to NumPy arrays with the
      tensors' logical shapes and dtypes (bfloat16 as ``ml_dtypes.bfloat16``).

    Raises:
      UnsafeCheckpointError: the file names a global outside the allow-list (nothing in the file
        was executed).
      CheckpointError: the file is corrupt, truncated or not a PyTorch checkpoint.
      FileNotFoundError: the file does not exist.

    Example:
      >>> state = load("vgg19-dcbb9e9d.pth")            # doctest: +SKIP
      >>> state["features.0.weight"].shape                # doctest: +SKIP
      (64, 3, 3, 3)
    """
    path = os.fspath(path)
    where = str(path)
    with open(path, "rb") as f:
        head = f.read(4)
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        obj, raw, big_endian = _read_zip(path, where)
    elif head[:1] == b"\x80":
        obj, raw, big_endian = _read_legacy(path, where)
    elif not head:
        raise CheckpointError(f"{where}: empty file")
    else:
        raise CheckpointError(
            f"{where}: neither a zip-format nor a legacy PyTorch checkpoint "
            f"(starts with {head!r})"
        )
    out: dict[str, np.ndarray] = {}
    _flatten(obj, "", out, raw, big_endian, where)
    return out
