"""Fingerprints of planned trajectories, to show that a refactor changes no trajectory.

Plans the seeds the house issue names (DESI 500 random seeds 0-9, MOONS 61 unfold and random
seeds 0-4, SDSS 61 random seeds 0-4) with a planner's instrument defaults and writes, per run,
the SHA-256 of ``joints_rad`` (float64, C order) and of ``time_s``, with the run's counters::

    python benchmarks/trajectory_hashes.py --out /tmp/before.json
    PYTHONPATH=<snapshot>/src python benchmarks/trajectory_hashes.py --out /tmp/after.json
    python benchmarks/trajectory_hashes.py --compare /tmp/before.json /tmp/after.json

``--compare`` exits 1 and names every run whose trajectory differs. ``--sets`` plans other sets,
e.g. ``--sets moons-capsules:61:random:0-4,sdss:547:random:0-1,sdss:7:hard:0-9`` (``hard``: the groups of the gap tables).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

# The presets these name changed geometry after the house issue: `moons` is MOONS' own model since
# 80f3799 (the earlier one is `moons-capsules`), `sdss` the SDSS-V one since edda61d (`sdss-conservative`).
# Compare two snapshots of the same geometry, or edit the names here.
SETS = (
    ("desi", 500, "random", range(10)),
    ("moons", 61, "unfold", range(5)),
    ("moons", 61, "random", range(5)),
    ("sdss", 61, "random", range(5)),
)


def fingerprints(planner: str, sets=SETS, quick: bool = False) -> dict[str, dict]:
    """Plan every run of ``sets``; the fingerprint of each, keyed ``instrument-n-kind-seed``."""
    import numpy as np

    import fiberplan as fp
    from fiberplan.studies.scenarios import hard_scenario

    out: dict[str, dict] = {}
    for instrument, n, kind, seeds in sets:
        for seed in list(seeds)[: 1 if quick else None]:
            # hard: the clustered groups of the gap tables (fiberplan.studies.scenarios.hard_scenario)
            scenario = hard_scenario(instrument, n, seed) if kind == "hard" else fp.make_scenario(instrument, n, kind, seed)
            t0 = time.perf_counter()
            result = fp.plan(scenario, planner)
            joints = np.ascontiguousarray(result.trajectory.joints, dtype=np.float64)
            times = np.ascontiguousarray(result.trajectory.times, dtype=np.float64)
            key = f"{instrument}-{n}-{kind}-{seed}"
            out[key] = {
                "joints_sha256": hashlib.sha256(joints.tobytes()).hexdigest(),
                "times_sha256": hashlib.sha256(times.tobytes()).hexdigest(),
                "shape": list(joints.shape),
                "outcome_reached": int((result.outcome == "reached").sum()),
                "plan_wall_s": round(time.perf_counter() - t0, 3),
            }
            print(f"{key}: {out[key]['joints_sha256'][:16]} {out[key]['shape']}", file=sys.stderr)
    return out


def parse_sets(text: str) -> tuple[tuple[str, int, str, range], ...]:
    """``instrument:n:kind:first-last`` (or one seed), comma-separated."""
    sets = []
    for item in text.split(","):
        try:
            instrument, n, kind, seeds = item.split(":")
            lo, _, hi = seeds.partition("-")
            sets.append((instrument, int(n), kind, range(int(lo), int(hi or lo) + 1)))
        except ValueError:
            raise SystemExit(f"--sets: {item!r} is not instrument:n:kind:first-last (e.g. sdss:547:random:0-1)") from None
    return tuple(sets)


def compare(before: Path, after: Path) -> int:
    """Print the runs whose trajectories differ; 0 when every run is identical."""
    a = json.loads(before.read_text())["runs"]
    b = json.loads(after.read_text())["runs"]
    differ = [k for k in a if k not in b or a[k]["joints_sha256"] != b[k]["joints_sha256"] or a[k]["times_sha256"] != b[k]["times_sha256"]]
    for key in differ:
        print(f"differs: {key}")
    print(f"{len(a) - len(differ)} of {len(a)} runs bit-identical")
    return 1 if differ else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--planner", default="mpc")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--quick", action="store_true", help="first seed of each set only")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    parser.add_argument("--sets", type=parse_sets, default=SETS, help="instrument:n:kind:first-last, comma-separated (default: the house sets)")
    args = parser.parse_args()
    if args.compare:
        sys.exit(compare(*args.compare))
    import fiberplan

    runs = fingerprints(args.planner, sets=args.sets, quick=args.quick)
    payload = {"planner": args.planner, "fiberplan_module": str(Path(fiberplan.__file__).parent), "runs": runs}
    text = json.dumps(payload, indent=1)
    if args.out:
        args.out.write_text(text + "\n")
    else:
        print(text)


if __name__ == "__main__":
    main()
