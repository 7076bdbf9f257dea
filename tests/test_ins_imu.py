"""IMU synthesis and errors: closed-form increments, unit conversions, Allan deviation, file I/O and bad input."""

import math

import numpy as np
import pytest
from scipy.integrate import simpson

from ultratight.constants import OMEGA_E
from ultratight.errors import ConfigError, InputFileError
from ultratight.ins import imu as imu_mod
from ultratight.ins.earth import gravity_l
from ultratight.ins.imu import ImuErrors, allan_deviation, apply_errors, imu_errors_from_config, synthesize_imu
from ultratight.ins.imu_data import read_imu_csv, read_imu_h5, write_imu_csv, write_imu_h5
from ultratight.ins.trajectory import PAPER_HIGHDYN_RECEIVER, PAPER_HIGHDYN_TRAJECTORY, build_trajectory


def test_unit_conversions():
    assert math.isclose(imu_mod.DPH_TO_RADPS, 4.84813681109536e-06, rel_tol=1e-12)
    assert math.isclose(imu_mod.DPRH_TO_RADPRS, 2.908882086657216e-04, rel_tol=1e-12)   # 1 deg/sqrt(h)
    assert math.isclose(imu_mod.UG_TO_MPS2, 9.80665e-6, rel_tol=1e-12)
    e = imu_errors_from_config({"preset": "paper", "rate_hz": 100.0})
    assert np.allclose(e.gyro_bias, 0.01 * math.pi / 180 / 3600)
    assert np.allclose(e.accel_bias, 30e-6 * 9.80665)
    # paper white noise: 1 sigma of the 100 Hz rate samples -> arw = sigma / sqrt(100 Hz)
    assert np.allclose(e.gyro_arw, 0.005 * math.pi / 180 / 3600 / 10.0)
    assert np.allclose(e.accel_vrw, 3e-6 * 9.80665 / 10.0)
    t = imu_errors_from_config({"preset": "tactical", "gyro_arw_dprh": 0.06, "accel_vrw_ugrhz": 50.0,
                                "gyro_sf_ppm": [100, 200, 300]})
    assert np.allclose(t.gyro_arw, 0.06 * math.pi / 180 / 60)
    assert np.allclose(t.accel_vrw, 50e-6 * 9.80665)
    assert np.allclose(t.gyro_sf, [1e-4, 2e-4, 3e-4])


@pytest.mark.parametrize("cfg,needle", [
    ({"preset": "superb"}, "imu.preset"),
    ({"preset": "paper", "gyro_bias_dhp": 1.0}, "unknown key"),
    ({"gyro_noise_dph": 1.0, "gyro_arw_dprh": 1.0}, "not both"),
    ({"gyro_bi_dph": 1.0}, "gyro_bi_tau_s"),
    ({"gyro_bias_dph": [1.0, 2.0]}, "gyro_bias_dph"),
])
def test_config_errors(cfg, needle):
    with pytest.raises(ConfigError, match=needle):
        imu_errors_from_config(cfg)


def test_static_increments_closed_form():
    cfg = {"kind": "static", "attitude": "fixed", "att0_deg": [3.0, -2.0, 40.0]}
    tr = build_trajectory(cfg, {"lat_deg": 30.0, "lon_deg": 100.0, "h_m": 1000.0}, 1.0)
    imu = synthesize_imu(tr, 100.0)
    lat = math.radians(30.0)
    C_lb = tr.kinematics(np.array([0.0]))["C_lb"][0]
    w = C_lb.T @ np.array([0.0, OMEGA_E * math.cos(lat), OMEGA_E * math.sin(lat)])
    f = -C_lb.T @ gravity_l(lat, 1000.0)
    assert np.allclose(imu.dtheta_b, w * 0.01, rtol=0, atol=1e-19)
    assert np.allclose(imu.dv_b, f * 0.01, rtol=0, atol=1e-13)


