"""Ultra-tight engine: outer-loop geometry against geometry.light_time, hot start, metrics
against closed forms, an end-to-end run on generated IF/IMU data, and bad-input handling."""


import numpy as np
import pytest

from ultratight.constants import CA_LEN, F_CA
from ultratight.errors import ConfigError, InputFileError
from ultratight.receiver.cli import metrics as M
WEEK, TOW = 2190, 518400.0
PRNS = [31, 20, 18, 28, 21, 15, 1, 8, 6, 2, 10, 32, 22]


@pytest.fixture(scope="module")
def ephs():
    from ultratight.signals.constellation import nominal_ephemerides
    return nominal_ephemerides(WEEK, TOW)


def _rx():
    from ultratight.ins.earth import llh_to_ecef
    return np.array(llh_to_ecef(np.deg2rad(28.246), np.deg2rad(102.0266), 50000.0))


def test_multichannel_light_time_matches_geometry(ephs):
    from ultratight.signals.geometry import MultiLightTime, SatTable
    from ultratight.signals.geometry import light_time
    tab = SatTable(ephs, PRNS, TOW - 1.0, TOW + 70.0)
    ml = MultiLightTime(tab)
    rx, rv = _rx(), np.array([3000.0, -1200.0, 40.0])
    for t in (TOW + 0.37, TOW + 41.123):
        got = ml.solve(rx, rv, t, 12.5, 0.4, iters=4)
        for i, prn in enumerate(PRNS):
            ref = light_time(ephs[prn], rx, rv, WEEK, np.array([t]), 12.5, 0.4)
            dcp = (got["code_phase_chips"][i] - ref["code_phase_chips"][0] + 511.5) % CA_LEN - 511.5
            assert abs(dcp) < 2e-6
            assert got["doppler_hz"][i] == pytest.approx(ref["doppler_hz"][0], abs=1e-5)
            assert got["pseudorange_m"][i] == pytest.approx(ref["pseudorange_m"][0], abs=1e-3)
            np.testing.assert_allclose(got["los_e"][i], ref["los_e"][0], atol=1e-9)


def test_outer_loop_aiding_follows_a_ramp(ephs):
    """Constant-acceleration receiver: the CIC-interpolated 1 kHz aiding equals the direct
    prediction at the same instants (the lead compensates the CIC delay)."""
    from ultratight.receiver.deep.outer_loop import OuterLoop
    ol = OuterLoop(ephs, PRNS, WEEK, TOW, 1.0)
    p0, v0, a = _rx(), np.zeros(3), np.array([60.0, -80.0, 20.0])

    def kin(t):
        return p0 + v0 * t + 0.5 * a * t * t, v0 + a * t

    ol.prime(0.0, *kin(0.0), a, 0.0, 0.0)
    for k in range(30):
        t = k * 0.01
        ol.push(t, *kin(t), a, 0.0, 0.0)
    for j in (150, 200, 283):
        t = j * 1e-3
        ref = ol.predict(t, *kin(t), 0.0, 0.0)["doppler_hz"]
        np.testing.assert_allclose(ol.aid_doppler[j], ref, atol=0.02)


