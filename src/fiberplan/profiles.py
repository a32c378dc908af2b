"""Motor profiles: a verified trajectory as a few constant-speed segments per joint.

A planner's samples (every 10-50 ms, speeds that may jump from full to zero in one step) are
not what a motor controller takes. :func:`discretise` turns them into, per positioner and
joint, a start time, a start angle and a list of ``(duration, speed)`` segments: positions
piecewise linear in time, speeds piecewise constant (reference 004, section 11.5). The
algorithm and its guarantee are in ``formulations/profiles.md``; in short:

1. **Corridor.** Each positioner ``i`` may leave its planned path by at most a budget
   ``B_i(t) = f c_ij(t) / 2`` (``f c_ij`` when ``j`` never moves) for every neighbour ``j``
   with planned clearance ``c_ij``, measured by the motion bound
   ``rho_alpha |d alpha| + rho_beta |d beta|`` (:func:`fiberplan.geometry.motion_bound`): alpha
   gets half of it, beta what alpha leaves. At samples, no pair then comes closer than
   ``(1 - f) c_ij``. Hard stops bound the corridor too.
2. **Fewest segments.** From its start, each joint takes the longest constant-speed segment
   that stays in its corridor at every sample, whose speed the motors accept after the previous
   one (zero, or between the minimum and the top speed; within the relative speed change of the
   previous speed, or a stop first when reversing), and from whose end the target is still
   reachable. Breakpoints lie on the sample grid (on multiples of the controller's command
   period when the instrument states one); the last one is the target, exactly.
3. **Always re-checked.** The profiles are rebuilt into a trajectory (:meth:`Profiles.trajectory`)
   and passed through the independent verifier. Positioners in a collision are fitted again in
   a corridor four times narrower, twice; then they follow their verified planned samples.
   What cannot be verified is refused (:class:`~fiberplan.errors.ProfileError`), never exported.
4. **Creeps and pauses.** A segment still below the minimum speed becomes a move at the minimum
   and a hold (:func:`_mend_creeps`); where a joint would still reverse without a stop or jump in
   speed beyond the motors' limit, every positioner holds still for one sample step at that
   instant (:func:`_paused`: a stop and a start are exempt from both limits; a held
   configuration is one already verified); a joint moving through a pause runs through it,
   a little slower, where its motors allow (:func:`_stretchable`). The result is verified again.
5. **Smoothed samples.** Where a plan chatters (a joint turning back at every sample where it
   waits at a neighbour, as the dnf's plans do), the fit is made from its samples with each
   zigzag replaced by its midline (:func:`_dechattered`), verified first; the better fit is kept.
6. **Shortcuts.** Where limits are still broken, the joints of the positioners breaking them are
   cut short: straight moves between samples wherever every pair of theirs stays clear
   (:func:`_shortcut_joint`), verified whole, fitted again; the better fit is kept.
"""

from __future__ import annotations

import functools
import itertools
import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fiberplan import _fork, geometry
from fiberplan.errors import ProfileError
from fiberplan.geometry import point_extents
from fiberplan.instrument import Instrument, MotorLimits
from fiberplan.ramps import verify_commands
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult, Trajectory
from fiberplan.verify import VerificationReport, verify_with_clearances

JOINTS = ("alpha", "beta")
DEFAULT_FRACTION = 0.5  # f: the share of a pair's planned clearance the two profiles may use
NARROWING = 0.25  # the corridor of a positioner found in a collision shrinks by this factor per round
REFIT_ROUNDS = 2  # narrower fits before a positioner follows its planned samples
SAMPLE_MAX_S = 0.05  # the rebuilt trajectory has a sample at least this often
TIME_ROUND_S = 1e-9  # breakpoint times of different joints closer than this are one sample
SEARCH = (4, 400)  # (next segments tried from each breakpoint, breakpoints one joint's search may try) in the first pass
REFIT_SEARCH = (8, 800)  # the same for a positioner fitted again after breaking a motor limit
ONE_SEGMENT_SHORTCUTS = True  # joints one segment fits skip the search (all at once: :meth:`_Fitter._straight_pass`; one by one: :func:`_fit_joint`)
REFIT_PASSES = 1  # passes over the positioners that break a motor limit
ALPHA_SHARES = (0.5, 0.75)  # splits of a refitted positioner's room between alpha and beta
REFIT_FRACTION = 0.9  # share of a pair's planned clearance a positioner refitted after breaking a motor limit may use
WIDER_FRACTIONS = (0.7, 0.9)  # shares of the planned clearances tried in turn where the pauses leave motor-limit violations
REFINE = 5  # a positioner that breaks a motor limit is fitted again with this many breakpoint instants per sample interval
DECHATTER = True  # where the pauses leave violations or lengthen the makespan, a fit from the smoothed samples is tried (:func:`_dechatter`)
FORK_SEARCH = 200  # positioners to search from which half of them are fitted in a forked process (SDSS 547: all of them)
CHATTER_SHARE = 0.02  # a plan whose joints turn back after this share of their moving steps is fitted from its smoothed samples first
DECHATTER_GROWTH = 0.05  # the share of the makespan the pauses may add before the smoothed samples are tried
DECHATTER_ROUNDS = 3  # verifications of the smoothed samples, each keeping as planned the positioners found in a collision
STRETCH_PAUSES = True  # joints run through the pauses inside their segments where the motors allow (:func:`_stretch_pauses`)
EARLY_ARRIVAL_MM = 0.25  # a joint running through pauses at its minimum speed stays this close to the paused profile (motion bound)
STRETCH_ROUNDS = 3  # verifications of the stretched pauses, each keeping split the positioners found in a collision
_TOL = 1e-12


@dataclass(frozen=True, eq=False)
class JointProfile:
    """One joint's commands: from ``start_s`` at ``start_rad``, segments of constant speed.

    Attributes:
        start_s: time the first segment starts (s); the joint holds ``start_rad`` before.
        start_rad: angle at ``start_s`` (rad).
        durations_s: ``(S,)`` segment durations (s), positive.
        speeds_rad_s: ``(S,)`` segment speeds (rad/s); zero is a hold.
    """

    start_s: float
    start_rad: float
    durations_s: np.ndarray
    speeds_rad_s: np.ndarray

    def knots(self) -> tuple[np.ndarray, np.ndarray]:
        """Breakpoint times and angles ``(S + 1,)`` each: the time-stamped angle points (read-only)."""
        return self._knots

    @functools.cached_property
    def _knots(self) -> tuple[np.ndarray, np.ndarray]:
        if len(self.durations_s) == 1:  # most joints: the same values as the sums below, without their cost
            d = float(self.durations_s[0])
            times = np.array([self.start_s + 0.0, self.start_s + d])
            angles = np.array([self.start_rad + 0.0, self.start_rad + float(self.speeds_rad_s[0]) * d])
        else:
            times = self.start_s + np.concatenate([[0.0], np.cumsum(self.durations_s)])
            angles = self.start_rad + np.concatenate([[0.0], np.cumsum(self.speeds_rad_s * self.durations_s)])
        times.flags.writeable = False
        angles.flags.writeable = False
        return times, angles


@dataclass(frozen=True, eq=False)
class Profiles:
    """Motor profiles of every positioner of a scenario, with the verifier's report on them.

    Attributes:
        scenario: the positioners.
        joints: ``(positioner index, joint index) -> JointProfile`` for every joint that moves;
            the others hold their start.
        report: the verifier's report on :meth:`trajectory` (``None`` until checked).
        stats: how the profiles were made (segments, rounds, fallbacks, limits, timings).
    """

    scenario: Scenario
    joints: dict[tuple[int, int], JointProfile]
    report: VerificationReport | None = None
    stats: dict[str, Any] = field(default_factory=dict)

    def knots(self) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
        """Time-stamped angle points of every moving joint (see :meth:`JointProfile.knots`)."""
        return {key: prof.knots() for key, prof in self.joints.items()}

    def trajectory(self) -> Trajectory:
        """The trajectory the profiles command (:func:`rebuild`)."""
        return rebuild(self.scenario, self.knots())

    def segment_counts(self) -> np.ndarray:
        """``(N, 2)`` segments per joint (holds between moves included; 0: the joint never moves)."""
        counts = np.zeros((self.scenario.n_positioners, 2), dtype=int)
        for (i, axis), prof in self.joints.items():
            counts[i, axis] = len(prof.durations_s)
        return counts

    def summary(self) -> dict[str, Any]:
        """JSON-ready figures: segments per joint, limits applied, makespans, the verifier's verdict."""
        counts = self.segment_counts()
        moving = counts[counts > 0]
        report = self.report
        return {
            "positioners": self.scenario.n_positioners,
            "joints_moving": len(moving),
            "segments_median": float(np.median(moving)) if len(moving) else 0.0,
            "segments_p95": float(np.percentile(moving, 95)) if len(moving) else 0.0,
            "segments_max": int(moving.max()) if len(moving) else 0,
            **self.stats,
            "verified_ok": None if report is None else report.ok,
            "collisions": None if report is None else report.n_collisions,
            "min_clearance_mm": None if report is None else report.min_clearance_mm,
            "motor_violations": None if report is None or not report.motors_checked else len(report.motor_violations),
        }


def rebuild(scenario: Scenario, knots: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]) -> Trajectory:
    """The trajectory of piecewise-linear joint paths: ``(positioner index, joint index) ->
    (times, angles)`` points, each joint holding its first angle before its first point and its
    last after; joints not given hold the scenario's start.

    The grid is every point's time (rounded to ``TIME_ROUND_S``), with samples in between at
    least every ``SAMPLE_MAX_S``: a function of the points only, so every export form rebuilds
    the same trajectory, and linear interpolation between its samples is the paths themselves.
    """
    stamps = [t for t, _ in knots.values()]
    every = np.unique(np.round(np.concatenate([[0.0], *stamps]) / TIME_ROUND_S) * TIME_ROUND_S)
    if len(every) > 1:
        pieces = np.maximum(1, np.ceil(np.diff(every) / SAMPLE_MAX_S - 1e-9).astype(int))
        fill = [np.linspace(a, b, k, endpoint=False) for a, b, k in zip(every[:-1], every[1:], pieces, strict=True)]
        every = np.concatenate([*fill, every[-1:]])
    joints = np.repeat(scenario.start[None], len(every), axis=0)
    for (i, axis), (t_knot, q_knot) in knots.items():
        joints[:, i, axis] = np.interp(every, t_knot, q_knot)
    return Trajectory(every, joints)


