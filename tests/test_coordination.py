"""The coordination layer (planners/coordination.py) and the pre-check of targets: every target
reached through the problem's structure, one continuous verified trajectory, nothing dropped."""

from __future__ import annotations

import json
import multiprocessing
import os
import subprocess
import sys

import numpy as np
import pytest

import fiberplan as fp
from fiberplan.planners.coordination import leg_scenario
from fiberplan.planners.coordination.settings import REVERSE_LEG
from fiberplan.planners.mpc import plan_mpc
from fiberplan.scenario import scenario_from_dict

OWN_ROUTES = {"route_prioritized_up_to": 0, "route_retract_up_to": 0}
"""The planner's own routes only: tests of the layer's other rules, on groups small enough for the
prioritized schedule and the direct plan's partial retraction to be candidates too."""


def _check(scenario, result):
    report = fp.verify(scenario, result.trajectory)
    assert report.ok, report.to_dict()["collision_events"][:2]
    np.testing.assert_array_equal(result.trajectory.joints[0], scenario.start)
    return fp.summarize(result, report)


@pytest.mark.parametrize("planner", ["mpc", "dnf"])
def test_unfold_is_the_reverse_of_a_fold(planner):
    sc = fp.make_scenario("moons-capsules", 19, "unfold", 1)
    result = fp.plan(sc, planner)
    assert result.stats["route"] == "auto" and result.stats["chosen"] == "reverse"
    summary = _check(sc, result)
    assert summary["reached"] == summary["targets"] == 19
    # Played backwards it is a fold from the targets: the same motion, reversed (the leg's kind
    # tells the mpc's motor governor to apply the speed-change rule reversed).
    fold = fp.plan(leg_scenario(sc, sc.target, sc.start, REVERSE_LEG), planner, {"route": "direct"})
    np.testing.assert_array_equal(result.trajectory.joints, fold.trajectory.joints[::-1])


def test_via_datum_passes_through_the_datum_and_reaches_every_target():
    sc = fp.make_scenario("moons-capsules", 19, "random", 2)
    result = fp.plan(sc, "mpc", {"route": "via_datum", "route_overlap": False})
    summary = _check(sc, result)
    assert summary["reached"] == 19
    legs = result.stats["legs"]
    assert [leg["leg"] for leg in legs] == ["fold to the datum", "unfold from the datum (planned from the targets)"]
    k = round(legs[0]["t1_s"] / result.settings["dt_s"])
    datum = np.array(sc.instrument.datum_rad)
    np.testing.assert_allclose(result.trajectory.joints[k], np.broadcast_to(datum, (19, 2)), atol=1e-12)
    assert result.stats["n_via_datum"] == 19


def test_partial_folds_on_sdss_turn_alpha_less_than_the_datum_and_reach_every_target():
    # SDSS' datum alpha (10 deg) is at one end of its alpha range: each leg through the datum turns
    # alpha by up to 350 deg. Folded part of the way to half-way, the legs turn less.
    from fiberplan.planners.coordination import layer

    sc = fp.make_scenario("sdss", 37, "random", 1)
    result = fp.plan(sc, "mpc", OWN_ROUTES | {"route_groups": False})
    tried = {c["strategy"]: c for c in result.stats["candidates"]}
    assert result.stats["chosen"] == "via a partial fold (0.4)"
    summary = _check(sc, result)
    assert summary["reached"] == summary["targets"] == 37
    makespan = tried["via a partial fold (0.4)"]["makespan_s"]
    assert result.trajectory.times[-1] == pytest.approx(makespan)
    # Every positioner passes through its fold: beta at the datum's, alpha 0.4 of the way to half-way.
    datum = np.array(sc.instrument.datum_rad)
    fold = np.column_stack([datum[0] + 0.4 * (0.5 * (sc.start[:, 0] + sc.target[:, 0]) - datum[0]), np.full(37, datum[1])])
    assert all(np.any(np.all(np.abs(result.trajectory.joints[:, i] - fold[i]) < 1e-12, axis=1)) for i in range(37))
    # It ends before any positioner could go through the datum to its target: the two legs through
    # the datum, which could not be shorter unless they stalled and met elsewhere, are not planned
    # (and the fold at 0.3, whose own floor is no shorter, neither).
    assert makespan < layer._way_s(sc, layer._datum(sc)) - layer.FLOOR_MARGIN_S and set(tried) == {"via a partial fold (0.4)"}
    off = fp.plan(sc, "mpc", OWN_ROUTES | {"route_groups": False, "route_partial_folds": False})
    assert [c["strategy"] for c in off.stats["candidates"]] == ["via_datum"]
    assert makespan < 0.8 * off.trajectory.times[-1]


def test_partial_folds_are_planned_only_where_their_bounds_promise_a_gain(monkeypatch):
    # MOONS' datum alpha (0) is in the middle of its range: the partial folds' legs promise no gain.
    from fiberplan.planners.coordination import layer

    planned = []
    monkeypatch.setattr(layer, "_via_datum", lambda scenario, plan_leg, opts, part_way=0.0: planned.append(
        (scenario.instrument.name, part_way)))
    opts = layer._Options(4, None, False, 0.0, 1, 0.02, partial_folds=True)
    for inst in ("moons-capsules", "sdss"):
        sc = fp.make_scenario(inst, 61, "random", 1)
        assert layer._partial_folds(sc, None, opts, lambda name, pieces: {}) == np.inf
    assert planned == [("sdss", 0.4), ("sdss", 0.3)]
    # Not where a positioner's own way through the fold is already as long as the best plan found
    # (the fold at 0.4 here ending just after, or at, the floor of the fold at 0.3).
    floor = layer._way_s(sc, layer._held(sc, layer._folded_part_way(sc, sc.start, 0.3)))
    for makespan, expected in ((floor + 0.01, [("sdss", 0.4), ("sdss", 0.3)]), (floor, [("sdss", 0.4)])):
        planned.clear()
        layer._partial_folds(sc, None, opts, lambda name, pieces, m=makespan: {"short": 0, "makespan_s": m})
        assert planned == expected


def test_overlapped_legs_still_pass_every_positioner_through_the_datum_and_end_sooner():
    sc = fp.make_scenario("moons-capsules", 19, "random", 2)
    apart = fp.plan(sc, "mpc", {"route": "via_datum", "route_overlap": False})
    together = fp.plan(sc, "mpc", {"route": "via_datum"})
    summary = _check(sc, together)
    assert summary["reached"] == 19
    assert together.stats["overlap_s"] > 0
    assert together.trajectory.duration_s == pytest.approx(apart.trajectory.duration_s - together.stats["overlap_s"])
    datum = np.array(sc.instrument.datum_rad)
    at_datum = np.all(np.abs(together.trajectory.joints - datum) < 1e-12, axis=2)  # (T, N)
    assert at_datum.any(axis=0).all()  # every positioner still passes through the datum


