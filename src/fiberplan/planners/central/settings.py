"""Settings of the ``central`` planner."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from fiberplan._registry import planner_names
from fiberplan.errors import PlannerError, SettingsError
from fiberplan.instrument import Instrument
from fiberplan.planners import instrument_defaults
from fiberplan.settings import check_settings, setting

CentralMode = Literal["time", "energy"]

_IPOPT_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
_STRAIGHT = "straight"
"""Warm start name: every joint moves at constant speed from start to target (synchronised)."""
_SEQUENTIAL = "sequential"
"""Warm start name: positioners move straight at full speed one after another, longest first."""
_BUILTIN_STARTS = (_STRAIGHT, _SEQUENTIAL)


@dataclass(frozen=True)
class CentralSettings:
    """Settings of the ``central`` planner (defaults per instrument: :meth:`for_instrument`).

    Every field is declared with :func:`fiberplan.settings.setting` (doc, unit, valid range,
    group). ``warm_start`` names the starts to solve from: ``"straight"`` (constant-speed joint
    interpolation over ``straight_stretch`` lower bounds), ``"sequential"`` (one positioner
    after another, longest move first) or a registered planner (its trajectory, resampled);
    the best converged candidate is kept. In ``"time"`` mode the objective is ``t_f / t_LB +
    energy_weight E / E_ref``; in ``"energy"`` mode ``E / E_ref`` at a fixed makespan.
    """

    mode: CentralMode = setting("time", "minimise the makespan (time) or the energy at a fixed makespan", choices=("time", "energy"),
                                group="problem")
    steps: int = setting(40, "T, number of intervals of the discretised motion", low=2, high=2000, group="problem")
    energy_weight: float = setting(0.01, "w_E, weight of E / E_ref against t_f / t_LB in time mode", low=0.0, high=1e6, group="problem")
    makespan_s: float | None = setting(None, "energy mode: the fixed final time (null: makespan_factor lower bounds)", unit="s",
                                       low=0.0, high=1e5, low_open=True, optional=True, group="problem", kind="float")
    makespan_factor: float = setting(1.5, "energy mode default final time, in lower bounds", low=0.0, high=100.0, low_open=True,
                                     group="problem")
    warm_start: tuple[str, ...] = setting((_STRAIGHT, _SEQUENTIAL), "starts to solve from: straight, sequential or planner names",
                                          group="problem", kind="list")
    given_starts: str = setting("all", "other planners' trajectories at hand (compare passes its mpc and dnf results) to solve from: "
                                "all of them, or the best one (complete first, then the shortest)", choices=("all", "best"),
                                group="problem")
    straight_stretch: float = setting(1.2, "duration of the straight warm start, in lower bounds", low=0.0, high=100.0, low_open=True,
                                      group="problem")
    margin_mm: float = setting(0.02, "extra clearance m demanded by the collision constraints", unit="mm", low=0.0, high=10.0,
                               group="problem")
    activate_mm: float = setting(2.5, "a body pair (capsule or polygon zone) gets a line where its clearance along the guess is below this",
                                 unit="mm", low=0.0, high=1000.0, group="problem")
    activation_window: int = setting(2, "the initial activation also covers this many intervals around each close approach", low=0,
                                     high=1000, group="problem")
    lazy_rounds: int = setting(4, "re-solves allowed after adding the lines a solution made necessary", low=0, high=100, group="solver")
    warm_rounds: bool = setting(True, "a lazy round starts IPOPT from the last round's solution and multipliers (warm start)",
                                group="solver")
    max_iter: int = setting(1500, "IPOPT iteration limit per solve", low=2, high=1_000_000, group="solver")
    tol: float = setting(1e-7, "IPOPT convergence tolerance", low=0.0, high=1.0, low_open=True, group="solver")
    max_wall_s: float = setting(120.0, "IPOPT wall-time limit per solve", unit="s", low=0.0, high=1e6, low_open=True, group="solver")
    max_cpu_s: float | None = setting(None, "IPOPT CPU-time limit per solve (this process's CPU time: on a loaded machine the same "
                                      "iterations, where the wall-time limit gives fewer; null: none)", unit="s", low=0.0, high=1e6,
                                      low_open=True, optional=True, group="solver", kind="float")
    max_makespan_factor: float = setting(8.0, "upper bound of t_f in lower bounds", low=1.0, high=1000.0, group="problem")
    output_dt_s: float = setting(0.01, "the knots are merged with a uniform grid of this spacing in the output", unit="s", low=1e-4,
                                 high=10.0, group="output")

    @classmethod
    def for_instrument(cls, instrument: Instrument) -> CentralSettings:
        """Defaults scaled to an instrument: margins and activation distance from the pitch.

        ``margin_mm = 0.002 pitch`` (DESI 0.02 mm, MOONS 0.05 mm), ``activate_mm =
        0.25 pitch``, output grid at the instrument's control period.
        """
        defaults = cls(
            margin_mm=round(0.002 * instrument.pitch_mm, 4),
            activate_mm=round(0.25 * instrument.pitch_mm, 3),
            output_dt_s=instrument.control_dt_s,
        )
        return instrument_defaults(instrument, "central", defaults)

    def __post_init__(self) -> None:
        if isinstance(self.warm_start, str):
            object.__setattr__(self, "warm_start", tuple(s for s in self.warm_start.split(",") if s))
        else:
            object.__setattr__(self, "warm_start", tuple(self.warm_start))
        check_settings(self, "central")
        if not all(isinstance(w, str) for w in self.warm_start):
            raise SettingsError(f"central: warm_start must be a list of names, found {list(self.warm_start)!r}")
        if not self.warm_start:
            raise PlannerError("central: warm_start needs at least one start, e.g. ['straight'] or ['straight', 'dnf']")
        if "central" in self.warm_start:
            raise PlannerError("central: warm_start cannot name 'central' itself")
        unknown = [w for w in self.warm_start if w not in _BUILTIN_STARTS and w not in planner_names()]
        if unknown:
            raise SettingsError(
                f"central: warm_start {unknown[0]!r} is neither a built-in start ({', '.join(_BUILTIN_STARTS)}) nor a planner "
                f"({', '.join(p for p in planner_names() if p != 'central')})"
            )

    @property
    def warm_planners(self) -> tuple[str, ...]:
        """The planners whose trajectories this run starts from (the registry runs them first)."""
        return tuple(w for w in self.warm_start if w not in _BUILTIN_STARTS)
