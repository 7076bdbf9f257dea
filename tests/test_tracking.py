"""Tracking loops: closed-form loop properties, and closed-loop tracking of a signal synthesised here.

The test signal is built independently of the project's generator: complex baseband
``a * c(p(t)) * d * exp(j 2 pi theta(t)) + n`` with code phase coherent with the carrier
(``p = p0 + F_CA t + (F_CA/F_L1)(theta - theta0)``), unit noise per component and ``a`` from
C/N0 (``C = a^2``, ``N0 = 2 sigma^2 / fs``).
"""

import math

import numpy as np
import pytest

from ultratight.constants import CA_LEN, F_CA, F_L1
from ultratight.signals.ca_code import ca_code
from ultratight.receiver.dsp import tracking_kernels as tk
from ultratight.receiver.dsp.tracking import ScalarTracker, TrackingConfig, cn0_m2m4, cn0_power
from ultratight.receiver.dsp.tracking_layout import (FL_BIT_DONE, FL_PLL_LOCK, MODE_LOST, R_BIT, R_CARR_ACC, R_CN0,
                                                 R_CODE_PHASE, R_DOPP, RI_EPOCH, RI_FLAGS, RI_PTR, S_BIT_PHASE)

FS = 2.6e6


def synth(dur, prn, cn0, fd0, fr=0.0, p0=100.3, theta0=0.2, bits=None, seed=1, off_at=None):
    rng = np.random.default_rng(seed)
    n = int(round(FS * dur))
    t = np.arange(n) / FS
    theta = theta0 + fd0 * t + 0.5 * fr * t * t
    p = p0 + F_CA * t + (F_CA / F_L1) * (theta - theta0)
    c = ca_code(prn).astype(np.float32)[np.floor(p).astype(np.int64) % CA_LEN]
    if bits is not None:
        c = c * bits[np.floor(p / (CA_LEN * 20)).astype(np.int64) % len(bits)]
    a = math.sqrt(2.0 * 10 ** (cn0 / 10) / FS)
    amp = np.full(n, a, dtype=np.float32)
    if off_at is not None:
        amp[int(off_at * FS):] = 0.0
    x = (amp * c * np.exp(2j * np.pi * theta)).astype(np.complex64)
    x += (rng.normal(size=n) + 1j * rng.normal(size=n)).astype(np.complex64)
    return x, p, theta


def run_tracker(x, prn, code_phase, doppler, config=None, block_s=0.1, cn0=None):
    tr = ScalarTracker(1, FS, 0.0, True, config)
    tr.start_channel(0, prn, code_phase, doppler, 0, cn0)
    bl = int(block_s * FS)
    fs_, is_ = [], []
    while True:
        s = tr.next_needed_sample()
        if s is None or s >= len(x) - 3000:
            break
        rf, ri, nr = tr.run(x[s:s + bl], s, 1.0)
        fs_.append(rf[0, :nr[0]])
        is_.append(ri[0, :nr[0]])
    return tr, np.concatenate(fs_), np.concatenate(is_)


