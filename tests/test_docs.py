"""The documentation site builds without a warning (mkdocs --strict: every link, every API page)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_mkdocs_build_strict(tmp_path):
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")], cwd=ROOT,
                          capture_output=True, text=True, timeout=600, env=os.environ | {"NO_MKDOCS_2_WARNING": "1"})
    assert done.returncode == 0, done.stdout + done.stderr
    home = (tmp_path / "site" / "index.html").read_text()
    assert "fiberplan" in home and "formulations/mpc/" in home
    api = (tmp_path / "site" / "api" / "profiles" / "index.html").read_text()
    assert "discretise_trajectory" in api and "JointProfile" in api
    assert (tmp_path / "site" / "formulations" / "profiles" / "index.html").is_file()
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):  # rendered with their stored figures
        page = (tmp_path / "site" / "notebooks" / notebook.stem / "index.html").read_text()
        assert "data:image/png" in page, f"{notebook.name} shows no figure on the site (run benchmarks/execute_notebooks.py)"
