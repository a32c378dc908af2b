"""Sweeps: grid expansion, Dask cluster execution, loss-free resume after kill -9, analysis."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from fiberplan.study import StudyError, finished_tasks, load_study, rates, run_study, wilson_interval

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
dt_s = [0.01, 0.02, -1.0]
"""


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
    with pytest.raises(StudyError, match="does not exist"):
        load_study(tmp_path / "none.toml")


def test_local_sweep_records_failures_and_skips_finished(tmp_path):
    spec = load_study(write_spec(tmp_path, seeds=2))
    assert run_study(spec, workers=2, progress=False) == 12
    table = pd.read_parquet(spec.out)
    failed = table[table["status"] == "error"]
    assert len(failed) == 4 and (failed["setting.dt_s"] == -1.0).all()
    assert failed["error"].str.contains("'dt_s' = -1.0 s is outside its valid range").all()
    ok = table[table["status"] == "ok"]
    assert (ok["success_rate"] == 1.0).all() and ok["collisions"].notna().all()
    positioners = pd.read_parquet(spec.positioner_out)
    assert len(positioners) == 2 * 2 * (7 + 19)
    mtime = spec.out.stat().st_mtime_ns
    parts_before = sorted(p.name for p in spec.parts_dir.iterdir())
    run_study(spec, workers=2, progress=False)  # nothing left to run
    assert sorted(p.name for p in spec.parts_dir.iterdir()) == parts_before
    assert spec.out.stat().st_mtime_ns >= mtime


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


def test_dead_worker_is_replaced_and_its_run_recorded(tmp_path, monkeypatch):
    import fiberplan.study as study_module

    spec = load_study(write_spec(tmp_path, seeds=2))
    doomed = spec.tasks[1].key
    original = study_module.run_task

    def dies_on_one_task(task, per_positioner=False):
        if task.key == doomed:
            os._exit(1)  # the worker process dies, as under the OOM killer
        return original(task, per_positioner)

    # pickled by reference as fiberplan.study.run_task, which the forked workers see patched
    dies_on_one_task.__module__, dies_on_one_task.__qualname__ = "fiberplan.study", "run_task"
    monkeypatch.setattr(study_module, "run_task", dies_on_one_task)
    assert run_study(spec, workers=2, progress=False) == len(spec.tasks)
    table = pd.read_parquet(spec.out).set_index("task")
    assert table.loc[doomed, "status"] == "error"
    assert "worker process died on this run" in table.loc[doomed, "error"]
    others = table.drop(index=doomed)
    assert (others.loc[others["setting.dt_s"] > 0, "status"] == "ok").all()
