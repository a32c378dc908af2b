"""Each positioner's move spread over the makespan where clear (planners/stretch.py, setting
``stretch``): less energy, the same starts and ends, the makespan never later, verified whole."""

from __future__ import annotations

import json

import numpy as np
import pytest

import fiberplan as fp
from fiberplan.errors import SettingsError
from fiberplan.geometry import clearance_between
from fiberplan.instrument import MotorLimits
from fiberplan.metrics import arrival_times, energy, reached_mask
from fiberplan.planners import stretch as st
from fiberplan.studies.scenarios import hard_scenario
from fiberplan.trajectory import Trajectory


def test_a_lone_move_at_constant_speed_over_the_whole_makespan_halves_its_energy():
    times = np.linspace(0.0, 2.0, 201)
    column = np.zeros((201, 2))
    column[:101, 0] = np.linspace(0.0, 1.0, 101)  # 1 rad in the first second, then still
    column[101:, 0] = 1.0
    new = st._retimed(column, times, 0, 100, 0, 200, even=True)
    dt = np.diff(times)
    assert st._energy(new, dt) == pytest.approx(0.5 * st._energy(column, dt))
    np.testing.assert_array_equal(new[[0, -1]], column[[0, -1]])
    # A wait inside the move: scaled keeps it (in proportion), constant speed drops it.
    waiting = np.concatenate([np.linspace(0, 0.5, 51), np.full(50, 0.5), np.linspace(0.5, 1.0, 51)[1:], np.ones(50)])
    column = np.stack([waiting, np.zeros(201)], axis=1)
    f, last = st._span(column)
    assert (f, last) == (0, 150)
    scaled = st._retimed(column, times, f, last, 0, 200, even=False)
    even = st._retimed(column, times, f, last, 0, 200, even=True)
    assert np.sum(np.diff(scaled[:, 0]) == 0.0) > 30  # the wait, stretched
    np.testing.assert_allclose(np.diff(even[:, 0]), 1.0 / 200)
    assert st._energy(even, dt) < st._energy(scaled, dt) < st._energy(column, dt)


def _sample_clearances(sc, joints):
    """``(T, P)``: each neighbour pair's smallest clearance at every sample."""
    i, j = sc.pairs[:, 0], sc.pairs[:, 1]
    t = len(joints)
    q_i, q_j = (joints[:, k].transpose(1, 0, 2).reshape(-1, 2) for k in (i, j))
    c = clearance_between(sc.instrument, np.repeat(sc.base_xy[i], t, axis=0), np.repeat(sc.orient[i], t), q_i,
                          np.repeat(sc.base_xy[j], t, axis=0), np.repeat(sc.orient[j], t), q_j)
    return c.min(axis=1).reshape(len(i), t).T


@pytest.mark.parametrize(("instrument", "n", "seed"), [("desi", 19, 0), ("desi", 7, 4), ("sdss", 7, 3)])
def test_the_stretched_plan_verifies_with_less_energy_and_no_later_makespan(instrument, n, seed):
    sc = hard_scenario(instrument, n, seed)
    plain = fp.plan(sc, "mpc")
    result = fp.plan(sc, "mpc", {"stretch": True})
    report = fp.verify(sc, result.trajectory)
    assert report.ok, report.to_dict()["collision_events"][:2]
    before, after = fp.summarize(plain), fp.summarize(result, report)
    assert after["reached"] == before["reached"] == n
    assert after["makespan_s"] <= before["makespan_s"]
    assert after["energy_rad2_s"] < 0.9 * before["energy_rad2_s"]
    assert result.stats["stretch"]["positioners"] >= 1
    assert result.stats["stretch"]["energy_after_rad2_s"] == pytest.approx(after["energy_rad2_s"])
    np.testing.assert_array_equal(result.trajectory.joints[[0, -1]], plain.trajectory.joints[[0, -1]])
    # At the samples, no pair closer than the smaller of the margin and its own closest in the plan.
    floors = np.minimum(result.settings["safety_margin_mm"], _sample_clearances(sc, plain.trajectory.joints).min(axis=0))
    assert np.all(_sample_clearances(sc, result.trajectory.joints) >= floors[None, :])


def _planned(instrument, n, seed):
    """A hard group, its mpc plan, the plan's times and joints and the mpc's margin."""
    sc = hard_scenario(instrument, n, seed)
    plain = fp.plan(sc, "mpc")
    return sc, plain, plain.trajectory.times, plain.trajectory.joints, plain.settings["safety_margin_mm"]


