"""Motor profiles: fewest constant-speed segments within the motor limits, rebuilt, verified,
exported and read back identically; foreign paths verified; bad input refused by name."""

from __future__ import annotations

import csv
import itertools
import json
import math

import h5py
import numpy as np
import pytest

import fiberplan as fp
from fiberplan.errors import InstrumentError, ProfileError
from fiberplan.instrument import MotorLimits
from fiberplan.instrument_io import instrument_from_dict, instrument_text
from fiberplan.profile_io import read_paths, write_profiles
from fiberplan.profiles import _allowed_speeds, _fit_joint, discretise_trajectory, rebuild
from fiberplan.trajectory import Trajectory

MPC_OWN = {"motor_limits": False, "route_prioritized_up_to": 0, "route_retract_up_to": 0}
"""The mpc without its motor governor, on its own routes (not the prioritized schedule the layer
tries on groups this small, nor its partial retractions): stop-and-go samples that break the motor limits, for the
discretiser to mend."""


@pytest.fixture(scope="module")
def moons_run() -> fp.PlanResult:
    """MOONS (capsule model, motor limits stated) 19 unfold seed 1, planned by the mpc without its
    motor governor: samples that break the motor limits, for the discretiser to mend."""
    return fp.plan(fp.make_scenario("moons-capsules", 19, "unfold", 1), "mpc", MPC_OWN)


@pytest.fixture(scope="module")
def moons_profiles(moons_run):
    return fp.discretise(moons_run)


def test_profiles_are_verified_reach_the_same_ends_and_keep_the_makespan(moons_run, moons_profiles):
    report = moons_profiles.report
    assert report is not None and report.ok and report.n_collisions == 0
    rebuilt = moons_profiles.trajectory()
    np.testing.assert_array_equal(rebuilt.joints[0], moons_run.trajectory.joints[0])
    np.testing.assert_allclose(rebuilt.joints[-1], moons_run.trajectory.joints[-1], atol=1e-12)
    summary = moons_profiles.summary()
    assert summary["makespan_after_s"] <= summary["makespan_before_s"] + 1e-9
    assert fp.summarize(fp.PlanResult(moons_run.scenario, rebuilt, moons_run.outcome, "mpc", {}, {}, 0.0))["reached"] == 19


def test_profiles_respect_the_motor_limits_the_samples_break(moons_run, moons_profiles):
    """The planned samples break MOONS' motor limits; the profiles of this run do not."""
    source = fp.verify(moons_run.scenario, moons_run.trajectory)
    assert source.motors_checked and len(source.motor_violations) > 0
    assert moons_profiles.report.motor_violations == []
    motors = moons_run.scenario.instrument.motors
    for (_, axis), prof in moons_profiles.joints.items():
        speeds = prof.speeds_rad_s
        moving = speeds[speeds != 0]
        assert np.all(np.abs(moving) >= motors.min_speed_rad_s[axis] * (1 - 1e-9))
        assert len(speeds) <= motors.max_segments
        for a, b in itertools.pairwise(speeds):
            if a != 0 and b != 0:
                assert a * b > 0, "reversal without a stop"
                assert abs(b - a) <= motors.max_speed_change * abs(a) * (1 + 1e-9)


def test_fewer_segments_than_samples(moons_run, moons_profiles):
    counts = moons_profiles.segment_counts()
    samples = len(moons_run.trajectory.times)
    assert counts.max() < samples / 4
    assert np.median(counts[counts > 0]) <= 3


@pytest.mark.parametrize("form,name", [("json", "p.json"), ("csv", "p.csv"), ("points", "pts.json"), ("h5", "p.h5")])
def test_every_export_form_rebuilds_the_same_trajectory(moons_run, moons_profiles, tmp_path, form, name):
    path = write_profiles(moons_profiles, moons_run, tmp_path / name, form)
    scenario, trajectory, found = read_paths(path, moons_run.scenario if form == "csv" else None)
    reference = moons_profiles.trajectory()
    assert found == form
    assert scenario.n_positioners == 19
    np.testing.assert_array_equal(trajectory.times, reference.times)
    np.testing.assert_array_equal(trajectory.joints, reference.joints)


def test_points_in_degrees_read_as_radians(moons_run, moons_profiles, tmp_path):
    path = write_profiles(moons_profiles, moons_run, tmp_path / "pts.json", "points")
    data = json.loads(path.read_text())
    data["angle_unit"] = "deg"
    for entry in data["positioners"]:
        for joint in ("alpha", "beta"):
            if joint in entry:
                entry[joint] = [[t, math.degrees(q)] for t, q in entry[joint]]
    (tmp_path / "deg.json").write_text(json.dumps(data))
    _, trajectory, _ = read_paths(tmp_path / "deg.json")
    np.testing.assert_allclose(trajectory.joints, moons_profiles.trajectory().joints, atol=1e-12)


