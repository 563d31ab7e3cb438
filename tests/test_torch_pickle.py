"""Tests for wrinkle_jax.io.torch_pickle: checkpoints written without torch (see
tests/torch_checkpoint_writer.py), both formats."""

import collections
import io
import os
import pickle
import struct
import subprocess

import ml_dtypes
import numpy as np
import pytest
from torch_checkpoint_writer import (  # tests/ is on sys.path
    WRITERS,
    Parameter,
    Storage,
    Tensor,
    write_legacy,
    write_zip,
)

from wrinkle_jax.io import torch_pickle
from wrinkle_jax.io.torch_pickle import CheckpointError, UnsafeCheckpointError


def _example():
    """A state dict exercising offsets, strides, dtypes, parameters and nesting."""
    rng = np.random.default_rng(0)
    f32 = Storage("0", rng.standard_normal(40).astype(np.float32))
    f16 = Storage("1", rng.standard_normal(12).astype(np.float16))
    i64 = Storage("2", rng.integers(-2**40, 2**40, 30).astype(np.int64))
    bf16 = Storage("3", rng.standard_normal(6).astype(ml_dtypes.bfloat16))
    f64 = Storage("4", rng.standard_normal(5))
    i32 = Storage("5", np.arange(7, dtype=np.int32))
    u8 = Storage("6", np.arange(9, dtype=np.uint8))
    storages = [f32, f16, i64, bf16, f64, i32, u8]
    obj = collections.OrderedDict()
    obj["conv.weight"] = Parameter(Tensor(f32, 5, (2, 3, 2), (6, 2, 1)))
    obj["conv.weight_t"] = Tensor(f32, 5, (2, 3), (1, 2))  # transposed, shares the storage
    obj["half"] = Tensor(f16, 2, (2, 4), (4, 1))
    obj["long_strided"] = Tensor(i64, 1, (3, 4), (8, 2))
    obj["bf16"] = Tensor(bf16, 0, (6,), (1,))
    obj["f64"] = Tensor(f64, 4, (), ())
    obj["i32"] = Tensor(i32, 0, (7,), (1,), version="v1")
    obj["nested"] = {"u8": Tensor(u8, 1, (2, 2), (1, 3)), "epoch": 7, "name": "vgg"}
    obj["empty"] = Tensor(f32, 0, (0, 3), (3, 1))
    f = f32.data
    expected = {
        "conv.weight": f[5:17].reshape(2, 3, 2),
        "conv.weight_t": np.lib.stride_tricks.as_strided(f[5:], (2, 3), (4, 8)),
        "half": f16.data[2:10].reshape(2, 4),
        "long_strided": i64.data[1:].reshape(-1)[: 8 * 3].reshape(3, 8)[:, :8:2],
        "bf16": bf16.data,
        "f64": np.asarray(f64.data[4]),
        "i32": i32.data,
        "nested.u8": np.array([[u8.data[1], u8.data[4]], [u8.data[2], u8.data[5]]]),
        "nested.epoch": np.asarray(7),
        "empty": np.zeros((0, 3), np.float32),
    }
    return obj, storages, expected


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_round_trip_exact(tmp_path, fmt):
    obj, storages, expected = _example()
    path = tmp_path / f"ckpt_{fmt}.pth"
    WRITERS[fmt](path, obj, storages)
    got = torch_pickle.load(path)
    assert set(got) == set(expected)
    for key, want in expected.items():
        assert got[key].dtype == want.dtype, key
        assert got[key].shape == want.shape, key
        np.testing.assert_array_equal(got[key], want, err_msg=key)
        assert got[key].flags["C_CONTIGUOUS"] and got[key].flags["OWNDATA"]


def test_zip_untyped_storage_with_dtype(tmp_path):
    values = np.arange(10, dtype=np.float32) * 0.5
    raw = Storage("7", values.view(np.uint8), untyped=True)
    obj = {"w": Tensor(raw, 2, (2, 3), (3, 1), version="v3", dtype="float32")}
    path = tmp_path / "v3.pt"
    write_zip(path, obj, [raw], prefix="some_model")
    got = torch_pickle.load(path)
    np.testing.assert_array_equal(got["w"], values[2:8].reshape(2, 3))


