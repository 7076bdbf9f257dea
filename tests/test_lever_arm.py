"""Lever arm IMU -> antenna: the generator's IMU at the lever-arm point (error-free SINS follows
the IMU truth, not the antenna), the tight filter's measurement partials against a numerical
differentiation of the antenna prediction, and the ultra-tight engine on a generated recording."""

import math

import numpy as np
import pytest

from ultratight.fusion.coupling import tight
from ultratight.ins.attitude import dcm_to_quat, quat_to_dcm, rotvec_to_dcm
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef, llh_to_ecef_batch
from ultratight.ins.imu import synthesize_imu
from ultratight.ins.imu_data import read_imu_h5
from ultratight.ins.sins import make_state, nav_errors, sins_run
from ultratight.ins.trajectory import build_trajectory
from ultratight.receiver.cli import main
from ultratight.receiver.deep.recordings import run_ultratight_on_files
from ultratight.receiver.deep.sins_clock import InsClock

LEVER = np.array([2.0, 1.0, 2.5])      # FLU, m (3.4 m)


def write_ecef_csv(path, duration_s):
    """10 Hz ECEF CSV of a 200 m, 20 m/s circle at 41.275 N 1.987 E, 50 m."""
    lat, lon = math.radians(41.275), math.radians(1.987)
    t = np.arange(0.0, duration_s + 1e-9, 0.1)
    enu = np.stack([200.0 - 200.0 * np.cos(0.1 * t), 200.0 * np.sin(0.1 * t), 0 * t], 1)
    p = enu @ dcm_ecef_from_enu(lat, lon).T + np.asarray(llh_to_ecef(lat, lon, 50.0))
    np.savetxt(path, np.column_stack([t, p]), delimiter=",", fmt="%.4f")


@pytest.fixture(scope="module")
def circle_csv(tmp_path_factory):
    p = tmp_path_factory.mktemp("lever") / "circle.csv"
    write_ecef_csv(p, duration_s=60.0)
    return p


def test_generated_imu_sits_at_the_lever_arm_point(circle_csv):
    tr = build_trajectory({"kind": "file", "path": str(circle_csv)}, {}, 60.0)
    imu = synthesize_imu(tr, 100.0, lever_arm_b=LEVER)
    imu0 = synthesize_imu(tr, 100.0)
    T = imu.truth
    assert np.array_equal(imu.lever_arm_b, LEVER) and "llh_antenna" in T
    # truth: IMU = antenna - C_eb l
    d = llh_to_ecef_batch(T["llh_antenna"]) - llh_to_ecef_batch(T["llh"])
    assert np.allclose(np.linalg.norm(d, axis=1), np.linalg.norm(LEVER), atol=1e-6)
    x0 = make_state(T["q_lb"][0], T["vel_l"][0], T["llh"][0])
    q, v, p = sins_run(x0, imu.dtheta_b, imu.dv_b, 0.01)
    dp, dv, _ = nav_errors(q, v, p, T["q_lb"], T["vel_l"], T["llh"])
    assert np.max(np.linalg.norm(dp, axis=1)) < 2e-3 and np.max(np.linalg.norm(dv, axis=1)) < 5e-5
    # the antenna's increments (no lever-arm terms) from the IMU point drift by metres
    q, v, p = sins_run(x0, imu0.dtheta_b, imu0.dv_b, 0.01)
    dp, _, _ = nav_errors(q, v, p, T["q_lb"], T["vel_l"], T["llh"])
    assert np.max(np.linalg.norm(dp, axis=1)) > 1.0


def test_measurement_partials_match_numerical_differentiation():
    rng = np.random.default_rng(5)
    llh = np.array([math.radians(41.0), math.radians(2.0), 100.0])
    q = np.array([0.9, 0.1, -0.2, 0.3])
    q /= np.linalg.norm(q)
    ins = InsClock(q, np.array([10.0, -3.0, 0.5]), llh, 0.0, 0.0)
    ins.lever_b = LEVER.copy()
    ins.w_b = np.array([0.05, -0.3, 0.4])
    los_e = rng.standard_normal((5, 3))
    los_e /= np.linalg.norm(los_e, axis=1)[:, None]
    pos0, vel0, C_el = ins.antenna_pos_vel_e()
    los_l = los_e @ C_el
    rm, rn = 6.36e6, 6.39e6          # any radii: only the attitude / bias columns are compared
    H = tight.measurement_matrix(los_l, tight.pos_error_to_enu(llh[0], llh[2], rm, rn), ins.lever_terms())
    H0 = tight.measurement_matrix(los_l, tight.pos_error_to_enu(llh[0], llh[2], rm, rn))
    assert np.array_equal(H[:, :3] != 0, np.ones_like(H[:, :3], bool))
    assert np.array_equal(np.delete(H, list(range(0, 3)) + list(range(9, 12)), axis=1),
                          np.delete(H0, list(range(0, 3)) + list(range(9, 12)), axis=1))
    eps = 1e-4                      # central differences: O(eps^2) truncation, ~1e-5 rounding on ECEF metres
    C_lb = quat_to_dcm(q)

    def antenna(phi=np.zeros(3), dbg=np.zeros(3)):
        """Antenna prediction with attitude error phi (C_lb_est = (I - [phi x]) C_lb) and residual gyro
        bias dbg (omega_est = omega + dbg)."""
        pert = InsClock(dcm_to_quat(rotvec_to_dcm(-phi) @ C_lb), np.array([10.0, -3.0, 0.5]), llh, 0.0, 0.0)
        pert.lever_b, pert.w_b = LEVER.copy(), ins.w_b + dbg
        return pert.antenna_pos_vel_e()[:2]

    for j in range(3):
        d = np.zeros(3)
        d[j] = eps
        (pp, vp), (pm, vm) = antenna(phi=d), antenna(phi=-d)
        # predicted range change -e . d r_ant, rate change -e . d v_ant
        assert np.allclose(-los_e @ (pp - pm) / (2 * eps), H[:5, j], atol=1e-4)
        assert np.allclose(-los_e @ (vp - vm) / (2 * eps), H[5:, j], atol=1e-4)
        (_, vp), (_, vm) = antenna(dbg=d), antenna(dbg=-d)
        assert np.allclose(-los_e @ (vp - vm) / (2 * eps), H[5:, 9 + j], atol=1e-4)