def test_an_unverified_trajectory_is_refused(moons_run):
    scenario = moons_run.scenario
    straight = fp.plan(scenario, "straight")
    if fp.verify(scenario, straight.trajectory).ok:
        pytest.skip("the straight plan happens to be clean")
    with pytest.raises(ProfileError, match="verified trajectory"):
        fp.discretise(straight)


def test_fit_joint_holds_or_moves_within_the_speed_range_and_the_corridor():
    """A slow creep (below the minimum speed) in a corridor: holds and moves at allowed speeds only."""
    times = np.arange(0, 4.0001, 0.05)
    q = np.concatenate([np.linspace(0.0, 0.1, 41), np.linspace(0.1, 0.5, 40)[1:], [0.5]])[: len(times)]
    band = np.full(len(times), 0.02)
    motors = MotorLimits(min_speed_rad_s=(0.1, 0.1), max_speed_change=0.4, stop_before_reversing=True)
    prof, relaxed = _fit_joint(times, q, band, (-1.0, 1.0), 0.6, motors, 0, 1)
    assert relaxed == 0
    t_knot, q_knot = prof.knots()
    assert q_knot[-1] == pytest.approx(q[-1], abs=1e-12)
    moving = prof.speeds_rad_s[prof.speeds_rad_s != 0]
    assert np.all((np.abs(moving) >= 0.1 - 1e-12) & (np.abs(moving) <= 0.6 + 1e-12))
    path = np.interp(times, t_knot, q_knot, left=q[0], right=q[-1])
    assert np.max(np.abs(path - q)) <= 0.02 + 1e-9
    assert len(prof.durations_s) < 10


def test_allowed_speeds_after_a_move():
    motors = MotorLimits(min_speed_rad_s=(0.1, 0.2), max_speed_change=0.4, stop_before_reversing=True)
    assert _allowed_speeds(0.0, 1.0, motors, 1) == [(0.0, 0.0), (0.2, 1.0), (-1.0, -0.2)]
    allowed = _allowed_speeds(0.5, 1.0, motors, 0)
    assert allowed[0] == (0.0, 0.0) and len(allowed) == 2
    assert allowed[1] == pytest.approx((0.3, 0.7))


def test_rebuild_holds_before_and_after_the_points(desi_random_61):
    knots = {(0, 0): (np.array([0.5, 1.0]), np.array([0.2, 0.4]))}
    trajectory = rebuild(desi_random_61, knots)
    assert trajectory.times[0] == 0.0 and trajectory.times[-1] == pytest.approx(1.0)
    assert np.all(np.diff(trajectory.times) <= 0.05 + 1e-12)
    assert trajectory.at(0.25)[0, 0] == pytest.approx(0.2)
    assert trajectory.at(0.75)[0, 0] == pytest.approx(0.3)
    np.testing.assert_array_equal(trajectory.joints[:, 1:], np.repeat(desi_random_61.start[None, 1:], len(trajectory.times), axis=0))


def test_command_period_must_divide_into_samples(moons_run):
    spec = json.loads(json.dumps(moons_run.scenario.instrument.to_dict()))
    spec["motors"]["command_period_s"] = 0.07
    inst = instrument_from_dict(spec, origin="test")
    assert inst.motors.command_period_s == pytest.approx(0.07)
    with pytest.raises(ProfileError, match="command period 0.07 s is not a multiple"):
        discretise_trajectory(moons_run.scenario, moons_run.trajectory, instrument=inst)
    spec["motors"]["command_period_s"] = 0.1
    made = discretise_trajectory(moons_run.scenario, moons_run.trajectory, instrument=instrument_from_dict(spec, origin="test"))
    assert made.report.ok
    for prof in made.joints.values():
        ratio = prof.durations_s / 0.1
        assert np.allclose(ratio, np.round(ratio), atol=1e-6)


def test_motor_keys_are_validated():
    import tomllib

    spec = tomllib.loads(instrument_text("moons-capsules"))
    spec["motors"]["command_period_s"] = "0.1"
    with pytest.raises(InstrumentError, match="command_period_s must be a number"):
        instrument_from_dict(spec, origin="x")
    spec["motors"]["command_period_s"] = 0.1
    spec["motors"]["max_speed_change"] = 1.5
    with pytest.raises(InstrumentError, match="max_speed_change must lie in"):
        instrument_from_dict(spec, origin="x")


