"""Studies: parameter sweeps over instruments, sizes, scenarios, seeds and planner settings.

A study file (TOML) names the grid; every cell x seed is one task: generate the seeded
scenario, plan, verify, summarise. Results go to a Parquet table, one row per run with every
metric and every parameter. Runs are executed on a local process pool or on a Dask
distributed cluster, and the sweep is resumable and loss-free:

- each finished run is written at once as its own small Parquet file in ``<out>.parts/``
  (atomic rename), so nothing finished is lost if the driver is killed (even ``kill -9``);
- the table ``<out>`` is rebuilt from the parts as runs finish (at most every few seconds)
  and at the end;
- re-running the same command skips every run whose part exists;
- a run that raises is recorded as a row with ``status = "error"`` and the message; when a
  worker process dies, the runs that were in flight are retried one by one in fresh
  processes, and the one that dies again alone is recorded as an error.

Study file layout::

    [study]
    name = "deadlocks"
    out = "deadlocks.parquet"        # default: <study file stem>.parquet beside it
    per_positioner = false           # also write <out stem>.positioners.parquet

    [grid]
    instrument = ["desi", "moons"]
    n_positioners = [19, 61]
    scenario_kind = ["random", "clustered"]
    planner = ["dnf", "mpc"]
    seeds = 20                       # seeds 0..19; or a list [3, 5, 8]

    [scenario]                       # options of make_scenario; lists are grid axes
    cluster_fraction = [0.0, 0.5, 0.9]

    [settings.dnf]                   # per-planner settings; lists are grid axes
    lambda_2 = [0.05, 0.2]
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import itertools
import json
import math
import os
import time
import tomllib
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan._atomic import atomic_path
from fiberplan.errors import FiberplanError

GRID_KEYS = ("instrument", "n_positioners", "scenario_kind", "planner")
SCENARIO_OPTIONS = ("clusters", "cluster_fraction", "random_orientation", "radius_mm")
"""Keyword arguments of :func:`fiberplan.generate.make_scenario` a study may vary (``[scenario]``)."""


class StudyError(FiberplanError, ValueError):
    """A study file is missing, malformed, or names something unknown."""


@dataclass(frozen=True)
class Task:
    """One run of a sweep: a grid cell and a seed."""

    instrument: str
    n_positioners: int
    scenario_kind: str
    planner: str
    seed: int
    settings: tuple[tuple[str, Any], ...] = ()
    scenario_options: tuple[tuple[str, Any], ...] = ()

    def parameters(self) -> dict[str, Any]:
        """The run's parameters as row columns (``setting.*`` and ``scenario.*`` flattened)."""
        return {
            "task": self.key,
            "instrument": self.instrument,
            "n_positioners": self.n_positioners,
            "scenario_kind": self.scenario_kind,
            "planner": self.planner,
            "seed": self.seed,
            "settings_json": json.dumps(dict(self.settings), sort_keys=True),
            **{f"setting.{k}": v for k, v in self.settings},
            **{f"scenario.{k}": v for k, v in self.scenario_options},
        }

    @property
    def key(self) -> str:
        """Stable identifier (hash of the canonical parameters) used to resume."""
        payload = json.dumps(
            {
                "instrument": self.instrument,
                "n_positioners": self.n_positioners,
                "scenario_kind": self.scenario_kind,
                "planner": self.planner,
                "seed": self.seed,
                "settings": dict(self.settings),
                **({"scenario": dict(self.scenario_options)} if self.scenario_options else {}),
            },
            sort_keys=True,
        )
        return hashlib.sha1(payload.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class StudySpec:
    """A parsed study file."""

    name: str
    out: Path
    tasks: tuple[Task, ...]
    per_positioner: bool = False
    source: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def parts_dir(self) -> Path:
        """Folder of per-run part files."""
        return self.out.with_name(self.out.name + ".parts")

    @property
    def positioner_out(self) -> Path:
        """Per-positioner table path."""
        return self.out.with_name(self.out.stem + ".positioners.parquet")


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, list) else [value]