def test_unchecked_stretching_collides_so_the_check_is_what_keeps_it_clear(monkeypatch):
    sc, plain, times, joints, margin = _planned("desi", 7, 0)
    checked = st.stretch(sc, times, joints, margin)
    assert fp.verify(sc, Trajectory(times, checked.joints)).ok
    monkeypatch.setattr(st._Checker, "clear", lambda self, i, column, a, b: True)
    unchecked = st.stretch(sc, times, joints, margin)
    assert unchecked.positioners > checked.positioners
    assert fp.verify(sc, Trajectory(times, unchecked.joints)).n_collisions > 0
    np.testing.assert_array_equal(joints, plain.trajectory.joints)  # the input is not modified


def test_no_motor_rule_is_broken_more_often_than_by_the_plan():
    sc = hard_scenario("moons", 7, 2)
    plain = fp.plan(sc, "mpc")  # governed: its samples keep MOONS' motor rules where it can
    times = plain.trajectory.times
    done = st.stretch(sc, times, plain.trajectory.joints, plain.settings["safety_margin_mm"])
    assert done.positioners >= 1
    dt, motors = np.diff(times), sc.instrument.motors
    for i in range(sc.n_positioners):
        assert np.all(st.motor_counts(done.joints[:, i], dt, motors) <= st.motor_counts(plain.trajectory.joints[:, i], dt, motors))
    stretched = Trajectory(times, done.joints)
    report, before = fp.verify(sc, stretched), fp.verify(sc, plain.trajectory)
    assert report.ok
    kinds = {(v.positioner_id, v.joint, v.kind) for v in report.motor_violations}
    assert kinds <= {(v.positioner_id, v.joint, v.kind) for v in before.motor_violations}
    assert energy(stretched) < energy(plain.trajectory)
    arrive, reached = arrival_times(sc, stretched), reached_mask(sc, stretched)
    assert reached.all() and np.nanmax(arrive) <= np.nanmax(arrival_times(sc, plain.trajectory))


def test_constant_speed_along_a_path_that_turns_back_drops_its_stop_so_motor_rules_refuse_it():
    times = np.linspace(0.0, 0.6, 61)
    out = np.concatenate([np.linspace(0.0, 0.1, 11), [0.1], np.linspace(0.1, 0.0, 11)[1:], np.zeros(39)])  # out, a stop, back
    column = np.stack([out, np.zeros(61)], axis=1)
    motors = MotorLimits(stop_before_reversing=True, max_speed_change=0.4)
    dt = np.diff(times)
    assert not st.motor_counts(column, dt, motors).any()
    f, g = st._span(column)
    even = st._retimed(column, times, f, g, 0, 30, even=True)
    assert st.motor_counts(even, dt, motors)[0, 1] == 1  # alpha reverses without the stop
    twice = st._retimed(column, times, f, g, 0, 2 * g, even=False)  # twice as slow: the stop kept, two samples long
    assert not st.motor_counts(twice, dt, motors).any()
    uneven = st._retimed(column, times, f, g, 0, 60, even=False)  # 60 / 21 samples a sample: steps of uneven speed
    assert st.motor_counts(uneven, dt, motors)[0, 2] > 0


def test_stretch_is_a_setting_of_the_route_planners_only():
    sc = hard_scenario("desi", 7, 0)
    assert fp.plan(sc, "dnf", {"stretch": True}).stats["stretch"]["positioners"] >= 1
    with pytest.raises(SettingsError, match="stretch"):
        fp.plan(sc, "straight", {"stretch": True})


def test_the_straight_joint_move_is_offered_too(monkeypatch):
    sc, _, times, joints, margin = _planned("desi", 7, 1)
    both = st.stretch(sc, times, joints, margin)
    monkeypatch.setattr(st, "STRAIGHTEN", False)
    own_paths = st.stretch(sc, times, joints, margin)
    assert both.energy_after < own_paths.energy_after < own_paths.energy_before == both.energy_before
    for done in (both, own_paths):
        assert fp.verify(sc, Trajectory(times, done.joints)).ok
    # More positioners move on the straight line from their start to their end, at constant speed.
    def straight(done):
        count = 0
        for i in range(sc.n_positioners):
            span = st._span(done.joints[:, i])
            if span is None:  # (a round trip made straight: it holds still)
                continue
            f, g = span
            count += np.allclose(done.joints[f : g + 1, i], np.linspace(done.joints[f, i], done.joints[g, i], g - f + 1), atol=1e-12)
        return count

    assert straight(both) > straight(own_paths)


