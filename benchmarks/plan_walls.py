"""Plan wall time of one set, seed after seed in this one process (run it alone: the figure is the
machine's), with each plan's makespan and chosen route.

    python benchmarks/plan_walls.py --instrument sdss -n 547 --kind random --seeds 20 --planners mpc,dnf --name plan_walls_sdss547
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from bench import write_summary  # (benchmarks/ is on the path when run as a script)

import fiberplan as fp


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--instrument", default="sdss")
    parser.add_argument("-n", type=int, default=547)
    parser.add_argument("--kind", default="random")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--planners", default="mpc,dnf")
    parser.add_argument("--name", required=True, help="result file name in benchmarks/results/")
    args = parser.parse_args()
    rows = []
    for planner in args.planners.split(","):
        for seed in range(args.seeds):
            scenario = fp.make_scenario(args.instrument, args.n, args.kind, seed)
            result = fp.plan(scenario, planner)
            summary = fp.summarize(result, fp.verify(scenario, result.trajectory))
            rows.append({"planner": planner, "seed": seed, "plan_wall_s": result.plan_wall_s, "makespan_s": summary["makespan_s"],
                         "makespan_over_bound": summary["makespan_over_bound"], "reached": summary["reached"],
                         "targets": summary["targets"], "verified_ok": summary["verified_ok"], "chosen": result.stats.get("chosen")})
            print(planner, seed, f"{result.plan_wall_s:.1f} s", f"{summary['makespan_over_bound']:.3f} x", flush=True)
    per = {}
    for planner in args.planners.split(","):
        walls = np.array([r["plan_wall_s"] for r in rows if r["planner"] == planner])
        per[planner] = {"plan_wall_s_median": float(np.median(walls)), "plan_wall_s_max": float(walls.max()),
                        "makespan_over_bound_median": float(np.median([r["makespan_over_bound"] for r in rows if r["planner"] == planner])),
                        "seeds": len(walls)}
    # (write_summary records the machine, the versions and the commit of the fiberplan imported)
    path = write_summary(args.name, {"command": " ".join(sys.argv), "set": vars(args), "summary": per, "rows": rows})
    print(per)
    print("wrote", path)


if __name__ == "__main__":
    main()