def test_hot_start_predictions_use_the_perturbed_state(ephs):
    from ultratight.receiver.deep.startup import StartupErrors, perturb_state, predict_channels
    from ultratight.signals.geometry import light_time
    from ultratight.ins.earth import llh_to_ecef
    truth0 = {"llh": np.array([np.deg2rad(28.246), np.deg2rad(102.0266), 50000.0]), "vel_l": np.zeros(3),
              "q_lb": np.array([1.0, 0, 0, 0]), "clk_bias_m": 0.0, "clk_drift_mps": 0.0}
    errs = StartupErrors(pos_m=5.0, vel_mps=0.1, clk_bias_m=3.0, clk_drift_mps=0.05)
    draws = [perturb_state(truth0, errs, np.random.default_rng(s)) for s in range(400)]
    e_pos = np.array([d["err_pos_l"] for d in draws])
    assert np.std(e_pos) == pytest.approx(5.0, rel=0.1)
    assert np.std([d["clk_bias_m"] for d in draws]) == pytest.approx(3.0, rel=0.15)
    st = draws[0]
    pos = np.array(llh_to_ecef(*st["llh"]))
    from ultratight.ins.earth import dcm_ecef_from_enu
    vel = dcm_ecef_from_enu(st["llh"][0], st["llh"][1]) @ st["vel_l"]
    pr = predict_channels(ephs, PRNS[:3], WEEK, TOW, pos, vel, st["clk_bias_m"], st["clk_drift_mps"])
    ref = light_time(ephs[PRNS[0]], pos, vel, WEEK, np.array([TOW - st["clk_bias_m"] / 299792458.0]),
                     st["clk_bias_m"], st["clk_drift_mps"])
    assert pr["doppler_hz"][0] == pytest.approx(ref["doppler_hz"][0], abs=1e-9)
    # ... and differs from the truth's prediction by the drawn errors (not zero)
    truth_pos = np.array(llh_to_ecef(*truth0["llh"]))
    pt = predict_channels(ephs, PRNS[:3], WEEK, TOW, truth_pos, np.zeros(3), 0.0, 0.0)
    assert np.all(np.abs(pr["code_phase_chips"] - pt["code_phase_chips"]) > 1e-5)


def test_assisted_bits_match_the_generator_convention(ephs):
    from ultratight.receiver.deep.startup import BitWipeoff
    from ultratight.signals.lnav import nav_bits
    w = BitWipeoff(ephs, PRNS[:2], WEEK, TOW, 2.0)
    assert w.mode == "assisted-bits"
    ms = np.array([int(TOW * 1000) + 40, int(TOW * 1000) + 59])
    ref = nav_bits(ephs[PRNS[0]], WEEK, TOW + 0.04, 1)[0]
    assert w.signs(ms)[0] == ref


def test_metrics_closed_forms():
    t_truth = np.arange(0, 1.0, 1e-3)
    f = 100.0 + 500.0 * t_truth                       # Doppler ramp
    cp = np.mod(3.0 + F_CA * t_truth * (1 + 0.0) + 0.25 * t_truth ** 2, CA_LEN)
    truth_cp = np.stack([cp, cp], 1)
    t_est = np.stack([t_truth[10:900] + 3e-4, t_truth[10:900] + 7e-4], 1)
    cp_true_at = np.mod(3.0 + F_CA * t_est + 0.25 * t_est ** 2, CA_LEN)
    d_est = 100.0 + 500.0 * (t_est + 0.5e-3) + 0.1
    c_est = np.mod(cp_true_at - 0.02, CA_LEN)
    de, ce = M.tracking_errors(t_est, d_est, c_est, t_truth, np.stack([f, f], 1), truth_cp)
    np.testing.assert_allclose(de, 0.1, atol=1e-9)
    np.testing.assert_allclose(ce, -0.02, atol=1e-6)
    rms = M.segment_rms(t_est, de, ((0, 0.5), (0.5, 1.0)))
    np.testing.assert_allclose(rms, [0.1, 0.1])
    err = np.zeros((1000, 2))
    err[600:, 1] = 30.0
    lost = M.loss_of_lock(np.stack([t_truth, t_truth], 1), err, np.zeros((1000, 2)))
    assert np.isnan(lost[0]) and lost[1] == pytest.approx(0.606, abs=1e-9)   # 7 of 20 samples at 30 Hz: mean 10.5


# ------------------------------------------------------------------ end to end (generated data)
@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """3 s of paper-highdyn at 2.046 MHz (generation ~5 s) processed by dlb-ckf."""
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.receiver.cli.scenario_runner import errors_vs_truth, prepare_data, run_method
    out = tmp_path_factory.mktemp("eng")
    cfg = load_scenario("paper-highdyn", {"duration_s": 3.0, "frontend.fs_hz": 2.046e6})
    paths, _ = prepare_data(cfg, 11, out, progress=False)
    res, truth = run_method(paths, cfg, "dlb-ckf", 11)
    return paths, cfg, res, errors_vs_truth(res, truth)


