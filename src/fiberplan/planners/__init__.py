"""Planner registry: every planner is ``plan_xxx(scenario, settings, progress) -> PlanResult``.

Planners are registered here by name and imported only when used (so that, for instance,
CasADi is loaded only by the ``central`` planner).
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol, cast

from fiberplan._keys import unknown_key_message
from fiberplan._registry import PLANNERS, planner_names
from fiberplan.errors import PlannerError, SettingsError
from fiberplan.instrument import Instrument
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult

ProgressCallback = Callable[..., None]
"""Called with the fraction of the work done, in [0, 1], and, if it takes a second argument, the
phase (``"start schedule"``, ``"control loop"``, ``"planner run 2: control loop"``...)."""


def phased(progress: Callable[..., None] | None) -> Callable[..., None] | None:
    """``progress`` as a callback taking ``(fraction, phase=None)``: a one-argument callback gets
    the fraction only."""
    if progress is None:
        return None
    callback = progress
    try:
        parameters = list(inspect.signature(callback).parameters.values())
    except (TypeError, ValueError):
        parameters = []
    positional = [p for p in parameters if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    takes_phase = len(positional) >= 2 or any(p.kind == p.VAR_POSITIONAL for p in parameters)

    def report(fraction: float, phase: str | None = None) -> None:
        if takes_phase:
            callback(fraction, phase)
        else:
            callback(fraction)

    return report


_PLANNERS = PLANNERS


class PlannerFunction(Protocol):
    """Signature every registered planner follows (``warm_results``: only for planners whose
    settings name ``warm_planners``)."""

    def __call__(self, scenario: Scenario, settings: Any, progress: ProgressCallback | None = None, **kwargs: Any) -> PlanResult: ...


def instrument_defaults(instrument: Instrument, table: str, defaults: Any) -> Any:
    """``defaults`` (a settings dataclass) with the instrument file's ``[planner_defaults.<table>]`` applied.

    Raises:
        SettingsError: the table names a setting the dataclass does not have, or a value is
            out of its range.
    """
    overrides = dict(instrument.planner_defaults.get(table, {}))
    known = {f.name for f in dataclasses.fields(defaults)}
    for key in overrides:
        if key not in known:
            raise SettingsError(unknown_key_message(key, known, f"instrument {instrument.name!r}: [planner_defaults.{table}]", "setting"))
    try:
        return dataclasses.replace(defaults, **overrides)
    except SettingsError as e:
        raise SettingsError(f"instrument {instrument.name!r}: [planner_defaults.{table}]: {e}") from e


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


def make_settings(name: str, scenario: Scenario | Instrument, overrides: Mapping[str, Any] | None = None) -> Any:
    """Settings dataclass of planner ``name`` with the instrument's defaults and ``overrides``.

    Args:
        name: a registered planner.
        scenario: the scenario to plan, or just its instrument (the defaults depend on it).
        overrides: setting values, e.g. from ``--set KEY=VALUE``.

    Raises:
        SettingsError: an override names no setting of this planner (the closest is named),
            has the wrong type, or lies outside its documented range.
    """
    _, settings_cls = _lookup(name)
    instrument = scenario.instrument if isinstance(scenario, Scenario) else scenario
    defaults = settings_cls.for_instrument(instrument) if hasattr(settings_cls, "for_instrument") else settings_cls()
    overrides = dict(overrides or {})
    known = {f.name: f for f in dataclasses.fields(settings_cls)}
    for key in overrides:
        if key not in known:
            raise SettingsError(unknown_key_message(key, known, f"planner {name!r}", "setting"))
    try:
        return dataclasses.replace(defaults, **overrides)
    except SettingsError:
        raise
    except (TypeError, ValueError) as e:
        raise SettingsError(f"planner {name!r}: bad setting ({e})") from e


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
        progress: optional callback receiving the fraction done (and the phase, if it takes
            a second argument: :data:`ProgressCallback`).
    """
    progress = phased(progress)
    _, settings_cls = _lookup(planner)
    if not isinstance(settings, settings_cls):
        settings = make_settings(planner, scenario, settings)
    # A planner that starts from others' trajectories (``central``'s warm starts) gets them
    # planned first, with their defaults; their wall time is not the planner's.
    warm = [plan(scenario, name) for name in getattr(settings, "warm_planners", ())]
    t0 = time.perf_counter()
    result = _plan_with(scenario, planner, settings, progress, warm)
    from fiberplan.planners.motors import governs  # here: importing the verifier loads no planner module

    if getattr(settings, "motor_limits", False) and governs(scenario.instrument.motors):
        # Completion comes first: a governed plan that leaves positioners short is planned again
        # without the governor, and the one that brings more home is kept (the discretiser then
        # keeps the motor limits).
        short = _short(scenario, result)
        if short:
            again = None
            if progress is not None:
                outer = progress

                def again(fraction: float, phase: str | None = None) -> None:
                    outer(fraction, "again without the motor governor" + (f": {phase}" if phase else ""))

            free = _plan_with(scenario, planner, dataclasses.replace(settings, motor_limits=False), again, warm)
            if _short(scenario, free) < short:
                note = (f"{planner}: the motor governor left {short} positioner(s) short; planned again without it, "
                        f"{_short(scenario, free)} short (the motor limits are left to `fiberplan profiles`)")
                result = dataclasses.replace(free, stats=free.stats | {"motor_governor": "dropped"}, warnings=(*free.warnings, note))
            result = dataclasses.replace(result, plan_wall_s=time.perf_counter() - t0)
    if getattr(settings, "stretch", False):
        result = _stretched(scenario, result, settings, progress, t0)
    return result


