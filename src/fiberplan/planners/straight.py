"""The ``straight`` planner: every joint straight to its target at full speed, all at once.

It ignores collisions on purpose: it is the reference for the physical lower bound and
shows why planning is needed. Each joint ``k`` of positioner ``i`` moves at
``sign(delta) * omega_k`` until it arrives, then stops:

.. math:: q_{ik}(t) = q_{ik}(0) + \\operatorname{sign}(\\Delta_{ik}) \\min(\\omega_k t, |\\Delta_{ik}|)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from fiberplan.instrument import Instrument
from fiberplan.kinematics import move_times
from fiberplan.planners import ProgressCallback
from fiberplan.scenario import Scenario
from fiberplan.settings import check_settings, check_step_budget, setting
from fiberplan.trajectory import PlanResult, Trajectory


@dataclass(frozen=True)
class StraightSettings:
    """Settings of the ``straight`` planner (declared with :func:`fiberplan.settings.setting`)."""

    dt_s: float = setting(0.01, "sample spacing of the output trajectory (instrument default: its control period)", unit="s",
                          low=1e-4, high=10.0, group="run")

    @classmethod
    def for_instrument(cls, instrument: Instrument) -> StraightSettings:
        """Defaults for an instrument."""
        return cls(dt_s=instrument.control_dt_s)

    def __post_init__(self) -> None:
        check_settings(self, "straight")


def plan_straight(scenario: Scenario, settings: StraightSettings, progress: ProgressCallback | None = None) -> PlanResult:
    """Move every joint straight to its target at full speed (collisions ignored)."""
    inst = scenario.instrument
    delta = scenario.target - scenario.start
    duration = float(move_times(inst, scenario.start, scenario.target).max())
    n_steps = max(1, int(np.ceil(duration / settings.dt_s - 1e-9)))
    check_step_budget("straight", n_steps, settings.dt_s, duration)
    times = np.minimum(np.arange(n_steps + 1) * settings.dt_s, duration) if duration > 0 else np.array([0.0, settings.dt_s])
    if duration > 0:
        times[-1] = duration
    travel = np.minimum(times[:, None, None] * inst.speeds_rad_s, np.abs(delta)[None])
    joints = scenario.start[None] + np.sign(delta)[None] * travel
    joints[-1] = scenario.target
    if progress is not None:
        progress(1.0)
    return PlanResult(
        scenario=scenario,
        trajectory=Trajectory(times, joints),
        outcome=np.full(scenario.n_positioners, "reached"),
        planner="straight",
        settings=dataclasses.asdict(settings),
        stats={"n_samples": len(times)},
    )