def test_engine_tracks_paper_highdyn_start(short_run):
    paths, cfg, res, (de, ce) = short_run
    assert res.doppler_hz.shape[1] == 13 and res.info["wipeoff_mode"] == "assisted-bits"
    seg = ((1.0, 3.0),)
    # Hz, after the 1 s pull-in. docs/ultratight.md acceptance table: dlb-ckf 0-5 s (before the burst)
    # 0.0850 Hz (4 MHz, 5 seeds).  This run (seed 11, 1-3 s): 0.062 Hz; seeds 1-3: 0.055-0.069 Hz.
    # Bound 0.11 Hz = documented x 1.29 (a doubling of this run's figure breaks it)
    assert M.segment_rms(res.t_start, de, seg)[0] < 0.11
    assert M.segment_rms(res.t_start, ce, seg)[0] < 0.01         # chips
    assert np.all(np.isnan(M.loss_of_lock(res.t_start, de, ce)))
    assert set(np.unique(res.mode)) <= {0, 1, 3}
    assert res.info["n_tight_updates"] >= 25
    # the 10 Hz solution stays near the truth trajectory: it starts from the hot-start draw of
    # docs/ultratight.md "Assisted hot start" (1 sigma per axis 0.5 m, 0.02 m/s) and over 3 s the
    # tight feedback keeps it at that error.  Bound: the 99.9 % chi-square(3) radius of those sigmas,
    # 0.5 m x 4.03 = 2.0 m and 0.02 m/s x 4.03 = 0.081 m/s.  Measured max: seed 11 0.64 m / 0.044 m/s;
    # seeds 1-3 (their own start draws) 0.85-1.50 m / 0.032-0.057 m/s
    from ultratight.ins.trajectory import build_trajectory
    traj = build_trajectory(cfg["trajectory"], cfg["receiver"], cfg["duration_s"])
    pos_t, vel_t = traj.pos_vel_e(res.nav_t)
    assert np.max(np.linalg.norm(res.nav_pos_e - pos_t, axis=1)) < 2.0
    assert np.max(np.linalg.norm(res.nav_vel_e - vel_t, axis=1)) < 0.081


def test_run_on_files_and_bad_inputs(short_run, tmp_path):
    from ultratight.receiver.deep.recordings import run_ultratight_on_files
    from ultratight.receiver.deep.outputs import write_result_h5
    from ultratight.ins.imu_data import read_imu_h5, write_imu_h5
    paths, cfg, res, _ = short_run
    # 0.3 s leave no time for the scalar receiver's own fix: the named (assisted) truth start-up
    r2 = run_ultratight_on_files(paths["if"], paths["imu"], method="dlb-ckf", seed=11, duration_s=0.3,
                                 startup="truth-perturbed")
    assert r2.doppler_hz.shape[1] == 13
    write_result_h5(tmp_path / "r.h5", r2)
    import h5py
    with h5py.File(tmp_path / "r.h5") as f:
        assert f["doppler_hz"].shape == r2.doppler_hz.shape and f.attrs["method"] == "dlb-ckf"
    with pytest.raises(ConfigError):
        run_ultratight_on_files(paths["if"], paths["imu"], method="dlb-pf")
    imu = read_imu_h5(paths["imu"])
    # gap
    bad = tmp_path / "gap.imu.h5"
    imu_gap = type(imu)(t=np.delete(imu.t, 50), dtheta_b=np.delete(imu.dtheta_b, 50, 0),
                        dv_b=np.delete(imu.dv_b, 50, 0), rate_hz=imu.rate_hz, t0=imu.t0, meta=imu.meta)
    write_imu_h5(bad, imu_gap)
    with pytest.raises(InputFileError, match="gap"):
        run_ultratight_on_files(paths["if"], bad, method="dlb-ckf")
    # time offset: the IMU starts 0.2 s late
    off = tmp_path / "off.imu.h5"
    imu_off = type(imu)(t=imu.t + 0.2, dtheta_b=imu.dtheta_b, dv_b=imu.dv_b, rate_hz=imu.rate_hz,
                        t0=imu.t0 + 0.2, meta=imu.meta)
    write_imu_h5(off, imu_off)
    with pytest.raises(InputFileError, match="offset"):
        run_ultratight_on_files(paths["if"], off, method="dlb-ckf")
    # IMU start time (GPS) different from the IF start time
    shifted = dict(imu.meta)
    shifted["start_week"], shifted["start_tow_s"] = WEEK, TOW + 1.0
    tow_off = tmp_path / "tow.imu.h5"
    write_imu_h5(tow_off, type(imu)(t=imu.t, dtheta_b=imu.dtheta_b, dv_b=imu.dv_b, rate_hz=imu.rate_hz,
                                    t0=imu.t0, meta=shifted))
    with pytest.raises(InputFileError, match="offset"):
        run_ultratight_on_files(paths["if"], tow_off, method="dlb-ckf")


