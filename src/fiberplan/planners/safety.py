"""The safety layer every planner that moves positioners at once shares: one motion bound, one
certificate, and two ways to make an unsafe step safe.

Motion bound: over a linear joint move ``dq`` no capsule point moves further than

.. math:: M = \\rho_\\alpha |\\Delta\\alpha| + \\rho_\\beta |\\Delta\\beta|

(:func:`motion_bound`; ``rho`` from :func:`point_extents`: the farthest capsule point from the
base, and from the elbow). A pair's clearance is 1-Lipschitz in its points, so over a step
whose ends have clearances ``c0``, ``c1`` and whose points move at most ``B = M_i + M_j``,

.. math:: c(s) \\ge \\max(c_0 - s B, c_1 - (1 - s) B) \\ge (c_0 + c_1 - B) / 2

(:func:`clearance_along`, the certificate). The verifier bisects with the same bound. Two
policies use it: :class:`SafetyLayer` (the ``mpc``) stops the lower-priority mover of an unsafe
pair, refining the certificate over sub-steps first; :func:`halve_steps` (the ``dnf``) halves
both movers' steps, then holds them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.geometry import clearance_rows, motion_bound, pair_clearance, point_extents
from fiberplan.scenario import Scenario


def clearance_along(c0: np.ndarray, c1: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """Lower bound of a pair's clearance over a step with end clearances ``c0``, ``c1`` and motion bound ``bound``."""
    return 0.5 * (c0 + c1 - bound)


