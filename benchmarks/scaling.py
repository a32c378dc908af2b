"""Scaling: plan and verify N = 500 ... 50,000 DESI-like positioners in one process, with the time split.

    python benchmarks/scaling.py --out benchmarks/results/scaling.json            # every size, both executors
    python benchmarks/scaling.py --out benchmarks/results/scaling.json --sizes 50000 --executors sequential
    python benchmarks/scaling.py --table benchmarks/results/scaling.json          # Markdown, for docs/results.md

Each run (size, executor, seed) is its own process, so its peak memory is its own: the scenario is
generated (``random``, seed 0 unless ``--seeds``), planned with the default ``mpc`` and verified by
the independent verifier, as ``fiberplan plan`` does. A run records: generation, plan, start schedule
(inside the plan) and verify wall times; the peak resident memory of the planning process after
planning and after verifying, and of its worker processes (the ``parallel`` executor); reached,
makespan over the lower bound, collisions, and the smallest clearance of the generated start.
Finished runs are kept in ``--out`` (written after every run, atomically) and skipped when the
command is run again, so an interrupted sweep loses nothing; ``--force`` runs them again.

Timing figures are only comparable on one quiet machine: run nothing else beside this.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info

SIZES = (500, 1000, 2000, 5000, 10000, 20000, 50000)
EXECUTORS = ("sequential", "parallel")
TARGETS = "50,000: plan <= 30 s, peak memory <= 2 GB, makespan <= 1.2 x bound, verify <= 15 s, plan <= 10 x that at 5,000"


def one(n: int, executor: str, seed: int, instrument: str) -> dict:
    """Generate, plan and verify one scenario in this process; the figures of the run."""
    import resource

    from fiberplan.generate import make_scenario
    from fiberplan.geometry import min_pair_clearance
    from fiberplan.metrics import summarize
    from fiberplan.planners import plan
    from fiberplan.verify import verify

    def peak_mb(who: int = resource.RUSAGE_SELF) -> float:
        return resource.getrusage(who).ru_maxrss / 1024.0

    t = time.perf_counter()
    scenario = make_scenario(instrument, n, "random", seed)
    gen_s = time.perf_counter() - t
    start_clearance = float(min_pair_clearance(scenario.instrument, scenario.base_xy, scenario.orient, scenario.start,
                                               scenario.pairs).min())
    result = plan(scenario, "mpc", {"executor": executor})
    plan_peak = peak_mb()
    t = time.perf_counter()
    report = verify(scenario, result.trajectory)
    verify_s = time.perf_counter() - t
    summary = summarize(result, report)
    return {
        "n": n, "executor": executor, "seed": seed, "instrument": instrument,
        "samples": int(result.trajectory.joints.shape[0]),
        "generate_s": round(gen_s, 3),
        "plan_s": round(result.plan_wall_s, 3),
        "schedule_s": round(float(result.stats.get("schedule_wall_s", 0.0)), 3),
        "verify_s": round(verify_s, 3),
        "peak_mb_after_plan": round(plan_peak, 1),
        "peak_mb": round(peak_mb(), 1),
        # The largest forked process: a worker of the parallel executor, or (above 10,000 positioners, either
        # executor) the start schedule's second half.
        "worker_peak_mb": round(peak_mb(resource.RUSAGE_CHILDREN), 1),
        **{key: summary[key] for key in ("reached", "targets", "makespan_s", "lower_bound_s", "makespan_over_bound",
                                         "collisions", "limit_violations", "verified_ok")},
        "min_start_clearance_mm": start_clearance,
    }


def write(path: Path, data: dict) -> None:
    """Write ``data`` as JSON under a temporary name and rename it into place."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def table(data: dict) -> str:
    """Markdown table of the runs, sequential and parallel side by side per size."""
    rows = sorted(data["runs"], key=lambda r: (r["n"], r["seed"], EXECUTORS.index(r["executor"])))
    lines = ["| N | executor | seed | plan | of it the start schedule | verify | peak memory | makespan / bound | reached | min start clearance |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        mem = f"{r['peak_mb']:.0f} MB" + (f" (+ largest forked process {r['worker_peak_mb']:.0f} MB)" if r["worker_peak_mb"] > 0 else "")
        ratio = f"{r['makespan_over_bound']:.2f}" if r["makespan_over_bound"] is not None else "-"
        lines.append(f"| {r['n']:,} | {r['executor']} | {r['seed']} | {r['plan_s']:.1f} s | {r['schedule_s']:.1f} s | {r['verify_s']:.1f} s "
                     f"| {mem} | {ratio} | {r['reached']:,} / {r['targets']:,} | {r['min_start_clearance_mm'] * 1000:.2f} um |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="results JSON (read, extended, rewritten after every run)")
    parser.add_argument("--sizes", default=",".join(map(str, SIZES)), help="comma-separated N")
    parser.add_argument("--executors", default=",".join(EXECUTORS), help="sequential, parallel or both")
    parser.add_argument("--seeds", type=int, default=1, help="seeds 0 .. SEEDS-1 per size")
    parser.add_argument("--instrument", default="desi")
    parser.add_argument("--force", action="store_true", help="run finished runs again")
    parser.add_argument("--table", type=Path, metavar="JSON", help="print the Markdown table of a results file and stop")
    parser.add_argument("--one", nargs=3, metavar=("N", "EXECUTOR", "SEED"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(one(int(args.one[0]), args.one[1], int(args.one[2]), args.instrument)))
        return
    if args.table:
        print(table(json.loads(args.table.read_text())))
        return
    if args.out is None:
        parser.error("give --out (results JSON) or --table")
    try:
        sizes = [int(s) for s in args.sizes.split(",")]
    except ValueError:
        parser.error(f"--sizes must be comma-separated integers, found {args.sizes!r}")
    executors = args.executors.split(",")
    unknown = [e for e in executors if e not in EXECUTORS]
    if unknown:
        parser.error(f"unknown executor {unknown[0]!r}; choose from {', '.join(EXECUTORS)}")
    data = json.loads(args.out.read_text()) if args.out.exists() else {"name": "scaling", "runs": []}
    data.update({"command": " ".join(["python", *sys.argv]), "targets": TARGETS})
    done = {(r["n"], r["executor"], r["seed"], r["instrument"]) for r in data["runs"]}
    for n in sizes:
        for seed in range(args.seeds):
            for executor in executors:
                key = (n, executor, seed, args.instrument)
                if key in done and not args.force:
                    continue
                print(f"N={n} {executor} seed {seed} ...", file=sys.stderr, flush=True)
                child = subprocess.run([sys.executable, __file__, "--instrument", args.instrument, "--one", str(n), executor, str(seed)],
                                       capture_output=True, text=True, check=False)
                if child.returncode != 0:
                    sys.exit(f"N={n} {executor} seed {seed} failed (results so far kept in {args.out}):\n{child.stderr[-3000:]}")
                run = json.loads(child.stdout.strip().splitlines()[-1])
                run["machine"] = machine_info(("osqp",))
                run["date_utc"] = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
                data["runs"] = [r for r in data["runs"] if (r["n"], r["executor"], r["seed"], r["instrument"]) != key] + [run]
                write(args.out, data)
                print(json.dumps({k: run[k] for k in ("n", "executor", "plan_s", "schedule_s", "verify_s", "peak_mb",
                                                      "makespan_over_bound", "reached")}), file=sys.stderr, flush=True)
    print(table(data))


if __name__ == "__main__":
    main()
