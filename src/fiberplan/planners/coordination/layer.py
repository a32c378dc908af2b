"""Strategies of the coordination layer and :func:`coordinate` (see the package docstring)."""

from __future__ import annotations

import contextvars
import dataclasses
import functools
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from fiberplan import _fork
from fiberplan.errors import PlannerError
from fiberplan.geometry import min_pair_clearance
from fiberplan.metrics import arrival_times, lower_bound_s, move_times, reached_mask
from fiberplan.outcomes import outcome_labels
from fiberplan.planners.coordination.fork import CHILD_RUNS, RUN_LOG, Ahead, both
from fiberplan.planners.coordination.legs import Leg, PlanLeg, _park_candidates, complete_leg, exactly_at, leg_scenario, with_neighbours
from fiberplan.planners.coordination.retime import overlap_legs, ramp_rests
from fiberplan.planners.coordination.settings import REVERSE_LEG, UNFOLD_REVERSED_LEG
from fiberplan.profiles import chatters
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult, Trajectory

DENSE_REACH = 0.8
"""Patrol regions overlap densely when the reach exceeds this fraction of the pitch (MOONS,
SDSS: 1.0; DESI: 0.58): there the two-leg plan comes first and bounds the direct attempt."""

AHEAD_UP_TO = 10_000
"""The largest field on which a candidate that may not be needed is planned ahead in a forked
process (beyond it, a second plan at once would double the memory, and the mpc's start schedule
uses the second core itself)."""


@dataclasses.dataclass(frozen=True)
class _Options:
    """What the strategies take from the run's settings."""

    attempts: int  # route_attempts
    restarts: float | None  # the sample period if route_restarts, else None
    overlap: bool  # route_overlap
    floor_mm: float  # the clearance new pairs of overlapped legs and solo moves keep (the planner's safety margin)
    coarse_steps: int  # stride of the search for the overlap
    dt_s: float  # the planner's control step
    rest_steps: int = 0  # steps a joint holds still before turning back where runs meet (the instrument's speed ramp; governed planners)
    tails: bool = True  # route_tails
    prioritized_up_to: int = 0  # route_prioritized_up_to
    retract_up_to: int = 0  # route_retract_up_to
    pairs_above: float = 0.0  # schedule_pairs_retry of a planner with schedule_pairs off (the mpc's), else 0: never
    rescue_up_to: int = 0  # route_rescue_up_to
    groups: bool = False  # route_groups
    partial_folds: bool = False  # route_partial_folds

    @property
    def solo(self) -> tuple[float, float]:
        return self.floor_mm, self.dt_s


@dataclasses.dataclass
class _Piece:
    """Part of the combined trajectory: samples ``(K, N, 2)`` after the previous piece's end."""

    name: str
    joints: np.ndarray
    moved: list[int]
    attempts: int
    wall_s: float
    overlap_steps: int = 0
    first_samples: int = 0  # samples before restarts and overlap shortened it (0: not known)
    rescued: bool = False  # a leg of it needed the later fallback rounds (legs.Leg.rescued)
    through_datum: bool = False  # a leg of the two-leg plan (the stats' via_datum_ids count its movers)
    grouped: tuple[int, ...] = ()  # positioners group moves moved in a leg of it (legs.Leg.grouped)


def _join(scenario: Scenario, pieces: list[_Piece], dt: float, rest: int = 0) -> Trajectory:
    """One trajectory from pieces that each start where the previous one ended (first piece
    from the scenario's start); with ``rest`` steps (speed ramps), everyone holds where a joint
    would turn back sooner after a fast move (:func:`ramp_rests`: where planner runs meet), except
    within pieces that chatter (a fallback dnf's: the discretiser smooths those first)."""
    joints = np.concatenate([scenario.start[None], *[p.joints[1:] for p in pieces]])
    if rest:
        where = np.concatenate([np.full(len(p.joints) - 1, not chatters(p.joints)) for p in pieces])
        joints, _ = ramp_rests(joints, rest, scenario.instrument.speeds_rad_s * dt, where)
    return Trajectory(np.arange(len(joints)) * dt, joints)


def _reversed(joints: np.ndarray) -> np.ndarray:
    return joints[::-1].copy()


# ---------------------------------------------------------------------------- strategies
def _direct(scenario: Scenario, plan_leg: PlanLeg, opts: _Options) -> list[_Piece]:
    t0 = time.perf_counter()
    leg = complete_leg(scenario, plan_leg, opts.attempts, strict=False, restarts=opts.restarts, solo=opts.solo, tails=opts.tails, groups=opts.groups)
    return [_Piece("direct", leg.joints, np.flatnonzero(scenario.has_target).tolist(), leg.runs, time.perf_counter() - t0,
                   first_samples=leg.first_samples, rescued=leg.rescued, grouped=leg.grouped)]


def _reverse(scenario: Scenario, plan_leg: PlanLeg, opts: _Options) -> list[_Piece] | None:
    """The move planned from the targets back to the starts, played forwards. A reversed plan
    that stalls is met where it stalled (:func:`_meet`): the move from the starts is planned to
    that configuration, and the two join there (overlapped where that is clear). ``None`` unless
    the plan brings every positioner exactly back to its start, or the two legs join."""
    t0 = time.perf_counter()
    back = leg_scenario(scenario, scenario.target, scenario.start, REVERSE_LEG)
    leg = complete_leg(back, plan_leg, opts.attempts, restarts=opts.restarts, solo=opts.solo, tails=opts.tails, groups=opts.groups)
    if leg.complete:
        who = np.flatnonzero(scenario.has_target).tolist()
        return [_Piece("reverse (planned from the targets)", _reversed(leg.joints), who, leg.runs, time.perf_counter() - t0,
                       first_samples=leg.first_samples, rescued=leg.rescued, grouped=leg.grouped)]
    # The reversed plan stalled (an unfold under MOONS' zones, MOONS 500 seed 4: 5 of 500 short
    # after every round, the paired fold 1; the direct plan 9 short): the starts meet it where it stalled, with the
    # positioners it brought home holding there (the leg from the starts is then the stalled ones'
    # own way out, among neighbours at their starts).
    staying = Leg(scenario.start[None].copy(), 0, True, 1)
    legs = _meet(scenario, plan_leg, opts, scenario.start, scenario.target, staying, leg)
    if legs is None:
        return None
    first, second = legs
    # (The stalled leg's runs count once: it is the second leg unless _meet planned that one again.)
    return _met_pieces(scenario, opts, first, second, time.perf_counter() - t0, extra_runs=0 if second.joints is leg.joints else leg.runs,
                       names=("from the starts to where the reverse stalled", "reverse (planned from the targets), met where it stalled"))


