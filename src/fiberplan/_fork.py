"""Two independent computations at once: the second in a forked process while the first runs here.

Used where each computation is deterministic and depends only on what both share at the fork, so
the results are the same as one after the other, which is what happens on a machine with one
core, where ``fork`` is missing, inside a daemonic process (a Dask worker cannot have children),
inside a forked child already, or when the forked process dies (its computation is then made
here). The second's result travels back through a pipe (pickled).
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Callable
from typing import Any

_IN_CHILD = [False]


def can_fork() -> bool:
    """Whether :func:`both` would fork here."""
    return (
        (os.cpu_count() or 1) >= 2
        and "fork" in mp.get_all_start_methods()
        and not _IN_CHILD[0]
        and not mp.current_process().daemon
    )


def both(first: Callable[[], Any], second: Callable[[], Any]) -> tuple[Any, Any, bool]:
    """``(first(), second(), forked)``: the second in a forked process where that is safe (module
    docstring); ``forked`` says whether its result came from there (else it ran here)."""
    if not can_fork():
        return first(), second(), False
    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)

    def run() -> None:
        _IN_CHILD[0] = True
        try:
            out = ("ok", second())
        except BaseException as e:  # reported to the parent, which raises it
            out = ("error", repr(e))
        child.send(out)
        child.close()

    proc = ctx.Process(target=run, daemon=False)  # the computation may start worker processes of its own
    proc.start()
    child.close()
    try:
        a = first()
        try:
            status, b = parent.recv()
        except EOFError:  # the forked process died without a word: make its part here
            status, b = "lost", None
    finally:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.terminate()
    if status == "lost":
        return a, second(), False
    if status != "ok":
        raise RuntimeError(f"the part computed in a forked process failed: {b}")
    return a, b, True