class SafetyLayer:
    """Stops positioners whose executed step would bring a pair too close (exact distances)."""

    def __init__(self, scenario: Scenario, floor_mm: float, subdivisions: int = 8, bisections: int = 6) -> None:
        self.inst = scenario.instrument
        self.base = scenario.base_xy
        self.orient = scenario.orient
        self.pairs = scenario.pairs
        self.floor = floor_mm
        self.subdivisions = subdivisions
        self.bisections = bisections
        self.rho = point_extents(self.inst)
        # Per pair: the floor, but at most half the pair's clearance at the targets, so that
        # targets closer together than the floor stay reachable (still proven > 0 in between).
        self.half_target_clearance = 0.5 * np.maximum(self.clearance(scenario.target, self.pairs), 0.0)
        self.pair_floor = np.minimum(floor_mm, self.half_target_clearance)

    def clearance(self, joints: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """Smallest clearance over capsule combinations of each pair, all at ``joints``."""
        if len(pairs) == 0:
            return np.zeros(0)
        return pair_clearance(self.inst, self.base, self.orient, joints, pairs).clearance.min(axis=-1)

    def refresh(self, c_now: np.ndarray, q: np.ndarray, q_next: np.ndarray, exact_below: float | None = None) -> None:
        """Update ``c_now`` (the clearance of every scenario pair) in place after the step ``q -> q_next``:
        only pairs with a positioner that moved change.

        With ``exact_below``, a pair is computed exactly only where it may be closer than that:
        elsewhere ``c_now`` holds a lower bound, the last value less the motion bound of both
        positioners' steps since (a clearance changes by at most ``M_i + M_j`` over a step, the
        certificate's bound), computed exactly once the bound falls below ``exact_below``. Every
        value below ``exact_below`` is then exact, and every other one is at least
        ``exact_below``: a caller whose every decision compares ``c_now`` with thresholds below
        ``exact_below`` decides exactly as with exact values everywhere (the ``mpc``: at 50,000
        positioners 12 % of the exact computations)."""
        if not len(self.pairs):
            return
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        joint_moved = q_next != q
        moved = joint_moved[:, 0] | joint_moved[:, 1]
        changed = np.flatnonzero(moved[i] | moved[j])
        if exact_below is not None:
            motion = motion_bound(self.rho, q_next - q)
            c_now[changed] -= motion[i[changed]] + motion[j[changed]]
            changed = changed[c_now[changed] < exact_below]
        c_now[changed] = self.clearance(q_next, self.pairs[changed])

    def _between(self, pairs: np.ndarray, qi: np.ndarray, qj: np.ndarray) -> np.ndarray:
        """Clearance of row-matched pairs with ``i`` at ``qi`` and ``j`` at ``qj``."""
        i, j = pairs[:, 0], pairs[:, 1]
        return clearance_rows(self.inst, self.base[i], self.orient[i], qi, self.base[j], self.orient[j], qj).min(axis=-1)

    def unsafe(self, pairs: np.ndarray, q: np.ndarray, q_next: np.ndarray, c0: np.ndarray, floor: np.ndarray) -> np.ndarray:
        """Which pairs are unsafe when moving from ``q`` to ``q_next`` (linear in joints).

        Safe: clearance at the next sample ``c1 >= f = min(floor, c0)``, and the clearance
        provably stays ``>= f / 2`` in between. Proof: over a piece of the step where the
        pair's capsule points move at most ``B`` (the verifier's motion bound
        ``M_i + M_j``), the clearance is at least ``(c_a + c_b - B) / 2`` with ``c_a, c_b``
        the clearances at the piece's ends. The whole step is tried first, then
        ``subdivisions`` equal pieces with exact clearances at their ends.
        """
        i, j = pairs[:, 0], pairs[:, 1]
        return self.unsafe_rows(pairs, q[i], q[j], q_next[i], q_next[j], c0, floor)

    def unsafe_rows(
        self, pairs: np.ndarray, qi: np.ndarray, qj: np.ndarray, qi_next: np.ndarray, qj_next: np.ndarray,
        c0: np.ndarray, floor: np.ndarray,
    ) -> np.ndarray:
        """:meth:`unsafe` with the pair's configurations given row by row (so that several
        trial steps of the same pairs are checked in one vectorised call)."""
        bound = motion_bound(self.rho, qi_next - qi) + motion_bound(self.rho, qj_next - qj)
        f = np.minimum(floor, c0)
        c1 = self._between(pairs, qi_next, qj_next)
        bad = c1 < f
        coarse = ~bad & (clearance_along(c0, c1, bound) < 0.5 * f)
        rows = np.flatnonzero(coarse)
        if len(rows):
            n_sub = self.subdivisions
            pr = pairs[rows]
            t = np.arange(1, n_sub) / n_sub
            qi_mid = qi[rows][None] + t[:, None, None] * (qi_next[rows] - qi[rows])[None]
            qj_mid = qj[rows][None] + t[:, None, None] * (qj_next[rows] - qj[rows])[None]
            m = len(rows)
            c_mid = self._between(np.tile(pr, (n_sub - 1, 1)), qi_mid.reshape(-1, 2), qj_mid.reshape(-1, 2)).reshape(n_sub - 1, m)
            c_all = np.vstack([c0[rows][None], c_mid, c1[rows][None]])
            lower = clearance_along(c_all[:-1], c_all[1:], bound[rows] / n_sub)
            sampled_bad = np.any(c_mid < f[rows], axis=0)
            unproven = (lower < 0.5 * f[rows]) & ~sampled_bad[None, :]
            bad[rows] = sampled_bad
            if np.any(unproven):
                # Pieces the bound cannot prove: bisected (a pair in near contact can only
                # be proven to part over short pieces, since the bound assumes the closest
                # points approach at the full motion speed).
                k, r = np.nonzero(unproven)
                row = rows[r]
                t0 = k / n_sub
                proves = self._bisect_proves(
                    pairs[row], qi[row], qj[row], qi_next[row], qj_next[row], t0, 1.0 / n_sub,
                    c_all[k, r], c_all[k + 1, r], bound[row] / n_sub, f[row],
                )
                bad[np.unique(row[~proves])] = True
        return bad

    def _bisect_proves(
        self, pairs: np.ndarray, qi: np.ndarray, qj: np.ndarray, qi_next: np.ndarray, qj_next: np.ndarray,
        t0: np.ndarray, width: float, ca: np.ndarray, cb: np.ndarray, bound: np.ndarray, f: np.ndarray,
    ) -> np.ndarray:
        """Whether each piece ``[t0, t0 + width]`` of a step keeps the clearance ``>= f / 2``,
        by bisection (exact clearances at the midpoints, at most ``bisections`` levels)."""
        failed = np.zeros(len(pairs), dtype=bool)
        piece = np.arange(len(pairs))  # the original piece each open sub-piece belongs to
        for _ in range(self.bisections):
            if len(piece) == 0:
                break
            width = 0.5 * width
            tm = t0 + width
            cm = self._between(
                pairs[piece], qi[piece] + tm[:, None] * (qi_next[piece] - qi[piece]), qj[piece] + tm[:, None] * (qj_next[piece] - qj[piece]),
            )
            failed[piece[cm < 0.5 * f]] = True
            half = 0.5 * bound
            open_l = ~failed[piece] & (clearance_along(ca, cm, half) < 0.5 * f)
            open_r = ~failed[piece] & (clearance_along(cm, cb, half) < 0.5 * f)
            piece = np.concatenate([piece[open_l], piece[open_r]])
            t0 = np.concatenate([t0[open_l], tm[open_r]])
            ca, cb = np.concatenate([ca[open_l], cm[open_r]]), np.concatenate([cm[open_l], cb[open_r]])
            bound, f = np.concatenate([half[open_l], half[open_r]]), np.concatenate([f[open_l], f[open_r]])
        failed[piece] = True  # still open after the last level: not proven
        return ~failed

    def apply(
        self, q: np.ndarray, q_next: np.ndarray, c_now: np.ndarray, first: Callable[[np.ndarray, np.ndarray], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Return the safe next configuration, which positioners were stopped, and iterations.

        For an unsafe pair, the lower-priority mover (``first(a, b)``: whether ``a`` has
        priority over ``b``, row-wise) is stopped if that makes the pair safe, else the
        higher-priority one, else both; repeated until every pair is safe (holding still is
        always safe, so this terminates).
        """
        q_next = q_next.copy()
        held = np.zeros(len(q), dtype=bool)
        pairs = self.pairs
        iterations = 0
        if len(pairs) == 0:
            return q_next, held, 0
        i_all, j_all = pairs[:, 0], pairs[:, 1]
        recheck = np.ones(len(pairs), dtype=bool)
        while True:
            motion = motion_bound(self.rho, q_next - q)
            bound = motion[i_all] + motion[j_all]
            # Only pairs with a positioner stopped in the last round can have changed (every
            # unsafe pair had one of its positioners stopped; the others were safe and are as
            # they were), so later rounds re-check those alone.
            idx = np.flatnonzero(recheck & (bound > 0) & (c_now - bound < self.pair_floor + 1e-9))
            if len(idx) == 0:
                break
            bad = self.unsafe(pairs[idx], q, q_next, c_now[idx], self.pair_floor[idx])
            if not np.any(bad):
                break
            iterations += 1
            bp = pairs[idx[bad]]
            c0b = c_now[idx[bad]]
            fb = self.pair_floor[idx[bad]]
            i, j = bp[:, 0], bp[:, 1]
            i_first = first(i, j)  # i has the higher priority
            hi = np.where(i_first, i, j)
            lo = np.where(i_first, j, i)
            moving = np.any(q_next != q, axis=1)
            # Two trial steps per pair, checked in one call: (a) the lower-priority one stopped,
            # (b) the higher-priority one stopped.
            q_a = q_next.copy()
            q_a[lo] = q[lo]
            q_b = q_next.copy()
            q_b[hi] = q[hi]
            pp = np.concatenate([bp, bp])
            trial_bad = self.unsafe_rows(
                pp, np.concatenate([q[i], q[i]]), np.concatenate([q[j], q[j]]),
                np.concatenate([q_a[i], q_b[i]]), np.concatenate([q_a[j], q_b[j]]),
                np.concatenate([c0b, c0b]), np.concatenate([fb, fb]),
            )
            ok_a = moving[lo] & ~trial_bad[: len(bp)]
            ok_b = moving[hi] & ~ok_a & ~trial_bad[len(bp):]
            both = ~ok_a & ~ok_b
            stop = np.unique(np.concatenate([lo[ok_a], hi[ok_b], lo[both], hi[both]]))
            stop = stop[moving[stop]]
            if len(stop) == 0:  # pragma: no cover - every unsafe pair has a mover
                raise PlannerError("safety layer found an unsafe pair with both positioners still")
            q_next[stop] = q[stop]
            held[stop] = True
            stopped_now = np.zeros(len(q), dtype=bool)
            stopped_now[stop] = True
            recheck = stopped_now[i_all] | stopped_now[j_all]
        return q_next, held, iterations




@dataclass
class HalvingStats:
    """What :func:`halve_steps` did over a run."""

    interventions: int = 0
    held: int = 0
    iterations: int = 0


def halve_steps(
    scenario: Scenario, pairs: np.ndarray, joints: np.ndarray, step: np.ndarray, clear0: np.ndarray, margin_mm: float,
    motion_factor: float, max_halvings: int, rho: np.ndarray, stats: HalvingStats,
) -> np.ndarray:
    """Shorten steps so that every pair stays provably apart over the whole step (the ``dnf``'s policy).

    A pair passes when ``c_1 >= f`` and :func:`clearance_along` with the motion bound
    enlarged by ``motion_factor`` is at least ``f = min(margin_mm, c_0)``. The steps of both
    positioners of a failing pair are halved; after ``max_halvings`` halvings they are held
    (zero step), which a pair that was safe always passes.
    """
    if len(pairs) == 0:
        return step
    inst = scenario.instrument
    eta = motion_factor
    motion_full = motion_bound(rho, step)
    bound_full = motion_full[pairs[:, 0]] + motion_full[pairs[:, 1]]
    floor0 = np.minimum(margin_mm, np.maximum(clear0, 0.0))
    # A pair can fail only if the certificate fails with the worst end clearance c1 = c0 - B.
    risky = np.flatnonzero((bound_full > 0) & (clearance_along(clear0, clear0 - bound_full, (1.0 + eta) * bound_full) < floor0))
    if len(risky) == 0:
        return step
    scale = np.ones(len(joints))
    min_scale = 0.5**max_halvings
    sub = pairs[risky]
    c0 = clear0[risky]
    f0 = floor0[risky]
    ii, jj = sub[:, 0], sub[:, 1]
    base_i, base_j = scenario.base_xy[ii], scenario.base_xy[jj]
    orient_i, orient_j = scenario.orient[ii], scenario.orient[jj]
    while True:
        stats.iterations += 1
        qi = joints[ii] + scale[ii, None] * step[ii]
        qj = joints[jj] + scale[jj, None] * step[jj]
        c1 = clearance_rows(inst, base_i, orient_i, qi, base_j, orient_j, qj).min(axis=1)
        bound = scale[ii] * motion_full[ii] + scale[jj] * motion_full[jj]
        bad = (bound > 0) & ((c1 < f0) | (clearance_along(c0, c1, (1.0 + eta) * bound) < f0))
        if not np.any(bad):
            break
        stats.interventions += int(bad.sum())
        who = np.unique(np.concatenate([ii[bad], jj[bad]]))
        who = who[scale[who] > 0]
        halved = scale[who] * 0.5
        scale[who] = np.where(halved < min_scale, 0.0, halved)
    stats.held += int(np.sum(scale == 0.0))
    return step * scale[:, None]
