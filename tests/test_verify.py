"""The independent verifier: finds collisions (also between samples), limit and speed violations."""

from __future__ import annotations

import numpy as np
import pytest

from fiberplan.generate import make_scenario
from fiberplan.instrument_io import load_instrument
from fiberplan.planners import plan
from fiberplan.scenario import TARGET_JOINTS, Scenario
from fiberplan.trajectory import Trajectory
from fiberplan.verify import verify


def _pair_scenario(start_deg, target_deg, instrument="desi"):
    inst = load_instrument(instrument)
    return Scenario(
        instrument=inst,
        ids=np.array([7, 8]),
        base_xy=np.array([[0.0, 0.0], [inst.pitch_mm, 0.0]]),
        orient_deg=np.zeros(2),
        start_deg=np.array(start_deg, dtype=float),
        target_kind=np.full(2, TARGET_JOINTS),
        target_values=np.array(target_deg, dtype=float),
        target_parity=np.zeros(2, dtype=int),
        instrument_preset=instrument,
    )


@pytest.mark.parametrize("instrument", ["desi", "moons-capsules", "sdss"])
def test_straight_moves_on_random_targets_collide(instrument):
    sc = make_scenario(instrument, 61, "random", 1)
    report = verify(sc, plan(sc, "straight").trajectory)
    assert report.n_collisions > 0 and not report.ok
    event = report.collisions[0]
    assert event.id_i in sc.ids and event.id_j in sc.ids
    assert event.min_distance_mm < event.required_mm
    assert 0.0 <= event.t_first_s <= event.t_worst_s


def test_the_report_does_not_depend_on_the_time_chunk(monkeypatch):
    # The default chunk shrinks on large fields (verify.CHUNK_PAIR_SAMPLES); whatever the chunk, the
    # same collisions, first and worst times, clearance and probes.
    import dataclasses
    import importlib

    verify_module = importlib.import_module("fiberplan.verify")
    sc = make_scenario("sdss", 61, "random", 1)
    collided = []
    for trajectory in (plan(sc, "straight").trajectory, plan(sc, "dnf").trajectory):
        reports = [verify(sc, trajectory, time_chunk=chunk) for chunk in (1, 3, 64)]
        monkeypatch.setattr(verify_module, "CHUNK_PAIR_SAMPLES", 2 * len(sc.pairs))  # the default: 2 samples at a time (one thread)
        reports.append(verify(sc, trajectory))
        monkeypatch.undo()
        first = dataclasses.asdict(reports[0])
        assert all(dataclasses.asdict(r) == first for r in reports[1:])
        assert reports[0].probes > 0
        collided.append(reports[0].n_collisions > 0)
    assert collided == [True, False]


@pytest.mark.parametrize("instrument", ["sdss", "moons"])
def test_the_report_and_clearances_do_not_depend_on_the_threads(monkeypatch, instrument):
    # Chunks of samples, and the pairs' intervals to bisect, are shared between threads
    # (verify.THREADS): the same report, bit for bit, and the same clearance table as on one thread.
    import dataclasses
    import importlib

    verify_module = importlib.import_module("fiberplan.verify")
    sc = make_scenario(instrument, 19, "random", 1)
    collided = []
    for trajectory in (plan(sc, "straight").trajectory, plan(sc, "dnf").trajectory):
        found = []
        for threads in (1, 3):
            monkeypatch.setattr(verify_module, "THREADS", threads)
            monkeypatch.setattr(verify_module, "_THREADED_INTERVALS", 0)  # split even a few intervals
            monkeypatch.setattr(verify_module, "THREADED_PAIR_SAMPLES", 0)  # and a small trajectory's chunks
            report, pairs, clear = verify_module.verify_with_clearances(sc, trajectory, time_chunk=5)
            found.append((dataclasses.asdict(report), pairs, clear))
        (first, pairs, clear), (again, pairs_again, clear_again) = found
        assert first == again and first["probes"] > 0
        assert np.array_equal(pairs, pairs_again) and np.array_equal(clear, clear_again)
        collided.append(bool(first["collisions"]))
    assert collided == [True, False]


def test_rigid_rotation_is_clear():
    # Every positioner turns alpha by the same angle with the same beta: the arms stay
    # translated copies of each other, so straight moves cannot collide.
    base = make_scenario("desi", 19, "random", 0)
    n = base.n_positioners
    sc = Scenario(
        instrument=base.instrument, ids=base.ids, base_xy=base.base_xy, orient_deg=np.zeros(n),
        start_deg=np.tile([-170.0, 60.0], (n, 1)), target_kind=np.full(n, TARGET_JOINTS),
        target_values=np.tile([170.0, 120.0], (n, 1)), target_parity=np.zeros(n, dtype=int), instrument_preset="desi",
    )
    report = verify(sc, plan(sc, "straight").trajectory)
    assert report.ok and report.n_collisions == 0
    assert report.min_clearance_mm > 0


