"""The ``dnf`` planner: decentralized navigation functions (references 000 and 002).

Every positioner ``i`` descends its own potential (``formulations/dnf.md``)

.. math::

    \\psi_i = \\lambda_1 A_i(q_i) + \\lambda_2 \\sum_{j \\in N(i)} \\sum_{k} \\phi(r_{ijk}; d_k, D_{ik}),
    \\qquad
    \\phi(r; d, D) = \\begin{cases} \\dfrac{D^2 - r^2}{r^2 - d^2} & d < r < D \\\\ 0 & r \\ge D \\end{cases}

with the attraction ``A_i`` either ``rho^2 ||q_i - q_iT||^2`` in joint space (default) or
``||p_i(q_i) - p_iT||^2`` in the focal plane (reference 000, eq. 2), and ``r_ijk`` the
separation of capsule combination ``k`` of the pair: the segment distance (for DESI, the
fiber-end distance of reference 000), or for arm capsules the weighted (ellipse) distance of
reference 002, eqs. 6-7. ``d_k`` is the sum of the two radii and ``D_ik = d_k + m_ik`` with the
envelope margin ``m_ik`` of positioner ``i`` (reference 002, section 2.4: per-positioner zone
sizes act as an implicit priority).

The control law is the chain rule through the Jacobian (reference 000, eqs. 3-4),
``omega_i = -grad_{q_i} psi_i``, saturated at the motor speeds with the direction kept. A safety
layer then checks the exact capsule clearances of the configuration that is actually reached
(all positioners step at once) and shortens the steps of the positioners of every pair whose
linear motion over the step could not be proven collision-free (halving, then holding).
A positioner that is not within tolerance and has not come closer to its target over a
window is marked ``deadlocked``. By default (``deadlock_escape = "retreat"``, not part of the
printed method) a pair blocked for a shorter window is resolved by a temporary sub-goal: its
lower-priority member folds its beta arm for a while, as positioner 5 backs away in reference
002, fig. 5. The run stops when every positioner sits exactly on its
target joints or can make no more progress, or at the time limit (positioners still moving
then are ``unfinished``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.geometry import pair_clearance
from fiberplan.instrument import Instrument
from fiberplan.kinematics import fiber_jacobian, fiber_positions, move_times
from fiberplan.outcomes import outcome_labels
from fiberplan.planners import ProgressCallback, instrument_defaults
from fiberplan.planners.safety import HalvingStats, halve_steps, motion_bound, point_extents
from fiberplan.scenario import Scenario
from fiberplan.settings import check_settings, check_step_budget, setting
from fiberplan.trajectory import PlanResult, Trajectory

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
class DnfSettings:
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


# ---------------------------------------------------------------------------------------------
# Convergence condition (reference 000, eq. 5)


@dataclass(frozen=True)
class ConvergenceCheck:
    """Reference 000, eq. 5, evaluated for one parameter set.

    .. math:: \\frac{\\lambda_1}{\\lambda_2} < \\frac{1}{R} \\frac{D}{D^2 - d^2}

    Attributes:
        ratio: ``lambda_1 / lambda_2``.
        bound: the right-hand side (the smallest over the capsule combinations).
        holds: ``ratio < bound``.
        R_mm, D_mm, d_mm: the lengths used (those of the binding combination).
    """

    ratio: float
    bound: float
    holds: bool
    R_mm: float
    D_mm: float
    d_mm: float


def convergence_bound(R_mm: float, D_mm: float, d_mm: float) -> float:
    """Right-hand side of reference 000, eq. 5: ``D / (R (D^2 - d^2))`` (1/mm).

    Raises:
        PlannerError: the lengths do not satisfy ``0 < d < D`` and ``R > 0``.
    """
    if not (R_mm > 0 and 0 < d_mm < D_mm):
        raise PlannerError(f"convergence condition needs R > 0 and 0 < d < D, found R={R_mm}, D={D_mm}, d={d_mm} mm")
    return D_mm / (R_mm * (D_mm**2 - d_mm**2))


def convergence_condition(
    instrument: Instrument, lambda_attract: float, lambda_repel: float, envelope_mm: float
) -> ConvergenceCheck:
    """Whether ``lambda_1``, ``lambda_2`` and the envelope satisfy reference 000, eq. 5.

    ``R`` is the largest distance any capsule surface reaches from the base (7 mm for DESI:
    3 + 3 mm arms plus the 1 mm fiber-end radius, reference 000 table 3), ``d`` the sum of
    radii of a capsule combination and ``D = d + envelope_mm``; the condition must hold for
    every combination, so the smallest bound is used. For DESI's printed parameters
    (lambda_1 = 1, lambda_2 = 0.05, R = 7, D = 4, d = 2 mm) the bound is 1/21 mm^-1 and the
    condition fails (ratio 20): the printed "lambda_1 < 72 lambda_2" is a slip.

    Raises:
        PlannerError: a weight is not positive or the envelope is not positive.
    """
    if not (lambda_attract > 0 and lambda_repel > 0 and envelope_mm > 0):
        raise PlannerError(
            f"convergence condition needs lambda_attract > 0, lambda_repel > 0 and envelope_mm > 0, "
            f"found {lambda_attract}, {lambda_repel}, {envelope_mm}"
        )
    R = instrument.extent_mm
    best: tuple[float, float, float] | None = None
    for a, b in instrument.capsule_pairs:
        d = instrument.capsules[a].radius_mm + instrument.capsules[b].radius_mm
        bound = convergence_bound(R, d + envelope_mm, d)
        if best is None or bound < best[0]:
            best = (bound, d + envelope_mm, d)
    assert best is not None  # an instrument has at least one capsule, so one combination
    ratio = lambda_attract / lambda_repel
    return ConvergenceCheck(ratio=ratio, bound=best[0], holds=ratio < best[0], R_mm=R, D_mm=best[1], d_mm=best[2])


# ---------------------------------------------------------------------------------------------
# Potential gradients


def repulsion_slope(r: np.ndarray, d: np.ndarray, D: np.ndarray, potential: PotentialKind = "reference") -> np.ndarray:
    """Derivative ``d phi / d r`` of the repulsive term (zero for ``r >= D``).

    .. math::

        \\phi'_{ref}(r) = -\\frac{2 r (D^2 - d^2)}{(r^2 - d^2)^2}, \\qquad
        \\phi'_{smooth}(r) = -\\frac{2 r (D^2 - r^2) (D^2 + r^2 - 2 d^2)}{(r^2 - d^2)^2 (D^2 - d^2)}
        \\qquad (d < r < D)

    ``r^2 - d^2`` is floored at ``1e-4 d^2`` so that the slope stays finite at contact.
    """
    gap = np.maximum(r * r - d * d, _MIN_SEP2_FRACTION * d * d)
    span = D * D - d * d
    if potential == "reference":
        slope = -2.0 * r * span / (gap * gap)
    else:
        room = D * D - r * r
        slope = -2.0 * r * room * (room + 2.0 * gap) / (gap * gap * np.maximum(span, 1e-300))
    return np.where(r < D, slope, 0.0)


def repulsion_potential(r: np.ndarray, d: np.ndarray, D: np.ndarray, potential: PotentialKind = "reference") -> np.ndarray:
    """The repulsive term ``phi(r; d, D)`` (``formulations/dnf.md``).

    .. math::

        \\phi_{ref} = \\frac{D^2 - r^2}{r^2 - d^2}, \\qquad
        \\phi_{smooth} = \\frac{(D^2 - r^2)^2}{(r^2 - d^2)(D^2 - d^2)} \\qquad (d < r < D),
        \\text{ zero for } r \\ge D.
    """
    gap = np.maximum(r * r - d * d, _MIN_SEP2_FRACTION * d * d)
    room = D * D - r * r
    value = room / gap if potential == "reference" else room * room / (gap * np.maximum(D * D - d * d, 1e-300))
    return np.where(r < D, value, 0.0)


def _perp(v: np.ndarray) -> np.ndarray:
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


def ellipse_arm_distance(
    instrument: Instrument,
    capsule_index: int,
    base_xy: np.ndarray,
    orient: np.ndarray,
    joints: np.ndarray,
    pairs: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted (ellipse) distance between the arm zones of positioner pairs (reference 002, eq. 6).

    The arm zone of capsule ``c`` (a segment of half-length ``h`` on the beta arm, radius
    ``b``) is the ellipse of semi-axes ``a = h + b`` along the arm and ``b`` across it,
    centred on the segment's middle ``c_i``. In the frame of arm ``i`` (unit vector ``u_i``)
    the weighted distance maps that ellipse onto a circle of radius ``b``:

    .. math::

        f_i = \\frac{b^2}{a^2} (\\Delta \\cdot u_i)^2 + (\\Delta \\cdot u_i^\\perp)^2, \\quad
        \\Delta = c_i - c_j, \\qquad r_w = \\sqrt{(f_i + f_j) / 2}

    (symmetrised over the two frames, so that ``r_w`` is the same for ``i`` and ``j``). Two
    parallel zones touch side by side or end to end at ``r_w = 2 b``.

    Returns:
        ``(r_w, grad_i, grad_j)``: ``(P,)`` distances and ``(P, 2)`` gradients w.r.t.
        ``(alpha, beta)`` of ``i`` and of ``j``.
    """
    cap = instrument.capsules[capsule_index]
    half = 0.5 * abs(cap.end_mm - cap.start_mm)
    mid = 0.5 * (cap.start_mm + cap.end_mm)
    w_par = (cap.radius_mm / (half + cap.radius_mm)) ** 2
    a = joints[:, 0] + orient
    ab = a + joints[:, 1]
    ua = np.stack([np.cos(a), np.sin(a)], axis=-1)
    u = np.stack([np.cos(ab), np.sin(ab)], axis=-1)
    elbow = base_xy + instrument.alpha_arm_mm * ua
    centre = elbow + mid * u
    ii, jj = pairs[:, 0], pairs[:, 1]
    delta = centre[ii] - centre[jj]
    ui, uj = u[ii], u[jj]
    pi, pj = _perp(ui), _perp(uj)
    ei, fi = np.einsum("pk,pk->p", delta, ui), np.einsum("pk,pk->p", delta, pi)
    ej, fj = np.einsum("pk,pk->p", delta, uj), np.einsum("pk,pk->p", delta, pj)
    s = 0.5 * (w_par * ei**2 + fi**2 + w_par * ej**2 + fj**2)
    r_w = np.sqrt(np.maximum(s, 1e-24))
    # s = r_w^2; d s / d delta = W_i delta + W_j delta
    wd = (w_par * ei)[:, None] * ui + fi[:, None] * pi + (w_par * ej)[:, None] * uj + fj[:, None] * pj
    # rotation of each frame: d f / d theta = 2 (w_par - 1) e f; s carries a factor 1/2
    rot_i = (w_par - 1.0) * ei * fi
    rot_j = (w_par - 1.0) * ej * fj
    d_alpha_i = _perp(centre[ii] - base_xy[ii])
    d_beta_i = mid * pi
    d_alpha_j = -_perp(centre[jj] - base_xy[jj])
    d_beta_j = -mid * pj
    grad_i = np.stack(
        [np.einsum("pk,pk->p", wd, d_alpha_i) + rot_i, np.einsum("pk,pk->p", wd, d_beta_i) + rot_i], axis=-1
    )
    grad_j = np.stack(
        [np.einsum("pk,pk->p", wd, d_alpha_j) + rot_j, np.einsum("pk,pk->p", wd, d_beta_j) + rot_j], axis=-1
    )
    # d r_w = d s / (2 r_w)
    return r_w, grad_i / (2.0 * r_w[:, None]), grad_j / (2.0 * r_w[:, None])


