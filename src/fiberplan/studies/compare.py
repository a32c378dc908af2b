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
:func:`fiberplan.studies.central_reference` (verified candidates only), with the other
planners' trajectories of that scenario as extra warm starts. Rows are those of
:mod:`fiberplan.studies.runner` (one table format everywhere), with the gap columns filled.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fiberplan._json import json_ready as _json_ready
from fiberplan.errors import PlannerError
from fiberplan.instrument import Instrument
from fiberplan.scenario import Scenario
from fiberplan.studies.analysis import aggregate
from fiberplan.studies.runner import CENTRAL, RunSpec, run_one, write_rows
from fiberplan.studies.scenarios import HARD_KIND, study_scenario
from fiberplan.trajectory import PlanResult


@dataclass
class CompareResult:
    """Rows (one per planner x scenario) and per-planner aggregates."""

    rows: list[dict[str, Any]]
    aggregates: dict[str, dict[str, Any]] = field(default_factory=dict)
    parameters: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN and inf become None; no tracebacks)."""
        rows = [{k: v for k, v in r.items() if k != "traceback" and not k.startswith("_")} for r in self.rows]
        return _json_ready({"parameters": self.parameters, "rows": rows, "aggregates": self.aggregates})


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
        energy_gap: also solve central in energy mode at each clean planner's makespan (with or
            without ``central`` among ``planners``: the makespan-mode reference is not needed
            for it, and can be taken from a stored compare with ``bench.py gap``).
        progress: called with a short label after every run (and, with ``energy_gap``, after
            every decentralised planner's energy-mode reference: the long part of such a run).
        scenario_factory: build the scenario of a seed (default :func:`~fiberplan.studies.scenarios.study_scenario`).

    A planner that raises on one scenario gives a row with its ``error`` and NaN metrics.

    Raises:
        PlannerError: an unknown planner name, or an empty list.
        ScenarioError: bad scenario kind or size.
    """
    from fiberplan.planners import make_settings, planner_names

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
    label = instrument if isinstance(instrument, str) else instrument.name
    build = scenario_factory or (lambda seed: study_scenario(instrument, n_positioners, kind, seed))
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
            spec = RunSpec(label, n_positioners, kind, name, int(seed), tuple(sorted(settings.get(name, {}).items())))
            row = run_one(spec, scenario=scenario, warm_results=list(done.values()), keep_result=True)
            result = row.pop("_result", None)
            if result is not None:
                done[name] = result
            seed_rows[name] = row
            if progress is not None:
                progress(f"{name} seed {seed}")
        add_gaps(seed_rows)
        if energy_gap:  # (the energy-mode solves need no makespan-mode central row: central may be left out)
            _add_energy_gaps(scenario, seed_rows, done, settings.get(CENTRAL), progress=progress, seed=int(seed))
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
    scenario: Scenario, seed_rows: dict[str, dict[str, Any]], done: Mapping[str, PlanResult], central_settings: Mapping[str, Any] | None,
    progress: Callable[[str], None] | None = None, seed: int | None = None,
) -> None:
    """Energy-mode central at each clean decentralised planner's own makespan (reference 004, table 7.3);
    ``progress`` hears of every decentralised planner's row once its reference is there (or not needed)."""
    solved: dict[tuple[float, bytes], dict[str, Any]] = {}  # planners that returned the same trajectory share one solve
    # (keyed by the makespan and the trajectory's times and joints; each row's gap from its own energy)
    for name in seed_rows:
        if name != CENTRAL:
            _energy_gap_of(name, scenario, seed_rows, done, central_settings, solved)
            if progress is not None:
                progress(f"energy reference {name} seed {seed}")


