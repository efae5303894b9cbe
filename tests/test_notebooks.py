"""The notebooks (jupytext percent scripts) execute without error on the small preset.

Each is converted with jupytext and run by nbclient in a fresh kernel; the session's small
sweep and emulator are passed through SKINID_DATA / SKINID_EMULATOR.
"""

from __future__ import annotations

from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("[0-9][0-9]_*.py"))


def test_all_five_notebooks_exist():
    assert [p.name[:2] for p in NOTEBOOKS] == ["01", "02", "03", "04", "05"]


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, small_dataset, small_emulator, mesh_dir, tmp_path, monkeypatch):
    import jupytext
    from nbclient import NotebookClient

    monkeypatch.setenv("SKINID_DATA", str(small_dataset))
    monkeypatch.setenv("SKINID_EMULATOR", str(small_emulator))
    monkeypatch.setenv("SKINID_MESH_DIR", str(mesh_dir))
    monkeypatch.setenv("SKINID_NOTEBOOK_OUT", str(tmp_path))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    notebook = jupytext.read(path)
    client = NotebookClient(
        notebook, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()  # raises CellExecutionError naming the cell that failed
    assert any(cell.get("outputs") for cell in notebook.cells if cell.cell_type == "code")
