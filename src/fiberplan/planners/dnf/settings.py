"""Settings of the ``dnf`` planner: the potential's weights, the safety layer, the deadlock escape."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from fiberplan.instrument import Instrument
from fiberplan.planners import instrument_defaults
from fiberplan.planners.coordination.settings import RouteSettings
from fiberplan.settings import check_settings, setting

AttractionKind = Literal["joint", "fiber"]
SeparationKind = Literal["capsule", "ellipse"]
PriorityKind = Literal["none", "move_time"]
PotentialKind = Literal["reference", "smooth"]
EscapeKind = Literal["none", "retreat"]

_DESI_RHO_MM = 6.0
"""Reach of the DESI positioner (3 + 3 mm, reference 000 table 3): the scale at which the
printed lambda_1 = 1 (table 4) is kept."""

_DESI_DT_S = 0.01
"""Reference 000, table 4: dt = 10 ms."""

_REPULSION_RATIO = 0.01
"""Default lambda_2 / (lambda_1 rho^2); measured on DESI (``formulations/dnf.md``, tuning table)."""

_ENVELOPE_CAP_MM = 2.0
"""Default envelope margin ``D - d`` is the smallest collision distance, at most 2 mm (reference
000 table 3: D - d = 2 mm); measured on MOONS-like unfold at N = 61, 2 mm beats 4 mm."""

_MIN_SEP2_FRACTION = 1e-4
"""Floor of ``(r^2 - d^2) / d^2`` in the repulsive gradient (keeps it finite at contact)."""


@dataclass(frozen=True)
class DnfSettings(RouteSettings):
    """Settings of the ``dnf`` planner (defaults per instrument: :meth:`for_instrument`).

    Every field is declared with :func:`fiberplan.settings.setting` (doc, unit, valid range,
    group). Notes on some of them:

    - ``potential``: ``"reference"`` is the corrected term of reference 000 eq. 2,
      ``(D^2 - r^2) / (r^2 - d^2)``, whose slope jumps at ``r = D``; ``"smooth"`` is
      ``(D^2 - r^2)^2 / ((r^2 - d^2)(D^2 - d^2))``, the same barrier with a slope that vanishes at D.
    - ``attraction``: ``"joint"`` is ``rho^2 ||q - q_T||^2`` with ``rho`` the reach (a straight
      joint move, never across a hard stop); ``"fiber"`` the squared fiber distance of eq. 2.
    - ``separation``: ``"ellipse"`` is reference 002 eq. 7 for two arm capsules.
    - ``zone_priority = "move_time"``: per-positioner envelopes (reference 002 section 2.4),
      margins over ``envelope_mm * [1 - spread, 1 + spread]``, the smallest for the longest move.
    - ``deadlock_escape = "retreat"`` (not part of the printed method): a positioner stuck for
      ``escape_window_s`` inside a neighbour's envelope makes the one of the pair already at its
      target (else the one with the shorter move) fold its beta arm for ``retreat_s``, as
      positioner 5 yields in reference 002, fig. 5.
    """

    dt_s: float = setting(_DESI_DT_S, "control step and trajectory sample spacing (reference 000 table 4: 10 ms)", unit="s",
                          low=1e-4, high=1.0, group="run")
    # --- the potential
    lambda_attract: float = setting(1.0, "lambda_1, weight of the attraction (1 for DESI, reference 000 table 4)", low=0.0,
                                    high=1e9, low_open=True, group="potential")
    lambda_repel: float = setting(_REPULSION_RATIO * _DESI_RHO_MM**2, "lambda_2, weight of the repulsion", unit="mm^2", low=0.0,
                                  high=1e12, group="potential")
    envelope_mm: float = setting(2.0, "clearance below which the repulsion acts, D - d (reference 000 table 3: 2 mm)", unit="mm",
                                 low=0.0, high=100.0, low_open=True, group="potential")
    potential: PotentialKind = setting("reference", "form of the repulsive term", choices=("reference", "smooth"), group="potential")
    attraction: AttractionKind = setting("joint", "attraction in joint space or in the focal plane", choices=("joint", "fiber"),
                                         group="potential")
    separation: SeparationKind = setting("capsule", "capsule segment distance, or reference 002's ellipse distance for arms",
                                         choices=("capsule", "ellipse"), group="potential")
    zone_priority: PriorityKind = setting("none", "one envelope for all, or per-positioner envelopes by move time",
                                          choices=("none", "move_time"), group="potential")
    zone_spread: float = setting(0.5, "relative spread of the per-positioner envelopes", low=0.0, high=1.0, high_open=True,
                                 group="potential")
    goal_envelope_cap: bool = setting(True, "cap each pair's envelope at its clearance at the goals (targets an equilibrium)",
                                      group="potential")
    # --- the safety layer
    safety_margin_mm: float = setting(1e-3, "smallest clearance the safety layer keeps along every step", unit="mm", low=0.0,
                                      high=10.0, group="safety")
    safety_motion_factor: float = setting(0.1, "a step needs c0 + c1 >= (1 + factor) B + 2 margin", low=0.0, high=100.0,
                                          group="safety")
    max_halvings: int = setting(4, "halvings of a step before the positioner holds for this step", low=0, high=30, group="safety")
    # --- deadlocks
    deadlock_window_s: float = setting(1.5, "a positioner not progress_mm closer over this window is stuck", unit="s", low=0.0,
                                       high=1e5, low_open=True, group="deadlocks")
    progress_mm: float = setting(0.1, "progress threshold of the deadlock test (instrument default: the tolerance)", unit="mm",
                                 low=0.0, high=100.0, low_open=True, group="deadlocks")
    deadlock_escape: EscapeKind = setting("retreat", "none: the printed method; retreat: a temporary fold sub-goal",
                                          choices=("none", "retreat"), group="deadlocks")
    escape_window_s: float = setting(0.2, "no-progress window that starts a retreat", unit="s", low=0.0, high=1e5, low_open=True,
                                     group="deadlocks")
    retreat_s: float = setting(0.5, "duration of a retreat", unit="s", low=0.0, high=1e5, low_open=True, group="deadlocks")
    max_retreats: int = setting(3, "retreats per positioner and run", low=0, high=1000, group="deadlocks")
    # --- the route (fiberplan.planners.coordination; the other route settings: RouteSettings)
    route_fallback_planner: str | None = setting("mpc", "the planner of a leg's last attempts (up to two) when this one stalls, "
                                                 "and of the whole move when this one's routes fall short (null: none, "
                                                 "for studies of this planner alone)", choices=("mpc", "dnf", None), optional=True,
                                                 group="route")
    # --- run length
    time_limit_s: float | None = setting(None, "stop here at the latest (null: 4 x the lower bound plus two deadlock windows)",
                                         unit="s", low=0.0, high=1e5, low_open=True, optional=True, group="run", kind="float")

    @classmethod
    def for_instrument(cls, instrument: Instrument) -> DnfSettings:
        """Defaults for an instrument.

        ``dt_s`` is the instrument's control period; ``lambda_attract`` keeps reference 000's
        ``lambda_1 = 1`` at DESI's reach and 10 ms and scales as ``1 / (rho^2 dt)`` otherwise
        (the same discrete loop gain ``2 lambda_1 rho^2 dt = 0.72``); ``lambda_repel`` keeps
        the measured ratio to ``lambda_1 rho^2``; the envelope margin is the smallest sum of
        capsule radii, at most 2 mm (reference 000 table 3: ``D - d = 2`` mm); the deadlock window is the
        time of half a turn of the slower joint. An instrument file may override any of
        them in a ``[planner_defaults.dnf]`` table.

        Raises:
            PlannerError: the ``[planner_defaults.dnf]`` table names an unknown setting.
        """
        dt = instrument.control_dt_s
        rho = instrument.reach_max_mm
        lam1 = (_DESI_RHO_MM**2 * _DESI_DT_S) / (rho**2 * dt)
        radii = [a.radius_mm + b.radius_mm for a, b in ((instrument.capsules[i], instrument.capsules[j]) for i, j in instrument.capsule_pairs)]
        # Polygon zones (sharp, unpadded edges) have no radius: the cap stands for them.
        radii = [r for r in radii if r > 0.0] or [_ENVELOPE_CAP_MM]
        half_turn = instrument.full_turn_s / 2.0
        defaults = cls(
            dt_s=dt,
            lambda_attract=lam1,
            lambda_repel=_REPULSION_RATIO * lam1 * rho**2,
            envelope_mm=min(float(min(radii)), _ENVELOPE_CAP_MM),
            deadlock_window_s=half_turn,
            escape_window_s=half_turn / 7.5,
            retreat_s=half_turn / 3.0,
            progress_mm=instrument.tolerance_mm,
        )
        return instrument_defaults(instrument, "dnf", defaults)

    def __post_init__(self) -> None:
        check_settings(self, "dnf")
