"""The central reference's set-up against its solve, one NLP at a time::

    python benchmarks/central_setup.py --cases sdss:7:0-4,moons:19:0-1 --out benchmarks/results/central_setup.json

For each case (instrument, group size, hard seeds): the ``mpc`` plans the group, its trajectory is
the warm start, the lines it activates (the central settings' defaults, or ``--set KEY=JSON``)
make the first NLP of the candidate; that NLP is built (``set-up``: expressions, derivatives,
``nlpsol``, the start point) and, unless ``--build-only``, solved once by IPOPT (``max_wall_s``
caps it). Compare two versions of the code with ``PYTHONPATH=<snapshot>/src``.

With ``--whole``, each case is the whole reference instead (issue 25's measure: set-up within 10 %
of the solves, per seed): every start (``straight``, ``sequential``, the ``mpc``'s and the
``dnf``'s plans), every lazy round; the row gives the set-up and the IPOPT time summed over them,
the NLPs and iterations, the process's CPU time and the optimum found::

    python benchmarks/central_setup.py --whole --cases sdss:7:0-4 --out benchmarks/results/central_setup_whole.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info


def parse_cases(text: str) -> list[tuple[str, int, int]]:
    """``"sdss:7:0-4,moons:19:1"`` -> ``[("sdss", 7, 0), ..., ("moons", 19, 1)]``."""
    cases = []
    for item in text.split(","):
        try:
            name, n, seeds = item.split(":")
            lo, _, hi = seeds.partition("-")
            cases += [(name, int(n), s) for s in range(int(lo), int(hi or lo) + 1)]
        except ValueError:
            sys.exit(f"--cases: {item!r} is not INSTRUMENT:N:SEED or INSTRUMENT:N:FIRST-LAST")
    return cases


def one(name: str, n: int, seed: int, overrides: dict[str, Any], build_only: bool) -> dict[str, Any]:
    from fiberplan.planners import make_settings, plan
    from fiberplan.planners.central.nlp import _activate, _make_problem, _solve_nlp
    from fiberplan.planners.central.solve import _trajectory_guess
    from fiberplan.studies.scenarios import hard_scenario

    scenario = hard_scenario(name, n, seed)
    settings = make_settings("central", scenario, {"warm_start": ["mpc"], **overrides})
    warm = plan(scenario, "mpc")
    problem = _make_problem(scenario, settings)
    q, tau = _trajectory_guess(problem, warm)
    active = np.argwhere(_activate(problem, q, settings.activation_window))
    started = time.perf_counter()
    raw, build_s = _solve_nlp(problem, active, [] if build_only else [(q, tau)])
    row = {
        "instrument": name, "n_positioners": n, "seed": seed, "lines": len(active), "build_s": build_s,
        "solve_s": raw["solve_s"] if not build_only else None, "iterations": raw["iterations"],
        "status": raw.get("status"), "wall_s": time.perf_counter() - started,
    }
    row["build_over_solve"] = build_s / raw["solve_s"] if not build_only and raw["solve_s"] > 0 else None
    return row


def whole(name: str, n: int, seed: int, overrides: dict[str, Any]) -> dict[str, Any]:
    """The whole reference on one hard group, as ``fiberplan.plan`` runs it (the warm-start
    planners first); ``wall_s`` and ``cpu_s`` cover the call, warm-start planners included."""
    from fiberplan.planners import plan
    from fiberplan.studies.scenarios import hard_scenario

    scenario = hard_scenario(name, n, seed)
    wall, cpu = time.perf_counter(), time.process_time()
    result = plan(scenario, "central", {"warm_start": ["straight", "sequential", "mpc", "dnf"], **overrides})
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    stats = result.stats
    build_s, solve_s = stats["build_s_total"], stats["solve_s_total"]
    lower = stats["lower_bound_s"]
    return {
        "instrument": name, "n_positioners": n, "seed": seed, "build_s": build_s, "solve_s": solve_s,
        "build_over_solve": build_s / solve_s if solve_s > 0 else None, "wall_s": wall, "cpu_s": cpu,
        "nlps": sum(len(c["attempts"]) for c in stats["candidates"]), "iterations": stats["iterations_total"],
        "converged": stats["chosen"] is not None, "chosen": stats["chosen"], "objective": stats.get("objective"),
        "makespan_over_bound": stats["makespan_s"] / lower if stats["chosen"] is not None and lower > 0 else None,
        "solves": {c["source"]: c["attempts"] for c in stats["candidates"]},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="sdss:7:0-4,moons:7:0-4", help="INSTRUMENT:N:SEEDS, comma-separated")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=JSON", help="a central setting, e.g. max_wall_s=120")
    parser.add_argument("--build-only", action="store_true", help="build the NLPs, do not solve them")
    parser.add_argument("--whole", action="store_true", help="the whole reference per case (every start and lazy round)")
    parser.add_argument("--out", type=Path, help="JSON result file (refused if it exists)")
    args = parser.parse_args()
    if args.out is not None and args.out.exists():
        sys.exit(f"{args.out} exists: choose another --out or remove it")
    overrides = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            sys.exit(f"--set {item!r}: expected KEY=JSON")
        overrides[key] = json.loads(value)
    rows = []
    for name, n, seed in parse_cases(args.cases):
        if args.whole:
            row = whole(name, n, seed, overrides)
            rows.append(row)
            print(f"{name} {n} seed {seed}: {row['nlps']} NLPs, set-up {row['build_s']:.2f} s, IPOPT {row['solve_s']:.1f} s "
                  f"(set-up / solves {row['build_over_solve'] or float('nan'):.3f}), "
                  f"{row['makespan_over_bound'] or float('nan'):.4f} x the bound ({row['chosen']})",
                  flush=True)
            continue
        row = one(name, n, seed, overrides, args.build_only)
        rows.append(row)
        ratio = "" if row["build_over_solve"] is None else f", set-up / solve {row['build_over_solve']:.3f}"
        print(f"{name} {n} seed {seed}: {row['lines']} lines, set-up {row['build_s']:.3f} s, "
              f"solve {row['solve_s'] if row['solve_s'] is not None else '-'} s ({row['status']}){ratio}", flush=True)
    out = {
        "name": "central_setup_whole" if args.whole else "central_setup",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(("casadi",)),
        "command": "python " + " ".join(sys.argv),
        "settings": overrides,
        "rows": rows,
    }
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
