"""Studies: parameter sweeps over instruments, sizes, scenarios, seeds and planner settings.

A study file (TOML) names the grid; every cell x seed is one task: generate the seeded
scenario, plan, verify, summarise. Results go to a Parquet table, one row per run with every
metric and every parameter. Runs are executed on a local process pool or on a Dask
distributed cluster, and the sweep is resumable and loss-free:

- each finished run is written at once as its own small Parquet file in ``<out>.parts/``
  (atomic rename), so nothing finished is lost if the driver is killed (even ``kill -9``);
- the table ``<out>`` is rebuilt from the parts as runs finish (at most every few seconds)
  and at the end;
- re-running the same command skips every run whose part exists, and every finished run of
  the table when not one part is left (a fresh clone has the table only): those rows get their
  parts again (:func:`adopt_table`), so the rebuilt table keeps them;
- a run that raises is recorded as a row with ``status = "error"`` and the message (a
  deterministic result of its inputs, kept on resume); a run lost to the machinery (its
  worker process died, its Dask worker was lost) is retried during the sweep (``retries``
  times) and, if still lost, recorded as ``status = "lost"`` and run again on resume;
- with no live Dask worker for ``no_worker_timeout_s`` the sweep stops with an error (exit
  status 3 from the command line), keeping every finished row.
- a second run of the same study (the same table) while one is going on is refused, naming
  the process that runs it: the two would run the same tasks twice.

Study file layout::

    [study]
    name = "deadlocks"
    out = "deadlocks.parquet"        # default: <study file stem>.parquet beside it
    per_positioner = false           # also write <out stem>.positioners.parquet
    retries = 2                      # re-runs of a run lost to a dead worker, during the sweep
    no_worker_timeout_s = 60         # stop when no Dask worker is alive for this long

    [grid]
    instrument = ["desi", "moons"]
    n_positioners = [19, 61]
    scenario_kind = ["random", "clustered"]
    planner = ["dnf", "mpc"]
    seeds = 20                       # seeds 0..19; or a list [3, 5, 8]

    [scenario]                       # options of make_scenario; lists are grid axes
    cluster_fraction = [0.0, 0.5, 0.9]

    [settings.dnf]                   # per-planner settings; lists are grid axes
    lambda_repel = [0.05, 0.2]

Every key is checked (a misspelling is an error naming the closest valid key) and every
setting value is checked against its range for every instrument before any run starts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import math
import os
import sys
import time
import tomllib
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fiberplan._atomic import atomic_path, exclusive
from fiberplan._keys import check_keys
from fiberplan.errors import FiberplanError, InfrastructureError, StudyError
from fiberplan.studies.runner import RunSpec, empty_row, rows_frame, run_one

GRID_KEYS = ("instrument", "n_positioners", "scenario_kind", "planner")
STUDY_FILE_KEYS = ("study", "grid", "scenario", "settings")
STUDY_KEYS = ("name", "out", "per_positioner", "retries", "no_worker_timeout_s")

STATUS_OK = "ok"
STATUS_ERROR = "error"
"""The run raised: a deterministic result of its inputs, kept on resume."""
STATUS_LOST = "lost"
"""The machinery failed (the worker process died, the Dask worker was lost): run again on resume."""
SCENARIO_OPTIONS = ("clusters", "cluster_fraction", "random_orientation", "radius_mm", "min_start_clearance_mm")
"""Keyword arguments of :func:`fiberplan.generate.make_scenario` a study may vary (``[scenario]``)."""




Task = RunSpec
"""One run of a sweep: a grid cell and a seed (a :class:`~fiberplan.studies.runner.RunSpec`)."""


@dataclass(frozen=True)
class StudySpec:
    """A parsed study file."""

    name: str
    out: Path
    tasks: tuple[Task, ...]
    per_positioner: bool = False
    retries: int = 2
    no_worker_timeout_s: float = 60.0
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
    from fiberplan._keys import unknown_key_message
    from fiberplan.instrument_io import load_instrument
    from fiberplan.planners import make_settings, planner_names, settings_class
    from fiberplan.studies.scenarios import STUDY_KINDS as SCENARIO_KINDS

    check_keys(data, STUDY_FILE_KEYS, origin, StudyError)
    grid = data.get("grid")
    if not isinstance(grid, dict):
        raise StudyError(f"{origin}: a [grid] table is needed (keys: {', '.join(GRID_KEYS)}, seeds)")
    check_keys(grid, (*GRID_KEYS, "seeds"), f"{origin}: [grid]", StudyError)
    missing = [k for k in (*GRID_KEYS, "seeds") if k not in grid]
    if missing:
        raise StudyError(f"{origin}: [grid] lacks {', '.join(missing)}")
    instruments = [str(v) for v in _as_list(grid["instrument"])]
    for name in instruments:
        try:
            load_instrument(name)
        except FiberplanError as e:
            raise StudyError(f"{origin}: {e}") from e
    sizes = _as_list(grid["n_positioners"])
    if not sizes or not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 50_000 for v in sizes):
        raise StudyError(f"{origin}: [grid] n_positioners must be integers from 1 to 50,000, found {grid['n_positioners']!r}")
    kinds = [str(v) for v in _as_list(grid["scenario_kind"])]
    for kind in kinds:
        if kind not in SCENARIO_KINDS:
            raise StudyError(f"{origin}: unknown scenario kind {kind!r}; choose from {', '.join(SCENARIO_KINDS)}")
    planners = [str(v) for v in _as_list(grid["planner"])]
    for name in planners:
        if name not in planner_names():
            raise StudyError(f"{origin}: unknown planner {name!r}; choose from {', '.join(planner_names())}")
    seeds_raw = grid["seeds"]
    if isinstance(seeds_raw, bool) or not isinstance(seeds_raw, (int, list)):
        raise StudyError(f"{origin}: [grid] seeds must be a count or a list of seeds, found {seeds_raw!r}")
    if isinstance(seeds_raw, int):
        if not 1 <= seeds_raw <= 1_000_000:
            raise StudyError(f"{origin}: [grid] seeds = {seeds_raw} must lie in [1, 1000000]")
        seeds = list(range(seeds_raw))
    else:
        seeds = list(seeds_raw)
        if not seeds or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 2**63 - 1 for v in seeds):
            raise StudyError(f"{origin}: [grid] seeds must be integers in [0, 2**63 - 1], found {seeds_raw!r}")
    settings_tables = data.get("settings", {})
    if not isinstance(settings_tables, dict) or not all(isinstance(v, dict) for v in settings_tables.values()):
        raise StudyError(f"{origin}: [settings] must hold one table per planner, e.g. [settings.mpc]")
    for name in settings_tables:
        if name not in planners:
            raise StudyError(
                f"{origin}: [settings.{name}] names a planner that is not in [grid] planner ({', '.join(planners)}); "
                "add it to the grid or remove the table"
            )
    scenario_table = data.get("scenario", {})
    if not isinstance(scenario_table, dict):
        raise StudyError(f"{origin}: [scenario] must be a table of make_scenario options")
    scenario_table = dict(scenario_table)
    check_keys(scenario_table, SCENARIO_OPTIONS, f"{origin}: [scenario]", StudyError)
    for name, values in scenario_table.items():
        for value in _as_list(values):
            _check_scenario_option(name, value, origin)
    option_names = sorted(scenario_table)
    option_combos = list(itertools.product(*(_as_list(scenario_table[n]) for n in option_names))) if option_names else [()]
    tasks: list[Task] = []
    for planner in planners:
        table = dict(settings_tables.get(planner, {}))
        settings_cls = settings_class(planner)
        known = {f.name for f in dataclasses.fields(settings_cls)}
        for key in table:
            if key not in known:
                raise StudyError(unknown_key_message(key, known, f"{origin}: planner {planner!r}", "setting"))
        names = sorted(table)
        combos = list(itertools.product(*(_as_list(table[n]) for n in names))) if names else [()]
        # Every value is checked now, for every instrument: a bad one is refused before any run.
        for instrument, combo in itertools.product(instruments, combos):
            try:
                make_settings(planner, load_instrument(instrument), dict(zip(names, combo, strict=True)))
            except FiberplanError as e:
                raise StudyError(f"{origin}: [settings.{planner}] on {instrument}: {e}") from e
        for instrument, n, kind, options, combo, seed in itertools.product(instruments, sizes, kinds, option_combos, combos, seeds):
            tasks.append(
                Task(
                    instrument, n, kind, planner, seed,
                    tuple(zip(names, combo, strict=True)),
                    tuple(zip(option_names, options, strict=True)),
                )
            )
    return tasks


def _check_scenario_option(name: str, value: Any, origin: str) -> None:
    """Refuse a ``[scenario]`` value :func:`fiberplan.generate.make_scenario` cannot take."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    ok = {
        "clusters": isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 100_000,
        "cluster_fraction": number and 0.0 <= value <= 1.0,
        "random_orientation": isinstance(value, bool),
        "radius_mm": number and math.isfinite(value) and value > 0,
        "min_start_clearance_mm": number and math.isfinite(value) and value >= 0,
    }[name]
    valid = {
        "clusters": "an integer >= 1", "cluster_fraction": "a number in [0, 1]", "random_orientation": "true or false",
        "radius_mm": "a number of mm > 0", "min_start_clearance_mm": "a number of mm >= 0",
    }[name]
    if not ok:
        raise StudyError(f"{origin}: [scenario] {name} must be {valid}, found {value!r}")


