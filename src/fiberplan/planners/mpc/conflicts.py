"""Conflicts and the linearised collision constraints of the ``mpc`` planner's QPs.

A pair of neighbours is *in conflict* when its clearance now, or between the two positioners'
published plans at any horizon step, is below ``conflict_radius_mm`` (:func:`select_conflicts`).
For every positioner in conflict, its separation from each neighbour ``j`` at horizon step
``k`` is linearised around its own previous plan ``qbar_i(k)`` and ``j``'s published plan
``qhat_j(k)`` (:func:`build_qp_batch`):

.. math:: g_{ij}(\\bar q_i(k), \\hat q_j(k)) + \\nabla_{q_i} g_{ij} \\cdot (q_i(k) - \\bar q_i(k)) \\ge m_{ij} - s_{ij}

with the small margin and the cheap slack on the higher-priority side; the ``S`` most critical
neighbours of each positioner (smallest predicted clearance) get the QP's neighbour slots.
"""

from __future__ import annotations

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.geometry import pair_clearance
from fiberplan.planners.mpc.executors import QpBatch
from fiberplan.planners.mpc.kernels import holds_at_goal
from fiberplan.planners.mpc.priority import outranks
from fiberplan.planners.mpc.qp import QpLayout
from fiberplan.planners.mpc.settings import MpcSettings
from fiberplan.scenario import Scenario


def select_conflicts(
    scenario: Scenario, settings: MpcSettings, c_now: np.ndarray, q: np.ndarray, plan: np.ndarray, goal_prev: np.ndarray,
    step_mm: float,
) -> np.ndarray:
    """Rows of the pairs in conflict: near enough now to need a look, and closer than
    ``conflict_radius_mm`` now or along the published plans.

    Two positioners holding still at their goals need no QP: nothing changes between them.
    """
    pairs = scenario.pairs
    if not len(pairs):
        return np.zeros(0, dtype=np.int64)
    H = plan.shape[1]
    resting = holds_at_goal(q, goal_prev, plan)  # at its goal with a plan that holds it there
    near = c_now < settings.conflict_radius_mm + 2 * H * step_mm
    cand = np.flatnonzero(near & ~(resting[pairs[:, 0]] & resting[pairs[:, 1]]))
    sel = cand
    if len(cand):
        pred = pair_clearance(scenario.instrument, scenario.base_xy, scenario.orient, np.swapaxes(plan, 0, 1), pairs[cand])
        c_min = np.minimum(c_now[cand], pred.clearance.min(axis=(0, 2)))
        sel = cand[c_min < settings.conflict_radius_mm]
    return sel


def build_qp_batch(
    scenario: Scenario,
    settings: MpcSettings,
    layout: QpLayout,
    cp: np.ndarray,
    cap_mm: np.ndarray,
    q: np.ndarray,
    own_plan: np.ndarray,
    plan: np.ndarray,
    ref: np.ndarray,
    v_prev: np.ndarray,
    rank: np.ndarray,
    defer_to: np.ndarray,
    boosted: np.ndarray,
    step_rad: np.ndarray,
    lim: np.ndarray,
) -> QpBatch:
    """Linearise the separation of every conflicting pair along the plans; stack per-positioner QP data."""
    inst = scenario.instrument
    H, S = layout.horizon_steps, layout.n_slots
    i, j = cp[:, 0], cp[:, 1]
    owner = np.concatenate([i, j])
    nbr = np.concatenate([j, i])
    n_d = len(owner)
    # Virtual positioners: row r = (directed pair d, step k): the owner at its own plan
    # (index r), the neighbour at its published plan (index R + r).
    R = n_d * H
    oo = np.repeat(owner, H)
    nn = np.repeat(nbr, H)
    kk = np.tile(np.arange(H), n_d)
    base = np.concatenate([scenario.base_xy[oo], scenario.base_xy[nn]])
    orient = np.concatenate([scenario.orient[oo], scenario.orient[nn]])
    joints = np.concatenate([own_plan[oo, kk], plan[nn, kk]])
    virt = np.stack([np.arange(R), R + np.arange(R)], axis=1)
    pc = pair_clearance(inst, base, orient, joints, virt, gradient=True)
    if pc.grad_i is None:  # pragma: no cover - asked for above
        raise PlannerError("mpc: clearance gradients missing")
    best = pc.clearance.argmin(axis=1)
    rows = np.arange(R)
    g2 = pc.clearance[rows, best].reshape(n_d, H)
    grad = pc.grad_i[rows, best].reshape(n_d, H, 2)
    higher = outranks(owner, nbr, rank, defer_to)
    cap2 = np.concatenate([cap_mm, cap_mm])
    margin = np.minimum(np.where(higher, settings.priority_margin_mm, settings.margin_mm), cap2)
    # A deadlocked positioner (boosted) plans straight through lower-priority neighbours,
    # which see its plan and yield; the safety layer keeps the executed steps apart.
    ratio = np.where(boosted[owner], 0.01 * settings.priority_slack_ratio, settings.priority_slack_ratio)
    slack_w = settings.slack_weight_linear * np.where(higher, ratio, 1.0)
    lin_point = own_plan[owner]  # (D, H, 2)
    rhs = margin[:, None] - g2 + np.einsum("dkc,dkc->dk", grad, lin_point - q[owner][:, None, :])
    coef = grad * step_rad

    order = np.lexsort((nbr, g2.min(axis=1), owner))
    owner, rhs, coef, slack_w = owner[order], rhs[order], coef[order], slack_w[order]
    index, first, counts = np.unique(owner, return_index=True, return_counts=True)
    local = np.repeat(np.arange(len(index)), counts)
    slot = np.arange(len(owner)) - np.repeat(first, counts)
    keep = slot < S  # the S most critical neighbours of each positioner
    owner, rhs, coef, slack_w, local, slot = owner[keep], rhs[keep], coef[keep], slack_w[keep], local[keep], slot[keep]
    m = len(index)
    coef_b = np.zeros((m, S, H, 2))
    rhs_b = np.zeros((m, S, H))
    active_b = np.zeros((m, S), dtype=bool)
    slack_b = np.full((m, S), settings.slack_weight_linear)
    coef_b[local, slot] = coef
    rhs_b[local, slot] = rhs
    active_b[local, slot] = True
    slack_b[local, slot] = slack_w
    qi = q[index]
    return QpBatch(
        index=index,
        z_ref=(ref[index] - qi[:, None, :]) / step_rad,
        z_lo=(lim[:, 0] - qi) / step_rad,
        z_hi=(lim[:, 1] - qi) / step_rad,
        v_prev=v_prev[index],
        coef=coef_b,
        rhs=rhs_b,
        active=active_b,
        slack_linear=slack_b,
    )
