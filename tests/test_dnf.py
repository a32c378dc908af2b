"""The ``dnf`` planner: collision-free on every instrument (checked by the verifier), success on
DESI, exact arrival, deadlock marking, the convergence condition, potentials and settings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fiberplan.errors import PlannerError
from fiberplan.generate import make_scenario
from fiberplan.instrument_io import load_instrument
from fiberplan.metrics import summarize
from fiberplan.planners import make_settings, plan
from fiberplan.planners.dnf import (
    DnfSettings,
    convergence_bound,
    convergence_condition,
    ellipse_arm_distance,
    repulsion_potential,
    repulsion_slope,
)
from fiberplan.scenario import TARGET_XY, Scenario
from fiberplan.verify import verify


def _check(scenario, result):
    report = verify(scenario, result.trajectory)
    assert report.n_collisions == 0, report.to_dict()["collision_events"][:3]
    assert not report.limit_violations, report.limit_violations[:3]
    assert report.ok
    return report


@pytest.mark.parametrize(
    ("instrument", "n", "kind", "seed"),
    [
        ("desi", 7, "random", 0),
        ("desi", 19, "random", 1),
        ("desi", 19, "clustered", 2),
        ("moons-capsules", 7, "unfold", 0),
        ("moons-capsules", 7, "random", 1),
        ("sdss", 7, "random", 0),
        ("sdss", 7, "fold", 1),
    ],
)
def test_dnf_is_collision_free_and_within_limits(instrument, n, kind, seed):
    scenario = make_scenario(instrument, n, kind, seed)
    result = plan(scenario, "dnf", {"route": "direct"})
    _check(scenario, result)
    assert result.planner == "dnf"
    assert set(result.outcome.tolist()) <= {"reached", "deadlocked", "unfinished", "held"}
    assert np.allclose(np.diff(result.trajectory.times), scenario.instrument.control_dt_s)


@pytest.mark.parametrize(
    "overrides",
    [
        {"separation": "ellipse"},
        {"zone_priority": "move_time"},
        {"separation": "ellipse", "zone_priority": "move_time", "potential": "smooth"},
    ],
)
def test_moons_variants_are_collision_free(overrides):
    scenario = make_scenario("moons-capsules", 7, "unfold", 2)
    _check(scenario, plan(scenario, "dnf", overrides))


def test_fiber_space_attraction_of_reference_000_is_collision_free():
    scenario = make_scenario("desi", 19, "random", 5)
    result = plan(scenario, "dnf", {"attraction": "fiber", "lambda_repel": 0.05})
    _check(scenario, result)
    assert np.mean(result.outcome == "reached") > 0.5


def test_safety_layer_alone_keeps_positioners_apart():
    # Without repulsion the attraction drives straight at the neighbours; only the safety
    # layer stands between them and a collision.
    scenario = make_scenario("desi", 19, "random", 4)
    result = plan(scenario, "dnf", {"lambda_repel": 0.0, "deadlock_escape": "none"})
    _check(scenario, result)
    assert result.stats["safety_interventions"] > 0


def test_dnf_reaches_desi_targets():
    # Measured: every positioner reached on these seeds (formulations/dnf.md); the threshold
    # leaves room for one deadlock in 57.
    rates = []
    for seed in range(3):
        scenario = make_scenario("desi", 19, "random", seed)
        result = plan(scenario, "dnf", {"route": "direct"})
        report = _check(scenario, result)
        summary = summarize(result, report)
        rates.append(summary["success_rate"])
        assert summary["makespan_s"] < 4.0 * summary["lower_bound_s"] + 1.0
    assert np.mean(rates) >= 0.98


def test_reached_positioners_hold_their_target_joints_exactly():
    scenario = make_scenario("desi", 7, "random", 0)
    result = plan(scenario, "dnf", {"route": "direct"})
    reached = result.outcome == "reached"
    assert reached.all()
    assert np.array_equal(result.trajectory.joints[-1][reached], scenario.target[reached])
    # The run stops once everyone is there.
    assert result.trajectory.duration_s < result.stats["time_limit_s"]


def test_same_seed_gives_same_trajectory():
    scenario = make_scenario("desi", 19, "random", 6)
    a = plan(scenario, "dnf")
    b = plan(scenario, "dnf")
    assert np.array_equal(a.trajectory.joints, b.trajectory.joints)
    assert np.array_equal(a.outcome, b.outcome)


def _overlapping_targets() -> Scenario:
    """Two DESI positioners whose targets are 2.5 mm apart: inside each other's 4 mm envelope."""
    inst = load_instrument("desi")
    return Scenario(
        instrument=inst,
        ids=np.array([3, 4]),
        base_xy=np.array([[0.0, 0.0], [inst.pitch_mm, 0.0]]),
        orient_deg=np.zeros(2),
        start_deg=np.array([[180.0, 0.0], [0.0, 0.0]]),
        target_kind=np.full(2, TARGET_XY),
        target_values=np.array([[5.0, 0.5], [7.5, 0.5]]),
        target_parity=np.zeros(2, dtype=int),
        instrument_preset="desi",
    )


