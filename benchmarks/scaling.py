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

Resident peaks count a page shared between the planning process and a forked one (the start
schedule's second half above 10,000 positioners, the parallel executor's workers) in both. With
``--pss`` a thread also samples, every 0.1 s while planning and verifying, the memory the process
and all its descendants hold together (``/proc/PID/smaps_rollup``): their anonymous and shared
memory as proportional set sizes (``Pss_Anon + Pss_Shmem``: a page shared after a fork counted
once, split between the processes), plus the largest file-backed resident set among them (``Rss -
Anonymous``: the libraries, counted whole and once). Its largest sample is ``tree_pss_peak_mb``
(Linux only; the sampling costs some CPU, so time the runs without it).
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


class TreePss:
    """Samples the memory this process and its descendants hold together (the module docstring), in a thread; ``peak_mb``."""

    def __init__(self, every_s: float = 0.1) -> None:
        import threading

        self.every_s, self.peak_kb, self.samples = every_s, 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def _tree(pid: int) -> list[int]:
        out, todo = [], [pid]
        while todo:
            p = todo.pop()
            out.append(p)
            for task in Path(f"/proc/{p}/task").glob("*"):
                try:
                    todo += [int(c) for c in (task / "children").read_text().split()]
                except OSError:  # (the process or thread ended meanwhile)
                    pass
        return out

    @staticmethod
    def _rollup_kb(pid: int) -> dict[str, int]:
        try:
            rows = [line.split() for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]]
        except OSError:  # (ended meanwhile)
            return {}
        return {row[0].rstrip(":"): int(row[1]) for row in rows if len(row) >= 2 and row[1].isdigit()}

    def _run(self) -> None:
        while not self._stop.is_set():
            rollups = [self._rollup_kb(p) for p in self._tree(os.getpid())]
            held = sum(r.get("Pss_Anon", 0) + r.get("Pss_Shmem", 0) for r in rollups)
            files = max((r.get("Rss", 0) - r.get("Anonymous", 0) for r in rollups), default=0)
            self.peak_kb = max(self.peak_kb, held + files)
            self.samples += 1
            self._stop.wait(self.every_s)

    def __enter__(self) -> TreePss:
        pid = os.getpid()
        if not (Path(f"/proc/{pid}/smaps_rollup").exists() and Path(f"/proc/{pid}/task/{pid}/children").exists()):
            raise SystemExit("--pss needs Linux's /proc/PID/smaps_rollup and /proc/PID/task/TID/children")
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def peak_mb(self) -> float:
        return self.peak_kb / 1024.0


def one(n: int, executor: str, seed: int, instrument: str, pss: bool = False) -> dict:
    """Generate, plan and verify one scenario in this process; the figures of the run."""
    import contextlib
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
    with TreePss() if pss else contextlib.nullcontext() as sampler:
        result = plan(scenario, "mpc", {"executor": executor})
        plan_peak = peak_mb()
        t = time.perf_counter()
        report = verify(scenario, result.trajectory)
        verify_s = time.perf_counter() - t
    summary = summarize(result, report)
    extra = {"tree_pss_peak_mb": round(sampler.peak_mb, 1), "tree_pss_samples": sampler.samples} if sampler is not None else {}
    return extra | {
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
        if "tree_pss_peak_mb" in r:
            mem += f"; all processes together {r['tree_pss_peak_mb']:.0f} MB"
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
    parser.add_argument("--pss", action="store_true", help="also sample the memory the process tree holds together (tree_pss_peak_mb; Linux)")
    parser.add_argument("--table", type=Path, metavar="JSON", help="print the Markdown table of a results file and stop")
    parser.add_argument("--one", nargs=3, metavar=("N", "EXECUTOR", "SEED"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(one(int(args.one[0]), args.one[1], int(args.one[2]), args.instrument, args.pss)))
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
                child = subprocess.run([sys.executable, __file__, "--instrument", args.instrument, "--one", str(n), executor, str(seed),
                                        *(["--pss"] if args.pss else [])],
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
