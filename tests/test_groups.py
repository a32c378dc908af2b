"""Group moves (planners/coordination/groups.py, setting route_groups): a stalled fold's stragglers
and the neighbours in their way brought home together, checked by the verifier."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

import fiberplan as fp
from fiberplan.geometry import clearance_rows, default_safety_margin_mm
from fiberplan.instrument_io import load_instrument
from fiberplan.layout import neighbour_lists
from fiberplan.planners.coordination import groups as groups_module
from fiberplan.planners.coordination.groups import _Group, groups
from fiberplan.planners.coordination.legs import leg_scenario, trim
from fiberplan.planners.coordination.settings import REVERSE_LEG
from fiberplan.trajectory import Trajectory


@pytest.fixture(scope="module")
def stalled():
    """MOONS 61 (`moons-capsules`) unfold seed 6: the fold from its targets, the mpc's first attempt
    alone, leaves positioners 4 and 24 short (each swept over by neighbours folded or not)."""
    sc = fp.make_scenario("moons-capsules", 61, "unfold", 6)
    fold = leg_scenario(sc, sc.target, sc.start, REVERSE_LEG)
    result = fp.plan(fold, "mpc", {"route": "direct", "route_attempts": 1, "route_tails": False, "route_restarts": False})
    joints = trim(result.trajectory.joints)
    short = np.flatnonzero(~np.all(joints[-1] == fold.target, axis=1))
    assert short.tolist() == [4, 24]
    return fold, joints, float(result.settings["dt_s"])


@pytest.fixture(scope="module")
def brought_home(stalled):
    """The stalled attempt with its groups brought home (one search shared by the tests); the early
    starts' calls and the starts they searched are recorded in ``early_calls`` / ``early_searched``."""
    fold, joints, dt = stalled
    early, connect = groups_module._early, groups_module._connect

    def spy_early(leg, out, part, *rest):
        early_calls.append((out.copy(), list(part), rest[4]))
        return early(leg, out, part, *rest)

    def spy_connect(group, start, goal, rng, iterations=None, goal_tree=None):
        if iterations == groups_module.EARLY_ITERATIONS:
            early_searched.append((group.members.tolist(), start.copy()))
        return connect(group, start, goal, rng, iterations, goal_tree)

    budget = groups_module._Budget

    class SpyBudget(budget):
        def __init__(self, checks):
            super().__init__(checks)
            budgets.append(self)

    groups_module._early, groups_module._connect, groups_module._Budget = spy_early, spy_connect, SpyBudget
    try:
        return groups(fold, joints, default_safety_margin_mm(fold.instrument), dt)
    finally:
        groups_module._early, groups_module._connect, groups_module._Budget = early, connect, budget


early_calls: list[tuple[np.ndarray, list[int], int]] = []
early_searched: list[tuple[list[int], np.ndarray]] = []
budgets: list[groups_module._Budget] = []


def test_group_moves_bring_a_stalled_fold_home_clear(stalled, brought_home):
    fold, joints, dt = stalled
    floor = default_safety_margin_mm(fold.instrument)
    out = brought_home
    assert out is not None
    np.testing.assert_array_equal(out[0], joints[0])
    np.testing.assert_array_equal(out[-1], fold.target)  # every positioner exactly on its target
    steps = np.abs(np.diff(out, axis=0))
    assert np.all(steps <= fold.instrument.speeds_rad_s * dt * (1 + 1e-9))
    report = fp.verify(fold, Trajectory(np.arange(len(out)) * dt, out))
    assert report.ok, report.to_dict()["collision_events"][:2]
    # Only the groups (the short ones and the neighbours in their way) move otherwise than planned.
    planned = np.concatenate([joints, np.repeat(joints[-1:], len(out) - len(joints), axis=0)])
    changed = np.flatnonzero(np.any(out != planned, axis=(0, 2)))
    assert {4, 24} <= set(changed.tolist()) and len(changed) <= 12
    # Seeded: the same leg gives the same moves.
    np.testing.assert_array_equal(groups(fold, joints, floor, dt), out)
    # Some group starts while its other neighbours still move (an early start): a member moves
    # otherwise than planned before the last sample at which a neighbour outside its group moves.
    nbrs = neighbour_lists(fold.pairs, fold.n_positioners)[0]
    differs = np.any(out[: len(joints)] != joints, axis=2)  # (K, N)
    early = False
    for i in changed.tolist():
        outer = np.setdiff1d(nbrs[i], changed)
        moves = np.flatnonzero(np.any(planned[1:, outer] != planned[:-1, outer], axis=(1, 2)))
        first = np.flatnonzero(differs[:, i])
        early |= bool(len(moves) and len(first) and first[0] < moves[-1])
    assert early


