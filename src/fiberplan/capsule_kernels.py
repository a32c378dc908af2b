"""Compiled capsule distances (numba): the inner loops of :mod:`fiberplan.geometry`.

Each loop runs over rows of end points (or of configurations read by index), with the calling
module shaping its inputs and outputs:

- :func:`segment_distances`: :func:`fiberplan.geometry.segment_distance` (distance and the
  closest points' parameters), which every planner's constraints, the safety layers and the
  verifier read;
- :func:`segment_distances_only`: :func:`fiberplan.geometry.segment_distance_only`, the
  distance alone (the zones' exact edge distances, the mpc's detours);
- :func:`capsule_ends`: :func:`fiberplan.geometry.capsule_segments` after numpy's cosines and
  sines (the planners' calls; the verifier keeps numpy's :func:`~fiberplan.geometry.capsule_coordinates`);
- :func:`zone_clearances`, :func:`zone_smallest`: :func:`fiberplan.zones.clearances` and
  :func:`fiberplan.zones.smallest`, MOONS' own zones (discs' bounds, exact edge distances near,
  the depth of a zone inside a polygon);
- :func:`detour_clearances`: the mpc's detour grids (:mod:`fiberplan.planners.mpc.detour`), a
  positioner's every joint cell against a neighbour held still (with MOONS' zones, 134 edge
  combinations per pair);
- :func:`smallest_combo`: :func:`fiberplan.geometry.smallest_clearance`, the smallest clearance
  over an instrument's capsule combinations for configurations read by index from the start
  schedule's tables (:mod:`fiberplan.planners.mpc.schedule`), without numpy's gathered copies;
- :func:`row_clearances`: :func:`fiberplan.geometry.clearance_rows`, the safety layers' pair
  clearances row by row from :func:`capsule_ends` (a safety layer checks a few rows at a time,
  thousands of times a run on small groups);
- :func:`indexed_smallest`: :func:`fiberplan.geometry.indexed_clearances`, the same values'
  smallest per pair, for pairs read by index from capsule ends placed once (group moves:
  :mod:`fiberplan.planners.coordination.groups`), and :func:`zone_indexed_clearances` the same
  for MOONS' own zones (:func:`fiberplan.zones.indexed_clearances`).

The arithmetic is numpy's, operation for operation and in the same order (the cheapest formula
each combination's shapes allow: point to point, point to segment, segment to segment closest at
an end point unless the segments cross). Compiled without ``fastmath``, numba fuses no
multiply-add and reorders nothing; ``sqrt`` and division are correctly rounded; the clamps keep a
NaN as ``np.minimum``/``np.maximum`` keep it. So the results are the numpy expressions' bit for
bit (``tests/test_geometry.py``, ``test_zones.py`` and ``test_mpc_detour.py`` keep them as
references), and no trajectory changes: the 23 runs of ``benchmarks/trajectory_hashes.py`` on
DESI, ``moons-capsules`` and SDSS and 8 on MOONS' zones were compared before and after. The
loops release the GIL, as numpy's array operations do, so the verifier's threads still run side
by side.

Measured (``docs/results.md``, Speed; whole ``fiberplan plan`` processes against ``7e50051``):
SDSS 547 random 0.62 x the time, ``moons-capsules`` 500 random 0.70 x, MOONS' zones 61 unfold
0.40 x and 7 random 0.36 x (with less memory: numpy's temporaries are gone), DESI 5,000 0.97 x.
The price is numba itself: about 100 MB more resident memory per process (its import and compiled
code), and a few seconds of compilation the first time (cached after, beside this file).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, error_model="numpy", inline="always")
def _crosses(p0x: float, p0y: float, p1x: float, p1y: float, q0x: float, q0y: float, q1x: float, q1y: float) -> bool:
    """Whether the segments cross properly: each one's end points strictly on both sides of the other."""
    d1x, d1y, d2x, d2y = p1x - p0x, p1y - p0y, q1x - q0x, q1y - q0y
    rx, ry = q0x - p0x, q0y - p0y
    return ((d1x * ry - d1y * rx) * (d1x * (q1y - p0y) - d1y * (q1x - p0x)) < 0.0) and (
        (d2x * (-ry) - d2y * (-rx)) * (d2x * (p1y - q0y) - d2y * (p1x - q0x)) < 0.0)


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


