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
again after it (a delay, an L-shaped move or a timed path), or both are restored.

The schedule only sets when each positioner's reference starts: collision avoidance stays
with the QPs and the safety layer. Clearances are checked every ``stride`` steps. See
``formulations/mpc.md`` (Start schedule).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fiberplan.geometry import capsule_segments, capsule_tables, combo_clearances
from fiberplan.kinematics import straight_path
from fiberplan.layout import neighbour_lists
from fiberplan.planners.mpc_detour import dilate
from fiberplan.scenario import Scenario

__all__ = ["StartSchedule", "space_time_path", "start_schedule", "timed_waypoints"]


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
    n_layers = free.shape[0]
    if not free[0][start]:
        return None
    reach = np.zeros_like(free)
    reach[0][start] = True
    # Layers from which the goal stays free to the end.
    stay = np.flip(np.logical_and.accumulate(np.flip(free[:, goal[0], goal[1]])))
    if not stay.any():
        return None
    arrive = 0
    while not (reach[arrive][goal] and stay[arrive]):
        arrive += 1
        if arrive == n_layers:
            return None
        reach[arrive] = dilate(reach[arrive - 1]) & free[arrive]
        if not reach[arrive].any():
            return None
    moves = np.array([(da, db) for da in (-1, 0, 1) for db in (-1, 0, 1)])
    cells = [np.array(goal)]
    s = np.array(start)
    for layer in range(arrive, 0, -1):
        cand = cells[-1] + moves
        inside = np.all((cand >= 0) & (cand < free.shape[1:]), axis=1)
        cand = cand[inside]
        cand = cand[reach[layer - 1][cand[:, 0], cand[:, 1]]]
        cells.append(cand[np.argmin(np.max(np.abs(cand - s), axis=1))])
    return np.array(cells[::-1])


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