def test_csv_errors_name_the_row(moons_run, moons_profiles, tmp_path):
    path = write_profiles(moons_profiles, moons_run, tmp_path / "p.csv", "csv")
    rows = list(csv.reader(path.open()))
    rows[3][4] = "fast"
    bad = tmp_path / "bad.csv"
    with bad.open("w", newline="") as handle:
        csv.writer(handle).writerows(rows)
    with pytest.raises(ProfileError, match="row 4, column duration_s: expected a number, found 'fast'"):
        read_paths(bad, moons_run.scenario)
    rows = list(csv.reader(path.open()))
    rows[2][0] = "999"
    with bad.open("w", newline="") as handle:
        csv.writer(handle).writerows(rows)
    with pytest.raises(ProfileError, match="row 3: positioner 999 is not in the scenario"):
        read_paths(bad, moons_run.scenario)
    with pytest.raises(ProfileError, match="holds no scenario"):
        read_paths(path)


def test_json_errors_name_the_entry(moons_run, moons_profiles, tmp_path):
    path = write_profiles(moons_profiles, moons_run, tmp_path / "p.json", "json")
    data = json.loads(path.read_text())
    data["profiles"][1]["joint"] = "gamma"
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(ProfileError, match=r"profiles\[1\]: joint must be 'alpha' or 'beta'"):
        read_paths(tmp_path / "bad.json")
    (tmp_path / "other.json").write_text(json.dumps({"format": "something"}))
    with pytest.raises(ProfileError, match="not a fiberplan profiles or points file"):
        read_paths(tmp_path / "other.json")


def test_cli_profiles_then_verify(moons_run, tmp_path, run_cli):
    run = tmp_path / "m.h5"
    fp.save_result(moons_run, run)
    code, out, _ = run_cli(["profiles", str(run), "--out", str(tmp_path / "p.h5"), "--json"])
    assert code == 0
    summary = json.loads(out)
    assert summary["verified_ok"] is True and summary["format"] == "h5" and summary["motor_violations"] == 0
    code, out, _ = run_cli(["verify", str(tmp_path / "p.h5"), "--json", "--motors"])
    assert code == 0
    report = json.loads(out)
    assert report["verified_ok"] and report["collisions"] == 0 and report["report"]["motor_violations"] == []
    assert report["reached"] == 19


def test_cli_verify_reads_foreign_paths(moons_run, moons_profiles, tmp_path, run_cli):
    write_profiles(moons_profiles, moons_run, tmp_path / "p.csv", "csv")
    (tmp_path / "s.json").write_text(json.dumps(moons_run.scenario.to_dict()))
    code, out, _ = run_cli(["verify", "--paths", str(tmp_path / "p.csv"), "--scenario", str(tmp_path / "s.json"), "--json"])
    assert code == 0 and json.loads(out)["verified_ok"] is True
    code, _, err = run_cli(["verify", "--paths", str(tmp_path / "p.csv")])
    assert code == 2 and "holds no scenario" in err and "Traceback" not in err
    code, _, err = run_cli(["verify"])
    assert code == 2 and "give a trajectory FILE, or --paths" in err


def test_cli_verify_catches_colliding_foreign_paths(moons_run, tmp_path, run_cli):
    """Time-stamped points that drive two positioners straight to their targets collide: exit 1."""
    scenario = moons_run.scenario
    straight = fp.plan(scenario, "straight")
    report = fp.verify(scenario, straight.trajectory)
    if report.ok:
        pytest.skip("the straight plan happens to be clean")
    positioners = []
    for i, ident in enumerate(scenario.ids.tolist()):
        entry = {"id": ident}
        for axis, joint in enumerate(("alpha", "beta")):
            entry[joint] = [[float(t), float(q)] for t, q in zip(straight.trajectory.times, straight.trajectory.joints[:, i, axis], strict=True)]
        positioners.append(entry)
    (tmp_path / "pts.json").write_text(json.dumps({"format": "fiberplan-points", "version": 1, "angle_unit": "rad", "positioners": positioners}))
    (tmp_path / "s.json").write_text(json.dumps(scenario.to_dict()))
    code, out, _ = run_cli(["verify", "--paths", str(tmp_path / "pts.json"), "--scenario", str(tmp_path / "s.json")])
    assert code == 1 and "collision: positioners" in out


