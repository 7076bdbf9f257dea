"""Observables from tracking records against closed forms (constant code rate, Doppler ramp)."""

import numpy as np
import pytest

from ultratight.constants import C, CA_LEN, F_CA
from ultratight.receiver.scalar.observables import ChannelHistory, observe, pseudorange
from ultratight.receiver.dsp.tracking_layout import (N_RF, N_RI, R_CARR_ACC, R_CN0, R_CODE_PHASE, R_CODE_RATE, R_DOPP,
                                                 RI_EPOCH, RI_FLAGS, RI_N, RI_PTR, FL_PLL_LOCK)

FS = 2.6e6


class FakeNav:
    has_time = True

    def __init__(self, tow0):
        self.tow0 = tow0

    def tx_time(self, epoch):
        return self.tow0 + np.asarray(epoch, dtype=float) * 1e-3


def _records(n_ep, code_rate, f0, fdot, cp0=0.3, ptr0=1234):
    """NCO records as the tracking kernel writes them (periods end where the replica wraps)."""
    rf = np.zeros((n_ep, N_RF))
    ri = np.zeros((n_ep, N_RI), dtype=np.int64)
    cp, ptr, acc = cp0, ptr0, 0.0
    dp = code_rate / FS
    for e in range(n_ep):
        n = int(np.ceil((CA_LEN - cp) / dp))
        f = f0 + fdot * (ptr - ptr0) / FS
        rf[e, [R_CODE_PHASE, R_CODE_RATE, R_CARR_ACC, R_DOPP, R_CN0]] = cp, code_rate, acc, f, 44.0
        ri[e, [RI_PTR, RI_N, RI_EPOCH, RI_FLAGS]] = ptr, n, e, FL_PLL_LOCK
        cp = cp + n * dp - CA_LEN
        acc += n * f / FS
        ptr += n
    return rf, ri


def test_transmit_time_and_doppler_closed_form():
    code_rate = F_CA * (1 + 2500.0 / 1575.42e6)
    f0, fdot = 2500.0, 100.0
    rf, ri = _records(1500, code_rate, f0, fdot)
    h = ChannelHistory(FS)
    # appended in blocks, as the pipeline does
    for k in range(0, 1500, 97):
        h.append(rf[k:k + 97], ri[k:k + 97])
    nav = FakeNav(518400.0)
    hs = int(0.05 * FS)
    for s in (1234 + 1_700_000, 1234 + 2_600_000, 1234 + 3_500_123):   # within the kept 1 s
        o = observe(h, nav, s, hs)
        assert o is not None
        chips = 0.3 + (s - 1234) * code_rate / FS          # replica chips since epoch 0 (constant rate)
        assert o["t_tx_sv"] == pytest.approx(518400.0 + chips / F_CA, abs=1e-12)
        assert o["code_phase_chips"] == pytest.approx(chips % CA_LEN, abs=1e-6)
        t = (s - 1234) / FS
        # piecewise-constant (per 1 ms) frequency ramp: centred difference within fdot * 1 ms
        assert o["doppler_hz"] == pytest.approx(f0 + fdot * t, abs=fdot * 1.1e-3)
        assert o["pll_lock"] and o["cn0_dbhz"] == 44.0
    # outside the records or without h on both sides -> None
    assert observe(h, nav, 100, hs) is None
    assert observe(h, nav, int(ri[-1, RI_PTR]) - 10, hs) is None


def test_restart_inside_window_rejected():
    rf, ri = _records(400, F_CA, 0.0, 0.0)
    ri[200:, RI_EPOCH] = np.arange(200)          # the channel was re-acquired at epoch 200
    h = ChannelHistory(FS)
    h.append(rf, ri)
    s = int(ri[200, RI_PTR])
    assert observe(h, FakeNav(0.0), s, int(0.05 * FS)) is None
    assert observe(h, FakeNav(0.0), int(ri[100, RI_PTR]), int(0.05 * FS)) is not None


def test_history_window_is_bounded():
    rf, ri = _records(5000, F_CA, 0.0, 0.0)
    h = ChannelHistory(FS)
    for k in range(0, 5000, 100):
        h.append(rf[k:k + 100], ri[k:k + 100])
    assert h.ptr.size < 1300      # HIST_KEEP_S = 1 s of 1 ms epochs (+ one block)


def test_pseudorange_week_rollover():
    assert pseudorange(0.07, 604800.0 - 0.001) == pytest.approx(C * 0.071)
    assert pseudorange(518400.075, 518400.0) == pytest.approx(C * 0.075)


def test_code_noise_is_the_rms_of_the_code_around_the_carrier():
    """Ranges with white code noise of known sigma per channel and an exact carrier: the smoother's
    code-noise figure approaches each sigma (a 2 s average at 10 Hz, taken over the last 20 s here);
    none before the channel has settled and measured a few epochs, none again after a lock loss."""
    from ultratight.receiver.scalar.observables import NOISE_SETTLE_EPOCHS, CarrierSmoother
    rng = np.random.default_rng(11)
    lam = 0.19029367279836487
    sig = np.array([0.5, 0.8, 2.0, 0.0])
    sm = CarrierSmoother(4, 1000, wavelength_m=lam, noise_epochs=20)
    lock = np.ones(4, dtype=bool)
    rho0 = np.array([2.0e7, 2.1e7, 2.2e7, 2.3e7])
    est = []
    for k in range(600):
        rho = rho0 + np.array([-300.0, 120.0, 40.0, 700.0]) * 0.1 * k
        pr = rho + sig * rng.standard_normal(4)
        sm.update(pr, rho / lam, lock)
        nz = sm.code_noise_m()
        if k < NOISE_SETTLE_EPOCHS + 3:
            assert np.isnan(nz).all(), k
        if k >= 400:
            est.append(nz)
    est = np.sqrt(np.mean(np.square(est), axis=0))
    # the innovation is the code noise plus the smoothed range's own error (sigma / sqrt(M), small here)
    assert est[:3] == pytest.approx(sig[:3], rel=0.1)
    assert est[3] < 1e-6
    lost = lock.copy()
    lost[1] = False
    sm.update(pr, rho / lam, lost)
    assert np.isnan(sm.code_noise_m()[1]) and np.isfinite(sm.code_noise_m()[[0, 2, 3]]).all()


def test_noise_weights_scale_the_noisy_channels_only():
    from ultratight.receiver.scalar.observables import noise_weights
    w = noise_weights([0.8, 0.7, 0.9, 0.8, 2.0, np.nan, 50.0])
    # median of the six measured: 0.85; below it 1 (never trusted more than the a-priori sigma)
    assert w == pytest.approx([1.0, 1.0, 0.9 / 0.85, 1.0, 2.0 / 0.85, 1.0, 10.0])
    assert noise_weights([0.8, 0.9, np.nan, 1.0]) is None        # fewer than four measured
    assert noise_weights([0.0, 0.0, 0.0, 0.0]) is None