def test_overlap_keeps_new_pairs_apart_or_is_refused():
    from fiberplan.planners.coordination.retime import _new_pairs_clear, _phases, overlap_legs

    sc = fp.make_scenario("moons-capsules", 19, "random", 2)
    result = fp.plan(sc, "mpc", {"route": "via_datum", "route_overlap": False})
    k = round(result.stats["legs"][0]["t1_s"] / result.settings["dt_s"])
    j1, j2 = result.trajectory.joints[: k + 1], result.trajectory.joints[k:]
    joints, shift = overlap_legs(sc, j1, j2, floor=0.0, coarse=5)
    assert 0 < shift < k and len(joints) == len(result.trajectory.joints) - shift
    assert fp.verify(sc, fp.Trajectory(np.arange(len(joints)) * result.settings["dt_s"], joints)).ok
    # No new pair can keep a floor of 100 mm: the overlap is then only as long as no new pair arises.
    _, shift_far = overlap_legs(sc, j1, j2, floor=100.0, coarse=5)
    assert shift_far < shift
    a, b = _phases(j1, j2)
    assert _new_pairs_clear(sc, j1, j2, a, b, shift_far, floor=np.inf)  # true only where there is no new pair
    assert not _new_pairs_clear(sc, j1, j2, a, b, shift, floor=np.inf)
    # With speed ramps, a positioner that turns back at the datum stays there ``rest`` samples at least.
    from fiberplan.planners.coordination.retime import turns_back

    back = turns_back(j1, j2)
    assert back.any()
    for rest in (4, 3 * k):
        rested, shift_rest = overlap_legs(sc, j1, j2, floor=0.0, coarse=5, rest=rest)
        assert shift_rest <= shift and len(rested) == len(j1) + len(j2) - 1 - shift_rest
        at_hold = np.all(rested == j1[-1][None], axis=2)  # (T, N)
        assert at_hold[:, back].sum(axis=0).min() >= rest + 1  # rest steps between arrival and departure
    assert shift_rest < 0  # rests longer than the legs' holds: the second leg starts later


def test_where_runs_meet_a_fast_reversal_waits_a_ramp_at_rest():
    """``ramp_rests``: everyone holds (as few samples as needed) where a joint turns back within
    ``rest`` samples at speeds adding up to more than the top; slow or rested reversals are left."""
    from fiberplan.planners.coordination.retime import ramp_rests

    top = np.array([0.1, 0.1])
    alpha = np.cumsum([0.0, 0.1, 0.1, -0.1, -0.1])  # full speed out and straight back
    joints = np.zeros((5, 2, 2))
    joints[:, 0, 0] = alpha
    joints[:, 1, 1] = np.linspace(0.0, 0.2, 5)  # another positioner, moving steadily
    rested, inserted = ramp_rests(joints, 3, top)
    assert inserted == 3
    np.testing.assert_array_equal(rested[:3], joints[:3])
    np.testing.assert_array_equal(rested[3:6], np.repeat(joints[2:3], 3, axis=0))  # everyone holds
    np.testing.assert_array_equal(rested[6:], joints[3:])
    assert ramp_rests(rested, 3, top)[1] == 0  # once rested, nothing more
    slow = joints.copy()
    slow[:, 0, 0] = np.cumsum([0.0, 0.05, 0.05, -0.05, -0.05])  # 0.05 + 0.05 <= the top: may turn at once
    assert ramp_rests(slow, 3, top)[1] == 0
    assert ramp_rests(joints, 0, top) == (joints, 0)  # no ramp: unchanged
    assert ramp_rests(joints, 3, top, where=np.array([True, True, False, True]))[1] == 0  # a step not counted (chattering samples)


def test_two_legs_on_a_ramped_instrument_keep_the_ramps_where_they_meet():
    """The legs, overlapped, with the mpc's governor keeping the ramps within each: executed as
    commands with 0.2 s ramps, no speed changes faster than they allow (3 such changes where the
    legs met before the rests)."""
    from fiberplan.instrument_io import load_instrument
    from fiberplan.ramps import verify_commands

    spec = load_instrument("moons-capsules").to_dict()
    spec["motors"]["ramp_time_s"] = 0.2
    scenario = scenario_from_dict(fp.make_scenario("moons-capsules", 19, "random", 2).to_dict() | {"instrument": spec}, origin="test")
    result = fp.plan(scenario, "mpc", {"route": "via_datum"})
    assert fp.summarize(result)["reached"] == 19 and result.stats["overlap_s"] > 0
    assert result.stats["ramp_rest_s"] > 0
    report = verify_commands(scenario, result.trajectory)
    assert report.ok and not [v for v in report.motor_violations if v.kind == "acceleration"]


def test_restarts_shorten_a_leg_with_stragglers_and_never_lengthen_one():
    sc = fp.make_scenario("moons-capsules", 61, "random", 0)
    fold = leg_scenario(sc, sc.target, np.broadcast_to(np.array(sc.instrument.datum_rad), (61, 2)), "fold")
    plain = fp.plan(fold, "mpc", {"route": "direct"})
    once = fp.plan(fold, "mpc", {"route_restarts": False} | OWN_ROUTES)  # a fold: the planner alone, through the layer
    assert once.stats["structure"] == "fold"
    np.testing.assert_array_equal(once.trajectory.joints, plain.trajectory.joints)
    shortened = fp.plan(fold, "mpc", OWN_ROUTES)
    assert shortened.stats["planner_runs"] > 1
    assert shortened.trajectory.duration_s < 0.9 * plain.trajectory.duration_s  # 37.85 s -> 19-20 s when measured
    summary = _check(fold, shortened)
    assert summary["reached"] == 61
    np.testing.assert_array_equal(shortened.trajectory.joints[:100], plain.trajectory.joints[:100])  # a restart keeps the start


@pytest.mark.parametrize(("instrument", "n", "seed"), [("moons-capsules", 19, 0), ("sdss", 19, 1)])
def test_auto_reaches_every_target_on_dense_instruments_and_is_never_worse_than_two_legs(instrument, n, seed):
    sc = fp.make_scenario(instrument, n, "random", seed)
    auto = fp.plan(sc, "mpc")
    summary = _check(sc, auto)
    assert summary["reached"] == summary["targets"]
    two = fp.plan(sc, "mpc", {"route": "via_datum"})
    assert summary["makespan_s"] <= fp.summarize(two)["makespan_s"] + 1e-9


def test_auto_keeps_the_direct_plan_where_it_is_complete():
    sc = fp.make_scenario("desi", 61, "random", 3)
    auto = fp.plan(sc, "mpc")
    alone = plan_mpc(sc, fp.make_settings("mpc", sc, {"route": "direct"}))
    np.testing.assert_array_equal(auto.trajectory.joints, alone.trajectory.joints)
    assert auto.stats["chosen"] == "direct" and auto.stats["qp_solves"] == alone.stats["qp_solves"]


