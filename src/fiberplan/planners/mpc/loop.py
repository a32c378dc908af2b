"""The ``mpc`` planner: decentralised model-predictive control with per-positioner OSQP QPs.

At every control step (``formulations/mpc.md``):

1. Conflict detection (vectorised): a pair of neighbours is *in conflict* when its clearance
   now, or between the two positioners' published plans at any horizon step, is below
   ``conflict_radius_mm``. Positioners in no conflict take the saturated step toward their
   target without a QP.
2. Every positioner in conflict solves its own QP (:mod:`~fiberplan.planners.mpc.qp`) against
   the plans its neighbours published in the previous round (Jacobi style: the result does
   not depend on solve order, and the solves run in parallel,
   :mod:`~fiberplan.planners.mpc.executors`). Its separation from each neighbour ``j`` at horizon
   step ``k`` is linearised around its own previous plan ``qbar_i(k)`` and ``j``'s plan
   ``qhat_j(k)``:

   .. math:: g_{ij}(\\bar q_i(k), \\hat q_j(k)) + \\nabla_{q_i} g_{ij} \\cdot (q_i(k) - \\bar q_i(k)) \\ge m_{ij} - s_{ij}

   with asymmetric margins and slack weights from priorities (the higher-priority side of a
   pair gets the small margin and the cheap slack: the other side yields).
3. Safety layer: the configuration every positioner will actually reach is checked with
   exact capsule distances, together with a bound on the clearance between the two samples;
   positioners of unsafe pairs are stopped (the lower-priority one first) until every pair is
   safe. Holding still is always safe, so this terminates.
4. Deadlocks: a positioner not at its target whose time-to-go has not decreased for
   ``deadlock_window_steps`` is deadlocked. If it and a neighbour in conflict are ordered by
   their targets (one's path crosses the other's target or position), the one that must wait
   goes to a waiting configuration until the other has arrived (:mod:`~fiberplan.planners.mpc.deadlock`).
   Otherwise it is given top priority (its neighbours fold out of its way); if it stays stuck
   for two more windows it retreats: folds, turns alpha to its target, and unfolds with top
   priority.
5. The run ends when all are at their targets, when nothing can progress any more
   (``stop_after_stalled_windows``), or at the time limit.

Before the first step (on by default), every positioner gets a start delay
such that the delayed straight moves keep their margins pairwise where a delay can; a
positioner no delay fits may take an L-shaped move instead, followed as a route through its
corner, or else a timed path found by a search over its joint grid x time, followed as a route
whose waypoints it leaves no earlier than scheduled; one no timed path fits may go first, a
neighbour being placed again after it (:mod:`~fiberplan.planners.mpc.schedule`). Each
positioner holds until its start.
"""

from __future__ import annotations

import dataclasses
import math
import time
from functools import partial
from typing import Any

import numpy as np

from fiberplan.kinematics import fiber_positions, straight_path
from fiberplan.outcomes import outcome_labels
from fiberplan.planners import ProgressCallback
from fiberplan.planners.coordination.settings import REVERSED_LEGS
from fiberplan.planners.motors import govern, governs, hold_for_ramps
from fiberplan.planners.mpc.conflicts import build_qp_batch, select_conflicts
from fiberplan.planners.mpc.deadlock import Deadlocks, Level
from fiberplan.planners.mpc.executors import make_executor
from fiberplan.planners.mpc.kernels import straight_reference
from fiberplan.planners.mpc.priority import outranks
from fiberplan.planners.mpc.qp import USABLE, OsqpOptions, QpLayout, QpWeights, reference_keeps_constraints
from fiberplan.planners.mpc.routes import RouteBook, route_path
from fiberplan.planners.mpc.schedule import StartSchedule, start_schedule
from fiberplan.planners.mpc.settings import MpcSettings
from fiberplan.planners.mpc.stats import RunStats
from fiberplan.planners.safety import SafetyLayer, motion_bound, point_extents
from fiberplan.scenario import Scenario
from fiberplan.settings import check_step_budget
from fiberplan.trajectory import PlanResult, Trajectory

