"""The plain install (no extras) gives a working command line: every subcommand's help, and a
tiny compare (Parquet I/O is a core dependency). Slow: it builds a fresh virtual environment
and installs fiberplan and its dependencies from the package index (or pip's cache)."""

from __future__ import annotations

import json
import os
import subprocess
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ("plan", "verify", "profiles", "view", "show", "animate", "scenario", "instruments", "planners", "compare", "sweep", "study-plot")


@pytest.mark.slow
def test_plain_install_runs_every_command(tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, clear=True).create(env_dir)
    bin_dir = env_dir / ("Scripts" if os.name == "nt" else "bin")
    python = bin_dir / "python"
    subprocess.run([str(python), "-m", "pip", "install", "-q", str(ROOT)], check=True, timeout=1800)
    probe = subprocess.run([str(python), "-c", "import importlib.util as u; print(u.find_spec('dask') is None)"], capture_output=True, text=True)
    assert probe.stdout.strip() == "True", "the plain install pulled in an extra"
    fiberplan = bin_dir / "fiberplan"
    for command in COMMANDS:
        done = subprocess.run([str(fiberplan), command, "--help"], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, f"{command} --help: {done.stderr}"
    done = subprocess.run([str(fiberplan), "compare", "--instrument", "desi", "-n", "7", "--planners", "mpc,dnf", "--seeds", "2", "--json",
                           "--out", str(tmp_path / "c.parquet")], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1])