def _met_pieces(scenario: Scenario, opts: _Options, first: Leg, second: Leg, wall: float, names: tuple[str, str],
                extra_runs: int = 0) -> list[_Piece]:
    """The pieces of two legs joined by :func:`_meet` (``first``, then ``second`` played backwards),
    overlapped where that is clear (:func:`overlap_legs`): one piece, else the two (both ``rescued``)."""
    who = np.flatnonzero(scenario.has_target).tolist()
    ahead, played = first.joints, _reversed(second.joints)
    joints, shift = overlap_legs(scenario, ahead, played, opts.floor_mm, opts.coarse_steps, rest=opts.rest_steps) if opts.overlap else (None, 0)
    if joints is not None and shift > 0:
        return [_Piece(f"{names[0]}, then {names[1]}, overlapped by {shift} steps", joints, who, extra_runs + first.runs + second.runs, wall,
                       overlap_steps=shift, first_samples=len(ahead) + len(played) - 1, rescued=True,
                       grouped=first.grouped + second.grouped)]
    return [_Piece(names[0], ahead, who, first.runs, wall, first_samples=first.first_samples, rescued=True, grouped=first.grouped),
            _Piece(names[1], played, who, extra_runs + second.runs, 0.0, first_samples=second.first_samples, rescued=True,
                   grouped=second.grouped)]


def _met_from_the_goal(scenario: Scenario, plan_leg: PlanLeg, opts: _Options, direct: _Piece) -> list[_Piece] | None:
    """A fold whose direct plan stalled, completed the other way round: the move from the goals
    (the datum) to where it stalled, planned and played backwards (:func:`_meet`, the second leg
    staying at the goals; the mirror of :func:`_reverse`'s meeting). ``None`` unless they join."""
    t0 = time.perf_counter()
    stalled = Leg(direct.joints, direct.attempts, False, direct.first_samples, direct.wall_s)
    staying = Leg(scenario.target[None].copy(), 0, True, 1)
    legs = _meet(scenario, plan_leg, opts, scenario.start, scenario.target, stalled, staying)
    if legs is None:
        return None
    first, second = legs
    return _met_pieces(scenario, opts, first, second, time.perf_counter() - t0,
                       names=("direct (until it stalled)", "from the datum to where the direct plan stalled, played backwards"))


def _datum(scenario: Scenario) -> np.ndarray:
    datum = np.broadcast_to(np.array(scenario.instrument.datum_rad), (scenario.n_positioners, 2)).copy()
    datum[scenario.locked] = scenario.start[scenario.locked]
    return datum


def _home(scenario: Scenario) -> np.ndarray:
    """Where each positioner must end: its target, or its start if it has none."""
    return np.where(scenario.has_target[:, None], scenario.target, scenario.start)


def _with_neighbours(scenario: Scenario, movers: np.ndarray) -> np.ndarray:
    """``movers`` (a mask) with their neighbours, none of them locked."""
    return with_neighbours(movers, scenario.pairs) & ~scenario.locked


def _folded_part_way(scenario: Scenario, start: np.ndarray, fraction: float) -> np.ndarray:
    """Folded (the datum's beta) at the alpha ``fraction`` of the way from the datum's to the one
    half-way between the start and the target (1: half-way, each leg turning alpha half the way).
    Safe for everyone (folded positioners of every preset keep clear of each other at any alphas)."""
    home = _home(scenario)
    out = _datum(scenario)
    free = ~scenario.locked
    half = 0.5 * (start[free, 0] + home[free, 0])
    out[free, 0] = half if fraction == 1 else out[free, 0] + fraction * (half - out[free, 0])
    return out


PARTIAL_FOLDS = (0.4, 0.3)
"""Fractions (:func:`_folded_part_way`) at which a dense move's two legs are also planned, besides
the datum (``route_partial_folds``). SDSS 547 random seeds 0-4, the mpc, makespan / bound through
the datum 2.11, 1.98, 2.19, 2.26, 2.10 (its alpha 10 deg is at one end of SDSS' alpha range: each
leg turns alpha up to 350 deg); at 0.4: 1.50, 1.86, 1.49, 1.43, 1.36; at 0.3: 1.49, 1.58, 1.47,
1.62, 1.56; half-way (1): 5.95 on seed 0, its legs straggle (the arms turn every way); the smaller
fractions turn most arms towards the datum's side, the same way (docs/results.md, session 51)."""

PARTIAL_FOLD_GAIN = 0.85
"""A partial fold is planned only where its two legs' lower bounds add up to at most this fraction
of the datum's (SDSS 547 random: 0.79 at 0.4; MOONS, whose datum alpha is in the middle of its
range and so already on the way of most moves: 0.96-0.99 on MOONS 500, 0.89-0.95 on MOONS 61 random
seeds 0-2, where each leg costs seconds of planning)."""


def _legs_bound_s(scenario: Scenario, start: np.ndarray, safe: np.ndarray) -> float:
    """The two legs' lower bounds through ``safe``, added."""
    movers = ~scenario.locked
    there = move_times(scenario.instrument, start, safe)[movers]
    back = move_times(scenario.instrument, _home(scenario), safe)[movers]
    return float(there.max() + back.max()) if movers.any() else 0.0


def _clear_holds(scenario: Scenario, hold: np.ndarray, movers: np.ndarray) -> np.ndarray:
    """The intermediate configuration with every mover whose datum collides with a positioner
    holding still (locked, say) folded at another alpha instead, where it is clear."""
    pairs = scenario.pairs
    if not len(pairs):
        return hold
    lim = scenario.instrument.limits_rad
    for _ in range(3):
        clearance = min_pair_clearance(scenario.instrument, scenario.base_xy, scenario.orient, hold, pairs)
        bad = np.flatnonzero(clearance < 0.0)
        if not len(bad):
            break
        for r in bad.tolist():
            for k in pairs[r].tolist():
                if not movers[k]:
                    continue
                rows = np.flatnonzero((pairs == k).any(axis=1))
                for cand in _park_candidates(hold[k], lim):
                    trial = hold.copy()
                    trial[k] = cand
                    if np.all(min_pair_clearance(scenario.instrument, scenario.base_xy, scenario.orient, trial, pairs[rows]) > 0.0):
                        hold[k] = cand
                        break
                break
    return hold


