"""Compiled capsule distances (numba): the inner loops of :mod:`fiberplan.geometry`.

Two loops run here, each over rows of end points, with :mod:`fiberplan.geometry` shaping their
inputs and outputs:

- :func:`segment_distances`: :func:`fiberplan.geometry.segment_distance` (distance and the
  closest points' parameters), which every planner's constraints, the safety layers and the
  verifier read;
- :func:`segment_distances_only`: :func:`fiberplan.geometry.segment_distance_only`, the
  distance alone (the zones' exact edge distances, the mpc's detours);
- :func:`smallest_combo`: :func:`fiberplan.geometry.smallest_clearance`, the smallest clearance
  over an instrument's capsule combinations for configurations read by index from the start
  schedule's tables (:mod:`fiberplan.planners.mpc.schedule`), without numpy's gathered copies.

The arithmetic is numpy's, operation for operation and in the same order (the cheapest formula
each combination's shapes allow: point to point, point to segment, segment to segment closest at
an end point unless the segments cross). Compiled without ``fastmath``, numba fuses no
multiply-add and reorders nothing; ``sqrt`` and division are correctly rounded; the clamps keep a
NaN as ``np.minimum``/``np.maximum`` keep it. So the results are the numpy expressions' bit for
bit (``tests/test_geometry.py`` keeps them as references), and no trajectory changes: the 23 runs
of ``benchmarks/trajectory_hashes.py`` on DESI, ``moons-capsules`` and SDSS and 7 on MOONS' zones
were compared before and after. The loops release the GIL, as numpy's array operations do, so the
verifier's threads still run side by side.

Measured (``docs/results.md``, Scale): on MOONS 500 random seed 0 the start schedule's clearance
searches took 10.8 of 50 s (cProfile); the plan 0.78 x the time (SDSS 547 random 0.65 x). The
price is numba itself: about 100 MB more resident memory per process (its import and compiled
code), and about a second of compilation the first time (cached after, beside this file).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, error_model="numpy", inline="always")
def _point_segment_sq(px: float, py: float, ax: float, ay: float, dx: float, dy: float, dd: float) -> float:
    """:func:`fiberplan.geometry._point_segment_sq` for one point and one segment."""
    u = _unit(((px - ax) * dx + (py - ay) * dy) / dd)
    ex = px - (ax + u * dx)
    ey = py - (ay + u * dy)
    return ex * ex + ey * ey


@numba.njit(cache=True, error_model="numpy", inline="always")
def _unit(u: float) -> float:
    """``np.minimum(np.maximum(u, 0.0), 1.0)``, NaN kept as numpy keeps it."""
    if u < 0.0:
        u = 0.0
    if u > 1.0:
        u = 1.0
    return u


@numba.njit(cache=True, error_model="numpy", inline="always")
def _minimum(a: float, b: float) -> float:
    """``np.minimum(a, b)``: NaN if either is."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@numba.njit(cache=True, error_model="numpy", inline="always")
def _point_segment_sq_safe(px: float, py: float, ax: float, ay: float, dx: float, dy: float, nonzero: bool, safe_dd: float) -> float:
    """:func:`fiberplan.geometry._point_segment_sq_safe`'s squared distance, for one point and one segment."""
    u = _unit(((px - ax) * dx + (py - ay) * dy) / safe_dd) if nonzero else 0.0
    ex = px - (ax + u * dx)
    ey = py - (ay + u * dy)
    return ex * ex + ey * ey


@numba.njit(cache=True, error_model="numpy", inline="always")
def _point_segment(px: float, py: float, ax: float, ay: float, dx: float, dy: float, nonzero: bool, safe_dd: float) -> tuple[float, float]:
    """:func:`fiberplan.geometry.point_to_segment` for one point and one segment: ``(distance, u)``."""
    u = _unit(((px - ax) * dx + (py - ay) * dy) / safe_dd) if nonzero else 0.0
    ex = px - (ax + u * dx)
    ey = py - (ay + u * dy)
    return np.sqrt(ex * ex + ey * ey), u


