"""The double-loop ultra-tight receiver engine (seed 000 Fig. 1, SPEC §1).

Data flow per 1 ms epoch (Python orchestrates; every stage is one batched call for all
channels)::

    IF block ─► CorrelatorBank.step ─► data wipe-off (assisted LNAV bits)
             ─► PrefilterBank.step (inner loop, 1 kHz)  ─► InnerLoop.apply (NCO feedback,
                 outer-loop Doppler increments when the arbitration allows)
             ─► residuals vs the SINS prediction ─► averaging decimator (10 Hz)
             ─► tight 17-state filter ⇄ SINS (100 Hz, feedback) ─► OuterLoop (100 Hz
                 predictions, CIC to 1 kHz) ─► aiding of the next epochs

Methods (all on the same IF/IMU data; each is a spec of the registry
:mod:`ultratight.receiver.methods`, naming its tracking bank and loop structure):

* ``dlb-rackf`` (default), ``dlb-ckf``, ``dlb-ukf``: double loop — each channel's prefilter
  (the numba bank of fusion.prefilter) closes its own inner loop every epoch; the outer loop feeds the
  SINS-predicted Doppler *increments* forward into the carrier NCO (the code NCO rate is
  slaved to the carrier, so it is aided too).
* ``pb-kf-utc``: single loop baseline — discriminator outputs into a linear KF per channel
  (``ultratight.fusion.pbkf``); the NCOs are driven by the outer loop only (absolute
  SINS-predicted Doppler and code phase, no inner loop).
* ``scalar``: the scalar tracking pipeline of receiver.tracking (no INS), for reference;
  :meth:`UltratightEngine.run` hands it to :func:`ultratight.receiver.scenario_runner.run_scalar`.

Arbitration (double loop, logged per channel per epoch in ``mode``): after every tight
update the 1-sigma of each channel's predicted Doppler is computed from the tight filter
covariance, ``sigma_i = sqrt(u_i' P_vv u_i + P_dd - 2 u_i' P_vd) / lambda`` (velocity /
clock-drift block projected on the line of sight, :func:`ultratight.fusion.tight.doppler_sigma_hz`),
and propagated between updates with the filter's time update.  A channel uses the combined
command (outer prediction + inner correction, ``MODE_COMBINED``) while ``sigma_i <
arbitration_sigma_hz`` and the outer loop is healthy (no divergence flag), otherwise the inner
loop alone (``MODE_INNER``).  PB-KF-UTC is always ``MODE_OUTER``.

Tracking estimates recorded per channel per epoch (for the paper's metrics): the Doppler
``carr_freq - IF + df/2pi`` and the code phase ``code_phase + dtau`` at the *start* of the
integration interval (the prefilter state refers to the interval start; see
ultratight.fusion.prefilter), with their time ``t_start`` (s since the first sample).
"""

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np
from numba import njit

from ultratight.errors import ConfigError, InputFileError
from ultratight.receiver.blockstream import BlockStream, NoiseFloor  # noqa: F401 (NoiseFloor: public here too)
from ultratight.receiver.methods import DEFAULT_METHOD, METHODS, check_method, method_spec  # noqa: F401
from ultratight.signals.signal import GPS_L1CA


MODE_INNER = 0
MODE_COMBINED = 1
MODE_OUTER = 2
MODE_COAST = 3      # signal lost: NCO on the outer-loop aiding only, prefilter restarted on return

# process noise of the aided prefilters (same for the three DLB methods; densities of eq. 2)
DLB_PREFILTER_Q = {
    "q_amp": 2.5e-3,     # amplitude random walk
    "q_tau": 1e-8,       # chips^2/s: code-carrier divergence (none in the simulation: small)
    "q_phi": 0.01,       # rad^2/s
    "q_f": 0.1,          # rad^2/s^3: aiding error drift (INS velocity / clock-drift error rate)
    "q_a": 0.1,          # rad^2/s^5: residual LOS jerk after aiding (CIC/extrapolation residuals)
}


@njit(cache=True)
def _wipe_bits(bits, t0_ms, ms, out, per_bit):
    """Assisted data bit of the code period starting at transmit code-period count ms (per channel;
    ``per_bit`` code periods per bit, :attr:`ultratight.signals.signal.SignalDescription.codes_per_bit`);
    advances ms by one period."""
    nb = bits.shape[1]
    for c in range(bits.shape[0]):
        k = (ms[c] - t0_ms[c]) // per_bit
        if k < 0:
            k = 0
        if k > nb - 1:
            k = nb - 1
        out[c] = bits[c, k]
        ms[c] += 1


@njit(cache=True)
def _epoch_post(k_ep, t_start, fs, if_hz, f0, cp0, x_post, P, i_ptau, i_pf, ring_t, ring_cp, ring_r, ring_f, ring_k,
                imu_dt, t_next_upd, acc, rec_t, rec_f, rec_cp, rec_a, rec_mode, mode_now,
                aid_grid, n_filled, sample_ptr, half_period_s, code_len, aid_out, aid_dt=0.0):
    """Per-epoch bookkeeping for all channels in one compiled call.

    Records the estimates (NCO + prefilter at the interval start), forms the residuals against
    the exact SINS predictions (ring of 100 Hz predictions, linear in between), accumulates
    them in the decimator window (acc rows: n, code, doppler, P_tautau, P_ff, amplitude) and
    interpolates the 1 kHz outer-loop Doppler aiding at the middle of each channel's next
    interval. ``code_len``: chips per code period (the signal description's ``code_length``).
    """
    two_pi = 2.0 * math.pi
    n_ch = t_start.shape[0]
    ring_n = ring_t.shape[0]
    i1 = (ring_k - 1) % ring_n
    t_last = ring_t[i1]
    half = 0.5 * code_len
    for c in range(n_ch):
        tk = float(t_start[c]) / fs
        # Doppler estimate for the middle of the interval: NCO + df + da T/2 (state at the start)
        f_meas = f0[c] - if_hz + (x_post[c, 3] + x_post[c, 4] * half_period_s) / two_pi
        cp_meas = cp0[c] + x_post[c, 1]
        rec_t[k_ep, c] = tk
        rec_f[k_ep, c] = f_meas
        rec_cp[k_ep, c] = cp_meas % code_len
        rec_a[k_ep, c] = x_post[c, 0]
        rec_mode[k_ep, c] = mode_now[c]
        back = int(math.floor((t_last - tk) / imu_dt)) + 1
        if back < 1:
            back = 1
        if back > ring_n - 2:
            back = ring_n - 2
        ia = (ring_k - 1 - back) % ring_n
        ib = (ia + 1) % ring_n
        ta = ring_t[ia]
        w = (tk - ta) / imu_dt
        cp_pred = ring_cp[ia, c] + ring_r[ia, c] * (tk - ta)
        # the Doppler estimate is the interval mean: compare with the prediction at mid-interval
        w += half_period_s / imu_dt
        f_pred = ring_f[ia, c] + w * (ring_f[ib, c] - ring_f[ia, c])
        r_cp = (cp_meas - cp_pred + half) % code_len - half
        r_f = f_meas - f_pred
        if tk < t_next_upd:
            acc[0, c] += 1.0
            acc[1, c] += r_cp
            acc[2, c] += r_f
            acc[3, c] += P[c, i_ptau, i_ptau]
            acc[4, c] += P[c, i_pf, i_pf]
            acc[5, c] += x_post[c, 0]
        u = (sample_ptr[c] / fs + half_period_s + aid_dt) * 1000.0
        j = int(math.floor(u))
        if j < 0:
            j = 0
        if j > n_filled - 2:
            j = n_filled - 2
        fr = u - j
        aid_out[c] = aid_grid[j, c] * (1.0 - fr) + aid_grid[j + 1, c] * fr


