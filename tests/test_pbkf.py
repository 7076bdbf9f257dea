"""PB-KF-UTC baseline: discriminator calibration, one KF epoch vs an independent batch KF,
closed loop on the correlator-level simulator, bad input."""

import math

import numpy as np
import pytest
from scipy.special import hyp1f1

from ultratight.constants import BETA_CODE_CARRIER, T_CA
from ultratight.errors import FilterError
from ultratight.fusion.channel.loopsim import run_closed_loop
from ultratight.fusion.channel.pbkf import CAL_DLG, CAL_LG0, PbKfBank, discriminator_calibration
from ultratight.signals import corr_model
from ultratight.signals.synth.corrsim import SimScenario, make_truth, rms

T = T_CA


def test_calibration_high_and_low_cn0():
    tab = discriminator_calibration(1.0, T, True)
    i40 = int(round((1.0 - CAL_LG0) / CAL_DLG))            # C/N0 T = 10 (40 dB-Hz)
    k_tau, k_phi, k_f, v_tau, v_phi, v_f = tab[i40]
    assert k_phi == pytest.approx(1.0, abs=0.02) and k_f == pytest.approx(1.0, abs=0.05)
    # envelope DLL slope from the Rice-envelope mean (ratio of means; independent closed form)
    s0 = math.sqrt(2 * 10.0) * 0.5
    m = math.sqrt(math.pi / 2) * hyp1f1(-0.5, 1, -s0 * s0 / 2)
    g1 = math.sqrt(math.pi / 2) * (s0 / 2) * hyp1f1(0.5, 2, -s0 * s0 / 2)
    assert k_tau == pytest.approx(0.5 * math.sqrt(20.0) * g1 / m, rel=0.06)
    c = 10.0
    assert v_phi == pytest.approx(1 / (2 * c) * (1 + 1 / (2 * c)), rel=0.1)   # textbook atan PLL
    assert v_f == pytest.approx(2 * v_phi / T ** 2, rel=0.15)
    i20 = int(round((-1.0 - CAL_LG0) / CAL_DLG))           # 20 dB-Hz: strong suppression
    assert tab[i20, 0] < 0.1 and 0.3 < tab[i20, 1] < 0.6
    assert v_tau < (1.0 ** 2) / 12 + 1e-9


def _eq3(A, tau, phi, f_rad):
    s = f_rad * T / 2
    snc = math.sin(s) / s if s else 1.0
    tm = tau + BETA_CODE_CARRIER * s
    R = corr_model.code_autocorr(np.array([tm, tm - 0.5, tm + 0.5]))
    return np.concatenate([A * snc * R * math.cos(s + phi), A * snc * R * math.sin(s + phi)])


