"""Independent verifier: joint limits, speed limits and collisions, at and between samples.

This module imports no planner: it checks any trajectory (``Trajectory`` of linear joint
motion between samples) against the scenario's instrument with exact capsule distances.

Between two samples a positioner's joints move linearly, so no point of its capsules moves
further than

.. math:: M_i = \\rho_{\\alpha} |\\Delta\\alpha_i| + \\rho_{\\beta} |\\Delta\\beta_i|

(``rho_alpha``: farthest capsule point from the base, ``rho_beta``: from the elbow). The
clearance of pair ``(i, j)`` therefore changes by at most ``M_i + M_j`` over the interval.
Each interval is bisected until, on every piece, the pair's points move less than
``fraction`` of the clearance measured at both ends of the piece; a piece with positive
clearances at both ends then cannot hide a contact. A collision found between samples is
reported at the instant it was probed.

Non-finite joint angles (NaN, inf) are violations of their own: every such sample is
reported (as runs of consecutive samples per positioner), and the geometric checks leave the
unknown positions out. :func:`check_run_file` checks a trajectory file against itself (its
``/positioners/*`` datasets against the embedded scenario, an embedded preset instrument
against the preset shipped with fiberplan).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from fiberplan.errors import TrajectoryError
from fiberplan.geometry import capsule_coordinates, clearance_between, motion_bound, point_extents
from fiberplan.instrument import Instrument, MotorLimits
from fiberplan.instrument_io import load_instrument, preset_names
from fiberplan.layout import neighbour_pairs
from fiberplan.scenario import Scenario
from fiberplan.trajectory import RunFile, Trajectory

_ANGLE_TOL = 1e-9
_SPEED_REL_TOL = 1e-6
_MAX_BISECTIONS = 40
_PRUNE_MM = 2.0  # pairs whose enclosing discs are this far apart skip the exact distance
_THREADED_INTERVALS = 20_000  # intervals to bisect from which the pairs are split between threads


@dataclass(frozen=True)
class CollisionEvent:
    """One colliding pair: when it first collided, and its worst overlap."""

    id_i: int
    id_j: int
    capsule_i: str
    capsule_j: str
    t_first_s: float
    t_worst_s: float
    min_distance_mm: float
    required_mm: float

    @property
    def overlap_mm(self) -> float:
        """How far the capsules interpenetrate at worst."""
        return self.required_mm - self.min_distance_mm


@dataclass(frozen=True)
class LimitViolation:
    """A joint beyond a hard stop or faster than its motor: its worst excess, and when it began.

    ``t_s`` and ``value`` are those of the worst sample (the largest excess), ``t_first_s`` the
    first offending sample of that positioner and joint.
    """

    positioner_id: int
    joint: str
    t_s: float
    value: float
    limit: float
    kind: str  # "hard_stop" or "speed"; motor limits: "min_speed", "speed_change", "reversal", "segments", "start_stops", "acceleration"
    t_first_s: float = float("nan")


@dataclass(frozen=True)
class NonFiniteRun:
    """Consecutive samples of one positioner whose joint angles are not finite (NaN or inf)."""

    positioner_id: int
    t_first_s: float
    t_last_s: float
    n_samples: int


@dataclass
class VerificationReport:
    """Everything the verifier found.

    ``ok`` is true when every sample is finite, the trajectory starts at the scenario's
    start, respects every hard stop and speed limit, no pair collides at any instant, and (for
    a file) the file agrees with itself.
    """

    n_positioners: int
    n_samples: int
    n_pairs: int
    collisions: list[CollisionEvent] = field(default_factory=list)
    limit_violations: list[LimitViolation] = field(default_factory=list)
    start_mismatch_ids: list[int] = field(default_factory=list)
    non_finite: list[NonFiniteRun] = field(default_factory=list)
    file_mismatches: list[str] = field(default_factory=list)
    motor_violations: list[LimitViolation] = field(default_factory=list)
    motors_checked: bool = False
    warnings: list[str] = field(default_factory=list)
    min_clearance_mm: float = float("inf")
    probes: int = 0
    executed_ramp_s: float | None = None  # motor commands also checked as executed with this ramp time (fiberplan.ramps)

    @property
    def ok(self) -> bool:
        """No non-finite sample, collision, limit violation or file mismatch; starts at the start."""
        return not (self.collisions or self.limit_violations or self.start_mismatch_ids or self.non_finite or self.file_mismatches)

    @property
    def motors_ok(self) -> bool:
        """No violation of the instrument's motor limits (minimum speed, speed change, reversal
        without a stop, segment count); true when the instrument states none. Not part of
        :attr:`ok`: a planner's samples are checked for safety, motor commands for these."""
        return not self.motor_violations

    @property
    def n_non_finite_samples(self) -> int:
        """Number of (sample, positioner) entries with a non-finite joint angle."""
        return sum(r.n_samples for r in self.non_finite)

    @property
    def n_collisions(self) -> int:
        """Number of colliding positioner pairs."""
        return len(self.collisions)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (collision and violation lists included)."""
        return {
            "ok": self.ok,
            "n_positioners": self.n_positioners,
            "n_samples": self.n_samples,
            "n_pairs_checked": self.n_pairs,
            "collisions": self.n_collisions,
            "collision_events": [asdict(c) | {"overlap_mm": c.overlap_mm} for c in self.collisions],
            "limit_violations": [asdict(v) for v in self.limit_violations],
            "start_mismatch_ids": self.start_mismatch_ids,
            "non_finite_samples": self.n_non_finite_samples,
            "non_finite": [asdict(r) for r in self.non_finite],
            "file_mismatches": self.file_mismatches,
            "motors_checked": self.motors_checked,
            "motor_violations": [asdict(v) for v in self.motor_violations],
            "warnings": self.warnings,
            "min_clearance_mm": self.min_clearance_mm,
            "probes": self.probes,
            "executed_ramp_s": self.executed_ramp_s,
        }


CHUNK_PAIR_SAMPLES = 1_000_000
"""Pair-samples the verifier takes at once by default (memory: a few hundred bytes each)."""

THREADS = min(2, os.cpu_count() or 1)
"""Chunks the verifier works on at once: numpy releases the GIL inside its array operations,
so two threads check a large trajectory in a little over half the time (the report does not
depend on it: each chunk writes its own rows, and collisions are recorded in chunk order)."""


THREADED_PAIR_SAMPLES = 1_000_000
"""Pair-samples (samples x neighbour pairs) from which a trajectory is checked on :data:`THREADS`
threads: below, one thread is faster (the threads would wait on each other for the GIL between
small array operations; DESI 7 took 14 ms on two threads against 2.5 ms on one)."""


def _chunk_map(func: Callable[[int], Any], starts: range, threaded: bool) -> list[Any]:
    """``[func(k0) for k0 in starts]``, on :data:`THREADS` threads if ``threaded`` and there is more than one chunk."""
    if not threaded or THREADS <= 1 or len(starts) <= 1:
        return [func(k0) for k0 in starts]
    with ThreadPoolExecutor(max_workers=THREADS) as pool:
        return list(pool.map(func, starts))


def verify(
    scenario: Scenario, trajectory: Trajectory, *, fraction: float = 0.5, time_chunk: int | None = None, instrument: Instrument | None = None,
) -> VerificationReport:
    """Check a trajectory against the scenario's instrument (or the one given).

    Args:
        scenario: positioners, bases and instrument.
        trajectory: joint angles ``(T, N, 2)`` on a time grid, linear between samples.
        fraction: bisect each inter-sample interval until no point moves more than this
            fraction of the clearance between two checks (0 < fraction < 1).
        time_chunk: samples processed at once (memory bound for large N); default: 64, fewer
            on a large field, so that the chunks in work at once (one per thread,
            :data:`THREADS`) hold about a million pair-samples in all
            (:data:`CHUNK_PAIR_SAMPLES`). The report does not depend on it.
        instrument: check against this geometry and these limits instead of the scenario's.

    Returns:
        A :class:`VerificationReport`.

    Raises:
        TrajectoryError: ``fraction`` outside (0, 1), or the trajectory and the scenario do
            not have the same positioners.
    """
    return verify_with_clearances(scenario, trajectory, fraction=fraction, time_chunk=time_chunk, instrument=instrument)[0]


def verify_with_clearances(
    scenario: Scenario, trajectory: Trajectory, *, fraction: float = 0.5, time_chunk: int | None = None, instrument: Instrument | None = None,
) -> tuple[VerificationReport, np.ndarray, np.ndarray]:
    """:func:`verify`, also returning what it measured at the samples: the neighbour pairs
    ``(P, 2)`` (positioner indices, :func:`~fiberplan.geometry.neighbour_pairs`) and their
    clearances ``(T, P)`` in mm, exact where a pair's enclosing discs are closer than
    ``_PRUNE_MM`` (2 mm) and that gap, a lower bound, elsewhere (used by the motor profiles,
    which budget their deviation from the planned path by it)."""
    if not 0.0 < fraction < 1.0:
        raise TrajectoryError(f"fraction must lie in (0, 1), found {fraction}")
    if time_chunk is not None and (int(time_chunk) != time_chunk or time_chunk < 1):
        raise TrajectoryError(f"time_chunk must be an integer >= 1, found {time_chunk}")
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite samples are reported, not warned about
        return _verify(scenario, trajectory, fraction, None if time_chunk is None else int(time_chunk), instrument)


def _verify(
    scenario: Scenario, trajectory: Trajectory, fraction: float, time_chunk: int | None, instrument: Instrument | None,
) -> tuple[VerificationReport, np.ndarray, np.ndarray]:
    inst = scenario.instrument if instrument is None else instrument
    times = trajectory.times
    n_t, n = trajectory.joints.shape[0], trajectory.joints.shape[1]
    if n != scenario.n_positioners:
        raise TrajectoryError(f"trajectory has {n} positioners, scenario has {scenario.n_positioners}")
    pairs = neighbour_pairs(inst, scenario.base_xy)
    threaded = n_t * len(pairs) >= THREADED_PAIR_SAMPLES
    if time_chunk is None:  # the same memory on every thread count
        time_chunk = max(1, min(64, CHUNK_PAIR_SAMPLES // (THREADS if threaded else 1) // max(1, len(pairs))))
    report = VerificationReport(n_positioners=n, n_samples=n_t, n_pairs=len(pairs))
    ids = scenario.ids
    _check_finite(scenario, trajectory, report)
    # Unknown positions (non-finite samples) are left out of the geometric checks: NaN
    # compares false everywhere below, so they can neither hide nor fake a collision.
    joints = trajectory.joints if not report.non_finite else np.where(np.isfinite(trajectory.joints), trajectory.joints, np.nan)

    mismatch = np.flatnonzero(~np.all(np.abs(joints[0] - scenario.start) <= 1e-7, axis=1))
    report.start_mismatch_ids = [int(ids[k]) for k in mismatch]
    _check_limits(inst, scenario.ids, trajectory, report)
    _check_motors(inst, scenario.ids, trajectory, report)
    if len(pairs) == 0 or n_t == 0:
        return report, pairs, np.zeros((n_t, len(pairs)))

    combos = np.array(inst.capsule_pairs).reshape(-1, 2)
    names = [c.name for c in inst.capsules]
    radii_sum = np.array([inst.capsules[a].radius_mm + inst.capsules[b].radius_mm for a, b in combos])
    worst: dict[int, list[float]] = {}  # pair index -> [t_first, t_worst, clearance, combo]

    def record(pair_idx: np.ndarray, t: np.ndarray, clear_k: np.ndarray) -> None:
        best = clear_k.argmin(axis=1)
        value = clear_k[np.arange(len(best)), best]
        for p, tt, v, k in zip(pair_idx.tolist(), t.tolist(), value.tolist(), best.tolist(), strict=True):
            entry = worst.get(p)
            if entry is None:
                worst[p] = [tt, tt, v, k]
            else:
                entry[0] = min(entry[0], tt)
                if v < entry[2]:
                    entry[1], entry[2], entry[3] = tt, v, k

    # Clearances at every sample, chunk by chunk. A pair whose enclosing discs are more than
    # ``_PRUNE_MM`` apart cannot be closer than that: its clearance is replaced by that lower
    # bound, which only makes the checks between samples more cautious.
    sample_clear = np.empty((len(pairs), n_t)).T  # (T, P), a pair's samples contiguous (as the motor profiles read them)
    radii = np.array([c.radius_mm for c in inst.capsules])

    def sample_chunk(k0: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """Samples ``k0`` to ``k0 + time_chunk`` into ``sample_clear`` (rows no other chunk
        writes); returns what ``record`` needs, recorded afterwards in chunk order."""
        k1 = min(n_t, k0 + time_chunk)
        lower = _enclosing_disc_gap(inst, scenario.base_xy, scenario.orient, joints[k0:k1], pairs, radii)
        near_t, near_p = np.nonzero(lower < _PRUNE_MM)
        if len(near_t) == 0:
            sample_clear[k0:k1] = lower
            return 0, near_t, near_p, np.empty((0, len(combos)))
        i_rows, j_rows = pairs[near_p, 0], pairs[near_p, 1]
        exact = clearance_between(
            inst,
            scenario.base_xy[i_rows], scenario.orient[i_rows], joints[k0 + near_t, i_rows],
            scenario.base_xy[j_rows], scenario.orient[j_rows], joints[k0 + near_t, j_rows],
        )
        nearest = exact.min(axis=1)
        lower[near_t, near_p] = nearest
        sample_clear[k0:k1] = lower
        hit = nearest < 0.0
        return len(near_t), k0 + near_t[hit], near_p[hit], exact[hit]

    report.probes = 0
    for probes, t_hit, p_hit, exact_hit in _chunk_map(sample_chunk, range(0, n_t, time_chunk), threaded):
        report.probes += probes
        if len(p_hit):
            record(p_hit, times[t_hit], exact_hit)
    if report.non_finite:
        report.min_clearance_mm = float(np.min(sample_clear, where=np.isfinite(sample_clear), initial=np.inf))
    else:  # every sample finite: so is every clearance (no copy of the whole table)
        report.min_clearance_mm = float(sample_clear.min())

    # Between samples: bisect the intervals whose motion bound is not small against the clearance.
    if n_t > 1:
        _between_samples(inst, scenario, joints, times, pairs, sample_clear, fraction, report, record, worst, time_chunk, threaded)

    for p, (t_first, t_worst, value, k) in sorted(worst.items(), key=lambda item: item[1][0]):
        i, j = pairs[p]
        a, b = combos[int(k)]
        report.collisions.append(
            CollisionEvent(
                id_i=int(ids[i]),
                id_j=int(ids[j]),
                capsule_i=names[a],
                capsule_j=names[b],
                t_first_s=float(t_first),
                t_worst_s=float(t_worst),
                min_distance_mm=float(value + radii_sum[int(k)]),
                required_mm=float(radii_sum[int(k)]),
            )
        )
    return report, pairs, sample_clear


def _between_samples(
    inst: Instrument, scenario: Scenario, joints: np.ndarray, times: np.ndarray, pairs: np.ndarray, sample_clear: np.ndarray,
    fraction: float, report: VerificationReport, record: Callable[[np.ndarray, np.ndarray, np.ndarray], None],
    worst: dict[int, list[float]], time_chunk: int, threaded: bool,
) -> None:
    """Bisect every interval whose pairs' motion bound is not small against their clearance at
    both ends, until each piece is proven clear (the motion bound of :mod:`fiberplan.planners.safety`)
    or found colliding (``record``). The intervals to bisect are found ``time_chunk`` at a time."""
    rho = point_extents(inst)

    def intervals(k0: int) -> tuple[np.ndarray, ...]:
        k1 = min(len(joints) - 1, k0 + time_chunk)
        motion = motion_bound(rho, np.abs(joints[k0 + 1:k1 + 1] - joints[k0:k1]))  # (chunk, N)
        bound = motion[:, pairs[:, 0]] + motion[:, pairs[:, 1]]  # (chunk, P)
        c0, c1 = sample_clear[k0:k1], sample_clear[k0 + 1:k1 + 1]
        both = np.minimum(c0, c1)  # NaN where either is unknown; >= 0 where neither collides
        needs = (bound > fraction * both) & (both >= 0.0)  # then bound > 0 too
        kk, pp = np.nonzero(needs)
        return kk + k0, pp, c0[kk, pp], c1[kk, pp], bound[kk, pp]

    found = _chunk_map(intervals, range(0, len(joints) - 1, time_chunk), threaded)
    k_all, p_all, clo_all, chi_all, bnd_all = (np.concatenate(parts) for parts in zip(*found, strict=True))
    known = np.fromiter(worst.keys(), dtype=np.int64)  # pairs already found colliding at the samples

    def bisect(group: np.ndarray) -> tuple[int, float, list[tuple[np.ndarray, ...]]]:
        """Bisect the intervals ``group``; returns the probes, the smallest clearance probed and
        the collisions found, in order. The groups split the pairs: a pair's pieces are probed
        in the same order whichever group it is in, and only its own hits stop its probing."""
        k_idx, p_idx, c_lo, c_hi, bnd = k_all[group], p_all[group], clo_all[group], chi_all[group], bnd_all[group]
        lo = np.zeros(len(k_idx))
        hi = np.ones(len(k_idx))
        probes, smallest, hits = 0, np.inf, []
        colliding = known
        for _ in range(_MAX_BISECTIONS):
            if len(k_idx) == 0:
                break
            mid = 0.5 * (lo + hi)
            i_rows, j_rows = pairs[p_idx, 0], pairs[p_idx, 1]
            q_i = (1 - mid)[:, None] * joints[k_idx, i_rows] + mid[:, None] * joints[k_idx + 1, i_rows]
            q_j = (1 - mid)[:, None] * joints[k_idx, j_rows] + mid[:, None] * joints[k_idx + 1, j_rows]
            clear_k = clearance_between(
                inst,
                scenario.base_xy[i_rows], scenario.orient[i_rows], q_i,
                scenario.base_xy[j_rows], scenario.orient[j_rows], q_j,
            )
            cmid = clear_k.min(axis=1)
            probes += len(cmid)
            smallest = min(smallest, float(np.nanmin(cmid, initial=np.inf)))
            hit = cmid < 0.0
            if np.any(hit):
                t_mid = times[k_idx] + mid * (times[k_idx + 1] - times[k_idx])
                hits.append((p_idx[hit], t_mid[hit], clear_k[hit]))
                colliding = np.union1d(colliding, p_idx[hit])
            # Split every surviving piece in two halves with half the motion bound.
            half = 0.5 * bnd
            keep = ~hit
            new_k = np.concatenate([k_idx[keep], k_idx[keep]])
            new_p = np.concatenate([p_idx[keep], p_idx[keep]])
            new_lo = np.concatenate([lo[keep], mid[keep]])
            new_hi = np.concatenate([mid[keep], hi[keep]])
            new_clo = np.concatenate([c_lo[keep], cmid[keep]])
            new_chi = np.concatenate([cmid[keep], c_hi[keep]])
            new_b = np.concatenate([half[keep], half[keep]])
            still = new_b > fraction * np.minimum(new_clo, new_chi)
            # Pairs already known to collide need no further probing.
            if len(colliding):
                still &= ~np.isin(new_p, colliding)
            k_idx, p_idx, lo, hi = new_k[still], new_p[still], new_lo[still], new_hi[still]
            c_lo, c_hi, bnd = new_clo[still], new_chi[still], new_b[still]
        return probes, smallest, hits

    split = threaded and len(k_all) >= _THREADED_INTERVALS  # one group per thread, by pair
    groups = [np.flatnonzero(p_all % THREADS == g) for g in range(THREADS)] if split else [np.arange(len(k_all))]
    for probes, smallest, hits in _chunk_map(lambda g: bisect(groups[g]), range(len(groups)), threaded):
        report.probes += probes
        report.min_clearance_mm = min(report.min_clearance_mm, smallest)
        for p_hit, t_hit, clear_hit in hits:
            record(p_hit, t_hit, clear_hit)


def _enclosing_disc_gap(
    instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray, pairs: np.ndarray, radii: np.ndarray
) -> np.ndarray:
    """Lower bound ``(T, P)`` on each pair's clearance from discs enclosing every capsule of a
    positioner (centred on the bounding box of the capsules' end points). The few end points
    are taken one at a time: numpy reduces a short last axis several times slower."""
    start_x, start_y, end_x, end_y = capsule_coordinates(instrument, base_xy, orient, joints)  # (T, N, C) each
    n_caps = start_x.shape[-1]
    xs = [start_x[..., k] for k in range(n_caps)] + [end_x[..., k] for k in range(n_caps)]
    ys = [start_y[..., k] for k in range(n_caps)] + [end_y[..., k] for k in range(n_caps)]
    cx = 0.5 * (functools.reduce(np.minimum, xs) + functools.reduce(np.maximum, xs))  # (T, N)
    cy = 0.5 * (functools.reduce(np.minimum, ys) + functools.reduce(np.maximum, ys))
    point_radii = np.concatenate([radii, radii])
    radius = functools.reduce(
        np.maximum, (np.sqrt((x - cx) ** 2 + (y - cy) ** 2) + r for x, y, r in zip(xs, ys, point_radii.tolist(), strict=True))
    )  # (T, N)
    dx, dy = cx[:, pairs[:, 0]] - cx[:, pairs[:, 1]], cy[:, pairs[:, 0]] - cy[:, pairs[:, 1]]
    return np.sqrt(dx * dx + dy * dy) - radius[:, pairs[:, 0]] - radius[:, pairs[:, 1]]


def _check_finite(scenario: Scenario, trajectory: Trajectory, report: VerificationReport) -> None:
    """Append every non-finite sample, as runs of consecutive samples per positioner."""
    bad = ~np.isfinite(trajectory.joints).all(axis=-1)  # (T, N)
    if not bad.any():
        return
    times, ids = trajectory.times, scenario.ids
    for i in np.flatnonzero(bad.any(axis=0)):
        col = np.concatenate([[False], bad[:, i], [False]]).astype(np.int8)
        edges = np.diff(col)
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)  # [start, stop)
        for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
            report.non_finite.append(NonFiniteRun(int(ids[i]), float(times[a]), float(times[b - 1]), b - a))


def _check_limits(inst: Instrument, ids: np.ndarray, trajectory: Trajectory, report: VerificationReport) -> None:
    """Append hard-stop and speed violations: one per positioner, joint and kind, at its worst sample."""
    joints, times = trajectory.joints, trajectory.times
    lim = inst.limits_rad
    for axis, joint_name in enumerate(("alpha", "beta")):
        values = joints[:, :, axis]
        for sign, limit in ((-1.0, lim[axis, 0]), (1.0, lim[axis, 1])):
            excess = sign * (values - limit)
            mask = excess > _ANGLE_TOL
            for i in np.flatnonzero(mask.any(axis=0)):
                first = int(np.argmax(mask[:, i]))
                worst = int(np.nanargmax(np.where(mask[:, i], excess[:, i], -np.inf)))
                report.limit_violations.append(
                    LimitViolation(int(ids[i]), joint_name, float(times[worst]), float(values[worst, i]), float(limit), "hard_stop",
                                   float(times[first]))
                )
        if len(times) > 1:
            speed = np.abs(np.diff(values, axis=0)) / np.diff(times)[:, None]
            max_speed = inst.speeds_rad_s[axis]
            fast = speed > max_speed * (1 + _SPEED_REL_TOL) + 1e-12
            for i in np.flatnonzero(fast.any(axis=0)):
                first = int(np.argmax(fast[:, i]))
                worst = int(np.nanargmax(np.where(fast[:, i], speed[:, i], -np.inf)))
                report.limit_violations.append(
                    LimitViolation(int(ids[i]), joint_name, float(times[worst]), float(speed[worst, i]), float(max_speed), "speed",
                                   float(times[first]))
                )


def _check_motors(inst: Instrument, ids: np.ndarray, trajectory: Trajectory, report: VerificationReport) -> None:
    """Append violations of the instrument's motor limits: one per positioner, joint and kind, at its worst.

    Each interval between samples is one constant-speed command. A joint is moving where its
    speed exceeds 1e-9 rad/s. ``min_speed``: a moving joint slower than the minimum (worst: the
    slowest). ``speed_change``: consecutive moving commands in one direction whose speeds differ
    by more than ``max_speed_change`` times the first (worst: the largest ratio; starts and
    stops exempt). ``reversal``: consecutive moving commands in opposite directions (worst: the
    largest jump). ``segments``: more constant-speed runs than ``max_segments``. ``start_stops``:
    more starts from rest than ``max_start_stops``.
    """
    motors = inst.motors
    report.motors_checked = motors.stated
    times = trajectory.times
    if not motors.stated or len(times) < 2:
        return
    dt = np.diff(times)[:, None]
    for axis, joint_name in enumerate(("alpha", "beta")):
        v = np.diff(trajectory.joints[:, :, axis], axis=0) / dt  # (T-1, N)
        for kind, mask, value, limit, worst_is_max in motor_breaches(motors, v, axis):
            offset = 0 if kind == "min_speed" else 1  # a change is at the start of the second command
            for i in np.flatnonzero(mask.any(axis=0)):
                first = int(np.argmax(mask[:, i]))
                pick = np.where(mask[:, i], value[:, i], -np.inf if worst_is_max else np.inf)
                worst = int(np.argmax(pick) if worst_is_max else np.argmin(pick))
                report.motor_violations.append(LimitViolation(
                    int(ids[i]), joint_name, float(times[worst + offset]), float(value[worst, i]), float(limit), kind,
                    float(times[first + offset])))
        from_rest, starts = motor_runs(v)
        if motors.max_start_stops is not None:
            cycles = from_rest.sum(axis=0)
            for i in np.flatnonzero(cycles > motors.max_start_stops):
                k = int(np.flatnonzero(from_rest[:, i])[motors.max_start_stops])
                report.motor_violations.append(LimitViolation(
                    int(ids[i]), joint_name, float(times[-1]), float(cycles[i]), float(motors.max_start_stops), "start_stops", float(times[k])))
        if motors.max_segments is not None:
            count = starts.sum(axis=0)
            for i in np.flatnonzero(count > motors.max_segments):
                k = int(np.flatnonzero(starts[:, i])[motors.max_segments])
                report.motor_violations.append(LimitViolation(
                    int(ids[i]), joint_name, float(times[-1]), float(count[i]), float(motors.max_segments), "segments", float(times[k])))


_MOVING = 1e-9  # rad/s: a joint faster than this is moving


def motor_breaches(motors: MotorLimits, v: np.ndarray, axis: int) -> list[tuple[str, np.ndarray, np.ndarray, float, bool]]:
    """The commands of one joint (``axis``) that break a stated motor rule, from its speeds ``v``
    (``(K, N)`` rad/s, one constant-speed command per step): per rule ``(kind, mask, value, limit,
    worst is the largest)``, the masks ``(K, N)`` for ``min_speed`` and ``(K - 1, N)`` (the second
    of two commands) for ``reversal`` and ``speed_change`` (see :func:`_check_motors`)."""
    moving = np.abs(v) > _MOVING
    found: list[tuple[str, np.ndarray, np.ndarray, float, bool]] = []
    if motors.min_speed_rad_s is not None:
        low = motors.min_speed_rad_s[axis]
        found.append(("min_speed", moving & (np.abs(v) < low * (1 - 1e-9)), np.abs(v), low, False))
    both = moving[:-1] & moving[1:]
    jump = np.abs(v[1:] - v[:-1])
    if motors.stop_before_reversing:
        found.append(("reversal", both & (v[:-1] * v[1:] < 0), jump, 0.0, True))
    if motors.max_speed_change is not None:
        ratio = jump / np.maximum(np.abs(v[:-1]), _MOVING)
        found.append(("speed_change", both & (v[:-1] * v[1:] > 0) & (ratio > motors.max_speed_change * (1 + 1e-9)),
                      ratio, motors.max_speed_change, True))
    return found


def motor_runs(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(from_rest, starts)`` ``(K, N)``: the commands of a joint with speeds ``v`` that start it from
    rest (counted against ``max_start_stops``) and that begin a constant-speed run (counted against
    ``max_segments``)."""
    moving = np.abs(v) > _MOVING
    first = np.ones((1, v.shape[1]), dtype=bool)
    from_rest = moving & np.vstack([first, ~moving[:-1]])
    starts = moving & np.vstack([first, ~moving[:-1] | (np.abs(v[1:] - v[:-1]) > _MOVING)])
    return from_rest, starts


_DATASET_CHECKS = (
    ("id", "ids"),
    ("base_xy_mm", "base_xy"),
    ("orient_rad", "orient"),
    ("start_rad", "start"),
    ("target_rad", "target"),
    ("target_xy_mm", "target_xy"),
    ("has_target", "has_target"),
)


def check_run_file(run: RunFile) -> tuple[list[str], list[str]]:
    """Check a trajectory file against itself: ``(mismatches, warnings)``.

    Mismatches (the file fails verification): a ``/positioners/*`` dataset missing or
    disagreeing with the embedded scenario (ids, bases, orientations, starts, targets).
    Warnings: the embedded instrument table carries a preset's name but differs from the
    preset shipped with fiberplan (each differing field named; ``fiberplan verify --instrument``
    checks against the preset instead).
    """
    mismatches: list[str] = []
    sc = run.scenario
    for dataset, attr in _DATASET_CHECKS:
        stored = run.positioners.get(dataset)
        expected = np.asarray(getattr(sc, attr))
        if stored is None:
            mismatches.append(f"/positioners/{dataset} is missing")
            continue
        if stored.shape != expected.shape:
            mismatches.append(f"/positioners/{dataset} has shape {stored.shape}, the embedded scenario {expected.shape}")
            continue
        if expected.dtype.kind in "biu":
            differ = np.flatnonzero((stored != expected).reshape(len(expected), -1).any(axis=1))
        else:
            close = np.isclose(stored.astype(float), expected.astype(float), rtol=0.0, atol=1e-9)
            differ = np.flatnonzero(~close.reshape(len(expected), -1).all(axis=1))
        if len(differ):
            k = int(differ[0])
            mismatches.append(
                f"/positioners/{dataset} disagrees with the embedded scenario for {len(differ)} positioner(s), first "
                f"positioner {sc.ids[k]}: dataset {np.round(stored[k], 9).tolist()}, scenario {np.round(expected[k], 9).tolist()}"
            )
    warnings: list[str] = []
    if sc.instrument_preset is None and sc.instrument.name in preset_names():
        differences = instrument_differences(sc.instrument, load_instrument(sc.instrument.name))
        if differences:
            warnings.append(
                f"the file embeds an instrument named {sc.instrument.name!r} that differs from the shipped preset: "
                f"{'; '.join(differences)}; run `fiberplan verify FILE --instrument {sc.instrument.name}` to check against the preset"
            )
    return mismatches, warnings


def instrument_differences(found: Instrument, reference: Instrument) -> list[str]:
    """The fields of two instruments that differ, each ``"field: found X, reference Y"``."""
    out: list[str] = []
    for name in (
        "pitch_mm", "alpha_arm_mm", "beta_arm_mm", "alpha_speed_rad_s", "beta_speed_rad_s", "alpha_limits_rad",
        "beta_limits_rad", "datum_rad", "tolerance_mm",
    ):
        a, b = np.asarray(getattr(found, name), dtype=float), np.asarray(getattr(reference, name), dtype=float)
        if a.shape != b.shape or not np.allclose(a, b, rtol=1e-12, atol=1e-12):
            out.append(f"{name}: file {np.round(a, 9).tolist()}, preset {np.round(b, 9).tolist()}")
    if len(found.capsules) != len(reference.capsules):
        out.append(f"capsules: file has {len(found.capsules)}, preset {len(reference.capsules)}")
    else:
        for k, (ca, cb) in enumerate(zip(found.capsules, reference.capsules, strict=True)):
            for name in ("name", "arm", "start_mm", "end_mm", "radius_mm", "layer"):
                va, vb = getattr(ca, name), getattr(cb, name)
                if va != vb:
                    out.append(f"capsules[{k}].{name}: file {va!r}, preset {vb!r}")
    return out
