"""Capsule geometry: segment-segment distances between neighbouring positioners and their gradients.

The collision model (``formulations/collision_geometry.md``): every positioner carries the
instrument's capsules, each a segment along one arm plus a radius, on a layer. Capsules
``A`` of positioner ``i`` and ``B`` of positioner ``j`` on the same layer are separated by

.. math:: g_{ij}^{AB}(q_i, q_j) = \\min_{s, t \\in [0, 1]} \\| A(s; q_i) - B(t; q_j) \\| - (r_A + r_B)

and collide when ``g < 0``. Everything here is vectorised over pairs (and, for clearances,
over any leading time axes) with numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fiberplan.instrument import Instrument

_EPS = 1e-12  # distances below this (mm) count as contact for gradients


def capsule_segments(
    instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """End points of every capsule segment in the focal plane.

    Args:
        instrument: the positioner type.
        base_xy: ``(N, 2)`` base positions.
        orient: ``(N,)`` base orientations (rad).
        joints: ``(..., N, 2)`` joint angles (rad).

    Returns:
        ``(start, end)``, each of shape ``(..., N, C, 2)`` for the instrument's ``C`` capsules.
    """
    a = joints[..., 0] + orient
    ab = a + joints[..., 1]
    ua = np.stack([np.cos(a), np.sin(a)], axis=-1)
    uab = np.stack([np.cos(ab), np.sin(ab)], axis=-1)
    elbow = base_xy + instrument.alpha_arm_mm * ua
    starts, ends = [], []
    for capsule in instrument.capsules:
        origin, direction = (base_xy, ua) if capsule.arm == "alpha" else (elbow, uab)
        starts.append(origin + capsule.start_mm * direction)
        ends.append(origin + capsule.end_mm * direction)
    return np.stack(starts, axis=-2), np.stack(ends, axis=-2)


def _point_to_segment(p: np.ndarray, a: np.ndarray, d: np.ndarray, dd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from points ``p`` to segments ``a + u d`` (``dd = d . d``) and the parameter ``u``."""
    u = np.clip(np.einsum("...i,...i->...", p - a, d) / np.where(dd > 0.0, dd, 1.0), 0.0, 1.0)
    u = np.where(dd > 0.0, u, 0.0)
    diff = p - (a + u[..., None] * d)
    return np.sqrt(np.einsum("...i,...i->...", diff, diff)), u


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def segment_distance(
    p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Distance between segments ``[p0, p1]`` and ``[q0, q1]`` in the plane (arrays ``(..., 2)``).

    In two dimensions two segments that do not cross are closest at an end point of one of
    them, so

    .. math:: d = \begin{cases} 0 & \text{the segments cross} \\
        \min(d(p_0, Q), d(p_1, Q), d(q_0, P), d(q_1, P)) & \text{otherwise} \end{cases}

    which, unlike the 3-D closest-approach formula, stays exact for (nearly) parallel and
    zero-length segments. Vectorised over leading axes.

    Returns:
        ``(distance, s, t)``: closest points are ``p0 + s (p1 - p0)`` and ``q0 + t (q1 - q0)``.
    """
    d1 = p1 - p0
    d2 = q1 - q0
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    dist_p0, t_p0 = _point_to_segment(p0, q0, d2, e)
    dist_p1, t_p1 = _point_to_segment(p1, q0, d2, e)
    dist_q0, s_q0 = _point_to_segment(q0, p0, d1, a)
    dist_q1, s_q1 = _point_to_segment(q1, p0, d1, a)
    cand_d = np.stack([dist_p0, dist_p1, dist_q0, dist_q1])
    cand_s = np.stack([np.zeros_like(a), np.ones_like(a), s_q0, s_q1])
    cand_t = np.stack([t_p0, t_p1, np.zeros_like(e), np.ones_like(e)])
    best = np.argmin(cand_d, axis=0)[None]
    dist = np.take_along_axis(cand_d, best, axis=0)[0]
    s = np.take_along_axis(cand_s, best, axis=0)[0]
    t = np.take_along_axis(cand_t, best, axis=0)[0]
    # Proper crossing: each segment's end points lie strictly on both sides of the other.
    r = q0 - p0
    denom = _cross(d1, d2)
    side_q0, side_q1 = _cross(d1, r), _cross(d1, q1 - p0)
    side_p0, side_p1 = _cross(d2, -r), _cross(d2, p1 - q0)
    crossing = (side_q0 * side_q1 < 0.0) & (side_p0 * side_p1 < 0.0)
    safe = np.where(crossing, denom, 1.0)
    s = np.where(crossing, _cross(r, d2) / safe, s)
    t = np.where(crossing, _cross(r, d1) / safe, t)
    dist = np.where(crossing, 0.0, dist)
    return dist, s, t


@dataclass(frozen=True)
class PairClearance:
    """Clearances of the same-layer capsule combinations of positioner pairs.

    Attributes:
        clearance: ``(..., P, K)`` segment distance minus the sum of radii (mm); < 0 collides.
        distance: ``(..., P, K)`` segment distance (mm).
        grad_i: ``(P, K, 2)`` derivative of the clearance w.r.t. ``(alpha_i, beta_i)`` (mm/rad),
            or ``None`` when not asked for.
        grad_j: the same w.r.t. ``(alpha_j, beta_j)``.
    """

    clearance: np.ndarray
    distance: np.ndarray
    grad_i: np.ndarray | None = None
    grad_j: np.ndarray | None = None


def _perp(v: np.ndarray) -> np.ndarray:
    """Rotate ``(..., 2)`` vectors by +90 degrees: ``d/d angle`` of a rotated vector."""
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


def pair_clearance(
    instrument: Instrument,
    base_xy: np.ndarray,
    orient: np.ndarray,
    joints: np.ndarray,
    pairs: np.ndarray,
    *,
    gradient: bool = False,
) -> PairClearance:
    """Clearances between capsules of positioner pairs, optionally with joint gradients.

    Args:
        instrument: the positioner type (its ``capsule_pairs`` list the combinations ``K``).
        base_xy, orient: ``(N, 2)`` and ``(N,)`` base geometry.
        joints: ``(..., N, 2)`` joint angles; leading axes (e.g. time) are allowed when
            ``gradient`` is False.
        pairs: ``(P, 2)`` positioner indices ``(i, j)``.
        gradient: also return the gradient of each clearance.

    The gradient follows from the envelope theorem: with closest points ``x_i``, ``x_j`` and
    unit normal ``n = (x_i - x_j) / ||x_i - x_j||``,

    .. math::

        \\partial g / \\partial \\alpha_i = n \\cdot (x_i - b_i)^{\\perp}, \\qquad
        \\partial g / \\partial \\beta_i = n \\cdot (x_i - e_i)^{\\perp} \\;[\\text{beta-arm capsule, else } 0]

    and the same with ``-n`` for ``j`` (``b`` base, ``e`` elbow, ``v^perp`` = v rotated +90 deg).
    It is exact wherever the closest points are unique and the distance is positive.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    combos = np.array(instrument.capsule_pairs, dtype=np.int64).reshape(-1, 2)
    start, end = capsule_segments(instrument, base_xy, orient, joints)
    ii, jj = pairs[:, 0], pairs[:, 1]
    ca, cb = combos[:, 0], combos[:, 1]
    # (..., P, K, 2)
    p0 = start[..., ii[:, None], ca[None, :], :]
    p1 = end[..., ii[:, None], ca[None, :], :]
    q0 = start[..., jj[:, None], cb[None, :], :]
    q1 = end[..., jj[:, None], cb[None, :], :]
    dist, s, t = segment_distance(p0, p1, q0, q1)
    clearance = dist - _combo_radii(instrument)
    if not gradient:
        return PairClearance(clearance=clearance, distance=dist)
    if joints.ndim != 2:
        raise ValueError("gradients are computed for one configuration (joints of shape (N, 2))")
    xi = p0 + s[..., None] * (p1 - p0)
    xj = q0 + t[..., None] * (q1 - q0)
    normal = (xi - xj) / np.maximum(dist, _EPS)[..., None]
    normal = np.where((dist > _EPS)[..., None], normal, 0.0)
    elbow = base_xy + instrument.alpha_arm_mm * np.stack(
        [np.cos(joints[:, 0] + orient), np.sin(joints[:, 0] + orient)], axis=-1
    )
    on_beta = np.array([c.arm == "beta" for c in instrument.capsules])
    grad_i = np.empty((*dist.shape, 2))
    grad_j = np.empty((*dist.shape, 2))
    grad_i[..., 0] = np.einsum("pki,pki->pk", normal, _perp(xi - base_xy[ii][:, None, :]))
    grad_i[..., 1] = np.einsum("pki,pki->pk", normal, _perp(xi - elbow[ii][:, None, :])) * on_beta[ca][None, :]
    grad_j[..., 0] = -np.einsum("pki,pki->pk", normal, _perp(xj - base_xy[jj][:, None, :]))
    grad_j[..., 1] = -np.einsum("pki,pki->pk", normal, _perp(xj - elbow[jj][:, None, :])) * on_beta[cb][None, :]
    return PairClearance(clearance=clearance, distance=dist, grad_i=grad_i, grad_j=grad_j)


def _combo_radii(instrument: Instrument) -> np.ndarray:
    """Sum of radii of each same-layer capsule combination, shape ``(K,)``."""
    radii = np.array([c.radius_mm for c in instrument.capsules])
    combos = np.array(instrument.capsule_pairs, dtype=np.int64).reshape(-1, 2)
    return radii[combos[:, 0]] + radii[combos[:, 1]]


def clearance_between(
    instrument: Instrument,
    base_i: np.ndarray,
    orient_i: np.ndarray,
    joints_i: np.ndarray,
    base_j: np.ndarray,
    orient_j: np.ndarray,
    joints_j: np.ndarray,
) -> np.ndarray:
    """Clearances ``(M, K)`` between row-matched positioners ``i`` and ``j`` (all inputs ``(M, ...)``).

    The same quantity as :func:`pair_clearance`, for explicit configurations of each pair
    (the verifier uses it to probe instants between samples).
    """
    combos = np.array(instrument.capsule_pairs, dtype=np.int64).reshape(-1, 2)
    start_i, end_i = capsule_segments(instrument, base_i, orient_i, joints_i)
    start_j, end_j = capsule_segments(instrument, base_j, orient_j, joints_j)
    ca, cb = combos[:, 0], combos[:, 1]
    dist, _, _ = segment_distance(start_i[:, ca], end_i[:, ca], start_j[:, cb], end_j[:, cb])
    return dist - _combo_radii(instrument)


def min_pair_clearance(
    instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray, pairs: np.ndarray
) -> np.ndarray:
    """Smallest clearance over capsule combinations for each pair, shape ``(..., P)``."""
    if len(pairs) == 0:
        return np.zeros((*joints.shape[:-2], 0))
    return pair_clearance(instrument, base_xy, orient, joints, pairs).clearance.min(axis=-1)
