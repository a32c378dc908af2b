"""Forward and inverse kinematics of theta-phi positioners, Jacobians and joint limits.

Fiber position of positioner ``i`` (reference 000, eq. 1, with the base orientation
``orient_i`` added):

.. math::

    p_i = b_i + R(o_i) \\left[ l_1 (\\cos a, \\sin a) + l_2 (\\cos(a + b), \\sin(a + b)) \\right]

Parity: ``+1`` when ``sin(beta) > 0`` (elbow on one side of the base-fiber line), ``-1``
when ``sin(beta) < 0``. Instruments whose beta range is ``[0, 180]`` deg only have parity +1.

Angles are absolute inside the hard stops: a move goes straight from one angle to another
and never wraps across a stop.
"""

from __future__ import annotations

import numpy as np

from fiberplan.instrument import Instrument

TWO_PI = 2.0 * np.pi


def rotate(vectors: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate ``(..., 2)`` vectors by ``angle`` (broadcast against ``vectors[..., 0]``)."""
    c, s = np.cos(angle), np.sin(angle)
    x, y = vectors[..., 0], vectors[..., 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=-1)


def elbow_positions(instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Elbow (alpha arm tip) positions, shape ``joints.shape``."""
    a = joints[..., 0] + orient
    return base_xy + instrument.alpha_arm_mm * np.stack([np.cos(a), np.sin(a)], axis=-1)


def fiber_positions(instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Fiber positions in the focal plane for joints ``(..., N, 2)``; returns ``(..., N, 2)``."""
    a = joints[..., 0] + orient
    ab = a + joints[..., 1]
    l1, l2 = instrument.alpha_arm_mm, instrument.beta_arm_mm
    return base_xy + np.stack([l1 * np.cos(a) + l2 * np.cos(ab), l1 * np.sin(a) + l2 * np.sin(ab)], axis=-1)


def fiber_jacobian(instrument: Instrument, orient: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Jacobian ``d(x, y) / d(alpha, beta)`` of the fiber position, shape ``(..., 2, 2)``.

    .. math::

        J = \\begin{pmatrix} -l_1 \\sin a - l_2 \\sin(a+b) & -l_2 \\sin(a+b) \\\\
                             l_1 \\cos a + l_2 \\cos(a+b) & l_2 \\cos(a+b) \\end{pmatrix}

    with ``a`` including the base orientation.
    """
    a = joints[..., 0] + orient
    ab = a + joints[..., 1]
    l1, l2 = instrument.alpha_arm_mm, instrument.beta_arm_mm
    jac = np.empty((*joints.shape[:-1], 2, 2))
    jac[..., 0, 1] = -l2 * np.sin(ab)
    jac[..., 1, 1] = l2 * np.cos(ab)
    jac[..., 0, 0] = -l1 * np.sin(a) + jac[..., 0, 1]
    jac[..., 1, 0] = l1 * np.cos(a) + jac[..., 1, 1]
    return jac


def parity_of(beta: np.ndarray) -> np.ndarray:
    """Parity ``+1`` / ``-1`` of beta angles (``+1`` where ``sin(beta) >= 0``)."""
    return np.where(np.sin(beta) >= 0.0, 1, -1)


def into_range(angle: np.ndarray, lo: float, hi: float, tol: float = 1e-9) -> np.ndarray:
    """Shift each angle by a multiple of 2 pi into ``[lo, hi]``; NaN where no shift fits.

    Angles within ``tol`` outside a stop are clipped onto it.
    """
    angle = np.asarray(angle, dtype=float)
    shifted = lo + np.mod(angle - lo, TWO_PI)
    # An angle just below ``lo`` maps to lo + 2 pi - tiny: bring it back onto ``lo``.
    near_lo_wrap = shifted > lo + TWO_PI - tol
    shifted = np.where(near_lo_wrap, lo, shifted)
    ok = shifted <= hi + tol
    return np.where(ok, np.minimum(shifted, hi), np.nan)


def inverse_kinematics(
    instrument: Instrument,
    base_xy: np.ndarray,
    orient: np.ndarray,
    fiber_xy: np.ndarray,
    parity: np.ndarray,
) -> np.ndarray:
    """Joint angles placing each fiber at ``fiber_xy`` with the given parity (+1 or -1).

    Returns ``(N, 2)`` angles inside the hard stops, NaN rows where the point is outside the
    patrol region or the parity's solution lies beyond a hard stop.
    """
    fiber_xy = np.asarray(fiber_xy, dtype=float)
    local = rotate(fiber_xy - base_xy, -np.asarray(orient, dtype=float))
    l1, l2 = instrument.alpha_arm_mm, instrument.beta_arm_mm
    r2 = np.sum(local**2, axis=-1)
    cos_b = (r2 - l1**2 - l2**2) / (2 * l1 * l2)
    # Points within rounding of the reach circles are pulled onto them.
    eps = 1e-9
    reachable = (cos_b >= -1 - eps) & (cos_b <= 1 + eps)
    b = np.asarray(parity, dtype=float) * np.arccos(np.clip(cos_b, -1.0, 1.0))
    a = np.arctan2(local[..., 1], local[..., 0]) - np.arctan2(l2 * np.sin(b), l1 + l2 * np.cos(b))
    lim = instrument.limits_rad
    alpha = into_range(a, lim[0, 0], lim[0, 1])
    beta = into_range(b, lim[1, 0], lim[1, 1])
    joints = np.stack([alpha, beta], axis=-1)
    joints[~reachable] = np.nan
    joints[np.isnan(joints).any(axis=-1)] = np.nan
    return joints


def straight_path(q: np.ndarray, goal: np.ndarray, step_rad: np.ndarray, n_steps: int) -> np.ndarray:
    """Saturated joint-space path from ``q`` toward ``goal``: ``(N, n_steps, 2)``: every joint at full
    speed (``step_rad`` per step) straight toward its goal, stopping there.

    .. math:: r(k) = q + \\operatorname{clip}(g - q, -k \\omega h, k \\omega h), \\quad k = 1..n
    """
    k = np.arange(1, n_steps + 1)[None, :, None]
    delta = (goal - q)[:, None, :]
    return q[:, None, :] + np.clip(delta, -k * step_rad, k * step_rad)


def move_times(instrument: Instrument, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Unobstructed straight-move time of each positioner, every joint at full speed (s).

    .. math:: T_i = \\max_k |q_{goal,ik} - q_{start,ik}| / \\omega_{max,k}
    """
    return np.max(np.abs(np.asarray(goal) - np.asarray(start)) / instrument.speeds_rad_s, axis=-1)


def best_parity_joints(
    instrument: Instrument,
    base_xy: np.ndarray,
    orient: np.ndarray,
    fiber_xy: np.ndarray,
    start: np.ndarray,
) -> np.ndarray:
    """Joint solution of the faster parity from ``start`` (NaN rows where neither exists)."""
    n = len(fiber_xy)
    plus = inverse_kinematics(instrument, base_xy, orient, fiber_xy, np.ones(n))
    minus = inverse_kinematics(instrument, base_xy, orient, fiber_xy, -np.ones(n))
    t_plus = np.where(np.isnan(plus[:, 0]), np.inf, move_times(instrument, start, np.nan_to_num(plus)))
    t_minus = np.where(np.isnan(minus[:, 0]), np.inf, move_times(instrument, start, np.nan_to_num(minus)))
    return np.where((t_minus < t_plus)[:, None], minus, plus)