def _via_datum(scenario: Scenario, plan_leg: PlanLeg, opts: _Options, start: np.ndarray | None = None,
               movers: np.ndarray | None = None, label: str = "", part_way: float = 0.0) -> list[_Piece] | None:
    """Two legs through the datum (``part_way`` > 0: through the folded configuration that fraction of
    the way to half-way in alpha, :func:`_folded_part_way`, if it keeps the safety margin; else
    ``None``) for ``movers`` (default: every positioner that is not locked),
    the others holding where ``start`` has them: ``start -> safe``, then ``(target -> safe)``
    reversed, overlapped where that is clear (:func:`overlap_legs`). A leg left short is met
    where it stalled by the other leg planned again (:func:`_meet`); ``None`` unless the two legs
    then join."""
    start = scenario.start if start is None else start
    movers = ~scenario.locked if movers is None else movers
    home = _home(scenario)
    safe = _folded_part_way(scenario, start, part_way) if part_way else _datum(scenario)
    hold = _clear_holds(scenario, np.where(movers[:, None], safe, start), movers)
    if part_way and len(scenario.pairs):
        clearance = min_pair_clearance(scenario.instrument, scenario.base_xy, scenario.orient, hold, scenario.pairs)
        if float(clearance.min()) < opts.floor_mm:  # (a mover's fold beside a held positioner, say)
            return None
    fold = leg_scenario(scenario, start, hold, "fold")
    back_start = np.where(movers[:, None], home, start)
    back = leg_scenario(scenario, back_start, hold, UNFOLD_REVERSED_LEG)
    # The two legs are independent: the second is planned in a forked process meanwhile.
    first, second = both(
        lambda: complete_leg(fold, plan_leg, opts.attempts, restarts=opts.restarts, solo=opts.solo, tails=opts.tails, groups=opts.groups),
        lambda: complete_leg(back, plan_leg, opts.attempts, restarts=opts.restarts, solo=opts.solo, tails=opts.tails, groups=opts.groups),
    )
    met = ""
    place = "the datum"
    if part_way:
        place = "the datum's beta, alpha " + ("half-way" if part_way == 1 else f"{part_way:g} of the way to half-way")
    if not (first.complete and second.complete):
        legs = _meet(scenario, plan_leg, opts, start, back_start, first, second)
        if legs is None:
            return None
        first, second = legs
        met = " (the legs meet where one stalled)"
    who = np.flatnonzero(movers).tolist()
    rescued = first.rescued or second.rescued
    plain = first.first_samples + second.first_samples - 1  # the two legs as first planned, one after the other
    # A leg shortened by a backward tail may overlap the other less than before: each leg with and
    # without its tail, the shortest whole kept (the tailed ones first, on a tie).
    best: tuple[int, np.ndarray, np.ndarray, np.ndarray | None, int] | None = None
    for fold_joints in _forms(first):
        for back_joints in _forms(second):
            unfold = _reversed(back_joints)
            joints, shift = None, 0
            if opts.overlap:
                joints, shift = overlap_legs(scenario, fold_joints, unfold, opts.floor_mm, opts.coarse_steps, rest=opts.rest_steps)
            length = len(joints) if shift > 0 else len(fold_joints) + len(unfold) - 1
            if best is None or length < best[0]:
                best = (length, fold_joints, unfold, joints if shift > 0 else None, shift)
    assert best is not None
    _, fold_joints, unfold, joints, shift = best
    if joints is not None:
        return [_Piece(f"{label}fold to {place}, then unfold from it (planned from the targets), overlapped by {shift} steps{met}",
                       joints, who, first.runs + second.runs, first.wall_s + second.wall_s, overlap_steps=shift,
                       first_samples=plain, rescued=rescued, through_datum=True, grouped=first.grouped + second.grouped)]
    return [
        _Piece(f"{label}fold to {place}{met}", fold_joints, who, first.runs, first.wall_s, first_samples=first.first_samples,
               rescued=rescued, through_datum=True, grouped=first.grouped),
        _Piece(f"{label}unfold from {place} (planned from the targets){met}", unfold, who, second.runs, second.wall_s,
               first_samples=second.first_samples, rescued=rescued, through_datum=True, grouped=second.grouped),
    ]


def _forms(leg: Leg) -> list[np.ndarray]:
    """A leg's joints, then (if a backward tail shortened it) the leg before."""
    return [leg.joints] if leg.untailed is None else [leg.joints, leg.untailed]


MEET_ROUNDS = 3
"""Legs planned again by :func:`_meet` (each a whole leg: attempts, solo moves, fallback rounds)."""


def _meet(scenario: Scenario, plan_leg: PlanLeg, opts: _Options, start: np.ndarray, back_start: np.ndarray,
          first: Leg, second: Leg) -> tuple[Leg, Leg] | None:
    """The two legs of :func:`_via_datum` (or of :func:`_reverse`, whose first leg then stays at
    the starts) when one of them stalls, joined where it stalled.

    The legs need not meet at the datum: any configuration both reach will do, and one in which a
    stalled leg ended is collision-free (with everyone else folded, the few short positioners
    unfolded). So the other leg is planned again to that configuration (the second leg, from the
    targets, when the first stalled; else the first, from the starts); if that one stalls in turn,
    the first is planned to where it stalled, and so on, :data:`MEET_ROUNDS` legs at most. The
    positioners a fold leaves short are those its datum blocks (an arm at its hard stop beside a
    folded neighbour, two arms each in the other's way); the other leg then only has to bring them
    to where they stand, among folded neighbours, not past each other. Returns the two legs, ending
    and starting at one configuration (both ``rescued``: the layer then also weighs the fallback
    planner's whole move and the direct plan), or ``None``."""
    second_meets = not first.complete  # the leg that did not stall meets the one that did (both: the second meets the first)
    for _ in range(MEET_ROUNDS):
        if second_meets:
            meeting = first.joints[-1]
            leg = leg_scenario(scenario, back_start, meeting, UNFOLD_REVERSED_LEG)
            second = complete_leg(leg, plan_leg, opts.attempts, restarts=opts.restarts, solo=opts.solo, tails=opts.tails, groups=opts.groups)
            if second.complete:
                second = second.ending_at(leg.target, meeting)
                break
        else:
            meeting = second.joints[-1]
            leg = leg_scenario(scenario, start, meeting, "fold")
            first = complete_leg(leg, plan_leg, opts.attempts, restarts=opts.restarts, solo=opts.solo, tails=opts.tails, groups=opts.groups)
            if first.complete:
                first = first.ending_at(leg.target, meeting)
                break
        second_meets = not second_meets
    else:
        return None
    return dataclasses.replace(first, rescued=True), dataclasses.replace(second, rescued=True)


def _fix_up(scenario: Scenario, direct: _Piece, plan_leg: PlanLeg, opts: _Options, rounds: int = 3) -> list[_Piece] | None:
    """The direct plan until its last arrival, then the positioners still short (and, round by
    round, the neighbours that block them) through the datum, everyone else holding."""
    traj = Trajectory(np.arange(len(direct.joints)), direct.joints)
    reached = reached_mask(scenario, traj)
    arrive = arrival_times(scenario, traj)
    cut = int(np.nanmax(arrive[reached])) if reached.any() else 0
    state = direct.joints[cut]
    # The positioners still short, and the held ones away from home, go through the datum.
    home = _home(scenario)
    movers = ~np.all(state == home, axis=1) & ~scenario.locked
    if not movers.any():
        return None
    head = _Piece("direct (until its last arrival)", direct.joints[: cut + 1], direct.moved, direct.attempts, direct.wall_s)
    for _ in range(rounds):
        legs = _via_datum(scenario, plan_leg, opts, start=state, movers=movers, label="fix-up: ")
        if legs is not None:
            return [head, *legs]
        grown = _with_neighbours(scenario, movers)  # the neighbours of the movers fold too, next round
        if np.array_equal(grown, movers):
            break
        movers = grown
    return None


