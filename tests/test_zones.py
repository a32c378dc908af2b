"""Polygon zones and interaction tables (fiberplan.zones): MOONS' own collision model, exact
against a brute-force reference, symmetric where its table is, asymmetric where it is not."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import fiberplan as fp
from fiberplan import zones
from fiberplan.geometry import capsule_segments, clearance_between, pair_clearance, segment_distance, segment_distance_only
from fiberplan.instrument_io import load_instrument

MOONS = load_instrument("moons")
PITCH = MOONS.pitch_mm


def _zone_outlines(inst, base, orient, q, spacing=0.02):
    """Dense points on every zone's boundary and inside it (brute-force reference), per zone name."""
    start, end = capsule_segments(inst, base[None], np.array([orient]), q[None])
    out = {}
    for k, cap in enumerate(inst.capsules):
        a, b = start[0, k], end[0, k]
        n = max(2, int(np.linalg.norm(b - a) / spacing) + 1)
        pts = a + np.linspace(0, 1, n)[:, None] * (b - a)
        if cap.radius_mm > 0:  # a disc or capsule: its outline at the radius
            ang = np.linspace(0, 2 * np.pi, 400, endpoint=False)
            pts = (pts[:, None, :] + cap.radius_mm * np.stack([np.cos(ang), np.sin(ang)], -1)[None]).reshape(-1, 2)
        out.setdefault(cap.zone_name, []).append(pts)
    return {name: np.concatenate(p) for name, p in out.items()}


def _brute(inst, bi, qi, bj, qj):
    """Smallest boundary-to-boundary distance over the checked zone pairs, and whether any pair overlaps."""
    zi, zj = _zone_outlines(inst, bi, 0.0, qi), _zone_outlines(inst, bj, 0.0, qj)
    best = np.inf
    for a, b in inst.zone_pairs:
        d = np.linalg.norm(zi[a][:, None, :] - zj[b][None, :, :], axis=-1).min()
        best = min(best, d)
    return best


configs = st.tuples(st.floats(-np.pi, np.pi), st.floats(*MOONS.beta_limits_rad))


@settings(max_examples=25, deadline=None)
@given(qi=configs, qj=configs, angle=st.floats(0, 2 * np.pi), gap=st.floats(0.7, 1.2))
def test_zone_clearance_matches_a_brute_force_reference_and_is_symmetric(qi, qj, angle, gap):
    bi = np.zeros(2)
    bj = gap * PITCH * np.array([np.cos(angle), np.sin(angle)])
    qi, qj = np.array(qi), np.array(qj)
    c = clearance_between(MOONS, bi[None], np.zeros(1), qi[None], bj[None], np.zeros(1), qj[None]).min()
    back = clearance_between(MOONS, bj[None], np.zeros(1), qj[None], bi[None], np.zeros(1), qi[None]).min()
    assert c == pytest.approx(back, abs=1e-9)  # MOONS' table is symmetric
    if c >= zones.EXACT_BELOW_MM:
        return  # a lower bound there: nothing to compare
    ref = _brute(MOONS, bi, qi, bj, qj)
    if c > 0:  # separated: the edge distance is the boundary distance (sampling error <= 0.02 mm)
        assert abs(c - ref) < 0.05
    else:  # overlapping (or one inside the other): the outlines touch, or one holds the other
        assert ref < 0.05 or c < 0


@settings(max_examples=25, deadline=None)
@given(threshold=st.floats(-1.0, zones.EXACT_BELOW_MM), seed=st.integers(0, 2**16))
def test_a_lower_exact_below_decides_every_threshold_under_it_as_the_exact_values_do(threshold, seed):
    """The start schedule's searches ask ``>= floor`` with ``exact_below = floor``: the same answers."""
    rng = np.random.default_rng(seed)
    q = np.stack([rng.uniform(-np.pi, np.pi, 200), rng.uniform(*MOONS.beta_limits_rad, 200)], axis=1)
    angle = rng.uniform(0, 2 * np.pi, 200)
    bases = np.concatenate([np.zeros((200, 2)), PITCH * np.stack([np.cos(angle), np.sin(angle)], axis=1)])
    start, end = capsule_segments(MOONS, bases, np.zeros(400), np.concatenate([q, q[::-1]]))
    exact = zones.smallest(MOONS, start[:200], end[:200], start[200:], end[200:])
    cheap = zones.smallest(MOONS, start[:200], end[:200], start[200:], end[200:], exact_below=threshold)
    np.testing.assert_array_equal(cheap >= threshold, exact >= threshold)
    assert np.any(exact < zones.EXACT_BELOW_MM)  # the draw has near pairs to decide


