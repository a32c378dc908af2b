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
    /outcome/status          (N,)      ASCII: an outcome of fiberplan.outcomes (reached, deadlocked, ...)
    /planner                 attrs: name, settings_json, stats_json, plan_wall_s, warnings_json

Files are written under a temporary name and renamed into place when complete.
"""

from __future__ import annotations

import datetime as _dt
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from fiberplan._atomic import atomic_path
from fiberplan.errors import FiberplanError, PlannerError, TrajectoryError, TrajectoryFileError
from fiberplan.outcomes import OUTCOMES
from fiberplan.scenario import Scenario, scenario_from_dict

FORMAT_NAME = "fiberplan-trajectory"
FORMAT_VERSION = 1



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
        try:
            times = np.asarray(self.times, dtype=float)
            joints = np.asarray(self.joints, dtype=float)
        except (TypeError, ValueError) as e:
            raise TrajectoryError(f"trajectory times and joints must be numeric arrays ({e})") from e
        if times.ndim != 1 or joints.ndim != 3 or joints.shape[0] != times.shape[0] or joints.shape[2] != 2:
            raise TrajectoryError(
                f"trajectory shapes do not match: times {times.shape}, joints {joints.shape} (expected (T,) and (T, N, 2))"
            )
        if len(times) == 0:
            raise TrajectoryError("a trajectory needs at least one sample")
        if not np.all(np.isfinite(times)):
            raise TrajectoryError("trajectory times must be finite")
        if len(times) > 1 and not np.all(np.diff(times) > 0):
            raise TrajectoryError("trajectory times must be strictly increasing")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "joints", joints)

    def non_finite(self) -> tuple[np.ndarray, np.ndarray]:
        """Sample and positioner indices ``(k, i)`` of every sample with a non-finite joint angle."""
        k, i = np.nonzero(~np.isfinite(self.joints).all(axis=-1))
        return k, i

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
        outcome: ``(N,)`` the planner's own verdict per positioner, in the vocabulary of
            :mod:`fiberplan.outcomes` (the verifier and metrics recompute what they need).
        planner: registry name of the planner.
        settings: the settings used (JSON-serialisable).
        stats: planner statistics (JSON-serialisable): solver calls, failures, timings.
        plan_wall_s: wall-clock time of the planning call.
        warnings: what the planner gave up on or could not do (shown by the command line).

    Raises:
        TrajectoryError: shapes or outcomes do not match the scenario.
        PlannerError: the trajectory holds a non-finite sample: no planner may return one
            (the message names the planner, positioners and times).
    """

    scenario: Scenario
    trajectory: Trajectory
    outcome: np.ndarray
    planner: str
    settings: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    plan_wall_s: float = 0.0
    warnings: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        outcome = np.asarray(self.outcome, dtype=str)
        n = self.scenario.n_positioners
        if outcome.shape != (n,):
            raise TrajectoryError(f"outcome has shape {outcome.shape}, expected ({n},)")
        unknown = set(outcome.tolist()) - set(OUTCOMES)
        if unknown:
            raise TrajectoryError(f"unknown outcomes {sorted(unknown)}; expected {OUTCOMES}")
        if self.trajectory.joints.shape[1] != n:
            raise TrajectoryError(f"trajectory has {self.trajectory.joints.shape[1]} positioners, scenario has {n}")
        k, i = self.trajectory.non_finite()
        if len(k):
            ids = np.unique(self.scenario.ids[i])
            raise PlannerError(
                f"internal error: planner {self.planner!r} produced non-finite joint angles for {len(ids)} positioner(s) "
                f"(first: positioner {self.scenario.ids[i[0]]} at t = {self.trajectory.times[k[0]]:.4g} s; ids {ids[:10].tolist()}); "
                "this is a bug in the planner, please report it"
            )
        object.__setattr__(self, "outcome", outcome)
        object.__setattr__(self, "warnings", tuple(str(w) for w in self.warnings))


def _fiberplan_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fiberplan")
    except PackageNotFoundError:
        return "unknown"


def save_result(result: PlanResult, path: str | Path, extra: Callable[[h5py.File], None] | None = None) -> Path:
    """Write a plan result to an HDF5 file, atomically. Returns the path.

    ``extra`` may add groups to the open file before it is renamed into place (the motor
    profiles beside the trajectory they rebuild: :mod:`fiberplan.profile_io`).

    Raises:
        OutputError: the path must not be written (not a regular file) or writing failed.
    """
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
            planner.attrs["warnings_json"] = json.dumps(list(result.warnings))
            if extra is not None:
                extra(f)
    return path


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


