"""A governor that makes each executed step one the instrument's motor controllers accept.

Planners that step on a fixed grid (the ``mpc``, and the coordination layer through it) pass
each proposed step through :func:`govern` before their safety layer. Each step is one
constant-speed command per joint; the rules are the verifier's
(:func:`fiberplan.verify.verify`, kinds ``reversal``, ``speed_change``, ``min_speed``):

1. **Stop before reversing** (``stop_before_reversing``, and implied by ``max_speed_change``):
   a joint moving one way whose proposal turns back holds for this step.
2. **Speed change** (``max_speed_change = c``): a joint moving at speed ``v`` keeps a speed in
   ``[(1 - c) |v|, (1 + c) |v|]`` in the same direction (``[|v| / (1 + c), |v| / (1 - c)]`` in
   a leg planned backwards, to be played reversed). A proposal below that band holds (a stop,
   which is exempt) when it is under half the band's low end, else takes the low end; a
   proposal above it takes the high end.
3. **Minimum speed** (``min_speed_rpm``): a moving joint turns at least the minimum speed; a
   slower proposal takes the minimum speed (a joint is never held forever short of its goal),
   or stops where the minimum lies above the band.
4. **Ramps** (``ramp_time_s``, :mod:`fiberplan.ramps`): the controller ramps each speed change
   over the ramp time, at most the top speed per ramp, so a speed and an opposite one commanded
   less than a ramp before add up to at most the top speed. A joint whose step would break that
   (turning back soon after moving fast) holds: a reversal of a fast joint waits a ramp at rest.

A joint heading for its goal takes the allowed speed nearest its proposal that leaves a
remainder the rules can still cover exactly (:func:`_arrive_in_band`), so arrivals keep the
band where they can. A step that lands a joint on its goal without reversing is exempt from
rules 2 and 3 (a remainder shorter than a minimum-speed step can only be covered slowly; the
discretiser absorbs it), and no rounding carries a joint past its goal or a hard stop.

Holding is always safe, and the safety layer checks exactly what the governor returns, so
collisions stay excluded; the cost is time, measured in ``docs/results.md`` (issue 23).
"""

from __future__ import annotations

import numpy as np

from fiberplan.instrument import MotorLimits

_TOL = 1e-12


def governs(motors: MotorLimits) -> bool:
    """Whether :func:`govern` changes anything under these limits."""
    return bool(motors.stop_before_reversing or motors.max_speed_change is not None or motors.min_speed_rad_s is not None
                or motors.ramp_time_s is not None)


