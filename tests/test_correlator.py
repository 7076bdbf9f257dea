"""Correlator bank against an independent numpy correlation, noise statistics and sign conventions."""

import numpy as np
import pytest

from ultratight.constants import CA_LEN, F_CA, F_L1
from ultratight.errors import ConfigError
from ultratight.receiver.dsp.chipbits import code_window, unit_chips
from ultratight.receiver.dsp.correlator import (
    COLUMNS, COS_LUT, LUT_BITS, LUT_SIZE, SIN_LUT, CorrelatorBank, code_rate_from_doppler, estimate_sigma_arm,
    integrate_channel, nco_fixed_point, tap_fixed_point)
from ultratight.signals.ca_code import ca_code
from ultratight.signals.corr_model import (
    amplitude_from_cn0, code_autocorr, epl_noise_covariance, signal_amplitude, tap_offsets)


def synth(prn, fs, n, code_phase0, doppler_hz, carr_phase0_rad, if_hz=0.0, complex_sampling=True, amp=1.0,
          sigma=0.0, rng=None, data=None):
    """Signal whose code phase at sample 0 is code_phase0 (chips) and carrier phase carr_phase0_rad."""
    t = np.arange(n) / fs
    p = code_phase0 + t * F_CA * (1.0 + doppler_hz / F_L1)
    c = ca_code(prn)[np.floor(p).astype(np.int64) % CA_LEN].astype(float)
    if data is not None:
        c = c * data[np.floor(p / CA_LEN).astype(np.int64) % data.size]
    ph = 2 * np.pi * (if_hz + doppler_hz) * t + carr_phase0_rad
    if complex_sampling:
        x = amp * c * np.exp(1j * ph)
        if sigma > 0:
            x = x + sigma * (rng.standard_normal(n) + 1j * rng.standard_normal(n))
        return x.astype(np.complex64)
    x = amp * c * np.cos(ph)
    if sigma > 0:
        x = x + sigma * rng.standard_normal(n)
    return x.astype(np.float32)


def reference_epoch(x, fs, prn, code_phase, code_rate, carr_phase_cyc, carr_freq, offsets, sigma_arm):
    """Straightforward numpy correlation over one period starting at x[0] (exact float64 carrier)."""
    dp = code_rate / fs
    k = np.arange(int(2 * fs * 1e-3) + 10)
    p = code_phase + k * dp
    n = int(np.count_nonzero(p < CA_LEN))
    k = k[:n]
    p = p[:n]
    base = x[:n].astype(np.complex128) * np.exp(-2j * np.pi * (carr_phase_cyc + k * carr_freq / fs))
    code = ca_code(prn).astype(float)
    res_i, res_q = [], []
    for o in offsets:
        s = np.sum(base * code[np.floor(p + o).astype(np.int64) % CA_LEN])
        res_i.append(s.real)
        res_q.append(s.imag)
    return np.array(res_i + res_q) / (sigma_arm * np.sqrt(n)), n


@pytest.mark.parametrize("complex_sampling,fs,if_hz", [(True, 4.0e6, 0.0), (False, 5.3e6, 1.25e6),
                                                        (True, 2.5e6, 0.0)])
