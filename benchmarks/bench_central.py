"""How far are the decentralised planners from the central optimum? (issue 5, reference 004 section 7.5)

For each instrument and group size, runs ``central``, ``mpc`` and ``dnf`` on the same seeded
``hard`` scenarios (:func:`fiberplan.studies.hard_scenario`), verifies every result, and writes
``benchmarks/results/central_<instrument>_<n>.json`` with machine info, versions, date,
parameters, per-planner aggregates (success, makespan gap to central: median and 90th
percentile, energy gap at equal makespan, plan wall times) and every row. The file is
rewritten after each seed, so an interrupted run keeps what it measured (``seeds_done``);
``--resume`` continues such a file (same parameters) with the seeds it lacks. ``--replace
PLANNER`` re-runs one decentralised planner on the seeds of existing files (after a change
to it) and recomputes its gaps against the central rows kept in the file; refused where the
central solutions depended on that planner (it is among central's warm starts) or where energy
gaps are recorded (they need new central solves).

Usage::

    python benchmarks/bench_central.py --instrument desi --positioners 7 19 --seeds 30
    python benchmarks/bench_central.py --table          # markdown gap table from the result files
    python benchmarks/bench_central.py --instrument moons --positioners 7 --replace mpc
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import statistics
import time
from pathlib import Path
from typing import Any

from _machine import machine_info

from fiberplan._atomic import atomic_path
from fiberplan.studies import HARD_KIND, add_gaps, aggregate, run_compare

RESULTS = Path(__file__).resolve().parent / "results"


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if hasattr(value, "item"):
        return _clean(value.item())
    return value


def _previous(out: Path, instrument: str, n: int, planners: list[str], energy_gap: bool, central: dict[str, Any]) -> dict[str, Any] | None:
    """The result file to continue, or None; refuses one measured with other parameters."""
    if not out.exists():
        return None
    prev = json.loads(out.read_text())
    par = prev["parameters"]
    mine = {"instrument": instrument, "n_positioners": n, "planners": planners, "energy_gap": energy_gap, "central_overrides": central}
    theirs = {k: par.get(k) for k in mine}
    if theirs != _clean(mine):
        raise SystemExit(f"--resume: {out} was measured with {theirs}, not {mine}; move it away or drop --resume")
    return prev


def run_one(
    instrument: str, n: int, seeds: list[int], planners: list[str], energy_gap: bool, budget_s: float, out: Path,
    central: dict[str, Any], resume: bool = False,
) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    t0 = time.perf_counter()
    done: list[int] = []
    sessions: list[dict[str, Any]] = []
    elapsed_before = 0.0
    prev = _previous(out, instrument, n, planners, energy_gap, central) if resume else None
    if prev is not None:
        rows = list(prev["rows"])
        done = list(prev["parameters"]["seeds_done"])
        elapsed_before = float(prev.get("elapsed_s", 0.0))
        sessions = prev.get("sessions") or [{"date_utc": prev["date_utc"], "seeds": list(done), "elapsed_s": elapsed_before}]
        started = prev["date_utc"]
    session = {"date_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), "seeds": [], "elapsed_s": 0.0}
    payload: dict[str, Any] = {}
    for seed in seeds:
        if seed in done:
            continue
        if time.perf_counter() - t0 > budget_s:
            break
        result = run_compare(instrument, n, planners, [seed], kind=HARD_KIND, energy_gap=energy_gap, settings={"central": central})
        rows.extend(result.rows)
        done.append(seed)
        session["seeds"].append(seed)
        session["elapsed_s"] = time.perf_counter() - t0
        payload = {
            "benchmark": "bench_central",
            "date_utc": started,
            "machine": machine_info(("casadi", "osqp")),
            "parameters": {
                "instrument": instrument,
                "n_positioners": n,
                "scenario_kind": HARD_KIND,
                "seeds_requested": sorted(set(seeds) | set(done)),
                "seeds_done": sorted(done),
                "planners": planners,
                "energy_gap": energy_gap,
                "time_budget_s": budget_s,
                "planner_settings": "defaults, except central overrides below; central also warm-starts from the other planners' results",
                "central_overrides": central,
            },
            "elapsed_s": elapsed_before + time.perf_counter() - t0,
            "sessions": [*sessions, session] if prev is not None else [session],
            "aggregates": aggregate(rows),
            "rows": rows,
        }
        with atomic_path(out) as tmp:
            tmp.write_text(json.dumps(_clean(payload), indent=1))
        gaps = {p: payload["aggregates"][p]["gap_to_central"]["median"] for p in planners}
        print(f"{instrument} {n} seed {seed}: {time.perf_counter() - t0:.0f} s, median gaps {gaps}", flush=True)
    return payload


def replace_planner(out: Path, planner: str) -> dict[str, Any]:
    """Re-run ``planner`` on every seed of the result file ``out``; keep the other rows."""
    if not out.exists():
        raise SystemExit(f"--replace: {out} does not exist; run the benchmark first")
    data = json.loads(out.read_text())
    par = data["parameters"]
    if planner not in par["planners"] or planner == "central":
        raise SystemExit(f"--replace: {planner!r} is not a decentralised planner of {out} ({par['planners']})")
    if par["energy_gap"]:
        raise SystemExit(f"--replace: {out} records energy gaps, which need new central solves; re-run it whole")
    warm = (par.get("central_overrides") or {}).get("warm_start")
    if warm is None or planner in warm:
        raise SystemExit(f"--replace: central in {out} warm-started from {planner!r}'s results; re-run it whole")
    t0 = time.perf_counter()
    rows = data["rows"]
    for seed in par["seeds_done"]:
        new = run_compare(par["instrument"], par["n_positioners"], [planner], [seed], kind=HARD_KIND, energy_gap=False).rows[0]
        by_planner = {r["planner"]: r for r in rows if r["seed"] == seed and r["planner"] != planner}
        by_planner[planner] = new
        add_gaps(by_planner)
        rows = [r for r in rows if not (r["seed"] == seed and r["planner"] == planner)] + [new]
        print(f"{par['instrument']} {par['n_positioners']} seed {seed}: {planner} success {new['success_rate']:.3f} "
              f"gap {new['gap_to_central']}", flush=True)
    rows.sort(key=lambda r: (r["seed"], par["planners"].index(r["planner"])))
    data["rows"] = rows
    data["aggregates"] = aggregate(rows)
    data.setdefault("replaced", []).append({
        "planner": planner,
        "date_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(("casadi", "osqp")),
        "elapsed_s": time.perf_counter() - t0,
    })
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(_clean(data), indent=1))
    return data


def _fmt(value: Any, spec: str) -> str:
    return "n/a" if value is None or (isinstance(value, float) and not math.isfinite(value)) else format(value, spec)


def table(results_dir: Path) -> str:
    """Markdown gap table from every ``central_*.json`` file."""
    lines = [
        "| instrument | N | seeds | planner | clean | collisions | makespan / bound (median) | gap to central: median | p90 | n | "
        "energy gap at equal makespan: median | p90 | plan wall s: median | max |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for path in sorted(results_dir.glob("central_*.json")):
        data = json.loads(path.read_text())
        par = data["parameters"]
        for name, agg in data["aggregates"].items():
            gap, egap, wall = agg["gap_to_central"], agg["energy_gap_to_central"], agg["plan_wall_s"]
            lines.append(
                f"| {par['instrument']} | {par['n_positioners']} | {len(par['seeds_done'])} | {name} | {_fmt(agg['clean_fraction'], '.0%')} | "
                f"{agg['collisions_total']} | {_fmt(agg['makespan_over_bound']['median'], '.3f')} | {_fmt(gap['median'], '+.1%')} | "
                f"{_fmt(gap['p90'], '+.1%')} | {gap['n']} | {_fmt(egap['median'], '+.1%')} | {_fmt(egap['p90'], '+.1%')} | "
                f"{_fmt(wall['median'], '.2f')} | {_fmt(wall['max'], '.1f')} |"
            )
    lines += [
        "",
        "Paired, on the seeds where both decentralised planners are clean (same instances):",
        "",
        "| instrument | N | seeds (both clean) | mpc gap median | dnf gap median | mpc smaller gap | dnf smaller gap |",
        "|---|---|---|---|---|---|---|",
    ]
    for path in sorted(results_dir.glob("central_*.json")):
        data = json.loads(path.read_text())
        par = data["parameters"]
        by_seed: dict[int, dict[str, Any]] = {}
        for row in data["rows"]:
            by_seed.setdefault(row["seed"], {})[row["planner"]] = row
        both = [v for v in by_seed.values() if all(v.get(p, {}).get("gap_to_central") is not None for p in ("mpc", "dnf"))]
        if not both:
            continue
        g_mpc = [v["mpc"]["gap_to_central"] for v in both]
        g_dnf = [v["dnf"]["gap_to_central"] for v in both]
        lines.append(
            f"| {par['instrument']} | {par['n_positioners']} | {len(both)} | {statistics.median(g_mpc):+.1%} | "
            f"{statistics.median(g_dnf):+.1%} | {sum(a < b for a, b in zip(g_mpc, g_dnf, strict=True))} | "
            f"{sum(b < a for a, b in zip(g_mpc, g_dnf, strict=True))} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--instrument", nargs="+", default=["desi"])
    parser.add_argument("--positioners", nargs="+", type=int, default=[7, 19])
    parser.add_argument("--seeds", type=int, default=30, help="seeds 0..K-1")
    parser.add_argument("--planners", default="central,mpc,dnf")
    parser.add_argument("--no-energy-gap", action="store_true", help="skip the energy-mode central solves")
    parser.add_argument("--budget-s", type=float, default=3600.0, help="stop starting new seeds after this many seconds per group")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--central-set", nargs="*", default=[], metavar="KEY=VALUE", help="central setting overrides (JSON values)")
    parser.add_argument(
        "--resume", action="store_true",
        help="continue the existing result file (same parameters): keep its rows, run the seeds it lacks",
    )
    parser.add_argument("--table", action="store_true", help="print the markdown gap table of the result files and exit")
    parser.add_argument("--replace", metavar="PLANNER", help="re-run this planner on the seeds of the existing result files")
    args = parser.parse_args()
    if args.table:
        print(table(args.results))
        return
    planners = [p for p in args.planners.split(",") if p]
    central: dict[str, Any] = {}
    for item in args.central_set:
        key, raw = item.split("=", 1)
        try:
            central[key] = json.loads(raw)
        except json.JSONDecodeError:
            central[key] = raw
    for instrument in args.instrument:
        for n in args.positioners:
            out = args.results / f"central_{instrument}_{n}.json"
            if args.replace:
                replace_planner(out, args.replace)
                continue
            run_one(instrument, n, list(range(args.seeds)), planners, not args.no_energy_gap, args.budget_s, out, central, args.resume)


if __name__ == "__main__":
    main()
