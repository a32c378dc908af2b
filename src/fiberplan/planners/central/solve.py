"""Warm starts, the solve from every one, and the plan result of the ``central`` planner."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.kinematics import move_times
from fiberplan.outcomes import outcome_labels
from fiberplan.planners import ProgressCallback
from fiberplan.planners.central.nlp import Candidate, CentralSolution, _make_problem, _Problem, _solve_candidate
from fiberplan.planners.central.settings import _SEQUENTIAL, _STRAIGHT, CentralSettings
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult, Trajectory


# ---------------------------------------------------------------------------- warm starts
def _straight_guess(problem: _Problem, stretch: float) -> tuple[np.ndarray, float]:
    sc = problem.scenario
    s = np.linspace(0.0, 1.0, problem.steps + 1)[:, None, None]
    q = sc.start[None] + s * (sc.target - sc.start)[None]
    return q, max(stretch, 1.0) if problem.tau_fixed is None else problem.tau_fixed


def _sequential_guess(problem: _Problem) -> tuple[np.ndarray, float]:
    """One positioner after another (longest move first), each at full speed, on ``T + 1`` knots.

    Another homotopy than :func:`_straight_guess`: where two straight moves cross, the one
    that moves first passes before the other leaves. Its duration (the sum of the move
    times) is capped at ``max_makespan_factor`` lower bounds, the knots then moving too fast
    for IPOPT to repair.
    """
    sc = problem.scenario
    times = move_times(sc.instrument, sc.start, sc.target)
    order = np.argsort(-times, kind="stable")
    begin = np.zeros(len(times))
    begin[order] = np.concatenate([[0.0], np.cumsum(times[order])[:-1]])
    total = float(times.sum())
    t = np.linspace(0.0, total, problem.steps + 1)[:, None]
    frac = np.clip((t - begin[None]) / np.where(times > 0, times, 1.0)[None], 0.0, 1.0)
    q = sc.start[None] + frac[..., None] * (sc.target - sc.start)[None]
    if problem.tau_fixed is not None:
        return q, problem.tau_fixed
    return q, min(total / problem.lower_bound_s, problem.settings.max_makespan_factor)


def _trajectory_guess(problem: _Problem, result: PlanResult) -> tuple[np.ndarray, float]:
    """Resample another planner's trajectory to ``T + 1`` knots ending at the target."""
    from fiberplan.metrics import arrival_times

    sc = problem.scenario
    traj = result.trajectory
    arrivals = arrival_times(sc, traj)
    t_end = float(np.nanmax(arrivals)) if np.all(np.isfinite(arrivals[sc.has_target])) and np.any(sc.has_target) else traj.duration_s
    t_end = max(t_end, problem.lower_bound_s, 1e-9)
    T = problem.steps
    q = np.stack([traj.at(t) for t in np.linspace(0.0, t_end, T + 1)])
    q[0] = sc.start
    q[-1] = sc.target
    if problem.tau_fixed is not None:
        return q, problem.tau_fixed
    lb = problem.lower_bound_s
    needed = float((np.abs(np.diff(q, axis=0)) / sc.instrument.speeds_rad_s).max()) * T / lb
    return q, max(t_end / lb, needed)


def hold_result(scenario: Scenario, settings: CentralSettings, stats: dict[str, Any]) -> PlanResult:
    """Every positioner holds still: safe, and ``failed`` where a target was not reached.

    The result says why in its warnings (the command line prints them).
    """
    at_target = np.all(np.abs(scenario.target - scenario.start) < 1e-12, axis=1)
    joints = np.stack([scenario.start, scenario.start])
    warnings: tuple[str, ...] = ()
    if not at_target.all():
        tried = ", ".join(f"{c['source']}: {c['status']}" for c in stats.get("candidates", [])) or "no warm start"
        rejected = stats.get("rejected") or []
        why = (f"no converged candidate passed the verifier ({len(rejected)} rejected)" if rejected
               else f"IPOPT converged from no warm start ({tried})")
        warnings = (f"central: gave up: {why}; every positioner holds still and {int((~at_target).sum())} are marked failed",)
    return PlanResult(
        scenario=scenario,
        trajectory=Trajectory(np.array([0.0, settings.output_dt_s]), joints),
        outcome=outcome_labels(scenario, scenario.start, np.zeros(scenario.n_positioners, dtype=bool), failed=~at_target),
        planner="central",
        settings=_settings_dict(settings),
        stats=stats,
        warnings=warnings,
    )


def _settings_dict(settings: CentralSettings) -> dict[str, Any]:
    out = dataclasses.asdict(settings)
    out["warm_start"] = list(settings.warm_start)
    return out


def result_of(problem: _Problem, cand: Candidate, stats: dict[str, Any]) -> PlanResult:
    """Trajectory on the knots merged with the output grid; ``reached`` for a converged candidate."""
    sc, st = problem.scenario, problem.settings
    T = problem.steps
    tf = cand.makespan_s
    knots_t = np.linspace(0.0, tf, T + 1)
    grid = np.arange(0.0, tf, st.output_dt_s)
    close = np.min(np.abs(grid[:, None] - knots_t[None, :]), axis=1) < 1e-9 * max(tf, 1.0)
    times = np.union1d(knots_t, grid[~close])
    k = np.clip(np.searchsorted(knots_t, times, side="right") - 1, 0, T - 1)
    w = ((times - knots_t[k]) / (knots_t[k + 1] - knots_t[k]))[:, None, None]
    joints = (1 - w) * cand.joints[k] + w * cand.joints[k + 1]
    lim = sc.instrument.limits_rad
    joints = np.clip(joints, lim[:, 0], lim[:, 1])
    joints[0] = sc.start
    joints[-1] = sc.target
    outcome = outcome_labels(sc, joints[-1], np.zeros(sc.n_positioners, dtype=bool), failed=np.full(sc.n_positioners, not cand.converged))
    return PlanResult(
        scenario=sc,
        trajectory=Trajectory(times, joints),
        outcome=outcome,
        planner="central",
        settings=_settings_dict(st),
        stats=stats,
    )