@dataclass(frozen=True, eq=False)
class RunFile:
    """A trajectory file as stored, non-finite samples included (what ``fiberplan verify`` checks).

    Attributes:
        path: the file.
        scenario: the scenario embedded as ``scenario_json``.
        trajectory: time grid and joint angles (which may hold non-finite samples).
        outcome: the planner's verdicts per positioner.
        planner, settings, stats, plan_wall_s, warnings: the ``/planner`` group.
        positioners: the ``/positioners/*`` datasets, by name.
    """

    path: Path
    scenario: Scenario
    trajectory: Trajectory
    outcome: np.ndarray
    planner: str
    settings: dict[str, Any]
    stats: dict[str, Any]
    plan_wall_s: float
    warnings: tuple[str, ...]
    positioners: dict[str, np.ndarray]

    def to_result(self) -> PlanResult:
        """The :class:`PlanResult` of the file.

        Raises:
            TrajectoryFileError: the file holds non-finite samples (``fiberplan verify`` names them).
        """
        k, i = self.trajectory.non_finite()
        if len(k):
            raise TrajectoryFileError(
                f"{str(self.path)!r} holds non-finite joint angles (positioner {self.scenario.ids[i[0]]} at "
                f"t = {self.trajectory.times[k[0]]:.4g} s, {len(k)} sample(s) in all); run `fiberplan verify` on it for the list"
            )
        return PlanResult(
            scenario=self.scenario, trajectory=self.trajectory, outcome=self.outcome, planner=self.planner,
            settings=self.settings, stats=self.stats, plan_wall_s=self.plan_wall_s, warnings=self.warnings,
        )


def read_run(path: str | Path) -> RunFile:
    """Read a trajectory file as stored, without judging its samples (see :class:`RunFile`).

    Raises:
        TrajectoryFileError: missing, truncated or foreign file, or unreadable content.
    """
    path = Path(path)
    if not path.is_file():
        what = "does not exist" if not path.exists() else "is not a regular file"
        raise TrajectoryFileError(f"trajectory file {str(path)!r} {what}")
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
            if outcome.shape != (scenario.n_positioners,):
                raise TrajectoryFileError(f"{str(path)!r}: /outcome/status has {outcome.shape} entries for {scenario.n_positioners} positioners")
            unknown = sorted(set(outcome.tolist()) - set(OUTCOMES))
            if unknown:
                raise TrajectoryFileError(f"{str(path)!r}: /outcome/status holds unknown outcomes {unknown}; expected {OUTCOMES}")
            planner = f["planner"]
            positioners = {name: f["positioners"][name][...] for name in f["positioners"]} if "positioners" in f else {}
            trajectory = Trajectory(times, joints)
            if joints.shape[1] != scenario.n_positioners:
                raise TrajectoryFileError(
                    f"{str(path)!r}: the trajectory has {joints.shape[1]} positioners, the scenario {scenario.n_positioners}"
                )
            run = RunFile(
                path=path,
                scenario=scenario,
                trajectory=trajectory,
                outcome=outcome,
                planner=str(planner.attrs["name"]),
                settings=json.loads(planner.attrs["settings_json"]),
                stats=json.loads(planner.attrs["stats_json"]),
                plan_wall_s=float(planner.attrs["plan_wall_s"]),
                warnings=tuple(json.loads(planner.attrs.get("warnings_json", "[]"))),
                positioners=positioners,
            )
    except FiberplanError as e:
        if isinstance(e, TrajectoryFileError):
            raise
        raise TrajectoryFileError(f"{str(path)!r}: {e}") from e
    except (OSError, KeyError, ValueError, TypeError, json.JSONDecodeError) as e:
        raise TrajectoryFileError(
            f"cannot read trajectory file {str(path)!r} ({type(e).__name__}: {e}); it may be truncated or not a fiberplan file"
        ) from e
    return run


def load_result(path: str | Path) -> PlanResult:
    """Read a plan result written by :func:`save_result`.

    Raises:
        TrajectoryFileError: missing, truncated or foreign file, inconsistent content, or
            non-finite samples (read those with :func:`read_run`, check them with ``verify``).
    """
    return read_run(path).to_result()
