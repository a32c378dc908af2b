"""Two independent legs planned at once: the second in a forked process while the first runs here.

Each leg is planned deterministically from its own scenario, so the results are the same as
one after the other (:mod:`fiberplan._fork` says where it forks and where it does not). The
forked leg sends back the statistics of its planner runs with its result. :class:`Ahead` starts
a candidate that may not be needed (planned ahead, let go if it is not).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fiberplan import _fork

CHILD_RUNS: list[dict[str, Any]] = []
"""Statistics of the planner runs made in a forked process, for the totals."""

RUN_LOG: list[dict[str, Any]] = []
"""Statistics of every planner run of this process (the forked leg sends its own back)."""


def both(first: Callable[[], Any], second: Callable[[], Any]) -> tuple[Any, Any]:
    """``(first(), second())``, the second in a forked process where that is safe."""
    with Ahead(second) as ahead:
        return first(), ahead.result()


class Ahead:
    """A candidate planned ahead in a forked process (:class:`fiberplan._fork.Ahead`): its result
    when asked for (with its planner runs' statistics), or let go on leaving the ``with`` block;
    ``start=False``: planned here if asked for."""

    def __init__(self, compute: Callable[[], Any], start: bool = True) -> None:
        def logged() -> tuple[Any, list[dict[str, Any]]]:
            runs_before = len(RUN_LOG)
            return compute(), list(RUN_LOG[runs_before:])

        self._ahead = _fork.Ahead(logged, start)

    def result(self) -> Any:
        value, child_runs = self._ahead.result()
        if self._ahead.forked:
            CHILD_RUNS.extend(child_runs)
        return value

    def __enter__(self) -> Ahead:
        return self

    def __exit__(self, *exc: object) -> None:
        self._ahead.cancel()