@numba.njit(cache=True, error_model="numpy", inline="always")
def _segment_pair(p0x: float, p0y: float, p1x: float, p1y: float, q0x: float, q0y: float, q1x: float, q1y: float) -> tuple[float, float, float]:
    """One segment pair's ``(distance, s, t)`` as :func:`segment_distances` computes it."""
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
    if _crosses(p0x, p0y, p1x, p1y, q0x, q0y, q1x, q1y):
        rx, ry = q0x - p0x, q0y - p0y
        cross = d1x * d2y - d1y * d2x
        ss = (rx * d2y - ry * d2x) / cross
        tt = (rx * d1y - ry * d1x) / cross
        d = 0.0
    return d, ss, tt


@numba.njit(cache=True, error_model="numpy", nogil=True)
def segment_distances(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray,
                      dist: np.ndarray, s: np.ndarray, t: np.ndarray) -> None:  # pragma: no cover
    """:func:`fiberplan.geometry.segment_distance` of ``(M, 2)`` end points into ``dist``, ``s``,
    ``t`` ``(M,)``: the same candidates in the same order, a later one kept only where strictly
    closer, then the crossing segments at distance 0. (Compiled; tested bit for bit.)"""
    for m in range(p0.shape[0]):
        dist[m], s[m], t[m] = _segment_pair(p0[m, 0], p0[m, 1], p1[m, 0], p1[m, 1], q0[m, 0], q0[m, 1], q1[m, 0], q1[m, 1])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _distance_only(p0x: float, p0y: float, p1x: float, p1y: float, q0x: float, q0y: float, q1x: float, q1y: float) -> float:
    """One segment pair's distance as :func:`segment_distances_only` computes it."""
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
    return 0.0 if _crosses(p0x, p0y, p1x, p1y, q0x, q0y, q1x, q1y) else np.sqrt(sq)


@numba.njit(cache=True, error_model="numpy", nogil=True)
def segment_distances_only(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray, dist: np.ndarray) -> None:  # pragma: no cover
    """:func:`fiberplan.geometry.segment_distance_only` of ``(M, 2)`` end points into ``dist``
    ``(M,)``: the smallest squared candidate (NaN if any is), one square root, 0 where they cross."""
    for m in range(p0.shape[0]):
        dist[m] = _distance_only(p0[m, 0], p0[m, 1], p1[m, 0], p1[m, 1], q0[m, 0], q0[m, 1], q1[m, 0], q1[m, 1])