def test_overlapping_envelopes_deadlock_and_are_marked():
    # Reference 000's potential with targets closer than D: the repulsion at the targets is
    # not zero, so both settle off target (a local minimum); the planner must say so and stop.
    scenario = _overlapping_targets()
    result = plan(scenario, "dnf", {"goal_envelope_cap": False, "lambda_repel": 36.0, "deadlock_escape": "none", "route": "direct"})
    _check(scenario, result)
    assert result.outcome.tolist() == ["deadlocked", "deadlocked"]
    assert result.stats["n_deadlocked"] == 2
    assert not result.stats["time_limit_hit"]
    assert result.trajectory.duration_s < result.stats["time_limit_s"]


def test_goal_envelope_cap_removes_that_minimum():
    scenario = _overlapping_targets()
    result = plan(scenario, "dnf", {"route": "direct"})
    _check(scenario, result)
    assert result.outcome.tolist() == ["reached", "reached"]


def test_time_limit_marks_moving_positioners_failed():
    scenario = make_scenario("desi", 7, "random", 0)
    result = plan(scenario, "dnf", {"time_limit_s": 0.05, "route": "direct"})
    _check(scenario, result)
    assert result.stats["time_limit_hit"]
    assert "unfinished" in result.outcome.tolist()
    assert result.trajectory.duration_s == pytest.approx(0.05)


def test_convergence_condition_as_printed():
    inst = load_instrument("desi")
    # Reference 000, tables 3-4: R = 7, D = 4, d = 2 mm, lambda_1 = 1, lambda_2 = 0.05.
    assert convergence_bound(7.0, 4.0, 2.0) == pytest.approx(4.0 / (7.0 * 12.0))
    printed = convergence_condition(inst, 1.0, 0.05, 2.0)
    assert (printed.R_mm, printed.D_mm, printed.d_mm) == (7.0, 4.0, 2.0)
    assert printed.ratio == pytest.approx(20.0)
    assert not printed.holds
    strong = convergence_condition(inst, 1.0, 25.0, 2.0)
    assert strong.holds and strong.ratio < strong.bound
    # The boundary: lambda_2 = 21 lambda_1 is exactly the bound, so it does not hold.
    assert not convergence_condition(inst, 1.0, 21.0, 2.0).holds
    assert convergence_condition(inst, 1.0, 21.01, 2.0).holds


def test_convergence_condition_takes_the_worst_capsule_combination():
    inst = load_instrument("moons-capsules")
    check = convergence_condition(inst, 1.0, 100.0, 2.0)
    bounds = [
        convergence_bound(inst.extent_mm, d + 2.0, d)
        for d in (inst.capsules[a].radius_mm + inst.capsules[b].radius_mm for a, b in inst.capsule_pairs)
    ]
    assert check.bound == pytest.approx(min(bounds))


@pytest.mark.parametrize(("args", "match"), [((1.0, 0.0, 2.0), "lambda_repel"), ((1.0, 1.0, -1.0), "envelope_mm")])
def test_convergence_condition_rejects_bad_parameters(args, match):
    with pytest.raises(PlannerError, match=match):
        convergence_condition(load_instrument("desi"), *args)
    with pytest.raises(PlannerError, match="0 < d < D"):
        convergence_bound(7.0, 2.0, 4.0)


@pytest.mark.parametrize("potential", ["reference", "smooth"])
def test_repulsion_slope_is_the_derivative_of_the_potential(potential):
    d, D = np.array(2.0), np.array(4.0)
    r = np.linspace(2.05, 3.99, 50)
    h = 1e-6
    numeric = (repulsion_potential(r + h, d, D, potential) - repulsion_potential(r - h, d, D, potential)) / (2 * h)
    assert np.allclose(repulsion_slope(r, d, D, potential), numeric, rtol=1e-5)
    assert np.all(repulsion_slope(r, d, D, potential) < 0)  # pushes apart
    assert np.all(repulsion_potential(r, d, D, potential) > 0)
    far = np.array([4.0, 5.0, 9.0])
    assert np.all(repulsion_potential(far, d, D, potential) == 0) and np.all(repulsion_slope(far, d, D, potential) == 0)
    # Unbounded as r -> d (up to the contact floor).
    assert repulsion_potential(np.array(2.0001), d, D, potential) > 1e3


def test_smooth_potential_has_no_slope_jump_at_the_envelope():
    d, D = np.array(2.0), np.array(4.0)
    inside = np.array(4.0 - 1e-7)
    assert abs(float(repulsion_slope(inside, d, D, "smooth"))) < 1e-5
    assert float(repulsion_slope(inside, d, D, "reference")) == pytest.approx(-2 * 4.0 / 12.0, rel=1e-5)