def test_matches_numpy_reference(complex_sampling, fs, if_hz):
    rng = np.random.default_rng(11)
    prn, fd, cp0, ph0 = 7, -3210.7, 517.37, 0.9
    n = int(fs * 4.2e-3)
    x = synth(prn, fs, n, cp0, fd, ph0, if_hz, complex_sampling, amp=1.0, sigma=0.5, rng=rng)
    bank = CorrelatorBank([prn], fs, if_hz, complex_sampling, spacing_chips=0.5, vel_spacing_chips=1.5)
    # replica deliberately a bit off the signal (so that all taps see signal and noise)
    rep_cp, rep_fd, rep_ph = cp0 + 0.13, fd + 40.0, 0.2
    bank.init_channel(0, prn, rep_cp, rep_fd, 0, carr_phase_cycles=rep_ph, align=False)
    offsets = [0.0, 0.25, -0.25, 0.75, -0.75]        # [P, E, L, VE, VL] per the documented convention
    cols = [0, 1, 2, 6, 7, 3, 4, 5, 8, 9]              # order of reference [I_P,I_E,I_L,I_VE,I_VL,Q_...]
    sigma_arm = 0.37
    start = 0
    for epoch in range(4):
        cp, cr, ph, cf = bank.code_phase[0], bank.code_rate[0], bank.carr_phase[0], bank.carr_freq[0]
        ref, n_ref = reference_epoch(x[start:], fs, prn, cp, cr, ph, cf, offsets, sigma_arm)
        out, t0, ns = bank.step(x, 0, sigma_arm)
        assert t0[0] == start and ns[0] == n_ref
        got = out[0, cols]
        rel = np.linalg.norm(got - ref) / np.linalg.norm(ref)
        assert rel < 1e-4, (epoch, rel)          # observed ~5e-6
        start += n_ref
    assert bank.sample_ptr[0] == start
    # the state advanced exactly: code phase continues from the start of the next period
    dp = code_rate_from_doppler(rep_fd) / fs
    assert bank.code_phase[0] == pytest.approx((rep_cp + start * dp) % CA_LEN, abs=1e-9)


def fixed_point_sums(buf, is_complex, off, n, code_ext, cp0, cstep, ph0, phstep, tap_fix, cos_lut, sin_lut):
    """The kernel's arithmetic as documented, in float64 numpy: carrier table entry = bits
    ``32 - LUT_BITS ..`` of the 32-bit phase ``ph0 + k*phstep``; tap t uses code entry
    ``(cp0 + k*cstep + tap_fix[t]) >> 32``.  Returns [I_t..., Q_t...] and sum_k (|bi| + |bq|)."""
    k = np.arange(n, dtype=np.int64)
    li = ((ph0 + k * phstep) >> (32 - LUT_BITS)) & (LUT_SIZE - 1)
    c, s = cos_lut[li].astype(float), sin_lut[li].astype(float)
    if is_complex:
        xr, xi = buf[2 * (off + k)].astype(float), buf[2 * (off + k) + 1].astype(float)
        bi, bq = xr * c + xi * s, xi * c - xr * s
    else:
        xr = buf[off + k].astype(float)
        bi, bq = xr * c, -xr * s
    codes = [code_ext[(cp0 + k * cstep + d) >> 32].astype(float) for d in tap_fix]
    sums = [np.sum(bi * cd) for cd in codes] + [np.sum(bq * cd) for cd in codes]
    return np.array(sums), float(np.sum(np.abs(bi) + np.abs(bq)))


# (n samples, start code phase in chips, carrier Hz, taps): block lengths around the 1024-sample
# float32 block, one shorter than a block, a start where the late tap reads the table's left
# padding, one running past the period end into the right padding, a falling carrier phase
KERNEL_CASES = [(4000, 0.0, 1234.5, (0.0, 0.5, -0.5)), (1024, 300.25, -2345.6, (0.0, 0.5, -0.5)),
                (1023, 10.5, 800.0, (0.0, 0.25, -0.25)), (1025, 700.0, -4000.0, (0.0, 0.5, -0.5)),
                (3000, 3.3, 150.0, (0.0, 0.9, -0.9)), (300, 0.1, -9000.0, (0.0, 0.5, -0.5)),
                (12, 1022.6, 2000.0, (0.0, 0.5, -0.5)), (2600, 300.0, -1.0, (0.0, 0.5, -0.5, 1.5, -1.5))]