def test_tampered_profiles_group_is_a_file_inconsistency(moons_run, moons_profiles, tmp_path, run_cli):
    path = write_profiles(moons_profiles, moons_run, tmp_path / "p.h5", "h5")
    with h5py.File(path, "r+") as f:
        f["profiles/speed_rad_s"][0] = f["profiles/speed_rad_s"][0] * 1.01
    code, out, _ = run_cli(["verify", str(path)])
    assert code == 1 and "/profiles does not rebuild /trajectory exactly" in out


def test_cli_refuses_an_unknown_extension_before_work(moons_run, tmp_path, run_cli):
    run = tmp_path / "m.h5"
    fp.save_result(moons_run, run)
    code, _, err = run_cli(["profiles", str(run), "--out", str(tmp_path / "p.txt")])
    assert code == 2 and "cannot tell the format" in err
    assert not (tmp_path / "p.txt").exists()


def test_show_profiles_draws_a_picture_and_refuses_unknown_ids(moons_run, tmp_path, run_cli):
    run = tmp_path / "m.h5"
    fp.save_result(moons_run, run)
    ident = int(moons_run.scenario.ids[3])
    code, out, _ = run_cli(["show", str(run), "--profiles", f"{ident},0", "--out", str(tmp_path / "p.png")])
    assert code == 0 and "profiles verified: True" in out
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    code, _, err = run_cli(["show", str(run), "--profiles", "999", "--out", str(tmp_path / "q.png")])
    assert code == 2 and "positioner(s) [999] not in" in err
    assert not (tmp_path / "q.png").exists()


def test_profiles_the_verifier_refuses_are_fitted_again_then_follow_their_samples(desi_random_61, monkeypatch):
    """With the room ignored (corridors only bounded by the hard stops), the first profiles cut
    corners through neighbours; the verifier's objections narrow them, then make those
    positioners follow their planned samples: what is returned is verified all the same."""
    from fiberplan import profiles as module

    # The plan without the QP screening: its motion has neighbours close enough for unbounded
    # corridors to cut through (the screened plan of this scenario happens to have none).
    run = fp.plan(desi_random_61, "mpc", {"qp_screen_mm": None})
    unbounded = lambda self, i, *rest: np.full(self.near_t.shape[1], np.inf)  # noqa: E731
    monkeypatch.setattr(module._Room, "half", unbounded)
    monkeypatch.setattr(module._Room, "left", unbounded)
    monkeypatch.setattr(module._Room, "half_bound", lambda self: np.full((self.near_t.shape[1], len(self.still)), np.inf))
    monkeypatch.setattr(module._Room, "half_of", lambda self, idx: np.full((self.near_t.shape[1], len(idx)), np.inf))
    made = fp.discretise(run)
    summary = made.summary()
    assert made.report.ok and made.report.n_collisions == 0
    assert summary["refit_rounds"] >= 1
    assert summary["followed_samples"], "expected positioners to fall back to their planned samples"


def test_verifier_counts_start_stop_cycles(moons_run):
    """Reference 003's nSSC: a joint that starts from rest three times breaks max_start_stops = 2."""
    spec = json.loads(json.dumps(moons_run.scenario.instrument.to_dict()))
    spec["motors"]["max_start_stops"] = 2
    inst = instrument_from_dict(spec, origin="test")
    scenario = moons_run.scenario
    times = np.arange(0, 3.0001, 0.05)
    joints = np.repeat(scenario.start[None], len(times), axis=0)
    ident = int(scenario.ids[0])
    speed = 0.2
    moves = (times > 0.2) & (times <= 0.5) | (times > 1.0) & (times <= 1.3) | (times > 2.0) & (times <= 2.3)
    joints[:, 0, 0] = scenario.start[0, 0] + np.concatenate([[0.0], np.cumsum(np.where(moves[1:], speed * 0.05, 0.0))])
    report = fp.verify(scenario, Trajectory(times, joints), instrument=inst)
    found = [v for v in report.motor_violations if v.kind == "start_stops"]
    assert [(v.positioner_id, v.joint, int(v.value), int(v.limit)) for v in found] == [(ident, "alpha", 3, 2)]
    assert found[0].t_first_s == pytest.approx(2.0)
    spec["motors"]["max_start_stops"] = 0
    with pytest.raises(InstrumentError, match="max_start_stops must be an integer >= 1"):
        instrument_from_dict(spec, origin="test")