def limits_applied(instrument: Instrument) -> dict[str, Any]:
    """The motor limits the profiles respect, in the instrument file's units (``None``: unconstrained)."""
    motors = instrument.motors
    rpm = 60.0 / (2.0 * np.pi)
    return {
        "max_speed_rpm": [round(instrument.alpha_speed_rad_s * rpm, 9), round(instrument.beta_speed_rad_s * rpm, 9)],
        "min_speed_rpm": None if motors.min_speed_rad_s is None else [round(v * rpm, 9) for v in motors.min_speed_rad_s],
        "max_speed_change": motors.max_speed_change,
        "stop_before_reversing": motors.stop_before_reversing,
        "max_segments": motors.max_segments,
        "command_period_s": motors.command_period_s,
        "ramp_time_s": motors.ramp_time_s,
    }


def discretise(
    result: PlanResult, *, fraction: float = DEFAULT_FRACTION, instrument: Instrument | None = None, pauses: bool = True,
) -> Profiles:
    """Motor profiles of a plan result (see :func:`discretise_trajectory`)."""
    return discretise_trajectory(result.scenario, result.trajectory, fraction=fraction, instrument=instrument, pauses=pauses)


def discretise_trajectory(
    scenario: Scenario, trajectory: Trajectory, *, fraction: float = DEFAULT_FRACTION, instrument: Instrument | None = None,
    pauses: bool = True,
) -> Profiles:
    """Motor profiles of a verified trajectory, rebuilt and verified (see the module docstring).

    Args:
        scenario: the positioners the trajectory moves.
        trajectory: a trajectory the verifier passes (a plan result's, or anyone's).
        fraction: the share ``f`` of each pair's planned clearance the profiles may use (0, 1).
        instrument: the instrument whose limits apply (default: the scenario's).
        pauses: mend what the fit leaves of the motor limits: a creep below the minimum speed
            becomes a move at the minimum and a hold (:func:`_mend_creeps`); where a joint still
            reverses without a stop or changes speed by more than the motors allow, every
            positioner holds still for one sample step (or command period) at that instant
            (:func:`_paused`): the makespan grows by the pauses, and joints moving through a
            pause run through it where they can (:data:`STRETCH_PAUSES`). Where that leaves
            violations or adds more than :data:`DECHATTER_GROWTH` of makespan, or where the plan
            chatters (:data:`CHATTER_SHARE`, then first), the fit is made from the planned
            samples with their zigzags smoothed and verified (:func:`_dechatter`,
            ``stats["source"]``). Where violations are still left, the fit is made again in
            wider shares of the planned clearances (:data:`WIDER_FRACTIONS`: fewer breakpoints
            to mend); still left, the violating positioners' back-and-forth is cut short where
            every pair stays clear and fitted again (:data:`SHORTCUT`, :func:`_shortcut`).
            The verified profiles with the fewest violations, then the shortest makespan, then
            the fewest segments are kept (``stats["fraction"]``,
            ``stats["fractions_tried"]``, ``stats["sources_tried"]``). Where the instrument
            states a ramp time, every check is also of the motion the motors execute
            (:func:`fiberplan.ramps.verify_commands`), the fit keeps the acceleration, and
            ``stats["makespan_after_s"]`` includes the last ramp.

    Returns:
        :class:`Profiles` with ``report.ok`` true.

    Raises:
        ProfileError: the trajectory is not verified clean, ``fraction`` is outside (0, 1), the
            command period is not a multiple of the sample step, or the profiles of some
            positioners could not be verified even on their planned samples (named).
    """
    inst = scenario.instrument if instrument is None else instrument
    if not 0.0 < fraction < 1.0:
        raise ProfileError(f"fraction must lie in (0, 1), found {fraction}")
    started = time.perf_counter()
    source, pairs, clear = verify_with_clearances(scenario, trajectory, instrument=inst)
    verify_s = time.perf_counter() - started
    if not source.ok:
        raise ProfileError(
            f"profiles are made only from a verified trajectory; this one has {source.n_collisions} collision(s), "
            f"{len(source.limit_violations)} limit violation(s), {source.n_non_finite_samples} non-finite sample(s): "
            "run `fiberplan verify` on it"
        )
    sources = {"planned": (trajectory, pairs, _near(clear))}  # the verifier's table, its own: made each sample's room in place
    tried: list[tuple[str, float]] = []
    best: tuple[dict[tuple[int, int], JointProfile], VerificationReport, dict[str, Any]] | None = None
    failed: list[ProfileError] = []
    planned_makespan = _makespan(trajectory.times, trajectory.joints)

    def attempt(name: str, f: float) -> None:
        """One fit from the source ``name`` in the share ``f``; kept if better than the best so far
        (:func:`_quality`)."""
        nonlocal best, verify_s
        try:
            samples, pairs_of, near_of = sources[name]
            made = _attempt(scenario, samples, inst, pairs_of, near_of, f, pauses)
        except ProfileError as e:
            failed.append(e)  # profiles that cannot be verified: the others stand
            return
        tried.append((name, f))
        verify_s += made[3]
        made[2]["source"] = name
        if best is None or _quality(made[:3]) < _quality(best):
            best = made[:3]

    def mended() -> bool:
        """Whether the best profiles so far break no motor limit and the pauses cost at most
        :data:`DECHATTER_GROWTH` of the planned makespan."""
        return best is not None and not best[1].motor_violations and best[2]["makespan_after_s"] <= planned_makespan * (1.0 + DECHATTER_GROWTH)

    def smoothed_attempt() -> int:
        """The fit from the smoothed samples, if they verify (:func:`_dechatter`); the samples changed."""
        nonlocal verify_s
        dechattered, changed, checked_s = _dechatter(scenario, trajectory, inst)
        verify_s += checked_s
        if dechattered is not None:
            sources["dechattered"] = dechattered
            attempt("dechattered", fraction)
        return changed

    smoothed = 0
    smoothing = pauses and DECHATTER and inst.motors.stated
    if smoothing and chatters(trajectory.joints):  # a chattering plan: the smoothed samples first,
        smoothed = smoothed_attempt()
        if best is None or best[1].motor_violations:  # and as planned only where they leave violations
            attempt("planned", fraction)
    else:
        attempt("planned", fraction)
        if smoothing and best is not None and best[1].motors_checked and not mended():
            smoothed = smoothed_attempt()
    if best is None:
        raise failed[-1]
    for f in (w for w in WIDER_FRACTIONS if w > fraction):
        if not (pauses and best[1].motors_checked and best[1].motor_violations):
            break  # wider corridors are tried only where the pauses leave motor-limit violations
        attempt(best[2]["source"], f)
    cut = 0
    if smoothing and SHORTCUT and best[1].motors_checked and best[1].motor_violations:
        # the last resort: the violating positioners' back-and-forth cut short where every pair stays clear
        samples, pairs_of, near_of = sources[best[2]["source"]]
        targets = {scenario.index_of(v.positioner_id) for v in best[1].motor_violations}
        shortened, cut, checked_s = _shortcut(scenario, inst, samples, pairs_of, near_of, targets)
        verify_s += checked_s
        if shortened is not None:
            sources["shortcut"] = shortened
            attempt("shortcut", fraction)
    joints, report, stats = best
    stats |= {"fractions_tried": [f for _, f in tried], "sources_tried": [name for name, _ in tried], "dechattered_samples": smoothed,
              "shortcut_samples": cut,
              "makespan_before_s": planned_makespan,
              "discretise_s": time.perf_counter() - started, "of_which_verify_s": verify_s}
    return Profiles(scenario, joints, report, stats)


def _named(report: VerificationReport) -> set[int]:
    """The ids of the positioners in a collision or beyond a hard stop or top speed in ``report``."""
    return {e.id_i for e in report.collisions} | {e.id_j for e in report.collisions} | {v.positioner_id for v in report.limit_violations}


def _quality(made: tuple[dict[tuple[int, int], JointProfile], VerificationReport, dict[str, Any]]) -> tuple[int, float, int]:
    """What makes one set of verified profiles better than another: fewer motor-limit
    violations, then a shorter makespan, then fewer segments."""
    joints, report, stats = made
    return len(report.motor_violations), stats["makespan_after_s"], sum(len(p.durations_s) for p in joints.values())


def _turn_share(joints: np.ndarray) -> float:
    """The share of the moving joint steps ``(T, N, 2)`` after which the joint turns back."""
    step = np.diff(joints, axis=0)
    return float(np.count_nonzero(step[1:] * step[:-1] < 0.0)) / max(int(np.count_nonzero(step)), 1)


def chatters(joints: np.ndarray) -> bool:
    """Whether planned samples ``(T, N, 2)`` chatter: their joints turn back after at least
    :data:`CHATTER_SHARE` of their moving steps (a planner waiting at a neighbour by bouncing
    off it, as the dnf's plans do). Such samples are fitted from their smoothed midline first."""
    return _turn_share(joints) >= CHATTER_SHARE


def _dechattered(joints: np.ndarray, keep: set[int]) -> np.ndarray:
    """The planned samples ``(T, N, 2)`` with each zigzag smoothed: at every sample where a joint
    reverses, and at the samples either side, the angle becomes ``(q[k-1] + 2 q[k] + q[k+1]) / 4``
    (a chatter at the sample step, ``+ - + -``, becomes its midline; a steady motion is unchanged).
    The first and last samples and the positioners in ``keep`` (indices) stay as planned. Each
    new sample is a convex combination of planned ones, and each step one of planned steps: the
    speed bound and the hard stops still hold."""
    step = np.diff(joints, axis=0)
    turns = np.zeros(joints.shape, dtype=bool)
    turns[1:-1] = step[1:] * step[:-1] < 0.0
    near = turns.copy()
    near[1:] |= turns[:-1]
    near[:-1] |= turns[1:]
    near[0] = near[-1] = False
    if keep:
        near[:, sorted(keep)] = False
    out = joints.copy()
    out[1:-1] = np.where(near[1:-1], 0.25 * joints[:-2] + 0.5 * joints[1:-1] + 0.25 * joints[2:], joints[1:-1])
    return out


def _dechatter(
    scenario: Scenario, trajectory: Trajectory, inst: Instrument,
) -> tuple[tuple[Trajectory, np.ndarray, np.ndarray] | None, int, float]:
    """The planned trajectory with its zigzags smoothed (:func:`_dechattered`), verified with its
    clearances; positioners found in a collision keep their planned samples and the rest is
    verified again, up to :data:`DECHATTER_ROUNDS` times (:func:`_verified_rounds`)."""
    return _verified_rounds(scenario, trajectory, inst, DECHATTER_ROUNDS, lambda keep: _dechattered(trajectory.joints, keep))


