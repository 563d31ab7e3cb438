"""The matrix products a compiled XLA program runs, and how long they take alone: a GEMM
ceiling for a network's time on this machine.

Why: the U-Net's convolution forms (`nn.fastconv`, `nn.winograd`) lower every layer to dots,
and on a CPU the dots are the part no rewrite of the surrounding data movement can remove. So
the time of a program's dots, each replayed alone at its exact operand shapes, dtypes, layouts
and contraction, is a measured lower bound on what that decomposition of the program can reach
(`benchmarks/bench_ceiling.py`): the program's time over it is the most that removing every
other cost (im2col copies, Winograd transforms, normalizations, activations) could gain.

`program_dots` reads the optimized HLO of a compiled program (`jax.stages.Compiled`), so dead
code that XLA dropped (e.g. the unused forward dots a custom VJP's backward traces) is not
counted, and dots that XLA merged or split are counted as XLA runs them. Each dot instruction
counts once per program run: none of the programs measured here has loops around its dots
(`Dot.in_loop` says when one does; its count is then a lower bound, as it is for a
computation that several call sites share; XLA clones fusions per call site).

Example:
  >>> import jax, jax.numpy as jnp
  >>> f = jax.jit(lambda a, b: (a @ b).sum()).lower(jnp.ones((64, 32)), jnp.ones((32, 16)))
  >>> [(d.lhs_shape, d.rhs_shape, d.flops) for d in program_dots(f.compile())]
  [((64, 32), (32, 16), 65536)]
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections import Counter
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = ["Dot", "dot_runner", "dots_flops", "operand_bytes", "program_dots", "unique_dots"]

_DTYPES = {"f32": jnp.float32, "bf16": jnp.bfloat16, "f16": jnp.float16, "f64": jnp.float64,
           "s32": jnp.int32, "s8": jnp.int8}
# `%name = dtype[d0,d1,...]{minor-to-major layout} opcode(`
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%(\S+)\s*=\s*(\w+)\[([\d,]*)\](?:\{([\d,]*)[^}]*\})?\s+"
                    r"([\w-]+)\((.*)$")
_COMPUTATION = re.compile(r"^\s*(?:ENTRY\s+)?%(\S+)\s.*\{\s*$")
_DIMS = re.compile(r"(lhs_contracting_dims|rhs_contracting_dims|lhs_batch_dims|"
                   r"rhs_batch_dims)=\{([\d,]*)\}")
_OPERAND = re.compile(r"%([\w.\-]+)")
_CALLED = re.compile(r"(?:calls|body|condition|to_apply|branch_computations)=\{?%([\w.\-]+)")


def _ints(text: str) -> tuple[int, ...]:
    return tuple(int(t) for t in text.split(",") if t)


@dataclasses.dataclass(frozen=True)
class Dot:
    """One dot instruction of an optimized HLO program.

    Attributes:
      lhs_shape, rhs_shape, out_shape: logical shapes.
      lhs_layout, rhs_layout: minor-to-major dimension order of the operands in memory.
      lhs_dtype, rhs_dtype, out_dtype: HLO element types ("bf16", "f32", ...).
      lhs_contracting, rhs_contracting, lhs_batch, rhs_batch: dimension numbers.
      in_loop: the dot sits in a computation a while loop runs (it may run more than once).
    """

    lhs_shape: tuple[int, ...]
    rhs_shape: tuple[int, ...]
    out_shape: tuple[int, ...]
    lhs_layout: tuple[int, ...]
    rhs_layout: tuple[int, ...]
    lhs_dtype: str
    rhs_dtype: str
    out_dtype: str
    lhs_contracting: tuple[int, ...]
    rhs_contracting: tuple[int, ...]
    lhs_batch: tuple[int, ...] = ()
    rhs_batch: tuple[int, ...] = ()
    in_loop: bool = False

    @property
    def flops(self) -> int:
        """2 x multiply-adds: 2 x prod(output shape) x prod(contracted sizes)."""
        k = math.prod(self.lhs_shape[d] for d in self.lhs_contracting)
        return 2 * math.prod(self.out_shape) * k

    @property
    def key(self) -> tuple:
        """Everything that sets its speed (the same product wherever it occurs)."""
        return dataclasses.astuple(dataclasses.replace(self, in_loop=False))


def program_dots(compiled) -> list[Dot]:
    """Every dot instruction of a compiled program (`jax.jit(f).lower(...).compile()`), in
    program order. Raises ValueError if a dot's operand shape cannot be found."""
    text = compiled.as_text()
    shapes: dict[str, tuple[str, tuple[int, ...], tuple[int, ...]]] = {}
    pending, loop_bodies = [], set()
    calls: dict[str | None, set[str]] = {}
    computation = None
    for line in text.splitlines():
        head = _COMPUTATION.match(line)
        if head and "=" not in line.split("{")[0]:
            computation = head.group(1)
            continue
        # Calls and loops first: tuple-shaped instructions (while, calls) do not match _INSTR.
        calls.setdefault(computation, set()).update(_CALLED.findall(line))
        if " while(" in line:
            loop_bodies.update(re.findall(r"body=%([\w.\-]+)", line))
        m = _INSTR.match(line)
        if not m:
            continue
        name, dtype, dims, layout, opcode, rest = m.groups()
        shape = _ints(dims)
        lay = _ints(layout) if layout is not None else tuple(range(len(shape) - 1, -1, -1))
        shapes[name] = (dtype, shape, lay)
        if opcode == "dot":
            pending.append((computation, dtype, shape, rest))
    in_loops, todo = set(), list(loop_bodies)
    while todo:  # every computation a loop body runs, directly or through fusions and calls
        c = todo.pop()
        if c not in in_loops:
            in_loops.add(c)
            todo.extend(calls.get(c, ()))
    dots = []
    for comp, dtype, shape, rest in pending:
        args = rest.split(")", 1)[0]
        names = _OPERAND.findall(args)
        if len(names) != 2 or any(n not in shapes for n in names):
            raise ValueError(f"cannot read the operands of a dot: {rest[:120]!r}")
        (ld, ls, ll), (rd, rs, rl) = (shapes[n] for n in names)
        nums = {k: _ints(v) for k, v in _DIMS.findall(rest)}
        dots.append(Dot(ls, rs, shape, ll, rl, ld, rd, dtype,
                        nums.get("lhs_contracting_dims", ()),
                        nums.get("rhs_contracting_dims", ()),
                        nums.get("lhs_batch_dims", ()), nums.get("rhs_batch_dims", ()),
                        in_loop=comp in in_loops))
    return dots


