"""Tests of the ``mpc`` planner's detours (``planners/mpc/detour.py``): grid clearances against the
exact capsule distances, routes that keep their clearance, pair resolutions whose three routes
are clear of the other positioner, and a pair that deadlocks without detours and arrives with them."""

from __future__ import annotations

import numpy as np
import pytest

from fiberplan.generate import make_scenario
from fiberplan.planners import make_settings, plan
from fiberplan.planners.mpc.detour import DetourGrid as _Grid
from fiberplan.planners.mpc.detour import detour_route, pair_resolution
from fiberplan.planners.mpc.grid import clearance_to as _clearance_to
from fiberplan.planners.mpc.grid import densify as _densify
from fiberplan.planners.mpc.waiting import path_clearance as _path_clearance
from fiberplan.scenario import Scenario
from fiberplan.verify import verify


def _subset(scenario: Scenario, rows: list[int]) -> Scenario:
    return scenario.subset(rows, name="pair")


@pytest.fixture(scope="module")
def pair():
    """DESI N = 500 seed 0, positioners 65 and 93 alone: 93's straight path crosses 65's target,
    so once 65 has arrived the two push each other off their targets in turn."""
    sc = _subset(make_scenario("desi", 500, "random", 0), [65, 93])
    settings = make_settings("mpc", sc)
    return sc, settings, sc.instrument.speeds_rad_s * settings.dt_s


def _route_clearance(sc, i, q_from, waypoints, j, q_j, step_rad):
    pts = _densify(np.vstack([q_from, waypoints]), 0.25 * step_rad)
    return _clearance_to(sc, i, pts, np.array([j]), q_j[None, :]).min()


@pytest.mark.parametrize("instrument", ["desi", "moons-capsules", "sdss"])
def test_grid_clearances_are_exact_below_the_cutoff(instrument):
    sc = make_scenario(instrument, 19, "random", 3)
    settings = make_settings("mpc", sc)
    step_rad = sc.instrument.speeds_rad_s * settings.dt_s
    i = int(sc.pairs[0, 0])
    nb = np.concatenate([sc.pairs[sc.pairs[:, 0] == i, 1], sc.pairs[sc.pairs[:, 1] == i, 0]])
    grid = _Grid(sc, i, step_rad, settings.margin_mm, settings.safety_margin_mm, cell_steps=4.0)
    exact = _clearance_to(sc, i, grid.configs, nb, sc.start[nb])
    cutoff = float(np.median(exact))
    fast = grid.clearance(nb, sc.start[nb], cutoff).ravel()
    below = exact < cutoff
    assert below.any() and (~below).any()
    np.testing.assert_allclose(fast[below], exact[below], atol=1e-9)
    assert np.all(fast[~below] >= cutoff - 1e-9)  # a lower bound where not computed exactly
    assert np.array_equal(grid.clearance(nb, sc.start[nb], cutoff).ravel(), fast)  # kept, not recomputed differently


def test_detour_route_goes_around_a_neighbour(pair):
    sc, settings, step_rad = pair
    # 93 held at 65's target side: 65's route must keep the grid clearance away from its ends.
    wp = detour_route(sc, 0, sc.start[0], sc.target[0], np.array([1]), sc.target[[1]], step_rad, settings.margin_mm, settings.safety_margin_mm)
    assert wp is not None and np.array_equal(wp[-1], sc.target[0])
    inner = _densify(wp[:-1], 0.25 * step_rad)  # the grid part of the route
    assert _clearance_to(sc, 0, inner, np.array([1]), sc.target[[1]]).min() >= settings.margin_mm - 1e-9
    assert _route_clearance(sc, 0, sc.start[0], wp, 1, sc.target[1], step_rad) > 0
    # Nothing to find when the neighbour sits on the target itself: 93 held where its straight
    # path comes closest to 65's target (they overlap there).
    path = _densify(np.array([sc.start[1], sc.target[1]]), step_rad)
    overlap = [float(_clearance_to(sc, 0, sc.target[[0]], np.array([1]), p[None, :])[0]) for p in path]
    q_block = path[int(np.argmin(overlap))]
    assert min(overlap) < 0
    assert detour_route(sc, 0, sc.start[0], sc.target[0], np.array([1]), q_block[None, :], step_rad,
                        settings.margin_mm, settings.safety_margin_mm) is None


def test_pair_resolution_routes_are_clear_of_the_other(pair):
    sc, settings, step_rad = pair
    # The straight moves block each other: 93's path crosses 65 at its target.
    blocked = _path_clearance(sc, np.array([1]), np.array([0]), sc.start[[1]], sc.target[[1]], sc.target[[0]], step_rad)
    assert blocked[0] < 0
    nb = [np.array([1]), np.array([0])]
    for first, waiter in ((0, 1), (1, 0)):
        res = pair_resolution(sc, first, waiter, sc.start, sc.target, nb, step_rad, settings.margin_mm, settings.safety_margin_mm)
        assert res is not None and (res.first, res.waiter) == (first, waiter)
        assert np.array_equal(res.first_route[-1], sc.target[first]) and np.array_equal(res.from_wait[-1], sc.target[waiter])
        assert np.array_equal(res.to_wait[-1], res.wait_q) and np.array_equal(res.from_wait[0], res.wait_q)
        # first's whole route clears the waiter at its waiting place ...
        assert _route_clearance(sc, first, sc.start[first], res.first_route, waiter, res.wait_q, step_rad) >= settings.margin_mm - 1e-9
        # ... the waiter gets there clear of first where it is, and home clear of first at its target.
        assert _route_clearance(sc, waiter, sc.start[waiter], res.to_wait, first, sc.start[first], step_rad) > 0
        assert _route_clearance(sc, waiter, res.wait_q, res.from_wait, first, sc.target[first], step_rad) > 0