@numba.njit(cache=True, error_model="numpy", nogil=True)
def detour_clearances(a: np.ndarray, d: np.ndarray, nonzero: np.ndarray, safe_dd: np.ndarray, combo_capsule: np.ndarray,
                      base_x: float, base_y: float, reach: np.ndarray, radii: np.ndarray, cutoff: float,
                      seg_start: np.ndarray, seg_end: np.ndarray, ca: np.ndarray, q0: np.ndarray, q1: np.ndarray,
                      mid: np.ndarray, half: np.ndarray, mid_q: np.ndarray, half_q: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """:meth:`fiberplan.planners.mpc.detour.DetourGrid.clearance` against one neighbour held still,
    every cell of the grid into ``out`` (cells,).

    Per cell, the lower bound: the distance from the neighbour's base to each of the cell's
    capsules (``a + u d``, ``(cells, U, 2)``), less the neighbour's reach and the radii, the
    smallest over the combinations (``combo_capsule`` names each one's capsule among ``U``). Below
    ``cutoff``, the exact clearance: the smallest of ``distance - radii`` over the combinations
    (``seg_*[cell, ca[k]]`` against ``q0[k], q1[k]``), computed only for those whose bound (their
    midpoints' distance less half lengths and radii) is below the exact clearance of the one with
    the lowest bound."""
    n_u = a.shape[1]
    n_k = ca.shape[0]
    dist = np.empty(n_u)
    lower = np.empty(n_k)
    for cell in range(a.shape[0]):
        for u in range(n_u):
            dist[u] = np.sqrt(_point_segment_sq_safe(base_x, base_y, a[cell, u, 0], a[cell, u, 1], d[cell, u, 0], d[cell, u, 1],
                                                     nonzero[cell, u], safe_dd[cell, u]))
        lb = 0.0
        for k in range(n_k):
            v = dist[combo_capsule[k]] - reach[k] - radii[k]
            lb = v if k == 0 else _minimum(lb, v)
        if not lb < cutoff:
            out[cell] = lb
            continue
        first = 0
        for k in range(n_k):
            c = ca[k]
            lower[k] = np.hypot(mid[cell, c, 0] - mid_q[k, 0], mid[cell, c, 1] - mid_q[k, 1]) - half[cell, c] - half_q[k] - radii[k]
            if lower[first] == lower[first] and not lower[k] >= lower[first]:  # np.argmin: the first smallest, or the first NaN
                first = k
        c = ca[first]
        upper = _distance_only(seg_start[cell, c, 0], seg_start[cell, c, 1], seg_end[cell, c, 0], seg_end[cell, c, 1],
                               q0[first, 0], q0[first, 1], q1[first, 0], q1[first, 1]) - radii[first]
        best = upper
        for k in range(n_k):
            if lower[k] - 1e-9 < upper:  # a margin for the bound's rounding
                c = ca[k]
                best = _minimum(best, _distance_only(seg_start[cell, c, 0], seg_start[cell, c, 1], seg_end[cell, c, 0], seg_end[cell, c, 1],
                                                     q0[k, 0], q0[k, 1], q1[k, 0], q1[k, 1]) - radii[k])
        out[cell] = best


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
                c = np.sqrt(dx * dx + dy * dy) - radii[k]
            elif disc[a] or disc[b]:
                if disc[a]:  # p is the point, q the segment (of positive length)
                    px, py, ax, ay, ex, ey = p0x, p0y, q0x, q0y, q_end[v, b, 0], q_end[v, b, 1]
                else:
                    px, py, ax, ay, ex, ey = q0x, q0y, p0x, p0y, p_end[u, a, 0], p_end[u, a, 1]
                dx, dy = ex - ax, ey - ay
                c = np.sqrt(_point_segment_sq_safe(px, py, ax, ay, dx, dy, True, dx * dx + dy * dy)) - radii[k]
            else:  # closest at an end point unless they cross
                c = _distance_only(p0x, p0y, p_end[u, a, 0], p_end[u, a, 1], q0x, q0y, q_end[v, b, 0], q_end[v, b, 1]) - radii[k]
            best = c if k == 0 else _minimum(best, c)
        out[m] = best


@numba.njit(cache=True, error_model="numpy", inline="always")
def _maximum(a: float, b: float) -> float:
    """``np.maximum(a, b)``: NaN if either is."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@numba.njit(cache=True, error_model="numpy", inline="always")
def _inside_depth(points_start: np.ndarray, points_end: np.ndarray, point_rows: np.ndarray, with_ends: bool,
                  polygon: np.ndarray, polygon_rows: np.ndarray) -> float:
    """:func:`fiberplan.zones._inside_depth` of one zone's core points (its capsules' starts at
    ``point_rows``, and their ends ``with_ends``) in one convex polygon (its edges' starts at
    ``polygon_rows``): the largest over the points of the smallest signed distance to an edge's line."""
    n_v = polygon_rows.shape[0]
    deepest = 0.0
    for half in range(2 if with_ends else 1):
        points = points_start if half == 0 else points_end
        for q in range(point_rows.shape[0]):
            px, py = points[point_rows[q], 0], points[point_rows[q], 1]
            nearest = 0.0
            for v in range(n_v):
                ax, ay = polygon[polygon_rows[v], 0], polygon[polygon_rows[v], 1]
                w = polygon_rows[(v + 1) % n_v]
                ex, ey = polygon[w, 0] - ax, polygon[w, 1] - ay
                length = np.sqrt(ex * ex + ey * ey)
                if not length >= 1e-12:  # np.maximum(norm, _EPS), NaN kept
                    length = length if length != length else 1e-12
                side = (ex * (py - ay) - ey * (px - ax)) / length
                nearest = side if v == 0 else _minimum(nearest, side)
            deepest = nearest if (half == 0 and q == 0) else _maximum(deepest, nearest)
    return deepest