def _verified_rounds(
    scenario: Scenario, trajectory: Trajectory, inst: Instrument, rounds: int, changed_joints: Callable[[set[int]], np.ndarray],
) -> tuple[tuple[Trajectory, np.ndarray, np.ndarray] | None, int, float]:
    """New samples for ``trajectory`` (``changed_joints(keep)``: the positioners ``keep``, indices,
    as planned), verified with their clearances; positioners found in a collision are kept as
    planned and the rest is verified again, up to ``rounds`` times. Returns ``((trajectory, pairs,
    clearances as :func:`_near` leaves them) or None, samples changed, time spent verifying)``."""
    keep: set[int] = set()
    verify_s = 0.0
    for _ in range(rounds):
        joints = changed_joints(keep)
        changed = int(np.count_nonzero(joints != trajectory.joints))
        if not changed:
            return None, 0, verify_s
        candidate = Trajectory(trajectory.times, joints)
        checked = time.perf_counter()
        report, pairs, clear = verify_with_clearances(scenario, candidate, instrument=inst)
        verify_s += time.perf_counter() - checked
        if report.ok:
            return (candidate, pairs, _near(clear)), changed, verify_s
        named = {scenario.index_of(ident) for ident in _named(report)}
        if named <= keep:
            return None, 0, verify_s
        keep |= named
    return None, 0, verify_s


SHORTCUT = True  # where violations are left, the violating positioners' back-and-forth motion is cut short (:func:`_shortcut`)
SHORTCUT_CLEARANCE_MM = 0.5  # a shortcut keeps each pair this clear, or as clear as planned where it was closer
SHORTCUT_ROUNDS = 3  # verifications of the shortcut samples, each keeping as they were the positioners found in a collision


def _shortcut(
    scenario: Scenario, inst: Instrument, trajectory: Trajectory, pairs: np.ndarray, near: np.ndarray, targets: set[int],
) -> tuple[tuple[Trajectory, np.ndarray, np.ndarray] | None, int, float]:
    """The samples ``trajectory`` with the joints of the positioners ``targets`` (indices) cut
    short (:func:`_shortcut_joint`: back-and-forth motion replaced by straight moves between
    samples where every pair stays clear), verified with their clearances; positioners found in
    a collision keep their samples and the rest is verified again, up to :data:`SHORTCUT_ROUNDS`
    times (:func:`_verified_rounds`). ``near`` holds the clearances of ``trajectory`` at
    ``pairs`` as :func:`_near` leaves them."""
    rho = point_extents(inst)

    def cut(keep: set[int]) -> np.ndarray:
        joints = trajectory.joints.copy()
        for i in sorted(targets - keep):
            for axis in (0, 1):
                joints[:, i, axis] = _shortcut_joint(scenario, inst, trajectory, joints, pairs, near, i, axis, rho)
        return joints

    return _verified_rounds(scenario, trajectory, inst, SHORTCUT_ROUNDS, cut)


def _shortcut_joint(
    scenario: Scenario, inst: Instrument, planned: Trajectory, joints: np.ndarray, pairs: np.ndarray, near: np.ndarray, i: int, axis: int,
    rho: np.ndarray,
) -> np.ndarray:
    """Joint ``axis`` of positioner ``i`` in ``joints`` (``(T, N, 2)``, the others as they now
    are), cut short: from each kept sample ``a``, the farthest sample ``b`` found (by doubling,
    then bisection) such that the straight move from ``q[a]`` to ``q[b]`` keeps every pair of
    ``i`` at least ``min(planned clearance, SHORTCUT_CLEARANCE_MM)`` clear at every sample in
    between. The planned clearances ``near`` less the motion bound of both positioners' departure
    from ``planned`` decide where that holds; the clearance is computed exactly only where they
    do not. A straight move between two samples stays within the hard stops and, the joint having
    covered at least that angle in that time, within the top speed."""
    times = planned.times
    q = joints[:, i, axis]
    rows = np.flatnonzero((pairs == i).any(axis=1))
    if len(rows) == 0 or len(q) < 3:
        return q
    other = pairs[rows].sum(axis=1) - i
    need = np.minimum(near[:, rows], SHORTCUT_CLEARANCE_MM)
    off_other = np.abs(joints[:, other] - planned.joints[:, other]) @ rho  # (T, R): the neighbours' departure from the planned path
    fixed = np.abs(joints[:, i, 1 - axis] - planned.joints[:, i, 1 - axis]) * rho[1 - axis]  # (T,): the other joint's
    base_i, orient_i = scenario.base_xy[i], scenario.orient[i]

    def clear(a: int, b: int) -> tuple[bool, np.ndarray]:
        line = q[a] + (q[b] - q[a]) * (times[a:b + 1] - times[a]) / (times[b] - times[a])
        off = np.abs(line - planned.joints[a:b + 1, i, axis]) * rho[axis] + fixed[a:b + 1]
        slack = near[a:b + 1, rows] - off[:, None] - off_other[a:b + 1] - need[a:b + 1]
        kk, rr = np.nonzero(slack < 0.0)
        if len(kk) == 0:
            return True, line
        mine = joints[a + kk, i].copy()
        mine[:, axis] = line[kk]
        n = other[rr]
        exact = geometry.clearance_between(
            inst, np.broadcast_to(base_i, (len(kk), 2)), np.broadcast_to(orient_i, len(kk)), mine,
            scenario.base_xy[n], scenario.orient[n], joints[a + kk, n],
        ).min(axis=1)
        return bool(np.all(exact >= need[a + kk, rr])), line

    out = q.copy()
    last = len(q) - 1
    a = 0
    while a < last:
        good, bad = a + 1, None
        probe = a + 2
        while probe <= last:
            if not clear(a, probe)[0]:
                bad = probe
                break
            good = probe
            probe = a + 2 * (probe - a)
        if bad is None and good < last:
            if clear(a, last)[0]:
                good = last
            else:
                bad = last
        if bad is not None:
            while bad - good > 1:
                mid = (good + bad) // 2
                if clear(a, mid)[0]:
                    good = mid
                else:
                    bad = mid
        if good > a + 1:
            out[a:good + 1] = clear(a, good)[1]
        a = good
    return out


def _attempt(
    scenario: Scenario, trajectory: Trajectory, inst: Instrument, pairs: np.ndarray, near: np.ndarray, fraction: float, pauses: bool,
) -> tuple[dict[tuple[int, int], JointProfile], VerificationReport, dict[str, Any], float]:
    """One fit of every positioner in the share ``fraction`` of its planned clearances (``near``,
    the verifier's at ``pairs``, as :func:`_near` leaves them), refitted until verified, then
    mended (``pauses``): the verified profiles, their report, their statistics and the time spent
    verifying."""
    verify_s = 0.0
    times, joints = trajectory.times, trajectory.joints
    fitter = _Fitter(inst, times, joints, _period_steps(inst.motors, times), _Room(inst, joints, pairs, near, fraction))
    fitter.fit_all(fraction)
    followed: list[int] = []
    rounds = settle_pauses = 0
    while True:
        profiles = Profiles(scenario, dict(sorted(fitter.fits.items())))
        checked = time.perf_counter()
        rebuilt = profiles.trajectory()
        report = verify_commands(scenario, rebuilt, instrument=inst)
        verify_s += time.perf_counter() - checked
        if report.ok:
            break
        if inst.motors.ramp_time_s is not None and report.collisions:  # the ramps may cut a corner the commands turn
            settled, checked_s = _settle_ramps(scenario, inst, profiles.joints, report)
            verify_s += checked_s
            if settled is not None:
                profiles, rebuilt, report, settle_pauses = settled
                break
        named = _named(report)
        if rounds > REFIT_ROUNDS or not named:
            ramp = "" if inst.motors.ramp_time_s is None else f" as the motors execute them with {inst.motors.ramp_time_s:g} s ramps"
            raise ProfileError(f"the profiles of positioners {sorted(named)} could not be verified{ramp}, even on their planned samples; "
                               "nothing exported")
        rounds += 1
        for ident in sorted(named):
            if rounds > REFIT_ROUNDS:
                fitter.follow(scenario.index_of(ident))
                followed.append(ident)
            else:
                fitter.narrow(scenario.index_of(ident))
    pause_times: list[float] = []
    mended = n_stretched = 0
    pause_s = max(float(np.median(np.diff(times))) if len(times) > 1 else 0.0, inst.motors.command_period_s or 0.0)  # one sample step
    if inst.motors.ramp_time_s is not None:  # a stop between opposite moves lasts a ramp: the executed speed then turns at the limit
        pause_s = max(pause_s, inst.motors.ramp_time_s)
    if pauses and report.motors_checked and report.motor_violations and pause_s > 0.0:
        # Creeps first (they may add transitions), then pauses; the first variant the verifier passes is kept.
        variants = [True, False] if inst.motors.min_speed_rad_s is not None and inst.motors.command_period_s is None else [False]
        for creeps in variants:
            joints_now, n_mended = _mend_creeps(profiles.joints, inst.motors) if creeps else (profiles.joints, 0)
            if creeps and not n_mended:
                continue
            times_now = _pause_times(joints_now, inst.motors, (inst.alpha_speed_rad_s, inst.beta_speed_rad_s))
            if not times_now and not n_mended:
                break
            candidate = Profiles(scenario, _paused(joints_now, times_now, pause_s) if times_now else joints_now)
            checked = time.perf_counter()
            candidate_rebuilt = candidate.trajectory()
            candidate_report = verify_commands(scenario, candidate_rebuilt, instrument=inst)
            verify_s += time.perf_counter() - checked
            if candidate_report.ok:  # held configurations are the profiles' own; a mended creep moves a hair: checked
                profiles, rebuilt, report, pause_times, mended = candidate, candidate_rebuilt, candidate_report, times_now, n_mended
                if times_now and STRETCH_PAUSES:
                    stretched, checked_s = _stretch_pauses(scenario, inst, joints_now, times_now, pause_s, profiles, report)
                    verify_s += checked_s
                    if stretched is not None:
                        profiles, rebuilt, report, n_stretched = stretched
                break
    stats = {
        "limits": limits_applied(inst),
        "fraction": fraction,
        "pauses": len(pause_times),
        "pause_s": pause_s * len(pause_times),
        "creeps_mended": mended,
        "pauses_run_through": n_stretched,
        "ramp_pauses": settle_pauses,
        "refit_rounds": rounds,
        "followed_samples": sorted(set(followed)),
        "relaxed_segments": int(fitter.relaxed.sum()),
        "makespan_before_s": _makespan(times, joints),
        "makespan_after_s": _executed_makespan(_makespan(rebuilt.times, rebuilt.joints), inst),
    }
    return profiles.joints, report, stats, verify_s


RAMP_ROUNDS = 3  # verifications of the pauses that let the ramps settle where the executed motion collides