PRIORITIZED_SLACKS = (1.2, 1.5, 2.0)
"""The ``prioritized`` planner's ``slack`` values tried in turn (every scheduled move ends by this
many times the longest): the first that brings everyone home is kept. SDSS 7 hard seeds 0-29:
complete on 12, 15 and 16 seeds at 1.2, 1.5 and 2.0 alone."""


RETRACTION_ROUNDS = 3
"""Rounds of :func:`_through_retraction` in :func:`_prioritized`: the positioners the schedule
left short retract; if a leg then leaves anyone short, their neighbours too, and so on. SDSS 7
hard seeds 6, 8, 14, 20, 27, 29 (measured with the datum's beta at the target's alpha alone): no
retraction of the short ones alone completes, of the whole group (their neighbours) 1.23-1.63 x
the bound against 1.66-3.33 x through the datum."""


def _at_bound(makespan_s: float, bound_s: float, dt_s: float) -> bool:
    """A plan's makespan on the lower bound (within half a control step: the grid rounds it up)."""
    return makespan_s <= bound_s + 0.5 * dt_s


PRIORITIZED_SHAPES = ((False, 0), (True, 0), (True, 1), (True, 2), (True, 3))
"""The ``prioritized`` planner's ``(late_corners, late_longest)`` tried for the whole move (each
with :data:`PRIORITIZED_SLACKS`): as reference 003's schedule; then with each delayed positioner
also trying its move with the faster joint starting late; then also with the longest, second and
third longest move starting so. Both joints still arrive in the slower one's time, but the arm
sweeps other places, letting a neighbour pass without a delay. SDSS 7 hard seeds 0, 3, 5, 10, 11,
13, 15: 9.90, 10.62, 10.82, (incomplete), 11.16, 11.72, 8.98 s with the first alone, 7.96, 9.42,
9.42, 10.74, 9.70, 9.92, 8.16 s with them all (the central reference: 7.15, 9.41, 9.41, 10.73,
9.68, 9.90, 7.91 s)."""


def _scheduled(leg: Scenario, opts: _Options, shapes: tuple[tuple[bool, int], ...] = PRIORITIZED_SHAPES[:1],
               ) -> tuple[np.ndarray, np.ndarray, str, float] | None:
    """The ``prioritized`` planner's plan of ``leg`` on the run's time grid (and with its safety
    margin, if it has one): for each of ``shapes`` (:data:`PRIORITIZED_SHAPES`), each of
    :data:`PRIORITIZED_SLACKS` in turn until one brings everyone home; ``(joints, reached, how,
    makespan)`` of the shortest plan that brings everyone home (the rest not tried once one
    arrives at the lower bound), else of the one that brought most home (the first of those);
    ``None`` if none could be planned."""
    from fiberplan.planners import plan

    bound_s = lower_bound_s(leg)
    best: tuple[tuple[int, float], np.ndarray, np.ndarray, str] | None = None
    for late_corners, late_longest in shapes:
        for slack in PRIORITIZED_SLACKS:
            overrides: dict[str, Any] = {"dt_s": opts.dt_s, "slack": slack, "late_corners": late_corners,
                                         "late_longest": late_longest}
            if opts.floor_mm > 0.0:
                overrides["safety_margin_mm"] = opts.floor_mm
            try:
                result = plan(leg, "prioritized", overrides)
            except PlannerError:  # (its step budget, say): one try fewer
                continue
            joints = result.trajectory.joints
            traj = Trajectory(np.arange(len(joints)) * opts.dt_s, joints)
            reached = reached_mask(leg, traj)
            short, makespan = _score(leg, traj)
            how = f"slack {slack:g}" + (", delayed moves with the faster joint late" if late_corners else "") + (
                f", move {late_longest} (longest first) with the faster joint late" if late_longest else "")
            # Most brought home, then the shortest: a plan left short is compared by what it reached alone.
            if best is None or (short, makespan if short == 0 else 0.0) < best[0]:
                best = ((short, makespan if short == 0 else 0.0), joints, reached, how)
            if short == 0:
                break
        if best is not None and best[0][0] == 0 and _at_bound(best[0][1], bound_s, opts.dt_s):
            break  # at the lower bound: no shape can be shorter
    return None if best is None else (best[1], best[2], best[3], best[0][1])


def _prioritized(scenario: Scenario, opts: _Options) -> dict[str, list[_Piece]]:
    """Candidates from the ``prioritized`` planner's schedule (reference 003's prioritized
    state-time planning, executed under the safety layer; :func:`_scheduled`), by name:

    - ``prioritized``: the shortest of its plans of the whole move that bring everyone home,
      reference 003's schedule and then the late-joint shapes (:data:`PRIORITIZED_SHAPES`; not
      tried once a plan arrives at the lower bound);
    - ``prioritized through a retraction``, where reference 003's schedule leaves some short
      (beside a complete shaped plan, unless that one is at the lower bound): two legs of the
      schedule through a configuration in which the positioners it left short sit retracted (:data:`RETRACTIONS`: beta part or all the
      way to the datum's, alpha at the target's, the start's or half-way), everyone else on the
      targets: ``start -> that``, then ``(targets -> that)`` reversed, overlapped where clear
      (:func:`overlap_legs`), the shortest kept; if none is complete, their neighbours retract
      too (:data:`RETRACTION_ROUNDS`). The issue's partial retract: only those the plan cannot
      bring home (and the neighbours they need) retract.

    Where a group's moves cross, the schedule's timed paths through each positioner's joint grid
    find crossing motions near the bound that the reactive planners miss (SDSS 7 hard groups: they
    go through the datum at about 1.8 x the bound where the central reference finds 1.0 x); on a
    larger field it paid too little for its planning time (MOONS 61: ``formulations/coordination.md``), hence
    ``route_prioritized_up_to``. (The schedule's plan until its last arrival completed by the
    run's planner was a third candidate: on SDSS 7 hard seeds 0-29 it was never the shortest, and
    on MOONS 7 hard seed 9 under MOONS' zones it took 12 s of the 27 s of planning.)"""
    t0 = time.perf_counter()
    found = _scheduled(scenario, opts)  # reference 003's schedule
    if found is None:
        return {}
    joints, reached, how, makespan = found
    left_short = bool((scenario.has_target & ~reached).any())
    bound_s = lower_bound_s(scenario)
    at_bound = not left_short and _at_bound(makespan, bound_s, opts.dt_s)
    if not at_bound:  # the other shapes: the shortest complete plan of them all
        shaped = _scheduled(scenario, opts, PRIORITIZED_SHAPES[1:])
        if shaped is not None and not (scenario.has_target & ~shaped[1]).any() and (left_short or shaped[3] < makespan):
            joints, reached, how, makespan = shaped
            at_bound = _at_bound(makespan, bound_s, opts.dt_s)
    found_pieces: dict[str, list[_Piece]] = {}
    if not (scenario.has_target & ~reached).any():
        found_pieces["prioritized"] = [_Piece(f"prioritized (reference 003's schedule, {how})", joints,
                                              np.flatnonzero(scenario.has_target).tolist(), 1, time.perf_counter() - t0)]
    if not left_short or at_bound:
        return found_pieces
    # Reference 003's schedule left some short: they retract (with a complete shape, a candidate beside it).
    home = _home(scenario)
    retract = scenario.has_target & ~found[1]
    for _ in range(RETRACTION_ROUNDS):
        retracted = _through_retraction(scenario, opts, home, retract)
        if retracted is not None:
            return found_pieces | {"prioritized through a retraction": retracted}
        grown = _with_neighbours(scenario, retract) & scenario.has_target  # their neighbours retract too, next round
        if np.array_equal(grown, retract):
            break
        retract = grown
    return found_pieces


