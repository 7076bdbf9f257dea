"""Batched correlator bank (numba), one primary-code period per step (GPS L1 C/A: 1023 chips, 1 ms).

Every active channel integrates the input from its own ``sample_ptr`` to the
end of its current C/A code period (the samples whose replica code phase is
``< 1023`` chips), in one fused pass per channel: carrier wipe-off, code
multiplication for the prompt, early and late taps (plus very-early/very-late
when asked), and the coherent sums.  The outputs are normalised as defined in
:mod:`ultratight.signals.corr_model` (unit noise per arm).

Sign conventions (the prefilter model of Zhao et al. 2014, eq. 3 relies on them)
------------------------------------------------------------------------
Carrier.  ``carr_phase`` is in cycles, ``carr_freq`` in Hz (IF + Doppler;
for complex baseband IF = 0).  The local carrier replica at sample ``k`` of an
integration is ``exp(-j*2*pi*(carr_phase + k*carr_freq/fs))`` and the output
is ``I + jQ = sum_k x_k * replica_k * code_k``.  For an input
``x = a*c*d*exp(j*2*pi*theta_in)`` (complex) or ``a*c*d*cos(2*pi*theta_in)``
(real) the carrier phase error is ``dphi = 2*pi*(theta_in - theta_replica)``
(rad, input minus replica): ``I ~ cos(dphi)``, ``Q ~ sin(dphi)``, and with a
frequency error ``df = 2*pi*(f_in - carr_freq)`` (rad/s) the sums follow
``sinc(df*T/2) * cos/sin(df*T/2 + dphi)`` with ``dphi`` taken at the first
sample of the integration.

Code.  ``code_phase`` (chips) is the prompt replica's code phase at sample
``sample_ptr``; it advances by ``code_rate/fs`` chips per sample.  A tap with
offset ``o`` chips uses the chip ``floor(p_k + o)`` of the (periodic) code at
sample ``k``; the **early tap is ahead** of the prompt: ``o_E = +D/2``,
``o_L = -D/2`` (``o_VE = +D_v/2``, ``o_VL = -D_v/2``).  With the code phase
error defined as ``dtau = p_in - p_replica`` (chips, input minus prompt
replica), tap ``x`` sees ``R(dtau + d_x)`` with ``d_P = 0, d_E = -D/2,
d_L = +D/2`` exactly as :func:`ultratight.signals.corr_model.tap_offsets`
and Zhao et al. 2014, eq. 3.  So an input whose code phase is *larger* than the
replica's (``dtau > 0``: the replica lags and must be advanced) gives
``|E| > |L|``; ``E - L > 0`` therefore means "advance the code NCO".

Output columns: ``[I_P, I_E, I_L, Q_P, Q_E, Q_L]`` and, with very-early/late
taps, ``[..., I_VE, I_VL, Q_VE, Q_VL]`` appended (see :data:`COLUMNS`).

Implementation: the carrier uses a 32-bit phase accumulator (int64 arithmetic,
wrapped by masking) indexing a ``2**LUT_BITS``-entry float32 cos/sin table
built at bin centres (unbiased; phase error uniform within +-pi/2**LUT_BITS);
the code uses a fixed-point (32 fractional bits) code-phase accumulator
indexing a +-1 chip table padded on both sides so that no modulo is needed
(the three-tap kernel reads those chips from 64-bit windows of their sign bits,
:mod:`ultratight.receiver.dsp.chipbits`: the same chips, without a look-up per tap).
The NCO state kept in the public float64 arrays is advanced exactly (float64)
after every integration, so accumulator quantisation never accumulates.

Not-ready channels.  A channel whose period does not end inside the buffer
reports ``n_samples = NOT_READY`` (0; state unchanged: refill and call again, starting the
next buffer at or before its ``sample_ptr``).  A channel whose ``sample_ptr``
lies before ``buf_start`` (its samples are no longer in the buffer) reports
``n_samples = BEHIND_BUFFER`` (-1; state unchanged; use :meth:`CorrelatorBank.advance_to`).
Inactive channels report ``NOT_READY`` and zero outputs.  A channel with an
invalid NCO state (``code_rate <= 0`` or non-finite phases/frequency) reports
``n_samples = INVALID_NCO`` (-2; state unchanged).

Kernel-level API (public and stable: the tracking module's fused loops and the ultra-tight
engine's compiled epoch runner, :mod:`ultratight.receiver.deep.epochs`, call it):
:func:`step_bank` (one code period for every channel) and :func:`correlate_one` (one channel of it,
with the caller's work array), :func:`integrate_channel` (one channel, raw sums over ``n`` samples), :func:`period_samples`
(samples to the end of the current code period), :func:`nco_fixed_point` /
:func:`tap_fixed_point` (the kernel's fixed-point start values and tap offsets), the carrier tables :data:`COS_LUT` /
:data:`SIN_LUT` (``LUT_SIZE = 2**LUT_BITS`` float32 entries at bin centres, indexed by the top
``LUT_BITS`` bits of the 32-bit carrier phase), and the bank's padded code table
:attr:`CorrelatorBank.code_ext` (n_ch, code length + 2*pad) with :attr:`CorrelatorBank.pad` chips of
wrap-around on each side; the fixed-point code phase passed to the kernel is
``floor((code_phase + pad) * 2**32)``.
"""

