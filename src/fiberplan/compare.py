"""Compare planners on the same seeded scenarios; every result goes through the verifier.

One row per planner x scenario (:func:`run_compare`), with success, collisions, makespan,
makespan over the lower bound, fiber path length, energy (integral of squared joint
velocity), plan wall time and, for each planner, its gap to the ``central`` reference:

.. math:: \\text{gap}_P = \\frac{\\text{makespan}_P}{\\text{makespan}_{central}} - 1

on the scenarios where both ``P`` and ``central`` are *clean* (every target reached, no
collision, no limit violation). With ``energy_gap``, the central NLP is also solved in
energy mode at ``P``'s own makespan (warm-started from ``P``'s trajectory), and
``energy_P / energy_central - 1`` is recorded: the analogue of reference 004, table 7.3.

The ``central`` planner is run last on each scenario, through
:func:`fiberplan.planners.central.central_reference` (verified candidates only), with the
other planners' trajectories of that scenario as extra warm starts.

Scenario kind ``hard`` (:func:`hard_scenario`) is built here rather than in
:mod:`fiberplan.generate`: starts and targets clustered, and the draw with the most
straight-line conflicts on the critical path kept.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan._atomic import atomic_path
from fiberplan.errors import PlannerError, ScenarioError
from fiberplan.instrument import Instrument
from fiberplan.instrument_io import load_instrument
from fiberplan.kinematics import move_times
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult

HARD_KIND = "hard"
CENTRAL = "central"

ROW_COLUMNS = (
    "planner", "instrument", "scenario_kind", "n_positioners", "seed", "scenario", "error",
    "success_rate", "reached", "targets", "collisions", "limit_violations", "verified_ok", "clean",
    "makespan_s", "lower_bound_s", "makespan_over_bound", "path_length_mm_mean", "energy_rad2_s",
    "plan_wall_s", "min_clearance_mm", "solver_status", "solver_iterations", "solver_s", "warm_start",
    "gap_to_central", "central_energy_same_makespan", "energy_gap_to_central",
)
"""Columns of a comparison row, in order."""


# ---------------------------------------------------------------------------- hard scenarios
def hard_scenario(
    instrument: str | Instrument,
    n_positioners: int,
    seed: int,
    *,
    draws: int = 16,
    positioners_per_cluster: int = 2,
    sigma_pitch: float = 1.0 / 6.0,
    background: float = 0.05,
) -> Scenario:
    """A seeded scenario whose neighbours start and end close together and must cross.

    Starts and targets are each drawn from :func:`fiberplan.generate.clustered_sampler`
    (independent Gaussian clusters, one per ``positioners_per_cluster`` positioners, width
    ``sigma_pitch`` pitches, ``background`` uniform share), collision-free. Of ``draws``
    such draws from one generator seeded by ``seed``, the one whose straight-line motion
    (every joint at full speed) has the largest conflict score is kept:

    .. math:: \\text{score} = \\sum_{(i, j)\\ \\text{colliding}} \\max(T_i, T_j) / T_{LB}

    so that conflicts involve the long moves that set the makespan.

    Raises:
        ScenarioError: bad size or no collision-free configuration found.
        InstrumentError: unknown instrument preset.
    """
    from fiberplan.generate import clustered_sampler, joint_scenario, random_configuration
    from fiberplan.instrument_io import preset_names
    from fiberplan.layout import hex_patch, neighbour_pairs
    from fiberplan.planners.straight import StraightSettings, plan_straight
    from fiberplan.verify import verify

    if int(draws) != draws or draws < 1:
        raise ScenarioError(f"hard scenario: draws must be an integer >= 1, found {draws}")
    preset = instrument if isinstance(instrument, str) and instrument in preset_names() else None
    inst = load_instrument(instrument) if isinstance(instrument, str) else instrument
    rng = np.random.default_rng(seed)
    base = hex_patch(n_positioners, inst.pitch_mm)
    n = len(base)
    orient = np.zeros(n)
    pairs = neighbour_pairs(inst, base)
    n_clusters = max(1, n // positioners_per_cluster)
    sigma = inst.pitch_mm * sigma_pitch
    best: tuple[float, Scenario] | None = None
    for draw in range(int(draws)):
        start_sampler = clustered_sampler(inst, base, rng, n_clusters=n_clusters, sigma_mm=sigma, background=background)
        start = random_configuration(inst, base, orient, pairs, rng, sampler=start_sampler)
        target_sampler = clustered_sampler(inst, base, rng, n_clusters=n_clusters, sigma_mm=sigma, background=background)
        target = random_configuration(inst, base, orient, pairs, rng, sampler=target_sampler)
        scenario = joint_scenario(
            inst, base, orient, start, target, kind=HARD_KIND, seed=int(seed), instrument_preset=preset,
            meta={"hard_draw": draw, "hard_draws": int(draws)},
        )
        times = move_times(inst, scenario.start, scenario.target)
        lb = float(times.max())
        if lb <= 0:
            continue
        report = verify(scenario, plan_straight(scenario, StraightSettings.for_instrument(inst)).trajectory)
        score = sum(max(times[c.id_i], times[c.id_j]) / lb for c in report.collisions)
        if best is None or score > best[0]:
            best = (score, dataclasses.replace(scenario, meta=scenario.meta | {"hard_score": score}))
    if best is None:
        raise ScenarioError(f"hard scenario: every draw of seed {seed} had start = target; try another seed")
    return best[1]


def make_compare_scenario(instrument: str | Instrument, n_positioners: int, kind: str, seed: int) -> Scenario:
    """``hard`` (:func:`hard_scenario`) or any kind of :func:`fiberplan.generate.make_scenario`.

    Raises:
        ScenarioError: unknown kind or bad size.
    """
    if kind == HARD_KIND:
        return hard_scenario(instrument, n_positioners, seed)
    from fiberplan.generate import SCENARIO_KINDS, make_scenario

    if kind not in SCENARIO_KINDS:
        raise ScenarioError(f"unknown scenario kind {kind!r}; choose one of {', '.join((HARD_KIND, *SCENARIO_KINDS))}")
    return make_scenario(instrument, n_positioners, kind, seed)


# ---------------------------------------------------------------------------- running
@dataclass
class CompareResult:
    """Rows (one per planner x scenario) and per-planner aggregates."""

    rows: list[dict[str, Any]]
    aggregates: dict[str, dict[str, Any]] = field(default_factory=dict)
    parameters: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN and inf become None)."""
        return _json_ready({"parameters": self.parameters, "rows": self.rows, "aggregates": self.aggregates})