@dataclass
class _PairModel:
    """Per pair-combination constants of the repulsion (fixed during a run)."""

    pairs: np.ndarray  # (P, 2)
    d: np.ndarray  # (K,) collision distance of each combination
    D_i: np.ndarray  # (P, K) envelope seen by i
    D_j: np.ndarray  # (P, K) envelope seen by j
    ellipse_combos: np.ndarray  # combination indices that use the weighted distance
    ellipse_capsule: np.ndarray  # capsule index of each of them
    cull_clearance: float  # capsule clearance beyond which no term of the pair is active


def _zone_margins(scenario: Scenario, settings: DnfSettings) -> np.ndarray:
    """Per-positioner envelope margins (mm): reference 002 section 2.4's implicit priority.

    ``move_time``: the positioner with the longest unobstructed move gets the smallest zone
    (it reacts last, so it has priority); margins are spread linearly by rank over
    ``envelope * [1 - spread, 1 + spread]``.
    """
    n = scenario.n_positioners
    base = np.full(n, settings.envelope_mm)
    if settings.zone_priority == "none" or n == 1 or settings.zone_spread == 0.0:
        return base
    times = move_times(scenario.instrument, scenario.start, scenario.target)
    order = np.lexsort((scenario.ids, -times))  # longest move first; ties by id (deterministic)
    rank = np.empty(n)
    rank[order] = np.arange(n) / (n - 1)  # 0 for the longest move
    return settings.envelope_mm * (1.0 + settings.zone_spread * (2.0 * rank - 1.0))


