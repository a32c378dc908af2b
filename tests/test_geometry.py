"""Capsule geometry: property tests against a brute-force reference and finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fiberplan.geometry import (
    capsule_segments,
    capsule_tables,
    combo_clearances,
    pair_clearance,
    segment_distance,
    segment_distance_only,
    smallest_clearance,
)
from fiberplan.instrument_io import load_instrument

coord = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
point = st.tuples(coord, coord)
angles = st.floats(-np.pi, np.pi, allow_nan=False)
INSTRUMENTS = {name: load_instrument(name) for name in ("desi", "moons-capsules", "sdss")}


def _point_segment(p, a, b):
    ab = b - a
    denom = ab @ ab
    t = 0.0 if denom == 0 else float(np.clip((p - a) @ ab / denom, 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def _segments_cross(p0, p1, q0, q1):
    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    d1, d2 = orient(q0, q1, p0), orient(q0, q1, p1)
    d3, d4 = orient(p0, p1, q0), orient(p0, p1, q1)
    return (d1 * d2 < 0) and (d3 * d4 < 0)


def brute_force_distance(p0, p1, q0, q1):
    """Exact 2-D segment distance: 0 if they cross, else the least endpoint-to-segment distance."""
    if _segments_cross(p0, p1, q0, q1):
        return 0.0
    return min(_point_segment(p0, q0, q1), _point_segment(p1, q0, q1), _point_segment(q0, p0, p1), _point_segment(q1, p0, p1))


def convex_reference_distance(p0, p1, q0, q1):
    """Independent reference: minimise the convex function s -> dist(P(s), Q) numerically."""
    from scipy.optimize import minimize_scalar

    res = minimize_scalar(lambda s: _point_segment(p0 + s * (p1 - p0), q0, q1), bounds=(0.0, 1.0), method="bounded",
                          options={"xatol": 1e-12})
    return min(res.fun, _point_segment(p0, q0, q1), _point_segment(p1, q0, q1))


@settings(max_examples=500, deadline=None)
@given(p0=point, p1=point, q0=point, q1=point, degenerate=st.sampled_from(["none", "p", "q", "both"]))
def test_segment_distance_matches_brute_force_and_is_symmetric(p0, p1, q0, q1, degenerate):
    p0, p1, q0, q1 = map(np.array, (p0, p1, q0, q1))
    if degenerate in ("p", "both"):
        p1 = p0.copy()
    if degenerate in ("q", "both"):
        q1 = q0.copy()
    d, s, t = segment_distance(p0, p1, q0, q1)
    d_sym, _, _ = segment_distance(q0, q1, p0, p1)
    assert d >= 0.0
    assert 0.0 <= s <= 1.0 and 0.0 <= t <= 1.0
    assert d == pytest.approx(brute_force_distance(p0, p1, q0, q1), abs=1e-9)
    assert d == pytest.approx(float(d_sym), abs=1e-9)
    assert d == pytest.approx(convex_reference_distance(p0, p1, q0, q1), abs=1e-6)
    # the closest points really are that far apart
    assert np.linalg.norm(p0 + s * (p1 - p0) - (q0 + t * (q1 - q0))) == pytest.approx(float(d), abs=1e-9)


@settings(max_examples=300, deadline=None)
@given(p0=point, p1=point, q0=point, q1=point, degenerate=st.sampled_from(["none", "p", "q", "both"]))
def test_the_distance_alone_is_segment_distances_bit_for_bit(p0, p1, q0, q1, degenerate):
    p0, p1, q0, q1 = map(np.array, (p0, p1, q0, q1))
    if degenerate in ("p", "both"):
        p1 = p0.copy()
    if degenerate in ("q", "both"):
        q1 = q0.copy()
    assert segment_distance_only(p0, p1, q0, q1) == segment_distance(p0, p1, q0, q1)[0]


def test_segment_distance_is_vectorised():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, size=(4, 300, 2))
    d, _, _ = segment_distance(*pts)
    expected = [brute_force_distance(*(pts[:, k])) for k in range(300)]
    np.testing.assert_allclose(d, expected, atol=1e-9)


def _two_positioners(name, offset):
    inst = INSTRUMENTS[name]
    base = np.array([[0.0, 0.0], [inst.pitch_mm * offset, 0.0]])
    return inst, base


@pytest.mark.parametrize("name", list(INSTRUMENTS))
@settings(max_examples=150, deadline=None)
@given(q=st.lists(angles, min_size=4, max_size=4), orient=st.lists(angles, min_size=2, max_size=2))
def test_pair_clearance_symmetric_and_matches_brute_force(name, q, orient):
    inst, base = _two_positioners(name, 1.0)
    joints = np.array(q).reshape(2, 2)
    ori = np.array(orient)
    forward = pair_clearance(inst, base, ori, joints, np.array([[0, 1]])).clearance[0]
    backward = pair_clearance(inst, base, ori, joints, np.array([[1, 0]])).clearance[0]
    start, end = capsule_segments(inst, base, ori, joints)
    radii = [c.radius_mm for c in inst.capsules]
    for k, (a, b) in enumerate(inst.capsule_pairs):
        expected = brute_force_distance(start[0, a], end[0, a], start[1, b], end[1, b]) - radii[a] - radii[b]
        assert forward[k] == pytest.approx(expected, abs=1e-9)
    assert forward.min() == pytest.approx(backward.min(), abs=1e-12)
    assert (forward + np.array([radii[a] + radii[b] for a, b in inst.capsule_pairs]) >= 0).all()


@pytest.mark.parametrize("name", list(INSTRUMENTS))
@settings(max_examples=200, deadline=None)
@given(q=st.lists(angles, min_size=4, max_size=4), orient=st.lists(angles, min_size=2, max_size=2), offset=st.floats(0.5, 1.0))
def test_clearance_gradient_matches_finite_differences(name, q, orient, offset):
    inst, base = _two_positioners(name, offset)
    joints = np.array(q).reshape(2, 2)
    ori = np.array(orient)
    pairs = np.array([[0, 1]])
    result = pair_clearance(inst, base, ori, joints, pairs, gradient=True)
    assume(np.all(result.distance > 1e-3))
    h = 1e-6
    for row, grad in ((0, result.grad_i), (1, result.grad_j)):
        for k in range(2):
            dq = np.zeros_like(joints)
            dq[row, k] = h
            plus = pair_clearance(inst, base, ori, joints + dq, pairs).clearance[0]
            minus = pair_clearance(inst, base, ori, joints - dq, pairs).clearance[0]
            centre = result.clearance[0]
            # At kinks (closest point switching, parallel segments) the derivative is one-sided;
            # skip those whose one-sided slopes differ by more than the tolerance compared below
            # (a looser check let a kink of slope change 4.5e-4 through: SDSS, beta = pi).
            one_sided_agree = np.abs((plus - centre) - (centre - minus)) < 2e-5 * h
            fd = (plus - minus) / (2 * h)
            ok = one_sided_agree
            np.testing.assert_allclose(grad[0, ok, k], fd[ok], atol=2e-5)


@pytest.mark.parametrize("name", list(INSTRUMENTS))
def test_combo_clearances_equal_segment_distance_bit_for_bit(name):
    # The planners' searches use the per-shape formulas; a schedule must not change with them.
    inst = INSTRUMENTS[name]
    rng = np.random.default_rng(7)
    n = 20000
    lim = inst.limits_rad
    base_j = rng.uniform(-1.2, 1.2, (n, 2)) * inst.pitch_mm
    start_i, end_i = capsule_segments(inst, np.zeros((n, 2)), np.zeros(n), rng.uniform(lim[:, 0], lim[:, 1], (n, 2)))
    start_j, end_j = capsule_segments(inst, base_j, rng.uniform(-np.pi, np.pi, n), rng.uniform(lim[:, 0], lim[:, 1], (n, 2)))
    _, _, _, combos, radii = capsule_tables(inst)
    ca, cb = combos[:, 0], combos[:, 1]
    expected = segment_distance(start_i[:, ca], end_i[:, ca], start_j[:, cb], end_j[:, cb])[0] - radii
    assert (expected < 0).any()  # colliding pairs are among the samples
    _, start_mm, end_mm, _, _ = capsule_tables(inst)
    if (start_mm != end_mm).any():  # and crossing segments, where a segment-segment combination exists
        assert (expected <= -radii).any()
    np.testing.assert_array_equal(combo_clearances(inst, start_i, end_i, start_j, end_j), expected)
    np.testing.assert_array_equal(combo_clearances(inst, start_i, end_i, start_j, end_j, smallest=True), expected.min(axis=1))
    # Leading axes broadcast: a few configurations of i against all of j.
    grid = combo_clearances(inst, start_i[:3, None], end_i[:3, None], start_j[None], end_j[None])
    assert grid.shape == (3, n, len(combos))
    np.testing.assert_array_equal(grid[[0, 1, 2], [0, 1, 2]], expected[:3])
    if not inst.polygons:  # the compiled search, reading the configurations by index
        order = rng.permutation(n)
        got = smallest_clearance(inst, start_i, end_i, order, start_j[::-1], end_j[::-1], (n - 1 - order))
        np.testing.assert_array_equal(got, expected.min(axis=1)[order])
        outer = smallest_clearance(inst, start_i, end_i, np.arange(3)[:, None], start_j, end_j, np.arange(n)[None, :])
        np.testing.assert_array_equal(outer, grid.min(axis=2))


def test_leading_time_axes_are_supported():
    inst, base = _two_positioners("moons-capsules", 1.0)
    rng = np.random.default_rng(1)
    joints = rng.uniform(0.1, 3.0, size=(5, 2, 2))
    stacked = pair_clearance(inst, base, np.zeros(2), joints, np.array([[0, 1]])).clearance
    for t in range(5):
        single = pair_clearance(inst, base, np.zeros(2), joints[t], np.array([[0, 1]])).clearance
        np.testing.assert_allclose(stacked[t], single)


def test_tiny_segments_are_not_points():
    # found by hypothesis: a 1e-7 mm segment ending on a point is at distance 0 from it
    d, _, _ = segment_distance(np.zeros(2), np.zeros(2), np.array([0.0, 1.192092896e-07]), np.zeros(2))
    assert d == 0.0


def test_the_compiled_search_refuses_zones_and_indices_outside_its_tables():
    inst = INSTRUMENTS["sdss"]
    start, end = capsule_segments(inst, np.zeros((2, 2)), np.zeros(2), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="q_index outside"):
        smallest_clearance(inst, start, end, np.array([0]), start, end, np.array([2]))
    with pytest.raises(ValueError, match="p_index outside"):
        smallest_clearance(inst, start, end, np.array([-1]), start, end, np.array([0]))
    zoned = load_instrument("moons")
    with pytest.raises(ValueError, match="capsule instruments"):
        smallest_clearance(zoned, start, end, np.array([0]), start, end, np.array([0]))


def _segment_distance_numpy(p0, p1, q0, q1):
    """``segment_distance`` as numpy computed it before it was compiled: the reference its compiled
    loop must equal bit for bit (every planner's constraint and the verifier read it)."""
    with np.errstate(divide="ignore", invalid="ignore"):  # the awkward cases below divide by zero, as numpy did
        return _numpy_reference(p0, p1, q0, q1)


def _numpy_reference(p0, p1, q0, q1):
    (p0x, p0y, p1x, p1y, q0x, q0y, q1x, q1y), (d1x, d1y, d2x, d2y), (a_nz, e_nz, a_safe, e_safe) = _segment_parts(p0, p1, q0, q1)
    dist, t = _point_to_segment(p0x, p0y, q0x, q0y, d2x, d2y, e_nz, e_safe)
    s = np.zeros_like(dist)
    d_c, t_c = _point_to_segment(p1x, p1y, q0x, q0y, d2x, d2y, e_nz, e_safe)
    better = d_c < dist
    dist, s, t = np.where(better, d_c, dist), np.where(better, 1.0, s), np.where(better, t_c, t)
    d_c, s_c = _point_to_segment(q0x, q0y, p0x, p0y, d1x, d1y, a_nz, a_safe)
    better = d_c < dist
    dist, s, t = np.where(better, d_c, dist), np.where(better, s_c, s), np.where(better, 0.0, t)
    d_c, s_c = _point_to_segment(q1x, q1y, p0x, p0y, d1x, d1y, a_nz, a_safe)
    better = d_c < dist
    dist, s, t = np.where(better, d_c, dist), np.where(better, s_c, s), np.where(better, 1.0, t)
    crossing, rx, ry = _crossing(p0x, p0y, p1x, p1y, q0x, q0y, q1x, q1y, d1x, d1y, d2x, d2y)
    safe = np.where(crossing, d1x * d2y - d1y * d2x, 1.0)
    s = np.where(crossing, (rx * d2y - ry * d2x) / safe, s)
    t = np.where(crossing, (rx * d1y - ry * d1x) / safe, t)
    dist = np.where(crossing, 0.0, dist)
    return dist, s, t


def _point_to_segment(
    px: np.ndarray, py: np.ndarray, ax: np.ndarray, ay: np.ndarray, dx: np.ndarray, dy: np.ndarray,
    nonzero: np.ndarray, safe_dd: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Distance from points ``p`` to segments ``a + u d`` and the parameter ``u`` (components
    apart: these arrays are small and numpy's per-call cost dominates). ``nonzero`` marks
    segments of positive length ``dd = d . d``; ``safe_dd`` is ``dd`` with zeros replaced by 1."""
    sq, u = _point_segment_sq_safe(px, py, ax, ay, dx, dy, nonzero, safe_dd)
    return np.sqrt(sq), u


def _point_segment_sq_safe(
    px: np.ndarray, py: np.ndarray, ax: np.ndarray, ay: np.ndarray, dx: np.ndarray, dy: np.ndarray,
    nonzero: np.ndarray, safe_dd: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`point_to_segment`'s squared distance and parameter ``u`` (the one arithmetic both use)."""
    u = np.minimum(np.maximum(((px - ax) * dx + (py - ay) * dy) / safe_dd, 0.0), 1.0)
    u = np.where(nonzero, u, 0.0)
    ex = px - (ax + u * dx)
    ey = py - (ay + u * dy)
    return ex * ex + ey * ey, u


def _segment_parts(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> tuple[tuple, tuple, tuple]:
    """The end points' components, the two directions, and which segments have positive length
    (with their squared lengths, zeros replaced by 1), as the numpy references use them."""
    p0x, p0y, p1x, p1y = p0[..., 0], p0[..., 1], p1[..., 0], p1[..., 1]
    q0x, q0y, q1x, q1y = q0[..., 0], q0[..., 1], q1[..., 0], q1[..., 1]
    d1x, d1y = p1x - p0x, p1y - p0y
    d2x, d2y = q1x - q0x, q1y - q0y
    a = d1x * d1x + d1y * d1y
    e = d2x * d2x + d2y * d2y
    a_nz, e_nz = a > 0.0, e > 0.0
    return (p0x, p0y, p1x, p1y, q0x, q0y, q1x, q1y), (d1x, d1y, d2x, d2y), (a_nz, e_nz, np.where(a_nz, a, 1.0), np.where(e_nz, e, 1.0))


def _crossing(p0x: np.ndarray, p0y: np.ndarray, p1x: np.ndarray, p1y: np.ndarray, q0x: np.ndarray, q0y: np.ndarray, q1x: np.ndarray,
              q1y: np.ndarray, d1x: np.ndarray, d1y: np.ndarray, d2x: np.ndarray, d2y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Proper crossing (each segment's end points strictly on both sides of the other), and
    ``r = q0 - p0``."""
    rx, ry = q0x - p0x, q0y - p0y
    side_q0 = d1x * ry - d1y * rx
    side_q1 = d1x * (q1y - p0y) - d1y * (q1x - p0x)
    side_p0 = d2x * (-ry) - d2y * (-rx)
    side_p1 = d2x * (p1y - q0y) - d2y * (p1x - q0x)
    return (side_q0 * side_q1 < 0.0) & (side_p0 * side_p1 < 0.0), rx, ry


def _segment_distance_only_numpy(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """``segment_distance_only`` as numpy computed it before it was compiled (the reference)."""
    (p0x, p0y, p1x, p1y, q0x, q0y, q1x, q1y), (d1x, d1y, d2x, d2y), (a_nz, e_nz, a_safe, e_safe) = _segment_parts(p0, p1, q0, q1)
    sq = np.minimum(
        np.minimum(_point_segment_sq_safe(p0x, p0y, q0x, q0y, d2x, d2y, e_nz, e_safe)[0],
                   _point_segment_sq_safe(p1x, p1y, q0x, q0y, d2x, d2y, e_nz, e_safe)[0]),
        np.minimum(_point_segment_sq_safe(q0x, q0y, p0x, p0y, d1x, d1y, a_nz, a_safe)[0],
                   _point_segment_sq_safe(q1x, q1y, p0x, p0y, d1x, d1y, a_nz, a_safe)[0]),
    )
    crossing = _crossing(p0x, p0y, p1x, p1y, q0x, q0y, q1x, q1y, d1x, d1y, d2x, d2y)[0]
    return np.where(crossing, 0.0, np.sqrt(sq))


def _awkward_segments(rng, n):
    """Random segments with the awkward cases mixed in: zero-length, parallel and collinear,
    crossing, touching at an end, far apart, and a few NaN coordinates."""
    p0, p1, q0, q1 = (rng.normal(0.0, 5.0, (n, 2)) for _ in range(4))
    k = n // 8
    p1[:k] = p0[:k]  # p a point
    q1[k:2 * k] = q0[k:2 * k]  # q a point
    q0[2 * k:3 * k] = p0[2 * k:3 * k] + 0.5 * (p1[2 * k:3 * k] - p0[2 * k:3 * k])  # q starts on p
    q1[3 * k:4 * k] = q0[3 * k:4 * k] + 2.0 * (p1[3 * k:4 * k] - p0[3 * k:4 * k])  # parallel
    q0[4 * k:5 * k] = p0[4 * k:5 * k] + 3.0 * (p1[4 * k:5 * k] - p0[4 * k:5 * k])  # collinear
    q1[4 * k:5 * k] = p0[4 * k:5 * k] - 1.0 * (p1[4 * k:5 * k] - p0[4 * k:5 * k])
    q0[5 * k:6 * k] *= 1e6  # far
    p0[6 * k:6 * k + 5, 0] = np.nan
    q1[6 * k + 5:6 * k + 10, 1] = np.nan
    return p0, p1, q0, q1


def test_segment_distance_compiled_equals_numpy_bit_for_bit():
    rng = np.random.default_rng(11)
    p0, p1, q0, q1 = _awkward_segments(rng, 40000)
    got, want = segment_distance(p0, p1, q0, q1), _segment_distance_numpy(p0, p1, q0, q1)
    assert (want[0] == 0.0).sum() > 1000 and np.isnan(want[0]).sum() >= 10  # crossings and NaN among the samples
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    with np.errstate(divide="ignore", invalid="ignore"):
        only = _segment_distance_only_numpy(p0, p1, q0, q1)
    np.testing.assert_array_equal(segment_distance_only(p0, p1, q0, q1), only)
    assert np.isnan(only).sum() >= 10
    # The distances agree where no candidate is NaN (segment_distance keeps a first candidate it cannot compare).
    finite = np.isfinite(np.stack([p0, p1, q0, q1])).all(axis=(0, 2))
    np.testing.assert_array_equal(only[finite], want[0][finite])
    # Leading axes broadcast as numpy broadcasts them: one segment against many, stacked.
    got = segment_distance(p0[:1, None], p1[:1, None], q0[None, :50].reshape(1, 50, 2), q1[None, :50])
    want = _segment_distance_numpy(p0[:1, None], p1[:1, None], q0[None, :50], q1[None, :50])
    for g, w in zip(got, want, strict=True):
        assert g.shape == (1, 50)
        np.testing.assert_array_equal(g, w)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-20, 20, allow_nan=False), min_size=8, max_size=8))
def test_segment_distance_compiled_equals_numpy_on_any_segments(c):
    p0, p1, q0, q1 = (np.array([c[2 * k:2 * k + 2]]) for k in range(4))
    for g, w in zip(segment_distance(p0, p1, q0, q1), _segment_distance_numpy(p0, p1, q0, q1), strict=True):
        np.testing.assert_array_equal(g, w)
    np.testing.assert_array_equal(segment_distance_only(p0, p1, q0, q1), _segment_distance_only_numpy(p0, p1, q0, q1))


def test_the_smallest_clearance_is_nan_where_a_capsule_is():
    # As np.minimum made it: a non-finite configuration is never mistaken for a clear one.
    inst = INSTRUMENTS["moons-capsules"]
    start, end = capsule_segments(inst, np.array([[0.0, 0.0], [25.0, 0.0]]), np.zeros(2), np.array([[0.3, 1.0], [2.0, 0.5]]))
    start[0, 1, 0] = np.nan  # the fiber holder of the first
    got = smallest_clearance(inst, start, end, np.array([0, 1]), start, end, np.array([1, 0]))
    assert np.isnan(got).all()


@pytest.mark.parametrize("name", ["desi", "moons-capsules", "sdss", "moons"])
def test_capsule_segments_compiled_equal_the_verifiers_coordinates_bit_for_bit(name):
    # The planners' capsule ends (a compiled loop after numpy's cosines) and the verifier's (numpy alone).
    from fiberplan.geometry import capsule_coordinates

    inst = load_instrument(name)
    rng = np.random.default_rng(3)
    base, orient = rng.uniform(-50, 50, (6, 2)), rng.uniform(-np.pi, np.pi, 6)
    lim = inst.limits_rad
    for joints, b, o in (
        (rng.uniform(lim[:, 0], lim[:, 1], (6, 2)), base, orient),
        (rng.uniform(lim[:, 0], lim[:, 1], (5, 6, 2)), base, orient),  # leading time axis
        (rng.uniform(lim[:, 0], lim[:, 1], (6, 9, 2)), base[:, None], orient[:, None]),  # paths per positioner
        (rng.uniform(lim[:, 0], lim[:, 1], 2), base, orient),  # one configuration on every base
        (rng.uniform(lim[:, 0], lim[:, 1], 2), base, 0.0),
    ):
        start, end = capsule_segments(inst, b, o, joints)
        sx, sy, ex, ey = capsule_coordinates(inst, b, o, joints)
        np.testing.assert_array_equal(start, np.stack([sx, sy], axis=-1))
        np.testing.assert_array_equal(end, np.stack([ex, ey], axis=-1))


@pytest.mark.parametrize("name", ["desi", "moons-capsules", "sdss", "moons"])
def test_the_safety_layers_clearances_are_clearance_between_bit_for_bit(name):
    # The safety layers' compiled rows (clearance_rows) against the verifier's clearance_between:
    # neighbours at the pitch, every joint anywhere in its range (crossing, touching and parted arms).
    from fiberplan.geometry import clearance_between, clearance_rows

    inst = load_instrument(name)
    rng = np.random.default_rng(5)
    lim = inst.limits_rad
    m = 4000
    base_i = rng.uniform(-100, 100, (m, 2))
    angle = rng.uniform(-np.pi, np.pi, m)
    base_j = base_i + inst.pitch_mm * rng.uniform(0.5, 1.2, m)[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    orient_i, orient_j = rng.uniform(-np.pi, np.pi, m), rng.uniform(-np.pi, np.pi, m)
    qi, qj = rng.uniform(lim[:, 0], lim[:, 1], (m, 2)), rng.uniform(lim[:, 0], lim[:, 1], (m, 2))
    qj[::5] = qi[::5]  # some pairs in the same configuration
    got = clearance_rows(inst, base_i, orient_i, qi, base_j, orient_j, qj)
    expected = clearance_between(inst, base_i, orient_i, qi, base_j, orient_j, qj)
    assert got.shape == expected.shape and got.tobytes() == expected.tobytes()
    assert (expected.min(axis=1) < 0).any() and (expected.min(axis=1) > 0).any()
    assert clearance_rows(inst, base_i[:0], orient_i[:0], qi[:0], base_j[:0], orient_j[:0], qj[:0]).shape == (0, expected.shape[1])


@pytest.mark.parametrize("name", ["desi", "moons-capsules", "sdss", "moons"])
def test_clearances_read_by_index_are_clearance_rows_bit_for_bit(name):
    # Group moves' pairs read by index from capsule ends placed once (capsule_ends_rows,
    # indexed_clearances) against clearance_rows' smallest per pair: rows shared by many pairs,
    # in any order, a row on either side of its pairs.
    from fiberplan.geometry import capsule_ends_rows, clearance_rows, indexed_clearances

    inst = load_instrument(name)
    rng = np.random.default_rng(7)
    lim = inst.limits_rad
    r = 300
    base = rng.uniform(-60, 60, (r, 2))
    orient = rng.uniform(-np.pi, np.pi, r)
    joints = rng.uniform(lim[:, 0], lim[:, 1], (r, 2))
    i_index, j_index = rng.integers(0, r, 5000), rng.integers(0, r, 5000)
    near = np.linalg.norm(base[i_index] - base[j_index], axis=1) < 2.5 * inst.pitch_mm
    i_index, j_index = i_index[near], j_index[near]
    start, end = capsule_ends_rows(inst, base, orient, joints)
    got = indexed_clearances(inst, start, end, i_index, j_index)
    expected = clearance_rows(inst, base[i_index], orient[i_index], joints[i_index], base[j_index], orient[j_index],
                              joints[j_index]).min(axis=1)
    assert got.tobytes() == expected.tobytes()
    assert (expected < 0).any() and (expected > 0).any() and len(expected) > 100