def test_collision_between_samples_is_found():
    # Positioner 7 sweeps its fiber through (6, 0) where positioner 8's fiber waits at (4.4, 0);
    # the only two samples are clear, the motion between them is not.
    sc = _pair_scenario([[60.0, 0.0], [180.0, 0.0]], [[-60.0, 0.0], [180.0, 0.0]])
    traj = Trajectory(np.array([0.0, 1.0]), np.stack([sc.start, sc.target]))
    from fiberplan.geometry import min_pair_clearance

    assert (min_pair_clearance(sc.instrument, sc.base_xy, sc.orient, traj.joints, sc.pairs) > 0).all()
    report = verify(sc, traj)
    assert report.n_collisions == 1
    event = report.collisions[0]
    assert (event.id_i, event.id_j) == (7, 8)
    assert 0.0 < event.t_first_s < 1.0
    assert event.t_worst_s == pytest.approx(0.5, abs=0.05)
    assert event.min_distance_mm < 2.0


def test_near_miss_between_samples_is_not_a_collision():
    # Same sweep with positioner 8's fiber pulled back to (8.4, 0), 2 mm from its base: clearance 0.4 mm.
    from fiberplan.kinematics import inverse_kinematics

    inst = load_instrument("desi")
    q8 = np.degrees(inverse_kinematics(inst, np.array([[10.4, 0.0]]), np.zeros(1), np.array([[8.4, 0.0]]), np.array([1]))[0])
    sc = _pair_scenario([[60.0, 0.0], q8], [[-60.0, 0.0], q8])
    traj = Trajectory(np.array([0.0, 1.0]), np.stack([sc.start, sc.target]))
    report = verify(sc, traj)
    assert report.ok
    assert report.min_clearance_mm == pytest.approx(0.4, abs=0.05)


def test_hard_stop_speed_and_start_violations():
    sc = _pair_scenario([[0.0, 90.0], [180.0, 90.0]], [[0.0, 90.0], [180.0, 90.0]])
    joints = np.stack([sc.start, sc.start, sc.start])
    joints[1, 0, 1] = np.radians(185.0)  # beta beyond its 180 deg stop
    joints[2, 0, 1] = np.radians(90.0)
    joints[2, 1, 0] = np.radians(100.0)  # alpha: 80 deg in 0.01 s, far above 30 rpm
    report = verify(sc, Trajectory(np.array([0.0, 0.5, 0.51]), joints))
    kinds = {(v.positioner_id, v.joint, v.kind) for v in report.limit_violations}
    assert (7, "beta", "hard_stop") in kinds
    assert (8, "alpha", "speed") in kinds
    assert not report.ok
    moved = joints.copy()
    moved[:, 1, 0] = 0.0
    assert verify(sc, Trajectory(np.array([0.0, 0.5, 0.51]), moved)).start_mismatch_ids == [8]


def test_fraction_must_be_a_fraction(desi_random_61):
    with pytest.raises(ValueError, match="fraction"):
        verify(desi_random_61, plan(desi_random_61, "straight").trajectory, fraction=1.5)


def test_verifier_imports_no_planner():
    import ast
    import subprocess
    import sys
    from pathlib import Path

    import fiberplan.verify as verify_module  # noqa: F401  (the module, via sys.modules)

    source = Path(sys.modules["fiberplan.verify"].__file__).read_text()
    imported = {
        node.module for node in ast.walk(ast.parse(source)) if isinstance(node, ast.ImportFrom) and node.module
    } | {alias.name for node in ast.walk(ast.parse(source)) if isinstance(node, ast.Import) for alias in node.names}
    assert not any(name.startswith("fiberplan.planners") for name in imported)
    code = "import sys, fiberplan.verify; print(sorted(m for m in sys.modules if m.startswith('fiberplan.planners.')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"


@pytest.mark.parametrize("instrument", ["desi", "moons-capsules", "sdss"])
def test_pruning_keeps_every_sampled_collision(instrument):
    from fiberplan.geometry import min_pair_clearance

    sc = make_scenario(instrument, 37, "random", 4)
    traj = plan(sc, "straight").trajectory
    exact = min_pair_clearance(sc.instrument, sc.base_xy, sc.orient, traj.joints, sc.pairs)  # (T, P) at samples
    report = verify(sc, traj)
    sampled = {tuple(sc.ids[sc.pairs[p]]) for p in np.unique(np.nonzero(exact < 0)[1])}
    found = {(c.id_i, c.id_j) for c in report.collisions}
    assert sampled <= found
    assert report.min_clearance_mm <= exact.min() + 1e-12


def _one_joint(speeds_deg_s, dt=0.1):
    """A lone MOONS positioner whose alpha turns at the given speeds (deg/s), one command per interval."""
    sc = make_scenario("moons-capsules", 1, "unfold", 0)
    steps = np.radians(np.asarray(speeds_deg_s, dtype=float)) * dt
    joints = np.repeat(sc.start[None], len(steps) + 1, axis=0)
    joints[1:, 0, 0] += np.cumsum(steps)
    return sc, Trajectory(np.arange(len(steps) + 1) * dt, joints)


