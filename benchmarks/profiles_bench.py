"""Motor profiles on the benchmark sets: segments per joint, verified exports, makespan and time.

For each run of a set: plan (the planner's instrument defaults), discretise
(:func:`fiberplan.discretise`), and record the segments per moving joint, whether the first
fit passed the verifier (``refit_rounds == 0``) and whether the export is verified, the motor
violations left, the makespan before and after, and the discretisation time against the plan
time. Writes one JSON file (rows and aggregates, with the machine)::

    python benchmarks/profiles_bench.py --out benchmarks/results/profiles.json            # the quick sets
    python benchmarks/profiles_bench.py --full --out benchmarks/results/profiles_full.json  # the issue's sets
    python benchmarks/profiles_bench.py --dnf --out benchmarks/results/profiles_dnf.json    # the dnf on its SDSS, MOONS sets
    python benchmarks/profiles_bench.py --governor --out benchmarks/results/motor_governor.json  # the mpc with and without
                                                                                               # its motor governor

``--only INSTRUMENT`` keeps the sets of one instrument, ``--seeds A:B`` the seeds A to B - 1. With ``--governor`` each run is planned
twice, with the mpc's ``motor_limits`` off and on (:mod:`fiberplan.planners.motors`); the
aggregates then compare the two: the motor limits broken in the plan's own samples and after
discretisation, and what the governor costs in makespan.

Rows are written after every run (a killed run keeps what was measured); each row holds the
histogram of segments per moving joint (``segments_hist``: count -> joints).
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info

QUICK = (
    ("mpc", "desi", 500, "random", range(20)),
    ("mpc", "moons", 61, "unfold", range(10)),
    ("mpc", "moons-capsules", 61, "unfold", range(10)),
    ("mpc", "sdss", 547, "random", range(5)),
    ("dnf", "desi", 500, "random", range(10)),
    ("dnf", "moons-capsules", 61, "unfold", range(10)),
)
FULL = (  # the quick sets first: a run stopped for time keeps them
    ("mpc", "desi", 500, "random", range(100)),
    ("mpc", "sdss", 547, "random", range(20)),
    ("dnf", "desi", 500, "random", range(100)),
    ("mpc", "moons", 61, "unfold", range(50)),
)

DNF = (  # the dnf on the sets that FULL plans with the mpc only
    ("dnf", "sdss", 547, "random", range(20)),
    ("dnf", "moons", 61, "unfold", range(50)),
)

GOVERNOR = (
    ("mpc", "moons-capsules", 61, "unfold", range(50)),
    ("mpc", "moons", 61, "unfold", range(10)),
)


def measure(planner: str, instrument: str, n: int, kind: str, seed: int, motor_limits: bool | None = None) -> dict:
    """Plan (with the mpc's ``motor_limits`` as given, else its default) and discretise one run; its figures."""
    import fiberplan as fp

    scenario = fp.make_scenario(instrument, n, kind, seed)
    result = fp.plan(scenario, planner, settings=None if motor_limits is None else {"motor_limits": motor_limits})
    row = {"planner": planner, "instrument": instrument, "n": n, "kind": kind, "seed": seed, "plan_wall_s": result.plan_wall_s}
    if motor_limits is not None:
        row["motor_limits"] = motor_limits
    plan_report = fp.verify(scenario, result.trajectory)
    if not plan_report.ok:
        return row | {"error": "plan not verified"}
    row["plan_motor_violations"] = len(plan_report.motor_violations) if plan_report.motors_checked else None
    started = time.perf_counter()
    try:
        made = fp.discretise(result)
    except fp.FiberplanError as e:
        return row | {"error": str(e), "discretise_s": time.perf_counter() - started}
    summary = made.summary()
    counts = made.segment_counts()
    moving = counts[counts > 0]
    return row | {
        "discretise_s": summary["discretise_s"],
        "segments_hist": {str(k): int(v) for k, v in zip(*np.unique(moving, return_counts=True), strict=True)},
        "segments_median": float(np.median(moving)) if len(moving) else 0.0,
        "segments_max": int(moving.max()) if len(moving) else 0,
        "first_pass_verified": summary["refit_rounds"] == 0,
        "verified_ok": summary["verified_ok"],
        "followed_samples": len(summary["followed_samples"]),
        "motor_violations": summary["motor_violations"],
        "motor_violation_kinds": dict(collections.Counter(v.kind for v in made.report.motor_violations)) if made.report else {},
        "makespan_before_s": summary["makespan_before_s"],
        "makespan_after_s": summary["makespan_after_s"],
        "pauses": summary.get("pauses", 0),
        "creeps_mended": summary.get("creeps_mended", 0),
        "joints_over_128_segments": int(np.count_nonzero(moving > 128)),
        "reached": fp.summarize(result)["reached"],
    }


def aggregate(rows: list[dict]) -> list[dict]:
    """Per (planner, instrument, n, kind): the issue's figures."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["planner"], row["instrument"], row["n"], row["kind"], row.get("motor_limits")), []).append(row)
    out = []
    for (planner, instrument, n, kind, governed), group in groups.items():
        ok = [r for r in group if "error" not in r]
        segments = np.concatenate([np.repeat(np.array([int(k) for k in r["segments_hist"]], dtype=int), list(r["segments_hist"].values()))
                                   for r in ok]) if ok else np.zeros(0)
        increase = [r["makespan_after_s"] / r["makespan_before_s"] - 1 for r in ok if r["makespan_before_s"] > 0]
        share = [r["discretise_s"] / r["plan_wall_s"] for r in ok if r["plan_wall_s"] > 0]
        violations = [r["motor_violations"] for r in ok if r["motor_violations"] is not None]
        in_plan = [r["plan_motor_violations"] for r in ok if r.get("plan_motor_violations") is not None]
        out.append({
            "planner": planner, "instrument": instrument, "n": n, "kind": kind, "runs": len(group), "errors": len(group) - len(ok),
            **({} if governed is None else {"motor_limits": governed}),
            "runs_complete": sum(r["reached"] == n for r in ok),
            "plan_motor_violations_total": sum(in_plan) if in_plan else None,
            "segments_median": float(np.median(segments)) if len(segments) else None,
            "segments_p95": float(np.percentile(segments, 95)) if len(segments) else None,
            "segments_max": int(segments.max()) if len(segments) else None,
            "verified_first_pass": sum(r["first_pass_verified"] for r in ok) / len(group),
            "verified_exported": sum(bool(r["verified_ok"]) for r in ok) / len(group),
            "runs_with_motor_violations": sum(v > 0 for v in violations) if violations else None,
            "motor_violations_total": sum(violations) if violations else None,
            "makespan_increase_median": float(np.median(increase)) if increase else None,
            "makespan_increase_max": float(np.max(increase)) if increase else None,
            "runs_with_pauses": sum(bool(r.get("pauses")) for r in ok),
            "runs_with_joints_over_128_segments": sum(bool(r.get("joints_over_128_segments")) for r in ok),
            "discretise_over_plan_median": float(np.median(share)) if share else None,
            "discretise_s_median": float(np.median([r["discretise_s"] for r in ok])) if ok else None,
            "plan_wall_s_median": float(np.median([r["plan_wall_s"] for r in group])),
        })
    return out


def governor_costs(rows: list[dict]) -> list[dict]:
    """Per set measured with ``--governor``: the governed plan against the ungoverned one, seed by seed."""
    pairs: dict[tuple, dict[bool, dict]] = {}
    for row in rows:
        if "motor_limits" in row and "error" not in row:
            pairs.setdefault((row["planner"], row["instrument"], row["n"], row["kind"], row["seed"]), {})[row["motor_limits"]] = row
    sets: dict[tuple, list[dict[bool, dict]]] = {}
    for key, both in pairs.items():
        if len(both) == 2:
            sets.setdefault(key[:4], []).append(both)
    out = []
    for (planner, instrument, n, kind), runs in sets.items():
        ratio = np.array([b[True]["makespan_before_s"] / b[False]["makespan_before_s"] for b in runs])
        time_ratio = np.array([b[True]["plan_wall_s"] / b[False]["plan_wall_s"] for b in runs])
        out.append({
            "planner": planner, "instrument": instrument, "n": n, "kind": kind, "seeds": len(runs),
            "makespan_ratio_median": float(np.median(ratio)), "makespan_ratio_mean": float(ratio.mean()),
            "makespan_ratio_p95": float(np.percentile(ratio, 95)), "makespan_ratio_min": float(ratio.min()),
            "makespan_ratio_max": float(ratio.max()), "plan_time_ratio_median": float(np.median(time_ratio)),
        })
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--full", action="store_true", help="The issue's sets (hours) instead of the quick ones.")
    which.add_argument("--governor", action="store_true", help="MOONS sets planned with the mpc's motor governor off and on.")
    which.add_argument("--dnf", action="store_true", help="The dnf on the issue's SDSS and MOONS sets.")
    parser.add_argument("--only", metavar="INSTRUMENT", help="Keep the sets of this instrument only.")
    parser.add_argument("--seeds", metavar="A:B", help="Keep the seeds A to B - 1 of each set (to finish a set stopped for time).")
    args = parser.parse_args()
    sets = GOVERNOR if args.governor else FULL if args.full else DNF if args.dnf else QUICK
    if args.only:
        sets = tuple(s for s in sets if s[1] == args.only)
        if not sets:
            parser.error(f"--only {args.only}: no set of that instrument here")
    if args.seeds:
        try:
            first, stop = (int(v) for v in args.seeds.split(":"))
        except ValueError:
            parser.error(f"--seeds {args.seeds}: give A:B, two integers")
        sets = tuple((*s[:4], range(max(first, s[4].start), min(stop, s[4].stop))) for s in sets)
        sets = tuple(s for s in sets if len(s[4]))
    modes: tuple[bool | None, ...] = (False, True) if args.governor else (None,)
    total = sum(len(seeds) for *_, seeds in sets) * len(modes)
    rows: list[dict] = []
    meta = {"benchmark": "motor_governor" if args.governor else "profiles", "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "machine": machine_info(), "sets": [[p, i, n, k, [min(s), max(s)]] for p, i, n, k, s in sets]}
    for planner, instrument, n, kind, seeds in sets:
        for seed in seeds:
            for mode in modes:
                rows.append(measure(planner, instrument, n, kind, seed, mode))
                last = rows[-1]
                figures = last.get("error") or (f"makespan {last['makespan_before_s']:.2f} s, violations in the plan "
                                                f"{last['plan_motor_violations']}, after {last['motor_violations']}, segments max "
                                                f"{last['segments_max']}, {last['discretise_s']:.2f} s / plan {last['plan_wall_s']:.1f} s")
                label = "" if mode is None else f" motor_limits={mode}"
                print(f"[{len(rows)}/{total}] {planner} {instrument} {n} {kind} seed {seed}{label}: {figures}", flush=True)
                extra = {"governor": governor_costs(rows)} if args.governor else {}
                tmp = args.out.with_suffix(".tmp")
                tmp.write_text(json.dumps(meta | {"aggregates": aggregate(rows), **extra, "rows": rows}, indent=1))
                tmp.replace(args.out)


if __name__ == "__main__":
    main()
