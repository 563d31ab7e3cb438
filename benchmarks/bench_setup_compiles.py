"""Count the XLA compilations a notebook user's first calls trigger; prints one JSON object.

Issue 22: every eager jnp operation (op-by-op dispatch) compiles a one-op XLA program the
first time it runs with a new shape/dtype (23-36 ms each on a 2-core machine with XLA's
defaults), so set-up code that runs eagerly pays for dozens of tiny compiles before the
first jitted stage. This script runs one user path in this (fresh) process and records every
backend compile (`jax.monitoring` event "/jax/core/compile/backend_compile_duration"):

  readme:   the README's "Python example" (executed from the README itself; frame0.png goes
            to a temporary folder);
  frame_fn: `pipeline.make_pipeline(garment, model)` (lift on, stages compiled) and the first
            call of `pipeline.frame_fn(pipe)` on the demo skirt's frame 0;
  stream:   `pipeline.make_pipeline` and `pipeline.iter_enhance` over the demo's first 2
            frames;
  eager:    library functions a notebook calls outside any jit, once each: vertex normals and
            a bake of the demo skirt's frame 0, an order-1 masked blur and a detail-frame
            transform of two 128 x 128 patches.

Reported: compiles, op-by-op compiles (programs named after a single primitive, e.g.
jit(add), jit(broadcast_in_dim)), eager compiles of jnp-level wrappers (named after a jitted
jnp function, e.g. jit(clip)), their compile seconds, the path's wall time, and where the
op-by-op compiles come from (the innermost `wrinkle_jax` or script frame of each, top
sources). XLA's own defaults are used: the script refuses to run if XLA_FLAGS already holds
the fusion-emitter flag the CLI adds, unless --allow-flags. Run one path per process:

    python benchmarks/bench_setup_compiles.py --path readme|frame_fn|stream|eager [--top N]
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import sys
import tempfile
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PATHS = ("readme", "frame_fn", "stream", "eager")


def readme_example() -> str:
    """The README's "Python example" code block."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Python example", 1)[1]
    return section.split("```python", 1)[1].split("```", 1)[0]


def primitive_names() -> set[str]:
    """Names of every primitive JAX has registered (the op-by-op programs' names)."""
    import jax  # noqa: F401
    from jax._src import core

    names = set()
    for mod in list(sys.modules.values()):
        if mod is None or not getattr(mod, "__name__", "").startswith("jax"):
            continue
        for value in list(vars(mod).values()):
            if isinstance(value, core.Primitive):
                names.add(value.name)
    return names


def _source(stack) -> str:
    """The innermost frame of the project (library, this script, the executed example)."""
    for frame in reversed(stack):
        name = frame.filename
        if (name.startswith(str(ROOT)) and "site-packages" not in name) or name == "<readme>":
            rel = name.split(str(ROOT) + os.sep)[-1]
            return f"{rel}:{frame.lineno} {frame.name}"
    return "?"


