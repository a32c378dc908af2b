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
import signal
from collections.abc import Callable
from typing import Any

_IN_CHILD = [False]


def in_child() -> bool:
    """Whether this is a forked process of this module (which shows no progress of its own: the
    parent's progress bar is the one on the screen)."""
    return _IN_CHILD[0]


def can_fork() -> bool:
    """Whether :func:`both` would fork here."""
    return (
        (os.cpu_count() or 1) >= 2
        and "fork" in mp.get_all_start_methods()
        and not _IN_CHILD[0]
        and not mp.current_process().daemon
    )


class Ahead:
    """A computation started now in a forked process where that is safe (module docstring),
    whose result is asked for later (:meth:`result`) or let go (:meth:`cancel`, also on leaving a
    ``with`` block): speculation on a core that would otherwise idle. Where it cannot fork, the
    computation is made here when its result is asked for, and never if it is let go; so too
    with ``start=False``."""

    def __init__(self, compute: Callable[[], Any], start: bool = True) -> None:
        self._compute = compute
        self._proc: Any = None
        self._pipe: Any = None
        self.forked = False  # whether the result came from the forked process
        if not (start and can_fork()):
            return
        ctx = mp.get_context("fork")
        parent, child = ctx.Pipe(duplex=False)

        def run() -> None:
            _IN_CHILD[0] = True
            os.setpgid(0, 0)  # its own process group: cancelling it also ends what it started
            try:
                out = ("ok", compute())
            except BaseException as e:  # reported to the parent, which raises it
                out = ("error", repr(e))
            child.send(out)
            child.close()

        self._proc = ctx.Process(target=run, daemon=False)  # the computation may start worker processes of its own
        self._proc.start()
        try:  # (also from here, so that a cancel right after the start finds the group)
            os.setpgid(self._proc.pid, self._proc.pid)
        except OSError:  # it has set it already, or has ended
            pass
        child.close()
        self._pipe = parent

    def result(self) -> Any:
        """The computation's result (made here if it was not forked, or if the forked process died
        without a word)."""
        if self._proc is None:
            return self._compute()
        try:
            status, value = self._pipe.recv()
        except EOFError:
            status, value = "lost", None
        finally:
            self._end(timeout=10.0)
        if status == "lost":
            return self._compute()
        if status != "ok":
            raise RuntimeError(f"the part computed in a forked process failed: {value}")
        self.forked = True
        return value

    def cancel(self) -> None:
        """Let the computation go: its forked process (and any it started) is ended."""
        if self._proc is not None:
            self._end(timeout=0.0)

    def _end(self, timeout: float) -> None:
        proc, self._proc = self._proc, None
        self._pipe.close()
        proc.join(timeout=timeout)
        if proc.is_alive():
            try:
                os.killpg(proc.pid, signal.SIGTERM)
            except (ProcessLookupError, PermissionError):
                proc.terminate()
            proc.join(timeout=10.0)

    def __enter__(self) -> Ahead:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()


def both(first: Callable[[], Any], second: Callable[[], Any]) -> tuple[Any, Any, bool]:
    """``(first(), second(), forked)``: the second in a forked process where that is safe (module
    docstring); ``forked`` says whether its result came from there (else it ran here)."""
    with Ahead(second) as ahead:
        a = first()
        b = ahead.result()
    return a, b, ahead.forked