def study_from_dict(data: Mapping[str, Any], out: str | Path, origin: str = "study") -> StudySpec:
    """Build a study from the file layout as a dict (for notebooks and scripts).

    Raises:
        StudyError: invalid grid.
    """
    study = data.get("study", {})
    if not isinstance(study, dict):
        raise StudyError(f"{origin}: [study] must be a table ({', '.join(STUDY_KEYS)})")
    check_keys(study, STUDY_KEYS, f"{origin}: [study]", StudyError)
    per_positioner = study.get("per_positioner", False)
    retries = study.get("retries", 2)
    timeout = study.get("no_worker_timeout_s", 60.0)
    if not isinstance(per_positioner, bool):
        raise StudyError(f"{origin}: [study] per_positioner must be true or false, found {per_positioner!r}")
    if isinstance(retries, bool) or not isinstance(retries, int) or not 0 <= retries <= 100:
        raise StudyError(f"{origin}: [study] retries must be an integer in [0, 100], found {retries!r}")
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not 0 < timeout <= 86400:
        raise StudyError(f"{origin}: [study] no_worker_timeout_s must be a number of seconds in (0, 86400], found {timeout!r}")
    if "name" in study and not isinstance(study["name"], str):
        raise StudyError(f"{origin}: [study] name must be a string, found {study['name']!r}")
    return StudySpec(
        name=str(study.get("name", Path(out).stem)),
        out=Path(out),
        tasks=tuple(expand_grid(data, origin=origin)),
        per_positioner=per_positioner,
        retries=retries,
        no_worker_timeout_s=float(timeout),
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
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise StudyError(f"study file {str(path)!r} is not valid TOML ({e})") from e
    study_table = data.get("study", {})
    raw_out = study_table.get("out", path.with_suffix(".parquet").name) if isinstance(study_table, dict) else None
    if not isinstance(raw_out, str) or not raw_out:
        raise StudyError(f"study file {str(path)!r}: [study] out must be a file name, found {raw_out!r}")
    out = Path(raw_out)
    if not out.is_absolute():
        out = path.parent / out
    return study_from_dict(data, out, origin=f"study file {str(path)!r}")


def run_task(task: Task, per_positioner: bool = False) -> dict[str, Any]:
    """Run one task (:func:`~fiberplan.studies.runner.run_one`). Never raises: errors become a row."""
    return run_one(task, per_positioner)


def _write_part(parts_dir: Path, row: dict[str, Any]) -> None:
    positioners = row.pop("_positioners", None)
    parts_dir.mkdir(parents=True, exist_ok=True)
    lost = parts_dir / f"{row['task']}.lost.parquet"
    if row.get("status") == STATUS_LOST:  # shown in the table, but not a finished run
        with atomic_path(lost) as tmp:
            rows_frame([row]).to_parquet(tmp, index=False)
        return
    with atomic_path(parts_dir / f"{row['task']}.parquet") as tmp:
        rows_frame([row]).to_parquet(tmp, index=False)
    lost.unlink(missing_ok=True)
    if positioners is not None:
        import pandas as pd

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
    """Keys of tasks whose result exists (skipped on resume); ``lost`` runs are not finished."""
    return {p.name.split(".")[0] for p in _parts(spec) if not p.name.endswith(".lost.parquet")}


def lost_tasks(spec: StudySpec) -> set[str]:
    """Keys of tasks lost to the machinery (a dead worker) and not finished since."""
    return {p.name.split(".")[0] for p in _parts(spec) if p.name.endswith(".lost.parquet")} - finished_tasks(spec)


def _unadopted_rows(spec: StudySpec) -> Any:
    """The existing table's finished rows to adopt (:func:`adopt_table`): ``None`` unless the
    table exists and not one part does."""
    if not spec.out.is_file() or _parts(spec) or _parts(spec, positioners=True):
        return None
    import pandas as pd

    table = pd.read_parquet(spec.out)
    if "task" not in table.columns or "status" not in table.columns:
        raise StudyError(f"{spec.out} is not a study table (no 'task' or 'status' column), so the study cannot go on "
                         "from it; move it away or set another `out` in the study file")
    table = table[table["status"] != STATUS_LOST]
    if spec.per_positioner:  # (a run without its positioners' rows is run again)
        held = set(pd.read_parquet(spec.positioner_out, columns=["task"])["task"]) if spec.positioner_out.is_file() else set()
        table = table[table["task"].isin(held) | (table["status"] != "ok")]
    return table


def recorded_tasks(spec: StudySpec) -> set[str]:
    """Keys of the study's tasks a run of it skips: those with a part, or, where the parts are
    gone, the table's finished rows (:func:`adopt_table`)."""
    rows = _unadopted_rows(spec)
    keys = {t.key for t in spec.tasks}
    return (finished_tasks(spec) | (set() if rows is None else set(rows["task"]))) & keys


def adopt_table(spec: StudySpec) -> int:
    """Where a study's table exists and none of its parts does, give the table's finished rows
    their parts again; returns how many runs were adopted.

    The parts are working files (a fresh clone has the table without them): without this, a
    resumed study would run those tasks again and, until they finished, rebuild the table
    without their rows. A row recorded ``lost`` is not adopted (it runs again); where the study
    writes per-positioner rows, a finished run is adopted with its rows from
    ``<out stem>.positioners.parquet``, and run again if that has none. Where any part exists
    the parts are the record, as before (a part deleted runs again).
    """
    rows = _unadopted_rows(spec)
    if rows is None or rows.empty:
        return 0
    import pandas as pd

    positioners = None
    if spec.per_positioner and spec.positioner_out.is_file():
        positioners = dict(iter(pd.read_parquet(spec.positioner_out).groupby("task", sort=False)))
    spec.parts_dir.mkdir(parents=True, exist_ok=True)
    for key, row in rows.groupby("task", sort=False):
        mine = None if positioners is None else positioners.get(key)
        if mine is not None and len(mine):  # written first: a run's part is what marks it finished
            with atomic_path(spec.parts_dir / f"{key}.positioners.parquet") as tmp:
                mine.reset_index(drop=True).to_parquet(tmp, index=False)
        with atomic_path(spec.parts_dir / f"{key}.parquet") as tmp:
            row.reset_index(drop=True).to_parquet(tmp, index=False)
    return rows["task"].nunique()


def consolidate(spec: StudySpec) -> int:
    """Rebuild the results table (and the per-positioner table) from the parts. Returns the row count."""
    import pandas as pd

    done = finished_tasks(spec)
    parts = [p for p in _parts(spec) if not p.name.endswith(".lost.parquet") or p.name.split(".")[0] not in done]
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


def _progress_bar(total: int, initial: int) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc="runs", unit="run", dynamic_ncols=True)


