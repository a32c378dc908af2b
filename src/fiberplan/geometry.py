"""Capsule geometry: segment-segment distances between neighbouring positioners and their gradients.

The collision model (``formulations/collision_geometry.md``): every positioner carries the
instrument's capsules, each a segment along one arm plus a radius, on a layer. Capsules
``A`` of positioner ``i`` and ``B`` of positioner ``j`` on the same layer are separated by

.. math:: g_{ij}^{AB}(q_i, q_j) = \\min_{s, t \\in [0, 1]} \\| A(s; q_i) - B(t; q_j) \\| - (r_A + r_B)

and collide when ``g < 0``. Everything here is vectorised over pairs (and, for clearances,
over any leading time axes) with numpy.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from fiberplan import capsule_kernels
from fiberplan.instrument import Instrument
from fiberplan.kinematics import straight_path

_EPS = 1e-12  # distances below this (mm) count as contact for gradients


def point_extents(instrument: Instrument) -> np.ndarray:
    """``[rho_alpha, rho_beta]``: the farthest capsule point from the base and from the elbow (mm)."""
    return np.array([instrument.alpha_point_extent_mm, instrument.beta_point_extent_mm])


def motion_bound(rho: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """The motion bound: farthest any capsule point moves over the linear joint moves ``dq``
    (``(..., 2)`` rad), in mm, with ``rho`` from :func:`point_extents`.

    .. math:: M = \\rho_\\alpha |\\Delta\\alpha| + \\rho_\\beta |\\Delta\\beta|

    The one bound every planner, the safety layer and the verifier use.
    """
    return np.abs(dq) @ rho


def step_motion_mm(instrument: Instrument, dt_s: float) -> float:
    """Largest distance a capsule point moves in one step of ``dt_s`` at full speed (mm)."""
    return float(motion_bound(point_extents(instrument), instrument.speeds_rad_s) * dt_s)


def default_safety_margin_mm(instrument: Instrument) -> float:
    """The smallest clearance the planners' safety layers keep by default: a tenth of the step
    motion of one control period (:func:`step_motion_mm`), rounded to 0.1 um. The generated
    starts keep at least this much (:func:`fiberplan.generate.make_scenario`)."""
    return round(0.1 * step_motion_mm(instrument, instrument.control_dt_s), 4)


@functools.lru_cache(maxsize=32)
def capsule_tables(instrument: Instrument) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-capsule arrays ``(on_alpha, start_mm, end_mm)`` (along the arm) and the checked
    ``combos (K, 2)`` with their radii sums ``(K,)``, computed once per instrument."""
    caps = instrument.capsules
    on_alpha = np.array([c.arm == "alpha" for c in caps])
    start_mm = np.array([c.start_mm for c in caps])
    end_mm = np.array([c.end_mm for c in caps])
    combos = np.array(instrument.capsule_pairs, dtype=np.int64).reshape(-1, 2)
    radii = np.array([c.radius_mm for c in caps])
    for arr in (on_alpha, start_mm, end_mm, combos, radii):
        arr.flags.writeable = False
    return on_alpha, start_mm, end_mm, combos, radii[combos[:, 0]] + radii[combos[:, 1]]