WORKSPACES_KEPT_UP_TO = 4000
"""Runs of up to this many positioners keep every QP workspace for the whole run (every
benchmark set but the scaling one: their trajectories are those of before). A larger run starts
a positioner's workspace afresh after :data:`FRESH_AFTER_STEPS` idle steps and frees the idle
ones (:mod:`.executors`): 50,000 DESI positioners create ~19,000 workspaces of ~50 kB each."""

FRESH_AFTER_STEPS = 5

def plan_mpc(scenario: Scenario, settings: MpcSettings, progress: ProgressCallback | None = None) -> PlanResult:
    """Plan with decentralised MPC; see the module docstring and ``formulations/mpc.md``."""
    inst = scenario.instrument
    n = scenario.n_positioners
    h, H = settings.dt_s, settings.horizon_steps
    step_rad = inst.speeds_rad_s * h
    goal_final = scenario.target.copy()
    pairs = scenario.pairs
    degree = np.bincount(pairs.ravel(), minlength=n) if len(pairs) else np.zeros(n, dtype=np.int64)
    n_slots = int(max(1, min(degree.max(initial=0), settings.max_neighbour_constraints)))
    step_mm = float(motion_bound(point_extents(inst), step_rad))
    weights = QpWeights(
        tracking=settings.weight_tracking, terminal=settings.weight_terminal, input=settings.weight_input,
        input_change=settings.weight_input_change, slack_quadratic=settings.slack_weight_quadratic,
    )
    layout = QpLayout(H, n_slots, weights, settings.max_input_change)
    options = OsqpOptions(eps_abs=settings.osqp_eps, eps_rel=settings.osqp_eps, max_iter=settings.osqp_max_iter)
    safety = SafetyLayer(scenario, settings.safety_margin_mm)
    # A pair whose targets are closer than the margins could never both arrive: its QP
    # margins are capped at half its clearance at the targets.
    margin_cap = safety.half_target_clearance

    move = np.max(np.abs(goal_final - scenario.start) / inst.speeds_rad_s, axis=1)
    bound_s = float(move[scenario.has_target].max()) if np.any(scenario.has_target) else 0.0
    limit_s = settings.max_duration_factor * bound_s + settings.max_duration_extra_s if settings.time_limit_s is None else settings.time_limit_s
    max_steps = int(np.ceil(limit_s / h))
    check_step_budget("mpc", max_steps, h, limit_s)

    schedule_t0 = time.perf_counter()
    if progress is not None and settings.start_schedule:
        progress(0.0, "start schedule")
    schedule = start_schedule(scenario, step_rad, settings.margin_mm, settings.schedule_delay_steps, settings.schedule_slack,
                              l_paths=settings.schedule_l_paths, space_time=settings.schedule_space_time,
                              cell_steps=settings.schedule_cell_steps, repair=settings.schedule_repair,
                              pair_paths=settings.schedule_pairs) if settings.start_schedule else None
    schedule_wall_s = time.perf_counter() - schedule_t0
    start_step = schedule.delay_steps if schedule is not None else np.zeros(n, dtype=np.int64)

    q = scenario.start.copy()
    goal = goal_prev = goal_final.copy()
    c_now = safety.clearance(q, pairs)
    # Every decision on c_now compares it with a threshold below this (the conflict range and the
    # look-ahead of select_conflicts, the safety layer's floor plus a step of both, the deadlock
    # rules' conflict radius): above it, c_now may hold a lower bound (SafetyLayer.refresh).
    exact_below = max(settings.conflict_radius_mm + 2 * H * step_mm, float(safety.pair_floor.max(initial=0.0)) + 2 * step_mm) + 1e-6
    plan = straight_path(q, np.where((start_step > 0)[:, None], q, goal), step_rad, H)  # published plans (what neighbours see)
    own_plan = plan.copy()  # linearisation points of each positioner's own QP
    v_prev = np.zeros((n, 2))
    history = [q.copy()]
    stats = RunStats()
    routes = RouteBook()
    deadlocks = Deadlocks(scenario, settings, move, step_rad, routes)
    if schedule is not None:
        _follow_schedule(schedule, routes, q, goal_final, start_step, plan, own_plan, step_rad)
        if settings.route_progress:
            deadlocks.best_ttg[list(routes)] = np.inf  # measured along their routes

    govern_motors = settings.motor_limits and governs(inst.motors)
    reversed_leg = scenario.kind in REVERSED_LEGS  # a leg planned backwards: the motor rules read backwards
    step = 0
    stopped_stalled = False
    fresh_after = FRESH_AFTER_STEPS if n > WORKSPACES_KEPT_UP_TO else None
    executor = make_executor(settings.executor, layout, options, settings.qp_solver, settings.workers, fresh_after)
    try:
        for step in range(max_steps):
            at_goal = _both_joints(q == goal_final)
            if np.all(at_goal):
                break
            if deadlocks.nothing_can_progress(step, at_goal):
                stopped_stalled = True
                break
            # Holding: unstarted (waiting for its scheduled start), or at a waypoint of a timed
            # route until its next departure.
            unstarted = step < start_step
            holding = unstarted.copy()
            routes.holding(step, q, step_rad, holding)
            ttg = deadlocks.track(step, q, at_goal, holding)

            # --- conflicts (from the configuration and the published plans), deadlocks, priorities.
            sel = select_conflicts(scenario, settings, c_now, q, plan, goal_prev, step_mm)
            stalled, new_dead = deadlocks.detect(step, q, ttg, at_goal, holding)
            deadlocks.resolve(step, q, ttg, at_goal, stalled, new_dead, c_now)
            rank, boosted = deadlocks.priorities(ttg)
            fold = deadlocks.yielders(step, pairs[sel], rank, boosted)
            goal = goal_prev = deadlocks.goals(step, q, at_goal, holding, fold)

            # --- the reference (time-optimal toward the goal, or along the route), then the QPs.
            ref = np.empty((n, H, 2))
            straight_reference(q, goal, step_rad, ref)  # straight_path(q, goal, step_rad, H), compiled
            routes.reference(ref, q, unstarted, step_rad, step)
            q_next, new_plan = _solve_qps(scenario, settings, layout, executor, stats, sel, margin_cap, q, own_plan, plan, ref, v_prev,
                                          rank, deadlocks.wait_first, boosted, step_rad, step)
            # Snap onto the goal when within a small fraction of a step of it.
            near = _both_joints(np.abs(goal - q_next) <= 0.05 * step_rad) & _both_joints(np.abs(goal - q) <= step_rad)
            q_next[near] = goal[near]
            q_next[scenario.locked] = q[scenario.locked]  # locked positioners never move
            # A non-finite step (none is known to arise: every QP solution is checked) holds.
            bad_step = ~np.isfinite(q_next).all(axis=1)
            if bad_step.any():
                q_next[bad_step] = q[bad_step]
                stats.non_finite_steps += int(bad_step.sum())
            # --- the motors' limits (stop before reversing, speed change, minimum speed), except for
            # positioners stalled or climbing the deadlock ladder (completion first: their fine
            # moves are left to the discretiser); then the safety layer: exact distances of what
            # will actually be executed.
            if govern_motors:
                proposed = q_next
                recent = _recent_speeds(history, h, inst.motors.ramp_time_s)
                q_next = govern(q, q_next, v_prev * inst.speeds_rad_s, goal, h, inst.motors, inst.speeds_rad_s, inst.limits_rad,
                                reverse=reversed_leg, recent=recent)
                free = stalled | (deadlocks.level != Level.NORMAL)
                # The exempt keep the ramps (rule 4) alone: a reversal of a fast joint waits a ramp at rest.
                q_next[free] = hold_for_ramps(q[free], proposed[free], h, inst.speeds_rad_s,
                                              None if recent is None else (recent[0][free], recent[1][free]))
                governed = np.any(q_next != proposed, axis=1)
            q_next, held, iters = safety.apply(q, q_next, c_now, partial(outranks, rank=rank, defer_to=deadlocks.wait_first))
            stats.safety_holds += int(held.sum())
            deadlocks.held(step, held)
            stats.safety_iterations_max = max(stats.safety_iterations_max, iters)

            # --- publish plans for the next round (shifted by one step).
            tail = new_plan[:, -1] + np.clip(goal - new_plan[:, -1], -step_rad, step_rad)
            shifted = np.concatenate([new_plan[:, 1:], tail[:, None]], axis=1)
            # A stopped positioner publishes its intention one step late, but linearises its
            # own next QP around where it actually is (holding).
            # A positioner the governor slowed or stopped does the same.
            late = held | governed if govern_motors else held
            plan = np.where(late[:, None, None], new_plan, shifted)
            own_plan = np.where(late[:, None, None], q_next[:, None, :], shifted)
            v_prev = (q_next - q) / step_rad
            safety.refresh(c_now, q, q_next, exact_below)  # exact where a decision below reads them
            q = q_next
            history.append(q.copy())
            if progress is not None and step % 20 == 0:
                progress(min(1.0, step / max_steps), "control loop")
    finally:
        executor.close()
    if progress is not None:
        progress(1.0)
    return _result(scenario, settings, np.stack(history), stats, deadlocks, schedule, schedule_wall_s, start_step, n_slots,
                   stopped_stalled, step)