def _settle_ramps(
    scenario: Scenario, inst: Instrument, joints: dict[tuple[int, int], JointProfile], report: VerificationReport,
) -> tuple[tuple[Profiles, Trajectory, VerificationReport, int] | None, float]:
    """Where the motion the motors execute collides though the commands may not (a ramp cuts the
    corner where one joint stops and another starts): everyone holds still for a ramp time at
    each breakpoint of the colliding positioners' joints from a ramp before the collision to a
    ramp after its worst instant (:func:`_paused`). After such a stop every joint has settled on
    its commanded angle, and from it both joints of a positioner ramp up together, so its
    executed path follows its commanded one; the pair meets only configurations the commands
    meet. Verified again, up to :data:`RAMP_ROUNDS` times. Returns ``(profiles, rebuilt,
    report, pauses)`` or ``None``, and the time spent verifying."""
    tau = float(inst.motors.ramp_time_s or 0.0)
    verify_s = 0.0
    count = 0
    for _ in range(RAMP_ROUNDS):
        found: set[float] = set()
        for event in report.collisions:
            lo, hi = event.t_first_s - tau, event.t_worst_s + tau
            pair = [joints[key] for ident in (event.id_i, event.id_j) for key in ((scenario.index_of(ident), 0), (scenario.index_of(ident), 1))
                    if key in joints]
            for prof in pair:
                t_knot, _ = prof.knots()
                for t in t_knot[(t_knot >= lo) & (t_knot <= hi)].tolist():
                    # a ramp before it meets one after it (a start from rest, or the end of all motion, has nothing to settle)
                    if any(_moves_in(other, t - tau, t) for other in pair) and any(_moves_in(other, t, t + tau) for other in pair):
                        found.add(float(t))
        if not found:
            return None, verify_s
        merged = _distinct(found)
        joints = _paused(joints, merged, tau)
        count += len(merged)
        candidate = Profiles(scenario, joints)
        checked = time.perf_counter()
        rebuilt = candidate.trajectory()
        report = verify_commands(scenario, rebuilt, instrument=inst)
        verify_s += time.perf_counter() - checked
        if report.ok:
            return (candidate, rebuilt, report, count), verify_s
    return None, verify_s


def _moves_in(prof: JointProfile, a: float, b: float) -> bool:
    """Whether the joint has a moving segment overlapping the open interval ``(a, b)``."""
    t_knot, _ = prof.knots()
    moving = np.abs(prof.speeds_rad_s) > _MOVING
    return bool(np.any(moving & (t_knot[:-1] < b - TIME_ROUND_S) & (t_knot[1:] > a + TIME_ROUND_S)))


def _stretch_pauses(
    scenario: Scenario, inst: Instrument, joints: dict[tuple[int, int], JointProfile], pause_times: list[float], pause_s: float,
    paused: Profiles, paused_report: VerificationReport,
) -> tuple[tuple[Profiles, Trajectory, VerificationReport, int] | None, float]:
    """The paused profiles with the segments that pauses split stretched over them instead
    (:func:`_stretchable`, :func:`_paused`), verified; positioners found in a collision are kept
    split and the rest verified again, up to :data:`STRETCH_ROUNDS` times. Kept only where no more
    motor limits are broken than with the pauses alone and the joints have fewer segments in all.
    Returns ``(profiles, rebuilt, report, pauses run through)`` or ``None``, and the time spent
    verifying."""
    keep: set[int] = set()
    verify_s = 0.0
    rho = point_extents(inst)
    reach = (EARLY_ARRIVAL_MM / float(rho[0]), EARLY_ARRIVAL_MM / float(rho[1]))
    motors = inst.motors
    lows = (0.0, 0.0) if motors.min_speed_rad_s is None else tuple(m * (1.0 + _CREEP_MARGIN) for m in motors.min_speed_rad_s)
    for _ in range(STRETCH_ROUNDS):
        mask = _stretchable(joints, pause_times, pause_s, motors, keep, reach)
        if not mask:
            return None, verify_s
        candidate = Profiles(scenario, _paused(joints, pause_times, pause_s, mask, lows))
        checked = time.perf_counter()
        rebuilt = candidate.trajectory()
        report = verify_commands(scenario, rebuilt, instrument=inst)
        verify_s += time.perf_counter() - checked
        if report.ok:
            better = (len(report.motor_violations) <= len(paused_report.motor_violations)
                      and candidate.segment_counts().sum() < paused.segment_counts().sum())
            return ((candidate, rebuilt, report, sum(sum(sum(f) for f in plan.values()) for plan in mask.values())) if better else None), verify_s
        named = _named(report)
        if not named:
            return None, verify_s
        keep |= {scenario.index_of(ident) for ident in named}
    return None, verify_s


_MOVING = 1e-9  # rad/s: the verifier's threshold of a moving command


def _breaks(a: float, b: float, motors: MotorLimits) -> bool:
    """Whether a moving segment at speed ``b`` right after one at ``a`` breaks the motors' limits:
    a reversal without a stop (``stop_before_reversing``) or a speed change beyond
    ``max_speed_change`` of the first (a stop or a start between them is exempt from both)."""
    if abs(a) <= _MOVING or abs(b) <= _MOVING:
        return False
    return (motors.stop_before_reversing and a * b < 0) or (
        motors.max_speed_change is not None and a * b > 0 and abs(b - a) / abs(a) > motors.max_speed_change * (1 + 1e-9))


def _pause_times(joints: dict[tuple[int, int], JointProfile], motors: MotorLimits, tops: tuple[float, float] = (math.inf, math.inf)) -> list[float]:
    """The breakpoints (s) where some joint's consecutive moving segments break the motors'
    limits (:func:`_breaks`), or (with a ramp time) where a joint starts a segment whose speed and
    an opposite one within the ramp before add up to more than its top speed (``tops``; the
    executed speed would change faster than the ramps allow, :func:`_ramp_caps`): what a stop of
    everyone there (of at least a ramp) mends."""
    found: list[float] = []
    ramp = motors.ramp_time_s
    for key, prof in joints.items():
        t_knot, _ = prof.knots()
        speeds = prof.speeds_rad_s.tolist()
        found += [float(t_knot[k]) for k in range(1, len(speeds)) if _breaks(speeds[k - 1], speeds[k], motors)]
        if ramp is not None:
            top = tops[key[1]]
            segments = list(zip(t_knot[:-1].tolist(), t_knot[1:].tolist(), speeds, strict=True))
            for k in range(1, len(speeds)):
                caps = _ramp_caps((segments[j] for j in range(k - 1, -1, -1)), segments[k][0], top, ramp)  # latest first, lazily
                v = speeds[k]
                if v > caps[0] * (1 + 1e-9) + _TOL or -v > caps[1] * (1 + 1e-9) + _TOL:
                    found.append(float(t_knot[k]))
    return _distinct(found)


def _distinct(times: Iterable[float]) -> list[float]:
    """The instants ``times`` in order, those closer than :data:`TIME_ROUND_S` to the previous one left out."""
    merged: list[float] = []
    for t in sorted(times):
        if not merged or t - merged[-1] > TIME_ROUND_S:
            merged.append(t)
    return merged


_CREEP_MIN_S = 1e-3  # a creep is mended only if its move at the minimum speed lasts at least this long
_CREEP_MARGIN = 1e-6  # the mended move runs this much above the minimum speed (rounding of the rebuilt grid)


def _mend_creeps(joints: dict[tuple[int, int], JointProfile], motors: MotorLimits) -> tuple[dict[tuple[int, int], JointProfile], int]:
    """Every moving segment slower than the motors' minimum becomes a move at the minimum speed
    (a hair above) over the same angle, then a hold to the segment's end: the joint arrives early
    and waits, never farther from its profile than the creep's own angle. Returns the profiles
    and the number of segments changed (the speed changes this adds are left to the pauses)."""
    assert motors.min_speed_rad_s is not None
    out: dict[tuple[int, int], JointProfile] = {}
    count = 0
    for (i, axis), prof in joints.items():
        low = motors.min_speed_rad_s[axis] * (1.0 + _CREEP_MARGIN)
        durations: list[float] = []
        speeds: list[float] = []
        changed = 0
        starts, _ = prof.knots()
        for d, v, t0 in zip(prof.durations_s.tolist(), prof.speeds_rad_s.tolist(), starts[:-1].tolist(), strict=True):
            # The arrival lands on the rebuilt trajectory's time grid (TIME_ROUND_S), so the hold after it stays still there.
            move = round((t0 + d * abs(v) / low) / TIME_ROUND_S) * TIME_ROUND_S - t0
            if v != 0.0 and abs(v) < motors.min_speed_rad_s[axis] * (1 - 1e-9) and _CREEP_MIN_S <= move < d:
                durations += [move, d - move]
                speeds += [v * d / move, 0.0]  # the same angle, at the minimum speed (a hair above)
                changed += 1
            else:
                durations.append(d)
                speeds.append(v)
        out[(i, axis)] = _trimmed(prof.start_s, prof.start_rad, np.array(durations), np.array(speeds)) if changed else prof
        count += changed
    return out, count


def _paused(
    joints: dict[tuple[int, int], JointProfile], pause_times: list[float], pause_s: float,
    stretched: dict[tuple[int, int], dict[int, list[bool]]] | None = None, lows: tuple[float, float] = (0.0, 0.0),
) -> dict[tuple[int, int], JointProfile]:
    """Every joint's profile with everyone holding still for ``pause_s`` at each of ``pause_times``
    (times of the profiles before pausing): a joint in a segment there is split, holds, and goes
    on at the same speed; a joint that has not started starts later; one that has finished holds.
    Every configuration is one the profiles pass through, held: the positions at each instant of
    the paused profiles are those of the profiles at an earlier instant, for everyone alike.

    ``stretched[key][s]``: per pause inside segment ``s`` of that joint (farther than
    :data:`TIME_ROUND_S` from its ends), whether the joint runs through it instead of holding:
    the piece between two holds (or the segment's ends) then runs slower over its paused span,
    its speed times ``D / (D + a pause_s)`` for ``D`` of the profile's time and ``a`` pauses run
    through, or, where that would fall below ``lows[joint]``, moves at that speed and waits
    (:func:`_piece`); either way it is at the same angle as the paused profile at each hold and
    at the segment's end (:func:`_stretchable`). A pause at a segment's start is a hold either way.
    """
    out: dict[tuple[int, int], JointProfile] = {}
    for key, prof in joints.items():
        edges, _ = prof.knots()
        durations: list[float] = []
        speeds: list[float] = []
        pending = [t for t in pause_times if t > prof.start_s + TIME_ROUND_S]
        start_s = prof.start_s + pause_s * (len(pause_times) - len(pending))  # pauses before its start: it starts later
        through = {} if stretched is None else stretched.get(key, {})
        segments = zip(prof.durations_s.tolist(), prof.speeds_rad_s.tolist(), edges[:-1].tolist(), edges[1:].tolist(), strict=True)
        for s, (d, v, t0, t1) in enumerate(segments):
            flags = iter(through.get(s, ()))
            cut = t0
            run = 0  # pauses run through since the last cut
            while pending and pending[0] < t1 - TIME_ROUND_S:  # a pause inside this segment (or at its start)
                t = pending.pop(0)
                if t - cut > TIME_ROUND_S or run:
                    if next(flags, False):
                        run += 1
                        continue
                    if run:
                        for duration, speed in _piece(v, t - cut, run, pause_s, lows[key[1]]):
                            durations.append(duration)
                            speeds.append(speed)
                    else:
                        durations.append(t - cut)
                        speeds.append(v)
                durations.append(pause_s)
                speeds.append(0.0)
                cut, run = t, 0
            if run:
                for duration, speed in _piece(v, t1 - cut, run, pause_s, lows[key[1]]):
                    durations.append(duration)
                    speeds.append(speed)
            else:
                durations.append(t1 - cut if cut > t0 else d)
                speeds.append(v)
        out[key] = _trimmed(start_s, prof.start_rad, np.array(durations), np.array(speeds))
    return out