@pytest.mark.parametrize("instrument, kind, planner", [("desi", "random", "mpc"), ("moons-capsules", "unfold", "mpc"), ("desi", "random", "dnf")])
def test_the_one_segment_shortcuts_give_the_searchs_profiles(instrument, kind, planner, monkeypatch):
    """Joints fitted by the one-segment shortcuts (all positioners at once, then joint by joint)
    get exactly the profiles the search would give them (and the pass does fit some, so this
    compares something)."""
    import fiberplan.profiles as profiles_module

    result = fp.plan(fp.make_scenario(instrument, 61, kind, 3), planner)
    fitted = []
    original = profiles_module._Fitter._straight_pass

    def counted(self):
        done = original(self)
        fitted.append(int(done.sum()))
        return done

    monkeypatch.setattr(profiles_module._Fitter, "_straight_pass", counted)
    fast = fp.discretise(result)
    monkeypatch.setattr(profiles_module, "ONE_SEGMENT_SHORTCUTS", False)
    searched = fp.discretise(result)
    assert fitted and fitted[0] > 0
    assert fast.joints.keys() == searched.joints.keys()
    for key, prof in searched.joints.items():
        other = fast.joints[key]
        assert (other.start_s, other.start_rad) == (prof.start_s, prof.start_rad), key
        np.testing.assert_array_equal(other.durations_s, prof.durations_s)
        np.testing.assert_array_equal(other.speeds_rad_s, prof.speeds_rad_s)
    np.testing.assert_array_equal(fast.trajectory().joints, searched.trajectory().joints)


def test_wider_corridors_are_tried_where_the_pauses_leave_motor_violations(monkeypatch):
    """A stop-and-go plan (the dnf's, MOONS 61 unfold seed 16) whose profiles in half of each
    pair's clearance keep motor-limit violations after the pauses (joints with more than 128
    moving segments): the fit is made again in wider shares of the clearances, the verified
    profiles with the fewest violations are kept, and they are the ones that share gives alone.
    (Without the other two menders, which leave nothing to widen for on this plan: tested below.)"""
    import fiberplan.profiles as profiles_module

    monkeypatch.setattr(profiles_module, "STRETCH_PAUSES", False)
    monkeypatch.setattr(profiles_module, "DECHATTER", False)
    run = fp.plan(fp.make_scenario("moons", 61, "unfold", 16), "dnf")
    kept = fp.discretise(run)
    monkeypatch.setattr(profiles_module, "WIDER_FRACTIONS", ())
    narrow = fp.discretise(run)
    alone = fp.discretise(run, fraction=kept.stats["fraction"])
    assert narrow.stats["fractions_tried"] == [profiles_module.DEFAULT_FRACTION]
    assert len(narrow.report.motor_violations) > 0  # the case this test is about
    assert kept.report.ok and kept.stats["fractions_tried"][0] == profiles_module.DEFAULT_FRACTION
    assert kept.stats["fraction"] in kept.stats["fractions_tried"][1:]
    assert len(kept.report.motor_violations) < len(narrow.report.motor_violations)
    assert kept.joints.keys() == alone.joints.keys()
    for key, prof in alone.joints.items():
        np.testing.assert_array_equal(kept.joints[key].durations_s, prof.durations_s)
        np.testing.assert_array_equal(kept.joints[key].speeds_rad_s, prof.speeds_rad_s)


def test_a_zigzag_becomes_its_midline_and_a_steady_motion_is_unchanged():
    """:func:`_dechattered` smooths the samples where a joint turns back (and their neighbours)
    with ``(1, 2, 1) / 4``: a chatter at the sample step becomes its midline, a ramp and a hold
    stay as they are, the first and last samples never move, a kept positioner keeps its samples."""
    from fiberplan.profiles import _dechattered

    ramp = np.linspace(0.0, 1.0, 12)
    zigzag = np.concatenate([np.zeros(3), 0.1 * (np.arange(6) % 2), [0.05, 0.05, 0.05]])
    joints = np.stack([np.stack([ramp, zigzag], axis=1), np.stack([zigzag, ramp], axis=1)], axis=1)  # (12, 2 positioners, 2)
    out = _dechattered(joints, set())
    np.testing.assert_array_equal(out[:, 0, 0], ramp)
    np.testing.assert_array_equal(out[[0, -1]], joints[[0, -1]])
    np.testing.assert_allclose(out[4:8, 0, 1], 0.05)  # the inner zigzag samples: its midline
    assert np.max(np.abs(np.diff(out, axis=0))) <= np.max(np.abs(np.diff(joints, axis=0)))
    np.testing.assert_array_equal(_dechattered(joints, {1})[:, 1], joints[:, 1])


