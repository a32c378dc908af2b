"""Start schedule of the ``mpc`` planner: prioritised start delays along straight (or L-shaped) moves.

Before the first control step, positioners in decreasing order of their move time each take
the smallest start delay (a multiple of ``delay_steps``) for which their straight full-speed
move, so delayed, keeps at least ``margin_mm`` (capped by the pair's clearance with both at
their starts and with both at their targets) from every neighbour already scheduled, moving as
scheduled; every move must end by ``slack`` x the longest move. This is path-velocity
decomposition with priorities: it orders the pairs whose targets impose an order (one's
target lies on the other's path) before anyone moves, where the reactive loop would find
them only as deadlocks a window later.

A positioner that no delay fits swaps with the neighbours in its way: it takes the delay with
the fewest conflicts and those neighbours are scheduled again after it; if one of them then
fits nowhere the swap is undone and it starts at once (``unplaced``: the reactive loop and its
deadlock rules handle it, as without a schedule). With ``l_paths``, each unplaced positioner then
tries the two L-shaped moves (alpha first, or beta first, through the corner where one joint has
arrived and the other not yet moved) with the same delays and checks; the planner follows a
placed one as a route through its corner. With ``space_time``, those still unplaced search a
timed path over their joint grid x time around everyone as scheduled (:func:`space_time_path`),
which the planner follows as a route leaving each waypoint no earlier than its departure step.
With ``repair``, each positioner still unplaced then goes first: a placed neighbour leaves the
schedule, the positioner searches its timed path around the others, and the neighbour is placed
again after it (a delay, an L-shaped move or a timed path), or both are restored. With
``pair_paths``, each one still unplaced then searches timed paths together with a placed
neighbour, over the pairs of their grid cells x time (:func:`pair_space_time_path`).

The schedule only sets when each positioner's reference starts: collision avoidance stays
with the QPs and the safety layer. Clearances are checked every ``stride`` steps. See
``formulations/mpc.md`` (Start schedule).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fiberplan import _fork, zones
from fiberplan.geometry import capsule_segments, capsule_tables, combo_clearances, smallest_clearance
from fiberplan.kinematics import straight_path
from fiberplan.layout import neighbour_lists
from fiberplan.planners.mpc.grid import JointGrid
from fiberplan.planners.mpc.kernels import space_time_cells
from fiberplan.scenario import Scenario

__all__ = ["SPLIT_ABOVE", "StartSchedule", "StartScheduler", "space_time_path", "start_schedule", "timed_waypoints"]


def _full_speed_steps(a: np.ndarray, b: np.ndarray, step_rad: np.ndarray) -> np.ndarray:
    """Control steps of each straight full-speed move ``a -> b`` (rows): the slower joint's."""
    return np.ceil(np.max(np.abs(b - a) / step_rad, axis=1) - 1e-9).astype(np.int64)


@dataclass(frozen=True)
class StartSchedule:
    """Start delays (control steps) per positioner, and how they were found."""

    delay_steps: np.ndarray
    unplaced: np.ndarray
    swaps: int
    corner: np.ndarray  # (N, 2): the corner of a positioner's L-shaped move; NaN rows: straight
    timed: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # i -> (waypoints, departure steps)