def _stretched(scenario: Scenario, result: PlanResult, settings: Any, progress: ProgressCallback | None, t0: float) -> PlanResult:
    """``result`` with each positioner's move spread over more of the makespan where clear (``stretch``)."""
    from fiberplan.geometry import default_safety_margin_mm
    from fiberplan.planners.stretch import stretch
    from fiberplan.trajectory import Trajectory

    if progress is not None:
        progress(1.0, "stretching the moves")
    margin = getattr(settings, "safety_margin_mm", None)
    margin = default_safety_margin_mm(scenario.instrument) if margin is None else float(margin)
    done = stretch(scenario, result.trajectory.times, result.trajectory.joints, margin)
    stats = dict(result.stats or {}) | {"stretch": {"positioners": done.positioners, "energy_before_rad2_s": done.energy_before,
                                                    "energy_after_rad2_s": done.energy_after}}
    return dataclasses.replace(result, trajectory=Trajectory(result.trajectory.times, done.joints), stats=stats,
                               plan_wall_s=time.perf_counter() - t0)


def _short(scenario: Scenario, result: PlanResult) -> int:
    """Positioners with a target that the result leaves short of it."""
    from fiberplan.metrics import reached_mask

    return int(scenario.has_target.sum() - reached_mask(scenario, result.trajectory).sum())


def _plan_with(scenario: Scenario, planner: str, settings: Any, progress: ProgressCallback | None, warm: list[PlanResult]) -> PlanResult:
    """One run of ``planner`` with these settings (through the coordination layer unless ``route`` is direct)."""
    func, _ = _lookup(planner)
    t0 = time.perf_counter()
    route = getattr(settings, "route", "direct")
    if route != "direct":
        # The coordination layer plans the legs with this planner alone (route = direct).
        coordination = importlib.import_module("fiberplan.planners.coordination")
        direct: Any = dataclasses.replace(cast(Any, settings), route="direct")

        fallback = getattr(settings, "route_fallback_planner", None)

        def plan_leg(leg: Scenario, time_limit_s: float | None = None, use_fallback: bool = False,
                     progress: ProgressCallback | None = None, overrides: Mapping[str, Any] | None = None) -> PlanResult:
            if use_fallback and fallback:
                other_func, _ = _lookup(fallback)
                other = dataclasses.replace(make_settings(fallback, leg, {"route": "direct"}), time_limit_s=time_limit_s)
                return other_func(leg, other, progress)
            leg_settings = direct if time_limit_s is None else dataclasses.replace(direct, time_limit_s=time_limit_s)
            if overrides:  # (the layer's own variants of a leg: this planner's settings only)
                leg_settings = dataclasses.replace(leg_settings, **overrides)
            return func(leg, leg_settings, progress)

        result = coordination.coordinate(scenario, planner, settings, plan_leg, t0, progress)
        if progress is not None:
            progress(1.0)
        return result
    result = func(scenario, settings, progress, warm_results=warm) if warm else func(scenario, settings, progress)
    wall = time.perf_counter() - t0
    return dataclasses.replace(result, plan_wall_s=wall)