def _pair_model(scenario: Scenario, settings: DnfSettings) -> _PairModel:
    inst = scenario.instrument
    pairs = scenario.pairs
    combos = np.array(inst.capsule_pairs, dtype=np.int64).reshape(-1, 2)
    radii = np.array([c.radius_mm for c in inst.capsules])
    d = radii[combos[:, 0]] + radii[combos[:, 1]]
    margins = _zone_margins(scenario, settings)
    m_i = np.broadcast_to(margins[pairs[:, 0]][:, None], (len(pairs), len(combos))).copy()
    m_j = np.broadcast_to(margins[pairs[:, 1]][:, None], (len(pairs), len(combos))).copy()
    ellipse = np.array(
        [
            settings.separation == "ellipse" and a == b and inst.capsules[a].end_mm != inst.capsules[a].start_mm
            for a, b in combos
        ],
        dtype=bool,
    )
    if settings.goal_envelope_cap and len(pairs):
        goal = scenario.target
        sep = pair_clearance(inst, scenario.base_xy, scenario.orient, goal, pairs).distance
        if ellipse.any():
            for k in np.flatnonzero(ellipse):
                sep[:, k] = ellipse_arm_distance(inst, int(combos[k, 0]), scenario.base_xy, scenario.orient, goal, pairs)[0]
        goal_gap = np.maximum(sep - d, 0.0)
        m_i = np.minimum(m_i, goal_gap)
        m_j = np.minimum(m_j, goal_gap)
    return _PairModel(
        pairs=pairs,
        d=d,
        D_i=d + m_i,
        D_j=d + m_j,
        ellipse_combos=np.flatnonzero(ellipse),
        ellipse_capsule=combos[ellipse, 0],
        cull_clearance=_cull_clearance(inst, combos, d, ellipse, float(max(np.max(m_i, initial=0.0), np.max(m_j, initial=0.0)))),
    )


