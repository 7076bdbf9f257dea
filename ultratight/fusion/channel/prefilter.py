"""Per-channel nonlinear I/Q prefilters (Zhao et al. 2014, §2.1–2.3): the batched CKF / UKF / RACKF bank.

:class:`PrefilterBank` holds ``n_ch`` 5-state prefilters ``x = [A, dtau, dphi, df, da]`` on the six
correlator outputs ``z = [I_P, I_E, I_L, Q_P, Q_E, Q_L]`` of each channel; the model (state,
measurement eq. 3, process model eq. 2) and the layout of the bank's packed buffers are in
``prefilter_model``, the compiled measurement and time updates (CKF, UKF, RACKF with its Huber and
adaptive steps, the guards) in ``prefilter_kernels``.

Cycle (one call per 1 ms epoch for all channels): the bank holds the *prior*
x_{k|k-1}, P_{k|k-1} for the interval that was just integrated; ``step(z)``
does the measurement update (eqs. 9–17, or Algorithm 1 for RACKF), then the
time update (eqs. 4–8) to the start of the next interval and returns that
predicted state.  The inner-loop law (``ultratight.fusion.channel.innerloop``) then
moves the NCOs by (part of) the predicted errors and removes the applied part
from the state with :meth:`PrefilterBank.correct` (error-state feedback).

The bank's whole state lives in one float and one int buffer (:attr:`PrefilterBank.packed`); its
attributes are views of them, and compiled callers step it with :func:`bank_epoch` or, channel by
channel, :func:`channel_update` with the arrays of :meth:`PrefilterBank.kernel_arrays`.  This module is
the prefilter's import path for the receiver and the tests: it also provides the names of the model and
the kernels they use (``__all__``).
"""

from __future__ import annotations

import numpy as np

from ultratight.constants import BETA_CODE_CARRIER, T_CA
from ultratight.errors import FilterError
from ultratight.fusion.channel.prefilter_kernels import (_views, bank_epoch, channel_settings, channel_update,
                                                        inputs_finite)
from ultratight.fusion.channel.prefilter_kernels import _h  # noqa: F401  (the eq. 3 kernel, tested as prefilter._h)
from ultratight.fusion.channel.prefilter_model import (
    ACC_LAM,
    ADAPTIVE_STAT_CODES,
    ADAPTIVE_STATS,
    CNT_CORRECTION_PERIOD,
    CNT_EPOCH,
    DEFAULT_P_LIMITS,
    DEFAULT_Q,
    FLAG_DIVERGED,
    FLAG_ROBUST,
    FSEG_END,
    IA,
    IE,
    IF,
    IL,
    IPHI,
    IPRM_ADAPTIVE_STAT,
    IPRM_ROBUST_EVERY,
    ISEG_COUNTERS,
    ISEG_END,
    ISEG_RESETS,
    ITAU,
    KIND_CODES,
    KINDS,
    NACC,
    N_W1,
    N_W2,
    NX,
    NZ,
    PRM_ADAPT_KSIG,
    PRM_BETA,
    PRM_DHALF,
    PRM_HUBER_C,
    PRM_MIN_WINDOW,
    PRM_P_LIMITS,
    PRM_PHI_VAR_MAX,
    PRM_T,
    PRM_THETA_MIN,
    PRM_UT_SCALE,
    PRM_UT_WC0,
    PRM_UT_WI,
    PRM_UT_WM0,
    QP,
    ROBUST_MODES,
    default_initial_covariance,
    measurement_model,
    packed_float_offsets,
    packed_int_offsets,
    prefilter_model,
    ut_weights,
)
from ultratight.signals import corr_model

# the names imported from this module by the receiver, the PB-KF baseline, the benchmarks and the tests
__all__ = [
    "PackedActiveMask", "PrefilterBank", "bank_epoch", "channel_settings", "channel_update", "empty_kernel_arrays",
    "inputs_finite", "N_W1", "N_W2", "NX", "NZ", "IE", "IF",
    "IL", "IPHI", "QP", "KINDS", "FLAG_DIVERGED", "FLAG_ROBUST", "default_initial_covariance", "measurement_model",
    "prefilter_model",
]