# ------------------------------------------------------------------------------ loop filters alone
def _closed_loop_variance(order, bn, t, n=200_000, seed=3):
    """NCO phase variance when the discriminator sees white noise of unit variance."""
    rng = np.random.default_rng(seed)
    w = rng.normal(size=n)
    st = np.zeros(2)
    theta = 0.0
    out = np.empty(n)
    for k in range(n):
        ep = w[k] - theta
        f = tk.pll_fll_update(st, ep, 0.0, t, bn, 0.0, order)
        theta += f * t
        out[k] = theta
    return np.var(out[n // 10:])


@pytest.mark.parametrize("order,bn", [(2, 10.0), (3, 15.0)])
def test_pll_noise_bandwidth(order, bn):
    # a loop of noise bandwidth Bn updated every T passes var = 2 Bn T of white unit-variance noise
    t = 1e-3
    v = _closed_loop_variance(order, bn, t)
    assert v == pytest.approx(2.0 * bn * t, rel=0.15)


def test_pll_steady_state_errors():
    # frequency ramp R (Hz/s): 2nd-order loop lags R / w0^2 cycles, 3rd-order loop -> 0
    t, R = 1e-3, 50.0
    for order, bn in ((2, 10.0), (3, 15.0)):
        st = np.array([0.0, 0.0])
        theta_nco = 0.0
        for k in range(20000):
            theta_in = 0.5 * R * (k * t) ** 2
            ep = theta_in - theta_nco
            f = tk.pll_fll_update(st, ep, 0.0, t, bn, 0.0, order)
            theta_nco += f * t
        if order == 2:
            w0 = bn / 0.53
            assert ep == pytest.approx(R / w0 ** 2, rel=0.05)
        else:
            assert abs(ep) < 1e-4


def test_dll_first_order_bandwidth():
    rng = np.random.default_rng(5)
    t, bn, n = 1e-3, 2.0, 200_000
    w = rng.normal(size=n)
    tau = 0.0
    out = np.empty(n)
    for k in range(n):
        u, _ = tk.dll_update(0.0, w[k] - tau, t, bn, 1)
        tau += u * t
        out[k] = tau
    assert np.var(out[1000:]) == pytest.approx(2 * bn * t / (1 - 2 * bn * t), rel=0.1)


def test_discriminators_closed_form():
    # Costas: atan(Q/I)/2pi; insensitive to a data sign flip
    for phi in (-0.2, 0.0, 0.1, 0.24):
        i, q = math.cos(2 * math.pi * phi), math.sin(2 * math.pi * phi)
        assert tk.costas_disc(i, q) == pytest.approx(phi)
        assert tk.costas_disc(-i, -q) == pytest.approx(phi)
    # FLL: phase advance over t
    df, t = 30.0, 1e-3
    a1, a2 = 0.3, 0.3 + 2 * math.pi * df * t
    assert tk.fll_disc(math.cos(a1), math.sin(a1), math.cos(a2), math.sin(a2), t) == pytest.approx(df)
    assert tk.fll_disc(math.cos(a1), math.sin(a1), -math.cos(a2), -math.sin(a2), t) == pytest.approx(df)
    # DLL: triangle correlation, taps at -D/2 (early sees R(dtau - D/2)) and +D/2
    for d in (1.0, 0.5):
        for dtau in (-0.2, 0.0, 0.15):
            e = 1 - abs(dtau - d / 2)
            l = 1 - abs(dtau + d / 2)
            assert tk.dll_disc(e, 0.0, l, 0.0, d) == pytest.approx(dtau)
    # dot-product (1 chip): exact on the triangle, any carrier phase
    for dtau in (-0.4, -0.1, 0.0, 0.25, 0.45):
        e, l, pr = 1 - abs(dtau - 0.5), 1 - abs(dtau + 0.5), 1 - abs(dtau)
        for phi in (0.0, 1.0, 2.5):
            c, s_ = math.cos(phi), math.sin(phi)
            assert tk.dll_disc_dot((e - l) * c, (e - l) * s_, pr * c, pr * s_) == pytest.approx(dtau)


def test_prompt_el_kernels_match_a_direct_sum():
    """Both prompt / early-minus-late passes of the scalar tracking (the vectorised one on 64-bit code
    windows and the half-chip table one) give the sums of the taps P, E, L at 0, +-1/2 chip with the
    tracking's carrier table, computed here sample by sample in float64 (complex and real input)."""
    from ultratight.receiver.dsp.correlator import tap_fixed_point
    rng = np.random.default_rng(4)
    pad = 3
    code = ca_code(9).astype(np.float32)
    code_ext = code[(np.arange(CA_LEN + 2 * pad) - pad) % CA_LEN]
    tab = tk.half_chip_tables(9, pad)
    taps = tap_fixed_point(np.array([0.0, 0.5, -0.5]))
    for fs, n, is_complex in ((2.6e6, 2600, True), (4e6, 4000, True), (4e6, 4000, False)):
        x = rng.normal(size=(2 if is_complex else 1) * n).astype(np.float32)
        dp = F_CA * (1 + 1234.0 / F_L1) / fs
        cp0 = np.int64(np.floor((0.37 + pad) * 2 ** 32))
        cst = np.int64(np.floor(dp * 2 ** 32 + 0.5))
        ph0, phs = np.int64(123456789), np.int64(np.floor(1234.0 / fs * 2 ** 32))
        k = np.arange(n, dtype=np.int64)
        cp = cp0 + k * cst
        p_chip = code_ext[cp >> 32].astype(float)
        el_chip = code_ext[(cp + 2 ** 31) >> 32].astype(float) - code_ext[(cp - 2 ** 31) >> 32]
        li = ((ph0 + k * phs) >> (32 - tk.TRK_LUT_BITS)) & (tk.TRK_LUT_SIZE - 1)
        c, s = tk.TRK_COS_LUT[li].astype(float), tk.TRK_SIN_LUT[li].astype(float)
        if is_complex:
            xr, xi = x[0::2].astype(float), x[1::2].astype(float)
            bi, bq = xr * c + xi * s, xi * c - xr * s
        else:
            bi, bq = x * c, -x.astype(float) * s
        ref = np.array([bi @ p_chip, bi @ el_chip, 0.0, bq @ p_chip, bq @ el_chip, 0.0])
        window, half = np.zeros(6), np.zeros(6)
        tk.integrate_pel(x, is_complex, 0, n, code_ext, True, tab, cp0, cst, ph0, phs, taps, window)
        tk._integrate_pel(x, is_complex, 0, n, tab, cp0, cst, ph0, phs, tk._CS_LUT, half)
        for got in (window, half):
            np.testing.assert_allclose(got, ref, rtol=1e-5, atol=2e-3)
        # a table that is not all +-1 takes the half-chip pass
        fallback = np.zeros(6)
        tk.integrate_pel(x, is_complex, 0, n, code_ext, False, tab, cp0, cst, ph0, phs, taps, fallback)
        np.testing.assert_array_equal(fallback, half)


def test_cn0_estimators_against_model():
    rng = np.random.default_rng(9)
    n, t = 20000, 1e-3
    for cn0 in (30.0, 40.0):
        a = math.sqrt(2 * 10 ** (cn0 / 10) * t)
        phase = 0.3 + np.cumsum(rng.normal(0, 0.01, n))
        d = np.repeat(rng.choice([-1.0, 1.0], n // 20), 20)
        i = a * d * np.cos(phase) + rng.normal(size=n)
        q = a * d * np.sin(phase) + rng.normal(size=n)
        assert cn0_power(i, q, t) == pytest.approx(cn0, abs=0.3)
        assert cn0_m2m4(i, q, t) == pytest.approx(cn0, abs=0.7 if cn0 < 35 else 0.3)


# ------------------------------------------------------------------------------ closed loop on IF
def _code_err(p, ri, rf):
    truth = p[ri[:, RI_PTR]] % CA_LEN
    return (truth - rf[:, R_CODE_PHASE] + CA_LEN / 2) % CA_LEN - CA_LEN / 2


def test_track_static_45dbhz_bits_and_cn0():
    rng = np.random.default_rng(2)
    bits = rng.choice([-1.0, 1.0], size=200).astype(np.float32)
    x, p, theta = synth(3.0, 7, 45.0, 1500.0, bits=bits)
    tr, rf, ri = run_tracker(x, 7, (p[0] + 0.3) % CA_LEN, 1500.0 + 80.0)
    late = slice(1000, None)
    cerr = _code_err(p, ri, rf)[late]
    assert np.sqrt(np.mean(cerr ** 2)) < 0.02
    # carrier phase: NCO phase (IF 0) vs truth, modulo the Costas half-cycle ambiguity
    acc = rf[late, R_CARR_ACC]
    th = theta[ri[late, RI_PTR]]
    perr = (th - acc - (th[0] - acc[0]) + 0.25) % 0.5 - 0.25
    perr -= np.mean(perr)
    assert np.sqrt(np.mean(perr ** 2)) < 0.02
    assert np.all(ri[late, RI_FLAGS] & FL_PLL_LOCK)
    assert abs(np.mean(rf[late, R_DOPP]) - 1500.0) < 0.3
    assert rf[-1, R_CN0] == pytest.approx(45.0, abs=1.0)
    # bit sync: bit edges where the true code-period count is a multiple of 20
    bph = int(tr.state.si[0, S_BIT_PHASE])
    assert bph >= 0
    k = np.flatnonzero(ri[:, RI_EPOCH] % 20 == bph)[0]
    assert round(p[ri[k, RI_PTR]] / CA_LEN) % 20 == 0
    # decoded bits equal the transmitted ones (up to the Costas sign)
    done = np.flatnonzero(ri[:, RI_FLAGS] & FL_BIT_DONE)
    start_ptr = ri[done - 19, RI_PTR]
    true_bits = bits[np.round(p[start_ptr] / (CA_LEN * 20)).astype(int) % len(bits)]
    got = np.sign(rf[done, R_BIT])
    assert len(got) > 50
    assert np.all(got == true_bits) or np.all(got == -true_bits)


def test_track_2g_line_of_sight_acceleration():
    # 100 Hz/s Doppler rate = 19 m/s^2 along the line of sight, starting at t = 0
    x, p, theta = synth(2.5, 12, 45.0, -2000.0, fr=100.0, seed=4)
    tr, rf, ri = run_tracker(x, 12, p[0] % CA_LEN, -2000.0)
    late = slice(800, None)
    assert np.all(ri[late, RI_FLAGS] & FL_PLL_LOCK)
    acc = rf[late, R_CARR_ACC]
    th = theta[ri[late, RI_PTR]]
    perr = (th - acc - (th[0] - acc[0]) + 0.25) % 0.5 - 0.25
    assert np.max(np.abs(perr - np.mean(perr))) < 0.1
    assert np.sqrt(np.mean(_code_err(p, ri, rf)[late] ** 2)) < 0.03


def test_loss_of_lock_detected():
    cfg = TrackingConfig(lost_s=0.5)
    x, p, theta = synth(3.0, 3, 45.0, 500.0, off_at=1.0, seed=6)
    tr, rf, ri = run_tracker(x, 3, p[0] % CA_LEN, 500.0, config=cfg)
    assert not tr.active[0]
    assert tr.state.si[0, 0] == MODE_LOST
    t_lost = (ri[-1, RI_PTR] + 2600) / FS
    # C/N0 window 100 ms + smoothing + lost_s 0.5 s after the signal stops at 1.0 s
    assert 1.4 < t_lost < 2.2
    # the phase-lock flag (which gates observables) drops well before the channel is declared lost
    after = ri[:, RI_PTR] > 1.6 * FS
    assert after.any() and not np.any(ri[after, RI_FLAGS] & FL_PLL_LOCK)


def test_long_coherent_integration_at_low_cn0():
    # 30 dB-Hz, 20 ms coherent after bit sync: lock is kept and the code error stays small
    rng = np.random.default_rng(8)
    bits = rng.choice([-1.0, 1.0], size=300).astype(np.float32)
    cfg = TrackingConfig(coh_ms=20, track_pll_bw_hz=6.0, track_dll_bw_hz=0.5)
    x, p, theta = synth(5.0, 21, 30.0, 800.0, bits=bits, seed=7)
    tr, rf, ri = run_tracker(x, 21, p[0] % CA_LEN, 800.0, config=cfg, cn0=30.0)
    assert tr.active[0]
    late = slice(3000, None)
    assert np.mean(ri[late, RI_FLAGS] & FL_PLL_LOCK > 0) > 0.95
    assert np.sqrt(np.mean(_code_err(p, ri, rf)[late] ** 2)) < 0.08
    assert rf[-1, R_CN0] == pytest.approx(30.0, abs=1.5)


def test_threaded_tracking_with_idle_channels_equals_one_thread():
    """An all-in-view receiver's bank: tracked channels first, then idle ones (inactive). The threaded
    kernel (channels over numba's threads, the loop over the active ones only) gives every record
    bit for bit as the one-thread kernel; idle channels write nothing."""
    x1, p1, _ = synth(0.6, 7, 45.0, 1500.0, seed=5)
    x2, p2, _ = synth(0.6, 12, 42.0, -900.0, seed=6)
    x = (x1 + x2).astype(np.complex64)            # two satellites (the noise of both: 3 dB more)
    out = []
    for parallel in (False, True):
        tr = ScalarTracker(10, FS, 0.0, True, None, parallel=parallel)
        tr.start_channel(0, 7, p1[0] % CA_LEN, 1500.0, 0, None)
        tr.start_channel(5, 12, p2[0] % CA_LEN, -900.0, 0, None)
        recs = []
        for _ in range(5):
            start = tr.next_needed_sample()
            recs.append(tr.run(x[start:start + int(0.1 * FS)], start, 1.0))
        out.append(recs)
    for (rf_a, ri_a, n_a), (rf_b, ri_b, n_b) in zip(*out):
        np.testing.assert_array_equal(n_a, n_b)
        assert n_a[0] > 0 and n_a[5] > 0 and n_a[[1, 2, 3, 4, 6, 7, 8, 9]].sum() == 0
        np.testing.assert_array_equal(rf_a, rf_b)
        np.testing.assert_array_equal(ri_a, ri_b)
