"""Each positioner's move spread over the plan's makespan where its neighbours allow
(``stretch``; ``formulations/coordination.md``, Stretching the moves).

The decentralised planners drive every joint at full speed and stop: each positioner arrives as
early as it can, and then waits for the last one. At the same makespan that costs energy
(:func:`fiberplan.metrics.energy`, :math:`\\sum_i \\int \\|\\dot q_i\\|^2 dt`): a path of joint-space
length :math:`L` traversed in time :math:`D` needs at least :math:`L^2 / D`, reached at constant
speed, so a positioner that arrives at half the makespan uses at least twice what it needs
(the energy gaps of ``docs/results.md``, session 39).

Here every positioner that moves and arrives by the makespan's sample (most energy to save
first) is offered a new timing on the plan's time grid over a longer window:

- the window from its departure, or from the start, to the makespan's sample, or half or a
  quarter of the way there from its arrival, or its own;
- along its own path with its own timing scaled (its waits kept, in proportion), or along its
  own path at constant speed, or along the straight joint move from its start to its end at
  constant speed (:data:`STRAIGHTEN`).

The candidate with the least energy that keeps every neighbour pair at least ``floor`` apart at
every sample (the smaller of the safety margin and the pair's own smallest clearance at the
plan's samples), proven clear between samples (the motion bound, bisected where it is not small
against the clearance), within the joint speeds, and, where the instrument states motor limits,
with no rule broken more often than by its own samples (:func:`motor_counts`), replaces the
positioner's samples; the next positioner is checked against the moves as they now are, and the
positioners refused are offered again (:data:`PASSES` rounds). Every start and end is unchanged
(the joint box is convex: a straight move keeps the hard stops), and the makespan is never later
(it can be a sample earlier: a slower last approach enters the tolerance disc sooner); the
positioners that do not reach their target are left as planned. The result is verified whole by
the caller.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fiberplan.geometry import capsule_segments, clearance_between, motion_bound, point_extents, segment_clearances
from fiberplan.instrument import MotorLimits
from fiberplan.metrics import arrival_times, reached_mask
from fiberplan.scenario import Scenario
from fiberplan.verify import motor_breaches, motor_runs

WINDOW_DIVISORS = (1, 2, 4)
"""The windows offered end at the makespan's sample, or half or a quarter of the way to it from
the positioner's arrival; each starts at the start or at its departure."""

STRAIGHTEN = True
"""Also offered: the straight joint move from the start to the end (the least energy of all)."""

PASSES = 3
"""Rounds over the positioners: one stretched may leave room for another refused before."""

PRECHECK_STRIDE = 8
"""A candidate's clearances are looked at every this many samples first (a cheap refusal), then at all."""

BISECTIONS = 8
"""Halvings of a step whose motion bound is not small against the clearance at its ends; a piece
still not proven clear after them rejects the candidate (conservative)."""


@dataclass(frozen=True)
class Stretched:
    """The stretched joints and what changed."""

    joints: np.ndarray
    positioners: int  # positioners whose samples changed
    energy_before: float
    energy_after: float


def _energy(column: np.ndarray, dt: np.ndarray) -> float:
    """Energy of one positioner's samples ``(T, 2)`` on steps ``dt`` ``(T - 1,)``."""
    return float(np.sum(np.diff(column, axis=0) ** 2 / dt[:, None]))


def _span(column: np.ndarray) -> tuple[int, int] | None:
    """``(f, g)``: the positioner moves from sample ``f`` to sample ``g`` (``None`` if it holds still)."""
    moving = np.any(column[1:] != column[:-1], axis=1)
    if not moving.any():
        return None
    return int(np.argmax(moving)), int(len(moving) - np.argmax(moving[::-1]))


def _retimed(column: np.ndarray, times: np.ndarray, f: int, g: int, a: int, b: int, even: bool) -> np.ndarray:
    """The positioner's path from sample ``f`` to ``g`` played from sample ``a`` to ``b`` (``a <= f``,
    ``b >= g``): its own timing scaled, or at constant speed along the path (``even``)."""
    new = np.empty_like(column)
    new[: a + 1] = column[f]
    new[b:] = column[g]
    t = times[a + 1 : b]
    share = (t - times[a]) / (times[b] - times[a])  # (0, 1)
    seg = column[f : g + 1]
    if even:
        length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(seg, axis=0), axis=1))])
        keep = np.concatenate([[True], np.diff(length) > 0.0])  # the waits dropped
        x, seg = length[keep], seg[keep]
        u = share * x[-1]
    else:
        x = times[f : g + 1]
        u = times[f] + share * (times[g] - times[f])
    new[a + 1 : b, 0] = np.interp(u, x, seg[:, 0])
    new[a + 1 : b, 1] = np.interp(u, x, seg[:, 1])
    return new