def _piece(v: float, span: float, run: int, pause_s: float, low: float) -> list[tuple[float, float]]:
    """``(duration, speed)`` of the piece of a segment at speed ``v`` that covers ``span`` of the
    profile's time and runs through ``run`` pauses: one slower segment over its paused span where
    that stays at or above ``low``, else a move over the same angle at ``low`` and a hold (the
    joint arrives early and waits, on the rebuilt trajectory's time grid)."""
    total = span + run * pause_s
    move = total if abs(v) * span >= low * total else round(abs(v) * span / low / TIME_ROUND_S) * TIME_ROUND_S
    if move >= total - TIME_ROUND_S:  # no hold left on the grid: one segment over the whole span
        return [(total, v * span / total)]
    return [(move, v * span / move), (total - move, 0.0)]


def _runs_through(speed: float, span: float, run: int, pause_s: float, low: float, reach: float) -> bool:
    """Whether a piece at ``speed`` (> 0) over ``span`` of the profile's time may run through
    ``run`` pauses (:func:`_piece`): always where its slower speed stays at or above ``low``;
    arriving early at ``low`` only where it stays within ``reach`` (rad) of the paused profile:
    ahead of it by at most ``angle (1 - low / speed)``, behind by at most ``speed`` times the
    shorter of the pauses and the hold at its end."""
    total = span + run * pause_s
    if speed * span >= low * total:
        return True
    angle = speed * span
    return max(angle * (1.0 - low / speed), speed * min(run * pause_s, total - angle / low)) <= reach


def _stretchable(
    joints: dict[tuple[int, int], JointProfile], pause_times: list[float], pause_s: float, motors: MotorLimits, keep: set[int],
    reach: tuple[float, float],
) -> dict[tuple[int, int], dict[int, list[bool]]]:
    """Which pauses inside which moving segments :func:`_paused` may let a joint run through
    (``stretched`` of :func:`_paused`), for the positioners not in ``keep`` (indices): along each
    segment, a pause is run through while the piece it joins stays at or above the motors'
    minimum speed, else held (the next piece starts there, at the segment's speed). A segment
    whose first or last piece would then change speed beyond the motors' limits against the
    moving pieces around it (:func:`_breaks`; a pause at a segment's start is a stop) holds at
    every pause, and the check is made again until nothing changes."""
    paused_at = np.array(pause_times)
    out: dict[tuple[int, int], dict[int, list[bool]]] = {}
    for key, prof in joints.items():
        if key[0] in keep:
            continue
        low = 0.0 if motors.min_speed_rad_s is None else motors.min_speed_rad_s[key[1]] * (1.0 + _CREEP_MARGIN)
        edges, _ = prof.knots()
        # The pauses strictly inside each segment, and whether one falls at its start (as :func:`_paused` finds them).
        first = np.searchsorted(paused_at, edges[:-1] + TIME_ROUND_S, side="right")
        last = np.searchsorted(paused_at, edges[1:] - TIME_ROUND_S, side="left")
        stopped = (first > np.searchsorted(paused_at, edges[:-1] - TIME_ROUND_S, side="left")).tolist()
        v = prof.speeds_rad_s.tolist()
        plan: dict[int, list[bool]] = {}
        ends: dict[int, tuple[float, float]] = {}  # speeds of a stretched segment's first and last pieces
        for s in np.flatnonzero((last > first) & (prof.speeds_rad_s != 0.0)).tolist():
            if abs(v[s]) < low:
                continue
            t0, t1 = float(edges[s]), float(edges[s + 1])
            cuts = [*paused_at[first[s]:last[s]].tolist(), t1]
            flags: list[bool] = []
            speeds: list[float] = []
            cut, run = t0, 0
            for t, t_next in itertools.pairwise(cuts):
                if _runs_through(abs(v[s]), t_next - cut, run + 1, pause_s, low, reach[key[1]]):  # the piece, run through t, to t_next at least
                    flags.append(True)
                    run += 1
                else:
                    flags.append(False)
                    speeds.append(_piece(v[s], t - cut, run, pause_s, low)[0][1])
                    cut, run = t, 0
            last_piece = _piece(v[s], t1 - cut, run, pause_s, low)
            if any(flags):
                plan[s], ends[s] = flags, (speeds[0] if speeds else last_piece[0][1], last_piece[-1][1])
        changed = bool(plan)
        while changed:
            changed = False
            for s in range(1, len(v)):
                if stopped[s] or not (s - 1 in plan or s in plan):
                    continue
                before = ends[s - 1][1] if s - 1 in plan else v[s - 1]
                after = ends[s][0] if s in plan else v[s]
                if _breaks(before, after, motors):
                    plan.pop(s - 1, None)
                    plan.pop(s, None)
                    changed = True
        if plan:
            out[key] = plan
    return out