def dots_flops(dots: Sequence[Dot]) -> int:
    """Total FLOPs (2 x multiply-adds) of `dots`."""
    return sum(d.flops for d in dots)


def unique_dots(dots: Sequence[Dot]) -> list[tuple[Dot, int]]:
    """(dot, how many times the program runs one like it), first occurrence order."""
    counts = Counter(d.key for d in dots)
    seen, out = set(), []
    for d in dots:
        if d.key not in seen:
            seen.add(d.key)
            out.append((d, counts[d.key]))
    return out


def _physical(shape, layout, dims):
    """Row-major shape holding an array of logical `shape` stored in minor-to-major `layout`,
    and where each logical dimension of `dims` sits in it."""
    major_to_minor = tuple(reversed(layout))
    return (tuple(shape[d] for d in major_to_minor),
            tuple(major_to_minor.index(d) for d in dims))


def dot_runner(dot: Dot, key=None):
    """(run, operands): `run(*operands)` computes `dot` alone, jitted, on random operands laid
    out in memory as the program stores them (a transposed operand is a row-major array of the
    transposed shape, so no copy is added). The output has the dot's element type."""
    key = jax.random.key(0) if key is None else key
    lshape, lc = _physical(dot.lhs_shape, dot.lhs_layout, dot.lhs_contracting)
    lb = _physical(dot.lhs_shape, dot.lhs_layout, dot.lhs_batch)[1]
    rshape, rc = _physical(dot.rhs_shape, dot.rhs_layout, dot.rhs_contracting)
    rb = _physical(dot.rhs_shape, dot.rhs_layout, dot.rhs_batch)[1]
    k1, k2 = jax.random.split(key)
    a = jax.random.normal(k1, lshape, jnp.float32).astype(_DTYPES[dot.lhs_dtype])
    b = jax.random.normal(k2, rshape, jnp.float32).astype(_DTYPES[dot.rhs_dtype])
    out = _DTYPES[dot.out_dtype]
    run = jax.jit(lambda x, y: lax.dot_general(x, y, ((lc, rc), (lb, rb)),
                                               preferred_element_type=out))
    return run, (a, b)


def operand_bytes(dot: Dot) -> int:
    """Bytes of the two operands `dot_runner` allocates."""
    size = lambda s, t: math.prod(s) * np.dtype(_DTYPES[t]).itemsize  # noqa: E731
    return size(dot.lhs_shape, dot.lhs_dtype) + size(dot.rhs_shape, dot.rhs_dtype)
