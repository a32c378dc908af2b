"""Benchmarks of the ``mpc`` planner (issue 4), side by side with ``dnf`` on the same seeds.

Results go to ``benchmarks/results/mpc_<set>.json`` (rewritten after every run, so an
interrupted benchmark keeps what it measured). Sets:

- ``desi``: DESI-like random targets (default N = 500).
- ``moons``: MOONS-like unfold and random targets (default N = 61 and 500).
- ``sdss``: SDSS-like random collision-free start -> random targets (default N = 547).
- ``scaling``: plan wall time vs N (default 500, 1000, 2000, 5000), DESI-like, sequential
  and parallel executors (``--workers``).

Every trajectory is checked by :func:`fiberplan.verify.verify`; collisions are counted from
its report, never from the planner. Run from the repository root, e.g.::

    python benchmarks/bench_mpc.py desi --seeds 100
    python benchmarks/bench_mpc.py moons --seeds 50 --sizes 61 500
    python benchmarks/bench_mpc.py sdss --seeds 20
    python benchmarks/bench_mpc.py scaling --seeds 1 --workers 2
    python benchmarks/bench_mpc.py table      # Markdown table of the saved results
    python benchmarks/bench_mpc.py figure     # results/mpc_desi_makespan.png from the saved results

``table`` also fills the ``dnf`` column of the DESI set from ``results/dnf_desi.json``
(written by ``bench_dnf.py``) for the same seeds when this benchmark did not run the DNF.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from _machine import machine_info

from fiberplan._atomic import atomic_path
from fiberplan.generate import make_scenario
from fiberplan.metrics import summarize
from fiberplan.planners import plan, planner_names
from fiberplan.verify import verify

RESULTS = Path(__file__).resolve().parent / "results"

SETS: dict[str, dict[str, Any]] = {
    "desi": {"instrument": "desi", "kinds": ["random"], "sizes": [500]},
    "moons": {"instrument": "moons", "kinds": ["unfold", "random"], "sizes": [61, 500]},
    "sdss": {"instrument": "sdss", "kinds": ["random"], "sizes": [547]},
    "scaling": {"instrument": "desi", "kinds": ["random"], "sizes": [500, 1000, 2000, 5000]},
}

REFERENCE = {
    "sdss": (
        "published C++ planner (kaiju) on fold moves of 547 robots at 0.1 deg steps: 10/10 seeds solved "
        "at a 2.0 mm buffer in 13-17 s per attempt, ~22 s of motion at 30 deg/s; its greedy variant 1/10"
    ),
}





def run_one(instrument: str, n: int, kind: str, seed: int, planner: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """Plan one seeded scenario, verify it, and return its figures."""
    scenario = make_scenario(instrument, n, kind, seed)
    result = plan(scenario, planner, overrides)
    t0 = time.perf_counter()
    report = verify(scenario, result.trajectory)
    verify_s = time.perf_counter() - t0
    summary = summarize(result, report)
    record: dict[str, Any] = {
        "seed": seed,
        "n_positioners": scenario.n_positioners,
        "collisions": report.n_collisions,
        "limit_violations": len(report.limit_violations),
        "verified_ok": report.ok,
        "min_clearance_mm": report.min_clearance_mm,
        "success_rate": summary["success_rate"],
        "reached": summary["reached"],
        "targets": summary["targets"],
        "not_reached": summary["targets"] - summary["reached"],
        "makespan_s": summary["makespan_s"],
        "lower_bound_s": summary["lower_bound_s"],
        "makespan_over_bound": summary["makespan_over_bound"],
        "duration_s": summary["duration_s"],
        "plan_wall_s": summary["plan_wall_s"],
        "verify_wall_s": verify_s,
    }
    stats = result.stats
    for key in (
        "qp_solves", "qp_failures", "qp_inaccurate", "qp_fraction", "qp_solve_ms_median", "qp_solve_ms_p95",
        "qp_iterations_median", "safety_holds", "deadlocks_detected", "deadlocks_resolved", "deadlocks_remaining",
        "retreats", "yielding_positioners", "n_steps", "waiting_rules", "detours", "pair_resolutions",
        "schedule_delayed", "schedule_unplaced", "schedule_l_paths", "schedule_timed", "schedule_swaps", "schedule_wall_s",
    ):
        if key in stats:
            record[key] = stats[key]
    return record


def aggregate_runs(runs: list[dict[str, Any]]) -> dict[str, Any]:
    def col(key: str) -> np.ndarray:
        return np.array([r[key] for r in runs if key in r and r[key] is not None], dtype=float)

    out: dict[str, Any] = {
        "seeds_run": len(runs),
        "collisions_total": int(col("collisions").sum()),
        "limit_violations_total": int(col("limit_violations").sum()),
        "runs_verified_ok": int(sum(bool(r["verified_ok"]) for r in runs)),
        "success_rate_mean": float(col("success_rate").mean()),
        "success_rate_min": float(col("success_rate").min()),
        "positioners_not_reached_total": int(col("not_reached").sum()),
        "makespan_over_bound_median": float(np.nanmedian(col("makespan_over_bound"))),
        "makespan_over_bound_p90": float(np.nanpercentile(col("makespan_over_bound"), 90)),
        "plan_wall_s_median": float(np.median(col("plan_wall_s"))),
        "plan_wall_s_max": float(col("plan_wall_s").max()),
    }
    if len(col("qp_solves")):
        out.update(
            {
                "qp_solve_ms_median_of_runs": float(np.median(col("qp_solve_ms_median"))),
                "qp_solve_ms_p95_of_runs": float(np.median(col("qp_solve_ms_p95"))),
                "qp_fraction_mean": float(col("qp_fraction").mean()),
                "qp_failures_total": int(col("qp_failures").sum()),
                "qp_solves_total": int(col("qp_solves").sum()),
                "deadlocks_detected_total": int(col("deadlocks_detected").sum()),
                "deadlocks_remaining_total": int(col("deadlocks_remaining").sum()),
                "safety_holds_total": int(col("safety_holds").sum()),
            }
        )
    return out


def _row(label: str, kind: str, n: int, s: dict[str, Any]) -> str:
    qp = (
        f"{s['qp_solve_ms_median_of_runs']:.2f} / {s['qp_solve_ms_p95_of_runs']:.1f} | {100 * s['qp_fraction_mean']:.1f} % | "
        f"{s['deadlocks_detected_total']} / {s['deadlocks_remaining_total']}"
        if "qp_solves_total" in s
        else "- | - | -"
    )
    return (
        f"| {label} | {kind} | {n} | {s['seeds_run']} | {s['collisions_total']} | {100 * s['success_rate_mean']:.2f} % "
        f"(min {100 * s['success_rate_min']:.1f} %) | {s['makespan_over_bound_median']:.2f} | {s['plan_wall_s_median']:.1f} | {qp} |"
    )


def _dnf_cell_from_dnf_benchmark(seeds: list[int], n: int) -> dict[str, Any] | None:
    path = RESULTS / "dnf_desi.json"
    if not path.exists():
        return None
    document = json.loads(path.read_text())
    for cell in document.get("cells", []):
        if cell.get("n_positioners") == n and cell.get("variant", "default") == "default":
            runs = [r for r in cell["runs"] if r["seed"] in seeds]
            if not runs:
                return None
            return {
                "seeds_run": len(runs),
                "collisions_total": int(sum(r["collisions"] for r in runs)),
                "success_rate_mean": float(np.mean([r["success_rate"] for r in runs])),
                "success_rate_min": float(np.min([r["success_rate"] for r in runs])),
                "makespan_over_bound_median": float(np.median([r["makespan_s"] / r["lower_bound_s"] for r in runs])),
                "plan_wall_s_median": float(np.median([r["plan_wall_s"] for r in runs])),
            }
    return None


def write_result(path: Path, document: dict[str, Any]) -> None:
    """Write a result file atomically: an interrupted benchmark never leaves it truncated."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(document, indent=1, default=float) + "\n")