def test_the_reactive_mpc_alone_stays_selectable():
    sc = fp.make_scenario("moons-capsules", 19, "random", 0)
    settings = {"route": "direct", "start_schedule": False}
    reactive = fp.plan(sc, "mpc", settings)
    alone = plan_mpc(sc, fp.make_settings("mpc", sc, settings))
    np.testing.assert_array_equal(reactive.trajectory.joints, alone.trajectory.joints)
    assert "route" not in reactive.stats


def _locked_infeasible_scenario():
    sc = fp.make_scenario("moons-capsules", 19, "random", 5)
    data = sc.to_dict()
    rows = data["positioners"]
    # Positioner 3 is locked where it starts; 7 has no target; 0 and 1 get targets that collide.
    rows[3]["locked"] = True
    rows[3]["target"] = None
    rows[7]["target"] = None
    a, b = rows[0], rows[1]
    mid = [(a["x_mm"] + b["x_mm"]) / 2, (a["y_mm"] + b["y_mm"]) / 2]
    a["target"] = {"x_mm": mid[0], "y_mm": mid[1]}
    b["target"] = {"x_mm": mid[0] + 0.5, "y_mm": mid[1]}
    return scenario_from_dict(data)


def test_infeasible_pair_is_reported_before_planning_and_the_rest_is_planned():
    sc = _locked_infeasible_scenario()
    why = {int(sc.ids[k]): reason for k, reason in sc.infeasible.items()}
    assert "collides with positioner 1's target" in why[0] and "collides with positioner 0's target" in why[1]
    result = fp.plan(sc, "mpc")
    summary = _check(sc, result)
    outcome = dict(zip(sc.ids.tolist(), result.outcome.tolist(), strict=True))
    assert outcome[0] == outcome[1] == "infeasible" and outcome[3] == "locked" and outcome[7] == "held"
    assert summary["reached"] == summary["targets"] == int(sc.has_target.sum()) >= 13  # everyone else
    assert summary["infeasible"] == len(sc.infeasible) >= 2 and summary["locked"] == 1
    joints = result.trajectory.joints
    assert np.all(joints[:, 3] == sc.start[3])  # the locked one never moves
    for k in (0, 1, 7):  # held ones end where they started
        np.testing.assert_allclose(joints[-1, k], sc.start[k], atol=1e-9)
    assert summary["not_reached"][0].startswith("infeasible: target collides with positioner 1")


@pytest.mark.parametrize("planner", ["dnf", "prioritized"])
def test_locked_positioners_never_move_whatever_the_planner(planner):
    sc = _locked_infeasible_scenario()
    result = fp.plan(sc, planner)
    assert np.all(result.trajectory.joints[:, 3] == sc.start[3])
    assert fp.verify(sc, result.trajectory).n_collisions == 0


def test_prioritized_is_a_registered_baseline():
    sc = fp.make_scenario("desi", 19, "random", 2)
    result = fp.plan(sc, "prioritized")
    summary = _check(sc, result)
    assert summary["reached"] == 19 and result.stats["restarts"] >= 0