class _Fitter:
    """The profiles of every positioner as they are fitted, and the passes that fit them
    (``fits``: ``(positioner, joint) -> JointProfile``; ``relaxed``: per positioner, the
    segments that break a motor limit)."""

    def __init__(self, inst: Instrument, times: np.ndarray, joints: np.ndarray, step: int, room: _Room) -> None:
        self.inst, self.times, self.joints, self.step, self.room = inst, times, joints, step, room
        self.fits: dict[tuple[int, int], JointProfile] = {}
        self.relaxed = np.zeros(joints.shape[1], dtype=int)
        self.narrowing = np.ones(joints.shape[1])

    def _fit(self, i: int, budget: np.ndarray) -> int:
        return _fit_positioner(self.inst, self.times, self.joints[:, i], budget, self.step, self.fits, i, self.room)

    def _refit(self, i: int, fraction: float) -> None:
        budget = self.room.left(i, max(fraction, REFIT_FRACTION))
        self.relaxed[i] = _refit_positioner(self.inst, self.times, self.joints[:, i], budget, self.step, self.fits, i, self.room)

    def fit_all(self, fraction: float) -> None:
        """First every positioner in half of each pair's room; then those that break a motor
        limit in the room their neighbours leave; last, for those still short, the neighbours
        make room (each fitted in a quarter of its half, kept only if it breaks no limit)."""
        done = self._straight_pass() if ONE_SEGMENT_SHORTCUTS else np.zeros(self.joints.shape[1], dtype=bool)
        self._search(np.flatnonzero(~done).tolist())
        for _ in range(REFIT_PASSES):
            for i in np.argsort(-self.relaxed, kind="stable")[: np.count_nonzero(self.relaxed)].tolist():
                self._refit(i, fraction)
        for i in np.flatnonzero(self.relaxed).tolist():
            for j in self.room.neighbours(i).tolist():
                kept = {key: self.fits[key] for key in ((j, 0), (j, 1)) if key in self.fits}
                if self.relaxed[j] or not kept or self._fit(j, self.room.half(j) * NARROWING):
                    self._restore(j, kept)
            self._refit(i, fraction)

    def _search(self, todo: list[int]) -> None:
        """Fit the positioners ``todo`` by the search, each in half of each pair's room: from
        :data:`FORK_SEARCH` of them on, every other one in a forked process (:mod:`fiberplan._fork`)
        while the rest are fitted here. Each fit depends only on the planned samples and clearances,
        so the profiles, deviations and counts are those of one process, bit for bit."""

        def fit(idx: list[int]) -> tuple[dict[tuple[int, int], JointProfile], np.ndarray, np.ndarray]:
            for i in idx:
                self.relaxed[i] = self._fit(i, self.room.half(i))
            mine = set(idx)
            fitted = {key: prof for key, prof in self.fits.items() if key[0] in mine}
            return fitted, self.room.deviation[:, idx], self.relaxed[idx]

        if len(todo) < FORK_SEARCH or not _fork.can_fork():
            fit(todo)
            return
        here, there = todo[0::2], todo[1::2]
        _, (fitted, deviation, relaxed), forked = _fork.both(lambda: fit(here), lambda: fit(there))
        if forked:
            self.fits.update(fitted)
            self.room.deviation[:, there] = deviation
            self.relaxed[there] = relaxed

    def _straight_pass(self) -> np.ndarray:
        """Fit at once, with numpy over all positioners, those each of whose moving joints
        holds one constant-speed segment from its first move to its last (most positioners on
        DESI-like plans): the profiles the search of :func:`_fit_positioner` would return
        (its first option, the farthest end, is taken there), in a fraction of its time.
        Returns ``(N,)`` which positioners were fitted; the others are left to the search.

        A joint qualifies when the line's speed is one the motors accept from a stop and its
        deviation from the planned samples, as the rebuilt trajectory will have it, stays
        strictly inside the corridor (a relative margin of ``1e-9``, so the search, which has
        a tolerance of its own, would take the same segment). The corridor is worked out only
        for the positioners whose lines fit the room of their closest pair."""
        times, joints, step, room, inst = self.times, self.joints, self.step, self.room, self.inst
        n_t, n = joints.shape[0], joints.shape[1]
        if n_t < 2:
            return np.zeros(n, dtype=bool)
        changed = joints[1:] != joints[:-1]  # (T - 1, N, 2)
        moving = changed.any(axis=0)  # (N, 2)
        # A joint that holds still between two moves rarely fits one segment; where every positioner
        # has such a joint (each move in two legs through the datum), the search alone fits them (the
        # same profiles: it takes one segment wherever this pass would).
        moved = np.logical_or.accumulate(changed, axis=0)  # (T - 1, N, 2): has moved by then
        resumes = (changed[1:] & ~changed[:-1] & moved[:-1]).any(axis=0)  # (N, 2): moves again after holding
        if np.all(resumes.any(axis=1) | ~moving.any(axis=1)):
            return np.zeros(n, dtype=bool)
        ok = np.ones(n, dtype=bool)
        cols = np.arange(n)
        lows = (0.0, 0.0) if inst.motors.min_speed_rad_s is None else inst.motors.min_speed_rad_s
        stops = (inst.alpha_limits_rad, inst.beta_limits_rad)
        tops = (inst.alpha_speed_rad_s, inst.beta_speed_rad_s)
        found: list[tuple[np.ndarray, ...]] = []
        for axis in (0, 1):
            q = joints[:, :, axis]  # (T, N)
            first = np.argmax(changed[:, :, axis], axis=0)
            last = n_t - 2 - np.argmax(changed[::-1, :, axis], axis=0)
            k0 = first // step * step
            k1 = k0 + -(-(last + 1 - k0) // step) * step
            mv = moving[:, axis]
            ok &= ~mv | (k1 < n_t)
            k1 = np.minimum(k1, n_t - 1)
            t0, q0, q1 = times[k0], q[k0, cols], q[k1, cols]
            with np.errstate(divide="ignore", invalid="ignore"):
                d = times[k1] - t0
                speed = (q1 - q0) / d
                t_end, q_end = t0 + d, q0 + speed * d  # the knots, as JointProfile.knots has them
                slope = (q_end - q0) / (t_end - t0)
                tt = times[:, None]
                line = np.where(tt < t0, q0, np.where(tt >= t_end, q_end, slope * (tt - t0) + q0))  # np.interp's values
                dev = np.where(mv, room.rho[axis] * np.abs(line - q), 0.0)  # (T, N) mm
            allowed = (np.abs(speed) <= tops[axis]) & (np.abs(speed) >= max(lows[axis], _TOL))
            in_stops = (np.minimum(q0, q_end) >= stops[axis][0] - _TOL) & (np.maximum(q0, q_end) <= stops[axis][1] + _TOL)
            ok &= ~mv | (allowed & in_stops)
            found.append((mv, t0, q0, d, speed, dev))
        dev_a, dev_b = found[0][5], found[1][5]
        share = np.where(moving[:, 1], 0.5, 1.0)  # alpha's share of the budget: half when beta moves
        bound = room.half_bound()  # (T, N) >= each positioner's budget
        ok &= np.all((dev_a <= share * bound) & (dev_a + dev_b <= bound), axis=0)
        idx = np.flatnonzero(ok)
        left = room.half_of(idx)  # (T, len(idx)) the budget, as _fit_positioner has it
        share = share[idx]
        band_a = np.where(np.isfinite(left), share * np.maximum(left, 0.0), np.inf)
        left = left - dev_a[:, idx]  # beta has what alpha leaves
        band_b = np.where(np.isfinite(left), np.maximum(left, 0.0), np.inf)
        margin = 1.0 - 1e-9
        fits = np.all((dev_a[:, idx] <= band_a * margin) & (dev_b[:, idx] <= band_b * margin), axis=0)
        ok[idx[~fits]] = False
        for i in np.flatnonzero(ok).tolist():
            for axis, (mv, t0, q0, d, speed, _) in enumerate(found):
                if mv[i]:
                    self.fits[(i, axis)] = JointProfile(float(t0[i]), float(q0[i]), np.array([d[i]]), np.array([speed[i]]))
        room.deviation[:, ok] = (dev_a + dev_b)[:, ok]
        return ok

    def _restore(self, i: int, kept: dict[tuple[int, int], JointProfile]) -> None:
        for axis in (0, 1):
            self.fits.pop((i, axis), None)
        self.fits.update(kept)
        self.room.record(i, self.fits, self.times, self.joints[:, i])

    def narrow(self, i: int) -> None:
        """Fit positioner ``i`` again in a corridor ``NARROWING`` times narrower than its last."""
        self.narrowing[i] *= NARROWING
        self.relaxed[i] = self._fit(i, self.room.half(i) * self.narrowing[i])

    def follow(self, i: int) -> None:
        """Positioner ``i`` follows its planned samples."""
        _follow_samples(self.times, self.joints[:, i], self.fits, i)
        self.room.record(i, self.fits, self.times, self.joints[:, i])


def _makespan(times: np.ndarray, joints: np.ndarray) -> float:
    """Time of the last sample at which any joint still changes."""
    moving = np.flatnonzero(np.any(joints[1:] != joints[:-1], axis=(1, 2)))
    return float(times[moving[-1] + 1]) if len(moving) else 0.0


def _executed_makespan(commanded_s: float, inst: Instrument) -> float:
    """When the motors stop: the commands' makespan, and the last ramp where the instrument states one."""
    return commanded_s + (inst.motors.ramp_time_s or 0.0) if commanded_s > 0.0 else commanded_s


def _period_steps(motors: MotorLimits, times: np.ndarray) -> int:
    """Samples per command period (1 without one); the period must be a multiple of the sample step."""
    if motors.command_period_s is None or len(times) < 2:
        return 1
    dt = np.diff(times)
    ratio = motors.command_period_s / dt[0]
    if not np.allclose(dt, dt[0], rtol=1e-9) or abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
        raise ProfileError(
            f"the command period {motors.command_period_s} s is not a multiple of the trajectory's sample step {dt[0]:.6g} s; "
            "plan with a dt that divides it (--set dt_s=...)"
        )
    return round(ratio)


_NEAR_ROWS = 256  # pairs whose clearances :func:`_near` works on at once (a small copy each)


def _near(clear: np.ndarray) -> np.ndarray:
    """The verifier's planned clearances ``(T, P)`` with each sample's clearance the least of its
    own and its two neighbours' (the deviation is linear between samples, so a sample's room
    covers both intervals), floored at zero: in place when ``clear`` is pair-major (as the
    verifier stores it), else in a copy."""
    if not clear.flags.f_contiguous:
        clear = np.asfortranarray(clear)  # a copy: the caller's array is left as it was
    clear_t = clear.T  # (P, T), C-contiguous: a pair's samples together
    for start in range(0, clear_t.shape[0], _NEAR_ROWS):
        block = clear_t[start:start + _NEAR_ROWS]
        planned = block.copy()
        np.minimum(block[:, 1:], planned[:, :-1], out=block[:, 1:])
        np.minimum(block[:, :-1], planned[:, 1:], out=block[:, :-1])
        np.maximum(block, 0.0, out=block)
    return clear


class _Room:
    """How far (mm, motion bound) each positioner may leave its planned path at each sample.

    A pair ``(i, j)`` shares ``f c_ij``, with ``c_ij`` its planned clearance at the sample and
    its two neighbours (the deviation is linear between samples, so a sample's room covers both
    intervals), as the verifier measured it on the planned trajectory (exact where the pair's
    enclosing discs are within 2 mm, that gap, a lower bound, beyond). :meth:`half` gives ``i`` half of it (all of it when ``j`` never moves);
    :meth:`left` what ``j``'s profile, as fitted so far, leaves (:meth:`record`).
    """

    def __init__(self, inst: Instrument, joints: np.ndarray, pairs: np.ndarray, near: np.ndarray, fraction: float) -> None:
        """``near``: the planned clearances as :func:`_near` leaves them, ``(T, P)``."""
        self.rho = point_extents(inst)
        self.pairs = pairs
        n_t, n = joints.shape[0], joints.shape[1]
        self.clear = near  # (T, P)
        self.near_t = np.ascontiguousarray(near.T)  # (P, T): a pair's samples contiguous (a view of the verifier's pair-major table)
        self.fraction = fraction  # a pair's room at a sample: fraction * near, computed where it is read
        self.still = np.all(joints == joints[:1], axis=(0, 2))  # (N,) never moves
        self.deviation = np.zeros((n_t, n))  # (T, N) motion bound of each fitted profile's deviation
        ends = np.concatenate([np.arange(len(pairs)), np.arange(len(pairs))])
        owner = pairs.T.ravel()  # the positioner at each pair end, first ends then second
        order = np.lexsort((ends, owner))
        self._rows = ends[order]  # every positioner's pair rows, ascending, positioner after positioner
        self._offsets = np.searchsorted(owner[order], np.arange(n + 1))  # positioner i's rows: _rows[_offsets[i]:_offsets[i + 1]]

    def _others(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        rows = self._rows[self._offsets[i]:self._offsets[i + 1]]
        return rows, np.where(self.pairs[rows, 0] == i, self.pairs[rows, 1], self.pairs[rows, 0])

    def neighbours(self, i: int) -> np.ndarray:
        """Indices of ``i``'s neighbours."""
        return self._others(i)[1]

    def half(self, i: int) -> np.ndarray:
        """``(T,)``: half of each pair's room (all of it next to a positioner that never moves)."""
        rows, other = self._others(i)
        if len(rows) == 0:
            return np.full(self.near_t.shape[1], np.inf)
        return (self.fraction * self.near_t[rows] * np.where(self.still[other], 1.0, 0.5)[:, None]).min(axis=0)

    def half_bound(self) -> np.ndarray:
        """``(T, N)``: an upper bound on :meth:`half` of every positioner, from its closest
        pair alone (the one whose planned clearance falls lowest); infinite without pairs."""
        n_t, n = self.near_t.shape[1], len(self.still)
        out = np.full((n_t, n), np.inf)
        if len(self.pairs) == 0:
            return out
        low = self.clear.min(axis=0)  # (P,)
        owner = np.repeat(np.arange(n), np.diff(self._offsets))
        first = np.lexsort((low[self._rows], owner))[self._offsets[:-1][np.diff(self._offsets) > 0]]  # closest row of each
        has = owner[first]
        rows = self._rows[first]
        other = np.where(self.pairs[rows, 0] == has, self.pairs[rows, 1], self.pairs[rows, 0])
        out[:, has] = (self.fraction * self.near_t[rows] * np.where(self.still[other], 1.0, 0.5)[:, None]).T
        return out

    def half_of(self, idx: np.ndarray) -> np.ndarray:
        """``(T, len(idx))``: :meth:`half` of the positioners ``idx`` at once (the same values)."""
        n_t = self.near_t.shape[1]
        out = np.full((n_t, len(idx)), np.inf)
        sizes = self._offsets[idx + 1] - self._offsets[idx]
        total = int(sizes.sum())
        if total == 0:
            return out
        starts_all = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        rows_all = self._rows[np.arange(total) - np.repeat(starts_all, sizes) + np.repeat(self._offsets[idx], sizes)]
        owner = np.repeat(idx, sizes)
        other = np.where(self.pairs[rows_all, 0] == owner, self.pairs[rows_all, 1], self.pairs[rows_all, 0])
        values = self.fraction * self.near_t[rows_all] * np.where(self.still[other], 1.0, 0.5)[:, None]  # (rows, T)
        has = np.flatnonzero(sizes)
        out[:, has] = np.minimum.reduceat(values, starts_all[has], axis=0).T
        return out

    def left(self, i: int, fraction: float) -> np.ndarray:
        """``(T,)``: each pair's room, ``fraction`` of its planned clearance, less the neighbour's
        recorded deviation."""
        rows, other = self._others(i)
        if len(rows) == 0:
            return np.full(self.near_t.shape[1], np.inf)
        return np.maximum((fraction * self.clear[:, rows] - self.deviation[:, other]).min(axis=1), 0.0)

    def record(self, i: int, fits: dict[tuple[int, int], JointProfile], times: np.ndarray, q: np.ndarray, refine: int = 1) -> None:
        """Store positioner ``i``'s deviation from its planned angles ``q (T, 2)`` under its
        fitted profiles; with breakpoints between samples (``refine > 1``), the largest
        deviation around each sample."""
        if refine == 1:
            self.deviation[:, i] = _deviation(self.rho, fits, i, times, q)
            return
        fine_t, fine_q, _ = _refined(times, q, np.zeros(len(times)), refine)
        fine = _deviation(self.rho, fits, i, fine_t, fine_q)
        per_interval = np.concatenate([fine[:-1].reshape(-1, refine).max(axis=1), fine[-1:]])
        dev = per_interval.copy()
        dev[1:] = np.maximum(dev[1:], per_interval[:-1])
        self.deviation[:, i] = dev


def _deviation(rho: np.ndarray, fits: dict[tuple[int, int], JointProfile], i: int, times: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``(T,)`` motion bound of positioner ``i``'s profiles' deviation from ``q (T, 2)`` at the samples."""
    out = np.zeros(len(times))
    for axis in (0, 1):
        prof = fits.get((i, axis))
        if prof is not None:
            t_knot, q_knot = prof.knots()
            out += rho[axis] * np.abs(np.interp(times, t_knot, q_knot) - q[:, axis])
    return out


def _fit_positioner(
    inst: Instrument, times: np.ndarray, q: np.ndarray, budget: np.ndarray, step: int,
    fits: dict[tuple[int, int], JointProfile], i: int, room: _Room, alpha_share: float = 0.5, refine: int = 1,
    search: tuple[int, int] = SEARCH,
) -> int:
    """Fit both joints of positioner ``i`` (planned angles ``q (T, 2)``) into ``fits`` and record
    its deviation in ``room``: alpha within ``alpha_share`` of the budget (mm), beta within what
    alpha leaves. With ``refine > 1`` breakpoints may also fall on ``refine - 1`` instants
    between samples (the planned path is linear there; the budget is the smaller of the two
    samples'). Returns the segments that had to break a motor limit."""
    rho = room.rho
    limits = (inst.alpha_limits_rad, inst.beta_limits_rad)
    speeds = (inst.alpha_speed_rad_s, inst.beta_speed_rad_s)
    fine_t, fine_q, left = _refined(times, q, budget, refine)
    relaxed = 0
    for axis in (0, 1):
        fits.pop((i, axis), None)
        share = alpha_share if axis == 0 and np.any(q[:, 1] != q[0, 1]) else 1.0
        band = np.where(np.isfinite(left), share * np.maximum(left, 0.0) / rho[axis], np.inf)
        fit = _fit_joint(fine_t, fine_q[:, axis], band, limits[axis], speeds[axis], inst.motors, axis, step * refine, search)
        if fit is None:
            continue
        prof, n_relaxed = fit
        fits[(i, axis)] = prof
        relaxed += n_relaxed
        if axis == 0:
            t_knot, q_knot = prof.knots()
            left = left - rho[0] * np.abs(np.interp(fine_t, t_knot, q_knot) - fine_q[:, 0])
    room.record(i, fits, times, q, refine)
    return relaxed


def _refined(times: np.ndarray, q: np.ndarray, budget: np.ndarray, refine: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sample grid with ``refine - 1`` instants added in each interval: times, planned
    angles (linear between samples) and budget (the smaller of the interval's two samples')."""
    if refine == 1:
        return times, q, budget.copy()
    w = np.arange(refine) / refine
    fine_t = np.concatenate([(times[:-1, None] + w * np.diff(times)[:, None]).ravel(), times[-1:]])
    fine_q = np.stack([np.interp(fine_t, times, q[:, axis]) for axis in (0, 1)], axis=1)
    inner = np.minimum(budget[:-1], budget[1:])[:, None].repeat(refine, axis=1)
    inner[:, 0] = budget[:-1]
    return fine_t, fine_q, np.concatenate([inner.ravel(), budget[-1:]])


def _refit_positioner(
    inst: Instrument, times: np.ndarray, q: np.ndarray, budget: np.ndarray, step: int,
    fits: dict[tuple[int, int], JointProfile], i: int, room: _Room,
) -> int:
    """Fit positioner ``i`` again in the room its neighbours' profiles leave, trying several
    splits between its joints (``ALPHA_SHARES``), then breakpoints between samples (``REFINE``, when the instrument
    states no command period); keep the fit with the fewest motor-limit breaks, then segments."""
    tries = [(share, 1) for share in ALPHA_SHARES]
    if inst.motors.command_period_s is None:
        tries += [(share, REFINE) for share in ALPHA_SHARES]
    best: tuple[int, int, dict[tuple[int, int], JointProfile], int] = (np.iinfo(int).max, 0, {}, 1)
    for share, refine in tries:
        trial: dict[tuple[int, int], JointProfile] = {}
        n_relaxed = _fit_positioner(inst, times, q, budget, step, trial, i, room, share, refine, REFIT_SEARCH)
        n_segments = sum(len(p.durations_s) for p in trial.values())
        if (n_relaxed, n_segments) < best[:2]:
            best = (n_relaxed, n_segments, trial, refine)
        if n_relaxed == 0:
            break
    for axis in (0, 1):
        fits.pop((i, axis), None)
    fits.update(best[2])
    room.record(i, fits, times, q, best[3])
    return best[0]


def _allowed_speeds(prev: float, top: float, motors: MotorLimits, axis: int, caps: tuple[float, float] | None = None) -> list[tuple[float, float]]:
    """Speed intervals a segment may take after one at ``prev``: a hold, or a move between the
    minimum and the top speed, within the speed change of ``prev`` and not reversing without a
    stop; with a ramp time, at most ``caps`` (the fastest forward and backward speeds the ramp
    allows after the speeds of the ramp before, :func:`_ramp_caps`)."""
    low = 0.0 if motors.min_speed_rad_s is None else motors.min_speed_rad_s[axis]
    moves = [(max(low, _TOL), top), (-top, -max(low, _TOL))]
    if caps is not None:
        moves = [(m[0], min(m[1], caps[0])) if m[0] > 0 else (max(m[0], -caps[1]), m[1]) for m in moves]
    if prev != 0.0:
        if motors.stop_before_reversing or motors.max_speed_change is not None:
            moves = [m for m in moves if (m[0] > 0) == (prev > 0)]
        if motors.max_speed_change is not None:
            a, b = sorted((prev * (1 - motors.max_speed_change), prev * (1 + motors.max_speed_change)))
            moves = [(max(lo, a), min(hi, b)) for lo, hi in moves]
    return [(0.0, 0.0), *[(lo, hi) for lo, hi in moves if lo <= hi]]


def _ramp_caps(before: Iterable[tuple[float, float, float]], t0: float, top: float, ramp: float) -> tuple[float, float]:
    """``(forward, backward)``: the fastest speeds a segment starting at ``t0`` may take under a
    ramp time (:mod:`fiberplan.ramps`): the executed speed changes by ``v(t) - v(t - ramp)`` per
    ramp, at most the ``top`` speed, so a speed and an opposite one commanded less than a ramp
    before add up to at most the top. ``before``: the joint's earlier segments ``(start, end,
    speed)``, latest first (read only as far back as a ramp)."""
    forward = backward = 0.0
    since = t0 - ramp * (1 - 1e-9)
    for _, end, v in before:
        if end <= since:
            break
        if v > 0.0:
            forward = max(forward, v)
        elif v < 0.0:
            backward = max(backward, -v)
    return top - backward, top - forward


def _stack_segments(stack: list[_Node], times: np.ndarray) -> Iterator[tuple[float, float, float]]:
    """The segments of a search path, latest first: ``(start, end, speed)``."""
    for idx in range(len(stack) - 1, 0, -1):
        yield float(times[stack[idx - 1].k]), float(times[stack[idx].k]), stack[idx].speed


def _fit_joint(
    times: np.ndarray, q: np.ndarray, band: np.ndarray, stops: tuple[float, float], top: float, motors: MotorLimits,
    axis: int, step: int, search: tuple[int, int] = SEARCH,
) -> tuple[JointProfile, int] | None:
    """Fit one joint (planned angles ``q (T,)``, corridor half-width ``band (T,)`` rad): ``None``
    if the joint never moves, else its profile and the number of segments that had to break a
    motor limit (0 unless the search below fails).

    Depth-first search over breakpoints, longest segment first (:func:`_options`, ``search[0]``
    from each); a dead end (no allowed speed stays in the corridor) backtracks. After
    ``search[1]`` breakpoints tried, the greedy fit that breaks a motor limit where it must
    (:func:`_relaxed_fit`) is taken.
    """
    moved = np.flatnonzero(q[1:] != q[:-1])
    if len(moved) == 0:
        return None
    k0 = int(moved[0]) // step * step
    k1 = k0 + -(-(int(moved[-1]) + 1 - k0) // step) * step  # the last move's end, on the command grid
    if k1 >= len(times):  # past the last sample: the joint holds its final angle
        extra = k1 - len(times) + 1
        times = np.concatenate([times, times[-1] + (times[-1] - times[-2]) * np.arange(1, extra + 1)])
        q = np.concatenate([q, np.repeat(q[-1:], extra)])
        band = np.concatenate([band, np.repeat(band[-1:], extra)])
    lo = np.maximum(q - band, stops[0] - _TOL)
    hi = np.minimum(q + band, stops[1] + _TOL)
    lo[k0], hi[k0], lo[k1], hi[k1] = q[k0], q[k0], q[k1], q[k1]
    _reachable(lo, hi, times, top, k0, k1)
    cor = _Corridor(times, q, lo, hi, k0, k1, step, top, motors, axis, search[0])
    p0 = float(q[k0])
    cone = _cone(cor, k0, p0)
    if ONE_SEGMENT_SHORTCUTS and _reaches_end(cor, cone, 0.0):
        # One segment fits: the search's first option (the farthest end, here the last), taken directly.
        durations = np.diff(times[[k0, k1]])
        return _trimmed(float(times[k0]), p0, durations, np.diff(np.array([p0, float(q[k1])])) / durations), 0
    stack = [_Node(k0, p0, 0.0, _options(cor, k0, p0, 0.0, cone))]
    tried = 0
    while stack and stack[-1].k < k1 and tried < search[1]:
        node = stack[-1]
        if not node.options:
            stack.pop()
            continue
        m, s = node.options.pop(0)
        tried += 1
        p = float(q[k1]) if m == k1 else node.p + s * float(times[m] - times[node.k])
        if m == k1:
            stack.append(_Node(m, p, s, []))
            continue
        cone = _cone(cor, m, p)
        caps = None if motors.ramp_time_s is None else _ramp_caps(
            itertools.chain([(float(times[node.k]), float(times[m]), s)], _stack_segments(stack, times)), float(times[m]), top, motors.ramp_time_s)
        if ONE_SEGMENT_SHORTCUTS and tried < search[1] and _reaches_end(cor, cone, s, caps):
            # The search's next step from here would be that last segment (its farthest option): taken directly.
            stack += [_Node(m, p, s, []), _Node(k1, float(q[k1]), 0.0, [])]
            break
        stack.append(_Node(m, p, s, _options(cor, m, p, s, cone, caps)))
    if stack and stack[-1].k == k1:
        knots = [(node.k, node.speed) for node in stack[1:]]
        ks = np.array([k0] + [k for k, _ in knots])
        durations = np.diff(times[ks])
        speeds = np.diff(np.array([node.p for node in stack])) / durations
        relaxed = 0
    else:
        durations, speeds, relaxed = _relaxed_fit(cor)
        if relaxed and motors.ramp_time_s is not None:  # the planned samples themselves, where they break fewer limits
            sampled = _sampled_fit(cor)
            if sampled[2] < relaxed:
                durations, speeds, relaxed = sampled
    return _trimmed(float(times[k0]), float(q[k0]), durations, speeds), relaxed


def _sampled_fit(cor: _Corridor) -> tuple[np.ndarray, np.ndarray, int]:
    """The joint's planned samples as its segments (every sample a breakpoint, on the command
    grid), and how many of them break a motor limit (:func:`_allowed_speeds`, with the ramp's
    caps; and each segment beyond ``max_segments``). A planner that keeps the limits in its
    steps (the mpc's governor) leaves few: where the search runs out, following the plan can
    then break fewer than the greedy fit (taken only with a ramp time: without one nothing
    changes)."""
    ks = np.arange(cor.k0, cor.k1 + 1, cor.step)
    if ks[-1] != cor.k1:
        ks = np.append(ks, cor.k1)
    durations = np.diff(cor.times[ks])
    speeds = np.diff(cor.q[ks]) / durations
    ramp = cor.motors.ramp_time_s
    done: list[tuple[float, float, float]] = []
    broken = 0
    prev = 0.0
    tol = 1e-9 * cor.top + _TOL
    for k, k_next, v in zip(ks[:-1].tolist(), ks[1:].tolist(), speeds.tolist(), strict=True):
        caps = None if ramp is None else _ramp_caps(reversed(done), float(cor.times[k]), cor.top, ramp)
        allowed = _allowed_speeds(prev, cor.top, cor.motors, cor.axis, caps)
        if not any(a - tol <= v <= b + tol for a, b in allowed):
            broken += 1
        done.append((float(cor.times[k]), float(cor.times[k_next]), v))
        prev = v
    runs = 1 + int(np.count_nonzero(np.abs(np.diff(speeds)) > _TOL))
    if cor.motors.max_segments is not None and runs > cor.motors.max_segments:
        broken += runs - cor.motors.max_segments  # too many segments: each one over counts
    return durations, speeds, broken


@dataclass(frozen=True, eq=False)
class _Corridor:
    """One joint's fitting problem: planned angles, corridor, window ``[k0, k1]``, limits."""

    times: np.ndarray
    q: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    k0: int
    k1: int
    step: int
    top: float
    motors: MotorLimits
    axis: int
    branches: int


@dataclass(eq=False)
class _Node:
    """A breakpoint of the search: sample ``k``, angle ``p``, speed of the segment ending here,
    and the segments still to try from here."""

    k: int
    p: float
    speed: float
    options: list[tuple[int, float]]


def _cone(cor: _Corridor, k: int, p: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float]:
    """From angle ``p`` at sample ``k``: the candidate breakpoint samples, and at each the
    speeds ``[s_lo, s_hi]`` that keep a segment in the corridor, and the speed back onto the
    path; last, those speeds for a segment to the window's end (the cone's last extent)."""
    window = slice(k + 1, cor.k1 + 1)
    dt = cor.times[window] - cor.times[k]
    s_lo = np.maximum.accumulate((cor.lo[window] - p) / dt)
    s_hi = np.minimum.accumulate((cor.hi[window] - p) / dt)
    closed = s_lo > s_hi + _TOL  # from its first True on (the cone only narrows)
    open_ = int(np.argmax(closed)) if closed[-1] else len(dt)
    if cor.step == 1:  # every sample up to the cone's closing (at least the next)
        n = max(open_, 1)
        return (np.arange(k + 1, k + 1 + n), s_lo[:n], s_hi[:n], (cor.q[k + 1:k + 1 + n] - p) / dt[:n],
                float(s_lo[-1]), float(s_hi[-1]))
    js = np.arange(k + 1, cor.k1 + 1)
    on_grid = ((js - cor.k0) % cor.step == 0) | (js == cor.k1)
    cand = np.flatnonzero(on_grid[:open_])
    if len(cand) == 0:
        cand = np.flatnonzero(on_grid)[:1]
    return js[cand], s_lo[cand], s_hi[cand], (cor.q[js[cand]] - p) / dt[cand], float(s_lo[-1]), float(s_hi[-1])


def _reaches_end(cor: _Corridor, cone: tuple[Any, ...], prev: float, caps: tuple[float, float] | None = None) -> bool:
    """Whether one segment from the cone's apex reaches the last sample's angle inside the
    corridor at a speed the motors accept after ``prev``: exactly when :func:`_options` would
    offer the last sample first (the cone only narrows, so its last extent decides)."""
    s_lo, s_hi = cone[4], cone[5]
    return s_lo <= s_hi + _TOL and any(max(s_lo, a) <= min(s_hi, b) + _TOL for a, b in _allowed_speeds(prev, cor.top, cor.motors, cor.axis, caps))


def _options(
    cor: _Corridor, k: int, p: float, prev: float, cone: tuple[Any, ...] | None = None, caps: tuple[float, float] | None = None,
) -> list[tuple[int, float]]:
    """Up to ``cor.branches`` next segments ``(end sample, speed)`` the motors accept after ``prev``
    (and ``caps``, :func:`_allowed_speeds`) and the corridor holds (from ``cone``, :func:`_cone`
    at ``k, p``, if given): farthest end first, then the speed nearest the path."""
    ends, s_lo, s_hi, aim, _, _ = _cone(cor, k, p) if cone is None else cone
    found: list[tuple[int, float, float]] = []
    for a, b in _allowed_speeds(prev, cor.top, cor.motors, cor.axis, caps):
        lo = np.maximum(s_lo, a)
        hi = np.minimum(s_hi, b)
        for c in np.flatnonzero(lo <= hi + _TOL)[-cor.branches:].tolist():
            lo_c, hi_c, aim_c = float(lo[c]), float(hi[c]), float(aim[c])
            s = min(max(aim_c, lo_c), max(lo_c, hi_c))  # np.clip's value, without its per-call cost
            found.append((int(ends[c]), s, abs(s - aim_c)))
    found.sort(key=lambda f: (-f[0], f[2]))
    return [(m, s) for m, s, _ in found[:cor.branches]]


def _relaxed_fit(cor: _Corridor) -> tuple[np.ndarray, np.ndarray, int]:
    """The greedy fit that stays in the corridor and, where no allowed speed does, takes the
    speed back onto the path (clipped to the corridor and the top speed), breaking a motor
    limit. Returns durations, speeds and the number of such segments."""
    k, p, prev = cor.k0, float(cor.q[cor.k0]), 0.0
    ks, ps = [k], [p]
    relaxed = 0
    ramp = cor.motors.ramp_time_s
    done: list[tuple[float, float, float]] = []  # the segments so far, in order (:func:`_ramp_caps` reads them latest first)
    while k < cor.k1:
        caps = None if ramp is None else _ramp_caps(reversed(done), float(cor.times[k]), cor.top, ramp)
        opts = _options(cor, k, p, prev, caps=caps)
        if opts:
            m, s = opts[0]
        else:
            relaxed += 1
            ends, s_lo, s_hi, aim, _, _ = _cone(cor, k, p)
            m, s = int(ends[0]), float(np.clip(np.clip(aim[0], s_lo[0], s_hi[0]), -cor.top, cor.top))
        p = float(cor.q[cor.k1]) if m == cor.k1 else p + s * float(cor.times[m] - cor.times[k])
        done.append((float(cor.times[k]), float(cor.times[m]), s))
        k, prev = m, s
        ks.append(k)
        ps.append(p)
    durations = np.diff(cor.times[np.array(ks)])
    return durations, np.diff(np.array(ps)) / durations, relaxed


def _trimmed(start_s: float, start_rad: float, durations: np.ndarray, speeds: np.ndarray) -> JointProfile:
    """A profile with consecutive equal speeds merged and leading and trailing holds dropped."""
    keep_d: list[float] = []
    keep_s: list[float] = []
    for d, s in zip(durations.tolist(), speeds.tolist(), strict=True):
        if keep_s and abs(s - keep_s[-1]) <= _TOL:
            keep_d[-1] += d
        else:
            keep_d.append(d)
            keep_s.append(s)
    while keep_s and keep_s[-1] == 0.0:
        keep_s.pop()
        keep_d.pop()
    while keep_s and keep_s[0] == 0.0:
        start_s += keep_d.pop(0)
        keep_s.pop(0)
    return JointProfile(start_s, start_rad, np.array(keep_d), np.array(keep_s))


def _reachable(lo: np.ndarray, hi: np.ndarray, times: np.ndarray, top: float, k0: int, k1: int) -> None:
    """Narrow the corridor ``[lo, hi]`` in place, backwards from ``k1``, so that from any angle in
    it at one sample the corridor at the next is reachable at the top speed. The planned path,
    itself within the top speed, stays inside; so does every greedy segment's end.

    With ``C_k`` the top-speed travel from ``k0`` to ``k``, the recursion
    ``lo_k <- max(lo_k, lo_{k+1} - (C_{k+1} - C_k))`` is ``lo_k <- C_k + max_{j >= k}(lo_j - C_j)``
    (and ``hi`` alike), a reversed running extremum.
    """
    travel = np.concatenate([[0.0], np.cumsum(top * np.diff(times[k0:k1 + 1]))])
    window = slice(k0, k1 + 1)
    lo[window] = travel + np.maximum.accumulate((lo[window] - travel)[::-1])[::-1]
    hi[window] = -travel + np.minimum.accumulate((hi[window] + travel)[::-1])[::-1]


def _follow_samples(times: np.ndarray, q: np.ndarray, fits: dict[tuple[int, int], JointProfile], i: int) -> None:
    """Replace positioner ``i``'s profiles by its planned samples (one segment per change of speed)."""
    for axis in (0, 1):
        fits.pop((i, axis), None)
        dq = np.diff(q[:, axis])
        moved = np.flatnonzero(dq != 0)
        if len(moved) == 0:
            continue
        k0, k1 = int(moved[0]), int(moved[-1]) + 1
        dt = np.diff(times[k0:k1 + 1])
        v = dq[k0:k1] / dt
        change = np.flatnonzero(np.abs(np.diff(v)) > _TOL) + 1
        bounds = np.concatenate([[0], change, [len(v)]])
        durations = np.array([dt[a:b].sum() for a, b in itertools.pairwise(bounds)])
        speeds = v[bounds[:-1]]
        fits[(i, axis)] = JointProfile(float(times[k0]), float(q[k0, axis]), durations, speeds)