@pytest.mark.parametrize("is_complex", [True, False])
@pytest.mark.parametrize("n,cp_chips,f_hz,taps", KERNEL_CASES)
def test_integrate_channel_exact_on_dyadic_data(is_complex, n, cp_chips, f_hz, taps):
    """Samples in {-4..4} and carrier tables of multiples of 1/8: every product and partial sum is
    exact in float32, so the kernel's sums equal the numpy ones exactly, in any order of the
    additions; any wrong table index, sample or block boundary shows."""
    rng = np.random.default_rng(n)
    fs = 4.0e6
    bank = CorrelatorBank([13], fs, 0.0, is_complex, vel_spacing_chips=3.0 if len(taps) == 5 else None)
    code_ext = bank.code_ext[0]
    cos_t = (rng.integers(-8, 9, LUT_SIZE) / 8.0).astype(np.float32)
    sin_t = (rng.integers(-8, 9, LUT_SIZE) / 8.0).astype(np.float32)
    off = 7
    buf = rng.integers(-4, 5, (off + n) * (2 if is_complex else 1)).astype(np.float32)
    dp = F_CA * (1.0 + f_hz / F_L1) / fs
    cp0, cstep, ph0, phstep = nco_fixed_point(cp_chips, bank.pad, dp, 0.3, f_hz, fs)
    tap_fix = tap_fixed_point(np.array(taps))
    acc = np.zeros(2 * len(taps))
    integrate_channel(buf, is_complex, off, n, code_ext, cp0, cstep, ph0, phstep, tap_fix, cos_t, sin_t, acc)
    ref, _ = fixed_point_sums(buf, is_complex, off, n, code_ext, cp0, cstep, ph0, phstep, tap_fix, cos_t, sin_t)
    np.testing.assert_array_equal(acc, ref)


@pytest.mark.parametrize("is_complex", [True, False])
@pytest.mark.parametrize("n,cp_chips,f_hz,taps", KERNEL_CASES[:3])
def test_integrate_channel_float32_rounding_on_noise(is_complex, n, cp_chips, f_hz, taps):
    """With the carrier tables and Gaussian samples the sums differ from the float64 ones only by
    float32 rounding: at most gamma_m * sum|terms| with gamma_m = m u / (1 - m u), u = 2**-24,
    m = 1024 + 3 (worst case of a float32 sum of a block plus its products; Higham 2002, ch. 3)."""
    rng = np.random.default_rng(5 + n)
    fs = 4.0e6
    bank = CorrelatorBank([21], fs, 0.0, is_complex)
    buf = rng.standard_normal(2 * n if is_complex else n).astype(np.float32)
    dp = F_CA * (1.0 + f_hz / F_L1) / fs
    cp0, cstep, ph0, phstep = nco_fixed_point(cp_chips, bank.pad, dp, 0.6, f_hz, fs)
    tap_fix = tap_fixed_point(np.array(taps))
    acc = np.zeros(6)
    integrate_channel(buf, is_complex, 0, n, bank.code_ext[0], cp0, cstep, ph0, phstep, tap_fix, COS_LUT, SIN_LUT,
                      acc)
    ref, abs_sum = fixed_point_sums(buf, is_complex, 0, n, bank.code_ext[0], cp0, cstep, ph0, phstep, tap_fix,
                                    COS_LUT, SIN_LUT)
    mu = (1024 + 3) * 2.0 ** -24
    assert np.all(np.abs(acc - ref) <= mu / (1 - mu) * abs_sum)
    assert np.max(np.abs(ref)) > 10.0                  # the sums are not trivially small


# (fs, start code phase in chips, carrier Hz, taps): from near the chip rate (few samples per 64-chip
# window) to 16 MHz, spacings up to 1.9 chips (early and late two chips apart in the window),
# taps not in the bank's [P, E, L] order (late tap not the lowest: the float64 loop)
RATE_CASES = [(1.1e6, 5.5, 3100.0, (0.0, 0.5, -0.5)), (2.046e6, 1000.9, -700.0, (0.0, 0.95, -0.95)),
              (2.5e6, 17.25, 60.0, (0.0, 0.05, -0.05)), (16.0e6, 512.0, -4400.0, (0.0, 0.5, -0.5)),
              (4.0e6, 200.0, 1234.5, (0.0, -0.5, 0.5)), (4.0e6, 0.0, 0.0, (0.25, 0.75, -0.25))]


