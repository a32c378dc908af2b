"""Trajectories, plan results, and the HDF5 file that carries them.

A trajectory is a time grid ``(T,)`` and joint angles ``(T, N, 2)``; between samples each
joint moves linearly in time (constant speed), which is how motor controllers replay it and
how the verifier checks it.

HDF5 layout (``format = "fiberplan-trajectory"``, version 1), readable with plain h5py::

    /                        attrs: format, version, fiberplan_version, created_utc, planner,
                                    instrument, n_positioners, seed, scenario_json
    /positioners/id          (N,)      int64
    /positioners/base_xy_mm  (N, 2)    float64
    /positioners/orient_rad  (N,)      float64
    /positioners/start_rad   (N, 2)    float64   (alpha, beta)
    /positioners/target_rad  (N, 2)    float64
    /positioners/target_xy_mm (N, 2)   float64
    /positioners/has_target  (N,)      bool
    /trajectory/time_s       (T,)      float64
    /trajectory/joints_rad   (T, N, 2) float64   (time, positioner, joint)
    /outcome/status          (N,)      ASCII: reached | deadlocked | failed
    /planner                 attrs: name, settings_json, stats_json, plan_wall_s

Files are written under a temporary name and renamed into place when complete.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from fiberplan._atomic import atomic_path
from fiberplan.errors import FiberplanError, TrajectoryFileError
from fiberplan.scenario import Scenario, scenario_from_dict

FORMAT_NAME = "fiberplan-trajectory"
FORMAT_VERSION = 1
OUTCOMES = ("reached", "deadlocked", "failed")


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Joint angles on a time grid.

    Attributes:
        times: ``(T,)`` strictly increasing sample times (s), starting at 0.
        joints: ``(T, N, 2)`` joint angles (rad); linear in time between samples.
    """

    times: np.ndarray
    joints: np.ndarray

    def __post_init__(self) -> None:
        times = np.asarray(self.times, dtype=float)
        joints = np.asarray(self.joints, dtype=float)
        if times.ndim != 1 or joints.ndim != 3 or joints.shape[0] != times.shape[0] or joints.shape[2] != 2:
            raise ValueError(f"trajectory shapes do not match: times {times.shape}, joints {joints.shape} (expected (T,) and (T, N, 2))")
        if len(times) > 1 and not np.all(np.diff(times) > 0):
            raise ValueError("trajectory times must be strictly increasing")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "joints", joints)

    @property
    def duration_s(self) -> float:
        """Time of the last sample."""
        return float(self.times[-1])

    def at(self, t: float) -> np.ndarray:
        """Joint angles ``(N, 2)`` at time ``t`` (linear interpolation, clamped at the ends)."""
        k = int(np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 1))
        if k == len(self.times) - 1:
            return self.joints[k].copy()
        w = (t - self.times[k]) / (self.times[k + 1] - self.times[k])
        w = min(max(w, 0.0), 1.0)
        return (1 - w) * self.joints[k] + w * self.joints[k + 1]


@dataclass(frozen=True, eq=False)
class PlanResult:
    """What a planner returns: the trajectory with its evidence.

    Attributes:
        scenario: the planned scenario.
        trajectory: the motion of every positioner.
        outcome: ``(N,)`` the planner's own verdict per positioner: ``reached``,
            ``deadlocked`` or ``failed`` (the verifier and metrics recompute what they need).
        planner: registry name of the planner.
        settings: the settings used (JSON-serialisable).
        stats: planner statistics (JSON-serialisable): solver calls, failures, timings.
        plan_wall_s: wall-clock time of the planning call.
    """

    scenario: Scenario
    trajectory: Trajectory
    outcome: np.ndarray
    planner: str
    settings: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    plan_wall_s: float = 0.0

    def __post_init__(self) -> None:
        outcome = np.asarray(self.outcome, dtype=str)
        n = self.scenario.n_positioners
        if outcome.shape != (n,):
            raise ValueError(f"outcome has shape {outcome.shape}, expected ({n},)")
        unknown = set(outcome.tolist()) - set(OUTCOMES)
        if unknown:
            raise ValueError(f"unknown outcomes {sorted(unknown)}; expected {OUTCOMES}")
        if self.trajectory.joints.shape[1] != n:
            raise ValueError(f"trajectory has {self.trajectory.joints.shape[1]} positioners, scenario has {n}")
        object.__setattr__(self, "outcome", outcome)