SCEN = """name = "circle-lever"
duration_s = 8.0
seed = 3
[time]
week = 2190
tow_s = 518400.0
[trajectory]
kind = "file"
path = "circle.csv"
[satellites]
max_count = 8
cn0_dbhz = 45.0
[frontend]
fs_hz = 2.046e6
format = "ci8"
bits = 8
[imu]
preset = "tactical"
rate_hz = 100.0
lever_arm_m = [2.0, 1.0, 2.5]
"""


def test_engine_estimates_the_imu_point_with_the_lever_arm(circle_csv, tmp_path):
    (tmp_path / "circle.csv").write_text(circle_csv.read_text())
    (tmp_path / "s.toml").write_text(SCEN)
    assert main(["generate", str(tmp_path / "s.toml"), "--out", str(tmp_path / "c"), "--no-progress"]) == 0
    imu = read_imu_h5(tmp_path / "c.imu.h5")
    assert np.array_equal(imu.lever_arm_b, LEVER)
    T = imu.truth
    p_imu = llh_to_ecef_batch(T["llh"])
    p_ant = llh_to_ecef_batch(T["llh_antenna"])

    def rms(res, ref):
        t = np.asarray(res.nav_t)
        r = np.stack([np.interp(t, T["t"], ref[:, i]) for i in range(3)], 1)
        e = np.linalg.norm(np.asarray(res.nav_pos_e) - r, axis=1)[t > 3.0]
        return float(np.sqrt(np.mean(e ** 2)))

    # the scenario simulates no atmosphere (no [atmosphere] table): the receiver is told so, as a user of
    # such a recording would (--iono off --tropo off), so that the figure is the lever arm's alone
    # the 8 s recording is too short for the scalar receiver's own fix: the named (assisted) truth start
    vacuum = {"iono": "off", "tropo": "off", "startup": "truth-perturbed"}
    res = run_ultratight_on_files(tmp_path / "c.ci8", tmp_path / "c.imu.h5", **vacuum)
    assert res.info["n_lock_lost_events"] == 0
    with_lever = rms(res, p_imu)
    # the same recording with the lever arm declared away (the flag overrides the file's)
    res0 = run_ultratight_on_files(tmp_path / "c.ci8", tmp_path / "c.imu.h5",
                                   imu_declaration={"lever_arm_m": [0, 0, 0]}, **vacuum)
    without = rms(res0, p_imu)
    # with the lever arm the solution is the IMU point (the antenna is 3.4 m away); declared away,
    # the filter pulls it towards the antenna and it leaves the IMU truth by a metre more
    assert with_lever < 1.0 and rms(res, p_ant) > 2.0
    assert without > with_lever + 1.0


def test_the_hand_over_window_keeps_the_lever_arm():
    """The engine sees the IMU from the hand-over time on (handover.imu_window): the lever arm goes
    with the data (it used to be dropped, leaving a scalar-fix start at the antenna)."""
    from ultratight.ins.imu_data import ImuData
    from ultratight.receiver.deep.handover import imu_window

    n = 500
    t = (np.arange(n) + 1) * 0.01
    imu = ImuData(t=t, dtheta_b=np.zeros((n, 3)), dv_b=np.tile([0, 0, 0.0980665], (n, 1)), rate_hz=100.0, t0=0.0,
                  truth=None, meta={}, lever_arm_b=LEVER.copy())
    w = imu_window(imu, 2.0)
    assert np.array_equal(w.lever_arm_b, LEVER) and w.t[0] == pytest.approx(0.01) and w.n == n - 200
