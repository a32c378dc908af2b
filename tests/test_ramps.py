"""Speed ramps: the instrument states how long a speed change takes; the motion the motors then
execute is modelled, checked with the commands, and the motor profiles keep it collision-free."""

from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest

import fiberplan as fp
from fiberplan.errors import InstrumentError
from fiberplan.instrument_io import instrument_from_dict, instrument_text, load_instrument
from fiberplan.profile_io import write_profiles
from fiberplan.profiles import discretise_trajectory
from fiberplan.ramps import executed_motion, max_acceleration_rad_s2, verify_commands
from fiberplan.scenario import scenario_from_dict
from fiberplan.trajectory import Trajectory
from fiberplan.verify import verify


def _with_motors(spec: dict, **motors: object) -> dict:
    out = json.loads(json.dumps(spec))
    out.setdefault("motors", {}).update(motors)
    return out


def test_ramp_keys_are_read_and_validated():
    spec = tomllib.loads(instrument_text("moons-capsules"))
    inst = instrument_from_dict(_with_motors(spec, ramp_time_s=0.1), origin="x")
    assert inst.motors.ramp_time_s == pytest.approx(0.1)
    assert "ramp_time_s" not in inst.motors.unstated()
    assert max_acceleration_rad_s2(inst) == pytest.approx((inst.alpha_speed_rad_s / 0.1, inst.beta_speed_rad_s / 0.1))
    # An acceleration limit per joint: the ramp of the joint slowest to reach its top speed.
    acc = [30.0, 60.0]  # rpm per second
    inst = instrument_from_dict(_with_motors(spec, max_acceleration_rpm_per_s=acc), origin="x")
    rpm = 2 * math.pi / 60
    expected = max(inst.alpha_speed_rad_s / (acc[0] * rpm), inst.beta_speed_rad_s / (acc[1] * rpm))
    assert inst.motors.ramp_time_s == pytest.approx(expected)
    assert all(a <= b * rpm * (1 + 1e-12) for a, b in zip(max_acceleration_rad_s2(inst), acc, strict=True))
    with pytest.raises(InstrumentError, match="ramp_time_s or max_acceleration_rpm_per_s, not both"):
        instrument_from_dict(_with_motors(spec, ramp_time_s=0.1, max_acceleration_rpm_per_s=acc), origin="x")
    with pytest.raises(InstrumentError, match=r"\[motors\]: ramp_time_s must be > 0"):
        instrument_from_dict(_with_motors(spec, ramp_time_s=0), origin="x")
    with pytest.raises(InstrumentError, match="max_acceleration_rpm_per_s must be > 0"):
        instrument_from_dict(_with_motors(spec, max_acceleration_rpm_per_s=[1.0, -1.0]), origin="x")
    assert "ramp_time_s" in load_instrument("moons").motors.unstated()  # no preset states one: unconstrained, and said so


def test_executed_motion_ramps_each_speed_change_and_lags_half_a_ramp():
    """One joint starts from rest at 1 rad/s at t = 0.5 s and stops at 1.5 s; ramps of 0.2 s."""
    t = np.array([0.0, 0.5, 1.5, 2.0])
    q = np.zeros((4, 1, 2))
    q[:, 0, 0] = [0.0, 0.0, 1.0, 1.0]
    moved = executed_motion(Trajectory(t, q), 0.2)
    alpha = moved.joints[:, 0, 0]

    def at(x: float) -> float:
        return float(alpha[np.argmin(np.abs(moved.times - x))])

    assert at(0.5) == 0.0 and at(0.6) == pytest.approx(0.5 * 5.0 * 0.1**2)  # speed ramps at 5 rad/s^2 for 0.2 s
    assert at(0.7) == pytest.approx(0.1) and at(1.2) == pytest.approx(0.6)  # then the commands, 0.1 s late
    assert at(1.7) == pytest.approx(1.0, abs=1e-12) and at(1.9) == pytest.approx(1.0, abs=1e-12)  # at rest a ramp after the stop
    assert moved.times[-1] == pytest.approx(2.2) and alpha[-1] == 1.0  # and exactly at the end
    assert moved.joints[0].tolist() == q[0].tolist() and np.all(moved.joints[:, 0, 1] == 0.0)
    speed = np.diff(alpha) / np.diff(moved.times)
    assert speed.max() <= 1.0 + 1e-9 and speed.min() >= -1e-12
    assert np.abs(np.diff(speed)).max() / np.diff(moved.times).min() <= 5.0 * (1 + 1e-6)


