"""The ``stretch`` setting on whole fields: energy before and after, the same makespan, verified.

    python benchmarks/stretch_bench.py --sets desi:500:random:0-9,sdss:547:random:0-4 --out benchmarks/results/stretch_fields.json

Each scenario is planned twice by the planner (default ``mpc``, its default route), without and
with ``stretch = true``; both trajectories are verified. Per run the file records both energies,
makespans (the stretched one is never later: checked) and plan walls, both runs' motor-limit
violations where the instrument states limits, the positioners stretched, and the stretch's own time:
``planners.stretch.stretch`` timed alone on the plain plan, which is what ``plan`` applies (the
stretched run's trajectory must equal that stretch, bit for bit; a mismatch is recorded as an
error).
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info
from scaling import write

import fiberplan as fp
from fiberplan.planners.stretch import stretch


def _sets(text: str) -> list[tuple[str, int, str, int]]:
    """``inst:n:kind:a-b,...`` -> (instrument, n, kind, seed) runs."""
    runs = []
    for part in text.split(","):
        inst, n, kind, seeds = part.split(":")
        lo, _, hi = seeds.partition("-")
        runs += [(inst, int(n), kind, s) for s in range(int(lo), int(hi or lo) + 1)]
    return runs


def one(instrument: str, n: int, kind: str, seed: int, planner: str) -> dict:
    scenario = fp.make_scenario(instrument, n, kind, seed)
    plain = fp.plan(scenario, planner)
    stretched = fp.plan(scenario, planner, {"stretch": True})
    t0 = time.perf_counter()
    alone = stretch(scenario, plain.trajectory.times, plain.trajectory.joints, float(plain.settings["safety_margin_mm"]))
    stretch_s = time.perf_counter() - t0
    row: dict = {"instrument": instrument, "n": n, "kind": kind, "seed": seed, "planner": planner, "stretch_s": stretch_s}
    for name, result in (("plain", plain), ("stretched", stretched)):
        report = fp.verify(scenario, result.trajectory)
        s = fp.summarize(result, report)
        row[name] = {k: s[k] for k in ("reached", "targets", "makespan_s", "makespan_over_bound", "energy_rad2_s",
                                       "plan_wall_s", "collisions", "verified_ok", "min_clearance_mm", "motor_violations")}
    row["positioners_stretched"] = stretched.stats["stretch"]["positioners"]
    row["energy_change"] = row["stretched"]["energy_rad2_s"] / row["plain"]["energy_rad2_s"] - 1.0
    row["same_makespan"] = row["stretched"]["makespan_s"] == row["plain"]["makespan_s"]
    row["makespan_not_later"] = row["stretched"]["makespan_s"] <= row["plain"]["makespan_s"]
    if not np.array_equal(stretched.trajectory.joints, alone.joints):
        row["error"] = "the stretched run differs from the stretch of the plain run"
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", required=True, help="instrument:n:kind:first-last,...")
    parser.add_argument("--planner", default="mpc")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.out.exists():
        sys.exit(f"stretch_bench.py: {args.out} exists; give another --out")
    data = {"name": args.out.stem, "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "machine": machine_info(), "command": " ".join(["python", *sys.argv]), "rows": []}
    for inst, n, kind, seed in _sets(args.sets):
        r = one(inst, n, kind, seed, args.planner)
        data["rows"].append(r)
        write(args.out, data)  # after every run, atomically: an interrupted run keeps what it finished
        print(f"{inst} {n} {kind} seed {seed}: energy {r['energy_change']:+.1%}, {r['positioners_stretched']} stretched, "
              f"makespan {r['plain']['makespan_s']:.2f} -> {r['stretched']['makespan_s']:.2f} s, verified "
              f"{r['plain']['verified_ok']}/{r['stretched']['verified_ok']}, stretch {r['stretch_s']:.2f} s"
              + (f"  ERROR {r['error']}" if "error" in r else ""), flush=True)
    rows = data["rows"]
    for key in sorted({(r["instrument"], r["n"], r["kind"]) for r in rows}):
        sel = [r for r in rows if (r["instrument"], r["n"], r["kind"]) == key]
        change = np.array([r["energy_change"] for r in sel])
        print(f"{key[0]} {key[1]} {key[2]}: {len(sel)} runs, energy change median {np.median(change):+.1%} "
              f"(range {change.min():+.1%} to {change.max():+.1%}), same makespan {sum(r['same_makespan'] for r in sel)}, "
              f"not later {sum(r['makespan_not_later'] for r in sel)}, "
              f"verified {sum(r['stretched']['verified_ok'] for r in sel)}, stretch median {np.median([r['stretch_s'] for r in sel]):.2f} s")


if __name__ == "__main__":
    main()
