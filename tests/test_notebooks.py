"""Every notebook in notebooks/ executes at small size (its parameters cell overridden)."""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))

# Small-size overrides per notebook; keys must be names of its parameters cell.
SMALL = {
    "01_quickstart": {"N_POSITIONERS": 19},
    "03_tuning": {"N_POSITIONERS": 7, "SEEDS": 1, "LAMBDA_REPEL": [0.36, 36.0], "HORIZONS": [4, 8], "STEP_LENGTHS": [0.01], "WORKERS": 1,
                  "SCHEDULE_POSITIONERS": 19, "SCHEDULE_SEEDS": 2},
    "04_central_gap": {"N_POSITIONERS": 2, "SEEDS": 1},
    "05_scaling": {"SIZES": [7, 19], "SEEDS": 1},
    "02_deadlock_rates": {"INSTRUMENTS": ["desi"], "N_POSITIONERS": 7, "CLUSTER_FRACTIONS": [0.0, 0.9], "SEEDS": 1, "WORKERS": 1},
}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes_at_small_size(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    index = next(k for k, cell in enumerate(nb.cells) if "parameters" in cell.metadata.get("tags", []))
    overrides = SMALL.get(path.stem, {})
    assert overrides, f"{path.name}: give small-size parameters in SMALL"
    params_source = nb.cells[index].source
    for name in overrides:
        assert f"{name} =" in params_source, f"{path.name}: {name} is not a parameter"
    injected = "\n".join(f"{name} = {value!r}" for name, value in overrides.items())
    nb.cells.insert(index + 1, nbformat.v4.new_code_cell(injected))
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    draws = any("plot_" in cell.source or "plt." in cell.source for cell in nb.cells if cell.cell_type == "code")
    shown = sum("image/png" in output.get("data", {}) for cell in nb.cells for output in cell.get("outputs", []))
    assert shown > 0 or not draws, f"{path.name} draws figures but shows none inline (a forced non-interactive backend?)"