def expand_grid(data: Mapping[str, Any], origin: str = "study") -> list[Task]:
    """Every task of a study description (the ``grid`` and ``settings`` tables).

    Raises:
        StudyError: a grid key is missing, an instrument, kind or planner is unknown, or a
            setting does not exist for its planner.
    """
    from fiberplan.generate import SCENARIO_KINDS
    from fiberplan.instrument import load_instrument
    from fiberplan.planners import planner_names, settings_class

    grid = data.get("grid")
    if not isinstance(grid, dict):
        raise StudyError(f"{origin}: a [grid] table is needed (keys: {', '.join(GRID_KEYS)}, seeds)")
    missing = [k for k in (*GRID_KEYS, "seeds") if k not in grid]
    if missing:
        raise StudyError(f"{origin}: [grid] lacks {', '.join(missing)}")
    instruments = [str(v) for v in _as_list(grid["instrument"])]
    for name in instruments:
        try:
            load_instrument(name)
        except FiberplanError as e:
            raise StudyError(f"{origin}: {e}") from e
    sizes = [int(v) for v in _as_list(grid["n_positioners"])]
    kinds = [str(v) for v in _as_list(grid["scenario_kind"])]
    for kind in kinds:
        if kind not in SCENARIO_KINDS:
            raise StudyError(f"{origin}: unknown scenario kind {kind!r}; choose from {', '.join(SCENARIO_KINDS)}")
    planners = [str(v) for v in _as_list(grid["planner"])]
    for name in planners:
        if name not in planner_names():
            raise StudyError(f"{origin}: unknown planner {name!r}; choose from {', '.join(planner_names())}")
    seeds_raw = grid["seeds"]
    seeds = list(range(int(seeds_raw))) if isinstance(seeds_raw, int) else [int(s) for s in seeds_raw]
    if not seeds:
        raise StudyError(f"{origin}: no seeds")
    settings_tables = data.get("settings", {})
    scenario_table = dict(data.get("scenario", {}))
    allowed = set(SCENARIO_OPTIONS)
    unknown_options = sorted(set(scenario_table) - allowed)
    if unknown_options:
        raise StudyError(f"{origin}: unknown scenario option {unknown_options[0]!r}; choose from {', '.join(sorted(allowed))}")
    option_names = sorted(scenario_table)
    option_combos = list(itertools.product(*(_as_list(scenario_table[n]) for n in option_names))) if option_names else [()]
    tasks: list[Task] = []
    for planner in planners:
        table = dict(settings_tables.get(planner, {}))
        settings_cls = settings_class(planner)
        known = {f.name for f in dataclasses.fields(settings_cls)}
        unknown = sorted(set(table) - known)
        if unknown:
            raise StudyError(f"{origin}: planner {planner!r} has no setting {unknown[0]!r}; its settings are {', '.join(sorted(known))}")
        names = sorted(table)
        combos = list(itertools.product(*(_as_list(table[n]) for n in names))) if names else [()]
        for instrument, n, kind, options, combo, seed in itertools.product(instruments, sizes, kinds, option_combos, combos, seeds):
            tasks.append(
                Task(
                    instrument, n, kind, planner, seed,
                    tuple(zip(names, combo, strict=True)),
                    tuple(zip(option_names, options, strict=True)),
                )
            )
    return tasks


def study_from_dict(data: Mapping[str, Any], out: str | Path, origin: str = "study") -> StudySpec:
    """Build a study from the file layout as a dict (for notebooks and scripts).

    Raises:
        StudyError: invalid grid.
    """
    study = dict(data.get("study", {}))
    return StudySpec(
        name=str(study.get("name", Path(out).stem)),
        out=Path(out),
        tasks=tuple(expand_grid(data, origin=origin)),
        per_positioner=bool(study.get("per_positioner", False)),
        source=dict(data),
    )


def load_study(path: str | Path) -> StudySpec:
    """Read a study TOML file.

    Raises:
        StudyError: missing, not TOML, or an invalid grid.
    """
    path = Path(path)
    if not path.is_file():
        raise StudyError(f"study file {str(path)!r} does not exist")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise StudyError(f"study file {str(path)!r} is not valid TOML ({e})") from e
    out = Path(data.get("study", {}).get("out", path.with_suffix(".parquet").name))
    if not out.is_absolute():
        out = path.parent / out
    return study_from_dict(data, out, origin=f"study file {str(path)!r}")


def run_task(task: Task, per_positioner: bool = False) -> dict[str, Any]:
    """Run one task: generate, plan, verify, summarise. Never raises: errors become a row."""
    row = task.parameters()
    t0 = time.perf_counter()
    try:
        from fiberplan.generate import make_scenario
        from fiberplan.metrics import arrival_times, path_lengths_mm, reached_mask, summarize
        from fiberplan.planners import plan
        from fiberplan.verify import verify

        scenario = make_scenario(task.instrument, task.n_positioners, task.scenario_kind, task.seed, **dict(task.scenario_options))
        result = plan(scenario, task.planner, dict(task.settings))
        report = verify(scenario, result.trajectory)
        summary = summarize(result, report)
        summary.pop("planner", None)
        summary.pop("instrument", None)
        summary.pop("seed", None)
        summary.pop("n_positioners", None)
        summary.pop("scenario_kind", None)
        row.update(summary)
        for name, value in result.stats.items():
            if isinstance(value, (int, float, bool, np.integer, np.floating)) and not isinstance(value, bool):
                row[f"stat.{name}"] = float(value)
        row["status"] = "ok"
        row["error"] = ""
        if per_positioner:
            reached = reached_mask(scenario, result.trajectory)
            row["_positioners"] = {
                "id": scenario.ids.tolist(),
                "outcome": result.outcome.tolist(),
                "reached": reached.tolist(),
                "arrival_s": arrival_times(scenario, result.trajectory).tolist(),
                "path_length_mm": path_lengths_mm(scenario, result.trajectory).tolist(),
            }
    except Exception as e:  # a failing run is a result, not a crash of the sweep
        row["status"] = "error"
        row["error"] = f"{type(e).__name__}: {e}"
        row["traceback"] = traceback.format_exc(limit=5)
    row["run_wall_s"] = time.perf_counter() - t0
    return row