def test_increments_integrate_body_signals():
    # increments of the paper flight against an independent fine Simpson rule on the body signals
    tr = build_trajectory(PAPER_HIGHDYN_TRAJECTORY, PAPER_HIGHDYN_RECEIVER, 60.0)
    edges = np.array([19.98, 19.99, 20.0, 20.01, 20.5, 20.51, 40.99, 41.0])
    dth, dv = imu_mod.ideal_increments(tr, edges)
    for k in (0, 2, 4, 6):
        tt = np.linspace(edges[k], edges[k + 1], 2001)
        w, f = imu_mod.body_signals(tr, tt)
        assert np.allclose(dth[k], simpson(w, x=tt, axis=0), rtol=0, atol=1e-12)
        assert np.allclose(dv[k], simpson(f, x=tt, axis=0), rtol=0, atol=2e-8)
    # an interval straddling the 21 s breakpoint (acceleration kink): reference split at the kink
    dth, dv = imu_mod.ideal_increments(tr, np.array([20.995, 21.005]))
    ref_w, ref_f = np.zeros(3), np.zeros(3)
    for a, b in ((20.995, 21.0), (21.0, 21.005)):
        tt = np.linspace(a, b, 1001)
        w, f = imu_mod.body_signals(tr, tt)
        ref_w += simpson(w, x=tt, axis=0)
        ref_f += simpson(f, x=tt, axis=0)
    assert np.allclose(dth[0], ref_w, rtol=0, atol=1e-12)
    assert np.allclose(dv[0], ref_f, rtol=0, atol=2e-8)


def test_scale_factor_misalignment_quantisation():
    rng = np.random.default_rng(1)
    dth = rng.normal(size=(500, 3)) * 1e-3
    dv = rng.normal(size=(500, 3)) * 0.1
    e = imu_errors_from_config({"gyro_sf_ppm": [100, -200, 50], "gyro_misalign_mrad": 0.5,
                                "accel_sf_ppm": 300, "accel_misalign_mrad": [[0, 1, 0], [0, 0, 0], [0, -1, 0]]})
    a, b = apply_errors(dth, dv, e, rng, 0.01)
    Mg = np.eye(3) + np.diag([1e-4, -2e-4, 5e-5]) + 5e-4 * (np.ones((3, 3)) - np.eye(3))
    assert np.allclose(a, dth @ Mg.T, atol=1e-18)
    Ma = np.eye(3) * (1 + 3e-4) + np.array([[0, 1e-3, 0], [0, 0, 0], [0, -1e-3, 0]])
    assert np.allclose(b, dv @ Ma.T, atol=1e-16)
    q = imu_errors_from_config({"gyro_quant_urad": 2.0, "accel_quant_mmps": 1.0})
    a, b = apply_errors(dth, dv, q, rng, 0.01)
    assert np.allclose(a / 2e-6, np.round(a / 2e-6), atol=1e-6)
    assert np.all(np.abs(np.cumsum(a, 0) - np.cumsum(dth, 0)) <= 1e-6 + 1e-18)     # residual carried
    assert np.all(np.abs(np.cumsum(b, 0) - np.cumsum(dv, 0)) <= 5e-4 + 1e-15)


def _noise_only(errors, rate, n, seed):
    rng = np.random.default_rng(seed)
    z = np.zeros((n, 3))
    return apply_errors(z, z, errors, rng, 1.0 / rate)


def test_paper_noise_is_per_sample_sigma():
    e = imu_errors_from_config({"preset": "paper"})
    e.gyro_bias[:] = 0.0
    e.accel_bias[:] = 0.0
    a, b = _noise_only(e, 100.0, 200000, 7)
    assert abs(np.std(a / 0.01) / (0.005 * imu_mod.DPH_TO_RADPS) - 1.0) < 0.01
    assert abs(np.std(b / 0.01) / (3.0 * imu_mod.UG_TO_MPS2) - 1.0) < 0.01


def test_allan_deviation_white_noise_at_1s():
    e = imu_errors_from_config({"gyro_arw_dprh": 0.1, "accel_vrw_ugrhz": 60.0})
    a, b = _noise_only(e, 100.0, 300000, 11)
    for x, level in ((a, 0.1 * imu_mod.DPRH_TO_RADPRS), (b, 60.0 * imu_mod.UGPRHZ_TO_MPSPRS)):
        for ax in range(3):
            adev = allan_deviation(x[:, ax] / 0.01, 0.01, [1.0, 10.0])
            assert abs(adev[0] / level - 1.0) < 0.10
            assert abs(adev[1] / (level / math.sqrt(10.0)) - 1.0) < 0.10


def test_bias_instability_plateau():
    sigma, tau = 2.0 * imu_mod.DPH_TO_RADPS, 10.0
    e = ImuErrors(gyro_gm_sigma=np.full(3, sigma), gyro_gm_tau=tau)
    rate = 10.0
    a, _ = _noise_only(e, rate, 1_000_000, 5)
    taus = np.array([1.0, 3.0, 10.0, 19.0, 40.0, 100.0])

    def gm_adev(T):     # closed-form Allan deviation of a first-order Gauss-Markov process
        x = T / tau
        return math.sqrt(2 * sigma ** 2 * tau / T * (1 - (3 - 4 * math.exp(-x) + math.exp(-2 * x)) / (2 * x)))
    adev = np.mean([allan_deviation(a[:, ax] * rate, 1.0 / rate, taus) for ax in range(3)], axis=0)
    expect = np.array([gm_adev(T) for T in taus])
    assert np.all(np.abs(adev / expect - 1.0) < 0.10)
    # the plateau (maximum) sits near 1.89 tau at 0.62 sigma
    assert taus[np.argmax(adev)] == 19.0
    assert abs(adev.max() / (0.6178 * sigma) - 1.0) < 0.10


