"""Waiting places: when the targets of a deadlocked pair impose an order, where the one that
must wait goes so that the other can arrive first (``formulations/mpc.md``, Deadlocks)."""

from __future__ import annotations

import numpy as np

from fiberplan.geometry import path_clearance
from fiberplan.scenario import Scenario

__all__ = ["path_clearance", "waiting_configuration"]


def waiting_configuration(
    scenario: Scenario, first: int, waiter: int, q: np.ndarray, datum: np.ndarray, step_rad: np.ndarray, blocked_mm: float,
) -> np.ndarray | None:
    """Where ``waiter`` should wait so that its neighbour ``first`` can arrive first, or ``None``.

    Precedence from the targets: ``first`` must arrive first when its straight path from ``q``
    to its target passes closer than ``blocked_mm`` to ``waiter`` at its target. The waiting
    configuration is the first of: ``waiter``'s start, folded at its target alpha, folded at
    its current alpha, such that ``first``'s path clears it and ``waiter``'s path from it to its
    target clears ``first`` at its target. ``first``'s path blocked by where ``waiter`` is now
    also imposes the order (a face-to-face deadlock mid-way).
    """
    f, w = np.array([first]), np.array([waiter])
    target = scenario.target
    blockers = np.array([target[waiter], q[waiter]])
    f2, w2 = np.repeat(f, 2), np.repeat(w, 2)
    if np.all(path_clearance(scenario, f2, w2, q[f2], target[f2], blockers, step_rad) >= blocked_mm):
        return None  # no precedence: first's path is free of waiter's target and of where it is
    candidates = np.array([
        scenario.start[waiter],
        [target[waiter, 0], datum[waiter, 1]],
        [q[waiter, 0], datum[waiter, 1]],
    ])
    m = len(candidates)
    ff, ww = np.repeat(f, m), np.repeat(w, m)
    ok = path_clearance(scenario, ff, ww, np.repeat(q[f], m, axis=0), np.repeat(target[f], m, axis=0), candidates, step_rad) >= blocked_mm
    ok &= path_clearance(scenario, ww, ff, candidates, np.repeat(target[w], m, axis=0), np.repeat(target[f], m, axis=0), step_rad) >= blocked_mm
    good = np.flatnonzero(ok)
    return candidates[good[0]] if len(good) else None