def _corner_scenario(ramp_s: float):
    """Two DESI positioners: 0 holds; 1 turns alpha, then beta (an L in its joint space) close
    past 0's arm. With long ramps the executed motion cuts the corner into 0."""
    data = fp.make_scenario("desi", 2, "random", 5).to_dict()
    data["instrument"] = _with_motors(load_instrument("desi").to_dict(), ramp_time_s=ramp_s)
    data["positioners"][0]["start_deg"] = [15.6, 18.0]
    data["positioners"][0].pop("target")
    data["positioners"][1]["start_deg"] = [35.0, 115.8]
    data["positioners"][1]["target"] = {"alpha_deg": 154.8, "beta_deg": 90.6}
    scenario = scenario_from_dict(data, origin="test")
    inst = scenario.instrument
    s, c, e = np.radians([[35.0, 115.8], [154.8, 115.8], [154.8, 90.6]])
    t1 = (c[0] - s[0]) / inst.alpha_speed_rad_s
    t2 = t1 + (c[1] - e[1]) / inst.beta_speed_rad_s
    still = np.radians([15.6, 18.0])
    return scenario, (t1, t2), (s, c, e), still


def test_the_executed_check_catches_a_corner_the_ramps_cut():
    scenario, (t1, t2), (s, c, e), still = _corner_scenario(3.0)
    q = np.stack([np.tile(still, (3, 1)), np.array([s, c, e])], axis=1)
    commands = Trajectory(np.array([0.0, t1, t2]), q)
    assert verify(scenario, commands).ok  # the commands pass 0.4 mm away
    report = verify_commands(scenario, commands)
    assert not report.ok and [(ev.id_i, ev.id_j) for ev in report.collisions] == [(0, 1)]
    # A stop of a ramp at the corner: alpha settles before beta starts, nothing is cut.
    q_hold = np.stack([np.tile(still, (4, 1)), np.array([s, c, c, e])], axis=1)
    held = verify_commands(scenario, Trajectory(np.array([0.0, t1, t1 + 3.0, t2 + 3.0]), q_hold))
    assert held.ok and held.min_clearance_mm > 0.3
    # The motor profiles find the cut and stop everyone for a ramp there (not at the start, not at the end).
    made = discretise_trajectory(scenario, commands)
    assert made.report.ok and made.stats["ramp_pauses"] == 1
    assert made.stats["makespan_after_s"] == pytest.approx(t2 + 3.0 + 3.0)


def test_a_reversal_needs_a_stop_of_a_ramp():
    scenario = fp.make_scenario("desi", 1, "random", 0)
    scenario = scenario_from_dict(scenario.to_dict() | {"instrument": _with_motors(load_instrument("desi").to_dict(), ramp_time_s=0.2)},
                                  origin="test")
    a0, b0 = scenario.start[0]
    w = -3.0 if a0 > 0 else 3.0  # rad/s, below the top speed (pi), towards the middle of the range
    # Turning back from w to -w: the executed speed changes by 2 |w| over a ramp (30 rad/s^2, above
    # pi / 0.2 = 15.7) unless the stop lasts a ramp (then |w| per ramp: 15).
    for hold, violated in ((0.05, True), (0.2, False)):
        t = np.array([0.0, 0.5, 0.5 + hold, 1.0 + hold])
        q = np.array([[[a0, b0]], [[a0 + 0.5 * w, b0]], [[a0 + 0.5 * w, b0]], [[a0, b0]]])
        report = verify_commands(scenario, Trajectory(t, q))
        kinds = [(v.joint, v.kind) for v in report.motor_violations]
        assert (("alpha", "acceleration") in kinds) == violated, (hold, kinds)
        assert report.ok  # the acceleration is a motor limit, listed apart


@pytest.fixture(scope="module")
def ramped_run():
    """The mpc's plan of MOONS (capsules) 19 unfold seed 1, on an instrument with 0.1 s ramps."""
    spec = _with_motors(load_instrument("moons-capsules").to_dict(), ramp_time_s=0.1)
    spec["name"] = "moons-capsules-ramps"
    data = fp.make_scenario("moons-capsules", 19, "unfold", 1).to_dict() | {"instrument": spec}
    return fp.plan(scenario_from_dict(data, origin="test"), "mpc")


