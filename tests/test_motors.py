"""The motor governor: each executed step of the mpc is one the motor controllers accept."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import fiberplan as fp
from fiberplan.instrument import MotorLimits
from fiberplan.planners.motors import govern, hold_for_ramps

MOONS = MotorLimits(min_speed_rad_s=(0.08, 0.1), max_speed_change=0.4, stop_before_reversing=True)
TOP = np.array([0.29, 0.39])
LIMITS = np.array([[-10.0, 10.0], [-10.0, 10.0]])
DT = 0.05


def _one(q: float, step: float, v_prev: float, goal: float, reverse: bool = False) -> float:
    """Govern alpha alone (beta holds); the governed step's speed (rad/s)."""
    q0 = np.array([[q, 0.0]])
    out = govern(q0, q0 + [[step, 0.0]], np.array([[v_prev, 0.0]]), np.array([[goal, 0.0]]), DT, MOONS, TOP, LIMITS, reverse)  # noqa: RUF005 (numpy addition)
    return float((out[0, 0] - q) / DT)


def test_a_reversal_holds_first():
    assert _one(0.0, -0.01, 0.2, -1.0) == 0.0


def test_the_speed_change_is_clipped_to_the_band_or_stops():
    assert _one(0.0, 0.29 * DT, 0.1, 5.0) == pytest.approx(0.14)  # up at most 40 %
    assert _one(0.0, 0.05 * DT, 0.1, 5.0) == pytest.approx(0.08)  # down to 60 % (and the minimum)
    assert _one(0.0, 0.02 * DT, 0.2, 5.0) == 0.0  # far below the band: a stop
    assert _one(0.0, 0.15 * DT, 0.2, 5.0) == pytest.approx(0.15)  # within the band: unchanged


def test_a_start_takes_at_least_the_minimum_speed_and_never_passes_the_goal():
    assert _one(0.0, 0.01 * DT, 0.0, 5.0) == pytest.approx(0.08)
    assert _one(0.0, 0.001 * DT, 0.0, 0.002 * DT) == pytest.approx(0.002)  # lands on the goal, not past it


@given(st.lists(st.floats(-1.0, 1.0), min_size=5, max_size=80), st.floats(-3.0, 3.0), st.booleans())
@settings(max_examples=200, deadline=None)
def test_governed_steps_keep_the_motor_rules_except_on_arrival(proposals, goal, reverse):
    """Whatever is proposed, consecutive moving steps never reverse, keep the speed change (its
    reversed form for a leg planned backwards) and the minimum speed; only the step that lands
    on the goal may break the latter two."""
    q, v_prev, c = 0.0, 0.0, MOONS.max_speed_change
    speeds = []
    for u in proposals:
        v = _one(q, u * TOP[0] * DT, v_prev, goal, reverse)
        q += v * DT
        arrived = abs(q - goal) < 1e-12
        if abs(v) > 1e-12 and not arrived:
            assert abs(v) >= MOONS.min_speed_rad_s[0] * (1 - 1e-9)
            assert abs(v) <= TOP[0] * (1 + 1e-9)
        if abs(v) > 1e-12 and abs(v_prev) > 1e-12:
            assert v * v_prev > 0, "a reversal without a stop"
            if not arrived:
                ratio = abs(v - v_prev) / (abs(v) if reverse else abs(v_prev))
                assert ratio <= c * (1 + 1e-6)
        speeds.append(v)
        v_prev = v


def test_the_mpc_keeps_most_motor_limits_in_its_samples_at_no_cost():
    """MOONS (capsules) 61 unfold seed 0: the governed plan's samples break few motor limits
    where the ungoverned plan's break one per joint or more; both verified and complete, the
    makespan within a few steps."""
    scenario = fp.make_scenario("moons-capsules", 61, "unfold", 0)
    runs = {on: fp.plan(scenario, "mpc", settings={"motor_limits": on}) for on in (False, True)}
    reports = {on: fp.verify(scenario, r.trajectory) for on, r in runs.items()}
    for on, r in runs.items():
        assert reports[on].ok and fp.summarize(r)["reached"] == 61
    assert len(reports[False].motor_violations) > 100
    assert len(reports[True].motor_violations) < 20
    assert fp.summarize(runs[True])["makespan_s"] <= fp.summarize(runs[False])["makespan_s"] + 10 * 0.05


def test_the_governor_is_off_where_no_motor_limit_is_stated():
    scenario = fp.make_scenario("desi", 19, "random", 1)
    on = fp.plan(scenario, "mpc", settings={"motor_limits": True})
    off = fp.plan(scenario, "mpc", settings={"motor_limits": False})
    np.testing.assert_array_equal(on.trajectory.joints, off.trajectory.joints)