def start_schedule(
    scenario: Scenario, step_rad: np.ndarray, margin_mm: float, delay_steps: int = 4, slack: float = 1.2, stride: int = 2,
    max_options: int = 64, swap_tries: int = 1, l_paths: bool = False, space_time: bool = False, cell_steps: int = 2,
    repair: bool = False,
) -> StartSchedule:
    """Start delays such that the delayed moves keep their margins pairwise (greedy).

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

    Returns:
        The delays; ``unplaced`` lists the positioners no delay fitted (delay 0); ``corner``
        the corners of the L-shaped moves placed; ``timed`` the waypoints and departure steps
        of the timed paths placed (their delay is their first departure).
    """
    inst = scenario.instrument
    n = scenario.n_positioners
    pairs = scenario.pairs
    delay = np.zeros(n, dtype=np.int64)
    if n == 0 or len(pairs) == 0:
        return StartSchedule(delay, np.zeros(0, dtype=np.int64), 0, np.full((n, 2), np.nan))
    move = _full_speed_steps(scenario.start, scenario.target, step_rad)
    horizon = int(np.ceil(slack * move.max()))
    # Joints of every straight full-speed move at steps 0..horizon.
    path = np.concatenate([scenario.start[:, None], straight_path(scenario.start, scenario.target, step_rad, horizon)], axis=1)
    times = np.unique(np.append(np.arange(0, horizon + 1, stride), horizon))
    base, orient = scenario.base_xy, scenario.orient
    # Capsule segments of every move at every step, computed once: (N, steps, C, 2) each.
    seg_start, seg_end = capsule_segments(inst, base, orient, np.swapaxes(path, 0, 1))
    seg_start, seg_end = np.ascontiguousarray(np.swapaxes(seg_start, 0, 1)), np.ascontiguousarray(np.swapaxes(seg_end, 0, 1))
    combo_radii = capsule_tables(inst)[4]

    def moving_min(i: np.ndarray, ti: np.ndarray, j: np.ndarray, tj: np.ndarray) -> np.ndarray:
        """Clearance of ``i`` after ``ti`` steps of its move to ``j`` after ``tj`` (index arrays, broadcast)."""
        return combo_clearances(inst, seg_start[i, ti], seg_end[i, ti], seg_start[j, tj], seg_end[j, tj], smallest=True)

    a, b = pairs[:, 0], pairs[:, 1]
    # Step 0 is the start and the last step the target of every move.
    floor = np.minimum(margin_mm, 0.9 * np.minimum(moving_min(a, 0, b, 0), moving_min(a, horizon, b, horizon)))
    # Pairs whose undelayed moves keep their margin need no check while both start at once.
    clean = moving_min(a[:, None], times[None, :], b[:, None], times[None, :]).min(axis=1) >= floor
    nb, nb_row = neighbour_lists(pairs, n)

    def fits(i: int, delays: np.ndarray, js: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(D, J): whether ``i`` delayed by each of ``delays`` keeps its margin to each ``j``."""
        # Only while one of them moves: before and after, both hold (the ends are sampled).
        t_lo = min(int(delays.min()), int(delay[js].min()))
        t_hi = max(int(delays.max()) + int(move[i]), int((delay[js] + move[js]).max()))
        t = np.unique(np.concatenate([times[(times >= t_lo) & (times <= t_hi)], [t_lo, min(t_hi, horizon)]]))
        ti = np.clip(t[None, None, :] - delays[:, None, None], 0, horizon)  # (D, 1, K)
        tj = np.clip(t[None, None, :] - delay[js][None, :, None], 0, horizon)  # (1, J, K)
        c = moving_min(np.int64(i), ti, js[None, :, None], tj).min(axis=2)  # (D, J)
        return c >= floor[rows][None, :]

    done = np.zeros(n, dtype=bool)

    def place(i: int) -> tuple[int | None, np.ndarray, np.ndarray, np.ndarray]:
        """Smallest fitting delay of ``i`` against the scheduled neighbours, else ``None``."""
        sel = done[nb[i]]
        js, rows = nb[i][sel], nb_row[i][sel]
        # No delay: only pairs with a delayed neighbour or a conflict between the undelayed
        # moves need a check.
        check = (delay[js] != 0) | ~clean[rows]
        if not np.any(check) or fits(i, np.zeros(1, dtype=np.int64), js[check], rows[check]).all():
            return 0, js, np.zeros(0, dtype=np.int64), np.zeros((0, 0), dtype=bool)
        room = max(0, horizon - int(move[i]))
        options = np.arange(0, room + 1, max(delay_steps, int(np.ceil(room / max_options))))
        ok = np.zeros((0, len(js)), dtype=bool)
        for lo in range(0, len(options), 8):  # a few delays at a time: most fit early
            part = fits(i, options[lo:lo + 8], js, rows)
            ok = np.concatenate([ok, part])
            good = np.flatnonzero(part.all(axis=1))
            if len(good):
                return int(options[lo + good[0]]), js, options, ok
        return None, js, options, ok

    corner = np.full((n, 2), np.nan)

    def reroute(i: int) -> bool:
        """Place the unplaced ``i`` on one of its two L-shaped moves (one joint, then the other), if one fits."""
        s_i, t_i = scenario.start[i], scenario.target[i]
        saved = seg_start[i].copy(), seg_end[i].copy(), int(move[i]), clean[nb_row[i]].copy()
        for c in (np.array([t_i[0], s_i[1]]), np.array([s_i[0], t_i[1]])):
            k1, k2 = (int(k) for k in _full_speed_steps(np.array([s_i, c]), np.array([c, t_i]), step_rad))
            if k1 == 0 or k2 == 0 or k1 + k2 > horizon:
                continue
            leg1 = straight_path(s_i[None], c[None], step_rad, k1)[0]
            leg2 = straight_path(c[None], t_i[None], step_rad, horizon - k1)[0]
            p_i = np.concatenate([s_i[None], leg1, leg2])
            ss, se = capsule_segments(inst, base[i:i + 1], orient[i:i + 1], p_i[:, None, :])
            seg_start[i], seg_end[i] = ss[:, 0], se[:, 0]
            move[i] = k1 + k2
            clean[nb_row[i]] = False
            done[i] = False  # place() checks against the others only
            d = place(i)[0]
            done[i] = True
            if d is not None:
                delay[i], corner[i] = d, c
                return True
            seg_start[i], seg_end[i], move[i], clean[nb_row[i]] = saved
        return False

    timed: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    lim = inst.limits_rad
    n_layers = horizon // cell_steps
    # Every layer is checked at each step within half a layer of it.
    samples = np.arange(0, n_layers * cell_steps + cell_steps // 2 + 1)
    offsets = np.arange(-(cell_steps // 2), cell_steps // 2 + 1)
    window = np.clip(np.arange(n_layers + 1)[:, None] * cell_steps + offsets[None, :], 0, len(samples) - 1)

    def timed_grid(i: int) -> tuple | None:
        """The joint grid of ``i``'s timed search and, per neighbour as scheduled, the cells it
        comes close to and at which layers each of them keeps the pair's floor; ``None`` when
        the start and the target share a cell. ``repair_timed`` computes it once for all the
        neighbours it leaves out in turn (the others do not change meanwhile)."""
        cell = cell_steps * step_rad
        s_i, t_i = scenario.start[i], scenario.target[i]
        lo = s_i - np.floor((s_i - lim[:, 0]) / cell + 1e-9) * cell
        shape = tuple(int(v) for v in np.floor((lim[:, 1] - lo) / cell + 1e-9) + 1)
        axes = [lo[k] + np.arange(shape[k]) * cell[k] for k in range(2)]
        coords = np.stack(np.meshgrid(axes[0], axes[1], indexing="ij"), axis=-1)
        s_cell = tuple(int(v) for v in np.round((s_i - lo) / cell))
        g_cell = tuple(int(v) for v in np.clip(np.round((t_i - lo) / cell), 0, np.array(shape) - 1))
        if s_cell == g_cell:
            return None
        coords[s_cell], coords[g_cell] = s_i, t_i
        flat = coords.reshape(-1, 2)
        c_start, c_end = capsule_segments(inst, base[i:i + 1], orient[i:i + 1], flat[:, None, :])
        c_start, c_end = c_start[:, 0], c_end[:, 0]  # (cells, C, 2)
        # Bounding boxes of i's capsule segments at every cell, for a quick lower bound.
        box_lo = np.minimum(c_start, c_end).min(axis=1)
        box_hi = np.maximum(c_start, c_end).max(axis=1)
        blocks = []
        for j, row in zip(nb[i].tolist(), nb_row[i].tolist(), strict=True):
            at = np.clip(samples - delay[j], 0, move[j])  # j holds its target after its move
            used, inv = np.unique(at, return_inverse=True)
            j_start, j_end = seg_start[j, used], seg_end[j, used]  # (U, C, 2)
            # Cells whose box keeps clear of the box around all of j's capsules as scheduled.
            j_lo, j_hi = np.minimum(j_start, j_end).min(axis=(0, 1)), np.maximum(j_start, j_end).max(axis=(0, 1))
            gap = np.maximum(np.maximum(j_lo - box_hi, box_lo - j_hi), 0.0)
            close = np.flatnonzero(np.hypot(gap[:, 0], gap[:, 1]) - combo_radii.max() < floor[row])
            if len(close) == 0:
                continue
            ok = combo_clearances(inst, c_start[close][:, None], c_end[close][:, None], j_start[None], j_end[None], smallest=True) >= floor[row]
            ok = ok[:, inv]  # (close, samples)
            blocks.append((j, close, ok[:, window].all(axis=2)))
        return shape, coords, s_cell, g_cell, blocks

    def search_timed(i: int, ignore: int = -1, grid: tuple | None = None) -> bool:
        """Place the unplaced ``i`` on a timed path through a grid of its joint configurations, if one fits.

        A cell is ``cell_steps`` full steps per joint, so every move to a neighbouring cell takes
        one layer of ``cell_steps`` steps. A cell is free at a layer when its clearance to every
        neighbour, as scheduled, at every step within half a layer is at least the pair's floor.
        Between those steps ``i`` is within half a cell of the cell, unchecked, as the greedy
        pass leaves the motion between its samples unchecked: the schedule only orders the
        moves, the QPs and the safety layer keep the real distances. Adding half a cell's
        motion to the floor (0.25 mm on DESI) measured worse: DESI N = 500 seeds 0-99,
        makespan <= 1.2 x bound on 86 seeds, against 93 without. The neighbour ``ignore`` is
        left out (``repair_timed``); ``grid`` is ``timed_grid(i)`` if already computed.
        """
        grid = grid if grid is not None else timed_grid(i)
        if grid is None:
            return False
        shape, coords, s_cell, g_cell, blocks = grid
        free = np.ones((int(np.prod(shape)), n_layers + 1), dtype=bool)
        for j, close, ok in blocks:
            if j != ignore:
                free[close] &= ok
        # At layer 0 the start keeps its floor by definition; a departure at once is checked
        # at the next cell, over the steps within half a layer of layer 1.
        free[np.ravel_multi_index(s_cell, shape), 0] = True
        cells = space_time_path(free.T.reshape((n_layers + 1, *shape)), s_cell, g_cell)
        if cells is None:
            return False
        waypoints, depart = timed_waypoints(cells, coords, cell_steps)
        # i's configuration at every step, for the positioners searched after it.
        at_layers = coords[cells[:, 0], cells[:, 1]]
        steps = np.arange(horizon + 1)
        p_i = np.stack([np.interp(steps, np.arange(len(cells)) * cell_steps, at_layers[:, k]) for k in range(2)], axis=1)
        ss, se = capsule_segments(inst, base[i:i + 1], orient[i:i + 1], p_i[:, None, :])
        seg_start[i], seg_end[i] = ss[:, 0], se[:, 0]
        delay[i], move[i] = 0, (len(cells) - 1) * cell_steps
        clean[nb_row[i]] = False  # place() must check i's pairs even at no delay
        timed[i] = (waypoints, depart)
        return True

    straight_move = move.copy()

    def state(ks: list[int]) -> list[tuple]:
        return [(k, seg_start[k].copy(), seg_end[k].copy(), int(delay[k]), int(move[k]), corner[k].copy(), timed.get(k),
                 bool(unplaced[k]), clean[nb_row[k]].copy()) for k in ks]

    def restore(saved: list[tuple]) -> None:
        for k, ss, se, d, m, c, t, u, cl in saved:
            seg_start[k], seg_end[k], delay[k], move[k], corner[k], unplaced[k], clean[nb_row[k]] = ss, se, d, m, c, u, cl
            if t is None:
                timed.pop(k, None)
            else:
                timed[k] = t

    def repair_timed(i: int) -> bool:
        """Place the unplaced ``i`` first: a placed neighbour leaves the schedule, ``i`` searches
        around the others, and the neighbour is placed again after it; undone if it fits nowhere."""
        grid = None
        for j in nb[i][np.lexsort((nb[i], -move[nb[i]]))].tolist():
            if unplaced[j]:
                continue
            if grid is None:
                grid = timed_grid(i)
                if grid is None:
                    return False
            saved = state([i, j])
            if search_timed(i, ignore=j, grid=grid):
                # j again, on its straight move first, against everyone as now scheduled.
                ss, se = capsule_segments(inst, base[j:j + 1], orient[j:j + 1], path[j][:, None, :])
                seg_start[j], seg_end[j], move[j], corner[j] = ss[:, 0], se[:, 0], straight_move[j], np.nan
                timed.pop(j, None)
                done[j] = False
                d = place(j)[0]
                done[j] = True
                if d is not None:
                    delay[j] = d
                    return True
                if (l_paths and reroute(j)) or search_timed(j):
                    return True
            restore(saved)
        return False

    order = np.lexsort((np.arange(n), -move))
    unplaced = np.zeros(n, dtype=bool)

    def unplaced_longest_first() -> list[int]:
        who = np.flatnonzero(unplaced)
        return who[np.lexsort((who, -move[who]))].tolist()

    swaps = 0
    for i in order.tolist():
        d, js, options, ok = place(i)
        if d is None:
            # Swap: i takes one of the delays with the fewest conflicts (up to swap_tries of
            # them, fewest first); those neighbours are scheduled again after it.
            conflicts = (~ok).sum(axis=1)
            placed = False
            for best in np.lexsort((options, conflicts))[:swap_tries].tolist():
                others = js[~ok[best]]
                saved = delay[others].copy(), unplaced[others].copy()
                delay[i], done[i] = options[best], True
                done[others] = False
                placed = True
                for j in others[np.lexsort((others, -move[others]))].tolist():
                    dj = place(j)[0]
                    if dj is None:
                        placed = False
                        break
                    delay[j], done[j], unplaced[j] = dj, True, False
                done[others] = True
                if placed:
                    break
                delay[others], unplaced[others] = saved
            if placed:
                swaps += 1
                continue
            d = 0
            unplaced[i] = True
        delay[i], done[i] = d, True
    if l_paths:
        # Unplaced positioners try the two L-shaped moves, which sweep other places than the
        # straight one, against every neighbour as scheduled.
        for i in unplaced_longest_first():
            if reroute(i):
                unplaced[i] = False
    if space_time:
        for i in unplaced_longest_first():
            if search_timed(i):
                unplaced[i] = False
        if repair:
            for i in unplaced_longest_first():
                if repair_timed(i):
                    unplaced[i] = False
    for i, (_, depart) in timed.items():
        delay[i] = depart[0]
    return StartSchedule(delay, np.flatnonzero(unplaced), swaps, corner, timed)
