"""Plan one fold leg alone: the unfold scenario's fold from its targets to the datum, by the mpc
alone (``route = direct``), and print its wall time and the trajectory's fingerprint.

The leg the coordination layer plans first for an unfold (and plays backwards); a unit of work
to time code changes of the planner on MOONS' own zones, whole process, with ``farm-bench``::

    farm-bench -n 2 --vs 'env PYTHONPATH=<before>/src python benchmarks/fold_leg.py moons 500 2' \\
        -- env PYTHONPATH=<after>/src python benchmarks/fold_leg.py moons 500 2
"""

from __future__ import annotations

import argparse
import hashlib
import time

import fiberplan as fp
from fiberplan.planners.coordination.legs import leg_scenario


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("instrument")
    parser.add_argument("n", type=int)
    parser.add_argument("seed", type=int)
    args = parser.parse_args()
    scenario = fp.make_scenario(args.instrument, args.n, "unfold", seed=args.seed)
    fold = leg_scenario(scenario, scenario.target, scenario.start, "fold")
    t0 = time.perf_counter()
    result = fp.plan(fold, "mpc", {"route": "direct"})
    wall = time.perf_counter() - t0
    digest = hashlib.sha256(result.trajectory.joints.tobytes()).hexdigest()[:16]
    print(f"{args.instrument} {args.n} unfold seed {args.seed}, the fold leg: {wall:.1f} s of planning, joints {digest}")


if __name__ == "__main__":
    main()
