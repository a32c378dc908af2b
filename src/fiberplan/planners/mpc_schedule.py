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
placed one as a route through its corner.

The schedule only sets when each positioner's reference starts: collision avoidance stays
with the QPs and the safety layer. Clearances are checked every ``stride`` steps. See
``formulations/mpc.md`` (Start schedule).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fiberplan.geometry import capsule_segments, capsule_tables, segment_distance
from fiberplan.kinematics import straight_path
from fiberplan.layout import neighbour_lists
from fiberplan.scenario import Scenario

__all__ = ["StartSchedule", "start_schedule"]


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


def start_schedule(
    scenario: Scenario, step_rad: np.ndarray, margin_mm: float, delay_steps: int = 4, slack: float = 1.2, stride: int = 2,
    max_options: int = 64, swap_tries: int = 1, l_paths: bool = False,
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

    Returns:
        The delays; ``unplaced`` lists the positioners no delay fitted (delay 0); ``corner``
        the corners of the L-shaped moves placed.
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
    _, _, _, combos, combo_radii = capsule_tables(inst)
    ca, cb = combos[:, 0], combos[:, 1]

    def moving_min(i: np.ndarray, ti: np.ndarray, j: np.ndarray, tj: np.ndarray) -> np.ndarray:
        """Clearance of ``i`` after ``ti`` steps of its move to ``j`` after ``tj`` (index arrays, broadcast)."""
        dist = segment_distance(seg_start[i, ti][..., ca, :], seg_end[i, ti][..., ca, :],
                                seg_start[j, tj][..., cb, :], seg_end[j, tj][..., cb, :])[0]
        return (dist - combo_radii).min(axis=-1)

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

    order = np.lexsort((np.arange(n), -move))
    unplaced = np.zeros(n, dtype=bool)
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
        for i in np.flatnonzero(unplaced)[np.lexsort((np.flatnonzero(unplaced), -move[unplaced]))].tolist():
            if reroute(i):
                unplaced[i] = False
    return StartSchedule(delay, np.flatnonzero(unplaced), swaps, corner)
