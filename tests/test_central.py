"""The ``central`` CasADi/IPOPT reference on tiny groups with a known answer."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from fiberplan.errors import PlannerError
from fiberplan.instrument_io import load_instrument
from fiberplan.kinematics import inverse_kinematics, move_times
from fiberplan.metrics import energy, lower_bound_s, summarize
from fiberplan.planners import make_settings, plan
from fiberplan.planners.central import solve_central
from fiberplan.scenario import TARGET_JOINTS, TARGET_NONE, Scenario
from fiberplan.studies import central_reference
from fiberplan.trajectory import Trajectory
from fiberplan.verify import verify

DESI = load_instrument("desi")


def _desi_pair(start_xy: list[tuple[float, float]], target_xy: list[tuple[float, float]], base: np.ndarray) -> Scenario:
    n = len(base)
    start = np.stack([inverse_kinematics(DESI, base[i : i + 1], np.zeros(1), np.array([start_xy[i]]), np.ones(1))[0] for i in range(n)])
    target = np.stack([inverse_kinematics(DESI, base[i : i + 1], np.zeros(1), np.array([target_xy[i]]), np.ones(1))[0] for i in range(n)])
    return Scenario(
        instrument=DESI,
        ids=np.arange(n),
        base_xy=base,
        orient_deg=np.zeros(n),
        start_deg=np.degrees(start),
        target_kind=np.full(n, TARGET_JOINTS),
        target_values=np.degrees(target),
        target_parity=np.zeros(n, dtype=np.int64),
        name="crossing",
    )


@pytest.fixture(scope="module")
def crossing() -> Scenario:
    """Two DESI positioners 10.4 mm apart whose fibers swap sides: their straight moves collide."""
    base = np.array([[0.0, 0.0], [0.0, 10.4]])
    return _desi_pair([(2.6, 3.8), (-2.6, 6.6)], [(-2.6, 3.8), (2.6, 6.6)], base)


def _sequential_baseline(scenario: Scenario) -> Trajectory:
    """Positioner 0 moves straight at full speed, then positioner 1: a safe plan with a known makespan."""
    dt = 0.002
    times_each = move_times(scenario.instrument, scenario.start, scenario.target)
    total = float(times_each.sum())
    t = np.append(np.arange(0.0, total, dt), total)
    begin = np.array([0.0, times_each[0]])
    frac = np.clip((t[:, None] - begin[None]) / times_each[None], 0.0, 1.0)
    joints = scenario.start[None] + frac[..., None] * (scenario.target - scenario.start)[None]
    return Trajectory(t, joints)


@pytest.fixture(scope="module")
def crossing_central(crossing: Scenario):
    return central_reference(crossing)


def test_straight_collides_and_sequential_is_safe(crossing: Scenario) -> None:
    assert verify(crossing, plan(crossing, "straight").trajectory).n_collisions == 1
    assert verify(crossing, _sequential_baseline(crossing)).ok


def test_central_is_verified_and_between_bound_and_sequential(crossing: Scenario, crossing_central) -> None:
    result = crossing_central
    report = verify(crossing, result.trajectory)
    assert report.ok and report.n_collisions == 0
    assert result.stats["verified"] is True
    assert result.stats["status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    assert result.stats["iterations"] > 0 and result.stats["solve_s"] > 0
    assert np.all(result.outcome == "reached")
    summary = summarize(result, report)
    assert summary["success_rate"] == 1.0
    sequential = float(move_times(DESI, crossing.start, crossing.target).sum())
    bound = lower_bound_s(crossing)
    # The trajectory ends exactly at the target; the optimum must beat "one waits for the other".
    np.testing.assert_allclose(result.trajectory.joints[-1], crossing.target, atol=1e-12)
    assert bound <= result.trajectory.duration_s + 1e-9
    assert result.trajectory.duration_s < sequential
    assert summary["makespan_s"] <= sequential


def test_central_never_beats_the_bound_and_samples_the_instrument_grid(crossing_central) -> None:
    traj = crossing_central.trajectory
    assert np.max(np.diff(traj.times)) <= make_settings("central", crossing_central.scenario).output_dt_s + 1e-12


def test_energy_mode_at_fixed_makespan(crossing: Scenario, crossing_central) -> None:
    makespan = 1.5 * crossing_central.trajectory.duration_s
    result = central_reference(crossing, {"mode": "energy", "makespan_s": makespan})
    assert result.stats["verified"] is True
    assert verify(crossing, result.trajectory).ok
    assert result.trajectory.duration_s == pytest.approx(makespan, rel=1e-6)
    # More time, less energy than the minimum-time solution.
    assert energy(result.trajectory) < energy(crossing_central.trajectory)


def test_three_positioners_with_a_bystander() -> None:
    """A third positioner with no target may step aside but must end where it started."""
    base = np.array([[0.0, 0.0], [0.0, 10.4], [9.0067, 5.2]])
    sc = _desi_pair([(2.6, 3.8), (-2.6, 6.6), (4.5, 5.2)], [(-2.6, 3.8), (2.6, 6.6), (4.5, 5.2)], base)
    sc = dataclasses.replace(sc, target_kind=np.array([TARGET_JOINTS, TARGET_JOINTS, TARGET_NONE]))
    result = central_reference(sc, {"steps": 30})
    assert result.stats["verified"] is True
    assert verify(sc, result.trajectory).ok
    np.testing.assert_allclose(result.trajectory.joints[-1, 2], sc.start[2], atol=1e-12)


def test_nothing_to_move_holds_still(crossing: Scenario) -> None:
    still = dataclasses.replace(crossing, target_values=crossing.start_deg)
    result = plan(still, "central")
    assert np.all(result.outcome == "reached")
    assert verify(still, result.trajectory).ok


def test_a_colliding_candidate_is_reported_failed(crossing: Scenario, monkeypatch: pytest.MonkeyPatch) -> None:
    """Item 2 of the issue: a central solution the verifier rejects is never returned as optimal."""
    import fiberplan.planners.central.solve as solve_module
    import fiberplan.studies.reference as reference_module

    real = reference_module.solve_central

    def colliding(*args, **kwargs):
        solution, problem = real(*args, **kwargs)
        straight, _ = solve_module._straight_guess(problem, 1.0)
        for cand in solution.candidates:
            cand.joints = straight
            cand.makespan_s = problem.lower_bound_s
        return solution, problem

    monkeypatch.setattr(reference_module, "solve_central", colliding)
    result = central_reference(crossing, {"warm_start": ["sequential"]})
    assert result.stats["verified"] is False
    assert result.stats["rejected"] and result.stats["rejected"][0]["collisions"] >= 1
    assert np.all(result.outcome == "failed")
    assert verify(crossing, result.trajectory).ok  # holding still is safe


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"mode": "fastest"}, "'mode' must be one of time, energy, found 'fastest'"),
        ({"steps": 1}, r"'steps' = 1 is outside its valid range integer in \[2, 2000\]"),
        ({"warm_start": []}, "warm_start needs at least one start"),
        ({"warm_start": ["central"]}, "cannot name 'central'"),
        ({"margin_mm": -1.0}, r"'margin_mm' = -1.0 mm is outside its valid range \[0, 10\] mm"),
    ],
)
def test_bad_settings(crossing: Scenario, overrides: dict, match: str) -> None:
    with pytest.raises(PlannerError, match=match):
        make_settings("central", crossing, overrides)


def test_energy_mode_below_the_bound_is_refused(crossing: Scenario) -> None:
    settings = make_settings("central", crossing, {"mode": "energy", "makespan_s": 0.5 * lower_bound_s(crossing)})
    with pytest.raises(PlannerError, match="lower bound"):
        solve_central(crossing, settings)


def test_unknown_warm_start_planner(crossing: Scenario) -> None:
    with pytest.raises(PlannerError, match="warm_start 'nope' is neither a built-in start"):
        make_settings("central", crossing, {"warm_start": ["nope"]})


def test_warm_start_planners_are_planned_by_the_registry(crossing: Scenario) -> None:
    settings = make_settings("central", crossing, {"warm_start": ["dnf"], "steps": 30})
    with pytest.raises(PlannerError, match="warm start 'dnf' needs that planner's result"):
        solve_central(crossing, settings)
    result = plan(crossing, "central", settings)  # the registry plans the dnf first
    assert result.stats["chosen"] == "dnf" or "dnf" in [c["source"] for c in result.stats["candidates"]]


def test_polygon_zones_are_separated_as_whole_bodies() -> None:
    """MOONS' own model: one separating line per zone pair of the interaction table (15), not per
    edge pair (134); a polygon's vertices enter once; a body pair's clearance is the smallest of its
    edge pairs'. Capsule instruments keep one body per capsule, in the same order."""
    from fiberplan.geometry import pair_clearance
    from fiberplan.planners.central.nlp import _bodies, _capsule_points

    moons = load_instrument("moons")
    bodies = _bodies(moons)
    assert len(moons.capsule_pairs) == 134 and len(bodies.combos) == len(moons.zone_pairs) == 15
    assert not bodies.identity
    points = _capsule_points(moons, bodies)
    corners = {(int(b), x, y) for b, x, y in zip(points.body, points.dist, points.lateral, strict=True)}
    assert len(corners) == len(points.body) == 27  # 8 zones: a disc and 26 polygon corners, none twice
    rng = np.random.default_rng(3)
    base = np.array([[0.0, 0.0], [25.0, 0.0]])
    joints = np.stack([rng.uniform(moons.limits_rad[:, 0], moons.limits_rad[:, 1], size=(2, 2)) for _ in range(50)])
    edge = pair_clearance(moons, base, np.zeros(2), joints, np.array([[0, 1]])).clearance  # (50, 1, 134)
    body = bodies.reduce(edge)
    for b in range(len(bodies.combos)):
        np.testing.assert_array_equal(body[..., b], edge[..., bodies.of_combo == b].min(axis=-1))
    for name in ("desi", "sdss", "moons-capsules"):
        inst = load_instrument(name)
        assert _bodies(inst).identity
        np.testing.assert_array_equal(_bodies(inst).combos, np.array(inst.capsule_pairs))


