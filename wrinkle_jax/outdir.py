"""Output folders that never lose user data.

A command writes its whole output into a hidden temporary sibling folder and renames it into
place only when complete (`staged_folder`), so a failure or an interrupt leaves no partial,
no empty and no hidden folder behind. An existing output folder is replaced only when every
file in it is one the tool writes (`foreign_files`); otherwise the command refuses and lists
the other files, unless forced. The replacement keeps the old folder's permissions (a new
folder gets the usual ones, umask applied, not `mkdtemp`'s 0700).

`summary` is the few lines a command prints about a finished output folder.

SIGTERM is turned into a `Terminated` exception while a command runs (`terminate_as_exception`),
so the same cleanup runs for SIGTERM as for Ctrl-C (KeyboardInterrupt).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

from wrinkle_jax.fileio import _UMASK
from wrinkle_jax.mesh import GarmentError

# Files the `enhance`, `demo` and `bake` commands write, relative to the output folder.
TOOL_FILES = re.compile(
    r"^(report\.json|detailed\.npz|normal_map_\d{5,}\.png|normal_maps/normal_map_\d{5,}\.png"
    r"|meshes/frame_\d{5,}\.(obj|ply)|previews/preview_\d{5,}\.png|previews/preview\.mp4)$")
TOOL_FOLDERS = frozenset({"normal_maps", "meshes", "previews"})


class OutputError(GarmentError):
    """The output folder cannot be used as given (exit code 1)."""


class Terminated(BaseException):
    """SIGTERM arrived while a command ran (exit code 143)."""


def foreign_files(out: Path) -> list[str]:
    """Entries under `out` (relative, sorted; folders end in "/") that the tool did not write."""
    found = []
    for root, dirs, files in os.walk(out):
        rel_root = Path(root).relative_to(out)
        for d in list(dirs):
            rel = (rel_root / d).as_posix()
            if rel not in TOOL_FOLDERS:
                found.append(rel + "/")
                dirs.remove(d)  # list the folder once, not its contents
        found += [(rel_root / f).as_posix() for f in files
                  if not TOOL_FILES.match((rel_root / f).as_posix())]
    return sorted(found)


def check_out_dir(out: Path, force: bool = False) -> None:
    """Refuse an output path that is a file, or a folder holding files the tool did not write.

    Raises:
      OutputError: naming the folder and listing (up to 5 of) the other files; `force`
        allows replacing such a folder (a file path is always refused).
    """
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: output path exists and is not a folder")
    if not out.is_dir() or force:
        return
    other = foreign_files(out)
    if other:
        shown = ", ".join(other[:5]) + (f" and {len(other) - 5} more" if len(other) > 5 else "")
        raise OutputError(f"{out}: the output folder holds files wrinkle-jax did not write "
                          f"({shown}); choose another --out, or pass --force to replace the "
                          f"folder and delete them")


@contextlib.contextmanager
def staged_folder(out: Path) -> Iterator[Path]:
    """A temporary sibling of `out` to write into; renamed to `out` when the block succeeds.

    On any exception (including KeyboardInterrupt and `Terminated`) the temporary folder and
    any parent folders this call created are removed and the exception propagates; an
    existing `out` is left untouched. On success `out` is replaced (its permissions kept).
    """
    out = Path(out)
    created = []
    parent = out.parent
    while not parent.exists():
        created.append(parent)
        parent = parent.parent
    tmp = None
    try:
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            # The folder exists once mkdtemp's mkdir returns; a Ctrl-C or SIGTERM arriving
            # before `tmp` is bound would leave it behind, so both wait until it is.
            with _signals_deferred():
                tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp",
                                            dir=out.parent))
        except OSError as e:
            raise OutputError(f"{out}: cannot create the output folder "
                              f"({e.strerror or e})") from None
        yield tmp
        _replace_dir(tmp, out)
    except BaseException:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        for folder in created:  # innermost first; only if still empty
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


def _replace_dir(tmp: Path, out: Path) -> None:
    """Move the finished `tmp` into place as `out`, with `out`'s old permissions (or the
    usual ones for a new folder)."""
    mode = stat.S_IMODE(out.stat().st_mode) if out.is_dir() else 0o777 & ~_UMASK
    os.chmod(tmp, mode)
    # No interrupt between moving the old folder aside and deleting it (a signal arriving
    # meanwhile is delivered right after).
    with _signals_deferred():
        old = None
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
            os.replace(out, old / out.name)
        try:
            os.replace(tmp, out)
        except BaseException:
            if old is not None:  # put the previous output back
                os.replace(old / out.name, out)
                shutil.rmtree(old, ignore_errors=True)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM inside the block: one arriving meanwhile is recorded and its
    handler (KeyboardInterrupt, `Terminated`, the default action) runs right after the block.

    Done with Python handlers, not a signal mask: the process has other threads (XLA's), and
    the kernel delivers a process signal to any thread that does not block it, after which
    Python runs the handler in the main thread regardless of the main thread's mask. Outside
    the main thread (no handlers can be set there) the block runs as is.
    """
    pending = []
    try:
        previous = {s: signal.signal(s, lambda signum, frame: pending.append(signum))
                    for s in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if pending:
            handler = previous[pending[0]]
            if callable(handler):
                handler(pending[0], None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(pending[0])


@contextlib.contextmanager
def terminate_as_exception() -> Iterator[None]:
    """Raise `Terminated` on SIGTERM inside the block (main thread only; else a no-op).

    A signal's exception raised inside C code can come out as another error: NumPy's
    structured-array comparison (`np.unique(..., axis=0)`) turned a Ctrl-C into a TypeError
    ("Cannot compare structured arrays"). So the block records SIGTERM and, where Python's
    usual Ctrl-C handler is installed, SIGINT, and an exception leaving the block after one
    arrived becomes that signal's (`Terminated` or KeyboardInterrupt, from the original).
    """
    received = []

    def on_term(signum, frame):
        received.append(signum)
        raise Terminated()

    def on_int(signum, frame):
        received.append(signum)
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, on_term)
    except ValueError:  # not the main thread
        yield
        return
    # Only Python's own Ctrl-C handler is wrapped: an ignored SIGINT (a background job) or a
    # caller's handler is left as it is.
    previous_int = signal.getsignal(signal.SIGINT)
    if previous_int is signal.default_int_handler:
        signal.signal(signal.SIGINT, on_int)
    try:
        yield
    except (KeyboardInterrupt, Terminated):
        raise
    except BaseException as e:
        if not received:
            raise
        if received[-1] == signal.SIGTERM:
            raise Terminated() from e
        raise KeyboardInterrupt from e
    finally:
        signal.signal(signal.SIGTERM, previous)
        if previous_int is signal.default_int_handler:
            signal.signal(signal.SIGINT, previous_int)


def display_path(path) -> str:
    """A path for reports: package files relative to the package's parent (e.g.
    ``wrinkle_jax/assets/enhancer.npz``, the same on every machine); others as given."""
    root = Path(__file__).resolve().parents[1]
    try:
        return Path(path).resolve().relative_to(root).as_posix()
    except ValueError:
        return str(path)


def summary(report: dict, cmd: str, out: Path) -> str:
    """A few lines about a finished run (what was written where, material, sizes, time per
    stage, notes); the full report is `out`/report.json."""
    lines = [f"wrinkle-jax {cmd}: wrote {out}/ ({report['frames']} frames of "
             f"{report['input']}; report.json holds the details)"]
    if report.get("material"):
        lift = f"lifted to {report['detailed_vertices']} vertices" if report["lift"] else "no lift"
        lines.append(f"  material {report['material']} ({report.get('material_source')}); "
                     f"{report['patches']['per_frame']} patches per frame; {lift}")
    h, w = report["map_shape"]
    lines.append(f"  normal maps {h}x{w} texels at {report['texel_size_m'] * 1e3:g} mm")
    t = report.get("timings_s")
    if t:
        lines.append(f"  {t['wall']:.1f} s: setup {t['setup']:.1f}, compile {t['compile']:.1f}, "
                     + ", ".join(f"{k} {v:.0f} ms/frame"
                                 for k, v in report["ms_per_frame"].items() if v >= 0.5))
    lines += [f"  note: {n}" for n in report.get("notes", [])]
    return "\n".join(lines)
