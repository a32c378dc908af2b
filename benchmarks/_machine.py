"""Machine and package description written into every benchmark result file."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

BASE_PACKAGES = ("fiberplan", "numpy", "scipy")


def package_version(name: str) -> str:
    """Installed version of a distribution, or "not installed"."""
    try:
        return version(name)
    except PackageNotFoundError:
        return "not installed"


def _source_id(rev: str) -> str:
    """``git rev-parse rev`` in the checkout of the imported fiberplan, ``-dirty`` when ``src/``
    has uncommitted changes; "unknown" outside a git checkout."""
    import fiberplan

    root = Path(fiberplan.__file__).resolve().parents[2]  # <checkout>/src/fiberplan/__init__.py
    try:
        top = subprocess.run(["git", "-C", str(root), "rev-parse", "--show-toplevel"], capture_output=True, text=True, timeout=10)
        # (An installed copy inside some other repository, a virtual environment in a checkout say,
        # is not that repository's code.)
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != root or not (root / "src" / "fiberplan").is_dir():
            return "unknown"
        head = subprocess.run(["git", "-C", str(root), "rev-parse", rev], capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "src"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if head.returncode != 0 or dirty.returncode != 0:
        return "unknown"
    return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def source_commit() -> str:
    """The git commit of the fiberplan source that is imported (see :func:`_source_id`)."""
    return _source_id("HEAD")


def source_tree() -> str:
    """The git tree id of the imported fiberplan's ``src/``: equal across commits that leave the
    code alone (see :func:`_source_id`)."""
    return _source_id("HEAD:src")


def machine_info(extra_packages: tuple[str, ...] = ()) -> dict[str, Any]:
    """Platform, CPU count, load average at start, and the versions of the packages that matter."""
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
        "load_average_at_start": list(os.getloadavg()),
        "packages": {name: package_version(name) for name in (*BASE_PACKAGES, *extra_packages)},
        "fiberplan_commit": source_commit(),
    }
