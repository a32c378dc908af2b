"""Trajectory files: round trip, plain-h5py readability, truncation and atomic writes."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from fiberplan.errors import TrajectoryFileError
from fiberplan.planners import plan
from fiberplan.trajectory import PlanResult, Trajectory, load_result, save_result


@pytest.fixture(scope="module")
def straight_result(desi_random_61):
    return plan(desi_random_61, "straight")


def test_round_trip(tmp_path, straight_result):
    path = save_result(straight_result, tmp_path / "r.h5")
    back = load_result(path)
    assert np.array_equal(back.trajectory.times, straight_result.trajectory.times)
    assert np.array_equal(back.trajectory.joints, straight_result.trajectory.joints)
    assert np.array_equal(back.outcome, straight_result.outcome)
    assert back.planner == "straight" and back.settings == straight_result.settings
    assert back.stats == straight_result.stats
    assert back.plan_wall_s == straight_result.plan_wall_s
    assert np.array_equal(back.scenario.target, straight_result.scenario.target)


def test_readable_without_fiberplan(tmp_path, straight_result):
    path = save_result(straight_result, tmp_path / "r.h5")
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "fiberplan-trajectory"
        joints = f["trajectory/joints_rad"][...]
        times = f["trajectory/time_s"][...]
        ids = f["positioners/id"][...]
        status = [s.decode() for s in f["outcome/status"][...]]
    assert joints.shape == (len(times), len(ids), 2)
    assert set(status) <= {"reached", "deadlocked", "unfinished", "held"}


def test_truncated_file_is_rejected(tmp_path, straight_result):
    path = save_result(straight_result, tmp_path / "r.h5")
    data = path.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 3])
    with pytest.raises(TrajectoryFileError, match="truncated"):
        load_result(cut)


def test_foreign_files_are_rejected(tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = np.arange(3)
    with pytest.raises(TrajectoryFileError, match="not a fiberplan trajectory file"):
        load_result(other)
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(TrajectoryFileError, match="cannot read"):
        load_result(text)
    with pytest.raises(TrajectoryFileError, match="does not exist"):
        load_result(tmp_path / "missing.h5")


def test_failed_write_leaves_no_partial_file(tmp_path, straight_result, monkeypatch):
    path = tmp_path / "r.h5"
    save_result(straight_result, path)
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(h5py.Group, "create_dataset", boom)
    with pytest.raises(OSError, match="disk full"):
        save_result(straight_result, path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["r.h5"]
    with pytest.raises(OSError):
        save_result(straight_result, tmp_path / "new.h5")
    assert not (tmp_path / "new.h5").exists()


def test_trajectory_interpolates_linearly():
    traj = Trajectory(np.array([0.0, 1.0]), np.array([[[0.0, 0.0]], [[1.0, 2.0]]]))
    np.testing.assert_allclose(traj.at(0.25), [[0.25, 0.5]])
    np.testing.assert_allclose(traj.at(5.0), [[1.0, 2.0]])
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(np.array([0.0, 0.0]), np.zeros((2, 1, 2)))


def test_plan_result_checks_outcomes(straight_result):
    with pytest.raises(ValueError, match="unknown outcomes"):
        PlanResult(straight_result.scenario, straight_result.trajectory, np.full(61, "maybe"), "x")
