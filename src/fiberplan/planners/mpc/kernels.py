"""Compiled loops of the ``mpc`` (numba), each the numpy form it replaces operation for
operation, so that no trajectory changes (``tests/test_mpc_kernels.py`` compares them bit for
bit with those forms). The control loop's, at every step:

- :func:`straight_reference`: :func:`fiberplan.kinematics.straight_path` into a given array;
- :func:`time_to_go`: ``np.max(np.abs(goal - q) / speeds, axis=1)``;
- :func:`holds_at_goal`: ``np.all(q == goal, axis=1) & np.all(plan == q[:, None, :], axis=(1, 2))``;
- :func:`route_paths`: :func:`fiberplan.planners.mpc.routes.route_path` of many routes at once.

At 50,000 DESI positioners these numpy expressions cost 1-6 ms each per control step, over
(N, H, 2) temporaries with broadcast bounds; the loops take a tenth of that. And the start
schedule's:

- :func:`space_time_cells`: the search of :func:`fiberplan.planners.mpc.schedule.space_time_path`
  (a dilation per time layer, then the path back), a third of the timed paths' search time in numpy.

Compiled without ``fastmath``: each clamp is a comparison, each sum and quotient one correctly
rounded operation, as in numpy.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, error_model="numpy", nogil=True)
def straight_reference(q: np.ndarray, goal: np.ndarray, step_rad: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[:] = straight_path(q, goal, step_rad, out.shape[1])``: every joint at full speed
    toward its goal, stopping there, ``r(k) = q + clip(g - q, -k w h, k w h)``."""
    n, n_steps = out.shape[0], out.shape[1]
    for i in range(n):
        for j in range(2):
            d = goal[i, j] - q[i, j]
            for k in range(n_steps):
                lim = (k + 1) * step_rad[j]
                out[i, k, j] = q[i, j] + min(max(d, -lim), lim)