@pytest.mark.parametrize("is_complex", [True, False])
@pytest.mark.parametrize("fs,cp_chips,f_hz,taps", RATE_CASES)
def test_integrate_channel_exact_across_rates(is_complex, fs, cp_chips, f_hz, taps):
    """As the dyadic test above, one code period at other sampling rates and tap sets: the chips the
    kernel reads from its windows of code sign bits are those of the floor rule at every sample."""
    rng = np.random.default_rng(int(fs) % 1000 + len(taps))
    bank = CorrelatorBank([5], fs, 0.0, is_complex, spacing_chips=1.9)
    code_ext = bank.code_ext[0]
    cos_t = (rng.integers(-8, 9, LUT_SIZE) / 8.0).astype(np.float32)
    sin_t = (rng.integers(-8, 9, LUT_SIZE) / 8.0).astype(np.float32)
    dp = F_CA * (1.0 + f_hz / F_L1) / fs
    n = int((CA_LEN - cp_chips) / dp)
    buf = rng.integers(-4, 5, n * (2 if is_complex else 1)).astype(np.float32)
    cp0, cstep, ph0, phstep = nco_fixed_point(cp_chips, bank.pad, dp, 0.7, f_hz, fs)
    tap_fix = tap_fixed_point(np.array(taps))
    acc = np.zeros(6)
    integrate_channel(buf, is_complex, 0, n, code_ext, cp0, cstep, ph0, phstep, tap_fix, cos_t, sin_t, acc)
    ref, _ = fixed_point_sums(buf, is_complex, 0, n, code_ext, cp0, cstep, ph0, phstep, tap_fix, cos_t, sin_t)
    np.testing.assert_array_equal(acc, ref)


def test_integrate_channel_chip_table_not_unit():
    """A chip table with an entry other than +-1 (the windows hold signs only) takes the float64
    loop: the sums are still those of the table's values (dyadic data: exact)."""
    rng = np.random.default_rng(9)
    fs, n = 4.0e6, 3000
    bank = CorrelatorBank([8], fs, 0.0, True)
    code_ext = bank.code_ext[0].copy()
    code_ext[40] = 0.5
    cos_t = (rng.integers(-8, 9, LUT_SIZE) / 8.0).astype(np.float32)
    sin_t = (rng.integers(-8, 9, LUT_SIZE) / 8.0).astype(np.float32)
    buf = rng.integers(-4, 5, 2 * n).astype(np.float32)
    cp0, cstep, ph0, phstep = nco_fixed_point(1.0, bank.pad, F_CA / fs, 0.2, 900.0, fs)
    tap_fix = tap_fixed_point(bank.tap_offsets_chips)
    acc = np.zeros(6)
    integrate_channel(buf, True, 0, n, code_ext, cp0, cstep, ph0, phstep, tap_fix, cos_t, sin_t, acc)
    ref, _ = fixed_point_sums(buf, True, 0, n, code_ext, cp0, cstep, ph0, phstep, tap_fix, cos_t, sin_t)
    np.testing.assert_array_equal(acc, ref)
    assert np.any(code_ext[(cp0 + np.arange(n) * cstep) >> 32] == 0.5)     # the odd entry is read


def test_code_window_bits():
    """Window bit c is the sign of chip j0 + c, also where fewer than 64 chips remain."""
    code = CorrelatorBank([3], 4e6, 0.0, True).code_ext[0]
    for j0 in (0, 17, code.shape[0] - 64, code.shape[0] - 30, code.shape[0] - 1):
        w = int(code_window(code, j0))
        want = sum(1 << c for c in range(min(64, code.shape[0] - j0)) if code[j0 + c] < 0)
        assert w == want, j0
    assert unit_chips(code) and not unit_chips(np.where(np.arange(code.size) == 5, 2.0, code).astype(np.float32))


