"""Tests of the ``mpc`` start schedule: delayed straight moves keep their margins pairwise,
end in time, and the planner holds each positioner until its scheduled start."""

from __future__ import annotations

import numpy as np
import pytest

from fiberplan.generate import make_scenario
from fiberplan.geometry import clearance_between
from fiberplan.planners import make_settings, plan
from fiberplan.planners.mpc_schedule import start_schedule
from fiberplan.verify import verify


def _delayed_moves(sc, step_rad, delay, t):
    """Joints at step ``t`` of every straight full-speed move started after ``delay`` (an independent restatement)."""
    k = np.clip(t - delay, 0, None)[:, None]
    return sc.start + np.clip(sc.target - sc.start, -k * step_rad, k * step_rad)


def _pair_clearance(sc, pairs, qa, qb):
    a, b = pairs[:, 0], pairs[:, 1]
    return clearance_between(sc.instrument, sc.base_xy[a], sc.orient[a], qa[a], sc.base_xy[b], sc.orient[b], qb[b]).min(axis=-1)


@pytest.mark.parametrize(("instrument", "n", "seed"), [("desi", 500, 0), ("desi", 200, 3)])
def test_placed_moves_keep_their_margins_and_end_in_time(instrument, n, seed):
    sc = make_scenario(instrument, n, "random", seed)
    settings = make_settings("mpc", sc)
    step_rad = sc.instrument.speeds_rad_s * settings.dt_s
    schedule = start_schedule(sc, step_rad, settings.margin_mm, delay_steps=4, slack=1.2, stride=2)
    delay = schedule.delay_steps
    move = np.ceil(np.max(np.abs(sc.target - sc.start) / step_rad, axis=1) - 1e-9)
    assert np.all(delay >= 0) and np.all(delay % 4 == 0)
    assert np.all(delay + move <= np.ceil(1.2 * move.max()))
    assert np.count_nonzero(delay) > 0  # DESI 500 needs some: targets on neighbours' paths
    placed = np.ones(sc.n_positioners, dtype=bool)
    placed[schedule.unplaced] = False
    pairs = sc.pairs[placed[sc.pairs[:, 0]] & placed[sc.pairs[:, 1]]]
    floor = np.minimum(settings.margin_mm, 0.9 * np.minimum(_pair_clearance(sc, pairs, sc.start, sc.start),
                                                            _pair_clearance(sc, pairs, sc.target, sc.target)))
    worst = np.full(len(pairs), np.inf)
    for t in range(0, int(np.ceil(1.2 * move.max())) + 1, 2):
        q = _delayed_moves(sc, step_rad, delay, t)
        worst = np.minimum(worst, _pair_clearance(sc, pairs, q, q))
    assert np.all(worst >= floor - 1e-9)
    # Without the delays the same pairs would not keep their margins.
    undelayed = np.full(len(pairs), np.inf)
    for t in range(0, int(move.max()) + 1, 2):
        q = _delayed_moves(sc, step_rad, np.zeros_like(delay), t)
        undelayed = np.minimum(undelayed, _pair_clearance(sc, pairs, q, q))
    assert np.any(undelayed < floor)


def test_no_pairs_no_delays():
    sc = make_scenario("desi", 1, "random", 0)
    schedule = start_schedule(sc, sc.instrument.speeds_rad_s * 0.01, 0.3)
    assert schedule.delay_steps.tolist() == [0] and len(schedule.unplaced) == 0


def test_planner_holds_each_positioner_until_its_start():
    sc = make_scenario("desi", 200, "random", 3)
    result = plan(sc, "mpc")
    report = verify(sc, result.trajectory)
    assert report.n_collisions == 0
    settings = make_settings("mpc", sc)
    delay = start_schedule(sc, sc.instrument.speeds_rad_s * settings.dt_s, settings.margin_mm).delay_steps
    assert result.stats["schedule_delayed"] == int(np.count_nonzero(delay)) > 0
    joints = result.trajectory.joints
    delayed = np.flatnonzero(delay)
    # Held until its start (joints[k] is the configuration after k steps), then on its way
    # (a neighbour's QP or the safety layer could hold it on, but here most start at once).
    assert all(np.all(joints[: delay[i] + 1, i] == sc.start[i]) for i in delayed)
    started = sum(bool(np.any(joints[delay[i] + 1, i] != sc.start[i])) for i in delayed)
    assert started >= len(delayed) / 2
    off = plan(sc, "mpc", {"start_schedule": False})
    assert off.stats["schedule_delayed"] == 0
    assert not np.array_equal(off.trajectory.joints[:5], joints[:5])