def test_a_stop_and_go_plan_is_fitted_from_its_smoothed_samples(monkeypatch):
    """The dnf's plan of MOONS 61 unfold seed 16 chatters at the sample step where positioners
    wait on each other; fitted as planned, its profiles need 118 pauses (+28 % of makespan). The
    fit from its smoothed samples (verified first, with their own clearances) needs few, and is
    kept: no motor-limit violation, a makespan within 5 % of the plan's, fewer segments. (A plan
    that chatters is fitted from its smoothed samples first; one that does not, as planned first.)"""
    import fiberplan.profiles as profiles_module

    run = fp.plan(fp.make_scenario("moons", 61, "unfold", 16), "dnf")
    smoothed = fp.discretise(run)
    monkeypatch.setattr(profiles_module, "DECHATTER", False)
    planned = fp.discretise(run)
    assert planned.stats["makespan_after_s"] > 1.05 * planned.stats["makespan_before_s"]  # the case this test is about
    assert smoothed.report.ok and smoothed.report.motor_violations == []
    assert profiles_module._turn_share(run.trajectory.joints) >= profiles_module.CHATTER_SHARE  # it chatters: smoothed first,
    assert smoothed.stats["sources_tried"] == ["dechattered"] and smoothed.stats["source"] == "dechattered"  # and that is enough
    assert smoothed.stats["dechattered_samples"] > 0
    assert smoothed.stats["makespan_before_s"] == planned.stats["makespan_before_s"]
    assert smoothed.stats["makespan_after_s"] <= 1.05 * smoothed.stats["makespan_before_s"]
    assert smoothed.stats["pauses"] < planned.stats["pauses"]
    assert smoothed.segment_counts().sum() < planned.segment_counts().sum()
    end = smoothed.trajectory().joints[-1]
    np.testing.assert_allclose(end, run.trajectory.joints[-1], atol=1e-12)  # every joint ends at its planned final angle


def test_pauses_and_mended_creeps_leave_no_motor_violation(monkeypatch):
    """Where the fitted profiles still creep below the minimum speed, the joint moves at the
    minimum and waits (never farther from its profile than the creep's angle); where they
    reverse without a stop or jump in speed, everyone holds still for one sample step: no motor
    violation is left on this run, and the rest of the motion is the same, retimed (each joint's
    angle at a paused instant is its angle at the mapped instant before). Joints running through
    the pauses inside their segments (:data:`STRETCH_PAUSES`) are tested below."""
    import fiberplan.profiles as profiles_module

    run = fp.plan(fp.make_scenario("moons-capsules", 19, "unfold", 3), "mpc", MPC_OWN)
    motors = run.scenario.instrument.motors
    plain = fp.discretise(run, pauses=False)
    monkeypatch.setattr(profiles_module, "STRETCH_PAUSES", False)
    monkeypatch.setattr(profiles_module, "DECHATTER", False)
    paused = fp.discretise(run)
    assert paused.stats["pauses_run_through"] == 0
    assert {"reversal", "speed_change", "min_speed"} <= {v.kind for v in plain.report.motor_violations}  # the case this test is about
    assert paused.report.ok and paused.report.motors_checked and paused.report.motor_violations == []
    assert paused.stats["fractions_tried"] == [profiles_module.DEFAULT_FRACTION]  # nothing left to widen for
    mended, n_mended = profiles_module._mend_creeps(plain.joints, motors)
    stats = paused.stats
    assert stats["creeps_mended"] == n_mended > 0
    pause_times = profiles_module._pause_times(mended, motors)
    assert stats["pauses"] == len(pause_times) > 0
    step = float(np.median(np.diff(run.trajectory.times)))
    assert stats["pause_s"] == pytest.approx(step * len(pause_times))
    assert stats["makespan_after_s"] <= stats["makespan_before_s"] + stats["pause_s"] + 1e-6

    tau = np.linspace(0.0, stats["makespan_after_s"], 4001)
    creep = max(float(np.max(np.abs(p.speeds_rad_s * p.durations_s)[(p.speeds_rad_s != 0) & (np.abs(p.speeds_rad_s) < motors.min_speed_rad_s[axis])],
                             initial=0.0)) for (_, axis), p in plain.joints.items())
    for key, prof in mended.items():  # a mended creep stays within its own angle of the profile
        assert np.max(np.abs(np.interp(tau, *prof.knots()) - np.interp(tau, *plain.joints[key].knots()))) <= creep + 1e-12

    def mapped(tau: np.ndarray) -> np.ndarray:  # paused time -> time before pausing
        sigma = tau.copy()
        for k, t in enumerate(pause_times):
            begin = t + k * step  # the k-th pause starts here on the paused clock
            sigma = np.where(tau >= begin + step, sigma - step, np.where(tau > begin, sigma - (tau - begin), sigma))
        return sigma

    for key, prof in paused.joints.items():
        t_new, q_new = prof.knots()
        t_old, q_old = mended[key].knots()
        np.testing.assert_allclose(np.interp(tau, t_new, q_new), np.interp(mapped(tau), t_old, q_old), atol=1e-9, err_msg=str(key))


