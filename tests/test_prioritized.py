"""The ``prioritized`` planner (reference 003's prioritized state-time planning, executed under
the safety layer): its execution loop against the loop as it was before its stalled tail was
taken as a whole."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from fiberplan.kinematics import move_times
from fiberplan.planners import make_settings
from fiberplan.planners.mpc.priority import outranks
from fiberplan.planners.mpc.routes import route_path
from fiberplan.planners.prioritized import _execute, _schedule
from fiberplan.planners.safety import SafetyLayer
from fiberplan.studies.scenarios import hard_scenario


def _execute_step_by_step(scenario, settings, schedule, step_rad):
    """``_execute`` as it was: every step computed, to the time limit if anyone stalls."""
    n = scenario.n_positioners
    goal = scenario.target
    move = move_times(scenario.instrument, scenario.start, goal)
    bound = float(move[scenario.has_target].max()) if scenario.has_target.any() else 0.0
    limit_s = settings.time_limit_s or settings.max_duration_factor * bound + scenario.instrument.full_turn_s
    max_steps = int(np.ceil(limit_s / settings.dt_s))
    routes = {}
    for i in np.flatnonzero(~np.isnan(schedule.corner[:, 0])).tolist():
        routes[i] = (np.array([schedule.corner[i], goal[i]]), None)
    for i, (waypoints, depart) in schedule.timed.items():
        routes[i] = (waypoints, depart)
    pos = dict.fromkeys(routes, 0)
    unplaced = np.zeros(n, dtype=bool)
    unplaced[schedule.unplaced] = True
    safety = SafetyLayer(scenario, settings.safety_margin_mm)
    rank = np.lexsort((np.arange(n), -move, scenario.priority_rank))
    order = np.empty(n, dtype=np.int64)
    order[rank] = np.arange(n)
    first = partial(outranks, rank=order, defer_to=np.full(n, -1))
    q = scenario.start.copy()
    c_now = safety.clearance(q, scenario.pairs)
    history, held_total = [q.copy()], 0
    for step in range(max_steps):
        if np.all((q == goal).all(axis=1) | unplaced):
            break
        q_next = q + np.clip(goal - q, -step_rad, step_rad)
        for i, (waypoints, departs) in routes.items():
            path = route_path(q[i], waypoints, pos[i], step_rad, 1, departs, step)
            q_next[i] = path[0]
            while pos[i] < len(waypoints) - 1 and np.all(np.abs(q_next[i] - waypoints[pos[i]]) <= 0.5 * step_rad):
                pos[i] += 1
        waiting = step < schedule.delay_steps
        q_next[waiting | unplaced | scenario.locked] = q[waiting | unplaced | scenario.locked]
        q_next, held, _ = safety.apply(q, q_next, c_now, first)
        held_total += int(held.sum())
        safety.refresh(c_now, q, q_next)
        q = q_next
        history.append(q.copy())
    return np.stack(history), held_total


@pytest.mark.parametrize(("instrument", "n", "seed"), [("sdss", 19, 3), ("sdss", 19, 8), ("sdss", 7, 6), ("moons", 7, 1)])
def test_a_stalled_execution_is_the_step_by_step_one(instrument, n, seed):
    """Where positioners stall (held by the safety layer with no departure ahead), the rest of the
    run is taken as that configuration held: the same joints, bit for bit, and the same count of
    holds as computing every step to the time limit."""
    scenario = hard_scenario(instrument, n, seed)
    settings = make_settings("prioritized", scenario, {})
    step_rad = scenario.instrument.speeds_rad_s * settings.dt_s
    schedule = _schedule(scenario, settings, step_rad, np.zeros(n, dtype=bool))
    joints, held = _execute(scenario, settings, schedule, step_rad, None)
    before, held_before = _execute_step_by_step(scenario, settings, schedule, step_rad)
    assert joints.shape == before.shape
    np.testing.assert_array_equal(joints, before)
    assert held == held_before
    # The case exercises the stalled tail: someone ends short of the target, the run at its limit.
    assert not np.all((joints[-1] == scenario.target).all(axis=1))


def _two_desi(start_deg, target_deg):
    from fiberplan.instrument_io import load_instrument
    from fiberplan.scenario import TARGET_JOINTS, Scenario

    return Scenario(instrument=load_instrument("desi"), ids=np.arange(2), base_xy=np.array([[0.0, 0.0], [0.0, 100.0]]),
                    orient_deg=np.zeros(2), start_deg=np.array(start_deg), target_kind=np.full(2, TARGET_JOINTS),
                    target_values=np.array(target_deg), target_parity=np.zeros(2, dtype=np.int64), name="two")


def _both_ways(scenario, schedule, monkeypatch, hold=None):
    if hold is not None:  # a stand-in safety layer that holds the steps ``hold`` names
        def apply(self, q, q_next, c_now, first):
            held = hold(q_next - q)
            out = q_next.copy()
            out[held] = q[held]
            return out, held, 0
        monkeypatch.setattr(SafetyLayer, "apply", apply)
    settings = make_settings("prioritized", scenario, {})
    step_rad = scenario.instrument.speeds_rad_s * settings.dt_s
    joints, held = _execute(scenario, settings, schedule, step_rad, None)
    before, held_before = _execute_step_by_step(scenario, settings, schedule, step_rad)
    np.testing.assert_array_equal(joints, before)
    assert held == held_before
    return joints


def test_a_wait_for_a_start_delay_is_not_a_stall(monkeypatch):
    """Everyone still at a step before someone's start delay has run out is not the end: the
    delayed move is executed."""
    from fiberplan.planners.mpc.schedule import StartSchedule

    scenario = _two_desi([[0.0, 150.0], [0.0, 150.0]], [[20.0, 150.0], [0.0, 150.0]])
    schedule = StartSchedule(np.array([30, 0]), np.zeros(0, dtype=np.int64), 0, np.full((2, 2), np.nan))
    joints = _both_ways(scenario, schedule, monkeypatch)
    np.testing.assert_array_equal(joints[-1], scenario.target)


def test_a_held_step_that_passes_a_corner_is_not_a_stall(monkeypatch):
    """A positioner held on the step that passes its route's corner heads for the next waypoint
    at the next step (another step, which may be let through): not the end either."""
    from fiberplan.planners.mpc.schedule import StartSchedule

    probe = _two_desi([[0.0, 150.0], [0.0, 150.0]], [[0.0, 150.0], [0.0, 150.0]])
    alpha_step_deg = float(np.degrees(probe.instrument.speeds_rad_s[0] * make_settings("prioritized", probe, {}).dt_s))
    # Alpha 3/4 of a step: the first step reaches the corner (more than half a step away: not passed at the start).
    scenario = _two_desi([[0.0, 150.0], [0.0, 150.0]], [[0.75 * alpha_step_deg, 120.0], [0.0, 150.0]])
    corner = np.full((2, 2), np.nan)
    corner[0] = [scenario.target[0, 0], scenario.start[0, 1]]  # alpha first, then beta
    schedule = StartSchedule(np.zeros(2, dtype=np.int64), np.zeros(0, dtype=np.int64), 0, corner)
    joints = _both_ways(scenario, schedule, monkeypatch, hold=lambda d: (d[:, 0] > 0) & (d[:, 1] == 0))  # alpha alone: held
    np.testing.assert_array_equal(joints[-1], scenario.target)