@njit(cache=True)
def _lock_monitor(out, D, win_i, win_c, sums_i, sums_c, ptr, count, present, thr_off, thr_on, events, phase):
    """Per-channel signal/lock monitor on the wiped prompt (unit noise per arm).

    Sliding window of W epochs: while ``present``, the mean in-phase prompt ``mean(I_P D)``
    (coherent: the carrier loop keeps the phase) below ``thr_off`` declares the signal lost;
    while absent, the coherent magnitude ``|mean((I_P + j Q_P) D)|`` above ``thr_on`` declares
    it back (``phase`` = its angle, for the restart).  ``events[c]``: 0 none, -1 lost, +1 regained.
    """
    W = win_i.shape[1]
    k = ptr[0]
    for c in range(out.shape[0]):
        vi = out[c, 0] * D[c]
        vq = out[c, 3] * D[c]
        sums_i[c] += vi - win_i[c, k]
        sums_c[c] += complex(vi, vq) - win_c[c, k]
        win_i[c, k] = vi
        win_c[c, k] = complex(vi, vq)
        events[c] = 0
        if count[c] < W:
            count[c] += 1
            continue
        if present[c]:
            if abs(sums_i[c].real) / W < thr_off:
                present[c] = False
                events[c] = -1
        else:
            m = sums_c[c] / W
            if abs(m) > thr_on:
                present[c] = True
                events[c] = 1
                phase[c] = math.atan2(m.imag, m.real)
                # restart the window so the next decision uses post-restart data only
                count[c] = 0
    ptr[0] = (k + 1) % W




class _BankProxy:
    """The prefilter bank seen by the inner-loop law with some channels masked inactive
    (channels whose NCO follows the outer-loop aiding alone this epoch)."""

    def __init__(self, bank):
        self._bank = bank
        self.x = bank.x
        self.active = bank.active.copy()

    def note_correction(self, dx):
        self._bank.note_correction(dx)


MONITOR_MODES = {
    "off": {"lock_monitor": False, "monitor_gates_tight": False},    # paper structure (default)
    "gate": {"lock_monitor": False, "monitor_gates_tight": True},    # only gates tight-filter rows
    "coast": {"lock_monitor": True, "monitor_gates_tight": True},    # gates, coasts and restarts
}


def monitor_options(mode):
    """EngineOptions fields of a signal-monitor mode ("off" | "gate" | "coast")."""
    if mode not in MONITOR_MODES:
        raise ConfigError(f"unknown signal-monitor mode {mode!r}; expected one of {', '.join(MONITOR_MODES)}")
    return dict(MONITOR_MODES[mode])


def monitor_mode(opt):
    """The monitor mode name of an EngineOptions."""
    for k, v in MONITOR_MODES.items():
        if v == {"lock_monitor": opt.lock_monitor, "monitor_gates_tight": opt.monitor_gates_tight}:
            return k
    return "coast-only"


def _outer_freq_update(x, P, sel, resid_hz, r_var):
    """Scalar Kalman update of the prefilters' frequency states (rad/s) of channels ``sel`` with
    the outer loop's Doppler: innovation -2 pi (estimate - prediction) = -2 pi ``resid_hz``,
    measurement variance ``r_var`` ((rad/s)^2)."""
    from ultratight.fusion.prefilter import IF as I_F
    for c in np.flatnonzero(sel):
        s_ = P[c, I_F, I_F] + r_var[c]
        if not (s_ > 0.0):
            continue
        k = P[c, :, I_F] / s_
        x[c] += k * (-2.0 * math.pi * resid_hz[c])
        P[c] -= np.outer(k, P[c, I_F, :])
        P[c] = 0.5 * (P[c] + P[c].T)


@dataclass
class EngineOptions:
    """Parameters of the engine (all recorded in the outputs)."""

    tight_rate_hz: float = 10.0          # integration-filter (decimated) rate
    tight_core: str = "ekf"              # ekf | ukf | ckf | iakf
    arbitration_sigma_hz: float = 2.0    # combined command when predicted Doppler 1-sigma < this
    prefilter_q: dict = field(default_factory=lambda: dict(DLB_PREFILTER_Q))
    rackf_period: int = 50               # RACKF robust-adaptive correction period, epochs
    huber_c: float = 1.5
    robust_mode: str = "every"           # RACKF: Huber step every epoch, adaptive factor every period
    rackf_kwargs: dict = field(default_factory=lambda: {"adaptive_stat": "window"})
    cn0_init_dbhz: float = 25.0          # assumed C/N0 for the prefilters' initial amplitude
    block_ms: int = 10                   # IF read block (noise estimate granularity)
    # noise-floor estimator: 0 = the estimate of each IF block alone (follows every noise change);
    # tau > 0 = exponential average of the block variances with this time constant (a slow
    # noise-floor tracker); inf = calibrated on the first block and then held.
    noise_tau_s: float = 0.0
    cic_order: int = 3
    pr_sigma_floor_m: float = 3.0        # tight filter pseudorange noise floor
    prr_sigma_floor_mps: float = 0.05    # tight filter pseudorange-rate noise floor
    meas_corr_factor: float = 10.0       # inflation of prefilter variances (correlated outputs)
    amp_min: float = 0.15                # channels below this amplitude estimate skip the update
    gate_sigma: float = 5.0
    code_sigma_margin_chips: float = 0.002   # added to the hot-start code sigma of the prefilters
    clock_q_drift: float = 1e-4          # (m/s)^2/s clock drift random walk in the tight filter
    phase_init_ms: int = 40              # startup coherent phase initialisation window (0: off)
    aid_time_offset_s: float = 0.5e-3    # aiding sampled at next-interval middle + this (see docs)
    # double loop: a channel whose rows are out of the tight filter (amplitude below amp_min) gets
    # the outer loop's Doppler as a frequency pseudo-measurement (variance sigma_i^2), see docs
    outer_freq_update: bool = False
    # engine-level signal monitor (not part of the paper's structure, off by default: the prefilters
    # must ride through fades themselves; see docs/ultratight.md "Signal monitor"):
    monitor_gates_tight: bool = False    # keep fading channels out of the tight filter (NCOs untouched)
    lock_monitor: bool = False           # coast (NCO on the outer loop alone) / restart on fades
    lock_window_ms: int = 300            # signal/lock monitor window
    lock_off_dbhz: float = 10.0          # coast (outer loop only) below this C/N0 (in-phase estimate)
    lock_on_dbhz: float = 16.5           # restart the prefilter above this C/N0 (coherent magnitude)
    cn0_min_dbhz: float = 10.0           # floor of the re-initialised amplitude
    reinit_sigma_f_hz: float = 0.3       # frequency 1-sigma after a phase (re)initialisation
    reinit_sigma_a_hzps: float = 0.3     # Doppler-rate 1-sigma after a (re)initialisation (aided)
    prefilter_kwargs: dict = field(default_factory=dict)   # extra PrefilterBank parameters
    startup: dict = field(default_factory=dict)   # StartupErrors overrides

    def as_dict(self):
        return asdict(self)


