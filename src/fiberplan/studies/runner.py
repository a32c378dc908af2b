"""The one runner: scenario -> plan -> verify -> row, used by sweeps, comparisons and benchmarks.

A :class:`RunSpec` names one run (instrument, size, scenario kind and options, planner and
settings, seed); :func:`run_one` plans it, verifies the trajectory with the independent
verifier and returns one row of the results table (:data:`ROW_COLUMNS` first, then
``setting.*``, ``scenario.*`` and the planner's numeric statistics as ``stat.*``). It never
raises: a run that raises is a row with ``status = "error"`` and the message. Every table
fiberplan writes (sweeps, ``compare``, benchmarks) has this format.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan._atomic import atomic_path
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult
from fiberplan.verify import VerificationReport

CENTRAL = "central"

ROW_COLUMNS = (
    "task", "planner", "instrument", "n_positioners", "scenario_kind", "seed", "scenario", "settings_json", "status", "error",
    "targets", "reached", "success_rate", "held", "deadlocked", "unfinished", "failed", "displaced", "infeasible", "locked",
    "collisions", "limit_violations", "verified_ok", "clean", "min_clearance_mm",
    "makespan_s", "lower_bound_s", "makespan_over_bound", "duration_s", "plan_wall_s", "path_length_mm_mean", "path_length_mm_total",
    "energy_rad2_s", "solver_status", "solver_iterations", "solver_s", "warm_start",
    "gap_to_central", "central_energy_same_makespan", "energy_gap_to_central", "run_wall_s",
)
"""The columns every results row has, in order (more follow: ``setting.*``, ``scenario.*``, ``stat.*``)."""

_TEXT = ("task", "planner", "instrument", "scenario_kind", "scenario", "settings_json", "status", "error", "solver_status", "warm_start")
_FLAGS = ("verified_ok", "clean")


@dataclass(frozen=True)
class RunSpec:
    """One run: a scenario (instrument, size, kind, options, seed) and a planner with its settings."""

    instrument: str
    n_positioners: int
    scenario_kind: str
    planner: str
    seed: int
    settings: tuple[tuple[str, Any], ...] = ()
    scenario_options: tuple[tuple[str, Any], ...] = ()

    def parameters(self) -> dict[str, Any]:
        """The run's parameters as row columns (``setting.*`` and ``scenario.*`` flattened)."""
        return {
            "task": self.key,
            "instrument": self.instrument,
            "n_positioners": self.n_positioners,
            "scenario_kind": self.scenario_kind,
            "planner": self.planner,
            "seed": self.seed,
            "settings_json": json.dumps(dict(self.settings), sort_keys=True),
            **{f"setting.{k}": v for k, v in self.settings},
            **{f"scenario.{k}": v for k, v in self.scenario_options},
        }

    @property
    def key(self) -> str:
        """Stable identifier (hash of the canonical parameters) used to resume."""
        payload = json.dumps(
            {
                "instrument": self.instrument,
                "n_positioners": self.n_positioners,
                "scenario_kind": self.scenario_kind,
                "planner": self.planner,
                "seed": self.seed,
                "settings": dict(self.settings),
                **({"scenario": dict(self.scenario_options)} if self.scenario_options else {}),
                # Drawn starts keep the instrument's safety margin since the minimum start clearance
                # came in: a part written before then is not this run.
                **({"start_clearance": "instrument margin"} if self._default_start_clearance else {}),
            },
            sort_keys=True,
        )
        return hashlib.sha1(payload.encode()).hexdigest()[:16]

    @property
    def _default_start_clearance(self) -> bool:
        """The scenario's start is drawn with the default minimum clearance (not given in ``[scenario]``)."""
        from fiberplan.generate import DRAWN_START_KINDS

        return self.scenario_kind in DRAWN_START_KINDS and "min_start_clearance_mm" not in dict(self.scenario_options)

    def scenario(self) -> Scenario:
        """The run's scenario (seeded: the same spec gives the same scenario)."""
        from fiberplan.studies.scenarios import study_scenario

        return study_scenario(self.instrument, self.n_positioners, self.scenario_kind, self.seed, **dict(self.scenario_options))


def empty_row(parameters: dict[str, Any]) -> dict[str, Any]:
    """A row with every column: the parameters, text columns empty, flags false, numbers NaN."""
    row: dict[str, Any] = dict.fromkeys(ROW_COLUMNS, math.nan)
    for key in _TEXT:
        row[key] = ""
    for key in _FLAGS:
        row[key] = False
    row.update(parameters)
    return row


