"""Progress, deadlock and escape bookkeeping of the ``dnf`` planner (the ``retreat`` escape)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fiberplan.planners.dnf.settings import DnfSettings

# ---------------------------------------------------------------------------------------------
# Progress, deadlock and escape bookkeeping


def _distance_to_go(settings: DnfSettings, rho_mm: float, q: np.ndarray, target: np.ndarray, fiber_err: np.ndarray) -> np.ndarray:
    """The distance the attraction shrinks (mm): ``rho ||q - q_T||`` (joint) or the fiber error.

    Progress is measured on it, not on the fiber error, because a straight joint move may
    take the fiber away from its target before bringing it back.
    """
    if settings.attraction == "joint":
        return rho_mm * np.linalg.norm(q - target, axis=1)
    return fiber_err


class _ProgressWindow:
    """Best distance-to-target of each positioner over a sliding window of steps.

    A positioner is stuck when it has been tracked for ``window`` steps and its best
    distance to go (:func:`_distance_to_go`) has not improved by more than ``threshold_mm`` over the last ``window`` steps.
    """

    def __init__(self, err: np.ndarray, window: int, threshold_mm: float) -> None:
        self.window = window
        self.threshold = threshold_mm
        self.best = err.copy()
        self.ring = np.full((window + 1, len(err)), np.inf)
        self.ring[0] = self.best
        self.age = np.zeros(len(err), dtype=np.int64)
        self.count = 0

    def update(self, err: np.ndarray) -> None:
        self.count += 1
        self.age += 1
        self.best = np.minimum(self.best, err)
        self.ring[self.count % (self.window + 1)] = self.best

    def stuck(self) -> np.ndarray:
        before = self.ring[(self.count - self.window) % (self.window + 1)] if self.count >= self.window else np.inf
        return (self.age >= self.window) & (before - self.best <= self.threshold)

    def reset(self, rows: np.ndarray, err: np.ndarray) -> None:
        self.best[rows] = err[rows]
        self.ring[:, rows] = np.inf
        self.ring[self.count % (self.window + 1), rows] = err[rows]
        self.age[rows] = 0


@dataclass
class _Escape:
    """Retreat sub-goals: who yields, to where, until when."""

    active: np.ndarray  # (N,) bool
    goal: np.ndarray  # (N, 2)
    until: np.ndarray  # (N,) step index at which the retreat ends
    count: np.ndarray  # (N,) retreats so far
    started: int = 0


def _start_retreats(
    escape: _Escape,
    stuck: np.ndarray,
    reached: np.ndarray,
    pairs: np.ndarray,
    clear0: np.ndarray,
    envelope_mm: float,
    rank: np.ndarray,
    ids: np.ndarray,
    q: np.ndarray,
    fold_beta: float,
    step_index: int,
    retreat_steps: int,
    max_retreats: int,
) -> np.ndarray:
    """Pick the yielding positioner of every blocked pair and send it toward its folded arm.

    A pair blocks when one of its positioners is stuck (not reached) and their clearance is
    inside the envelope. Of the two, the one with the lower ``rank`` yields (ties: the larger
    id), as positioner 5 of reference 002, fig. 5 does: its sub-goal keeps its alpha and folds
    beta. Returns the rows that started a retreat.
    """
    if len(pairs) == 0:
        return np.zeros(0, dtype=np.int64)
    ii, jj = pairs[:, 0], pairs[:, 1]
    blocked = (clear0 < envelope_mm) & ((stuck[ii] & ~reached[ii]) | (stuck[jj] & ~reached[jj]))
    if not np.any(blocked):
        return np.zeros(0, dtype=np.int64)
    bi, bj = ii[blocked], jj[blocked]
    i_yields = (rank[bi] < rank[bj]) | ((rank[bi] == rank[bj]) & (ids[bi] > ids[bj]))
    yielders = np.unique(np.where(i_yields, bi, bj))
    yielders = yielders[~escape.active[yielders] & (escape.count[yielders] < max_retreats)]
    if len(yielders) == 0:
        return yielders
    escape.active[yielders] = True
    escape.goal[yielders, 0] = q[yielders, 0]
    escape.goal[yielders, 1] = fold_beta
    escape.until[yielders] = step_index + retreat_steps
    escape.count[yielders] += 1
    escape.started += len(yielders)
    return yielders
