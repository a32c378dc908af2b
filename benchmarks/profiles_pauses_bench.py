"""How the pauses are mended, compared on the same plans: every joint split at every pause
(``split``, as before session 21), running through the pauses inside its segments where the
motors allow (``run_through``: :data:`fiberplan.profiles.STRETCH_PAUSES`), and that with a fit
from the smoothed samples tried where the pauses leave violations or cost makespan
(``dechatter``: :data:`fiberplan.profiles.DECHATTER`), and that with the violating positioners'
back-and-forth cut short (``shortcut``: :data:`fiberplan.profiles.SHORTCUT`, the default).

Each seed is planned once (the planner's instrument defaults; ``--cache DIR`` keeps the plans as
``.h5`` files and reuses them) and discretised each way. Rows: motor-limit violations left and
their kinds, the share ``f`` and the source kept, pauses, pauses run through, segments (sum, max;
moving segments per joint, max), makespan before and after, time::

    python benchmarks/profiles_pauses_bench.py --instrument moons -n 61 --kind unfold \\
        --seeds 15,17,20,27,28,32,39,44,47 --cache /tmp/plans --out benchmarks/results/profiles_pauses.json
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info

WAYS = {"split": (False, False, False), "run_through": (True, False, False), "dechatter": (True, True, False),
        "shortcut": (True, True, True)}  # (STRETCH_PAUSES, DECHATTER, SHORTCUT)


def discretised(result, way: str) -> dict:
    """One discretisation of ``result`` the way named in :data:`WAYS`: its figures."""
    import fiberplan as fp
    import fiberplan.profiles as profiles

    saved = profiles.STRETCH_PAUSES, profiles.DECHATTER, profiles.SHORTCUT
    profiles.STRETCH_PAUSES, profiles.DECHATTER, profiles.SHORTCUT = WAYS[way]
    try:
        started = time.perf_counter()
        made = fp.discretise(result)
        took = time.perf_counter() - started
    finally:
        profiles.STRETCH_PAUSES, profiles.DECHATTER, profiles.SHORTCUT = saved
    moving = np.array([int(np.count_nonzero(p.speeds_rad_s)) for p in made.joints.values()])
    return figures(made, took) | {
        "fraction": made.stats["fraction"],
        "fractions_tried": made.stats["fractions_tried"],
        "source": made.stats["source"],
        "sources_tried": made.stats["sources_tried"],
        "dechattered_samples": made.stats["dechattered_samples"],
        "shortcut_samples": made.stats["shortcut_samples"],
        "pauses_run_through": made.stats["pauses_run_through"],
        "segments_max": int(made.segment_counts().max()),
        "moving_segments_max": int(moving.max()) if len(moving) else 0,
    }


def figures(made, took: float) -> dict:
    """What every profiles benchmark records of one discretisation ``made`` (taking ``took`` s):
    verified, motor-limit violations and their kinds, joints above 128 moving segments, pauses,
    segments (sum, histogram), makespan before and after."""
    counts = made.segment_counts()
    moving = np.array([int(np.count_nonzero(p.speeds_rad_s)) for p in made.joints.values()])
    return {
        "verified_ok": bool(made.report.ok),
        "motor_violations": len(made.report.motor_violations),
        "kinds": dict(collections.Counter(v.kind for v in made.report.motor_violations)),
        "joints_over_128_moving": int(np.count_nonzero(moving > 128)),
        "pauses": made.stats["pauses"],
        "segments_sum": int(counts.sum()),
        "segments_hist": {str(k): int(v) for k, v in zip(*np.unique(counts[counts > 0], return_counts=True), strict=True)},
        "makespan_before_s": made.stats["makespan_before_s"],
        "makespan_after_s": made.stats["makespan_after_s"],
        "discretise_s": took,
    }


def plan_arguments(doc: str, seeds_help: str) -> argparse.ArgumentParser:
    """The options every profiles benchmark takes: which plans (instrument, size, kind, planner,
    seeds), where they are kept (``--cache``) and where the results go (``--out``)."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--instrument", default="moons")
    parser.add_argument("-n", type=int, default=61)
    parser.add_argument("--kind", default="unfold")
    parser.add_argument("--planner", default="mpc")
    parser.add_argument("--seeds", required=True, help=seeds_help)
    parser.add_argument("--cache", type=Path, help="directory of plans kept as .h5 and reused")
    parser.add_argument("--out", type=Path, required=True)
    return parser


