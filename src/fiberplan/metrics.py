"""Metrics with one definition everywhere (``DESIGN.md``, Metrics).

- reached: final fiber within the instrument's tolerance of the target;
  success rate = reached / positioners with a target.
- makespan: time at which the last *reached* positioner reaches its target and stays
  (positioners that never reach it are counted by the success rate, not here).
- lower bound: max over positioners of the unobstructed straight joint move at full speed,
  :math:`\\max_i \\max_k |\\Delta q_{ik}| / \\omega_k`; no planner can beat it.
- path length: length of each fiber's path in the focal plane (mm).
- energy: :math:`\\sum_i \\int \\|\\dot q_i\\|^2 dt` (rad^2/s), exact for piecewise-linear motion.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fiberplan.kinematics import fiber_positions, move_times
from fiberplan.outcomes import count, explain
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult, RunFile, Trajectory
from fiberplan.verify import VerificationReport


def reached_mask(scenario: Scenario, trajectory: Trajectory) -> np.ndarray:
    """Which positioners end within tolerance of their target (False for those without)."""
    final = fiber_positions(scenario.instrument, scenario.base_xy, scenario.orient, trajectory.joints[-1])
    error = np.linalg.norm(final - scenario.target_xy, axis=-1)
    return (error <= scenario.instrument.tolerance_mm) & scenario.has_target


def arrival_times(scenario: Scenario, trajectory: Trajectory) -> np.ndarray:
    """Time each positioner enters its tolerance disc for good (NaN if it never stays).

    From the sample after which a positioner holds its last configuration exactly, its fiber is
    where it ends; so a positioner inside its disc at the end is looked at backwards from there
    until a sample outside (usually the one just before): a large field's fiber positions are
    never computed, or held, at every sample."""
    joints = trajectory.joints
    n_t, n = joints.shape[0], joints.shape[1]
    inst, target_xy = scenario.instrument, scenario.target_xy

    def outside(k: int | np.ndarray, rows: np.ndarray) -> np.ndarray:
        fibers = fiber_positions(inst, scenario.base_xy[rows], scenario.orient[rows], joints[k, rows])
        return ~(np.linalg.norm(fibers - target_xy[rows], axis=-1) <= inst.tolerance_mm)  # NaN: outside

    # hold[i]: the first sample from which positioner i keeps its last configuration (NaN at the
    # end: never, but such a positioner ends outside).
    held = np.arange(n)  # those holding their last configuration from sample k on
    hold = np.full(n, n_t - 1)
    for k in range(n_t - 2, -1, -1):
        held = held[np.all(joints[k, held] == joints[-1, held], axis=-1)]
        if not len(held):
            break
        hold[held] = k
    last_out = np.full(n, -1)  # last sample outside the disc; arrival is the sample after it
    ends_out = outside(n_t - 1, np.arange(n))
    last_out[ends_out] = n_t - 1
    rows = np.flatnonzero(~ends_out & (hold > 0))
    k = hold[rows] - 1
    while len(rows):  # back from where each settled, until outside
        out = outside(k, rows)
        last_out[rows[out]] = k[out]
        keep = ~out & (k > 0)
        rows, k = rows[keep], k[keep] - 1
    times = np.append(trajectory.times, np.nan)
    return np.where(scenario.has_target, times[last_out + 1], np.nan)


def lower_bound_s(scenario: Scenario) -> float:
    """Physical lower bound on the makespan (s)."""
    times = move_times(scenario.instrument, scenario.start, scenario.target)
    return float(times[scenario.has_target].max()) if np.any(scenario.has_target) else 0.0


def path_lengths_mm(scenario: Scenario, trajectory: Trajectory) -> np.ndarray:
    """Fiber path length of each positioner (mm), along the sampled polyline."""
    fibers = fiber_positions(scenario.instrument, scenario.base_xy, scenario.orient, trajectory.joints)
    return np.linalg.norm(np.diff(fibers, axis=0), axis=-1).sum(axis=0)


def energy(trajectory: Trajectory) -> float:
    """Integral of squared joint velocity summed over positioners and joints (rad^2/s)."""
    if len(trajectory.times) < 2:
        return 0.0
    dt = np.diff(trajectory.times)
    velocity = np.diff(trajectory.joints, axis=0) / dt[:, None, None]
    return float(np.sum(velocity**2 * dt[:, None, None]))


def summarize(result: PlanResult | RunFile, report: VerificationReport | None = None) -> dict[str, Any]:
    """One JSON-ready summary of a planned (and optionally verified) run.

    ``held`` counts the positioners without a target (they should end where they started),
    so that a target lost to a typo shows.
    """
    with np.errstate(invalid="ignore", over="ignore"):  # a file's non-finite samples give NaN metrics
        return _summarize(result, report)


def _summarize(result: PlanResult | RunFile, report: VerificationReport | None) -> dict[str, Any]:
    scenario, trajectory = result.scenario, result.trajectory
    reached = reached_mask(scenario, trajectory)
    n_targets = int(scenario.has_target.sum())
    arrivals = arrival_times(scenario, trajectory)
    arrived = arrivals[reached]
    makespan = float(np.nanmax(arrived)) if len(arrived) else float("nan")
    bound = lower_bound_s(scenario)
    paths = path_lengths_mm(scenario, trajectory)
    counts = count(np.asarray(result.outcome))
    # Held / displaced from the trajectory itself: no target, and ending within tolerance of the start or not.
    start_xy = fiber_positions(scenario.instrument, scenario.base_xy, scenario.orient, scenario.start)
    final_xy = fiber_positions(scenario.instrument, scenario.base_xy, scenario.orient, trajectory.joints[-1])
    moved = ~(np.linalg.norm(final_xy - start_xy, axis=-1) <= scenario.instrument.tolerance_mm)
    infeasible = np.isin(np.arange(scenario.n_positioners), list(scenario.infeasible))
    summary: dict[str, Any] = {
        "planner": result.planner,
        "instrument": scenario.instrument.name,
        "scenario_kind": scenario.kind,
        "n_positioners": scenario.n_positioners,
        "seed": scenario.seed,
        "reached": int(reached.sum()),
        "targets": n_targets,
        "held": int(np.sum(~scenario.has_target & ~scenario.locked & ~infeasible & ~moved)),
        "success_rate": float(reached.sum() / n_targets) if n_targets else 1.0,
        "deadlocked": counts["deadlocked"],
        "unfinished": counts["unfinished"],
        "failed": counts["failed"],
        "displaced": int(np.sum(~scenario.has_target & ~scenario.locked & ~infeasible & moved)),
        "infeasible": int(infeasible.sum()),
        "locked": int(scenario.locked.sum()),
        "makespan_s": makespan,
        "lower_bound_s": bound,
        "makespan_over_bound": makespan / bound if bound > 0 else float("nan"),
        "duration_s": trajectory.duration_s,
        "plan_wall_s": float(result.plan_wall_s),
        "path_length_mm_mean": float(paths[scenario.has_target].mean()) if n_targets else 0.0,
        "path_length_mm_total": float(paths.sum()),
        "energy_rad2_s": energy(trajectory),
    }
    stats, settings = result.stats or {}, result.settings or {}
    if "structure" in stats and "chosen" in stats:  # planned through the coordination layer: the route it took
        summary["route"] = stats["chosen"]
    elif settings.get("route") == "direct":  # the planner alone, as asked
        summary["route"] = "direct"
    summary["not_reached"] = explain(scenario, trajectory.joints[-1], np.asarray(result.outcome)) if np.isfinite(
        trajectory.joints[-1]).all() else {}
    if report is not None:
        summary.update(
            {
                "collisions": report.n_collisions,
                "limit_violations": len(report.limit_violations),
                "motor_violations": len(report.motor_violations) if report.motors_checked else None,
                "verified_ok": report.ok,
                "min_clearance_mm": report.min_clearance_mm,
            }
        )
    return summary
