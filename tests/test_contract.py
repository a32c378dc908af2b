"""The contract every registered planner keeps on every preset instrument (small groups).

- the result speaks the outcome vocabulary of :mod:`fiberplan.outcomes`;
- the independent verifier finds no collision and no limit violation (``straight`` excepted:
  it ignores collisions on purpose, so only its limits are checked);
- the same seed gives the same trajectory, bit for bit;
- every setting survives the round trip through the command line's ``--set KEY=VALUE``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import fiberplan as fp
from fiberplan.cli import _parse_settings
from fiberplan.outcomes import OUTCOMES
from fiberplan.settings import describe_settings

SIZES = {"central": 2}
"""Positioners per group (central solves one NLP over the whole group: kept tiny here)."""
FAST = {"central": {"steps": 16, "warm_start": ["straight"], "lazy_rounds": 1, "max_wall_s": 20.0}}


OWN_ROUTES = {("dnf", "moons"): {"route_prioritized_up_to": 0, "route_retract_up_to": 0}}
"""Runs whose prioritized and retraction candidates (the coordination layer's, on small groups) cost minutes on
MOONS' own zones (dnf, MOONS 7 random seed 4: 148 s for the two plans of this test, every
candidate short or longer); the candidates have their own tests."""


def _plan(planner: str, instrument: str, seed: int = 4):
    scenario = fp.make_scenario(instrument, SIZES.get(planner, 7), "random", seed)
    return scenario, fp.plan(scenario, planner, FAST.get(planner) or OWN_ROUTES.get((planner, instrument)))


SLOW = {("mpc", "moons"), ("prioritized", "moons"), ("central", "moons")}
"""Runs of minutes on MOONS' own zones (the start schedule and the loop leave positioners of a
random MOONS 7 short and retry: measured 47-360 s per plan); run with ``pytest -m slow``."""
CASES = [pytest.param(p, i, marks=pytest.mark.slow) if (p, i) in SLOW else pytest.param(p, i)
         for p in fp.planner_names() for i in fp.preset_names()]


@pytest.mark.parametrize(("planner", "instrument"), CASES)
def test_planner_contract(planner: str, instrument: str) -> None:
    scenario, result = _plan(planner, instrument)
    assert set(result.outcome.tolist()) <= set(OUTCOMES)
    assert np.all(np.isfinite(result.trajectory.joints))
    report = fp.verify(scenario, result.trajectory)
    assert not report.limit_violations and not report.start_mismatch_ids
    if planner != "straight":
        assert report.n_collisions == 0, report.to_dict()["collision_events"][:2]
    summary = fp.summarize(result, report)
    assert summary["reached"] == int(np.sum(result.outcome == "reached"))
    _, again = _plan(planner, instrument)
    np.testing.assert_array_equal(again.trajectory.joints, result.trajectory.joints)
    np.testing.assert_array_equal(again.trajectory.times, result.trajectory.times)


@pytest.mark.parametrize("instrument", fp.preset_names())
@pytest.mark.parametrize("planner", fp.planner_names())
def test_settings_round_trip_through_set(planner: str, instrument: str) -> None:
    inst = fp.load_instrument(instrument)
    settings = fp.make_settings(planner, inst)
    pairs = [f"{row['name']}={json.dumps(row['value'])}" for row in describe_settings(settings)]
    again = fp.make_settings(planner, inst, _parse_settings(pairs))
    assert again == settings