def test_early_starts_the_members_cannot_hold_at_are_not_searched(stalled, brought_home):
    """Every early start searched is one from which the members could wait, where they stand,
    while their neighbours go on (HOLD_SCREEN_S), and the screen passes over some start that the
    clearance checks alone would have searched."""
    fold, _, dt = stalled
    assert brought_home is not None and early_calls and early_searched
    floor = default_safety_margin_mm(fold.instrument)
    nbrs = neighbour_lists(fold.pairs, fold.n_positioners)[0]
    stride = max(1, round(groups_module.EARLY_STEP_S / dt))
    searched = passed_over = 0
    for out, part, k0 in early_calls:
        members = np.array(part)
        group = _Group(fold, out[-1], part, nbrs, floor)
        field, last = out[:, group.outer[:, 1]], len(out) - 1
        starts = [x for m, x in early_searched if m == part]
        for ks in range(0, k0, stride):
            start = out[ks, members].ravel()
            if not (group.edge_ok(start, start) and group.edge_ok(fold.target[members].ravel(), fold.target[members].ravel())):
                continue
            hold = np.broadcast_to(out[ks, members][None], (last - ks, len(part), 2))
            holds = bool(group.played_ok(hold, hold, field[ks:last], field[ks + 1 :]).all())
            was_searched = any(np.array_equal(x, start) for x in starts)
            if was_searched:
                assert holds, (part, ks)
                searched += 1
            elif not holds:
                passed_over += 1
    assert searched and passed_over


def test_searches_from_successive_starts_share_the_goals_tree(stalled, brought_home):
    """The goal's side of a search stays valid for the next start among the same neighbours: a
    second search grows the same tree further, and its path runs from its own start to the goal
    along moves the check accepts."""
    fold = stalled[0]
    assert brought_home is not None
    floor = default_safety_margin_mm(fold.instrument)
    nbrs = neighbour_lists(fold.pairs, fold.n_positioners)[0]
    searched = [(out, part, [x for m, x in early_searched if m == part]) for out, part, _ in early_calls]
    out, part, starts = max(searched, key=lambda c: len(c[2]))  # (the group searched from most starts)
    assert len(starts) >= 2
    group = _Group(fold, out[-1], part, nbrs, floor)
    goal = fold.target[part].ravel()
    tree = groups_module._Tree(goal)
    sizes = []
    for n, start in enumerate(starts[:2]):
        path = groups_module._connect(group, start, goal, np.random.default_rng(n), 200, tree)
        sizes.append(len(tree.nodes))
        if path is not None:
            np.testing.assert_array_equal(path[0], start)
            np.testing.assert_array_equal(path[-1], goal)
            assert all(group.edge_ok(a, b) for a, b in itertools.pairwise(path))
    np.testing.assert_array_equal(tree.nodes[0], goal)
    assert 1 < sizes[0] <= sizes[1]


def test_the_groups_after_one_without_a_way_are_not_searched(stalled, brought_home, monkeypatch):
    """A leg is kept completed by group moves only where every group finds a way: once one finds
    none, the groups after it are not searched (the stalled fold has two, searched one by one)."""
    fold, joints, dt = stalled
    assert len(early_calls) == 2  # (the fixture's run: both groups searched)
    calls = []
    monkeypatch.setattr(groups_module, "_move", lambda leg, out, part, *rest: calls.append(part))
    assert groups(fold, joints, default_safety_margin_mm(fold.instrument), dt) is None
    assert len(calls) == 1