import math

import numpy as np
from numba import njit

from ultratight.errors import ConfigError
from ultratight.signals.nco import NcoBank
from ultratight.signals.signal import GPS_L1CA
from ultratight.receiver.dsp.blockstream import block_sigma_arm
from ultratight.receiver.dsp.chipbits import chip_at, code_window, unit_chips

LUT_BITS = 14                   # carrier table: 2**LUT_BITS entries, indexed by the top phase bits
LUT_SIZE = 1 << LUT_BITS
_PHASE_BITS = 32
_PHASE_MASK = (1 << _PHASE_BITS) - 1
_LUT_SHIFT = _PHASE_BITS - LUT_BITS
_CODE_FRAC_BITS = 32
_CODE_ONE = float(1 << _CODE_FRAC_BITS)
_CARR_ONE = float(1 << _PHASE_BITS)

# Column indices of the outputs.
I_P, I_E, I_L, Q_P, Q_E, Q_L = range(6)
I_VE, I_VL, Q_VE, Q_VL = range(6, 10)
COLUMNS = ("I_P", "I_E", "I_L", "Q_P", "Q_E", "Q_L", "I_VE", "I_VL", "Q_VE", "Q_VL")

# status codes in n_samples
NOT_READY = 0
BEHIND_BUFFER = -1
INVALID_NCO = -2


def _carrier_lut():
    ang = 2.0 * np.pi * (np.arange(LUT_SIZE) + 0.5) / LUT_SIZE
    return np.cos(ang).astype(np.float32), np.sin(ang).astype(np.float32)


COS_LUT, SIN_LUT = _carrier_lut()   # cos/sin of 2*pi*(i + 0.5)/LUT_SIZE, float32 (public kernel API)


def code_rate_from_doppler(doppler_hz, signal=GPS_L1CA):
    """Code rate (chips/s) matching a carrier Doppler (Hz): chip rate * (1 + fd / carrier)."""
    return signal.code_rate_cps(np.asarray(doppler_hz, dtype=float))


def estimate_sigma_arm(block, is_complex):
    """Per-arm noise std after carrier wipe-off, estimated from a block's sample power.

    GPS signals lie far below the noise, so the block's power is the noise power:
    complex input ``sigma = sqrt(mean(|x|^2)/2)``; real input ``sigma = rms(x)``,
    then :func:`ultratight.signals.corr_model.noise_sigma_arm` (``/sqrt(2)`` for real).
    The mean is removed first (front-end DC offsets would otherwise count as noise).
    The estimator is :func:`ultratight.receiver.dsp.blockstream.block_sigma_arm`; this raises on an
    empty block or one without power.
    """
    x = np.asarray(block)
    if x.size == 0:
        raise ConfigError("estimate_sigma_arm: empty block (need samples to estimate the noise power)")
    sigma_arm = block_sigma_arm(x, is_complex)
    if not sigma_arm > 0.0:
        raise ConfigError("estimate_sigma_arm: block has zero noise power (all samples equal)")
    return sigma_arm


