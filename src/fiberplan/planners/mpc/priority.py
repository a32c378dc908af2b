"""Priorities of the ``mpc`` planner: who yields to whom.

Deadlocked positioners come first, in the order they were first found deadlocked (sticky, so
two of them never swap roles); then the longest time-to-go. A waiter always defers to the
neighbour it waits for. The higher-priority side of a pair keeps the small margin and the
cheap slack in its QP (the other side yields), and the safety layer stops the lower-priority
mover of an unsafe pair first.
"""

from __future__ import annotations

import numpy as np


def outranks(a: np.ndarray, b: np.ndarray, rank: np.ndarray, defer_to: np.ndarray) -> np.ndarray:
    """Whether ``a`` has priority over ``b`` (row-wise): global ``rank``, except that a waiter
    ``w`` always defers to the neighbour ``defer_to[w]`` it waits for."""
    res = rank[a] < rank[b]
    res = np.where(defer_to[b] == a, True, res)
    return np.where(defer_to[a] == b, False, res)


def ranks(boosted: np.ndarray, first_dead: np.ndarray, time_to_go: np.ndarray, locked: np.ndarray | None = None) -> np.ndarray:
    """Rank of every positioner (0 first): locked ones (static obstacles: everyone yields to
    them), then boosted ones (by when they were first found deadlocked), then the longest
    time-to-go, then the index."""
    n = len(boosted)
    locked = np.zeros(n, dtype=bool) if locked is None else locked
    order = np.lexsort((np.arange(n), -time_to_go, np.where(boosted, first_dead, 0), ~boosted, ~locked))
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    return rank
