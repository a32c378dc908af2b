"""Benchmarks: a study file (``benchmarks/studies/*.toml``) run by the one study runner, summarised.

Every run is planned, verified by the independent verifier and written as a row of the study's
Parquet table (resumable: re-running skips finished runs). The summary goes to
``benchmarks/results/<study>.json`` with the machine, package versions, commit and date, one
entry per group (instrument, size, scenario kind and options, planner, settings)::

    python benchmarks/bench.py run benchmarks/studies/mpc_desi.toml [--workers 2]
    python benchmarks/bench.py table benchmarks/results/mpc_desi.json       # Markdown, for docs/results.md
    python benchmarks/bench.py compare --instrument moons -n 7 --seeds 30    # gaps to central -> results/central_moons_7.json (--name, --overwrite)
    python benchmarks/bench.py gap --central results/central_sdss_7_30seeds.json --against results/X.json --name Y  # newer planners, stored reference

Timing figures (``plan_wall_s``) are only comparable between runs on one quiet machine with the
same ``--workers``; the scaling study runs with ``--workers 1``.
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
from _machine import machine_info

from fiberplan._json import json_ready as _json_ready

RESULTS = Path(__file__).resolve().parent / "results"
GROUP = ("instrument", "n_positioners", "scenario_kind", "planner", "settings_json")


def _finite(values: Any) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    return arr[np.isfinite(arr)]


def _stat(values: Any, fn: Any) -> float | None:
    arr = _finite(values)
    return float(fn(arr)) if len(arr) else None


def summarise(frame: Any) -> list[dict[str, Any]]:
    """One summary per group of runs."""
    options = sorted(c for c in frame.columns if c.startswith("scenario."))
    groups = []
    for key, g in frame.groupby([*GROUP, *options], dropna=False, sort=False):
        ok = g[g["status"] == "ok"]
        entry: dict[str, Any] = dict(zip([*GROUP, *options], [k.item() if hasattr(k, "item") else k for k in key], strict=True))
        entry |= {
            "runs": len(g),
            "errors": int((g["status"] == "error").sum()),
            "lost": int((g["status"] == "lost").sum()),
            "collisions_total": int(ok["collisions"].sum()),
            "limit_violations_total": int(ok["limit_violations"].sum()),
            "runs_verified_ok": int(ok["verified_ok"].sum()),
            "targets_total": int(ok["targets"].sum()),
            "reached_total": int(ok["reached"].sum()),
            "reached_fraction": float(ok["reached"].sum() / ok["targets"].sum()) if ok["targets"].sum() else None,
            "success_rate_min": _stat(ok["success_rate"], np.min),
            "runs_all_reached": int((ok["reached"] == ok["targets"]).sum()),
            "deadlocked_total": int(ok["deadlocked"].sum()),
            "unfinished_total": int(ok["unfinished"].sum()),
            "makespan_over_bound_median": _stat(ok["makespan_over_bound"], np.median),
            "makespan_over_bound_p90": _stat(ok["makespan_over_bound"], lambda a: np.percentile(a, 90)),
            "makespan_over_bound_max": _stat(ok["makespan_over_bound"], np.max),
            "makespan_s_median": _stat(ok["makespan_s"], np.median),
            "plan_wall_s_median": _stat(ok["plan_wall_s"], np.median),
            "plan_wall_s_max": _stat(ok["plan_wall_s"], np.max),
        }
        for stat in ("stat.schedule_wall_s", "stat.qp_solve_ms_median", "stat.deadlocks_detected"):
            if stat in ok:
                entry[f"{stat[5:]}_median"] = _stat(ok[stat], np.median)
        groups.append(entry)
    return groups


def write_summary(name: str, payload: dict[str, Any]) -> Path:
    from fiberplan._atomic import atomic_path

    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    payload = {"name": name, "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
               "machine": machine_info(("osqp", "casadi", "pandas", "dask"))} | payload
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_json_ready(payload), indent=1) + "\n")
    return path


def cmd_run(args: argparse.Namespace) -> None:
    from fiberplan.studies import load_results, load_study, run_study

    spec = load_study(args.study)
    run_study(spec, workers=args.workers, progress=not args.quiet)
    frame = load_results(spec.out)
    path = write_summary(Path(args.study).stem, {
        "study": str(args.study), "table": str(spec.out), "workers": args.workers,
        "command": f"python benchmarks/bench.py run {args.study}" + (f" --workers {args.workers}" if args.workers else ""),
        "groups": summarise(frame),
    })
    print(f"wrote {path}")


def cmd_table(args: argparse.Namespace) -> None:
    data = json.loads(Path(args.result).read_text())

    def fmt(v: Any, spec: str = ".3f") -> str:
        return "n/a" if v is None else format(v, spec)

    print("| instrument | N | kind | planner | settings | seeds | reached | seeds all reached | collisions | "
          "makespan / bound (median, max) | plan wall median |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for g in data["groups"]:
        settings = "" if g["settings_json"] in ("{}", "") else g["settings_json"]
        print(f"| {g['instrument']} | {g['n_positioners']} | {g['scenario_kind']} | {g['planner']} | {settings} | {g['runs']} | "
              f"{fmt(100 * g['reached_fraction'] if g['reached_fraction'] is not None else None, '.2f')} % | "
              f"{g['runs_all_reached']} | {g['collisions_total']} | {fmt(g['makespan_over_bound_median'])}, "
              f"{fmt(g['makespan_over_bound_max'])} | {fmt(g['plan_wall_s_median'], '.2f')} s |")
    print(f"\n`{data.get('command', '')}` ({data['date_utc']}, {data['machine']['fiberplan_commit'][:10]})")


def _seed_list(text: str) -> list[int]:
    try:
        return [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        sys.exit(f"--seed-list: expected comma-separated integers such as 1,2,3, got {text!r}")


def cmd_compare(args: argparse.Namespace) -> None:
    from fiberplan._atomic import exclusive

    name = args.name or f"central_{args.instrument}_{args.n}"
    path = RESULTS / f"{name}.json"
    # Held for the whole run: a second compare of the same name (a resume started twice) would
    # rewrite the file with its own seeds after each one, and the first's would be lost.
    with exclusive(path, what="bench.py compare: result", fix="wait for that compare to end or stop it, or give another --name"):
        _compare(args, name, path)


def _compare(args: argparse.Namespace, name: str, path: Path) -> None:
    from _machine import source_tree

    from fiberplan.studies import run_compare
    from fiberplan.studies.analysis import aggregate
    from fiberplan.studies.compare import CompareResult

    if args.resume and args.overwrite:
        sys.exit("bench.py compare: --resume keeps the seeds of a stopped run, --overwrite replaces them; give one of the two")
    if args.resume and not path.exists():
        sys.exit(f"bench.py compare --resume: there is no {path} to go on with; check --name, or leave out --resume to start it")
    if path.exists() and not (args.overwrite or args.resume):  # checked before hours of solving
        sys.exit(f"bench.py compare: {path} exists; give --name for a new file, --resume to go on with its seeds, or --overwrite to replace it")
    settings: dict[str, dict[str, Any]] = {}
    for item in args.set:
        key, raw = item.split("=", 1)
        planner, setting_name = key.split(".", 1)
        settings.setdefault(planner, {})[setting_name] = json.loads(raw)
    seeds = _seed_list(args.seed_list) if args.seed_list else list(range(args.seeds))
    command = " ".join(["python", "benchmarks/bench.py", *sys.argv[1:]])
    tree = source_tree()
    rows: list[dict[str, Any]] = []
    done_seeds: list[int] = []
    if args.resume and path.exists() and not args.overwrite:
        rows, done_seeds = _resumable(path, tree, {"instrument": args.instrument, "n_positioners": args.n, "scenario_kind": args.kind,
                                                   "planners": [p.strip() for p in args.planners.split(",") if p.strip()],
                                                   "settings": settings, "energy_gap": args.energy_gap})
        print(f"resuming {path}: seeds {done_seeds} kept", flush=True)
    todo = [s for s in seeds if s not in done_seeds]
    for seed in todo:  # one seed at a time, the file written after each: a stopped run keeps its seeds (--resume goes on)
        def progress(label: str, began: float = time.perf_counter()) -> None:  # (a seed can take many minutes: say what is done)
            print(f"  {label} done, {time.perf_counter() - began:.0f} s into the seed", flush=True)

        part = run_compare(args.instrument, args.n, args.planners.split(","), [seed], kind=args.kind, settings=settings,
                           energy_gap=args.energy_gap, progress=progress)
        rows.extend(part.rows)
        done_seeds.append(seed)
        result = CompareResult(rows=rows, aggregates=aggregate(rows), parameters=part.parameters | {"seeds": done_seeds})
        path = write_summary(name, {"command": command, "complete": set(seeds) <= set(done_seeds), "src_tree": tree} | result.to_dict())
        print(f"seed {seed} ({len(done_seeds)} of {len(set(seeds) | set(done_seeds))}) -> {path}", flush=True)
    if not todo:
        print(f"{path}: every seed asked for is there already", flush=True)


def _resumable(path: Path, tree: str, expected: dict[str, Any]) -> tuple[list[dict[str, Any]], list[int]]:
    """The rows and seeds of a stopped compare ``path``, if it was run with the same parameters
    and the same code (``src/`` tree); otherwise exit naming what differs."""
    data = json.loads(path.read_text())
    if data.get("src_tree") in (None, "unknown") or tree == "unknown" or data["src_tree"].endswith("-dirty") or tree.endswith("-dirty"):
        sys.exit(f"bench.py compare --resume: cannot tell whether {path} was run with this code (src tree {data.get('src_tree')!r}, "
                 f"now {tree!r}); give --name for a new file")
    if data["src_tree"] != tree:
        sys.exit(f"bench.py compare --resume: {path} was run with other code (src tree {data['src_tree'][:12]}, now {tree[:12]}): "
                 "its rows and new ones would not be one code state; give --name for a new file")
    params = data.get("parameters", {})
    for key, value in expected.items():
        if _json_ready(params.get(key)) != _json_ready(value):
            sys.exit(f"bench.py compare --resume: {path} has {key} = {params.get(key)!r}, this command {value!r}; "
                     "give the same options, or --name for a new file")
    return list(data["rows"]), [int(s) for s in params.get("seeds", [])]


def _gap_rows(central: dict[str, Any], other: dict[str, Any]) -> list[dict[str, Any]]:
    """Per seed and planner of ``other``: its makespan against the central reference's of
    ``central`` on the same scenario (rows matched by scenario name; only references converged,
    verified and complete count, as in ``compare``)."""
    # (Files written before the rows had a status hold only finished runs.)
    ref = {r["scenario"]: r for r in central["rows"] if r["planner"] == "central" and r.get("status") in ("ok", None)
           and r.get("clean") and r.get("success_rate") == 1.0}
    out = []
    for r in other["rows"]:
        if r["planner"] == "central" or r.get("status") not in ("ok", None):
            continue
        c = ref.get(r["scenario"])
        if c is not None and not np.isclose(c["lower_bound_s"], r["lower_bound_s"], rtol=1e-12, atol=0.0):
            sys.exit(f"bench.py gap: {r['scenario']} is not the scenario the reference solved (lower bound {c['lower_bound_s']} s "
                     f"there, {r['lower_bound_s']} s here): the scenario generator changed; solve the reference again")
        complete = bool(r.get("clean")) and r.get("success_rate") == 1.0
        gap = None if c is None or not complete else float(r["makespan_s"] / c["makespan_s"] - 1.0)
        before = next((b for b in central["rows"] if b["scenario"] == r["scenario"] and b["planner"] == r["planner"]), None)
        gap_before = (None if c is None or before is None or before.get("success_rate") != 1.0 or not before.get("clean")
                      else float(before["makespan_s"] / c["makespan_s"] - 1.0))
        out.append({"scenario": r["scenario"], "seed": r["seed"], "planner": r["planner"], "complete": complete,
                    "makespan_s": r["makespan_s"], "central_makespan_s": None if c is None else c["makespan_s"],
                    "gap_to_central": gap, "gap_to_central_before": gap_before, "plan_wall_s": r["plan_wall_s"],
                    # (from the newer compare's own energy-mode solves, --energy-gap: the reference at this planner's makespan)
                    "energy_gap_to_central": _finite_or_none(r.get("energy_gap_to_central"))})
    return out


def _finite_or_none(value: Any) -> float | None:
    return None if value is None or not np.isfinite(value) else float(value)


def cmd_gap(args: argparse.Namespace) -> None:
    """Gaps of a newer run of the decentralised planners to a stored central reference."""
    out = RESULTS / f"{args.name}.json"
    if out.exists() and not args.overwrite:  # (the name may be one of the inputs: hours of solves)
        sys.exit(f"bench.py gap: {out} exists; give --name for a new file, or --overwrite to replace it")
    for given in (args.central, args.against):
        if not given.is_file():
            sys.exit(f"bench.py gap: no result file {given}")
    central = json.loads(Path(args.central).read_text())
    other = json.loads(Path(args.against).read_text())
    rows = _gap_rows(central, other)
    summary: dict[str, Any] = {}
    for planner in sorted({r["planner"] for r in rows}):
        mine = [r for r in rows if r["planner"] == planner]
        gaps = [r["gap_to_central"] for r in mine if r["gap_to_central"] is not None]
        before = [r["gap_to_central_before"] for r in mine if r["gap_to_central_before"] is not None]
        energy = [r["energy_gap_to_central"] for r in mine if r["energy_gap_to_central"] is not None]
        summary[planner] = {"seeds": len(mine), "complete": sum(r["complete"] for r in mine), "with_reference": len(gaps),
                            "gap_median": _stat(gaps, np.median), "gap_p90": _stat(gaps, lambda a: np.percentile(a, 90)),
                            "gap_max": _stat(gaps, np.max), "within_5_percent": sum(g <= 0.05 for g in gaps),
                            "gap_median_before": _stat(before, np.median),
                            "energy_gaps": len(energy), "energy_gap_median": _stat(energy, np.median),
                            "plan_wall_s_median": _stat([r["plan_wall_s"] for r in mine], np.median)}
        s = summary[planner]

        def pct(v: float | None) -> str:
            return "n/a" if v is None else f"{v:+.1%}"

        print(f"{planner}: {s['complete']} of {s['seeds']} complete; against {s['with_reference']} references: gap median "
              f"{pct(s['gap_median'])} (before {pct(s['gap_median_before'])}), p90 {pct(s['gap_p90'])}, max {pct(s['gap_max'])}, "
              f"within 5 %: {s['within_5_percent']}; plan wall median {s['plan_wall_s_median']:.2f} s"
              + (f"; energy at equal makespan: median {pct(s['energy_gap_median'])} on {len(energy)}" if energy else ""))
    command = " ".join(["python", "benchmarks/bench.py", *sys.argv[1:]])
    path = write_summary(args.name, {"command": command, "central": str(args.central), "against": str(args.against),
                                     "against_commit": other.get("machine", {}).get("fiberplan_commit"),
                                     "summary": summary, "rows": rows})
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a study file and summarise it")
    run.add_argument("study", type=Path)
    run.add_argument("--workers", type=int, default=None)
    run.add_argument("--quiet", "-q", action="store_true")
    table = sub.add_parser("table", help="Markdown table of a summary")
    table.add_argument("result", type=Path)
    comp = sub.add_parser("compare", help="planners against the central reference on hard groups")
    comp.add_argument("--instrument", default="desi")
    comp.add_argument("-n", type=int, default=7)
    comp.add_argument("--planners", default="central,mpc,dnf")
    comp.add_argument("--seeds", type=int, default=30)
    comp.add_argument("--seed-list", default=None, help="comma-separated seeds (instead of --seeds)")
    comp.add_argument("--kind", default="hard")
    comp.add_argument("--set", action="append", default=[], metavar="PLANNER.KEY=JSON")
    comp.add_argument("--energy-gap", action="store_true")
    comp.add_argument("--name", default=None, help="result file name (default central_<instrument>_<n>)")
    comp.add_argument("--overwrite", action="store_true", help="replace an existing result file of that name")
    comp.add_argument("--resume", action="store_true",
                      help="go on with a stopped run of that name (same options, same code): its seeds are kept, the rest planned")
    gap = sub.add_parser("gap", help="a newer compare's planners against a stored central reference (same scenarios)")
    gap.add_argument("--central", type=Path, required=True, help="a compare result holding the central rows")
    gap.add_argument("--against", type=Path, required=True, help="a compare result of the planners to measure")
    gap.add_argument("--name", required=True, help="result file name")
    gap.add_argument("--overwrite", action="store_true", help="replace an existing result file of that name")
    args = parser.parse_args()
    from fiberplan.errors import FiberplanError

    try:
        {"run": cmd_run, "table": cmd_table, "compare": cmd_compare, "gap": cmd_gap}[args.command](args)
    except FiberplanError as e:  # (a refused input or a result in use: one line, no traceback)
        sys.exit(f"bench.py {args.command}: {e}" if not str(e).startswith("bench.py") else str(e))


if __name__ == "__main__":
    main()
