"""Signal synthesis of the GPS L1 C/A IF generator: the signal model, the :class:`SignalPlan` that
turns geometry into per-interval polynomial coefficients and data bits, and the numba kernels that
add the satellites' signals to a block of samples (batched over satellites; the generation driver,
noise, front end and files are in :mod:`ultratight.signals.synth.generator`).

Signal model (receiver sample ``n``, receiver-clock time ``T_n = tow0 + n/fs``)::

    complex:  x_n = sum_k a_k D_k c_k(chi_k(n)) exp(j 2 pi (f_IF n/fs + phi_k(n))) + w_n
    real:     x_n = sum_k a_k D_k c_k(chi_k(n)) cos(2 pi (f_IF n/fs + phi_k(n)))   + w_n

``chi_k`` (C/A code phase, chips) and ``phi_k`` (carrier phase, cycles, = -pseudorange/lambda,
i.e. relative to a nominal L1 oscillator driven by the receiver clock) come from
:func:`ultratight.signals.geometry.light_time` for the signal arriving when the receiver
clock reads ``T_n``. ``w`` is white Gaussian noise of std ``sigma = 1`` per real component
(times the noise-event factor; drawn by the generator), ``a_k`` from
:func:`ultratight.signals.corr_model.signal_amplitude` for the satellite's C/N0, ``D_k`` the LNAV
bit (:func:`ultratight.signals.lnav.nav_bits`) of the C/A epoch being received (bits align with
the satellite-clock transmit time). Spectral inversion writes ``conj`` (complex) or
``cos(2 pi f_IF t - phi)`` (real) and marks the sidecar ``inversion: true``;
:func:`ultratight.signals.recording.iffile.open_if` undoes it.

Geometry: the light-time solution is evaluated per satellite at the start and the middle of
every interval of ``L = round(fs * 1 ms)`` samples (plus the final end point); inside an
interval the code phase and carrier phase are the quadratic through those three nodes,
evaluated per sample. For the paper's 20 g / 40 g/s flight the interpolation error is far
below 1 mm (tests/test_generator.py checks it against direct light-time solutions).

Receiver clock: bias ``b(e) = clock_bias_m + clock_drift_mps * e`` (e = receiver-clock seconds
since the start); the true reception time of sample ``n`` is ``T_n - b/c`` and the trajectory
time is ``e - (b(e) - b(0))/c``.

Atmosphere (scenario table ``[atmosphere]``, opt-in; :mod:`ultratight.signals.atmosphere`): the
code is delayed by ``I + T`` and the carrier phase advanced by ``I`` and delayed by ``T``
(``I``: Klobuchar ionosphere times ``iono_scale``, ``T``: Saastamoinen troposphere with the
named mapping function), evaluated at the true receive time with the receiver's geodetic
position and the satellite's elevation/azimuth: ``pseudorange += I + T``,
``t_tx_tow -= (I + T)/c`` (code phase and data bits follow), ``carrier_phase_cycles -= (T - I)/lambda``
and the truth Doppler gets ``-d(T - I)/dt / lambda``.  The truth file records ``iono_m`` and
``tropo_m`` (zeros without ``[atmosphere]``); with ``broadcast = true`` the coefficients are sent
in subframe 4 page 18 of every satellite's LNAV.
"""

import numpy as np
from numba import njit, prange

from ultratight.constants import C, CA_LEN, F_CA, LAMBDA_L1, T_CA
from ultratight.signals.ca_code import ca_code
from ultratight.signals.corr_model import signal_amplitude
from ultratight.ins.earth import ecef_to_llh_batch, enu_frames
from ultratight.signals.ephemeris import eph_params
from ultratight.signals.geometry import light_time_many

LUT_BITS = 11
LUT_N = 1 << LUT_BITS
_LUT_ANG = 2.0 * np.pi * np.arange(LUT_N) / LUT_N
COS_LUT = np.cos(_LUT_ANG).astype(np.float32)
SIN_LUT = np.sin(_LUT_ANG).astype(np.float32)
PHASE_OFFSET = float(1 << 20)     # keeps the per-sample carrier phase positive (see kernels)
INTERVAL_S = 1e-3                 # geometry node spacing (one C/A period)
N_EXT = 3 * CA_LEN                # extended code table length (an interval spans <= 3 code periods)

