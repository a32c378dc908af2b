"""Detour routes and waiting places for deadlocked positioners of the ``mpc`` planner.

Two tools, both searches over a grid of one positioner's joint configurations with its
neighbours held still (prioritised planning, one positioner at a time):

- :func:`detour_route`: a route around the neighbours for a positioner whose straight move is
  blocked;
- :func:`pair_resolution`: for a pair that blocks each other (typically each one's target lies
  on the other's straight path, so they push each other off their targets in turn): a route for
  the one that goes first, and for the other a waiting place off that route from which it can
  still reach its own target once the first has arrived, with routes to and from it.

On the grid of :mod:`fiberplan.planners.mpc.grid` (``cell_steps`` full steps per cell), a cell is free when its clearance is at least ``clear_mm``
plus half the motion bound of a diagonal move, so the clearance along every grid move is at
least ``clear_mm`` (half the sum of the end clearances minus the motion bound, the bound the
safety layer uses). See ``formulations/mpc.md`` (Deadlocks).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from fiberplan import capsule_kernels
from fiberplan.geometry import capsule_segments, capsule_tables, motion_bound, point_extents
from fiberplan.planners.mpc.grid import JointGrid, clearance_to, cross_clearance, densify
from fiberplan.scenario import Scenario

__all__ = ["DetourGrid", "PairResolution", "detour_route", "pair_resolution"]


class DetourGrid(JointGrid):
    """The joint grid of one positioner over its whole range, with the clearances of its cells to
    neighbours held still (kept per obstacle configuration, as the same neighbours are met again)."""

    def __init__(self, scenario: Scenario, i: int, step_rad: np.ndarray, clear_mm: float, end_clear_mm: float,
                 cell_steps: float = 2.0, end_cells: int = 3) -> None:
        inst = scenario.instrument
        cell = cell_steps * step_rad
        super().__init__(scenario, i, cell, *JointGrid.over_stops(scenario, cell))
        self.step_rad = step_rad
        self.threshold = clear_mm + 0.5 * float(motion_bound(point_extents(inst), self.cell))
        self.end_clear_mm, self.end_cells = end_clear_mm, end_cells
        self._memo: dict[tuple[int, float, float, float], np.ndarray] = {}  # (j, q_j, cutoff) -> clearances
        # i's capsules that take part in a same-layer combination (each once: many-edged zones
        # have many combinations per capsule), and each combination's capsule among them.
        used, self._combo_capsule = np.unique(capsule_tables(inst)[3][:, 0], return_inverse=True)
        a = self.seg_start[:, used]  # (cells, U, 2)
        d = self.seg_end[:, used] - a
        dd = d[..., 0] ** 2 + d[..., 1] ** 2
        self._lb_tables = (a, d, dd > 0, np.where(dd > 0, dd, 1.0))
        # Each capsule's midpoint and half length at every cell (the combinations' bounds).
        self._mid = 0.5 * (self.seg_start + self.seg_end)
        self._half = 0.5 * np.hypot(self.seg_end[..., 0] - self.seg_start[..., 0], self.seg_end[..., 1] - self.seg_start[..., 1])

    def clearance(self, others: np.ndarray, q_others: np.ndarray, cutoff: float) -> np.ndarray:
        """Clearance of every cell to ``others`` held at ``q_others``, exact where below ``cutoff``
        (elsewhere a lower bound at least ``cutoff``); one array per obstacle configuration is
        kept, as the same neighbours are met again at the same places."""
        out = np.full(len(self.configs), np.inf)
        if len(others) == 0:
            return out.reshape(self.shape)
        keys = [(int(j), float(qj[0]), float(qj[1]), float(cutoff)) for j, qj in zip(others, q_others, strict=True)]
        todo = [k for k, key in enumerate(keys) if key not in self._memo]
        if todo:
            if len(self._memo) + len(todo) > 256:
                self._memo.clear()
            for k, c in zip(todo, self._clearance_each(others[todo], q_others[todo], cutoff), strict=True):
                self._memo[keys[k]] = c
        for key in keys:
            out = np.minimum(out, self._memo[key])
        return out.reshape(self.shape)

    def _clearance_each(self, others: np.ndarray, q_others: np.ndarray, cutoff: float) -> list[np.ndarray]:
        """Each cell's clearance to each of ``others`` held at ``q_others`` (:meth:`clearance`), in
        one compiled loop per neighbour (:func:`fiberplan.capsule_kernels.detour_clearances`): a lower
        bound from the neighbour's base and reach, and below ``cutoff`` the exact smallest clearance
        over the combinations, those whose midpoint bound cannot hold it skipped."""
        inst = self.scenario.instrument
        _, _, _, combos, radii = capsule_tables(inst)
        ca, cb = combos[:, 0], combos[:, 1]
        res = []
        o_start, o_end = capsule_segments(inst, self.scenario.base_xy[others], self.scenario.orient[others], q_others)
        a, d, nz, safe = self._lb_tables
        for k, j in enumerate(others):
            # Lower bound: distance from j's base to i's capsule minus the farthest point of j's capsule from its base.
            base = self.scenario.base_xy[j]
            reach = np.maximum(np.linalg.norm(o_start[k] - base, axis=-1), np.linalg.norm(o_end[k] - base, axis=-1))[cb]
            q0, q1 = o_start[k][cb], o_end[k][cb]
            mid_q = 0.5 * (q0 + q1)
            half_q = 0.5 * np.hypot(q1[..., 0] - q0[..., 0], q1[..., 1] - q0[..., 1])
            c = np.empty(len(a))
            capsule_kernels.detour_clearances(a, d, nz, safe, self._combo_capsule, float(base[0]), float(base[1]), reach, radii, float(cutoff),
                                              self.seg_start, self.seg_end, ca, q0, q1, self._mid, self._half, mid_q, half_q, c)
            res.append(c)
        return res

    def ends(self, q: np.ndarray, free: np.ndarray, others: np.ndarray, q_others: np.ndarray) -> np.ndarray:
        """Free cells near ``q`` joined to it by a straight segment with enough clearance: (K, 2) indices.

        The segment needs ``end_clear_mm``, or half the clearance at ``q`` when that is less."""
        floor = min(self.end_clear_mm, 0.5 * float(clearance_to(self.scenario, self.i, q[None, :], others, q_others)[0]))
        centre = np.round((q - self.lo) / self.cell).astype(int)
        offs = np.arange(-self.end_cells, self.end_cells + 1)
        idx = np.stack(np.meshgrid(offs, offs, indexing="ij"), axis=-1).reshape(-1, 2) + centre
        idx = idx[np.all((idx >= 0) & (idx < self.shape), axis=1)]
        idx = idx[free[idx[:, 0], idx[:, 1]]]
        if len(idx) == 0:
            return idx
        # Nearest first (in steps): of equally good cells, the one nearest q is taken.
        pts = self.lo + idx * self.cell
        idx = idx[np.argsort(np.max(np.abs(pts - q) / self.step_rad, axis=1), kind="stable")]
        segs = [densify(np.array([q, p]), 0.5 * self.step_rad) for p in self.lo + idx * self.cell]
        c = clearance_to(self.scenario, self.i, np.concatenate(segs), others, q_others)
        bounds = np.cumsum([0] + [len(s) for s in segs])
        ok = np.array([c[a:b].min() >= floor for a, b in itertools.pairwise(bounds)])
        return idx[ok]


def _grid(scenario: Scenario, i: int, step_rad: np.ndarray, clear_mm: float, end_clear_mm: float, cell_steps: float,
          cache: dict[int, DetourGrid] | None) -> DetourGrid:
    """Positioner ``i``'s grid, from ``cache`` when given (one planning run: same settings)."""
    if cache is not None and i in cache:
        return cache[i]
    grid = DetourGrid(scenario, i, step_rad, clear_mm, end_clear_mm, cell_steps)
    if cache is not None:
        cache[i] = grid
    return grid


