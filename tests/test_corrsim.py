"""Correlator-level simulator: outputs vs the eq.-3 closed form, noise statistics, truth dynamics."""

import math

import numpy as np
import pytest

from ultratight.constants import BETA_CODE_CARRIER, F_CA, F_L1, T_CA
from ultratight.errors import ConfigError
from ultratight.signals.synth.corrsim import CorrSim, SimScenario, make_truth
from ultratight.signals import corr_model

T = T_CA


def _eq3(A, D, tau, phi, f_rad, spacing=1.0):
    s = f_rad * T / 2
    snc = math.sin(s) / s if s else 1.0
    taum = tau + BETA_CODE_CARRIER * s
    R = corr_model.code_autocorr(np.array([taum, taum - spacing / 2, taum + spacing / 2]))
    return np.concatenate([A * D * snc * R * math.cos(s + phi), A * D * snc * R * math.sin(s + phi)])


@pytest.mark.parametrize("spacing", [1.0, 0.5])
def test_noise_free_outputs_match_eq3_for_constant_frequency(spacing):
    sc = SimScenario(duration_s=0.01, n_ch=3, cn0_dbhz=45.0, f0_hz=[1200.0, -300.0, 50.0],
                     segments=[(0.0, 0.0, 0.0)], data_bits=True, spacing_chips=spacing)
    sim = CorrSim(sc, np.random.default_rng(3))
    errs = dict(code_err_chips=[0.1, -0.3, 0.45], phase_err_rad=[0.4, -2.0, 3.0], freq_err_hz=[20.0, -80.0, 0.0])
    sim.init_nco(**errs)
    sim._noise(0)
    sim._chunk[:] = 0.0
    tr = sim.truth
    for k in range(3):
        z = sim.outputs().copy()
        A = tr.amp[k]
        for c in range(3):
            ref = _eq3(A[c], tr.bits[k, c], sim.err[c, 0], sim.err[c, 1], sim.err[c, 2], spacing)
            # eq. 3 treats the code error as constant over the interval: exact to ~1e-6 A here
            np.testing.assert_allclose(z[c], ref, atol=1e-5 * A[c])
        sim.advance()
    assert sim.err[0, 2] == pytest.approx(2 * np.pi * 20.0, rel=1e-9)


def test_noise_covariance_and_noise_events():
    sc = SimScenario(duration_s=4.0, n_ch=2, cn0_dbhz=-100.0, segments=[(0.0, 0.0, 0.0)],
                     noise_events=[(2.0, 4.0, 20.0)])
    sim = CorrSim(sc, np.random.default_rng(5))
    sim.init_nco()
    Z = np.empty((sim.N, 2, 6))
    for k in range(sim.N):
        Z[k] = sim.outputs()
        if k + 1 < sim.N:
            sim.advance()
    C = np.cov(Z[:2000].reshape(-1, 6).T)
    np.testing.assert_allclose(C, corr_model.epl_noise_covariance(1.0), atol=0.04)
    s_burst = Z[2000:].reshape(-1, 6).std(axis=0)
    np.testing.assert_allclose(s_burst, 20.0, rtol=0.05)


def test_truth_dynamics_closed_form_and_aiding():
    sc = SimScenario(duration_s=3.0, n_ch=2, f0_hz=[100.0, -50.0], los_scale=[1.0, 0.5],
                     segments=[(0.0, 10.0, 0.0), (1.0, 10.0, 4.0), (2.0, 30.0, 0.0)],
                     aid_bias_hz=[0.5, 0.0], aid_scale_err=[0.0, 0.01], aid_delay_s=0.0)
    tr = make_truth(sc, np.random.default_rng(1))

    def f_dyn(t):
        t = np.asarray(t, float)
        return np.where(t < 1, 10 * t, np.where(t < 2, 10 + 10 * (t - 1) + 2 * (t - 1) ** 2,
                                                   22 + 30 * (t - 2)))
    k = np.array([0, 500, 1500, 2500, 3000])
    np.testing.assert_allclose(tr.freq[k, 0], 100 + f_dyn(k * T), atol=1e-9)
    np.testing.assert_allclose(tr.freq[k, 1], -50 + 0.5 * f_dyn(k * T), atol=1e-9)
    tm = (np.arange(3000) + 0.5) * T
    # mean Doppler over the interval = Doppler at the centre (+ jerk term T^2/24)
    np.testing.assert_allclose(tr.freq_mid[:, 0], 100 + f_dyn(tm), atol=1e-6)
    np.testing.assert_allclose(tr.aid_hz[:, 0], tr.freq_mid[:, 0] + 0.5, atol=1e-6)
    np.testing.assert_allclose(tr.aid_hz[:, 1], tr.freq_mid[:, 1] + 0.01 * (tr.freq_mid[:, 1] + 50), atol=1e-6)
    # data bits: constant over 20 ms, +-1
    b = tr.bits[:, 0]
    assert set(np.unique(b)) <= {-1.0, 1.0}
    assert np.all(b.reshape(-1, 20) == b.reshape(-1, 20)[:, :1])
    # latency: the aiding is the truth of aid_delay_s ago
    sc2 = SimScenario(duration_s=1.0, n_ch=1, f0_hz=0.0, segments=[(0.0, 100.0, 0.0)], aid_delay_s=0.01)
    tr2 = make_truth(sc2, np.random.default_rng(1))
    np.testing.assert_allclose(tr2.aid_hz[20:, 0], tr2.freq_mid[20:, 0] - 100.0 * 0.01, atol=1e-9)


def test_code_phase_is_carrier_coherent():
    sc = SimScenario(duration_s=0.5, n_ch=1, f0_hz=2000.0, segments=[(0.0, 300.0, 0.0)])
    sim = CorrSim(sc, np.random.default_rng(1))
    sim.init_nco()
    p0 = sim.p_true.copy()
    for _ in range(400):
        sim.outputs()
        sim.advance()
    th = sim.truth.theta
    expected = p0 + 400 * (F_CA * T - 1023) + F_CA / F_L1 * (th[400] - th[0])
    np.testing.assert_allclose(sim.p_true, expected, rtol=0, atol=1e-8)


def test_bad_scenarios():
    with pytest.raises(ConfigError):
        make_truth(SimScenario(duration_s=0.0), np.random.default_rng(0))
    with pytest.raises(ConfigError):
        make_truth(SimScenario(duration_s=1.0, noise_events=[(0.0, 1.0, 0.0)]), np.random.default_rng(0))
    with pytest.raises(ConfigError):
        make_truth(SimScenario(duration_s=1.0, f0_hz=np.nan), np.random.default_rng(0))