@pytest.mark.parametrize("rscale", [1.0, 20.0])
def test_one_epoch_matches_batch_kalman_update(rscale):
    """``rscale`` (a filter-R noise event, receiver.burst) multiplies the discriminator variances."""
    bank = PbKfBank(1, cn0_dbhz_init=40.0)
    x0 = np.array([bank.x0[0, 0], 0.02, -0.1, 2 * np.pi * 1.5, 3.0])
    P0 = np.diag([0.05 ** 2, 0.2 ** 2, (2 * np.pi * 3) ** 2, (2 * np.pi * 5) ** 2])
    bank.reset([0], x0=x0, P0=P0)
    a = float(corr_model.amplitude_from_cn0(40.0, T))
    z = _eq3(a, 0.1, 0.3, 2 * np.pi * 2.0) + np.array([0.3, -0.2, 0.1, 0.05, 0.4, -0.3])
    bank.step(z[None], np.array([1.0]), rscale=np.array([rscale]))
    # independent: moment C/N0, discriminators, gains from the table, batch KF (first epoch: no FLL)
    alpha = T / 1.0
    m2 = (1 - alpha) * (x0[0] ** 2 + 2) + alpha * (z[0] ** 2 + z[3] ** 2)
    m4 = (1 - alpha) * (x0[0] ** 4 + 8 * x0[0] ** 2 + 8) + alpha * (z[0] ** 2 + z[3] ** 2) ** 2
    a2 = math.sqrt(2 * m2 ** 2 - m4)
    cn = 0.5 * a2 / (0.5 * (m2 - a2))
    tab = discriminator_calibration(1.0, T, True)
    grid = CAL_LG0 + CAL_DLG * np.arange(tab.shape[0])
    g = np.array([np.interp(math.log10(cn), grid, tab[:, i]) for i in range(6)])
    e, l = math.hypot(z[1], z[4]), math.hypot(z[2], z[5])
    y = np.array([0.5 * (e - l) / (e + l), math.atan2(z[3], z[0])])
    H = np.array([[1, 0, BETA_CODE_CARRIER * T / 2, 0], [0, 1, T / 2, 0]]) * g[:2, None]
    R = np.diag(g[3:5]) * rscale
    xs = x0[1:]
    S = H @ P0 @ H.T + R
    K = P0 @ H.T @ np.linalg.inv(S)
    xu = xs + K @ (y - H @ xs)
    Pu = P0 - K @ S @ K.T
    np.testing.assert_allclose(bank.x[0, 1:], bank.Phi @ xu, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(bank.P[0], bank.Phi @ Pu @ bank.Phi.T + bank.Qd, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(bank.x_post[0, 1:], xu, rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize("cn0,dopp_max,code_max,n_ok,cn0_tol", [(30.0, 0.3, 0.03, 4, 1.5), (20.0, 1.0, 0.2, 3, 6.0)])
def test_closed_loop_tracks(cn0, dopp_max, code_max, n_ok, cn0_tol):
    """At 20 dB-Hz the 1 ms discriminators are nearly saturated: the baseline keeps lock on most
    channels (this seed: 3 of 4), unlike the I/Q prefilters; the moment C/N0 estimator (1 s time
    constant) is within ~1 dB at 30 dB-Hz but only ~5 dB at 20 dB-Hz."""
    sc = SimScenario(duration_s=3.0, n_ch=4, cn0_dbhz=cn0, f0_hz=1000.0, segments=[(0.0, 500.0, 0.0)],
                     aid_scale_err=0.002, aid_bias_hz=0.5, aid_delay_s=0.0135)
    truth = make_truth(sc, np.random.default_rng(4))
    bank = PbKfBank(4, cn0_dbhz_init=cn0)
    bank.reset(np.arange(4))
    log = run_closed_loop(sc, bank, np.random.default_rng(5), truth=truth,
                          init_err=dict(code_err_chips=0.05, phase_err_rad=0.2, freq_err_hz=2.0))
    m = log["t"] >= 1.5
    ok = (rms(log["dopp_err_hz"][m]) < dopp_max) & (rms(log["code_err_chips"][m]) < code_max)
    assert ok.sum() >= n_ok
    est_cn0 = corr_model.cn0_from_amplitude(log["amp_est"][m].mean(axis=0), T)
    np.testing.assert_allclose(est_cn0[ok], cn0, atol=cn0_tol)


def test_bad_input():
    bank = PbKfBank(2)
    bank.reset([0, 1])
    with pytest.raises(FilterError):
        bank.step(np.zeros((2, 5)))
    with pytest.raises(FilterError):
        bank.step(np.full((2, 6), np.nan))
    with pytest.raises(FilterError):
        PbKfBank(2, q={"q_amp": 1.0})
    bank.P[0] *= 1e15
    bank.step(np.ones((2, 6)), np.ones(2))
    assert bank.diverged[0] and np.all(np.isfinite(bank.x))


def test_divergence_after_a_restart_returns_to_amplitude_only():
    # as the prefilter bank: x0's errors are against the restart epoch's NCOs, applied once
    bank = PbKfBank(1)
    x0 = np.array([3.0, 0.1, 0.5, 2.0 * np.pi * 250.0, 40.0])
    bank.reset([0], x0=x0)
    np.testing.assert_array_equal(bank.x[0], x0)
    bank.P[0] *= 1e15
    bank.step(np.ones((1, 6)), np.ones(1))
    assert bank.diverged[0]
    np.testing.assert_array_equal(bank.x[0], [3.0, 0.0, 0.0, 0.0, 0.0])