@numba.njit(cache=True, error_model="numpy", nogil=True)
def _pair_depth(s_i: np.ndarray, e_i: np.ndarray, s_j: np.ndarray, e_j: np.ndarray, za: int, zb: int, poly_a: bool, poly_b: bool,
                zone_rows: np.ndarray, zone_offsets: np.ndarray, zone_is_polygon: np.ndarray) -> float:  # pragma: no cover
    """The depth of the deepest core point of zone ``za`` of one positioner (capsule ends
    ``s_i``, ``e_i`` ``(C, 2)``) inside polygon ``zb`` of the other, or of ``zb`` inside polygon
    ``za`` (whichever are polygons), 0 if none is inside: the zone kernels' containment check."""
    rows_a, rows_b = zone_rows[zone_offsets[za]:zone_offsets[za + 1]], zone_rows[zone_offsets[zb]:zone_offsets[zb + 1]]
    deep = 0.0
    if poly_b:  # zone a of i inside polygon b of j
        deep = _maximum(deep, _inside_depth(s_i, e_i, rows_a, not zone_is_polygon[za], s_j, rows_b))
    if poly_a:  # zone b of j inside polygon a of i
        deep = _maximum(deep, _inside_depth(s_j, e_j, rows_b, not zone_is_polygon[zb], s_i, rows_a))
    return deep


@numba.njit(cache=True, error_model="numpy", nogil=True)
def zone_clearances(si: np.ndarray, ei: np.ndarray, sj: np.ndarray, ej: np.ndarray, ci: np.ndarray, cj: np.ndarray,
                    pair_a: np.ndarray, pair_b: np.ndarray, disc_radius: np.ndarray, pair_poly_a: np.ndarray, pair_poly_b: np.ndarray,
                    pair_radius_sum: np.ndarray, combo_pair: np.ndarray, combo_ca: np.ndarray, combo_cb: np.ndarray,
                    combo_radii: np.ndarray, zone_rows: np.ndarray, zone_offsets: np.ndarray, zone_is_polygon: np.ndarray,
                    exact_below: float, clear: np.ndarray, dist: np.ndarray, s: np.ndarray, t: np.ndarray,
                    exact: np.ndarray) -> None:  # pragma: no cover
    """:func:`fiberplan.zones.clearances` of ``L`` row-matched positioner pairs into ``clear``,
    ``dist``, ``s``, ``t``, ``exact`` ``(L, K)``.

    Per row: each zone pair's bound from its enclosing discs (centres ``ci``, ``cj`` ``(L, Z,
    2)``); each combination's exact segment distance where its pair's bound is below
    ``exact_below``, else the bound; then, for a zone pair with a polygon whose discs overlap,
    the depth of the deepest core point of either zone inside the other's polygon, which lowers
    the pair's combinations to ``-(depth + radii)``. ``zone_rows[zone_offsets[z]:zone_offsets[z +
    1]]`` are zone ``z``'s capsule rows."""
    n_p = pair_a.shape[0]
    bounds = np.empty(n_p)
    depth = np.empty(n_p)
    for m in range(si.shape[0]):
        for p in range(n_p):
            za, zb = pair_a[p], pair_b[p]
            dx, dy = ci[m, za, 0] - cj[m, zb, 0], ci[m, za, 1] - cj[m, zb, 1]
            bounds[p] = np.sqrt(dx * dx + dy * dy) - disc_radius[za] - disc_radius[zb]
        for k in range(combo_pair.shape[0]):
            bound = bounds[combo_pair[k]]
            if bound < exact_below:
                a, b = combo_ca[k], combo_cb[k]
                d, ss, tt = _segment_pair(si[m, a, 0], si[m, a, 1], ei[m, a, 0], ei[m, a, 1], sj[m, b, 0], sj[m, b, 1], ej[m, b, 0], ej[m, b, 1])
                clear[m, k], dist[m, k], s[m, k], t[m, k], exact[m, k] = d - combo_radii[k], d, ss, tt, True
            else:
                clear[m, k], dist[m, k], s[m, k], t[m, k], exact[m, k] = bound, bound + combo_radii[k], 0.0, 0.0, False
        lowered = False
        for p in range(n_p):
            depth[p] = 0.0
            if (pair_poly_a[p] or pair_poly_b[p]) and bounds[p] <= 0.0:
                deep = _pair_depth(si[m], ei[m], sj[m], ej[m], pair_a[p], pair_b[p], pair_poly_a[p], pair_poly_b[p],
                                   zone_rows, zone_offsets, zone_is_polygon)
                depth[p] = deep
                lowered = lowered or deep > 0.0
        if lowered:
            for k in range(combo_pair.shape[0]):
                p = combo_pair[k]
                if depth[p] > 0.0:
                    clear[m, k] = _minimum(clear[m, k], -(depth[p] + pair_radius_sum[p]))


