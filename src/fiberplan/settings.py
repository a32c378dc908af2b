"""Planner settings that document and check themselves.

Every field of a planner's settings dataclass is declared with :func:`setting`: its default,
one line of documentation, its unit, its valid range (or choices) and its group. The
dataclass calls :func:`check_settings` when it is built, so a value outside its range is
refused at once with a message naming the setting, the value, the range and the unit, never
found minutes into a run. :func:`describe_settings` lists them (``fiberplan planners
--settings NAME``).

Example::

    @dataclass(frozen=True)
    class MySettings:
        dt_s: float = setting(0.01, "control step", unit="s", low=1e-3, high=1.0, group="run")

        def __post_init__(self) -> None:
            check_settings(self, "my-planner")
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np

from fiberplan.errors import SettingsError

_KINDS = ("float", "int", "bool", "choice", "text", "list")

MAX_CONTROL_STEPS = 1_000_000
"""Largest number of control steps a run may be given (its time limit over its step): beyond,
the settings cannot give a result in reasonable time and are refused before the run starts."""


def check_step_budget(planner: str, max_steps: int, dt_s: float, limit_s: float) -> None:
    """Refuse a run whose time limit is more than :data:`MAX_CONTROL_STEPS` control steps.

    Raises:
        SettingsError: naming the step, the time limit and what to change.
    """
    if max_steps > MAX_CONTROL_STEPS:
        raise SettingsError(
            f"{planner}: the run could take {max_steps:,} control steps (time limit {limit_s:.4g} s at dt_s = {dt_s:g} s), more "
            f"than {MAX_CONTROL_STEPS:,}; raise dt_s or lower the time limit"
        )


def setting(
    default: Any,
    doc: str,
    *,
    unit: str = "",
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    choices: Sequence[Any] | None = None,
    optional: bool = False,
    group: str = "",
    kind: str | None = None,
) -> Any:
    """A dataclass field carrying its documentation and valid range.

    Args:
        default: the value when neither the instrument file nor the user sets it.
        doc: one line: what the setting does.
        unit: the unit of the value (``"s"``, ``"mm"``, ``"steps"``...), empty when dimensionless.
        low, high: the valid range (inclusive unless ``low_open`` / ``high_open``).
        choices: the valid values of a setting that names one of a few options.
        optional: ``None`` is also valid (meaning "off" or "derived", as ``doc`` says).
        group: the section the setting is listed under.
        kind: ``float``, ``int``, ``bool``, ``choice``, ``text`` or ``list``; by default from
            ``default`` and ``choices``.
    """
    if kind is None:
        if choices is not None:
            kind = "choice"
        elif isinstance(default, bool):
            kind = "bool"
        elif isinstance(default, int):
            kind = "int"
        elif isinstance(default, float):
            kind = "float"
        elif isinstance(default, (tuple, list)):
            kind = "list"
        else:
            kind = "text"
    if kind not in _KINDS:
        raise ValueError(f"unknown setting kind {kind!r}")
    metadata = {
        "doc": doc, "unit": unit, "low": low, "high": high, "low_open": low_open, "high_open": high_open,
        "choices": tuple(choices) if choices is not None else None, "optional": optional, "group": group, "kind": kind,
    }
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def range_text(meta: dict[str, Any]) -> str:
    """The valid values of a setting in words: ``[0.001, 1]``, ``(0, 1]``, ``one of a, b``..."""
    if meta.get("choices") is not None:
        text = "one of " + ", ".join(str(c) for c in meta["choices"] if c is not None)
    elif meta.get("kind") == "bool":
        text = "true or false"
    elif meta.get("low") is None and meta.get("high") is None:
        text = "any" if meta.get("kind") in ("text", "list") else "any finite number"
    else:
        lo = "-inf" if meta["low"] is None else f"{meta['low']:g}"
        hi = "inf" if meta["high"] is None else f"{meta['high']:g}"
        left = "(" if meta["low_open"] or meta["low"] is None else "["
        right = ")" if meta["high_open"] or meta["high"] is None else "]"
        text = f"{left}{lo}, {hi}{right}"
        if meta.get("kind") == "int":
            text = "integer in " + text
    if meta.get("optional"):
        text += ", or null"
    return text


def check_settings(settings: Any, planner: str) -> None:
    """Check every field of a settings dataclass against its declared type and range.

    Raises:
        SettingsError: a field has the wrong type or lies outside its range; the message names
            the planner, the setting, the value found and the valid range with its unit.
    """
    for f in dataclasses.fields(settings):
        meta = f.metadata
        if "doc" not in meta:
            raise SettingsError(f"{planner}: setting {f.name!r} is not declared with fiberplan.settings.setting (no doc, no range)")
        value = getattr(settings, f.name)
        if value is None and meta["optional"]:
            continue
        _check_one(planner, f.name, value, meta)
        if meta["kind"] == "int" and not isinstance(value, int):
            object.__setattr__(settings, f.name, int(value))  # 4.0 -> 4 (frozen dataclasses)
        elif meta["kind"] == "float" and not isinstance(value, float):
            object.__setattr__(settings, f.name, float(value))
        elif meta["kind"] == "bool":
            object.__setattr__(settings, f.name, bool(value))


def _check_one(planner: str, name: str, value: Any, meta: Any) -> None:
    kind = meta["kind"]
    unit = f" {meta['unit']}" if meta["unit"] else ""
    where = f"{planner}: setting {name!r}"
    if kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise SettingsError(f"{where} must be true or false, found {value!r}")
        return
    if kind == "choice":
        if value not in meta["choices"]:
            raise SettingsError(f"{where} must be {range_text(meta)}, found {value!r}")
        return
    if kind in ("text", "list"):
        return
    is_number = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
    if not is_number or not math.isfinite(float(value)):
        raise SettingsError(f"{where} must be a finite number{unit and ' in' + unit}, found {value!r}")
    if kind == "int" and float(value) != int(value):
        raise SettingsError(f"{where} must be an integer, found {value!r}")
    lo, hi = meta["low"], meta["high"]
    v = float(value)
    below = lo is not None and (v < lo or (meta["low_open"] and v == lo))
    above = hi is not None and (v > hi or (meta["high_open"] and v == hi))
    if below or above:
        raise SettingsError(f"{where} = {value!r}{unit} is outside its valid range {range_text(meta)}{unit}: {meta['doc']}")


def describe_settings(settings: Any, sources: dict[str, str] | None = None) -> list[dict[str, Any]]:
    """One row per setting: name, value, where it came from, group, unit, valid range and doc.

    ``sources`` names where each value came from (:func:`setting_sources`); ``"default"`` otherwise.
    """
    rows = []
    for f in dataclasses.fields(settings):
        meta = f.metadata
        value = getattr(settings, f.name)
        rows.append(
            {
                "name": f.name,
                "value": list(value) if isinstance(value, tuple) else value,
                "source": (sources or {}).get(f.name, "default"),
                "group": meta.get("group", ""),
                "unit": meta.get("unit", ""),
                "range": range_text(dict(meta)) if meta else "",
                "doc": meta.get("doc", ""),
            }
        )
    return rows


def setting_sources(settings_cls: type, instrument: Any, table: str, overrides: dict[str, Any] | None = None) -> dict[str, str]:
    """Where each setting's value comes from: ``default`` (the class), ``instrument`` (scaled to
    the instrument's control step and motion by ``for_instrument``), ``instrument file``
    (its ``[planner_defaults.<table>]``) or ``--set``."""
    defaults = settings_cls()
    file_table = dict(instrument.planner_defaults.get(table, {}))
    if hasattr(settings_cls, "for_instrument"):
        bare = dataclasses.replace(instrument, planner_defaults={k: v for k, v in instrument.planner_defaults.items() if k != table})
        scaled = settings_cls.for_instrument(bare)
    else:
        scaled = defaults
    out = {}
    for f in dataclasses.fields(settings_cls):
        if f.name in (overrides or {}):
            out[f.name] = "--set"
        elif f.name in file_table:
            out[f.name] = "instrument file"
        elif getattr(scaled, f.name) != getattr(defaults, f.name):
            out[f.name] = "instrument"
        else:
            out[f.name] = "default"
    return out