@numba.njit(cache=True, error_model="numpy", nogil=True)
def time_to_go(q: np.ndarray, goal: np.ndarray, speeds: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """The straight move's time of each positioner, the slower joint's: ``(N,)``."""
    out = np.empty(q.shape[0])
    for i in range(q.shape[0]):
        t0 = abs(goal[i, 0] - q[i, 0]) / speeds[0]
        t1 = abs(goal[i, 1] - q[i, 1]) / speeds[1]
        out[i] = t1 if (t1 > t0 or t1 != t1) else t0  # a NaN kept, as np.max keeps it
    return out


@numba.njit(cache=True, error_model="numpy", nogil=True)
def holds_at_goal(q: np.ndarray, goal: np.ndarray, plan: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Whether each positioner is at its goal with a published plan that holds it there: ``(N,)``."""
    n, n_steps = plan.shape[0], plan.shape[1]
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if q[i, 0] != goal[i, 0] or q[i, 1] != goal[i, 1]:
            continue
        still = True
        for k in range(n_steps):
            if plan[i, k, 0] != q[i, 0] or plan[i, k, 1] != q[i, 1]:
                still = False
                break
        out[i] = still
    return out


@numba.njit(cache=True, error_model="numpy", nogil=True)
def route_paths(q: np.ndarray, who: np.ndarray, pos: np.ndarray, offsets: np.ndarray, way: np.ndarray, depart: np.ndarray,
                timed: np.ndarray, skip: np.ndarray, step_rad: np.ndarray, pass_rad: np.ndarray, step: int,
                out: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`~fiberplan.planners.mpc.routes.route_path` of every route ``r`` (waypoints
    ``way[offsets[r]:offsets[r + 1]]``, departure steps ``depart`` likewise where ``timed[r]``,
    heading for waypoint ``pos[r]``) whose positioner ``who[r]`` is not ``skip``-ped, written to
    ``out[who[r]]`` (``(N, H, 2)``); ``pass_rad`` is ``ROUTE_PASS * step_rad``."""
    n_steps = out.shape[1]
    s0, s1 = step_rad[0], step_rad[1]
    pass0, pass1 = pass_rad[0], pass_rad[1]
    for r in range(len(who)):
        i = who[r]
        if skip[i]:
            continue
        base = offsets[r]
        last = offsets[r + 1] - base - 1
        m = pos[r]
        p0, p1 = q[i, 0], q[i, 1]
        for k in range(n_steps):
            while (m < last and abs(p0 - way[base + m, 0]) <= pass0 and abs(p1 - way[base + m, 1]) <= pass1
                   and (not timed[r] or step + k >= depart[base + m + 1])):
                m += 1
            if not timed[r] or step + k >= depart[base + m]:
                p0 = p0 + min(max(way[base + m, 0] - p0, -s0), s0)
                p1 = p1 + min(max(way[base + m, 1] - p1, -s1), s1)
            out[i, k, 0] = p0
            out[i, k, 1] = p1


@numba.njit(cache=True, error_model="numpy", nogil=True)
def space_time_cells(free: np.ndarray, s0: int, s1: int, g0: int, g1: int) -> np.ndarray:  # pragma: no cover - compiled
    """The cells ``(l* + 1, 2)`` of :func:`~fiberplan.planners.mpc.schedule.space_time_path`
    from cell ``(s0, s1)`` to ``(g0, g1)`` through ``free`` ``(L + 1, A, B)``; ``(0, 2)`` if
    there is none. Layer by layer, the cells reachable are the free ones within one move (the
    3 x 3 box) of one reachable at the layer before; back from the goal, each layer's cell is
    the first, in the move order ``(-1, -1), (-1, 0), ..., (1, 1)``, of the reachable ones
    nearest the start (Chebyshev). Each layer looks only within one move of the box of the cells
    reached at the layer before."""
    n_layers, n_a, n_b = free.shape
    none = np.zeros((0, 2), dtype=np.int64)
    if not free[0, s0, s1]:
        return none
    stay = np.zeros(n_layers, dtype=np.bool_)  # layers from which the goal stays free to the end
    held = True
    for layer in range(n_layers - 1, -1, -1):
        held = held and free[layer, g0, g1]
        stay[layer] = held
    if not stay.any():
        return none
    reach = np.zeros((n_layers, n_a, n_b), dtype=np.bool_)
    reach[0, s0, s1] = True
    lo_a, hi_a, lo_b, hi_b = s0, s0, s1, s1  # the box of the cells reached at the last layer
    rows = np.zeros(n_b, dtype=np.bool_)
    arrive = 0
    while not (reach[arrive, g0, g1] and stay[arrive]):
        arrive += 1
        if arrive == n_layers:
            return none
        found = False
        box = (n_a, -1, n_b, -1)
        a_lo, a_hi, b_lo, b_hi = max(lo_a - 1, 0), min(hi_a + 2, n_a), max(lo_b - 1, 0), min(hi_b + 2, n_b)
        prev, now, here = reach[arrive - 1], reach[arrive], free[arrive]
        for a in range(a_lo, a_hi):
            # The previous layer's rows a - 1 .. a + 1, or-ed: one move along alpha.
            for b in range(b_lo, b_hi):
                rows[b] = prev[a, b] or (a > 0 and prev[a - 1, b]) or (a + 1 < n_a and prev[a + 1, b])
            for b in range(b_lo, b_hi):
                if here[a, b] and (rows[b] or (b > b_lo and rows[b - 1]) or (b + 1 < b_hi and rows[b + 1])):
                    now[a, b] = True
                    found = True
                    box = (min(box[0], a), max(box[1], a), min(box[2], b), max(box[3], b))
        if not found:
            return none
        lo_a, hi_a, lo_b, hi_b = box
    cells = np.empty((arrive + 1, 2), dtype=np.int64)
    cells[arrive, 0], cells[arrive, 1] = g0, g1
    for layer in range(arrive, 0, -1):
        c0, c1 = cells[layer, 0], cells[layer, 1]
        best_a, best_b, best_d = -1, -1, np.iinfo(np.int64).max
        for da in range(-1, 2):
            for db in range(-1, 2):
                a, b = c0 + da, c1 + db
                if 0 <= a < n_a and 0 <= b < n_b and reach[layer - 1, a, b]:
                    d = max(abs(a - s0), abs(b - s1))
                    if d < best_d:
                        best_a, best_b, best_d = a, b, d
        cells[layer - 1, 0], cells[layer - 1, 1] = best_a, best_b
    return cells