def test_a_governed_plan_left_short_is_planned_again_without_the_governor(monkeypatch):
    """Completion first: a governed plan that leaves positioners short (here: cut before anyone
    arrives) is made again without the governor; the complete one is kept, and says so."""
    import dataclasses

    import fiberplan.planners as planners
    from fiberplan.trajectory import Trajectory

    real = planners._plan_with

    def cut_when_governed(scenario, planner, settings, progress, warm):
        result = real(scenario, planner, settings, progress, warm)
        if settings.motor_limits:
            result = dataclasses.replace(result, trajectory=Trajectory(result.trajectory.times[:2], result.trajectory.joints[:2]))
        return result

    monkeypatch.setattr(planners, "_plan_with", cut_when_governed)
    scenario = fp.make_scenario("moons-capsules", 7, "random", 1)
    phases = []
    result = fp.plan(scenario, "mpc", {"route": "direct"}, progress=lambda fraction, phase=None: phases.append(phase))
    assert fp.summarize(result)["reached"] == 7
    assert "again without the motor governor: control loop" in phases  # the progress bar says why it starts again
    assert result.stats["motor_governor"] == "dropped"
    assert any("motor governor left 7 positioner(s) short" in w for w in result.warnings)
    assert not fp.plan(fp.make_scenario("desi", 7, "random", 1), "mpc", {"route": "direct"}).stats.get("motor_governor")


def test_with_a_ramp_a_fast_joint_turns_back_only_after_a_ramp_at_rest():
    """Rule 4: a speed and an opposite one within a ramp add up to at most the top speed."""
    ramps = MotorLimits(ramp_time_s=0.1)
    q0 = np.array([[0.0, 0.0]])

    def step(proposal: float, forward: float, backward: float) -> float:
        recent = (np.array([[forward, 0.0]]), np.array([[backward, 0.0]]))
        out = govern(q0, q0 + [[proposal * DT, 0.0]], np.zeros((1, 2)), np.array([[-5.0, 0.0]]), DT, ramps, TOP, LIMITS,  # noqa: RUF005
                     recent=recent)
        return float(out[0, 0] / DT)

    assert step(-0.2, forward=0.25, backward=0.0) == 0.0  # 0.2 + 0.25 > 0.29: holds
    assert step(-0.04, forward=0.25, backward=0.0) == pytest.approx(-0.04)  # 0.04 + 0.25 <= 0.29: may turn back slowly
    assert step(-0.2, forward=0.0, backward=0.1) == pytest.approx(-0.2)  # the same way: free
    assert step(-0.2, forward=0.0, backward=0.0) == pytest.approx(-0.2)  # rested a ramp: free


def test_the_positioners_exempt_from_the_governor_still_wait_a_ramp_before_turning_back():
    """Rule 4 alone (the stalled and those on the deadlock ladder): the fast reversal holds, the
    rest of the step (the other joint, a slow reversal, a rested joint) is kept."""
    q = np.zeros((3, 2))
    proposed = np.array([[-0.2, 0.3], [-0.04, 0.0], [-0.2, 0.0]]) * DT
    forward = np.array([[0.25, 0.0], [0.25, 0.0], [0.0, 0.0]])
    out = hold_for_ramps(q, proposed, DT, TOP, (forward, np.zeros((3, 2))))
    np.testing.assert_allclose(out / DT, [[0.0, 0.3], [-0.04, 0.0], [-0.2, 0.0]])
    assert hold_for_ramps(q, proposed, DT, TOP, None) is proposed  # no ramp stated: unchanged


def test_the_mpc_plans_on_a_ramped_instrument_keep_the_ramps():
    """Its samples, executed as commands with the ramps, never change speed faster than they allow."""
    import json

    from fiberplan.instrument_io import load_instrument
    from fiberplan.ramps import verify_commands
    from fiberplan.scenario import scenario_from_dict

    spec = json.loads(json.dumps(load_instrument("moons-capsules").to_dict()))
    spec["motors"]["ramp_time_s"] = 0.2
    data = fp.make_scenario("moons-capsules", 19, "unfold", 1).to_dict() | {"instrument": spec}
    scenario = scenario_from_dict(data, origin="test")
    result = fp.plan(scenario, "mpc")
    assert fp.summarize(result)["reached"] == 19
    report = verify_commands(scenario, result.trajectory)
    assert report.ok and not [v for v in report.motor_violations if v.kind == "acceleration"]
    free = fp.plan(scenario, "mpc", {"motor_limits": False})  # the same without the governor: the ramps are broken
    assert [v for v in verify_commands(scenario, free.trajectory).motor_violations if v.kind == "acceleration"]
