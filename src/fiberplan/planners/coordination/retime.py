"""Overlapping two legs that meet at a common configuration (``formulations/coordination.md``,
Overlapping the legs).

A two-leg plan ``J1`` (start -> hold) then ``J2`` (hold -> goal) keeps every positioner at its
hold configuration ``H`` from its arrival in the first leg (sample ``a_i``) until its departure
in the second (sample ``b_i`` of ``J2``). Starting the second leg ``s`` samples early, for
everyone at once, gives positioner ``i``

    q_i(k) = J2[k - (K1 - s), i]   once k - (K1 - s) >= b_i,   else J1[min(k, K1), i],

which is continuous (both sides equal ``H_i`` at the switch) as long as
``s <= K1 - a_i + b_i`` for every ``i``. Each positioner runs its own samples of the two legs,
so speeds and hard stops are those of the legs. A pair with both positioners in the same leg
is in a configuration of that leg at one instant of it (a positioner waiting at ``H`` is in both
legs), so it is as clear as the leg made it. Only a pair with one positioner still on its way to
``H`` in the first leg and the other already on its way from ``H`` in the second is in a new
configuration; those pairs are checked at every sample and between samples with the motion
bound (clearance ``>= (c_k + c_{k+1} - M_i - M_j) / 2`` over a step), and the largest ``s`` for
which every new pair keeps the floor is taken.
"""

from __future__ import annotations

import numpy as np

from fiberplan.geometry import min_pair_clearance, motion_bound, point_extents
from fiberplan.scenario import Scenario


