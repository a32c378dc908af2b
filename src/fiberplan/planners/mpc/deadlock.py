"""Deadlocks of the ``mpc`` planner: detection and the escalation ladder that resolves them.

A positioner not at its target whose time-to-go (along its route, if it follows one and
``route_progress`` is on) has not improved for ``deadlock_window_steps`` is *stalled*; a
stalled one at :attr:`Level.NORMAL` is newly *deadlocked*. The ladder, deterministic, one rung
at a time (``formulations/mpc.md``, Deadlocks):

1. **Waiting rule.** If it and a neighbour in conflict are ordered by their targets (one's path
   crosses the other's target or position), the one that must wait goes to a waiting
   configuration until the other has arrived (:func:`~fiberplan.planners.mpc.waiting.waiting_configuration`);
   the other gets :attr:`Level.TOP_PRIORITY`.
2. **Top priority.** Otherwise it outranks everyone; its lower-priority neighbours in conflict
   fold their beta arms out of its way (yield) while it stays there.
3. **Detour.** Deadlocked again (or still stuck two windows later; the leader of a waiting rule
   that was not newly deadlocked itself, stalled and held by the safety layer for a window: one
   window after the rule): a pair resolution with its closest neighbour (one goes first, the other to a waiting place and home afterwards) or a
   lone detour route around its neighbours (:mod:`~fiberplan.planners.mpc.detour`).
4. **Retreat.** Still stuck at top priority two windows on: it folds (:attr:`Level.FOLDING`),
   turns alpha to its target while folded (:attr:`Level.TURNING`), and unfolds with top
   priority again.

:class:`Deadlocks` holds the state of all of it; the loop calls its phases in order every step.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Any

import numpy as np

from fiberplan.layout import neighbour_lists
from fiberplan.planners.mpc.detour import PairResolution, detour_route, pair_resolution
from fiberplan.planners.mpc.kernels import time_to_go
from fiberplan.planners.mpc.priority import outranks, ranks
from fiberplan.planners.mpc.routes import RouteBook
from fiberplan.planners.mpc.settings import MpcSettings
from fiberplan.planners.mpc.waiting import path_clearance, waiting_configuration
from fiberplan.scenario import Scenario


class Level(IntEnum):
    """Rung of the escalation ladder a positioner stands on."""

    NORMAL = 0
    """Follows its goal with its ordinary priority."""
    TOP_PRIORITY = 1
    """Deadlocked: outranks its neighbours, who fold out of its way."""
    FOLDING = 2
    """Retreat, first leg: folds its beta arm to the datum, alpha held."""
    TURNING = 3
    """Retreat, second leg: turns alpha to its target while folded, then back to top priority."""


_TOL = 1e-9


class Deadlocks:
    """Deadlock state of every positioner and the phases of its resolution.

    Args:
        scenario: the run's scenario.
        settings: the ``mpc`` settings (deadlock group).
        move_s: ``(N,)`` unobstructed move times (the first time-to-go).
        step_rad: joint motion per control step at full speed.
        routes: the positioners' routes (the detours put theirs there).
    """

    def __init__(self, scenario: Scenario, settings: MpcSettings, move_s: np.ndarray, step_rad: np.ndarray, routes: RouteBook) -> None:
        n = scenario.n_positioners
        self.scenario, self.settings, self.step_rad, self.routes = scenario, settings, step_rad, routes
        self.speeds = scenario.instrument.speeds_rad_s
        self.goal_final = scenario.target.copy()
        self.datum = np.broadcast_to(np.array(scenario.instrument.datum_rad), (n, 2))
        self.window = settings.deadlock_window_steps
        self.stop_steps = settings.stop_after_stalled_windows * self.window
        self.progress_eps = settings.deadlock_progress_fraction * self.window * settings.dt_s
        # Progress: the best time-to-go so far, along the route or straight (reset by a retreat), and ever.
        self.best_ttg = move_s.copy()
        self.last_progress = np.zeros(n, dtype=np.int64)
        self.best_ever = move_s.copy()
        self.last_best_ever = np.zeros(n, dtype=np.int64)
        # The ladder.
        self.level = np.zeros(n, dtype=np.int64)
        self.level_since = np.zeros(n, dtype=np.int64)
        self.rule_leader = np.zeros(n, dtype=bool)  # given top priority by a waiting rule (not deadlocked itself)
        self.free_since = np.zeros(n, dtype=np.int64)  # the last step the safety layer did not hold it
        self.ever_deadlocked = np.zeros(n, dtype=bool)
        self.first_dead = np.zeros(n, dtype=np.int64)
        self.n_dead = np.zeros(n, dtype=np.int64)
        # Yielding neighbours of a top-priority positioner.
        self.yield_until = np.zeros(n, dtype=np.int64)
        self.yield_to = np.zeros(n, dtype=np.int64)
        self.ever_yielded = np.zeros(n, dtype=bool)
        # Waiting rules: waiter -> (the neighbour it waits for, its waiting configuration).
        self.wait_first = np.full(n, -1, dtype=np.int64)
        self.wait_q = np.zeros((n, 2))
        self.first_arrived = np.zeros(n, dtype=bool)
        self.leader_home_since = np.zeros(n, dtype=np.int64)
        self.waiting = np.zeros(n, dtype=bool)
        self.ever_waited = np.zeros(n, dtype=bool)
        self.after_wait: dict[int, np.ndarray] = {}  # a waiter's route from its waiting place, once released
        # Detours.
        self.n_routes = np.zeros(n, dtype=np.int64)
        self.grids: dict = {}  # joint-space grids of the positioners that needed a detour
        self.neighbours, self.neighbour_rows = neighbour_lists(scenario.pairs, n) if settings.detours else ([], [])
        self.n_rules = self.n_detour_failed = self.n_pair_resolutions = self.retreats = 0

    # ------------------------------------------------------------------ phase 1: progress
    def nothing_can_progress(self, step: int, at_goal: np.ndarray) -> bool:
        """No positioner not at its target has come closer than it ever was for
        ``stop_after_stalled_windows`` windows (a retreat cycle included), waiters included
        unless the neighbour they wait for is still on its way: planning on would only burn time."""
        return bool(self.settings.stop_after_stalled_windows and np.all(at_goal | (step - self.last_best_ever >= self.stop_steps)))

    def track(self, step: int, q: np.ndarray, at_goal: np.ndarray, holding: np.ndarray) -> np.ndarray:
        """Update the best time-to-go ever; returns the straight time-to-go of every positioner.

        A waiter counts as progressing while the neighbour it waits for is on its way, and a
        positioner holding (before its start, or at a timed waypoint) as well."""
        ttg = time_to_go(q, self.goal_final, self.speeds)  # np.max(np.abs(goal - q) / speeds, axis=1), compiled
        better = ttg < self.best_ever - self.progress_eps
        self.best_ever = np.where(better, ttg, self.best_ever)
        first = np.maximum(self.wait_first, 0)
        first_moving = ~at_goal[first] & (step - self.last_best_ever[first] < self.stop_steps)
        self.last_best_ever = np.where(better | (self.waiting & first_moving) | holding, step, self.last_best_ever)
        return ttg

    def detect(self, step: int, q: np.ndarray, ttg: np.ndarray, at_goal: np.ndarray, holding: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(stalled, new_dead)``: no progress for a window; stalled at :attr:`Level.NORMAL`
        (these go to :attr:`Level.TOP_PRIORITY`)."""
        # On a route the time-to-go is the time along the route (an L-shaped move's first leg
        # need not bring the slower joint closer to its target).
        ttg_progress = self.routes.time_to_go(q, self.goal_final, self.speeds, ttg) if self.settings.route_progress else ttg
        improved = ttg_progress < self.best_ttg - self.progress_eps
        self.best_ttg = np.where(improved, ttg_progress, self.best_ttg)
        self.last_progress = np.where(improved | at_goal | self.waiting | holding, step, self.last_progress)
        self.best_ttg = np.where(self.waiting, ttg_progress, self.best_ttg)
        stalled = (step - self.last_progress >= self.window) & ~at_goal
        new_dead = stalled & (self.level == Level.NORMAL)
        self.first_dead[new_dead & ~self.ever_deadlocked] = step
        self.ever_deadlocked |= new_dead
        self.level[new_dead] = Level.TOP_PRIORITY
        self.level_since[new_dead] = step
        self.rule_leader[new_dead] = False
        return stalled, new_dead

    # ------------------------------------------------------------------ phase 2: the ladder
    def resolve(
        self, step: int, q: np.ndarray, ttg: np.ndarray, at_goal: np.ndarray, stalled: np.ndarray, new_dead: np.ndarray,
        c_now: np.ndarray,
    ) -> None:
        """Climb the ladder for the deadlocked positioners: waiting rules, detours, retreats;
        then advance the routes (a waypoint passed is progress)."""
        if self.settings.wait_rules and np.any(new_dead) and len(self.scenario.pairs):
            self._waiting_rules(step, q, at_goal, new_dead, c_now)
        # Still stuck with top priority for two more windows: retreat.
        # The leader of a waiting rule (not newly deadlocked itself), stalled and held by the safety
        # layer for a window, is escalated a window after the rule, not two: its waiter's way out did
        # not free it (DESI 50,000 seed 0: a pair started 32 um apart, the waiter pinned at its hard
        # stops, the leader held by the safety layer for 80 more steps).
        blocked = self.rule_leader & (step - self.free_since >= self.window)
        patience = np.where(blocked, 1, 2) * self.window
        escalate = (self.level == Level.TOP_PRIORITY) & stalled & (step - self.level_since >= patience)
        if self.settings.detours:
            self._detours(step, q, ttg, new_dead, escalate, c_now)
        self._retreats(step, q, ttg, at_goal, escalate)
        for who in self.routes.passed(step, q, self.step_rad, leaving=self.level >= Level.FOLDING):
            self.last_progress[who] = self.last_best_ever[who] = step

    def held(self, step: int, held: np.ndarray) -> None:
        """Note who the safety layer held this step (a leader held for a window is escalated sooner)."""
        self.free_since[~held] = step

    def _waiting_rules(self, step: int, q: np.ndarray, at_goal: np.ndarray, new_dead: np.ndarray, c_now: np.ndarray) -> None:
        """A deadlocked pair whose targets impose an order: the one that must wait goes to a
        waiting configuration, the other keeps top priority."""
        pairs, settings = self.scenario.pairs, self.settings
        hit = new_dead[pairs[:, 0]] | new_dead[pairs[:, 1]]
        for r in np.flatnonzero(hit & (c_now < settings.conflict_radius_mm)):
            a, b = int(pairs[r, 0]), int(pairs[r, 1])
            for leader, waiter in ((a, b), (b, a)):
                if self.wait_first[leader] >= 0 or self.wait_first[waiter] >= 0 or at_goal[leader]:
                    continue
                wq = waiting_configuration(self.scenario, leader, waiter, q, self.datum, self.step_rad, settings.margin_mm)
                if wq is not None:
                    self.wait_first[waiter] = leader
                    self.wait_q[waiter] = wq
                    self.level[waiter] = Level.NORMAL
                    self.level[leader] = Level.TOP_PRIORITY
                    self.level_since[leader] = step
                    self.rule_leader[leader] = not new_dead[leader]
                    self.n_rules += 1
                    break

    def _detours(self, step: int, q: np.ndarray, ttg: np.ndarray, new_dead: np.ndarray, escalate: np.ndarray, c_now: np.ndarray) -> None:
        """Deadlocked a second time (pairs that push each other off their targets in turn), or
        still stuck two windows after: a waiting place for one of the pair that lets the other
        through, else a detour route (:func:`resolve_blocked`), before any retreat."""
        settings, level = self.settings, self.level
        self.n_dead[new_dead] += 1
        want = (new_dead & (self.n_dead >= settings.detour_after_deadlocks) & (level == Level.TOP_PRIORITY)) | escalate
        want &= (self.n_routes < settings.detour_max) & ((self.wait_first < 0) | self.first_arrived)
        for b in np.flatnonzero(want).tolist():
            if self.wait_first[b] >= 0 and not self.first_arrived[b]:
                continue  # made a waiter earlier in this loop
            self.n_routes[b] += 1
            resolution = resolve_blocked(self.scenario, settings, b, q, self.goal_final, self.neighbours, c_now[self.neighbour_rows[b]],
                                         self.wait_first, self.first_arrived, self.step_rad, self.grids)
            if isinstance(resolution, PairResolution):
                f, w = resolution.first, resolution.waiter
                routed = [(f, resolution.first_route), (w, resolution.to_wait)]
                self.wait_first[w] = f
                self.wait_q[w] = resolution.wait_q
                self.first_arrived[w] = False
                self.after_wait[w] = resolution.from_wait
                level[w] = Level.NORMAL
                escalate[w] = False
                self.n_pair_resolutions += 1
            elif resolution is not None:
                routed = [(b, resolution)]
            else:
                self.n_detour_failed += 1
                continue
            for k, (who, route) in enumerate(routed):
                self.routes.follow(who, route)
                if k == 0:
                    escalate[who] = False
                    level[who] = Level.TOP_PRIORITY
                    self.level_since[who] = step
                    self.rule_leader[who] = False
                    self.last_progress[who] = step
                    # Measured along the new route from the next step.
                    self.best_ttg[who] = np.inf if settings.route_progress else ttg[who]

    def _retreats(self, step: int, q: np.ndarray, ttg: np.ndarray, at_goal: np.ndarray, escalate: np.ndarray) -> None:
        """Retreat sub-goals: fold the beta arm, turn alpha to the target while folded, then
        unfold with top priority again (or give up the retreat after four windows)."""
        level, since = self.level, self.level_since
        level[escalate] = Level.FOLDING
        since[escalate] = step
        self.rule_leader[escalate] = False
        self.retreats += int(escalate.sum())
        folded = np.abs(q[:, 1] - self.datum[:, 1]) <= _TOL
        turned = folded & (np.abs(q[:, 0] - self.goal_final[:, 0]) <= _TOL)
        timeout = (level >= Level.FOLDING) & (step - since >= 4 * self.window)
        level[(level == Level.FOLDING) & folded] = Level.TURNING
        back = ((level == Level.TURNING) & turned) | timeout
        level[back] = Level.TOP_PRIORITY
        since[back] = step
        self.last_progress[back] = step
        self.best_ttg[back] = ttg[back]
        level[(level > Level.NORMAL) & at_goal] = Level.NORMAL

    # ------------------------------------------------------------------ phase 3: priorities and goals
    def priorities(self, ttg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(rank, boosted)``: deadlocked positioners first (sticky order), then the longest time-to-go."""
        boosted = self.level >= Level.TOP_PRIORITY
        return ranks(boosted, self.first_dead, ttg, self.scenario.locked), boosted

    def yielders(self, step: int, sel_pairs: np.ndarray, rank: np.ndarray, boosted: np.ndarray) -> np.ndarray:
        """Who folds its beta arm this step: a lower-priority neighbour in conflict with a
        top-priority positioner (for a window after the last conflict, as long as that one is
        still at top priority), and the retreating ones."""
        if len(sel_pairs):
            ci, cj = sel_pairs[:, 0], sel_pairs[:, 1]
            i_first = outranks(ci, cj, rank, self.wait_first)
            hi = np.where(i_first, ci, cj)
            lo = np.where(i_first, cj, ci)
            pushing = self.level[hi] == Level.TOP_PRIORITY
            self.yield_until[lo[pushing]] = step + self.window
            self.yield_to[lo[pushing]] = hi[pushing]
        yielding = (self.yield_until > step) & ~boosted & (self.level[self.yield_to] == Level.TOP_PRIORITY)
        self.ever_yielded |= yielding
        return yielding | (self.level == Level.FOLDING)

    def goals(self, step: int, q: np.ndarray, at_goal: np.ndarray, holding: np.ndarray, fold: np.ndarray) -> np.ndarray:
        """Where every positioner heads this step: its target, or where it holds, folds, waits,
        or its route's next waypoint."""
        goal = self.goal_final.copy()
        goal[holding] = q[holding]
        # Folding (yielders and retreats) moves beta to the datum with alpha held. Letting alpha
        # head for its target meanwhile measured no better on DESI (N = 500 failures, seeds
        # 0-11 / 36-47: 17 / 16 held, 16 / 19 not) and worse on MOONS (N = 61 random, seeds
        # 0-4: 69 % reached held, 63 % not).
        goal[fold, 0] = q[fold, 0]
        self._release_waiters(step, q, at_goal)
        self.waiting = (self.wait_first >= 0) & ~self.first_arrived
        goal[self.waiting] = self.wait_q[self.waiting]
        self.ever_waited |= self.waiting
        goal[fold, 1] = self.datum[fold, 1]
        self.routes.headings(goal, holding)
        turning = self.level == Level.TURNING
        goal[turning, 1] = self.datum[turning, 1]
        return goal

    def _release_waiters(self, step: int, q: np.ndarray, at_goal: np.ndarray) -> None:
        """Waiting rules, in two phases: the waiter goes to its waiting configuration and stays
        there until its neighbour has arrived, then moves to its target still deferring to that
        neighbour; the rule ends when it arrives."""
        wait_first = self.wait_first
        has_rule = wait_first >= 0
        # Released once the neighbour has arrived and the waiter is at its waiting place; a
        # waiter of a pair resolution also when it has not got there within a window of the
        # neighbour's arrival (blocked on its way by a third positioner).
        leader_home = has_rule & at_goal[np.maximum(wait_first, 0)]
        self.leader_home_since = np.where(leader_home, self.leader_home_since, step)
        release = np.all(q == self.wait_q, axis=1)
        # A waiter still on its way to its waiting place when its neighbour arrives goes
        # straight to its target if that path clears the neighbour there (the detour via the
        # waiting place only served to let the neighbour through).
        early = np.flatnonzero(leader_home & ~release & ~self.first_arrived)
        if len(early):
            ahead = wait_first[early]
            clear = path_clearance(self.scenario, early, ahead, q[early], self.goal_final[early], self.goal_final[ahead], self.step_rad)
            release[early[clear >= self.settings.margin_mm]] = True
        if self.after_wait:
            late = np.zeros(len(q), dtype=bool)
            late[list(self.after_wait)] = True
            release |= late & (step - self.leader_home_since >= self.window)
        self.first_arrived |= leader_home & release
        for w in [w for w in self.after_wait if self.first_arrived[w]]:
            route = self.after_wait.pop(w)
            if np.all(q[w] == self.wait_q[w]):  # else the route does not start where it is
                self.routes.follow(w, route)
                if self.settings.route_progress:
                    self.best_ttg[w] = np.inf  # measured along the route from the next step
            else:
                self.routes.drop(w)
        ended = has_rule & at_goal
        wait_first[ended] = -1
        self.first_arrived[ended] = False

    # ------------------------------------------------------------------ the end
    def stuck(self, step: int) -> np.ndarray:
        """Who has not come closer than it ever was for a window (``deadlocked`` if not at its target)."""
        return step - self.last_best_ever >= self.window

    def stats(self, reached: np.ndarray, has_target: np.ndarray) -> dict[str, Any]:
        """The deadlock part of the run statistics."""
        return {
            "deadlocks_detected": int(self.ever_deadlocked.sum()),
            "deadlocks_resolved": int(np.sum(self.ever_deadlocked & reached)),
            "deadlocks_remaining": int(np.sum(~reached & has_target)),
            "retreats": self.retreats,
            "yielding_positioners": int(self.ever_yielded.sum()),
            "waiting_rules": self.n_rules,
            "waiting_positioners": int(self.ever_waited.sum()),
            "detours": int(self.n_routes.sum()) - self.n_detour_failed - self.n_pair_resolutions,
            "pair_resolutions": self.n_pair_resolutions,
            "detours_not_found": self.n_detour_failed,
        }


def resolve_blocked(
    scenario: Scenario, settings: MpcSettings, i: int, q: np.ndarray, goal: np.ndarray, neighbours: list[np.ndarray],
    c_nb: np.ndarray, wait_first: np.ndarray, released: np.ndarray, step_rad: np.ndarray, grids: dict,
) -> PairResolution | np.ndarray | None:
    """A way out for the deadlocked positioner ``i`` (:mod:`~fiberplan.planners.mpc.detour`), or ``None``.

    First a pair resolution with its closest neighbour in conflict (``i`` first, else the
    neighbour first): the waiter gets a way home around the first at its target, where a lone
    detour could end on a target that blocks the neighbour (the pair would then push each other
    off their targets in turn). Else a lone detour route around the neighbours held where they
    are. Neighbours waiting for someone (not yet released) or waited for are left alone.
    ``c_nb`` are the clearances to ``neighbours[i]`` now (the loop's ``c_now``).
    """
    nb = neighbours[i]
    leaders = set(wait_first[wait_first >= 0].tolist())
    for k in np.argsort(c_nb, kind="stable"):
        j = int(nb[k])
        if c_nb[k] >= settings.conflict_radius_mm or (wait_first[j] >= 0 and not released[j]) or j in leaders:
            continue
        for f, w in ((i, j), (j, i)):
            resolution = pair_resolution(scenario, f, w, q, goal, neighbours, step_rad, settings.margin_mm, settings.safety_margin_mm,
                                         cache=grids)
            if resolution is not None:
                return resolution
        break  # the closest one only
    return detour_route(scenario, i, q[i], goal[i], nb, q[nb], step_rad, settings.margin_mm, settings.safety_margin_mm, cache=grids)