def test_a_zone_inside_a_polygon_is_a_collision():
    inst = fp.Instrument(
        name="nested", pitch_mm=20.0, alpha_arm_mm=5.0, beta_arm_mm=10.0, alpha_speed_rad_s=1.0, beta_speed_rad_s=1.0,
        alpha_limits_rad=(-np.pi, np.pi), beta_limits_rad=(0.0, 1.9 * np.pi), datum_rad=(0.0, np.pi), tolerance_mm=0.01,
        capsules=(fp.instrument.Capsule("dot", "beta", 10.0, 10.0, 0.1),
                  *fp.instrument.Polygon("plate", "beta", ((6.0, -3.0), (14.0, -3.0), (14.0, 3.0), (6.0, 3.0))).edges()),
        polygons=(fp.instrument.Polygon("plate", "beta", ((6.0, -3.0), (14.0, -3.0), (14.0, 3.0), (6.0, 3.0))),),
        interactions=(("dot", "plate"),),
    )
    # j's dot sits in the middle of i's plate: no edge is near it, yet it is inside.
    bi, bj = np.zeros((1, 2)), np.array([[0.0, 0.0]])
    q = np.array([[0.0, 0.0]])
    c = clearance_between(inst, bi, np.zeros(1), q, bj, np.zeros(1), q)
    assert c.min() < 0.0
    # Moved 20 mm away: clear, by the discs' bound or exactly.
    far = clearance_between(inst, bi, np.zeros(1), q, np.array([[0.0, 40.0]]), np.zeros(1), q)
    assert far.min() > 0.0


def test_interaction_table_is_asymmetric_where_moons_is():
    # MOONS tests the fibre snag triangle against the other's holder only: two snag triangles
    # may overlap, a holder inside the other's snag triangle may not.
    zone_pairs = set(MOONS.zone_pairs)
    assert ("fibre_snag", "holder") in zone_pairs and ("holder", "fibre_snag") in zone_pairs
    assert ("fibre_snag", "fibre_snag") not in zone_pairs and ("beta_1", "beta_2") not in zone_pairs
    assert ("beta_2", "beta_2") in zone_pairs


def test_arms_crossing_at_different_heights_are_clear_under_moons_and_collide_as_capsules():
    # Positioner j's beta arm crosses i's where i carries its lowest zone and j its highest, and
    # the fibres and metrology zones are far apart: MOONS allows it, the capsule model does not.
    found = None
    rng = np.random.default_rng(3)
    base = np.array([[0.0, 0.0], [PITCH, 0.0]])
    capsules = load_instrument("moons-capsules")
    for _ in range(4000):
        q = np.stack([rng.uniform(-np.pi, np.pi, 2), rng.uniform(*MOONS.beta_limits_rad, 2)], axis=1)
        faithful = pair_clearance(MOONS, base, np.zeros(2), q, np.array([[0, 1]])).clearance.min()
        approx = pair_clearance(capsules, base, np.zeros(2), q, np.array([[0, 1]])).clearance.min()
        if faithful > 0.2 and approx < -1.0:
            found = q
            break
    assert found is not None, "no crossing configuration found"
    sc = fp.scenario.scenario_from_dict({
        "format": "fiberplan-scenario", "version": 1, "name": "crossing", "kind": "custom", "seed": 0, "instrument": "moons",
        "meta": {}, "positioners": [
            {"id": k, "x_mm": float(base[k, 0]), "y_mm": float(base[k, 1]), "orient_deg": 0.0,
             "start_deg": [0.0, 0.0], "target": {"alpha_deg": float(np.degrees(found[k, 0])),
                                                   "beta_deg": float(np.degrees(found[k, 1]))}}
            for k in range(2)]})
    assert not sc.infeasible  # the crossing targets are accepted under MOONS' model


def test_a_small_plan_under_moons_own_model_verifies_clean():
    sc = fp.make_scenario("moons", 7, "unfold", 1)
    result = fp.plan(sc, "mpc")
    report = fp.verify(sc, result.trajectory)
    assert report.ok and fp.summarize(result, report)["reached"] == 7


