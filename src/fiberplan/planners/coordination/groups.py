"""Group moves: the positioners a leg's first attempt leaves short go home together with the
neighbours in their way, by a search in their joint configurations together, everyone around
them holding still (``formulations/coordination.md``, Completing a leg; setting
``route_groups``, on by default since session 50).

A stalled fold (MOONS 500, session 38) has a few stragglers whose way home sweeps over a
neighbour both where that neighbour started and where it folded: neither can go first along its
own path, and a search of one around the other held still (:mod:`.solo`) finds nothing. Searched
together, the neighbour steps aside while the straggler passes and then goes home. Here:

- each positioner left short and the neighbours its straight joint move to its target crosses
  (held where the attempt left them) form a group; groups that share a member are one; groups
  that touch are first searched as one, up to :data:`MERGE_UP_TO` members;
- a group starts as early as it can (:func:`_early`): at 0, 1, 2, ... s, from where its members
  stand then, with a path found among its other neighbours where they will hold and played
  along their motion (velocity tuning, :func:`_tune`); else at the sample after which none of
  its other neighbours moves (they hold from there on, as obstacles). Groups are planned one
  after the other, each in the trajectory as the ones before left it;
- a bidirectional rapidly-exploring random tree (RRT-Connect, Kuffner and LaValle 2000) in the
  group's joint angles together, between that configuration and the targets, inside the hard
  stops, joins the two by straight joint moves; random shortcuts then shorten the path. Its
  samples mix uniform draws with configurations in which only some members are drawn, the others
  at their start (or goal), and an extension that is not clear is halved a few times before it is
  given up: a stalled attempt leaves its stragglers pressed together, and only small moves of a
  few members untangle them (MOONS 500 unfold seed 3: a group of five found no way in 10,000
  samples without these two, and finds one with them);
- every straight move of the path is checked at sub-steps whose motion bound is at most
  :data:`RESOLUTION_MM`: each pair (two members, or a member and a neighbour held still) keeps
  the floor at the sub-steps, and the bound proves the pair clear between them (an interval
  where it does not is halved, up to :data:`BISECTIONS` times);
- the path is played with its segments one after the other, each as fast as its slowest joint
  allows, on the planner's time grid; the rest of the field keeps its planned motion. (Played so,
  like solo moves, it starts and stops each segment at once, and a joint other than a segment's
  slowest moves slower than full speed: an instrument's motor rules (speed changes, stops before
  reversing, minimum speeds) are not applied to it; the verifier reports any breach.)

The search is seeded (the same leg, the same path) and bounded by :data:`ITERATIONS` (and
:data:`SEARCHES`, and optionally :data:`CHECKS`), not by time, so plans are reproducible.
Groups that find no way stay where the attempt left them, held still (as the groups planned
beside them assumed); the coordination layer uses the result only when every group got home
(``legs.complete_leg``). The caller's verifier checks the whole trajectory.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from fiberplan.geometry import capsule_ends_rows, clearance_rows, indexed_clearances, motion_bound, point_extents
from fiberplan.layout import neighbour_lists
from fiberplan.scenario import Scenario

RESOLUTION_MM = 0.3
"""Largest motion bound (mm) of a sub-step at which a straight move of the path is checked."""

BISECTIONS = 4
"""Times an interval between sub-steps may be halved to prove it clear (down to 1/16 of
:data:`RESOLUTION_MM`)."""

STEP_RAD = 0.15
"""Largest joint change (rad) of one extension of a tree."""

ITERATIONS = 2000
"""Samples one group's search may draw per member before it gives up (a group of five: 10,000);
each extends the smaller tree (halved up to :data:`SHRINKS` times) and pulls the other after it."""

MERGE_UP_TO = 5
"""Groups that touch are first searched as one up to this many members together (MOONS 500
unfold seed 3: a straggler next to a group of two, 9 s of motion after it; together 6.5 s less
for the leg); larger groups find no way (MOONS 61 unfold seed 6: eight in 20,000 samples)."""

SEARCHES = 2
"""Searches per group, each with its own random stream, before the group is given up (a search
of MOONS 500 unfold seed 3's group of five finds a way in 7 of 10 streams)."""

SHORTCUTS = 400
"""Random shortcuts tried on a found path (between two instants of it, not only its waypoints:
on MOONS 500 unfold seed 2's groups, 11.1 against 16.0 s of motion for one, 0.5-5 s shorter for
four of five)."""

GOAL_BIAS = 0.1
"""Share of the samples that aim at the other tree's root."""

UNIFORM_SHARE = 0.4
"""Share of the other samples drawn uniformly within the hard stops; the rest keep the start's (or
the goal's) angles for a random part of the members and draw the others."""

SHRINKS = 6
"""Times an extension that is not clear is halved before the tree gives it up (down to 1/64 of
:data:`STEP_RAD`: a stalled group's members are pressed together, and from there only small
moves in a few directions are clear)."""


COARSE = 8
"""A long move's sub-steps measured first, one in this many (:meth:`_Group.first_ok`): a random
shortcut is mostly refused, and most refusals are found among them."""

CHECKS: float = np.inf
"""Pair clearances (a pair at one configuration) that one leg's group moves may evaluate, all
searches, shortcuts, screens and plays together (not the checks that form the groups), before
they are given up (the leg stays as its attempts left it). Counted, not timed, so plans stay
reproducible; what one check is follows the code (a finite bound gives up at other points after
a change that measures less). ``inf``: unbounded (session 48: no bound separated the groups that
found a way from those that did not)."""


class _Spent(Exception):
    """A leg's group moves used up :data:`CHECKS`."""


class _Budget:
    """Pair clearances a leg's group moves have left (:data:`CHECKS`), and how many they used."""

    def __init__(self, checks: float) -> None:
        self.left, self.used = checks, 0

    def spend(self, n: int) -> None:
        self.used += n
        self.left -= n
        if self.left < 0:
            raise _Spent


CACHED_SIZES = 32
"""Sizes of clearance call whose arrays a group keeps (its members' and the index arrays; a few
MB; all of them, over 200 sizes on MOONS 61 unfold seed 6, held over 100 MB a group when each
pair's rows were kept, before session 48)."""


class _Group:
    """Clearance checks of one group's members moving together among neighbours held at ``q``."""

    def __init__(self, leg: Scenario, q: np.ndarray, members: list[int], nbrs: list[np.ndarray], floor_mm: float,
                 budget: _Budget | None = None) -> None:
        self.leg, self.members, self.floor, self.budget = leg, np.asarray(members, dtype=np.int64), floor_mm, budget
        index = {m: a for a, m in enumerate(members)}
        inner, outer = [], []
        for a, i in enumerate(members):
            for j in nbrs[i].tolist():
                if j in index:
                    if a < index[j]:
                        inner.append((a, index[j]))
                else:
                    outer.append((a, j))
        self.inner = np.array(inner, dtype=np.int64).reshape(-1, 2)
        self.outer = np.array(outer, dtype=np.int64).reshape(-1, 2)
        self.q_outer = q[self.outer[:, 1]]
        self._index_rows: dict[tuple[int, bool], tuple[np.ndarray, ...]] = {}  # (M, neighbours moving) -> arrays for M configurations
        # The capsules (polygon zones: their edges) of the neighbours held still are placed once,
        # and each configuration places the members' only (:func:`capsule_ends_rows`); the pairs
        # are read by index (:func:`indexed_clearances`), the same values as :func:`clearance_rows` gives.
        j = self.outer[:, 1]
        self._held = capsule_ends_rows(leg.instrument, leg.base_xy[j], leg.orient[j], self.q_outer)
        self.rho = point_extents(leg.instrument)
        lim = leg.instrument.limits_rad
        self.lo, self.hi = np.tile(lim[:, 0], len(members)), np.tile(lim[:, 1], len(members))

    def clearance(self, x: np.ndarray, q_outer: np.ndarray | None = None) -> np.ndarray:
        """``(M, P)`` clearances of the group's pairs (inner, then outer) at configurations ``x``
        ``(M, g, 2)``, the outer neighbours where they hold or, given, at ``q_outer`` ``(M, len(outer), 2)``:
        the members' capsules placed at each configuration, the outer neighbours' once where they
        hold (else at each), every pair read by index."""
        if self.budget is not None:
            self.budget.spend(len(x) * (len(self.inner) + len(self.outer)))
        leg, m, g, n_out = self.leg, len(x), len(self.members), len(self.outer)
        key = (m, q_outer is not None)
        rows = self._index_rows.get(key)
        if rows is None:
            at = np.arange(m)[:, None] * g
            i_index = np.concatenate([at + self.inner[:, 0][None], at + self.outer[:, 0][None]], axis=1).ravel()
            held = m * g + (np.arange(m)[:, None] * n_out if q_outer is not None else 0) + np.arange(n_out)[None]
            j_index = np.concatenate([at + self.inner[:, 1][None], np.broadcast_to(held, (m, n_out))], axis=1).ravel()
            j = self.outer[:, 1]
            moving = q_outer is not None  # (held: the neighbours' capsules were placed once, at q_outer)
            rows = (np.tile(leg.base_xy[self.members], (m, 1)), np.tile(leg.orient[self.members], m), i_index, j_index,
                    np.tile(leg.base_xy[j], (m, 1)) if moving else None, np.tile(leg.orient[j], m) if moving else None)
            if len(self._index_rows) < CACHED_SIZES:
                self._index_rows[key] = rows
        base, orient, i_index, j_index, base_out, orient_out = rows
        start, end = capsule_ends_rows(leg.instrument, base, orient, x.reshape(-1, 2))
        if q_outer is None:
            s_out, e_out = self._held
        else:
            s_out, e_out = capsule_ends_rows(leg.instrument, base_out, orient_out, q_outer.reshape(-1, 2))
        c = indexed_clearances(leg.instrument, np.concatenate([start, s_out]), np.concatenate([end, e_out]), i_index, j_index)
        return c.reshape(m, -1)

    def edge_ok(self, x0: np.ndarray, x1: np.ndarray) -> bool:
        """Whether the straight joint move ``x0 -> x1`` (flat ``(2g,)``) keeps every pair at the
        floor at its sub-steps and clear between them. Sub-steps are at most
        :data:`RESOLUTION_MM` of motion apart; an interval between two whose clearances do not
        prove it clear is halved, up to :data:`BISECTIONS` times (pairs near the floor: a stalled
        attempt leaves its stragglers pressed together, 0.12 mm apart on MOONS 500 unfold seed 3)."""
        return self.first_ok(x0, [x1]) == 0

    def first_ok(self, x0: np.ndarray, ends: list[np.ndarray]) -> int | None:
        """The first of ``ends`` to which :meth:`edge_ok` accepts the straight move from ``x0``
        (``None``: none), each decided exactly as :meth:`edge_ok` decides it (a tree's extension
        and its halvings). An end not at the floor is refused before the sub-steps of its move are
        measured, and a long move's every :data:`COARSE`-th sub-step is measured before the others:
        a move with a sub-step below the floor is refused whichever is found first (the same
        decisions, for a fraction of the clearances where most moves are refused)."""
        if len(ends) > 1:
            c_end = self.clearance(np.stack(ends).reshape(len(ends), -1, 2)).min(axis=1, initial=np.inf)
            for n in np.flatnonzero(c_end >= self.floor).tolist():
                if self.first_ok(x0, [ends[n]]) == 0:
                    return n
            return None
        x1 = ends[0]
        moved = motion_bound(self.rho, np.abs(x1 - x0).reshape(-1, 2))  # (g,) over the whole move
        s = np.linspace(0.0, 1.0, max(1, int(np.ceil(moved.max() / RESOLUTION_MM))) + 1)
        along = self._along(x0, x1, s)
        if len(s) > 4 * COARSE and np.any(self.clearance(along[::COARSE]) < self.floor):
            return None
        c = self.clearance(along)  # (k + 1, P)
        if not np.any(c < self.floor) and self._proved(x0, x1, moved, s, c):
            return 0
        return None

    def _proved(self, x0: np.ndarray, x1: np.ndarray, moved: np.ndarray, s: np.ndarray, c: np.ndarray) -> bool:
        """Whether the clearances ``c`` at the sub-steps ``s`` of the move ``x0 -> x1`` (each at the
        floor) prove every pair clear between them, halving the intervals they do not prove."""
        # Each pair's motion bound over the whole move (the sum of its members'; an outer neighbour holds).
        bound = np.concatenate([moved[self.inner[:, 0]] + moved[self.inner[:, 1]], moved[self.outer[:, 0]]])
        lo, hi, c_lo, c_hi = s[:-1], s[1:], c[:-1], c[1:]
        for depth in range(BISECTIONS + 1):
            # Clear between two sub-steps when their clearances exceed the motion between them.
            open_ = ~np.all(0.5 * (c_lo + c_hi - (hi - lo)[:, None] * bound[None]) > 0.0, axis=1)
            if not open_.any():
                return True
            if depth == BISECTIONS:
                return False
            lo, hi, c_lo, c_hi = lo[open_], hi[open_], c_lo[open_], c_hi[open_]
            mid = 0.5 * (lo + hi)
            c_mid = self.clearance(self._along(x0, x1, mid))
            if np.any(c_mid < self.floor):
                return False
            lo, hi = np.concatenate([lo, mid]), np.concatenate([mid, hi])
            c_lo, c_hi = np.concatenate([c_lo, c_mid]), np.concatenate([c_mid, c_hi])
        return False  # (not reached)

    def played_ok(self, x0: np.ndarray, x1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
        """Which of ``M`` sample intervals keep every pair at the floor at both ends and clear
        between them, the members moving straight from ``x0`` to ``x1`` ``(M, g, 2)`` while the outer
        neighbours move straight from ``q0`` to ``q1`` ``(M, len(outer), 2)`` (as the verifier plays
        samples): ``(M,)`` bools. A pair's motion bound is the sum of both its positioners' (a
        neighbour moves too); an interval it does not prove clear is halved, up to
        :data:`BISECTIONS` times, as in :meth:`edge_ok`."""
        c0, c1 = self.clearance(x0, q0), self.clearance(x1, q1)
        good = (c0.min(axis=1, initial=np.inf) >= self.floor) & (c1.min(axis=1, initial=np.inf) >= self.floor)  # (no pairs: clear)
        mx = motion_bound(self.rho, np.abs(x1 - x0))  # (M, g)
        mq = motion_bound(self.rho, np.abs(q1 - q0))  # (M, len(outer))
        bound = np.concatenate([mx[:, self.inner[:, 0]] + mx[:, self.inner[:, 1]], mx[:, self.outer[:, 0]] + mq], axis=1)
        rows = np.arange(len(x0))
        lo, hi, c_lo, c_hi = np.zeros(len(x0)), np.ones(len(x0)), c0, c1
        for depth in range(BISECTIONS + 1):
            open_ = good[rows] & ~np.all(0.5 * (c_lo + c_hi - (hi - lo)[:, None] * bound[rows]) > 0.0, axis=1)
            if not open_.any():
                break
            if depth == BISECTIONS:
                good[rows[open_]] = False
                break
            rows, lo, hi, c_lo, c_hi = rows[open_], lo[open_], hi[open_], c_lo[open_], c_hi[open_]
            mid = 0.5 * (lo + hi)
            f = mid[:, None, None]
            c_mid = self.clearance(x0[rows] * (1.0 - f) + x1[rows] * f, q0[rows] * (1.0 - f) + q1[rows] * f)
            good[rows[c_mid.min(axis=1, initial=np.inf) < self.floor]] = False
            rows, lo, hi = np.concatenate([rows, rows]), np.concatenate([lo, mid]), np.concatenate([mid, hi])
            c_lo, c_hi = np.concatenate([c_lo, c_mid]), np.concatenate([c_mid, c_hi])
        return good

    def _along(self, x0: np.ndarray, x1: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Configurations ``(len(s), g, 2)`` at fractions ``s`` of the straight move ``x0 -> x1``."""
        return (x0[None] * (1.0 - s[:, None]) + x1[None] * s[:, None]).reshape(len(s), -1, 2)


class _Tree:
    """A search tree: its nodes (flat configurations), each one's parent (-1: the root), and the
    nodes as one array for the nearest-node queries (grown by doubling)."""

    def __init__(self, root: np.ndarray) -> None:
        self.nodes, self.parents = [root], [-1]
        self._array = np.empty((16, len(root)))
        self._array[0] = root

    def add(self, x: np.ndarray, parent: int) -> int:
        if len(self.nodes) == len(self._array):
            self._array = np.concatenate([self._array, np.empty_like(self._array)])
        self._array[len(self.nodes)] = x
        self.nodes.append(x)
        self.parents.append(parent)
        return len(self.nodes) - 1

    def nearest(self, x: np.ndarray) -> int:
        return int(np.argmin(np.abs(self._array[: len(self.nodes)] - x).max(axis=1)))

    def chain(self, k: int) -> list[np.ndarray]:
        """The nodes from ``k`` to the root."""
        out = []
        while k != -1:
            out.append(self.nodes[k])
            k = self.parents[k]
        return out


def _connect(group: _Group, start: np.ndarray, goal: np.ndarray, rng: np.random.Generator,
             iterations: int | None = None, goal_tree: _Tree | None = None) -> np.ndarray | None:
    """RRT-Connect between ``start`` and ``goal`` (flat): waypoints ``(W, 2g)`` or ``None``, after
    at most ``iterations`` (default :data:`ITERATIONS`) samples per member. The smaller tree is the
    one extended towards each sample (the balanced form of Kuffner and LaValle's alternation), the
    other then pulled towards the new node. A ``goal_tree`` (rooted at ``goal``, grown in place)
    carries the goal's side over from an earlier search among the same neighbours."""
    trees = [_Tree(start), _Tree(goal) if goal_tree is None else goal_tree]
    swapped = False

    def extend(tree: _Tree, x: np.ndarray) -> tuple[int | None, bool]:
        near = tree.nearest(x)
        x_near = tree.nodes[near]
        d = x - x_near
        n = float(np.abs(d).max())
        new = x if n <= STEP_RAD else x_near + d * (STEP_RAD / n)
        ends = [new]
        for _ in range(SHRINKS):  # (halved where not clear)
            ends.append(x_near + (ends[-1] - x_near) * 0.5)
        first = group.first_ok(x_near, ends)
        if first is None:
            return None, False
        return tree.add(ends[first], near), n <= STEP_RAD and first == 0

    g = len(group.members)
    lo, hi = group.lo.reshape(g, 2), group.hi.reshape(g, 2)

    def sample() -> np.ndarray:
        u = rng.random()
        if u < UNIFORM_SHARE:
            return rng.uniform(group.lo, group.hi)
        # Some members drawn anew, the others where they start (or end): the moves that untangle a
        # stalled group are mostly of a few members at a time.
        x = (start if u < 0.5 * (1.0 + UNIFORM_SHARE) else goal).reshape(g, 2).copy()
        drawn = rng.random(g) < rng.uniform(0.2, 0.6)
        if not drawn.any():
            drawn[rng.integers(g)] = True
        x[drawn] = rng.uniform(lo[drawn], hi[drawn])
        return x.ravel()

    for _ in range((ITERATIONS if iterations is None else iterations) * g):
        a, b = trees
        x = b.nodes[0] if rng.random() < GOAL_BIAS else sample()
        k, _ = extend(a, x)
        if k is not None:
            while True:
                kb, reached = extend(b, a.nodes[k])
                if kb is None:
                    break
                if reached:
                    path = a.chain(k)[::-1] + b.chain(kb)
                    return np.array(path[::-1] if swapped else path)
        if len(trees[0].nodes) > len(trees[1].nodes):  # the smaller tree extends next (a stalled start's grows slowly)
            trees = [b, a]
            swapped = not swapped
    return None


def _shortcut(group: _Group, path: np.ndarray, rng: np.random.Generator, speeds: np.ndarray) -> np.ndarray:
    """``path`` shortened by :data:`SHORTCUTS` random shortcuts between two instants of it played
    (each segment as fast as its slowest joint), not only between its waypoints: a shortcut
    between two points inside segments ``i`` and ``j`` replaces what lies between them where that
    straight move is clear (the parts of the two segments it keeps were clear already)."""
    w = np.tile(speeds, path.shape[1] // 2)
    points = np.asarray(path)
    for _ in range(SHORTCUTS):
        seg = np.max(np.abs(np.diff(points, axis=0)) / w, axis=1)  # each segment's time
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        if len(points) < 3 or cum[-1] <= 0.0:
            break
        (i, a), (j, b) = (_at(points, seg, cum, t) for t in np.sort(rng.uniform(0.0, cum[-1], 2)))
        if j > i and group.edge_ok(a, b):
            points = np.concatenate([points[: i + 1], a[None], b[None], points[j + 1 :]])
    keep = np.concatenate([[True], np.any(points[1:] != points[:-1], axis=1)])  # (no segment of zero length)
    return points[keep]


def _at(points: np.ndarray, seg: np.ndarray, cum: np.ndarray, t: float) -> tuple[int, np.ndarray]:
    """The segment of ``points`` played at time ``t`` and the configuration there."""
    k = min(int(np.searchsorted(cum, t, side="right")) - 1, len(seg) - 1)
    f = (t - cum[k]) / seg[k] if seg[k] > 0.0 else 0.0
    return k, points[k] * (1.0 - f) + points[k + 1] * f


def _timed(path: np.ndarray, speeds: np.ndarray, dt_s: float) -> np.ndarray:
    """Samples ``(K, 2g)`` of ``path`` on the time grid, each segment as fast as its slowest joint allows."""
    w = np.tile(speeds, path.shape[1] // 2)
    out = [path[:1]]
    for x0, x1 in itertools.pairwise(path):
        steps = max(1, int(np.ceil(float(np.max(np.abs(x1 - x0) / w)) / dt_s - 1e-9)))  # (within the verifier's speed tolerance)
        s = (np.arange(1, steps + 1) / steps)[:, None]
        out.append(x0[None] * (1.0 - s) + x1[None] * s)
    timed = np.concatenate(out)
    timed[-1] = path[-1]
    return timed


@dataclasses.dataclass(frozen=True, eq=False)
class Stop:
    """Where :func:`groups` without ``rescue`` stopped: at ``part`` (its members, sorted), the
    ``index``-th group of the ``unit``-th unit, which found no way, with ``out`` the joints
    ``(K, N, 2)`` the groups before it had brought home."""

    out: np.ndarray
    unit: int
    index: int
    part: list[int]


def groups(leg: Scenario, joints: np.ndarray, floor_mm: float, dt_s: float, seed: int = 0, rescue: bool = False,
           stopped: list[Stop] | None = None, resume: Stop | None = None) -> np.ndarray | None:
    """``joints`` ``(K, N, 2)`` (an attempt of ``leg``) with the positioners it left short brought
    home by group moves, or ``None`` as soon as a group finds no way, if they use up
    :data:`CHECKS`, or if nobody is short.
    Groups that touch are searched as one up to :data:`MERGE_UP_TO` members, else (or if that
    finds no way) one after the other.

    With ``rescue`` (a leg's last resort, ``legs.complete_leg``), a group that finds no way holds
    where the attempt left it while the groups after it are searched; then each such group is
    searched again, in the field the others left, with :data:`RESCUE_EFFORT` times the samples
    and :data:`RESCUE_SEARCHES` streams (the first search's streams carried on, and more; its
    early starts from other streams); ``None`` if one still finds none, or as soon as one of more
    than :data:`RESCUE_UP_TO` members finds none.

    A search without ``rescue`` that stops at a group without a way appends to ``stopped`` where
    it stopped (a :class:`Stop`); a rescue given that as ``resume`` (with the same ``leg``,
    ``joints``, ``floor_mm``, ``dt_s`` and ``seed``) goes on from there instead of searching the
    groups before it again: the same result, the groups' searches being seeded (with
    :data:`CHECKS` finite, it counts only its own checks)."""
    target, end = leg.target, joints[-1]
    short = np.flatnonzero(~np.all(end == target, axis=1) & ~leg.locked)
    if not len(short):
        return None
    nbrs = neighbour_lists(leg.pairs, leg.n_positioners)[0]
    inst = leg.instrument
    rho = point_extents(inst)
    parts: list[set[int]] = []
    for i in short.tolist():
        part = {i}
        others = nbrs[i][~leg.locked[nbrs[i]]]
        if len(others):
            steps = int(np.ceil(float(motion_bound(rho, np.abs(target[i] - end[i]))) / RESOLUTION_MM)) + 1
            way = end[i][None] + (target[i] - end[i])[None] * np.linspace(0.0, 1.0, steps)[:, None]
            rows_i = np.full(steps * len(others), i)
            rows_j = np.tile(others, steps)
            c = clearance_rows(inst, leg.base_xy[rows_i], leg.orient[rows_i], np.repeat(way, len(others), axis=0),
                               leg.base_xy[rows_j], leg.orient[rows_j], end[rows_j]).min(axis=1).reshape(steps, -1)
            part.update(others[c.min(axis=0) < floor_mm].tolist())
        # Groups that share a member are one.
        for other in [p for p in parts if p & part]:
            parts.remove(other)
            part |= other
        parts.append(part)
    # Groups that touch (a member of one is a neighbour of the other's) wait for each other; up
    # to MERGE_UP_TO members together they are first searched as one, else one after the other.
    units = [[p] for p in sorted(sorted(p) for p in parts)]
    joined = True
    while joined:
        joined = False
        for a, b in itertools.combinations(range(len(units)), 2):
            in_a, in_b = set().union(*units[a]), set().union(*units[b])
            touch = any(j in in_b for i in in_a for j in nbrs[i].tolist())
            if touch and len(in_a | in_b) <= MERGE_UP_TO:
                units[a] += units.pop(b)
                joined = True
                break
    out, budget = joints, _Budget(CHECKS)
    stuck: list[list[int]] = []  # (rescue: the groups that found no way, held)
    go_on = (0, 0)  # (the unit, and the part in it, to search from)
    if rescue and resume is not None:  # (going on from where the search without rescue stopped)
        if len(resume.part) > RESCUE_UP_TO:
            return None
        out, stuck, go_on = resume.out, [resume.part], (resume.unit, resume.index + 1)
    try:
        for u in range(go_on[0], len(units)):
            unit = units[u]
            first = go_on[1] if u == go_on[0] else 0
            if len(unit) > 1 and first == 0:
                moved = _move(leg, out, sorted(set().union(*unit)), nbrs, floor_mm, dt_s, seed, budget)
                if moved is not None:
                    out = moved
                    continue
            for index in range(first, len(unit)):  # (one after the other: each starts once the ones before it are home)
                part = unit[index]
                moved = _move(leg, out, part, nbrs, floor_mm, dt_s, seed, budget)
                if moved is None:
                    # A leg is completed by group moves only where every group finds a way (the
                    # coordination layer keeps no partial one): the groups after this one need no search.
                    if not rescue and stopped is not None:
                        stopped.append(Stop(out, u, index, sorted(part)))
                    if not rescue or len(part) > RESCUE_UP_TO:
                        return None
                    stuck.append(sorted(part))
                    continue
                out = moved
        for part in stuck:
            moved = _move(leg, out, part, nbrs, floor_mm, dt_s, seed, budget, RESCUE_EFFORT)
            if moved is None:
                return None
            out = moved
    except _Spent:  # (:data:`CHECKS` used up)
        return None
    return out


RESCUE_EFFORT = 4
"""Times :data:`ITERATIONS` a group's search may draw, with :data:`RESCUE_SEARCHES` streams, when
it is searched again in a leg's last resort (:func:`groups` with ``rescue``). MOONS 500 unfold
under MOONS' zones seed 15, the fold's first attempt (33 short): four groups of four to six
members found no way at 2,000 samples per member (the leg ended 12 short after every attempt);
searched again after the others, at 8,000 samples per member and three streams, each found one,
in 5-363 s each (on a machine shared with two or three other jobs)."""

RESCUE_SEARCHES = 3
"""Searches (random streams) of a group searched again in a leg's last resort (:data:`RESCUE_EFFORT`)."""

RESCUE_UP_TO = 6
"""Largest group searched again in a leg's last resort: a larger group without a way ends it.
Groups of seven or eight cost 78-250 s at the first search's samples (MOONS 500, session 48);
MOONS 500 random seed 0's group of seven, searched again, found no way in 71 s, for a plan 2.7 x
as long to make and no shorter. The rescues that completed a leg searched groups of four to six
(MOONS' zones 500 unfold seed 15, ``moons-capsules`` 500 unfold seed 21)."""


def _move(leg: Scenario, out: np.ndarray, part: list[int], nbrs: list[np.ndarray], floor_mm: float, dt_s: float,
          seed: int, budget: _Budget | None = None, effort: int = 1) -> np.ndarray | None:
    """``out`` with group ``part`` brought home (:func:`groups`): from the earliest start that
    :func:`_early` finds, else from the sample after which its other neighbours hold; ``None``
    if its searches find no way. With ``effort`` other than 1 (a rescue), the early starts are
    searched from other random streams, and the latter with ``effort`` times :data:`ITERATIONS`
    and :data:`RESCUE_SEARCHES` streams (the first :data:`SEARCHES` of them the first search's,
    carried on past where it gave up)."""
    speeds = leg.instrument.speeds_rad_s
    members = np.array(part, dtype=np.int64)
    outer = np.setdiff1d(np.concatenate([nbrs[i] for i in part]), members)
    moving = np.any(out[1:, outer] != out[:-1, outer], axis=(1, 2)) if len(outer) else np.zeros(0, dtype=bool)
    later = np.flatnonzero(moving)
    k0 = int(later[-1]) + 1 if len(later) else 0  # its other neighbours hold from here on
    # (A rescue's early starts are searched from other random streams than the first search's.)
    early = _early(leg, out, part, nbrs, floor_mm, dt_s, seed, k0, budget, SEARCHES if effort == 1 else RESCUE_SEARCHES)
    if early is not None:
        ks, played = early
        return _placed(leg, out, members, ks, played)
    group = _Group(leg, out[k0], part, nbrs, floor_mm, budget)
    start, goal = out[k0, members].ravel(), leg.target[members].ravel()
    if not (group.edge_ok(start, start) and group.edge_ok(goal, goal)):
        return None
    for attempt in range(SEARCHES if effort == 1 else RESCUE_SEARCHES):
        # (Each group's own random stream: its search does not depend on the groups before it.)
        rng = np.random.default_rng((seed, attempt, *part))
        path = _connect(group, start, goal, rng, None if effort == 1 else ITERATIONS * effort)
        if path is None:
            continue
        timed = _timed(_shortcut(group, path, rng, speeds), speeds, dt_s).reshape(-1, len(part), 2)
        # The margin at every played sample, as solo moves keep it (the check proves the moves
        # clear between sub-steps, not at the margin): else the next search.
        if group.clearance(timed).min(initial=np.inf) >= floor_mm:
            return _placed(leg, out, members, k0, timed)
    return None


def _placed(leg: Scenario, out: np.ndarray, members: np.ndarray, k: int, played: np.ndarray) -> np.ndarray:
    """``out`` (lengthened if need be) with ``members`` playing ``played`` ``(M, g, 2)`` from sample
    ``k`` on, then holding at their targets."""
    length = max(len(out), k + len(played))
    out = np.concatenate([out, np.repeat(out[-1:], length - len(out), axis=0)])
    out[k : k + len(played), members] = played
    out[k + len(played) :, members] = leg.target[members]
    return out


EARLY_STEP_S = 1.0
"""Spacing (s) of the start times a group tries before its other neighbours hold (:func:`_early`)."""

EARLY_ITERATIONS = 500
"""Samples per member of the search from each early start (:data:`ITERATIONS` for the start
where the neighbours hold, :func:`_move`)."""


HOLD_SCREEN_S: float | None = np.inf
"""How long (s) the members must be able to hold at an early start while their neighbours go on
for :func:`_early` to search from it (``inf``: to the end of the attempt; ``None``: every start
is searched, as in session 46)."""


SHARED_GOAL_TREE = False
"""Whether :func:`_early`'s searches from successive starts share the goal's tree (the neighbours
where they will hold are the same for every start: the goal's side grown by one search stays
valid for the next). Off: on MOONS 500 and MOONS 61 it planned faster on most seeds but found other
ways, as often longer (MOONS 500 unfold seed 5: 4.16 -> 5.41 x the bound) as shorter
(docs/results.md, session 47)."""


def _early(leg: Scenario, out: np.ndarray, part: list[int], nbrs: list[np.ndarray], floor_mm: float, dt_s: float,
           seed: int, k0: int, budget: _Budget | None = None, stream: int = SEARCHES) -> tuple[int, np.ndarray] | None:
    """Group ``part`` brought home starting before sample ``k0`` (after which its other
    neighbours hold), while they still move: the first of the starts ``0, EARLY_STEP_S, ...``
    before ``k0`` from which it works, as ``(start sample, the members' samples (M, g, 2))``, or
    ``None``.

    From each start, the members' configuration there: a path is searched among the neighbours
    where they will hold (:func:`_connect`, :data:`EARLY_ITERATIONS` samples per member), then
    played along the neighbours' own motion by :func:`_tune`. A start whose configuration (or
    the targets) is not clear of the neighbours where they will hold is passed over. (A stalled
    attempt's stragglers are those with the longest moves, blocked from the start: MOONS 500
    unfold seed 0's straggler groups start 5-9 s earlier so, and end 5.7-8.6 s earlier.)"""
    members = np.array(part, dtype=np.int64)
    group = _Group(leg, out[-1], part, nbrs, floor_mm, budget)  # (the neighbours where they hold)
    field, last = out[:, group.outer[:, 1]], len(out) - 1  # (the outer neighbours, sample by sample)
    goal = leg.target[members].ravel()
    if not group.edge_ok(goal, goal):  # (the same for every start)
        return None
    goal_tree = _Tree(goal) if SHARED_GOAL_TREE else None
    for ks in range(0, k0, max(1, round(EARLY_STEP_S / dt_s))):
        start = out[ks, members].ravel()
        if not group.edge_ok(start, start):
            continue
        # A start from which the members could not wait where they stand while the neighbours go
        # on is passed over before any search: from such starts most plays met a neighbour within
        # their first 2 s with no way to wait, and every early start that worked on MOONS 500
        # unfold seed 5's first fold was one the members could wait at (:data:`HOLD_SCREEN_S`).
        if HOLD_SCREEN_S is not None:
            until = last if HOLD_SCREEN_S == np.inf else min(last, ks + max(1, round(HOLD_SCREEN_S / dt_s)))
            hold = np.broadcast_to(out[ks, members][None], (until - ks, len(part), 2))
            if not group.played_ok(hold, hold, field[ks:until], field[ks + 1 : until + 1]).all():
                continue
        rng = np.random.default_rng((seed, stream, ks, *part))
        path = _connect(group, start, goal, rng, EARLY_ITERATIONS, goal_tree)
        if path is None:
            continue
        played = _tune(group, _shortcut(group, path, rng, leg.instrument.speeds_rad_s), out, ks, dt_s)
        if played is not None:
            return ks, played
    return None


TUNE_STEPS = (1.0, 0.5, 0.25, 0.0)
"""Fractions of a full-speed step along the path tried at each sample by :func:`_tune` (0: wait)."""


def _tune(group: _Group, path: np.ndarray, out: np.ndarray, ks: int, dt_s: float) -> np.ndarray | None:
    """``path`` (flat waypoints, each segment as fast as its slowest joint allows) played from
    sample ``ks`` among the outer neighbours moving as in ``out`` (velocity tuning along a fixed
    path, Kant and Zucker 1986): at each sample the members go as far along the path as
    :data:`TUNE_STEPS` allows with every pair clear (:meth:`_Group.played_ok`), waiting where
    nothing does, then hold at their targets while the neighbours go on. Samples ``(M, g, 2)``
    from ``ks`` on, or ``None`` where even waiting is not clear (or the neighbours hold and the
    path is still blocked)."""
    speeds = group.leg.instrument.speeds_rad_s
    w = np.tile(speeds, path.shape[1] // 2)
    seg = np.max(np.abs(np.diff(path, axis=0)) / w, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total, last = float(cum[-1]), len(out) - 1
    field = out[:, group.outer[:, 1]]  # (K, P_outer, 2): the outer neighbours, sample by sample
    g = len(group.members)

    def at(s: float) -> np.ndarray:
        return path[-1] if s >= total else _at(path, seg, cum, s)[1]

    s, k, x = 0.0, ks, path[0]
    samples = [x]
    budget = ks + 4 * int(np.ceil(total / dt_s)) + len(out)  # (a path the neighbours block for good)
    while s < total:
        if k >= budget:
            return None
        q0, q1 = field[min(k, last)][None], field[min(k + 1, last)][None]
        for frac in TUNE_STEPS:
            s1 = min(s + frac * dt_s, total)
            x1 = at(s1)
            if group.played_ok(x.reshape(1, g, 2), x1.reshape(1, g, 2), q0, q1)[0]:
                break
        else:
            return None
        if frac == 0.0 and k >= last:  # the neighbours hold and the path stays blocked
            return None
        s, k, x = s1, k + 1, x1
        samples.append(x)
    # Home: the members hold at their targets while the neighbours go on.
    if k < last:
        hold = np.broadcast_to(x.reshape(1, g, 2), (last - k, g, 2))
        if not group.played_ok(hold, hold, field[k:last], field[k + 1 : last + 1]).all():
            return None
    return np.array(samples).reshape(-1, g, 2)