@numba.njit(cache=True, error_model="numpy", nogil=True)
def zone_indexed_clearances(start: np.ndarray, end: np.ndarray, centres: np.ndarray, i_index: np.ndarray, j_index: np.ndarray,
                            pair_a: np.ndarray, pair_b: np.ndarray, disc_radius: np.ndarray, pair_poly_a: np.ndarray,
                            pair_poly_b: np.ndarray, pair_radius_sum: np.ndarray, combo_pair: np.ndarray, combo_ca: np.ndarray,
                            combo_cb: np.ndarray, combo_radii: np.ndarray, zone_rows: np.ndarray, zone_offsets: np.ndarray,
                            zone_is_polygon: np.ndarray, exact_below: float, out: np.ndarray) -> None:  # pragma: no cover
    """``out[m]``: the smallest over the combinations of :func:`zone_clearances`' ``clear`` (the
    same arithmetic: every combination's value as it computes it, then the same lowering) for
    the capsule ends ``start``, ``end`` ``(R, C, 2)`` (their zones' disc centres ``centres``) of
    row ``i_index[m]`` against row ``j_index[m]``: :func:`indexed_smallest` for polygon zones
    (group moves' members at many configurations against neighbours held still)."""
    n_p = pair_a.shape[0]
    bounds = np.empty(n_p)
    depth = np.empty(n_p)
    for m in range(i_index.shape[0]):
        u, v = i_index[m], j_index[m]
        for p in range(n_p):
            za, zb = pair_a[p], pair_b[p]
            dx, dy = centres[u, za, 0] - centres[v, zb, 0], centres[u, za, 1] - centres[v, zb, 1]
            bounds[p] = np.sqrt(dx * dx + dy * dy) - disc_radius[za] - disc_radius[zb]
        lowered = False
        for p in range(n_p):
            depth[p] = 0.0
            if (pair_poly_a[p] or pair_poly_b[p]) and bounds[p] <= 0.0:
                deep = _pair_depth(start[u], end[u], start[v], end[v], pair_a[p], pair_b[p], pair_poly_a[p], pair_poly_b[p],
                                   zone_rows, zone_offsets, zone_is_polygon)
                depth[p] = deep
                lowered = lowered or deep > 0.0
        best = 0.0
        for k in range(combo_pair.shape[0]):
            p = combo_pair[k]
            bound = bounds[p]
            if bound < exact_below:
                a, b = combo_ca[k], combo_cb[k]
                c = _segment_pair(start[u, a, 0], start[u, a, 1], end[u, a, 0], end[u, a, 1],
                                  start[v, b, 0], start[v, b, 1], end[v, b, 0], end[v, b, 1])[0] - combo_radii[k]
            else:
                c = bound
            if lowered and depth[p] > 0.0:
                c = _minimum(c, -(depth[p] + pair_radius_sum[p]))
            best = c if k == 0 else _minimum(best, c)
        out[m] = best