RETRACTIONS = ((1.0, "target"), (1.0, "start"), (1.0, "half-way"), (0.75, "target"), (0.75, "start"), (0.75, "half-way"),
               (0.5, "target"), (0.5, "start"), (0.5, "half-way"))
"""The retracted configurations :func:`_through_retraction` tries: ``(f, alpha)``, beta the
fraction ``f`` of the way from the target's to the datum's, alpha the target's, the start's or
half-way between. Each is the shortest on some SDSS 7 hard seed (of the 12 that need a
retraction: the datum's beta at the target's alpha alone gave 1.16-1.70 x the bound, these
1.00-1.64 x; seed 8 1.273 -> 1.001, seed 29 1.225 -> 1.031)."""


def _scheduled_leg(opts: _Options) -> Callable[[Scenario], np.ndarray | None]:
    """A leg planned by the ``prioritized`` planner's schedule (:func:`_scheduled`): its joints if it brings everyone home, else ``None``."""
    def plan(leg: Scenario) -> np.ndarray | None:
        found = _scheduled(leg, opts)
        return None if found is None or (leg.has_target & ~found[1]).any() else found[0]
    return plan


def _through_retraction(scenario: Scenario, opts: _Options, home: np.ndarray, short: np.ndarray,
                        plan: Callable[[Scenario], np.ndarray | None] | None = None, names: tuple[str, str, str] = (
                            "prioritized-retract", "prioritized-retract-reversed", "prioritized"),
                        shorter_than: int | None = None) -> list[_Piece] | None:
    """The ``prioritized through a retraction`` candidate of :func:`_prioritized`: of the
    retracted configurations :data:`RETRACTIONS`, the shortest whole; ``None`` if none is clear or
    every one has a leg that leaves anyone short. They are tried in the order of their bounds (each
    positioner's full-speed time to the retracted configuration and on to its target); once the
    best plan found is no longer than the next bound, the rest cannot beat it and are not planned
    (the same result as planning all nine, for less: on MOONS' zones each leg costs seconds).

    ``plan`` plans each leg (its joints if complete, else ``None``; default: the ``prioritized``
    planner's schedule, :func:`_scheduled_leg`); ``names``: the two legs' kinds and the piece's
    first word (:func:`_direct_retraction` plans the legs with the run's planner); with
    ``shorter_than`` (samples), retractions whose bound is not shorter are not planned."""
    t0 = time.perf_counter()
    plan = _scheduled_leg(opts) if plan is None else plan
    beta = _datum(scenario)[:, 1]
    alphas = {"target": scenario.target[:, 0], "start": scenario.start[:, 0],
              "half-way": 0.5 * (scenario.start[:, 0] + scenario.target[:, 0])}
    speed = scenario.instrument.speeds_rad_s
    tried = []
    for k, (fraction, where) in enumerate(RETRACTIONS):
        mid = home.copy()
        mid[short, 0] = alphas[where][short]
        mid[short, 1] = home[short, 1] + fraction * (beta[short] - home[short, 1])
        # No plan through ``mid`` ends sooner: each positioner passes through it, at full speed at best.
        bound_s = float(np.max(np.max(np.abs(mid - scenario.start) / speed, axis=1) + np.max(np.abs(home - mid) / speed, axis=1)))
        tried.append((bound_s, k, fraction, where, mid))
    best: tuple[np.ndarray, int, str, int] | None = None
    for bound_s, k, fraction, where, mid in sorted(tried, key=lambda t: (t[0], t[1])):  # the most promising first
        if best is not None and bound_s > (len(best[0]) - 1) * opts.dt_s + 1e-9:
            break  # this one and the rest cannot be shorter
        if shorter_than is not None and bound_s > (shorter_than - 1) * opts.dt_s + 1e-9:
            break
        if len(scenario.pairs) and float(np.min(min_pair_clearance(scenario.instrument, scenario.base_xy, scenario.orient, mid,
                                                                   scenario.pairs))) <= opts.floor_mm:
            continue
        first = leg_scenario(scenario, scenario.start, mid, names[0])
        back = leg_scenario(scenario, home, mid, names[1])
        # The second leg first: only the retracting ones move in it, and where one of them cannot
        # retract among the others on their targets (the usual failure), the first is not planned.
        two = plan(back)
        if two is None:
            continue
        one = plan(first)
        if one is None:
            continue
        j1 = exactly_at(one, first.target, mid)
        j2 = exactly_at(two, back.target, mid)[::-1]
        joints, shift = (overlap_legs(scenario, j1, j2, opts.floor_mm, opts.coarse_steps, rest=opts.rest_steps) if opts.overlap
                         else (np.concatenate([j1, j2[1:]]), 0))
        if best is None or (len(joints), k) < (len(best[0]), best[3]):  # (on a tie, the first of RETRACTIONS)
            best = (joints, shift, f"beta {fraction:g} of the way to the datum's, alpha at the {where}'s", k)
    if best is None:
        return None
    joints, shift, how, _ = best
    return [_Piece(f"{names[2]} through a retraction of {int(short.sum())} ({how}), overlapped by {shift} steps", joints,
                   np.flatnonzero(scenario.has_target).tolist(), 2, time.perf_counter() - t0, overlap_steps=shift)]


RETRACT_LATE = (1.5, 1.2)
""":func:`_direct_retraction` retracts the positioners the direct plan leaves short, then also
those it brings home later than these many lower bounds of the move (each a larger set, tried
in turn). SDSS 19 hard seeds 0-14 (session 37): the short ones alone were best on seed 3 (13.46
s, the datum's 20.78), the late ones too on seeds 12 and 14 (13.86 / 12.64 s, the layer's best
before 15.46 / 14.46 s)."""


