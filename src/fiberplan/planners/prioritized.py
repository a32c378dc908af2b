"""The ``prioritized`` planner: reference 003's prioritized state-time planning, as a baseline.

Reference 003 (Sabater et al. 2018, Algorithm 1) plans the arms one after another in priority
order (the longest estimated travel first), each one's trajectory avoiding the space-time
regions of those planned before it; if an arm finds no trajectory, planning is restarted with
another priority scheme, a bounded number of times. fiberplan's single-arm planner is the
``mpc`` start scheduler (:class:`~fiberplan.planners.mpc.schedule.StartScheduler`): a start delay
of the straight move, an L-shaped move, or a timed path through the positioner's joint grid x
time, with the repair. Here it runs alone, without the MPC loop:

1. schedule every positioner (longest move first);
2. while some are unplaced and restarts remain: schedule again with the unplaced ones first
   (re-prioritisation on failure, reference 003 section 2.1), keep the schedule that places most;
3. execute it: each placed positioner follows its scheduled path at full speed (leaving each
   waypoint no earlier than scheduled), the unplaced hold at their starts; the shared safety
   layer (:mod:`fiberplan.planners.safety`) stops a mover whose step it cannot prove safe (the
   schedule checks its paths only at sampled instants), so the trajectory is collision-free.

Outcomes: ``reached``; ``deadlocked`` for the unplaced and for those the safety layer held
back until the time limit.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from functools import partial

import numpy as np

from fiberplan.geometry import default_safety_margin_mm, step_motion_mm
from fiberplan.instrument import Instrument
from fiberplan.kinematics import move_times
from fiberplan.outcomes import outcome_labels
from fiberplan.planners import ProgressCallback, instrument_defaults
from fiberplan.planners.mpc.priority import outranks
from fiberplan.planners.mpc.routes import route_path
from fiberplan.planners.mpc.schedule import StartSchedule, StartScheduler
from fiberplan.planners.safety import SafetyLayer
from fiberplan.scenario import Scenario
from fiberplan.settings import check_settings, check_step_budget, setting
from fiberplan.trajectory import PlanResult, Trajectory


@dataclass(frozen=True)
class PrioritizedSettings:
    """Settings of the ``prioritized`` planner (declared with :func:`fiberplan.settings.setting`)."""

    dt_s: float = setting(0.01, "control step and sample spacing (instrument default: its control period)", unit="s", low=1e-3,
                          high=1.0, group="run")
    restarts: int = setting(4, "re-schedules with the unplaced positioners first (reference 003's re-prioritisation)", low=0,
                            high=100, group="priorities")
    margin_mm: float = setting(0.3, "clearance the schedule keeps between positioners (instrument default: 1.2 step motions)",
                               unit="mm", low=0.0, high=10.0, group="schedule")
    delay_steps: int = setting(4, "granularity of the start delays", unit="steps", low=1, high=10000, group="schedule")
    slack: float = setting(1.2, "every scheduled move must end by this many times the longest move", low=1.0, high=100.0,
                           group="schedule")
    l_paths: bool = setting(True, "L-shaped moves for positioners no delay fits", group="schedule")
    space_time: bool = setting(True, "timed paths through the joint grid x time for those still unplaced", group="schedule")
    cell_steps: int = setting(16, "full-speed control steps per grid cell and time layer", unit="steps", low=1, high=1000,
                              group="schedule")
    repair: bool = setting(True, "an unplaced positioner goes first, a placed neighbour being placed again after it",
                           group="schedule")
    late_corners: bool = setting(False, "a positioner that needs a delay also tries its move with the faster joint starting late "
                                 "(the same duration, another sweep), keeping the one that ends first", group="schedule")
    late_longest: int = setting(0, "the move this far down the order of move times (1: the longest) starts with the faster joint "
                                "late; 0: none", low=0, high=1000, group="schedule")
    safety_margin_mm: float = setting(0.02, "smallest clearance the safety layer lets an executed step reach", unit="mm", low=0.0,
                                      high=10.0, group="safety")
    max_duration_factor: float = setting(3.0, "the execution stops after this many times the lower bound, plus one turn of the "
                                         "slower joint", low=0.0, high=100.0, low_open=True, group="run")
    time_limit_s: float | None = setting(None, "stop here at the latest (null: max_duration_factor)", unit="s", low=0.0, high=1e5,
                                         low_open=True, optional=True, group="run", kind="float")

    @classmethod
    def for_instrument(cls, instrument: Instrument) -> PrioritizedSettings:
        """Defaults scaled to the instrument as the ``mpc``'s: its control step, margins of its step motion."""
        dt = instrument.control_dt_s
        step_mm = step_motion_mm(instrument, dt)
        defaults = cls(dt_s=dt, margin_mm=round(1.2 * step_mm, 4), safety_margin_mm=default_safety_margin_mm(instrument))
        return instrument_defaults(instrument, "prioritized", defaults)

    def __post_init__(self) -> None:
        check_settings(self, "prioritized")


def _schedule(scenario: Scenario, settings: PrioritizedSettings, step_rad: np.ndarray, first: np.ndarray) -> StartSchedule:
    late = np.zeros(scenario.n_positioners, dtype=bool)
    if 0 < settings.late_longest <= scenario.n_positioners:
        move = move_times(scenario.instrument, scenario.start, scenario.target)
        late[np.lexsort((np.arange(len(move)), -move))[settings.late_longest - 1]] = True
    return StartScheduler(
        scenario, step_rad, settings.margin_mm, settings.delay_steps, settings.slack, l_paths=settings.l_paths,
        space_time=settings.space_time, cell_steps=settings.cell_steps, repair=settings.repair, first=first,
        late_corners=settings.late_corners, late=late,
    ).run()