def _energy_gap_of(
    name: str, scenario: Scenario, seed_rows: dict[str, dict[str, Any]], done: Mapping[str, PlanResult],
    central_settings: Mapping[str, Any] | None, solved: dict[tuple[float, bytes], dict[str, Any]],
) -> None:
    """``name``'s row of ``seed_rows`` with its energy gap, from ``solved`` if a planner with the same
    trajectory was solved for already (the same problem and warm start: the same deterministic solve)."""
    from fiberplan.metrics import energy, lower_bound_s
    from fiberplan.studies.reference import central_reference

    row = seed_rows[name]
    if not row["clean"] or name not in done:
        return
    makespan = max(float(row["makespan_s"]), lower_bound_s(scenario))
    trajectory = done[name].trajectory
    key = (makespan, trajectory.times.tobytes() + trajectory.joints.tobytes())
    if key not in solved:
        overrides = dict(central_settings or {}) | {"mode": "energy", "makespan_s": makespan, "warm_start": [name]}
        try:
            ref = central_reference(scenario, overrides, warm_results=[done[name]])
        except PlannerError as e:
            solved[key] = {"error": f"energy-mode central: {e}"}
        else:
            solved[key] = {"central_energy_same_makespan": energy(ref.trajectory)} if ref.stats.get("verified") else {}
    found = solved[key]
    if "error" in found:
        row["error"] = found["error"]
    elif "central_energy_same_makespan" in found:
        row["central_energy_same_makespan"] = e_central = found["central_energy_same_makespan"]
        if e_central > 0:
            row["energy_gap_to_central"] = row["energy_rad2_s"] / e_central - 1.0


def write_parquet(rows: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Write comparison rows to a Parquet table (the one row format), atomically."""
    return write_rows([dict(r) for r in rows], path)


def format_table(result: CompareResult) -> str:
    """Human-readable rows and aggregates (with the energy gaps where they were solved)."""
    lines = []
    energy = bool(result.parameters.get("energy_gap")) or any(
        isinstance(r.get("energy_gap_to_central"), float) and math.isfinite(r["energy_gap_to_central"]) for r in result.rows)
    header = (
        f"{'planner':<9} {'seed':>4} {'success':>7} {'coll':>4} {'makespan':>9} {'/bound':>7} {'gap':>7} "
        f"{'path mm':>8} {'energy':>8} " + (f"{'e gap':>7} " if energy else "") + f"{'wall s':>7}  note"
    )
    lines.append(header)

    def fmt(value: Any, spec: str) -> str:
        return "n/a" if value is None or (isinstance(value, float) and not math.isfinite(value)) else format(value, spec)

    for r in result.rows:
        note = r["error"][:60] if r["error"] else (r["solver_status"] if r["planner"] == CENTRAL else "")
        e_gap = f"{fmt(r.get('energy_gap_to_central'), '+.1%'):>7} " if energy else ""
        lines.append(
            f"{r['planner']:<9} {r['seed']!s:>4} {fmt(r['success_rate'], '.3f'):>7} {fmt(r['collisions'], '.0f'):>4} "
            f"{fmt(r['makespan_s'], '.3f'):>9} {fmt(r['makespan_over_bound'], '.3f'):>7} {fmt(r['gap_to_central'], '+.1%'):>7} "
            f"{fmt(r['path_length_mm_mean'], '.2f'):>8} {fmt(r['energy_rad2_s'], '.2f'):>8} {e_gap}{fmt(r['plan_wall_s'], '.2f'):>7}  {note}"
        )
    lines.append("")
    lines.append(f"{'planner':<9} {'runs':>4} {'clean':>6} {'coll':>5} {'gap med':>8} {'gap p90':>8} {'n gap':>5} "
                 + (f"{'e gap med':>9} {'n e':>4} " if energy else "") + f"{'wall med':>8} {'wall max':>8}")
    for name, a in result.aggregates.items():
        e_agg = a.get("energy_gap_to_central") or {"median": None, "n": 0}
        e_cols = f"{fmt(e_agg['median'], '+.1%'):>9} {e_agg['n']:>4} " if energy else ""
        lines.append(
            f"{name:<9} {a['runs']:>4} {fmt(a['clean_fraction'], '.2f'):>6} {a['collisions_total']:>5} "
            f"{fmt(a['gap_to_central']['median'], '+.1%'):>8} {fmt(a['gap_to_central']['p90'], '+.1%'):>8} {a['gap_to_central']['n']:>5} "
            f"{e_cols}{fmt(a['plan_wall_s']['median'], '.2f'):>8} {fmt(a['plan_wall_s']['max'], '.2f'):>8}"
        )
    return "\n".join(lines)