def print_table() -> None:
    """Print a Markdown table of every ``results/mpc_*.json``."""
    print(
        "| planner | kind | N | seeds | collisions | success (mean, min) | makespan / lower bound (median) | plan wall s "
        "(median) | QP solve ms median / p95 | positioner-steps with a QP | deadlocks detected / left |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for path in sorted(RESULTS.glob("mpc_*.json")):
        document = json.loads(path.read_text())
        instrument = document["parameters"]["instrument"]
        for cell in document["cells"]:
            if "summary" not in cell:
                continue
            label = f"{instrument} {cell['planner']}"
            print(_row(label, cell["kind"], cell["n_positioners"], cell["summary"]))
            has_dnf = any(c["planner"] == "dnf" and c["n_positioners"] == cell["n_positioners"] for c in document["cells"])
            if document["benchmark"] == "mpc_desi" and cell["planner"] == "mpc" and not has_dnf:
                dnf = _dnf_cell_from_dnf_benchmark([r["seed"] for r in cell["runs"]], cell["n_positioners"])
                if dnf is not None:
                    print(_row(f"{instrument} dnf (dnf_desi.json, same seeds)", cell["kind"], cell["n_positioners"], dnf))


# DESI result files drawn by ``figure``: label -> file (missing files are skipped).
FIGURE_DESI = {
    "mpc, current": "mpc_desi.json",
    "mpc, repair, straight-line progress": "mpc_desi_before_route_progress.json",
    "mpc, timed paths without the repair": "mpc_desi_before_repair.json",
    "mpc, start schedule without timed paths": "mpc_desi_before_space_time.json",
    "mpc, start schedule without L-shaped moves": "mpc_desi_before_l_paths.json",
    "mpc, before the start schedule (7a53f8e)": "mpc_desi_before_schedule.json",
}


def desi_makespan_figure(out: Path) -> Path:
    """Empirical distribution of makespan / lower bound over the DESI seeds, mpc versions and the DNF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fiberplan.plotting import save_figure

    series: dict[str, np.ndarray] = {}
    for label, name in FIGURE_DESI.items():
        path = RESULTS / name
        if path.exists():
            runs = [r for c in json.loads(path.read_text())["cells"] if c["planner"] == "mpc" for r in c["runs"]]
            series[label] = np.array([r["makespan_over_bound"] for r in runs])
    seeds = [r["seed"] for r in json.loads((RESULTS / "mpc_desi.json").read_text())["cells"][0]["runs"]]
    dnf_path = RESULTS / "dnf_desi.json"
    if dnf_path.exists():
        for cell in json.loads(dnf_path.read_text())["cells"]:
            if cell.get("n_positioners") == 500 and cell.get("variant", "default") == "default":
                series["dnf"] = np.array([r["makespan_s"] / r["lower_bound_s"] for r in cell["runs"] if r["seed"] in seeds])
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for label, values in series.items():
        x = np.sort(values)
        ax.step(x, np.arange(1, len(x) + 1) / len(x), where="post",
                label=f"{label}: median {np.median(values):.2f}, <= 1.2 on {int(np.sum(values <= 1.2))} of {len(values)}")
    ax.axvline(1.2, color="#999999", ls="--", lw=0.8)
    ax.text(1.22, 0.5, "target 1.2", color="#666666", fontsize=8)
    ax.set_xlabel("makespan / lower bound")
    ax.set_ylabel("fraction of seeds")
    ax.set_title(f"DESI-like, N = 500, random targets, {len(seeds)} seeds")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    return save_figure(fig, out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("set", choices=[*sorted(SETS), "table", "figure"])
    parser.add_argument("--seeds", type=int, default=10, help="seeds per cell")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--sizes", type=int, nargs="+", help="numbers of positioners (default per set)")
    parser.add_argument("--kinds", nargs="+", help="scenario kinds (default per set)")
    parser.add_argument("--planners", nargs="+", default=["mpc", "dnf"], help="planners to compare (dnf skipped if absent)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes of the parallel executor (scaling)")
    parser.add_argument("--set-override", action="append", default=[], metavar="KEY=JSON", help="mpc setting override")
    parser.add_argument("--out", type=Path, help="output file (default benchmarks/results/mpc_<set>.json)")
    parser.add_argument("--budget-s", type=float, help="stop starting new seeds of a (kind, N) group after this many seconds")
    args = parser.parse_args(argv)

    if args.set == "table":
        print_table()
        return 0
    if args.set == "figure":
        print(desi_makespan_figure(args.out or RESULTS / "mpc_desi_makespan.png"))
        return 0
    spec = SETS[args.set]
    sizes = args.sizes or spec["sizes"]
    kinds = args.kinds or spec["kinds"]
    overrides = {k: json.loads(v) for k, v in (item.split("=", 1) for item in args.set_override)}
    planners = [p for p in args.planners if p in planner_names()]
    skipped = sorted(set(args.planners) - set(planners))
    variants: list[tuple[str, str, dict[str, Any]]] = []
    for name in planners:
        if name == "mpc":
            variants.append(("mpc", "mpc", dict(overrides)))
            if args.set == "scaling":
                variants.append(("mpc-parallel", "mpc", {**overrides, "executor": "parallel", "workers": args.workers}))
        else:
            variants.append((name, name, {}))

    out_path = args.out or RESULTS / f"mpc_{args.set}.json"
    out_path.parent.mkdir(parents=True, exist_ok=True)
    document: dict[str, Any] = {
        "benchmark": f"mpc_{args.set}",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "command": "python benchmarks/bench_mpc.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine_info(("osqp", "qpsolvers", "clarabel", "cvxpy")),
        "parameters": {
            "instrument": spec["instrument"],
            "kinds": kinds,
            "sizes": sizes,
            "seeds_requested": args.seeds,
            "first_seed": args.first_seed,
            "planners": [v[0] for v in variants],
            "planners_skipped_not_registered": skipped,
            "mpc_overrides": overrides,
        },
        "reference": REFERENCE.get(args.set, ""),
        "cells": [],
    }
    t_start = time.perf_counter()
    for kind in kinds:
        for n in sizes:
            cells = []
            for label, _planner, over in variants:
                cell: dict[str, Any] = {"kind": kind, "n_positioners": n, "planner": label, "overrides": over, "runs": []}
                document["cells"].append(cell)
                cells.append(cell)
            t_group = time.perf_counter()
            # Seeds outermost, so that every planner has run the same seeds when a budget stops the group.
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                if args.budget_s is not None and time.perf_counter() - t_group > args.budget_s:
                    document.setdefault("stopped_by_budget", []).append({"kind": kind, "n_positioners": n, "next_seed": seed})
                    break
                for cell, (label, planner, over) in zip(cells, variants, strict=True):
                    record = run_one(spec["instrument"], n, kind, seed, planner, over)
                    cell["runs"].append(record)
                    cell["summary"] = aggregate_runs(cell["runs"])
                    document["wall_s"] = time.perf_counter() - t_start
                    write_result(out_path, document)
                    print(
                        f"{label:13s} {kind:7s} N={n:5d} seed={seed:3d} success={record['success_rate']:.4f} "
                        f"collisions={record['collisions']} T/LB={record['makespan_over_bound']:.2f} "
                        f"plan={record['plan_wall_s']:.1f}s",
                        flush=True,
                    )
    document["wall_s"] = time.perf_counter() - t_start
    write_result(out_path, document)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