def test_column_names():
    assert COLUMNS[:6] == ("I_P", "I_E", "I_L", "Q_P", "Q_E", "Q_L")


def test_noise_unit_variance_and_epl_covariance():
    rng = np.random.default_rng(5)
    fs, n_ep = 2.5e6, 3000
    n = int(fs * 1e-3 * n_ep) + 5000
    sigma = 3.0
    x = (sigma * (rng.standard_normal(n) + 1j * rng.standard_normal(n))).astype(np.complex64)
    bank = CorrelatorBank([1, 2], fs, 0.0, True, spacing_chips=1.0)
    bank.init_channel(0, 1, 100.0, 1500.0, 0)
    bank.init_channel(1, 2, 900.0, -4200.0, 0)
    out, _, _, n_done = bank.run_epochs(x, 0, estimate_sigma_arm(x, True))
    assert np.all(n_done >= n_ep - 5)
    z = out[0, :n_done[0]]
    var = z.var(axis=0)
    assert np.allclose(var, 1.0, atol=0.1), var
    cov = np.cov(z.T)
    assert np.allclose(cov, epl_noise_covariance(1.0), atol=0.08), np.round(cov, 3)


def test_noise_unit_variance_real_input():
    rng = np.random.default_rng(6)
    fs, if_hz = 5.0e6, 1.2e6
    n = int(fs * 1.5)
    x = (2.0 * rng.standard_normal(n)).astype(np.float32)
    sa = estimate_sigma_arm(x, False)
    assert sa == pytest.approx(2.0 / np.sqrt(2.0), rel=0.01)
    bank = CorrelatorBank([9], fs, if_hz, False, spacing_chips=0.5)
    bank.init_channel(0, 9, 0.0, 2000.0, 0)
    out, _, _, n_done = bank.run_epochs(x, 0, sa)
    z = out[0, :n_done[0]]
    assert np.allclose(z.var(axis=0), 1.0, atol=0.12), z.var(axis=0)
    assert np.allclose(np.cov(z.T), epl_noise_covariance(0.5), atol=0.1)


@pytest.mark.parametrize("complex_sampling", [True, False])
def test_prompt_amplitude_matches_cn0(complex_sampling):
    rng = np.random.default_rng(21 + complex_sampling)
    fs, cn0, sigma = 4.0e6, 42.0, 2.0
    if_hz = 0.0 if complex_sampling else 1.1e6
    n_ep = 400
    n = int(fs * 1e-3 * (n_ep + 2))
    a = float(signal_amplitude(cn0, fs, sigma, complex_sampling))
    x = synth(12, fs, n, 300.0, 1500.0, 0.0, if_hz, complex_sampling, amp=a, sigma=sigma, rng=rng)
    bank = CorrelatorBank([12], fs, if_hz, complex_sampling)
    bank.init_channel(0, 12, 300.0, 1500.0, 0, carr_phase_cycles=0.0)  # aligned to period start
    sa = estimate_sigma_arm(x, complex_sampling)
    out, _, ns, n_done = bank.run_epochs(x, 0, sa)
    ip = out[0, :n_done[0], 0]
    qp = out[0, :n_done[0], 3]
    a_hat = ip.mean()
    a_true = float(amplitude_from_cn0(cn0, 1e-3))
    assert 20 * np.log10(a_hat / a_true) == pytest.approx(0.0, abs=0.3)
    assert abs(qp.mean()) < 0.2                       # phase aligned: signal all in I
    # C/N0 from the power: (I^2+Q^2 - 2)/2 / T
    p = np.mean(ip ** 2 + qp ** 2) - 2.0
    assert 10 * np.log10(p / 2 / 1e-3) == pytest.approx(cn0, abs=0.3)


