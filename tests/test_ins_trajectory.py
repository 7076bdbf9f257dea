"""Analytic trajectory: Zhao et al. 2014 Table 2 kinematics, ECEF mapping, attitude/rate consistency, turns,
config errors."""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from ultratight.constants import OMEGA_E
from ultratight.errors import ConfigError
from ultratight.ins.attitude import skew
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef, radii
from ultratight.ins.trajectory import PAPER_HIGHDYN_RECEIVER, PAPER_HIGHDYN_TRAJECTORY, build_trajectory


@pytest.fixture(scope="module")
def paper():
    return build_trajectory(PAPER_HIGHDYN_TRAJECTORY, PAPER_HIGHDYN_RECEIVER, 60.0)


def test_table2_velocities(paper):
    # Zhao et al. 2014, Table 2 integrated by hand: east speed 100 t, +150 in 20-21 s, 200 m/s^2 to 40 s, ...
    t = np.array([0.0, 10.0, 20.0, 21.0, 40.0, 41.0, 60.0])
    k = paper.kinematics(t)
    vE = np.array([0.0, 1000.0, 2000.0, 2150.0, 5950.0, 5950.0, 2150.0])
    assert np.allclose(k["vel_l0"][:, 0], vE, atol=1e-9)
    assert np.allclose(k["vel_l0"][:, 1], 4.0 * t, atol=1e-12)
    assert np.allclose(k["vel_l0"][:, 2], 0.0)
    assert np.allclose(k["acc_l0"][:, 0], [100, 100, 100, 200, 200, -200, -200])
    # east distance at 60 s: 20000 + (2000 + 100/2 + 100/6) + (2150*19 + 200*19^2/2) + ... computed piecewise
    e = 0.5 * 100 * 20 ** 2
    e += 2000 * 1 + 0.5 * 100 + 100 / 6
    e += 2150 * 19 + 0.5 * 200 * 19 ** 2
    e += 5950 * 1 + 0.5 * 200 - 400 / 6
    e += 5950 * 19 - 0.5 * 200 * 19 ** 2
    assert abs(k["pos_l0"][-1, 0] - e) < 1e-6
    assert abs(k["pos_l0"][-1, 1] - 2.0 * 60 ** 2) < 1e-9
    assert np.max(np.linalg.norm(k["vel_l0"], axis=1)) < 6000


def test_ecef_mapping_and_height_gain(paper):
    pos, vel = paper.pos_vel_e(np.array([0.0]))
    lat0, lon0 = math.radians(28.2460), math.radians(102.0266)
    assert np.allclose(pos[0], llh_to_ecef(lat0, lon0, 50000.0), atol=1e-9)
    t = np.linspace(0, 60, 61)
    k = paper.kinematics(t)
    C = dcm_ecef_from_enu(lat0, lon0)
    assert np.allclose((k["pos_e"] - pos[0]) @ C, k["pos_l0"], atol=1e-6)
    # the tangent plane rises above the ellipsoid: h gain ~ d^2 / (2 R) (documented 2.58 km)
    d2 = np.sum(k["pos_l0"][-1, :2] ** 2)
    rm, rn = radii(lat0)
    e, n = k["pos_l0"][-1, :2]
    r_dir = (e * e + n * n) / (e * e / (rn + 5e4) + n * n / (rm + 5e4))
    assert abs((k["llh"][-1, 2] - 5e4) - d2 / (2 * r_dir)) < 0.01 * d2 / (2 * r_dir)
    assert 2500 < k["llh"][-1, 2] - 5e4 < 2650


def test_derivatives_consistent(paper):
    t = np.linspace(0.3, 59.7, 41)
    h = 1e-4
    p1, v1 = paper.pos_vel_e(t + h)
    p0, v0 = paper.pos_vel_e(t - h)
    _, v = paper.pos_vel_e(t)
    assert np.max(np.abs((p1 - p0) / (2 * h) - v)) < 1e-4
    k = paper.kinematics(t)
    assert np.max(np.abs((v1 - v0) / (2 * h) - k["acc_e"])) < 1e-4


def _omega_from_dcm(Cp, Cm, C, h):
    W = np.einsum("nji,njk->nik", C, (Cp - Cm) / (2 * h))
    return np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=1)


def test_velocity_attitude_and_inertial_rate(paper):
    t = np.linspace(0.5, 59.5, 30)
    h = 1e-4
    kp, km, k = paper.kinematics(t + h), paper.kinematics(t - h), paper.kinematics(t)
    # body x along velocity, wings level in l0
    u = k["vel_l"] / np.linalg.norm(k["vel_l"], axis=1)[:, None]
    assert np.allclose(k["C_lb"][:, :, 0], u, atol=1e-12)
    assert np.allclose(k["C_l0b"][:, 2, 1], 0.0, atol=1e-15)
    # omega_ib_b from the ECEF attitude C_eb = C_el C_lb and C_ib = R3(w t) C_eb (finite differences)
    def C_ib(kk):
        C_eb = np.einsum("nij,njk->nik", np.stack([dcm_ecef_from_enu(a, b) for a, b in kk["llh"][:, :2]]), kk["C_lb"])
        ang = OMEGA_E * kk["t"]
        R = np.zeros_like(C_eb)
        R[:, 0, 0] = R[:, 1, 1] = np.cos(ang)
        R[:, 0, 1], R[:, 1, 0] = -np.sin(ang), np.sin(ang)
        R[:, 2, 2] = 1.0
        return R @ C_eb
    w = _omega_from_dcm(C_ib(kp), C_ib(km), C_ib(k), h)
    assert np.max(np.abs(w - k["omega_ib_b"])) < 1e-9


