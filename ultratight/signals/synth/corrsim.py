"""Correlator-level simulator: true signal dynamics vs a closed-loop NCO -> the outputs of eq. 3
of Zhao et al. 2014 (see docs/references.md).

Instead of sampling an IF signal, each 1 ms epoch produces the six normalised
correlator outputs ``[I_P, I_E, I_L, Q_P, Q_E, Q_L]`` (units of
ultratight.signals.corr_model: unit noise per arm, prompt amplitude
A = sqrt(2 C/N0 T)) directly from the true signal and the NCO state:

    z = A D mean_t[ R(e(t) + d_x) exp(j psi(t)) ] + s_k n_k,    n_k ~ N(0, epl_noise_covariance)

where psi(t) = 2 pi (theta_true(t) - theta_nco(t)) (carrier, cubic in t within an
epoch: true phase with constant jerk per epoch vs a constant-frequency NCO),
e(t) = p_true(t) - p_nco(t) (code, chips), and the mean over the interval is an
8-node Gauss-Legendre quadrature (exact to ~1e-10 for these smooth phases).
This is the physics the correlator bank computes, written independently of the
prefilter's eq. 3 code (which assumes constant df over the interval).  s_k is
the noise factor (``noise_events``: std x factor over a window, the paper's
"measurement noise x20"); C/N0 may vary per epoch and channel.  The receiver is
complex baseband (IF = 0): NCO frequencies are Dopplers.

Truth dynamics (per channel, line of sight, in Hz of L1 Doppler): piecewise
segments ``(t0, acc_hzps, jerk_hzps2)`` like the scenario trajectory (at the
start of a segment the Doppler rate is ``acc`` and it changes with constant
``jerk`` during the segment), scaled per channel by ``los_scale``, plus an
optional receiver-clock random walk (phase ``q_phi`` rad^2/s, frequency
``q_f`` rad^2/s^3) drawn from the Generator.  The code phase is carrier
coherent: p = p0 + F_CA t + (F_CA/F_L1) (theta(t) - theta(0)).

Outer-loop aiding (optional): the Doppler prediction for the middle of each
interval is the true (dynamics-only) Doppler plus an error
``bias_hz + scale_err * (f(t) - f(0))`` per channel — an outer loop that knows
the dynamics up to a scale error (a slightly wrong SINS) and an offset — taken
``aid_delay_s`` late (the outer loop's latency, e.g. the CIC interpolator's
group delay), which turns every jerk of the truth into a residual acceleration
step J * delay for the inner loop (a dynamics mismatch).

The simulator needs only the correlator model (:mod:`ultratight.signals.corr_model`) and the
signal constants; :func:`ultratight.fusion.channel.loopsim.run_closed_loop` drives a prefilter bank and
the inner-loop law (:class:`ultratight.fusion.channel.innerloop.InnerLoop`) against it, logging true vs
estimated Doppler and code phase.  It serves the tests and benchmarks of the prefilters; the
receiver itself does not use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from ultratight.constants import CA_LEN, CODE_PER_BIT, F_CA, F_L1, T_CA
from ultratight.errors import ConfigError
from ultratight.signals import corr_model
from ultratight.signals.nco import NcoBank

_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)
GL_NODES = 0.5 * (_GL_X + 1.0)        # on [0, 1]
GL_WEIGHTS = 0.5 * _GL_W              # sum to 1
TWO_PI = 2.0 * math.pi


class SimNco(NcoBank):
    """The simulator's NCOs (complex baseband: IF = 0, carr_freq = Doppler)."""

    def __init__(self, n_ch):
        super().__init__(n_ch, 0.0, F_CA)


@dataclass
class SimScenario:
    """Parameters of a correlator-level run (see module docstring)."""
    duration_s: float = 10.0
    n_ch: int = 1
    T: float = T_CA
    spacing_chips: float = 1.0
    cn0_dbhz: float = 20.0
    f0_hz: np.ndarray | float = 1000.0                 # initial Doppler per channel
    segments: list = field(default_factory=lambda: [(0.0, 0.0, 0.0)])  # (t0, acc_hzps, jerk_hzps2)
    los_scale: np.ndarray | float = 1.0                # per-channel factor on the segment dynamics
    noise_events: list = field(default_factory=list)   # (t0_s, t1_s, factor)
    cn0_events: list = field(default_factory=list)     # (t0_s, t1_s, cn0_dbhz)
    q_phi_clk: float = 0.0                             # rad^2/s
    q_f_clk: float = 0.0                               # rad^2/s^3
    aid_bias_hz: np.ndarray | float = 0.0
    aid_scale_err: np.ndarray | float = 0.0
    aid_delay_s: float = 0.0                           # outer-loop latency (e.g. the CIC group delay)
    data_bits: bool = True

    def n_epochs(self):
        return int(round(self.duration_s / self.T))