def main() -> None:
    parser = plan_arguments(__doc__, "comma-separated seeds")
    parser.add_argument("--ways", default=",".join(WAYS), help=f"comma-separated, of {', '.join(WAYS)}")
    args = parser.parse_args()
    import fiberplan as fp

    seeds = [int(s) for s in args.seeds.split(",")]
    ways = args.ways.split(",")
    unknown = sorted(set(ways) - set(WAYS))
    if unknown:
        parser.error(f"--ways: unknown {unknown}; choose from {', '.join(WAYS)}")
    meta = {"benchmark": "profiles_pauses", "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "machine": machine_info(), "command": " ".join(sys.argv)}
    rows = []
    for seed in seeds:
        cached = None if args.cache is None else args.cache / f"{args.instrument}_{args.n}_{args.kind}_{args.planner}_{seed}.h5"
        if cached is not None and cached.exists():
            result = fp.load_result(cached)
        else:
            result = fp.plan(fp.make_scenario(args.instrument, args.n, args.kind, seed), args.planner)
            if cached is not None:
                cached.parent.mkdir(parents=True, exist_ok=True)
                fp.save_result(result, cached)
        row = {"seed": seed, "plan_wall_s": result.plan_wall_s, "reached": fp.summarize(result)["reached"],
               **{way: discretised(result, way) for way in ways}}
        rows.append(row)
        print(seed, {k: (v["motor_violations"], v["segments_sum"]) for k, v in row.items() if isinstance(v, dict)}, flush=True)
        args.out.write_text(json.dumps(meta | {"rows": rows, "totals": totals(rows, ways)}, indent=1))


def segment_percentiles(figures: list[dict]) -> dict:
    """Segments per moving joint (holds between moves included) over the runs: median, p95, max."""
    counts = np.concatenate([np.repeat([int(k) for k in f["segments_hist"]], list(f["segments_hist"].values())) for f in figures]) \
        if figures else np.zeros(0)
    if not len(counts):
        return {}
    return {"segments_median": float(np.median(counts)), "segments_p95": float(np.percentile(counts, 95)), "segments_max": int(counts.max())}


def totals(rows: list[dict], ways: list[str]) -> dict:
    """Over the rows: runs with violations, violations and segments, each way."""
    out = {}
    for way in ways:
        growth = [r[way]["makespan_after_s"] / r[way]["makespan_before_s"] - 1 for r in rows if r[way]["makespan_before_s"] > 0]
        share = [r[way]["discretise_s"] / r["plan_wall_s"] for r in rows if r["plan_wall_s"]]
        out[way] = {"runs": len(rows), "runs_with_violations": sum(r[way]["motor_violations"] > 0 for r in rows),
                    "makespan_growth_median": float(np.median(growth)), "makespan_growth_max": float(np.max(growth)),
                    "runs_over_5_percent": sum(g > 0.05 for g in growth),
                    "joints_over_128_moving": sum(r[way]["joints_over_128_moving"] for r in rows),
                    "discretise_over_plan_median": float(np.median(share)) if share else None,
                    "motor_violations": sum(r[way]["motor_violations"] for r in rows),
                    "segments_sum": sum(r[way]["segments_sum"] for r in rows),
                    **segment_percentiles([r[way] for r in rows if "segments_hist" in r[way]]),
                    "discretise_s_median": float(np.median([r[way]["discretise_s"] for r in rows]))}
    return out


if __name__ == "__main__":
    main()
