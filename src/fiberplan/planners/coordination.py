"""The coordination layer: the problem's structure decides how a move is planned, above any planner.

A collision-free trajectory played backwards in time is collision-free, keeps the same speed
limits and hard stops, and starts where the original ended. So (``formulations/coordination.md``):

- ``reverse``: a move whose reverse is easier is planned in reverse and played forwards (an
  unfold, datum -> targets, is a fold from the targets, reversed);
- ``via_datum``: the whole move as two legs through the datum, each planned in its easy
  direction: start -> datum (a fold), then (target -> datum) reversed;
- ``via_fold``: the same through the folded configuration half-way in alpha (measured: the legs
  stall far more often than through the datum, where every arm turns the same way);
- ``auto`` (the default): by the scenario's structure: an unfold is reversed, a fold planned
  directly; on instruments whose patrol regions overlap densely (reach > 0.8 pitch: MOONS,
  SDSS) the two-leg plan; elsewhere the direct plan, and where it leaves positioners short, the
  better of a **fix-up** (the direct plan until its last arrival, then only the positioners
  still short, and the neighbours they need, through the datum, everyone else holding) and the
  **two-leg** plan. It is never worse than the two-leg plan: a candidate slower than it, or
  leaving more short, is not returned. Whatever the first choice, if it is incomplete the
  direct plan is the fallback;
- ``direct``: the planner alone.

Every leg is planned by the same planner (``mpc`` or ``dnf``, so that comparisons stay fair),
completed by further attempts from where the previous one stopped (each attempt is the same
planner from a new start, which breaks the state of a deadlock), and the legs are joined at
configurations that are equal, into one continuous trajectory that the caller verifies whole.
The result's ``stats`` name the route, the legs (times, planner attempts, positioners moved) and
which positioners each strategy carried.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from fiberplan.geometry import min_pair_clearance, motion_bound, path_clearance, point_extents
from fiberplan.metrics import arrival_times, reached_mask
from fiberplan.outcomes import outcome_labels
from fiberplan.scenario import TARGET_JOINTS, TARGET_NONE, Scenario, _replace
from fiberplan.trajectory import PlanResult, Trajectory

ROUTES = ("direct", "reverse", "via_datum", "via_fold", "auto")
"""Values of the ``route`` setting."""

PlanLeg = Callable[..., PlanResult]
"""Plans one leg with the run's planner and settings (``route = direct``); ``time_limit_s``
(optional) stops it early."""

DENSE_REACH = 0.8
"""Patrol regions overlap densely when the reach exceeds this fraction of the pitch (MOONS,
SDSS: 1.0; DESI: 0.58): there the two-leg plan comes first and bounds the direct attempt."""


@dataclasses.dataclass
class _Piece:
    """Part of the combined trajectory: samples ``(K, N, 2)`` after the previous piece's end."""

    name: str
    joints: np.ndarray
    moved: list[int]
    attempts: int
    wall_s: float


def leg_scenario(scenario: Scenario, start: np.ndarray, goal: np.ndarray, name: str) -> Scenario:
    """The same positioners from ``start`` to ``goal`` (rad), every one with a joint target
    (locked ones stay locked, without a target)."""
    n = scenario.n_positioners
    kind = np.where(scenario.locked, TARGET_NONE, TARGET_JOINTS)
    return _replace(
        scenario, start_deg=np.degrees(start), target_kind=kind, target_values=np.where(scenario.locked[:, None], 0.0, np.degrees(goal)),
        target_parity=np.zeros(n, dtype=np.int64), name=f"{scenario.name}:{name}", kind=name,
    )


def _at(scenario: Scenario, joints: np.ndarray) -> np.ndarray:
    """Which positioners sit exactly on their (leg) targets."""
    return np.all(joints == scenario.target, axis=1)