def _write_part(parts_dir: Path, row: dict[str, Any]) -> None:
    import pandas as pd

    positioners = row.pop("_positioners", None)
    parts_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(parts_dir / f"{row['task']}.parquet") as tmp:
        pd.DataFrame([row]).to_parquet(tmp, index=False)
    if positioners is not None:
        frame = pd.DataFrame(positioners)
        frame.insert(0, "task", row["task"])
        with atomic_path(parts_dir / f"{row['task']}.positioners.parquet") as tmp:
            frame.to_parquet(tmp, index=False)


def _parts(spec: StudySpec, positioners: bool = False) -> list[Path]:
    """Complete part files (a temporary file left by a killed writer starts with a dot)."""
    if not spec.parts_dir.is_dir():
        return []
    return sorted(
        p
        for p in spec.parts_dir.glob("*.parquet")
        if not p.name.startswith(".") and p.name.endswith(".positioners.parquet") == positioners
    )


def finished_tasks(spec: StudySpec) -> set[str]:
    """Keys of tasks whose part file exists (they are skipped on resume)."""
    return {p.name.split(".")[0] for p in _parts(spec)}


def consolidate(spec: StudySpec) -> int:
    """Rebuild the results table (and the per-positioner table) from the parts. Returns the row count."""
    import pandas as pd

    parts = _parts(spec)
    if not parts:
        return 0
    keys = {t.key: k for k, t in enumerate(spec.tasks)}
    frame = pd.concat([pd.read_parquet(p) for p in parts], ignore_index=True)
    frame = frame.assign(_order=frame["task"].map(keys).fillna(len(keys))).sort_values("_order").drop(columns="_order")
    with atomic_path(spec.out) as tmp:
        frame.reset_index(drop=True).to_parquet(tmp, index=False)
    if spec.per_positioner:
        pos_parts = _parts(spec, positioners=True)
        if pos_parts:
            with atomic_path(spec.positioner_out) as tmp:
                pd.concat([pd.read_parquet(p) for p in pos_parts], ignore_index=True).to_parquet(tmp, index=False)
    return len(frame)


ProgressFactory = Callable[[int, int], Any]


def _progress_bar(total: int, initial: int) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc="runs", unit="run", dynamic_ncols=True)


def _local_results(tasks: Sequence[Task], per_positioner: bool, workers: int) -> Iterator[dict[str, Any]]:
    """Run tasks on a process pool; a dead worker does not stop the sweep.

    When a worker process dies, every run then in flight fails with the broken pool, and
    which one killed it is unknown: those runs are retried one by one, each in a pool of its
    own, so that a death is blamed on exactly the run that caused it (recorded as an error).
    """
    suspects: list[Task] = []
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures: dict[Future[dict[str, Any]], Task] = {pool.submit(run_task, t, per_positioner): t for t in tasks}
        while futures:
            done, _ = wait(futures, return_when=FIRST_COMPLETED)
            for fut in done:
                task = futures.pop(fut)
                try:
                    yield fut.result()
                except BrokenProcessPool:
                    suspects.append(task)
            if suspects and futures:
                # The pool is broken: every run still queued is a suspect too.
                suspects.extend(futures.values())
                futures = {}
    for task in suspects:
        with ProcessPoolExecutor(max_workers=1) as alone:
            try:
                yield alone.submit(run_task, task, per_positioner).result()
            except BrokenProcessPool:
                yield _crash_row(task, "worker process died on this run (retried alone)")


def _crash_row(task: Task, message: str) -> dict[str, Any]:
    return {
        **task.parameters(),
        "status": "error",
        "error": message,
    }