@numba.njit(cache=True, error_model="numpy", nogil=True)
def zone_smallest(si: np.ndarray, ei: np.ndarray, ci: np.ndarray, i_index: np.ndarray, sj: np.ndarray, ej: np.ndarray, cj: np.ndarray,
                  j_index: np.ndarray, pair_a: np.ndarray, pair_b: np.ndarray, disc_radius: np.ndarray, pair_poly_a: np.ndarray,
                  pair_poly_b: np.ndarray, pair_radius_sum: np.ndarray, pair_combos: np.ndarray, pair_offsets: np.ndarray,
                  combo_ca: np.ndarray, combo_cb: np.ndarray, combo_radii: np.ndarray, zone_rows: np.ndarray, zone_offsets: np.ndarray,
                  zone_is_polygon: np.ndarray, exact_below: float, out: np.ndarray) -> None:  # pragma: no cover
    """:func:`fiberplan.zones.smallest` for configurations read by index (``si[i_index[m]]``
    against ``sj[j_index[m]]``, their zones' disc centres ``ci``, ``cj``) into ``out`` ``(M,)``:
    per zone pair, the discs' bound where it is at least ``exact_below``, else the smallest exact
    clearance over the pair's combinations (``pair_combos[pair_offsets[p]:pair_offsets[p + 1]]``),
    lowered to ``-(depth + radii)`` where the discs overlap and a zone lies inside the other's
    polygon; the smallest over the pairs. The exact pairs are taken in the order of their bounds
    and the rest skipped once a bound exceeds the smallest so far: the same value."""
    n_p = pair_a.shape[0]
    bounds = np.empty(n_p)
    order = np.empty(n_p, dtype=np.int64)
    for m in range(i_index.shape[0]):
        u, v = i_index[m], j_index[m]
        best = np.inf
        n_exact = 0
        for p in range(n_p):
            za, zb = pair_a[p], pair_b[p]
            dx, dy = ci[u, za, 0] - cj[v, zb, 0], ci[u, za, 1] - cj[v, zb, 1]
            bound = np.sqrt(dx * dx + dy * dy) - disc_radius[za] - disc_radius[zb]
            if bound >= exact_below:
                best = _minimum(best, bound)
                continue
            # The pairs to compute exactly, in the order of their bounds (insertion sort: a few pairs).
            bounds[p] = bound
            k = n_exact
            while k > 0 and bounds[order[k - 1]] > bound:
                order[k] = order[k - 1]
                k -= 1
            order[k] = p
            n_exact += 1
        for r in range(n_exact):
            p = order[r]
            bound = bounds[p]
            # A pair whose discs keep clear (no polygon depth then) by more than the smallest so
            # far cannot lower it: its exact clearance is at least its bound. The rest, bounded
            # further, neither (1 nm of slack for the rounding of the exact distances).
            if bound > 0.0 and bound - 1e-6 >= best:
                break
            za, zb = pair_a[p], pair_b[p]
            value = 0.0
            for n in range(pair_offsets[p], pair_offsets[p + 1]):
                k = pair_combos[n]
                a, b = combo_ca[k], combo_cb[k]
                c = _distance_only(si[u, a, 0], si[u, a, 1], ei[u, a, 0], ei[u, a, 1],
                                   sj[v, b, 0], sj[v, b, 1], ej[v, b, 0], ej[v, b, 1]) - combo_radii[k]
                value = c if n == pair_offsets[p] else _minimum(value, c)
            if bound <= 0.0 and (pair_poly_a[p] or pair_poly_b[p]):
                deep = _pair_depth(si[u], ei[u], sj[v], ej[v], za, zb, pair_poly_a[p], pair_poly_b[p], zone_rows, zone_offsets,
                                   zone_is_polygon)
                if deep > 0.0:
                    value = _minimum(value, -(deep + pair_radius_sum[p]))
            best = _minimum(best, value)
        out[m] = best


