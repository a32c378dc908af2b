"""The ``dnf`` planner: decentralized navigation functions (references 000 and 002).

Every positioner ``i`` descends its own potential (``formulations/dnf.md``)

.. math::

    \\psi_i = \\lambda_1 A_i(q_i) + \\lambda_2 \\sum_{j \\in N(i)} \\sum_{k} \\phi(r_{ijk}; d_k, D_{ik}),
    \\qquad
    \\phi(r; d, D) = \\begin{cases} \\dfrac{D^2 - r^2}{r^2 - d^2} & d < r < D \\\\ 0 & r \\ge D \\end{cases}

with the attraction ``A_i`` either ``rho^2 ||q_i - q_iT||^2`` in joint space (default) or
``||p_i(q_i) - p_iT||^2`` in the focal plane (reference 000, eq. 2), and ``r_ijk`` the
separation of capsule combination ``k`` of the pair: the segment distance (for DESI, the
fiber-end distance of reference 000), or for arm capsules the weighted (ellipse) distance of
reference 002, eqs. 6-7. ``d_k`` is the sum of the two radii and ``D_ik = d_k + m_ik`` with the
envelope margin ``m_ik`` of positioner ``i`` (reference 002, section 2.4: per-positioner zone
sizes act as an implicit priority).

The control law is the chain rule through the Jacobian (reference 000, eqs. 3-4),
``omega_i = -grad_{q_i} psi_i``, saturated at the motor speeds with the direction kept. A safety
layer then checks the exact capsule clearances of the configuration that is actually reached
(all positioners step at once) and shortens the steps of the positioners of every pair whose
linear motion over the step could not be proven collision-free (halving, then holding).
A positioner that is not within tolerance and has not come closer to its target over a
window is marked ``deadlocked``. By default (``deadlock_escape = "retreat"``, not part of the
printed method) a pair blocked for a shorter window is resolved by a temporary sub-goal: its
lower-priority member folds its beta arm for a while, as positioner 5 backs away in reference
002, fig. 5. The run stops when every positioner sits exactly on its
target joints or can make no more progress, or at the time limit (positioners still moving
then are ``unfinished``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from fiberplan.kinematics import fiber_jacobian, fiber_positions, move_times
from fiberplan.outcomes import outcome_labels
from fiberplan.planners import ProgressCallback
from fiberplan.planners.dnf.escape import _distance_to_go, _Escape, _ProgressWindow, _start_retreats
from fiberplan.planners.dnf.potential import _ClearanceBound, _pair_model, _PairModel, _repulsion_gradient, convergence_condition
from fiberplan.planners.dnf.settings import DnfSettings
from fiberplan.planners.safety import HalvingStats, halve_steps, point_extents
from fiberplan.scenario import Scenario
from fiberplan.settings import check_step_budget
from fiberplan.trajectory import PlanResult, Trajectory

# ---------------------------------------------------------------------------------------------
# The planner


def plan_dnf(scenario: Scenario, settings: DnfSettings, progress: ProgressCallback | None = None) -> PlanResult:
    """Plan with decentralized navigation functions (see the module docstring).

    Every control step costs O(N): one vectorised pass over the neighbour pairs that may be
    inside an envelope for the repulsion, one over the pairs at risk for the safety layer;
    there is no Python loop over positioners.

    Args:
        scenario: what to plan.
        settings: see :class:`DnfSettings` (``DnfSettings.for_instrument`` for defaults).
        progress: optional callback receiving the fraction of the time limit simulated.

    Returns:
        The trajectory (samples every ``dt_s`` from 0), per-positioner outcome
        (``reached``: within the instrument's tolerance at the end; ``deadlocked``: not, and no
        progress over ``deadlock_window_s``; ``unfinished``: not, and still progressing at the time
        limit; ``held`` / ``displaced``: no target, ending where it started or not) and
        statistics (steps, retreats, safety-layer interventions, timings, whether reference
        000's eq. 5 holds for the settings).
    """
    t_wall = time.perf_counter()
    inst = scenario.instrument
    n = scenario.n_positioners
    dt = settings.dt_s
    lim = inst.limits_rad
    rho_reach = inst.reach_max_mm
    rho_motion = point_extents(inst)
    target = scenario.target
    target_xy = scenario.target_xy
    model = _pair_model(scenario, settings)
    pairs = model.pairs
    fold_beta = float(np.clip(inst.datum_rad[1], lim[1, 0], lim[1, 1]))

    initial_move = move_times(inst, scenario.start, target)
    lower = float(initial_move.max())
    time_limit = settings.time_limit_s if settings.time_limit_s is not None else 4.0 * lower + 2.0 * settings.deadlock_window_s
    max_steps = max(1, math.ceil(time_limit / dt - 1e-9))
    check_step_budget("dnf", max_steps, dt, time_limit)
    window = max(1, round(settings.deadlock_window_s / dt))
    escape_window = max(1, round(settings.escape_window_s / dt))
    retreat_steps = max(1, round(settings.retreat_s / dt))
    tol = inst.tolerance_mm

    q = scenario.start.copy()
    history = [q.copy()]
    err = np.linalg.norm(fiber_positions(inst, scenario.base_xy, scenario.orient, q) - target_xy, axis=1)
    togo = _distance_to_go(settings, rho_reach, q, target, err)
    deadlock = _ProgressWindow(togo, window, settings.progress_mm)
    blocking = _ProgressWindow(togo, escape_window, settings.progress_mm)
    escape = _Escape(
        active=np.zeros(n, dtype=bool), goal=target.copy(), until=np.zeros(n, dtype=np.int64), count=np.zeros(n, dtype=np.int64)
    )
    stuck = np.zeros(n, dtype=bool)
    stuck_ever = np.zeros(n, dtype=bool)
    safety = HalvingStats()
    culling = _ClearanceBound(pairs, n, rho_motion)
    repulsion_active_steps = 0
    t_grad = t_safe = 0.0
    step_count = 0
    non_finite_steps = 0
    for step_count in range(1, max_steps + 1):
        t0 = time.perf_counter()
        step, clear0, snap, n_repelled = _desired_step(scenario, settings, model, culling, q, escape, rho_reach)
        repulsion_active_steps += n_repelled
        snap_step = step[snap]
        step[scenario.locked] = 0.0  # locked positioners never move
        bad_step = ~np.isfinite(step).all(axis=1)  # a non-finite gradient holds the positioner
        if bad_step.any():
            step[bad_step] = 0.0
            non_finite_steps += int(bad_step.sum())
        t1 = time.perf_counter()
        step = halve_steps(scenario, pairs, q, step, clear0, settings.safety_margin_mm, settings.safety_motion_factor,
                           settings.max_halvings, rho_motion, safety)
        t2 = time.perf_counter()
        t_grad += t1 - t0
        t_safe += t2 - t1
        q = q + step
        culling.moved(step)
        # A snap step that was executed in full lands exactly on the target joints.
        landed = np.flatnonzero(snap)[np.all(step[snap] == snap_step, axis=1)]
        q[landed] = target[landed]
        history.append(q.copy())

        err = np.linalg.norm(fiber_positions(inst, scenario.base_xy, scenario.orient, q) - target_xy, axis=1)
        _track_deadlocks(scenario, settings, model, q, err, clear0, escape, deadlock, blocking, initial_move, fold_beta, step_count,
                         retreat_steps, rho_reach)
        settled = ~escape.active & deadlock.stuck()
        stuck = (err > tol) & settled
        stuck_ever |= stuck
        if progress is not None and step_count % 50 == 0:
            progress(min(1.0, step_count / max_steps), "control loop")
        # Done when every positioner sits exactly on its target joints or cannot progress
        # (a reached one held off its exact target by a neighbour, or a deadlocked one).
        if np.all(np.all(q == target, axis=1) | settled):
            break

    if progress is not None:
        progress(1.0)
    counters = {
        "n_steps": step_count,
        "time_limit_s": float(time_limit),
        "time_limit_hit": bool(step_count == max_steps and not np.all(np.all(q == target, axis=1) | settled)),
        "lower_bound_s": lower,
        "deadlock_window_steps": window,
        "n_ever_stuck": int(stuck_ever.sum()),
        "non_finite_steps_held": non_finite_steps,
        "retreats": escape.started,
        "safety_interventions": safety.interventions,
        "safety_held_steps": safety.held,
        "safety_iterations": safety.iterations,
        "repulsion_active_positioner_steps": repulsion_active_steps,
        "n_pairs": len(pairs),
        "gradient_time_s": t_grad,
        "safety_time_s": t_safe,
        "loop_wall_s": time.perf_counter() - t_wall,
    }
    return _dnf_result(scenario, settings, np.stack(history), stuck, err <= tol, counters)


def _track_deadlocks(
    scenario: Scenario, settings: DnfSettings, model: _PairModel, q: np.ndarray, err: np.ndarray, clear0: np.ndarray,
    escape: _Escape, deadlock: _ProgressWindow, blocking: _ProgressWindow, initial_move: np.ndarray, fold_beta: float, step_count: int,
    retreat_steps: int, rho_reach: float,
) -> None:
    """Progress windows after a step; escapes that end; retreats that start (``deadlock_escape = "retreat"``)."""
    reached = err <= scenario.instrument.tolerance_mm
    togo = _distance_to_go(settings, rho_reach, q, scenario.target, err)
    deadlock.update(togo)
    blocking.update(togo)
    ended = np.flatnonzero(escape.active & (escape.until <= step_count))
    if len(ended):
        escape.active[ended] = False
        deadlock.reset(ended, togo)
        blocking.reset(ended, togo)
    if settings.deadlock_escape == "retreat":
        started = _start_retreats(
            escape, blocking.stuck(), reached, model.pairs, clear0, settings.envelope_mm,
            np.where(reached, -1.0, initial_move), scenario.ids, q, fold_beta, step_count, retreat_steps, settings.max_retreats,
        )
        if len(started):
            deadlock.reset(started, togo)
            blocking.reset(started, togo)


def _desired_step(
    scenario: Scenario, settings: DnfSettings, model: _PairModel, culling: _ClearanceBound, q: np.ndarray, escape: _Escape,
    rho_reach: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The control law: ``omega = -grad psi`` saturated at the motor speeds (direction kept),
    inside the hard stops, snapping onto the target from within a step when no repulsion acts.

    Returns ``(step, clearances, snap, repelled)``: the joint step of every positioner, the pair
    clearances (exact where evaluated), who snaps, and how many feel a repulsion.
    """
    inst = scenario.instrument
    speeds, lim, dt = inst.speeds_rad_s, inst.limits_rad, settings.dt_s
    target, target_xy = scenario.target, scenario.target_xy
    g_rep, clear0 = _repulsion_gradient(scenario, model, q, settings.lambda_repel, settings.potential, culling)
    goal = np.where(escape.active[:, None], escape.goal, target)
    if settings.attraction == "joint":
        g_att = 2.0 * settings.lambda_attract * rho_reach**2 * (q - goal)
    else:
        goal_xy = np.where(escape.active[:, None], fiber_positions(inst, scenario.base_xy, scenario.orient, goal), target_xy)
        p = fiber_positions(inst, scenario.base_xy, scenario.orient, q)
        jac = fiber_jacobian(inst, scenario.orient, q)
        g_att = 2.0 * settings.lambda_attract * np.einsum("nij,ni->nj", jac, p - goal_xy)
    omega = -(g_att + g_rep)
    over = (np.abs(omega) / speeds).max(axis=1)
    omega = omega / np.maximum(over, 1.0)[:, None]
    step = dt * omega
    free = ~np.any(g_rep != 0.0, axis=1)
    one_step = dt * speeds * (1.0 - 1e-9)
    snap = free & ~escape.active & np.all(np.abs(target - q) <= one_step, axis=1)
    step[snap] = (target - q)[snap]
    step = np.clip(q + step, lim[:, 0], lim[:, 1]) - q
    return step, clear0, snap, int(np.sum(~free))


def _dnf_result(
    scenario: Scenario, settings: DnfSettings, joints: np.ndarray, stuck: np.ndarray, reached: np.ndarray, counters: dict[str, Any],
) -> PlanResult:
    """Outcomes, statistics and warnings of a run."""
    inst = scenario.instrument
    outcome = outcome_labels(scenario, joints[-1], stuck)
    times = np.arange(len(joints)) * settings.dt_s
    stats: dict[str, Any] = counters | {
        "duration_s": float(times[-1]),
        "n_reached": int(reached.sum()),
        "n_deadlocked": int(np.sum(outcome == "deadlocked")),
        "n_unfinished": int(np.sum(outcome == "unfinished")),
        "convergence_condition_holds": convergence_condition(
            inst, settings.lambda_attract, max(settings.lambda_repel, 1e-300), settings.envelope_mm
        ).holds,
    }
    warnings = []
    short = int(np.sum(scenario.has_target & ~reached))
    if short:
        warnings.append(
            f"dnf: {short} of {int(scenario.has_target.sum())} positioners did not reach their targets ({stats['n_deadlocked']} "
            f"deadlocked, {stats['n_unfinished']} still moving at the time limit of {stats['time_limit_s']:.2f} s)"
        )
    if counters["non_finite_steps_held"]:
        warnings.append(f"dnf: {counters['non_finite_steps_held']} non-finite step(s) were held (a positioner at a singular configuration)")
    return PlanResult(
        scenario=scenario,
        trajectory=Trajectory(times, joints),
        outcome=outcome,
        planner="dnf",
        settings=dataclasses.asdict(settings),
        stats=stats,
        warnings=tuple(warnings),
    )