def _route(grid: DetourGrid, free: np.ndarray, q_from: np.ndarray, q_to: np.ndarray, others: np.ndarray, q_others: np.ndarray) -> np.ndarray | None:
    starts, goals = grid.ends(q_from, free, others, q_others), grid.ends(q_to, free, others, q_others)
    if len(starts) == 0 or len(goals) == 0:
        return None
    targets = np.zeros(grid.shape, dtype=bool)
    targets[goals[:, 0], goals[:, 1]] = True
    dist = grid.search(free, starts, targets)
    d = dist[goals[:, 0], goals[:, 1]]
    if not np.any(d >= 0):
        return None
    best = goals[np.flatnonzero(d >= 0)[np.argmin(d[d >= 0])]]
    return np.concatenate([grid.waypoints(dist, (int(best[0]), int(best[1]))), q_to[None, :]])


def detour_route(
    scenario: Scenario, i: int, q_from: np.ndarray, q_to: np.ndarray, others: np.ndarray, q_others: np.ndarray,
    step_rad: np.ndarray, clear_mm: float, end_clear_mm: float, cell_steps: float = 2.0, cache: dict[int, DetourGrid] | None = None,
) -> np.ndarray | None:
    """Waypoints ``(W, 2)`` (the last one ``q_to``) leading positioner ``i`` from ``q_from`` to ``q_to``
    around ``others`` held at ``q_others`` (one row per obstacle configuration), or ``None``.

    The route leaves ``q_from`` and enters ``q_to`` through straight segments to free cells at
    most three cells away whose sampled clearance is at least ``end_clear_mm`` (the ends
    themselves may be closer to the obstacles than the grid's threshold).
    """
    grid = _grid(scenario, i, step_rad, clear_mm, end_clear_mm, cell_steps, cache)
    free = grid.clearance(others, q_others, 2 * grid.threshold) >= grid.threshold
    return _route(grid, free, q_from, q_to, others, q_others)