def _direct_retraction(scenario: Scenario, plan_leg: PlanLeg, opts: _Options, direct: _Piece,
                       shorter_than: int | None = None) -> list[_Piece] | None:
    """The ``direct through a retraction`` candidate: the positioners the direct plan leaves short
    or brings home late (:data:`RETRACT_LATE`) retract (:data:`RETRACTIONS`: beta part or all the
    way to the datum's, alpha at the target's, the start's or half-way), everyone else goes
    straight to its target, in two legs of the run's planner: ``start -> that``, then ``(targets
    -> that)`` reversed, overlapped where clear (:func:`_through_retraction`). The issue's hybrid
    for small dense groups: direct moves for those the direct plan brings home in time, a partial
    retract for the others only, not the whole group through the datum; the sets tried: the
    short ones, with the late ones, and the short ones with their neighbours. The shortest whole
    kept; only retractions whose bound is below ``shorter_than`` samples (the best plan at hand) are
    planned; ``None`` if none gives two complete legs."""
    traj = Trajectory(np.arange(len(direct.joints)) * opts.dt_s, direct.joints)
    reached = reached_mask(scenario, traj)
    arrive = arrival_times(scenario, traj)
    bound_s = lower_bound_s(scenario)
    movable = scenario.has_target & ~scenario.locked
    candidates = [movable & (~reached | (arrive > late * bound_s)) for late in (np.inf, *RETRACT_LATE)]
    candidates.append(_with_neighbours(scenario, candidates[0]) & movable)  # the short ones' neighbours too
    sets: list[np.ndarray] = []
    for retract in candidates:
        if retract.any() and not any(np.array_equal(retract, r) for r in sets):
            sets.append(retract)

    def plan(leg: Scenario) -> np.ndarray | None:
        done = complete_leg(leg, plan_leg, opts.attempts, restarts=opts.restarts, solo=opts.solo, tails=opts.tails, groups=opts.groups)
        return done.joints if done.complete else None

    best: list[_Piece] | None = None
    home = _home(scenario)
    for retract in sets:
        bars = [n for n in (shorter_than, None if best is None else len(best[0].joints)) if n is not None]
        found = _through_retraction(scenario, opts, home, retract, plan, ("retract", UNFOLD_REVERSED_LEG, "direct"),
                                    shorter_than=min(bars, default=None))
        if found is not None and (best is None or len(found[0].joints) < len(best[0].joints)):
            best = found
    return best


def _retraction_candidates(scenario: Scenario, plan_leg: PlanLeg, opts: _Options, consider: Callable[[str, list[_Piece] | None],
                           dict[str, Any]], scored: Callable[[], list[tuple[int, float]]]) -> None:
    """The candidates ``direct`` and ``direct through a retraction`` (:func:`_direct_retraction`)
    of a small dense group, unless a complete plan at hand (``scored``: ``(short, makespan)`` of
    each) is at the lower bound; only retractions that can beat the best complete one are planned."""
    def best() -> float | None:
        return min((makespan for short, makespan in scored() if short == 0), default=None)

    at_hand = best()
    if at_hand is not None and _at_bound(at_hand, lower_bound_s(scenario), opts.dt_s):
        return
    direct = _direct(scenario, plan_leg, opts)
    consider("direct", direct)
    at_hand = best()
    shorter_than = None if at_hand is None else round(at_hand / opts.dt_s) + 1
    consider("direct through a retraction", _direct_retraction(scenario, plan_leg, opts, direct[0], shorter_than))


# ---------------------------------------------------------------------------- the layer
def _is_at_datum(scenario: Scenario, joints: np.ndarray) -> bool:
    free = ~scenario.locked
    return bool(np.all(joints[free] == _datum(scenario)[free]))


def _score(scenario: Scenario, traj: Trajectory) -> tuple[int, float]:
    """(positioners short, makespan): smaller is better."""
    reached = reached_mask(scenario, traj)
    arrive = arrival_times(scenario, traj)
    short = int(np.sum(scenario.has_target & ~reached))
    return short, float(np.nanmax(arrive[reached])) if reached.any() else 0.0


def _options(settings: Any, scenario: Scenario) -> _Options:
    step = max(1, round(0.25 / settings.dt_s))  # the overlap is searched in strides of 0.25 s, then refined
    ramp = scenario.instrument.motors.ramp_time_s
    # The ramps are kept where runs meet only by a planner that keeps them within its runs (the mpc's motor
    # governor): the others' plans turn back at every step where they wait, and are left to the discretiser.
    rest = 0 if ramp is None or not getattr(settings, "motor_limits", False) else math.ceil(ramp / settings.dt_s - 1e-9)
    return _Options(settings.route_attempts, settings.dt_s if settings.route_restarts else None, settings.route_overlap,
                    float(getattr(settings, "safety_margin_mm", 0.0)), step, settings.dt_s, rest, settings.route_tails,
                    int(getattr(settings, "route_prioritized_up_to", 0)), int(getattr(settings, "route_retract_up_to", 0)),
                    0.0 if getattr(settings, "schedule_pairs", True) else float(getattr(settings, "schedule_pairs_retry", 0.0)),
                    int(getattr(settings, "route_rescue_up_to", 0)), bool(getattr(settings, "route_groups", False)),
                    bool(getattr(settings, "route_partial_folds", False)))


def _is_dense(scenario: Scenario) -> bool:
    return scenario.instrument.reach_max_mm > DENSE_REACH * scenario.instrument.pitch_mm


def _strategies(scenario: Scenario, route: str, plan_leg: PlanLeg, opts: _Options,
                consider: Callable[[str, list[_Piece] | None], dict[str, Any]]) -> str:
    """Plan along ``route`` (every candidate goes to ``consider``); returns the structure found."""
    if route == "direct":
        consider("direct", _direct(scenario, plan_leg, opts))
    elif route == "reverse":
        consider("reverse", _reverse(scenario, plan_leg, opts))
    elif route == "via_datum":
        consider("via_datum", _via_datum(scenario, plan_leg, opts))
    elif route == "via_fold":
        consider("via_fold", _via_datum(scenario, plan_leg, opts, part_way=1.0))
    elif _is_at_datum(scenario, scenario.start):  # an unfold: the reverse of a fold
        # The fold's stragglers: a long alpha turn beside a neighbour folding in its way, which
        # neither the schedule's single searches nor the loop resolve. A fold that straggles is
        # planned again with the two searched together (mpc: schedule_pairs), the shorter kept.
        # On a dense field that second plan starts at once, on the core the first leaves idle,
        # and is let go if the first does not straggle: the same candidates either way.
        paired = functools.partial(plan_leg, overrides={"schedule_pairs": True})
        ahead = opts.pairs_above > 0 and _is_dense(scenario) and scenario.n_positioners <= AHEAD_UP_TO
        with Ahead(lambda: _reverse(scenario, paired, opts), start=ahead) as again:
            pieces = _reverse(scenario, plan_leg, opts)
            found = consider("reverse", pieces)
            # (A fold that group moves completed straggled too: without them it may have been long,
            # and the paired fold shorter than the grouped one; MOONS 61 unfold seed 7, 13.65 against 14.30 s.)
            grouped = pieces is not None and any(p.grouped for p in pieces)
            if opts.pairs_above and (found.get("short", 1) > 0 or found["makespan_s"] > opts.pairs_above * lower_bound_s(scenario) or grouped):
                consider("reverse (paired timed paths)", again.result())
        return "unfold"
    elif _is_at_datum(scenario, scenario.target):
        direct = _direct(scenario, plan_leg, opts)
        if consider("direct", direct).get("short", 0) > 0:
            consider("direct, met from the datum", _met_from_the_goal(scenario, plan_leg, opts, direct[0]))
        return "fold"
    elif _is_dense(scenario):
        # Dense: the direct plan leaves positioners short on every seed measured, and a fix-up
        # after it was slower than the two-leg plan on every one: the two legs (and in small
        # groups, after the prioritized schedule's candidates, the direct plan with a partial
        # retraction: coordinate).
        # Partial folds first: where one ends before the longest of the positioners' ways through the
        # datum to their targets at full speed, the two legs through the datum cannot be shorter, and
        # are not planned. (Only legs that stall and meet elsewhere, _meet, could be: a rescue, not
        # planned then.)
        best = _partial_folds(scenario, plan_leg, opts, consider) if opts.partial_folds else math.inf
        if best >= _way_s(scenario, _held(scenario, _datum(scenario))) - FLOOR_MARGIN_S:
            consider("via_datum", _via_datum(scenario, plan_leg, opts))
        return "dense"
    else:
        direct = _direct(scenario, plan_leg, opts)
        if consider("direct", direct).get("short", 1) > 0:
            consider("via_datum", _via_datum(scenario, plan_leg, opts))
            consider("fix_up", _fix_up(scenario, direct[0], plan_leg, opts))
    return "general"