def test_motor_limits_are_reported_apart_worst_first():
    fast = 12.0  # deg/s: inside 4.38 (0.73 rpm) .. 16.68 (2.78 rpm)
    speeds = [0.0, fast, fast, 1.0, 0.5, fast, -fast, fast, fast * 1.3, 0.0]
    sc, traj = _one_joint(speeds)
    report = verify(sc, traj)
    assert report.ok and report.motors_checked and not report.motors_ok  # safety passes; motor limits do not
    kinds = {v.kind: v for v in report.motor_violations}
    assert set(kinds) == {"min_speed", "reversal", "speed_change"}
    assert kinds["min_speed"].value == pytest.approx(np.radians(0.5)) and kinds["min_speed"].t_first_s == pytest.approx(0.3)
    assert kinds["reversal"].t_first_s == pytest.approx(0.6)  # the command that turns back (and again at 0.7)
    assert kinds["reversal"].value == pytest.approx(np.radians(2 * fast))
    # changes: 12 -> 1 (-92 %, the first), 1 -> 0.5 (-50 %), 0.5 -> 12 (+2300 %, the worst); 12 -> 15.6 (+30 %) is allowed
    change = kinds["speed_change"]
    assert change.t_first_s == pytest.approx(0.3) and change.value == pytest.approx(23.0) and change.t_s == pytest.approx(0.5)


def test_motor_segment_count_and_unconstrained_instruments():
    sc, traj = _one_joint([5.0, 6.0, 7.0, 8.0] * 40)  # 160 segments of changing speed, > 128
    report = verify(sc, traj)
    assert [v.kind for v in report.motor_violations] == ["segments"] and report.motor_violations[0].value == 160
    desi = make_scenario("desi", 7, "random", 0)
    assert not verify(desi, plan(desi, "straight").trajectory).motors_checked  # DESI states no motor limits


def test_motor_table_is_read_strictly(tmp_path):
    from fiberplan.errors import InstrumentError
    from fiberplan.instrument_io import instrument_text

    text = instrument_text("moons-capsules")
    for bad, message in (("max_segments = 128", "max_segments must be an integer >= 1"),
                         ("stop_before_reversing = true", "stop_before_reversing must be true or false"),
                         ("max_speed_change = 0.4", "max_speed_change must be a number")):
        path = tmp_path / "m.toml"
        path.write_text(text.replace(bad, bad.split("=")[0] + '= "x"'))
        with pytest.raises(InstrumentError, match=message):
            load_instrument(path)


@pytest.mark.parametrize("instrument", ["desi", "moons", "sdss"])
def test_clearances_the_verifier_returns_are_exact_near_and_lower_bounds_far(instrument):
    """``verify_with_clearances``: the same report as ``verify``; each pair's clearance at each
    sample is the exact one where the verifier computed it, and never above the exact one."""
    from fiberplan.geometry import min_pair_clearance
    from fiberplan.verify import verify_with_clearances

    sc = make_scenario(instrument, 19, "random", 2)
    traj = plan(sc, "straight").trajectory
    report, pairs, clear = verify_with_clearances(sc, traj)
    assert report.to_dict() == verify(sc, traj).to_dict()
    np.testing.assert_array_equal(pairs, sc.pairs)
    exact = min_pair_clearance(sc.instrument, sc.base_xy, sc.orient, traj.joints, pairs)
    assert clear.shape == exact.shape
    assert np.all(clear <= exact + 1e-9)
    near = clear < 2.0
    assert near.any() and (~near).any()
    np.testing.assert_allclose(clear[near], exact[near], atol=1e-9)


def test_enclosing_disc_gap_equals_the_plain_reduction():
    """The verifier's lower bound, written one end point at a time, equals the plain numpy one."""
    from fiberplan.geometry import capsule_segments
    from fiberplan.verify import _enclosing_disc_gap

    for name in ("desi", "moons", "sdss"):
        sc = make_scenario(name, 37, "random", 1)
        joints = plan(sc, "straight").trajectory.joints[::7]
        radii = np.array([c.radius_mm for c in sc.instrument.capsules])
        start, end = capsule_segments(sc.instrument, sc.base_xy, sc.orient, joints)
        points = np.concatenate([start, end], axis=-2)
        centre = 0.5 * (points.min(axis=-2) + points.max(axis=-2))
        radius = (np.linalg.norm(points - centre[..., None, :], axis=-1) + np.concatenate([radii, radii])).max(axis=-1)
        a, b = sc.pairs[:, 0], sc.pairs[:, 1]
        plain = np.linalg.norm(centre[:, a] - centre[:, b], axis=-1) - radius[:, a] - radius[:, b]
        np.testing.assert_array_equal(_enclosing_disc_gap(sc.instrument, sc.base_xy, sc.orient, joints, sc.pairs, radii), plain)