def _at_clearance(q, angle, wanted):
    """Bases ``(2, 2)`` along ``angle`` at which the pair's smallest clearance is about ``wanted``
    (bisection on the distance between the bases)."""
    direction = np.array([np.cos(angle), np.sin(angle)])
    lo, hi = 0.0, 2.5 * PITCH
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        base = np.array([[0.0, 0.0], mid * direction])
        c = pair_clearance(MOONS, base, np.zeros(2), q, np.array([[0, 1]])).clearance.min()
        lo, hi = (mid, hi) if c < wanted else (lo, mid)
    return np.array([[0.0, 0.0], hi * direction])


@settings(max_examples=25, deadline=None)
@given(qi=configs, qj=configs, angle=st.floats(0, 2 * np.pi), wanted=st.floats(0.2, 2.0))
def test_zone_gradients_equal_finite_differences(qi, qj, angle, wanted):
    q = np.array([qi, qj])
    base = _at_clearance(q, angle, wanted)
    pairs = np.array([[0, 1]])
    pc = pair_clearance(MOONS, base, np.zeros(2), q, pairs, gradient=True)
    clearance = pc.clearance[0]
    k = int(np.argmin(clearance))
    # In the band where the planners need gradients (exact edge distances); the bisection can stop
    # at the step where the discs' bound takes over, which the band leaves out.
    assume(0.1 < clearance[k] < 2.1)
    h = 1e-6
    for who, grad in ((0, pc.grad_i[0, k]), (1, pc.grad_j[0, k])):
        for axis in range(2):
            dq = np.zeros_like(q)
            dq[who, axis] = h
            up = pair_clearance(MOONS, base, np.zeros(2), q + dq, pairs).clearance[0, k]
            down = pair_clearance(MOONS, base, np.zeros(2), q - dq, pairs).clearance[0, k]
            mid = pc.clearance[0, k]
            if abs((up - mid) - (mid - down)) > 1e-3 * h:
                continue  # a kink (parallel edges, a vertex changing sides): no derivative to compare
            numeric = (up - down) / (2 * h)
            assert grad[axis] == pytest.approx(numeric, abs=1e-4, rel=1e-3), (who, axis)


def test_solo_free_cells_match_the_exact_clearance_test():
    # The solo moves' free-cell test takes exact zone distances only where the discs come within
    # the threshold: the same cells as the exact clearances, on a grid of MOONS' own model.
    from fiberplan.planners.coordination import solo
    from fiberplan.planners.mpc.grid import JointGrid, clearance_to

    sc = fp.make_scenario("moons", 19, "random", 2)
    i = 9
    cell = sc.instrument.speeds_rad_s * 0.05 * 8
    lo, shape = JointGrid.through(sc, sc.start[i], cell)
    grid = JointGrid(sc, i, cell, lo, shape, exact={})
    others = solo._neighbours(sc, i)
    for threshold in (0.3, 1.0):
        exact = clearance_to(sc, i, grid.configs, others, sc.start[others]) >= threshold
        fast = solo._free(sc, i, grid.configs, others, sc.start[others], threshold)
        assert 0 < exact.sum() < len(exact)
        np.testing.assert_array_equal(fast, exact)


# The numpy forms of zones.clearances and zones.smallest before they were compiled: the references.
def _exact(zp: zones._ZonePair, si: np.ndarray, ei: np.ndarray, sj: np.ndarray, ej: np.ndarray) -> np.ndarray:
    """Segment distances ``(R, Kz)`` of the zone pair's combos for capsule ends ``(R, C, 2)``."""
    return segment_distance_only(si[:, zp.ca], ei[:, zp.ca], sj[:, zp.cb], ej[:, zp.cb])


def _depth(zp: zones._ZonePair, rows: np.ndarray, si: np.ndarray, ei: np.ndarray, sj: np.ndarray, ej: np.ndarray) -> np.ndarray:
    """How deep a zone lies inside the other, a polygon (> 0), for the rows ``rows``, ``(R,)``."""
    depth = np.zeros(len(rows))
    if zp.poly_b:  # zone a of i inside polygon b of j
        depth = np.maximum(depth, _inside_depth(_core(si[rows], ei[rows], zp.points_a, zp.ends_a), sj[rows][:, zp.points_b]))
    if zp.poly_a:  # zone b of j inside polygon a of i
        depth = np.maximum(depth, _inside_depth(_core(sj[rows], ej[rows], zp.points_b, zp.ends_b), si[rows][:, zp.points_a]))
    return depth


def _core(start: np.ndarray, end: np.ndarray, rows: np.ndarray, ends: bool) -> np.ndarray:
    """A zone's core points ``(L, Q, 2)``: a polygon's vertices (its edges' starts), a capsule's two ends."""
    return np.concatenate([start[:, rows], end[:, rows]], axis=1) if ends else start[:, rows]


