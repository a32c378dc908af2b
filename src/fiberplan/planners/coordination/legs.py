"""Legs: one planner's move from a start to a goal configuration, completed by further attempts
and shortened by restarts (``formulations/coordination.md``, Completing a leg).

A leg is a scenario in which every positioner that is not locked has a joint target. It is
planned by ``plan_leg`` (the run's planner with ``route = direct``), then again from where each
attempt stopped until every positioner sits exactly on its target (:func:`complete_leg`). A
complete leg whose last arrivals straggle is planned again from where most positioners had
arrived, and the shortest is kept (:func:`shorten_leg`): a new run of the planner starts a new
schedule and resets the state of its deadlocks, which the stragglers of the first run were left
to resolve one by one.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from fiberplan.geometry import motion_bound, path_clearance, point_extents
from fiberplan.metrics import arrival_times
from fiberplan.planners.coordination.groups import Stop
from fiberplan.planners.coordination.groups import groups as group_moves
from fiberplan.planners.coordination.settings import REVERSE_LEG, REVERSED_LEGS, TAIL_FORWARD
from fiberplan.planners.coordination.solo import solo_moves
from fiberplan.scenario import TARGET_JOINTS, TARGET_NONE, Scenario, _replace
from fiberplan.trajectory import PlanResult, Trajectory


@dataclasses.dataclass(frozen=True)
class Leg:
    """A planned leg: ``joints`` ``(K, N, 2)``, the planner ``runs`` it took, whether it is
    ``complete``, and the samples it had before restarts shortened it (``first_samples``);
    ``rescued``: the fallback planner ran after the leg had parked, or the leg's own planner ran
    again after the fallback planner (the rounds added in session 24: such legs are often long,
    and the coordination layer then also tries the fallback planner's whole move and the direct
    plan)."""

    joints: np.ndarray
    runs: int
    complete: bool
    first_samples: int
    wall_s: float = 0.0
    rescued: bool = False
    untailed: np.ndarray | None = None  # the leg before a backward tail shortened it (None: no tail kept)
    grouped: tuple[int, ...] = ()  # positioners (indices) group moves moved (the stragglers and those that made way)

    def ending_at(self, goal: np.ndarray, exact: np.ndarray) -> Leg:
        """This leg (and its untailed form) with every positioner sitting on ``goal`` set to
        ``exact`` (:func:`exactly_at`)."""
        untailed = None if self.untailed is None else exactly_at(self.untailed, goal, exact)
        return dataclasses.replace(self, joints=exactly_at(self.joints, goal, exact), untailed=untailed)


PlanLeg = Callable[..., PlanResult]
"""Plans one leg with the run's planner and settings (``route = direct``); ``time_limit_s``
(optional) stops it early; ``use_fallback`` plans it with the fallback planner instead;
``overrides`` (optional) changes settings of the run's planner for this leg."""

RESTART_FRACTIONS = (0.7, 0.8, 0.9, 0.95)
"""A complete leg is planned again from the first sample at which these fractions of its
movers sat on their targets (:func:`shorten_leg`)."""

RESTART_ABOVE = 1.2
"""Only a leg longer than this many times its lower bound (the slowest straight joint move at
full speed) is restarted: below, a restart costs planning time for little (DESI runs end at
1.0-1.2 times the bound)."""


LOCAL_ABOVE = 2000
"""A leg attempt on more positioners than this, with few of them away from their targets, is
planned on the part of the field that still moves (:func:`_plan_part`): below, every attempt is
planned whole (every benchmark set: their trajectories are those of before)."""

LOCAL_SHARE = 0.5
"""... and only when that part holds at most this share of the positioners."""


def _plan_part(leg: Scenario, plan_leg: PlanLeg, **kwargs: object) -> tuple[np.ndarray, float]:
    """``plan_leg(leg, **kwargs)``'s joints ``(K, N, 2)`` and duration (s). A large leg in which
    few positioners are away from their targets is planned on those positioners and their
    neighbours (who may yield to them), the neighbours around those held as locked obstacles; the
    rest of the field holds where it is, as it would in a whole plan, and is not planned: a leg's
    later attempts and restarts then cost what the positioners still moving cost, not the field."""
    moving = _moving_part(leg)
    if moving is None:
        result = plan_leg(leg, **kwargs)
        return result.trajectory.joints, result.trajectory.duration_s
    rows, ring = moving
    part = leg.subset(rows, name=f"{leg.name}:part")
    held = ring[rows]
    part = _replace(part, locked=part.locked | held, target_kind=np.where(held, TARGET_NONE, part.target_kind),
                    target_values=np.where(held[:, None], 0.0, part.target_values))
    result = plan_leg(part, **kwargs)
    moved = result.trajectory.joints
    joints = np.repeat(leg.start[None], len(moved), axis=0)
    joints[:, rows] = moved
    return joints, result.trajectory.duration_s