def _json_ready(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _json_ready(value.item())
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    return value


def _empty_row(planner: str, scenario: Scenario) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(ROW_COLUMNS)
    nan = float("nan")
    row.update(
        {
            "planner": planner,
            "instrument": scenario.instrument.name,
            "scenario_kind": scenario.kind,
            "n_positioners": scenario.n_positioners,
            "seed": scenario.seed,
            "scenario": scenario.name,
            "error": "",
            "clean": False,
            "verified_ok": False,
            "solver_status": "",
            "warm_start": "",
        }
    )
    for key in ROW_COLUMNS:
        if row[key] is None:
            row[key] = nan
    return row


def _row(result: PlanResult) -> dict[str, Any]:
    """Verify a result and turn it into a comparison row."""
    from fiberplan.metrics import summarize
    from fiberplan.verify import verify

    report = verify(result.scenario, result.trajectory)
    summary = summarize(result, report)
    row = _empty_row(result.planner, result.scenario)
    for key in ROW_COLUMNS:
        if key in summary:
            row[key] = summary[key]
    row["clean"] = bool(summary["success_rate"] >= 1.0 and report.ok)
    stats = result.stats
    if result.planner == CENTRAL:
        row["solver_status"] = str(stats.get("status", ""))
        row["solver_iterations"] = float(stats.get("iterations_total", float("nan")))
        row["solver_s"] = float(stats.get("solve_s_total", float("nan")))
        row["warm_start"] = str(stats.get("chosen") or "")
    return row


def _error_row(planner: str, scenario: Scenario, error: BaseException, wall_s: float) -> dict[str, Any]:
    row = _empty_row(planner, scenario)
    row["error"] = f"{type(error).__name__}: {error}"
    row["plan_wall_s"] = wall_s
    return row


def run_compare(
    instrument: str | Instrument,
    n_positioners: int,
    planners: Sequence[str],
    seeds: Sequence[int],
    *,
    kind: str = HARD_KIND,
    settings: Mapping[str, Mapping[str, Any]] | None = None,
    energy_gap: bool = False,
    progress: Callable[[str], None] | None = None,
    scenario_factory: Callable[[int], Scenario] | None = None,
) -> CompareResult:
    """Run every planner on every seeded scenario, verify each result, and aggregate.

    Args:
        instrument: preset name, file, or :class:`Instrument`.
        n_positioners: size of the hexagonal group.
        planners: registered planner names; ``central`` runs last on each scenario.
        seeds: scenario seeds.
        kind: scenario kind (``hard`` or a :mod:`fiberplan.generate` kind).
        settings: per-planner setting overrides, e.g. ``{"central": {"steps": 30}}``.
        energy_gap: also solve central in energy mode at each clean planner's makespan.
        progress: called with a short label after every run.
        scenario_factory: build the scenario of a seed (default :func:`make_compare_scenario`).

    A planner that raises on one scenario gives a row with its ``error`` and NaN metrics.

    Raises:
        PlannerError: an unknown planner name, or an empty list.
        ScenarioError: bad scenario kind or size.
    """
    from fiberplan.planners import make_settings, plan, planner_names
    from fiberplan.planners.central import central_reference

    names = [p.strip() for p in planners if p.strip()]
    if not names:
        raise PlannerError("compare: give at least one planner, e.g. --planners central,mpc,dnf")
    unknown = [p for p in names if p not in planner_names()]
    if unknown:
        raise PlannerError(f"compare: unknown planner {unknown[0]!r}; choose from {', '.join(planner_names())}")
    if len(set(names)) != len(names):
        raise PlannerError(f"compare: planner list {names} names a planner twice")
    settings = {k: dict(v) for k, v in (settings or {}).items()}
    ordered = [p for p in names if p != CENTRAL] + ([CENTRAL] if CENTRAL in names else [])
    build = scenario_factory or (lambda seed: make_compare_scenario(instrument, n_positioners, kind, seed))
    rows: list[dict[str, Any]] = []
    checked = False
    for seed in seeds:
        scenario = build(int(seed))
        if not checked:  # bad settings are bad input, not a per-scenario failure
            for name in names:
                make_settings(name, scenario, settings.get(name))
            checked = True
        done: dict[str, PlanResult] = {}
        seed_rows: dict[str, dict[str, Any]] = {}
        for name in ordered:
            t0 = time.perf_counter()
            try:
                if name == CENTRAL:
                    result = central_reference(scenario, settings.get(CENTRAL), warm_results=list(done.values()))
                else:
                    result = plan(scenario, name, settings.get(name))
                row = _row(result)
                done[name] = result
            except Exception as e:  # a planner failing on one scenario must not stop the study
                row = _error_row(name, scenario, e, time.perf_counter() - t0)
            seed_rows[name] = row
            if progress is not None:
                progress(f"{name} seed {seed}")
        add_gaps(seed_rows)
        if energy_gap and CENTRAL in names:
            _add_energy_gaps(scenario, seed_rows, done, settings.get(CENTRAL))
        rows.extend(seed_rows[name] for name in names)
    parameters = {
        "instrument": instrument if isinstance(instrument, str) else instrument.name,
        "n_positioners": n_positioners,
        "scenario_kind": kind,
        "seeds": [int(s) for s in seeds],
        "planners": names,
        "settings": settings,
        "energy_gap": energy_gap,
    }
    return CompareResult(rows=rows, aggregates=aggregate(rows), parameters=parameters)


def add_gaps(seed_rows: dict[str, dict[str, Any]]) -> None:
    """Set each row's gaps to the ``central`` row of the same scenario (planner -> row), in place."""
    central = seed_rows.get(CENTRAL)
    if central is None or not central["clean"]:
        return
    for row in seed_rows.values():
        if row["clean"] and central["makespan_s"] > 0:
            row["gap_to_central"] = row["makespan_s"] / central["makespan_s"] - 1.0


def _add_energy_gaps(
    scenario: Scenario, seed_rows: dict[str, dict[str, Any]], done: Mapping[str, PlanResult], central_settings: Mapping[str, Any] | None
) -> None:
    """Energy-mode central at each clean decentralised planner's own makespan (reference 004, table 7.3)."""
    from fiberplan.metrics import energy, lower_bound_s
    from fiberplan.planners.central import central_reference

    bound = lower_bound_s(scenario)
    for name, row in seed_rows.items():
        if name == CENTRAL or not row["clean"] or name not in done:
            continue
        makespan = max(float(row["makespan_s"]), bound)
        overrides = dict(central_settings or {}) | {"mode": "energy", "makespan_s": makespan, "warm_start": [name]}
        try:
            ref = central_reference(scenario, overrides, warm_results=[done[name]])
        except PlannerError as e:
            row["error"] = f"energy-mode central: {e}"
            continue
        if ref.stats.get("verified"):
            e_central = energy(ref.trajectory)
            row["central_energy_same_makespan"] = e_central
            if e_central > 0:
                row["energy_gap_to_central"] = row["energy_rad2_s"] / e_central - 1.0


def _quantiles(values: Sequence[float]) -> dict[str, float]:
    arr = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if len(arr) == 0:
        nan = float("nan")
        return {"median": nan, "p90": nan, "mean": nan, "max": nan, "n": 0}
    return {
        "median": float(np.median(arr)),
        "p90": float(np.percentile(arr, 90)),
        "mean": float(arr.mean()),
        "max": float(arr.max()),
        "n": len(arr),
    }


def aggregate(rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per-planner aggregates: success, collisions, makespan ratio, gap to central, energy gap, wall time."""
    out: dict[str, dict[str, Any]] = {}
    for name in dict.fromkeys(r["planner"] for r in rows):
        mine = [r for r in rows if r["planner"] == name]
        ok = [r for r in mine if not r["error"]]
        rates = [r["success_rate"] for r in ok]
        out[name] = {
            "runs": len(mine),
            "errors": len(mine) - len(ok),
            "success_rate_mean": float(np.mean(rates)) if rates else float("nan"),
            "clean_fraction": float(np.mean([bool(r["clean"]) for r in mine])) if mine else float("nan"),
            "collisions_total": int(sum(int(r["collisions"]) for r in ok if math.isfinite(r["collisions"]))),
            "makespan_over_bound": _quantiles([r["makespan_over_bound"] for r in mine if r["clean"]]),
            "gap_to_central": _quantiles([r["gap_to_central"] for r in mine]),
            "energy_gap_to_central": _quantiles([r["energy_gap_to_central"] for r in mine]),
            "energy_rad2_s": _quantiles([r["energy_rad2_s"] for r in mine if r["clean"]]),
            "plan_wall_s": _quantiles([r["plan_wall_s"] for r in mine]),
        }
    return out


def write_parquet(rows: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Write comparison rows to a Parquet file, atomically. Returns the path."""
    import pandas as pd

    path = Path(path)
    frame = pd.DataFrame(list(rows), columns=list(ROW_COLUMNS))
    for column in ("planner", "instrument", "scenario_kind", "scenario", "error", "solver_status", "warm_start"):
        frame[column] = frame[column].astype(str)
    frame["clean"] = frame["clean"].astype(bool)
    frame["verified_ok"] = frame["verified_ok"].astype(bool)
    frame["seed"] = pd.array(frame["seed"], dtype="Int64")
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False)
    return path


def format_table(result: CompareResult) -> str:
    """Human-readable rows and aggregates."""
    lines = []
    header = (
        f"{'planner':<9} {'seed':>4} {'success':>7} {'coll':>4} {'makespan':>9} {'/bound':>7} {'gap':>7} "
        f"{'path mm':>8} {'energy':>8} {'wall s':>7}  note"
    )
    lines.append(header)

    def fmt(value: Any, spec: str) -> str:
        return "n/a" if value is None or (isinstance(value, float) and not math.isfinite(value)) else format(value, spec)

    for r in result.rows:
        note = r["error"][:60] if r["error"] else (r["solver_status"] if r["planner"] == CENTRAL else "")
        lines.append(
            f"{r['planner']:<9} {r['seed']!s:>4} {fmt(r['success_rate'], '.3f'):>7} {fmt(r['collisions'], '.0f'):>4} "
            f"{fmt(r['makespan_s'], '.3f'):>9} {fmt(r['makespan_over_bound'], '.3f'):>7} {fmt(r['gap_to_central'], '+.1%'):>7} "
            f"{fmt(r['path_length_mm_mean'], '.2f'):>8} {fmt(r['energy_rad2_s'], '.2f'):>8} {fmt(r['plan_wall_s'], '.2f'):>7}  {note}"
        )
    lines.append("")
    lines.append(f"{'planner':<9} {'runs':>4} {'clean':>6} {'coll':>5} {'gap med':>8} {'gap p90':>8} {'n gap':>5} {'wall med':>8} {'wall max':>8}")
    for name, a in result.aggregates.items():
        lines.append(
            f"{name:<9} {a['runs']:>4} {fmt(a['clean_fraction'], '.2f'):>6} {a['collisions_total']:>5} "
            f"{fmt(a['gap_to_central']['median'], '+.1%'):>8} {fmt(a['gap_to_central']['p90'], '+.1%'):>8} {a['gap_to_central']['n']:>5} "
            f"{fmt(a['plan_wall_s']['median'], '.2f'):>8} {fmt(a['plan_wall_s']['max'], '.2f'):>8}"
        )
    return "\n".join(lines)