def _cull_clearance(instrument: Instrument, combos: np.ndarray, d: np.ndarray, ellipse: np.ndarray, margin_max: float) -> float:
    """Smallest pair clearance at which every repulsive term of the pair is surely zero.

    A segment term is active only below ``margin_max``. An ellipse term with weight
    ``w = b^2 / a^2`` has ``r_w >= sqrt(w) |c_i - c_j| >= sqrt(w) (c + d)`` (the centres lie on
    the segments), so it is inactive once the clearance ``c`` exceeds ``(d + m) / sqrt(w) - d``.
    """
    limit = margin_max
    for k in np.flatnonzero(ellipse):
        cap = instrument.capsules[int(combos[k, 0])]
        sqrt_w = cap.radius_mm / (0.5 * abs(cap.end_mm - cap.start_mm) + cap.radius_mm)
        limit = max(limit, (d[k] + margin_max) / sqrt_w - d[k])
    return float(limit)


class _ClearanceBound:
    """Lower bounds on pair clearances between exact evaluations (pair culling).

    Over any motion the clearance of a pair drops by at most the sum of the motion bounds
    of its two positioners (see :func:`_safe_steps`), so after an exact evaluation ``c_ref``

    .. math:: c_{ij}(t) \\ge c_{ref} - (S_i(t) + S_j(t) - S_i(t_{ref}) - S_j(t_{ref}))

    with ``S`` the cumulative motion bound. Pairs whose bound is at least the largest
    envelope margin exert no repulsion and need no exact evaluation.
    """

    def __init__(self, pairs: np.ndarray, n: int, rho: np.ndarray) -> None:
        self.pairs = pairs
        self.rho = rho
        self.c_ref = np.full(len(pairs), -np.inf)
        self.s_ref = np.zeros(len(pairs))
        self.cum = np.zeros(n)

    def lower_bound(self) -> np.ndarray:
        return self.c_ref - (self.cum[self.pairs[:, 0]] + self.cum[self.pairs[:, 1]] - self.s_ref)

    def record(self, rows: np.ndarray, clearance: np.ndarray) -> None:
        self.c_ref[rows] = clearance
        self.s_ref[rows] = self.cum[self.pairs[rows, 0]] + self.cum[self.pairs[rows, 1]]

    def moved(self, step: np.ndarray) -> None:
        self.cum += motion_bound(self.rho, step)