@njit(cache=True, fastmath={"reassoc", "contract"})
def _epl_block(buf, is_complex, off, m, w, u, cstep, ph, phstep, s_p, t_p, s_e, t_e, cos_lut, sin_lut):
    """float32 sums ``(I_P, I_E, I_L, Q_P, Q_E, Q_L)`` over the ``m`` samples from buffer offset
    ``off``, the chips read from ``w``, the 64-bit window of code sign bits that starts at a chip
    ``j0`` (bit ``c``: chip ``j0 + c``, :func:`ultratight.receiver.dsp.chipbits.code_window`).

    ``u`` (uint64) is the late tap's code accumulator relative to chip ``j0`` at the first sample
    (the late tap has the lowest offset): its chip is bit ``u >> 32`` of the window.  A tap whose
    offset above the late tap's is ``h*2**32 + l`` (``0 <= l < 2**32``) reads the bit ``h`` or
    ``h + 1`` above it, ``h + 1`` when the low 32 bits of ``u`` plus ``l`` carry: with the low bits
    sign-flipped (``lo``) the carry is the signed ``lo > t``, ``t = (2**32 - 1 - l) ^ 2**31``, and
    ``s = 31 - h`` (:func:`_tap_shift`; ``s_p, t_p`` prompt, ``s_e, t_e`` early).  These are the
    chips of the documented rule ``floor(p_k + o)`` exactly (integer arithmetic throughout).
    ``ph``/``phstep``: the carrier accumulator at the first sample and its step, as
    :func:`integrate_channel`.

    Its own kernel so that only these sums are reassociated: LLVM splits each of the six over the
    lanes of 8-wide float32 vectors, contracts the multiply-adds, and computes the chips of eight
    samples with a few vector shifts and compares (:mod:`ultratight.receiver.dsp.chipbits`); only
    the two carrier-table look-ups remain one load per sample and lane.  That took the bank from
    0.60-0.65 to 0.79-0.84 G channel-samples/s per core (8 channels, complex input; 13 channels
    0.63-0.65 -> 0.74-0.79; AMD EPYC Zen 3, load 0.7-2.6), the kernel before doing three code
    look-ups per sample; the sums change by float32 rounding only (shorter float32 stretches,
    another order of the additions); commands and figures in docs/receiver_blocks.md.
    Indices are unsigned (``np.uint64``): numba then leaves out the negative-index wraparound of
    every look-up.
    """
    shift = 32 - LUT_BITS
    mask = LUT_SIZE - 1
    one = np.uint64(1)
    flip = np.uint32(0x80000000)
    ip = np.float32(0.0); ie = np.float32(0.0); il = np.float32(0.0)
    qp = np.float32(0.0); qe = np.float32(0.0); ql = np.float32(0.0)
    if is_complex:
        for kk in range(m):
            j = np.uint64(2 * (off + kk))
            xr = buf[j]
            xi = buf[j + one]
            li = np.uint64((ph + kk * phstep) >> shift) & np.uint64(mask)
            c = cos_lut[li]
            s = sin_lut[li]
            bi = xr * c + xi * s
            bq = xi * c - xr * s
            v = np.uint32(w >> (u >> np.uint64(32)))
            lo = np.uint32(u) ^ flip
            cP = chip_at(v, s_p, lo, t_p)
            cE = chip_at(v, s_e, lo, t_e)
            cL = chip_at(v, 31, 0, 0)
            ip += bi * cP; ie += bi * cE; il += bi * cL
            qp += bq * cP; qe += bq * cE; ql += bq * cL
            u += cstep
        return ip, ie, il, qp, qe, ql
    for kk in range(m):
        xr = buf[np.uint64(off + kk)]
        li = np.uint64((ph + kk * phstep) >> shift) & np.uint64(mask)
        bi = xr * cos_lut[li]
        bq = -xr * sin_lut[li]
        v = np.uint32(w >> (u >> np.uint64(32)))
        lo = np.uint32(u) ^ flip
        cP = chip_at(v, s_p, lo, t_p)
        cE = chip_at(v, s_e, lo, t_e)
        cL = chip_at(v, 31, 0, 0)
        ip += bi * cP; ie += bi * cE; il += bi * cL
        qp += bq * cP; qe += bq * cE; ql += bq * cL
        u += cstep
    return ip, ie, il, qp, qe, ql


@njit(cache=True)
def _tap_shift(d):
    """``(s, t)`` of :func:`_epl_block` for a tap ``d >= 0`` (fixed point) above the late tap."""
    low = d & 0xFFFFFFFF
    return np.int32(31 - (d >> 32)), np.int32(np.uint32((0xFFFFFFFF - low) ^ 0x80000000))