def _complete(
    leg: Scenario, plan_leg: PlanLeg, attempts: int, time_limit_s: float | None = None, unblock: bool = True, strict: bool = True,
) -> tuple[np.ndarray, int, bool]:
    """Plan ``leg``, then again from where each attempt stopped, until every positioner sits on
    its target, an attempt brings none closer, or ``time_limit_s`` of motion is used up. When an
    attempt stalls on folded neighbours in the way (a fold whose datum blocks the last ones),
    those neighbours are parked at another alpha, folded (:func:`_parking`), while the blocked
    ones arrive, and come back in the next attempt. Returns ``(joints (K, N, 2), attempts, complete)``."""
    if strict and leg.infeasible:  # a leg target that cannot be reached would break the joint between legs
        return leg.start[None].copy(), 0, False
    pieces: list[np.ndarray] = []
    current = leg
    done_before = -1
    used = 0.0
    k = 0
    fallback_used = False

    def current_from(q: np.ndarray) -> Scenario:
        return dataclasses.replace(leg, start_deg=np.degrees(q), name=f"{leg.name}:fallback")

    while k < attempts:
        k += 1
        if time_limit_s is None:
            result = plan_leg(current)
        else:
            if time_limit_s - used <= 0:
                break
            result = plan_leg(current, time_limit_s=time_limit_s - used)
        joints = _trim(result.trajectory.joints)
        used += result.trajectory.duration_s
        pieces.append(joints if not pieces else joints[1:])
        end = joints[-1]
        at = _at(leg, end)
        if at.all():
            return np.concatenate(pieces), k, True
        if k < attempts and int(at.sum()) > done_before:  # another attempt follows: it starts at the last arrival
            cut = _until_last_arrival(leg, joints)
            pieces[-1] = cut if len(pieces) == 1 else cut[1:]
            end = cut[-1]
            at = _at(leg, end)
        if int(at.sum()) <= done_before:
            # An attempt that brought no one home is dropped: it only cost time.
            pieces.pop()
            end = current.start
            parked = _parking(leg, end) if unblock else None
            if parked is None:
                if fallback_used or not unblock:
                    break
                # The last resort: one attempt of the fallback planner from where this one stalled.
                fallback_used = True
                result = plan_leg(current_from(end), use_fallback=True)
                joints = _trim(result.trajectory.joints)
                pieces.append(joints[1:])
                end = joints[-1]
                if _at(leg, end).all():
                    return np.concatenate(pieces), k + 1, True
                break
            detour = dataclasses.replace(leg, start_deg=np.degrees(end), target_values=np.degrees(parked), name=f"{leg.name}:parked")
            d_joints, _, _ = _complete(detour, plan_leg, 2, None, unblock=False, strict=False)
            d_joints = _trim(d_joints)
            pieces.append(d_joints[1:])
            end = d_joints[-1]
            attempts = max(attempts, k + 2)  # the parked ones come back
            unblock = False  # once per leg
        done_before = int(_at(leg, end).sum())
        current = dataclasses.replace(leg, start_deg=np.degrees(end), name=f"{leg.name}:attempt{k + 1}")
    return np.concatenate(pieces), k, False


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
    stuck = ~_at(leg, end) & leg.has_target
    fold_beta = inst.datum_rad[1]
    resting = _at(leg, end) & (np.abs(end[:, 1] - fold_beta) < 1e-9) & ~leg.locked
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


def _trim(joints: np.ndarray) -> np.ndarray:
    """An attempt without its idle end (after the last sample at which anything moved, everyone holds)."""
    moved = np.flatnonzero(np.any(joints[1:] != joints[:-1], axis=(1, 2)))
    return joints[: (moved[-1] + 2) if len(moved) else 1]


def _join(scenario: Scenario, pieces: list[_Piece], dt: float) -> Trajectory:
    """One trajectory from pieces that each start where the previous one ended (first piece
    from the scenario's start)."""
    joints = np.concatenate([scenario.start[None], *[p.joints[1:] for p in pieces]])
    return Trajectory(np.arange(len(joints)) * dt, joints)


def _reversed(joints: np.ndarray) -> np.ndarray:
    return joints[::-1].copy()


# ---------------------------------------------------------------------------- strategies
def _direct(scenario: Scenario, plan_leg: PlanLeg, attempts: int, time_limit_s: float | None = None) -> list[_Piece]:
    t0 = time.perf_counter()
    joints, k, _ = _complete(scenario, plan_leg, attempts, time_limit_s, strict=False)
    return [_Piece("direct", joints, np.flatnonzero(scenario.has_target).tolist(), k, time.perf_counter() - t0)]