@dataclass
class EngineResult:
    method: str
    prns: list
    t_start: np.ndarray          # (n_ep, n_ch) s since the first sample
    doppler_hz: np.ndarray       # (n_ep, n_ch) estimate (NCO + prefilter)
    code_phase_chips: np.ndarray  # (n_ep, n_ch) estimate (NCO + prefilter), mod 1023
    amp: np.ndarray              # (n_ep, n_ch) prefilter amplitude estimate
    mode: np.ndarray             # (n_ep, n_ch) int8 MODE_*
    nav_t: np.ndarray            # (n_nav,) tight-update times
    nav_pos_e: np.ndarray        # (n_nav, 3)
    nav_vel_e: np.ndarray
    nav_clk: np.ndarray          # (n_nav, 2) bias m, drift m/s
    nav_sigma_doppler_hz: np.ndarray  # (n_nav, n_ch)
    runtime_s: float
    duration_s: float
    info: dict


# ---------------------------------------------------------------------------------------
# SINS + clock wrapper (ins.sins mechanisation; feedback of the tight filter's error state)
# ---------------------------------------------------------------------------------------
class InsClock:
    """Corrected SINS (``ins.sins.sins_step``) plus receiver-clock estimates."""

    def __init__(self, q_lb, vel_l, llh, clk_bias_m, clk_drift_mps):
        from ultratight.ins import sins
        self._sins = sins
        self.x = sins.make_state(q_lb, vel_l, llh)
        self.clk_b = float(clk_bias_m)
        self.clk_d = float(clk_drift_mps)
        self.bg = np.zeros(3)        # estimated gyro bias (rad/s), removed from the increments
        self.ba = np.zeros(3)        # estimated accelerometer bias (m/s^2)
        self.f_b = np.zeros(3)       # last specific force (body), for the error model
        self.w_b = np.zeros(3)

    def step(self, dtheta, dv, dt):
        dth = dtheta - self.bg * dt
        dvc = dv - self.ba * dt
        self.f_b = dvc / dt
        self.w_b = dth / dt
        self._sins.sins_step(self.x, dth, dvc, dt)
        self.clk_b += self.clk_d * dt

    @property
    def llh(self):
        return self.x[7:10]

    @property
    def vel_l(self):
        return self.x[4:7]

    @property
    def q_lb(self):
        return self.x[0:4]

    def pos_vel_e(self):
        from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
        lat, lon, h = self.x[7], self.x[8], self.x[9]
        C_el = dcm_ecef_from_enu(lat, lon)
        return np.asarray(llh_to_ecef(lat, lon, h)), C_el @ self.x[4:7], C_el

    def feedback(self, dx):
        """Apply the tight filter's error state (estimate minus truth) and clear it."""
        from ultratight.fusion import tight
        from ultratight.ins import error_model
        error_model.apply_feedback(self.x, dx)      # attitude, velocity, position
        self.bg += dx[tight.BG]
        self.ba += dx[tight.BA]
        self.clk_b -= dx[tight.CLK_B]
        self.clk_d -= dx[tight.CLK_D]