# coefficient columns: code c0, c1, c2 (chips; chips/sample; chips/sample^2), carrier p0, p1, p2
C0, C1, C2, P0, P1, P2 = range(6)


# ------------------------------------------------------------------------------------------
# numba kernels
# ------------------------------------------------------------------------------------------
@njit(cache=True, fastmath=True, nogil=True, inline="always")
def _interval_indices(cis, lis, L, c0, c1, c2, p0, p1, p2, mask):
    """Per sample of one interval of one satellite: the extended code table's index ``cis`` (the code
    phase ``u = c0 + (c1 + c2 i) i`` truncated, never negative, clamped to the table) and the carrier
    table's ``lis`` (``p0 + (p1 + p2 i) i`` in table steps, rounded, wrapped by ``mask``). Arithmetic
    only, so the loop runs in vector lanes."""
    for i in range(L):
        fi = float(i)
        u = c0 + (c1 + c2 * fi) * fi
        cis[i] = np.int32(min(int(u), N_EXT - 1))
        lis[i] = np.int32(int(p0 + (p1 + p2 * fi) * fi + 0.5) & mask)


@njit(cache=True, fastmath=True, nogil=True, inline="always")
def _signed_code(gc, codes, s, d0, d1, d2):
    """The satellite's extended code table times the amplitude and data bit of each of the three code
    periods an interval can span (``d0``, ``d1``, ``d2``)."""
    us = np.uint64(s)
    for q in range(CA_LEN):
        gc[q] = d0 * codes[us, np.uint64(q)]
        gc[q + CA_LEN] = d1 * codes[us, np.uint64(q + CA_LEN)]
        gc[q + 2 * CA_LEN] = d2 * codes[us, np.uint64(q + 2 * CA_LEN)]


@njit(cache=True, fastmath=True, parallel=True, nogil=True)
def _synth_complex(out, L, n_int, codes, coefs, amps, bits, cos_lut, sin_lut):
    """Add the satellites' signals to ``out`` (float32 (n_int*L, 2): I, Q). Per interval and satellite
    the table indices of every sample are computed first (:func:`_interval_indices`, vector lanes),
    then the look-ups and sums run over them (the same operations per sample, in the same order, as
    one loop doing both: the samples are the same to the bit, in about two thirds of the time). Indices
    are unsigned, so numba leaves out the negative-index wraparound of every look-up."""
    nsat = codes.shape[0]
    lutn = cos_lut.shape[0]
    mask = lutn - 1
    flut = float(lutn)
    zero = np.uint64(0)
    one = np.uint64(1)
    for k in prange(n_int):          # intervals are independent: spread over numba's threads
        base = k * L
        cis = np.empty(L, np.int32)
        lis = np.empty(L, np.int32)
        gc = np.empty(N_EXT, np.float32)
        for s in range(nsat):
            a = amps[k, s]
            if a == 0.0:
                continue
            _interval_indices(cis, lis, L, coefs[k, s, 0], coefs[k, s, 1], coefs[k, s, 2], coefs[k, s, 3] * flut,
                              coefs[k, s, 4] * flut, coefs[k, s, 5] * flut, mask)
            _signed_code(gc, codes, s, a * bits[k, s, 0], a * bits[k, s, 1], a * bits[k, s, 2])
            for i in range(L):
                v = gc[np.uint32(cis[i])]
                li = np.uint32(lis[i])
                j = np.uint64(base + i)
                out[j, zero] += v * cos_lut[li]
                out[j, one] += v * sin_lut[li]


@njit(cache=True, fastmath=True, parallel=True, nogil=True)
def _synth_real(out, L, n_int, codes, coefs, amps, bits, cos_lut):
    """Add the satellites' signals to ``out`` (float32 (n_int*L,)); as :func:`_synth_complex`."""
    nsat = codes.shape[0]
    lutn = cos_lut.shape[0]
    mask = lutn - 1
    flut = float(lutn)
    for k in prange(n_int):          # intervals are independent: spread over numba's threads
        base = k * L
        cis = np.empty(L, np.int32)
        lis = np.empty(L, np.int32)
        gc = np.empty(N_EXT, np.float32)
        for s in range(nsat):
            a = amps[k, s]
            if a == 0.0:
                continue
            _interval_indices(cis, lis, L, coefs[k, s, 0], coefs[k, s, 1], coefs[k, s, 2], coefs[k, s, 3] * flut,
                              coefs[k, s, 4] * flut, coefs[k, s, 5] * flut, mask)
            _signed_code(gc, codes, s, a * bits[k, s, 0], a * bits[k, s, 1], a * bits[k, s, 2])
            for i in range(L):
                out[np.uint64(base + i)] += gc[np.uint32(cis[i])] * cos_lut[np.uint32(lis[i])]


