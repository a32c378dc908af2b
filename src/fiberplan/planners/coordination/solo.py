"""Solo moves: the positioners a leg's planner runs left short go home while everyone else holds,
each along a shortest path of its own joint grid (``formulations/coordination.md``, Completing a
leg).

With its neighbours held still, one positioner's motion is a path in its two joint angles around
fixed obstacles: a breadth-first search over its joint grid (the ``mpc``'s
:class:`~fiberplan.planners.mpc.grid.JointGrid`) finds one whenever the grid resolves the free
space. A cell is free when its clearance to the held neighbours exceeds the floor plus half the
motion bound of a cell move, so that the straight move between two free adjacent cells keeps the
floor (the clearance changes by at most the motion bound along it). Every path is played at full
speed, one control step at a time, and checked sample by sample and between samples before it
is used (the motion bound again), so a move from a tight start is never taken on trust.

Positioners left short often block each other (two arms stretched across each other's way). When
no one of them has a way alone, one of them yields: a positioner ``i`` with a way once a blocking
neighbour ``j`` is out of it gets it, after ``j`` has moved to the nearest configuration it can
reach that clears all of ``i``'s way; ``j`` goes home later.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from fiberplan import zones
from fiberplan.geometry import capsule_segments, motion_bound, point_extents
from fiberplan.planners.mpc.grid import JointGrid, clearance_to, cross_clearance, densify
from fiberplan.scenario import Scenario

CELL_STEPS = 4
"""Grid cell size, in full-speed control steps per joint."""

MAX_SEARCHES = 24
"""Grid searches one :func:`solo_moves` call may make. Each costs a clearance over the whole
joint grid (measured on MOONS 61: 0.7 s with the capsule model, 3.8 s with MOONS' own zones), so
the limit bounds a call to about 20 s and 90 s there. A search whose positioner and neighbours
stand where they stood at an earlier one is not repeated (its answer is kept): the limit counts
new questions only (at 120, a dnf leg of a random MOONS 61 under MOONS' zones spent over 6 minutes
in solo moves)."""


class _Searches:
    """:func:`grid_path` with its answers kept per positioner, ignored neighbours and the
    joints of the positioner and its neighbours; at most :data:`MAX_SEARCHES` new ones."""

    def __init__(self, leg: Scenario, floor_mm: float, dt_s: float) -> None:
        self.leg, self.floor_mm, self.dt_s = leg, floor_mm, dt_s
        self.kept: dict[tuple[int, tuple[int, ...], bytes], np.ndarray | None] = {}
        self.left = MAX_SEARCHES

    def path(self, q: np.ndarray, i: int, ignore: Sequence[int] = ()) -> np.ndarray | None:
        key = (i, tuple(ignore), q[np.concatenate([[i], _neighbours(self.leg, i)])].tobytes())
        if key not in self.kept:
            if self.left <= 0:
                return None
            self.left -= 1
            self.kept[key] = grid_path(self.leg, q, i, self.floor_mm, self.dt_s, ignore=ignore)
        return self.kept[key]


def _neighbours(leg: Scenario, i: int, ignore: Sequence[int] = ()) -> np.ndarray:
    pairs = leg.pairs
    rows = (pairs == i).any(axis=1)
    found = np.setdiff1d(np.unique(pairs[rows]), [i]) if rows.any() else np.zeros(0, dtype=np.int64)
    return np.setdiff1d(found, np.asarray(ignore, dtype=np.int64))


def _clear(leg: Scenario, i: int, path: np.ndarray, q: np.ndarray, floor_mm: float, ignore: Sequence[int] = ()) -> bool:
    """Whether ``i`` moving along ``path`` ``(K, 2)`` (samples one control step apart, the first
    where it is) keeps the floor at every later sample and stays clear between samples, against
    its neighbours held at ``q``."""
    others = _neighbours(leg, i, ignore)
    if not len(others):
        return True
    c = cross_clearance(leg, i, path, others, q[others]).min(axis=1)
    bound = motion_bound(point_extents(leg.instrument), np.abs(np.diff(path, axis=0)))
    return not (np.any(c[1:] < floor_mm) or np.any(0.5 * (c[:-1] + c[1:] - bound) <= 0.0))


def _free(leg: Scenario, i: int, configs: np.ndarray, others: np.ndarray, q_others: np.ndarray, threshold: float) -> np.ndarray:
    """Which of ``i``'s ``configs`` ``(K, 2)`` keep ``threshold`` to ``others`` held at ``q_others``:
    ``clearance_to(...) >= threshold``. With polygon zones the exact distances are taken only
    where the zones' enclosing discs come within the threshold (the same answer, several times
    faster: :func:`fiberplan.zones.smallest`)."""
    inst = leg.instrument
    if not len(others) or not inst.polygons:
        return clearance_to(leg, i, configs, others, q_others) >= threshold
    s_i, e_i = capsule_segments(inst, leg.base_xy[[i]], leg.orient[[i]], configs[:, None, :])
    s_j, e_j = capsule_segments(inst, leg.base_xy[others], leg.orient[others], q_others)
    c = zones.smallest(inst, s_i[:, 0, None], e_i[:, 0, None], s_j[None], e_j[None], exact_below=threshold)
    return np.asarray(c.min(axis=1) >= threshold)


def grid_path(
    leg: Scenario, q: np.ndarray, i: int, floor_mm: float, dt_s: float, goal: np.ndarray | None = None,
    ignore: Sequence[int] = (), accept: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray | None:
    """Samples ``(K, 2)``, one control step apart, taking ``i`` from ``q[i]`` to ``goal`` (default
    its leg target) or, with ``accept`` (a function of the grid's configurations ``(M, 2)`` giving
    a mask), to the nearest accepted cell; its neighbours, but ``ignore``, held at ``q``. ``None``
    if the grid has no way or the way is not clear."""
    inst = leg.instrument
    step = inst.speeds_rad_s * dt_s
    cell = step * CELL_STEPS
    lo, shape = JointGrid.through(leg, q[i], cell)
    sa, sb = (int(v) for v in np.clip(np.round((q[i] - lo) / cell), 0, np.array(shape) - 1))
    exact = {(sa, sb): q[i]}
    if accept is None:
        goal = leg.target[i] if goal is None else goal
        ea, eb = (int(v) for v in np.clip(np.round((goal - lo) / cell), 0, np.array(shape) - 1))
        exact[(ea, eb)] = goal
    grid = JointGrid(leg, i, cell, lo, shape, exact=exact)
    # A move between adjacent cells spans at most 1.5 cells per joint (the exact cells sit within half a cell).
    move = float(motion_bound(point_extents(inst), 1.5 * cell))
    others = _neighbours(leg, i, ignore)
    free = _free(leg, i, grid.configs, others, q[others], floor_mm + 0.5 * move).reshape(shape)
    free[sa, sb] = True
    if accept is None:
        target = np.zeros(shape, dtype=bool)
        target[ea, eb] = True
    else:
        target = accept(grid.configs).reshape(shape) & free
    if not (target & free).any():
        return None
    dist = grid.search(free, np.array([(sa, sb)]), target)
    reached = np.argwhere(target & (dist >= 0))
    if not len(reached):
        return None
    end = tuple(int(v) for v in reached[np.argmin(dist[reached[:, 0], reached[:, 1]])])
    waypoints = grid.waypoints(dist, (end[0], end[1]))
    waypoints[0] = q[i]
    waypoints[-1] = grid.coords[end]
    samples = densify(waypoints, step)[1:]
    if not len(samples):  # within one cell: a straight move
        samples = densify(np.array([q[i], waypoints[-1]]), step)[1:]
    samples[-1] = waypoints[-1]
    if not _clear(leg, i, np.concatenate([q[i][None], samples]), q, floor_mm, ignore):
        return None
    return samples


def _yield(leg: Scenario, q: np.ndarray, i: int, floor_mm: float, dt_s: float, candidates: Sequence[int], searches: _Searches,
           ) -> tuple[int, np.ndarray, np.ndarray] | None:
    """A neighbour ``j`` among ``candidates`` that can move out of ``i``'s way: ``(j, j's samples,
    i's samples after)``, or ``None``."""
    inst = leg.instrument
    cell = inst.speeds_rad_s * dt_s * CELL_STEPS
    spare = 0.5 * float(motion_bound(point_extents(inst), cell)) + 0.5 * float(motion_bound(point_extents(inst), 1.5 * cell))
    for j in candidates:
        way = searches.path(q, i, ignore=[j])
        if way is None or searches.left <= 0:
            continue
        searches.left -= 1
        probe = np.concatenate([q[i][None], way])[::CELL_STEPS]  # samples at most a cell apart

        def clears_way(configs: np.ndarray, probe: np.ndarray = probe, j: int = j) -> np.ndarray:
            c = cross_clearance(leg, j, configs, np.full(len(probe), i), probe)  # (M, P): i at each sample of its way
            return np.asarray(c.min(axis=1) >= floor_mm + spare)

        aside = grid_path(leg, q, j, floor_mm, dt_s, accept=clears_way)
        if aside is None:
            continue
        after = q.copy()
        after[j] = aside[-1]
        if not _clear(leg, i, np.concatenate([q[i][None], way]), after, floor_mm):
            continue
        return j, aside, way
    return None