# ---------------------------------------------------------------------------------------
# the engine
# ---------------------------------------------------------------------------------------
class UltratightEngine:
    """Runs one method over an IF source + IMU data (see module docstring)."""

    def __init__(self, source, imu, ephs, prns, week, tow0_s, method=DEFAULT_METHOD, options=None,
                 init_state=None, rng=None, duration_s=None, signal=GPS_L1CA):
        self.method = check_method(method)
        self.signal = signal
        self.spec = method_spec(method)
        self.opt = options or EngineOptions()
        self.src = source
        self.imu = imu
        self.ephs = ephs
        self.prns = [int(p) for p in prns]
        self.week = int(week)
        self.tow0 = float(tow0_s)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.fs = float(source.fs_hz)
        self.if_hz = float(source.if_hz)
        avail = source.n_samples / self.fs
        imu_end = float(imu.t[-1])
        self.duration_s = min(avail, imu_end) if duration_s is None else min(float(duration_s), avail, imu_end)
        if init_state is None:
            raise ConfigError("engine: an initial INS state (init_state) is required for the hot start")
        self.init_state = init_state

    def run(self, progress=False):
        if self.spec.scalar:
            from ultratight.receiver.scenario_runner import run_scalar
            return run_scalar(self.src, self.prns, self.ephs, self.week, self.tow0, self.init_state,
                              self.duration_s)
        from ultratight.fusion import tight as tightmod
        from ultratight.fusion.innerloop import InnerLoop
        from ultratight.receiver.correlator import CorrelatorBank
        from ultratight.receiver.outer_loop import OuterLoop
        from ultratight.receiver.startup import BitWipeoff, first_period_ms, predict_channels

        opt = self.opt
        sgl = self.signal
        t_wall0 = time.perf_counter()
        n_ch = len(self.prns)
        fs = self.fs
        st = self.init_state
        rows = np.arange(n_ch)

        # ---- SINS + clock from the (perturbed) initial state
        ins = InsClock(st["q_lb"], st["vel_l"], st["llh"], st["clk_bias_m"], st["clk_drift_mps"])
        self.imu_noise = tightmod.imu_errors_from_meta(self.imu)
        imu_dt = 1.0 / float(self.imu.rate_hz)
        imu_t = np.asarray(self.imu.t, dtype=float)
        imu_dth = np.asarray(self.imu.dtheta_b, dtype=float)
        imu_dv = np.asarray(self.imu.dv_b, dtype=float)
        k_imu = 0                                  # next IMU sample to apply
        t_sins = float(getattr(self.imu, "t0", 0.0))

        # ---- hot start predictions (from the perturbed state, not truth)
        pos_e, vel_e, C_el = ins.pos_vel_e()
        pred0 = predict_channels(self.ephs, self.prns, self.week, self.tow0, pos_e, vel_e,
                                 ins.clk_b, ins.clk_d, signal=sgl)
        bank = CorrelatorBank(self.prns, fs, self.if_hz, self.src.is_complex)
        for ch, prn in enumerate(self.prns):
            bank.init_channel(ch, prn, pred0["code_phase_chips"][ch], pred0["doppler_hz"][ch], 0,
                              carr_phase_cycles=0.0, align=True)
        ms = first_period_ms(pred0["t_tx_tow"], pred0["code_phase_chips"], signal=sgl)
        wipe = BitWipeoff(self.ephs, self.prns, self.week, self.tow0, self.duration_s + 1.0, signal=sgl)

        # ---- tight filter
        P0 = tightmod.initial_covariance(ins.llh, st.get("sigmas", {}), self.imu_noise)
        tf = tightmod.TightFilter(P0, core=opt.tight_core, gate_sigma=opt.gate_sigma)
        lat, lon, h = ins.llh
        from ultratight.ins.earth import radii
        rm, rn = radii(lat)
        M_pos = tightmod.pos_error_to_enu(lat, h, rm, rn)

        # ---- outer loop (100 Hz predictions -> CIC -> 1 kHz)
        outer = OuterLoop(self.ephs, self.prns, self.week, self.tow0, self.duration_s + 0.5,
                          rate_hz=1.0 / imu_dt, cic_order=opt.cic_order)
        pr_now = outer.predict(t_sins, pos_e, vel_e, ins.clk_b, ins.clk_d)
        los_l = pr_now["los_e"] @ C_el
        sig_dopp = tightmod.doppler_sigma_hz(tf.P, los_l, sgl.wavelength_m)
        # initial acceleration from the first IMU interval (a trial SINS step on a copy)
        x_try = ins.x.copy()
        ins._sins.sins_step(x_try, imu_dth[0], imu_dv[0], float(imu_t[0] - t_sins))
        from ultratight.ins.earth import dcm_ecef_from_enu as _dcm
        acc0_e = (_dcm(x_try[7], x_try[8]) @ x_try[4:7] - vel_e) / float(imu_t[0] - t_sins)
        outer.prime(t_sins, pos_e, vel_e, acc0_e, ins.clk_b, ins.clk_d)
        # aiding for the first SINS interval: direct predictions
        for j in range(outer.ratio + 1):
            tj = j * 1e-3
            pj = outer.predict(t_sins + tj, pos_e + vel_e * tj + 0.5 * acc0_e * tj * tj, vel_e + acc0_e * tj,
                               ins.clk_b + ins.clk_d * tj, ins.clk_d)
            outer.aid_doppler[j] = pj["doppler_hz"]
            outer.aid_code_rate[j] = pj["code_rate_cps"]
        outer.push(t_sins, pos_e, vel_e, acc0_e, ins.clk_b, ins.clk_d)   # covers [10, 20) ms
        # exact predictions at SINS epochs for the residuals: ring of (t, cp, rate, f)
        ring_n = 64
        ring_t = np.full(ring_n, np.nan)
        ring_cp = np.zeros((ring_n, n_ch))
        ring_r = np.zeros((ring_n, n_ch))
        ring_f = np.zeros((ring_n, n_ch))
        ring_k = 0

        def ring_put(t, pr):
            nonlocal ring_k
            i = ring_k % ring_n
            ring_t[i] = t
            ring_cp[i] = pr["code_phase_chips"]
            ring_r[i] = pr["code_rate_cps"]
            ring_f[i] = pr["doppler_hz"]
            ring_k += 1

        ring_put(t_sins, pr_now)
        vel_e_prev = vel_e.copy()
        acc_e_prev = acc0_e.copy()
        have_acc = True

        # ---- prefilters + inner loop
        if self.spec.bank == "pbkf":
            from ultratight.fusion import pbkf
            pref = pbkf.PbKfBank(n_ch, cn0_dbhz_init=opt.cn0_init_dbhz)
            pref.reset(rows)
            inner = InnerLoop(n_ch, T=sgl.code_period_s, if_hz=self.if_hz)
        else:
            from ultratight.fusion.prefilter import PrefilterBank, default_initial_covariance
            kind = self.spec.bank
            pref = PrefilterBank(n_ch, kind=kind, q=opt.prefilter_q, huber_c=opt.huber_c,
                                 correction_period=opt.rackf_period, robust_mode=opt.robust_mode,
                                 cn0_dbhz_init=opt.cn0_init_dbhz,
                                 **(dict(opt.rackf_kwargs) if kind == "rackf" else {}), **opt.prefilter_kwargs)
            sig_code_chips = tightmod.code_sigma_m(tf.P, los_l, M_pos) / sgl.chip_m
            P_init = np.zeros((n_ch, 5, 5))
            base = default_initial_covariance(opt.cn0_init_dbhz, sgl.code_period_s)
            for ch in range(n_ch):
                P_init[ch] = base
                P_init[ch, 1, 1] = (sig_code_chips[ch] + opt.code_sigma_margin_chips) ** 2
                P_init[ch, 3, 3] = (2 * math.pi * (3.0 * sig_dopp[ch] + 0.5)) ** 2
                P_init[ch, 4, 4] = (2 * math.pi * 2.0) ** 2
            pref.reset(rows, P0=P_init)
            inner = InnerLoop(n_ch, T=sgl.code_period_s, if_hz=self.if_hz)

        # ---- NCO Doppler at the middle of each channel's first interval, aiding history consistent
        t1 = bank.sample_ptr / fs + 0.5 * sgl.code_period_s
        a1 = outer.aiding_at(t1)
        bank.carr_freq[:] = self.if_hz + a1
        bank.code_rate[:] = sgl.code_rate_cps(a1)
        aid_prev_ff = a1.copy()
        if opt.phase_init_ms <= 0:
            rate1 = (outer.aiding_at(t1 + sgl.code_period_s) - a1) / sgl.code_period_s
            inner.prime_aiding(pref, a1 - rate1 * sgl.code_period_s, rate1)

        # ---- records
        n_ep_max = int(self.duration_s * 1000.0 * 1.001) + 8
        rec_t = np.full((n_ep_max, n_ch), np.nan)
        rec_f = np.full((n_ep_max, n_ch), np.nan)
        rec_cp = np.full((n_ep_max, n_ch), np.nan)
        rec_a = np.full((n_ep_max, n_ch), np.nan)
        rec_mode = np.zeros((n_ep_max, n_ch), dtype=np.int8)
        nav = {"t": [], "pos_e": [], "vel_e": [], "clk": [], "sig": []}

        # ---- decimator accumulators (window of the tight filter)
        t_upd_step = 1.0 / opt.tight_rate_hz
        t_next_upd = t_upd_step
        acc = np.zeros((6, n_ch))          # decimator window sums: n, code, doppler, Ptt, Pff, amp
        D = np.ones(n_ch)
        aid = np.zeros(n_ch)
        ms = np.asarray(ms, dtype=np.int64).copy()
        init_left = int(opt.phase_init_ms)
        proxy = _BankProxy(pref)
        i_ptau, i_pf = pref.P_ITAU, pref.P_IF          # code / frequency error in the bank's covariance
        mode_aided = MODE_COMBINED if self.spec.double_loop else MODE_OUTER
        init_acc = np.zeros(n_ch, dtype=np.complex128)
        W = int(opt.lock_window_ms)
        lm_i = np.zeros((n_ch, W))
        lm_c = np.zeros((n_ch, W), dtype=np.complex128)
        lm_si = np.zeros(n_ch)
        lm_sc = np.zeros(n_ch, dtype=np.complex128)
        lm_ptr = np.zeros(1, dtype=np.int64)
        lm_count = np.zeros(n_ch, dtype=np.int64)
        present = np.ones(n_ch, dtype=np.bool_)
        lm_events = np.zeros(n_ch, dtype=np.int64)
        lm_phase = np.zeros(n_ch)
        thr_off = float(np.sqrt(2.0 * 10 ** (opt.lock_off_dbhz / 10.0) * sgl.code_period_s))
        thr_on = float(np.sqrt(2.0 * 10 ** (opt.lock_on_dbhz / 10.0) * sgl.code_period_s))
        n_lost_events = 0
        n_regained = 0
        xp_view = np.zeros((n_ch, 5))
        present_prev = np.ones(n_ch, dtype=np.bool_)
        gate_ok = np.ones(n_ch, dtype=np.bool_)
        restart_mask = np.zeros(n_ch, dtype=np.bool_)
        off_ring = np.zeros((W, n_ch))      # carrier NCO minus aiding (inner-loop offset) history
        rollback = np.zeros(n_ch)
        coast_any = False
        n_phase_inits = 0
        cp0 = np.zeros(n_ch)
        f0 = np.zeros(n_ch)

        # ---- IF buffer
        blk = int(round(opt.block_ms * 1e-3 * fs))
        n_total = int(min(self.src.n_samples, round(self.duration_s * fs)))
        stream = BlockStream(self.src, blk, floor=NoiseFloor(opt.noise_tau_s, blk / fs))
        per_max = int(math.ceil(fs * sgl.code_period_s * 1.001)) + 4
        use_aid = np.ones(n_ch, dtype=bool)
        mode_now = np.full(n_ch, mode_aided, dtype=np.int8)
        two_pi = 2.0 * math.pi
        k_ep = 0
        n_feedback = 0
        timing = {"correlate": 0.0, "prefilter": 0.0, "sins_outer": 0.0, "tight": 0.0}

        while True:
            sp = bank.sample_ptr
            sp_max = int(sp.max())
            hi = sp_max + per_max
            if hi > n_total or k_ep >= n_ep_max:
                break
            if not stream.ensure(hi, keep_from=int(sp.min())):
                break
            buf, buf_start = stream.buf, stream.buf_start
            # ---- SINS + outer loop run ahead so the aiding of the next interval exists
            tw = time.perf_counter()
            j_need = int((sp_max + per_max) / fs * 1000.0) + 2
            while outer.n_filled <= j_need and k_imu < imu_t.shape[0]:
                dt = imu_t[k_imu] - t_sins
                ins.step(imu_dth[k_imu], imu_dv[k_imu], dt)
                t_sins = imu_t[k_imu]
                k_imu += 1
                pos_e, vel_e, C_el = ins.pos_vel_e()
                acc_e = (vel_e - vel_e_prev) / dt
                jerk_e = (acc_e - acc_e_prev) / dt if have_acc else np.zeros(3)
                acc_e_prev = acc_e
                have_acc = True
                vel_e_prev = vel_e
                ring_put(t_sins, outer.predict(t_sins, pos_e, vel_e, ins.clk_b, ins.clk_d))
                # kinematics at the middle of the last interval -> extrapolate from there
                outer.push(t_sins, pos_e, vel_e, acc_e + 0.5 * dt * jerk_e, ins.clk_b, ins.clk_d, jerk_e)
            timing["sins_outer"] += time.perf_counter() - tw

            # ---- correlate one period per channel
            tw = time.perf_counter()
            cp0[:] = bank.code_phase
            f0[:] = bank.carr_freq
            sig = stream.sigma_at(sp)
            out, t_start, n_s = bank.step(buf, buf_start, sig)
            if n_s.min() <= 0:
                raise InputFileError(f"{self.src.path}: correlator could not integrate channels "
                                     f"{np.flatnonzero(n_s <= 0).tolist()} (buffer management)")
            timing["correlate"] += time.perf_counter() - tw
            tw = time.perf_counter()
            _wipe_bits(wipe.bits, wipe.t0_ms, ms, D, self.signal.codes_per_bit)
            restart = None
            init_now = init_left > 0
            if init_now:
                # carrier-phase initialisation: NCOs on the aiding only, coherent sum of wiped prompts
                init_acc += (out[:, 0] + 1j * out[:, 3]) * D
                init_left -= 1
                if init_left == 0:
                    restart = rows
                    restart_phase = np.angle(init_acc)
                    restart_amp = np.abs(init_acc) / opt.phase_init_ms
                    n_phase_inits += 1
            else:
                pref.step(out, bits=D)
                if opt.lock_monitor or opt.monitor_gates_tight:
                    present_prev[:] = present
                    _lock_monitor(out, D, lm_i, lm_c, lm_si, lm_sc, lm_ptr, lm_count, present, thr_off, thr_on,
                                  lm_events, lm_phase)
                    if not opt.lock_monitor:
                        # monitor used only to keep fading channels out of the tight filter
                        gate_ok[:] = present
                        present[:] = True
                        np.logical_or(lm_events > 0, False, out=restart_mask)
                        lm_events[:] = 0
                if opt.lock_monitor and lm_events.any():
                    lost = lm_events < 0
                    back = lm_events > 0
                    if lost.any():
                        n_lost_events += int(lost.sum())
                        # roll the carrier NCO's inner-loop offset back to its value before the
                        # monitor window (the prefilter fitted noise while the loss built up)
                        old = off_ring[lm_ptr[0] % W]
                        cur = bank.carr_freq - self.if_hz - aid
                        rollback[lost] = (old - cur)[lost]
                    if back.any():
                        n_regained += int(back.sum())
                        restart = np.flatnonzero(back)
                        restart_phase = lm_phase
                        restart_amp = np.abs(lm_sc) / W
                    coast_any = not present.all()
                    mode_now = np.where(present, np.where(use_aid, mode_aided, MODE_INNER),
                                        MODE_COAST).astype(np.int8)
            ff_any = init_now or coast_any or restart is not None   # NCO on the aiding only
            if ff_any:
                ff = np.ones(n_ch, dtype=bool) if init_now else ~present
                xp_view[:] = pref.x_post
                xp_view[ff | ~present_prev, 1:] = 0.0     # (a channel restarting now: estimate = NCO)
                xp_rec = xp_view
            else:
                xp_rec = pref.x_post
            _epoch_post(k_ep, t_start, fs, self.if_hz, f0, cp0, xp_rec, pref.P, i_ptau, i_pf,
                        ring_t, ring_cp, ring_r, ring_f, ring_k, imu_dt, t_next_upd, acc, rec_t, rec_f,
                        rec_cp, rec_a, rec_mode, mode_now, outer.aid_doppler, outer.n_filled,
                        bank.sample_ptr, 0.5 * sgl.code_period_s, float(sgl.code_length), aid,
                        opt.aid_time_offset_s)
            # ---- NCO commands for the next interval
            if restart is not None:
                t_code = sgl.code_period_s
                rate = (outer.aiding_at(bank.sample_ptr / fs + 1.5 * t_code) - aid) / t_code
                self._restart_channels(pref, inner, bank, restart, restart_phase, restart_amp, aid, rate)
                if init_now:
                    ff_any = False
                    init_now = False
            if ff_any:
                d_aid = np.where(ff, aid - aid_prev_ff, 0.0)
                bank.carr_freq += d_aid
                bank.code_rate[ff] = sgl.code_rate_cps(bank.carr_freq[ff] - self.if_hz)
                proxy.active = pref.active & ~ff
                inner.apply(proxy, bank, aid_doppler_hz=aid, use_aid=use_aid)
            else:
                inner.apply(pref, bank, aid_doppler_hz=aid, use_aid=use_aid)
            aid_prev_ff[:] = aid
            if opt.lock_monitor:
                if rollback.any():
                    bank.carr_freq += rollback
                    bank.code_rate[:] = sgl.code_rate_cps(bank.carr_freq - self.if_hz)
                    rollback[:] = 0.0
                off_ring[k_ep % W] = bank.carr_freq - self.if_hz - aid
            timing["prefilter"] += time.perf_counter() - tw

            # ---- tight filter update at the decimated rate, once every channel passed t_next_upd
            if t_start.min() >= t_next_upd * fs:
                tw = time.perf_counter()
                acc_n, acc_cp, acc_f, acc_pt, acc_pf, acc_a = acc
                ok = acc_n > 0
                nn = np.maximum(acc_n, 1)
                m_cp = acc_cp / nn
                m_f = acc_f / nn
                m_a = acc_a / nn
                dz_pr = sgl.chip_m * m_cp
                dz_prr = sgl.wavelength_m * m_f
                var_pr = sgl.chip_m ** 2 * (acc_pt / nn) * opt.meas_corr_factor + opt.pr_sigma_floor_m ** 2
                var_prr = (sgl.wavelength_m / two_pi) ** 2 * (acc_pf / nn) * opt.meas_corr_factor \
                    + opt.prr_sigma_floor_mps ** 2
                valid = ok & (np.abs(m_a) > opt.amp_min) & present & gate_ok   # (A < 0: half a cycle off)
                pos_e, vel_e, C_el = ins.pos_vel_e()
                lat, lon, h = ins.llh
                rm, rn = radii(lat)
                M_pos = tightmod.pos_error_to_enu(lat, h, rm, rn)
                los_l = ring_los(outer, pos_e, vel_e, ins, t_sins) @ C_el
                Phi, Qd = tightmod.phi_q(ins, t_upd_step, self.imu_noise, opt.clock_q_drift)
                tf.predict(Phi, Qd)
                dx = tf.update(dz_pr, dz_prr, los_l, M_pos, var_pr, var_prr, valid)
                dfp_all = np.zeros(n_ch)
                if np.any(dx != 0.0):
                    ins.feedback(dx)
                    tf.reset()
                    n_feedback += 1
                    # keep the residual predictions consistent with the corrected SINS
                    pos_e, vel_e, C_el = ins.pos_vel_e()
                    pr_fix = outer.predict(t_sins, pos_e, vel_e, ins.clk_b, ins.clk_d)
                    i1 = (ring_k - 1) % ring_n
                    half_code = 0.5 * sgl.code_length
                    dcp = np.mod(pr_fix["code_phase_chips"] - ring_cp[i1] + half_code, sgl.code_length) - half_code
                    dfp = pr_fix["doppler_hz"] - ring_f[i1]
                    ring_cp += dcp
                    ring_f += dfp
                    dfp_all = dfp
                    if self.spec.double_loop:
                        outer.offset_hz += dfp   # double loop: corrections do not jump the NCOs
                    ring_r[i1] = pr_fix["code_rate_cps"]
                    vel_e_prev = vel_e.copy()
                sig_dopp = tightmod.doppler_sigma_hz(tf.P, los_l, sgl.wavelength_m)
                if self.spec.double_loop:
                    use_aid = (sig_dopp < opt.arbitration_sigma_hz)
                if opt.outer_freq_update and self.spec.double_loop:
                    # frequency pseudo-measurement from the outer loop for channels the tight filter
                    # did not use (independent information: no double counting)
                    sel = ok & present & ~valid & pref.active & np.isfinite(m_f)
                    if sel.any():
                        _outer_freq_update(pref.x, pref.P, sel, m_f - dfp_all,
                                           (two_pi * sig_dopp) ** 2)
                mode_now = np.where(present, np.where(use_aid, mode_aided, MODE_INNER),
                                    MODE_COAST).astype(np.int8)
                nav["t"].append(t_sins)      # the SINS state logged is at t_sins (>= t_u)
                nav["pos_e"].append(pos_e.copy())
                nav["vel_e"].append(vel_e.copy())
                nav["clk"].append([ins.clk_b, ins.clk_d])
                nav["sig"].append(sig_dopp.copy())
                # start the next window with the epochs already past t_next_upd
                acc[:] = 0.0
                t_next_upd += t_upd_step
                timing["tight"] += time.perf_counter() - tw
            k_ep += 1
            if progress and k_ep % 5000 == 0:
                print(f"  {self.method}: {k_ep / 1000.0:6.1f} s", flush=True)

        runtime = time.perf_counter() - t_wall0
        n = k_ep
        info = {
            "options": self.opt.as_dict(),
            "wipeoff_mode": wipe.mode,
            "n_epochs": n,
            "n_tight_updates": tf.n_updates,
            "n_tight_rejected": tf.n_rejected,
            "n_feedback": n_feedback,
            "n_phase_inits": n_phase_inits,
            "n_lock_lost_events": n_lost_events,
            "n_prefilter_restarts": n_regained,
            "timing_s": timing,
            "prefilter": pref.describe(),
            "prefilter_resets": np.asarray(getattr(pref, "n_resets", np.zeros(n_ch))).tolist(),
            "arbitration_rule": "combined when sigma_doppler_i = sqrt(u'Pvv u + Pdd - 2u'Pvd)/lambda < "
                                f"{opt.arbitration_sigma_hz} Hz (tight filter P), else inner loop alone",
            "startup": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                        for k, v in st.items() if k.startswith("err_") or k == "sigmas"},
        }
        return EngineResult(
            method=self.method, prns=list(self.prns), t_start=rec_t[:n], doppler_hz=rec_f[:n],
            code_phase_chips=rec_cp[:n], amp=rec_a[:n], mode=rec_mode[:n],
            nav_t=np.asarray(nav["t"]), nav_pos_e=np.asarray(nav["pos_e"]).reshape(-1, 3),
            nav_vel_e=np.asarray(nav["vel_e"]).reshape(-1, 3), nav_clk=np.asarray(nav["clk"]).reshape(-1, 2),
            nav_sigma_doppler_hz=np.asarray(nav["sig"]).reshape(-1, n_ch), runtime_s=runtime,
            duration_s=n * sgl.code_period_s, info=info)

    def _restart_channels(self, pref, inner, bank, chans, phase, amp, aid, rate):
        """(Re)start channels' prefilters on a coherent carrier-phase estimate: rotate the carrier
        NCO by the phase of the coherent sum of the wiped prompts, restart the prefilter
        (amplitude from the coherent magnitude, startup-like covariance) and hand the aiding
        history to the inner loop (outer-loop Doppler rate injected into the acceleration state)."""
        chans = np.atleast_1d(np.asarray(chans))
        sgl = self.signal
        a_min = float(np.sqrt(2.0 * 10 ** (self.opt.cn0_min_dbhz / 10.0) * sgl.code_period_s))
        for c in chans:
            bank.carr_phase[c] = (bank.carr_phase[c] + phase[c] / (2.0 * math.pi)) % 1.0
        x0 = np.zeros((len(chans), 5))
        x0[:, 0] = np.maximum(amp[chans], a_min)
        # frequency error at the start of the next interval: the NCO still holds the last
        # interval's aided value while ``aid`` is the aiding of the next one, and the inner law
        # adds the injected rate (da T/2) itself -> df0 = aid - NCO keeps the channel's Doppler
        # continuous across the (re)start.  (df0 = 0 started the filter one aiding increment
        # off -- up to 0.5 Hz at 20 g -- which it then pulled in over ~0.5 s.)
        x0[:, 3] = 2.0 * math.pi * (aid[chans] - (bank.carr_freq[chans] - self.if_hz))
        if self.spec.bank == "pbkf":
            pref.reset(chans, x0=x0)
        else:
            from ultratight.fusion.prefilter import default_initial_covariance
            base = default_initial_covariance(self.opt.cn0_init_dbhz, sgl.code_period_s)
            P0 = np.zeros((len(chans), 5, 5))
            for i, c in enumerate(chans):
                P0[i] = base
                P0[i, 0, 0] = (0.3 * x0[i, 0]) ** 2
                P0[i, 1, 1] = pref.P[c, 1, 1] + self.opt.code_sigma_margin_chips ** 2
                P0[i, 2, 2] = 0.5 ** 2
                P0[i, 3, 3] = (2 * math.pi * self.opt.reinit_sigma_f_hz) ** 2
                P0[i, 4, 4] = (2 * math.pi * self.opt.reinit_sigma_a_hzps) ** 2
            pref.reset(chans, x0=x0, P0=P0)
        inner.prime_aiding(pref, aid - rate * sgl.code_period_s, rate, channels=chans)


