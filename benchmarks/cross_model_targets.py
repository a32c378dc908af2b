"""How many targets each MOONS collision model refuses when given the other's target sets.

Scenarios generated under one model (``moons``: MOONS' own zones; ``moons-capsules``: fiberplan's
first approximation) are put on the other (``Scenario.with_instrument``), and the targets it
reports ``infeasible`` (conflicting goals, or goals touching a held positioner) are counted::

    python benchmarks/cross_model_targets.py --sizes 61 --seeds 50 --out real_moons_cross_model_61.json
    python benchmarks/cross_model_targets.py --sizes 61 500 --seeds 20     # -> results/real_moons_cross_model.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
from pathlib import Path

import numpy as np
from _machine import machine_info

import fiberplan as fp
from fiberplan.errors import ScenarioError

RESULTS = Path(__file__).resolve().parent / "results"
MODELS = ("moons", "moons-capsules")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[61, 500])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--kinds", nargs="+", default=["random", "unfold"])
    parser.add_argument("--out", default="real_moons_cross_model.json", help="file name in benchmarks/results")
    args = parser.parse_args()
    rows = []
    for n in args.sizes:
        for kind in args.kinds:
            for source in MODELS:
                other = MODELS[1 - MODELS.index(source)]
                inst = fp.load_instrument(other)
                refused, sets, starts_collide = [], 0, 0
                for seed in range(args.seeds):
                    sc = fp.make_scenario(source, n, kind, seed)
                    try:
                        moved = sc.with_instrument(inst, other)
                    except ScenarioError:  # the start configuration itself collides under the other model
                        starts_collide += 1
                        continue
                    refused.append(len(moved.infeasible))
                    sets += len(moved.infeasible) > 0
                rows.append({"n_positioners": n, "scenario_kind": kind, "generated_under": source, "checked_under": other,
                             "seeds": args.seeds, "starts_colliding": starts_collide, "target_sets_with_refusals": sets,
                             "targets_refused_total": int(np.sum(refused)), "targets_refused_mean": float(np.mean(refused)) if refused else None})
                print(json.dumps(rows[-1]))
    out = {"name": "real-moons-cross-model", "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
           "machine": machine_info(), "command": "python benchmarks/cross_model_targets.py " + " ".join(
               [f"--sizes {' '.join(map(str, args.sizes))}", f"--seeds {args.seeds}", f"--kinds {' '.join(args.kinds)}", f"--out {args.out}"]),
           "rows": rows}
    path = RESULTS / args.out
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