def _repulsion_gradient(
    scenario: Scenario,
    model: _PairModel,
    joints: np.ndarray,
    lambda_repel: float,
    potential: PotentialKind,
    bound: _ClearanceBound,
) -> tuple[np.ndarray, np.ndarray]:
    """Gradient of each positioner's repulsive terms w.r.t. its own joints, and pair clearances.

    Only pairs that may lie inside an envelope are evaluated exactly (``_PairModel.cull_clearance``).

    Returns:
        ``(grad, clearance)``: ``(N, 2)`` gradients (``lambda_2`` included) and ``(P,)``
        smallest capsule clearance of each pair at ``joints``: exact for the evaluated
        pairs, a lower bound (at least the largest envelope margin) for the others.
    """
    inst = scenario.instrument
    n = scenario.n_positioners
    grad = np.zeros((n, 2))
    if len(model.pairs) == 0:
        return grad, np.zeros(0)
    clear = bound.lower_bound()
    rows = np.flatnonzero(clear < model.cull_clearance)
    if len(rows) == 0:
        return grad, clear
    pairs = model.pairs[rows]
    pc = pair_clearance(inst, scenario.base_xy, scenario.orient, joints, pairs, gradient=True)
    assert pc.grad_i is not None and pc.grad_j is not None
    exact = pc.clearance.min(axis=1)
    bound.record(rows, exact)
    clear[rows] = exact
    r = pc.distance
    g_i, g_j = pc.grad_i, pc.grad_j
    if len(model.ellipse_combos):
        r = r.copy()
        g_i, g_j = g_i.copy(), g_j.copy()
        for k, cap in zip(model.ellipse_combos.tolist(), model.ellipse_capsule.tolist(), strict=True):
            r[:, k], g_i[:, k], g_j[:, k] = ellipse_arm_distance(inst, cap, scenario.base_xy, scenario.orient, joints, pairs)
    d = model.d[None, :]
    slope_i = repulsion_slope(r, d, model.D_i[rows], potential)  # (P, K)
    slope_j = repulsion_slope(r, d, model.D_j[rows], potential)
    contrib_i = lambda_repel * np.einsum("pk,pkc->pc", slope_i, g_i)
    contrib_j = lambda_repel * np.einsum("pk,pkc->pc", slope_j, g_j)
    for c in range(2):
        grad[:, c] = np.bincount(pairs[:, 0], weights=contrib_i[:, c], minlength=n) + np.bincount(
            pairs[:, 1], weights=contrib_j[:, c], minlength=n
        )
    return grad, clear


# ---------------------------------------------------------------------------------------------
# Safety layer


# The safety layer is fiberplan.planners.safety.halve_steps.


# ---------------------------------------------------------------------------------------------
# Progress, deadlock and escape bookkeeping


def _distance_to_go(settings: DnfSettings, rho_mm: float, q: np.ndarray, target: np.ndarray, fiber_err: np.ndarray) -> np.ndarray:
    """The distance the attraction shrinks (mm): ``rho ||q - q_T||`` (joint) or the fiber error.

    Progress is measured on it, not on the fiber error, because a straight joint move may
    take the fiber away from its target before bringing it back.
    """
    if settings.attraction == "joint":
        return rho_mm * np.linalg.norm(q - target, axis=1)
    return fiber_err