FLOOR_MARGIN_S = 1.0
"""The two legs through the datum are skipped for their floor (:func:`_way_s`) only where the best
plan found ends this much before it (s). A makespan counts arrivals within the tolerance, a few
milliseconds before the exact joints; the second is a deliberately wide margin. (The partial folds'
own prune in :func:`_partial_folds` compares with the floor itself, as measured.)"""


def _held(scenario: Scenario, safe: np.ndarray) -> np.ndarray:
    """``safe`` as :func:`_via_datum` holds it for every positioner that is not locked (beside a
    locked one, a mover may fold at another alpha: :func:`_clear_holds`)."""
    movers = ~scenario.locked
    return _clear_holds(scenario, np.where(movers[:, None], safe, scenario.start), movers)


def _way_s(scenario: Scenario, safe: np.ndarray) -> float:
    """The longest of the positioners' own ways from the start through ``safe`` to their targets,
    each joint at full speed: no plan whose legs meet at ``safe`` ends before (the makespan counts
    the positioners with a target)."""
    way = move_times(scenario.instrument, scenario.start, safe) + move_times(scenario.instrument, safe, _home(scenario))
    return float(way[scenario.has_target & ~scenario.locked].max(initial=0.0))


def _partial_folds(scenario: Scenario, plan_leg: PlanLeg, opts: _Options,
                   consider: Callable[[str, list[_Piece] | None], dict[str, Any]]) -> float:
    """The two legs through the folded configurations of :data:`PARTIAL_FOLDS`, each where its legs'
    bounds promise a gain over the datum's (:data:`PARTIAL_FOLD_GAIN`) and its own floor
    (:func:`_way_s`) is below the best plan found. Returns the best complete plan's makespan (s;
    infinite if none)."""
    start = scenario.start
    datum_legs = _legs_bound_s(scenario, start, _datum(scenario))
    best = math.inf
    for fraction in PARTIAL_FOLDS:
        safe = _folded_part_way(scenario, start, fraction)
        if _legs_bound_s(scenario, start, safe) > PARTIAL_FOLD_GAIN * datum_legs or _way_s(scenario, _held(scenario, safe)) >= best:
            continue
        found = consider(f"via a partial fold ({fraction:g})", _via_datum(scenario, plan_leg, opts, part_way=fraction))
        if found.get("short", 1) == 0:
            best = min(best, found["makespan_s"])
    return best


_WHOLE_FALLBACK = contextvars.ContextVar("whole_fallback", default=False)
"""Set while a fallback planner plans a whole move: it is not handed back (the mpc and the dnf
are each other's fallback)."""


def _whole_by_fallback(scenario: Scenario, fallback: str, dt: float) -> list[_Piece] | None:
    """The whole move planned by the fallback planner with its own defaults (its own route
    through this layer, and its own fallback inside its legs, but no whole move handed back), as
    one piece; ``None`` if its control step differs (the pieces share one time grid)."""
    from fiberplan.planners import plan

    t0 = time.perf_counter()
    token = _WHOLE_FALLBACK.set(True)
    try:
        result = plan(scenario, fallback)
    finally:
        _WHOLE_FALLBACK.reset(token)
    times = result.trajectory.times
    if len(times) > 1 and not np.allclose(np.diff(times), dt, rtol=1e-9, atol=0.0):
        return None
    return [_Piece(f"fallback planner ({fallback})", result.trajectory.joints, np.flatnonzero(scenario.has_target).tolist(), 1,
                   time.perf_counter() - t0)]