def result_row(result: PlanResult, report: VerificationReport, parameters: dict[str, Any]) -> dict[str, Any]:
    """The row of a planned and verified run."""
    from fiberplan.metrics import summarize

    summary = summarize(result, report)
    row = empty_row(parameters)
    for key in ROW_COLUMNS:
        if key in summary and key not in parameters:
            row[key] = summary[key]
    row["scenario"] = result.scenario.name
    row["status"] = "ok"
    row["clean"] = bool(summary["success_rate"] >= 1.0 and report.ok)
    stats = result.stats
    if result.planner == CENTRAL:
        row["solver_status"] = str(stats.get("status", ""))
        row["solver_iterations"] = float(stats.get("iterations_total", math.nan))
        row["solver_s"] = float(stats.get("solve_s_total", math.nan))
        row["warm_start"] = str(stats.get("chosen") or "")
    for name, value in stats.items():
        if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)):
            row[f"stat.{name}"] = float(value)
    return row


def error_row(parameters: dict[str, Any], error: BaseException) -> dict[str, Any]:
    """The row of a run that raised."""
    row = empty_row(parameters)
    row["status"] = "error"
    row["error"] = f"{type(error).__name__}: {error}"
    row["traceback"] = traceback.format_exc(limit=5)
    return row


def plan_and_verify(
    scenario: Scenario, planner: str, settings: dict[str, Any] | None = None, warm_results: Sequence[PlanResult] = (),
) -> tuple[PlanResult, VerificationReport]:
    """Plan (``central`` through :func:`~fiberplan.studies.reference.central_reference`, verified
    candidates only, with ``warm_results`` as extra warm starts) and verify."""
    from fiberplan.planners import plan
    from fiberplan.studies.reference import central_reference
    from fiberplan.verify import verify

    if planner == CENTRAL:
        result = central_reference(scenario, settings, warm_results=warm_results)
    else:
        result = plan(scenario, planner, settings)
    return result, verify(scenario, result.trajectory)


def run_one(
    spec: RunSpec, per_positioner: bool = False, *, scenario: Scenario | None = None, warm_results: Sequence[PlanResult] = (),
    keep_result: bool = False,
) -> dict[str, Any]:
    """Run one spec: scenario, plan, verify, row. Never raises: an error becomes the row.

    Args:
        spec: the run.
        per_positioner: also return, under ``_positioners``, each positioner's outcome,
            reached flag, arrival time and path length.
        scenario: the spec's scenario when already built (a comparison builds it once).
        warm_results: other planners' results on this scenario (``central``'s warm starts).
        keep_result: also return the :class:`PlanResult` under ``_result``.
    """
    parameters = spec.parameters()
    t0 = time.perf_counter()
    try:
        sc = scenario if scenario is not None else spec.scenario()
        result, report = plan_and_verify(sc, spec.planner, dict(spec.settings), warm_results)
        row = result_row(result, report, parameters)
        if keep_result:
            row["_result"] = result
        if per_positioner:
            row["_positioners"] = positioner_rows(result)
    except Exception as e:  # a failing run is a result, not a crash of the study
        row = error_row(parameters, e)
    row["run_wall_s"] = time.perf_counter() - t0
    return row


def positioner_rows(result: PlanResult) -> dict[str, list[Any]]:
    """Each positioner's id, outcome, reached flag, arrival time and fiber path length."""
    from fiberplan.metrics import arrival_times, path_lengths_mm, reached_mask

    sc, traj = result.scenario, result.trajectory
    return {
        "id": sc.ids.tolist(),
        "outcome": result.outcome.tolist(),
        "reached": reached_mask(sc, traj).tolist(),
        "arrival_s": arrival_times(sc, traj).tolist(),
        "path_length_mm": path_lengths_mm(sc, traj).tolist(),
    }


def rows_frame(rows: Sequence[dict[str, Any]]) -> Any:
    """The rows as a pandas DataFrame: :data:`ROW_COLUMNS` first, then the others sorted."""
    import pandas as pd

    clean = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
    extra = sorted({k for r in clean for k in r} - set(ROW_COLUMNS))
    frame = pd.DataFrame(clean, columns=[*ROW_COLUMNS, *extra])
    for column in _TEXT:
        frame[column] = frame[column].fillna("").astype(str)
    for column in _FLAGS:
        frame[column] = frame[column].fillna(False).astype(bool)
    frame["seed"] = pd.array(frame["seed"], dtype="Int64")
    frame["n_positioners"] = pd.array(frame["n_positioners"], dtype="Int64")
    return frame


def write_rows(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """Write rows to a Parquet table, atomically. Returns the path."""
    path = Path(path)
    frame = rows_frame(rows)
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False)
    return path
