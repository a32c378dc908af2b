"""The verified central optimum: the reference the decentralised planners are measured against.

The ``central`` planner never checks itself (data flows one way: planner, then verifier);
this study-level function runs the independent verifier on its candidates, best first.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from typing import Any

from fiberplan.planners import ProgressCallback, make_settings, plan
from fiberplan.planners.central import CentralSettings, solve_central
from fiberplan.planners.central.solve import hold_result, result_of, solution_stats
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult
from fiberplan.verify import verify


def central_reference(
    scenario: Scenario,
    settings: CentralSettings | Mapping[str, Any] | None = None,
    *,
    warm_results: Sequence[PlanResult] = (),
    progress: ProgressCallback | None = None,
) -> PlanResult:
    """The verified central optimum: candidates are checked by :func:`fiberplan.verify.verify`, best first.

    The first converged candidate the independent verifier accepts is returned with
    ``stats["verified"] = True``. If none passes, every positioner holds still, is marked
    ``failed`` and ``stats["verified"]`` is False: a central solution with a collision or a
    limit violation is never reported as optimal. ``plan_wall_s`` covers the solves and
    the verification (not the runs of ``warm_results``).

    Raises:
        PlannerError: bad settings (see :func:`solve_central`).
    """
    chosen_settings: CentralSettings = settings if isinstance(settings, CentralSettings) else make_settings("central", scenario, settings)
    settings = chosen_settings
    given = {r.planner for r in warm_results}
    missing = [plan(scenario, name) for name in settings.warm_planners if name not in given]
    t0 = time.perf_counter()
    solution, problem = solve_central(scenario, settings, warm_results=[*warm_results, *missing], progress=progress)
    if problem.lower_bound_s <= 0:
        result = hold_result(scenario, settings, solution_stats(solution, None, True))
        return dataclasses.replace(result, plan_wall_s=time.perf_counter() - t0)
    rejected: list[dict[str, Any]] = []
    for cand in solution.candidates:
        if not cand.converged:
            continue
        result = result_of(problem, cand, {})
        report = verify(scenario, result.trajectory)
        if report.ok:
            stats = solution_stats(solution, cand, True) | {"rejected": rejected, "min_clearance_mm": report.min_clearance_mm}
            return dataclasses.replace(result, stats=stats, plan_wall_s=time.perf_counter() - t0)
        rejected.append({"source": cand.source, "collisions": report.n_collisions, "limit_violations": len(report.limit_violations)})
    stats = solution_stats(solution, None, False) | {"rejected": rejected}
    return dataclasses.replace(hold_result(scenario, settings, stats), plan_wall_s=time.perf_counter() - t0)