@pytest.mark.parametrize("dtau", [0.2, -0.2, 0.45])
def test_code_discriminator_sign(dtau):
    """Input code phase = replica + dtau: taps follow R(dtau + d_x), d_E=-D/2, d_L=+D/2."""
    fs = 16.0e6 + 123.0
    # PRN 12: one-chip-shift autocorrelation -1/1023, so R is the ideal triangle (some PRNs, e.g. 17,
    # have +63/1023 there, which lifts R(tau) by 0.06*|tau| for |tau| < 1)
    prn, fd = 12, 800.0
    n = int(fs * 3e-3)
    x = synth(prn, fs, n, 10.0 + dtau, fd, 0.0)
    bank = CorrelatorBank([prn], fs, 0.0, True, spacing_chips=1.0)
    bank.init_channel(0, prn, 10.0, fd, 0, align=False)
    out, _, ns = bank.step(x, 0, 1.0)
    a = np.sqrt(ns[0])                      # noise-free unit-amplitude input: P = sqrt(N) R(dtau)
    expected = code_autocorr(dtau + tap_offsets(1.0))
    assert np.allclose(out[0, :3] / a, expected, atol=0.02)
    assert np.allclose(out[0, 3:6], 0.0, atol=0.02 * a)
    if dtau > 0:
        assert out[0, 1] > out[0, 2]        # E > L when the input leads the replica
    else:
        assert out[0, 1] < out[0, 2]


def test_carrier_sign_and_frequency_error():
    fs, prn = 4.0e6, 4
    dphi, dfreq = 0.4, 150.0                # input minus replica: rad, Hz
    x = synth(prn, fs, int(fs * 2e-3), 0.0, 1000.0 + dfreq, dphi)
    bank = CorrelatorBank([prn], fs, 0.0, True)
    bank.init_channel(0, prn, 0.0, 1000.0, 0)
    out, _, ns = bank.step(x, 0, 1.0)
    T = ns[0] / fs
    dw = 2 * np.pi * dfreq
    amp = np.sqrt(ns[0]) * np.sinc(dfreq * T)     # np.sinc(x) = sin(pi x)/(pi x) = sinc(dw T/2)
    # the code rate follows fd, the input's code is slightly faster: negligible (1e-4 chip)
    assert out[0, 0] == pytest.approx(amp * np.cos(dw * T / 2 + dphi), rel=2e-3)
    assert out[0, 3] == pytest.approx(amp * np.sin(dw * T / 2 + dphi), rel=2e-3)


def test_not_ready_and_chunked_equals_whole():
    rng = np.random.default_rng(3)
    fs = 4.0e6
    n = int(fs * 6e-3)
    x = synth(5, fs, n, 200.0, 2500.0, 0.3, sigma=1.0, amp=0.3, rng=rng)
    whole = CorrelatorBank([5, 6], fs, 0.0, True)
    chunk = CorrelatorBank([5, 6], fs, 0.0, True)
    for b in (whole, chunk):
        b.init_channel(0, 5, 200.0, 2500.0, 0)
        b.init_channel(1, 6, 17.5, -900.0, 0)
    ref, ts_ref, ns_ref, nd = whole.run_epochs(x, 0, 1.0)
    # feed 5000-sample buffers that begin at the earliest sample still needed
    got = [[], []]
    while True:
        start = int(chunk.sample_ptr.min())
        if start + 4100 > n:
            break
        out, ts, ns = chunk.step(x[start:start + 5000], start, 1.0)
        assert np.all(ns >= 0) and np.any(ns > 0)
        for ch in range(2):
            if ns[ch] > 0:
                assert ts[ch] == ts_ref[ch, len(got[ch])]
                got[ch].append(out[ch])
            else:
                assert np.all(out[ch] == 0.0)
    # a buffer that begins too late: -1 and state untouched
    ptr = chunk.sample_ptr.copy()
    out, ts, ns = chunk.step(x[ptr.max() + 1:], int(ptr.max()) + 1, 1.0)
    assert np.all(ns == -1) and np.array_equal(chunk.sample_ptr, ptr)
    for ch in range(2):
        g = np.array(got[ch])
        assert nd[ch] - 1 <= g.shape[0] <= nd[ch]
        assert np.allclose(g, ref[ch, :g.shape[0]], rtol=1e-9, atol=1e-9)