@pytest.fixture(scope="module")
def small_imu():
    tr = build_trajectory(PAPER_HIGHDYN_TRAJECTORY, PAPER_HIGHDYN_RECEIVER, 2.0)
    return synthesize_imu(tr, 50.0, imu_errors_from_config({"preset": "paper"}), np.random.default_rng(2))


def test_h5_round_trip(tmp_path, small_imu):
    p = tmp_path / "imu.h5"
    write_imu_h5(p, small_imu, {"scenario": "x"})
    back = read_imu_h5(p)
    assert np.array_equal(back.dtheta_b, small_imu.dtheta_b) and np.array_equal(back.dv_b, small_imu.dv_b)
    assert back.rate_hz == 50.0 and back.t0 == 0.0
    assert np.array_equal(back.truth["q_lb"], small_imu.truth["q_lb"])
    assert back.meta["scenario"] == "x"


def test_csv_round_trip_and_rate_columns(tmp_path, small_imu):
    p = tmp_path / "imu.csv"
    write_imu_csv(p, small_imu)
    back = read_imu_csv(p)
    assert np.allclose(back.dtheta_b, small_imu.dtheta_b, rtol=1e-15, atol=0)
    assert np.allclose(back.dv_b, small_imu.dv_b, rtol=1e-15, atol=0)
    assert abs(back.rate_hz - 50.0) < 1e-6 and abs(back.t0) < 1e-9
    q = tmp_path / "rates.csv"
    q.write_text("# rates\nt_s,gx_dps,gy_dps,gz_dps,ax_g,ay_g,az_g\n"
                 "0.01,1,2,3,0,0,1\n0.02,1,2,3,0.5,0,1\n0.03,1,2,3,0,0,1\n")
    r = read_imu_csv(q)
    assert np.allclose(r.dtheta_b[1], np.radians([1, 2, 3]) * 0.01)
    assert np.allclose(r.dv_b[1], [0.5 * 9.80665 * 0.01, 0.0, 9.80665 * 0.01])


_HDR = "t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps\n"


@pytest.mark.parametrize("body,needle", [
    ("0.01,0,0,0,0,0,0.1\n0.02,0,0,0,0,0,0.1\n0.02,0,0,0,0,0,0.1\n", "line 4: duplicate"),
    ("0.01,0,0,0,0,0,0.1\n0.03,0,0,0,0,0,0.1\n0.02,0,0,0,0,0,0.1\n0.04,0,0,0,0,0,0.1\n", "line 4: out-of-order"),
    ("0.01,0,0,0,0,0,0.1\n0.02,0,0,0,0,0,0.1\n0.05,0,0,0,0,0,0.1\n0.06,0,0,0,0,0,0.1\n", "line 4: gap"),
    ("0.01,0,0,0,0,0,0.1\n0.02,0,nan,0,0,0,0.1\n0.03,0,0,0,0,0,0.1\n", "line 3: column 'dthy_rad'"),
    ("0.01,0,0,0,0,0,0.1\n0.02,0,x,0,0,0,0.1\n0.03,0,0,0,0,0,0.1\n", "line 3: column 'dthy_rad'"),
    ("0.01,0,0,0,0,0,0.1\n0.02,0,0,0,0,0.1\n0.03,0,0,0,0,0,0.1\n", "line 3: 6 fields"),
])
def test_csv_bad_rows_named(tmp_path, body, needle):
    p = tmp_path / "bad.csv"
    p.write_text(_HDR + body)
    with pytest.raises(InputFileError, match=needle):
        read_imu_csv(p)


def test_csv_bad_header_units(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("t_s,gx_rpm,gy_rpm,gz_rpm,ax_mps2,ay_mps2,az_mps2\n0.01,1,1,1,0,0,9.8\n0.02,1,1,1,0,0,9.8\n")
    with pytest.raises(InputFileError, match="line 1: column 'gx_rpm' has unknown unit 'rpm'"):
        read_imu_csv(p)
    p.write_text("time,a,b\n1,2,3\n")
    with pytest.raises(InputFileError, match="t_s"):
        read_imu_csv(p)
