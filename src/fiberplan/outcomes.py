"""The outcome of a positioner, one vocabulary for every planner, the verifier's summary and the studies.

=============  ==================================================================================
``reached``    ends within the instrument's tolerance of its target
``deadlocked`` has a target, did not reach it, and made no progress over the planner's window
               (stuck: its time-to-go, or distance-to-go, did not improve)
``unfinished`` has a target, did not reach it, and was still progressing at the time limit
``failed``     a solver or planner fault left it short (e.g. the central NLP did not converge)
``held``       has no target and ends where it started (it may have yielded meanwhile)
``displaced``  has no target and ends elsewhere (by more than the tolerance)
``infeasible`` its target cannot be reached at all (checked before planning)
``locked``     cannot move (a static obstacle for everyone)
=============  ==================================================================================

A rate of deadlocks is ``deadlocked / positioners with a target`` for every planner alike.
"""

from __future__ import annotations

import numpy as np

from fiberplan.kinematics import fiber_positions
from fiberplan.scenario import Scenario

OUTCOMES = ("reached", "deadlocked", "unfinished", "failed", "held", "displaced", "infeasible", "locked")
"""Every outcome a positioner can have."""

SHORT = ("deadlocked", "unfinished", "failed", "infeasible")
"""The outcomes of a positioner with a target that did not reach it."""


def outcome_labels(scenario: Scenario, final_joints: np.ndarray, stuck: np.ndarray, failed: np.ndarray | None = None) -> np.ndarray:
    """Outcome of every positioner from where it ended (``final_joints``, rad).

    Args:
        scenario: the planned scenario.
        final_joints: ``(N, 2)`` joints at the end of the trajectory.
        stuck: ``(N,)`` whether the planner saw no progress over its window at the end.
        failed: ``(N,)`` positioners a solver or planner fault left short (optional).
    """
    inst = scenario.instrument
    final_xy = fiber_positions(inst, scenario.base_xy, scenario.orient, final_joints)
    reached = (np.linalg.norm(final_xy - scenario.target_xy, axis=1) <= inst.tolerance_mm) & scenario.has_target
    out = np.where(reached, "reached", np.where(stuck, "deadlocked", "unfinished")).astype("<U10")
    if failed is not None:
        out[failed & ~reached & scenario.has_target] = "failed"
    start_xy = fiber_positions(inst, scenario.base_xy, scenario.orient, scenario.start)
    moved = np.linalg.norm(final_xy - start_xy, axis=1) > inst.tolerance_mm
    out[~scenario.has_target] = np.where(moved[~scenario.has_target], "displaced", "held")
    out[list(scenario.infeasible)] = "infeasible"
    out[scenario.locked] = "locked"
    return out


def explain(scenario: Scenario, final_joints: np.ndarray, outcome: np.ndarray) -> dict[int, str]:
    """Why, for every positioner not ``reached`` (keyed by id): the infeasibility reason; for
    ``deadlocked`` and ``unfinished`` ones the neighbour closest to it at the end, with the
    clearance (who it is stuck against); for ``displaced`` ones how far from their start."""
    from fiberplan.geometry import min_pair_clearance

    inst = scenario.instrument
    out: dict[int, str] = {}
    pairs = scenario.pairs
    clearance = min_pair_clearance(inst, scenario.base_xy, scenario.orient, final_joints, pairs) if len(pairs) else np.zeros(0)
    final_xy = fiber_positions(inst, scenario.base_xy, scenario.orient, final_joints)
    for k in np.flatnonzero(outcome != "reached").tolist():
        kind = str(outcome[k])
        pid = int(scenario.ids[k])
        if kind == "infeasible":
            out[pid] = f"infeasible: {scenario.infeasible.get(k, '')}"
        elif kind in ("deadlocked", "unfinished", "failed"):
            togo = float(np.linalg.norm(final_xy[k] - scenario.target_xy[k]))
            rows = np.flatnonzero((pairs == k).any(axis=1)) if len(pairs) else np.zeros(0, dtype=int)
            what = {"deadlocked": "no progress for a window", "unfinished": "still moving at the time limit",
                    "failed": "the planner failed"}[kind]
            if len(rows):
                r = rows[np.argmin(clearance[rows])]
                other = int(scenario.ids[pairs[r, 1] if pairs[r, 0] == k else pairs[r, 0]])
                out[pid] = f"{kind}: {what}, {togo:.3g} mm from its target, closest to positioner {other} ({clearance[r]:.3g} mm)"
            else:
                out[pid] = f"{kind}: {what}, {togo:.3g} mm from its target"
        elif kind == "displaced":
            start_xy = fiber_positions(inst, scenario.base_xy[[k]], scenario.orient[[k]], scenario.start[[k]])[0]
            out[pid] = f"displaced: no target, ends {float(np.linalg.norm(final_xy[k] - start_xy)):.3g} mm from its start"
    return out


def count(outcome: np.ndarray) -> dict[str, int]:
    """How many positioners have each outcome (every outcome listed, zeros included)."""
    return {name: int(np.sum(outcome == name)) for name in OUTCOMES}