def solo_moves(leg: Scenario, q: np.ndarray, floor_mm: float, dt_s: float) -> tuple[np.ndarray, list[int]]:
    """Positioners away from their leg targets sent home while everyone else holds, again and
    again while one more gets home. Positioners that are not neighbours of each other cannot
    touch, so each round moves a set of them at once (chosen nearest first: short moves clear the
    way for longer ones), each along its :func:`grid_path`; when none has a way, one yields to
    another (:func:`_yield`). Returns ``(joints (K, N, 2) from q, indices moved)``."""
    pieces = [q[None].copy()]
    moved: list[int] = []
    current = q.copy()
    pairs = leg.pairs
    movable = leg.has_target & ~leg.locked
    movable[list(leg.infeasible)] = False
    searches = _Searches(leg, floor_mm, dt_s)
    yields = 0
    while yields <= leg.n_positioners:
        away = np.flatnonzero(~np.all(current == leg.target, axis=1) & movable)
        if not len(away):
            break
        order = away[np.argsort(np.max(np.abs(leg.target[away] - current[away]) / leg.instrument.speeds_rad_s, axis=1), kind="stable")]
        busy = np.zeros(leg.n_positioners, dtype=bool)
        paths: dict[int, np.ndarray] = {}
        for i in order.tolist():
            if busy[i]:
                continue
            samples = searches.path(current, i)
            if samples is None:
                continue
            paths[i] = samples
            busy[i] = True
            busy[pairs[(pairs == i).any(axis=1)].ravel()] = True  # its neighbours wait for the next round
        if not paths:
            found = None
            for i in order.tolist():
                blockers = [j for j in _neighbours(leg, i).tolist() if not leg.locked[j]]
                blockers.sort(key=lambda j: (not bool(np.isin(j, away)), j))  # those still away first
                found = _yield(leg, current, i, floor_mm, dt_s, blockers, searches)
                if found is not None:
                    break
            if found is None:
                break
            j, aside, way = found
            yields += 1
            for who, samples in ((j, aside), (i, way)):
                block = np.repeat(current[None], len(samples), axis=0)
                block[:, who] = samples
                pieces.append(block)
                current = block[-1].copy()
            moved += [j, i]
            continue
        length = max(len(p) for p in paths.values())
        block = np.repeat(current[None], length, axis=0)
        for i, samples in paths.items():
            block[: len(samples), i] = samples
            block[len(samples):, i] = samples[-1]
        pieces.append(block)
        current = block[-1].copy()
        moved += list(paths)
    return np.concatenate(pieces), moved
