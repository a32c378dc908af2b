"""What speed ramps cost the motor profiles: the same plans discretised for an instrument whose
motors take ``tau`` to change speed (``[motors] ramp_time_s``; 0: instant, the preset), verified
as the motors execute them (:mod:`fiberplan.ramps`).

No preset states a ramp time (no source gives one); the ramp times here are assumptions, to
measure what a ramp of that length costs. Each seed is planned once with the preset
(``--cache DIR`` keeps the plans) and discretised for each ramp (``ramp_<tau>``); with
``--plan-with-ramps`` it is also planned on the instrument with the ramp (the ``mpc``'s motor
governor then keeps it, :mod:`fiberplan.planners.motors` rule 4) and that plan discretised
(``planned_<tau>``). Rows: verified, motor-limit violations left and their kinds, pauses (motor
limits; stops that let the ramps settle), segments, makespan before and after (as executed: the
last ramp included), time::

    python benchmarks/profiles_ramps_bench.py --instrument moons-capsules -n 61 --kind unfold --seeds 0-9 \\
        --ramps 0,0.05,0.1,0.2 --plan-with-ramps --cache /tmp/plans --out benchmarks/results/profiles_ramps_mc61.json
"""

from __future__ import annotations

import datetime as dt
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info
from profiles_pauses_bench import figures, plan_arguments, totals


def with_ramp(name: str, ramp_s: float):
    """The preset ``name`` with ``[motors] ramp_time_s`` (the preset itself for 0)."""
    from fiberplan.instrument_io import instrument_from_dict, load_instrument

    inst = load_instrument(name)
    if ramp_s == 0:
        return inst
    spec = json.loads(json.dumps(inst.to_dict()))
    spec.setdefault("motors", {})["ramp_time_s"] = ramp_s
    return instrument_from_dict(spec, origin=f"{name} with {ramp_s} s ramps")


def discretised(result, inst) -> dict:
    """One discretisation of ``result`` for ``inst``: its figures."""
    from fiberplan.errors import ProfileError
    from fiberplan.profiles import discretise_trajectory

    started = time.perf_counter()
    try:
        made = discretise_trajectory(result.scenario, result.trajectory, instrument=inst)
    except ProfileError as e:
        return {"verified_ok": False, "refused": str(e), "discretise_s": time.perf_counter() - started}
    return figures(made, time.perf_counter() - started) | {
        "min_clearance_mm": made.report.min_clearance_mm,
        "ramp_pauses": made.stats["ramp_pauses"],
        "refit_rounds": made.stats["refit_rounds"],
        "source": made.stats["source"],
        "of_which_verify_s": made.stats["of_which_verify_s"],
    }


def parse_seeds(text: str) -> list[int]:
    """``0-9`` or ``1,4,7``."""
    if "-" in text and "," not in text:
        lo, hi = (int(v) for v in text.split("-"))
        return list(range(lo, hi + 1))
    return [int(v) for v in text.split(",")]


def main() -> None:
    parser = plan_arguments(__doc__, "0-9 or comma-separated")
    parser.add_argument("--ramps", default="0,0.05,0.1,0.2", help="comma-separated ramp times (s); 0: the preset")
    parser.add_argument("--plan-with-ramps", action="store_true", help="also plan on the instrument with each ramp and discretise that plan")
    args = parser.parse_args()
    import fiberplan as fp

    ramps = [float(v) for v in args.ramps.split(",")]
    ways = [f"ramp_{r:g}" for r in ramps]
    instruments = {way: with_ramp(args.instrument, r) for way, r in zip(ways, ramps, strict=True)}
    planned = {f"planned_{r:g}": (r, with_ramp(args.instrument, r)) for r in ramps if r > 0} if args.plan_with_ramps else {}
    all_ways = ways + list(planned)
    meta = {"benchmark": "profiles_ramps", "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "machine": machine_info(), "command": " ".join(sys.argv),
            "note": "ramp times are assumptions (no preset states one): what a ramp of that length costs"}
    rows = []
    def plan(seed: int, inst, tag: str):
        cached = None if args.cache is None else args.cache / f"{args.instrument}{tag}_{args.n}_{args.kind}_{args.planner}_{seed}.h5"
        if cached is not None and cached.exists():
            return fp.load_result(cached)
        result = fp.plan(fp.make_scenario(inst, args.n, args.kind, seed), args.planner)
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            fp.save_result(result, cached)
        return result

    for seed in parse_seeds(args.seeds):
        result = plan(seed, args.instrument, "")
        row = {"seed": seed, "plan_wall_s": result.plan_wall_s, "reached": fp.summarize(result)["reached"],
               **{way: discretised(result, inst) for way, inst in instruments.items()}}
        for way, (r, inst) in planned.items():
            own = plan(seed, inst, f"_ramp{r:g}")
            row[way] = discretised(own, inst) | {"plan_wall_s": own.plan_wall_s, "reached": fp.summarize(own)["reached"]}
            if "makespan_after_s" in row[way] and row[ways[0]].get("makespan_before_s"):  # against the preset's plan
                row[way]["makespan_vs_preset_plan"] = row[way]["makespan_after_s"] / row[ways[0]]["makespan_before_s"] - 1
        rows.append(row)
        print(seed, {w: (row[w].get("motor_violations"), round(row[w].get("makespan_after_s", float("nan")), 2), round(row[w]["discretise_s"], 1))
                     for w in all_ways}, flush=True)
        done = [r for r in rows if all(r[w]["verified_ok"] for w in all_ways)]
        refused = {w: [r["seed"] for r in rows if not r[w]["verified_ok"]] for w in all_ways}
        versus = {w: {"median": float(np.median(g)), "max": float(np.max(g))} for w in planned
                  if (g := [r[w]["makespan_vs_preset_plan"] for r in done if "makespan_vs_preset_plan" in r[w]])}
        args.out.write_text(json.dumps(meta | {"rows": rows, "refused_seeds": refused, "totals": totals(done, all_ways) if done else {},
                                               "makespan_vs_preset_plan": versus}, indent=1))


if __name__ == "__main__":
    main()