def test_moons_zones_swap_converges_and_verifies() -> None:
    """Two MOONS positioners (MOONS' own zones) whose fibres swap sides: the reference converges
    from the one-after-the-other start and passes the verifier, between the bound and that start."""
    moons = load_instrument("moons")
    base = np.array([[0.0, 0.0], [25.0, 0.0]])

    def joints(xy: list[tuple[float, float]]) -> np.ndarray:
        return np.stack([inverse_kinematics(moons, base[i : i + 1], np.zeros(1), np.array([xy[i]]), np.ones(1))[0] for i in range(2)])

    scenario = Scenario(instrument=moons, ids=np.arange(2), base_xy=base, orient_deg=np.zeros(2),
                        start_deg=np.degrees(joints([(13.0, 6.0), (12.0, -6.0)])), target_kind=np.full(2, TARGET_JOINTS),
                        target_values=np.degrees(joints([(13.0, -6.0), (12.0, 6.0)])), target_parity=np.zeros(2, dtype=np.int64),
                        name="moons swap")
    result = central_reference(scenario, {"warm_start": ["sequential"]})
    assert result.stats["verified"] is True and result.stats["status"] == "Solve_Succeeded"
    assert verify(scenario, result.trajectory).ok
    one_after_other = float(move_times(moons, scenario.start, scenario.target).sum())
    assert lower_bound_s(scenario) <= result.stats["makespan_s"] < one_after_other


