"""The mpc's QP screening (``qp_screen_mm``), on and off, on the same scenarios: what it changes.

    python benchmarks/screening.py --out benchmarks/results/qp_screen_session34.json \
        --sets desi:500:random:0-19,desi:5000:random:0-4,sdss:547:random:0-3,moons-capsules:61:random:0-9
    python benchmarks/screening.py --table benchmarks/results/qp_screen_session34.json

Each scenario (``instrument:N:kind:seeds``; kind ``hard`` for the small hard groups) is planned by
the default ``mpc`` twice, with ``qp_screen_mm = null`` (every positioner in conflict solves its
QP, as before session 34) and with the instrument's default, and both trajectories are verified.
A row records, per variant: reached, makespan over the lower bound, verified, plan wall time, QP
solves and QPs screened. Rows are written after every scenario (atomically) and skipped when the
command is run again. Plan walls compare only on one quiet machine.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info
from scaling import write
from trajectory_hashes import parse_sets

VARIANTS = {"off": {"qp_screen_mm": None}, "default": {}}


def one(inst: str, n: int, kind: str, seed: int) -> dict:
    """Both variants on one scenario."""
    import fiberplan as fp
    from fiberplan.studies.scenarios import hard_scenario

    scenario = hard_scenario(inst, n, seed) if kind == "hard" else fp.make_scenario(inst, n, kind, seed=seed)
    row: dict = {"scenario": f"{inst}:{n}:{kind}:{seed}"}
    for name, settings in VARIANTS.items():
        t = time.perf_counter()
        result = fp.plan(scenario, "mpc", settings)
        wall = time.perf_counter() - t
        report = fp.verify(scenario, result.trajectory)
        s = fp.summarize(result, report)
        row[name] = {"reached": int(s["reached"]), "targets": int(s["targets"]), "makespan_over_bound": float(s["makespan_over_bound"]),
                     "verified_ok": bool(report.ok), "plan_wall_s": round(wall, 3), "qp_solves": int(result.stats.get("qp_solves", 0)),
                     "qp_screened": int(result.stats.get("qp_screened", 0))}
    return row


def table(data: dict) -> str:
    """Markdown summary per set: complete, makespans the same / shorter / longer, medians."""
    import numpy as np

    groups: dict[str, list[dict]] = {}
    for r in data["rows"]:
        inst, n, kind, _ = r["scenario"].split(":")
        groups.setdefault(f"{inst} {n} {kind}", []).append(r)
    lines = ["| set | seeds | complete and verified, off / on | makespan on vs off: shorter / the same / longer | makespan / bound median, off / on "
             "| QP solves, off / on (total) | plan wall median, off / on |", "|---|---|---|---|---|---|---|"]
    for name, rows in groups.items():
        def ok(r: dict, v: str) -> bool:
            return r[v]["verified_ok"] and r[v]["reached"] == r[v]["targets"]
        d = [r["default"]["makespan_over_bound"] - r["off"]["makespan_over_bound"] for r in rows]
        lines.append(f"| {name} | {len(rows)} | {sum(ok(r, 'off') for r in rows)} / {sum(ok(r, 'default') for r in rows)} "
                     f"| {sum(x < -1e-9 for x in d)} / {sum(abs(x) <= 1e-9 for x in d)} / {sum(x > 1e-9 for x in d)} "
                     f"| {np.median([r['off']['makespan_over_bound'] for r in rows]):.3f} / "
                     f"{np.median([r['default']['makespan_over_bound'] for r in rows]):.3f} "
                     f"| {sum(r['off']['qp_solves'] for r in rows):,} / {sum(r['default']['qp_solves'] for r in rows):,} "
                     f"| {np.median([r['off']['plan_wall_s'] for r in rows]):.2f} / {np.median([r['default']['plan_wall_s'] for r in rows]):.2f} s |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="results JSON (read, extended, rewritten after every scenario)")
    parser.add_argument("--sets", default="desi:500:random:0-19", help="instrument:N:kind:first-last, comma-separated")
    parser.add_argument("--table", type=Path, metavar="JSON", help="print the Markdown table of a results file and stop")
    args = parser.parse_args()
    if args.table:
        print(table(json.loads(args.table.read_text())))
        return
    if args.out is None:
        parser.error("give --out (results JSON) or --table")
    data = json.loads(args.out.read_text()) if args.out.exists() else {"name": "qp_screen", "rows": []}
    data.update({"command": " ".join(["python", *sys.argv]), "machine": machine_info(("osqp",))})
    done = {r["scenario"] for r in data["rows"]}
    runs = [(inst, n, kind, seed) for inst, n, kind, seeds in parse_sets(args.sets) for seed in seeds]
    for inst, n, kind, seed in runs:
        if f"{inst}:{n}:{kind}:{seed}" in done:
            continue
        row = one(inst, n, kind, seed)
        data["rows"].append(row)
        data["date_utc"] = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
        write(args.out, data)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
