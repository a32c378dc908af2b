"""Polygon zones and interaction tables (fiberplan.zones): MOONS' own collision model, exact
against a brute-force reference, symmetric where its table is, asymmetric where it is not."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import fiberplan as fp
from fiberplan import zones
from fiberplan.geometry import capsule_segments, clearance_between, pair_clearance
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
