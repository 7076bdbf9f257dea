"""Outer (vector) loop: per-channel carrier Doppler and code-phase rate predicted from the
corrected SINS position/velocity, the broadcast ephemeris and the receiver-clock estimates
(Zhao et al. 2014, Fig. 1, the "倍频" branch), at the SINS rate (100 Hz), CIC-interpolated to the
prefilter rate (1000 Hz) to aid every channel's NCO.

Speed.  The predictions are the all-channel light-time solution of
:class:`ultratight.signals.geometry.MultiLightTime` (the equations of
:func:`ultratight.signals.geometry.light_time` on satellite states tabulated once per run and
Hermite-interpolated, warm-started from the previous epoch's travel time, 2 iterations).

Timing.  ``t`` is seconds since the first IF sample, on the receiver clock; the receiver-clock
reading of GPS time is ``tow0 + t``, and the true reception time used in the light-time
equation is ``tow0 + t - b/c`` (``b`` = receiver clock bias estimate, m).

CIC latency.  A CIC interpolator of order N and rate R delays its input by a known group delay
D (s).  The value pushed at SINS epoch ``t_s`` is therefore the prediction for
``t_s + D + 1/rate`` (kinematic extrapolation with the SINS acceleration and jerk), so that the 1 kHz
samples that come out after the push at ``t_s`` cover ``[t_s + 1/rate, t_s + 2/rate)`` —
strictly causal: the SINS never needs IMU data past the current correlator epoch + one SINS
step.

Atmosphere.  With an :class:`ultratight.signals.atmosphere.AtmosphereModel` (``atmosphere``), every
prediction carries the L1 delays of :class:`ultratight.receiver.deep.atmosphere_terms.PredictionDelays`:
code phase / pseudorange delayed by ``I + T``, Doppler with the carrier's ``d(T - I)/dt``; the delays
are refreshed by :meth:`OuterLoop.refresh_atmosphere` (at each tight-filter update) and carried
linearly in between.  Without one the predictions are the geometric ones.
"""

import numpy as np

from ultratight.constants import C
from ultratight.errors import ConfigError
from ultratight.fusion.coupling import rateconv
from ultratight.receiver.deep.atmosphere_terms import REFRESH_S, PredictionDelays
from ultratight.signals.geometry import MultiLightTime, SatTable
from ultratight.signals.signal import GPS_L1CA