def test_joints_run_through_the_pauses_where_the_motors_allow(monkeypatch):
    """A joint moving through a pause need not stop with everyone: running the piece between two
    holds a little slower over the paused span (or at the minimum speed, arriving early and
    waiting) keeps every motor limit and leaves it at the same angle as the paused profiles at
    each of its breakpoints (held instants and segment ends), with fewer segments and the same
    makespan; the result is verified like any other."""
    import fiberplan.profiles as profiles_module

    run = fp.plan(fp.make_scenario("moons-capsules", 19, "unfold", 3), "mpc", MPC_OWN)
    motors = run.scenario.instrument.motors
    monkeypatch.setattr(profiles_module, "DECHATTER", False)
    through = fp.discretise(run)
    monkeypatch.setattr(profiles_module, "STRETCH_PAUSES", False)
    paused = fp.discretise(run)
    assert through.report.ok and through.report.motor_violations == [] and paused.report.motor_violations == []
    assert through.stats["pauses"] == paused.stats["pauses"] > 0
    assert through.stats["pauses_run_through"] > 0
    assert through.segment_counts().sum() < paused.segment_counts().sum()
    assert through.stats["makespan_after_s"] == paused.stats["makespan_after_s"]
    step = paused.stats["pause_s"] / paused.stats["pauses"]
    changed = 0
    for key, prof in through.joints.items():
        t, q = prof.knots()
        t_paused, q_paused = paused.joints[key].knots()
        # The same angle at each breakpoint, but where the joint arrived early and waits: there, at the hold's end.
        early = np.zeros(len(t), dtype=bool)
        early[1:-1] = (prof.speeds_rad_s[1:] == 0.0) & (prof.speeds_rad_s[:-1] != 0.0)
        at = np.where(early, np.roll(t, -1), t)
        np.testing.assert_allclose(np.interp(at, t_paused, q_paused), q, atol=1e-9, err_msg=str(key))
        moving = prof.speeds_rad_s[prof.speeds_rad_s != 0.0]
        assert np.all(np.abs(moving) >= motors.min_speed_rad_s[key[1]] * (1 - 1e-9))  # the verifier's tolerance
        tau = np.linspace(t[0], t[-1], 2001)
        gap = np.max(np.abs(np.interp(tau, t, q) - np.interp(tau, t_paused, q_paused)))
        assert gap <= step * paused.stats["pauses"] * np.max(np.abs(paused.joints[key].speeds_rad_s)) + 1e-9
        changed += len(prof.durations_s) < len(paused.joints[key].durations_s)
    assert changed > 0


def test_cli_no_pauses_leaves_the_violations_reported(tmp_path, run_cli):
    """``--no-pauses`` is honoured: the same run exported with the violations the fit left, reported."""
    run = tmp_path / "m.h5"
    fp.save_result(fp.plan(fp.make_scenario("moons-capsules", 19, "unfold", 3), "mpc", MPC_OWN), run)
    results = {}
    for flag in ("--pauses", "--no-pauses"):
        code, out, _ = run_cli(["profiles", str(run), "--out", str(tmp_path / f"p{flag}.json"), "--json", flag])
        assert code == 0
        results[flag] = json.loads(out)
    assert results["--pauses"]["pauses"] > 0 and results["--pauses"]["motor_violations"] == 0
    assert results["--no-pauses"]["pauses"] == 0 and results["--no-pauses"]["creeps_mended"] == 0
    assert results["--no-pauses"]["motor_violations"] > 0
    assert results["--no-pauses"]["makespan_after_s"] < results["--pauses"]["makespan_after_s"]


def test_knots_of_one_segment_are_the_sums():
    """The one-segment shortcut of ``JointProfile.knots`` gives the running sums' values, bit for bit."""
    from fiberplan.profiles import JointProfile

    rng = np.random.default_rng(5)
    for _ in range(500):
        n = int(rng.integers(1, 3))
        prof = JointProfile(float(rng.uniform(-1, 10)), float(rng.uniform(-3, 3)), rng.uniform(0.01, 5, n), rng.uniform(-0.3, 0.3, n))
        times, angles = prof.knots()
        np.testing.assert_array_equal(times, prof.start_s + np.concatenate([[0.0], np.cumsum(prof.durations_s)]))
        np.testing.assert_array_equal(angles, prof.start_rad + np.concatenate([[0.0], np.cumsum(prof.speeds_rad_s * prof.durations_s)]))
        assert not times.flags.writeable


