"""The notebooks: committed without outputs, and every cell runs at small sizes.

Each notebook runs in a fresh kernel of *this* interpreter (`sys.executable`): the test writes
ipykernel's kernelspec into a temporary folder and hands nbclient a kernel manager that only
looks there, so a user- or system-wide "python3" kernelspec pointing at another Python can
never be picked up. WRINKLE_JAX_SMALL=1 shrinks every notebook's sizes (its parameter cell).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def test_the_notebooks_exist():
    names = [p.name for p in NOTEBOOKS]
    assert {"01_quickstart.ipynb", "02_differentiable_lifting.ipynb",
            "03_end_to_end_gradients.ipynb"} <= set(names)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_notebooks_have_no_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    assert nb.metadata.kernelspec.name == "python3"
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{path.name}: cell {i} has outputs"
            assert cell.execution_count is None, f"{path.name}: cell {i} has an execution count"
        assert "attachments" not in cell or not cell.attachments, f"{path.name}: cell {i}"
    # A parameter cell lets the test (and papermill users) shrink the notebook.
    assert any("parameters" in c.metadata.get("tags", []) for c in nb.cells), path.name


def _kernel_manager(tmp_path: Path):
    """A kernel manager whose only "python3" kernelspec runs `sys.executable -m ipykernel`."""
    from ipykernel.kernelspec import write_kernel_spec
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager

    kernels = tmp_path / "kernels"
    write_kernel_spec(str(kernels / "python3"))
    ksm = KernelSpecManager(kernel_dirs=[str(kernels)], ensure_native_kernel=False)
    spec = ksm.get_kernel_spec("python3")
    assert spec.argv[0] == sys.executable, spec.argv
    return KernelManager(kernel_name="python3", kernel_spec_manager=ksm)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("WRINKLE_JAX_SMALL", "1")
    monkeypatch.setenv("WRINKLE_JAX_OUT", str(tmp_path / "out"))
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    nb = nbformat.read(path, as_version=4)
    # First, prove the kernel is this interpreter (a cell added to the in-memory copy only).
    nb.cells.insert(0, nbformat.v4.new_code_cell("import sys; print(sys.executable)"))
    km = _kernel_manager(tmp_path)
    client = nbclient.NotebookClient(
        nb, km=km, timeout=600, allow_errors=False,
        resources={"metadata": {"path": str(tmp_path)}})
    try:
        client.execute()  # raises CellExecutionError naming the failing cell
    finally:
        # The client shuts down only kernels it started itself: this one would otherwise
        # stay alive (idle, ~0.7 GB) until the pytest process exits.
        if km.has_kernel:
            km.shutdown_kernel(now=True)
        assert not km.is_alive()
    first = "".join(o.get("text", "") for o in nb.cells[0].outputs).strip()
    assert first == sys.executable
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            assert out.output_type != "error", out