class OuterLoop:
    """100 Hz per-channel predictions -> CIC -> 1 kHz NCO aiding (see module docstring).

    ``interp_factory(n_ch)`` returns an interpolator object with ``push(x (n_ch, k)) ->
    (n_ch, k*R)`` semantics and attributes ``ratio`` and ``delay_s``; by default
    :func:`make_cic` (the CIC interpolator of fusion.coupling.rateconv).
    """

    def __init__(self, ephs, prns, week, tow0_s, duration_s, rate_hz=100.0, out_rate_hz=1000.0,
                 interp_factory=None, cic_order=3, signal=GPS_L1CA, atmosphere=None, iono_source=None):
        self.signal = signal
        self._chip_rate = float(signal.chip_rate_hz)
        self.prns = list(prns)
        self.week = week
        self.tow0 = float(tow0_s)
        self.rate_hz = float(rate_hz)
        self.out_rate_hz = float(out_rate_hz)
        ratio = self.out_rate_hz / self.rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
            raise ConfigError(f"outer loop: output rate {out_rate_hz} Hz must be an integer multiple of "
                              f"the SINS rate {rate_hz} Hz")
        self.ratio = int(round(ratio))
        self.table = SatTable(ephs, self.prns, self.tow0 - 1.0, self.tow0 + duration_s + 1.0)
        self.lt = MultiLightTime(self.table, signal)
        n_ch = len(self.prns)
        if interp_factory is None:
            interp_factory = make_cic
        self.interp = interp_factory(n_ch, self.ratio, cic_order, self.rate_hz)
        self.delay_s = float(self.interp.delay_s)
        n_out = int(np.ceil((duration_s + 1.0) * self.out_rate_hz)) + 4 * self.ratio
        self.aid_doppler = np.full((n_out, n_ch), np.nan)
        self.aid_code_rate = np.full((n_out, n_ch), np.nan)
        self.n_filled = 0          # aid arrays are valid on out-grid indices [j0, n_filled)
        # Doppler offset removed from the aiding stream (the double loop books the tight-filter
        # corrections here so that only the SINS *dynamics* reach the NCO increments)
        self.offset_hz = np.zeros(n_ch)
        self.j0 = None
        self.atmo = (PredictionDelays(atmosphere, n_ch, signal, iono_source)
                     if atmosphere is not None and atmosphere.active else None)

    def predict(self, t, pos_e, vel_e, clk_bias_m, clk_drift_mps):
        """Predictions for all channels at receiver time ``t`` (s since the first sample)."""
        t_true = self.tow0 + t - clk_bias_m / C
        pr = self.lt.solve(pos_e, vel_e, t_true, clk_bias_m, clk_drift_mps)
        if self.atmo is not None:
            self.atmo.apply(pr, t)
        return pr

    def refresh_atmosphere(self, t, pos_e, vel_e, clk_bias_m, clk_drift_mps):
        """Evaluate the atmospheric delays at receiver time ``t`` for the antenna state ``pos_e``,
        ``vel_e`` (no-op without an atmosphere model)."""
        if self.atmo is None:
            return
        t_true = self.tow0 + t - clk_bias_m / C
        h = REFRESH_S
        los = self.lt.solve(pos_e, vel_e, t_true, clk_bias_m, clk_drift_mps)["los_e"].copy()
        los_next = self.lt.solve(np.asarray(pos_e) + np.asarray(vel_e) * h, vel_e, t_true + h,
                                 clk_bias_m + clk_drift_mps * h, clk_drift_mps)["los_e"]
        self.atmo.refresh(t, t_true, pos_e, vel_e, los, los_next)

    def aiding_at(self, t):
        """Doppler aiding (Hz) of each channel at its receiver time ``t[c]`` (s since the first
        sample): linear interpolation on the output grid, clamped to the filled part."""
        u = np.asarray(t) * self.out_rate_hz
        j = np.clip(np.floor(u).astype(np.int64), 0, self.n_filled - 2)
        r = np.arange(u.shape[0])
        return self.aid_doppler[j, r] * (1.0 - (u - j)) + self.aid_doppler[j + 1, r] * (u - j)

    def push(self, t_s, pos_e, vel_e, acc_e, clk_bias_m, clk_drift_mps, jerk_e=None):
        """Feed the SINS state of epoch ``t_s``; appends 1 kHz aiding samples.

        The prediction is made for ``t_s + lead`` with ``lead = delay + 1/rate`` by kinematic
        extrapolation so the emerging 1 kHz samples refer to ``[t_s + 1/rate, t_s + 2/rate)``.
        """
        lead = self.delay_s + 1.0 / self.rate_hz
        j = np.zeros(3) if jerk_e is None else np.asarray(jerk_e)
        p = np.asarray(pos_e) + np.asarray(vel_e) * lead + 0.5 * np.asarray(acc_e) * lead * lead \
            + j * lead ** 3 / 6.0
        v = np.asarray(vel_e) + np.asarray(acc_e) * lead + 0.5 * j * lead * lead
        pr = self.predict(t_s + lead, p, v, clk_bias_m + clk_drift_mps * lead, clk_drift_mps)
        x = np.stack([pr["doppler_hz"] - self.offset_hz, pr["code_rate_cps"] - self._chip_rate], axis=0)   # (2, n_ch)
        y = self.interp.push(x)                                              # (2, n_ch, ratio)
        j_start = int(round((t_s + 1.0 / self.rate_hz) * self.out_rate_hz))
        if self.j0 is None:
            self.j0 = j_start
        j_end = min(j_start + self.ratio, self.aid_doppler.shape[0])
        k = j_end - j_start
        if k > 0 and j_start >= 0:
            self.aid_doppler[j_start:j_end] = y[0, :, :k].T
            self.aid_code_rate[j_start:j_end] = y[1, :, :k].T + self._chip_rate
            self.n_filled = j_end
        return pr

    def prime(self, t_s, pos_e, vel_e, acc_e, clk_bias_m, clk_drift_mps, n_hist=6):
        """Fill the interpolator's history with the kinematically extrapolated *past* predictions
        (constant acceleration), so that its output has no start-up transient on a ramp."""
        if hasattr(self.interp, "prime"):
            lead = self.delay_s + 1.0 / self.rate_hz
            p0 = self.predict(t_s + lead - n_hist / self.rate_hz, pos_e, vel_e, clk_bias_m, clk_drift_mps)
            self.interp.prime(np.stack([p0["doppler_hz"] - self.offset_hz, p0["code_rate_cps"] - self._chip_rate], axis=0))
        pos_e, vel_e, acc_e = (np.asarray(v, dtype=float) for v in (pos_e, vel_e, acc_e))
        for k in range(n_hist, 0, -1):
            tau = self.delay_s + 1.0 / self.rate_hz - k / self.rate_hz
            p = pos_e + vel_e * tau + 0.5 * acc_e * tau * tau
            v = vel_e + acc_e * tau
            pr = self.predict(t_s + tau, p, v, clk_bias_m + clk_drift_mps * tau, clk_drift_mps)
            self.interp.push(np.stack([pr["doppler_hz"] - self.offset_hz, pr["code_rate_cps"] - self._chip_rate], axis=0))


