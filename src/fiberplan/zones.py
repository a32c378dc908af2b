"""Polygon zones: clearances for instruments whose collision model has convex polygons
(``formulations/collision_geometry.md``, Zones beyond capsules).

An instrument with polygon zones (MOONS' own model: rectangles and triangles padded by a safety
distance, at several heights, with an interaction table) stores each polygon as its edges,
capsules of the polygon's radius (``Instrument.capsules``, ``zone`` naming the polygon), and
``Instrument.capsule_pairs`` lists the edge pairs of the zone pairs the table checks. Two zones
are then separated by the smallest edge-pair distance minus their radii, unless one lies wholly
inside a polygon, which no edge distance sees: that is checked here, and such a pair gets minus
the depth of the deepest point inside (minus the radii).

Many zones make many edge pairs (MOONS: 27 edges, 134 checked pairs, against 4 for the capsule
model), most of them far apart. So every zone pair is first bounded from below by the discs
enclosing each zone; an edge pair is computed exactly only where that bound is below
:data:`EXACT_BELOW_MM`, and elsewhere the bound stands for it (a lower bound, so a caller
comparing clearances with a smaller threshold decides as with exact values). Instruments made
of capsules only never come here: their path (``fiberplan.geometry``) is unchanged.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from fiberplan import capsule_kernels
from fiberplan.errors import InstrumentError
from fiberplan.geometry import _EPS, PairClearance, capsule_segments, capsule_tables, joint_gradients
from fiberplan.instrument import Instrument

EXACT_BELOW_MM = 3.0
"""Zone pairs whose enclosing discs leave more clearance than this are given that lower bound
instead of exact edge distances. Above every threshold the planners' defaults and the verifier
compare clearances with on MOONS (the mpc's conflict radius 2.79 mm, its margins under 1 mm, the
dnf's envelope 2 mm, the verifier's 2 mm); a larger threshold set by a user then meets lower
bounds, which only makes the planner more cautious."""


@dataclass(frozen=True)
class _ZonePair:
    """One ordered zone pair ``(a of i, b of j)``: its combos (indices into ``capsule_pairs``),
    their capsule rows, radii sums, and what the containment check needs."""

    combos: np.ndarray
    ca: np.ndarray
    cb: np.ndarray
    radii: np.ndarray
    zone_a: int
    zone_b: int
    points_a: np.ndarray  # capsule rows whose start (and, for a capsule zone, end) points are zone a's core points
    ends_a: bool
    points_b: np.ndarray
    ends_b: bool
    poly_a: bool
    poly_b: bool
    radius_sum: float


@dataclass(frozen=True)
class _Tables:
    zone_rows: tuple[np.ndarray, ...]  # per zone: its capsule rows
    centre_start: np.ndarray  # (C, Z): a zone's disc centre is the mean of its capsules' ends, start ...
    centre_end: np.ndarray  # ... and end weights (a rigid arm keeps affine combinations)
    disc_radius: np.ndarray  # (Z,): constant on the rigid arm, padding included
    pairs: tuple[_ZonePair, ...]
    n_combos: int
    pair_a: np.ndarray  # (P,) zone a of each zone pair
    pair_b: np.ndarray  # (P,) zone b
    combo_pair: np.ndarray  # (K,) the zone pair of each combo
    combo_ca: np.ndarray  # (K,) its capsule rows and radii sum
    combo_cb: np.ndarray
    combo_radii: np.ndarray
    pair_poly_a: np.ndarray  # (P,) whether zone a (b) of each pair is a polygon
    pair_poly_b: np.ndarray
    pair_radius_sum: np.ndarray  # (P,)
    zone_rows_flat: np.ndarray  # every zone's capsule rows, zone after zone ...
    zone_offsets: np.ndarray  # ... zone z's from zone_offsets[z] to zone_offsets[z + 1]
    zone_is_polygon: np.ndarray  # (Z,)
    pair_combos: np.ndarray  # every pair's combos, pair after pair ...
    pair_offsets: np.ndarray  # ... pair p's from pair_offsets[p] to pair_offsets[p + 1]


@functools.lru_cache(maxsize=32)
def _tables(instrument: Instrument) -> _Tables:
    names = instrument.zone_names
    index = {name: k for k, name in enumerate(names)}
    caps = instrument.capsules
    zone_of = np.array([index[c.zone_name] for c in caps])
    zone_rows = tuple(np.flatnonzero(zone_of == k) for k in range(len(names)))
    polygon = {p.name for p in instrument.polygons}
    radius = np.array([caps[int(rows[0])].radius_mm for rows in zone_rows])
    w_start = np.zeros((len(caps), len(names)))
    w_end = np.zeros((len(caps), len(names)))
    disc = np.zeros(len(names))
    for z, rows in enumerate(zone_rows):
        w_start[rows, z] = w_end[rows, z] = 0.5 / len(rows)
        pts = np.array([(caps[r].start_mm, caps[r].start_y_mm) for r in rows] + [(caps[r].end_mm, caps[r].end_y_mm) for r in rows])
        disc[z] = float(np.linalg.norm(pts - pts.mean(axis=0), axis=1).max()) + radius[z] + 1e-9
    _, _, _, combos, combo_radii = capsule_tables(instrument)
    pairs = []
    for a, b in instrument.zone_pairs:
        za, zb = index[a], index[b]
        mine = np.flatnonzero((zone_of[combos[:, 0]] == za) & (zone_of[combos[:, 1]] == zb))
        pairs.append(_ZonePair(
            combos=mine, ca=combos[mine, 0], cb=combos[mine, 1], radii=combo_radii[mine], zone_a=za, zone_b=zb,
            points_a=zone_rows[za], ends_a=a not in polygon, points_b=zone_rows[zb], ends_b=b not in polygon,
            poly_a=a in polygon, poly_b=b in polygon, radius_sum=float(radius[za] + radius[zb]),
        ))
    kept = tuple(p for p in pairs if len(p.combos))
    combo_pair = np.full(len(combos), -1, dtype=np.int64)
    for k, p in enumerate(kept):
        combo_pair[p.combos] = k
    if np.any(combo_pair < 0):
        missing = np.flatnonzero(combo_pair < 0).tolist()
        raise InstrumentError(f"instrument {instrument.name!r}: capsule combinations {missing} belong to no zone pair")
    return _Tables(zone_rows, w_start, w_end, disc, kept, len(combos), np.array([p.zone_a for p in kept], dtype=np.int64),
                   np.array([p.zone_b for p in kept], dtype=np.int64), combo_pair, combos[:, 0], combos[:, 1], combo_radii,
                   np.array([p.poly_a for p in kept]), np.array([p.poly_b for p in kept]), np.array([p.radius_sum for p in kept]),
                   np.concatenate(zone_rows).astype(np.int64), np.cumsum([0] + [len(rows) for rows in zone_rows]).astype(np.int64),
                   np.array([name in polygon for name in names]),
                   np.concatenate([p.combos for p in kept]).astype(np.int64), np.cumsum([0] + [len(p.combos) for p in kept]).astype(np.int64))


def _centres(tables: _Tables, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Centres ``(..., Z, 2)`` of the discs enclosing every zone, from its capsules' ends ``(..., C, 2)``."""
    return np.swapaxes(np.swapaxes(start, -1, -2) @ tables.centre_start + np.swapaxes(end, -1, -2) @ tables.centre_end, -1, -2)


