"""Lower bounds of the routes through folded configurations, against the direct bound.

For random -> random moves on a dense instrument the coordination layer plans two legs through the
datum. Whatever the planner, a route fixes each positioner's joint path, and so a lower bound on
its duration (each joint at full speed, no waiting). This script computes, per seed, the largest
per-positioner bound of each route family divided by the direct bound (the slowest straight joint
move):

- ``via_datum``: to the datum and out again (alpha through the datum's alpha);
- ``best_fold``: to a folded configuration at the best alpha of each positioner's own (alpha
  anywhere; each leg's time is the larger of its two joints' moves);
- ``nearest_datum``: to a folded configuration at the alpha of each positioner's own move nearest
  the datum's (every arm then turns towards the datum's alpha or holds it, as through the datum);
- ``retract_rotate_extend``: beta folded with alpha held, alpha turned folded, beta out again
  (the three in sequence: alpha turns only while folded);
- ``concurrent``: the same joint paths with alpha turning during the beta moves (no ordering).

Usage::

    python benchmarks/route_bounds.py --instrument sdss -n 547 --seeds 20 --out benchmarks/results/route_bounds_sdss547.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info

import fiberplan as fp


def route_ratios(scenario: fp.Scenario) -> dict[str, float]:
    """Each route family's largest per-positioner time bound over the direct bound."""
    inst = scenario.instrument
    w = inst.speeds_rad_s
    s, g = scenario.start, scenario.target
    free = scenario.has_target & ~scenario.locked
    s, g = s[free], g[free]
    datum = np.asarray(inst.datum_rad)
    direct = np.max(np.abs(g - s) / w, axis=1)
    bound = float(direct.max())

    def leg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.max(np.abs(b - a) / w, axis=1)

    via_datum = leg(s, np.broadcast_to(datum, s.shape)) + leg(np.broadcast_to(datum, g.shape), g)
    beta_out = np.abs(s[:, 1] - datum[1]) / w[1]
    beta_in = np.abs(g[:, 1] - datum[1]) / w[1]
    alpha = np.abs(g[:, 0] - s[:, 0]) / w[0]
    rre = beta_out + alpha + beta_in
    # Best hold alpha per positioner: a fold leg takes max(alpha part, beta part); with the hold alpha
    # on the segment between start and target alphas, the two alpha parts sum to the direct alpha move.
    grid = np.linspace(0.0, 1.0, 201)
    hold = s[:, :1] + grid[None, :] * (g[:, :1] - s[:, :1])
    best_fold = np.min(np.maximum(np.abs(hold - s[:, :1]) / w[0], beta_out[:, None])
                       + np.maximum(np.abs(g[:, :1] - hold) / w[0], beta_in[:, None]), axis=1)
    concurrent = np.maximum(alpha, beta_out + beta_in)
    near = np.clip(datum[0], np.minimum(s[:, 0], g[:, 0]), np.maximum(s[:, 0], g[:, 0]))
    held = np.column_stack([near, np.full(len(near), datum[1])])
    nearest_datum = leg(s, held) + leg(held, g)
    return {"direct_bound_s": bound, **{name: float(v.max() / bound) for name, v in
                                        (("via_datum", via_datum), ("best_fold", best_fold), ("nearest_datum", nearest_datum),
                                         ("retract_rotate_extend", rre), ("concurrent", concurrent))}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--instrument", default="sdss")
    ap.add_argument("-n", "--positioners", type=int, default=547)
    ap.add_argument("--kind", default="random")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    inst = fp.load_instrument(args.instrument)
    rows = []
    for seed in range(args.seeds):
        scenario = fp.make_scenario(inst, args.positioners, args.kind, seed=seed)
        rows.append({"seed": seed} | route_ratios(scenario))
    names = ["via_datum", "best_fold", "nearest_datum", "retract_rotate_extend", "concurrent"]
    summary = {name: {"median": statistics.median(r[name] for r in rows), "min": min(r[name] for r in rows),
                      "max": max(r[name] for r in rows)} for name in names}
    out = {"machine": machine_info(), "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
           "instrument": args.instrument, "positioners": args.positioners, "kind": args.kind, "rows": rows, "summary": summary}
    args.out.write_text(json.dumps(out, indent=1))
    for name in names:
        s = summary[name]
        print(f"{name:24s} median {s['median']:.2f}  range {s['min']:.2f}-{s['max']:.2f}")


if __name__ == "__main__":
    main()
