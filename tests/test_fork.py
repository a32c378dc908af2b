"""The forked computations (fiberplan._fork): the same results as here, and nothing left running."""

from __future__ import annotations

import os
import subprocess
import time

import pytest

from fiberplan import _fork

needs_fork = pytest.mark.skipif(not _fork.can_fork(), reason="forks only with fork and at least two cores")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A child ended but not yet reaped by its parent is a zombie: not running.
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@needs_fork
def test_a_computation_planned_ahead_comes_back_from_the_forked_process():
    here = os.getpid()
    ahead = _fork.Ahead(lambda: (os.getpid(), sum(range(1000))))
    pid, value = ahead.result()
    assert ahead.forked and pid != here and value == 499500


def test_a_computation_not_started_is_made_here_when_asked_for_and_never_if_let_go():
    calls = []
    with _fork.Ahead(lambda: calls.append(os.getpid()) or 7, start=False) as ahead:
        pass
    assert calls == []
    ahead = _fork.Ahead(lambda: calls.append(os.getpid()) or 7, start=False)
    assert ahead.result() == 7 and calls == [os.getpid()] and not ahead.forked


@needs_fork
def test_a_computation_let_go_ends_with_what_it_started(tmp_path):
    # The forked process starts a process of its own and runs on; leaving the block ends both.
    pid_file = tmp_path / "pid"

    def slow() -> int:
        sleeper = subprocess.Popen(["sleep", "60"])
        pid_file.write_text(str(sleeper.pid))
        time.sleep(60)
        return 1

    t0 = time.perf_counter()
    with _fork.Ahead(slow):
        for _ in range(200):
            if pid_file.exists() and pid_file.read_text():
                break
            time.sleep(0.05)
    assert time.perf_counter() - t0 < 30
    sleeper = int(pid_file.read_text())
    for _ in range(100):
        if not _alive(sleeper):
            break
        time.sleep(0.05)
    assert not _alive(sleeper)


@needs_fork
def test_a_failure_in_the_forked_process_is_raised_here():
    def broken() -> int:
        raise ValueError("positioner 12 is broken")

    with pytest.raises(RuntimeError, match="positioner 12 is broken"):
        _fork.Ahead(broken).result()


@needs_fork
def test_both_gives_the_two_results_in_order():
    a, b, forked = _fork.both(lambda: "first", lambda: "second")
    assert (a, b, forked) == ("first", "second", True)