@numba.njit(cache=True, error_model="numpy", nogil=True)
def segment_distances(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray,
                      dist: np.ndarray, s: np.ndarray, t: np.ndarray) -> None:  # pragma: no cover
    """:func:`fiberplan.geometry.segment_distance` of ``(M, 2)`` end points into ``dist``, ``s``,
    ``t`` ``(M,)``: the same candidates in the same order, a later one kept only where strictly
    closer, then the crossing segments at distance 0. (Compiled; tested bit for bit.)"""
    for m in range(p0.shape[0]):
        p0x, p0y, p1x, p1y = p0[m, 0], p0[m, 1], p1[m, 0], p1[m, 1]
        q0x, q0y, q1x, q1y = q0[m, 0], q0[m, 1], q1[m, 0], q1[m, 1]
        d1x, d1y, d2x, d2y = p1x - p0x, p1y - p0y, q1x - q0x, q1y - q0y
        a = d1x * d1x + d1y * d1y
        e = d2x * d2x + d2y * d2y
        a_nz, e_nz = a > 0.0, e > 0.0
        a_safe = a if a_nz else 1.0
        e_safe = e if e_nz else 1.0
        d, tt = _point_segment(p0x, p0y, q0x, q0y, d2x, d2y, e_nz, e_safe)
        ss = 0.0
        d_c, t_c = _point_segment(p1x, p1y, q0x, q0y, d2x, d2y, e_nz, e_safe)
        if d_c < d:
            d, ss, tt = d_c, 1.0, t_c
        d_c, s_c = _point_segment(q0x, q0y, p0x, p0y, d1x, d1y, a_nz, a_safe)
        if d_c < d:
            d, ss, tt = d_c, s_c, 0.0
        d_c, s_c = _point_segment(q1x, q1y, p0x, p0y, d1x, d1y, a_nz, a_safe)
        if d_c < d:
            d, ss, tt = d_c, s_c, 1.0
        rx, ry = q0x - p0x, q0y - p0y
        side_q0 = d1x * ry - d1y * rx
        side_q1 = d1x * (q1y - p0y) - d1y * (q1x - p0x)
        side_p0 = d2x * (-ry) - d2y * (-rx)
        side_p1 = d2x * (p1y - q0y) - d2y * (p1x - q0x)
        if side_q0 * side_q1 < 0.0 and side_p0 * side_p1 < 0.0:
            cross = d1x * d2y - d1y * d2x
            ss = (rx * d2y - ry * d2x) / cross
            tt = (rx * d1y - ry * d1x) / cross
            d = 0.0
        dist[m], s[m], t[m] = d, ss, tt


@numba.njit(cache=True, error_model="numpy", nogil=True)
def segment_distances_only(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray, dist: np.ndarray) -> None:  # pragma: no cover
    """:func:`fiberplan.geometry.segment_distance_only` of ``(M, 2)`` end points into ``dist``
    ``(M,)``: the smallest squared candidate (NaN if any is), one square root, 0 where they cross."""
    for m in range(p0.shape[0]):
        p0x, p0y, p1x, p1y = p0[m, 0], p0[m, 1], p1[m, 0], p1[m, 1]
        q0x, q0y, q1x, q1y = q0[m, 0], q0[m, 1], q1[m, 0], q1[m, 1]
        d1x, d1y, d2x, d2y = p1x - p0x, p1y - p0y, q1x - q0x, q1y - q0y
        a = d1x * d1x + d1y * d1y
        e = d2x * d2x + d2y * d2y
        a_safe = a if a > 0.0 else 1.0
        e_safe = e if e > 0.0 else 1.0
        sq = _minimum(
            _minimum(_point_segment_sq_safe(p0x, p0y, q0x, q0y, d2x, d2y, e > 0.0, e_safe),
                     _point_segment_sq_safe(p1x, p1y, q0x, q0y, d2x, d2y, e > 0.0, e_safe)),
            _minimum(_point_segment_sq_safe(q0x, q0y, p0x, p0y, d1x, d1y, a > 0.0, a_safe),
                     _point_segment_sq_safe(q1x, q1y, p0x, p0y, d1x, d1y, a > 0.0, a_safe)),
        )
        rx, ry = q0x - p0x, q0y - p0y
        if ((d1x * ry - d1y * rx) * (d1x * (q1y - p0y) - d1y * (q1x - p0x)) < 0.0) and (
                (d2x * (-ry) - d2y * (-rx)) * (d2x * (p1y - q0y) - d2y * (p1x - q0x)) < 0.0):
            dist[m] = 0.0
        else:
            dist[m] = np.sqrt(sq)