def _reverse(scenario: Scenario, plan_leg: PlanLeg, attempts: int) -> list[_Piece] | None:
    """The move planned from the targets back to the starts, played forwards; ``None`` unless
    the reversed plan brings every positioner exactly back to its start."""
    t0 = time.perf_counter()
    back = leg_scenario(scenario, scenario.target, scenario.start, "reverse")
    joints, k, complete = _complete(back, plan_leg, attempts)
    if not complete:
        return None
    return [_Piece("reverse (planned from the targets)", _reversed(joints), np.flatnonzero(scenario.has_target).tolist(), k,
                   time.perf_counter() - t0)]


def _datum(scenario: Scenario) -> np.ndarray:
    datum = np.broadcast_to(np.array(scenario.instrument.datum_rad), (scenario.n_positioners, 2)).copy()
    datum[scenario.locked] = scenario.start[scenario.locked]
    return datum


def _folded_midway(scenario: Scenario, start: np.ndarray) -> np.ndarray:
    """Folded (the datum's beta) at the alpha half-way between the start and the target: safe for
    everyone (folded positioners of every preset keep clear of each other at any alphas), and each
    leg turns alpha half the way."""
    home = np.where(scenario.has_target[:, None], scenario.target, scenario.start)
    out = _datum(scenario)
    free = ~scenario.locked
    out[free, 0] = 0.5 * (start[free, 0] + home[free, 0])
    return out


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


def _via_datum(scenario: Scenario, plan_leg: PlanLeg, attempts: int, start: np.ndarray | None = None,
               movers: np.ndarray | None = None, label: str = "", midway: bool = False) -> list[_Piece] | None:
    """Two legs through the datum (``midway``: through the folded configuration half-way in
    alpha, :func:`_folded_midway`) for ``movers`` (default: every positioner that is not locked),
    the others holding where ``start`` has them: ``start -> safe``, then ``(target -> safe)``
    reversed. ``None`` unless both legs are complete."""
    start = scenario.start if start is None else start
    movers = ~scenario.locked if movers is None else movers
    home = np.where(scenario.has_target[:, None], scenario.target, scenario.start)  # where each must end
    safe = _folded_midway(scenario, start) if midway else _datum(scenario)
    hold = _clear_holds(scenario, np.where(movers[:, None], safe, start), movers)
    fold = leg_scenario(scenario, start, hold, "fold")
    back_start = np.where(movers[:, None], home, start)
    back = leg_scenario(scenario, back_start, hold, "unfold-reversed")
    # The two legs are independent: the second is planned in a forked process meanwhile.
    (fold_joints, k1, ok1, w1), (back_joints, k2, ok2, w2) = _both(
        lambda: _timed(_complete, fold, plan_leg, attempts), lambda: _timed(_complete, back, plan_leg, attempts)
    )
    if not (ok1 and ok2):
        return None
    who = np.flatnonzero(movers).tolist()
    return [
        _Piece(f"{label}fold to the datum", fold_joints, who, k1, w1),
        _Piece(f"{label}unfold from the datum (planned from the targets)", _reversed(back_joints), who, k2, w2),
    ]


def _timed(fn: Callable[..., tuple[np.ndarray, int, bool]], *args: Any) -> tuple[np.ndarray, int, bool, float]:
    t0 = time.perf_counter()
    joints, k, ok = fn(*args)
    return joints, k, ok, time.perf_counter() - t0


_CHILD_RUNS: list[dict[str, Any]] = []
"""Statistics of the planner runs made in a forked process (:func:`_both`), for the totals."""