def _both_joints(rows: np.ndarray) -> np.ndarray:
    """``np.all(rows, axis=1)`` of an ``(N, 2)`` boolean array, without numpy's slow reduction over two columns."""
    return rows[:, 0] & rows[:, 1]


def _recent_speeds(history: list[np.ndarray], h: float, ramp_s: float | None) -> tuple[np.ndarray, np.ndarray] | None:
    """Each joint's fastest forward and backward speeds (rad/s, ``(N, 2)`` each, >= 0) over the
    executed steps that end within the last ramp time (the governor's ramp rule); ``None``
    without a ramp."""
    if ramp_s is None:
        return None
    k = max(1, math.ceil(ramp_s / h - 1e-9))
    recent = np.diff(np.stack(history[-k - 1:]), axis=0) / h if len(history) > 1 else np.zeros((1, *history[-1].shape))
    return np.maximum(recent, 0.0).max(axis=0), np.maximum(-recent, 0.0).max(axis=0)


def _solve_qps(
    scenario: Scenario, settings: MpcSettings, layout: QpLayout, executor: Any, stats: RunStats, sel: np.ndarray, margin_cap: np.ndarray,
    q: np.ndarray, own_plan: np.ndarray, plan: np.ndarray, ref: np.ndarray, v_prev: np.ndarray, rank: np.ndarray,
    wait_first: np.ndarray, boosted: np.ndarray, step_rad: np.ndarray, step: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The next configuration and the new plans: the reference for positioners in no conflict,
    the first step of its QP's plan for each one in conflict (a failed solve holds)."""
    lim = scenario.instrument.limits_rad
    q_next = ref[:, 0].copy()
    new_plan = ref.copy()
    n_qp = 0
    if len(sel):
        batch = build_qp_batch(scenario, settings, layout, scenario.pairs[sel], margin_cap[sel], q, own_plan, plan, ref, v_prev, rank,
                               wait_first, boosted, step_rad, lim)
        if settings.qp_screen_mm is not None:
            keeps = reference_keeps_constraints(layout, batch.z_ref, batch.z_lo, batch.z_hi, batch.v_prev, batch.coef, batch.rhs,
                                                batch.active, settings.qp_screen_mm)
            stats.qp_screened += int(keeps.sum())
            batch = batch.take(np.flatnonzero(~keeps))
        result = executor.solve(batch, step)
        idx = batch.index
        n_qp = len(idx)
        stats.record_qps(result)
        ok = np.isin(result.status, USABLE)
        qplan = np.clip(q[idx, None, :] + result.z * step_rad, lim[:, 0], lim[:, 1])
        # Executed first step: within the speed bound and the hard stops.
        first = np.clip(q[idx] + np.clip(qplan[:, 0] - q[idx], -step_rad, step_rad), lim[:, 0], lim[:, 1])
        # Failed solves brake: the positioner holds and publishes a hold plan.
        q_next[idx] = np.where(ok[:, None], first, q[idx])
        new_plan[idx] = np.where(ok[:, None, None], qplan, q[idx, None, :])
    stats.qp_per_step.append(n_qp)
    return q_next, new_plan


def _follow_schedule(
    schedule: StartSchedule, routes: RouteBook, q: np.ndarray, goal_final: np.ndarray, start_step: np.ndarray, plan: np.ndarray,
    own_plan: np.ndarray, step_rad: np.ndarray,
) -> None:
    """Routes of the scheduled L-shaped moves (through their corner) and timed paths (leaving
    each waypoint no earlier than scheduled); those that start at once publish them."""
    H = plan.shape[1]
    for who in np.flatnonzero(~np.isnan(schedule.corner[:, 0])).tolist():
        routes.follow(who, np.array([schedule.corner[who], goal_final[who]]))
        if start_step[who] == 0:
            plan[who] = own_plan[who] = route_path(q[who], routes[who].waypoints, 0, step_rad, H)
    for who, (waypoints, depart) in schedule.timed.items():
        routes.follow(who, waypoints, depart)
        if start_step[who] == 0:
            plan[who] = own_plan[who] = route_path(q[who], waypoints, 0, step_rad, H, depart, 0)


def _result(
    scenario: Scenario, settings: MpcSettings, joints: np.ndarray, stats: RunStats, deadlocks: Deadlocks,
    schedule: StartSchedule | None, schedule_wall_s: float, start_step: np.ndarray, n_slots: int, stopped_stalled: bool, step: int,
) -> PlanResult:
    """The plan result: outcomes in the shared vocabulary, statistics, warnings."""
    inst = scenario.instrument
    n = scenario.n_positioners
    times = np.arange(len(joints)) * settings.dt_s
    final_xy = fiber_positions(inst, scenario.base_xy, scenario.orient, joints[-1])
    at_target = np.linalg.norm(final_xy - scenario.target_xy, axis=1) <= inst.tolerance_mm
    reached = at_target & scenario.has_target
    displaced_mm = np.linalg.norm(final_xy - fiber_positions(inst, scenario.base_xy, scenario.orient, scenario.start), axis=1)
    outcome = outcome_labels(scenario, joints[-1], deadlocks.stuck(step))
    n_steps = len(joints) - 1
    out = stats.qp_dict(n, n_steps)
    out |= deadlocks.stats(reached, scenario.has_target)
    out |= {
        "n_slots": n_slots,
        "stopped_stalled": stopped_stalled,
        "schedule_delayed": int(np.count_nonzero(start_step)),
        "schedule_unplaced": len(schedule.unplaced) if schedule is not None else 0,
        "schedule_l_paths": int(np.count_nonzero(~np.isnan(schedule.corner[:, 0]))) if schedule is not None else 0,
        "schedule_timed": len(schedule.timed) if schedule is not None else 0,
        "schedule_swaps": schedule.swaps if schedule is not None else 0,
        "schedule_wall_s": schedule_wall_s,
        "held_displaced_mm_max": float(displaced_mm[~scenario.has_target].max(initial=0.0)),
    }
    warnings = []
    short = int(np.sum(scenario.has_target & ~reached))
    if short:
        why = "nothing could progress any more" if stopped_stalled else "the time limit was reached"
        warnings.append(f"mpc: {short} of {int(scenario.has_target.sum())} positioners did not reach their targets; "
                        f"the run stopped at t = {times[-1]:.2f} s because {why}")
    warnings += stats.warnings()
    return PlanResult(
        scenario=scenario,
        trajectory=Trajectory(times, joints),
        outcome=outcome,
        planner="mpc",
        settings=dataclasses.asdict(settings),
        stats=out,
        warnings=tuple(warnings),
    )


__all__ = ["Level", "MpcSettings", "plan_mpc"]