def test_turns_kind_closed_circle_and_2g():
    rate = math.degrees(2 * 9.80665 / 30.0)             # 2 g at 30 m/s
    T = 360.0 / rate
    cfg = {"kind": "turns", "speed0_mps": 30.0, "heading0_deg": 90.0,
           "segments": [{"t0": 0.0, "turn_rate_dps": 0.0}, {"t0": 5.0, "turn_rate_dps": rate},
                        {"t0": 5.0 + T, "turn_rate_dps": 0.0, "speed_mps": 20.0}]}
    tr = build_trajectory(cfg, {"lat_deg": 45.0, "lon_deg": 7.0, "h_m": 300.0}, 5.0 + T + 10.0)
    k = tr.kinematics(np.array([5.0, 5.0 + T / 2, 5.0 + T, 5.0 + T + 10.0]))
    assert np.allclose(k["pos_l0"][0], [150.0, 0.0, 0.0], atol=1e-9)     # heading 90 = east
    assert np.allclose(k["pos_l0"][2], k["pos_l0"][0], atol=1e-8)         # full circle closes
    r = 30.0 / math.radians(rate)
    assert np.allclose(k["pos_l0"][1], [150.0, -2 * r, 0.0], atol=1e-8)   # right turn: to the south
    assert abs(np.linalg.norm(k["acc_l0"][1]) - 2 * 9.80665) < 1e-9
    assert abs(np.linalg.norm(k["vel_l0"][3]) - 20.0) < 1e-9
    # velocity / acceleration / jerk consistency by finite differences
    t = np.linspace(0.2, 5 + T + 9.8, 57)
    h = 1e-5
    kp, km, kk = tr.kinematics(t + h), tr.kinematics(t - h), tr.kinematics(t)
    for a, b in (("pos_l0", "vel_l0"), ("vel_l0", "acc_l0"), ("acc_l0", "jerk_l0")):
        assert np.max(np.abs((kp[a] - km[a]) / (2 * h) - kk[b])) < 1e-5
    w = _omega_from_dcm(kp["C_l0b"], km["C_l0b"], kk["C_l0b"], h)
    assert np.max(np.abs(w - kk["omega_eb_b"])) < 1e-7


def test_rates_attitude_mode():
    cfg = {"kind": "static", "attitude": "rates", "att0_deg": [10.0, -5.0, 30.0],
           "segments": [{"t0": 0.0, "rate_dps": [1.0, 2.0, -3.0]}, {"t0": 2.0, "rate_dps": [0.0, -4.0, 0.5]}]}
    tr = build_trajectory(cfg, PAPER_HIGHDYN_RECEIVER, 5.0)
    k = tr.kinematics(np.array([0.0, 1.5, 4.0]))
    C0 = k["C_l0b"][0]
    w1, w2 = np.radians([1.0, 2.0, -3.0]), np.radians([0.0, -4.0, 0.5])
    assert np.allclose(k["C_l0b"][1], C0 @ expm(skew(w1 * 1.5)), atol=1e-13)
    assert np.allclose(k["C_l0b"][2], C0 @ expm(skew(w1 * 2.0)) @ expm(skew(w2 * 2.0)), atol=1e-13)
    assert np.allclose(np.degrees(k["euler"][0]), [10.0, -5.0, 30.0])


@pytest.mark.parametrize("cfg,needle", [
    ({"kind": "spiral"}, "trajectory.kind"),
    ({"kind": "segments", "segments": [{"t0": 1.0}]}, "segments[0].t0"),
    ({"kind": "segments", "segments": [{"t0": 0.0}, {"t0": 0.0}]}, "segments[1].t0"),
    ({"kind": "segments", "segments": [{"t0": 0.0, "acc_enu": [1.0, 2.0]}]}, "segments[0].acc_enu"),
    ({"kind": "segments", "attitude": "sideways", "segments": [{"t0": 0.0}]}, "trajectory.attitude"),
    ({"kind": "turns", "speed0_mps": 5.0, "segments": [{"t0": 0.0, "acc_mps2": -1.0}]}, "negative"),
])
def test_config_errors(cfg, needle):
    with pytest.raises(ConfigError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        build_trajectory(cfg, PAPER_HIGHDYN_RECEIVER, 10.0)


def test_save_h5(tmp_path, paper):
    import h5py
    p = tmp_path / "traj.h5"
    paper.save_h5(p, 10.0)
    with h5py.File(p, "r") as f:
        assert f["t"].shape == (601,)
        assert np.allclose(f["pos_e"][-1], paper.pos_vel_e(np.array([60.0]))[0][0])
        assert f.attrs["kind"] == "segments"
    assert not (tmp_path / "traj.h5.tmp").exists()