def govern(
    q: np.ndarray, q_next: np.ndarray, v_prev: np.ndarray, goal: np.ndarray, dt: float, motors: MotorLimits, top: np.ndarray,
    limits: np.ndarray, reverse: bool = False, recent: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """The steps ``q -> q_next`` made acceptable to the motors (see the module docstring).

    Args:
        q: ``(N, 2)`` the configuration now (rad).
        q_next: ``(N, 2)`` the proposed next configuration.
        v_prev: ``(N, 2)`` the speed of the step just executed (rad/s).
        goal: ``(N, 2)`` each positioner's current goal (a step landing on it is exempt).
        dt: the step (s).
        motors: the instrument's motor limits.
        top: ``(2,)`` top speeds (rad/s).
        limits: ``(2, 2)`` hard stops, ``[[alpha_lo, alpha_hi], [beta_lo, beta_hi]]``.
        reverse: the motion is planned backwards in time, to be played reversed (the
            coordination layer's ``reverse`` legs): the speed change is then bounded relative
            to the new step, ``[|v| / (1 + c), |v| / (1 - c)]``.
        recent: ``((N, 2), (N, 2))`` each joint's fastest forward and backward speeds (rad/s, both
            >= 0) over the steps of the last ramp time (rule 4).

    Returns:
        ``(N, 2)`` the governed next configuration.
    """
    v = (q_next - q) / dt
    speed = np.abs(v)
    direction = np.sign(v)
    prev = np.abs(v_prev)
    moving_before = prev > _TOL
    out = speed.copy()
    if motors.stop_before_reversing or motors.max_speed_change is not None:
        out = np.where(moving_before & (v * v_prev < 0), 0.0, out)
    c = motors.max_speed_change
    if c is not None:
        lo, hi = (prev / (1 + c), prev / (1 - c)) if reverse else ((1 - c) * prev, (1 + c) * prev)
        hi = np.minimum(hi, top)
        same = moving_before & (out > _TOL)
        out = np.where(same & (out > hi), hi, out)
        out = np.where(same & (out < lo), np.where(out < 0.5 * lo, 0.0, lo), out)
    low = np.zeros(2) if motors.min_speed_rad_s is None else np.asarray(motors.min_speed_rad_s)
    out = np.where((out > _TOL) & (out < low), low, out)
    if c is not None:  # the minimum above the band (after a slow arrival, say): stop
        out = np.where(moving_before & (out > hi), 0.0, out)
    ahead = direction * (goal - q)  # distance still to go toward the goal (rad), >= 0 when heading there
    if c is not None:
        out = _arrive_in_band(out, ahead / dt, prev, moving_before, lo, hi, low, top, c, reverse)
    ramp_hold = np.zeros(out.shape, dtype=bool)
    if motors.ramp_time_s is not None and recent is not None:  # rule 4: with an opposite speed of the ramp before, at most the top
        opposite = np.where(direction > 0, recent[1], recent[0])
        ramp_hold = (out > _TOL) & (out + opposite > top * (1 + 1e-9))
        out = np.where(ramp_hold, 0.0, out)
    governed = q + direction * out * dt
    # No rounding carries a joint past its goal or a hard stop; an arrival is exempt.
    passed = (out > _TOL) & (ahead >= 0) & (out * dt >= ahead * (1 - 1e-12)) & (speed * dt <= ahead + _TOL)
    governed = np.where(passed, goal, governed)
    governed = np.where((q_next == goal) & ~(moving_before & (v * v_prev < 0)) & ~ramp_hold, q_next, governed)
    return np.clip(governed, limits[:, 0], limits[:, 1])


def hold_for_ramps(q: np.ndarray, q_next: np.ndarray, dt: float, top: np.ndarray, recent: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """Rule 4 alone (the positioners exempt from the others, ``(M, 2)`` arrays): a joint whose
    step ``q -> q_next`` turns back with an opposite speed of the last ramp (``recent``, as in
    :func:`govern`) such that the two add up to more than the top speed holds."""
    if recent is None:
        return q_next
    step = q_next - q
    speed = np.abs(step) / dt
    opposite = np.where(step > 0, recent[1], recent[0])
    return np.where((speed > _TOL) & (speed + opposite > top * (1 + 1e-9)), q, q_next)


_CANDIDATES = 17
"""Speeds tried across the allowed band when a step must leave a reachable remainder."""

_CHAIN = 4
"""Steps looked ahead: a remainder beyond what this many steps cover counts as reachable."""


def _arrive_in_band(
    out: np.ndarray, rest: np.ndarray, prev: np.ndarray, moving_before: np.ndarray, lo: np.ndarray, hi: np.ndarray, low: np.ndarray,
    top: np.ndarray, c: float, reverse: bool,
) -> np.ndarray:
    """Speeds ``out`` (rad/s) changed, where a joint heads for its goal (``rest``: the distance
    to it over the step, rad/s), so that what this step leaves can still be covered by steps that
    keep the speed change and the minimum speed and end exactly on the goal: the allowed speed
    nearest the proposal with a reachable remainder, else the proposal (a limit then breaks)."""
    a, b = (1 / (1 + c), 1 / (1 - c)) if reverse else (1 - c, 1 + c)  # next step / this step
    a, b = a * (1 + 1e-6), b * (1 - 1e-6)  # strictly inside the verifier's band
    heading = (out > _TOL) & (out < rest)  # moving toward the goal, not arriving this step
    if not heading.any():
        return out
    band_lo = np.where(moving_before, np.maximum(lo, low), low)
    band_hi = np.where(moving_before, hi, top)
    frac = np.linspace(0.0, 1.0, _CANDIDATES)
    cand = np.concatenate([out[..., None], band_lo[..., None] + frac * (band_hi - band_lo)[..., None]], axis=-1)
    ok = _reachable(rest[..., None] - cand, cand, a, b, low[..., None], top[..., None])
    ok[..., 1:] &= band_lo[..., None] <= band_hi[..., None]
    ok[..., 1:] &= cand[..., 1:] < rest[..., None]
    arrive = (rest >= band_lo) & (rest <= band_hi)  # arriving now keeps the band
    dist = np.where(ok, np.abs(cand - out[..., None]), np.inf)
    best = np.take_along_axis(cand, np.argmin(dist, axis=-1)[..., None], axis=-1)[..., 0]
    fixed = np.where(ok.any(axis=-1), best, np.where(arrive, rest, out))
    return np.where(heading, fixed, out)


def _reachable(rest: np.ndarray, step: np.ndarray, a: float, b: float, low: np.ndarray, top: np.ndarray) -> np.ndarray:
    """Whether a remainder ``rest`` can be covered after a step at speed ``step`` by up to
    ``_CHAIN`` steps, each within ``[a, b]`` times the one before, the minimum and the top
    speed (a longer remainder: yes)."""
    ok = np.zeros(rest.shape, dtype=bool)
    step_lo, step_hi = step.copy(), step.copy()
    sum_lo, sum_hi = np.zeros_like(step), np.zeros_like(step)
    for _ in range(_CHAIN):
        step_lo, step_hi = np.maximum(a * step_lo, low), np.minimum(b * step_hi, top)
        sum_lo, sum_hi = sum_lo + step_lo, sum_hi + step_hi
        ok |= (step_lo <= step_hi) & (rest >= sum_lo) & (rest <= sum_hi)
    return ok | (rest > sum_hi)
