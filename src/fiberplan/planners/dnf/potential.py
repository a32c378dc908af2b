"""The decentralized navigation function of the ``dnf`` planner: potentials, their gradients, the
convergence condition of reference 000 (eq. 5), reference 002's ellipse distance, and the pair
culling that keeps a step O(N)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.geometry import pair_clearance
from fiberplan.instrument import Instrument
from fiberplan.kinematics import move_times
from fiberplan.planners.dnf.settings import _MIN_SEP2_FRACTION, DnfSettings, PotentialKind
from fiberplan.planners.safety import motion_bound
from fiberplan.scenario import Scenario

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
        if d <= 0.0:
            continue  # edges of unpadded polygon zones: eq. 5 assumes d > 0 and says nothing of them
        bound = convergence_bound(R, d + envelope_mm, d)
        if best is None or bound < best[0]:
            best = (bound, d + envelope_mm, d)
    ratio = lambda_attract / lambda_repel
    if best is None:
        return ConvergenceCheck(ratio=ratio, bound=math.nan, holds=False, R_mm=R, D_mm=math.nan, d_mm=0.0)
    return ConvergenceCheck(ratio=ratio, bound=best[0], holds=ratio < best[0], R_mm=R, D_mm=best[1], d_mm=best[2])


# ---------------------------------------------------------------------------------------------
# Potential gradients


def _gap_floor(d: np.ndarray) -> np.ndarray:
    """Floor of ``r^2 - d^2``: ``1e-4 d^2``, and for zones without a radius (``d = 0``, the
    sharp edges of polygon zones) ``1e-6 mm^2``, so that the slope stays finite at contact."""
    return np.where(d > 0.0, _MIN_SEP2_FRACTION * d * d, 1e-6)


def repulsion_slope(r: np.ndarray, d: np.ndarray, D: np.ndarray, potential: PotentialKind = "reference") -> np.ndarray:
    """Derivative ``d phi / d r`` of the repulsive term (zero for ``r >= D``).

    .. math::

        \\phi'_{ref}(r) = -\\frac{2 r (D^2 - d^2)}{(r^2 - d^2)^2}, \\qquad
        \\phi'_{smooth}(r) = -\\frac{2 r (D^2 - r^2) (D^2 + r^2 - 2 d^2)}{(r^2 - d^2)^2 (D^2 - d^2)}
        \\qquad (d < r < D)

    ``r^2 - d^2`` is floored (:func:`_gap_floor`) so that the slope stays finite at contact.
    """
    gap = np.maximum(r * r - d * d, _gap_floor(d))
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
    gap = np.maximum(r * r - d * d, _gap_floor(d))
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