@dataclass
class Truth:
    t: np.ndarray          # (N+1,) epoch boundaries, s
    theta: np.ndarray      # (N+1, n_ch) true carrier phase, cycles (incl. clock)
    freq: np.ndarray       # (N+1, n_ch) true Doppler, Hz (incl. clock)
    acc: np.ndarray        # (N+1, n_ch) Hz/s (dynamics)
    jerk: np.ndarray       # (N, n_ch) Hz/s^2, constant within each epoch
    freq_dyn: np.ndarray   # (N+1, n_ch) Doppler from the dynamics only (what an outer loop may know)
    amp: np.ndarray        # (N, n_ch) prompt amplitude A per epoch
    noise_factor: np.ndarray  # (N, n_ch)
    bits: np.ndarray       # (N, n_ch) +-1
    aid_hz: np.ndarray     # (N, n_ch) outer-loop Doppler prediction for the middle of each interval
    freq_mid: np.ndarray   # (N, n_ch) true mean Doppler over each interval


def _per_ch(v, n, name):
    a = np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy()
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"corrsim: {name} must be finite")
    return a


def make_truth(sc: SimScenario, rng: np.random.Generator) -> Truth:
    """Tabulate the true dynamics, amplitudes, noise factors, bits and aiding of a scenario."""
    N = sc.n_epochs()
    if N < 1:
        raise ConfigError(f"corrsim: duration_s={sc.duration_s} shorter than one epoch")
    n = int(sc.n_ch)
    T = float(sc.T)
    t = np.arange(N + 1) * T
    tm = t[:-1] + 0.5 * T
    scale = _per_ch(sc.los_scale, n, "los_scale")
    f0 = _per_ch(sc.f0_hz, n, "f0_hz")
    acc, freq, theta, jerk1 = _segment_dynamics(sc.segments, tm, N, T)
    freq_dyn = f0[None, :] + freq[:, None] * scale[None, :]
    theta_dyn = f0[None, :] * t[:, None] + theta[:, None] * scale[None, :]
    acc_c = acc[:, None] * scale[None, :]
    jerk_c = jerk1[:, None] * scale[None, :]
    clk_f, clk_th = _clock_walk(sc, rng, N, T)
    theta_true = theta_dyn + clk_th[:, None]
    freq_true = freq_dyn + clk_f[:, None]
    freq_mid = (theta_true[1:] - theta_true[:-1]) / T
    amp, nf = _amplitude_and_noise(sc, tm, N, n, T)
    if sc.data_bits:
        nb = N // CODE_PER_BIT + 1
        b = rng.choice(np.array([-1.0, 1.0]), size=(nb, n))
        bits = np.repeat(b, CODE_PER_BIT, axis=0)[:N]
    else:
        bits = np.ones((N, n))
    aid = _aiding(sc, theta_dyn, tm, f0, n, T)
    return Truth(t=t, theta=theta_true, freq=freq_true, acc=acc_c, jerk=jerk_c, freq_dyn=freq_dyn,
                 amp=amp, noise_factor=nf, bits=bits, aid_hz=aid, freq_mid=freq_mid)


def _segment_dynamics(segments, tm, N, T):
    """Line-of-sight dynamics of the ``(t0, acc_hzps, jerk_hzps2)`` segments at the N + 1 epoch
    boundaries, before the per-channel scale: acceleration (Hz/s), Doppler (Hz) and phase (cycles)
    from 0, and the jerk (Hz/s^2) of each epoch (that of the segment holding its middle ``tm``)."""
    segs = sorted(segments, key=lambda s: s[0])
    # per-epoch jerk and acceleration at segment starts
    seg_idx = np.searchsorted([s[0] for s in segs], tm, side="right") - 1
    seg_idx = np.maximum(seg_idx, 0)
    jerk1 = np.array([segs[i][2] for i in seg_idx])
    acc = np.empty(N + 1)
    acc[0] = segs[seg_idx[0]][1]
    freq = np.empty(N + 1)
    theta = np.empty(N + 1)
    freq[0] = 0.0
    theta[0] = 0.0
    # exact piecewise-polynomial integration (acceleration reset at each segment start)
    a = acc[0]
    f = 0.0
    th = 0.0
    for k in range(N):
        if k > 0 and seg_idx[k] != seg_idx[k - 1]:
            a = segs[seg_idx[k]][1]
            acc[k] = a
        j = jerk1[k]
        th += f * T + a * T * T / 2 + j * T ** 3 / 6
        f += a * T + j * T * T / 2
        a += j * T
        acc[k + 1] = a
        freq[k + 1] = f
        theta[k + 1] = th
    return acc, freq, theta, jerk1