def _phases(j1: np.ndarray, j2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a`` (first sample of ``j1`` from which each positioner stays at the hold) and ``b``
    (last sample of ``j2`` up to which it is still there)."""
    hold = j1[-1]
    off1 = np.any(j1 != hold[None], axis=2)
    k1 = len(j1) - 1
    a = np.where(off1.any(axis=0), k1 + 1 - np.argmax(off1[::-1], axis=0), 0)
    off2 = np.any(j2 != hold[None], axis=2)
    b = np.where(off2.any(axis=0), np.argmax(off2, axis=0) - 1, len(j2) - 1)
    return a, b


def _combined(j1: np.ndarray, j2: np.ndarray, b: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """The joints of the legs overlapped by ``s`` samples, and which positioner runs the second
    leg at each sample."""
    k1, k2 = len(j1) - 1, len(j2) - 1
    k = np.arange(k1 + k2 - s + 1)
    m = k - (k1 - s)
    second = (m[:, None] >= b[None, :]) & (m[:, None] >= 0)
    joints = np.where(second[..., None], j2[np.clip(m, 0, k2)], j1[np.minimum(k, k1)])
    return joints, second


def _new_pairs_clear(scenario: Scenario, j1: np.ndarray, j2: np.ndarray, a: np.ndarray, b: np.ndarray, s: int,
                     floor: float) -> bool:
    """Whether every pair in a new configuration keeps ``floor`` at the samples and stays clear between them."""
    pairs = scenario.pairs
    if not len(pairs) or s <= 0:
        return True
    k1 = len(j1) - 1
    joints, second = _combined(j1, j2, b, s)
    lo, hi = max(0, k1 - s - 1), min(len(joints) - 1, k1 + 1)
    window = joints[lo : hi + 1]
    first = np.arange(lo, hi + 1)[:, None] < a[None, :]  # still on its way to the hold
    then = second[lo : hi + 1]
    i, j = pairs[:, 0], pairs[:, 1]
    new = (first[:, i] & then[:, j]) | (first[:, j] & then[:, i])  # (W, P)
    step_new = new[:-1] | new[1:]
    rows = np.flatnonzero(step_new.any(axis=0))
    if not len(rows):
        return True
    c = min_pair_clearance(scenario.instrument, scenario.base_xy, scenario.orient, window, pairs[rows])  # (W, R)
    bound = motion_bound(point_extents(scenario.instrument), np.abs(np.diff(window, axis=0)))  # (W - 1, N)
    lower = 0.5 * (c[:-1] + c[1:] - bound[:, i[rows]] - bound[:, j[rows]])
    checked = step_new[:, rows]
    return bool(np.all(lower[checked] > 0.0) and np.all(np.minimum(c[:-1], c[1:])[checked] >= floor))


def turns_back(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Which positioners turn a joint back where ``before`` (``(K1 + 1, N, 2)``) ends and
    ``after`` (``(K2 + 1, N, 2)``) begins: the joint's last move in the first and its first move
    in the second have opposite directions (holds in between do not count)."""

    def direction(steps: np.ndarray) -> np.ndarray:  # (K, N, 2) -> the sign of the first nonzero step, 0 if none
        moving = steps != 0.0
        first = np.argmax(moving, axis=0)
        return np.where(moving.any(axis=0), np.sign(np.take_along_axis(steps, first[None], axis=0)[0]), 0.0)

    last = direction(np.diff(before, axis=0)[::-1])
    first = direction(np.diff(after, axis=0))
    return np.any(last * first < 0.0, axis=1)


def ramp_rests(joints: np.ndarray, rest: int, top: np.ndarray, where: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """``joints`` (``(K + 1, N, 2)`` samples) with everyone holding still, for as few steps as
    needed, wherever a joint turns back less than ``rest`` steps after moving the other way such
    that the two speeds add up to more than the top speed (``top``, per joint, rad per step
    unit: the same units as the steps): the speed ramps' rule (:mod:`fiberplan.ramps`; the
    ``mpc`` keeps it within a run, :func:`fiberplan.planners.motors.govern` rule 4; its runs are
    joined here). Only steps marked in ``where`` (``(K,)``, default all) count: samples that
    chatter are left to the discretiser, which smooths them first. Holding a sample is safe (each
    configuration is one already verified), and the motion is otherwise unchanged. Returns
    ``(joints, steps inserted)``."""
    if rest <= 0 or len(joints) < 3:
        return joints, 0
    where = np.ones(len(joints) - 1, dtype=bool) if where is None else np.asarray(where, dtype=bool)
    inserted = 0
    start = 1
    while True:
        steps = np.diff(joints, axis=0)  # (K, N, 2)
        first: tuple[int, int] | None = None  # (step, steps since the opposite move) of the earliest clash
        for d in range(1, rest + 1):
            if start < d or start >= len(steps):
                continue
            now, before = steps[max(start, d):], steps[max(start, d) - d: len(steps) - d]
            counted = where[max(start, d):] & where[max(start, d) - d: len(steps) - d]
            clash = (now * before < 0.0) & (np.abs(now) + np.abs(before) > top * (1 + 1e-9))
            hit = np.flatnonzero(clash.any(axis=(1, 2)) & counted)
            if len(hit):
                s = max(start, d) + int(hit[0])
                if first is None or s < first[0] or (s == first[0] and d < first[1]):
                    first = (s, d)
        if first is None:
            return joints, inserted
        s, d = first
        pad = rest + 1 - d
        joints = np.concatenate([joints[: s + 1], np.repeat(joints[s : s + 1], pad, axis=0), joints[s + 1 :]])
        where = np.concatenate([where[:s], np.ones(pad, dtype=bool), where[s:]])
        inserted += pad
        start = s + pad


def overlap_legs(scenario: Scenario, j1: np.ndarray, j2: np.ndarray, floor: float, coarse: int, rest: int = 0) -> tuple[np.ndarray, int]:
    """The two legs overlapped by the largest shift found safe (see the module docstring).

    Args:
        scenario: the positioners (bases, instrument, neighbour pairs).
        j1, j2: the legs, ``(K1 + 1, N, 2)`` and ``(K2 + 1, N, 2)``, with ``j1[-1] == j2[0]``.
        floor: smallest clearance a new pair may reach at a sample (mm).
        coarse: shifts are searched downward in strides of this many samples, then refined
            sample by sample above the first one found clear.
        rest: samples each positioner that turns a joint back at the hold (:func:`turns_back`)
            stays there at least (speed ramps: an opposite speed a ramp after a stop). Where the
            legs one after the other leave less, the second starts later (a negative shift).

    Returns:
        ``(joints, shift in samples)``; a shift of 0 is the legs one after the other.
    """
    if not np.array_equal(j1[-1], j2[0]):
        raise ValueError("the legs do not meet at one configuration")
    a, b = _phases(j1, j2)
    k1 = len(j1) - 1
    need = rest * turns_back(j1, j2) if rest > 0 else 0
    s_max = int(np.min(k1 - a + b - need))
    if s_max <= 0:
        shift = min(0, s_max)
        return _combined(j1, j2, b, shift)[0], shift
    coarse = max(1, coarse)
    found = 0
    for s in range(s_max, 0, -coarse):
        if _new_pairs_clear(scenario, j1, j2, a, b, s, floor):
            found = s
            break
    if found:
        for s in range(min(s_max, found + coarse - 1), found, -1):
            if _new_pairs_clear(scenario, j1, j2, a, b, s, floor):
                found = s
                break
    joints, _ = _combined(j1, j2, b, found)
    return joints, found