def space_time_path(free: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> np.ndarray | None:
    """Earliest path through a grid over time layers, staying at ``goal`` once there.

    Args:
        free: ``(L + 1, A, B)`` whether each cell may be occupied at each time layer.
        start: the cell at layer 0.
        goal: the cell to end in, and stay in up to the last layer.

    Returns:
        The cells ``(l* + 1, 2)`` at layers ``0..l*``, ``l*`` the earliest layer from which
        ``goal`` can be held (each layer moves to one of the 8 neighbouring cells or stays);
        ``None`` if there is none. Backward from ``goal``, each layer's cell is the reachable
        one nearest ``start`` (Chebyshev), so the path tends to wait at its start (a delay)
        rather than on its way.
    """
    cells = space_time_cells(np.ascontiguousarray(free, dtype=bool), int(start[0]), int(start[1]), int(goal[0]), int(goal[1]))
    return cells if len(cells) else None


def timed_waypoints(cells: np.ndarray, coords: np.ndarray, cell_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints and departure steps of a space-time path (:func:`space_time_path`).

    Args:
        cells: the path's cells at layers ``0..l*``.
        coords: ``(A, B, 2)`` joint configuration of every cell.
        cell_steps: control steps per layer.

    Returns:
        ``(waypoints (M, 2), depart (M,))``: the path runs at full speed through the cells
        where its direction changes; ``depart[m]`` is the control step at which it leaves for
        ``waypoints[m]`` (a stay at a cell delays the next departure).
    """
    d = np.diff(cells, axis=0)
    points, depart = [], []
    k = 0
    while k < len(d):
        e = k
        while e + 1 < len(d) and np.all(d[e + 1] == d[k]):
            e += 1
        if np.any(d[k] != 0):
            points.append(coords[tuple(cells[e + 1])])
            depart.append(k * cell_steps)
        k = e + 1
    return np.array(points).reshape(-1, 2), np.array(depart, dtype=np.int64)


def _dilate_pairs(front: np.ndarray) -> np.ndarray:
    """States ``(A, B, A', B')`` one layer on: each of the two positioners moves to one of its 8
    neighbouring cells or stays, independently."""
    out = front.copy()
    for axes in ((0, 1), (2, 3)):
        before = out.copy()
        for da, db in ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
            dst, src = [slice(None)] * 4, [slice(None)] * 4
            for axis, d in zip(axes, (da, db), strict=True):
                if d > 0:
                    dst[axis], src[axis] = slice(d, None), slice(None, -d)
                elif d < 0:
                    dst[axis], src[axis] = slice(None, d), slice(-d, None)
            out[tuple(dst)] |= before[tuple(src)]
    return out


def pair_space_time_path(free_i: np.ndarray, free_j: np.ndarray, together: np.ndarray, start: tuple[int, int, int, int],
                         goal: tuple[int, int, int, int]) -> np.ndarray | None:
    """Earliest joint path of two positioners through their grids over time layers, each staying
    at its goal once the two are there (:func:`space_time_path` for a pair).

    Args:
        free_i, free_j: ``(L + 1, A, B)`` and ``(L + 1, A', B')``: whether each of the two may
            occupy each of its cells at each layer (against everyone else as scheduled).
        together: ``(A, B, A', B')`` whether the two keep their pair's floor in those cells.
        start, goal: the two cells of each, ``(a, b, a', b')``.

    Returns:
        The states ``(l* + 1, 4)`` at layers ``0..l*``, ``l*`` the earliest layer from which
        both goals can be held; ``None`` if there is none. Backward from the goal, each layer's
        state is the reachable one nearest the start (Chebyshev), as in the single search.
    """
    layers = free_i.shape[0]
    hold_i = np.flip(np.logical_and.accumulate(np.flip(free_i[:, goal[0], goal[1]])))  # goal free from layer l on
    hold_j = np.flip(np.logical_and.accumulate(np.flip(free_j[:, goal[2], goal[3]])))
    front = np.zeros(together.shape, dtype=bool)
    front[start] = True
    fronts = [front]
    end = None
    for layer in range(1, layers):
        front = _dilate_pairs(front) & free_i[layer][:, :, None, None] & free_j[layer][None, None] & together
        fronts.append(front)
        if front[goal] and hold_i[layer] and hold_j[layer]:
            end = layer
            break
        if not front.any():
            return None
    if end is None:
        return None
    shape = np.array(together.shape)
    at = np.array(goal)
    begin = np.array(start)
    states = [at]
    moves = np.array(list(np.ndindex(3, 3, 3, 3))) - 1
    for layer in range(end - 1, -1, -1):
        before = at + moves
        inside = np.all((before >= 0) & (before < shape), axis=1)
        before = before[inside]
        ok = before[fronts[layer][tuple(before.T)]]
        at = ok[np.argmin(np.abs(ok - begin).max(axis=1))]  # (the first of the nearest)
        states.append(at)
    return np.array(states[::-1])


@dataclass
class _Placement:
    """One positioner's place in the schedule, saved to undo a trial (``StartScheduler._save``)."""

    k: int
    seg_start: np.ndarray
    seg_end: np.ndarray
    delay: int
    move: int
    corner: np.ndarray
    timed: tuple[np.ndarray, np.ndarray] | None
    unplaced: bool
    clean: np.ndarray


@dataclass(frozen=True)
class _TimedGrid:
    """The grid of one positioner's timed search, and per neighbour as scheduled the cells it
    comes close to with, per layer, whether each of them keeps the pair's floor."""

    grid: JointGrid
    s_cell: tuple[int, int]
    g_cell: tuple[int, int]
    blocks: list[tuple[int, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class _Fixed:
    """Positioners of a part of the field already scheduled by another part (rows of the part):
    their delays, moves (steps) and capsules at every step ``(F, horizon + 1, C, 2)``."""

    rows: np.ndarray
    delay: np.ndarray
    move: np.ndarray
    seg_start: np.ndarray
    seg_end: np.ndarray


@dataclass(frozen=True)
class _Part:
    """Some positioners of a scenario, as the scheduler reads a scenario: their pairs among
    themselves, renumbered (in the scenario's pair order)."""

    instrument: Any
    base_xy: np.ndarray
    orient: np.ndarray
    start: np.ndarray
    target: np.ndarray
    pairs: np.ndarray
    priority_rank: np.ndarray

    @property
    def n_positioners(self) -> int:
        return len(self.start)

    @staticmethod
    def of(scenario: Scenario, rows: np.ndarray) -> _Part:
        local = np.full(scenario.n_positioners, -1, dtype=np.int64)
        local[rows] = np.arange(len(rows))
        pairs = local[scenario.pairs]
        pairs = pairs[(pairs >= 0).all(axis=1)].reshape(-1, 2)
        return _Part(scenario.instrument, scenario.base_xy[rows], scenario.orient[rows], scenario.start[rows],
                     scenario.target[rows], pairs, scenario.priority_rank[rows])


class StartScheduler:
    """Greedy start delays such that the delayed moves keep their margins pairwise.

    Args:
        scenario: the scenario (starts, targets, neighbour pairs).
        step_rad: joint motion per control step at full speed (rad).
        margin_mm: clearance to keep, capped per pair at 0.9 x its clearance at the starts
            and at the targets (a pair that starts or ends closer could not keep it).
        delay_steps: granularity of the delays (control steps); coarser where a positioner
            would otherwise have more than ``max_options`` delays to try.
        slack: every delayed move must end by ``slack`` x the longest move.
        stride: clearances are checked every ``stride`` steps.
        max_options: delays tried per positioner at most.
        swap_tries: delays (fewest conflicts first) a positioner no delay fits tries to swap at.
        l_paths: positioners no delay of the straight move fits try the two L-shaped moves.
        space_time: positioners still unplaced search a timed path (joint grid x time) around
            every neighbour as scheduled (:func:`space_time_path`).
        cell_steps: full-speed control steps per grid cell and time layer of that search.
        repair: with ``space_time``, a positioner still unplaced goes first: each placed
            neighbour in turn leaves the schedule, the positioner searches its timed path around
            the others, and the neighbour is placed again after it (a delay, an L-shaped move or
            a timed path), or both are restored and the next neighbour is tried.
        first: ``(N,)`` positioners scheduled before all others (reference 003's re-prioritisation
            after a failure); within each group, the longest move first.
        horizon: the last step of every move (default ``slack`` x the longest move); a part of a
            field (:func:`start_schedule`) takes the whole field's.
        fixed: positioners already scheduled (by another part of the field), held as scheduled:
            the others are checked against them, they are not placed, swapped or repaired.
        late_corners: a positioner that needs a delay also tries its move with the faster joint
            starting late (:meth:`_late_corner`: the same duration, another sweep) and keeps the
            one that ends first.
        late: ``(N,)`` positioners whose move starts with that shape (before anyone is placed).
        pair_paths: a positioner still unplaced after the passes above searches timed paths
            together with a placed neighbour (:meth:`_repair_pair`).

    The state is explicit: per positioner its ``delay``, its ``move`` (steps), its capsules at
    every step of its move as scheduled (``seg_start``, ``seg_end``), its ``corner`` (L-shaped
    moves) or ``timed`` path, whether it is ``done`` (scheduled, for the others to check
    against) or ``unplaced``; per pair the ``floor`` it keeps and whether its undelayed moves are
    ``clean``. :meth:`run` fills it and returns a :class:`StartSchedule`.
    """

    def __init__(
        self, scenario: Scenario, step_rad: np.ndarray, margin_mm: float, delay_steps: int = 4, slack: float = 1.2, stride: int = 2,
        max_options: int = 64, swap_tries: int = 1, l_paths: bool = False, space_time: bool = False, cell_steps: int = 2,
        repair: bool = False, first: np.ndarray | None = None, horizon: int | None = None, fixed: _Fixed | None = None,
        late_corners: bool = False, late: np.ndarray | None = None, pair_paths: bool = False,
    ) -> None:
        self.scenario, self.step_rad = scenario, step_rad
        self.delay_steps, self.max_options, self.swap_tries = delay_steps, max_options, swap_tries
        self.l_paths, self.space_time, self.cell_steps, self.repair = l_paths, space_time, cell_steps, repair
        self.pair_paths = pair_paths
        self.first = np.zeros(scenario.n_positioners, dtype=bool) if first is None else np.asarray(first, dtype=bool)
        self.priority = scenario.priority_rank
        self.inst = scenario.instrument
        n = self.n = scenario.n_positioners
        self.pairs = scenario.pairs
        self.delay = np.zeros(n, dtype=np.int64)
        self.corner = np.full((n, 2), np.nan)
        self.timed: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.done = np.zeros(n, dtype=bool)
        self.unplaced = np.zeros(n, dtype=bool)
        self.swaps = 0
        if n == 0 or len(self.pairs) == 0:
            return
        self.move = _full_speed_steps(scenario.start, scenario.target, step_rad)
        self.horizon = horizon = int(np.ceil(slack * self.move.max())) if horizon is None else horizon
        # Joints of every straight full-speed move at steps 0..horizon.
        self.path = np.concatenate([scenario.start[:, None], straight_path(scenario.start, scenario.target, step_rad, horizon)], axis=1)
        self.times = np.unique(np.append(np.arange(0, horizon + 1, stride), horizon))
        self.base, self.orient = scenario.base_xy, scenario.orient
        # Capsule segments of every move at every step, computed once, in (N, steps, C, 2) order
        # directly (no transposed copy: 1.2 GB each at 50,000 positioners).
        self.seg_start, self.seg_end = capsule_segments(self.inst, self.base[:, None], self.orient[:, None], self.path)
        self.combo_radii = capsule_tables(self.inst)[4]
        a, b = self.pairs[:, 0], self.pairs[:, 1]
        # Step 0 is the start and the last step the target of every move.
        zero, last = np.zeros(len(a), dtype=np.int64), np.full(len(a), horizon, dtype=np.int64)
        self.floor = np.minimum(margin_mm, 0.9 * np.minimum(self._moving_min(a, zero, b, zero), self._moving_min(a, last, b, last)))
        # Pairs whose undelayed moves keep their margin need no check while both start at once.
        t = self.times[None, :]
        self.clean = np.empty(len(a), dtype=bool)
        chunk = max(1, 1_000_000 // len(self.times))  # pairs at a time: the (pairs, times, C, 2) gathers stay ~100 MB
        for r0 in range(0, len(a), chunk):
            r = slice(r0, r0 + chunk)
            self.clean[r] = self._moving_min(a[r, None], t, b[r, None], t).min(axis=1) >= self.floor[r]
        self.nb, self.nb_row = neighbour_lists(self.pairs, n)
        self.straight_move = self.move.copy()
        self.late_corners = late_corners
        for i in np.flatnonzero(np.zeros(n, dtype=bool) if late is None else late).tolist():
            c = self._late_corner(i)
            if c is not None and self._route_through(i, c):
                self.corner[i] = c
        self.fixed = np.zeros(n, dtype=bool)
        if fixed is not None and len(fixed.rows):
            f = fixed.rows
            self.fixed[f], self.done[f], self.delay[f], self.move[f] = True, True, fixed.delay, fixed.move
            self.seg_start[f], self.seg_end[f] = fixed.seg_start, fixed.seg_end
            self.clean[self.fixed[a] | self.fixed[b]] = False  # their moves may not be the straight ones
        self.n_layers = horizon // cell_steps
        # Every layer is checked at each step within half a layer of it.
        self.samples = np.arange(0, self.n_layers * cell_steps + cell_steps // 2 + 1)
        offsets = np.arange(-(cell_steps // 2), cell_steps // 2 + 1)
        self.window = np.clip(np.arange(self.n_layers + 1)[:, None] * cell_steps + offsets[None, :], 0, len(self.samples) - 1)

    # ------------------------------------------------------------------ the passes
    def run(self) -> StartSchedule:
        """Schedule every positioner (longest move first), then the fallbacks the settings turn on."""
        if self.n == 0 or len(self.pairs) == 0:
            return StartSchedule(self.delay, np.zeros(0, dtype=np.int64), 0, self.corner)
        # Longest move first, after the targets of higher priority (the scenario's, none by default).
        for i in np.lexsort((np.arange(self.n), -self.move, self.priority, ~self.first)).tolist():
            if self.fixed[i]:
                continue
            d, js, options, ok = self._place(i)
            if self.late_corners and d is not None and d > 0 and np.isnan(self.corner[i, 0]):
                d = self._try_late(i, d)
            if d is None:
                if self._swap(i, js, options, ok):
                    self.swaps += 1
                    continue
                d = 0
                self.unplaced[i] = True
            self.delay[i], self.done[i] = d, True
        if self.l_paths:
            # Unplaced positioners try the two L-shaped moves, which sweep other places than the
            # straight one, against every neighbour as scheduled.
            for i in self._unplaced_longest_first():
                if self._reroute(i):
                    self.unplaced[i] = False
        if self.space_time:
            for i in self._unplaced_longest_first():
                if self._search_timed(i):
                    self.unplaced[i] = False
            if self.repair:
                for i in self._unplaced_longest_first():
                    if self._repair_timed(i):
                        self.unplaced[i] = False
        if self.pair_paths:
            for i in self._unplaced_longest_first():
                if self._repair_pair(i):
                    self.unplaced[i] = False
        for i, (_, depart) in self.timed.items():
            self.delay[i] = depart[0]
        return StartSchedule(self.delay, np.flatnonzero(self.unplaced), self.swaps, self.corner, self.timed)

    def _unplaced_longest_first(self) -> list[int]:
        who = np.flatnonzero(self.unplaced)
        return who[np.lexsort((who, -self.move[who]))].tolist()

    # ------------------------------------------------------------------ delays on the straight move
    def _moving_min(self, i: np.ndarray | np.integer, ti: np.ndarray, j: np.ndarray, tj: np.ndarray,
                    exact_below: float | None = None) -> np.ndarray:
        """Clearance of ``i`` after ``ti`` steps of its move to ``j`` after ``tj`` (index arrays,
        broadcast); exact below ``exact_below`` (default: everywhere), a lower bound at least that above."""
        s, e = self.seg_start, self.seg_end
        if not self.inst.polygons:  # compiled, reading the capsules in place: the same numbers
            steps, c = s.shape[1], s.shape[2]
            flat_s, flat_e = s.reshape(-1, c, 2), e.reshape(-1, c, 2)
            return smallest_clearance(self.inst, flat_s, flat_e, np.asarray(i) * steps + ti, flat_s, flat_e, np.asarray(j) * steps + tj)
        # Polygon zones: the steps of the positioners asked about, read by index, not gathered as
        # (D, J, K, C, 2) copies first (a MOONS 500 fold leg's peak: 1.9 GB against 2.6 GB).
        i, j = np.asarray(i), np.asarray(j)
        steps, c = s.shape[1], s.shape[2]
        used = np.unique(np.concatenate([i.ravel(), j.ravel()]))  # (before broadcasting: a few positioners)
        if 2 * len(used) > len(s):  # most of them (the pairs' checks at the start): the whole table, in place
            table_s, table_e = s.reshape(-1, c, 2), e.reshape(-1, c, 2)
            p, q = i * steps + ti, j * steps + tj
        else:
            row = np.empty(len(s), dtype=np.int64)
            row[used] = np.arange(len(used))
            table_s, table_e = s[used].reshape(-1, c, 2), e[used].reshape(-1, c, 2)
            p, q = row[i] * steps + ti, row[j] * steps + tj
        return zones.smallest_indexed(self.inst, table_s, table_e, p, table_s, table_e, q,
                                      exact_below=zones.EXACT_BELOW_MM if exact_below is None else exact_below)

    def _fits(self, i: int, delays: np.ndarray, js: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(D, J): whether ``i`` delayed by each of ``delays`` keeps its margin to each ``j``."""
        delay, move, times, horizon = self.delay, self.move, self.times, self.horizon
        # Only while one of them moves: before and after, both hold (the ends are sampled).
        t_lo = min(int(delays.min()), int(delay[js].min()))
        t_hi = max(int(delays.max()) + int(move[i]), int((delay[js] + move[js]).max()))
        t = np.unique(np.concatenate([times[(times >= t_lo) & (times <= t_hi)], [t_lo, min(t_hi, horizon)]]))
        # np.minimum(np.maximum()) rather than np.clip: the same integers, without np.clip's
        # per-call overhead (this runs for every delay tried of every positioner).
        ti = np.minimum(np.maximum(t[None, None, :] - delays[:, None, None], 0), horizon)  # (D, 1, K)
        tj = np.minimum(np.maximum(t[None, None, :] - delay[js][None, :, None], 0), horizon)  # (1, J, K)
        floor = self.floor[rows]
        c = self._moving_min(np.int64(i), ti, js[None, :, None], tj, exact_below=float(floor.max())).min(axis=2)  # (D, J)
        return c >= floor[None, :]

    def _place(self, i: int) -> tuple[int | None, np.ndarray, np.ndarray, np.ndarray]:
        """Smallest fitting delay of ``i`` against the scheduled neighbours, else ``None``
        (with the neighbours checked, the delays tried and which fitted whom)."""
        sel = self.done[self.nb[i]]
        js, rows = self.nb[i][sel], self.nb_row[i][sel]
        # No delay: only pairs with a delayed neighbour or a conflict between the undelayed
        # moves need a check.
        check = (self.delay[js] != 0) | ~self.clean[rows]
        if not np.any(check) or self._fits(i, np.zeros(1, dtype=np.int64), js[check], rows[check]).all():
            return 0, js, np.zeros(0, dtype=np.int64), np.zeros((0, 0), dtype=bool)
        room = max(0, self.horizon - int(self.move[i]))
        options = np.arange(0, room + 1, max(self.delay_steps, int(np.ceil(room / self.max_options))))
        ok = np.zeros((0, len(js)), dtype=bool)
        for lo in range(0, len(options), 8):  # a few delays at a time: most fit early
            part = self._fits(i, options[lo:lo + 8], js, rows)
            ok = np.concatenate([ok, part])
            good = np.flatnonzero(part.all(axis=1))
            if len(good):
                return int(options[lo + good[0]]), js, options, ok
        return None, js, options, ok

    def _place_again(self, j: int) -> int | None:
        """:meth:`_place` for ``j`` against the others only (``j`` counts as scheduled after)."""
        self.done[j] = False
        d = self._place(j)[0]
        self.done[j] = True
        return d

    def _swap(self, i: int, js: np.ndarray, options: np.ndarray, ok: np.ndarray) -> bool:
        """``i`` takes one of the delays with the fewest conflicts (up to ``swap_tries`` of them,
        fewest first); the neighbours in its way are scheduled again after it, or undone."""
        delay, done, unplaced = self.delay, self.done, self.unplaced
        conflicts = (~ok).sum(axis=1)
        for best in np.lexsort((options, conflicts))[: self.swap_tries].tolist():
            others = js[~ok[best]]
            if self.fixed[others].any():  # scheduled by another part: held
                continue
            saved = delay[others].copy(), unplaced[others].copy()
            delay[i], done[i] = options[best], True
            done[others] = False
            placed = True
            for j in others[np.lexsort((others, -self.move[others]))].tolist():
                dj = self._place(j)[0]
                if dj is None:
                    placed = False
                    break
                delay[j], done[j], unplaced[j] = dj, True, False
            done[others] = True
            if placed:
                return True
            delay[others], unplaced[others] = saved
        return False

    # ------------------------------------------------------------------ L-shaped moves
    def _reroute(self, i: int) -> bool:
        """Place the unplaced ``i`` on one of its two L-shaped moves (one joint, then the other), if one fits."""
        s_i, t_i = self.scenario.start[i], self.scenario.target[i]
        rows = self.nb_row[i]
        saved = self.seg_start[i].copy(), self.seg_end[i].copy(), int(self.move[i]), self.clean[rows].copy()
        for c in (np.array([t_i[0], s_i[1]]), np.array([s_i[0], t_i[1]])):
            if not self._route_through(i, c):
                continue
            d = self._place_again(i)
            if d is not None:
                self.delay[i], self.corner[i] = d, c
                return True
            self.seg_start[i], self.seg_end[i], self.move[i], self.clean[rows] = saved
        return False

    def _route_through(self, i: int, c: np.ndarray) -> bool:
        """Set ``i``'s move to run through the corner ``c`` (each leg at full speed), if it ends in time."""
        s_i, t_i = self.scenario.start[i], self.scenario.target[i]
        k1, k2 = (int(k) for k in _full_speed_steps(np.array([s_i, c]), np.array([c, t_i]), self.step_rad))
        if k1 == 0 or k2 == 0 or k1 + k2 > self.horizon:
            return False
        leg1 = straight_path(s_i[None], c[None], self.step_rad, k1)[0]
        leg2 = straight_path(c[None], t_i[None], self.step_rad, self.horizon - k1)[0]
        self._set_path(i, np.concatenate([s_i[None], leg1, leg2]))
        self.move[i] = k1 + k2
        self.clean[self.nb_row[i]] = False
        return True

    def _late_corner(self, i: int) -> np.ndarray | None:
        """The corner of ``i``'s move with its faster joint starting late: the slower joint alone
        first, by as much as it needs more than the faster, then both at full speed, arriving
        together. The straight move (:func:`fiberplan.kinematics.straight_path`) starts both at
        once, the faster arriving first; both take the slower joint's time, but the arm sweeps
        other places. ``None`` when the two joints need about the same time (under a step apart)."""
        s_i, t_i = self.scenario.start[i], self.scenario.target[i]
        steps = np.abs(t_i - s_i) / self.step_rad
        slow = int(np.argmax(steps))
        lag = steps[slow] - steps[1 - slow]
        if lag < 1.0:
            return None
        c = s_i.copy()
        c[slow] += np.sign(t_i[slow] - s_i[slow]) * lag * self.step_rad[slow]
        return c

    def _try_late(self, i: int, d: int) -> int | None:
        """``i`` (not yet scheduled) on its late-joint move (:meth:`_late_corner`) if a delay fits
        it that ends sooner than ``d`` on the straight move; the delay kept (``d`` if not)."""
        c = self._late_corner(i)
        if c is None:
            return d
        rows = self.nb_row[i]
        saved = self.seg_start[i].copy(), self.seg_end[i].copy(), int(self.move[i]), self.clean[rows].copy()
        if self._route_through(i, c):
            late = self._place(i)[0]
            if late is not None and late + int(self.move[i]) < d + saved[2]:
                self.corner[i] = c
                return late
        self.seg_start[i], self.seg_end[i], self.move[i], self.clean[rows] = saved
        return d

    def _set_path(self, i: int, joints: np.ndarray) -> None:
        """``i``'s capsules along ``joints`` (one configuration per step)."""
        ss, se = capsule_segments(self.inst, self.base[i:i + 1], self.orient[i:i + 1], joints[:, None, :])
        self.seg_start[i], self.seg_end[i] = ss[:, 0], se[:, 0]

    # ------------------------------------------------------------------ timed paths
    def _timed_grid(self, i: int) -> _TimedGrid | None:
        """The joint grid of ``i``'s timed search and, per neighbour as scheduled, the cells it
        comes close to and at which layers each of them keeps the pair's floor; ``None`` when
        the start and the target share a cell. ``_repair_timed`` computes it once for all the
        neighbours it leaves out in turn (the others do not change meanwhile)."""
        cell = self.cell_steps * self.step_rad
        s_i, t_i = self.scenario.start[i], self.scenario.target[i]
        lo, shape = JointGrid.through(self.scenario, s_i, cell)
        s = np.round((s_i - lo) / cell)
        g = np.clip(np.round((t_i - lo) / cell), 0, np.array(shape) - 1)
        s_cell, g_cell = (int(s[0]), int(s[1])), (int(g[0]), int(g[1]))
        if s_cell == g_cell:
            return None
        grid = JointGrid(self.scenario, i, cell, lo, shape, exact={s_cell: s_i, g_cell: t_i})
        c_start, c_end = grid.seg_start, grid.seg_end  # (cells, C, 2)
        # Bounding boxes of i's capsule segments at every cell, for a quick lower bound.
        box_lo = np.minimum(c_start, c_end).min(axis=1)
        box_hi = np.maximum(c_start, c_end).max(axis=1)
        blocks = []
        for j, row in zip(self.nb[i].tolist(), self.nb_row[i].tolist(), strict=True):
            at = np.minimum(np.maximum(self.samples - self.delay[j], 0), self.move[j])  # j holds its target after its move
            used, inv = np.unique(at, return_inverse=True)
            j_start, j_end = self.seg_start[j, used], self.seg_end[j, used]  # (U, C, 2)
            # Cells whose box keeps clear of the box around all of j's capsules as scheduled.
            j_lo, j_hi = np.minimum(j_start, j_end).min(axis=(0, 1)), np.maximum(j_start, j_end).max(axis=(0, 1))
            gap = np.maximum(np.maximum(j_lo - box_hi, box_lo - j_hi), 0.0)
            close = np.flatnonzero(np.hypot(gap[:, 0], gap[:, 1]) - self.combo_radii.max() < self.floor[row])
            if len(close) == 0:
                continue
            if self.inst.polygons:
                clear = combo_clearances(self.inst, c_start[close][:, None], c_end[close][:, None], j_start[None], j_end[None],
                                         smallest=True, exact_below=float(self.floor[row]))
            else:
                clear = smallest_clearance(self.inst, c_start, c_end, close[:, None], j_start, j_end, np.arange(len(used))[None, :])
            ok = clear >= self.floor[row]
            ok = ok[:, inv]  # (close, samples)
            blocks.append((j, close, ok[:, self.window].all(axis=2)))
        return _TimedGrid(grid, s_cell, g_cell, blocks)

    def _search_timed(self, i: int, ignore: int = -1, timed_grid: _TimedGrid | None = None) -> bool:
        """Place the unplaced ``i`` on a timed path through a grid of its joint configurations, if one fits.

        A cell is ``cell_steps`` full steps per joint, so every move to a neighbouring cell takes
        one layer of ``cell_steps`` steps. A cell is free at a layer when its clearance to every
        neighbour, as scheduled, at every step within half a layer is at least the pair's floor.
        Between those steps ``i`` is within half a cell of the cell, unchecked, as the greedy
        pass leaves the motion between its samples unchecked: the schedule only orders the
        moves, the QPs and the safety layer keep the real distances. Adding half a cell's
        motion to the floor (0.25 mm on DESI) measured worse: DESI N = 500 seeds 0-99,
        makespan <= 1.2 x bound on 86 seeds, against 93 without. The neighbour ``ignore`` is
        left out (``_repair_timed``); ``timed_grid`` is ``_timed_grid(i)`` if already computed.
        """
        tg = timed_grid if timed_grid is not None else self._timed_grid(i)
        if tg is None:
            return False
        cells = space_time_path(self._free_cells(tg, ignore), tg.s_cell, tg.g_cell)
        if cells is None:
            return False
        self._take_timed(i, cells, tg.grid.coords)
        return True

    def _save(self, ks: list[int]) -> list[_Placement]:
        return [
            _Placement(k, self.seg_start[k].copy(), self.seg_end[k].copy(), int(self.delay[k]), int(self.move[k]), self.corner[k].copy(),
                       self.timed.get(k), bool(self.unplaced[k]), self.clean[self.nb_row[k]].copy())
            for k in ks
        ]

    def _restore(self, saved: list[_Placement]) -> None:
        for p in saved:
            k = p.k
            self.seg_start[k], self.seg_end[k], self.delay[k], self.move[k] = p.seg_start, p.seg_end, p.delay, p.move
            self.corner[k], self.unplaced[k], self.clean[self.nb_row[k]] = p.corner, p.unplaced, p.clean
            if p.timed is None:
                self.timed.pop(k, None)
            else:
                self.timed[k] = p.timed

    def _repair_timed(self, i: int) -> bool:
        """Place the unplaced ``i`` first: a placed neighbour leaves the schedule, ``i`` searches
        around the others, and the neighbour is placed again after it; undone if it fits nowhere."""
        tg = None
        nb = self.nb[i]
        for j in nb[np.lexsort((nb, -self.move[nb]))].tolist():
            if self.unplaced[j] or self.fixed[j]:
                continue
            if tg is None:
                tg = self._timed_grid(i)
                if tg is None:
                    return False
            saved = self._save([i, j])
            if self._search_timed(i, ignore=j, timed_grid=tg):
                # j again, on its straight move first, against everyone as now scheduled.
                self._set_path(j, self.path[j])
                self.move[j], self.corner[j] = self.straight_move[j], np.nan
                self.timed.pop(j, None)
                d = self._place_again(j)
                if d is not None:
                    self.delay[j] = d
                    return True
                if (self.l_paths and self._reroute(j)) or self._search_timed(j):
                    return True
            self._restore(saved)
        return False

    def _free_cells(self, tg: _TimedGrid, ignore: int = -1, placed_only: bool = False) -> np.ndarray:
        """``(L + 1, A, B)``: the cells of ``tg``'s positioner free at each layer against its
        neighbours as scheduled, but ``ignore`` (with ``placed_only``, unplaced ones left out too:
        they conflict anyway)."""
        shape = tg.grid.shape
        free = np.ones((int(np.prod(shape)), self.n_layers + 1), dtype=bool)
        for j, close, ok in tg.blocks:
            if j != ignore and not (placed_only and self.unplaced[j]):
                free[close] &= ok
        # At layer 0 the start keeps its floor by definition; a departure at once is checked
        # at the next cell, over the steps within half a layer of layer 1.
        free[np.ravel_multi_index(tg.s_cell, shape), 0] = True
        return free.T.reshape((self.n_layers + 1, *shape))

    def _repair_pair(self, i: int) -> bool:
        """Place the unplaced ``i`` together with a placed neighbour ``j`` (longest move first):
        both search their timed paths at once, over the pairs of their grid cells x time
        (:func:`pair_space_time_path`), each around everyone else as scheduled and the two apart
        by their pair's floor. For two whose ways cross where neither's start nor target leaves
        the other room (one must step aside while the other passes: a fold's long alpha turn beside
        a neighbour folding in its way), which the single searches, one around the other's fixed
        move, cannot find. Undone if no neighbour gives a pair of paths."""
        nb = self.nb[i]
        tg_i = None
        for j, row in sorted(zip(nb.tolist(), self.nb_row[i].tolist(), strict=True), key=lambda p: (-int(self.move[p[0]]), p[0])):
            if self.unplaced[j] or self.fixed[j]:
                continue
            tg_i = self._timed_grid(i) if tg_i is None else tg_i
            if tg_i is None:
                return False
            saved = self._save([i, j])
            tg_j = self._timed_grid(j)
            if tg_j is None:
                self._restore(saved)
                continue
            gi, gj = tg_i.grid, tg_j.grid
            ia, jb = np.arange(len(gi.configs))[:, None], np.arange(len(gj.configs))[None, :]
            if self.inst.polygons:
                c = combo_clearances(self.inst, gi.seg_start[:, None], gi.seg_end[:, None], gj.seg_start[None], gj.seg_end[None],
                                     smallest=True, exact_below=float(self.floor[row]))
            else:
                c = smallest_clearance(self.inst, gi.seg_start, gi.seg_end, ia, gj.seg_start, gj.seg_end, jb)
            together = (c >= self.floor[row]).reshape(*gi.shape, *gj.shape)
            states = pair_space_time_path(self._free_cells(tg_i, j, placed_only=True), self._free_cells(tg_j, i, placed_only=True),
                                          together, tg_i.s_cell + tg_j.s_cell, tg_i.g_cell + tg_j.g_cell)
            if states is None:
                self._restore(saved)
                continue
            for k, tg, cells in ((i, tg_i, states[:, :2]), (j, tg_j, states[:, 2:])):
                last = len(cells) - 1
                while last > 0 and np.all(cells[last - 1] == cells[-1]):  # its stay at the goal
                    last -= 1
                self._take_timed(k, cells[: last + 1], tg.grid.coords)
                self.corner[k] = np.nan  # (an L-shaped move it had is replaced by the timed path)
            return True
        return False

    def _take_timed(self, i: int, cells: np.ndarray, coords: np.ndarray) -> None:
        """``i`` on the timed path through ``cells`` (one per layer) of its grid (``coords``)."""
        waypoints, depart = timed_waypoints(cells, coords, self.cell_steps)
        # i's configuration at every step, for the positioners searched after it.
        at_layers = coords[cells[:, 0], cells[:, 1]]
        steps = np.arange(self.horizon + 1)
        self._set_path(i, np.stack([np.interp(steps, np.arange(len(cells)) * self.cell_steps, at_layers[:, k]) for k in range(2)], axis=1))
        self.delay[i], self.move[i] = 0, (len(cells) - 1) * self.cell_steps
        self.clean[self.nb_row[i]] = False  # _place must check i's pairs even at no delay
        self.timed[i] = (waypoints, depart)


SPLIT_ABOVE = 10_000
"""A field of more positioners is scheduled in two halves at once (:func:`start_schedule`);
up to this many (every benchmark set but the scaling one), whole as before."""


def start_schedule(
    scenario: Scenario, step_rad: np.ndarray, margin_mm: float, delay_steps: int = 4, slack: float = 1.2, stride: int = 2,
    max_options: int = 64, swap_tries: int = 1, l_paths: bool = False, space_time: bool = False, cell_steps: int = 2,
    repair: bool = False, pair_paths: bool = False,
) -> StartSchedule:
    """Start delays such that the delayed moves keep their margins pairwise (:class:`StartScheduler`).

    A field of more than :data:`SPLIT_ABOVE` positioners is scheduled in parts
    (:func:`_split_schedule`): a strip across its middle first, then the two halves beside it at
    once (one in a forked process where there is a second core), each against the strip as
    scheduled. Every pair is still checked, by whichever of its two is placed later; the order
    differs from the whole field's only in that the strip goes first.

    Returns:
        The delays; ``unplaced`` lists the positioners no delay fitted (delay 0); ``corner``
        the corners of the L-shaped moves placed; ``timed`` the waypoints and departure steps
        of the timed paths placed (their delay is their first departure).
    """
    args = (step_rad, margin_mm, delay_steps, slack, stride, max_options, swap_tries, l_paths, space_time, cell_steps, repair)
    if scenario.n_positioners > SPLIT_ABOVE and len(scenario.pairs):
        return _split_schedule(scenario, args, pair_paths)
    return StartScheduler(scenario, *args, pair_paths=pair_paths).run()


def _split_schedule(scenario: Scenario, args: tuple[Any, ...], pair_paths: bool = False) -> StartSchedule:
    """:func:`start_schedule` of a large field in three parts. The cut runs across the field at
    its median x; the strip holds every positioner within half the longest pair distance of it,
    so no pair joins the two halves beside it. The strip is scheduled first, alone; then each half
    with the strip's positioners it pairs with, those held as the strip scheduled them
    (:class:`_Fixed`). The halves share nothing but the strip, so they are scheduled at once
    (:func:`fiberplan._fork.both`): the same schedule with or without a second process."""
    step_rad, slack = args[0], args[3]
    n, pairs = scenario.n_positioners, scenario.pairs
    horizon = int(np.ceil(slack * _full_speed_steps(scenario.start, scenario.target, step_rad).max()))
    x = scenario.base_xy[:, 0]
    reach = float(np.max(np.linalg.norm(scenario.base_xy[pairs[:, 0]] - scenario.base_xy[pairs[:, 1]], axis=1)))
    cut = float(np.median(x))
    in_strip = np.abs(x - cut) <= 0.5 * reach
    strip = np.flatnonzero(in_strip)
    first = StartScheduler(_Part.of(scenario, strip), *args, horizon=horizon, pair_paths=pair_paths)
    strip_schedule = first.run()
    at = np.full(n, -1, dtype=np.int64)
    at[strip] = np.arange(len(strip))

    def half(side: np.ndarray) -> tuple[np.ndarray, StartSchedule, np.ndarray]:
        near = np.zeros(n, dtype=bool)
        touching = side[pairs[:, 0]] | side[pairs[:, 1]]
        near[pairs[touching].ravel()] = True
        rows = np.flatnonzero(side | (near & in_strip))
        held = in_strip[rows]
        k = at[rows[held]]
        fixed = _Fixed(np.flatnonzero(held), first.delay[k], first.move[k], first.seg_start[k], first.seg_end[k])
        return rows, StartScheduler(_Part.of(scenario, rows), *args, horizon=horizon, fixed=fixed,
                                         pair_paths=pair_paths).run(), held

    left, right, _ = _fork.both(lambda: half(x < cut - 0.5 * reach), lambda: half(x > cut + 0.5 * reach))
    delay = np.zeros(n, dtype=np.int64)
    unplaced = np.zeros(n, dtype=bool)
    corner = np.full((n, 2), np.nan)
    timed: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    swaps = 0
    for rows, schedule, held in ((strip, strip_schedule, np.zeros(len(strip), dtype=bool)), left, right):
        own = ~held
        delay[rows[own]] = schedule.delay_steps[own]
        unplaced[rows[schedule.unplaced]] = True
        corner[rows[own]] = schedule.corner[own]
        timed.update({int(rows[k]): path for k, path in schedule.timed.items()})
        swaps += schedule.swaps
    return StartSchedule(delay, np.flatnonzero(unplaced), swaps, corner, timed)
