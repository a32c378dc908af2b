"""Exceptions raised by fiberplan.

Every error derives from :class:`FiberplanError` and from the built-in exception whose
meaning it carries, so callers may catch either. Messages name the positioner, the value
found and what to change.
"""

from __future__ import annotations


class FiberplanError(Exception):
    """Base class of every error fiberplan raises on purpose."""


class InstrumentError(FiberplanError, ValueError):
    """An instrument preset or file is unknown, malformed or inconsistent."""


class ScenarioError(FiberplanError, ValueError):
    """A scenario is malformed, or a positioner's start or target cannot be used."""


class TrajectoryFileError(FiberplanError, ValueError):
    """A trajectory file is missing, truncated or not a fiberplan trajectory file."""


class PlannerError(FiberplanError, RuntimeError):
    """A planner is unknown, was given bad settings, or its backend failed."""
