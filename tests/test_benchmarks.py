"""The benchmark scripts' own measuring parts (what their figures rest on)."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

linux_rollup = pytest.mark.skipif(
    not (Path("/proc/self/smaps_rollup").exists() and Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children").exists()),
    reason="needs Linux's /proc/PID/smaps_rollup and /proc/PID/task/TID/children",
)


def _with_child(child, seconds: float) -> None:
    """Fork a process that runs ``child()`` and sleeps; end it after ``seconds``."""
    pid = os.fork()
    if pid == 0:
        child()
        time.sleep(5)
        os._exit(0)
    try:
        time.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)


@linux_rollup
def test_the_memory_a_process_tree_holds_counts_pages_shared_after_a_fork_once() -> None:
    from scaling import TreePss

    mb = 160
    with TreePss(every_s=0.02) as alone:
        block = np.ones(mb * 2**20 // 8)  # touched: resident, private to this process
        time.sleep(0.3)
    with TreePss(every_s=0.02) as shared:  # the child only holds the parent's pages (copy-on-write, never written)
        _with_child(lambda: None, 0.5)

    def write() -> None:  # the child writes every page: its own copy
        block[:] += 1.0

    with TreePss(every_s=0.02) as copied:
        _with_child(write, 1.5)
    assert block[0] == 1.0
    assert alone.samples > 3 and alone.peak_mb > mb
    # The child's resident set counts the block again; held together, it is there once.
    assert shared.peak_mb < alone.peak_mb + 0.3 * mb
    # Written in the child, it is there twice.
    assert copied.peak_mb > alone.peak_mb + 0.8 * mb


def test_gap_rows_carry_the_newer_compares_energy_gaps() -> None:
    from bench import _gap_rows

    def row(planner: str, makespan: float, **extra: object) -> dict[str, object]:
        return {"scenario": "s0", "seed": 0, "planner": planner, "status": "ok", "clean": True, "success_rate": 1.0,
                "makespan_s": makespan, "lower_bound_s": 5.0, "plan_wall_s": 1.0} | extra

    central = {"rows": [row("central", 10.0)]}
    other = {"rows": [row("mpc", 11.0, energy_gap_to_central=0.5), row("dnf", 12.0, energy_gap_to_central=float("nan"))]}
    mpc, dnf = _gap_rows(central, other)
    assert mpc["gap_to_central"] == pytest.approx(0.1) and mpc["energy_gap_to_central"] == 0.5
    assert dnf["gap_to_central"] == pytest.approx(0.2) and dnf["energy_gap_to_central"] is None  # not solved: no figure


def test_a_stopped_compare_resumes_with_its_seeds_kept(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    import json

    import _machine
    import bench

    monkeypatch.setattr(bench, "RESULTS", tmp_path)
    monkeypatch.setattr(_machine, "source_tree", lambda: "tree-a")

    def compare(*extra: str) -> None:
        base = ["bench.py", "compare", "--instrument", "desi", "-n", "7", "--planners", "straight", "--kind", "random", "--name", "c"]
        monkeypatch.setattr(sys, "argv", base + list(extra))
        bench.main()

    compare("--seed-list", "0")
    first = json.loads((tmp_path / "c.json").read_text())
    assert first["parameters"]["seeds"] == [0] and first["complete"]
    with pytest.raises(SystemExit, match="exists; give --name"):
        compare("--seed-list", "0,1")
    compare("--seed-list", "0,1", "--resume")
    both = json.loads((tmp_path / "c.json").read_text())
    assert both["parameters"]["seeds"] == [0, 1] and both["complete"] and [r["seed"] for r in both["rows"]] == [0, 1]
    assert both["rows"][0]["plan_wall_s"] == first["rows"][0]["plan_wall_s"]  # seed 0 kept, not planned again
    assert both["aggregates"]["straight"]["runs"] == 2
    with pytest.raises(SystemExit, match="planners"):  # other options: refused, naming the option
        compare("--seed-list", "0,1,2", "--resume", "--planners", "straight,dnf")
    monkeypatch.setattr(_machine, "source_tree", lambda: "tree-b")
    with pytest.raises(SystemExit, match="other code"):
        compare("--seed-list", "0,1,2", "--resume")
    assert json.loads((tmp_path / "c.json").read_text())["parameters"]["seeds"] == [0, 1]  # nothing lost
    with pytest.raises(SystemExit, match="give one of the two"):  # keep and replace at once: refused
        compare("--seed-list", "0,1,2", "--resume", "--overwrite")
    with pytest.raises(SystemExit, match="no .* to go on with"):  # a mistyped name is not a new run
        compare("--seed-list", "0", "--resume", "--name", "d")
    assert not (tmp_path / "d.json").exists()


def test_a_compare_in_use_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A compare writes its file after every seed: a second of the same name (a resume started
    twice) would overwrite the first's seeds with its own, so it is refused while the first runs."""
    import json

    import bench

    from fiberplan._atomic import exclusive

    monkeypatch.setattr(bench, "RESULTS", tmp_path)
    base = ["bench.py", "compare", "--instrument", "desi", "-n", "7", "--planners", "straight", "--kind", "random", "--name", "c"]
    with exclusive(tmp_path / "c.json"):  # (another run holds it: an open file description of its own)
        monkeypatch.setattr(sys, "argv", [*base, "--seed-list", "0"])
        with pytest.raises(SystemExit, match=r"c\.json' is being written by another run \(process \d+\); wait for that compare"):
            bench.main()
    assert not (tmp_path / "c.json").exists()
    bench.main()  # released: the same command runs
    assert json.loads((tmp_path / "c.json").read_text())["parameters"]["seeds"] == [0]


def test_gap_does_not_overwrite_a_result(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    import bench

    monkeypatch.setattr(bench, "RESULTS", tmp_path)
    stored = tmp_path / "central_x.json"
    stored.write_text(json.dumps({"rows": []}))
    monkeypatch.setattr(sys, "argv", ["bench.py", "gap", "--central", str(stored), "--against", str(stored), "--name", "central_x"])
    with pytest.raises(SystemExit, match="exists; give --name"):  # the reference itself, hours of solves
        bench.main()
    assert json.loads(stored.read_text()) == {"rows": []}
    monkeypatch.setattr(sys, "argv", ["bench.py", "gap", "--central", str(tmp_path / "none.json"), "--against", str(stored), "--name", "g"])
    with pytest.raises(SystemExit, match="no result file"):
        bench.main()


def test_an_installed_copy_inside_another_repository_has_no_commit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # fiberplan installed (not editable) into a virtual environment inside some git repository:
    # that repository's HEAD is not the imported code's commit.
    import subprocess

    import _machine

    import fiberplan

    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@example.org", "commit", "-q", "--allow-empty",
                    "-m", "a commit HEAD names"], check=True)
    copy = tmp_path / ".venv" / "lib" / "python3.11" / "site-packages" / "fiberplan" / "__init__.py"
    copy.parent.mkdir(parents=True)
    copy.write_text("")
    monkeypatch.setattr(fiberplan, "__file__", str(copy))
    assert _machine.source_commit() == "unknown" and _machine.source_tree() == "unknown"
    # The checkout itself is recognised (this test runs from one, or from a copy without git).
    monkeypatch.undo()
    assert _machine.source_commit() == "unknown" or len(_machine.source_commit().removesuffix("-dirty")) == 40