def test_ellipse_distance_gradient_matches_finite_differences():
    scenario = make_scenario("moons-capsules", 7, "random", 3)
    inst, q, pairs = scenario.instrument, scenario.start.copy(), scenario.pairs
    r, grad_i, grad_j = ellipse_arm_distance(inst, 0, scenario.base_xy, scenario.orient, q, pairs)
    assert np.all(r > 0)
    h = 1e-6
    for p, (i, j) in enumerate(pairs):
        for row, grad in ((i, grad_i), (j, grad_j)):
            for c in range(2):
                up, down = q.copy(), q.copy()
                up[row, c] += h
                down[row, c] -= h
                num = (
                    ellipse_arm_distance(inst, 0, scenario.base_xy, scenario.orient, up, pairs[p : p + 1])[0]
                    - ellipse_arm_distance(inst, 0, scenario.base_xy, scenario.orient, down, pairs[p : p + 1])[0]
                ) / (2 * h)
                assert num[0] == pytest.approx(grad[p, c], abs=1e-5)


def test_ellipse_distance_of_parallel_arms_touching_side_by_side_is_twice_the_radius():
    inst = load_instrument("moons-capsules")
    cap = inst.capsules[0]
    base = np.array([[0.0, 0.0], [0.0, 2 * cap.radius_mm]])
    joints = np.array([[0.0, 0.0], [0.0, 0.0]])
    r, _, _ = ellipse_arm_distance(inst, 0, base, np.zeros(2), joints, np.array([[0, 1]]))
    assert r[0] == pytest.approx(2 * cap.radius_mm)


@pytest.mark.parametrize("instrument", ["desi", "moons-capsules", "sdss"])
def test_defaults_follow_the_instrument(instrument):
    inst = load_instrument(instrument)
    settings = DnfSettings.for_instrument(inst)
    assert settings.dt_s == inst.control_dt_s
    # Same discrete loop gain as reference 000's lambda_1 = 1 at DESI's reach and 10 ms.
    assert 2 * settings.lambda_attract * inst.reach_max_mm**2 * settings.dt_s == pytest.approx(0.72)
    assert 0 < settings.envelope_mm <= 2.0
    if instrument == "desi":
        assert settings.lambda_attract == pytest.approx(1.0)
        assert settings.envelope_mm == 2.0  # D - d = 4 - 2 mm, reference 000 table 3


def test_class_defaults_are_the_desi_defaults():
    desi = DnfSettings.for_instrument(load_instrument("desi"))
    for field in dataclasses.fields(DnfSettings):
        assert getattr(DnfSettings(), field.name) == pytest.approx(getattr(desi, field.name)), field.name


def test_instrument_file_can_override_defaults():
    inst = load_instrument("desi")
    custom = dataclasses.replace(inst, planner_defaults={**inst.planner_defaults, "dnf": {"lambda_repel": 5.0}})
    assert DnfSettings.for_instrument(custom).lambda_repel == 5.0
    wrong = dataclasses.replace(inst, planner_defaults={"dnf": {"lambda_2": 5.0}})
    with pytest.raises(PlannerError, match="lambda_2"):
        DnfSettings.for_instrument(wrong)


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"attraction": "polar"}, "attraction"),
        ({"separation": "box"}, "separation"),
        ({"dt_s": 0.0}, "dt_s"),
        ({"lambda_repel": -1.0}, "lambda_repel"),
        ({"zone_spread": 1.0}, "zone_spread"),
        ({"deadlock_escape": "noise"}, "deadlock_escape"),
        ({"time_limit_s": -1.0}, "time_limit_s"),
        ({"no_such_setting": 1}, "no_such_setting"),
    ],
)
def test_bad_settings_are_rejected(overrides, match):
    scenario = make_scenario("desi", 7, "random", 0)
    with pytest.raises(PlannerError, match=match):
        make_settings("dnf", scenario, overrides)


@pytest.mark.slow
def test_desi_500_meets_the_issue_target():
    # Issue 3, "done when": 500 DESI positioners, seed 1: zero collisions, success >= 0.99.
    scenario = make_scenario("desi", 500, "random", 1)
    result = plan(scenario, "dnf", {"route": "direct"})
    summary = summarize(result, _check(scenario, result))
    assert summary["collisions"] == 0
    assert summary["success_rate"] >= 0.99


@pytest.mark.slow
@pytest.mark.parametrize("instrument", ["moons-capsules", "sdss"])
def test_dnf_61_is_collision_free_on_long_arm_instruments(instrument):
    scenario = make_scenario(instrument, 61, "unfold" if instrument == "moons-capsules" else "random", 0)
    result = plan(scenario, "dnf", {"route": "direct"})
    _check(scenario, result)
    assert set(result.outcome.tolist()) <= {"reached", "deadlocked", "unfinished", "held"}
