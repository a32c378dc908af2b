"""Exceptions raised by fiberplan.

Every error derives from :class:`FiberplanError` and from the built-in exception whose
meaning it carries, so callers may catch either. Messages name the positioner (or file, row,
key), the value found and what to change.

The command line maps them to exit statuses (``fiberplan.cli``): bad input is 2, an
infrastructure failure of a sweep (no live worker) is 3.
"""

from __future__ import annotations


class FiberplanError(Exception):
    """Base class of every error fiberplan raises on purpose."""


class InstrumentError(FiberplanError, ValueError):
    """An instrument preset or file is unknown, malformed or inconsistent."""


class ScenarioError(FiberplanError, ValueError):
    """A scenario is malformed, or a positioner's start or target cannot be used."""


class TrajectoryError(FiberplanError, ValueError):
    """A trajectory or plan result is malformed (shapes, times, outcomes, non-finite samples)."""


class TrajectoryFileError(TrajectoryError):
    """A trajectory file is missing, truncated or not a fiberplan trajectory file."""


class PlannerError(FiberplanError, RuntimeError):
    """A planner is unknown, was given bad settings, or its backend failed."""


class SettingsError(PlannerError, ValueError):
    """A planner setting is unknown, of the wrong type or outside its documented range."""


class OutputError(FiberplanError, OSError):
    """An output path cannot or must not be written (not a regular file, an input, unwritable)."""


class ProfileError(FiberplanError, ValueError):
    """Motor profiles cannot be made (an unverified trajectory) or read (a malformed profile or
    path file), or could not be verified."""


class InfrastructureError(FiberplanError, RuntimeError):
    """The machinery a sweep runs on failed (no live worker); finished results are kept."""


class StudyError(FiberplanError, ValueError):
    """A study file is missing, malformed, or names something unknown."""