def test_a_failed_start_is_followed_by_the_next(crossing: Scenario) -> None:
    """One NLP, several starts: a start IPOPT cannot use (here non-finite) is followed by the next,
    whose solve counts too; a lazy round falls back on the candidate's warm start this way."""
    from fiberplan.planners.central.nlp import _activate, _make_problem, _solve_nlp
    from fiberplan.planners.central.solve import _sequential_guess

    settings = make_settings("central", crossing, {"warm_start": ["sequential"]})
    problem = _make_problem(crossing, settings)
    q, tau = _sequential_guess(problem)
    active = np.argwhere(_activate(problem, q, settings.activation_window))
    alone, _ = _solve_nlp(problem, active, [(q, tau)])
    assert alone["status"] == "Solve_Succeeded"
    bad, _ = _solve_nlp(problem, active, [(np.full_like(q, np.nan), tau)])
    assert bad["status"] not in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    both, _ = _solve_nlp(problem, active, [(np.full_like(q, np.nan), tau), (q, tau)])
    assert both["status"] == "Solve_Succeeded"
    np.testing.assert_allclose(both["q"], alone["q"], atol=1e-9)
    assert both["solve_s"] > 0 and both["iterations"] >= alone["iterations"]


def test_the_cpu_time_limit_reaches_ipopt(crossing: Scenario) -> None:
    """``max_cpu_s`` is IPOPT's ``max_cpu_time``: a solve out of CPU time is not converged, and
    without the limit the same NLP converges."""
    from fiberplan.planners.central.nlp import _activate, _make_problem, _solve_nlp
    from fiberplan.planners.central.solve import _sequential_guess

    for cpu_s, converged in ((1e-9, False), (None, True)):
        settings = make_settings("central", crossing, {"warm_start": ["sequential"], "max_cpu_s": cpu_s})
        problem = _make_problem(crossing, settings)
        q, tau = _sequential_guess(problem)
        active = np.argwhere(_activate(problem, q, settings.activation_window))
        raw, _ = _solve_nlp(problem, active, [(q, tau)])
        assert (raw["status"] == "Solve_Succeeded") is converged
        if not converged:
            assert raw["status"] == "Maximum_CpuTime_Exceeded"