def _both(first: Callable[[], Any], second: Callable[[], Any]) -> tuple[Any, Any]:
    """``(first(), second())``, the second in a forked process while the first runs here (on a
    machine with one core, or where fork is missing, one after the other). The results are the
    same either way: each leg is planned deterministically from its own scenario."""
    import multiprocessing as mp
    import os

    if (os.cpu_count() or 1) < 2 or "fork" not in mp.get_all_start_methods() or _IN_CHILD[0]:
        return first(), second()
    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)

    def run() -> None:
        _IN_CHILD[0] = True
        runs_before = len(_RUN_LOG)
        try:
            out = ("ok", second(), [r for r in _RUN_LOG[runs_before:]])
        except BaseException as e:  # reported to the parent, which raises it
            out = ("error", repr(e), [])
        child.send(out)
        child.close()

    proc = ctx.Process(target=run, daemon=False)  # the leg may start the mpc's own worker processes
    proc.start()
    child.close()
    try:
        a = first()
        status, b, child_runs = parent.recv()
    finally:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.terminate()
    if status != "ok":
        raise RuntimeError(f"the leg planned in a forked process failed: {b}")
    _CHILD_RUNS.extend(child_runs)
    return a, b


_IN_CHILD = [False]
_RUN_LOG: list[dict[str, Any]] = []
"""Statistics of every planner run of this process (the forked leg sends its own back)."""


def _fix_up(scenario: Scenario, direct: _Piece, plan_leg: PlanLeg, attempts: int, rounds: int = 3) -> list[_Piece] | None:
    """The direct plan until its last arrival, then the positioners still short (and, round by
    round, the neighbours that block them) through the datum, everyone else holding."""
    traj = Trajectory(np.arange(len(direct.joints)), direct.joints)
    reached = reached_mask(scenario, traj)
    arrive = arrival_times(scenario, traj)
    cut = int(np.nanmax(arrive[reached])) if reached.any() else 0
    state = direct.joints[cut]
    # The positioners still short, and the held ones away from home, go through the datum.
    home = np.where(scenario.has_target[:, None], scenario.target, scenario.start)
    movers = ~np.all(state == home, axis=1) & ~scenario.locked
    if not movers.any():
        return None
    pairs = scenario.pairs
    head = _Piece("direct (until its last arrival)", direct.joints[: cut + 1], direct.moved, direct.attempts, direct.wall_s)
    for _ in range(rounds):
        legs = _via_datum(scenario, plan_leg, attempts, start=state, movers=movers, label="fix-up: ")
        if legs is not None:
            return [head, *legs]
        # The neighbours of the movers fold too, next round.
        near = np.unique(pairs[movers[pairs[:, 0]] | movers[pairs[:, 1]]].ravel()) if len(pairs) else np.zeros(0, dtype=int)
        grown = movers.copy()
        grown[near] = True
        grown &= ~scenario.locked
        if np.array_equal(grown, movers):
            break
        movers = grown
    return None


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