def _clock_walk(sc, rng, N, T):
    """Receiver-clock frequency (Hz) and phase (cycles) at the N + 1 epoch boundaries, common to all
    channels: the random walk of ``q_f_clk``, ``q_phi_clk`` drawn from ``rng`` (zeros without)."""
    clk_f = np.zeros(N + 1)
    clk_th = np.zeros(N + 1)
    if sc.q_f_clk > 0 or sc.q_phi_clk > 0:
        wf = rng.standard_normal(N) * math.sqrt(sc.q_f_clk * T) / TWO_PI
        wp = rng.standard_normal(N) * math.sqrt(sc.q_phi_clk * T) / TWO_PI
        clk_f[1:] = np.cumsum(wf)
        clk_th[1:] = np.cumsum(clk_f[:-1] * T + wp)
    return clk_f, clk_th


def _amplitude_and_noise(sc, tm, N, n, T):
    """(N, n) prompt amplitudes (C/N0 with its events) and noise factors of the epochs (middles ``tm``)."""
    cn0 = np.full((N, n), float(sc.cn0_dbhz))
    for (a0, a1, v) in sc.cn0_events:
        cn0[(tm >= a0) & (tm < a1)] = v
    nf = np.ones((N, n))
    for (a0, a1, v) in sc.noise_events:
        if not v > 0:
            raise ConfigError(f"corrsim: noise factor {v!r} must be > 0")
        nf[(tm >= a0) & (tm < a1)] = v
    return corr_model.amplitude_from_cn0(cn0, T), nf


def _aiding(sc, theta_dyn, tm, f0, n, T):
    """(N, n) outer-loop Doppler prediction for the middle of each interval (module docstring)."""
    bias = _per_ch(sc.aid_bias_hz, n, "aid_bias_hz")
    serr = _per_ch(sc.aid_scale_err, n, "aid_scale_err")
    fdyn_mid = (theta_dyn[1:] - theta_dyn[:-1]) / T
    if sc.aid_delay_s:
        if not sc.aid_delay_s > 0:
            raise ConfigError(f"corrsim: aid_delay_s={sc.aid_delay_s!r} must be >= 0")
        # the outer loop reports the Doppler of aid_delay_s ago (linear interpolation)
        td = np.maximum(tm - sc.aid_delay_s, tm[0])
        fdyn_mid = np.stack([np.interp(td, tm, fdyn_mid[:, c]) for c in range(n)], axis=1)
    return fdyn_mid + bias[None, :] + serr[None, :] * (fdyn_mid - f0[None, :])


@njit(cache=True)
def _epoch_outputs(theta0, f0, a0, j, p_true0, theta_n0, f_n, p_n0, r_n, amp, D, T, dhalf,
                   nodes, weights, f_ca_over_l1, f_ca, noise, out, err):
    """Noise-free eq.-3 physics by quadrature + given noise; err[:, 0:3] = dtau0, dphi0, df_mean."""
    n = theta0.shape[0]
    for c in range(n):
        # carrier phase difference at the start (cycles, reduced)
        d0 = theta0[c] - theta_n0[c]
        d0 = d0 - math.floor(d0 + 0.5)
        sp = 0.0
        se = 0.0
        sl = 0.0
        cp = 0.0
        ce = 0.0
        cl = 0.0
        for q in range(nodes.shape[0]):
            tq = nodes[q] * T
            dth_true = f0[c] * tq + 0.5 * a0[c] * tq * tq + j[c] * tq * tq * tq / 6.0
            psi = 2.0 * math.pi * (d0 + dth_true - f_n[c] * tq)
            e = (p_true0[c] + f_ca * tq + f_ca_over_l1 * dth_true) - (p_n0[c] + r_n[c] * tq)
            w = weights[q]
            cs = math.cos(psi) * w
            sn = math.sin(psi) * w
            ap = abs(e)
            rp = 1.0 - ap if ap < 1.0 else 0.0
            ae = abs(e - dhalf)
            re = 1.0 - ae if ae < 1.0 else 0.0
            al = abs(e + dhalf)
            rl = 1.0 - al if al < 1.0 else 0.0
            cp += rp * cs
            ce += re * cs
            cl += rl * cs
            sp += rp * sn
            se += re * sn
            sl += rl * sn
        g = amp[c] * D[c]
        out[c, 0] = g * cp + noise[c, 0]
        out[c, 1] = g * ce + noise[c, 1]
        out[c, 2] = g * cl + noise[c, 2]
        out[c, 3] = g * sp + noise[c, 3]
        out[c, 4] = g * se + noise[c, 4]
        out[c, 5] = g * sl + noise[c, 5]
        err[c, 0] = p_true0[c] - p_n0[c]
        err[c, 1] = 2.0 * math.pi * d0
        dth_T = f0[c] * T + 0.5 * a0[c] * T * T + j[c] * T * T * T / 6.0
        err[c, 2] = 2.0 * math.pi * (dth_T / T - f_n[c])


