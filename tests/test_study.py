"""Sweeps: grid expansion, Dask cluster execution, loss-free resume after kill -9, analysis."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fiberplan.studies import StudyError, finished_tasks, load_study, rates, recorded_tasks, run_study, wilson_interval

TIMING = ["plan_wall_s", "run_wall_s", "stat.loop_wall_s", "stat.gradient_time_s", "stat.safety_time_s", "traceback"]

SPEC = """
[study]
name = "t"
per_positioner = true

[grid]
instrument = ["desi"]
n_positioners = [7, 19]
scenario_kind = ["random"]
planner = ["straight"]
seeds = {seeds}

[settings.straight]
dt_s = [0.01, 0.02, 0.05]
"""

INJECTED = "injected failure for dt_s = 0.05"


@pytest.fixture
def failing_cell(monkeypatch):
    """``straight`` raises on the dt_s = 0.05 cells (a deterministic run error; forked workers see it)."""
    import fiberplan.planners.straight as straight_module

    original = straight_module.plan_straight

    def plan_straight(scenario, settings, progress=None):
        if settings.dt_s == 0.05:
            raise RuntimeError(INJECTED)
        return original(scenario, settings, progress)

    monkeypatch.setattr(straight_module, "plan_straight", plan_straight)


def write_spec(folder: Path, seeds: int = 3) -> Path:
    path = folder / "study.toml"
    path.write_text(SPEC.format(seeds=seeds))
    return path


def comparable(frame: pd.DataFrame) -> pd.DataFrame:
    drop = [c for c in frame.columns if c in TIMING or c.endswith("_time_s")]
    return frame.drop(columns=drop).sort_values("task").reset_index(drop=True)


def test_grid_expansion_and_errors(tmp_path):
    spec = load_study(write_spec(tmp_path, seeds=4))
    assert len(spec.tasks) == 2 * 3 * 4
    assert len({t.key for t in spec.tasks}) == len(spec.tasks)
    bad = tmp_path / "bad.toml"
    bad.write_text(SPEC.format(seeds=2).replace('planner = ["straight"]', 'planner = ["warp"]'))
    with pytest.raises(StudyError, match="unknown planner 'warp'"):
        load_study(bad)
    bad.write_text(SPEC.format(seeds=2).replace("dt_s = ", "speed = "))
    with pytest.raises(StudyError, match="has no setting 'speed'"):
        load_study(bad)
    # A value outside its range is refused before any run, naming planner, instrument and range.
    bad.write_text(SPEC.format(seeds=2).replace("0.05]", "-1.0]"))
    with pytest.raises(StudyError, match=r"\[settings.straight\] on desi: straight: setting 'dt_s' = -1.0 s is outside"):
        load_study(bad)
    # Misspelled keys anywhere name the closest valid key; nothing is ignored.
    for old, new, match in (
        ("seeds = ", "seed = ", r"\[grid\]: unknown key 'seed'; did you mean 'seeds'\?"),
        ("per_positioner", "per_positoner", "unknown key 'per_positoner'; did you mean 'per_positioner'"),
        ("[settings.straight]", "[setting.straight]", "unknown key 'setting'; did you mean 'settings'"),
        ("[settings.straight]", "[settings.dnf]", r"\[settings.dnf\] names a planner that is not in \[grid\]"),
        ("n_positioners = [7, 19]", "n_positioners = [7, 0]", "n_positioners must be integers from 1"),
    ):
        bad.write_text(SPEC.format(seeds=2).replace(old, new))
        with pytest.raises(StudyError, match=match):
            load_study(bad)
    bad.write_text(SPEC.format(seeds=2) + "\n[scenario]\ncluster_fraction = [0.5, 1.5]\n")
    with pytest.raises(StudyError, match=r"cluster_fraction must be a number in \[0, 1\], found 1.5"):
        load_study(bad)
    bad.write_text(SPEC.format(seeds=2) + "\n[scenario]\nmin_start_clearance_mm = -0.1\n")
    with pytest.raises(StudyError, match=r"min_start_clearance_mm must be a number of mm >= 0, found -0.1"):
        load_study(bad)
    # The starts of before the minimum, asked for: their own runs (another key than the default's).
    good = tmp_path / "good.toml"
    good.write_text(SPEC.format(seeds=2) + "\n[scenario]\nmin_start_clearance_mm = 0.0\n")
    zero = load_study(good).tasks
    assert {t.key for t in zero}.isdisjoint(t.key for t in spec.tasks)
    t = zero[0]
    from fiberplan.generate import make_scenario

    expected = make_scenario(t.instrument, t.n_positioners, t.scenario_kind, t.seed, min_start_clearance_mm=0.0)
    assert np.array_equal(t.scenario().start_deg, expected.start_deg)
    with pytest.raises(StudyError, match="does not exist"):
        load_study(tmp_path / "none.toml")


def test_local_sweep_records_failures_and_skips_finished(tmp_path, failing_cell):
    spec = load_study(write_spec(tmp_path, seeds=2))
    assert run_study(spec, workers=2, progress=False) == 12
    table = pd.read_parquet(spec.out)
    failed = table[table["status"] == "error"]
    assert len(failed) == 4 and (failed["setting.dt_s"] == 0.05).all()
    assert failed["error"].str.contains(INJECTED).all()
    ok = table[table["status"] == "ok"]
    assert (ok["success_rate"] == 1.0).all() and ok["collisions"].notna().all()
    positioners = pd.read_parquet(spec.positioner_out)
    assert len(positioners) == 2 * 2 * (7 + 19)
    mtime = spec.out.stat().st_mtime_ns
    parts_before = sorted(p.name for p in spec.parts_dir.iterdir())
    run_study(spec, workers=2, progress=False)  # nothing left to run
    assert sorted(p.name for p in spec.parts_dir.iterdir()) == parts_before
    assert spec.out.stat().st_mtime_ns >= mtime


def test_a_table_without_its_parts_is_kept_and_the_study_goes_on_from_it(tmp_path):
    """A fresh clone has the table, not its parts: its runs are not made again, nor its rows lost."""
    import shutil

    spec = load_study(write_spec(tmp_path, seeds=2))
    run_study(spec, workers=1, progress=False)
    table, positioners = pd.read_parquet(spec.out), pd.read_parquet(spec.positioner_out)
    shutil.rmtree(spec.parts_dir)
    grown = load_study(write_spec(tmp_path, seeds=3))  # one more seed, the same table
    assert len(recorded_tasks(grown)) == len(table) and not finished_tasks(grown)
    assert run_study(grown, workers=1, progress=False) == len(table) + 6
    after, after_positioners = pd.read_parquet(grown.out), pd.read_parquet(grown.positioner_out)
    kept = after[after["task"].isin(table["task"])].reset_index(drop=True)
    pd.testing.assert_frame_equal(kept, table)  # the timings too: not run again
    assert sorted(after.loc[~after["task"].isin(table["task"]), "seed"]) == [2] * 6
    old = after_positioners[after_positioners["task"].isin(table["task"])].reset_index(drop=True)
    pd.testing.assert_frame_equal(old, positioners)
    assert len(after_positioners) == len(positioners) + 3 * (7 + 19)
    # A row recorded lost runs again, and so does a run whose positioners' rows are gone; where
    # any part is left, the parts are the record (a part deleted runs again).
    shutil.rmtree(grown.parts_dir)
    lost, bare = after["task"].iloc[0], after["task"].iloc[1]
    after.loc[after["task"] == lost, "status"] = "lost"
    after.to_parquet(grown.out, index=False)
    after_positioners[after_positioners["task"] != bare].to_parquet(grown.positioner_out, index=False)
    assert recorded_tasks(grown) == set(after["task"]) - {lost, bare}
    grown.parts_dir.mkdir()
    after.iloc[2:3].to_parquet(grown.parts_dir / f"{after['task'].iloc[2]}.parquet", index=False)
    assert recorded_tasks(grown) == {after["task"].iloc[2]}


def test_sweep_on_a_real_local_dask_cluster(tmp_path):
    from dask.distributed import LocalCluster

    spec = load_study(write_spec(tmp_path, seeds=2))
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None) as cluster:
        rows = run_study(spec, scheduler=cluster.scheduler_address, progress=False)
    assert rows == 12
    dask_table = comparable(pd.read_parquet(spec.out))
    local_dir = tmp_path / "local"
    local_dir.mkdir()
    local = load_study(write_spec(local_dir, seeds=2))
    run_study(local, workers=1, progress=False)
    pd.testing.assert_frame_equal(dask_table, comparable(pd.read_parquet(local.out)))


def test_killed_sweep_resumes_to_the_same_table(tmp_path):
    killed_dir, clean_dir = tmp_path / "killed", tmp_path / "clean"
    killed_dir.mkdir()
    clean_dir.mkdir()
    spec_path = write_spec(killed_dir, seeds=6)
    spec = load_study(spec_path)
    cmd = [sys.executable, "-m", "fiberplan.cli", "sweep", str(spec_path), "--workers", "1", "-q"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        parts = list(spec.parts_dir.glob("*.parquet")) if spec.parts_dir.is_dir() else []
        if len(parts) >= 3 or proc.poll() is not None:
            break
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    finished = len(finished_tasks(spec))
    assert 0 < finished < len(spec.tasks), "the sweep should have been killed part-way"
    resumed = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{finished} already done" in resumed.stderr
    clean = load_study(write_spec(clean_dir, seeds=6))
    run_study(clean, workers=1, progress=False)
    pd.testing.assert_frame_equal(comparable(pd.read_parquet(spec.out)), comparable(pd.read_parquet(clean.out)))


def test_wilson_interval():
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-3)
    lo, hi = wilson_interval(50, 100)
    assert lo == pytest.approx(0.4038, abs=1e-3) and hi == pytest.approx(0.5962, abs=1e-3)


def test_rates_group_and_pool_positioners():
    frame = pd.DataFrame(
        {
            "planner": ["a", "a", "b"],
            "status": ["ok", "ok", "ok"],
            "targets": [10, 10, 10],
            "reached": [10, 8, 9],
            "deadlocked": [0, 2, 1],
            "collisions": [0, 0, 0],
        }
    )
    table = rates(frame, ["planner"]).set_index("planner")
    assert table.loc["a", "success_rate"] == pytest.approx(0.9)
    assert table.loc["a", "deadlock_rate"] == pytest.approx(0.1)
    assert table.loc["a", "runs_all_reached"] == pytest.approx(0.5)
    assert table.loc["a", "deadlock_lo"] < 0.1 < table.loc["a", "deadlock_hi"]


def test_dead_worker_is_retried_then_lost_and_run_again_on_resume(tmp_path, monkeypatch):
    import fiberplan.studies.sweep as study_module

    spec = load_study(write_spec(tmp_path, seeds=2))
    doomed = spec.tasks[1].key
    original = study_module.run_task
    attempts = tmp_path / "attempts"

    def dies_on_one_task(task, per_positioner=False):
        if task.key == doomed and not (tmp_path / "healed").exists():
            with attempts.open("a") as f:
                f.write("x")
            os._exit(1)  # the worker process dies, as under the OOM killer
        return original(task, per_positioner)

    # pickled by reference as fiberplan.studies.sweep.run_task, which the forked workers see patched
    dies_on_one_task.__module__, dies_on_one_task.__qualname__ = "fiberplan.studies.sweep", "run_task"
    monkeypatch.setattr(study_module, "run_task", dies_on_one_task)
    assert run_study(spec, workers=2, progress=False) == len(spec.tasks)
    table = pd.read_parquet(spec.out).set_index("task")
    assert table.loc[doomed, "status"] == "lost"
    assert "worker process died on this run (2 attempt(s) alone)" in table.loc[doomed, "error"]
    assert len(attempts.read_text()) == 1 + spec.retries  # once in the pool, then retried alone (bounded)
    assert (table.drop(index=doomed)["status"] == "ok").all()
    assert study_module.lost_tasks(spec) == {doomed} and doomed not in finished_tasks(spec)
    # The machinery recovers: the resumed sweep runs the lost run again, and only it.
    (tmp_path / "healed").touch()
    before = {p.name: p.stat().st_mtime_ns for p in spec.parts_dir.glob("*.parquet")}
    assert run_study(spec, workers=2, progress=False) == len(spec.tasks)
    table = pd.read_parquet(spec.out).set_index("task")
    assert table.loc[doomed, "status"] == "ok" and not study_module.lost_tasks(spec)
    after = {p.name: p.stat().st_mtime_ns for p in spec.parts_dir.glob("*.parquet")}
    assert {k for k in before if k in after and before[k] != after[k]} == set()


def test_sweep_without_live_workers_stops_and_keeps_finished_rows(tmp_path):
    import threading

    from dask.distributed import LocalCluster

    from fiberplan.errors import InfrastructureError

    spec_path = write_spec(tmp_path, seeds=40)
    spec_path.write_text(spec_path.read_text().replace('per_positioner = true', 'per_positioner = false\nno_worker_timeout_s = 2'))
    spec = load_study(spec_path)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None) as cluster:

        def retire_when_some_are_done():
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and len(finished_tasks(spec)) < 3:
                time.sleep(0.05)
            cluster.scale(0)

        killer = threading.Thread(target=retire_when_some_are_done, daemon=True)
        killer.start()
        t0 = time.monotonic()
        with pytest.raises(InfrastructureError, match="no live Dask worker .* for 2 s"):
            run_study(spec, scheduler=cluster.scheduler_address, progress=False)
        killer.join()
        assert time.monotonic() - t0 < 90
    kept = pd.read_parquet(spec.out)
    ok = kept[kept["status"] == "ok"]
    # Finished rows are kept; runs whose results died with the worker are "lost", to run again.
    assert 3 <= len(ok) and len(kept) < len(spec.tasks) and set(kept["status"]) <= {"ok", "lost"}
    assert finished_tasks(spec) == set(ok["task"])


def test_a_second_run_of_a_study_is_refused_while_the_first_runs(tmp_path):
    """Two runs of one study would run its tasks twice and race each other's table: the second
    is refused, naming the first's process; once the first ends (here killed), the study runs."""
    spec_path = write_spec(tmp_path, seeds=1)
    spec = load_study(spec_path)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom fiberplan._atomic import exclusive\n"
         f"with exclusive({str(spec.out)!r}):\n    print('held', flush=True)\n    time.sleep(600)"],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        cmd = [sys.executable, "-m", "fiberplan.cli", "sweep", str(spec_path), "--workers", "1", "-q"]
        refused = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        assert refused.returncode != 0 and "Traceback" not in refused.stderr
        assert f"being written by another run (process {holder.pid})" in refused.stderr
        assert "wait for it to end or stop it" in refused.stderr
        assert not spec.out.exists() and not finished_tasks(spec)  # nothing run, nothing written
    finally:
        holder.kill()
        holder.wait()
    ran = subprocess.run(cmd, capture_output=True, text=True, timeout=300)  # the lock went with its process
    assert ran.returncode == 0, ran.stderr
    assert len(pd.read_parquet(spec.out)) == len(spec.tasks)


def test_a_killed_run_leaves_no_lock_behind_in_its_orphaned_workers(tmp_path):
    """A run's worker processes are forked with a copy of its lock; killed with its workers still
    alive, the run must not leave its study locked by them."""
    out = tmp_path / "t.parquet"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import time\nfrom concurrent.futures import ProcessPoolExecutor\n"
         "from fiberplan._atomic import exclusive\n"
         f"with exclusive({str(out)!r}):\n    pool = ProcessPoolExecutor(1)\n    pid = pool.submit(__import__('os').getpid).result()\n"
         "    print(pid, flush=True)\n    time.sleep(600)"],
        stdout=subprocess.PIPE, text=True, start_new_session=True,
    )
    worker = int(holder.stdout.readline())
    try:
        from fiberplan._atomic import exclusive
        from fiberplan.errors import OutputError

        with pytest.raises(OutputError, match=f"process {holder.pid}"):
            with exclusive(out):
                pass
        holder.kill()  # the parent only: its worker lives on, orphaned
        holder.wait()
        os.kill(worker, 0)  # (still there)
        with exclusive(out):  # the lock went with the parent
            pass
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(worker, signal.SIGKILL)