def empty_kernel_arrays():
    """Arrays of the kinds of :meth:`PrefilterBank.kernel_arrays`, empty: what a compiled caller holds in
    their place for a tracking bank of another kind (the PB-KF), so that one compiled chain serves both."""
    return (np.zeros((0, NX)), np.zeros((0, NX, NX)), np.zeros((0, NZ)), np.zeros(0), np.zeros(0),
            np.zeros((0, NACC)), np.zeros((NX, NX)), np.zeros((NX, NX)), np.zeros((NZ, NZ)), np.zeros(0),
            np.zeros(0, dtype=np.int64))


def _checked_n_ch(n_ch, kind, spacing_chips, huber_c, correction_period, robust_mode, adaptive_stat, theta_min):
    """The channel count as an int, after checking the bank's settings (FilterError naming the bad one)."""
    if kind not in KIND_CODES:
        raise FilterError(f"prefilter kind {kind!r}: expected one of {KINDS}")
    if robust_mode not in ROBUST_MODES:
        raise FilterError(f"prefilter robust_mode {robust_mode!r}: expected one of {ROBUST_MODES}")
    n_ch = int(n_ch)
    if n_ch < 1:
        raise FilterError(f"prefilter n_ch={n_ch}: expected >= 1")
    if not (np.isfinite(spacing_chips) and 0 < spacing_chips <= 2.0):
        raise FilterError(f"prefilter spacing_chips={spacing_chips!r}: expected 0 < spacing <= 2")
    if not (1.0 <= huber_c <= 10.0):
        raise FilterError(f"prefilter huber_c={huber_c!r}: expected 1 <= c <= 10 (paper: 1.3-2.0)")
    if int(correction_period) < 1:
        raise FilterError(f"prefilter correction_period={correction_period!r}: expected >= 1 epoch")
    if adaptive_stat not in ADAPTIVE_STATS:
        raise FilterError(f"prefilter adaptive_stat {adaptive_stat!r}: expected one of {ADAPTIVE_STATS}")
    if not (0 < theta_min <= 1):
        raise FilterError(f"prefilter theta_min={theta_min!r}: expected 0 < theta_min <= 1")
    return n_ch


class PackedActiveMask:
    """The ``active`` mask of a bank that keeps it as integers in its packed buffer (``_active_i``)."""

    @property
    def active(self):
        """Per-channel active mask (read-only copy; change it with set_active / reset)."""
        a = self._active_i != 0
        a.flags.writeable = False
        return a

    @property
    def active_flags(self):
        """The integer active flags in the packed buffer itself (a writable view, for the compiled
        epoch runner that switches channels on and off)."""
        return self._active_i

    def set_active(self, mask):
        m = np.asarray(mask, dtype=np.bool_)
        if m.shape != (self.n_ch,):
            raise FilterError(f"{type(self).__name__} active mask: expected shape ({self.n_ch},), got {m.shape}")
        self._active_i[:] = m