def test_command_line_unfold_reaches_all_and_names_the_route(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "fiberplan.cli", "plan", "--instrument", "moons-capsules", "-n", "61", "--scenario-kind",
                           "unfold", "--seed", "1", "--planner", "mpc", "--json", "-q"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["reached"] == 61 and summary["collisions"] == 0
    assert summary["route"] == "reverse"  # the unfold is the fold from the targets, played backwards
    alone = fp.summarize(fp.plan(fp.make_scenario("desi", 7, "random", 0), "mpc", {"route": "direct"}))
    assert alone["route"] == "direct"


def test_a_restart_past_a_shortened_leg_is_not_planned():
    # dnf, MOONS 61 (capsules) unfold seed 2: a restart kept early in a round shortened the leg,
    # and a later cut lay past its end; planning it with no time left crashed the whole plan
    # ("need at least one array to concatenate", found by the real-instruments benchmark).
    sc = fp.make_scenario("moons-capsules", 61, "unfold", 2)
    result = fp.plan(sc, "dnf")
    summary = _check(sc, result)
    assert summary["reached"] == 61


def test_attempts_with_no_time_left_stay_at_the_start():
    from fiberplan.planners.coordination.legs import _attempts

    sc = fp.make_scenario("desi", 7, "random", 0)
    joints, runs, complete = _attempts(sc, lambda *a, **k: pytest.fail("no planner run expected"), 2, 0.0, False, False)
    np.testing.assert_array_equal(joints, sc.start[None])
    assert runs == 1 and not complete


@pytest.mark.parametrize("parks", [False, True])
def test_after_the_fallback_planner_this_planner_tries_again_from_where_it_stopped(monkeypatch, parks):
    # MOONS 61 unfold seed 35 under MOONS' zones, the fold from the targets: the mpc stalls, parks
    # folded neighbours, stalls again; the dnf from there brings no one more home, but the mpc from
    # the dnf's end brings all (before: no fallback once a leg had parked, and none after it).
    import types

    from fiberplan.planners.coordination import legs

    parked = []

    def parking(leg, end):
        if parks and not parked:
            parked.append(True)
            return end.copy()  # "parked" where they stand: the detour moves no one
        return None

    monkeypatch.setattr(legs, "_parking", parking)
    sc = fp.make_scenario("desi", 7, "random", 0)
    calls = []

    def still(joints):
        return types.SimpleNamespace(trajectory=fp.Trajectory(np.arange(len(joints)) * 0.01, joints))

    def plan_leg(leg, time_limit_s=None, use_fallback=False, progress=None):
        calls.append("fallback" if use_fallback else "own")
        if use_fallback:  # moves positioner 0 a little towards its target: no one more home
            nudged = leg.start.copy()
            nudged[0] += 1e-3 * np.sign(leg.target[0] - leg.start[0])
            return still(np.stack([leg.start, nudged]))
        if "after-fallback" not in leg.name:  # this planner stalls where it starts
            return still(np.stack([leg.start, leg.start]))
        return fp.plan(leg, "mpc", {"route": "direct"})

    notes = {}
    joints, _, complete = legs._attempts(sc, plan_leg, 2, None, True, False, None, notes)
    assert complete and calls.count("fallback") == 1 and calls[-2:] == ["fallback", "own"]
    assert notes["rescued"]  # the coordination layer then also tries the fallback planner's whole move
    assert bool(parked) == parks
    np.testing.assert_array_equal(joints[0], sc.start)
    np.testing.assert_array_equal(joints[-1], sc.target)
    assert fp.verify(sc, fp.Trajectory(np.arange(len(joints)) * 0.01, joints)).ok
    # With one fallback round (the rule before), the leg stops after the fallback.
    calls.clear()
    parked.clear()
    monkeypatch.setattr(legs, "FALLBACK_ROUNDS", 1)
    notes = {}
    _, _, complete = legs._attempts(sc, plan_leg, 2, None, True, False, None, notes)
    assert calls[-1] == "fallback" and not complete
    assert notes.get("rescued", False) == parks  # a fallback after parking is itself one of the later rounds


def test_fallback_rounds_that_move_no_one_end_the_leg_where_it_stood(monkeypatch):
    # MOONS 19 hard seed 1 (the mpc, the unfold leg of its two legs): both fallback rounds moved
    # no one, their pieces were empty, and the last solo pass took the last attempt from them
    # (IndexError: the whole plan crashed). The leg now ends, incomplete, where it stood.
    import types

    from fiberplan.planners.coordination import legs

    monkeypatch.setattr(legs, "_parking", lambda leg, end: None)
    monkeypatch.setattr(legs, "solo_moves", lambda leg, q, *a: (q[None],))
    sc = fp.make_scenario("desi", 7, "random", 0)
    calls = []

    def plan_leg(leg, time_limit_s=None, use_fallback=False, progress=None):
        calls.append("fallback" if use_fallback else "own")
        if use_fallback:  # one sample: nothing moves
            return types.SimpleNamespace(trajectory=fp.Trajectory(np.zeros(1), leg.start[None].copy()))
        if len(calls) == 1:  # the first attempt: positioner 0 moves a little, no one arrives
            nudged = leg.start.copy()
            nudged[0] += 1e-3 * np.sign(leg.target[0] - leg.start[0])
            joints = np.stack([leg.start, nudged])
        else:
            joints = np.stack([leg.start, leg.start])
        return types.SimpleNamespace(trajectory=fp.Trajectory(np.arange(len(joints)) * 0.01, joints))

    joints, _, complete = legs._attempts(sc, plan_leg, 2, None, True, False, (0.0, 0.01), {})
    assert not complete and calls.count("fallback") == legs.FALLBACK_ROUNDS
    np.testing.assert_array_equal(joints[0], sc.start)
    assert len(joints) == 2 and not np.array_equal(joints[-1], sc.start)  # the nudge kept, nothing lost or repeated


def _one_slow_candidate(monkeypatch, sc, name: str, structure: str):
    """The layer's routes replaced by one complete but slow candidate ``name`` (the direct plan
    after a 400-step wait; the fallback planner's own run keeps its routes). Returns the state
    whose ``"rescued"`` marks the candidate, and its joints."""
    from fiberplan.planners.coordination import layer

    quick = fp.plan(sc, "mpc", {"route": "direct"}).trajectory.joints
    slow = np.concatenate([sc.start[None].repeat(400, axis=0), quick])
    real, state = layer._strategies, {"rescued": True}

    def slow_candidate(scenario, route, plan_leg, opts, consider):
        if layer._WHOLE_FALLBACK.get():  # the fallback planner's own run
            return real(scenario, route, plan_leg, opts, consider)
        consider(name, [layer._Piece(name, slow, [], 1, 0.0, rescued=state["rescued"])])
        return structure

    monkeypatch.setattr(layer, "_strategies", slow_candidate)
    return state, slow


def test_a_plan_complete_only_through_the_later_fallback_rounds_is_weighed_against_the_fallback_planner(monkeypatch):
    """MOONS 61 unfold seed 23 under MOONS' zones: the reverse leg completes through the later
    fallback rounds in 51.6 s, the dnf's whole move in 13.7 s: the shorter is returned."""
    sc = fp.make_scenario("desi", 19, "random", 1)
    state, slow = _one_slow_candidate(monkeypatch, sc, "direct", "general")
    result = fp.plan(sc, "mpc", OWN_ROUTES)
    _check(sc, result)
    assert [c["strategy"] for c in result.stats["candidates"]] == ["direct", "fallback planner"]
    assert result.stats["chosen"] == "fallback planner"
    state["rescued"] = False  # a plan complete by the earlier rules is kept as it is
    result = fp.plan(sc, "mpc", OWN_ROUTES)
    assert [c["strategy"] for c in result.stats["candidates"]] == ["direct"]
    # On a field larger than route_rescue_up_to the rescued plan is kept as it is too (MOONS 500:
    # the other two cost most of the planning and were not shorter).
    state["rescued"] = True
    for up_to, tried in ((19, ["direct", "fallback planner"]), (18, ["direct"])):
        result = fp.plan(sc, "mpc", OWN_ROUTES | {"route_rescue_up_to": up_to})
        assert [c["strategy"] for c in result.stats["candidates"]] == tried
    _check(sc, result)
    np.testing.assert_array_equal(result.trajectory.joints[: len(slow)], slow)


def test_a_rescued_plan_is_weighed_against_the_direct_plan_too_when_the_fallback_planner_comes_first(monkeypatch):
    """MOONS 61 unfold seed 13 under MOONS' zones: the reverse met where it stalled (rescued, 171 s),
    the dnf's whole move 117.5 s, the direct plan 46.55 s: the direct plan is weighed even though
    the fallback planner's whole move (not itself marked rescued) came first."""
    sc = fp.make_scenario("desi", 19, "random", 1)
    _one_slow_candidate(monkeypatch, sc, "reverse", "unfold")
    result = fp.plan(sc, "mpc", OWN_ROUTES)
    _check(sc, result)
    assert [c["strategy"] for c in result.stats["candidates"]] == ["reverse", "fallback planner", "direct (fallback)"]
    assert result.stats["chosen"] != "reverse"
    assert not any("left positioners short" in w for w in result.warnings)  # the routes were complete, only longer


def test_when_every_route_leaves_positioners_short_the_fallback_planner_plans_the_whole_move(monkeypatch):
    """The fallback planner (the dnf for the mpc) alone over the whole move, with its own route,
    is a candidate once this planner's routes leave positioners short; the result says so."""
    from fiberplan.planners.coordination import layer

    real, calls = layer._strategies, []

    def nobody_moves_at_first(scenario, route, plan_leg, opts, consider):
        calls.append(route)
        if len(calls) > 1:  # the fallback planner's own run
            return real(scenario, route, plan_leg, opts, consider)
        consider("direct", [layer._Piece("direct", scenario.start[None].copy(), [], 1, 0.0)])
        return "general"

    monkeypatch.setattr(layer, "_strategies", nobody_moves_at_first)
    sc = fp.make_scenario("desi", 19, "random", 1)
    result = fp.plan(sc, "mpc", OWN_ROUTES)
    summary = _check(sc, result)
    assert summary["reached"] == 19
    assert result.stats["chosen"] == "fallback planner"
    assert result.stats["legs"][0]["leg"] == "fallback planner (dnf)"
    assert any("planned by the fallback planner dnf (" in w for w in result.warnings)
    # Without a fallback planner nothing else is tried.
    calls.clear()
    alone = fp.plan(sc, "mpc", {"route_fallback_planner": None} | OWN_ROUTES)
    assert alone.stats["chosen"] == "direct" and fp.summarize(alone)["reached"] == 0


def test_a_large_leg_with_few_away_is_planned_on_the_part_that_moves(monkeypatch):
    from fiberplan.planners.coordination import legs

    sc = fp.make_scenario("desi", 61, "random", 3)
    away = np.array([30, 31])  # two neighbours in the middle of the patch still to arrive, the others on their targets
    leg = leg_scenario(sc, np.where(np.isin(np.arange(61), away)[:, None], sc.start, sc.target), sc.target, "leg")
    seen = []

    def plan_leg(part, **kwargs):
        seen.append((part, kwargs))
        return fp.plan(part, "mpc", {"route": "direct"})

    whole, _ = legs._plan_part(leg, plan_leg, time_limit_s=5.0)  # 61 positioners: planned whole
    assert seen[-1][0] is leg and seen[-1][1] == {"time_limit_s": 5.0}
    monkeypatch.setattr(legs, "LOCAL_ABOVE", 10)
    joints, duration = legs._plan_part(leg, plan_leg, time_limit_s=5.0)
    part, kwargs = seen[-1]
    assert kwargs == {"time_limit_s": 5.0} and part.n_positioners < 61
    pairs = leg.pairs
    neighbours = set(pairs[np.isin(pairs, away).any(axis=1)].ravel().tolist())
    free = set(part.ids[~part.locked].tolist())
    assert free == neighbours  # the two and every neighbour of theirs may move (and yield) ...
    assert set(part.ids[part.locked].tolist()).isdisjoint(free) and not part.has_target[part.locked].any()  # ... the ring holds
    outside = ~np.isin(np.arange(61), part.ids)
    assert np.all(joints[:, outside] == leg.start[outside])  # the rest of the field holds
    assert joints.shape[1:] == (61, 2) and duration == pytest.approx((len(joints) - 1) * leg.instrument.control_dt_s)
    traj = fp.Trajectory(np.arange(len(joints)) * leg.instrument.control_dt_s, joints)
    assert fp.verify(leg, traj).ok and legs.at_targets(leg, joints[-1]).all()
    assert legs.at_targets(leg, whole[-1]).all()


def test_a_leg_is_restarted_by_its_last_arrival_within_the_tolerance_not_by_its_last_sample():
    # DESI 50,000 seed 0: the last arrival at 1.196 x the bound, the last sample (exactly on the
    # target) at 1.2016 x; four restarts then cost 80 s of planning and gained nothing.
    from fiberplan.kinematics import straight_path
    from fiberplan.planners.coordination.legs import RESTART_ABOVE, shorten_leg

    sc = fp.make_scenario("desi", 7, "random", 0)
    leg = leg_scenario(sc, sc.start, sc.target, "direct")
    dt = 0.01
    step = leg.instrument.speeds_rad_s * dt
    bound_s = float(np.max(np.abs(leg.target - leg.start) / leg.instrument.speeds_rad_s))
    k = int(np.ceil(bound_s / dt))
    moves = straight_path(leg.start, leg.target, step, k + 1)  # (N, K, 2), at the targets by the end
    joints = np.concatenate([leg.start[None], moves.transpose(1, 0, 2)])
    wait = int(np.ceil((RESTART_ABOVE - 1.0) * bound_s / dt)) + 3  # samples past 1.2 x the bound
    near = leg.target.copy()
    near[0, 1] += 1e-7  # within the tolerance disc, not exactly on the target
    joints = np.concatenate([joints, np.repeat(near[None], wait, axis=0), leg.target[None]])
    assert (len(joints) - 1) * dt > RESTART_ABOVE * bound_s
    kept, runs = shorten_leg(leg, joints, lambda *a, **kw: pytest.fail("no restart expected"), dt)
    assert runs == 0 and kept is joints
    # Away from the target (outside the disc) until the end: restarted.
    far = joints.copy()
    far[-wait - 1:-1, 0, 1] += 0.05
    with pytest.raises(RuntimeError, match="restart planned"):
        shorten_leg(leg, far, lambda *a, **kw: (_ for _ in ()).throw(RuntimeError("restart planned")), dt)


@pytest.mark.parametrize("stalls", ["fold to the datum", "fold from the targets"])
def test_two_legs_of_which_one_stalls_meet_where_it_stalled(monkeypatch, stalls):
    """A leg left short through every round ends in a collision-free configuration with a few
    positioners unfolded; the other leg is planned to that configuration instead of the datum,
    and the two legs join there: every target reached, one verified trajectory."""
    from fiberplan.planners.coordination import layer
    from fiberplan.planners.coordination.settings import UNFOLD_REVERSED_LEG

    sc = fp.make_scenario("moons-capsules", 19, "random", 2)
    settings = fp.make_settings("mpc", sc, {"route": "via_datum"})
    opts = layer._options(settings, sc)
    real = layer.complete_leg
    kind = "fold" if stalls == "fold to the datum" else UNFOLD_REVERSED_LEG
    stalled = []

    def one_leg_stalls(leg, *args, **kwargs):
        done = real(leg, *args, **kwargs)
        if leg.kind == kind and not stalled:  # cut where about half its positioners had arrived
            k = int(np.argmax((~np.all(done.joints == leg.target[None], axis=2)).sum(axis=1) <= 9))
            assert 0 < k < len(done.joints) - 1
            stalled.append(done.joints[k])
            return layer.Leg(done.joints[: k + 1], done.runs, False, k + 1, done.wall_s)
        return done

    monkeypatch.setattr(layer, "complete_leg", one_leg_stalls)
    monkeypatch.setattr(layer, "both", lambda f, g: (f(), g()))  # both legs in this process (the patch is seen)

    def plan_leg(leg, time_limit_s=None, use_fallback=False, progress=None):
        return fp.plan(leg, "mpc", {"route": "direct", "time_limit_s": time_limit_s})

    pieces = layer._via_datum(sc, plan_leg, opts)
    assert pieces is not None and all("meet where one stalled" in p.name for p in pieces) and all(p.rescued for p in pieces)
    meeting = stalled[0]
    assert not np.all(meeting == np.array(sc.instrument.datum_rad)), "the cut leaves positioners away from the datum"
    trajectory = layer._join(sc, pieces, opts.dt_s)
    # Every positioner passes through the configuration where the stalled leg ended (the legs are
    # overlapped: not all at one instant), exactly.
    assert all((trajectory.joints[:, i] == meeting[i]).all(axis=1).any() for i in range(19))
    np.testing.assert_array_equal(trajectory.joints[0], sc.start)
    np.testing.assert_array_equal(trajectory.joints[-1], sc.target)
    assert fp.verify(sc, trajectory).ok
    # Without the meeting (no round left), a stalled leg leaves the two-leg plan incomplete, as before.
    stalled.clear()
    monkeypatch.setattr(layer, "MEET_ROUNDS", 0)
    assert layer._via_datum(sc, plan_leg, opts) is None


def test_an_unfold_whose_reversed_fold_stalls_meets_it_where_it_stalled(monkeypatch):
    """The reverse route's fold from the targets left short through every round (MOONS 500 under
    MOONS' zones, seed 4: 5 of 500) ends in a collision-free configuration; the move from the
    starts is planned to it, and the reversed fold played on from there: every target reached,
    one verified trajectory, the same stalled leg played backwards at its end."""
    from fiberplan.planners.coordination import layer

    sc = fp.make_scenario("moons-capsules", 19, "unfold", 1)
    settings = fp.make_settings("mpc", sc, {"route": "reverse"})
    opts = layer._options(settings, sc)
    real = layer.complete_leg
    stalled = []
    runs = []  # the planner runs of every leg planned

    def the_reverse_stalls(leg, *args, **kwargs):
        done = real(leg, *args, **kwargs)
        runs.append(done.runs)
        if leg.kind == REVERSE_LEG and not stalled:  # cut where about half its positioners had arrived
            k = int(np.argmax((~np.all(done.joints == leg.target[None], axis=2)).sum(axis=1) <= 9))
            assert 0 < k < len(done.joints) - 1
            stalled.append(done.joints[: k + 1])
            return layer.Leg(done.joints[: k + 1], done.runs, False, k + 1, done.wall_s)
        return done

    monkeypatch.setattr(layer, "complete_leg", the_reverse_stalls)

    def plan_leg(leg, time_limit_s=None, use_fallback=False, progress=None):
        return fp.plan(leg, "mpc", {"route": "direct", "time_limit_s": time_limit_s})

    pieces = layer._reverse(sc, plan_leg, opts)
    assert pieces is not None and all(p.rescued for p in pieces) and "where the reverse stalled" in pieces[0].name
    trajectory = layer._join(sc, pieces, opts.dt_s)
    np.testing.assert_array_equal(trajectory.joints[0], sc.start)
    np.testing.assert_allclose(trajectory.joints[-1], sc.target, rtol=0, atol=1e-12)  # (the leg's start, through degrees and back)
    assert fp.verify(sc, trajectory).ok
    # Every positioner passes exactly through where the reverse stalled, and the stalled leg's own
    # motion, played backwards, is the trajectory's end.
    fold = stalled[0]
    meeting = fold[-1]
    assert (~np.all(meeting == sc.start, axis=1)).sum() >= 5, "the cut leaves positioners away from the datum"
    assert all((trajectory.joints[:, i] == meeting[i]).all(axis=1).any() for i in range(19))
    np.testing.assert_array_equal(trajectory.joints[-len(fold):], fold[::-1])
    assert sum(p.attempts for p in pieces) == sum(runs)  # each leg's runs once (the stalled one was counted twice)
    # Without the meeting (no round left), a stalled reverse is no candidate, as before.
    stalled.clear()
    monkeypatch.setattr(layer, "MEET_ROUNDS", 0)
    assert layer._reverse(sc, plan_leg, opts) is None


def test_a_fold_whose_direct_plan_stalls_is_completed_from_the_datum(monkeypatch):
    """The mirror of the reverse route's meeting: a fold's direct plan left short ends in a
    collision-free configuration; the move from the datum to it is planned and played backwards
    after it: every target reached, one verified trajectory that starts with the stalled plan."""
    from fiberplan.planners.coordination import layer

    sc = fp.make_scenario("moons-capsules", 19, "fold", 1)
    assert layer._is_at_datum(sc, sc.target)
    real = layer.complete_leg
    stalled = []

    def the_direct_plan_stalls(leg, *args, **kwargs):
        done = real(leg, *args, **kwargs)
        if not stalled:  # the first leg planned is the direct plan: cut where about half had arrived
            k = int(np.argmax((~np.all(done.joints == leg.target[None], axis=2)).sum(axis=1) <= 9))
            assert 0 < k < len(done.joints) - 1
            stalled.append(done.joints[: k + 1])
            return layer.Leg(done.joints[: k + 1], done.runs, False, k + 1, done.wall_s)
        return done

    monkeypatch.setattr(layer, "complete_leg", the_direct_plan_stalls)
    result = fp.plan(sc, "mpc", OWN_ROUTES | {"route_fallback_planner": None})
    tried = {c["strategy"]: c for c in result.stats["candidates"]}
    assert tried["direct"]["short"] > 0 and tried["direct, met from the datum"]["short"] == 0
    assert result.stats["chosen"] == "direct, met from the datum"
    assert result.stats["n_via_datum"] == 0  # (no leg through the datum; counted by the legs' names before)
    summary = _check(sc, result)
    assert summary["reached"] == summary["targets"] == 19
    head = stalled[0]
    np.testing.assert_array_equal(result.trajectory.joints[: len(head) - 1], head[:-1])  # the stalled plan first (up to an overlap)
    meeting = head[-1]
    assert all((result.trajectory.joints[:, i] == meeting[i]).all(axis=1).any() for i in range(19))


def test_a_straggling_tail_is_planned_backwards_from_the_goal_and_played_in_reverse():
    # MOONS 500 unfold seed 0: the fold from the targets brings 490 of 500 home by 13.7 s and the
    # last at 57.35 s; from the datum out to where those 10 stood takes 17.75 s (prototype).
    from fiberplan.kinematics import straight_path
    from fiberplan.planners.coordination.legs import RESTART_ABOVE, tail_backwards

    sc = fp.make_scenario("desi", 7, "random", 0)
    leg = leg_scenario(sc, sc.start, sc.target, "fold")
    dt = 0.01
    step = leg.instrument.speeds_rad_s * dt
    k = int(np.ceil(float(np.max(np.abs(leg.target - leg.start) / leg.instrument.speeds_rad_s)) / dt)) + 1
    moves = straight_path(leg.start, leg.target, step, k).transpose(1, 0, 2)
    mover = int(np.argmax(np.max(np.abs(leg.target - leg.start), axis=1)))
    # The others move as planned; the slowest waits at its start for 2 bounds, then goes.
    late = np.concatenate([np.repeat(leg.start[None, mover], 2 * k, axis=0), moves[:, mover]])
    joints = np.concatenate([leg.start[None], np.concatenate([moves, np.repeat(moves[-1:], 2 * k, axis=0)])])
    joints[1:, mover] = late
    assert fp.verify(sc, fp.Trajectory(np.arange(len(joints)) * dt, joints)).ok
    kinds = []

    def plan_leg(part, time_limit_s=None, use_fallback=False, progress=None):
        kinds.append(part.kind)
        return fp.plan(part, "mpc", {"route": "direct", "time_limit_s": time_limit_s})

    best, runs = tail_backwards(leg, joints, plan_leg, dt)
    assert runs >= 1 and set(kinds) == {REVERSE_LEG}  # played backwards within a forward leg
    assert len(best) < len(joints) - k  # the wait is gone
    np.testing.assert_array_equal(best[0], leg.start)
    np.testing.assert_array_equal(best[-1], leg.target)
    assert fp.verify(sc, fp.Trajectory(np.arange(len(best)) * dt, best)).ok
    # A leg within RESTART_ABOVE of its bound is kept as it is.
    quick = np.concatenate([leg.start[None], moves])
    assert (len(quick) - 1) * dt <= RESTART_ABOVE * k * dt
    kept, runs = tail_backwards(leg, quick, lambda *a, **kw: pytest.fail("no tail expected"), dt)
    assert runs == 0 and kept is quick


def test_two_legs_are_overlapped_with_and_without_their_backward_tails_and_the_shortest_kept(monkeypatch):
    """A backward tail shortens a leg but can change when its positioners leave the datum: MOONS
    500 random seed 2, both legs shorter, the overlapped whole longer (3.40 -> 3.82 x the bound)."""
    from fiberplan.planners.coordination import layer

    sc = fp.make_scenario("moons-capsules", 7, "random", 0)
    settings = fp.make_settings("mpc", sc, {"route": "via_datum"})
    opts = layer._options(settings, sc)
    datum = np.broadcast_to(np.array(sc.instrument.datum_rad), sc.start.shape)

    def leg_of(a, b, k):
        return np.concatenate([np.repeat(a[None], k, axis=0), np.repeat(b[None], 2, axis=0)])

    fold_tailed, fold_plain = leg_of(sc.start, datum, 10), leg_of(sc.start, datum, 12)
    back_tailed, back_plain = leg_of(sc.target, datum, 10), leg_of(sc.target, datum, 14)
    legs_made = iter([layer.Leg(fold_tailed, 2, True, 13, untailed=fold_plain), layer.Leg(back_tailed, 2, True, 16, untailed=back_plain)])
    monkeypatch.setattr(layer, "complete_leg", lambda *a, **kw: next(legs_made))
    monkeypatch.setattr(layer, "both", lambda f, g: (f(), g()))
    seen = []

    def overlap(scenario, j1, j2, *args, **kwargs):  # the plain fold overlaps the tailed unfold by 8 samples, the rest by 1
        seen.append((len(j1), len(j2)))
        shift = 8 if (j1 is fold_plain and len(j2) == len(back_tailed)) else 1
        return np.concatenate([j1[:-shift], j2]), shift

    monkeypatch.setattr(layer, "overlap_legs", overlap)
    pieces = layer._via_datum(sc, lambda *a, **kw: None, opts)
    assert sorted(seen) == sorted([(12, 12), (12, 16), (14, 12), (14, 16)])  # every form of each leg tried
    assert len(pieces) == 1 and pieces[0].overlap_steps == 8
    assert len(pieces[0].joints) == len(fold_plain) + len(back_tailed) - 8


def test_route_tails_off_plans_no_backward_tail(monkeypatch):
    from fiberplan.planners.coordination import layer, legs

    sc = fp.make_scenario("desi", 7, "random", 0)
    assert layer._options(fp.make_settings("mpc", sc, {"route_tails": False}), sc).tails is False
    assert layer._options(fp.make_settings("dnf", sc), sc).tails is True  # on by default, for every planner under the layer
    called = []
    monkeypatch.setattr(legs, "tail_backwards", lambda leg, joints, *a: (called.append(1), (joints, 0))[1])
    leg = leg_scenario(sc, sc.start, sc.target, "fold")

    def plan_leg(part, time_limit_s=None, use_fallback=False, progress=None):
        return fp.plan(part, "mpc", {"route": "direct", "time_limit_s": time_limit_s})

    legs.complete_leg(leg, plan_leg, 2, restarts=0.05, tails=False)
    assert not called
    legs.complete_leg(leg, plan_leg, 2, restarts=0.05, tails=True)
    assert called


def test_small_groups_whose_moves_cross_take_the_prioritized_schedule_where_it_is_shorter(monkeypatch):
    # SDSS 7 hard seed 3: the mpc's routes go through the datum (about 1.9 x the bound); the
    # prioritized schedule brings all 7 home at about 1.13 x, and at the bound (as the central
    # reference) where delayed moves and the longest ones may turn the faster joint late.
    from fiberplan.planners.coordination import layer
    from fiberplan.studies import hard_scenario

    sc = hard_scenario("sdss", 7, 3)
    auto = fp.plan(sc, "mpc")
    summary = _check(sc, auto)
    assert auto.stats["chosen"] == "prioritized" and summary["reached"] == 7
    assert summary["makespan_over_bound"] <= 1.01 and "faster joint late" in auto.stats["legs"][0]["leg"]
    with monkeypatch.context() as m:
        m.setattr(layer, "PRIORITIZED_SHAPES", layer.PRIORITIZED_SHAPES[:1])  # reference 003's schedule alone
        plain = fp.plan(sc, "mpc", {"route_retract_up_to": 0})
    assert plain.stats["chosen"] == "prioritized" and fp.summarize(plain)["makespan_over_bound"] >= 1.1
    own = fp.plan(sc, "mpc", OWN_ROUTES)
    assert "prioritized" not in {c["strategy"] for c in own.stats["candidates"]}
    assert summary["makespan_s"] < 0.8 * fp.summarize(own)["makespan_s"]
    # Planned on the run's own time grid.
    np.testing.assert_allclose(np.diff(auto.trajectory.times), auto.settings["dt_s"])
    # Above the limit, not tried.
    limited = fp.plan(sc, "mpc", {"route_prioritized_up_to": 6, "route_retract_up_to": 0})
    np.testing.assert_array_equal(limited.trajectory.joints, own.trajectory.joints)


def test_a_prioritized_plan_left_short_goes_through_a_retraction_of_the_short_ones(monkeypatch):
    from fiberplan.planners.coordination import layer
    from fiberplan.studies import hard_scenario

    sc = hard_scenario("sdss", 7, 1)  # the schedule places 5 of 7 at every slack tried
    settings = fp.make_settings("mpc", sc, {})
    opts = layer._options(settings, sc)
    with monkeypatch.context() as m:  # the datum's beta, at the target's alpha, alone
        m.setattr(layer, "RETRACTIONS", ((1.0, "target"),))
        found = layer._prioritized(sc, opts)
    (retraction,) = found["prioritized through a retraction"]
    assert set(found) == {"prioritized through a retraction"}
    traj = layer._join(sc, [retraction], settings.dt_s)
    assert fp.verify(sc, traj).ok
    np.testing.assert_allclose(traj.joints[-1], sc.target, rtol=0.0, atol=1e-12)
    # The two positioners left short pass through the datum's beta; the others never reach it.
    beta = sc.instrument.datum_rad[1]
    at_beta = np.any(np.isclose(retraction.joints[:, :, 1], beta, rtol=0.0, atol=1e-9), axis=0)
    assert int(at_beta.sum()) == 2 and "retraction of 2" in retraction.name
    # Every retraction tried: none longer than that one.
    (shortest,) = layer._prioritized(sc, opts)["prioritized through a retraction"]
    assert len(shortest.joints) <= len(retraction.joints)
    assert fp.verify(sc, layer._join(sc, [shortest], settings.dt_s)).ok
    # Through the layer: the shortest candidate, shorter than the two legs through the datum (the
    # direct plan's partial retraction and the partial folds aside: shorter still on this group,
    # 11.48 and 12.06 s against 13.96 s, their own tests).
    auto = fp.plan(sc, "mpc", {"route_retract_up_to": 0, "route_partial_folds": False})
    assert auto.stats["chosen"] == "prioritized through a retraction"
    via = {c["strategy"]: c for c in auto.stats["candidates"]}["via_datum"]
    assert fp.summarize(auto)["makespan_s"] < via["makespan_s"]


def test_where_retracting_the_short_ones_is_not_enough_their_neighbours_retract_too():
    from fiberplan.planners.coordination import layer
    from fiberplan.studies import hard_scenario

    sc = hard_scenario("sdss", 7, 8)  # 2 left short; retracting those 2 alone leaves a leg short
    settings = fp.make_settings("mpc", sc, {})
    opts = layer._options(settings, sc)
    home = sc.target
    _, reached, _, _ = layer._scheduled(sc, opts)
    short = ~reached
    assert int(short.sum()) == 2
    assert layer._through_retraction(sc, opts, home, short) is None
    found = layer._prioritized(sc, opts)
    (retraction,) = found["prioritized through a retraction"]
    assert "retraction of 7" in retraction.name
    traj = layer._join(sc, [retraction], settings.dt_s)
    assert fp.verify(sc, traj).ok
    np.testing.assert_allclose(traj.joints[-1], sc.target, rtol=0.0, atol=1e-12)


def test_a_small_dense_group_retracts_only_those_the_direct_plan_leaves_short_or_late():
    # SDSS 7 hard seed 1: the direct plan brings everyone home, the last ones late (33.2 s); the
    # late ones retract while the others go straight: 11.48 s, shorter than the prioritized
    # schedule's retraction (13.96 s), the partial fold (12.06 s) and the two legs through the datum
    # (16.98 s).
    from fiberplan.planners.coordination import layer
    from fiberplan.studies import hard_scenario

    sc = hard_scenario("sdss", 7, 1)
    auto = fp.plan(sc, "mpc")
    summary = _check(sc, auto)
    assert auto.stats["chosen"] == "direct through a retraction" and summary["reached"] == 7
    others = {c["strategy"]: c["makespan_s"] for c in auto.stats["candidates"] if c["strategy"] != auto.stats["chosen"]}
    # (The two legs through the datum are not planned: the partial fold at 0.4, 12.06 s, ends before
    # any positioner could pass through the datum to its target.)
    assert {"via a partial fold (0.4)", "direct"} <= set(others) and summary["makespan_s"] < min(others.values())
    assert "via_datum" not in others and others["via a partial fold (0.4)"] < layer._way_s(sc, layer._datum(sc)) - layer.FLOOR_MARGIN_S
    (leg,) = auto.stats["legs"]
    assert leg["leg"].startswith("direct through a retraction of ")
    retracted = int(leg["leg"].split("retraction of ")[1].split()[0])
    assert 0 < retracted < 7  # a partial retraction: some go straight
    # Off: not a candidate.
    off = fp.plan(sc, "mpc", {"route_retract_up_to": 6})
    assert "direct through a retraction" not in {c["strategy"] for c in off.stats["candidates"]}
    # The candidate alone is no longer than the best plan it was asked to beat.
    settings = fp.make_settings("mpc", sc, {})
    opts = layer._options(settings, sc)

    def plan_leg(leg, time_limit_s=None, use_fallback=False, progress=None):
        return fp.plan(leg, "mpc", {"route": "direct", "time_limit_s": time_limit_s})

    direct = layer._direct(sc, plan_leg, opts)[0]
    assert layer._direct_retraction(sc, plan_leg, opts, direct, shorter_than=10) is None  # nothing under 0.18 s


def test_no_prioritized_candidate_where_the_run_keeps_speed_ramps_between_its_runs():
    from fiberplan.instrument_io import load_instrument
    from fiberplan.studies import hard_scenario

    spec = load_instrument("sdss").to_dict()
    spec.setdefault("motors", {})["ramp_time_s"] = 0.2
    sc = hard_scenario("sdss", 7, 3)  # the schedule's plan is the shortest without ramps (above)
    ramped = scenario_from_dict(sc.to_dict() | {"instrument": spec}, origin="test")
    result = fp.plan(ramped, "mpc")
    assert result.settings["motor_limits"]
    assert not [c for c in result.stats["candidates"] if c["strategy"].startswith("prioritized")]
    assert fp.summarize(result)["reached"] == 7


def test_an_unfold_whose_fold_straggles_is_planned_again_with_paired_timed_paths(monkeypatch, tmp_path):
    # MOONS 61 unfold seed 6 (moons-capsules): the reversed fold ends at 29.25 s (2.8 x the
    # bound); planned again with the schedule's paired searches (schedule_pairs) it ends at
    # 27.95 s and is kept. schedule_pairs_retry = 0 plans the reverse alone, as before. (Without
    # group moves, which complete that fold at 22.6 s, as the paired fold does.)
    from fiberplan import _fork
    from fiberplan.metrics import lower_bound_s

    sc = fp.make_scenario("moons-capsules", 61, "unfold", 6)
    callers = tmp_path / "progress"

    def progress(fraction, phase=None):
        with open(callers, "a") as f:
            f.write(f"{os.getpid()}\n")

    result = fp.plan(sc, "mpc", {"route_groups": False}, progress=progress)
    tried = {c["strategy"]: c for c in result.stats["candidates"]}
    assert set(tried) == {"reverse", "reverse (paired timed paths)"}
    assert tried["reverse"]["makespan_s"] > 1.5 * lower_bound_s(sc)
    paired = tried["reverse (paired timed paths)"]
    assert paired["short"] == 0 and paired["makespan_s"] < tried["reverse"]["makespan_s"]
    assert result.stats["chosen"] == "reverse (paired timed paths)"
    summary = _check(sc, result)
    assert summary["success_rate"] == 1.0 and summary["makespan_s"] == pytest.approx(paired["makespan_s"])
    # On a dense field the paired fold was planned ahead in a forked process, which reports no
    # progress of its own (it would draw over the parent's bar); where nothing forks it is
    # planned after the first fold: the same trajectory and planner runs.
    assert set(callers.read_text().split()) == {str(os.getpid())}
    if _fork.can_fork():
        monkeypatch.setattr(_fork, "can_fork", lambda: False)
        after = fp.plan(sc, "mpc", {"route_groups": False})
        assert after.stats["chosen"] == "reverse (paired timed paths)"
        assert np.array_equal(result.trajectory.joints, after.trajectory.joints)
        assert result.stats["planner_runs"] == after.stats["planner_runs"]
        monkeypatch.undo()
    alone = fp.plan(sc, "mpc", {"schedule_pairs_retry": 0, "route_groups": False})
    assert [c["strategy"] for c in alone.stats["candidates"]] == ["reverse"]
    assert alone.stats["candidates"][0]["makespan_s"] == tried["reverse"]["makespan_s"]
    # A fold near its bound is not planned again (the plan started ahead is let go).
    near = fp.plan(fp.make_scenario("moons-capsules", 61, "unfold", 0), "mpc", {"route_groups": False})
    assert [c["strategy"] for c in near.stats["candidates"]] == ["reverse"]
    assert multiprocessing.active_children() == []