def test_the_command_line_says_what_the_stretch_did(tmp_path):
    from click.testing import CliRunner

    from fiberplan.cli import cli

    args = ["plan", "--instrument", "desi", "-n", "7", "--seed", "1", "--set", "stretch=true"]
    shown = CliRunner().invoke(cli, args)
    assert shown.exit_code == 0, shown.output
    assert "positioner(s) stretched, energy" in shown.output
    out = tmp_path / "run.h5"
    as_json = CliRunner().invoke(cli, [*args, "--json", "--out", str(out)])
    assert as_json.exit_code == 0, as_json.output
    summary = json.loads(as_json.output.splitlines()[-1])
    assert summary["stretch"]["positioners"] >= 1
    assert summary["stretch"]["energy_after_rad2_s"] == pytest.approx(summary["energy_rad2_s"])
    assert summary["energy_rad2_s"] < summary["stretch"]["energy_before_rad2_s"]
    assert fp.load_result(out).settings["stretch"] is True
    plain = CliRunner().invoke(cli, ["plan", "--instrument", "desi", "-n", "7", "--seed", "1"])
    assert "stretched" not in plain.output


def test_the_stretched_plan_makes_motor_profiles_that_verify():
    sc = hard_scenario("moons", 7, 2)  # MOONS' motor rules stated
    plain, stretched = fp.plan(sc, "mpc"), fp.plan(sc, "mpc", {"stretch": True})
    assert stretched.stats["stretch"]["positioners"] >= 1
    before, after = fp.discretise(plain), fp.discretise(stretched)
    assert after.report.ok and not after.report.motor_violations
    assert after.summary()["makespan_after_s"] <= before.summary()["makespan_after_s"]


def test_locked_held_and_unreached_positioners_keep_their_samples_or_their_ends():
    from fiberplan.scenario import scenario_from_dict

    data = fp.make_scenario("desi", 19, "random", 5).to_dict()
    rows = data["positioners"]
    rows[3]["locked"], rows[3]["target"] = True, None  # locked where it starts
    rows[7]["target"] = None  # held: may yield, ends where it started
    a, b = rows[0], rows[1]  # targets that collide: infeasible, planned as held
    a["target"] = {"x_mm": (a["x_mm"] + b["x_mm"]) / 2, "y_mm": (a["y_mm"] + b["y_mm"]) / 2}
    b["target"] = {"x_mm": a["target"]["x_mm"] + 0.05, "y_mm": a["target"]["y_mm"]}
    sc = scenario_from_dict(data)
    assert {0, 1} <= set(sc.infeasible)
    plain, result = fp.plan(sc, "mpc"), fp.plan(sc, "mpc", {"stretch": True})
    assert result.stats["stretch"]["positioners"] >= 1
    assert fp.verify(sc, result.trajectory).ok
    joints = result.trajectory.joints
    assert np.all(joints[:, 3] == sc.start[3])
    for k in (0, 1, 7):
        np.testing.assert_array_equal(joints[-1, k], plain.trajectory.joints[-1, k])
    np.testing.assert_array_equal(np.asarray(result.outcome), np.asarray(plain.outcome))


def test_a_positioner_left_short_keeps_its_samples_and_one_without_a_target_its_start():
    from fiberplan.scenario import scenario_from_dict

    data = fp.make_scenario("desi", 7, "random", 0).to_dict()
    data["positioners"][5]["target"] = None
    sc = scenario_from_dict(data)
    times = np.linspace(0.0, 2.0, 201)
    joints = np.repeat(sc.start[None], 201, axis=0)
    joints[:, 4] = np.linspace(sc.start[4], sc.target[4], 201)  # reached at the end: the makespan
    joints[:51, 1] = np.linspace(sc.start[1], 0.5 * (sc.start[1] + sc.target[1]), 51)  # half-way, then stops: short
    joints[51:, 1] = joints[50, 1]
    out = sc.start[5] + np.array([0.2, 0.0])  # no target: out and back early
    joints[:41, 5] = np.concatenate([np.linspace(sc.start[5], out, 21), np.linspace(out, sc.start[5], 21)[1:]])
    assert not reached_mask(sc, Trajectory(times, joints))[1]
    done = st.stretch(sc, times, joints, 0.0251)
    np.testing.assert_array_equal(done.joints[:, 1], joints[:, 1])  # short: as planned
    for i in (0, 2, 3, 6):  # with a target, never moved: still
        np.testing.assert_array_equal(done.joints[:, i], joints[:, i])
    np.testing.assert_array_equal(done.joints[-1, 5], sc.start[5])  # back where it started
    assert st._span(done.joints[:, 5]) != st._span(joints[:, 5])  # its round trip spread out (or, straight, dropped)