def _inside_depth(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """How deep the deepest of points ``(L, Q, 2)`` lies inside the convex counterclockwise
    polygon ``(L, V, 2)``: its smallest distance to an edge's line, > 0 only inside; ``(L,)``."""
    edge = np.roll(polygon, -1, axis=1) - polygon
    length = np.maximum(np.linalg.norm(edge, axis=-1), _EPS)  # (L, V)
    rel = points[:, :, None, :] - polygon[:, None, :, :]  # (L, Q, V, 2)
    side = (edge[:, None, :, 0] * rel[..., 1] - edge[:, None, :, 1] * rel[..., 0]) / length[:, None, :]
    return side.min(axis=-1).max(axis=-1)


def _rows(arr: np.ndarray, lead: tuple[int, ...], flat: np.ndarray) -> np.ndarray:
    """``arr[..., C, 2]``'s rows at the flat indices ``flat`` of the broadcast leading shape ``lead``."""
    own = arr.shape[:-2]
    idx = np.unravel_index(flat, lead)
    offset = len(lead) - len(own)
    pick = tuple(idx[offset + k] if own[k] > 1 else np.zeros(len(flat), dtype=np.int64) for k in range(len(own)))
    return arr[pick]


_EPS = 1e-12  # zones' contact distance (geometry._EPS)


def _clearances_numpy(instrument, start_i, end_i, start_j, end_j):
    """``zones.clearances`` as numpy computed it before it was compiled: the reference its loop
    must equal bit for bit (the safety layers, the mpc's constraints and the verifier read it)."""
    tables = zones._tables(instrument)
    n = len(start_i)
    clear = np.empty((n, tables.n_combos))
    dist = np.empty((n, tables.n_combos))
    s = np.zeros((n, tables.n_combos))
    t = np.zeros((n, tables.n_combos))
    exact = np.zeros((n, tables.n_combos), dtype=bool)
    ci, cj = zones._centres(tables, start_i, end_i), zones._centres(tables, start_j, end_j)
    # Every zone pair's disc bound at once, then every near combination's exact segment distance
    # in one call (the per-element arithmetic of the zone-by-zone form, without its Python loop).
    d = ci[:, tables.pair_a] - cj[:, tables.pair_b]  # (L, P, 2)
    bounds = np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) - tables.disc_radius[tables.pair_a] - tables.disc_radius[tables.pair_b]
    per_combo = bounds[:, tables.combo_pair]  # (L, K)
    clear[:] = per_combo
    dist[:] = per_combo + tables.combo_radii
    r, k = np.nonzero(per_combo < zones.EXACT_BELOW_MM)
    if len(r):
        ca, cb = tables.combo_ca[k], tables.combo_cb[k]
        dd, ss, tt = segment_distance(start_i[r, ca], end_i[r, ca], start_j[r, cb], end_j[r, cb])
        clear[r, k] = dd - tables.combo_radii[k]
        dist[r, k] = dd
        s[r, k] = ss
        t[r, k] = tt
        exact[r, k] = True
    # A zone wholly inside a polygon touches no edge: only possible where the discs overlap.
    for p, zp in enumerate(tables.pairs):
        if not (zp.poly_a or zp.poly_b):
            continue
        overlap = np.flatnonzero(bounds[:, p] <= 0.0)
        if len(overlap):
            depth = _depth(zp, overlap, start_i, end_i, start_j, end_j)
            inside = depth > 0.0
            if np.any(inside):
                rows, cols = overlap[inside][:, None], zp.combos[None, :]
                clear[rows, cols] = np.minimum(clear[rows, cols], -(depth[inside] + zp.radius_sum)[:, None])
    return clear, dist, s, t, exact


def _random_pairs(rng, n):
    """Capsule ends of ``n`` random MOONS pairs, from apart to deeply overlapping, random arms."""
    lim = MOONS.limits_rad
    base_j = rng.uniform(0.0, 1.2, n)[:, None] * PITCH * np.stack([np.cos(a := rng.uniform(0, 2 * np.pi, n)), np.sin(a)], -1)
    si, ei = capsule_segments(MOONS, np.zeros((n, 2)), np.zeros(n), rng.uniform(lim[:, 0], lim[:, 1], (n, 2)))
    sj, ej = capsule_segments(MOONS, base_j, rng.uniform(-np.pi, np.pi, n), rng.uniform(lim[:, 0], lim[:, 1], (n, 2)))
    return si, ei, sj, ej