class PredictionRing:
    """The outer loop's exact predictions at the last ``size`` SINS epochs (receiver time ``t``,
    code phase, code rate, Doppler per channel): the reference the tracking estimates are
    differenced against (residuals for the tight filter, linear in time between SINS epochs)."""

    def __init__(self, n_ch, size=64):
        self.t = np.full(size, np.nan)
        self.cp = np.zeros((size, n_ch))
        self.r = np.zeros((size, n_ch))
        self.f = np.zeros((size, n_ch))
        self.nf = np.zeros(size, dtype=np.int64)   # the outer loop's aiding grid end after each entry
        self.k = 0                   # predictions put so far; the latest is at (k - 1) % size

    @property
    def latest(self):
        return (self.k - 1) % self.t.shape[0]

    def put(self, t, pr, n_filled):
        i = self.k % self.t.shape[0]
        self.nf[i] = n_filled
        self.t[i] = t
        self.cp[i] = pr["code_phase_chips"]
        self.r[i] = pr["code_rate_cps"]
        self.f[i] = pr["doppler_hz"]
        self.k += 1


class SinsFollower:
    """Feeds an :class:`OuterLoop` from the corrected SINS (:class:`ultratight.receiver.deep.sins_clock.InsClock`):
    exact predictions at every SINS epoch into its :class:`PredictionRing`, and the kinematics
    (velocity, finite-difference acceleration and jerk) for the CIC-interpolated aiding.  Predictions
    are made at the antenna (``InsClock.antenna_pos_vel_e``: the IMU point plus the lever arm)."""

    def __init__(self, outer, ins, t_sins, dtheta0, dv0, dt0, code_period_s):
        """Start the outer loop at the SINS epoch ``t_sins``: the acceleration from a trial step over
        the first IMU interval, the interpolator's history, the aiding of the first interval by
        direct predictions, and the first ring entry."""
        self.outer = outer
        self.ins = ins
        self.t = float(t_sins)
        self.ring = PredictionRing(len(outer.prns))
        pos_e, vel_e, _ = ins.antenna_pos_vel_e()
        outer.refresh_atmosphere(self.t, pos_e, vel_e, ins.clk_b, ins.clk_d)
        self.first = outer.predict(self.t, pos_e, vel_e, ins.clk_b, ins.clk_d)
        acc0_e = (ins.trial_velocity_e(dtheta0, dv0, dt0) - ins.pos_vel_e()[1]) / dt0
        outer.prime(self.t, pos_e, vel_e, acc0_e, ins.clk_b, ins.clk_d)
        for j in range(outer.ratio + 1):
            tj = j * 1e-3
            pj = outer.predict(self.t + tj, pos_e + vel_e * tj + 0.5 * acc0_e * tj * tj, vel_e + acc0_e * tj,
                               ins.clk_b + ins.clk_d * tj, ins.clk_d)
            outer.aid_doppler[j] = pj["doppler_hz"]
            outer.aid_code_rate[j] = pj["code_rate_cps"]
        outer.push(self.t, pos_e, vel_e, acc0_e, ins.clk_b, ins.clk_d)
        self.ring.put(self.t, self.first, outer.n_filled)
        self.vel_prev = vel_e.copy()
        self.acc_prev = acc0_e.copy()

    def step(self, t_sins, dt):
        """After the SINS stepped to ``t_sins`` (interval ``dt``): ring entry and aiding samples."""
        ins = self.ins
        self.t = t_sins
        pos_e, vel_e, _ = ins.antenna_pos_vel_e()
        acc_e = (vel_e - self.vel_prev) / dt
        jerk_e = (acc_e - self.acc_prev) / dt
        self.acc_prev = acc_e
        self.vel_prev = vel_e
        pr = self.outer.predict(t_sins, pos_e, vel_e, ins.clk_b, ins.clk_d)
        # kinematics at the middle of the last interval -> extrapolate from there
        self.outer.push(t_sins, pos_e, vel_e, acc_e + 0.5 * dt * jerk_e, ins.clk_b, ins.clk_d, jerk_e)
        self.ring.put(t_sins, pr, self.outer.n_filled)

    def refresh_atmosphere(self):
        """The outer loop's atmospheric delays at the current SINS state (no-op without a model)."""
        pos_e, vel_e, _ = self.ins.antenna_pos_vel_e()
        self.outer.refresh_atmosphere(self.t, pos_e, vel_e, self.ins.clk_b, self.ins.clk_d)

    def los_e(self):
        """Unit lines of sight (ECEF) at the current SINS state."""
        pos_e, vel_e, _ = self.ins.antenna_pos_vel_e()
        return self.outer.predict(self.t, pos_e, vel_e, self.ins.clk_b, self.ins.clk_d)["los_e"]

    def apply_correction(self, code_length, book_offset):
        """After a tight-filter feedback: shift the ring's predictions to the corrected SINS (the
        residuals stay consistent) and, with ``book_offset`` (double loop), book the Doppler change
        in the outer loop's offset so the correction does not jump the NCOs. Returns the Doppler
        change per channel (Hz)."""
        ins = self.ins
        ring = self.ring
        pos_e, vel_e, _ = ins.antenna_pos_vel_e()
        pr_fix = self.outer.predict(self.t, pos_e, vel_e, ins.clk_b, ins.clk_d)
        i1 = ring.latest
        half = 0.5 * code_length
        dcp = np.mod(pr_fix["code_phase_chips"] - ring.cp[i1] + half, code_length) - half
        dfp = pr_fix["doppler_hz"] - ring.f[i1]
        ring.cp += dcp
        ring.f += dfp
        if book_offset:
            self.outer.offset_hz += dfp
        ring.r[i1] = pr_fix["code_rate_cps"]
        self.vel_prev = vel_e.copy()
        return dfp


def make_cic(n_ch, ratio, order, in_rate_hz):
    """The CIC interpolator of :mod:`ultratight.fusion.coupling.rateconv` for two quantities x n_ch
    channels (adapter)."""
    return _CicAdapter(n_ch, ratio, order, in_rate_hz)


class _CicAdapter:
    """Adapter around :mod:`ultratight.fusion.coupling.rateconv`'s CIC interpolator.

    Works on a (2, n_ch) input per push and returns (2, n_ch, ratio).
    """

    def __init__(self, n_ch, ratio, order, in_rate_hz):
        self.ratio = ratio
        self.n_ch = n_ch
        self._cic = rateconv.CicInterpolator(ratio, N=order, M=1, f_lo_hz=in_rate_hz, shape=(2 * n_ch,))
        self.delay_s = float(self._cic.delay_s)
        self._t = 0.0
        self._dt = 1.0 / in_rate_hz

    def prime(self, x):
        self._cic.prime(np.asarray(x, dtype=float).reshape(-1))

    def push(self, x):
        _, y = self._cic.push(self._t, np.asarray(x, dtype=float).reshape(-1))   # (ratio, 2*n_ch)
        self._t += self._dt
        return np.asarray(y).T.reshape(2, self.n_ch, self.ratio)