def ring_los(outer, pos_e, vel_e, ins, t):
    """Unit lines of sight (ECEF) at the current SINS state."""
    return outer.predict(t, pos_e, vel_e, ins.clk_b, ins.clk_d)["los_e"]


# ---------------------------------------------------------------------------------------
# recorded data: IF file + IMU file
# ---------------------------------------------------------------------------------------
IMU_IF_TOLERANCE_S = 1e-3      # largest accepted IMU/IF start-time mismatch


def _imu_start_tow(imu):
    """GPS time (week, tow) of the IMU's t = 0, when the file says (None otherwise)."""
    meta = getattr(imu, "meta", None) or {}
    if "start_tow_s" in meta:
        return meta.get("start_week"), float(meta["start_tow_s"])
    cfg = meta.get("config_json")
    if isinstance(cfg, str):
        import json
        try:
            cfg = json.loads(cfg)
        except ValueError:
            cfg = None
    if isinstance(cfg, dict) and isinstance(cfg.get("time"), dict) and "tow_s" in cfg["time"]:
        return cfg["time"].get("week"), float(cfg["time"]["tow_s"])
    return None


def check_imu_if_alignment(src, imu, if_path="IF file", imu_path="IMU file", tol_s=IMU_IF_TOLERANCE_S):
    """Check that the IMU data can drive the SINS over the IF record; returns the usable duration.

    * stamps: finite, strictly increasing, no gaps (also checked by the IMU readers);
    * the IMU time axis starts at the first IF sample: ``t0 == 0`` and, when the IMU file carries
      a GPS start time, it equals the IF start time within ``tol_s``;
    * the IMU covers at least one SINS step of the IF record.
    Raises InputFileError naming the file and the offending values.
    """
    t = np.asarray(imu.t, dtype=float)
    if t.size < 2 or not np.all(np.isfinite(t)):
        raise InputFileError(f"{imu_path}: IMU time stamps missing or not finite")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0]) + 1
        raise InputFileError(f"{imu_path}: sample {i}: out-of-order or duplicate time stamp t = {t[i]!r} s "
                             f"(previous {t[i - 1]!r} s)")
    dt = 1.0 / float(imu.rate_hz)
    if np.any(np.abs(d - dt) > 0.25 * dt):
        i = int(np.flatnonzero(np.abs(d - dt) > 0.25 * dt)[0]) + 1
        raise InputFileError(f"{imu_path}: sample {i}: interval {d[i - 1]:.6g} s at t = {t[i]!r} s differs from "
                             f"the nominal {dt:.6g} s ({imu.rate_hz} Hz): gap or irregular sampling")
    t0 = float(getattr(imu, "t0", t[0] - dt))
    if abs(float(t[0]) - dt) > tol_s:
        raise InputFileError(f"{imu_path}: first IMU stamp t = {float(t[0]):.6g} s; the first increment must end "
                             f"one IMU interval ({dt:.6g} s) after the first IF sample (t = 0): IMU/IF time offset "
                             f"{float(t[0]) - dt:+.6g} s")
    if abs(t0) > tol_s:
        raise InputFileError(f"{imu_path}: IMU time axis starts at t0 = {t0:.6g} s but must start at the first IF "
                             f"sample (t0 = 0 within {tol_s} s); IMU/IF time offset {t0:.6g} s")
    st = _imu_start_tow(imu)
    if st is not None and src.start_tow_s is not None:
        w_imu, tow_imu = st
        off = tow_imu - float(src.start_tow_s)
        if w_imu is not None and src.start_week is not None:
            off += (int(w_imu) - int(src.start_week)) * 604800.0
        if abs(off) > tol_s:
            raise InputFileError(f"{imu_path}: IMU starts at GPS TOW {tow_imu:.6f} s but {if_path} starts at "
                                 f"{float(src.start_tow_s):.6f} s: IMU/IF time offset {off:+.6f} s "
                                 f"(tolerance {tol_s} s)")
    usable = min(src.duration_s, float(t[-1]))
    if usable < 2 * dt:
        raise InputFileError(f"{imu_path}: IMU data end at t = {t[-1]:.6g} s; they must cover the IF record "
                             f"({src.duration_s:.6g} s)")
    return usable