def coordinate(
    scenario: Scenario, planner: str, settings: Any, plan_leg: PlanLeg, wall0: float, progress: Callable[..., None] | None = None,
) -> PlanResult:
    """Plan ``scenario`` along ``settings.route`` (see the package docstring).

    Args:
        scenario: what to plan.
        planner: the planner's registry name.
        settings: its settings (:class:`RouteSettings` fields, ``dt_s``, ``safety_margin_mm`` if any).
        plan_leg: plans one leg with this planner and ``route = direct``.
        wall0: ``time.perf_counter()`` when planning began.
        progress: called as ``progress(fraction, phase)`` during every planner run; run ``k``
            fills the fraction from ``1 - 2^(1-k)`` to ``1 - 2^-k`` (the number of runs is not
            known beforehand); the phase names the run and the planner's own phase.
    """
    route, dt = settings.route, settings.dt_s
    fallback = getattr(settings, "route_fallback_planner", None)
    candidates: dict[str, list[_Piece]] = {}
    scores: dict[str, tuple[int, float]] = {}  # (short, makespan) of each candidate, scored once
    tried: list[dict[str, Any]] = []
    runs: list[dict[str, Any]] = []  # every planner run's statistics
    # The runs from the scenario's own start, whole: only such a run can be the returned trajectory
    # alone (the others' trajectories are let go as soon as their legs are built).
    from_start: list[PlanResult] = []
    CHILD_RUNS.clear()

    def recorded(leg: Scenario, **kwargs: Any) -> PlanResult:
        number, done = len(runs) + 1, 1.0 - 0.5 ** len(runs)

        def inner(fraction: float, phase: str | None = None) -> None:  # each run fills half of what is left
            if progress is not None and not _fork.in_child():  # (a leg planned in a forked process: the parent's bar shows)
                progress(done + 0.5 ** number * fraction, f"planner run {number}" + (f": {phase}" if phase else ""))

        result = plan_leg(leg, progress=inner, **kwargs)
        runs.append(result.stats)
        if leg.start.shape == scenario.start.shape and np.array_equal(leg.start, scenario.start):
            from_start.append(result)
        RUN_LOG.append(dict(result.stats))
        return result

    def consider(name: str, pieces: list[_Piece] | None) -> dict[str, Any]:
        entry: dict[str, Any] = {"strategy": name, "complete": pieces is not None}
        if pieces is not None:
            short, makespan = scores[name] = _score(scenario, _join(scenario, pieces, dt, opts.rest_steps))
            entry |= {"short": short, "makespan_s": makespan}
            candidates[name] = pieces
        tried.append(entry)
        return entry

    opts = _options(settings, scenario)
    structure = _strategies(scenario, route, recorded, opts, consider)
    if route == "auto" and scenario.n_positioners <= opts.prioritized_up_to and not opts.rest_steps and not _WHOLE_FALLBACK.get():
        # (Not where the run keeps speed ramps between its runs: the schedule's moves start and stop at full speed.)
        for name, pieces in _prioritized(scenario, opts).items():
            consider(name, pieces)
    if route == "auto" and structure == "dense" and scenario.n_positioners <= opts.retract_up_to and not _WHOLE_FALLBACK.get():
        _retraction_candidates(scenario, recorded, opts, consider, lambda: [scores[name] for name in candidates])

    def short() -> bool:
        return not candidates or min(scores[name][0] for name in candidates) > 0

    def best() -> str:
        # Fewest short, then the shortest; on a tie the two-leg plan (so never worse than it).
        return min(candidates, key=lambda n: (scores[n], n != "via_datum"))

    def rescued() -> bool:
        # Compared only on fields of up to route_rescue_up_to positioners: on MOONS 500 (moons-capsules,
        # random) the fallback planner's whole move and the direct plan took most of a rescued plan's
        # planning (seed 12: 360 of 480 s) and were not shorter on the seeds measured (docs/results.md, session 40).
        # A leg group moves completed is one the planner's first attempt left short, as a rescued one:
        # without group moves it would have been rescued, or left short, and these compared (MOONS 7
        # random seed 4 under MOONS' zones: through the datum with group moves 25.65 s, the fallback
        # planner's whole move 22.9 s; MOONS 61 unfold seed 20: 19.10 s against 18.85 s).
        return (bool(candidates) and any(p.rescued or p.grouped for p in candidates[best()])
                and scenario.n_positioners <= opts.rescue_up_to)

    weighed = short() or rescued()  # (before the fallback planner's whole move, which may itself be long, joins)
    if weighed and fallback and not _WHOLE_FALLBACK.get():
        # Positioners left short: the fallback planner over the whole move, with its own route
        # (inside a leg it is tried only from where an attempt stalled, when the tangle may
        # already be beyond it). MOONS 7 random seed 4 under MOONS' zones: 7 of 7 this way, 3 of 7
        # by the mpc's direct plan. Also where the best plan is complete only through the later
        # fallback rounds inside a leg (legs.Leg.rescued): such legs are long (MOONS 61 unfold,
        # MOONS' zones, seed 23: 51.6 s through them, 13.7 s by the fallback planner's whole move).
        consider("fallback planner", _whole_by_fallback(scenario, fallback, dt))
    if not candidates or (weighed and "direct" not in candidates):  # the direct plan, with what it reached
        # (Also against a rescued plan: MOONS 61 unfold seed 5 under MOONS' zones, the reverse route rescued
        # 56.8 s, the fallback planner's whole move 2 short, the direct plan complete in 20.75 s. Also where the
        # fallback planner's whole move then came first: seed 13, the reverse met where it stalled (rescued),
        # the dnf's whole move 117.5 s, the direct plan 46.55 s.)
        consider("direct (fallback)", _direct(scenario, recorded, opts))
    chosen = best()  # (the one rescued() looked at, had no candidate joined since)
    pieces = candidates[chosen]
    trajectory = _join(scenario, pieces, dt, opts.rest_steps)
    stats: dict[str, Any] = {"route": route, "structure": structure, "chosen": chosen, "candidates": tried,
                             "planner_runs": len(runs) + len(CHILD_RUNS)} | _leg_stats(scenario, pieces, dt)
    if opts.rest_steps:  # the legs' times above are before these holds
        stats["ramp_rest_s"] = (len(trajectory.joints) - sum(len(p.joints) - 1 for p in pieces) - 1) * dt
    single = [r for r in from_start if np.array_equal(r.trajectory.joints, trajectory.joints)]
    if single:
        # The planner alone, in one run: its own result, with the route named.
        only = single[0]
        return dataclasses.replace(only, stats=only.stats | stats, settings=dataclasses.asdict(settings),
                                   plan_wall_s=time.perf_counter() - wall0)
    for run_stats in runs + CHILD_RUNS:  # the planners' counters, summed over every run of every leg tried
        for key, value in run_stats.items():
            if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)):
                stats[key] = stats.get(key, 0) + value
    final = trajectory.joints[-1]
    short = scenario.has_target & ~np.all(final == scenario.target, axis=1) & ~reached_mask(scenario, trajectory)
    warnings = []
    if chosen == "fallback planner":
        others = [e for e in tried if e["strategy"] != chosen]
        why = "left positioners short" if all(e.get("short", 1) > 0 for e in others) else "were longer or left positioners short"
        warnings.append(f"{planner} ({route}): the move was planned by the fallback planner {fallback} (this planner's routes "
                        f"{why}: {', '.join(e['strategy'] for e in others)})")
    if short.any():
        warnings.append(f"{planner} ({route}): {int(short.sum())} of {int(scenario.has_target.sum())} positioners did not reach their "
                        f"targets along any route tried ({', '.join(e['strategy'] for e in tried)})")
    return PlanResult(scenario=scenario, trajectory=trajectory, outcome=outcome_labels(scenario, final, short), planner=planner,
                      settings=dataclasses.asdict(settings), stats=stats, warnings=tuple(warnings),
                      plan_wall_s=time.perf_counter() - wall0)


def _leg_stats(scenario: Scenario, pieces: list[_Piece], dt: float) -> dict[str, Any]:
    """The legs (times, planner runs, positioners moved, plan time, overlap), the ids carried through
    the datum and the ids group moves moved (``route_groups``: not counted in a partial retraction's legs)."""
    legs, t = [], 0.0
    for p in pieces:
        duration = (len(p.joints) - 1) * dt
        legs.append({"leg": p.name, "t0_s": t, "t1_s": t + duration, "attempts": p.attempts, "moved": len(p.moved),
                     "plan_wall_s": p.wall_s, "overlap_s": p.overlap_steps * dt, "first_plan_s": ((p.first_samples or len(p.joints)) - 1) * dt})
        t += duration
    carried = sorted({int(scenario.ids[i]) for p in pieces if p.through_datum for i in p.moved})
    grouped = sorted({int(scenario.ids[i]) for p in pieces for i in p.grouped})
    first = [(p.first_samples or len(p.joints)) - 1 for p in pieces]
    # first_plan_s: the duration as the legs were first planned, one after the other, before restarts
    # and overlap shortened them (through the datum: the plain two-leg plan).
    return {"legs": legs, "via_datum_ids": carried, "n_via_datum": len(carried), "grouped_ids": grouped, "n_grouped": len(grouped),
            "overlap_s": sum(p.overlap_steps for p in pieces) * dt, "first_plan_s": sum(first) * dt}