class _ProgressWindow:
    """Best distance-to-target of each positioner over a sliding window of steps.

    A positioner is stuck when it has been tracked for ``window`` steps and its best
    distance to go (:func:`_distance_to_go`) has not improved by more than ``threshold_mm`` over the last ``window`` steps.
    """

    def __init__(self, err: np.ndarray, window: int, threshold_mm: float) -> None:
        self.window = window
        self.threshold = threshold_mm
        self.best = err.copy()
        self.ring = np.full((window + 1, len(err)), np.inf)
        self.ring[0] = self.best
        self.age = np.zeros(len(err), dtype=np.int64)
        self.count = 0

    def update(self, err: np.ndarray) -> None:
        self.count += 1
        self.age += 1
        self.best = np.minimum(self.best, err)
        self.ring[self.count % (self.window + 1)] = self.best

    def stuck(self) -> np.ndarray:
        before = self.ring[(self.count - self.window) % (self.window + 1)] if self.count >= self.window else np.inf
        return (self.age >= self.window) & (before - self.best <= self.threshold)

    def reset(self, rows: np.ndarray, err: np.ndarray) -> None:
        self.best[rows] = err[rows]
        self.ring[:, rows] = np.inf
        self.ring[self.count % (self.window + 1), rows] = err[rows]
        self.age[rows] = 0


@dataclass
class _Escape:
    """Retreat sub-goals: who yields, to where, until when."""

    active: np.ndarray  # (N,) bool
    goal: np.ndarray  # (N, 2)
    until: np.ndarray  # (N,) step index at which the retreat ends
    count: np.ndarray  # (N,) retreats so far
    started: int = 0


def _start_retreats(
    escape: _Escape,
    stuck: np.ndarray,
    reached: np.ndarray,
    pairs: np.ndarray,
    clear0: np.ndarray,
    envelope_mm: float,
    rank: np.ndarray,
    ids: np.ndarray,
    q: np.ndarray,
    fold_beta: float,
    step_index: int,
    retreat_steps: int,
    max_retreats: int,
) -> np.ndarray:
    """Pick the yielding positioner of every blocked pair and send it toward its folded arm.

    A pair blocks when one of its positioners is stuck (not reached) and their clearance is
    inside the envelope. Of the two, the one with the lower ``rank`` yields (ties: the larger
    id), as positioner 5 of reference 002, fig. 5 does: its sub-goal keeps its alpha and folds
    beta. Returns the rows that started a retreat.
    """
    if len(pairs) == 0:
        return np.zeros(0, dtype=np.int64)
    ii, jj = pairs[:, 0], pairs[:, 1]
    blocked = (clear0 < envelope_mm) & ((stuck[ii] & ~reached[ii]) | (stuck[jj] & ~reached[jj]))
    if not np.any(blocked):
        return np.zeros(0, dtype=np.int64)
    bi, bj = ii[blocked], jj[blocked]
    i_yields = (rank[bi] < rank[bj]) | ((rank[bi] == rank[bj]) & (ids[bi] > ids[bj]))
    yielders = np.unique(np.where(i_yields, bi, bj))
    yielders = yielders[~escape.active[yielders] & (escape.count[yielders] < max_retreats)]
    if len(yielders) == 0:
        return yielders
    escape.active[yielders] = True
    escape.goal[yielders, 0] = q[yielders, 0]
    escape.goal[yielders, 1] = fold_beta
    escape.until[yielders] = step_index + retreat_steps
    escape.count[yielders] += 1
    escape.started += len(yielders)
    return yielders


# ---------------------------------------------------------------------------------------------
# The planner