@njit(cache=True)
def _window_block(tap_fix, cstep):
    """Samples per :func:`_epl_block` call (a multiple of 8, at most 1024) such that every tap's chip
    stays inside one 64-chip window; 0 when the taps are not ``[P, E, L]`` with the late tap lowest
    and the others less than 30 chips above it, or not even 8 samples fit."""
    d_l = tap_fix[2]
    span = max(tap_fix[0], tap_fix[1]) - d_l
    room = (63 << 32) - span - 1
    if cstep <= 0 or span > (30 << 32) or tap_fix[0] < d_l or tap_fix[1] < d_l:
        return 0
    return min(room // cstep + 1, 1024) & ~7


@njit(cache=True)
def integrate_channel(buf, is_complex, off, n, code_ext, cp_fix0, cstep, ph0, phstep,
                      tap_fix, cos_lut, sin_lut, acc):
    """Fused wipe-off + taps for one channel over n samples starting at buffer offset ``off``.

    ``buf`` is float32: interleaved I,Q for complex input, plain samples for real.
    ``code_ext`` is one row of :attr:`CorrelatorBank.code_ext` (entries +-1); ``cp_fix0``/``cstep`` the code
    phase (``floor((code_phase + pad) * 2**32)``) and its step per sample, ``ph0``/``phstep`` the
    32-bit carrier phase and step; ``cos_lut``/``sin_lut`` are :data:`COS_LUT`/:data:`SIN_LUT`.
    ``tap_fix[t]`` are the tap offsets in fixed point (code chips * 2**32).
    ``acc`` (2*n_taps,) receives [I_t..., Q_t...] raw sums (float64).

    Three taps ``[P, E, L]`` with the late tap lowest (the bank's; the receiver's hot spot):
    float32 sums over stretches of samples whose chips fit one 64-chip window (at most 1024
    samples; 240 at 4 MHz; :func:`_epl_block`, vectorised), each flushed to float64; the
    accumulators at a stretch's first sample ``k`` are ``cp_fix0 + k*cstep`` and
    ``ph0 + k*phstep`` exactly (integers).  Other taps, or a chip table that is not all +-1: one
    float64 loop.
    """
    n_taps = tap_fix.shape[0]
    shift = 32 - LUT_BITS
    mask = LUT_SIZE - 1
    cp = cp_fix0
    ph = ph0
    for t in range(2 * n_taps):
        acc[t] = 0.0
    blk = _window_block(tap_fix, cstep) if n_taps == 3 else 0
    if blk > 0 and unit_chips(code_ext):
        d_l = tap_fix[2]
        s_p, t_p = _tap_shift(tap_fix[0] - d_l)
        s_e, t_e = _tap_shift(tap_fix[1] - d_l)
        k = 0
        while k < n:
            m = min(blk, n - k)
            cpk = cp_fix0 + k * cstep + d_l
            j0 = cpk >> 32
            s6 = _epl_block(buf, is_complex, off + k, m, code_window(code_ext, j0), np.uint64(cpk - (j0 << 32)),
                            np.uint64(cstep), ph0 + k * phstep, phstep, s_p, t_p, s_e, t_e, cos_lut, sin_lut)
            for t in range(6):
                acc[t] += s6[t]
            k += m
        return
    for kk in range(n):
        if is_complex:
            j = 2 * (off + kk)
            xr = buf[j]
            xi = buf[j + 1]
            li = (ph >> shift) & mask
            c = cos_lut[li]
            s = sin_lut[li]
            bi = xr * c + xi * s
            bq = xi * c - xr * s
        else:
            xr = buf[off + kk]
            li = (ph >> shift) & mask
            bi = xr * cos_lut[li]
            bq = -xr * sin_lut[li]
        for t in range(n_taps):
            ct = code_ext[(cp + tap_fix[t]) >> 32]
            acc[t] += bi * ct
            acc[n_taps + t] += bq * ct
        cp += cstep
        ph += phstep


@njit(cache=True)
def period_samples(code_phase, dp, code_len):
    """Samples k >= 0 with code_phase + k*dp < code_len (at least 1; ``code_len`` chips per period).

    A sample within 1e-9 sample of the period end counts as the next period's
    first, so that exact rates (e.g. fs = 4 MHz, code phase 0) give exactly
    fs/1000 samples despite float round-off in (code_len - cp)/dp.
    """
    n = np.int64(np.ceil((code_len - code_phase) / dp - 1e-9))
    if n < 1:
        n = 1
    return n


@njit(cache=True)
def tap_fixed_point(tap_off):
    """Tap offsets (chips, float64 array) in the kernel's 32.32 fixed point (int64 array)."""
    tap_fix = np.empty(tap_off.shape[0], dtype=np.int64)
    for t in range(tap_off.shape[0]):
        tap_fix[t] = np.int64(np.floor(tap_off[t] * _CODE_ONE))
    return tap_fix


@njit(cache=True)
def nco_fixed_point(code_phase, pad, dp, carr_phase, carr_freq, fs):
    """Kernel start values ``(cp_fix0, cstep, ph0, phstep)`` of :func:`integrate_channel` for a channel
    whose code phase (chips) is ``code_phase`` with ``dp`` chips per sample, in a code table padded
    by ``pad`` chips, and whose carrier is at ``carr_phase`` cycles and ``carr_freq`` Hz (fs in Hz)."""
    cp_fix0 = np.int64(np.floor((code_phase + pad) * _CODE_ONE))
    cstep = np.int64(np.floor(dp * _CODE_ONE + 0.5))
    frac = carr_phase - np.floor(carr_phase)
    ph0 = np.int64(np.floor(frac * _CARR_ONE))
    phstep = np.int64(np.floor(carr_freq / fs * _CARR_ONE + 0.5))
    return cp_fix0, cstep, ph0, phstep


@njit(cache=True)
def correlate_one(ch, buf, is_complex, buf_start, n_buf, code_ext, pad, active, sample_ptr,
                   code_phase, code_rate, carr_phase, carr_freq, fs, tap_fix, sigma_arm, out, t_start, n_samples,
                   code_len, acc):
    """One code period of channel ``ch`` (see :func:`step_bank`); touches only row ``ch`` and the
    work array ``acc`` (at least 2 * number of taps; the caller's, so no allocation per period)."""
    n_taps = tap_fix.shape[0]
    t_start[ch] = sample_ptr[ch]
    for c in range(out.shape[1]):
        out[ch, c] = 0.0
    n_samples[ch] = NOT_READY
    if not active[ch]:
        return
    dp = code_rate[ch] / fs
    if not (dp > 0.0 and dp < 1e6 and np.isfinite(code_phase[ch]) and np.isfinite(carr_freq[ch])
            and np.isfinite(carr_phase[ch])):
        n_samples[ch] = INVALID_NCO
        return
    n = period_samples(code_phase[ch], dp, code_len)
    off = sample_ptr[ch] - buf_start
    if off < 0:
        n_samples[ch] = BEHIND_BUFFER
        return
    if off + n > n_buf:
        return
    cp_fix0, cstep, ph0, phstep = nco_fixed_point(code_phase[ch], pad, dp, carr_phase[ch], carr_freq[ch], fs)
    integrate_channel(buf, is_complex, off, n, code_ext[ch], cp_fix0, cstep, ph0, phstep,
                      tap_fix, COS_LUT, SIN_LUT, acc)
    scale = 1.0 / (sigma_arm[ch] * np.sqrt(n))
    # column of I and Q of tap t: taps 0..2 -> [I_P,I_E,I_L,Q_P,Q_E,Q_L]; 3,4 -> 6..9
    for t in range(n_taps):
        if t < 3:
            ci = t
            cq = 3 + t
        else:
            ci = 6 + (t - 3)
            cq = 8 + (t - 3)
        out[ch, ci] = acc[t] * scale
        out[ch, cq] = acc[n_taps + t] * scale
    # advance the NCOs exactly (float64); -1e-9-sample round-off is clamped to 0
    code_phase[ch] = max(code_phase[ch] + n * dp - code_len, 0.0)
    ph = carr_phase[ch] + n * (carr_freq[ch] / fs)
    carr_phase[ch] = ph - np.floor(ph)
    sample_ptr[ch] = sample_ptr[ch] + n
    n_samples[ch] = n


@njit(cache=True)
def step_bank(buf, is_complex, buf_start, n_buf, code_ext, pad, active, sample_ptr,
               code_phase, code_rate, carr_phase, carr_freq, fs, tap_off, sigma_arm,
               out, t_start, n_samples, code_len):
    """One code period for every active channel (see module docstring)."""
    tap_fix = tap_fixed_point(tap_off)
    acc = np.empty(2 * tap_fix.shape[0])
    for ch in range(code_phase.shape[0]):
        correlate_one(ch, buf, is_complex, buf_start, n_buf, code_ext, pad, active, sample_ptr,
                       code_phase, code_rate, carr_phase, carr_freq, fs, tap_fix, sigma_arm, out, t_start, n_samples,
                       code_len, acc)


@njit(cache=True)
def _run_epochs(buf, is_complex, buf_start, n_buf, code_ext, pad, active, sample_ptr,
                code_phase, code_rate, carr_phase, carr_freq, fs, tap_off, sigma_arm,
                max_epochs, out, t_start, n_samples, code_len):
    """Open-loop: repeat step_bank until no channel can complete another period."""
    n_ch = code_phase.shape[0]
    row = np.empty((n_ch, out.shape[2]))
    ts = np.empty(n_ch, dtype=np.int64)
    ns = np.empty(n_ch, dtype=np.int64)
    n_done = np.zeros(n_ch, dtype=np.int64)
    for e in range(max_epochs):
        step_bank(buf, is_complex, buf_start, n_buf, code_ext, pad, active, sample_ptr,
                   code_phase, code_rate, carr_phase, carr_freq, fs, tap_off, sigma_arm,
                   row, ts, ns, code_len)
        any_done = False
        for ch in range(n_ch):
            if ns[ch] > 0:
                k = n_done[ch]
                for c in range(out.shape[2]):
                    out[ch, k, c] = row[ch, c]
                t_start[ch, k] = ts[ch]
                n_samples[ch, k] = ns[ch]
                n_done[ch] = k + 1
                any_done = True
        if not any_done:
            break
    return n_done


class CorrelatorBank:
    """Batched E/P/L correlators for ``len(prns)`` channels (see module docstring).

    Parameters
    ----------
    prns : sequence of int
        PRN of each channel (1..32); channels start inactive until
        :meth:`init_channel` (or :meth:`add_channel`) sets their NCOs.
    fs_hz : float
        Sampling rate (> 0).
    if_hz : float
        Intermediate frequency (0 for complex baseband); ``carr_freq`` = IF + Doppler.
    is_complex : bool
        Complex (I,Q) input (complex64 buffers) or real (float32 buffers).
    spacing_chips : float
        Early-late spacing D, 0 < D < 2.
    vel_spacing_chips : float or None
        Very-early/very-late spacing D_v (0 < D_v < 4) or None for none.

    Public NCO state (float64/int64 arrays of length n_ch, writable in place):
    ``code_phase`` (chips at ``sample_ptr``), ``code_rate`` (chips/s),
    ``carr_phase`` (cycles), ``carr_freq`` (Hz, IF + Doppler), ``sample_ptr``
    (absolute sample index), ``active`` (bool).

    Kernel tables (read-only for callers): ``code_ext`` (n_ch, code length + 2*pad) float32 +-1 code of
    each channel with ``pad`` chips of wrap-around on both sides, ``tap_offsets_chips`` (code
    offsets of [P, E, L, (VE, VL)]).
    """

    def __init__(self, prns, fs_hz, if_hz, is_complex, spacing_chips=1.0, vel_spacing_chips=None, signal=GPS_L1CA):
        fs_hz = float(fs_hz)
        if not (math.isfinite(fs_hz) and fs_hz > 0.0):
            raise ConfigError(f"CorrelatorBank: fs_hz must be a positive sampling rate, got {fs_hz!r}")
        chip_rate = float(signal.chip_rate_hz)
        if fs_hz < chip_rate:
            raise ConfigError(f"CorrelatorBank: fs_hz = {fs_hz} Hz is below the {signal.name} chip rate; "
                              f"need fs_hz >= {chip_rate} Hz")
        if_hz = float(if_hz)
        if not math.isfinite(if_hz) or abs(if_hz) >= fs_hz:
            raise ConfigError(f"CorrelatorBank: if_hz must satisfy |if_hz| < fs_hz = {fs_hz}, got {if_hz!r}")
        spacing_chips = float(spacing_chips)
        if not (0.0 < spacing_chips < 2.0):
            raise ConfigError(f"CorrelatorBank: spacing_chips (early-late spacing) must be in (0, 2) chips, "
                              f"got {spacing_chips!r}")
        if vel_spacing_chips is not None:
            vel_spacing_chips = float(vel_spacing_chips)
            if not (0.0 < vel_spacing_chips < 4.0):
                raise ConfigError(f"CorrelatorBank: vel_spacing_chips must be in (0, 4) chips or None, "
                                  f"got {vel_spacing_chips!r}")
        prns = [int(p) for p in np.atleast_1d(np.asarray(prns))]
        if len(prns) == 0:
            raise ConfigError("CorrelatorBank: need at least one PRN")
        self.signal = signal
        self.code_len = float(signal.code_length)       # chips per code period (kernel argument)
        for p in prns:
            self._check_prn(p, "CorrelatorBank")
        self.fs_hz = fs_hz
        self.if_hz = if_hz
        self.is_complex = bool(is_complex)
        self.spacing_chips = spacing_chips
        self.vel_spacing_chips = vel_spacing_chips
        taps = [0.0, 0.5 * spacing_chips, -0.5 * spacing_chips]
        if vel_spacing_chips is not None:
            taps += [0.5 * vel_spacing_chips, -0.5 * vel_spacing_chips]
        self.tap_offsets_chips = np.array(taps)       # code offsets of [P, E, L, (VE, VL)]
        self.n_cols = 6 if vel_spacing_chips is None else 10
        self.pad = int(math.ceil(max(abs(t) for t in taps))) + 2
        n_ch = len(prns)
        self.prns = np.array(prns, dtype=np.int64)
        self.nco = NcoBank(n_ch, if_hz, chip_rate)
        self.sample_ptr = np.zeros(n_ch, dtype=np.int64)
        self.active = np.zeros(n_ch, dtype=np.bool_)
        self.code_ext = np.zeros((n_ch, signal.code_length + 2 * self.pad), dtype=np.float32)
        for ch, p in enumerate(prns):
            self._set_code(ch, p)

    # the NCO state (:class:`ultratight.signals.nco.NcoBank`), commanded by the tracking loops
    @property
    def code_phase(self):
        return self.nco.code_phase

    @code_phase.setter
    def code_phase(self, value):
        self.nco.code_phase[:] = value

    @property
    def code_rate(self):
        return self.nco.code_rate

    @code_rate.setter
    def code_rate(self, value):
        self.nco.code_rate[:] = value

    @property
    def carr_phase(self):
        return self.nco.carr_phase

    @carr_phase.setter
    def carr_phase(self, value):
        self.nco.carr_phase[:] = value

    @property
    def carr_freq(self):
        return self.nco.carr_freq

    @carr_freq.setter
    def carr_freq(self, value):
        self.nco.carr_freq[:] = value

    @property
    def n_ch(self):
        return self.prns.shape[0]

    def _check_prn(self, prn, where):
        if int(prn) not in self.signal.prns:
            raise ConfigError(f"{where}: PRN must be in {min(self.signal.prns)}..{max(self.signal.prns)}, got {prn}")

    def _set_code(self, ch, prn):
        L = self.signal.code_length
        code = np.asarray(self.signal.code(prn)).astype(np.float32)
        idx = (np.arange(L + 2 * self.pad) - self.pad) % L
        self.code_ext[ch] = code[idx]
        self.prns[ch] = prn

    def init_channel(self, ch, prn, code_phase_chips, doppler_hz, sample_index, carr_phase_cycles=0.0,
                     align=True):
        """(Re-)initialise channel ``ch`` from acquisition and activate it.

        ``code_phase_chips`` is the signal's code phase at absolute sample
        ``sample_index`` and ``doppler_hz`` its carrier Doppler; the code rate
        follows the Doppler.  With ``align`` the NCOs are advanced to the next
        code-period start (code phase 0) so that every integration spans a full
        period; otherwise the first integration is the remainder of the period.
        """
        self._check_prn(prn, "init_channel")
        if not 0 <= ch < self.n_ch:
            raise ConfigError(f"init_channel: channel index {ch} out of range 0..{self.n_ch - 1}")
        if int(prn) != self.prns[ch]:
            self._set_code(ch, int(prn))
        L = self.signal.code_length
        self.code_phase[ch] = float(code_phase_chips) % L
        self.code_rate[ch] = float(self.signal.code_rate_cps(float(doppler_hz)))
        if L - self.code_phase[ch] < 1e-9 * self.code_rate[ch] / self.fs_hz:
            self.code_phase[ch] = 0.0          # within round-off of a period start: it is the start
        self.carr_freq[ch] = self.if_hz + float(doppler_hz)
        self.carr_phase[ch] = float(carr_phase_cycles) % 1.0
        self.sample_ptr[ch] = int(sample_index)
        self.active[ch] = True
        if align and self.code_phase[ch] > 0.0:
            n = int(period_samples(self.code_phase[ch], self.code_rate[ch] / self.fs_hz, self.code_len))
            self.advance_to(ch, int(sample_index) + n)
            if L - self.code_phase[ch] < 1e-9:     # round-off just below the period start
                self.code_phase[ch] = 0.0

    def add_channel(self, prn, code_phase_chips, doppler_hz, sample_index, carr_phase_cycles=0.0, align=True):
        """Reuse an inactive channel (or append one) for ``prn``; returns its index."""
        free = np.flatnonzero(~self.active)
        if free.size:
            ch = int(free[0])
        else:
            ch = self.n_ch
            self._grow(1)
        self.init_channel(ch, prn, code_phase_chips, doppler_hz, sample_index, carr_phase_cycles, align)
        return ch

    def remove_channel(self, ch):
        """Deactivate channel ``ch`` (its row then reports n_samples = 0 and zeros)."""
        self.active[ch] = False

    def _grow(self, k):
        n_old = self.n_ch
        self.prns = np.concatenate([self.prns, np.full(k, 1, dtype=np.int64)])
        self.nco.grow(k, self.signal.chip_rate_hz)
        self.sample_ptr = np.concatenate([self.sample_ptr, np.zeros(k, dtype=np.int64)])
        self.active = np.concatenate([self.active, np.zeros(k, dtype=np.bool_)])
        self.code_ext = np.concatenate(
            [self.code_ext, np.zeros((k, self.code_ext.shape[1]), dtype=np.float32)])
        for ch in range(n_old, n_old + k):
            self._set_code(ch, 1)

    def advance_to(self, ch, sample_index):
        """Propagate channel ``ch``'s NCOs (open loop, current rates) to ``sample_index``."""
        dn = int(sample_index) - int(self.sample_ptr[ch])
        dt_chips = dn * self.code_rate[ch] / self.fs_hz
        self.code_phase[ch] = (self.code_phase[ch] + dt_chips) % self.signal.code_length
        ph = self.carr_phase[ch] + dn * self.carr_freq[ch] / self.fs_hz
        self.carr_phase[ch] = ph - math.floor(ph)
        self.sample_ptr[ch] = int(sample_index)

    def _prep(self, buf, noise_sigma_arm):
        if not isinstance(buf, np.ndarray):
            buf = np.asarray(buf)
        if self.is_complex:
            if buf.dtype != np.complex64 or not buf.flags.c_contiguous:
                if not np.iscomplexobj(buf):
                    raise ConfigError("CorrelatorBank.step: bank is for complex input but the buffer is real")
                buf = np.ascontiguousarray(buf, dtype=np.complex64)
            b = buf.view(np.float32)
        else:
            if buf.dtype != np.float32 or not buf.flags.c_contiguous:
                if np.iscomplexobj(buf):
                    raise ConfigError("CorrelatorBank.step: bank is for real input but the buffer is complex")
                buf = np.ascontiguousarray(buf, dtype=np.float32)
            b = buf
        if buf.ndim != 1:
            raise ConfigError(f"CorrelatorBank.step: buffer must be 1-D, got shape {buf.shape}")
        n_buf = buf.shape[0]
        if isinstance(noise_sigma_arm, (float, int, np.floating, np.integer)):
            sv = float(noise_sigma_arm)
            if not sv > 0.0:
                raise ConfigError(f"CorrelatorBank.step: noise_sigma_arm must be > 0, got {noise_sigma_arm!r}")
            sig = np.full(self.n_ch, sv)
        else:
            sig = np.broadcast_to(np.asarray(noise_sigma_arm, dtype=float), (self.n_ch,)).copy()
            if not np.all(sig > 0.0):
                raise ConfigError(f"CorrelatorBank.step: noise_sigma_arm must be > 0, got {noise_sigma_arm!r}")
        return b, n_buf, sig

    def step(self, buf, buf_start, noise_sigma_arm):
        """Integrate one code period per active channel.

        ``buf`` holds samples ``buf_start .. buf_start+len(buf)-1`` (complex64 or
        float32); ``noise_sigma_arm`` is a scalar or (n_ch,) array (see
        :func:`estimate_sigma_arm`).  Returns ``(out (n_ch, n_cols),
        t_start_samples (n_ch,), n_samples (n_ch,))``; ``n_samples`` is ``NOT_READY`` (0) for a
        channel not ready (period not complete in the buffer, or inactive), ``BEHIND_BUFFER`` (-1)
        for a channel whose ``sample_ptr`` precedes ``buf_start`` and ``INVALID_NCO`` (-2) for an
        invalid NCO state (code_rate <= 0, non-finite phase/frequency).
        """
        b, n_buf, sig = self._prep(buf, noise_sigma_arm)
        out = np.zeros((self.n_ch, self.n_cols))
        t_start = np.zeros(self.n_ch, dtype=np.int64)
        n_samples = np.zeros(self.n_ch, dtype=np.int64)
        step_bank(b, self.is_complex, int(buf_start), n_buf, self.code_ext, self.pad, self.active,
                   self.sample_ptr, self.code_phase, self.code_rate, self.carr_phase, self.carr_freq,
                   self.fs_hz, self.tap_offsets_chips, sig, out, t_start, n_samples, self.code_len)
        return out, t_start, n_samples

    def run_epochs(self, buf, buf_start, noise_sigma_arm, max_epochs=None):
        """Open-loop convenience: integrate as many whole periods as the buffer holds.

        NCO rates are not changed between epochs.  Returns ``(out (n_ch, E,
        n_cols), t_start (n_ch, E), n_samples (n_ch, E), n_done (n_ch,))`` where
        only the first ``n_done[ch]`` epochs of each row are filled.
        """
        b, n_buf, sig = self._prep(buf, noise_sigma_arm)
        if max_epochs is None:
            max_epochs = int(n_buf * self.signal.chip_rate_hz * 1.01 / (self.fs_hz * self.signal.code_length)) + 2
        out = np.zeros((self.n_ch, max_epochs, self.n_cols))
        t_start = np.zeros((self.n_ch, max_epochs), dtype=np.int64)
        n_samples = np.zeros((self.n_ch, max_epochs), dtype=np.int64)
        n_done = _run_epochs(b, self.is_complex, int(buf_start), n_buf, self.code_ext, self.pad,
                             self.active, self.sample_ptr, self.code_phase, self.code_rate, self.carr_phase,
                             self.carr_freq, self.fs_hz, self.tap_offsets_chips, sig, int(max_epochs),
                             out, t_start, n_samples, self.code_len)
        return out, t_start, n_samples, n_done