def _local_results(tasks: Sequence[Task], per_positioner: bool, workers: int, retries: int) -> Iterator[dict[str, Any]]:
    """Run tasks on a process pool; a dead worker does not stop the sweep.

    When a worker process dies, every run then in flight fails with the broken pool, and
    which one killed it is unknown: those runs are retried one by one, each in a pool of its
    own, up to ``retries`` times, so that a death is blamed on exactly the run that caused it.
    A run whose worker still dies is recorded as ``lost`` (run again on resume), never as a
    result.
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
        for attempt in range(1, max(1, retries) + 1):
            with ProcessPoolExecutor(max_workers=1) as alone:
                try:
                    yield alone.submit(run_task, task, per_positioner).result()
                    break
                except BrokenProcessPool:
                    if attempt == max(1, retries):
                        yield _lost_row(task, f"worker process died on this run ({attempt} attempt(s) alone); run the sweep again to retry")


def _lost_row(task: Task, message: str) -> dict[str, Any]:
    row = empty_row(task.parameters())
    row["status"], row["error"] = STATUS_LOST, message
    return row


def _live_workers(client: Any) -> int:
    return len(client.scheduler_info().get("workers", {}))


def _dask_results(
    tasks: Sequence[Task], per_positioner: bool, scheduler: str, retries: int, no_worker_timeout_s: float,
) -> Iterator[dict[str, Any]]:
    """Run tasks on a Dask cluster. A lost worker's runs are re-run by Dask (``retries`` times);
    a run still lost becomes a ``lost`` row. With no live worker for ``no_worker_timeout_s``
    the sweep stops: :class:`InfrastructureError` (every finished row is kept)."""
    try:
        from dask.distributed import Client
    except ImportError as e:
        raise InfrastructureError('a Dask scheduler needs the study extra: python -m pip install "fiberplan[study]"') from e

    try:
        client = Client(scheduler, timeout=min(30.0, no_worker_timeout_s))
    except (OSError, TimeoutError) as e:
        raise InfrastructureError(f"cannot reach the Dask scheduler at {scheduler} ({type(e).__name__}: {e}); is it running?") from e
    with client:
        pending = {
            client.submit(run_task, t, per_positioner, key=f"fiberplan-{t.key}", pure=False, retries=retries): t for t in tasks
        }
        last_worker = time.monotonic()
        last_check = 0.0
        while pending:
            # Futures are polled (not waited on): a future the scheduler re-queues after losing its
            # worker must not block the sweep, which has to notice that no worker is left.
            ready = [f for f in pending if f.status in ("finished", "error", "cancelled", "lost")]
            for fut in ready:
                task = pending.pop(fut)
                if fut.status == "finished":
                    try:
                        yield fut.result(timeout=min(60.0, no_worker_timeout_s))
                        continue
                    except Exception as e:  # the result could not be fetched: its worker went away
                        yield _lost_row(task, f"{type(e).__name__}: {e}")
                        continue
                # run_task never raises: an error here is the machinery (a lost or killed worker)
                try:
                    detail = repr(fut.exception(timeout=min(10.0, no_worker_timeout_s))) if fut.status == "error" else fut.status
                except Exception as e:
                    detail = f"{type(e).__name__}: {e}"
                yield _lost_row(task, f"Dask run {fut.status}: {detail}")
            if ready:
                continue
            now = time.monotonic()
            if now - last_check >= 0.5:
                last_check = now
                try:
                    alive = _live_workers(client)
                except Exception as e:  # the scheduler itself is gone
                    raise InfrastructureError(f"lost the Dask scheduler at {scheduler} ({type(e).__name__}: {e})") from e
                if alive:
                    last_worker = now
                elif now - last_worker >= no_worker_timeout_s:
                    client.cancel(list(pending))
                    raise InfrastructureError(
                        f"no live Dask worker at {scheduler} for {no_worker_timeout_s:g} s; stopped. Every finished run is kept: "
                        "start workers and run the same command again to resume"
                    )
            time.sleep(0.05)


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

    Raises:
        OutputError: another run of the same study (the same table) is going on: two would run
            the same tasks twice and race each other's table.
    """
    with exclusive(spec.out, what="study table", fix="another run of this study is going on: wait for it to end or stop it "
                   "(the same command then resumes)"):
        return _run_study(spec, workers, scheduler, progress, consolidate_every_s)


def _run_study(spec: StudySpec, workers: int | None, scheduler: str | None, progress: bool, consolidate_every_s: float) -> int:
    if spec.parts_dir.is_dir():
        for stale in spec.parts_dir.glob(".*.part.parquet"):  # left by a writer that was killed
            stale.unlink(missing_ok=True)
    adopted = adopt_table(spec)
    if adopted and progress:
        print(f"{spec.out}: its parts were gone; {adopted} finished run(s) taken from the table", file=sys.stderr)
    done = finished_tasks(spec)
    todo = [t for t in spec.tasks if t.key not in done]
    bar = _progress_bar(len(spec.tasks), len(spec.tasks) - len(todo)) if progress else None
    last = time.monotonic()
    try:
        if todo:
            if scheduler:
                results: Iterable[dict[str, Any]] = _dask_results(
                    todo, spec.per_positioner, scheduler, spec.retries, spec.no_worker_timeout_s
                )
            else:
                results = _local_results(todo, spec.per_positioner, workers or os.cpu_count() or 1, spec.retries)
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