def test_each_samples_room_is_the_least_clearance_of_it_and_its_neighbours():
    """:func:`_near`, in blocks and in place on a pair-major table (as the verifier stores it),
    gives each sample the least of its own and its two neighbours' clearances, floored at zero;
    a table in another layout is left as it was."""
    from fiberplan.profiles import _NEAR_ROWS, _near

    rng = np.random.default_rng(3)
    clear = np.asfortranarray(rng.uniform(-0.5, 5.0, (40, 2 * _NEAR_ROWS + 7)))  # (T, P), pairs in three blocks
    padded = np.pad(clear, ((1, 1), (0, 0)), mode="edge")
    expected = np.maximum(np.minimum(np.minimum(padded[:-2], padded[1:-1]), padded[2:]), 0.0)
    c_ordered = np.ascontiguousarray(clear)
    kept = c_ordered.copy()
    assert _near(clear) is clear
    np.testing.assert_array_equal(clear, expected)
    np.testing.assert_array_equal(_near(c_ordered), expected)
    np.testing.assert_array_equal(c_ordered, kept)


def test_the_search_split_with_a_forked_process_gives_the_same_profiles(desi_random_61, monkeypatch):
    """Half of the positioners to search fitted in a forked process (from FORK_SEARCH of them on):
    the same profiles, deviations and counts as one process, bit for bit."""
    from fiberplan import _fork
    from fiberplan import profiles as module

    if not _fork.can_fork():
        pytest.skip("fork is not available here (one core, no fork start method, or a daemonic process)")
    run = fp.plan(desi_random_61, "dnf")
    calls = []
    real_both = _fork.both
    monkeypatch.setattr(_fork, "both", lambda first, second: calls.append(1) or real_both(first, second))
    monkeypatch.setattr(module, "FORK_SEARCH", 2)
    forked = fp.discretise(run)
    monkeypatch.setattr(module, "FORK_SEARCH", 10**9)
    alone = fp.discretise(run)
    assert calls, "the search was not split"
    assert forked.joints.keys() == alone.joints.keys()
    for key, prof in alone.joints.items():
        np.testing.assert_array_equal(forked.joints[key].durations_s, prof.durations_s)
        np.testing.assert_array_equal(forked.joints[key].speeds_rad_s, prof.speeds_rad_s)
        assert (forked.joints[key].start_s, forked.joints[key].start_rad) == (prof.start_s, prof.start_rad)
    assert forked.stats["relaxed_segments"] == alone.stats["relaxed_segments"]


def _shuffling_run() -> tuple[fp.Scenario, Trajectory]:
    """MOONS (capsules) 7 from the datum: positioner 0 turns alpha about 0.4 rad in 240 s,
    shuffling back and forth on the way (20 steps of +0.01 rad, then 19 of about -0.0104, every
    0.05 s: about 250 moving runs, within the top speed and above the minimum), the others
    still. Folded, it stays in its own patrol disc: collision-free."""
    scenario = fp.make_scenario("moons-capsules", 7, "unfold", 0)
    k = 4800
    steps = np.resize(np.concatenate([np.full(20, 0.01), np.full(19, -0.01 * 19.7 / 19)]), k)
    joints = np.repeat(scenario.start[None], k + 1, axis=0)
    joints[1:, 0, 0] += np.cumsum(steps)
    return scenario, Trajectory(np.arange(k + 1) * 0.05, joints)


def test_back_and_forth_beyond_the_segment_limit_is_cut_short(monkeypatch):
    """A joint that shuffles more often than the motors' 128 segments allow: the shortcut (a
    straight move where every pair stays clear) leaves none of the motor limits broken, and the
    export is verified; without it the segment limit is broken."""
    from fiberplan import profiles

    scenario, traj = _shuffling_run()
    assert fp.verify(scenario, traj).ok
    monkeypatch.setattr(profiles, "SHORTCUT", False)
    plain = discretise_trajectory(scenario, traj)
    assert plain.report.ok and any(v.kind == "segments" and v.positioner_id == int(scenario.ids[0]) for v in plain.report.motor_violations)
    monkeypatch.setattr(profiles, "SHORTCUT", True)
    cut = discretise_trajectory(scenario, traj)
    assert cut.report.ok and cut.report.motor_violations == [] and cut.stats["source"] == "shortcut" and cut.stats["shortcut_samples"] > 0
    np.testing.assert_allclose(cut.trajectory().joints[-1], traj.joints[-1], atol=1e-9)
    assert len(cut.joints[(int(scenario.ids[0]), 0)].durations_s) <= 128