def _dask_results(tasks: Sequence[Task], per_positioner: bool, scheduler: str) -> Iterator[dict[str, Any]]:
    from dask.distributed import Client, as_completed

    with Client(scheduler) as client:
        futures = {client.submit(run_task, t, per_positioner, key=f"fiberplan-{t.key}", pure=False): t for t in tasks}
        for fut in as_completed(futures):
            task = futures[fut]
            try:
                yield fut.result()
            except Exception as e:
                yield _crash_row(task, f"{type(e).__name__}: {e}")


def run_study(
    spec: StudySpec,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    consolidate_every_s: float = 5.0,
) -> int:
    """Run every unfinished task of a study; returns the number of rows in the table.

    Args:
        spec: the parsed study.
        workers: local worker processes (default: the machine's cores).
        scheduler: address of a Dask distributed scheduler; runs there instead of locally.
        progress: show a progress bar (counts and ETA) on stderr.
        consolidate_every_s: rebuild the table at most this often while runs finish.
    """
    if spec.parts_dir.is_dir():
        for stale in spec.parts_dir.glob(".*.part.parquet"):  # left by a writer that was killed
            stale.unlink(missing_ok=True)
    done = finished_tasks(spec)
    todo = [t for t in spec.tasks if t.key not in done]
    bar = _progress_bar(len(spec.tasks), len(spec.tasks) - len(todo)) if progress else None
    last = time.monotonic()
    try:
        if todo:
            if scheduler:
                results: Iterable[dict[str, Any]] = _dask_results(todo, spec.per_positioner, scheduler)
            else:
                results = _local_results(todo, spec.per_positioner, workers or os.cpu_count() or 1)
            for row in results:
                _write_part(spec.parts_dir, row)
                if bar is not None:
                    bar.update(1)
                if time.monotonic() - last > consolidate_every_s:
                    consolidate(spec)
                    last = time.monotonic()
    finally:
        if bar is not None:
            bar.close()
        with contextlib.suppress(Exception):
            consolidate(spec)
    return consolidate(spec)


# ---------------------------------------------------------------------------------- analysis


def load_results(path: str | Path) -> Any:
    """Read a study results table (pandas DataFrame)."""
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise StudyError(f"results table {str(path)!r} does not exist")
    return pd.read_parquet(path)


def wilson_interval(successes: float, trials: float, z: float = 1.96) -> tuple[float, float]:
    r"""Wilson score interval of a binomial proportion.

    .. math:: \frac{\hat p + \frac{z^2}{2n} \pm z \sqrt{\frac{\hat p (1 - \hat p)}{n} + \frac{z^2}{4 n^2}}}{1 + z^2 / n}
    """
    if trials <= 0:
        return (math.nan, math.nan)
    p = successes / trials
    denom = 1 + z**2 / trials
    centre = (p + z**2 / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z**2 / (4 * trials**2)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def rates(frame: Any, by: Sequence[str], z: float = 1.96) -> Any:
    """Success and deadlock rates over positioners, with Wilson intervals, grouped by ``by``.

    Counts pool every positioner with a target across the runs of a group (``reached``,
    ``deadlocked``, ``targets`` columns); error runs are counted in ``errors`` and left out.
    """
    import pandas as pd

    ok = frame[frame["status"] == "ok"]
    rows = []
    for key, group in ok.groupby(list(by), dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        targets = float(group["targets"].sum())
        reached = float(group["reached"].sum())
        dead = float(group["deadlocked"].sum())
        s_lo, s_hi = wilson_interval(reached, targets, z)
        d_lo, d_hi = wilson_interval(dead, targets, z)
        rows.append(
            {
                **dict(zip(by, key, strict=True)),
                "runs": len(group),
                "targets": int(targets),
                "success_rate": reached / targets if targets else math.nan,
                "success_lo": s_lo,
                "success_hi": s_hi,
                "deadlock_rate": dead / targets if targets else math.nan,
                "deadlock_lo": d_lo,
                "deadlock_hi": d_hi,
                "runs_all_reached": float((group["reached"] == group["targets"]).mean()),
                "collisions": int(group["collisions"].sum()),
            }
        )
    errors = frame[frame["status"] != "ok"].groupby(list(by), dropna=False).size()
    out = pd.DataFrame(rows)
    if len(out):
        out["errors"] = [int(errors.get(tuple(r[b] for b in by) if len(by) > 1 else r[by[0]], 0)) for _, r in out.iterrows()]
    return out


def percentiles(frame: Any, column: str, by: Sequence[str], q: Sequence[float] = (0.5, 0.9, 0.95)) -> Any:
    """Percentiles of a metric column per group (successful runs only)."""
    ok = frame[frame["status"] == "ok"]
    table = ok.groupby(list(by))[column].quantile(list(q)).unstack()
    table.columns = [f"{column}_p{round(100 * v)}" for v in q]
    return table.reset_index()