# ------------------------------------------------------------------------------------------
# geometry -> per-interval polynomial coefficients
# ------------------------------------------------------------------------------------------
class SignalPlan:
    """Everything fixed for a run: time base, satellites, trajectory, clock.

    ``ephs``: list of Ephemeris (one per satellite); ``cn0_dbhz``: (nsat,) array.
    """

    def __init__(self, ephs, cn0_dbhz, traj, week, tow0, fs_hz, if_hz, is_complex, inversion=False,
                 clock_bias_m=0.0, clock_drift_mps=0.0, n_samples=None, atmosphere=None, iono_broadcast=None):
        self.ephs = list(ephs)
        self._params = [eph_params(e) for e in self.ephs]
        self.prns = np.array([e.prn for e in self.ephs], dtype=np.int64)
        self.cn0_dbhz = np.broadcast_to(np.asarray(cn0_dbhz, dtype=float), (len(self.ephs),)).copy()
        self.traj = traj
        self.week = int(week)
        self.tow0 = float(tow0)
        self.fs = float(fs_hz)
        self.if_hz = float(if_hz)
        self.is_complex = bool(is_complex)
        self.inversion = bool(inversion)
        self.b0 = float(clock_bias_m)
        self.drift = float(clock_drift_mps)
        self.L = max(1, int(round(self.fs * INTERVAL_S)))
        self.n_samples = n_samples
        self.codes = np.stack([np.tile(ca_code(int(p)).astype(np.float32), 3) for p in self.prns]) \
            if len(self.prns) else np.zeros((0, N_EXT), np.float32)
        self.amp = signal_amplitude(self.cn0_dbhz, self.fs, 1.0, self.is_complex).astype(np.float32)
        self.bits = {}          # prn -> (first_bit_index (ms//20), int8 array); none held: all +1
        self.atmosphere = atmosphere if atmosphere is not None and atmosphere.active else None
        self.iono_broadcast = iono_broadcast     # lnav_message.IonoUtc sent in subframe 4 page 18 (or None)

    # --- time base
    def clock_bias_m(self, e):
        return self.b0 + self.drift * e

    def geometry(self, sample_pos):
        """light_time per satellite at (fractional) sample positions; list of dicts + rx dict."""

        e = np.asarray(sample_pos, dtype=float) / self.fs
        b = self.clock_bias_m(e)
        tau_traj = e - (b - self.b0) / C
        pos, vel = self.traj.pos_vel_e(np.maximum(tau_traj, 0.0))
        t_true = self.tow0 + e - b / C
        frames = enu_frames(pos)
        out = light_time_many(self._params, pos, vel, t_true, b, self.drift, frames)
        if self.atmosphere is not None:
            self._apply_atmosphere(out, pos, t_true, e)
        return out, {"pos_e": pos, "vel_e": vel, "clk_bias_m": b, "t_true": t_true, "e": e}

    def _apply_atmosphere(self, geo, pos, t_true, e):
        """Add the ionospheric and tropospheric delays to the light-time solutions (module doc)."""

        pos = np.asarray(pos, dtype=np.float64)
        llh = ecef_to_llh_batch(np.ascontiguousarray(pos.reshape(-1, 3))).reshape(pos.shape)
        lat, lon, h = llh[..., 0], llh[..., 1], llh[..., 2]
        for g in geo:
            iono, tropo = self.atmosphere.delays_m(lat, lon, h, g["elev_rad"], g["azim_rad"], t_true)
            d_code = iono + tropo
            d_carr = tropo - iono
            g["iono_m"] = iono
            g["tropo_m"] = tropo
            g["pseudorange_m"] = g["pseudorange_m"] + d_code
            g["t_tx_tow"] = g["t_tx_tow"] - d_code / C
            g["code_phase_chips"] = np.mod(g["t_tx_tow"] * F_CA, float(CA_LEN))
            g["carrier_phase_cycles"] = g["carrier_phase_cycles"] - d_carr / LAMBDA_L1
            if e.size >= 2:
                g["doppler_hz"] = g["doppler_hz"] - np.gradient(d_carr, e) / LAMBDA_L1

    def coefficients(self, j0, n_int):
        """Per-interval coefficients for intervals j0..j0+n_int-1.

        Returns coefs (n_int, nsat, 6), epoch0 (n_int, nsat) int64 (C/A epoch count, ms of week
        of the sat-clock transmit time, of the code period under way at the interval start),
        and the geometry at the interval starts (list of dicts, rx dict) for the truth.
        """
        L = self.L
        pos = (j0 * L + 0.5 * L * np.arange(2 * n_int + 1))
        geo, rx = self.geometry(pos)
        nsat = len(self.ephs)
        coefs = np.zeros((n_int, nsat, 6))
        epoch0 = np.zeros((n_int, nsat), dtype=np.int64)
        sgn = -1.0 if self.inversion else 1.0
        n_start = (j0 + np.arange(n_int)) * L
        # IF phase at interval start (cycles, mod 1), exact for integer rates
        if_frac = np.mod(np.mod(self.if_hz * n_start.astype(np.float64), self.fs) / self.fs, 1.0)
        if_rate = self.if_hz / self.fs
        for s, g in enumerate(geo):
            cp = g["code_phase_chips"]
            y0, ym, y1 = cp[0:-1:2], cp[1::2], cp[2::2]
            dm = np.mod(ym - y0, CA_LEN)
            d1 = dm + np.mod(y1 - ym, CA_LEN)
            cq = 2.0 * (d1 - 2.0 * dm) / (L * L)
            coefs[:, s, C0] = y0
            coefs[:, s, C2] = cq
            coefs[:, s, C1] = d1 / L - cq * L
            ph = g["carrier_phase_cycles"]
            f0, fm, f1 = ph[0:-1:2], ph[1::2], ph[2::2]
            pm = sgn * (fm - f0)
            p1 = sgn * (f1 - f0)
            pq = 2.0 * (p1 - 2.0 * pm) / (L * L)
            # complex inverted: conj of the whole signal (IF included); real inverted: cos(IF t - phi)
            if_sgn = -1.0 if (self.is_complex and self.inversion) else 1.0
            coefs[:, s, P0] = np.mod(sgn * f0 + if_sgn * if_frac, 1.0)
            coefs[:, s, P1] = p1 / L - pq * L + if_sgn * if_rate
            coefs[:, s, P2] = pq
            coefs[:, s, P0] += PHASE_OFFSET
            t_tx = g["t_tx_tow"][0:-1:2]
            epoch0[:, s] = np.rint((t_tx - y0 / F_CA) / T_CA).astype(np.int64)
        starts = [{k: (v[0:-1:2] if v.ndim == 1 else v[0:-1:2, :]) for k, v in g.items()} for g in geo]
        rx0 = {k: v[0:-1:2] for k, v in rx.items()}
        return coefs, epoch0, starts, rx0

    # --- navigation data (the bits themselves: ultratight.signals.synth.generator.set_nav_bits)
    def sent_bits(self):
        """(first bit index of week ``self.week``, (nsat, n_bits) int8 ±1) of the bits sent, or None."""
        if not self.bits:
            return None
        first = next(iter(self.bits.values()))[0]
        return first, np.stack([self.bits[int(p)][1] for p in self.prns])

    def bit_values(self, epoch0):
        """(n_int, nsat, 3) float32 data bits of epochs epoch0, +1, +2."""
        n_int, nsat = epoch0.shape
        out = np.ones((n_int, nsat, 3), dtype=np.float32)
        for s, prn in enumerate(self.prns):
            entry = self.bits.get(int(prn))
            if entry is None:
                continue
            first, b = entry
            idx = (epoch0[:, s, None] + _NEXT3) // 20 - first
            np.clip(idx, 0, len(b) - 1, out=idx)
            out[:, s, :] = b[idx]
        return out


_NEXT3 = np.arange(3, dtype=np.int64)     # bit_values: epochs epoch0, +1, +2


def eval_poly(coefs, i):
    """Evaluate code (chips) and carrier (cycles, offset removed) polynomials at sample offsets i."""
    i = np.asarray(i, dtype=float)
    code = coefs[..., C0] + (coefs[..., C1] + coefs[..., C2] * i) * i
    carr = (coefs[..., P0] - PHASE_OFFSET) + (coefs[..., P1] + coefs[..., P2] * i) * i
    return code, carr