def test_legacy_storage_view(tmp_path):
    root = Storage("9", np.arange(10, dtype=np.float32), view=("9_view", 3, 4))
    obj = {"v": Tensor(root, 1, (2,), (2,))}
    path = tmp_path / "view.pth"
    write_legacy(path, obj, [root])
    np.testing.assert_array_equal(torch_pickle.load(path)["v"], np.array([4.0, 6.0], np.float32))


# --- malicious pickles -------------------------------------------------------------------------


class _Reduce:
    """Pickles as a call of `func(*args)` -- what an attacker would put in a checkpoint."""

    def __init__(self, func, args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


def _malicious_payloads(marker):
    cmd = f"touch {marker}"
    return {
        "os.system": _Reduce(os.system, (cmd,)),  # pickled as GLOBAL 'posix system'
        "builtins.eval": _Reduce(eval, (f"open({str(marker)!r}, 'w')",)),
        "subprocess.Popen": _Reduce(subprocess.Popen, (["touch", str(marker)],)),
    }


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
@pytest.mark.parametrize("attack", ["os.system", "builtins.eval", "subprocess.Popen"])
def test_malicious_global_rejected_before_execution(tmp_path, fmt, attack):
    marker = tmp_path / "pwned"
    obj, storages, _ = _example()
    obj["payload"] = _malicious_payloads(marker)[attack]
    path = tmp_path / f"evil_{fmt}.pth"
    WRITERS[fmt](path, obj, storages)
    with pytest.raises(UnsafeCheckpointError, match="refusing to load global") as info:
        torch_pickle.load(path)
    assert str(path) in str(info.value)
    assert not marker.exists()


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_raw_global_builtins_eval(tmp_path, fmt):
    marker = tmp_path / "pwned"
    code = f"open({str(marker)!r}, 'w')".encode()
    # PROTO 2; GLOBAL 'builtins eval'; BINUNICODE code; TUPLE1; REDUCE; STOP
    pkl = b"\x80\x02cbuiltins\neval\nX" + struct.pack("<I", len(code)) + code + b"\x85R."
    path = tmp_path / "eval.pth"
    WRITERS[fmt](path, None, [], data_pkl=pkl)
    with pytest.raises(UnsafeCheckpointError, match="builtins.eval"):
        torch_pickle.load(path)
    assert not marker.exists()


@pytest.mark.parametrize("protocol", [2, 4])
def test_posix_system_global_named_directly(tmp_path, protocol):
    marker = tmp_path / "pwned"
    pkl = pickle.dumps(_Reduce(os.system, (f"touch {marker}",)), protocol=protocol)
    assert (b"posix" in pkl) and (b"system" in pkl)
    path = tmp_path / "evil.pth"
    write_zip(path, None, [], data_pkl=pkl)
    with pytest.raises(UnsafeCheckpointError, match="posix.system"):
        torch_pickle.load(path)
    assert not marker.exists()


def test_scan_rejects_before_unpickling(tmp_path, monkeypatch):
    """The static scan must stop the file before any unpickler (and thus any REDUCE) runs."""

    class Boom:
        def __init__(self, *args, **kwargs):
            raise AssertionError("unpickler constructed for an unsafe file")

    marker = tmp_path / "pwned"
    obj, storages, _ = _example()
    obj["z"] = _malicious_payloads(marker)["os.system"]
    path = tmp_path / "evil.pth"
    write_zip(path, obj, storages)  # a single pickle: data.pkl
    monkeypatch.setattr(torch_pickle, "_RestrictedUnpickler", Boom)
    with pytest.raises(UnsafeCheckpointError):
        torch_pickle.load(path)


def test_stack_global_names_through_memo_are_resolved(tmp_path):
    # Protocol 4: allowed global first, then 'posix' / 'system' fetched back from the memo.
    ops = (
        b"\x80\x04"
        b"\x8c\x0bcollections\x94\x8c\x0bOrderedDict\x94\x93\x94)R\x94"  # OrderedDict()
        b"\x8c\x05posix\x94\x8c\x06system\x94"  # memo 4, 5
        b"00"  # POP POP
        b"h\x04h\x05\x93"  # BINGET 4, BINGET 5, STACK_GLOBAL
        b"\x8c\x04true\x85R."
    )
    path = tmp_path / "memo.pth"
    write_zip(path, None, [], data_pkl=ops)
    with pytest.raises(UnsafeCheckpointError, match="posix.system"):
        torch_pickle.load(path)


def test_stack_global_with_unresolvable_names_rejected(tmp_path):
    ops = b"\x80\x04)\x8c\x04eval\x93."  # module name is a tuple: cannot be checked statically
    path = tmp_path / "weird.pth"
    write_zip(path, None, [], data_pkl=ops)
    with pytest.raises(UnsafeCheckpointError, match="cannot be checked"):
        torch_pickle.load(path)


def test_find_class_enforces_allow_list_without_scan():
    """Defence in depth: the unpickler itself refuses globals even if the scan were skipped."""
    pkl = pickle.dumps(_Reduce(eval, ("1 + 1",)), protocol=2, fix_imports=False)
    unpickler = torch_pickle._RestrictedUnpickler(io.BytesIO(pkl), "mem")
    with pytest.raises(UnsafeCheckpointError, match="builtins.eval"):
        unpickler.load()


# --- corrupt and truncated files ---------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
@pytest.mark.parametrize("fraction", [0.3, 0.9])
def test_truncated_file_names_the_file(tmp_path, fmt, fraction):
    obj, storages, _ = _example()
    path = tmp_path / f"trunc_{fmt}.pth"
    WRITERS[fmt](path, obj, storages)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(CheckpointError) as info:
        torch_pickle.load(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("content", [b"", b"hello world, not a checkpoint", b"\x80\x02garbage"])
def test_garbage_names_the_file(tmp_path, content):
    path = tmp_path / "bad.pth"
    path.write_bytes(content)
    with pytest.raises(CheckpointError) as info:
        torch_pickle.load(path)
    assert str(path) in str(info.value)


def test_bad_magic_number(tmp_path):
    path = tmp_path / "magic.pth"
    path.write_bytes(pickle.dumps(12345, protocol=2) + pickle.dumps(1001, protocol=2))
    with pytest.raises(CheckpointError, match="bad magic"):
        torch_pickle.load(path)


def test_missing_zip_storage_entry(tmp_path):
    obj, storages, _ = _example()
    path = tmp_path / "missing.pth"
    write_zip(path, obj, storages[1:])
    with pytest.raises(CheckpointError, match="missing storage entry"):
        torch_pickle.load(path)


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_out_of_bounds_stride_rejected(tmp_path, fmt):
    s = Storage("0", np.arange(6, dtype=np.float32))
    obj = {"w": Tensor(s, 2, (3, 3), (3, 1))}  # needs 11 elements
    path = tmp_path / "oob.pth"
    WRITERS[fmt](path, obj, [s])
    with pytest.raises(CheckpointError, match="past the end"):
        torch_pickle.load(path)


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_huge_declared_size_is_not_allocated(tmp_path, fmt):
    s = Storage("0", np.arange(4, dtype=np.float32))
    s.declared = 10**15  # 4 PB claimed by the header, 16 bytes present
    path = tmp_path / "huge.pth"
    WRITERS[fmt](path, {"w": Tensor(s, 0, (4,), (1,))}, [s])
    with pytest.raises(CheckpointError, match="needs|truncated"):
        torch_pickle.load(path)


class _TamperedTensor(Tensor):
    """Adds a BUILD after the rebuild call, trying to overwrite the validated geometry."""

    def __reduce__(self):
        func, args = super().__reduce__()
        return func, args, {"stride": (-1,)}


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_build_cannot_tamper_with_tensor_geometry(tmp_path, fmt):
    s = Storage("0", np.arange(4, dtype=np.float32))
    path = tmp_path / "tampered.pth"
    WRITERS[fmt](path, {"w": _TamperedTensor(s, 0, (2,), (1,))}, [s])
    with pytest.raises(CheckpointError) as info:
        torch_pickle.load(path)
    assert str(path) in str(info.value)


def test_build_cannot_modify_allowed_callables(tmp_path):
    # GLOBAL torch._utils._rebuild_tensor_v2; BUILD with slot state {'__defaults__': ()}.
    pkl = (b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\n"
           b"N}X\x0c\x00\x00\x00__defaults__)s\x86b.")
    path = tmp_path / "build.pth"
    write_zip(path, None, [], data_pkl=pkl)
    with pytest.raises(CheckpointError):
        torch_pickle.load(path)
    assert torch_pickle._rebuild_tensor_v2.__defaults__ == (False, None, None)