def _fiberplan_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fiberplan")
    except PackageNotFoundError:
        return "unknown"


def save_result(result: PlanResult, path: str | Path) -> Path:
    """Write a plan result to an HDF5 file, atomically. Returns the path."""
    path = Path(path)
    scenario = result.scenario
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["version"] = FORMAT_VERSION
            f.attrs["fiberplan_version"] = _fiberplan_version()
            f.attrs["created_utc"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
            f.attrs["planner"] = result.planner
            f.attrs["instrument"] = scenario.instrument.name
            f.attrs["n_positioners"] = scenario.n_positioners
            f.attrs["seed"] = -1 if scenario.seed is None else scenario.seed
            f.attrs["scenario_json"] = json.dumps(scenario.to_dict())
            pos = f.create_group("positioners")
            pos["id"] = scenario.ids
            pos["base_xy_mm"] = scenario.base_xy
            pos["orient_rad"] = scenario.orient
            pos["start_rad"] = scenario.start
            pos["target_rad"] = scenario.target
            pos["target_xy_mm"] = scenario.target_xy
            pos["has_target"] = scenario.has_target
            traj = f.create_group("trajectory")
            traj.create_dataset("time_s", data=result.trajectory.times)
            joints = result.trajectory.joints
            chunk = (max(1, min(len(joints), 64)), max(1, min(joints.shape[1], 1024)), 2)
            traj.create_dataset("joints_rad", data=joints, chunks=chunk, compression="gzip", compression_opts=4, shuffle=True)
            traj.attrs["interpolation"] = "linear in time between samples"
            traj.attrs["axes"] = "time, positioner, joint (alpha, beta)"
            out = f.create_group("outcome")
            out["status"] = np.array(result.outcome, dtype="S10")
            planner = f.create_group("planner")
            planner.attrs["name"] = result.planner
            planner.attrs["settings_json"] = json.dumps(result.settings, default=_json_default)
            planner.attrs["stats_json"] = json.dumps(result.stats, default=_json_default)
            planner.attrs["plan_wall_s"] = float(result.plan_wall_s)
    return path


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


def load_result(path: str | Path) -> PlanResult:
    """Read a plan result written by :func:`save_result`.

    Raises:
        TrajectoryFileError: missing, truncated or foreign file, or inconsistent content.
    """
    path = Path(path)
    if not path.is_file():
        raise TrajectoryFileError(f"trajectory file {str(path)!r} does not exist")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT_NAME:
                raise TrajectoryFileError(
                    f"{str(path)!r} is an HDF5 file but not a fiberplan trajectory file (attribute format={f.attrs.get('format')!r})"
                )
            version = int(f.attrs.get("version", -1))
            if version != FORMAT_VERSION:
                raise TrajectoryFileError(f"{str(path)!r}: unsupported trajectory format version {version}")
            scenario = scenario_from_dict(json.loads(f.attrs["scenario_json"]), origin=f"{str(path)!r}")
            times = f["trajectory/time_s"][...]
            joints = f["trajectory/joints_rad"][...]
            outcome = np.array([s.decode("ascii") for s in f["outcome/status"][...]])
            planner = f["planner"]
            result = PlanResult(
                scenario=scenario,
                trajectory=Trajectory(times, joints),
                outcome=outcome,
                planner=str(planner.attrs["name"]),
                settings=json.loads(planner.attrs["settings_json"]),
                stats=json.loads(planner.attrs["stats_json"]),
                plan_wall_s=float(planner.attrs["plan_wall_s"]),
            )
    except FiberplanError as e:
        if isinstance(e, TrajectoryFileError):
            raise
        raise TrajectoryFileError(f"{str(path)!r}: {e}") from e
    except (OSError, KeyError, ValueError, json.JSONDecodeError) as e:
        raise TrajectoryFileError(
            f"cannot read trajectory file {str(path)!r} ({type(e).__name__}: {e}); it may be truncated or not a fiberplan file"
        ) from e
    return result
