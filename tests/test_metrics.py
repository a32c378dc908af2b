"""Metrics: success, makespan, lower bound, path length, energy."""

from __future__ import annotations

import numpy as np
import pytest

from fiberplan.kinematics import move_times
from fiberplan.metrics import arrival_times, energy, lower_bound_s, reached_mask, summarize
from fiberplan.planners import plan
from fiberplan.trajectory import Trajectory


def test_straight_reaches_everything_at_the_lower_bound(desi_random_61):
    sc = desi_random_61
    result = plan(sc, "straight")
    summary = summarize(result)
    assert summary["success_rate"] == 1.0 and summary["reached"] == 61
    bound = lower_bound_s(sc)
    assert bound == pytest.approx(float(move_times(sc.instrument, sc.start, sc.target).max()))
    # arrival within the tolerance disc comes at most one sample before the exact arrival
    assert bound - sc.instrument.control_dt_s - 1e-9 <= summary["makespan_s"] <= bound + 1e-9
    for key in ("planner", "instrument", "n_positioners", "seed", "reached", "success_rate", "makespan_s", "lower_bound_s", "plan_wall_s"):
        assert key in summary


def test_holding_still_reaches_nothing(desi_random_61):
    sc = desi_random_61
    still = Trajectory(np.array([0.0, 1.0]), np.stack([sc.start, sc.start]))
    assert not reached_mask(sc, still).any()
    assert np.isnan(arrival_times(sc, still)).all()
    assert energy(still) == 0.0


def test_energy_of_constant_speed_motion():
    joints = np.array([[[0.0, 0.0]], [[1.0, 2.0]]])
    # velocity (1, 2) rad/s for 1 s: integral of |v|^2 = 5
    assert energy(Trajectory(np.array([0.0, 1.0]), joints)) == pytest.approx(5.0)
