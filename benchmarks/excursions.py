"""Excursions: how far each positioner's joints go beyond its move, in the central reference and in a planner's plan.

    python benchmarks/excursions.py --instrument sdss -n 19 --seeds 0,3,8,10 --out benchmarks/results/excursions_sdss_19.json

A positioner's *excursion* on a joint is how far that joint goes outside the interval between its
start and its target (degrees): 0 for a joint that moves monotonically, as every move of the
``prioritized`` schedule's straight, delayed and L-shaped moves does. On each hard group (the
``compare`` command's scenarios) the central reference (CasADi + IPOPT) and the planner (default
``mpc``, its default route) are planned and verified; per seed the file records both makespans, the
lower bound, the planner's chosen candidate, and per plan the positioners whose excursion exceeds
``--beyond-deg`` (default 10) on some joint and the largest excursion of each joint. It is how
``docs/results.md`` says what the central reference does that the planner's candidates do not.
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


def excursions_deg(start: np.ndarray, target: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """``(N, 2)``: how far each joint goes outside ``[start, target]`` along ``joints`` ``(T, N, 2)`` (degrees)."""
    d = target - start
    sign = np.where(d >= 0.0, 1.0, -1.0)
    along = (joints - start[None]) * sign[None]  # the move's direction positive
    beyond = np.maximum(along.max(axis=0) - np.abs(d), 0.0)
    behind = np.maximum(-along.min(axis=0), 0.0)
    return np.degrees(np.maximum(beyond, behind))


def one(instrument: str, n: int, seed: int, planner: str, beyond_deg: float) -> dict:
    import fiberplan as fp
    from fiberplan.metrics import lower_bound_s
    from fiberplan.studies.scenarios import hard_scenario

    scenario = hard_scenario(instrument, n, seed)
    row: dict = {"seed": seed, "lower_bound_s": lower_bound_s(scenario)}
    for name in ("central", planner):
        t = time.perf_counter()
        result = fp.plan(scenario, name)
        wall = time.perf_counter() - t
        summary = fp.summarize(result, fp.verify(scenario, result.trajectory))
        exc = excursions_deg(scenario.start, scenario.target, result.trajectory.joints)
        row[name] = {
            "makespan_s": summary["makespan_s"], "reached": summary["reached"], "verified_ok": summary["verified_ok"],
            "plan_wall_s": round(wall, 2), "chosen": result.stats.get("chosen"),
            f"positioners_beyond_{beyond_deg:g}_deg": int((exc.max(axis=1) > beyond_deg).sum()),
            "largest_excursion_deg": [round(float(v), 1) for v in exc.max(axis=0)],
            "excursion_deg": np.round(exc, 1).tolist(),
        }
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--instrument", default="sdss")
    parser.add_argument("-n", type=int, default=19)
    parser.add_argument("--seeds", default="0,3,8,10", help="comma-separated seeds")
    parser.add_argument("--planner", default="mpc")
    parser.add_argument("--beyond-deg", type=float, default=10.0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.out.exists():
        sys.exit(f"excursions.py: {args.out} exists; give another --out")
    seeds = [int(s) for s in args.seeds.split(",")]
    data = {"name": args.out.stem, "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "machine": machine_info(("casadi",)), "command": " ".join(["python", *sys.argv]), "rows": []}
    for seed in seeds:
        data["rows"].append(one(args.instrument, args.n, seed, args.planner, args.beyond_deg))
        write(args.out, data)  # after every seed, atomically: an interrupted run keeps what it finished
        r = data["rows"][-1]
        key = f"positioners_beyond_{args.beyond_deg:g}_deg"
        print(f"seed {seed}: central {r['central']['makespan_s']:.2f} s, {r['central'][key]} beyond; "
              f"{args.planner} {r[args.planner]['makespan_s']:.2f} s ({r[args.planner]['chosen']}), {r[args.planner][key]} beyond", flush=True)


if __name__ == "__main__":
    main()