class PrefilterBank(PackedActiveMask):
    """Batched 5-state I/Q prefilters ("ckf" | "ukf" | "rackf") for ``n_ch`` channels.

    Parameters
    ----------
    n_ch : number of channels.
    kind : "ckf", "ukf" or "rackf".
    T : coherent integration time (s), default one C/A period.
    spacing_chips : early-late spacing (the correlator's).
    q : dict overriding DEFAULT_Q (continuous process noise densities, eq. 2).
    huber_c : Huber constant c (Zhao et al. 2014, §2.3: 1.3–2.0).
    correction_period : RACKF robust-adaptive correction period in epochs (50 = 50 ms).
    robust_mode : "every" (default: Huber every epoch, adaptive factor on correction epochs)
        or "period" (paper: Huber + adaptive only on correction epochs, plain CKF between).
    adaptive_stat : "mean" (default), "window" or "epoch" (paper-literal eq. 38), see
        ``prefilter_kernels``.
    adapt_ksig : significance margin (sigmas) of the windowed statistics.
    theta_min : lower bound of the adaptive factor.
    phi_sigma_max : cap of the phase standard deviation (rad), all kinds.
    ukf_alpha, ukf_beta, ukf_kappa : UKF scaled sigma-point parameters.
    p_limits : per-state covariance-diagonal limits beyond which a channel is declared diverged.
    cn0_dbhz_init : C/N0 of the initial amplitude and covariance.

    Attributes (views, updated in place): ``x`` (n_ch, 5) predicted state for the next
    interval, ``P`` (n_ch, 5, 5), ``x_post`` (n_ch, 5) posterior of the last interval,
    ``innov`` (n_ch, 6), ``nis`` (n_ch,), ``theta`` (n_ch,), ``flags`` (n_ch,) bit field,
    ``diverged`` (n_ch,) bool for the last epoch, ``n_resets`` (n_ch,), ``active`` (n_ch,).
    """

    P_ITAU, P_IF = ITAU, IF        # code and frequency errors in the covariance P (the bank's state layout)

    def __init__(self, n_ch, kind="rackf", T=T_CA, spacing_chips=1.0, q=None, huber_c=1.5,
                 correction_period=50, robust_mode="every", adaptive_stat="mean", adapt_ksig=3.0,
                 theta_min=1e-3, phi_sigma_max=0.8,
                 ukf_alpha=0.5,
                 ukf_beta=2.0, ukf_kappa=0.0, p_limits=None, cn0_dbhz_init=35.0):
        n_ch = _checked_n_ch(n_ch, kind, spacing_chips, huber_c, correction_period, robust_mode, adaptive_stat,
                             theta_min)
        self.n_ch = n_ch
        self.kind = kind
        self._kind = KIND_CODES[kind]
        self.T = float(T)
        self.spacing_chips = float(spacing_chips)
        self.q = dict(DEFAULT_Q, **(q or {}))
        Phi, Qd = prefilter_model(self.T, q)
        self.huber_c = float(huber_c)
        self.correction_period = int(correction_period)
        self.robust_mode = robust_mode
        self.adaptive_stat = adaptive_stat
        self.theta_min = float(theta_min)
        self.ukf_params = dict(alpha=float(ukf_alpha), beta=float(ukf_beta), kappa=float(ukf_kappa))
        ut = ut_weights(ukf_alpha, ukf_beta, ukf_kappa)
        lim = DEFAULT_P_LIMITS if p_limits is None else np.asarray(p_limits, dtype=float)
        if lim.shape != (NX,):
            raise FilterError(f"prefilter p_limits: expected shape ({NX},), got {lim.shape}")
        self.phi_sigma_max = float(phi_sigma_max)
        self.adapt_ksig = float(adapt_ksig)
        self._allocate(n_ch)
        self.Phi[:] = Phi
        self.Qd[:] = Qd
        self.R[:] = corr_model.epl_noise_covariance(self.spacing_chips)
        self._fill_parameters(ut, lim)
        self._bits_unknown = np.zeros(n_ch)
        self._rscale_one = np.ones(n_ch)
        self._fill_initial_state(cn0_dbhz_init)

    def _allocate(self, n_ch):
        """One packed float buffer and one int buffer (few kernel arguments); the attributes are views."""
        io = packed_int_offsets(n_ch)
        self._fbuf = np.zeros(int(packed_float_offsets(n_ch)[FSEG_END]))
        self._ibuf = np.zeros(int(io[ISEG_END]), dtype=np.int64)
        (self.x, self.P, self.x_post, self.x0, self.P0, self.innov, self.nis, self.theta, self._acc, self.Phi,
         self.Qd, self.R, self._prm, _, _, self.flags, self._active_i, self._iprm) = \
            _views(self._fbuf, self._ibuf, n_ch)
        self.n_resets = self._ibuf[io[ISEG_RESETS]:io[ISEG_COUNTERS]]
        self._counters = self._ibuf[io[ISEG_COUNTERS]:io[ISEG_END]]

    def _fill_parameters(self, ut, lim):
        """The kernels' parameter vectors from the settings; ``ut``: :func:`ut_weights`, ``lim``: p_limits."""
        ut_scale, wm0, wc0, wi = ut
        prm = self._prm
        prm[PRM_T] = self.T
        prm[PRM_BETA] = BETA_CODE_CARRIER
        prm[PRM_DHALF] = float(corr_model.tap_offsets(self.spacing_chips)[IL])    # the late tap's +spacing/2
        prm[PRM_HUBER_C] = self.huber_c
        prm[PRM_THETA_MIN] = self.theta_min
        prm[PRM_UT_WM0] = wm0
        prm[PRM_UT_WC0] = wc0
        prm[PRM_UT_WI] = wi
        prm[PRM_UT_SCALE] = ut_scale
        prm[PRM_P_LIMITS:PRM_P_LIMITS + NX] = lim
        prm[PRM_ADAPT_KSIG] = self.adapt_ksig
        prm[PRM_MIN_WINDOW] = float(max(2, self.correction_period // 2))
        prm[PRM_PHI_VAR_MAX] = self.phi_sigma_max ** 2
        self._iprm[IPRM_ROBUST_EVERY] = 1 if self.robust_mode == "every" else 0
        self._iprm[IPRM_ADAPTIVE_STAT] = ADAPTIVE_STAT_CODES[self.adaptive_stat]
        self._counters[CNT_CORRECTION_PERIOD] = self.correction_period

    def _fill_initial_state(self, cn0_dbhz_init):
        """Every channel at its initial state: amplitude of ``cn0_dbhz_init``, zero errors, the default
        initial covariance; no measurement yet, noise scale 1, adaptive factor 1."""
        self._acc[:, ACC_LAM] = 1.0
        self.innov[:] = np.nan
        self.nis[:] = np.nan
        self.theta[:] = 1.0
        a0 = float(corr_model.amplitude_from_cn0(cn0_dbhz_init, self.T))
        P_init = default_initial_covariance(cn0_dbhz_init, self.T)
        for c in range(self.n_ch):
            self.x0[c, IA] = a0
            self.P0[c] = P_init
        self.x[:] = self.x0
        self.P[:] = self.P0
        self.x_post[:] = self.x0

    # -- initialisation -------------------------------------------------------------
    def reset(self, channels, x0=None, P0=None, activate=True):
        """(Re)initialise channels: x0 (k,5) or (5,), P0 (k,5,5) or (5,5) (defaults: the stored ones).

        The given P0 and the amplitude of x0 also become the state the channel returns to after a
        divergence; its code, phase, frequency and acceleration errors return to zero. They are
        errors against the NCOs of the reset epoch, which the inner-loop feedback moves into the
        NCOs: returning to them later would apply the same correction twice (a channel restarted
        far off its aiding then doubles its offset at every divergence).
        """
        ch = np.atleast_1d(np.asarray(channels, dtype=np.int64))
        if ch.size and (ch.min() < 0 or ch.max() >= self.n_ch):
            raise FilterError(f"prefilter reset: channel index out of range 0..{self.n_ch - 1}: {ch}")
        xa = None
        if x0 is not None:
            xa = np.broadcast_to(np.asarray(x0, dtype=float), (ch.size, NX))
            if not np.all(np.isfinite(xa)):
                raise FilterError("prefilter reset: x0 must be finite")
            self.x0[ch] = 0.0
            self.x0[ch, IA] = xa[:, IA]
        if P0 is not None:
            Pa = np.broadcast_to(np.asarray(P0, dtype=float), (ch.size, NX, NX))
            for k in range(ch.size):
                Pk = Pa[k]
                if not (np.all(np.isfinite(Pk)) and np.allclose(Pk, Pk.T)):
                    raise FilterError("prefilter reset: P0 must be finite and symmetric")
                try:
                    np.linalg.cholesky(Pk)
                except np.linalg.LinAlgError:
                    raise FilterError("prefilter reset: P0 must be positive definite") from None
            self.P0[ch] = Pa
        self.x[ch] = self.x0[ch] if xa is None else xa
        self.P[ch] = self.P0[ch]
        self.x_post[ch] = self.x[ch]
        self.nis[ch] = np.nan
        self.innov[ch] = np.nan
        self._acc[ch] = 0.0
        self._acc[ch, ACC_LAM] = 1.0
        if activate:
            self._active_i[ch] = 1


    # -- one epoch -----------------------------------------------------------------
    def step(self, z, bits=None, rscale=None):
        """Measurement update with z (n_ch, 6) then predict; returns the predicted x (n_ch, 5).

        bits: None (all unknown -> decision-directed) or (n_ch,) of +1/-1 (known) / 0 (unknown).
        rscale: None or (n_ch,) factors on R for this epoch (a filter-R noise event,
        :mod:`ultratight.receiver.dsp.burst`).
        """
        z = np.asarray(z, dtype=np.float64)
        if z.shape != (self.n_ch, NZ):
            raise FilterError(f"prefilter step: z must have shape ({self.n_ch}, {NZ}) "
                              f"[I_P, I_E, I_L, Q_P, Q_E, Q_L], got {z.shape}")
        if bits is None:
            b = self._bits_unknown
        else:
            b = np.asarray(bits, dtype=np.float64)
            if b.shape != (self.n_ch,):
                raise FilterError(f"prefilter step: bits must have shape ({self.n_ch},), got {b.shape}")
        rs = self._rscale_one if rscale is None else np.asarray(rscale, dtype=np.float64)
        if rs.shape != (self.n_ch,):
            raise FilterError(f"prefilter step: rscale must have shape ({self.n_ch},), got {rs.shape}")
        st = bank_epoch(self._kind, self._fbuf, self._ibuf, z, b, rs)
        if st < 0:
            c = -1 - st
            raise FilterError(f"prefilter step: non-finite measurement or bit on active channel {c}: "
                              f"z={z[c]}, bit={b[c]}")
        return self.x

    @property
    def epoch(self):
        """Epochs stepped since construction (the RACKF correction phase counts from it)."""
        return int(self._counters[CNT_EPOCH])

    @epoch.setter
    def epoch(self, value):
        self._counters[CNT_EPOCH] = int(value)

    @property
    def packed(self):
        """``(kind code, float buffer, int buffer)``: the bank's whole state for compiled callers
        (:func:`bank_epoch`); the attributes are views of these buffers."""
        return self._kind, self._fbuf, self._ibuf

    def kernel_arrays(self):
        """The bank's arrays :func:`channel_update` takes besides the state, the posterior, the covariance and the
        active flags: ``(x0, P0, innov, nis, theta, acc, Phi, Qd, R, prm, flags)``, views of the packed buffers,
        for a compiled caller that holds them across epochs (the receiver's epoch chain): building them from
        the buffers at every epoch (eighteen views) took a twentieth of an engine run."""
        return (self.x0, self.P0, self.innov, self.nis, self.theta, self._acc, self.Phi, self.Qd, self.R, self._prm,
                self.flags)

    @property
    def diverged(self):
        return (self.flags & FLAG_DIVERGED) != 0

    def correct(self, dx):
        """Error-state feedback: subtract the part dx (n_ch, 5) applied to the NCOs from the state."""
        self.x -= dx

    def state_sigma(self):
        """1-sigma of each state (n_ch, 5)."""
        return np.sqrt(np.maximum(np.diagonal(self.P, axis1=1, axis2=2), 0.0))

    def note_correction(self, dx):
        """Called by the inner-loop law after it moved the NCOs by ``dx``: the prefilter's state is
        already corrected in place (``x``), nothing else to update."""

    def describe(self):
        """Parameters for logs and outputs."""
        d = dict(kind=self.kind, T=self.T, spacing_chips=self.spacing_chips, q=self.q)
        if self.kind == "ukf":
            d["ukf"] = self.ukf_params
        if self.kind == "rackf":
            d.update(huber_c=self.huber_c, correction_period=self.correction_period,
                     robust_mode=self.robust_mode, adaptive_stat=self.adaptive_stat,
                     theta_min=self.theta_min)
        return d