@functools.lru_cache(maxsize=32)
def _lateral(instrument: Instrument) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-capsule offsets ``(start_y_mm, end_y_mm)`` to the arm's left, or ``None`` when every
    capsule lies on its arm's axis (the fast path, unchanged)."""
    start_y = np.array([c.start_y_mm for c in instrument.capsules])
    end_y = np.array([c.end_y_mm for c in instrument.capsules])
    if not (np.any(start_y) or np.any(end_y)):
        return None
    return start_y, end_y


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
    on_alpha, start_mm, end_mm, _, _ = capsule_tables(instrument)
    a = joints[..., 0] + orient
    ab = a + joints[..., 1]
    lead = np.broadcast_shapes(a.shape, base_xy.shape[:-1])
    # numpy's cosines and sines (as capsule_coordinates takes them), then one compiled loop
    # instead of a dozen (..., N, C) temporaries: the same numbers.
    trig = [np.ascontiguousarray(np.broadcast_to(x, lead), dtype=np.float64).reshape(-1) for x in (np.cos(a), np.sin(a), np.cos(ab), np.sin(ab))]
    base = [np.ascontiguousarray(np.broadcast_to(base_xy[..., k], lead), dtype=np.float64).reshape(-1) for k in (0, 1)]
    lateral = _lateral(instrument)
    start_y, end_y = lateral if lateral is not None else (start_mm, end_mm)
    start = np.empty((len(trig[0]), len(start_mm), 2))
    end = np.empty_like(start)
    capsule_kernels.capsule_ends(*trig, *base, float(instrument.alpha_arm_mm), on_alpha, start_mm, end_mm, lateral is not None,
                                 start_y, end_y, start, end)
    return start.reshape(*lead, len(start_mm), 2), end.reshape(*lead, len(start_mm), 2)