def solve_central(
    scenario: Scenario,
    settings: CentralSettings,
    *,
    warm_results: Sequence[PlanResult] = (),
    progress: ProgressCallback | None = None,
) -> tuple[CentralSolution, _Problem]:
    """Solve from every warm start; candidates sorted best first (converged ones first).

    Args:
        scenario: the group to plan.
        settings: see :class:`CentralSettings`.
        warm_results: trajectories already planned for this scenario by other planners, used
            as warm starts (named by their planner); every planner ``settings.warm_start``
            names must be among them (:func:`fiberplan.planners.plan` plans them first).
        progress: optional callback receiving the fraction done.

    Raises:
        PlannerError: a warm-start planner's result is missing, or energy mode asks for a
            makespan below the lower bound.
    """
    problem = _make_problem(scenario, settings)
    solution = CentralSolution(candidates=[], lower_bound_s=problem.lower_bound_s)
    if problem.lower_bound_s <= 0:
        return solution, problem
    starts: list[tuple[str, np.ndarray, float]] = []
    given = {r.planner: r for r in warm_results}
    for name in settings.warm_start:
        if name == _STRAIGHT:
            starts.append((name, *_straight_guess(problem, settings.straight_stretch)))
            continue
        if name == _SEQUENTIAL:
            starts.append((name, *_sequential_guess(problem)))
            continue
        if name not in given:
            raise PlannerError(
                f"central: warm start {name!r} needs that planner's result for this scenario; pass it in warm_results "
                "(fiberplan.plan runs the warm-start planners first)"
            )
        solution.warm_start_s[name] = float(given[name].plan_wall_s)
    others = {name: result for name, result in given.items() if name != "central"}
    if settings.given_starts == "best" and len(others) > 1:
        from fiberplan.metrics import summarize

        # Every target reached first, then the earliest last arrival (the summary's makespan, as compare ranks).
        ranks = {name: summarize(result) for name, result in others.items()}
        best = min(others, key=lambda name: (ranks[name]["targets"] - ranks[name]["reached"], ranks[name]["makespan_s"]))
        others = {best: others[best]}
    for name, result in others.items():
        starts.append((name, *_trajectory_guess(problem, result)))
    for idx, (name, q0, tau0) in enumerate(starts):
        solution.candidates.append(_solve_candidate(problem, name, q0, tau0))
        if progress is not None:
            progress((idx + 1) / len(starts))
    solution.candidates.sort(key=lambda c: (not c.converged, c.objective))
    return solution, problem


def solution_stats(solution: CentralSolution, chosen: Candidate | None, verified: bool | None) -> dict[str, Any]:
    stats: dict[str, Any] = {
        "lower_bound_s": solution.lower_bound_s,
        "candidates": [c.summary() for c in solution.candidates],
        "warm_start_s": dict(solution.warm_start_s),
        "chosen": None if chosen is None else chosen.source,
        "verified": verified,
    }
    if chosen is not None:
        stats.update(
            {
                "status": chosen.status,
                "iterations": chosen.iterations,
                "solve_s": chosen.solve_s,
                "objective": chosen.objective,
                "makespan_s": chosen.makespan_s,
                "lines": chosen.lines,
            }
        )
    else:
        stats.update({"status": "no_converged_candidate" if solution.candidates else "nothing_to_move"})
    stats["solve_s_total"] = float(sum(c.solve_s for c in solution.candidates))
    # Set-up: building the NLPs and their start points, outside IPOPT (issue 25: <= 10 % of the solves).
    stats["build_s_total"] = float(sum(c.build_s for c in solution.candidates))
    stats["iterations_total"] = int(sum(c.iterations for c in solution.candidates))
    return stats


def plan_central(
    scenario: Scenario, settings: CentralSettings, progress: ProgressCallback | None = None, warm_results: Sequence[PlanResult] = (),
) -> PlanResult:
    """Plan a small group with one NLP; return the best converged candidate (not verified here).

    Every positioner is ``reached`` when IPOPT converged (the last knot is the target by
    construction); when no start converged, every positioner holds still and is ``failed``.
    Use :func:`fiberplan.studies.central_reference` for a verified result.
    """
    solution, problem = solve_central(scenario, settings, warm_results=warm_results, progress=progress)
    if problem.lower_bound_s <= 0:
        return hold_result(scenario, settings, solution_stats(solution, None, None))
    best = solution.candidates[0] if solution.candidates and solution.candidates[0].converged else None
    if best is None:
        return hold_result(scenario, settings, solution_stats(solution, None, None))
    return result_of(problem, best, solution_stats(solution, best, None))


__all__ = ["hold_result", "plan_central", "result_of", "solution_stats", "solve_central"]
