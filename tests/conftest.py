"""Shared fixtures: small seeded scenarios and a scenario-file builder."""

from __future__ import annotations

import copy
from typing import Any

import pytest

from fiberplan.generate import make_scenario


@pytest.fixture(scope="session")
def desi_random_61():
    """61 DESI-like positioners, random start and targets, seed 3."""
    return make_scenario("desi", 61, "random", 3)


@pytest.fixture
def scenario_dict() -> dict[str, Any]:
    """A valid 7-positioner DESI scenario in the JSON layout (ids 10..16), to be spoiled by tests."""
    data = make_scenario("desi", 7, "random", 5).to_dict()
    for k, row in enumerate(data["positioners"]):
        row["id"] = 10 + k
    return copy.deepcopy(data)


@pytest.fixture
def run_cli(capsys):
    """Run the command line in-process: ``run_cli(["plan", ...]) -> (exit status, stdout, stderr)``."""
    from fiberplan.cli import main

    def run(args: list[str]) -> tuple[int, str, str]:
        try:
            main(args)
            code = 0
        except SystemExit as e:
            code = int(e.code or 0)
        out = capsys.readouterr()
        return code, out.out, out.err

    return run