@numba.njit(cache=True, error_model="numpy", nogil=True)
def smallest_combo(p_start: np.ndarray, p_end: np.ndarray, p_index: np.ndarray, q_start: np.ndarray, q_end: np.ndarray,
                   q_index: np.ndarray, combos: np.ndarray, disc: np.ndarray, radii: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out[m]``: the smallest clearance of capsules ``p_*[p_index[m]]`` against ``q_*[q_index[m]]``.

    (Compiled: coverage does not see inside; its results are tested bit for bit.)"""
    for m in range(p_index.shape[0]):
        u = p_index[m]
        v = q_index[m]
        best = 0.0
        for k in range(combos.shape[0]):
            a = combos[k, 0]
            b = combos[k, 1]
            p0x, p0y = p_start[u, a, 0], p_start[u, a, 1]
            q0x, q0y = q_start[v, b, 0], q_start[v, b, 1]
            if disc[a] and disc[b]:
                dx, dy = p0x - q0x, p0y - q0y
                sq = dx * dx + dy * dy
            elif disc[a] or disc[b]:
                if disc[a]:  # p is the point, q the segment
                    px, py, ax, ay, ex, ey = p0x, p0y, q0x, q0y, q_end[v, b, 0], q_end[v, b, 1]
                else:
                    px, py, ax, ay, ex, ey = q0x, q0y, p0x, p0y, p_end[u, a, 0], p_end[u, a, 1]
                dx, dy = ex - ax, ey - ay
                sq = _point_segment_sq(px, py, ax, ay, dx, dy, dx * dx + dy * dy)
            else:  # closest at an end point unless they cross
                p1x, p1y, q1x, q1y = p_end[u, a, 0], p_end[u, a, 1], q_end[v, b, 0], q_end[v, b, 1]
                d1x, d1y, d2x, d2y = p1x - p0x, p1y - p0y, q1x - q0x, q1y - q0y
                d1, d2 = d1x * d1x + d1y * d1y, d2x * d2x + d2y * d2y
                s_p0 = _point_segment_sq(p0x, p0y, q0x, q0y, d2x, d2y, d2)
                s_p1 = _point_segment_sq(p1x, p1y, q0x, q0y, d2x, d2y, d2)
                s_q0 = _point_segment_sq(q0x, q0y, p0x, p0y, d1x, d1y, d1)
                s_q1 = _point_segment_sq(q1x, q1y, p0x, p0y, d1x, d1y, d1)
                sq = _minimum(_minimum(s_p0, s_p1), _minimum(s_q0, s_q1))
                rx, ry = q0x - p0x, q0y - p0y
                if ((d1x * ry - d1y * rx) * (d1x * (q1y - p0y) - d1y * (q1x - p0x)) < 0.0) and (
                        (d2x * (-ry) - d2y * (-rx)) * (d2x * (p1y - q0y) - d2y * (p1x - q0x)) < 0.0):
                    sq = 0.0
            c = np.sqrt(sq) - radii[k]
            best = c if k == 0 else _minimum(best, c)
        out[m] = best
