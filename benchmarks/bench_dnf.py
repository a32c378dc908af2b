"""Benchmarks of the ``dnf`` planner (issue 3), written to ``benchmarks/results/dnf_<set>.json``.

Sets:

- ``desi``: DESI-like, random targets, ``--seeds`` seeds at each N (default 7, 19, 61, 500):
  collisions, success rate, median in-motion duration (makespan), plan wall time. Reference
  000: 0 collisions in 4100 sets, about 2.5 s in motion whatever N.
- ``scaling``: plan wall time vs N (default 500, 1000, 2000, 5000). Reference 000: 140 s for
  5000 positioners on a 2013 6-core Xeon, linear in N.
- ``moons``: MOONS-like, unfold (datum -> random targets) at N = 61 and 500, with and without
  reference 002's asymmetric-zone priority, and with both separations (capsule, ellipse).

Every trajectory is checked by :func:`fiberplan.verify.verify`; collisions are counted from
its report, never from the planner. Run from the repository root, e.g.::

    python benchmarks/bench_dnf.py desi --seeds 100
    python benchmarks/bench_dnf.py scaling --seeds 3
    python benchmarks/bench_dnf.py moons --seeds 20 --sizes 61
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
from fiberplan.planners import make_settings, plan
from fiberplan.verify import verify

RESULTS = Path(__file__).resolve().parent / "results"

DEFAULT_SIZES = {"desi": [7, 19, 61, 500], "scaling": [500, 1000, 2000, 5000], "moons": [61, 500]}
MOONS_VARIANTS = {
    "capsule": {},
    "capsule+priority": {"zone_priority": "move_time"},
    "ellipse": {"separation": "ellipse"},
    "ellipse+priority": {"separation": "ellipse", "zone_priority": "move_time"},
}





def run_one(instrument: str, n: int, kind: str, seed: int, overrides: dict[str, Any]) -> dict[str, Any]:
    """Plan and verify one scenario; return the metrics row."""
    scenario = make_scenario(instrument, n, kind, seed)
    result = plan(scenario, "dnf", overrides)
    t0 = time.perf_counter()
    report = verify(scenario, result.trajectory)
    verify_s = time.perf_counter() - t0
    row = summarize(result, report)
    row["verify_wall_s"] = verify_s
    row["retreats"] = result.stats["retreats"]
    row["safety_interventions"] = result.stats["safety_interventions"]
    row["time_limit_hit"] = result.stats["time_limit_hit"]
    row["n_steps"] = result.stats["n_steps"]
    row["us_per_positioner_step"] = 1e6 * result.plan_wall_s / (result.stats["n_steps"] * n)
    return row


def aggregate(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Figures of one (N, variant) cell."""
    success = np.array([r["success_rate"] for r in rows])
    makespan = np.array([r["makespan_s"] for r in rows], dtype=float)
    return {
        "seeds": len(rows),
        "collisions_total": int(sum(r["collisions"] for r in rows)),
        "limit_violations_total": int(sum(r["limit_violations"] for r in rows)),
        "runs_verified_ok": int(sum(bool(r["verified_ok"]) for r in rows)),
        "success_rate_mean": float(success.mean()),
        "success_rate_min": float(success.min()),
        "runs_with_success_ge_0.99": int(np.sum(success >= 0.99)),
        "deadlocked_total": int(sum(r["deadlocked"] for r in rows)),
        "failed_total": int(sum(r["failed"] for r in rows)),
        "deadlocked_per_run_mean": float(np.mean([r["deadlocked"] for r in rows])),
        "makespan_s_median": float(np.nanmedian(makespan)),
        "makespan_s_p90": float(np.nanpercentile(makespan, 90)),
        "lower_bound_s_median": float(np.median([r["lower_bound_s"] for r in rows])),
        "duration_s_median": float(np.median([r["duration_s"] for r in rows])),
        "plan_wall_s_median": float(np.median([r["plan_wall_s"] for r in rows])),
        "plan_wall_s_max": float(np.max([r["plan_wall_s"] for r in rows])),
        "verify_wall_s_median": float(np.median([r["verify_wall_s"] for r in rows])),
        "retreats_mean": float(np.mean([r["retreats"] for r in rows])),
        "us_per_positioner_step_median": float(np.median([r["us_per_positioner_step"] for r in rows])),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("set", choices=sorted(DEFAULT_SIZES), help="which benchmark set")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per size (default: desi 100, scaling 3, moons 20)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="numbers of positioners")
    parser.add_argument("--variants", nargs="+", default=None, help=f"moons only: subset of {', '.join(MOONS_VARIANTS)}")
    parser.add_argument("--settings", type=json.loads, default={}, help="JSON overrides of the dnf settings")
    parser.add_argument("--out", type=Path, default=None, help="output JSON (default results/dnf_<set>.json)")
    args = parser.parse_args(argv)

    sizes = args.sizes or DEFAULT_SIZES[args.set]
    seeds = args.seeds if args.seeds is not None else {"desi": 100, "scaling": 3, "moons": 20}[args.set]
    instrument, kind = ("moons", "unfold") if args.set == "moons" else ("desi", "random")
    variants = {"default": {}} if args.set != "moons" else {k: MOONS_VARIANTS[k] for k in (args.variants or MOONS_VARIANTS)}
    out = args.out or RESULTS / f"dnf_{args.set}.json"

    started = dt.datetime.now(dt.UTC)
    cells: list[dict[str, Any]] = []
    for n in sizes:
        for name, variant in variants.items():
            overrides = {**args.settings, **variant}
            rows = []
            for seed in range(args.first_seed, args.first_seed + seeds):
                row = run_one(instrument, n, kind, seed, overrides)
                rows.append(row)
                print(
                    f"{args.set} N={n} {name} seed={seed}: success={row['success_rate']:.3f} "
                    f"collisions={row['collisions']} makespan={row['makespan_s']:.2f}s plan={row['plan_wall_s']:.2f}s",
                    flush=True,
                )
            settings = make_settings("dnf", make_scenario(instrument, n, kind, args.first_seed), overrides)
            cell = {"n_positioners": n, "variant": name, "overrides": overrides, **aggregate(rows)}
            cell["settings"] = {k: v for k, v in settings.__dict__.items()}
            cell["runs"] = [
                {k: r[k] for k in ("seed", "success_rate", "deadlocked", "failed", "collisions", "makespan_s", "lower_bound_s",
                                   "plan_wall_s", "verify_wall_s", "retreats", "time_limit_hit", "duration_s", "n_steps",
                                   "us_per_positioner_step")}
                for r in rows
            ]
            cells.append(cell)
            print(json.dumps({k: v for k, v in cell.items() if k not in ("runs", "settings")}), flush=True)

    document = {
        "benchmark": f"dnf_{args.set}",
        "date_utc": started.isoformat(timespec="seconds"),
        "wall_s": (dt.datetime.now(dt.UTC) - started).total_seconds(),
        "command": "python benchmarks/bench_dnf.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine_info(),
        "parameters": {"instrument": instrument, "kind": kind, "sizes": sizes, "seeds": seeds, "first_seed": args.first_seed,
                       "variants": variants, "settings_overrides": args.settings},
        "reference": {
            "desi": "reference 000: 0 collisions in 4100 sets; in-motion ~2.5 s independent of N; 140 s plan for 5000 (2013 6-core Xeon)",
            "scaling": "reference 000: plan time linear in N; 140 s for 5000 positioners",
            "moons": "reference 002: some positioners end in deadlock on 1025-positioner runs (fig. 4)",
        }[args.set],
        "cells": cells,
    }
    with atomic_path(out) as tmp:  # a complete file or none
        tmp.write_text(json.dumps(document, indent=1, default=str) + "\n", encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