@numba.njit(cache=True, error_model="numpy", nogil=True)
def capsule_ends(cos_a: np.ndarray, sin_a: np.ndarray, cos_ab: np.ndarray, sin_ab: np.ndarray, base_x: np.ndarray, base_y: np.ndarray,
                 alpha_arm_mm: float, on_alpha: np.ndarray, start_mm: np.ndarray, end_mm: np.ndarray, lateral: bool,
                 start_y_mm: np.ndarray, end_y_mm: np.ndarray, start: np.ndarray, end: np.ndarray) -> None:  # pragma: no cover
    """:func:`fiberplan.geometry.capsule_segments` from the joints' cosines and sines (numpy's,
    computed before), ``(M,)`` rows, into ``start``, ``end`` ``(M, C, 2)``: each capsule from the
    joint it hangs from along its arm, and with ``lateral``, to the arm's left."""
    for m in range(cos_a.shape[0]):
        elbow_x = base_x[m] + alpha_arm_mm * cos_a[m]
        elbow_y = base_y[m] + alpha_arm_mm * sin_a[m]
        for c in range(on_alpha.shape[0]):
            if on_alpha[c]:
                ox, oy, dx, dy = base_x[m], base_y[m], cos_a[m], sin_a[m]
            else:
                ox, oy, dx, dy = elbow_x, elbow_y, cos_ab[m], sin_ab[m]
            if lateral:
                start[m, c, 0] = ox + start_mm[c] * dx - start_y_mm[c] * dy
                start[m, c, 1] = oy + start_mm[c] * dy + start_y_mm[c] * dx
                end[m, c, 0] = ox + end_mm[c] * dx - end_y_mm[c] * dy
                end[m, c, 1] = oy + end_mm[c] * dy + end_y_mm[c] * dx
            else:
                start[m, c, 0] = ox + start_mm[c] * dx
                start[m, c, 1] = oy + start_mm[c] * dy
                end[m, c, 0] = ox + end_mm[c] * dx
                end[m, c, 1] = oy + end_mm[c] * dy


@numba.njit(cache=True, error_model="numpy", nogil=True)
def row_clearances(start: np.ndarray, end: np.ndarray, combo_ca: np.ndarray, combo_cb: np.ndarray, combo_radii: np.ndarray,
                   out: np.ndarray) -> None:  # pragma: no cover
    """:func:`fiberplan.geometry.clearance_between` from the capsule ends ``(2M, C, 2)`` that
    :func:`capsule_ends` placed (rows ``0..M-1`` the ``i`` sides, ``M..2M-1`` the ``j`` sides):
    each combination's distance as :func:`segment_distances` measures it, less its radii, into
    ``out`` ``(M, K)``."""
    m_rows = out.shape[0]
    for m in range(m_rows):
        r = m + m_rows
        for k in range(combo_ca.shape[0]):
            a, b = combo_ca[k], combo_cb[k]
            d = _segment_pair(start[m, a, 0], start[m, a, 1], end[m, a, 0], end[m, a, 1],
                              start[r, b, 0], start[r, b, 1], end[r, b, 0], end[r, b, 1])[0]
            out[m, k] = d - combo_radii[k]


@numba.njit(cache=True, error_model="numpy", nogil=True)
def indexed_smallest(start: np.ndarray, end: np.ndarray, i_index: np.ndarray, j_index: np.ndarray, combo_ca: np.ndarray,
                     combo_cb: np.ndarray, combo_radii: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out[m]``: the smallest over the combinations of :func:`row_clearances`' values (the same
    arithmetic) for the capsule ends ``start``, ``end`` ``(R, C, 2)`` of row ``i_index[m]`` against
    row ``j_index[m]``: pairs read by index from rows placed once (a group's members at many
    configurations against neighbours held still)."""
    for m in range(i_index.shape[0]):
        u, v = i_index[m], j_index[m]
        best = 0.0
        for k in range(combo_ca.shape[0]):
            a, b = combo_ca[k], combo_cb[k]
            d = _segment_pair(start[u, a, 0], start[u, a, 1], end[u, a, 0], end[u, a, 1],
                              start[v, b, 0], start[v, b, 1], end[v, b, 0], end[v, b, 1])[0]
            c = d - combo_radii[k]
            best = c if k == 0 else _minimum(best, c)
        out[m] = best