def capsule_coordinates(
    instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`capsule_segments` as four ``(..., N, C)`` arrays ``start_x, start_y, end_x,
    end_y`` (the same values, without stacking them)."""
    on_alpha, start_mm, end_mm, _, _ = capsule_tables(instrument)
    a = joints[..., 0] + orient
    ab = a + joints[..., 1]
    cos_a, sin_a = np.cos(a), np.sin(a)
    base_x, base_y = base_xy[..., 0], base_xy[..., 1]
    # Per capsule (last axis): the joint it hangs from and the direction of its arm.
    origin_x = np.where(on_alpha, base_x[..., None], (base_x + instrument.alpha_arm_mm * cos_a)[..., None])
    origin_y = np.where(on_alpha, base_y[..., None], (base_y + instrument.alpha_arm_mm * sin_a)[..., None])
    dir_x = np.where(on_alpha, cos_a[..., None], np.cos(ab)[..., None])
    dir_y = np.where(on_alpha, sin_a[..., None], np.sin(ab)[..., None])
    lateral = _lateral(instrument)
    if lateral is None:
        return origin_x + start_mm * dir_x, origin_y + start_mm * dir_y, origin_x + end_mm * dir_x, origin_y + end_mm * dir_y
    start_y, end_y = lateral  # to the left: the direction turned by +90 degrees, (-dir_y, dir_x)
    return (origin_x + start_mm * dir_x - start_y * dir_y, origin_y + start_mm * dir_y + start_y * dir_x,
            origin_x + end_mm * dir_x - end_y * dir_y, origin_y + end_mm * dir_y + end_y * dir_x)


def _flat_rows(*points: np.ndarray) -> tuple[list[np.ndarray], tuple[int, ...]]:
    """Point arrays ``(..., 2)`` broadcast together, as contiguous float64 rows ``(M, 2)`` for the
    compiled loops, and the leading shape to give their results back."""
    arrays = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in points))
    return [np.ascontiguousarray(a).reshape(-1, 2) for a in arrays], arrays[0].shape[:-1]


def segment_distance(
    p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Distance between segments ``[p0, p1]`` and ``[q0, q1]`` in the plane (arrays ``(..., 2)``).

    In two dimensions two segments that do not cross are closest at an end point of one of
    them, so

    .. math:: d = \begin{cases} 0 & \text{the segments cross} \\
        \min(d(p_0, Q), d(p_1, Q), d(q_0, P), d(q_1, P)) & \text{otherwise} \end{cases}

    which, unlike the 3-D closest-approach formula, stays exact for (nearly) parallel and
    zero-length segments. Vectorised over leading axes; ties go to the first candidate in the
    order above.

    Returns:
        ``(distance, s, t)``: closest points are ``p0 + s (p1 - p0)`` and ``q0 + t (q1 - q0)``.
    """
    flat, shape = _flat_rows(p0, p1, q0, q1)
    dist, s, t = np.empty(len(flat[0])), np.empty(len(flat[0])), np.empty(len(flat[0]))
    capsule_kernels.segment_distances(*flat, dist, s, t)  # one compiled loop, numpy's arithmetic (tested bit for bit)
    return dist.reshape(shape), s.reshape(shape), t.reshape(shape)


def segment_distance_only(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """The distance of :func:`segment_distance` alone, bit for bit (squared distances compared,
    one square root: ``sqrt`` is monotone and correctly rounded), without the closest points'
    parameters, for the searches that need only the distance. (A NaN among the candidates gives
    NaN here, as ``np.minimum`` does; :func:`segment_distance` keeps the first candidate it cannot
    compare.)"""
    flat, shape = _flat_rows(p0, p1, q0, q1)
    dist = np.empty(len(flat[0]))
    capsule_kernels.segment_distances_only(*flat, dist)
    return dist.reshape(shape)


def combo_clearances(
    instrument: Instrument, p_start: np.ndarray, p_end: np.ndarray, q_start: np.ndarray, q_end: np.ndarray,
    smallest: bool = False, exact_below: float | None = None,
) -> np.ndarray:
    """Clearances ``(..., K)`` of the capsule combinations between two positioners' capsules.

    The same values as ``segment_distance(p[..., ca, :], q[..., cb, :])[0] - radii`` (``ca, cb,
    radii`` from :func:`capsule_tables`), for planners' searches: only the distance. The capsule
    arrays are ``(..., C, 2)`` with broadcastable leading axes. With ``smallest``, only the
    smallest clearance over the combinations, shape ``(...)``, each combination by the cheapest
    formula its capsule shapes allow (:func:`smallest_clearance`); then, on an instrument with polygon zones,
    ``exact_below`` (see :func:`fiberplan.zones.smallest`) skips the exact distances of zone
    pairs whose enclosing discs keep at least that much clearance: the result still decides
    ``>= t`` exactly for every threshold ``t <= exact_below``.
    """
    if instrument.polygons:
        from fiberplan import zones

        if smallest:
            if exact_below is None:
                return zones.smallest(instrument, p_start, p_end, q_start, q_end)
            return zones.smallest(instrument, p_start, p_end, q_start, q_end, exact_below)
        lead = np.broadcast_shapes(p_start.shape[:-2], q_start.shape[:-2])
        c = p_start.shape[-2]
        flat = [np.broadcast_to(a, (*lead, c, 2)).reshape(-1, c, 2) for a in (p_start, p_end, q_start, q_end)]
        return zones.clearances(instrument, *flat)[0].reshape(*lead, -1)
    _, _, _, combos, radii = capsule_tables(instrument)
    if not smallest:
        ca, cb = combos[:, 0], combos[:, 1]
        return segment_distance(p_start[..., ca, :], p_end[..., ca, :], q_start[..., cb, :], q_end[..., cb, :])[0] - radii
    lead = np.broadcast_shapes(p_start.shape[:-2], q_start.shape[:-2])
    p_rows, q_rows = (np.arange(int(np.prod(a.shape[:-2], dtype=np.int64))).reshape(a.shape[:-2]) for a in (p_start, q_start))
    c = p_start.shape[-2]
    return smallest_clearance(instrument, p_start.reshape(-1, c, 2), p_end.reshape(-1, c, 2), np.broadcast_to(p_rows, lead),
                              q_start.reshape(-1, c, 2), q_end.reshape(-1, c, 2), np.broadcast_to(q_rows, lead))


def smallest_clearance(
    instrument: Instrument, p_start: np.ndarray, p_end: np.ndarray, p_index: np.ndarray,
    q_start: np.ndarray, q_end: np.ndarray, q_index: np.ndarray,
) -> np.ndarray:
    """Smallest clearance (mm) over the capsule combinations of configurations taken by index.

    ``combo_clearances(instrument, p_start[p_index], p_end[p_index], q_start[q_index],
    q_end[q_index], smallest=True)`` bit for bit, without the gathered copies.

    Args:
        instrument: a capsule instrument (no polygon zones).
        p_start, p_end: ``(P, C, 2)`` capsule end points of ``P`` configurations of one side.
        p_index: integer indices into the first axis of ``p_*``, any shape.
        q_start, q_end: ``(Q, C, 2)`` the other side's.
        q_index: indices into ``q_*``, broadcastable with ``p_index``.

    Returns:
        The clearances, shaped as ``p_index`` and ``q_index`` broadcast.

    Raises:
        ValueError: an instrument with polygon zones, or an index outside its table.
    """
    if instrument.polygons:
        raise ValueError(f"{instrument.name}: smallest_clearance is for capsule instruments; use geometry.combo_clearances")
    _, start_mm, end_mm, combos, radii = capsule_tables(instrument)
    ip, iq = np.broadcast_arrays(np.asarray(p_index, dtype=np.int64), np.asarray(q_index, dtype=np.int64))
    shape = ip.shape
    ip, iq = ip.ravel(), iq.ravel()
    for name, index, table in (("p_index", ip, p_start), ("q_index", iq, q_start)):
        if index.size and (int(index.min()) < 0 or int(index.max()) >= len(table)):  # the compiled loop checks no bounds
            raise ValueError(f"{name} outside [0, {len(table)})")
    out = np.empty(ip.size)
    capsule_kernels.smallest_combo(p_start, p_end, ip, q_start, q_end, iq, combos, start_mm == end_mm, radii, out)
    return out.reshape(shape)


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
    if instrument.polygons:
        from fiberplan import zones

        return zones.pair_clearance(instrument, base_xy, orient, joints, pairs, gradient=gradient)
    _, _, _, combos, combo_radii = capsule_tables(instrument)
    used, inverse = np.unique(pairs, return_inverse=True)
    if len(used) < joints.shape[-2]:  # capsules of the positioners the pairs name, only
        base_xy, orient, joints = base_xy[used], orient[used], joints[..., used, :]
        pairs = inverse.reshape(pairs.shape)
    start, end = capsule_segments(instrument, base_xy, orient, joints)
    ii, jj = pairs[:, 0], pairs[:, 1]
    ca, cb = combos[:, 0], combos[:, 1]
    # (..., P, K, 2)
    p0 = start[..., ii[:, None], ca[None, :], :]
    p1 = end[..., ii[:, None], ca[None, :], :]
    q0 = start[..., jj[:, None], cb[None, :], :]
    q1 = end[..., jj[:, None], cb[None, :], :]
    dist, s, t = segment_distance(p0, p1, q0, q1)
    clearance = dist - combo_radii
    if not gradient:
        return PairClearance(clearance=clearance, distance=dist)
    if joints.ndim != 2:
        raise ValueError("gradients are computed for one configuration (joints of shape (N, 2))")
    grad_i, grad_j = joint_gradients(instrument, base_xy, orient, joints, pairs, (p0, p1, q0, q1), s, t, dist, dist > _EPS)
    return PairClearance(clearance=clearance, distance=dist, grad_i=grad_i, grad_j=grad_j)


def joint_gradients(
    instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray, pairs: np.ndarray,
    ends: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], s: np.ndarray, t: np.ndarray, dist: np.ndarray, valid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Gradients ``(P, K, 2)`` of the clearances with respect to ``i``'s and ``j``'s joints (the
    envelope theorem of :func:`pair_clearance`), from the combos' segment ends ``(p0, p1, q0, q1)``,
    the closest points' parameters ``s``, ``t`` and distances; zero where ``valid`` is false."""
    on_alpha, _, _, combos, _ = capsule_tables(instrument)
    ii, jj = pairs[:, 0], pairs[:, 1]
    ca, cb = combos[:, 0], combos[:, 1]
    p0, p1, q0, q1 = ends
    xi = p0 + s[..., None] * (p1 - p0)
    xj = q0 + t[..., None] * (q1 - q0)
    normal = (xi - xj) / np.maximum(dist, _EPS)[..., None]
    normal = np.where(valid[..., None], normal, 0.0)
    elbow = base_xy + instrument.alpha_arm_mm * np.stack(
        [np.cos(joints[:, 0] + orient), np.sin(joints[:, 0] + orient)], axis=-1
    )
    on_beta = ~on_alpha
    grad_i = np.empty((*dist.shape, 2))
    grad_j = np.empty((*dist.shape, 2))
    grad_i[..., 0] = np.einsum("pki,pki->pk", normal, _perp(xi - base_xy[ii][:, None, :]))
    grad_i[..., 1] = np.einsum("pki,pki->pk", normal, _perp(xi - elbow[ii][:, None, :])) * on_beta[ca][None, :]
    grad_j[..., 0] = -np.einsum("pki,pki->pk", normal, _perp(xj - base_xy[jj][:, None, :]))
    grad_j[..., 1] = -np.einsum("pki,pki->pk", normal, _perp(xj - elbow[jj][:, None, :])) * on_beta[cb][None, :]
    return grad_i, grad_j


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
    m = len(joints_i)
    start, end = capsule_segments(  # both sides in one call: these arrays are small
        instrument, np.concatenate([base_i, base_j]), np.concatenate([orient_i, orient_j]), np.concatenate([joints_i, joints_j])
    )
    return segment_clearances(instrument, start[:m], end[:m], start[m:], end[m:])


def segment_clearances(instrument: Instrument, start_i: np.ndarray, end_i: np.ndarray, start_j: np.ndarray, end_j: np.ndarray) -> np.ndarray:
    """:func:`clearance_between` from the capsule segments of row-matched positioners
    (:func:`capsule_segments`, ``(M, C, 2)`` each): for callers that keep the segments."""
    _, _, _, combos, combo_radii = capsule_tables(instrument)
    if instrument.polygons:
        from fiberplan import zones

        return zones.clearances(instrument, start_i, end_i, start_j, end_j)[0]
    ca, cb = combos[:, 0], combos[:, 1]
    dist, _, _ = segment_distance(start_i[:, ca], end_i[:, ca], start_j[:, cb], end_j[:, cb])
    return dist - combo_radii


def clearance_rows(
    instrument: Instrument, base_i: np.ndarray, orient_i: np.ndarray, joints_i: np.ndarray, base_j: np.ndarray,
    orient_j: np.ndarray, joints_j: np.ndarray,
) -> np.ndarray:
    """:func:`clearance_between` for the planners' safety layers, ``(M, 2)`` joints row by row:
    the same values bit for bit, from :func:`capsule_segments`' compiled ends and one compiled loop
    over the combinations (:func:`capsule_kernels.row_clearances`), without the broadcasting and
    gathered copies around them: a safety layer checks a few rows at a step, thousands of steps
    on small groups. Instruments with polygon zones go to :func:`clearance_between`. (The verifier
    keeps :func:`clearance_between`.)"""
    if instrument.polygons or len(joints_i) == 0:
        return clearance_between(instrument, base_i, orient_i, joints_i, base_j, orient_j, joints_j)
    _, _, _, combos, combo_radii = capsule_tables(instrument)
    start, end = capsule_ends_rows(instrument, np.concatenate([base_i, base_j]), np.concatenate([orient_i, orient_j]),
                                   np.concatenate([joints_i, joints_j]))
    out = np.empty((len(joints_i), len(combos)))
    capsule_kernels.row_clearances(start, end, combos[:, 0], combos[:, 1], combo_radii, out)
    return out


def capsule_ends_rows(instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The capsule ends ``(M, C, 2)`` (start, end) of ``(M, 2)`` joints as :func:`capsule_segments`
    places them, from numpy's cosines and sines and :func:`capsule_kernels.capsule_ends` (for
    :func:`clearance_rows` and :func:`indexed_clearances`; a polygon zone's edges are capsules too)."""
    on_alpha, start_mm, end_mm, _, _ = capsule_tables(instrument)
    a = joints[:, 0] + orient
    ab = a + joints[:, 1]
    trig = [np.ascontiguousarray(x, dtype=np.float64) for x in (np.cos(a), np.sin(a), np.cos(ab), np.sin(ab))]
    lateral = _lateral(instrument)
    start_y, end_y = lateral if lateral is not None else (start_mm, end_mm)
    start = np.empty((len(joints), len(start_mm), 2))
    end = np.empty_like(start)
    capsule_kernels.capsule_ends(*trig, np.ascontiguousarray(base_xy[:, 0], dtype=np.float64), np.ascontiguousarray(base_xy[:, 1], dtype=np.float64),
                                 float(instrument.alpha_arm_mm), on_alpha, start_mm, end_mm, lateral is not None, start_y, end_y, start, end)
    return start, end


def indexed_clearances(instrument: Instrument, start: np.ndarray, end: np.ndarray, i_index: np.ndarray, j_index: np.ndarray) -> np.ndarray:
    """``(M,)``: for each pair, the smallest of :func:`clearance_rows`' values (bit for bit) over
    the combinations, of the positioner whose capsule ends (:func:`capsule_ends_rows`) are row
    ``i_index[m]`` against row ``j_index[m]`` (polygon zones: :func:`fiberplan.zones.indexed_clearances`)."""
    if instrument.polygons:
        from fiberplan import zones

        return zones.indexed_clearances(instrument, start, end, i_index, j_index)
    _, _, _, combos, combo_radii = capsule_tables(instrument)
    out = np.empty(len(i_index))
    capsule_kernels.indexed_smallest(start, end, np.ascontiguousarray(i_index, dtype=np.int64), np.ascontiguousarray(j_index, dtype=np.int64),
                                     combos[:, 0], combos[:, 1], combo_radii, out)
    return out


def min_pair_clearance(
    instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray, pairs: np.ndarray
) -> np.ndarray:
    """Smallest clearance over capsule combinations for each pair, shape ``(..., P)``."""
    if len(pairs) == 0:
        return np.zeros((*joints.shape[:-2], 0))
    return pair_clearance(instrument, base_xy, orient, joints, pairs).clearance.min(axis=-1)


def path_clearance(
    scenario: Any, mover: np.ndarray, other: np.ndarray, q_from: np.ndarray, q_to: np.ndarray, q_other: np.ndarray,
    step_rad: np.ndarray, stride: int = 2,
) -> np.ndarray:
    """Smallest clearance of ``mover`` along its saturated path ``q_from -> q_to`` to ``other`` held at ``q_other``.

    All arrays are row-matched (one row per directed pair); the path is sampled every ``stride``
    control steps and at its end.
    """
    if len(mover) == 0:
        return np.zeros(0)
    n_steps = int(np.ceil(np.max(np.abs(q_to - q_from) / step_rad, initial=0.0))) + 1
    path = straight_path(q_from, q_to, stride * step_rad, max(1, int(np.ceil(n_steps / stride))))  # (M, K, 2)
    k = path.shape[1]
    c = clearance_between(
        scenario.instrument,
        np.repeat(scenario.base_xy[mover], k, axis=0), np.repeat(scenario.orient[mover], k), path.reshape(-1, 2),
        np.repeat(scenario.base_xy[other], k, axis=0), np.repeat(scenario.orient[other], k), np.repeat(q_other, k, axis=0),
    ).min(axis=-1)
    return c.reshape(-1, k).min(axis=1)