def test_noise_floor_estimator_modes():
    from ultratight.receiver.dsp.blockstream import NoiseFloor
    blocks = np.array([1.0, 1.0, 20.0, 20.0, 20.0, 1.0])
    per_block = NoiseFloor(0.0, 0.01)
    assert [per_block.update(b) for b in blocks] == pytest.approx(blocks)
    held = NoiseFloor(float("inf"), 0.01)
    assert [held.update(b) for b in blocks] == pytest.approx(np.ones(6))
    slow = NoiseFloor(0.04, 0.01)                  # alpha = 1/4 on the variances
    v, ref = 1.0, []
    for b in blocks:
        v = v + 0.25 * (b * b - v)
        ref.append(np.sqrt(v))
    assert [slow.update(b) for b in blocks] == pytest.approx(ref, rel=1e-12)
    with pytest.raises(ConfigError, match="noise_tau_s"):
        NoiseFloor(-1.0, 0.01)


def test_phase_init_handover_keeps_the_doppler_continuous(short_run):
    """At the end of the 40 ms aided phase initialisation the prefilters take over: the
    channel Doppler must not step (it stepped by up to one aiding increment, 0.5 Hz at 20 g,
    while the filter started with df = 0)."""
    paths, cfg, res, (de, ce) = short_run
    k = 40                                         # EngineOptions.phase_init_ms
    jump = np.abs(de[k + 1] - de[k - 2])
    assert np.max(jump) < 0.03, jump


def test_outer_freq_update_is_a_scalar_kalman_update():
    """The opt-in outer-loop frequency pseudo-measurement equals a textbook KF update of the
    prefilter's frequency state, only on the selected channels."""
    from ultratight.fusion.channel.prefilter import IF as I_F
    from ultratight.receiver.deep.engine import _outer_freq_update
    rng = np.random.default_rng(4)
    a = rng.standard_normal((2, 5, 5))
    P = np.einsum("cij,ckj->cik", a, a) + 0.1 * np.eye(5)
    x = rng.standard_normal((2, 5))
    x0, P0 = x.copy(), P.copy()
    resid_hz = np.array([0.3, -0.7])
    r_var = np.array([0.05, 0.02])
    _outer_freq_update(x, P, np.array([False, True]), resid_hz, r_var)
    # channel 0 untouched
    assert np.array_equal(x[0], x0[0]) and np.array_equal(P[0], P0[0])
    # channel 1: z - h(x) = -2 pi resid, H = e_IF
    H = np.zeros((1, 5))
    H[0, I_F] = 1.0
    S = H @ P0[1] @ H.T + r_var[1]
    K = P0[1] @ H.T / S
    x_ref = x0[1] + (K * (-2 * np.pi * resid_hz[1])).ravel()
    P_ref = (np.eye(5) - K @ H) @ P0[1]
    assert np.allclose(x[1], x_ref, atol=1e-12)
    assert np.allclose(P[1], 0.5 * (P_ref + P_ref.T), atol=1e-12)