def test_zone_clearances_compiled_equal_numpy_bit_for_bit():
    # Pairs from apart to deeply overlapping (a zone wholly inside a polygon among them), random arms.
    rng = np.random.default_rng(5)
    n = 3000
    si, ei, sj, ej = _random_pairs(rng, n)
    got, want = zones.clearances(MOONS, si, ei, sj, ej), _clearances_numpy(MOONS, si, ei, sj, ej)
    assert want[4].any() and (~want[4]).any()  # exact and bounded combinations among the samples
    assert (want[0] < -zones._tables(MOONS).pair_radius_sum.max()).any()  # and zones deep inside polygons
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


def _smallest_numpy(instrument, start_i, end_i, start_j, end_j, exact_below=zones.EXACT_BELOW_MM):
    exact_below = min(float(exact_below), zones.EXACT_BELOW_MM)
    tables = zones._tables(instrument)
    lead = np.broadcast_shapes(start_i.shape[:-2], start_j.shape[:-2])
    out = np.full(int(np.prod(lead)), np.inf)
    ci, cj = zones._centres(tables, start_i, end_i), zones._centres(tables, start_j, end_j)
    for zp in tables.pairs:
        d = ci[..., zp.zone_a, :] - cj[..., zp.zone_b, :]
        bound = (np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1])
                 - tables.disc_radius[zp.zone_a] - tables.disc_radius[zp.zone_b]).reshape(-1)
        far = bound >= exact_below
        np.minimum(out, np.where(far, bound, np.inf), out=out)
        near = np.flatnonzero(~far)
        if not len(near):
            continue
        si, ei = _rows(start_i, lead, near), _rows(end_i, lead, near)
        sj, ej = _rows(start_j, lead, near), _rows(end_j, lead, near)
        rows = np.arange(len(near))
        value = (_exact(zp, si, ei, sj, ej) - zp.radii).min(axis=1)
        overlap = bound[near] <= 0.0
        if overlap.any() and (zp.poly_a or zp.poly_b):
            depth = _depth(zp, rows[overlap], si, ei, sj, ej)
            value[overlap] = np.where(depth > 0.0, np.minimum(value[overlap], -(depth + zp.radius_sum)), value[overlap])
        out[near] = np.minimum(out[near], value)
    return out.reshape(lead)


@pytest.mark.parametrize("exact_below", [zones.EXACT_BELOW_MM, 0.5])
def test_zone_smallest_compiled_equals_numpy_bit_for_bit(exact_below):
    rng = np.random.default_rng(6)
    n = 400
    si, ei, sj, ej = _random_pairs(rng, n)
    want = _smallest_numpy(MOONS, si, ei, sj, ej, exact_below)
    assert (want < -1.0).any() and (want >= exact_below).any()
    np.testing.assert_array_equal(zones.smallest(MOONS, si, ei, sj, ej, exact_below), want)
    # Leading axes broadcast: a few configurations of i against all of j.
    grid = zones.smallest(MOONS, si[:3, None], ei[:3, None], sj[None], ej[None], exact_below)
    assert grid.shape == (3, n)
    np.testing.assert_array_equal(grid, _smallest_numpy(MOONS, si[:3, None], ei[:3, None], sj[None], ej[None], exact_below))


def test_zone_smallest_by_index_equals_the_gathered_rows_bit_for_bit():
    # The start schedule reads a few positioners' moves step by step: by index, the same numbers
    # as gathering the rows first, on one shared table or two.
    rng = np.random.default_rng(7)
    si, ei, sj, ej = _random_pairs(rng, 300)
    p = rng.integers(0, 300, (4, 1, 25))
    q = rng.integers(0, 300, (1, 5, 25))
    for exact_below in (zones.EXACT_BELOW_MM, 0.5):
        want = zones.smallest(MOONS, si[p], ei[p], sj[q], ej[q], exact_below)
        assert want.shape == (4, 5, 25) and (want < 0.0).any()
        np.testing.assert_array_equal(zones.smallest_indexed(MOONS, si, ei, p, sj, ej, q, exact_below), want)
        np.testing.assert_array_equal(zones.smallest_indexed(MOONS, si, ei, p, si, ei, q, exact_below),
                                      zones.smallest(MOONS, si[p], ei[p], si[q], ei[q], exact_below))
    with pytest.raises(ValueError, match="q_index outside"):
        zones.smallest_indexed(MOONS, si, ei, p, sj, ej, q + 300)
