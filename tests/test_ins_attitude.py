"""Attitude conversions: exact round trips and agreement with explicit rotation products."""

import math

import numpy as np
from hypothesis import given, settings, strategies as st
from scipy.linalg import expm

from ultratight.ins.attitude import (dcm_to_euler, dcm_to_quat, dcm_to_quat_vec, dcm_to_rotvec, euler_to_dcm,
                                     euler_to_dcm_vec, quat_mult, quat_to_dcm, quat_to_dcm_vec, quat_to_rotvec,
                                     rotvec_to_dcm, rotvec_to_dcm_vec, rotvec_to_quat, skew)


def R(axis, a):
    c, s = math.cos(a), math.sin(a)
    if axis == 0:
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 1:
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


angles = st.tuples(st.floats(-math.pi + 1e-6, math.pi - 1e-6), st.floats(-1.5, 1.5), st.floats(0.0, 2 * math.pi - 1e-9))
vec3 = st.tuples(*[st.floats(-3.0, 3.0)] * 3).map(np.array)


def test_euler_convention_geometry():
    # yaw 0 -> nose north, yaw 90 deg -> nose east; pitch up -> nose up; roll + -> right wing (-y) down
    C = euler_to_dcm(0.0, 0.0, 0.0)
    assert np.allclose(C[:, 0], [0, 1, 0]) and np.allclose(C[:, 1], [-1, 0, 0]) and np.allclose(C[:, 2], [0, 0, 1])
    assert np.allclose(euler_to_dcm(0.0, 0.0, math.pi / 2)[:, 0], [1, 0, 0], atol=1e-15)
    assert euler_to_dcm(0.0, 0.3, 0.0)[2, 0] > 0
    assert (euler_to_dcm(0.3, 0.0, 0.0) @ np.array([0, -1.0, 0]))[2] < 0


@settings(max_examples=120, deadline=None)
@given(angles)
def test_euler_dcm_round_trip_and_product(a):
    r, p, y = a
    C = euler_to_dcm(r, p, y)
    assert np.allclose(C, R(2, math.pi / 2 - y) @ R(1, -p) @ R(0, r), atol=1e-14)
    assert np.allclose(C, euler_to_dcm_vec(r, p, y), atol=1e-15)
    e = dcm_to_euler(C)
    assert abs(e[0] - r) < 1e-9 and abs(e[1] - p) < 1e-9
    assert abs(math.remainder(e[2] - y, 2 * math.pi)) < 1e-9


@settings(max_examples=120, deadline=None)
@given(vec3)
def test_quat_dcm_rotvec_round_trips(phi):
    ang = np.linalg.norm(phi)
    C = rotvec_to_dcm(phi)
    assert np.allclose(C, expm(skew(phi)), atol=1e-13)
    assert np.allclose(C.T @ C, np.eye(3), atol=1e-14)
    q = rotvec_to_quat(phi)
    assert abs(np.linalg.norm(q) - 1.0) < 1e-14
    assert np.allclose(quat_to_dcm(q), C, atol=1e-14)
    q2 = dcm_to_quat(C)
    assert q2[0] >= 0 and np.allclose(q2, q * np.sign(q[0] if q[0] != 0 else 1.0), atol=1e-12)
    back = quat_to_rotvec(q2)
    if ang < math.pi - 1e-6:
        assert np.allclose(back, phi, atol=1e-11)
    assert np.allclose(rotvec_to_dcm(dcm_to_rotvec(C)), C, atol=1e-12)
    assert np.allclose(rotvec_to_dcm_vec(phi[None])[0], C, atol=1e-14)


@settings(max_examples=100, deadline=None)
@given(vec3, vec3)
def test_quat_product_matches_dcm_product(a, b):
    qa, qb = rotvec_to_quat(a), rotvec_to_quat(b)
    assert np.allclose(quat_to_dcm(quat_mult(qa, qb)), quat_to_dcm(qa) @ quat_to_dcm(qb), atol=1e-13)


def test_small_angle_series_continuity():
    for a in (1e-12, 1e-6, 9.9e-5, 1.01e-4, 1e-3):
        phi = np.array([a, -0.5 * a, 0.3 * a])
        assert np.allclose(rotvec_to_dcm(phi), expm(skew(phi)), atol=4.5e-16, rtol=0)
        assert np.allclose(quat_to_rotvec(rotvec_to_quat(phi)), phi, rtol=1e-12, atol=0)


def test_vectorised_versions():
    rng = np.random.default_rng(3)
    phis = rng.normal(size=(50, 3))
    C = rotvec_to_dcm_vec(phis)
    q = dcm_to_quat_vec(C)
    assert np.allclose(quat_to_dcm_vec(q), C, atol=1e-14)
    assert np.all(q[:, 0] >= 0)
