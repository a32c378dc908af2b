"""Forward and inverse kinematics, Jacobians, joint limits."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fiberplan.instrument_io import load_instrument
from fiberplan.kinematics import (
    best_parity_joints,
    fiber_jacobian,
    fiber_positions,
    into_range,
    inverse_kinematics,
    move_times,
    parity_of,
)

INSTRUMENTS = {name: load_instrument(name) for name in ("desi", "moons-capsules", "sdss")}
angles = st.floats(-np.pi, np.pi, allow_nan=False)


@pytest.mark.parametrize("name", INSTRUMENTS)
@settings(max_examples=200, deadline=None)
@given(u=st.floats(0.0, 1.0), v=st.floats(0.02, 0.98), orient=angles, x=st.floats(-50, 50), y=st.floats(-50, 50))
def test_inverse_then_forward_returns_the_point(name, u, v, orient, x, y):
    inst = INSTRUMENTS[name]
    lim = inst.limits_rad
    joints = np.array([[lim[0, 0] + u * (lim[0, 1] - lim[0, 0]), lim[1, 0] + v * (lim[1, 1] - lim[1, 0])]])
    base, ori = np.array([[x, y]]), np.array([orient])
    point = fiber_positions(inst, base, ori, joints)
    parity = parity_of(joints[:, 1])
    back = inverse_kinematics(inst, base, ori, point, parity)
    assert not np.isnan(back).any()
    assert inst.within_limits(back).all()
    np.testing.assert_allclose(fiber_positions(inst, base, ori, back), point, atol=1e-9)


def test_desi_has_only_positive_parity():
    inst = INSTRUMENTS["desi"]
    point = np.array([[2.0, 1.0]])
    assert np.isnan(inverse_kinematics(inst, np.zeros((1, 2)), np.zeros(1), point, np.array([-1]))).all()
    assert not np.isnan(inverse_kinematics(inst, np.zeros((1, 2)), np.zeros(1), point, np.array([1]))).any()


def test_moons_has_both_parities():
    inst = INSTRUMENTS["moons-capsules"]
    point = np.array([[20.0, 3.0]])
    plus = inverse_kinematics(inst, np.zeros((1, 2)), np.zeros(1), point, np.array([1]))
    minus = inverse_kinematics(inst, np.zeros((1, 2)), np.zeros(1), point, np.array([-1]))
    assert not np.isnan(plus).any() and not np.isnan(minus).any()
    assert parity_of(plus[:, 1])[0] == 1 and parity_of(minus[:, 1])[0] == -1
    assert not np.allclose(plus, minus)


def test_outside_patrol_region_is_nan():
    inst = INSTRUMENTS["desi"]
    far = np.array([[6.5, 0.0]])
    assert np.isnan(inverse_kinematics(inst, np.zeros((1, 2)), np.zeros(1), far, np.array([1]))).all()


@pytest.mark.parametrize("name", INSTRUMENTS)
@settings(max_examples=100, deadline=None)
@given(a=angles, b=angles, orient=angles)
def test_jacobian_matches_finite_differences(name, a, b, orient):
    inst = INSTRUMENTS[name]
    q = np.array([[a, b]])
    ori = np.array([orient])
    base = np.zeros((1, 2))
    jac = fiber_jacobian(inst, ori, q)[0]
    h = 1e-6
    for k in range(2):
        dq = np.zeros((1, 2))
        dq[0, k] = h
        fd = (fiber_positions(inst, base, ori, q + dq) - fiber_positions(inst, base, ori, q - dq))[0] / (2 * h)
        np.testing.assert_allclose(jac[:, k], fd, atol=1e-6)


def test_into_range_never_wraps_across_a_stop():
    # MOONS beta range [0, 330] deg: -40 deg is 320 deg (inside); -20 deg is 340 deg (beyond the stop).
    lo, hi = 0.0, np.radians(330)
    assert np.degrees(into_range(np.radians(-40.0), lo, hi)) == pytest.approx(320.0)
    assert np.isnan(into_range(np.radians(-20.0), lo, hi))
    # angles a rounding error beyond a stop are put on it
    assert into_range(hi + 1e-12, lo, hi) == hi


def test_best_parity_is_the_faster_move():
    inst = INSTRUMENTS["moons-capsules"]
    point = np.array([[20.0, 3.0]])
    base, ori = np.zeros((1, 2)), np.zeros(1)
    plus = inverse_kinematics(inst, base, ori, point, np.array([1]))
    minus = inverse_kinematics(inst, base, ori, point, np.array([-1]))
    for start in (plus, minus):
        best = best_parity_joints(inst, base, ori, point, start)
        np.testing.assert_allclose(best, start, atol=1e-9)
    assert move_times(inst, plus, plus)[0] == 0.0
