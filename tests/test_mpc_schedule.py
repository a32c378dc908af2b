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


def _delayed_moves(sc, step_rad, delay, t, corner=None):
    """Joints at step ``t`` of every full-speed move started after ``delay`` (an independent
    restatement): straight, or through ``corner`` where it is not NaN (one leg, then the other)."""
    k = np.clip(t - delay, 0, None)[:, None]
    q = sc.start + np.clip(sc.target - sc.start, -k * step_rad, k * step_rad)
    if corner is not None:
        for i in np.flatnonzero(~np.isnan(corner[:, 0])):
            k1 = int(np.ceil(np.max(np.abs(corner[i] - sc.start[i]) / step_rad) - 1e-9))
            ki = k[i, 0]
            if ki <= k1:
                q[i] = sc.start[i] + np.clip(corner[i] - sc.start[i], -ki * step_rad, ki * step_rad)
            else:
                q[i] = corner[i] + np.clip(sc.target[i] - corner[i], -(ki - k1) * step_rad, (ki - k1) * step_rad)
    return q


def _pair_clearance(sc, pairs, qa, qb):
    a, b = pairs[:, 0], pairs[:, 1]
    return clearance_between(sc.instrument, sc.base_xy[a], sc.orient[a], qa[a], sc.base_xy[b], sc.orient[b], qb[b]).min(axis=-1)


def _placed_pairs_worst_and_floor(sc, settings, step_rad, schedule, horizon, corner=None):
    """Pairs of placed positioners, their smallest clearance along the scheduled moves (every
    second step and the last) and the floor the schedule promises them."""
    placed = np.ones(sc.n_positioners, dtype=bool)
    placed[schedule.unplaced] = False
    pairs = sc.pairs[placed[sc.pairs[:, 0]] & placed[sc.pairs[:, 1]]]
    floor = np.minimum(settings.margin_mm, 0.9 * np.minimum(_pair_clearance(sc, pairs, sc.start, sc.start),
                                                            _pair_clearance(sc, pairs, sc.target, sc.target)))
    worst = np.full(len(pairs), np.inf)
    for t in [*range(0, horizon + 1, 2), horizon]:
        q = _delayed_moves(sc, step_rad, schedule.delay_steps, t, corner)
        worst = np.minimum(worst, _pair_clearance(sc, pairs, q, q))
    return pairs, worst, floor


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
    pairs, worst, floor = _placed_pairs_worst_and_floor(sc, settings, step_rad, schedule, int(np.ceil(1.2 * move.max())))
    assert np.all(worst >= floor - 1e-9)
    # Without the delays the same pairs would not keep their margins.
    undelayed = np.full(len(pairs), np.inf)
    for t in range(0, int(move.max()) + 1, 2):
        q = _delayed_moves(sc, step_rad, np.zeros_like(delay), t)
        undelayed = np.minimum(undelayed, _pair_clearance(sc, pairs, q, q))
    assert np.any(undelayed < floor)


def test_l_shaped_moves_place_positioners_no_delay_fits():
    sc = make_scenario("desi", 500, "random", 0)
    settings = make_settings("mpc", sc)
    step_rad = sc.instrument.speeds_rad_s * settings.dt_s
    straight = start_schedule(sc, step_rad, settings.margin_mm)
    schedule = start_schedule(sc, step_rad, settings.margin_mm, l_paths=True)
    routed = np.flatnonzero(~np.isnan(schedule.corner[:, 0]))
    assert len(routed) > 0
    # Only positioners the straight schedule left unplaced are routed, and the rest keep their delays.
    assert set(routed) <= set(straight.unplaced) and len(schedule.unplaced) == len(straight.unplaced) - len(routed)
    keep = np.isnan(schedule.corner[:, 0])
    assert np.array_equal(schedule.delay_steps[keep], straight.delay_steps[keep])
    # A corner changes one joint only: alpha first or beta first.
    c = schedule.corner[routed]
    alpha_first = np.all(c == np.column_stack([sc.target[routed, 0], sc.start[routed, 1]]), axis=1)
    beta_first = np.all(c == np.column_stack([sc.start[routed, 0], sc.target[routed, 1]]), axis=1)
    assert np.all(alpha_first | beta_first)
    # Every placed pair keeps its floor along the scheduled moves, L-shaped ones included, and
    # every move ends in time.
    move = np.ceil(np.max(np.abs(sc.target - sc.start) / step_rad, axis=1) - 1e-9)
    horizon = int(np.ceil(1.2 * move.max()))
    _, worst, floor = _placed_pairs_worst_and_floor(sc, settings, step_rad, schedule, horizon, schedule.corner)
    assert np.all(worst >= floor - 1e-9)
    assert np.allclose(_delayed_moves(sc, step_rad, schedule.delay_steps, horizon, schedule.corner), sc.target)
    # The planner follows the corner (within half a step: the QP rounds it) and arrives.
    result = plan(sc, "mpc", {"schedule_l_paths": True})
    assert result.stats["schedule_l_paths"] == len(routed)
    assert verify(sc, result.trajectory).n_collisions == 0
    joints = result.trajectory.joints
    for i in routed:
        assert np.min(np.max(np.abs(joints[:, i] - schedule.corner[i]) / step_rad, axis=1)) <= 0.5 + 1e-9
        assert np.all(joints[-1, i] == sc.target[i])


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
    delay = start_schedule(sc, sc.instrument.speeds_rad_s * settings.dt_s, settings.margin_mm,
                           l_paths=settings.schedule_l_paths).delay_steps
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
