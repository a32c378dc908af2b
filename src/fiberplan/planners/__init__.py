"""Planner registry: every planner is ``plan_xxx(scenario, settings, progress) -> PlanResult``.

Planners are registered here by name and imported only when used (so that, for instance,
CasADi is loaded only by the ``central`` planner).
"""

from __future__ import annotations

import dataclasses
import importlib
import numbers
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.instrument import Instrument
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult

ProgressCallback = Callable[[float], None]
"""Called with the fraction of the work done, in [0, 1]."""

_PLANNERS: dict[str, tuple[str, str, str]] = {
    # name: (module, planning function, settings dataclass)
    "straight": ("fiberplan.planners.straight", "plan_straight", "StraightSettings"),
    "mpc": ("fiberplan.planners.mpc", "plan_mpc", "MpcSettings"),
    "dnf": ("fiberplan.planners.dnf", "plan_dnf", "DnfSettings"),
    "central": ("fiberplan.planners.central", "plan_central", "CentralSettings"),
}


class PlannerFunction(Protocol):
    """Signature every registered planner follows."""

    def __call__(self, scenario: Scenario, settings: Any, progress: ProgressCallback | None = None) -> PlanResult: ...


def instrument_defaults(instrument: Instrument, table: str, defaults: Any) -> Any:
    """``defaults`` (a settings dataclass) with the instrument file's ``[planner_defaults.<table>]`` applied.

    Raises:
        PlannerError: the table names a setting the dataclass does not have.
    """
    overrides = dict(instrument.planner_defaults.get(table, {}))
    known = {f.name for f in dataclasses.fields(defaults)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise PlannerError(
            f"instrument {instrument.name!r}: [planner_defaults.{table}] has no setting {unknown[0]!r}; "
            f"known settings are {', '.join(sorted(known))}"
        )
    return dataclasses.replace(defaults, **overrides)


def planner_names() -> list[str]:
    """Names of the registered planners."""
    return sorted(_PLANNERS)


def _lookup(name: str) -> tuple[PlannerFunction, type]:
    if name not in _PLANNERS:
        raise PlannerError(f"unknown planner {name!r}; choose one of {', '.join(planner_names())}")
    module_name, func_name, settings_name = _PLANNERS[name]
    module = importlib.import_module(module_name)
    return getattr(module, func_name), getattr(module, settings_name)


def settings_class(name: str) -> type:
    """The settings dataclass of planner ``name`` (its fields are the planner's settings).

    Raises:
        PlannerError: unknown planner.
    """
    return _lookup(name)[1]


def make_settings(name: str, scenario: Scenario, overrides: Mapping[str, Any] | None = None) -> Any:
    """Settings dataclass of planner ``name`` with the instrument's defaults and ``overrides``.

    Raises:
        PlannerError: an override names no setting of this planner, or has a bad value.
    """
    _, settings_cls = _lookup(name)
    defaults = settings_cls.for_instrument(scenario.instrument) if hasattr(settings_cls, "for_instrument") else settings_cls()
    overrides = dict(overrides or {})
    known = {f.name: f for f in dataclasses.fields(settings_cls)}
    unknown = sorted(set(overrides) - set(known))
    if unknown:
        raise PlannerError(f"planner {name!r} has no setting {unknown[0]!r}; its settings are {', '.join(sorted(known))}")
    for key, value in overrides.items():
        default = getattr(defaults, key)
        is_bool = isinstance(value, (bool, np.bool_))
        is_number = isinstance(value, numbers.Real) and not is_bool  # numpy scalars included
        if isinstance(default, bool) and not is_bool:
            raise PlannerError(f"planner {name!r}: setting {key!r} must be true or false, found {value!r}")
        if isinstance(default, (int, float)) and not isinstance(default, bool) and not is_number:
            raise PlannerError(f"planner {name!r}: setting {key!r} must be a number, found {value!r}")
    try:
        return dataclasses.replace(defaults, **overrides)
    except (TypeError, ValueError) as e:
        raise PlannerError(f"planner {name!r}: bad setting ({e})") from e


def plan(
    scenario: Scenario,
    planner: str = "straight",
    settings: Mapping[str, Any] | Any | None = None,
    progress: ProgressCallback | None = None,
) -> PlanResult:
    """Plan a scenario with a registered planner; the wall time of the call is recorded.

    Args:
        scenario: what to plan.
        planner: registry name (see :func:`planner_names`).
        settings: the planner's settings dataclass, or a mapping of overrides of its defaults.
        progress: optional callback receiving the fraction done.
    """
    func, settings_cls = _lookup(planner)
    if not isinstance(settings, settings_cls):
        settings = make_settings(planner, scenario, settings)
    t0 = time.perf_counter()
    result = func(scenario, settings, progress)
    wall = time.perf_counter() - t0
    return dataclasses.replace(result, plan_wall_s=wall)
