"""Speed ramps: what the motors do with commands whose speed changes take time.

A motor controller with a ramp time ``tau`` (the instrument file's ``[motors] ramp_time_s``, or
``max_acceleration_rpm_per_s``) cannot change a joint's speed at once: each commanded speed
change becomes a linear ramp of the speed over ``tau``, starting at the command. For commands
that are piecewise linear in time (motor profiles, time-stamped angle points, a planner's
samples), the joint then follows the **causal moving average** of the commanded angle over the
ramp time::

    e(t) = (1 / tau) * integral over [t - tau, t] of p(s) ds

whose speed ``(p(t) - p(t - tau)) / tau`` is the commanded speed ramped linearly over ``tau``
after each change, and whose acceleration ``(v(t) - v(t - tau)) / tau`` is at most the top
speed over ``tau`` unless a joint reverses with less than ``tau`` of hold between. The motion
starts at the commanded start (the joint rests before the first command), ends at the commanded
end ``tau`` after the last command, stays within the hard stops and the top speed (an average of
the commands), and lags the commands by ``tau / 2``; every joint of every positioner lags alike,
so the configurations met are those of the commands, each joint smoothed around its
breakpoints by at most ``|dv| tau / 8`` (``top tau / 8`` without reversals, ``top tau / 4``
with). :func:`verify_commands` checks commands as they are sent (motor limits) and as the
motors execute them (collisions, hard stops, speeds, acceleration).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fiberplan.instrument import Instrument, MotorLimits
from fiberplan.scenario import Scenario
from fiberplan.trajectory import Trajectory
from fiberplan.verify import LimitViolation, VerificationReport, verify

RAMP_CHORDS = 8  # the executed motion is sampled at least this often per ramp time (the chord of a ramp's parabola
# is then within top * tau / 512 of it: 1.5 micrometres of a 20 mm arm at 0.4 rad/s and 0.1 s)
SAMPLE_MAX_S = 0.05  # and at least this often (the rebuilt profiles' own grid)
_MIN_STEP_S = 1e-6  # executed samples closer than this to the previous one are left out
_CHUNK_SAMPLES = 256  # executed samples computed at once (memory: this x positioners x 2)


def max_acceleration_rad_s2(inst: Instrument) -> tuple[float, float] | None:
    """``(alpha, beta)`` the acceleration the ramps allow: top speed over ramp time (``None``: no ramp)."""
    tau = inst.motors.ramp_time_s
    if tau is None:
        return None
    return inst.alpha_speed_rad_s / tau, inst.beta_speed_rad_s / tau


def executed_motion(trajectory: Trajectory, ramp_s: float) -> Trajectory:
    """The motion of joints commanded along ``trajectory`` (linear between its samples) by a
    controller that ramps every speed change over ``ramp_s`` (see the module docstring).

    Sampled at every command time and every speed change plus ``ramp_s`` (the executed motion is
    quadratic between two of them and linear outside the ramps), at least every ``ramp_s /
    RAMP_CHORDS`` inside a ramp and every :data:`SAMPLE_MAX_S` outside; it lasts ``ramp_s``
    longer than the commands.
    """
    if not ramp_s > 0:
        raise ValueError(f"ramp_s must be > 0, found {ramp_s}")
    t = np.asarray(trajectory.times, dtype=float)
    q = np.asarray(trajectory.joints, dtype=float)
    if len(t) == 1:
        return Trajectory(t.copy(), q.copy())
    dt = np.diff(t)[:, None, None]
    slope = np.diff(q, axis=0) / dt  # (K-1, N, 2)
    # The speed changes where some joint's slope does (at the first sample, from rest): the ramps start there.
    turns = np.concatenate([[True], np.any(np.abs(np.diff(slope, axis=0)) > 1e-12, axis=(1, 2)), [True]])
    grid = np.unique(np.round(np.concatenate([t, t[turns] + ramp_s]) / 1e-9) * 1e-9)
    ramping = np.zeros(len(grid) - 1, dtype=bool)  # grid intervals inside some ramp: sampled finely
    for start in t[turns]:
        ramping[np.searchsorted(grid, start - 1e-9):max(np.searchsorted(grid, start + ramp_s - 1e-9), 0)] = True
    step = np.where(ramping, min(SAMPLE_MAX_S, ramp_s / RAMP_CHORDS), SAMPLE_MAX_S)
    pieces = np.maximum(1, np.ceil(np.diff(grid) / step - 1e-9).astype(int))
    grid = np.concatenate([*(np.linspace(a, b, k, endpoint=False) for a, b, k in zip(grid[:-1], grid[1:], pieces, strict=True)),
                           grid[-1:]])
    keep = np.concatenate([[True], np.diff(grid) > _MIN_STEP_S])  # no sliver intervals: a chord's speed stays exact
    if not keep[-1]:  # the last sample stays; the kept one just before it goes (unless it is the first)
        before = int(np.flatnonzero(keep)[-1])
        keep[before] = before == 0
        keep[-1] = True
    grid = grid[keep]
    area = np.concatenate([np.zeros((1, *q.shape[1:])), np.cumsum(0.5 * (q[1:] + q[:-1]) * dt, axis=0)])  # integral from t[0]

    def integral(x: np.ndarray) -> np.ndarray:
        """Integral of the commanded angle from ``t[0]`` to each ``x`` (resting before and after)."""
        k = np.clip(np.searchsorted(t, x, side="right") - 1, 0, len(t) - 1)
        h = (x - t[k])[:, None, None]
        inner = (k < len(t) - 1) & (x >= t[0])
        ks = np.minimum(k, len(t) - 2)
        out = area[k] + q[k] * h + np.where(inner[:, None, None], 0.5 * slope[ks] * h * h, 0.0)
        before = x < t[0]
        if before.any():
            out[before] = q[0] * (x[before] - t[0])[:, None, None]
        return out

    out = np.empty((len(grid), *q.shape[1:]))
    for a in range(0, len(grid), _CHUNK_SAMPLES):
        x = grid[a:a + _CHUNK_SAMPLES]
        out[a:a + _CHUNK_SAMPLES] = (integral(x) - integral(x - ramp_s)) / ramp_s
    out[grid <= t[0]] = q[0]  # exactly at rest before the first command is felt
    out[grid >= t[-1] + ramp_s] = q[-1]  # and exactly at the end once the last ramp is over
    return Trajectory(grid, out)


def verify_commands(scenario: Scenario, commands: Trajectory, instrument: Instrument | None = None) -> VerificationReport:
    """Check motor commands (a trajectory linear between its samples: rebuilt profiles, anyone's
    time-stamped points): as sent, every check of :func:`fiberplan.verify.verify` and the motor
    limits; where the instrument states a ramp time, also as the motors execute them
    (:func:`executed_motion`): collisions, hard stops and speeds (added to the report, so
    ``ok`` covers both), the smallest clearance of either, and an ``acceleration`` motor
    violation where the executed speed changes faster than the top speed over the ramp time."""
    inst = scenario.instrument if instrument is None else instrument
    report = verify(scenario, commands, instrument=inst)
    tau = inst.motors.ramp_time_s
    if tau is None or not report.motors_checked or report.non_finite:
        return report
    moved = executed_motion(commands, tau)
    safety = dataclasses.replace(inst, motors=MotorLimits())
    executed = verify(scenario, moved, instrument=safety)
    known = {(e.id_i, e.id_j, e.capsule_i, e.capsule_j) for e in report.collisions}
    report.collisions.extend(e for e in executed.collisions if (e.id_i, e.id_j, e.capsule_i, e.capsule_j) not in known)
    report.limit_violations.extend(executed.limit_violations)
    report.min_clearance_mm = min(report.min_clearance_mm, executed.min_clearance_mm)
    report.motor_violations.extend(_acceleration_violations(inst, scenario.ids, moved))
    report.executed_ramp_s = tau
    return report


def _acceleration_violations(inst: Instrument, ids: np.ndarray, moved: Trajectory) -> list[LimitViolation]:
    """One ``acceleration`` violation per positioner and joint whose executed speed (chord
    slopes) changes faster than :func:`max_acceleration_rad_s2` (worst and first instants)."""
    limits = max_acceleration_rad_s2(inst)
    if limits is None or len(moved.times) < 3:
        return []
    dt = np.diff(moved.times)
    found: list[LimitViolation] = []
    for axis, joint_name in enumerate(("alpha", "beta")):
        v = np.diff(moved.joints[:, :, axis], axis=0) / dt[:, None]
        acc = np.abs(np.diff(v, axis=0)) / (0.5 * (dt[1:] + dt[:-1]))[:, None]  # (M-2, N), at moved.times[1:-1]
        over = acc > limits[axis] * (1 + 1e-6) + 1e-9
        for i in np.flatnonzero(over.any(axis=0)):
            worst = int(np.argmax(np.where(over[:, i], acc[:, i], -np.inf)))
            first = int(np.argmax(over[:, i]))
            found.append(LimitViolation(int(ids[i]), joint_name, float(moved.times[worst + 1]), float(acc[worst, i]),
                                        float(limits[axis]), "acceleration", float(moved.times[first + 1])))
    return found