def _moving_part(leg: Scenario) -> tuple[np.ndarray, np.ndarray] | None:
    """The rows :func:`_plan_part` plans (those away, their neighbours and the ring around them)
    and the ring mask, or ``None`` when the leg is planned whole (small, nothing away, or the part
    more than :data:`LOCAL_SHARE` of the field)."""
    n, pairs = leg.n_positioners, leg.pairs
    away = ~at_targets(leg, leg.start) & ~leg.locked
    if n <= LOCAL_ABOVE or not away.any() or not len(pairs):
        return None
    free = with_neighbours(away, pairs)
    ring = with_neighbours(free, pairs) & ~free
    rows = np.flatnonzero(free | ring)
    return (rows, ring) if len(rows) <= LOCAL_SHARE * n else None


def with_neighbours(mask: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``mask`` and every positioner paired with one in it."""
    out = mask.copy()
    touching = mask[pairs[:, 0]] | mask[pairs[:, 1]]
    out[pairs[touching].ravel()] = True
    return out


def leg_scenario(scenario: Scenario, start: np.ndarray, goal: np.ndarray, name: str) -> Scenario:
    """The same positioners from ``start`` to ``goal`` (rad), every one with a joint target
    (locked ones stay locked, without a target)."""
    n = scenario.n_positioners
    kind = np.where(scenario.locked, TARGET_NONE, TARGET_JOINTS)
    return _replace(
        scenario, start_deg=np.degrees(start), target_kind=kind, target_values=np.where(scenario.locked[:, None], 0.0, np.degrees(goal)),
        target_parity=np.zeros(n, dtype=np.int64), name=f"{scenario.name}:{name}", kind=name,
    )


def at_targets(scenario: Scenario, joints: np.ndarray) -> np.ndarray:
    """Which positioners sit exactly on their (leg) targets."""
    return np.all(joints == scenario.target, axis=1)



def complete_leg(
    leg: Scenario, plan_leg: PlanLeg, attempts: int, time_limit_s: float | None = None, unblock: bool = True, strict: bool = True,
    restarts: float | None = None, solo: tuple[float, float] | None = None, tails: bool = False, groups: bool = False,
) -> Leg:
    """Plan ``leg``, then again from where each attempt stopped, until every positioner sits on
    its target, an attempt brings none closer, or ``time_limit_s`` of motion is used up. When an
    attempt stalls on folded neighbours in the way (a fold whose datum blocks the last ones),
    those neighbours are parked at another alpha, folded (:func:`_parking`), while the blocked
    ones arrive, and come back in the next attempt. A leg complete in one run is then shortened
    by restarts when ``restarts`` is given: the planner's sample period (s) (:func:`shorten_leg`).
    With ``solo = (floor_mm, dt_s)``, positioners the attempts leave short go home one at a time
    along their own grid paths while everyone else holds (:mod:`.solo`), before the fallback
    planner and once more at the end. With ``tails`` (and ``restarts``), a complete leg whose last
    positioners straggle has its tail planned backwards (:func:`tail_backwards`). With ``groups``
    (and ``solo``), the first attempt completed by group moves (:mod:`.groups`: its positioners
    left short go home with the neighbours in their way), where every group finds a way, is kept
    instead of the further attempts' leg if that is incomplete or longer (``Leg.grouped`` names the
    positioners they moved, also where a restart or backward tail then re-planned the leg's end).
    Where a group found no way and the attempts leave the leg short, the first attempt's group
    moves go on from where they stopped as a last resort, the groups without a way searched
    harder after the others (``groups.groups`` with ``rescue``); kept if every group then finds a
    way. Where group moves' leg replaced the attempts' complete one, both are tailed and the
    shorter kept (:data:`TAIL_BOTH`)."""
    t0 = time.perf_counter()
    notes: dict[str, Any] = {}
    joints, runs, complete = _attempts(leg, plan_leg, attempts, time_limit_s, unblock, strict, solo, notes, groups)
    grouped, carried = notes.pop("grouped", (None, ()))
    first_attempt, stopped = notes.pop("first", (None, None))
    if grouped is None and not complete and first_attempt is not None:
        # The last resort: the first attempt's groups again (from where they stopped), those
        # without a way searched harder after the others (MOONS' zones, MOONS 500 unfold seed 15:
        # 12 short after every attempt).
        grouped, carried = _grouped(leg, first_attempt, solo, time_limit_s, rescue=True, resume=stopped)
    attempts_leg = None  # (the attempts' complete leg, where group moves' shorter one replaced it)
    if grouped is not None and (not complete or len(grouped) < len(joints)):
        if complete:
            attempts_leg = (joints, notes.get("rescued", False))
        joints, complete, notes["rescued"] = grouped, True, False
    else:
        carried = ()
    first = len(joints)
    # Restarts help a leg whose planner brought everyone home in one run, its stragglers late; a
    # leg that needed further attempts has stragglers that restarts leave stuck again (measured
    # on MOONS 500 folds: every restart incomplete), at the cost of a planner run each.
    if complete and restarts and runs == 1:
        joints, more = shorten_leg(leg, joints, plan_leg, restarts)
        runs += more
    untailed = None
    if complete and restarts and tails:
        before = joints
        joints, more = tail_backwards(leg, joints, plan_leg, restarts)
        runs += more
        untailed = None if joints is before else before
        if attempts_leg is not None and TAIL_BOTH:
            # The attempts' leg, longer than group moves' before the tails, may end earlier with
            # its own tail (MOONS 500 unfold seed 42: the reversed fold 35.9 s with group moves'
            # leg, 33.7 s with the attempts'); its tails stop once they cannot end first.
            other, more = tail_backwards(leg, attempts_leg[0], plan_leg, restarts, within=len(joints))
            runs += more
            if len(other) < len(joints):
                first, carried, notes["rescued"] = len(attempts_leg[0]), (), attempts_leg[1]
                joints, untailed = other, (None if other is attempts_leg[0] else attempts_leg[0])
    # (The ids name the group moves of the kept candidate, also where a restart or tail then re-planned
    # its end: a grouped leg's stragglers arrive late, and tails follow such legs.)
    return Leg(joints, runs, complete, first, time.perf_counter() - t0, rescued=notes.get("rescued", False), untailed=untailed,
               grouped=carried)


def shorten_leg(leg: Scenario, joints: np.ndarray, plan_leg: PlanLeg, dt_s: float, rounds: int = 2) -> tuple[np.ndarray, int]:
    """A complete leg planned again from where most of its movers had arrived; the shortest kept.

    A leg whose last arrival (within the tolerance, as the results count it) is within
    :data:`RESTART_ABOVE` times its lower bound is kept as it is. Otherwise, for
    each fraction ``f`` of :data:`RESTART_FRACTIONS`, the leg is cut at the first sample at
    which all but ``1 - f`` of its movers sat on their targets, and completed from there by new
    planner runs (:func:`complete_leg`, without parking). A restart is kept only if the whole
    leg ends earlier; with ``rounds`` > 1 the best leg is cut again. Every candidate starts from a
    sample of a collision-free leg, so the kept leg is as safe as the planner's own runs.
    ``dt_s`` is the sample period. Returns ``(joints, planner runs made)``.
    """
    runs = 0
    best = joints
    if not _straggles(leg, joints, dt_s):
        return joints, 0
    tried_up_to = 0  # cuts before the last kept one were tried in an earlier round, from the same samples
    for _ in range(rounds):
        base = best
        away = ~np.all(base == leg.target[None], axis=2)  # (K, N)
        movers = int(away[0].sum())
        if movers == 0:
            break
        left = away.sum(axis=1)
        cuts = sorted({int(np.argmax(left <= (1.0 - f) * movers)) for f in RESTART_FRACTIONS})
        kept = 0
        for k in cuts:
            # (A restart kept earlier in this round shortened ``best``: a cut at or past its end has no
            # time left to beat it, and planning it would have nothing to return.)
            if k <= tried_up_to or k >= len(base) - 2 or k >= len(best) - 1:
                continue
            restart = dataclasses.replace(leg, start_deg=np.degrees(base[k]), name=f"{leg.name}:restart")
            # A restart that cannot end before the best leg so far is of no use: it stops there.
            tail, n_runs, ok = _attempts(restart, plan_leg, 2, (len(best) - 1 - k) * dt_s, unblock=False, strict=False)
            runs += n_runs
            if ok and k + len(tail) < len(best):
                best, kept = np.concatenate([base[: k + 1], tail[1:]]), k
        if best is base:
            break
        tried_up_to = kept
    return best, runs


TAIL_BOTH = True
"""Where group moves completed a leg shorter than its further attempts (both complete), the
attempts' leg is tailed too (:func:`tail_backwards`) and the shorter kept."""

TAIL_FRACTIONS = (0.95, 0.98)
"""A complete leg's tail is planned backwards from the first sample at which these fractions of
its movers sat on their targets (:func:`tail_backwards`)."""


def tail_backwards(leg: Scenario, joints: np.ndarray, plan_leg: PlanLeg, dt_s: float,
                   within: int | None = None) -> tuple[np.ndarray, int]:
    """A complete leg whose last positioners straggle, with its tail planned in the other direction.

    Cut at the first sample at which a fraction ``f`` of :data:`TAIL_FRACTIONS` of the movers sat
    on their targets, the leg stands at ``E`` with a few positioners still away; the tail ``E ->
    goal`` is planned backwards, ``goal -> E`` (everyone else holds on the goal, the stragglers go
    out from it to where they stood), and played in reverse (a motion played backwards keeps its
    clearances, speeds and hard stops: ``formulations/coordination.md``, Two facts). Stragglers
    that block each other on the way in often do not on the way out: from the goal (a fold's
    datum, where the arms are clear of each other) they often leave one by one. The shortest leg
    is kept. Only a leg longer than :data:`RESTART_ABOVE` times its bound is tried; each backward
    tail is at most two planner runs (no parking, solo moves or fallback planner), stopped at the
    time that could still beat the best leg so far. Returns ``(joints, planner runs made)``.

    Measured on MOONS 500 unfold (``moons-capsules``), the fold from the targets: seed 0, cut with
    10 away at 13.7 s, the tail out from the datum takes 17.75 s in one run: 57.35 -> 31.45 s; on
    seeds 1-3 no backward tail completes (the stragglers stall on the way out too)."""
    if not _straggles(leg, joints, dt_s):
        return joints, 0
    away = ~np.all(joints == leg.target[None], axis=2)  # (K, N)
    movers = int(away[0].sum())
    if movers == 0:
        return joints, 0
    left = away.sum(axis=1)
    # (At least one straggler left out: a small leg's fractions would otherwise all cut at its end.)
    cuts = sorted({int(np.argmax(left <= max(1.0, (1.0 - f) * movers))) for f in TAIL_FRACTIONS})
    # Played in reverse within this leg: the tail's own motor rules read the other way.
    kind = TAIL_FORWARD if leg.kind in REVERSED_LEGS else REVERSE_LEG
    best, runs = joints, 0
    for k in cuts:
        beat = len(best) if within is None else min(len(best), within)  # (samples a tail must end before)
        if k < 1 or k >= beat - 2:
            continue
        back = _replace(leg, start_deg=np.degrees(leg.target), target_values=np.where(leg.locked[:, None], 0.0, np.degrees(joints[k])),
                        name=f"{leg.name}:tail-backwards", kind=kind)
        tail, n_runs, ok = _attempts(back, plan_leg, 2, (beat - 1 - k) * dt_s, unblock=False, strict=False)
        runs += n_runs
        if ok and k + len(tail) - 1 < beat - 1:
            tail = exactly_at(exactly_at(tail, back.target, joints[k]), back.start, leg.target)
            best = np.concatenate([joints[: k + 1], tail[::-1][1:]])
    return best, runs


def exactly_at(joints: np.ndarray, goal: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """Samples ``(K, N, 2)`` with every positioner sitting on ``goal`` set to ``exact``: a leg's
    goal as it read it (through the scenario format's degrees) may differ from the configuration
    it was taken from in the last bit (1e-16 rad), and pieces must meet at one configuration."""
    if not np.allclose(goal, exact, rtol=0.0, atol=1e-12):
        raise ValueError("a leg's goal is not the configuration it should meet")
    on = np.all(joints == goal[None], axis=2)
    return np.where(on[..., None], exact[None], joints)


def _straggles(leg: Scenario, joints: np.ndarray, dt_s: float) -> bool:
    """Whether a complete leg's last arrival (within the tolerance, as the results count it, not
    its last sample exactly on the targets) is later than :data:`RESTART_ABOVE` times its lower
    bound. DESI 50,000 seed 0 arrives at 1.196 x the bound, its last sample at 1.2016 x: four
    restarts counted by the last sample cost 80 s of planning and gained nothing."""
    bound_s = float(np.max(np.abs(leg.target - leg.start) / leg.instrument.speeds_rad_s, initial=0.0))
    arrive = arrival_times(leg, Trajectory(np.arange(len(joints)) * dt_s, joints))[leg.has_target]
    makespan_s = float(arrive.max()) if len(arrive) and np.isfinite(arrive).all() else (len(joints) - 1) * dt_s
    return makespan_s > RESTART_ABOVE * bound_s


def _attempts(
    leg: Scenario, plan_leg: PlanLeg, attempts: int, time_limit_s: float | None, unblock: bool, strict: bool,
    solo: tuple[float, float] | None = None, notes: dict[str, Any] | None = None, groups: bool = False,
) -> tuple[np.ndarray, int, bool]:
    """The attempts of :func:`complete_leg`; ``notes["rescued"]`` is set when the rounds of
    :data:`FALLBACK_ROUNDS` went beyond the single fallback attempt of before (see :class:`Leg`);
    with ``groups``, ``notes["grouped"]`` holds the first attempt completed by group moves, where
    every group found a way (a candidate: the attempts go on as without it), and the positioners
    the group moves moved; where group moves did not complete it (a group without a way, the
    checks used up, or the time limit), ``notes["first"]`` holds the first attempt and where its
    group moves stopped (``groups.groups``' ``stopped``, or ``None``)."""
    notes = {} if notes is None else notes
    if strict and leg.infeasible:  # a leg target that cannot be reached would break the joint between legs
        return leg.start[None].copy(), 0, False
    pieces: list[np.ndarray] = []
    current = leg
    done_before = -1
    used = 0.0
    k = 0
    fallbacks = 0
    park = unblock

    def current_from(q: np.ndarray) -> Scenario:
        return dataclasses.replace(leg, start_deg=np.degrees(q), name=f"{leg.name}:fallback")

    while k < attempts:
        k += 1
        if time_limit_s is None:
            planned, duration = _plan_part(current, plan_leg)
        else:
            if time_limit_s - used <= 0:
                break
            planned, duration = _plan_part(current, plan_leg, time_limit_s=time_limit_s - used)
        joints = trim(planned)
        used += duration
        pieces.append(joints if not pieces else joints[1:])
        end = joints[-1]
        at = at_targets(leg, end)
        if groups and solo is not None and k == 1 and not at.all():
            # A candidate beside the attempts that follow (complete_leg keeps the shorter).
            stopped: list[Stop] = []
            grouped = _grouped(leg, joints, solo, time_limit_s, stopped=stopped)
            if grouped[0] is not None:
                notes["grouped"] = grouped
            else:
                notes["first"] = (joints, stopped[0] if stopped else None)  # (for complete_leg's last resort)
        if at.all():  # (one piece: the planner's own array, not a copy of it: 200 MB at 50,000 positioners)
            return (pieces[0] if len(pieces) == 1 else np.concatenate(pieces)), k, True
        if k < attempts and int(at.sum()) > done_before:  # another attempt follows: it starts at the last arrival
            cut = _until_last_arrival(leg, joints)
            pieces[-1] = cut if len(pieces) == 1 else cut[1:]
            end = cut[-1]
            at = at_targets(leg, end)
        if int(at.sum()) <= done_before:
            # An attempt that brought no one home is dropped: it only cost time.
            pieces.pop()
            end = current.start
            if solo is not None:
                moved = solo_moves(leg, end, *solo)[0]
                # Kept only if it brought more home than any attempt so far: the next attempt may undo a
                # yield, and solo moves that bring no one home would alternate with it for ever.
                if len(moved) > 1 and int(at_targets(leg, moved[-1]).sum()) > done_before:
                    pieces.append(moved[1:])
                    end = moved[-1]
                    if at_targets(leg, end).all():
                        return np.concatenate(pieces), k, True
                    done_before = int(at_targets(leg, end).sum())
                    current = dataclasses.replace(leg, start_deg=np.degrees(end), name=f"{leg.name}:after-solo{k}")
                    attempts = max(attempts, k + 1)
                    continue
            parked = _parking(leg, end) if park else None
            if parked is None:
                if fallbacks >= FALLBACK_ROUNDS or not unblock:
                    break
                # The last resort: an attempt of the fallback planner from where this one stalled.
                if not park:  # no fallback followed parking before
                    notes["rescued"] = True
                fallbacks += 1
                joints = trim(_plan_part(current_from(end), plan_leg, use_fallback=True)[0])
                pieces.append(joints[1:])
                end = joints[-1]
                k += 1
                if at_targets(leg, end).all():
                    return np.concatenate(pieces), k, True
                if fallbacks >= FALLBACK_ROUNDS:
                    break
                # Then this planner again from where the fallback stopped: a stall it left is a new
                # start, however many it brought home (MOONS 61 unfold seed 35 under MOONS' zones,
                # the fold from the targets: the dnf from the mpc's stall brings no one more home,
                # the mpc from the dnf's end all). An attempt that brings no more home than the
                # fallback is dropped as above.
                done_before = int(at_targets(leg, end).sum())
                notes["rescued"] = True
                current = dataclasses.replace(leg, start_deg=np.degrees(end), name=f"{leg.name}:after-fallback{fallbacks}")
                attempts = max(attempts, k + 1)
                continue
            detour = dataclasses.replace(leg, start_deg=np.degrees(end), target_values=np.degrees(parked), name=f"{leg.name}:parked")
            d_joints, _, _ = _attempts(detour, plan_leg, 2, None, unblock=False, strict=False)
            d_joints = trim(d_joints)
            pieces.append(d_joints[1:])
            end = d_joints[-1]
            attempts = max(attempts, k + 2)  # the parked ones come back
            park = False  # once per leg (the fallback planner may still follow)
        done_before = int(at_targets(leg, end).sum())
        current = dataclasses.replace(leg, start_deg=np.degrees(end), name=f"{leg.name}:attempt{k + 1}")
    if solo is not None and pieces:
        # Once more at the end: the last attempt cut at its last arrival, then the ones still short alone.
        # (The sample it starts from ends the last piece that has one: a fallback round that moved
        # no one leaves an empty piece. MOONS 19 hard seed 1 crashed on two of them.)
        before = next((p[-1:] for p in reversed(pieces[:-1]) if len(p)), None)  # None: the first attempt, with its start
        cut = _until_last_arrival(leg, pieces[-1] if before is None else np.concatenate([before, pieces[-1]]))
        pieces[-1] = cut if before is None else cut[1:]
        moved = solo_moves(leg, cut[-1], *solo)[0]
        pieces.append(moved[1:])
        if at_targets(leg, moved[-1]).all():
            return np.concatenate(pieces), k, True
    if not pieces:  # no attempt was made (no time left): the leg stays where it starts
        return leg.start[None].copy(), k, False
    return np.concatenate(pieces), k, False


FALLBACK_ROUNDS = 2
"""Attempts of the fallback planner per leg, each followed by this planner's own attempts from
where it stopped (one until session 24)."""


PARK_OFFSETS_DEG = (30.0, -30.0, 60.0, -60.0, 90.0, -90.0, 120.0, -120.0, 150.0, -150.0, 180.0, -180.0)
"""Alpha offsets tried, nearest first, to park a folded positioner out of a neighbour's way."""


def _park_candidates(q: np.ndarray, lim: np.ndarray) -> list[np.ndarray]:
    """Folded configurations at alphas offset from ``q``'s, nearest first, inside the hard stops."""
    out = []
    for off in np.radians(PARK_OFFSETS_DEG):
        alpha = q[0] + off
        if lim[0, 0] <= alpha <= lim[0, 1]:
            out.append(np.array([alpha, q[1]]))
    return out


def _parking(leg: Scenario, end: np.ndarray) -> np.ndarray | None:
    """Leg targets that let a stalled fold finish: a stuck positioner whose target is folded
    folds at another alpha where its straight way is clear; else the folded neighbours that block
    it are parked at another alpha, folded, where the stuck ones' straight paths clear them;
    ``None`` if neither helps. (Folded positioners keep clear of each other at any alphas, so a
    parked one can turn back to its target alpha once its neighbours are folded.)"""
    inst = leg.instrument
    step = inst.speeds_rad_s * inst.control_dt_s
    lim = inst.limits_rad
    pairs = leg.pairs
    # The planners keep margins of about a step's motion: a way counts as clear with twice that.
    room = 2.4 * float(motion_bound(point_extents(inst), step))
    stuck = ~at_targets(leg, end) & leg.has_target
    fold_beta = inst.datum_rad[1]
    resting = at_targets(leg, end) & (np.abs(end[:, 1] - fold_beta) < 1e-9) & ~leg.locked
    goal = leg.target.copy()
    parked_any = False
    folded_goal = np.abs(leg.target[:, 1] - fold_beta) < 1e-9
    for s in np.flatnonzero(stuck).tolist():
        rows = np.flatnonzero((pairs == s).any(axis=1)) if len(pairs) else np.zeros(0, dtype=int)
        nb = np.where(pairs[rows, 0] == s, pairs[rows, 1], pairs[rows, 0])
        if folded_goal[s]:
            # The stuck one itself folds at another alpha, nearest its target's, where its straight way is clear.
            for cand in _park_candidates(leg.target[s], lim):
                c = path_clearance(leg, np.full(len(nb), s), nb, np.repeat(end[[s]], len(nb), 0), np.repeat(cand[None], len(nb), 0),
                                   end[nb], step)
                if np.all(c > room):
                    goal[s] = cand
                    parked_any = True
                    break
            if parked_any and not np.array_equal(goal[s], leg.target[s]):
                continue
        c = path_clearance(leg, np.full(len(nb), s), nb, np.repeat(end[[s]], len(nb), 0), np.repeat(leg.target[[s]], len(nb), 0), end[nb], step)
        for j in nb[(c < 0.0) & resting[nb]].tolist():
            for cand in _park_candidates(end[j], lim):
                users = np.flatnonzero(stuck)
                users = users[np.isin(users, np.unique(pairs[(pairs == j).any(axis=1)].ravel()))]
                clear = path_clearance(leg, users, np.full(len(users), j), end[users], leg.target[users], np.repeat(cand[None], len(users), 0), step)
                if np.all(clear > room):
                    goal[j] = cand
                    resting[j] = False
                    parked_any = True
                    break
    return goal if parked_any else None


def _until_last_arrival(leg: Scenario, joints: np.ndarray) -> np.ndarray:
    """An incomplete attempt cut where its last positioner arrived for good: after that, no one
    arrives, and the ones still short are better off starting the next attempt from there."""
    at = np.all(joints == leg.target[None], axis=2)  # (K, N)
    done = at[-1]
    if not done.any():
        return joints
    away = ~at[:, done]
    last_away = np.where(away.any(axis=0), len(joints) - 1 - np.argmax(away[::-1], axis=0), -1)
    return joints[: int(last_away.max()) + 2]


def _grouped(leg: Scenario, joints: np.ndarray, solo: tuple[float, float], time_limit_s: float | None,
             rescue: bool = False, stopped: list[Stop] | None = None,
             resume: Stop | None = None) -> tuple[np.ndarray | None, tuple[int, ...]]:
    """An attempt ``joints`` of ``leg`` completed by group moves (:func:`.groups.groups`, with
    ``rescue``, ``stopped`` and ``resume`` as there), trimmed, and the positioners they moved;
    ``(None, ())`` unless every positioner ends on its target within ``time_limit_s``."""
    grouped = group_moves(leg, joints, *solo, rescue=rescue, stopped=stopped, resume=resume)
    grouped = None if grouped is None else trim(grouped)  # (its stragglers may have moved last: the idle end goes)
    if (grouped is None or not at_targets(leg, grouped[-1]).all()
            or (time_limit_s is not None and (len(grouped) - 1) * solo[1] > time_limit_s)):
        return None, ()
    return grouped, tuple(np.flatnonzero(_changed(joints, grouped)).tolist())


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Which positioners move differently in ``a`` and ``b`` ``(K, N, 2)``, each held at its end
    to the longer one's length."""
    k = max(len(a), len(b))
    a, b = (np.concatenate([x, np.repeat(x[-1:], k - len(x), axis=0)]) for x in (a, b))
    return np.any(a != b, axis=(0, 2))


def trim(joints: np.ndarray) -> np.ndarray:
    """An attempt without its idle end (after the last sample at which anything moved, everyone holds)."""
    moved = np.flatnonzero(np.any(joints[1:] != joints[:-1], axis=(1, 2)))
    return joints[: (moved[-1] + 2) if len(moved) else 1]