def test_moons_limits_each_solve_by_cpu_time() -> None:
    """MOONS' preset limits each solve by CPU time (the same iterations on a loaded machine), with a
    wall-time limit only as a net six times as long."""
    from fiberplan.planners.central import CentralSettings

    settings = CentralSettings.for_instrument(load_instrument("moons"))
    assert settings.max_cpu_s == 300.0 and settings.max_wall_s == 1800.0


def test_a_solution_short_of_lines_is_not_converged(crossing: Scenario) -> None:
    """A solve whose solution needs lines it did not have, with no lazy round left, is not
    converged (the lines are not added after the last solve and then counted as if solved with)."""
    settings = make_settings("central", crossing, {"warm_start": ["sequential"], "activate_mm": 0.5, "activation_window": 0,
                                                   "lazy_rounds": 0})
    cand = solve_central(crossing, settings)[0].candidates[0]
    assert cand.rounds == 1 and not cand.converged and cand.status == "Lazy_Rounds_Exhausted"
    more = solve_central(crossing, dataclasses.replace(settings, lazy_rounds=4))[0].candidates[0]
    assert more.converged and more.rounds > 1 and more.lines > cand.lines


@pytest.mark.parametrize("name, mode", [("sdss", "time"), ("moons", "time"), ("desi", "energy")])
def test_assembled_derivatives_equal_casadis_own(name: str, mode: str) -> None:
    """The Jacobian and the Hessian of the Lagrangian IPOPT is given (each line's kernel mapped
    over the lines, its entries summed into place) equal CasADi's differentiation of the whole
    NLP, at random points and multipliers: capsules (SDSS), polygon zones with lateral offsets
    (MOONS' own model), the energy mode (DESI). The rows keep their keys' order (the warm starts
    carry multipliers by key): separation rows by side, point, knot and line, then the norm rows."""
    import casadi as ca

    from fiberplan.planners.central.nlp import _KIND, _activate, _expressions, _make_problem
    from fiberplan.planners.central.solve import _straight_guess
    from fiberplan.studies.scenarios import hard_scenario

    scenario = hard_scenario(name, 3, 0)
    settings = make_settings("central", scenario, {"mode": mode, "steps": 8, "activate_mm": 5.0})
    problem = _make_problem(scenario, settings)
    q, _ = _straight_guess(problem, 1.2)
    active = np.argwhere(_activate(problem, q, 0))
    ex = _expressions(problem, active)
    assert len(active) > 20 and len(np.unique(active[:, 2])) > (5 if name == "moons" else 0)  # MOONS: many body pairs
    kinds = ex.row_keys // _KIND
    assert np.all(np.diff(kinds) >= 0) and set(kinds.tolist()) == {0, 1, 2}  # speed, separation, norm rows
    assert np.all(np.diff(ex.row_keys[kinds == 2]) > 0)  # the norm rows line by line
    given = ex.functions
    z, g = ex.z, ex.g
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", g.shape[0])
    own_hess = ca.Function("h", [z, lam_f, lam_g], [ca.triu(ca.hessian(lam_f * ex.objective + ca.dot(lam_g, g), z)[0])])
    own_jac = ca.Function("j", [z], [g, ca.jacobian(g, z)])
    rng = np.random.default_rng(1)
    for _ in range(3):
        x, lf, lg = rng.normal(size=z.shape[0]), rng.normal(), rng.normal(size=g.shape[0])
        x[(problem.steps + 1) * problem.n * 2] = 1.0 + abs(x[0])  # tau > 0
        h_given, h_own = (np.array(ca.densify(h)) for h in (given["hess_lag"](x, [], lf, lg), own_hess(x, lf, lg)))
        np.testing.assert_allclose(h_given, h_own, rtol=1e-12, atol=1e-12 * np.abs(h_own).max())
        g_given, j_given = given["jac_g"](x, [])
        g_own, j_own = own_jac(x)
        np.testing.assert_allclose(np.array(g_given), np.array(g_own), rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(np.array(ca.densify(j_given)), np.array(ca.densify(j_own)), rtol=1e-12, atol=1e-12)
        _, grad_given = given["grad_f"](x, [])
        grad_own = ca.Function("gf", [z], [ca.gradient(ex.objective, z)])(x)
        np.testing.assert_allclose(np.array(grad_given).ravel(), np.array(grad_own).ravel(), rtol=1e-13)
        # The separation rows themselves, from their keys, by the numpy kinematics.
        np.testing.assert_allclose(np.array(g_given).ravel()[kinds == 1], _separation_rows(problem, active, ex.row_keys[kinds == 1], x),
                                   rtol=1e-12, atol=1e-12)


def _separation_rows(problem: Any, active: np.ndarray, keys: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Each separation row ``s (n . (x_p - m) - c) - r_p - m rho / 2 - rho (c_a da^2 + c_b db^2)``
    of the central NLP from its key (line, side, point, knot), with numpy."""
    from fiberplan.planners.central.nlp import _KIND, _end_relief, _line_codes, _point_positions

    sc, pts = problem.scenario, problem.points
    n_q = (problem.steps + 1) * problem.n * 2
    q = x[:n_q].reshape(problem.steps + 1, problem.n, 2)
    code, rest = np.divmod(keys - _KIND, 2 * len(pts.arm) * 2)
    side, rest = np.divmod(rest, len(pts.arm) * 2)
    point, dk = np.divmod(rest, 2)
    line = np.searchsorted(_line_codes(problem, active), code)
    assert np.all(_line_codes(problem, active)[line] == code)
    k, pair = active[line, 0], active[line, 1]
    pos = sc.pairs[pair, side]
    xy = _point_positions(sc.instrument, pts, sc.base_xy, sc.orient, q)[k + dk, pos, point]
    mid = 0.5 * (sc.base_xy[sc.pairs[pair, 0]] + sc.base_xy[sc.pairs[pair, 1]])
    nx, ny, c = (x[n_q + 1 + 3 * line + t] for t in range(3))
    sign = np.where(side == 0, 1.0, -1.0)
    relief = _end_relief(problem, active)[line]
    d = q[k + 1, pos] - q[k, pos]
    chord = relief * (pts.chord_alpha[point] * d[:, 0] ** 2 + pts.chord_beta[point] * d[:, 1] ** 2)
    const = pts.radius[point] + 0.5 * problem.settings.margin_mm * relief
    return sign * (nx * (xy[:, 0] - mid[:, 0]) + ny * (xy[:, 1] - mid[:, 1]) - c) - const - chord


def test_lazy_rounds_start_warm_from_the_last_round(crossing: Scenario, monkeypatch: pytest.MonkeyPatch) -> None:
    """A lazy round's NLP is the last one with a few lines more: its rows and variables keep
    their keys, so IPOPT starts from the last solution and its multipliers (new rows at zero).
    Both ways converge and verify; the warm rounds take fewer iterations. A round that adds more
    than ``_WARM_MAX_NEW`` of the lines starts cold (here the second round adds more)."""
    from fiberplan.planners.central import nlp
    from fiberplan.planners.central.nlp import _carried

    found, values = _carried(np.array([5, 1, 9]), np.array([50.0, 10.0, 90.0]), np.array([9, 2, 1, 5]))
    np.testing.assert_array_equal(found, [True, False, True, True])
    np.testing.assert_array_equal(values, [90.0, 0.0, 10.0, 50.0])
    base = {"warm_start": ["sequential"], "activate_mm": 0.5, "activation_window": 0}
    default = solve_central(crossing, make_settings("central", crossing, base))[0].candidates[0]
    assert default.converged and [a[:2] for a in default.attempts][:2] == [(0, False), (1, False)]
    monkeypatch.setattr(nlp, "_WARM_MAX_NEW", 10.0)
    runs = {}
    for warm in (True, False):
        settings = make_settings("central", crossing, {**base, "warm_rounds": warm})
        solution, _ = solve_central(crossing, settings)
        cand = solution.candidates[0]
        assert cand.converged and cand.rounds > 1
        assert verify(crossing, central_reference(crossing, {**base, "warm_rounds": warm}).trajectory).ok
        runs[warm] = cand
    assert runs[True].iterations < runs[False].iterations
    assert [a[:2] for a in runs[True].attempts][:2] == [(0, False), (1, True)]  # round 0 cold, round 1 warm
    assert not any(warm for _, warm, *_ in runs[False].attempts)


def test_given_starts_best_solves_from_the_best_trajectory_at_hand(crossing: Scenario) -> None:
    """``given_starts = "best"``: of the trajectories at hand (compare passes its mpc and dnf
    results) only the best is a start: complete first, then the earliest last arrival."""
    dnf = plan(crossing, "dnf")
    assert summarize(dnf)["reached"] == 2
    held = dataclasses.replace(dnf, planner="mpc", trajectory=Trajectory(np.array([0.0, 1.0]), np.stack([crossing.start] * 2)))
    waits = Trajectory(np.concatenate([[0.0], dnf.trajectory.times + 1.0]), np.concatenate([crossing.start[None], dnf.trajectory.joints]))
    slow = dataclasses.replace(dnf, planner="prioritized", trajectory=waits)  # the dnf's plan a second later
    base = {"warm_start": ["sequential"], "steps": 30}

    def sources(given_starts: str) -> list[str]:
        settings = make_settings("central", crossing, base | {"given_starts": given_starts})
        return sorted(c.source for c in solve_central(crossing, settings, warm_results=[held, slow, dnf])[0].candidates)

    assert sources("all") == ["dnf", "mpc", "prioritized", "sequential"]
    assert sources("best") == ["dnf", "sequential"]  # complete and earliest: not the one that waits 1 s first
    with pytest.raises(Exception, match="given_starts"):
        make_settings("central", crossing, {"given_starts": "some"})