def run_path(path: str) -> None:
    import jax.numpy as jnp
    import numpy as np

    from wrinkle_jax import enhancer, meshio, pipeline
    from wrinkle_jax.cli import _demo_sequence_path

    if path == "readme":
        with tempfile.TemporaryDirectory() as tmp:
            code = readme_example().replace('"frame0.png"', repr(str(Path(tmp) / "frame0.png")))
            cwd = os.getcwd()
            os.chdir(ROOT)
            try:
                exec(compile(code, "<readme>", "exec"), {"__name__": "__readme__"})
            finally:
                os.chdir(cwd)
        return
    seq = meshio.load_sequence(_demo_sequence_path())
    if path == "eager":
        from wrinkle_jax import detail, mesh, normalmap, sharpen

        frame = seq.frames[0]
        np.asarray(mesh.vertex_normals(frame, seq.garment.faces))
        np.asarray(normalmap.bake(normalmap.make_plan(seq.garment), frame))
        x = np.random.default_rng(0).uniform(0.2, 0.8, (2, 128, 128, 3)).astype(np.float32)
        mask = np.ones((2, 128, 128, 1), np.float32)
        np.asarray(sharpen.masked_blur(x * 2 - 1, mask, 8.0))
        np.asarray(detail.to_detail_rgb(x, mask))
        return
    model = enhancer.load_enhancer()
    pipe = pipeline.make_pipeline(seq.garment, model)
    material = model.config.material_id(seq.metadata["material"])
    if path == "frame_fn":
        f = pipeline.frame_fn(pipe)
        out = f(model.params, jnp.asarray(seq.frames[0]), material)
        np.asarray(out.detailed)
    else:
        for fr in pipeline.iter_enhance(pipe, seq.frames, material, indices=[0, 1]):
            np.asarray(fr.detailed)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--path", choices=PATHS, required=True)
    ap.add_argument("--top", type=int, default=15, help="op-by-op sources listed")
    ap.add_argument("--events", action="store_true",
                    help="also list every compile (name, seconds, source)")
    ap.add_argument("--allow-flags", action="store_true",
                    help="run even if XLA_FLAGS holds --xla_cpu_use_fusion_emitters")
    args = ap.parse_args(argv)
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" in flags and not args.allow_flags:
        ap.error("XLA_FLAGS sets xla_cpu_use_fusion_emitters; unset it to measure XLA's "
                 "defaults (or pass --allow-flags)")
    load0 = os.getloadavg()[0]
    t_import = time.perf_counter()
    import jax
    from jax import monitoring

    events = []

    def listener(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            events.append((str(kw.get("fun_name", "?")), duration,
                           _source(traceback.extract_stack())))

    monitoring.register_event_duration_secs_listener(listener)
    import wrinkle_jax  # noqa: F401

    t0 = time.perf_counter()
    run_path(args.path)
    wall = time.perf_counter() - t0
    prims = primitive_names()

    def bare(name: str) -> str:
        return name[4:-1] if name.startswith("jit(") and name.endswith(")") else name

    op = [e for e in events if bare(e[0]) in prims]
    # jitted jnp/lax-level helpers run eagerly (jit(clip), jit(_where), jit(_mean), ...).
    jnp_names = set()
    for mod in list(sys.modules.values()):
        if getattr(mod, "__name__", "").startswith(("jax._src.numpy", "jax._src.lax")):
            jnp_names.update(k for k, v in vars(mod).items() if callable(v))
    other = [e for e in events if e not in op and bare(e[0]) in jnp_names]
    by_source = collections.Counter()
    secs_source = collections.defaultdict(float)
    for _name, d, src in op + other:
        by_source[src] += 1
        secs_source[src] += d
    top = [{"source": s, "compiles": n, "seconds": round(secs_source[s], 3)}
           for s, n in by_source.most_common(args.top)]
    result = {
        "path": args.path,
        "jax": jax.__version__,
        "xla_flags": flags,
        "compiles": len(events),
        "op_by_op_compiles": len(op),
        "eager_jnp_wrapper_compiles": len(other),
        "compile_seconds": round(sum(e[1] for e in events), 3),
        "op_by_op_seconds": round(sum(e[1] for e in op), 3),
        "eager_jnp_wrapper_seconds": round(sum(e[1] for e in other), 3),
        "wall_seconds": round(wall, 3),
        "import_seconds": round(t0 - t_import, 3),
        "load_1min_before": round(load0, 2),
        "load_1min_after": round(os.getloadavg()[0], 2),
        "eager_sources": top,
        "eager_names": collections.Counter(bare(e[0]) for e in op + other).most_common(args.top),
        "stage_compiles": sorted({bare(e[0]) for e in events if e not in op and e not in other}),
    }
    if args.events:
        result["events"] = [[n, round(d, 4), s] for n, d, s in events]
    with contextlib.suppress(BrokenPipeError):
        print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