def _bound(tables: _Tables, zp: _ZonePair, ci: np.ndarray, cj: np.ndarray) -> np.ndarray:
    """Lower bound ``(L,)`` of the zone pair's clearance from the enclosing discs."""
    d = ci[:, zp.zone_a] - cj[:, zp.zone_b]
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) - tables.disc_radius[zp.zone_a] - tables.disc_radius[zp.zone_b]


def clearances(
    instrument: Instrument, start_i: np.ndarray, end_i: np.ndarray, start_j: np.ndarray, end_j: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Clearances of every checked capsule combination of row-matched positioners ``i`` and ``j``.

    Args:
        instrument: an instrument with polygon zones.
        start_i, end_i, start_j, end_j: capsule ends ``(L, C, 2)`` in the focal plane.

    Returns:
        ``(clearance, distance, s, t, exact)``, each ``(L, K)``: exact values where the zone
        pair's enclosing discs come within :data:`EXACT_BELOW_MM` (``exact`` true; ``s``, ``t``
        the closest points' parameters), the discs' lower bound elsewhere (``s = t = 0``); a
        zone inside a polygon gives ``-(depth + radii)``.
    """
    tables = _tables(instrument)
    n = len(start_i)
    clear = np.empty((n, tables.n_combos))
    dist = np.empty((n, tables.n_combos))
    s = np.empty((n, tables.n_combos))
    t = np.empty((n, tables.n_combos))
    exact = np.empty((n, tables.n_combos), dtype=bool)
    ci, cj = _centres(tables, start_i, end_i), _centres(tables, start_j, end_j)
    # Row by row in one compiled loop (the numpy form this replaced spent ~1 ms a call on its
    # (L, K) arrays and its Python loop over zone pairs, for a few rows: the safety layer's calls).
    si, ei, sj, ej = (np.ascontiguousarray(a, dtype=np.float64) for a in (start_i, end_i, start_j, end_j))
    capsule_kernels.zone_clearances(
        si, ei, sj, ej, ci, cj, tables.pair_a, tables.pair_b, tables.disc_radius, tables.pair_poly_a, tables.pair_poly_b,
        tables.pair_radius_sum, tables.combo_pair, tables.combo_ca, tables.combo_cb, tables.combo_radii, tables.zone_rows_flat,
        tables.zone_offsets, tables.zone_is_polygon, EXACT_BELOW_MM, clear, dist, s, t, exact)
    return clear, dist, s, t, exact


def indexed_clearances(instrument: Instrument, start: np.ndarray, end: np.ndarray, i_index: np.ndarray,
                       j_index: np.ndarray) -> np.ndarray:
    """``(M,)``: ``clearances(...)[0].min(axis=1)`` (bit for bit) of the configuration whose
    capsule ends are row ``i_index[m]`` of ``start``, ``end`` ``(R, C, 2)`` against row
    ``j_index[m]``: every zone's disc placed once per row, the pairs read by index
    (``fiberplan.geometry.indexed_clearances`` on an instrument with polygon zones)."""
    tables = _tables(instrument)
    start, end = (np.ascontiguousarray(a, dtype=np.float64) for a in (start, end))
    i_index, j_index = (np.ascontiguousarray(a, dtype=np.int64) for a in (i_index, j_index))
    for name, index in (("i_index", i_index), ("j_index", j_index)):
        if index.size and (int(index.min()) < 0 or int(index.max()) >= len(start)):  # the compiled loop checks no bounds
            raise ValueError(f"{name} outside [0, {len(start)})")
    out = np.empty(len(i_index))
    capsule_kernels.zone_indexed_clearances(
        start, end, _centres(tables, start, end), i_index, j_index, tables.pair_a, tables.pair_b, tables.disc_radius,
        tables.pair_poly_a, tables.pair_poly_b, tables.pair_radius_sum, tables.combo_pair, tables.combo_ca, tables.combo_cb,
        tables.combo_radii, tables.zone_rows_flat, tables.zone_offsets, tables.zone_is_polygon, EXACT_BELOW_MM, out)
    return out


def smallest(instrument: Instrument, start_i: np.ndarray, end_i: np.ndarray, start_j: np.ndarray, end_j: np.ndarray,
             exact_below: float = EXACT_BELOW_MM) -> np.ndarray:
    """The smallest clearance over the checked combinations, for capsule ends ``(..., C, 2)``
    with broadcastable leading axes: ``clearances(...)[0].min(axis=-1)`` without the ``(L, K)``
    arrays, and with the exact distances taken only for the rows whose discs come near (the
    planners' searches ask for this over large grids). A smaller ``exact_below`` (at most
    :data:`EXACT_BELOW_MM`) takes fewer exact distances: the result then decides ``>= t``
    exactly only for thresholds ``t <= exact_below``."""
    lead = np.broadcast_shapes(start_i.shape[:-2], start_j.shape[:-2])
    c = start_i.shape[-2]
    # Each side's configurations as rows, read by index where the leading axes broadcast.
    i_rows, j_rows = (np.broadcast_to(np.arange(int(np.prod(a.shape[:-2], dtype=np.int64))).reshape(a.shape[:-2]), lead)
                      for a in (start_i, start_j))
    si, ei, sj, ej = (np.asarray(a).reshape(-1, c, 2) for a in (start_i, end_i, start_j, end_j))
    return smallest_indexed(instrument, si, ei, i_rows, sj, ej, j_rows, exact_below)


def smallest_indexed(instrument: Instrument, p_start: np.ndarray, p_end: np.ndarray, p_index: np.ndarray, q_start: np.ndarray,
                     q_end: np.ndarray, q_index: np.ndarray, exact_below: float = EXACT_BELOW_MM) -> np.ndarray:
    """:func:`smallest` of configurations taken by index: ``smallest(instrument, p_start[p_index],
    p_end[p_index], q_start[q_index], q_end[q_index], exact_below)`` without the gathered copies
    (the start schedule asks for many steps of a few positioners' moves at once).

    Args:
        p_start, p_end: ``(P, C, 2)`` capsule ends of ``P`` configurations of one side.
        p_index: indices into their first axis, any shape.
        q_start, q_end, q_index: the other side's (the same arrays as ``p_*`` allowed).

    Returns:
        The smallest clearances, shaped as the two index arrays broadcast.

    Raises:
        ValueError: an index outside its table.
    """
    exact_below = min(float(exact_below), EXACT_BELOW_MM)
    tables = _tables(instrument)
    ip, iq = np.broadcast_arrays(np.asarray(p_index, dtype=np.int64), np.asarray(q_index, dtype=np.int64))
    shape = ip.shape
    ip, iq = np.ascontiguousarray(ip.ravel()), np.ascontiguousarray(iq.ravel())
    for name, index, table in (("p_index", ip, p_start), ("q_index", iq, q_start)):
        if index.size and (int(index.min()) < 0 or int(index.max()) >= len(table)):  # the compiled loop checks no bounds
            raise ValueError(f"{name} outside [0, {len(table)})")
    si, ei = (np.ascontiguousarray(a, dtype=np.float64) for a in (p_start, p_end))
    ci = _centres(tables, si, ei)
    if q_start is p_start and q_end is p_end:
        sj, ej, cj = si, ei, ci
    else:
        sj, ej = (np.ascontiguousarray(a, dtype=np.float64) for a in (q_start, q_end))
        cj = _centres(tables, sj, ej)
    out = np.empty(ip.size)
    capsule_kernels.zone_smallest(
        si, ei, ci, ip, sj, ej, cj, iq, tables.pair_a, tables.pair_b, tables.disc_radius, tables.pair_poly_a, tables.pair_poly_b,
        tables.pair_radius_sum, tables.pair_combos, tables.pair_offsets, tables.combo_ca, tables.combo_cb, tables.combo_radii,
        tables.zone_rows_flat, tables.zone_offsets, tables.zone_is_polygon, exact_below, out)
    return out.reshape(shape)


def pair_clearance(
    instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray, pairs: np.ndarray, *, gradient: bool = False,
) -> PairClearance:
    """:func:`fiberplan.geometry.pair_clearance` for an instrument with polygon zones (same
    arguments and result; far combos hold the discs' lower bound and a zero gradient)."""
    used, inverse = np.unique(pairs, return_inverse=True)
    if len(used) < joints.shape[-2]:
        base_xy, orient, joints = base_xy[used], orient[used], joints[..., used, :]
        pairs = inverse.reshape(pairs.shape)
    start, end = capsule_segments(instrument, base_xy, orient, joints)  # (..., N, C, 2)
    ii, jj = pairs[:, 0], pairs[:, 1]
    lead = start.shape[:-3]
    c = start.shape[-2]

    def rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return a[..., idx, :, :].reshape(-1, c, 2)

    clear, dist, s, t, exact = clearances(instrument, rows(start, ii), rows(end, ii), rows(start, jj), rows(end, jj))
    shape = (*lead, len(pairs), clear.shape[-1])
    if not gradient:
        return PairClearance(clearance=clear.reshape(shape), distance=dist.reshape(shape))
    if joints.ndim != 2:
        raise ValueError("gradients are computed for one configuration (joints of shape (N, 2))")
    _, _, _, combos, _ = capsule_tables(instrument)
    ca, cb = combos[:, 0], combos[:, 1]
    ends = (start[ii][:, ca], end[ii][:, ca], start[jj][:, cb], end[jj][:, cb])
    # Far combos hold the discs' bound (``exact`` false): no closest points, a zero gradient.
    grad_i, grad_j = joint_gradients(instrument, base_xy, orient, joints, pairs, ends, s, t, dist, (dist > _EPS) & exact)
    return PairClearance(clearance=clear, distance=dist, grad_i=grad_i, grad_j=grad_j)