@dataclass(frozen=True)
class PairResolution:
    """Routes for a blocked pair: ``first`` goes to its target along ``first_route`` while
    ``waiter`` goes to ``wait_q`` along ``to_wait`` and, once ``first`` has arrived, to its
    target along ``from_wait`` (all waypoints, each ending at its destination)."""

    first: int
    waiter: int
    first_route: np.ndarray
    wait_q: np.ndarray
    to_wait: np.ndarray
    from_wait: np.ndarray


def pair_resolution(
    scenario: Scenario, first: int, waiter: int, q: np.ndarray, goal: np.ndarray, neighbours: list[np.ndarray],
    step_rad: np.ndarray, clear_mm: float, end_clear_mm: float, cell_steps: float = 2.0, cache: dict[int, DetourGrid] | None = None,
) -> PairResolution | None:
    """A waiting place for ``waiter`` that lets ``first`` reach its target, or ``None``.

    ``first`` routes around its other neighbours held where they are (``q``); ``waiter``'s
    waiting place is the cell nearest (in steps) to where it is such that: it can get there
    around its other neighbours and ``first`` held where they are; ``first``'s whole route
    clears it; and from it ``waiter`` can reach its target ``goal[waiter]`` around its other
    neighbours and ``first`` at its target.
    """
    f_other = neighbours[first][neighbours[first] != waiter]
    w_other = neighbours[waiter][neighbours[waiter] != first]
    f_grid = _grid(scenario, first, step_rad, clear_mm, end_clear_mm, cell_steps, cache)
    f_free = f_grid.clearance(f_other, q[f_other], 2 * f_grid.threshold) >= f_grid.threshold
    first_route = _route(f_grid, f_free, q[first], goal[first], f_other, q[f_other])
    if first_route is None:
        return None
    w_grid = _grid(scenario, waiter, step_rad, clear_mm, end_clear_mm, cell_steps, cache)
    c_other = w_grid.clearance(w_other, q[w_other], 2 * w_grid.threshold)
    thr = w_grid.threshold
    # Reachable now: around its neighbours and first where they are.
    free_now = (c_other >= thr) & (w_grid.clearance(np.array([first]), q[[first]], 2 * thr) >= thr)
    obstacles_now = np.concatenate([w_other, [first]])
    starts = w_grid.ends(q[waiter], free_now, obstacles_now, q[obstacles_now])
    if len(starts) == 0:
        return None
    d_from = w_grid.search(free_now, starts)
    # Able to reach the target once first is there.
    free_after = (c_other >= thr) & (w_grid.clearance(np.array([first]), goal[[first]], 2 * thr) >= thr)
    obstacles_after = np.concatenate([w_other, [first]])
    q_after = np.concatenate([q[w_other], goal[[first]]])
    goals = w_grid.ends(goal[waiter], free_after, obstacles_after, q_after)
    if len(goals) == 0:
        return None
    d_to = w_grid.search(free_after, goals)
    # Candidates nearest first (then the shortest way on), checked in chunks until one clears
    # first's whole route: samples one cell apart, so the clearance between samples needs
    # another half motion bound of a cell.
    reach = np.flatnonzero(((d_from >= 0) & (d_to >= 0)).ravel())
    if len(reach) == 0:
        return None
    score = d_from.ravel()[reach] * 4 + d_to.ravel()[reach]
    reach = reach[np.argsort(score, kind="stable")]
    path = densify(np.vstack([q[first], first_route]), w_grid.cell)
    need = thr + (thr - clear_mm)
    found = None
    for chunk in range(0, len(reach), 256):
        cand = reach[chunk:chunk + 256]
        c_route = cross_clearance(scenario, waiter, w_grid.configs[cand], np.full(len(path), first), path).min(axis=1)
        good = np.flatnonzero(c_route >= need)
        if len(good):
            found = cand[good[0]]
            break
    if found is None:
        return None
    a, b = np.unravel_index(found, w_grid.shape)
    cell = (int(a), int(b))
    wait_q = w_grid.lo + np.array(cell) * w_grid.cell
    to_wait = w_grid.waypoints(d_from, cell)
    from_wait = np.concatenate([w_grid.waypoints(d_to, cell, reverse=True), goal[waiter][None, :]])
    return PairResolution(first, waiter, first_route, wait_q, to_wait, from_wait)