class CorrSim:
    """Epoch-by-epoch correlator-level simulator for a closed loop.

    ``nco`` (SimNco) is the loop's NCO; :meth:`outputs` returns z for the current
    epoch k and advances the NCO over the interval (as the correlator does);
    :meth:`advance` moves the truth to the next epoch.
    """

    def __init__(self, sc: SimScenario, rng: np.random.Generator, truth: Truth | None = None,
                 code_phase0_chips=0.0):
        self.sc = sc
        self.rng = rng
        self.truth = truth if truth is not None else make_truth(sc, rng)
        self.n = int(sc.n_ch)
        self.N = self.truth.jerk.shape[0]
        self.T = float(sc.T)
        self.k = 0
        self.dhalf = float(corr_model.tap_offsets(sc.spacing_chips)[2])
        self.L = np.linalg.cholesky(corr_model.epl_noise_covariance(sc.spacing_chips))
        self.nco = SimNco(self.n)
        self.p_true = _per_ch(code_phase0_chips, self.n, "code_phase0_chips")
        self.theta_n_unwrapped = np.zeros(self.n)
        self._z = np.zeros((self.n, 6))
        self.err = np.zeros((self.n, 3))
        self._chunk = None
        self._chunk_k0 = 0
        self._CH = 2000

    def init_nco(self, code_err_chips=0.0, phase_err_rad=0.0, freq_err_hz=0.0):
        """Start the NCO at truth minus the given errors (true - NCO convention)."""
        tr = self.truth
        k = self.k
        self.nco.code_phase[:] = self.p_true - _per_ch(code_err_chips, self.n, "code_err_chips")
        ph = tr.theta[k] - _per_ch(phase_err_rad, self.n, "phase_err_rad") / TWO_PI
        self.nco.carr_phase[:] = ph - np.floor(ph)
        self.nco.carr_freq[:] = tr.freq_mid[k] - _per_ch(freq_err_hz, self.n, "freq_err_hz")
        self.nco.code_rate[:] = F_CA * (1.0 + self.nco.carr_freq / F_L1)

    def _noise(self, k):
        if self._chunk is None or k >= self._chunk_k0 + self._chunk.shape[0] or k < self._chunk_k0:
            m = min(self._CH, self.N - k)
            w = self.rng.standard_normal((m, self.n, 6))
            self._chunk = w @ self.L.T
            self._chunk_k0 = k
        return self._chunk[k - self._chunk_k0]

    def outputs(self):
        """z (n_ch, 6) for epoch k; also fills ``err`` = [dtau0, dphi0, df_mean] (true - NCO).

        Like the correlator bank, the NCO is then advanced to the end of the interval
        (its arrays describe the start of the next interval, where the inner loop acts).
        """
        k = self.k
        tr = self.truth
        noise = self._noise(k) * tr.noise_factor[k][:, None]
        nco = self.nco
        _epoch_outputs(tr.theta[k], tr.freq[k], tr.acc[k], tr.jerk[k], self.p_true,
                       nco.carr_phase, nco.carr_freq, nco.code_phase, nco.code_rate,
                       tr.amp[k], tr.bits[k], self.T, self.dhalf, GL_NODES, GL_WEIGHTS,
                       F_CA / F_L1, F_CA, noise, self._z, self.err)
        T = self.T
        nco.code_phase += nco.code_rate * T - CA_LEN
        ph = nco.carr_phase + nco.carr_freq * T
        nco.carr_phase[:] = ph - np.floor(ph)
        return self._z

    def advance(self):
        """Advance the truth by one epoch (code phase reduced by one code period, like the NCO)."""
        k = self.k
        tr = self.truth
        T = self.T
        self.p_true = self.p_true + F_CA * T + (F_CA / F_L1) * (tr.theta[k + 1] - tr.theta[k]) - CA_LEN
        self.k += 1


def rms(a, axis=0):
    """Root mean square along ``axis``, ignoring NaN entries."""
    a = np.asarray(a, dtype=float)
    return np.sqrt(np.nanmean(a * a, axis=axis))