def run_ultratight_on_files(if_path, imu_path, method=DEFAULT_METHOD, meta=None, nav_path=None, prns=None,
                            init_state=None, options=None, duration_s=None, seed=0, startup_errors=None):
    """Run the ultra-tight engine on a recorded IF file and an IMU file (HDF5 or CSV).

    * ``meta``: sidecar/ION metadata for the IF file (default ``IFFILE.json``); the IF start time
      (``start_week``/``start_tow_s``) is required.
    * Ephemerides: ``nav_path`` (RINEX) or, for generator files, the sidecar's scenario
      (nominal constellation).  PRNs: ``prns`` or the sidecar's list.
    * Initial INS state: ``init_state`` dict (``llh``, ``vel_l``, ``q_lb``, ``clk_bias_m``,
      ``clk_drift_mps``) or, for generator files, the IMU file's truth at t0 perturbed by
      ``startup_errors`` (seeded by ``seed``) — the hot start never uses the truth itself.
    * Time alignment is checked by :func:`check_imu_if_alignment` (gaps, out-of-order stamps,
      IMU/IF offset -> InputFileError).
    Returns an :class:`EngineResult`.
    """
    from pathlib import Path
    from ultratight.ins.imu import read_imu_csv, read_imu_h5
    from ultratight.receiver.startup import StartupErrors, perturb_state
    from ultratight.signals.iffile import open_if
    if not method_spec(method).needs_imu:
        raise ConfigError(f"method {method!r} is the scalar receiver: use `ultratight process` without "
                          f"--mode ultratight")
    src = open_if(if_path, meta=meta)
    if src.start_tow_s is None or src.start_week is None:
        raise InputFileError(f"{if_path}: the IF start time (start_week, start_tow_s) is unknown; "
                             "give it in the sidecar/metadata")
    imu_path = Path(imu_path)
    imu = read_imu_csv(imu_path) if imu_path.suffix.lower() == ".csv" else read_imu_h5(imu_path)
    usable = check_imu_if_alignment(src, imu, if_path, imu_path)
    dur = usable if duration_s is None else min(float(duration_s), usable)
    side = src.meta or {}
    gen_cfg = side.get("generator") if isinstance(side.get("generator"), dict) else None
    week, tow0 = int(src.start_week), float(src.start_tow_s)
    if nav_path is not None:
        from ultratight.signals.rinex import read_rinex_nav
        nav = read_rinex_nav(nav_path)
        ephs = {}
        for prn in sorted(nav.ephemerides):
            try:
                e = nav.select(prn, week, tow0)
            except Exception:  # noqa: BLE001 - PRN without a usable ephemeris
                continue
            if e is not None:
                ephs[prn] = e
    elif gen_cfg is not None and gen_cfg.get("satellites", {}).get("source", "nominal") == "nominal":
        from ultratight.signals.constellation import nominal_ephemerides
        ephs = nominal_ephemerides(week, tow0)
    else:
        raise ConfigError(f"{if_path}: no ephemerides: give a RINEX navigation file (--ephemeris)")
    if prns is None:
        prns = side.get("prn")
    if not prns:
        raise ConfigError(f"{if_path}: no PRN list in the sidecar: give the PRNs to track (--prn)")
    missing = [p for p in prns if p not in ephs]
    if missing:
        raise ConfigError(f"no ephemeris for PRN {missing}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    if init_state is None:
        tr = getattr(imu, "truth", None)
        if not tr or "llh" not in tr:
            raise ConfigError(f"{imu_path}: no initial INS state: give init_state (position, velocity, attitude)")
        rcv = (gen_cfg or {}).get("receiver", {})
        truth0 = {"llh": np.asarray(tr["llh"][0]), "vel_l": np.asarray(tr["vel_l"][0]),
                  "q_lb": np.asarray(tr["q_lb"][0]), "clk_bias_m": float(rcv.get("clock_bias_m", 0.0)),
                  "clk_drift_mps": float(rcv.get("clock_drift_mps", 0.0))}
        init_state = perturb_state(truth0, startup_errors or StartupErrors(), rng)
    eng = UltratightEngine(src, imu, ephs, [int(p) for p in prns], week, tow0, method=method,
                           options=options, init_state=init_state, rng=rng, duration_s=dur)
    return eng.run()


def write_result_h5(path, res, extra_attrs=None):
    """Write an :class:`EngineResult` to HDF5 (built in memory, written under a unique temporary
    name, then renamed; schema in docs/ultratight.md). Disk errors raise OutputError."""
    import json
    from ultratight import __version__
    from ultratight.io_guard import write_h5_atomic

    def build(f):
        f.attrs["schema"] = "ultratight engine result v1 (docs/ultratight.md)"
        f.attrs["version"] = __version__
        f.attrs["method"] = res.method
        f.attrs["prn"] = np.asarray(res.prns, dtype=np.int64)
        f.attrs["runtime_s"] = float(res.runtime_s)
        f.attrs["duration_s"] = float(res.duration_s)
        f.attrs["info_json"] = json.dumps(res.info, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
        for k, v in (extra_attrs or {}).items():
            f.attrs[k] = v
        for k, v in (("t_start_s", res.t_start), ("doppler_hz", res.doppler_hz),
                     ("code_phase_chips", res.code_phase_chips), ("amplitude", res.amp), ("mode", res.mode),
                     ("nav_t_s", res.nav_t), ("nav_pos_e", res.nav_pos_e), ("nav_vel_e", res.nav_vel_e),
                     ("nav_clk", res.nav_clk), ("nav_sigma_doppler_hz", res.nav_sigma_doppler_hz)):
            f.create_dataset(k, data=np.asarray(v), compression="gzip", compression_opts=1)

    return write_h5_atomic(path, build)