def test_group_moves_given_up_once_their_checks_are_used(stalled, brought_home, monkeypatch):
    """A leg's group moves evaluate at most CHECKS pair clearances (counted, so the same leg is
    given up alike on any machine), then give up: the leg stays as its attempts left it."""
    fold, joints, dt = stalled
    assert len(budgets) == 1 and budgets[0].used > 0  # (the fixture's run, unbounded)
    used = budgets[0].used
    cut = []

    class Cut(groups_module._Budget):
        def __init__(self, checks):
            super().__init__(checks)
            cut.append(self)

    monkeypatch.setattr(groups_module, "_Budget", Cut)
    monkeypatch.setattr(groups_module, "CHECKS", used // 2)
    assert groups(fold, joints, default_safety_margin_mm(fold.instrument), dt) is None
    assert used // 2 < cut[0].used < used  # (stopped at the first evaluation past the bound)


def test_a_rescue_searches_the_groups_without_a_way_again_after_the_others(stalled, monkeypatch):
    """``rescue`` (a leg's last resort): a group that finds no way holds while the groups after it
    are searched, then each such group is searched again with RESCUE_EFFORT times the samples, in
    the field the others left. Here searches of 5 samples per member find no way for either group
    of the stalled fold; searched again with 2,000 both do, and the leg verifies clean. A group
    larger than RESCUE_UP_TO without a way ends the rescue at once. A rescue going on from where
    the search without it stopped gives the same leg, bit for bit."""
    fold, joints, dt = stalled
    floor = default_safety_margin_mm(fold.instrument)
    monkeypatch.setattr(groups_module, "EARLY_ITERATIONS", 0)
    monkeypatch.setattr(groups_module, "ITERATIONS", 5)
    monkeypatch.setattr(groups_module, "RESCUE_EFFORT", 400)
    move, calls = groups_module._move, []

    def spy(leg, out, part, *rest):
        moved = move(leg, out, part, *rest)
        calls.append((sorted(part), rest[-1] if len(rest) == 6 else 1, moved is not None))
        return moved

    monkeypatch.setattr(groups_module, "_move", spy)
    early, streams = groups_module._early, []

    def spy_early(*args):
        streams.append(args[-1])
        return early(*args)

    monkeypatch.setattr(groups_module, "_early", spy_early)
    assert groups(fold, joints, floor, dt) is None  # (the first group without a way ends it)
    assert calls == [([0, 4, 5, 10], 1, False)]
    calls.clear()
    out = groups(fold, joints, floor, dt, rescue=True)
    assert calls == [([0, 4, 5, 10], 1, False), ([9, 16, 24, 34], 1, False), ([0, 4, 5, 10], 400, True), ([9, 16, 24, 34], 400, True)]
    # (The early starts searched again from other streams than the first search's.)
    assert groups_module.SEARCHES != groups_module.RESCUE_SEARCHES
    assert streams == [groups_module.SEARCHES] * 3 + [groups_module.RESCUE_SEARCHES] * 2
    assert out is not None
    np.testing.assert_array_equal(out[0], joints[0])
    np.testing.assert_array_equal(out[-1], fold.target)
    assert np.all(np.abs(np.diff(out, axis=0)) <= fold.instrument.speeds_rad_s * dt * (1 + 1e-9))
    assert fp.verify(fold, Trajectory(np.arange(len(out)) * dt, out)).ok
    # Going on from where the search without rescue stopped: the same leg, without searching the
    # groups before it again (here the first group's first search).
    stops: list = []
    assert groups(fold, joints, floor, dt, stopped=stops) is None
    (stopped,) = stops
    assert stopped.part == [0, 4, 5, 10] and stopped.out is joints and (stopped.unit, stopped.index) == (0, 0)
    calls.clear()
    resumed = groups(fold, joints, floor, dt, rescue=True, resume=stopped)
    assert calls == [([9, 16, 24, 34], 1, False), ([0, 4, 5, 10], 400, True), ([9, 16, 24, 34], 400, True)]
    assert resumed is not None and resumed.tobytes() == out.tobytes()
    monkeypatch.setattr(groups_module, "RESCUE_EFFORT", 1)  # (searched again no harder: still no way)
    assert groups(fold, joints, floor, dt, rescue=True) is None
    calls.clear()
    monkeypatch.setattr(groups_module, "RESCUE_EFFORT", 400)
    monkeypatch.setattr(groups_module, "RESCUE_UP_TO", 3)  # (a group larger than that without a way ends it)
    assert groups(fold, joints, floor, dt, rescue=True) is None
    assert calls == [([0, 4, 5, 10], 1, False)]
    calls.clear()
    assert groups(fold, joints, floor, dt, rescue=True, resume=stopped) is None and calls == []


def test_a_leg_left_short_is_completed_by_the_rescue(stalled, monkeypatch):
    """``complete_leg`` with ``groups``: where the first attempt's groups find no way and the
    attempts after it leave the leg short, the rescue's group moves complete it (its moves named
    in ``Leg.grouped``); a rescue that finds no way leaves the leg as the attempts left it."""
    import types

    from fiberplan.planners.coordination import legs

    fold, joints, dt = stalled
    floor = default_safety_margin_mm(fold.instrument)

    def plan_leg(leg, time_limit_s=None, use_fallback=False, progress=None):  # the stalled attempt, then nothing more
        planned = joints if np.array_equal(leg.start, fold.start) else np.stack([leg.start, leg.start])
        return types.SimpleNamespace(trajectory=Trajectory(np.arange(len(planned)) * dt, planned))

    monkeypatch.setattr(groups_module, "EARLY_ITERATIONS", 0)
    monkeypatch.setattr(groups_module, "ITERATIONS", 5)
    monkeypatch.setattr(legs, "solo_moves", lambda leg, q, *rest: (q[None], None))  # (no solo move brings one home)
    kwargs = {"unblock": False, "strict": False, "solo": (floor, dt), "groups": True}
    monkeypatch.setattr(groups_module, "RESCUE_EFFORT", 1)
    short = legs.complete_leg(fold, plan_leg, 2, **kwargs)
    assert not short.complete and short.grouped == ()
    monkeypatch.setattr(groups_module, "RESCUE_EFFORT", 400)
    done = legs.complete_leg(fold, plan_leg, 2, **kwargs)
    assert done.complete and {4, 24} <= set(done.grouped)
    np.testing.assert_array_equal(done.joints[-1], fold.target)
    assert fp.verify(fold, Trajectory(np.arange(len(done.joints)) * dt, done.joints)).ok


def _pairs_own(group: _Group, x: np.ndarray, q_outer: np.ndarray | None = None) -> np.ndarray:
    """:meth:`_Group.clearance` from each pair's own rows (:func:`clearance_rows`), the reference."""
    leg, m = group.leg, len(x)
    a, b, o = group.inner[:, 0], group.inner[:, 1], group.outer[:, 0]
    q_outer = np.broadcast_to(group.q_outer, (m, len(o), 2)) if q_outer is None else q_outer
    qi = np.concatenate([x[:, a], x[:, o]], axis=1).reshape(-1, 2)
    qj = np.concatenate([x[:, b], q_outer], axis=1).reshape(-1, 2)
    i = np.tile(np.concatenate([group.members[a], group.members[o]]), m)
    j = np.tile(np.concatenate([group.members[b], group.outer[:, 1]]), m)
    return clearance_rows(leg.instrument, leg.base_xy[i], leg.orient[i], qi, leg.base_xy[j], leg.orient[j], qj).min(axis=1).reshape(m, -1)


@pytest.mark.parametrize("zoned", [False, True])
def test_a_groups_clearances_by_index_are_the_pairs_own(stalled, zoned):
    """A group reads its pairs by index from capsules (polygon zones: their edges) placed once:
    the same values, bit for bit, as the pairs' own rows, with the neighbours held still and
    moving, on a capsule instrument and under MOONS' zones."""
    fold, joints, _ = stalled
    if zoned:  # (the same bases and configurations under MOONS' own zones)
        fold = dataclasses.replace(fold, instrument=load_instrument("moons"))
    nbrs = neighbour_lists(fold.pairs, fold.n_positioners)[0]
    group = _Group(fold, joints[-1], [4, 24, 5], nbrs, default_safety_margin_mm(fold.instrument))
    assert len(group.inner) and len(group.outer) and bool(fold.instrument.polygons) == zoned
    rng = np.random.default_rng(3)
    x = rng.uniform(group.lo, group.hi, (40, len(group.lo))).reshape(40, 3, 2)
    q = joints[rng.integers(0, len(joints), 40)][:, group.outer[:, 1]]
    held = _pairs_own(group, x)
    for got, expected in ((group.clearance(x), held), (group.clearance(x, q), _pairs_own(group, x, q)),
                          (group.clearance(x[:1]), held[:1])):
        assert got.shape == expected.shape and got.tobytes() == expected.tobytes()
    assert (held < 0).any() and (held > 0).any()


def test_no_way_means_no_group_moves(stalled, monkeypatch):
    fold, joints, dt = stalled
    monkeypatch.setattr(groups_module, "ITERATIONS", 0)  # searches that give up at once
    monkeypatch.setattr(groups_module, "EARLY_ITERATIONS", 0)
    assert groups(fold, joints, default_safety_margin_mm(fold.instrument), dt) is None
    assert groups(fold, np.repeat(fold.target[None], 3, axis=0), 0.05, dt) is None  # nobody short


def test_a_move_accepted_is_clear_at_every_instant_and_some_are_refused():
    """A straight joint move the check accepts keeps every pair clear at 2,000 instants along it;
    moves that sweep over a neighbour are refused."""
    sc = fp.make_scenario("moons-capsules", 19, "random", 0)
    q = sc.start.copy()
    nbrs = neighbour_lists(sc.pairs, sc.n_positioners)[0]
    centre = int(np.argmax([len(n) for n in nbrs]))
    group = _Group(sc, q, [centre], nbrs, 0.05)
    lim = sc.instrument.limits_rad
    rng = np.random.default_rng(1)
    accepted = refused = 0
    for _ in range(40):
        x0, x1 = (rng.uniform(lim[:, 0], lim[:, 1]) for _ in range(2))
        if not (group.edge_ok(x0, x0) and group.edge_ok(x1, x1)):
            continue
        if group.edge_ok(x0, x1):
            s = np.linspace(0.0, 1.0, 2000)[:, None]
            dense = (x0[None] * (1 - s) + x1[None] * s).reshape(-1, 1, 2)
            assert group.clearance(dense).min() > 0.0
            accepted += 1
        else:
            refused += 1
    assert accepted and refused


def test_moves_of_a_pressed_pair_are_proved_clear_by_halving(monkeypatch):
    """A positioner pressed 0.1 mm from a neighbour (as a stalled attempt leaves them): small moves
    the sub-steps alone cannot prove clear are accepted by halving the intervals between them, and
    each accepted move is clear at 2,000 instants; halving never refuses what the sub-steps accept."""
    sc = fp.make_scenario("moons-capsules", 19, "random", 0)
    nbrs = neighbour_lists(sc.pairs, sc.n_positioners)[0]
    centre = int(np.argmax([len(n) for n in nbrs]))
    group = _Group(sc, sc.start.copy(), [centre], nbrs, 0.07)
    lim = sc.instrument.limits_rad
    pressed = None
    for alpha in np.linspace(lim[0, 0], lim[0, 1], 2000):  # swept round until a pair comes within 0.1-0.14 mm
        x = np.array([alpha, sc.start[centre, 1]])
        if 0.1 < group.clearance(x[None, None])[0].min() < 0.14:
            pressed = x
            break
    assert pressed is not None
    rng = np.random.default_rng(0)
    only_halved = 0
    for _ in range(200):
        x1 = np.clip(pressed + rng.normal(0.0, 0.03, 2), lim[:, 0], lim[:, 1])
        monkeypatch.setattr(groups_module, "BISECTIONS", 0)
        plain = group.edge_ok(pressed, x1)
        monkeypatch.setattr(groups_module, "BISECTIONS", 4)
        halved = group.edge_ok(pressed, x1)
        assert halved or not plain
        if halved:
            s = np.linspace(0.0, 1.0, 2000)[:, None]
            assert group.clearance((pressed[None] * (1 - s) + x1[None] * s).reshape(-1, 1, 2)).min() > 0.0
            only_halved += not plain
    assert only_halved >= 10


def test_intervals_among_moving_neighbours_accepted_are_clear_at_every_instant():
    """``played_ok``: a member and its neighbours each moving straight over an interval; the
    intervals accepted keep every pair clear at 2,000 instants, and some are refused."""
    sc = fp.make_scenario("moons-capsules", 19, "random", 0)
    nbrs = neighbour_lists(sc.pairs, sc.n_positioners)[0]
    centre = int(np.argmax([len(n) for n in nbrs]))
    group = _Group(sc, sc.start.copy(), [centre], nbrs, 0.05)
    outer = group.outer[:, 1]
    lim = sc.instrument.limits_rad
    rng = np.random.default_rng(2)
    m = 400
    x0 = np.clip(sc.start[centre] + rng.normal(0.0, 0.6, (m, 2)), lim[:, 0], lim[:, 1])[:, None]
    x1 = np.clip(x0 + rng.normal(0.0, 0.05, (m, 1, 2)), lim[:, 0], lim[:, 1])
    q0 = np.clip(sc.start[outer][None] + rng.normal(0.0, 0.3, (m, len(outer), 2)), lim[:, 0], lim[:, 1])
    q1 = np.clip(q0 + rng.normal(0.0, 0.05, q0.shape), lim[:, 0], lim[:, 1])
    # Half the rows: the member holds while its neighbours sweep far (only their motion can close a pair).
    x1[m // 2 :] = x0[m // 2 :]
    q1[m // 2 :] = np.clip(q0[m // 2 :] + rng.normal(0.0, 0.5, q0[m // 2 :].shape), lim[:, 0], lim[:, 1])
    ok = group.played_ok(x0, x1, q0, q1)
    s = np.linspace(0.0, 1.0, 2000)[:, None, None]
    for r in np.flatnonzero(ok):
        dense = group.clearance(x0[r] * (1 - s) + x1[r] * s, q0[r] * (1 - s) + q1[r] * s)
        assert dense.min() > 0.0
    ends = np.minimum(group.clearance(x0, q0).min(axis=1), group.clearance(x1, q1).min(axis=1))
    assert ok.sum() >= 20 and (~ok & (ends >= 0.05)).sum() >= 1  # (refused with both ends at the floor: between them)


def test_a_tuned_path_waits_for_a_neighbour_in_its_way_and_keeps_the_speed_limits():
    """``_tune``: a member's straight path, a neighbour parked across it for 1 s, then going home:
    the member waits, never faster than its joints allow, clear at every sample, home at the end.
    With the neighbour parked there for good: no play."""
    from fiberplan.planners.coordination.groups import _tune

    sc = fp.make_scenario("moons-capsules", 7, "random", 0)
    nbrs = neighbour_lists(sc.pairs, sc.n_positioners)[0]
    dt, floor, lim, speeds = 0.05, 0.05, sc.instrument.limits_rad, sc.instrument.speeds_rad_s
    rng = np.random.default_rng(0)
    i = int(np.argmax([len(n) for n in nbrs]))
    group = _Group(sc, sc.start.copy(), [i], nbrs, floor)
    outer = group.outer[:, 1]
    case = None
    for _ in range(5000):
        a, b = (rng.uniform(lim[:, 0], lim[:, 1]) for _ in range(2))
        j = int(rng.choice(nbrs[i]))
        block = rng.uniform(lim[:, 0], lim[:, 1])
        if not group.edge_ok(a, b):  # (clear among the neighbours at their starts)
            continue
        field_ = np.repeat(sc.start[None], 20 + 40 + 100, axis=0)
        field_[:20, j] = block
        field_[20:60, j] = block[None] + (sc.start[j] - block)[None] * np.linspace(0.0, 1.0, 40)[:, None]
        waiting = np.repeat(a.reshape(1, 1, 2), len(field_) - 1, axis=0)
        blocked = _Group(sc, field_[0], [i], nbrs, floor)
        if blocked.edge_ok(a, b) or not group.played_ok(waiting, waiting, field_[:-1, outer], field_[1:, outer]).all():
            continue  # (the neighbour must cross the path, and leave the member clear where it waits)
        case = a, b, field_
        break
    assert case is not None
    a, b, field_ = case
    played = _tune(group, np.stack([a, b]), field_, 0, dt)
    assert played is not None
    np.testing.assert_array_equal(played[0, 0], a)
    np.testing.assert_array_equal(played[-1, 0], b)
    assert np.all(np.abs(np.diff(played[:, 0], axis=0)) <= speeds * dt * (1 + 1e-9))
    held = np.concatenate([played, np.repeat(played[-1:], max(0, len(field_) - len(played)), axis=0)])
    on = field_[np.minimum(np.arange(len(held)), len(field_) - 1)][:, outer]
    assert group.clearance(held, on).min() >= floor
    straight = int(np.ceil(np.max(np.abs(b - a) / speeds) / dt))
    assert len(played) - 1 > straight  # it waited (or went slower) for the neighbour
    parked = field_.copy()
    parked[:] = field_[0]
    assert _tune(group, np.stack([a, b]), parked, 0, dt) is None
    # Home, the member must stay clear while the neighbours go on: a neighbour that, after the
    # member arrived, moves onto its target refuses the play; the same field without that move does not.
    j = int(np.flatnonzero(np.any(field_[0] != field_[-1], axis=1))[0])

    def on_target(q: np.ndarray) -> bool:  # (j at q overlaps the member at its target)
        field_q = sc.start.copy()
        field_q[j] = q
        return _Group(sc, field_q, [i], nbrs, floor).clearance(b.reshape(1, 1, 2)).min() < 0.0

    onto = next(q for q in (rng.uniform(lim[:, 0], lim[:, 1]) for _ in range(5000)) if on_target(q))
    late = np.repeat(field_[-1:], len(played) + 40, axis=0)
    late[len(played) + 20 :, j] = onto
    calm = late.copy()
    calm[:] = field_[-1]
    assert _tune(group, np.stack([a, b]), calm, 0, dt) is not None
    assert _tune(group, np.stack([a, b]), late, 0, dt) is None


def test_the_grouped_first_attempt_is_kept_where_the_attempts_after_it_are_longer(stalled, brought_home):
    """``complete_leg`` with ``groups``: the first attempt completed by group moves is kept when
    the further attempts leave the leg short or longer; without ``groups`` they are all there is."""
    import types

    from fiberplan.planners.coordination import legs

    fold, joints, dt = stalled
    floor = default_safety_margin_mm(fold.instrument)

    def plan_leg(leg, time_limit_s=None, use_fallback=False, progress=None):  # the stalled attempt, then nothing more
        planned = joints if np.array_equal(leg.start, fold.start) else np.stack([leg.start, leg.start])
        return types.SimpleNamespace(trajectory=Trajectory(np.arange(len(planned)) * dt, planned))

    kwargs = {"unblock": False, "strict": False, "solo": (floor, dt)}
    plain = legs.complete_leg(fold, plan_leg, 2, **kwargs)
    grouped = legs.complete_leg(fold, plan_leg, 2, groups=True, **kwargs)
    expected = legs.trim(brought_home)
    assert grouped.complete and not grouped.rescued and plain.grouped == ()
    moved = np.flatnonzero(legs._changed(joints, expected))
    assert {4, 24} <= set(moved.tolist())  # the stragglers, with the neighbours that made way
    if plain.complete:  # (the solo moves at the end may bring them home too: the shorter is kept)
        assert len(grouped.joints) == min(len(plain.joints), len(expected))
        assert grouped.grouped == (tuple(moved.tolist()) if len(expected) < len(plain.joints) else ())
    else:
        np.testing.assert_array_equal(grouped.joints, expected)
        assert grouped.grouped == tuple(moved.tolist())
    from fiberplan.planners.coordination.layer import _leg_stats, _Piece

    stats = _leg_stats(fold, [_Piece("direct", grouped.joints, list(range(61)), grouped.runs, 0.0, grouped=grouped.grouped)], dt)
    assert stats["grouped_ids"] == sorted(int(fold.ids[i]) for i in grouped.grouped) and stats["n_grouped"] == len(grouped.grouped)
    report = fp.verify(fold, Trajectory(np.arange(len(grouped.joints)) * dt, grouped.joints))
    assert report.ok


def test_route_groups_plans_verified_and_off_as_before():
    """On (the default since session 50) with the layer, verified and complete; off: MOONS 61
    unfold seed 0 as planned before group moves existed (session 43's hash)."""
    import hashlib
    import json
    from pathlib import Path

    sc = fp.make_scenario("moons-capsules", 61, "unfold", 6)
    on = fp.plan(sc, "mpc")
    assert on.settings["route_groups"] and on.stats["n_grouped"] > 0
    report = fp.verify(sc, on.trajectory)
    assert report.ok and fp.summarize(on, report)["reached"] == 61
    stored = json.loads((Path(__file__).parents[1] / "benchmarks/results/hashes_s43_final.json").read_text())
    default = fp.plan(fp.make_scenario("moons-capsules", 61, "unfold", 0), "mpc", {"route_groups": False})
    digest = hashlib.sha256(np.ascontiguousarray(default.trajectory.joints).tobytes()).hexdigest()
    assert digest == stored["runs"]["moons-capsules-61-unfold-0"]["joints_sha256"]


def test_route_groups_is_not_longer_where_the_paired_fold_is_shorter():
    """MOONS 61 unfold seed 7: group moves complete the reversed fold at 14.30 s (1.34 x the bound,
    under the 1.5 x at which the paired fold is tried), while the paired fold, tried where the
    fold without them is long, gives 13.65 s: a fold that group moves completed straggled, so the
    paired fold is tried too, and group moves never make this plan longer."""
    sc = fp.make_scenario("moons-capsules", 61, "unfold", 7)
    off = fp.plan(sc, "mpc", {"route_groups": False})
    on = fp.plan(sc, "mpc")
    names = [c["strategy"] for c in on.stats["candidates"]]
    assert "reverse (paired timed paths)" in names
    assert on.trajectory.times[-1] <= off.trajectory.times[-1]
    assert fp.verify(sc, on.trajectory).ok


def test_the_attempts_leg_is_tailed_too_where_group_moves_replaced_it(monkeypatch):
    """Where group moves completed a leg shorter than the further attempts did, the attempts' leg
    is tailed too and kept if it then ends first (MOONS 500 unfold seed 42: 35.9 s with group
    moves, 33.7 s without); otherwise, or with ``TAIL_BOTH`` off, group moves' leg stays."""
    from fiberplan.planners.coordination import legs

    sc = fp.make_scenario("moons-capsules", 7, "unfold", 0)

    def ramp(k):  # a leg of k samples, home 10 samples before its end
        return sc.start[None] + (sc.target - sc.start)[None] * np.minimum(np.arange(k) / (k - 10), 1.0)[:, None, None]

    attempts, grouped = ramp(30), ramp(20)

    def fake_attempts(leg, plan_leg, n, time_limit_s, unblock, strict, solo, notes, groups):
        notes["grouped"], notes["rescued"] = (grouped, (1, 2)), True  # (the attempts' leg needed the fallback rounds)
        return attempts, 2, True

    tailed_to = {"length": 15}
    withins = []

    def fake_tail(leg, joints, plan_leg, dt_s, within=None):  # only the attempts' leg has a tail to gain
        withins.append(within)
        return (ramp(tailed_to["length"]), 1) if joints is attempts else (joints, 0)

    monkeypatch.setattr(legs, "_attempts", fake_attempts)
    monkeypatch.setattr(legs, "tail_backwards", fake_tail)
    kwargs = {"restarts": 0.05, "tails": True, "groups": True, "solo": (0.05, 0.05)}
    leg = legs.complete_leg(sc, None, 4, **kwargs)
    assert len(leg.joints) == 15 and leg.grouped == () and leg.untailed is attempts and leg.first_samples == 30
    assert leg.runs == 3 and leg.rescued and withins == [None, 20]  # (the attempts' tails must end before group moves' leg)
    tailed_to["length"] = 25  # (tailed, still longer than group moves' leg)
    leg = legs.complete_leg(sc, None, 4, **kwargs)
    assert leg.joints is grouped and leg.grouped == (1, 2) and leg.untailed is None and leg.first_samples == 20
    assert not leg.rescued
    tailed_to["length"] = 15
    monkeypatch.setattr(legs, "TAIL_BOTH", False)
    leg = legs.complete_leg(sc, None, 4, **kwargs)
    assert leg.joints is grouped and leg.grouped == (1, 2)