class _Checker:
    """Clearances of one positioner's candidate samples against its neighbours' current ones."""

    def __init__(self, scenario: Scenario, joints: np.ndarray, margin_mm: float):
        self.scenario = scenario
        self.inst = scenario.instrument
        self.joints = joints  # (T, N, 2), updated in place as candidates are accepted
        self.rho = point_extents(self.inst)
        pairs = scenario.pairs
        self.neighbours: list[list[int]] = [[] for _ in range(scenario.n_positioners)]
        for i, j in pairs.tolist():
            self.neighbours[i].append(j)
            self.neighbours[j].append(i)
        self.margin = margin_mm
        self._floor: dict[tuple[int, int], float] = {}
        self._original = joints.copy()
        self._segments: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # as they now move
        self._planned: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # as planned

    def segments(self, j: int, original: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Capsule segments ``(T, C, 2)`` (start, end) of positioner ``j`` as it now moves (or as
        planned), kept until it changes."""
        cache, joints = (self._planned, self._original) if original else (self._segments, self.joints)
        seg = cache.get(j)
        if seg is None:
            s = self.scenario
            start, end = capsule_segments(self.inst, s.base_xy[j : j + 1], s.orient[j : j + 1], joints[:, j : j + 1])
            seg = cache[j] = (start[:, 0], end[:, 0])
        return seg

    def clearances(self, seg_i: tuple[np.ndarray, np.ndarray], others: np.ndarray, samples: np.ndarray,
                   original: bool = False) -> np.ndarray:
        """``(J, W)`` smallest clearances of a positioner with segments ``seg_i`` (``(W, C, 2)``) to
        ``others`` as they now move (or as planned), at ``samples`` (``(W,)``)."""
        start_j = np.concatenate([self.segments(j, original)[0][samples] for j in others.tolist()])
        end_j = np.concatenate([self.segments(j, original)[1][samples] for j in others.tolist()])
        reps = (len(others), 1, 1)
        c = segment_clearances(self.inst, np.tile(seg_i[0], reps), np.tile(seg_i[1], reps), start_j, end_j)
        return c.min(axis=1).reshape(len(others), len(samples))

    def floors(self, i: int, others: np.ndarray) -> np.ndarray:
        """The smaller of the margin and each pair's smallest clearance at the plan's samples."""
        missing = [j for j in others.tolist() if (min(i, j), max(i, j)) not in self._floor]
        if missing:
            c = self.clearances(self.segments(i, original=True), np.array(missing), np.arange(len(self._original)), original=True)
            for j, low in zip(missing, c.min(axis=1).tolist(), strict=True):
                self._floor[(min(i, j), max(i, j))] = min(self.margin, low)
        return np.array([self._floor[(min(i, j), max(i, j))] for j in others.tolist()])

    def clear(self, i: int, column: np.ndarray, a: int, b: int) -> bool:
        """Whether ``column`` keeps every pair of ``i`` at its floor at the samples and clear between
        them. Only samples ``a`` to ``b`` are looked at: outside them ``i`` is where it was (at its
        start before ``a``, at its end after ``b``), against neighbours already checked against that."""
        others = np.array(sorted(self.neighbours[i]), dtype=np.int64)
        if not len(others):
            return True
        column, joints = column[a : b + 1], self.joints[a : b + 1]
        seg_i = self._window_segments(i, column)
        floors = self.floors(i, others)[:, None]
        if b - a > 2 * PRECHECK_STRIDE:  # most refusals show at a few samples: those first
            few = np.arange(PRECHECK_STRIDE // 2, b - a, PRECHECK_STRIDE)
            if np.any(self.clearances((seg_i[0][few], seg_i[1][few]), others, a + few) < floors):
                return False
        c = self.clearances(seg_i, others, np.arange(a, b + 1))  # (J, b - a + 1)
        if np.any(c < floors):
            return False
        move_i = motion_bound(self.rho, np.abs(np.diff(column, axis=0)))  # (b - a,)
        move_j = motion_bound(self.rho, np.abs(np.diff(joints[:, others], axis=0))).T  # (J, b - a)
        bound = move_i[None, :] + move_j
        c_lo, c_hi = c[:, :-1], c[:, 1:]
        jj, kk = np.nonzero(bound >= np.minimum(c_lo, c_hi))
        if not len(jj):
            return True
        return self._bisect(i, column, joints, others, jj, kk, c_lo[jj, kk], c_hi[jj, kk], bound[jj, kk])

    def _window_segments(self, i: int, column: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Capsule segments ``(W, C, 2)`` of positioner ``i`` at the samples ``column`` ``(W, 2)``."""
        s = self.scenario
        start, end = capsule_segments(self.inst, s.base_xy[i : i + 1], s.orient[i : i + 1], column[:, None])
        return start[:, 0], end[:, 0]

    def accept(self, i: int, column: np.ndarray, a: int, b: int) -> None:
        """Positioner ``i`` moves as ``column`` (changed from its samples ``a`` to ``b`` only)."""
        start, end = self._window_segments(i, column[a : b + 1])
        old_start, old_end = self.segments(i)
        new_start, new_end = old_start.copy(), old_end.copy()  # (the planned ones may be the same arrays)
        new_start[a : b + 1], new_end[a : b + 1] = start, end
        self.joints[:, i] = column
        self._segments[i] = (new_start, new_end)

    def _bisect(self, i: int, column: np.ndarray, joints: np.ndarray, others: np.ndarray, jj: np.ndarray, kk: np.ndarray,
                c_lo: np.ndarray, c_hi: np.ndarray, bound: np.ndarray) -> bool:
        s = self.scenario
        lo, hi = np.zeros(len(jj)), np.ones(len(jj))
        for _ in range(BISECTIONS):
            mid = 0.5 * (lo + hi)
            j = others[jj]
            q_i = (1 - mid)[:, None] * column[kk] + mid[:, None] * column[kk + 1]
            q_j = (1 - mid)[:, None] * joints[kk, j] + mid[:, None] * joints[kk + 1, j]
            rows_i = np.full(len(j), i)
            c_mid = clearance_between(self.inst, s.base_xy[rows_i], s.orient[rows_i], q_i, s.base_xy[j], s.orient[j],
                                      q_j).min(axis=1)
            if np.any(c_mid < 0.0):
                return False
            half = 0.5 * bound
            jj, kk = np.concatenate([jj, jj]), np.concatenate([kk, kk])
            lo, hi = np.concatenate([lo, mid]), np.concatenate([mid, hi])
            c_lo, c_hi = np.concatenate([c_lo, c_mid]), np.concatenate([c_mid, c_hi])
            bound = np.concatenate([half, half])
            still = bound >= np.minimum(c_lo, c_hi)
            if not still.any():
                return True
            jj, kk, lo, hi, c_lo, c_hi, bound = jj[still], kk[still], lo[still], hi[still], c_lo[still], c_hi[still], bound[still]
        return False


def motor_counts(column: np.ndarray, dt: np.ndarray, motors: MotorLimits) -> np.ndarray:
    """How often one positioner's samples ``(T, 2)`` break each motor rule the instrument states,
    per joint: ``(2, 5)`` counts of commands below the minimum speed, reversals without a stop,
    speed changes above the limit, and constant-speed runs and starts from rest beyond the limits
    (the verifier's rules, :func:`fiberplan.verify.motor_breaches` and :func:`~fiberplan.verify.motor_runs`,
    counted rather than reported at their worst)."""
    kinds = ("min_speed", "reversal", "speed_change")
    counts = np.zeros((2, 5), dtype=np.int64)
    v = np.diff(column, axis=0) / dt[:, None]  # (T - 1, 2)
    for axis in (0, 1):
        speeds = v[:, axis : axis + 1]
        for kind, mask, *_ in motor_breaches(motors, speeds, axis):
            counts[axis, kinds.index(kind)] = int(mask.sum())
        from_rest, starts = motor_runs(speeds)
        if motors.max_segments is not None:
            counts[axis, 3] = max(int(starts.sum()) - motors.max_segments, 0)
        if motors.max_start_stops is not None:
            counts[axis, 4] = max(int(from_rest.sum()) - motors.max_start_stops, 0)
    return counts


def stretch(scenario: Scenario, times: np.ndarray, joints: np.ndarray, margin_mm: float) -> Stretched:
    """Each positioner's move spread over more of the makespan where its neighbours allow.

    What ``plan(..., {"stretch": True})`` applies after the mpc's or the dnf's plan (the setting
    ``stretch``; ``formulations/coordination.md``, Stretching the moves). Each positioner that
    arrives before the makespan is offered its own path timed over a longer window (scaled, or at
    constant speed) or the straight joint move at constant speed; the least-energy offer that
    keeps every neighbour pair at least its floor at the samples (the smaller of ``margin_mm`` and
    the pair's closest approach in the plan), is proven clear between samples and breaks no
    stated motor rule more often than the plan did, is kept. Starts and ends are unchanged, the
    makespan never later; verify the result whole.

    Args:
        scenario: the planned scenario.
        times: ``(T,)`` the plan's sample times (s).
        joints: ``(T, N, 2)`` the plan's joint angles (rad); not modified.
        margin_mm: the planner's safety margin (mm).

    Returns:
        The stretched joints on the same times, how many positioners changed, and the energy
        (:func:`fiberplan.metrics.energy`) before and after.
    """
    times = np.asarray(times, dtype=float)
    joints = np.array(joints, dtype=float, copy=True)
    dt = np.diff(times)
    from fiberplan.trajectory import Trajectory

    trajectory = Trajectory(times, joints)
    reached = reached_mask(scenario, trajectory)
    arrive = arrival_times(scenario, trajectory)
    before = float(sum(_energy(joints[:, i], dt) for i in range(scenario.n_positioners)))
    if len(times) < 3 or not reached.any():
        return Stretched(joints, 0, before, before)
    end = int(np.searchsorted(times, np.nanmax(arrive[reached])))  # the makespan's sample
    inst = scenario.instrument
    top = np.asarray(inst.speeds_rad_s, dtype=float)
    motors = inst.motors if inst.motors.stated else None
    checker = _Checker(scenario, joints, margin_mm)
    movable = reached | ~scenario.has_target
    movable &= ~scenario.locked

    def offered(column: np.ndarray, f: int, g: int, a: int, b: int, way: int) -> np.ndarray:
        """The samples of one offer (made again when checked: only its energy is kept meanwhile)."""
        if way == 2:  # the straight joint move
            column = column.copy()
            column[f : g + 1] = np.linspace(column[f], column[g], g - f + 1)
        return _retimed(column, times, f, g, a, b, even=way != 1)

    ways = (0, 1, 2) if STRAIGHTEN else (0, 1)  # own path at constant speed, own timing scaled, straight
    offers: list[tuple[float, int, int, int, list[tuple[float, int, int, int]]]] = []
    for i in np.flatnonzero(movable).tolist():
        column = joints[:, i]
        span = _span(column)
        if span is None or span[1] > end:
            continue
        f, g = span
        own = _energy(column, dt)
        own_motors = motor_counts(column, dt, motors) if motors is not None else None
        windows = [(a, g + (end - g) // d) for d in WINDOW_DIVISORS for a in (0, f)] + [(f, g)]
        candidates = []
        for a, b in dict.fromkeys(windows):
            if b < g:
                continue
            for way in ways:
                new = offered(column, f, g, a, b, way)
                if np.any(np.abs(np.diff(new, axis=0)) > top[None, :] * dt[:, None] * (1 + 1e-9)):
                    continue
                if motors is not None and np.any(motor_counts(new, dt, motors) > own_motors):
                    continue
                e = _energy(new, dt)
                if e < own * (1 - 1e-9):
                    candidates.append((e, a, b, way))
        if candidates:
            candidates.sort(key=lambda c: c[0])
            offers.append((own - candidates[0][0], i, f, g, candidates))
    offers.sort(key=lambda o: (-o[0], o[1]))
    changed: set[int] = set()
    for _ in range(PASSES):
        left = []
        for offer in offers:
            _, i, f, g, candidates = offer
            for _, a, b, way in candidates:
                new = offered(joints[:, i], f, g, a, b, way)  # (i's samples are still its own: it changes once)
                if checker.clear(i, new, a, b):
                    checker.accept(i, new, a, b)
                    changed.add(i)
                    break
            else:
                left.append(offer)
        if len(left) == len(offers):
            break
        offers = left
    after = float(sum(_energy(joints[:, i], dt) for i in range(scenario.n_positioners)))
    return Stretched(joints, len(changed), before, after)
