"""A picture of what ``stretch`` does: every joint's speed over time, as planned and stretched.

    python benchmarks/stretch_figure.py --instrument desi -n 19 --seed 0 --out benchmarks/results/stretch_desi19.png

One hard group (the ``compare`` command's scenarios) planned by the planner (default ``mpc``)
without and with ``stretch = true``, both verified; two panels of every positioner's joint-space
speed ``||dq/dt||`` against time, with the energies and makespans in the titles.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import fiberplan as fp
from fiberplan.studies.scenarios import hard_scenario


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--instrument", default="desi")
    parser.add_argument("-n", type=int, default=19)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--planner", default="mpc")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    scenario = hard_scenario(args.instrument, args.n, args.seed)
    runs = [("as planned", fp.plan(scenario, args.planner)), ("stretched", fp.plan(scenario, args.planner, {"stretch": True}))]
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True, sharey=True)
    for ax, (label, result) in zip(axes, runs, strict=True):
        report = fp.verify(scenario, result.trajectory)
        summary = fp.summarize(result, report)
        times, joints = result.trajectory.times, result.trajectory.joints
        speed = np.linalg.norm(np.diff(joints, axis=0), axis=2) / np.diff(times)[:, None]  # (T - 1, N)
        ax.step(times[:-1], speed, where="post", lw=0.8)
        ax.axvline(summary["makespan_s"], color="k", ls="--", lw=0.8)
        ax.set_title(f"{label}: energy {summary['energy_rad2_s']:.1f} rad²/s, makespan {summary['makespan_s']:.2f} s, "
                     f"{summary['reached']} of {summary['targets']} reached, verified {'clean' if report.ok else 'NOT clean'}", fontsize=9)
        ax.set_ylabel("joint speed ||dq/dt|| (rad/s)")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(f"{args.planner}, {args.instrument} {args.n} hard seed {args.seed}: each line one positioner", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
