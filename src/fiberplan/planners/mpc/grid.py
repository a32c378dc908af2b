"""One positioner's joint-configuration grid, shared by the detour searches and the timed paths.

Joint motion is counted in full-speed steps: a cell is ``cell_steps`` steps on each joint, so
one grid move (axis or diagonal) takes the same time and a breadth-first search finds
time-shortest routes. The grid places the positioner's capsules at every cell once; the
searches then only ask which cells keep clear of given neighbours (``formulations/mpc.md``).
"""

from __future__ import annotations

import itertools

import numpy as np

from fiberplan.geometry import capsule_segments, clearance_between
from fiberplan.scenario import Scenario

MOVES_8 = [(da, db) for da in (-1, 0, 1) for db in (-1, 0, 1) if da or db]
"""The 8 grid moves, in the fixed order that breaks ties."""


def dilate(mask: np.ndarray) -> np.ndarray:
    """Cells of a 2-D mask and their 8 neighbours (one grid move in any direction)."""
    grow = mask.copy()
    grow[1:] |= mask[:-1]
    grow[:-1] |= mask[1:]
    grow[:, 1:] |= grow[:, :-1].copy()
    grow[:, :-1] |= grow[:, 1:].copy()
    return grow


def densify(waypoints: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Points along the straight joint-space segments between ``waypoints``, at most ``spacing`` apart per joint."""
    pts = [waypoints[:1]]
    for a, b in itertools.pairwise(waypoints):
        n = int(np.ceil(np.max(np.abs(b - a) / spacing, initial=0.0)))
        if n:
            t = np.arange(1, n + 1)[:, None] / n
            pts.append(a + t * (b - a))
    return np.concatenate(pts)


def cross_clearance(scenario: Scenario, i: int, configs: np.ndarray, others: np.ndarray, q_others: np.ndarray) -> np.ndarray:
    """Clearance ``(K, M)`` of positioner ``i`` at each of ``configs`` (K, 2) to each of ``others`` (M) at ``q_others`` (M, 2)."""
    k, m = len(configs), len(others)
    c = clearance_between(
        scenario.instrument,
        np.broadcast_to(scenario.base_xy[i], (k * m, 2)), np.full(k * m, scenario.orient[i]), np.repeat(configs, m, axis=0),
        scenario.base_xy[np.tile(others, k)], scenario.orient[np.tile(others, k)], np.tile(q_others, (k, 1)),
    ).min(axis=-1)
    return c.reshape(k, m)


def clearance_to(scenario: Scenario, i: int, configs: np.ndarray, others: np.ndarray, q_others: np.ndarray) -> np.ndarray:
    """Smallest clearance of positioner ``i`` at each of ``configs`` (K, 2) to ``others`` held at ``q_others``."""
    if len(others) == 0:
        return np.full(len(configs), np.inf)
    return cross_clearance(scenario, i, configs, others, q_others).min(axis=1)


class JointGrid:
    """The joint grid of positioner ``i``: cells ``lo + index * cell`` inside its hard stops,
    with its capsule segments placed at every cell.

    Attributes:
        lo: ``(2,)`` joint angles of cell ``(0, 0)``.
        cell: ``(2,)`` cell size per joint (rad).
        shape: cells per joint.
        coords: ``(A, B, 2)`` joint configuration of every cell.
        configs: the same, flat ``(A * B, 2)``.
        seg_start, seg_end: ``(A * B, C, 2)`` capsule segments at every cell.
    """

    def __init__(self, scenario: Scenario, i: int, cell: np.ndarray, lo: np.ndarray, shape: tuple[int, int],
                 exact: dict[tuple[int, int], np.ndarray] | None = None) -> None:
        inst = scenario.instrument
        self.scenario, self.i = scenario, i
        self.lo, self.cell, self.shape = lo, cell, shape
        axes = [lo[k] + np.arange(shape[k]) * cell[k] for k in range(2)]
        self.coords = np.stack(np.meshgrid(axes[0], axes[1], indexing="ij"), axis=-1)
        for where, q in (exact or {}).items():  # cells that stand for an exact configuration
            self.coords[where] = q
        self.configs = self.coords.reshape(-1, 2)
        start, end = capsule_segments(inst, scenario.base_xy[[i]], scenario.orient[[i]], self.configs[:, None, :])
        self.seg_start, self.seg_end = start[:, 0], end[:, 0]

    @staticmethod
    def over_stops(scenario: Scenario, cell: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
        """``(lo, shape)`` of a grid from the lower hard stops up to the upper ones."""
        lim = scenario.instrument.limits_rad
        lo = lim[:, 0]
        span = lim[:, 1] - lo
        return lo, (int(np.floor(span[0] / cell[0])) + 1, int(np.floor(span[1] / cell[1])) + 1)

    @staticmethod
    def through(scenario: Scenario, anchor: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
        """``(lo, shape)`` of a grid inside the hard stops with a cell exactly at ``anchor``."""
        lim = scenario.instrument.limits_rad
        lo = anchor - np.floor((anchor - lim[:, 0]) / cell + 1e-9) * cell
        shape = tuple(int(v) for v in np.floor((lim[:, 1] - lo) / cell + 1e-9) + 1)
        return lo, (shape[0], shape[1])

    def search(self, free: np.ndarray, sources: np.ndarray, targets: np.ndarray | None = None) -> np.ndarray:
        """Breadth-first search over free cells from ``sources`` (8-connected, one wave front per
        move): steps from the nearest source, -1 where unreachable. Stops early once a cell of
        ``targets`` (a mask) is reached."""
        dist = np.full(self.shape, -1, dtype=np.int64)
        front = np.zeros(self.shape, dtype=bool)
        front[sources[:, 0], sources[:, 1]] = True
        d = 0
        while front.any():
            dist[front] = d
            if targets is not None and np.any(front & targets):
                break
            front = dilate(front) & free & (dist < 0)
            d += 1
        return dist

    def waypoints(self, dist: np.ndarray, cell: tuple[int, int], reverse: bool = False) -> np.ndarray:
        """Joint waypoints of a shortest search path from a source to ``cell`` (``reverse``: from
        ``cell`` toward the source), keeping only the cells where the direction changes. The
        path steps down the distance map; ties go to the first of the 8 moves in a fixed order."""
        cells = [cell]
        a, b = cell
        while dist[a, b] > 0:
            for da, db in MOVES_8:
                x, y = a + da, b + db
                if 0 <= x < self.shape[0] and 0 <= y < self.shape[1] and dist[x, y] == dist[a, b] - 1:
                    a, b = x, y
                    break
            cells.append((a, b))
        path = np.array(cells if reverse else cells[::-1])
        if len(path) > 2:
            d = np.diff(path, axis=0)
            turn = np.any(d[1:] != d[:-1], axis=1)
            path = np.concatenate([path[:1], path[1:-1][turn], path[-1:]])
        return self.lo + path * self.cell
