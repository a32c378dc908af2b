"""Merge the runs of a continuation of ``bench_mpc.py`` into a result file.

Long sets are measured in pieces (``--first-seed``, ``--budget-s``, one piece per core); this
adds the extra file's runs of one cell (``kind``, ``N``) to the main file, for the seeds that
every planner of the extra file finished and the main file lacks, recomputes the summaries and
records the piece under ``merged_runs`` (its command, date, machine and seeds); a cell the main file
lacks is added whole::

    python benchmarks/bench_mpc.py sdss --first-seed 3 --seeds 17 --out /tmp/sdss3.json
    python benchmarks/merge_mpc.py benchmarks/results/mpc_sdss.json /tmp/sdss3.json random 547
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_mpc


def _piece(extra: dict[str, Any]) -> dict[str, Any]:
    """What ``merged_runs`` records of a piece: its command, date and machine (a piece may have
    run on another machine than the main file, so its wall times need its own machine)."""
    return {"command": extra["command"], "date_utc": extra["date_utc"], "machine": extra.get("machine")}


def merge(main: dict[str, Any], extra: dict[str, Any], kind: str, n: int) -> dict[str, tuple[int, float]]:
    """Merge in place; returns ``planner -> (seeds, success mean)`` of the merged cells."""

    def cells(doc: dict[str, Any]) -> dict[str, dict[str, Any]]:
        return {c["planner"]: c for c in doc["cells"] if c["kind"] == kind and c["n_positioners"] == n}

    cm, ce = cells(main), cells(extra)
    if not cm and ce:
        # A cell the main file lacks (another kind or N measured as a separate piece): added
        # whole, for the seeds every planner finished (a piece stopped mid-seed may have one
        # planner's run more).
        seeds = sorted(set.intersection(*({r["seed"] for r in c["runs"]} for c in ce.values())))
        for cell in ce.values():
            cell["runs"] = [r for r in cell["runs"] if r["seed"] in seeds]
            cell["summary"] = bench_mpc.aggregate_runs(cell["runs"])
        main["cells"].extend(ce.values())
        for key, value in (("kinds", kind), ("sizes", n)):
            if value not in main["parameters"][key]:
                main["parameters"][key].append(value)
        main.setdefault("merged_runs", []).append({**_piece(extra), "seeds": seeds, "new_cell": True})
        return {p: (c["summary"]["seeds_run"], c["summary"]["success_rate_mean"]) for p, c in ce.items()}
    if not cm or set(cm) != set(ce):
        raise SystemExit(f"cells of {kind} N={n}: main has planners {sorted(cm)}, extra {sorted(ce)}")
    common = set.intersection(*({r["seed"] for r in c["runs"]} for c in ce.values()))
    added: set[int] = set()
    for planner, cell in cm.items():
        have = {r["seed"] for r in cell["runs"]}
        new = [r for r in ce[planner]["runs"] if r["seed"] in common and r["seed"] not in have]
        added |= {r["seed"] for r in new}
        cell["runs"] = sorted(cell["runs"] + new, key=lambda r: r["seed"])
        cell["summary"] = bench_mpc.aggregate_runs(cell["runs"])
    main.setdefault("merged_runs", []).append({**_piece(extra), "seeds": sorted(added)})
    return {p: (c["summary"]["seeds_run"], c["summary"]["success_rate_mean"]) for p, c in cm.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("main", type=Path)
    parser.add_argument("extra", type=Path)
    parser.add_argument("kind")
    parser.add_argument("n", type=int)
    args = parser.parse_args()
    doc = json.loads(args.main.read_text())
    summary = merge(doc, json.loads(args.extra.read_text()), args.kind, args.n)
    bench_mpc.write_result(args.main, doc)
    print({p: (s, round(r, 4)) for p, (s, r) in summary.items()})


if __name__ == "__main__":
    main()