def coordinate(
    scenario: Scenario, planner: str, settings: Any, plan_leg: PlanLeg, wall0: float, progress: Callable[[float], None] | None = None,
) -> PlanResult:
    """Plan ``scenario`` along ``settings.route`` (see the module docstring).

    Args:
        scenario: what to plan.
        planner: the planner's registry name.
        settings: its settings (``route``, ``route_attempts``, ``dt_s``).
        plan_leg: plans one leg with this planner and ``route = direct``.
        wall0: ``time.perf_counter()`` when planning began.
        progress: called after every planner run with a fraction that grows toward 1 (the
            number of runs is not known beforehand).
    """
    route, attempts, dt = settings.route, settings.route_attempts, settings.dt_s
    candidates: dict[str, list[_Piece]] = {}
    tried: list[dict[str, Any]] = []
    runs: list[PlanResult] = []  # every planner run, for the statistics
    _CHILD_RUNS.clear()
    plan_one = plan_leg

    def recorded(leg: Scenario, **kwargs: Any) -> PlanResult:
        result = plan_one(leg, **kwargs)
        runs.append(result)
        _RUN_LOG.append(dict(result.stats))
        if progress is not None:
            progress(1.0 - 0.5 ** len(runs))
        return result

    plan_leg = recorded
    def consider(name: str, pieces: list[_Piece] | None) -> None:
        entry: dict[str, Any] = {"strategy": name, "complete": pieces is not None}
        if pieces is not None:
            short, makespan = _score(scenario, _join(scenario, pieces, dt))
            entry |= {"short": short, "makespan_s": makespan}
            candidates[name] = pieces
        tried.append(entry)

    structure = "general"
    if route == "direct":
        consider("direct", _direct(scenario, plan_leg, attempts))
    elif route == "reverse":
        consider("reverse", _reverse(scenario, plan_leg, attempts))
    elif route == "via_datum":
        consider("via_datum", _via_datum(scenario, plan_leg, attempts))
    elif route == "via_fold":
        consider("via_fold", _via_datum(scenario, plan_leg, attempts, midway=True))
    elif _is_at_datum(scenario, scenario.start):  # an unfold: the reverse of a fold
        structure = "unfold"
        consider("reverse", _reverse(scenario, plan_leg, attempts))
    elif _is_at_datum(scenario, scenario.target):
        structure = "fold"
        consider("direct", _direct(scenario, plan_leg, attempts))
    else:
        inst = scenario.instrument
        if inst.reach_max_mm > DENSE_REACH * inst.pitch_mm:
            # Dense: the direct plan leaves positioners short on every seed measured, and a fix-up
            # after it was slower than the two-leg plan on every one: the two legs alone.
            structure = "dense"
            consider("via_datum", _via_datum(scenario, plan_leg, attempts))
        else:
            direct = _direct(scenario, plan_leg, attempts)
            consider("direct", direct)
            if tried[-1].get("short", 1) > 0:
                consider("via_datum", _via_datum(scenario, plan_leg, attempts))
                consider("fix_up", _fix_up(scenario, direct[0], plan_leg, attempts))
    if not candidates:  # nothing complete: the direct plan, with what it reached
        consider("direct (fallback)", _direct(scenario, plan_leg, attempts))
    chosen = min(candidates, key=lambda name: (_score(scenario, _join(scenario, candidates[name], dt)), name != "via_datum"))
    if "via_datum" in candidates and chosen != "via_datum":
        # Never worse than the two-leg plan.
        if _score(scenario, _join(scenario, candidates[chosen], dt)) > _score(scenario, _join(scenario, candidates["via_datum"], dt)):
            chosen = "via_datum"
    pieces = candidates[chosen]
    trajectory = _join(scenario, pieces, dt)
    final = trajectory.joints[-1]
    short = scenario.has_target & ~np.all(final == scenario.target, axis=1) & ~reached_mask(scenario, trajectory)
    outcome = outcome_labels(scenario, final, short)
    legs, t = [], 0.0
    for p in pieces:
        duration = (len(p.joints) - 1) * dt
        legs.append({"leg": p.name, "t0_s": t, "t1_s": t + duration, "attempts": p.attempts, "moved": len(p.moved),
                     "plan_wall_s": p.wall_s})
        t += duration
    carried = sorted({int(scenario.ids[i]) for p in pieces if "datum" in p.name for i in p.moved})
    stats: dict[str, Any] = {
        "route": route, "structure": structure, "chosen": chosen, "candidates": tried, "legs": legs,
        "via_datum_ids": carried, "n_via_datum": len(carried), "planner_runs": len(runs) + len(_CHILD_RUNS),
    }
    single = [r for r in runs if np.array_equal(r.trajectory.joints, trajectory.joints)]
    if single:
        # The planner alone, in one run: its own result, with the route named.
        only = single[0]
        return dataclasses.replace(only, stats=only.stats | stats, settings=dataclasses.asdict(settings),
                                   plan_wall_s=time.perf_counter() - wall0)
    for run_stats in [r.stats for r in runs] + _CHILD_RUNS:  # the planners' counters, summed over every run of every leg tried
        for key, value in run_stats.items():
            if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)):
                stats[key] = stats.get(key, 0) + value
    warnings = []
    if short.any():
        warnings.append(f"{planner} ({route}): {int(short.sum())} of {int(scenario.has_target.sum())} positioners did not reach their "
                        f"targets along any route tried ({', '.join(e['strategy'] for e in tried)})")
    return PlanResult(scenario=scenario, trajectory=trajectory, outcome=outcome, planner=planner,
                      settings=dataclasses.asdict(settings), stats=stats, warnings=tuple(warnings),
                      plan_wall_s=time.perf_counter() - wall0)