def test_detours_resolve_a_pair_that_deadlocks_without_them(pair):
    sc, _, _ = pair
    reactive = {"route": "direct", "start_schedule": False}  # the loop alone, as on MOONS and SDSS
    without = plan(sc, "mpc", {**reactive, "detours": False})
    assert np.all(without.outcome == "deadlocked")  # the failure the detours exist for
    result = plan(sc, "mpc", reactive)
    assert np.all(result.outcome == "reached")
    assert result.stats["pair_resolutions"] >= 1
    report = verify(sc, result.trajectory)
    assert report.n_collisions == 0 and not report.limit_violations
    # DESI's start schedule orders this pair before either moves: no deadlock to resolve.
    scheduled = plan(sc, "mpc", {"start_schedule": True, "detours": False, "route": "direct"})
    assert np.all(scheduled.outcome == "reached")
    assert scheduled.stats["schedule_delayed"] == 1 and scheduled.stats["deadlocks_detected"] == 0
    report = verify(sc, scheduled.trajectory)
    assert report.n_collisions == 0 and not report.limit_violations


def test_bad_detour_settings_are_rejected():
    from fiberplan.errors import PlannerError

    sc = make_scenario("desi", 7, "random", 0)
    with pytest.raises(PlannerError, match="detour_max"):
        make_settings("mpc", sc, {"detour_max": 0})


def test_the_pruned_smallest_clearance_is_the_full_minimum_bit_for_bit():
    """The detour grid's clearance takes exact distances only for the combinations that can
    hold the minimum; the result is the full minimum's bits, degenerate segments included."""
    from fiberplan import capsule_kernels
    from fiberplan.geometry import segment_distance_only

    rng = np.random.default_rng(0)
    for _ in range(300):
        r, k = int(rng.integers(1, 50)), int(rng.integers(1, 140))
        p0 = rng.normal(size=(r, k, 2)) * 10
        p1 = p0 + rng.normal(size=(r, k, 2)) * rng.choice([0, 1, 5])
        q0 = rng.normal(size=(k, 2)) * 10
        q1 = q0 + rng.normal(size=(k, 2)) * rng.choice([0, 1, 5])
        radii = rng.uniform(0, 2, k)
        full = (segment_distance_only(p0, p1, q0, q1) - radii).min(axis=1)
        half = 0.5 * np.hypot(p1[..., 0] - p0[..., 0], p1[..., 1] - p0[..., 1])
        half_q = 0.5 * np.hypot(q1[:, 0] - q0[:, 0], q1[:, 1] - q0[:, 1])
        # Every cell below the cutoff (the bound's tables: one capsule, any numbers), so every cell is exact.
        lb_tables = np.zeros((r, 1, 2)), np.ones((r, 1, 2)), np.ones((r, 1), dtype=bool), np.full((r, 1), 2.0)
        out = np.empty(r)
        capsule_kernels.detour_clearances(*lb_tables, np.zeros(k, dtype=np.int64), 0.0, 0.0, np.zeros(k), radii, np.inf,
                                          p0, p1, np.arange(k), q0, q1, 0.5 * (p0 + p1), half, 0.5 * (q0 + q1), half_q, out)
        np.testing.assert_array_equal(out, full)


@pytest.mark.parametrize("name", ["desi", "moons-capsules", "sdss", "moons"])
def test_the_detour_grid_clearance_is_the_bound_above_the_cutoff_and_exact_below(name):
    """What the compiled loop gives, against numpy: the base-and-reach bound where it is at least
    the cutoff, the smallest exact clearance over the combinations below it."""
    from fiberplan.geometry import capsule_segments, capsule_tables, segment_distance_only
    from fiberplan.planners.mpc.detour import DetourGrid

    sc = make_scenario(name, 7, "random", 3)
    inst = sc.instrument
    step = inst.speeds_rad_s * inst.control_dt_s
    grid = DetourGrid(sc, 0, step, 0.1, 0.1)
    others = np.arange(1, 7)
    _, _, _, combos, radii = capsule_tables(inst)
    ca, cb = combos[:, 0], combos[:, 1]
    o_start, o_end = capsule_segments(inst, sc.base_xy[others], sc.orient[others], sc.start[others])
    a, d, nz, safe = grid._lb_tables
    cutoff = 2.0
    got = grid._clearance_each(others, sc.start[others], cutoff)
    for k, j in enumerate(others):
        base = sc.base_xy[j]
        reach = np.maximum(np.linalg.norm(o_start[k] - base, axis=-1), np.linalg.norm(o_end[k] - base, axis=-1))[cb]
        u = np.where(nz, np.clip(((base[0] - a[..., 0]) * d[..., 0] + (base[1] - a[..., 1]) * d[..., 1]) / safe, 0.0, 1.0), 0.0)
        ex, ey = base[0] - (a[..., 0] + u * d[..., 0]), base[1] - (a[..., 1] + u * d[..., 1])
        bound = (np.sqrt(ex * ex + ey * ey)[:, grid._combo_capsule] - reach - radii).min(axis=1)
        exact = (segment_distance_only(grid.seg_start[:, ca], grid.seg_end[:, ca], o_start[k][cb], o_end[k][cb]) - radii).min(axis=1)
        below = bound < cutoff
        assert below.any() and (~below).any()
        np.testing.assert_array_equal(got[k], np.where(below, exact, bound))
