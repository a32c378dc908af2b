"""Group moves' search alone on a stalled fold: the unfold scenario's fold from its targets, the
mpc's first attempt alone (``route = direct``, one attempt, no tails, no restarts), then
:func:`fiberplan.planners.coordination.groups.groups` on what it left short; prints the search's
wall time and the moves' fingerprint (the same fingerprint: the same moves).

The first attempts are planned once and kept in ``--cache`` (they do not depend on the group
moves), so that timing code changes of the group moves, whole process, with ``farm-bench``, times
the search::

    python benchmarks/group_search.py --cache /tmp/stalls 5 2      # plan and keep the attempts once
    farm-bench -n 3 --pin 0 --vs 'env PYTHONPATH=<before>/src python benchmarks/group_search.py --cache /tmp/stalls 5 2' \\
        -- env PYTHONPATH=<after>/src python benchmarks/group_search.py --cache /tmp/stalls 5 2
"""

from __future__ import annotations

import argparse
import hashlib
import time
from pathlib import Path

import numpy as np

import fiberplan as fp
from fiberplan.geometry import default_safety_margin_mm
from fiberplan.planners.coordination.groups import groups
from fiberplan.planners.coordination.legs import leg_scenario, trim
from fiberplan.planners.coordination.settings import REVERSE_LEG


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("seeds", type=int, nargs="+", help="MOONS 500 unfold seeds")
    parser.add_argument("--instrument", default="moons-capsules")
    parser.add_argument("-n", type=int, default=500)
    parser.add_argument("--cache", type=Path, required=True, help="directory keeping the first attempts")
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
        scenario = fp.make_scenario(args.instrument, args.n, "unfold", seed=seed)
        fold = leg_scenario(scenario, scenario.target, scenario.start, REVERSE_LEG)
        kept = args.cache / f"stall_{args.instrument}_{args.n}_{seed}.npz"
        if kept.exists():
            with np.load(kept) as f:
                joints, dt = f["joints"], float(f["dt"])
        else:
            settings = {"route": "direct", "route_attempts": 1, "route_tails": False, "route_restarts": False}
            result = fp.plan(fold, "mpc", settings)
            joints, dt = trim(result.trajectory.joints), float(result.settings["dt_s"])
            tmp = kept.with_suffix(".tmp.npz")
            np.savez(tmp, joints=joints, dt=dt)
            tmp.replace(kept)
        t0 = time.perf_counter()
        out = groups(fold, joints, default_safety_margin_mm(fold.instrument), dt)
        wall = time.perf_counter() - t0
        digest = "none" if out is None else hashlib.sha256(np.ascontiguousarray(out).tobytes()).hexdigest()[:16]
        print(f"{args.instrument} {args.n} unfold seed {seed}: group search {wall:.1f} s, moves {digest}", flush=True)


if __name__ == "__main__":
    main()
