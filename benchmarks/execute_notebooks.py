"""Store every notebook executed at its small documented size, so that its figures show on the
documentation site and on GitHub without running it.

The small sizes are the tests' (``tests/test_notebooks.py``: ``SMALL``); each is written as a
cell right after the parameters cell, tagged ``small-size``, saying so (delete that cell to run at
full size). Run after changing a notebook::

    python benchmarks/execute_notebooks.py
"""

from __future__ import annotations

import importlib.util
import sys
import tempfile
from pathlib import Path

import nbformat
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]


def small_sizes() -> dict[str, dict]:
    spec = importlib.util.spec_from_file_location("test_notebooks", ROOT / "tests" / "test_notebooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.SMALL


def execute(path: Path, overrides: dict) -> None:
    nb = nbformat.read(path, as_version=4)
    nb.cells = [c for c in nb.cells if "small-size" not in c.metadata.get("tags", [])]
    index = next(k for k, cell in enumerate(nb.cells) if "parameters" in cell.metadata.get("tags", []))
    lines = ["# Stored executed at a small size (benchmarks/execute_notebooks.py); delete this cell to run at full size."]
    lines += [f"{name} = {value!r}" for name, value in overrides.items()]
    cell = nbformat.v4.new_code_cell("\n".join(lines))
    cell.metadata["tags"] = ["small-size"]
    nb.cells.insert(index + 1, cell)
    with tempfile.TemporaryDirectory() as scratch:  # the notebooks' own output files go there
        NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": scratch}}).execute()
    nbformat.write(nb, path)


def main() -> None:
    sizes = small_sizes()
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        print(f"executing {path.name} at {sizes[path.stem]}", flush=True)
        execute(path, sizes[path.stem])
    sys.exit(0)


if __name__ == "__main__":
    main()