def test_invalid_nco_reports_minus_two():
    bank = CorrelatorBank([1, 2], 4e6, 0.0, True)
    bank.init_channel(0, 1, 0.0, 0.0, 0)
    bank.init_channel(1, 2, 0.0, 0.0, 0)
    bank.code_rate[1] = -5.0
    out, ts, ns = bank.step(np.zeros(8000, np.complex64), 0, 1.0)
    assert ns[0] == 4000 and ns[1] == -2 and bank.sample_ptr[1] == 0


def test_exact_rate_gives_exact_periods():
    """fs = 4 MHz, zero Doppler: every period is exactly 4000 samples despite float round-off."""
    bank = CorrelatorBank([1], 4e6, 0.0, True)
    bank.init_channel(0, 1, 0.0, 0.0, 0)
    _, ts, ns, nd = bank.run_epochs(np.zeros(4000 * 50, np.complex64), 0, 1.0)
    assert nd[0] == 50 and np.all(ns[0, :50] == 4000)
    assert np.array_equal(ts[0, :50], 4000 * np.arange(50))
    assert bank.code_phase[0] == pytest.approx(0.0, abs=1e-9)
    # and re-initialising from a code phase within round-off of a period start aligns to it
    bank.init_channel(0, 1, 1023.0 - 1e-12, 0.0, 100)
    assert bank.sample_ptr[0] == 100 and bank.code_phase[0] == 0.0


def test_add_remove_channels():
    bank = CorrelatorBank([1], 4e6, 0.0, True)
    ch0 = bank.add_channel(3, 10.0, 100.0, 0)
    assert ch0 == 0 and bank.prns[0] == 3
    ch1 = bank.add_channel(4, 10.0, 100.0, 0)
    assert ch1 == 1 and bank.n_ch == 2 and bank.prns[1] == 4
    bank.remove_channel(0)
    out, ts, ns = bank.step(np.zeros(8000, np.complex64), 0, 1.0)
    assert ns[0] == 0 and ns[1] > 0
    ch = bank.add_channel(9, 0.0, 0.0, 0)
    assert ch == 0 and bank.prns[0] == 9 and bank.active[0]


@pytest.mark.parametrize("kwargs,word", [
    (dict(fs_hz=0.0), "fs_hz"), (dict(fs_hz=-4e6), "fs_hz"),
    (dict(spacing_chips=0.0), "spacing"), (dict(spacing_chips=2.0), "spacing"),
    (dict(spacing_chips=-0.5), "spacing"), (dict(vel_spacing_chips=0.0), "vel_spacing"),
    (dict(prns=[0]), "PRN"), (dict(prns=[33]), "PRN"), (dict(if_hz=5e6), "if_hz"),
])
def test_bad_parameters(kwargs, word):
    args = dict(prns=[1], fs_hz=4e6, if_hz=0.0, is_complex=True)
    args.update(kwargs)
    with pytest.raises(ConfigError, match=word):
        CorrelatorBank(**args)


def test_bad_buffer_and_sigma():
    bank = CorrelatorBank([1], 4e6, 1e6, False)
    with pytest.raises(ConfigError, match="real input"):
        bank.step(np.zeros(10, np.complex64), 0, 1.0)
    with pytest.raises(ConfigError, match="noise_sigma_arm"):
        bank.step(np.zeros(10, np.float32), 0, 0.0)
    with pytest.raises(ConfigError, match="zero noise"):
        estimate_sigma_arm(np.ones(100), True)