def plan_dnf(scenario: Scenario, settings: DnfSettings, progress: ProgressCallback | None = None) -> PlanResult:
    """Plan with decentralized navigation functions (see the module docstring).

    Every control step costs O(N): one vectorised pass over the neighbour pairs that may be
    inside an envelope for the repulsion, one over the pairs at risk for the safety layer;
    there is no Python loop over positioners.

    Args:
        scenario: what to plan.
        settings: see :class:`DnfSettings` (``DnfSettings.for_instrument`` for defaults).
        progress: optional callback receiving the fraction of the time limit simulated.

    Returns:
        The trajectory (samples every ``dt_s`` from 0), per-positioner outcome
        (``reached``: within the instrument's tolerance at the end; ``deadlocked``: not, and no
        progress over ``deadlock_window_s``; ``unfinished``: not, and still progressing at the time
        limit; ``held`` / ``displaced``: no target, ending where it started or not) and statistics (steps, retreats, safety-layer interventions, timings, whether
        reference 000's eq. 5 holds for the settings).
    """
    t_wall = time.perf_counter()
    inst = scenario.instrument
    n = scenario.n_positioners
    dt = settings.dt_s
    speeds = inst.speeds_rad_s
    lim = inst.limits_rad
    rho_reach = inst.reach_max_mm
    rho_motion = point_extents(inst)
    target = scenario.target
    target_xy = scenario.target_xy
    model = _pair_model(scenario, settings)
    pairs = model.pairs
    fold_beta = float(np.clip(inst.datum_rad[1], lim[1, 0], lim[1, 1]))

    initial_move = move_times(inst, scenario.start, target)
    lower = float(initial_move.max())
    time_limit = settings.time_limit_s if settings.time_limit_s is not None else 4.0 * lower + 2.0 * settings.deadlock_window_s
    max_steps = max(1, math.ceil(time_limit / dt - 1e-9))
    check_step_budget("dnf", max_steps, dt, time_limit)
    window = max(1, round(settings.deadlock_window_s / dt))
    escape_window = max(1, round(settings.escape_window_s / dt))
    retreat_steps = max(1, round(settings.retreat_s / dt))
    tol = inst.tolerance_mm

    q = scenario.start.copy()
    history = [q.copy()]
    err = np.linalg.norm(fiber_positions(inst, scenario.base_xy, scenario.orient, q) - target_xy, axis=1)
    togo = _distance_to_go(settings, rho_reach, q, target, err)
    deadlock = _ProgressWindow(togo, window, settings.progress_mm)
    blocking = _ProgressWindow(togo, escape_window, settings.progress_mm)
    escape = _Escape(
        active=np.zeros(n, dtype=bool), goal=target.copy(), until=np.zeros(n, dtype=np.int64), count=np.zeros(n, dtype=np.int64)
    )
    stuck = np.zeros(n, dtype=bool)
    stuck_ever = np.zeros(n, dtype=bool)
    safety = HalvingStats()
    culling = _ClearanceBound(pairs, n, rho_motion)
    repulsion_active_steps = 0
    one_step = dt * speeds * (1.0 - 1e-9)
    t_grad = t_safe = 0.0
    step_count = 0
    non_finite_steps = 0
    for step_count in range(1, max_steps + 1):
        t0 = time.perf_counter()
        g_rep, clear0 = _repulsion_gradient(scenario, model, q, settings.lambda_repel, settings.potential, culling)
        goal = np.where(escape.active[:, None], escape.goal, target)
        if settings.attraction == "joint":
            g_att = 2.0 * settings.lambda_attract * rho_reach**2 * (q - goal)
        else:
            goal_xy = np.where(escape.active[:, None], fiber_positions(inst, scenario.base_xy, scenario.orient, goal), target_xy)
            p = fiber_positions(inst, scenario.base_xy, scenario.orient, q)
            jac = fiber_jacobian(inst, scenario.orient, q)
            g_att = 2.0 * settings.lambda_attract * np.einsum("nij,ni->nj", jac, p - goal_xy)
        omega = -(g_att + g_rep)
        over = (np.abs(omega) / speeds).max(axis=1)
        omega = omega / np.maximum(over, 1.0)[:, None]
        step = dt * omega
        free = ~np.any(g_rep != 0.0, axis=1)
        repulsion_active_steps += int(np.sum(~free))
        snap = free & ~escape.active & np.all(np.abs(target - q) <= one_step, axis=1)
        step[snap] = (target - q)[snap]
        step = np.clip(q + step, lim[:, 0], lim[:, 1]) - q
        snap_step = step[snap]
        bad_step = ~np.isfinite(step).all(axis=1)  # a non-finite gradient holds the positioner
        if bad_step.any():
            step[bad_step] = 0.0
            non_finite_steps += int(bad_step.sum())
        t1 = time.perf_counter()
        step = halve_steps(scenario, pairs, q, step, clear0, settings.safety_margin_mm, settings.safety_motion_factor,
                           settings.max_halvings, rho_motion, safety)
        t2 = time.perf_counter()
        t_grad += t1 - t0
        t_safe += t2 - t1
        q = q + step
        culling.moved(step)
        # A snap step that was executed in full lands exactly on the target joints.
        landed = np.flatnonzero(snap)[np.all(step[snap] == snap_step, axis=1)]
        q[landed] = target[landed]
        history.append(q.copy())

        err = np.linalg.norm(fiber_positions(inst, scenario.base_xy, scenario.orient, q) - target_xy, axis=1)
        reached = err <= tol
        togo = _distance_to_go(settings, rho_reach, q, target, err)
        deadlock.update(togo)
        blocking.update(togo)
        ended = np.flatnonzero(escape.active & (escape.until <= step_count))
        if len(ended):
            escape.active[ended] = False
            deadlock.reset(ended, togo)
            blocking.reset(ended, togo)
        if settings.deadlock_escape == "retreat":
            started = _start_retreats(
                escape, blocking.stuck(), reached, pairs, clear0, settings.envelope_mm,
                np.where(reached, -1.0, initial_move), scenario.ids, q, fold_beta, step_count, retreat_steps, settings.max_retreats,
            )
            if len(started):
                deadlock.reset(started, togo)
                blocking.reset(started, togo)
        settled = ~escape.active & deadlock.stuck()
        stuck = ~reached & settled
        stuck_ever |= stuck
        if progress is not None and step_count % 50 == 0:
            progress(min(1.0, step_count / max_steps))
        # Done when every positioner sits exactly on its target joints or cannot progress
        # (a reached one held off its exact target by a neighbour, or a deadlocked one).
        if np.all(np.all(q == target, axis=1) | settled):
            break

    reached = err <= tol
    outcome = outcome_labels(scenario, q, stuck)
    joints = np.stack(history)
    times = np.arange(len(joints)) * dt
    if progress is not None:
        progress(1.0)
    stats: dict[str, Any] = {
        "n_steps": step_count,
        "duration_s": float(times[-1]),
        "time_limit_s": float(time_limit),
        "time_limit_hit": bool(step_count == max_steps and not np.all(np.all(q == target, axis=1) | settled)),
        "lower_bound_s": lower,
        "deadlock_window_steps": window,
        "n_reached": int(reached.sum()),
        "n_deadlocked": int(np.sum(outcome == "deadlocked")),
        "n_unfinished": int(np.sum(outcome == "unfinished")),
        "n_ever_stuck": int(stuck_ever.sum()),
        "non_finite_steps_held": non_finite_steps,
        "retreats": escape.started,
        "safety_interventions": safety.interventions,
        "safety_held_steps": safety.held,
        "safety_iterations": safety.iterations,
        "repulsion_active_positioner_steps": repulsion_active_steps,
        "n_pairs": len(pairs),
        "gradient_time_s": t_grad,
        "safety_time_s": t_safe,
        "loop_wall_s": time.perf_counter() - t_wall,
        "convergence_condition_holds": convergence_condition(
            inst, settings.lambda_attract, max(settings.lambda_repel, 1e-300), settings.envelope_mm
        ).holds,
    }
    warnings = []
    short = int(np.sum(scenario.has_target & ~reached))
    if short:
        warnings.append(
            f"dnf: {short} of {int(scenario.has_target.sum())} positioners did not reach their targets "
            f"({stats['n_deadlocked']} deadlocked, {stats['n_unfinished']} still moving at the time limit of {time_limit:.2f} s)"
        )
    if non_finite_steps:
        warnings.append(f"dnf: {non_finite_steps} non-finite step(s) were held (a positioner at a singular configuration)")
    return PlanResult(
        scenario=scenario,
        trajectory=Trajectory(times, joints),
        outcome=outcome,
        planner="dnf",
        settings=dataclasses.asdict(settings),
        stats=stats,
        warnings=tuple(warnings),
    )
