"""Two independent legs planned at once: the second in a forked process while the first runs here.

Each leg is planned deterministically from its own scenario, so the results are the same as
one after the other, which is what happens on a machine with one core, where ``fork`` is
missing, inside a daemonic process (a Dask worker cannot have children), or when the forked
process dies (its leg is then planned here).
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Callable
from typing import Any

CHILD_RUNS: list[dict[str, Any]] = []
"""Statistics of the planner runs made in a forked process, for the totals."""

RUN_LOG: list[dict[str, Any]] = []
"""Statistics of every planner run of this process (the forked leg sends its own back)."""

_IN_CHILD = [False]


def _can_fork() -> bool:
    return (
        (os.cpu_count() or 1) >= 2
        and "fork" in mp.get_all_start_methods()
        and not _IN_CHILD[0]
        and not mp.current_process().daemon
    )


def both(first: Callable[[], Any], second: Callable[[], Any]) -> tuple[Any, Any]:
    """``(first(), second())``, the second in a forked process where that is safe (module docstring)."""
    if not _can_fork():
        return first(), second()
    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)

    def run() -> None:
        _IN_CHILD[0] = True
        runs_before = len(RUN_LOG)
        try:
            out = ("ok", second(), list(RUN_LOG[runs_before:]))
        except BaseException as e:  # reported to the parent, which raises it
            out = ("error", repr(e), [])
        child.send(out)
        child.close()

    proc = ctx.Process(target=run, daemon=False)  # the leg may start the mpc's own worker processes
    proc.start()
    child.close()
    try:
        a = first()
        try:
            status, b, child_runs = parent.recv()
        except EOFError:  # the forked process died without a word: plan its leg here
            status, b, child_runs = "lost", None, []
    finally:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.terminate()
    if status == "lost":
        return a, second()
    if status != "ok":
        raise RuntimeError(f"the leg planned in a forked process failed: {b}")
    CHILD_RUNS.extend(child_runs)
    return a, b