def test_profiles_with_ramps_are_verified_as_the_motors_execute_them(ramped_run, tmp_path, run_cli):
    made = fp.discretise(ramped_run)
    assert made.report.ok and made.report.motors_ok and made.stats["limits"]["ramp_time_s"] == 0.1
    commands = made.trajectory()
    moved = executed_motion(commands, 0.1)
    again = verify(ramped_run.scenario, moved, instrument=fp.load_instrument("moons-capsules"))
    assert again.n_collisions == 0
    ends = commands.times[np.flatnonzero(np.any(commands.joints[1:] != commands.joints[:-1], axis=(1, 2)))[-1] + 1]
    assert made.stats["makespan_after_s"] == pytest.approx(ends + 0.1)
    inst = ramped_run.scenario.instrument
    reversals = 0
    for (_, axis), prof in made.joints.items():  # a reversal within a ramp only as fast as the ramp allows
        speeds, durations = prof.speeds_rad_s, prof.durations_s
        top = (inst.alpha_speed_rad_s, inst.beta_speed_rad_s)[axis]
        for k in range(1, len(speeds) - 1):
            if speeds[k] == 0.0 and speeds[k - 1] * speeds[k + 1] < 0:
                reversals += 1
                assert durations[k] >= 0.1 - 1e-9 or abs(speeds[k - 1]) + abs(speeds[k + 1]) <= top * (1 + 1e-9)
    assert reversals > 0
    # The exported file and the exported paths are checked as executed too.
    fp.save_result(ramped_run, tmp_path / "m.h5")
    code, out, _ = run_cli(["profiles", str(tmp_path / "m.h5"), "--out", str(tmp_path / "p.h5"), "--json"])
    assert code == 0 and json.loads(out)["verified_ok"] is True
    code, out, _ = run_cli(["verify", str(tmp_path / "p.h5"), "--json", "--motors"])
    assert code == 0 and json.loads(out)["report"]["motor_violations"] == [] and json.loads(out)["report"]["executed_ramp_s"] == 0.1
    code, out, _ = run_cli(["verify", str(tmp_path / "m.h5")])  # a plan: its samples are not motor commands, and it says so
    assert code == 0 and "a planner's samples are not checked against it" in out
    write_profiles(made, ramped_run, tmp_path / "p.json", "json")
    code, out, _ = run_cli(["verify", "--paths", str(tmp_path / "p.json"), "--json"])
    assert code == 0 and json.loads(out)["verified_ok"] is True


def test_cli_verify_lists_acceleration_of_paths_that_reverse_at_once(ramped_run, tmp_path, run_cli):
    """Foreign time-stamped points on the ramped instrument that turn back without a stop."""
    scenario = ramped_run.scenario
    i = int(np.flatnonzero(np.any(ramped_run.trajectory.joints[-1] != scenario.start, axis=1))[0])
    a0, b0 = scenario.start[i]
    positioners = [{"id": int(scenario.ids[i]), "alpha": [[0.0, a0], [1.0, a0 + 0.2], [2.0, a0]], "beta": [[0.0, b0], [2.0, b0]]}]
    (tmp_path / "pts.json").write_text(json.dumps({"format": "fiberplan-points", "version": 1, "angle_unit": "rad", "positioners": positioners}))
    (tmp_path / "s.json").write_text(json.dumps(scenario.to_dict()))
    code, out, _ = run_cli(["verify", "--paths", str(tmp_path / "pts.json"), "--scenario", str(tmp_path / "s.json"), "--motors"])
    assert code == 1 and "as executed with the ramps" in out


def test_the_planned_samples_count_what_they_break_under_the_ramps():
    """The fallback of a joint whose search runs out (:func:`fiberplan.profiles._sampled_fit`)."""
    from fiberplan.instrument import MotorLimits
    from fiberplan.profiles import _Corridor, _sampled_fit

    times = np.arange(8) * 0.05
    calm = np.array([0.0, 0.0, 0.02, 0.04, 0.04, 0.04, 0.04, 0.02])  # 0.4 rad/s, a stop of 0.15 s, then back at 0.4
    rash = np.array([0.0, 0.0, 0.02, 0.04, 0.04, 0.02, 0.0, 0.0])  # back after a stop of 0.05 s: 0.4 + 0.4 > the top 0.5

    def corridor(q, motors):
        return _Corridor(times, q, q - 1.0, q + 1.0, 1, len(q) - 1, 1, 0.5, motors, 0, 4)  # from the first move

    ramps = MotorLimits(ramp_time_s=0.1)
    durations, speeds, broken = _sampled_fit(corridor(calm, ramps))
    assert broken == 0 and np.allclose(durations, 0.05) and np.allclose(speeds[[0, 1, 5]], [0.4, 0.4, -0.4])
    assert _sampled_fit(corridor(rash, ramps))[2] == 1
    assert _sampled_fit(corridor(calm, MotorLimits(ramp_time_s=0.1, max_segments=2)))[2] == 1  # three segments, one too many
