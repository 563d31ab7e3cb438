"""Write PyTorch checkpoints without torch, for tests.

The writers reproduce torch.save's byte layout (zip and legacy) with stub classes whose pickled
names are ``torch._utils._rebuild_tensor_v2``, ``torch.FloatStorage`` & co.; the stub modules
exist in ``sys.modules`` only while writing.
"""

import collections
import contextlib
import io
import pickle
import struct
import sys
import types
import zipfile

import ml_dtypes
import numpy as np

from wrinkle_jax.io import torch_pickle

STORAGE_NAMES = {
    np.dtype(np.float32): "FloatStorage",
    np.dtype(np.float64): "DoubleStorage",
    np.dtype(np.float16): "HalfStorage",
    np.dtype(ml_dtypes.bfloat16): "BFloat16Storage",
    np.dtype(np.int64): "LongStorage",
    np.dtype(np.int32): "IntStorage",
    np.dtype(np.uint8): "ByteStorage",
}


def _named(obj, module, name):
    obj.__module__, obj.__qualname__, obj.__name__ = module, name, name
    return obj


@contextlib.contextmanager
def fake_torch():
    """Stub `torch` / `torch._utils` modules so pickle can name their globals."""
    torch = types.ModuleType("torch")
    utils = types.ModuleType("torch._utils")

    def unreachable(*args):
        raise AssertionError("never called while writing")

    for name in ("_rebuild_tensor", "_rebuild_tensor_v2", "_rebuild_tensor_v3",
                 "_rebuild_parameter"):
        setattr(utils, name, _named(lambda *a: unreachable(), "torch._utils", name))
    for name in [*STORAGE_NAMES.values(), "UntypedStorage"]:
        setattr(torch, name, _named(type(name, (), {}), "torch", name))

    class FakeDType:
        def __init__(self, name):
            self.name = name

        def __reduce__(self):
            return self.name  # pickled by reference as torch.<name>

    FakeDType.__module__ = "torch"
    for name in ("float32", "int64", "float16"):
        setattr(torch, name, FakeDType(name))
    torch._utils = utils
    saved = {k: sys.modules.get(k) for k in ("torch", "torch._utils")}
    sys.modules.update({"torch": torch, "torch._utils": utils})
    try:
        yield torch
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


class Storage:
    """A storage to be written: `data` is a 1-D array; `view` = (view_key, offset, size)."""

    def __init__(self, key, data, untyped=False, view=None):
        self.key, self.data = key, np.ascontiguousarray(data)
        self.untyped, self.view = untyped, view


class Tensor:
    def __init__(self, storage, offset, shape, stride, version="v2", dtype=None):
        self.storage, self.offset, self.shape, self.stride = storage, offset, shape, stride
        self.version, self.dtype = version, dtype

    def __reduce__(self):
        utils = sys.modules["torch._utils"]
        hooks = collections.OrderedDict()
        if self.version == "v1":
            return utils._rebuild_tensor, (self.storage, self.offset, self.shape, self.stride)
        if self.version == "v3":
            dtype = getattr(sys.modules["torch"], self.dtype)
            return utils._rebuild_tensor_v3, (self.storage, self.offset, self.shape, self.stride,
                                              False, hooks, dtype)
        return utils._rebuild_tensor_v2, (self.storage, self.offset, self.shape, self.stride,
                                          False, hooks)


class Parameter:
    def __init__(self, tensor):
        self.tensor = tensor

    def __reduce__(self):
        utils = sys.modules["torch._utils"]
        return utils._rebuild_parameter, (self.tensor, True, collections.OrderedDict())


class _Pickler(pickle.Pickler):
    def persistent_id(self, obj):
        if not isinstance(obj, Storage):
            return None
        torch = sys.modules["torch"]
        if obj.untyped:
            return ("storage", torch.UntypedStorage, obj.key, "cpu", obj.data.nbytes)
        kind = getattr(torch, STORAGE_NAMES[obj.data.dtype])
        numel = getattr(obj, "declared", obj.data.size)
        if obj.view is not None:
            return ("storage", kind, obj.key, "cpu", numel, obj.view)
        return ("storage", kind, obj.key, "cpu", numel)


def _dump(obj, protocol=2):
    buf = io.BytesIO()
    with fake_torch():
        _Pickler(buf, protocol=protocol).dump(obj)
    return buf.getvalue()


def write_zip(path, obj, storages, prefix="archive", data_pkl=None):
    """torch >= 1.6 layout: <prefix>/data.pkl + <prefix>/data/<key> (+ byteorder, version)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as z:
        z.writestr(f"{prefix}/data.pkl", data_pkl if data_pkl is not None else _dump(obj))
        z.writestr(f"{prefix}/byteorder", "little")
        for s in storages:
            z.writestr(f"{prefix}/data/{s.key}", s.data.tobytes())
        z.writestr(f"{prefix}/version", "3\n")


def write_legacy(path, obj, storages, data_pkl=None):
    """torch < 1.6 layout: magic, protocol, sys info, object, keys, then (int64 numel, bytes)."""
    with open(path, "wb") as f:
        pickle.dump(torch_pickle.LEGACY_MAGIC_NUMBER, f, protocol=2)
        pickle.dump(1001, f, protocol=2)
        sys_info = {"protocol_version": 1001, "little_endian": True,
                    "type_sizes": {"short": 2, "int": 4, "long": 4}}
        pickle.dump(sys_info, f, protocol=2)
        f.write(data_pkl if data_pkl is not None else _dump(obj))
        pickle.dump([s.key for s in storages], f, protocol=2)
        for s in storages:
            f.write(struct.pack("<q", getattr(s, "declared", s.data.size)))
            f.write(s.data.tobytes())


WRITERS = {"zip": write_zip, "legacy": write_legacy}


def save_state_dict(path, tensors: dict, wrap_key: str | None = "model", fmt: str = "zip"):
    """Write {name: array} as contiguous tensors, optionally wrapped as {wrap_key: state_dict}."""
    storages, obj = [], collections.OrderedDict()
    for i, (name, value) in enumerate(tensors.items()):
        a = np.ascontiguousarray(value)
        s = Storage(str(i), a.reshape(-1))
        storages.append(s)
        stride = tuple(int(x) // a.itemsize for x in a.strides)
        obj[name] = Tensor(s, 0, a.shape, stride)
    WRITERS[fmt](path, {wrap_key: obj} if wrap_key else obj, storages)