def plan_prioritized(scenario: Scenario, settings: PrioritizedSettings, progress: ProgressCallback | None = None) -> PlanResult:
    """Prioritized planning with restarts (module docstring), executed under the safety layer."""
    inst = scenario.instrument
    n = scenario.n_positioners
    step_rad = inst.speeds_rad_s * settings.dt_s
    t0 = time.perf_counter()
    first = np.zeros(n, dtype=bool)
    best = _schedule(scenario, settings, step_rad, first)
    restarts = 0
    while len(best.unplaced) and restarts < settings.restarts:
        restarts += 1
        first[best.unplaced] = True
        trial = _schedule(scenario, settings, step_rad, first)
        if len(trial.unplaced) < len(best.unplaced):
            best = trial
        else:
            break
    schedule_wall_s = time.perf_counter() - t0
    joints, stopped = _execute(scenario, settings, best, step_rad, progress)
    placed = np.ones(n, dtype=bool)
    placed[best.unplaced] = False
    at = np.all(joints[-1] == scenario.target, axis=1)
    outcome = outcome_labels(scenario, joints[-1], ~at)
    stats = {
        "restarts": restarts, "schedule_unplaced": len(best.unplaced), "schedule_timed": len(best.timed),
        "schedule_l_paths": int(np.count_nonzero(~np.isnan(best.corner[:, 0]))), "schedule_delayed": int(np.count_nonzero(best.delay_steps)),
        "schedule_wall_s": schedule_wall_s, "safety_holds": stopped, "n_steps": len(joints) - 1,
    }
    short = int(np.sum(scenario.has_target & ~at))
    warnings = (f"prioritized: {short} of {int(scenario.has_target.sum())} positioners did not reach their targets "
                f"({len(best.unplaced)} unplaced after {restarts} restart(s))",) if short else ()
    return PlanResult(scenario=scenario, trajectory=Trajectory(np.arange(len(joints)) * settings.dt_s, joints), outcome=outcome,
                      planner="prioritized", settings=dataclasses.asdict(settings), stats=stats, warnings=warnings)


def _execute(
    scenario: Scenario, settings: PrioritizedSettings, schedule: StartSchedule, step_rad: np.ndarray, progress: ProgressCallback | None,
) -> tuple[np.ndarray, int]:
    """Follow the schedule at full speed under the safety layer; ``(joints, steps held)``."""
    n = scenario.n_positioners
    goal = scenario.target
    move = move_times(scenario.instrument, scenario.start, goal)
    bound = float(move[scenario.has_target].max()) if scenario.has_target.any() else 0.0
    limit_s = settings.time_limit_s or settings.max_duration_factor * bound + scenario.instrument.full_turn_s
    max_steps = int(np.ceil(limit_s / settings.dt_s))
    check_step_budget("prioritized", max_steps, settings.dt_s, limit_s)
    routes: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
    for i in np.flatnonzero(~np.isnan(schedule.corner[:, 0])).tolist():
        routes[i] = (np.array([schedule.corner[i], goal[i]]), None)
    for i, (waypoints, depart) in schedule.timed.items():
        routes[i] = (waypoints, depart)
    pos = dict.fromkeys(routes, 0)
    unplaced = np.zeros(n, dtype=bool)
    unplaced[schedule.unplaced] = True
    safety = SafetyLayer(scenario, settings.safety_margin_mm)
    # The schedule's priority: the scenario's priorities (none by default), then the longest move first.
    rank = np.lexsort((np.arange(n), -move, scenario.priority_rank))
    order = np.empty(n, dtype=np.int64)
    order[rank] = np.arange(n)
    first = partial(outranks, rank=order, defer_to=np.full(n, -1))
    q = scenario.start.copy()
    c_now = safety.clearance(q, scenario.pairs)
    history, held_total = [q.copy()], 0
    # From this step on no start delay or departure step lies ahead: a step is then a function of
    # the configuration and the route positions alone.
    timeless = max([int(schedule.delay_steps.max(initial=0))] + [int(np.max(d, initial=0)) for _, d in schedule.timed.values()])
    for step in range(max_steps):
        if np.all((q == goal).all(axis=1) | unplaced):
            break
        q_next = q + np.clip(goal - q, -step_rad, step_rad)
        passed = False
        for i, (waypoints, departs) in routes.items():
            path = route_path(q[i], waypoints, pos[i], step_rad, 1, departs, step)
            q_next[i] = path[0]
            while pos[i] < len(waypoints) - 1 and np.all(np.abs(q_next[i] - waypoints[pos[i]]) <= 0.5 * step_rad):
                pos[i] += 1
                passed = True
        waiting = step < schedule.delay_steps
        q_next[waiting | unplaced | scenario.locked] = q[waiting | unplaced | scenario.locked]
        q_next, held, _ = safety.apply(q, q_next, c_now, first)
        held_total += int(held.sum())
        if step >= timeless and not passed and np.array_equal(q_next, q):
            # Held where it stood, with nothing timed ahead: every later step is this one again
            # (the same configuration, route positions and clearances in, the same held out), so
            # the rest of the run is this configuration, held alike, without computing it.
            rest = max_steps - step - 1
            history.extend([q.copy()] * (rest + 1))
            held_total += rest * int(held.sum())
            break
        safety.refresh(c_now, q, q_next)
        q = q_next
        history.append(q.copy())
        if progress is not None and step % 50 == 0:
            progress(min(1.0, step / max_steps))
    return np.stack(history), held_total
