"""The double-loop ultra-tight receiver engine (Zhao et al. 2014, Fig. 1).

Stages, in the order of the paper's Fig. 1 (each a module of its own, arrays in and out)::

    IF block stream (receiver.blockstream, noise sigma per block)
      ─► correlator bank (receiver.correlator; its NCOs: signals.nco.NcoBank)
      ─► data wipe-off (receiver.wipeoff)
      ─► tracking bank (fusion.prefilter / fusion.pbkf, chosen by the method's spec in
         receiver.methods; the inner loop, 1 kHz)
      ─► inner-loop NCO command (fusion.innerloop; aiding increments from the outer loop
         when the arbitration allows)
      ─► residuals vs the SINS predictions ─► averaging decimator (fusion.rateconv.ResidualDecimator, 10 Hz)
      ─► tight 17-state filter (fusion.tight) ⇄ SINS + clock (receiver.sins_clock, 100 Hz, feedback)
      ─► outer loop (receiver.outer_loop: 100 Hz predictions, CIC to 1 kHz) ─► aiding of the next epochs
      ─► recorder (receiver.recorder); lock monitor (receiver.lockmon, optional)

The 1 kHz part runs compiled, many epochs per call (:func:`ultratight.receiver.deep.epochs.run_epochs`),
and hands back to :meth:`UltratightEngine.run` whenever the 100 Hz / 10 Hz part is due; the
start-up phase initialisation and the lock monitor's epochs take the same stages one epoch at a
time (:meth:`UltratightEngine._special_epoch`). The results do not depend on which path an epoch took.

Methods (all on the same IF/IMU data; each is a spec of the registry
:mod:`ultratight.receiver.deep.methods`, naming its tracking bank and loop structure):

* ``dlb-rackf`` (default), ``dlb-ckf``, ``dlb-ukf``, ``dlb-rackf-paper``: double loop — each
  channel's prefilter closes its own inner loop every epoch; the outer loop feeds the
  SINS-predicted Doppler *increments* forward into the carrier NCO (the code NCO rate is slaved
  to the carrier, so it is aided too).
* ``pb-kf-utc``: single loop baseline — discriminator outputs into a linear KF per channel
  (``ultratight.fusion.channel.pbkf``); the NCOs are driven by the outer loop only (absolute
  SINS-predicted Doppler and code phase, no inner loop).
* ``scalar``: the scalar tracking pipeline of receiver.tracking (no INS), for reference;
  :meth:`UltratightEngine.run` hands it to :func:`ultratight.receiver.deep.scalar_reference.run_scalar`.

Arbitration (double loop, logged per channel per epoch in ``mode``): after every tight
update the 1-sigma of each channel's predicted Doppler is computed from the tight filter
covariance, ``sigma_i = sqrt(u_i' P_vv u_i + P_dd - 2 u_i' P_vd) / lambda`` (velocity /
clock-drift block projected on the line of sight, :func:`ultratight.fusion.coupling.tight.doppler_sigma_hz`).
A channel uses the combined command (outer prediction + inner correction, ``MODE_COMBINED``) while
``sigma_i < arbitration_sigma_hz``, otherwise the inner loop alone (``MODE_INNER``). PB-KF-UTC
is always ``MODE_OUTER``.

Tracking estimates recorded per channel per epoch (for the paper's metrics): the Doppler
``carr_freq - IF + df/2pi`` and the code phase ``code_phase + dtau`` at the *start* of the
integration interval (the prefilter state refers to the interval start; see
ultratight.fusion.channel.prefilter), with their time ``t_start`` (s since the first sample).
References: docs/references.md.
"""

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numba
import numpy as np

from ultratight import __version__
from ultratight.errors import ConfigError, DivergenceError, FilterError, InputFileError
from ultratight.fusion.coupling import tight as tightmod
from ultratight.fusion.channel.innerloop import InnerLoop
from ultratight.fusion.channel.prefilter import IF as PREFILTER_IF
from ultratight.fusion.coupling.rateconv import ResidualDecimator
from ultratight.ins.earth import radii
from ultratight.ins import imu_decl
from ultratight.io_guard import write_h5_atomic
from ultratight.receiver.deep import epochs
from ultratight.receiver.dsp.blockstream import BlockStream, NoiseFloor
from ultratight.receiver.dsp.burst import burst_all, make_burst
from ultratight.receiver.dsp.correlator import CorrelatorBank
from ultratight.receiver.deep.epochs import (CONTINUE, END, ERR_BANK, ERR_CORR, NEED_IF, NEED_SINS, TIGHT,
                                        correlate, epoch_gate, epoch_post, run_epochs)
from ultratight.receiver.dsp.lockmon import LockMonitor, amplitude_threshold
from ultratight.receiver.deep.methods import DEFAULT_METHOD, METHODS, check_method, method_spec  # noqa: F401
from ultratight.receiver.deep.outer_loop import OuterLoop, SinsFollower
from ultratight.receiver.deep.recorder import EngineResult, EpochRecorder  # noqa: F401 (EngineResult: public here)
from ultratight.receiver.deep.scalar_reference import run_scalar
from ultratight.receiver.deep.sins_clock import InsClock  # noqa: F401 (public here too)
from ultratight.receiver.deep.bitsources import bit_source, check_strategy, decoded_from_pass
from ultratight.receiver.deep.startup import StartupErrors, first_period_ms, perturb_state, predict_channels
from ultratight.receiver.deep.tracking_banks import bank_view, make_tracking_bank, restart_covariance
from ultratight.receiver.dsp.wipeoff import BIT_SOURCE_NAMES, DataWipeoff
from ultratight.cores import stage_threads
from ultratight.signals.constellation import nominal_ephemerides
from ultratight.signals.ephemeris import sat_state
from ultratight.signals.recording.iffile import open_if
from ultratight.signals.rinex import read_rinex_nav
from ultratight.signals.signal import GPS_L1CA

__all__ = ["EngineOptions", "EngineResult", "UltratightEngine", "NoiseFloor", "BlockStream", "MODE_INNER",
           "MODE_COMBINED", "MODE_OUTER", "MODE_COAST", "monitor_options", "monitor_mode",
           "check_imu_if_alignment", "run_ultratight_on_files", "write_result_h5"]

PEND_EPOCHS = 256   # most epochs the compiled runner runs before summing their residuals

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
    for c in np.flatnonzero(sel):
        s_ = P[c, PREFILTER_IF, PREFILTER_IF] + r_var[c]
        if not (s_ > 0.0):
            continue
        k = P[c, :, PREFILTER_IF] / s_
        x[c] += k * (-2.0 * math.pi * resid_hz[c])
        P[c] -= np.outer(k, P[c, PREFILTER_IF, :])
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
    # noise events inside the receiver (receiver.burst): [[noise_events]] entries whose place is
    # "correlator" or "filter-r" ("if" ones are the generator's), and the seed of the correlator noise
    noise_events: list = field(default_factory=list)
    noise_seed: int = 0
    startup: dict = field(default_factory=dict)   # StartupErrors overrides
    threads: int = 0                     # epoch-stage threads: 0 = auto (epoch_threads), 1 = one, k = k
    # navigation-data bits (receiver.bitsources): assisted | decoded | blind | path of a bit file
    bits: str = "assisted"

    def as_dict(self):
        return asdict(self)


def epoch_threads(requested):
    """Threads for the compiled epoch stages (:func:`ultratight.cores.stage_threads`)."""
    return stage_threads(requested)


class EpochState:
    """What the engine's Python side carries from epoch to epoch (per channel unless noted)."""

    def __init__(self, n_ch, mode_aided, opt):
        self.k_ep = 0                                      # epochs run
        self.mode_aided = mode_aided
        self.mode_now = np.full(n_ch, mode_aided, dtype=np.int8)
        self.use_aid = np.ones(n_ch, dtype=np.bool_)       # arbitration: combined command allowed
        self.aid = np.zeros(n_ch)                          # outer-loop Doppler of the next interval
        self.aid_prev_ff = np.zeros(n_ch)                  # ... of the last interval
        self.sig_dopp = np.zeros(n_ch)                     # predicted Doppler 1-sigma (tight filter)
        self.present = np.ones(n_ch, dtype=np.bool_)       # lock monitor: signal present
        self.present_prev = np.ones(n_ch, dtype=np.bool_)
        self.gate_ok = np.ones(n_ch, dtype=np.bool_)       # monitor gate of the tight-filter rows
        self.restart_mask = np.zeros(n_ch, dtype=np.bool_)
        self.coast_any = False
        self.init_left = int(opt.phase_init_ms)            # start-up phase-initialisation epochs left
        self.init_acc = np.zeros(n_ch, dtype=np.complex128)
        self.init_bit = np.zeros(n_ch, dtype=np.complex128)   # ... per bit (channels with unknown bits)
        self.init_sq = np.zeros(n_ch, dtype=np.complex128)    # sum of the squared per-bit sums
        self.init_nb = np.zeros(n_ch, dtype=np.int64)
        self.init_n2 = np.zeros(n_ch, dtype=np.int64)
        self.init_kb = np.full(n_ch, -1, dtype=np.int64)
        self.rollback = np.zeros(n_ch)
        self.off_ring = np.zeros((int(opt.lock_window_ms), n_ch))   # carrier NCO minus aiding history
        self.xp_view = np.zeros((n_ch, 5))
        self.counts = {"n_feedback": 0, "n_phase_inits": 0, "n_lock_lost_events": 0, "n_prefilter_restarts": 0}
        self.timing = {"epochs": 0.0, "special_epochs": 0.0, "sins_outer": 0.0, "tight": 0.0}

    def special(self, opt):
        """The next epoch needs the one-epoch path (start-up initialisation or the lock monitor)."""
        return self.init_left > 0 or opt.lock_monitor or opt.monitor_gates_tight


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

    # ------------------------------------------------------------------ the run
    def run(self, progress=False):
        if self.spec.scalar:
            # the scalar pipeline has no INS: it is the scenario's reference receiver
            return run_scalar(self.src, self.prns, self.ephs, self.week, self.tow0, self.init_state,
                              self.duration_s)
        t_wall0 = time.perf_counter()
        st = self._build()
        while True:
            tw = time.perf_counter()
            if st.special(self.opt):
                status = self._special_epoch(st)
                st.timing["special_epochs"] += time.perf_counter() - tw
            else:
                status, st.k_ep, info = run_epochs(st.k_ep, *self._stage_views(st))
                st.timing["epochs"] += time.perf_counter() - tw
                self._check_status(status, info)
            if status == END or (status == NEED_IF and not self._read_if()):
                break
            if status == NEED_SINS:
                self._advance_sins(st)
            elif status == TIGHT:
                self._tight_update(st)
            if progress and status == TIGHT and st.k_ep // 5000 != (st.k_ep - 100) // 5000:
                print(f"  {self.method}: {st.k_ep / 1000.0:6.1f} s", flush=True)
        runtime = time.perf_counter() - t_wall0
        res = self.rec.result(self.method, self.prns, st.k_ep, runtime, self.signal.code_period_s, self._info(st))
        res.bit_source = self.wipe.rec_src[:st.k_ep]
        return res

    def _check_status(self, status, info):
        if status == ERR_CORR:
            c = self.corr_view
            bad = np.flatnonzero(c.n_s <= 0)
            off = ", ".join(f"{x:.3g}" for x in c.carr_freq[bad] - self.if_hz)
            raise DivergenceError(f"{self.src.path}: correlator could not integrate channels {bad.tolist()}: their "
                              f"NCOs left the IF buffer (carrier {off} Hz; sample pointers "
                              f"{c.sample_ptr[bad].tolist()} against {int(c.sample_ptr.min())}): tracking ran away")
        if status == ERR_BANK:
            raise FilterError(f"tracking bank step: non-finite measurement or bit on active channel {info}: "
                              f"z={self.corr_view.out[info, :6]}, bit={self.wipe.D[info]}")

    # ------------------------------------------------------------------ building the stages
    def _build(self):
        opt, sgl = self.opt, self.signal
        n_ch = len(self.prns)
        st = self.init_state
        self.ins = InsClock(st["q_lb"], st["vel_l"], st["llh"], st["clk_bias_m"], st["clk_drift_mps"])
        self.imu_noise = tightmod.imu_errors_from_meta(self.imu)
        self.imu_dt = 1.0 / float(self.imu.rate_hz)
        self.imu_t = np.asarray(self.imu.t, dtype=float)
        self.imu_dth = np.asarray(self.imu.dtheta_b, dtype=float)
        self.imu_dv = np.asarray(self.imu.dv_b, dtype=float)
        self.k_imu = 0                                  # next IMU sample to apply
        t_sins = float(getattr(self.imu, "t0", 0.0))
        lever = np.asarray(getattr(self.imu, "lever_arm_b", np.zeros(3)), dtype=float)
        if np.any(lever):          # antenna away from the IMU: predictions and H at the antenna
            self.ins.lever_b = lever
            self.ins.w_b = self.imu_dth[0] / float(self.imu_t[0] - t_sins)
        # hot start predictions (from the perturbed state, not truth)
        pos_e, vel_e, C_el = self.ins.antenna_pos_vel_e()
        pred0 = predict_channels(self.ephs, self.prns, self.week, self.tow0, pos_e, vel_e,
                                 self.ins.clk_b, self.ins.clk_d, signal=sgl)
        # a hand-over from tracking channels (ultratight.receiver.deep.handover) gives their code phases
        # at sample 0: the NCOs start there instead of the prediction (no re-acquisition either way)
        cp_given = st.get("code_phase_chips") or {}
        self.cp_given = np.array([int(p) in cp_given for p in self.prns])
        for ch, prn in enumerate(self.prns):
            if int(prn) in cp_given:
                pred0["code_phase_chips"][ch] = float(cp_given[int(prn)])
        self.corr = CorrelatorBank(self.prns, self.fs, self.if_hz, self.src.is_complex, signal=sgl)
        for ch, prn in enumerate(self.prns):
            self.corr.init_channel(ch, prn, pred0["code_phase_chips"][ch], pred0["doppler_hz"][ch], 0,
                                   carr_phase_cycles=0.0, align=True)
        self.ms0 = first_period_ms(pred0["t_tx_tow"], pred0["code_phase_chips"], signal=sgl)
        strategy, bits_path = check_strategy(opt.bits)
        if strategy == "decoded":
            source = self._decoding_pass()
        else:
            source = bit_source(strategy, bits_path, src=self.src, ephs=self.ephs, prns=self.prns, week=self.week,
                                tow_start_s=self.tow0, duration_s=self.duration_s + 1.0, pred0=pred0,
                                cn0_dbhz=opt.cn0_init_dbhz, signal=sgl)
        self.wipe = DataWipeoff(source, self.ms0.copy(), sgl.codes_per_bit, n_ep_max=self._n_ep_max(),
                                half_t=0.5 * sgl.code_period_s)
        P0 = tightmod.initial_covariance(self.ins.llh, st.get("sigmas", {}), self.imu_noise)
        self.tf = tightmod.TightFilter(P0, core=opt.tight_core, gate_sigma=opt.gate_sigma)
        self.outer = OuterLoop(self.ephs, self.prns, self.week, self.tow0, self.duration_s + 0.5, signal=sgl,
                               rate_hz=1.0 / self.imu_dt, cic_order=opt.cic_order)
        self.follow = SinsFollower(self.outer, self.ins, t_sins, self.imu_dth[0], self.imu_dv[0],
                                   float(self.imu_t[0] - t_sins), sgl.code_period_s)
        los_l = self.follow.first["los_e"] @ C_el
        es = EpochState(n_ch, MODE_COMBINED if self.spec.double_loop else MODE_OUTER, opt)
        es.sig_dopp = tightmod.doppler_sigma_hz(self.tf.P, los_l, sgl.wavelength_m)
        self._build_tracking(es, los_l)
        self._build_records(es)
        self.rec.set_sigma(self.tf.P, self.ins.llh)
        self.rec.log_sins(t_sins, self.ins.x, self.ins.clk_b, self.ins.clk_d)
        return es

    def _build_tracking(self, es, los_l):
        """Tracking bank + inner loop, and the NCOs at the aiding of each channel's first interval."""
        opt, sgl = self.opt, self.signal
        n_ch = len(self.prns)
        lat, _, h = self.ins.llh
        rm, rn = radii(lat)
        M_pos = tightmod.pos_error_to_enu(lat, h, rm, rn)
        sig_code_chips = tightmod.code_sigma_m(self.tf.P, los_l, M_pos) / sgl.chip_m
        if self.cp_given.any():
            sig_code_chips = np.where(self.cp_given, float(self.init_state.get("code_sigma_m", 3.0)) / sgl.chip_m,
                                      sig_code_chips)
        self.pref = make_tracking_bank(self.spec, n_ch, opt, (sig_code_chips, es.sig_dopp), sgl)
        self.inner = InnerLoop(n_ch, T=sgl.code_period_s, if_hz=self.if_hz, signal=sgl)
        # NCO Doppler at the middle of each channel's first interval, aiding history consistent
        t1 = self.corr.sample_ptr / self.fs + 0.5 * sgl.code_period_s
        a1 = self.outer.aiding_at(t1)
        self.corr.carr_freq[:] = self.if_hz + a1
        self.corr.code_rate[:] = sgl.code_rate_cps(a1)
        es.aid_prev_ff[:] = a1
        if opt.phase_init_ms <= 0:
            rate1 = (self.outer.aiding_at(t1 + sgl.code_period_s) - a1) / sgl.code_period_s
            self.inner.prime_aiding(self.pref, a1 - rate1 * sgl.code_period_s, rate1)

    def _build_records(self, es):
        """Recorder, decimator, lock monitor, IF block stream and the stage views."""
        opt, sgl = self.opt, self.signal
        n_ch = len(self.prns)
        self.rec = EpochRecorder(self._n_ep_max(), n_ch)
        self.dec = ResidualDecimator(n_ch, opt.tight_rate_hz)
        self.pend = np.zeros((PEND_EPOCHS, n_ch, 6))          # residual inputs of epochs run, not yet summed
        self.pend_ts = np.zeros((PEND_EPOCHS, n_ch), dtype=np.int64)
        self.mon = LockMonitor(n_ch, opt.lock_window_ms, opt.lock_off_dbhz, opt.lock_on_dbhz, sgl.code_period_s)
        self.mon.present = es.present           # one presence mask: the monitor's verdicts are the engine's
        blk = int(round(opt.block_ms * 1e-3 * self.fs))
        self.n_total = int(min(self.src.n_samples, round(self.duration_s * self.fs)))
        self.stream = BlockStream(self.src, blk, floor=NoiseFloor(opt.noise_tau_s, blk / self.fs))
        per_max = int(math.ceil(self.fs * sgl.code_period_s * 1.001)) + 4
        self.threads = epoch_threads(opt.threads)
        if self.threads > 1:
            numba.set_num_threads(self.threads)
        c = self.corr
        z = np.zeros((n_ch, c.n_cols))
        self.corr_view = epochs.Corr(
            c.code_ext, c.pad, c.active, c.sample_ptr, c.code_phase, c.code_rate, c.carr_phase, c.carr_freq, self.fs,
            c.tap_offsets_chips, per_max, self.threads > 1, z, np.zeros(n_ch, np.int64), np.zeros(n_ch, np.int64),
            np.zeros(n_ch), np.zeros(n_ch), np.zeros(n_ch))
        w = self.wipe
        self.wipe_view = epochs.Wipe(*w.view_args(), w.half_t)
        self.bank_view = bank_view(self.pref)
        r = self.rec
        self.rec_view = epochs.Rec(r.t, r.f, r.cp, r.a, r.mode, es.mode_now, r.n_ep_max)
        law = self.inner
        self.law_view = epochs.Law(es.aid, law.aid_prev, law.rate_prev, law.hist, es.use_aid, law.prm, law.dx,
                                   es.aid_prev_ff)
        self.sig_view = epochs.Sig(self.if_hz, 0.5 * sgl.code_period_s, float(sgl.code_length))
        self.burst = make_burst(opt.noise_events, n_ch, c.tap_offsets_chips[:3], sgl.code_period_s, opt.noise_seed)

    def _decoding_pass(self):
        """``decoded`` bits: the same method with blind bits over the same data first; its per-bit soft
        decisions go through the LNAV decoder (receiver.bitsources.decoded_from_pass)."""
        t0 = time.perf_counter()
        first = UltratightEngine(self.src, self.imu, self.ephs, self.prns, self.week, self.tow0, method=self.method,
                                 options=replace(self.opt, bits="blind"), init_state=self.init_state, rng=self.rng,
                                 duration_s=self.duration_s, signal=self.signal)
        first.run()
        source = decoded_from_pass(first.wipe, self.prns, self.tow0, self.duration_s + 1.0, self.signal)
        source.info["decoding_pass_s"] = round(time.perf_counter() - t0, 3)
        return source

    def _n_ep_max(self):
        """Rows of the per-epoch records."""
        return int(self.duration_s * 1000.0 * 1.001) + 8

    def _stage_views(self, st):
        """The arguments of the compiled epoch stages after :attr:`corr_view` etc.: the views whose
        scalars change between calls (IF buffer, SINS progress, decimator window)."""
        s = self.stream
        n_sig = s._n_sigma
        src = epochs.If(s.buf.view(np.float32), s.is_complex, int(s.buf_start), int(s.buf.shape[0]), self.n_total,
                        s.block_len, s._sigma[:max(n_sig, 1)])
        ring = self.follow.ring
        outer = epochs.Outer(ring.t, ring.cp, ring.r, ring.f, ring.nf, ring.k, self.imu_dt, self.outer.aid_doppler,
                             self.outer.n_filled, self.opt.aid_time_offset_s, self.k_imu < self.imu_t.shape[0])
        window = epochs.Window(self.dec.t_next, self.dec.acc, self.pend, self.pend_ts)
        return (src, self.corr_view, self.wipe_view, self.bank_view, outer, window, self.rec_view, self.law_view,
                self.sig_view, self.burst)

    # ------------------------------------------------------------------ 100 Hz: IF blocks, SINS + outer loop
    def _read_if(self):
        """Read IF blocks for the next epoch — and on to the end of the decimator window, so the epochs
        up to there can run in one compiled call; False at the end of the file."""
        sp = self.corr.sample_ptr
        pm = self.corr_view.per_max
        hi = int(sp.max()) + pm
        ahead = min(self.n_total, max(hi, int(math.ceil(self.dec.t_next * self.fs)) + 2 * pm))
        self.stream.ensure(ahead, keep_from=int(sp.min()))
        return hi <= self.stream.buf_end

    def _advance_sins(self, st):
        """SINS + outer loop run ahead until the aiding of the next interval exists — and on to what
        they will have reached anyway when the next tight update comes.

        The SINS state at a tight update (where the feedback lands) must be the one of a loop that
        steps the SINS only when an epoch needs its aiding: the SINS runs while the aiding grid ends
        at or before ``j_need`` of the epoch about to run, and ``j_need`` never decreases. The epoch
        of the next update starts with every channel past the window end, so its ``j_need`` is at
        least that of a channel exactly at the window end (``j_lb``); stepping up to ``j_lb`` early
        is what that loop would have done by then, and lets the epochs up to the window end run in
        one compiled call. Each epoch's residuals are formed against the SINS prediction that loop
        would have had as its latest (``epochs.ring_latest_for``)."""
        tw = time.perf_counter()
        pm = self.corr_view.per_max
        sp_max = int(self.corr.sample_ptr.max())
        j_lb = int((int(math.ceil(self.dec.t_next * self.fs)) + pm) / self.fs * 1000.0) + 2
        j_need = max(int((sp_max + pm) / self.fs * 1000.0) + 2, j_lb)
        while self.outer.n_filled <= j_need and self.k_imu < self.imu_t.shape[0]:
            k = self.k_imu
            dt = self.imu_t[k] - self.follow.t
            self.ins.step(self.imu_dth[k], self.imu_dv[k], dt)
            self.k_imu += 1
            self.follow.step(self.imu_t[k], dt)
            self.rec.log_sins(self.imu_t[k], self.ins.x, self.ins.clk_b, self.ins.clk_d)
        st.timing["sins_outer"] += time.perf_counter() - tw

    # ------------------------------------------------------------------ 10 Hz: tight filter
    def _tight_update(self, st):
        """Decimated residuals -> tight filter -> SINS/clock feedback -> outer loop correction ->
        arbitration; logs the navigation state."""
        tw = time.perf_counter()
        opt, sgl, ins = self.opt, self.signal, self.ins
        m = self.dec.means(sgl.chip_m, sgl.wavelength_m, opt.meas_corr_factor, opt.pr_sigma_floor_m,
                           opt.prr_sigma_floor_mps)
        valid = m["ok"] & (np.abs(m["amp"]) > opt.amp_min) & st.present & st.gate_ok   # (A < 0: half a cycle off)
        _, _, C_el = ins.pos_vel_e()
        lat, _, h = ins.llh
        rm, rn = radii(lat)
        M_pos = tightmod.pos_error_to_enu(lat, h, rm, rn)
        los_l = self.follow.los_e() @ C_el
        Phi, Qd = tightmod.phi_q(ins, self.dec.step_s, self.imu_noise, opt.clock_q_drift)
        self.tf.predict(Phi, Qd)
        dx = self.tf.update(m["dz_pr"], m["dz_prr"], los_l, M_pos, m["var_pr"], m["var_prr"], valid,
                            lever=ins.lever_terms())
        dfp_all = np.zeros(len(self.prns))
        if np.any(dx != 0.0):
            ins.feedback(dx)
            self.tf.reset()
            st.counts["n_feedback"] += 1
            dfp_all = self.follow.apply_correction(sgl.code_length, self.spec.double_loop)
        st.sig_dopp = tightmod.doppler_sigma_hz(self.tf.P, los_l, sgl.wavelength_m)
        self.rec.set_sigma(self.tf.P, ins.llh)
        self.rec.log_sins(self.follow.t, ins.x, ins.clk_b, ins.clk_d, replace=True)   # the step the feedback landed on
        if self.spec.double_loop:
            st.use_aid[:] = st.sig_dopp < opt.arbitration_sigma_hz
        if opt.outer_freq_update and self.spec.double_loop:
            # frequency pseudo-measurement from the outer loop for channels the tight filter
            # did not use (independent information: no double counting)
            sel = m["ok"] & st.present & ~valid & self.pref.active & np.isfinite(m["doppler_hz"])
            if sel.any():
                _outer_freq_update(self.pref.x, self.pref.P, sel, m["doppler_hz"] - dfp_all,
                                   (2.0 * math.pi * st.sig_dopp) ** 2)
        self._set_modes(st)
        pos_e, vel_e, _ = ins.pos_vel_e()
        self.rec.log_nav(self.follow.t, pos_e, vel_e, ins.clk_b, ins.clk_d, st.sig_dopp)  # SINS time >= update
        self.dec.next_window()      # the next window starts with the epochs already past its start
        st.timing["tight"] += time.perf_counter() - tw

    def _set_modes(self, st):
        st.mode_now[:] = np.where(st.present, np.where(st.use_aid, st.mode_aided, MODE_INNER), MODE_COAST)

    # ------------------------------------------------------------------ one epoch at a time
    def _special_epoch(self, st):
        """One epoch through the same stages as :func:`ultratight.receiver.deep.epochs.run_epochs`, with the
        start-up phase initialisation (NCOs on the aiding alone, coherent sum of the wiped prompts,
        then a restart of every channel) and the lock monitor (coast, restart)."""
        src, corr, _, bank, outer, window, rec, _, sig, burst = self._stage_views(st)
        status = epoch_gate(st.k_ep, src, corr, outer, rec)
        if status != CONTINUE:
            return status
        if not correlate(src, corr, sig):
            self._check_status(ERR_CORR, 0)
        burst_all(st.k_ep, corr.t_start, corr.fs, burst, corr.out)
        init_now = st.init_left > 0
        D = self.wipe.step(corr.out, self.pref.x, st.k_ep)
        restart = self._measure(st, corr.out, D, init_now)
        ff = None               # channels whose NCO follows the outer-loop aiding alone this epoch
        xp_rec = self.pref.x_post
        if init_now or st.coast_any or restart is not None:
            ff = np.ones(len(self.prns), dtype=bool) if init_now else ~st.present
            st.xp_view[:] = self.pref.x_post
            st.xp_view[ff | ~st.present_prev, 1:] = 0.0     # (a channel restarting now: estimate = NCO)
            xp_rec = st.xp_view
        epoch_post(st.k_ep, corr.t_start, corr.fs, sig.if_hz, corr.f0, corr.cp0, xp_rec, bank.P, bank.i_ptau,
                   bank.i_pf, corr.per_max, outer, window, rec.rec_t, rec.rec_f, rec.rec_cp, rec.rec_a, rec.rec_mode,
                   st.mode_now, corr.sample_ptr, sig, st.aid, outer.aid_dt, window.pend, window.pend_ts)
        if restart is not None:
            self._restart_channels(st, *restart)
            if init_now:
                ff = None
        self._command(st, ff)
        st.k_ep += 1
        return TIGHT if corr.t_start.min() >= window.t_next_upd * corr.fs else CONTINUE

    def _measure(self, st, out, D, init_now):
        """The tracking bank's epoch (or the start-up phase initialisation's coherent sum) and the
        lock monitor. Returns ``(channels, phase, amplitude)`` of channels to restart now, or None."""
        opt = self.opt
        if init_now:
            # carrier-phase initialisation: NCOs on the aiding only, coherent sum of wiped prompts
            zc = out[:, 0] + 1j * out[:, 3]
            st.init_acc += zc * D
            w = self.wipe
            if w.adaptive:
                # channels with unknown bits: coherent sums per bit, squared (two-quadrant: the
                # 180 degree ambiguity is the wipe stage's polarity to resolve)
                a = w.adapt
                new = a & (w.kb != st.init_kb)
                st.init_sq[new] += st.init_bit[new] ** 2
                st.init_n2[new] += st.init_nb[new] ** 2
                st.init_bit[new] = 0.0
                st.init_nb[new] = 0
                st.init_kb[new] = w.kb[new]
                st.init_bit[a] += zc[a]
                st.init_nb[a] += 1
            st.init_left -= 1
            if st.init_left == 0:
                st.counts["n_phase_inits"] += 1
                phase, amp = np.angle(st.init_acc), np.abs(st.init_acc) / opt.phase_init_ms
                if w.adaptive:
                    a = w.adapt
                    sq = st.init_sq + st.init_bit ** 2
                    n2 = st.init_n2 + st.init_nb ** 2
                    phase[a] = 0.5 * np.angle(sq[a])
                    amp[a] = np.sqrt(np.abs(sq[a]) / np.maximum(n2[a], 1))
                return np.arange(len(self.prns)), phase, amp
            return None
        self.pref.step(out, bits=D, rscale=self.burst.rscale)
        if not (opt.lock_monitor or opt.monitor_gates_tight):
            return None
        st.present_prev[:] = st.present
        events = self.mon.update(out, D)
        if not opt.lock_monitor:
            # monitor used only to keep fading channels out of the tight filter
            st.gate_ok[:] = st.present
            st.present[:] = True
            np.logical_or(events > 0, False, out=st.restart_mask)
            events[:] = 0
            return None
        return self._monitor_events(st, events)

    def _monitor_events(self, st, events):
        """Lost channels coast on the aiding (the carrier NCO's inner-loop offset rolled back to its
        value before the monitor window); regained ones restart on the coherent phase."""
        if not events.any():
            return None
        mon = self.mon
        restart = None
        lost = events < 0
        back = events > 0
        if lost.any():
            st.counts["n_lock_lost_events"] += int(lost.sum())
            old = st.off_ring[mon.ptr[0] % mon.W]
            cur = self.corr.carr_freq - self.if_hz - st.aid
            st.rollback[lost] = (old - cur)[lost]
        if back.any():
            st.counts["n_prefilter_restarts"] += int(back.sum())
            restart = np.flatnonzero(back), mon.phase, np.abs(mon.coherent_sum) / mon.W
        st.coast_any = not st.present.all()
        self._set_modes(st)
        return restart

    def _command(self, st, ff):
        """NCO commands for the next interval: the inner loop's (with the outer-loop aiding where the
        arbitration allows); channels in ``ff`` follow the aiding increments alone."""
        sgl, corr = self.signal, self.corr
        if ff is not None:
            d_aid = np.where(ff, st.aid - st.aid_prev_ff, 0.0)
            corr.carr_freq += d_aid
            corr.code_rate[ff] = sgl.code_rate_cps(corr.carr_freq[ff] - self.if_hz)
            self.inner.apply(_BankProxy(self.pref, self.pref.active & ~ff), corr.nco, aid_doppler_hz=st.aid,
                             use_aid=st.use_aid)
        else:
            self.inner.apply(self.pref, corr.nco, aid_doppler_hz=st.aid, use_aid=st.use_aid)
        st.aid_prev_ff[:] = st.aid
        if self.opt.lock_monitor:
            if st.rollback.any():
                corr.carr_freq += st.rollback
                corr.code_rate[:] = sgl.code_rate_cps(corr.carr_freq - self.if_hz)
                st.rollback[:] = 0.0
            st.off_ring[st.k_ep % self.mon.W] = corr.carr_freq - self.if_hz - st.aid

    def _restart_channels(self, st, chans, phase, amp):
        """(Re)start channels' tracking filters on a coherent carrier-phase estimate: rotate the carrier
        NCO by the phase of the coherent sum of the wiped prompts, restart the filter (amplitude from
        the coherent magnitude, start-up-like covariance) and hand the aiding history to the inner
        loop (outer-loop Doppler rate injected into the acceleration state)."""
        chans = np.atleast_1d(np.asarray(chans))
        sgl, corr, aid = self.signal, self.corr, st.aid
        t_code = sgl.code_period_s
        rate = (self.outer.aiding_at(corr.sample_ptr / self.fs + 1.5 * t_code) - aid) / t_code
        a_min = amplitude_threshold(self.opt.cn0_min_dbhz, t_code)
        for c in chans:
            corr.carr_phase[c] = (corr.carr_phase[c] + phase[c] / (2.0 * math.pi)) % 1.0
        x0 = np.zeros((len(chans), 5))
        x0[:, 0] = np.maximum(amp[chans], a_min)
        # frequency error at the start of the next interval: the NCO still holds the last
        # interval's aided value while ``aid`` is the aiding of the next one, and the inner law
        # adds the injected rate (da T/2) itself -> df0 = aid - NCO keeps the channel's Doppler
        # continuous across the (re)start.  (df0 = 0 started the filter one aiding increment
        # off -- up to 0.5 Hz at 20 g -- which it then pulled in over ~0.5 s.)
        x0[:, 3] = 2.0 * math.pi * (aid[chans] - (corr.carr_freq[chans] - self.if_hz))
        P0 = restart_covariance(self.pref, chans, x0, self.opt, sgl)
        if P0 is None:
            self.pref.reset(chans, x0=x0)
        else:
            self.pref.reset(chans, x0=x0, P0=P0)
        self.inner.prime_aiding(self.pref, aid - rate * t_code, rate, channels=chans)

    def _bits_info(self, st):
        """The bit strategy, per channel its code and epochs by bit source, the source's own record."""
        w = self.wipe
        src = getattr(w.source, "info", {}) or {}
        return {"strategy": getattr(w.source, "strategy", w.mode),
                "channel_strategy": [BIT_SOURCE_NAMES[int(c)] for c in w.code],
                "epochs_by_source": w.counts(st.k_ep), "polarity": w.pol.astype(int).tolist(),
                "source": src}

    def _info(self, st):
        opt = self.opt
        return {
            "options": opt.as_dict(),
            "wipeoff_mode": self.wipe.mode,
            # transmit-time count of code periods of each channel's first epoch (epoch k: + k)
            "first_period_count": np.asarray(self.ms0).tolist(),
            "bits": self._bits_info(st),
            "n_epochs": st.k_ep,
            "n_tight_updates": self.tf.n_updates,
            "n_tight_rejected": self.tf.n_rejected,
            **st.counts,
            "timing_s": st.timing,
            "threads": self.threads,
            "prefilter": self.pref.describe(),
            "prefilter_resets": np.asarray(self.pref.n_resets).tolist(),
            "arbitration_rule": "combined when sigma_doppler_i = sqrt(u'Pvv u + Pdd - 2u'Pvd)/lambda < "
                                f"{opt.arbitration_sigma_hz} Hz (tight filter P), else inner loop alone",
            "startup": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                        for k, v in self.init_state.items() if k.startswith("err_") or k == "sigmas"},
        }


class _BankProxy:
    """A tracking bank seen by the inner-loop law with some channels masked inactive (channels
    whose NCO follows the outer-loop aiding alone this epoch)."""

    def __init__(self, bank, active):
        self._bank = bank
        self.x = bank.x
        self.active = active

    def note_correction(self, dx):
        self._bank.note_correction(dx)

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
                            init_state=None, options=None, duration_s=None, seed=0, startup_errors=None,
                            imu_declaration=None, startup="auto", init_overrides=None, start_s=0.0,
                            handover=None):
    """Run the ultra-tight engine on a recorded IF file and an IMU file (HDF5 or CSV).

    * ``meta``: sidecar/ION metadata for the IF file (default ``IFFILE.json``); the IF start time
      (``start_week``/``start_tow_s``) is required.
    * Ephemerides: ``nav_path`` (RINEX) or, for generator files, the sidecar's scenario
      (nominal constellation).  PRNs: ``prns``, the sidecar's list or, after a scalar start-up,
      the satellites of the hand-over fix.
    * Initial state (``startup``: ``auto`` | ``scalar-fix`` | ``truth-perturbed``; the source used
      is ``result.info["startup_source"]``):

      - ``init_state`` dict (``llh``, ``vel_l``, ``q_lb``, ``clk_bias_m``, ``clk_drift_mps``) given
        by the caller: used as it is, at ``start_s`` (``init-state``);
      - ``init_overrides`` with all of ``llh``, ``vel_l``, ``q_lb`` (the ``--init-*`` flags,
        :func:`ultratight.receiver.deep.handover.parse_init_flags`): those at ``start_s``, clock zero
        (``init-flags``);
      - the IMU file's truth at t0 perturbed by ``startup_errors`` (seeded by ``seed``; the hot
        start never uses the truth itself) — the default (``auto``) for generator files with
        truth and ``start_s`` = 0 (``truth-perturbed``);
      - otherwise the scalar receiver's first fixes from ``start_s`` on (``scalar-fix``,
        :func:`ultratight.receiver.deep.handover.scalar_handover`, configured by ``handover``), the
        flags in ``init_overrides`` replacing their part.

      The engine starts at the hand-over time (an IMU stamp): the IF source and the IMU data are
      seen from there on (:class:`~ultratight.receiver.deep.handover.SourceWindow`,
      :func:`~ultratight.receiver.deep.handover.imu_window`), the channels from predicted code phase
      and Doppler (no acquisition); the result's times are shifted back to seconds since the first
      sample of the file.
    * IMU conventions: ``imu_declaration`` (sidecar keys, :mod:`ultratight.ins.imu_decl`) over the
      IMU file's sidecar; a GPS-stamped IMU starting before the IF is cut to the IF start.
    * Time alignment is checked by :func:`check_imu_if_alignment` (gaps, out-of-order stamps,
      IMU/IF offset -> InputFileError).
    Returns an :class:`EngineResult`.
    """
    from ultratight.receiver.deep import handover as ho
    if not method_spec(method).needs_imu:
        raise ConfigError(f"method {method!r} is the scalar receiver: use `ultratight process` without "
                          f"--mode ultratight")
    if startup not in ("auto", ho.STARTUP_SCALAR, ho.STARTUP_TRUTH):
        raise ConfigError(f"unknown start-up {startup!r}; expected auto, {ho.STARTUP_SCALAR} or {ho.STARTUP_TRUTH}")
    src = open_if(if_path, meta=meta)
    if src.start_tow_s is None or src.start_week is None:
        raise InputFileError(f"{if_path}: the IF start time (start_week, start_tow_s) is unknown; "
                             "give it in the sidecar/metadata")
    imu_path = Path(imu_path)
    # the IMU's declared conventions (sidecar IMU.csv.json + ``imu_declaration`` overrides, ins.imu_decl)
    imu = imu_decl.read_imu_file(imu_path, imu_declaration)
    imu = imu_decl.align_to_gps_start(imu, src.start_week, src.start_tow_s, imu_path)
    usable = check_imu_if_alignment(src, imu, if_path, imu_path)
    dur = usable if duration_s is None else min(float(duration_s), usable)
    side = src.meta or {}
    gen_cfg = side.get("generator") if isinstance(side.get("generator"), dict) else None
    week, tow0 = int(src.start_week), float(src.start_tow_s)
    nav, ephs = _file_ephemerides(if_path, nav_path, gen_cfg, week, tow0)
    if prns is None:
        prns = side.get("prn")
    start_s = float(start_s or 0.0)
    if not 0.0 <= start_s < dur:
        raise ConfigError(f"--start {start_s:g} s is outside the usable record (0 .. {dur:.3f} s)")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    source, hand, t_h, init_state, prns = _startup(
        src, imu, imu_path, nav if nav is not None else ephs, ephs, prns, startup, init_state,
        dict(init_overrides or {}), start_s, handover, gen_cfg, startup_errors, rng)
    if not prns:
        raise ConfigError(f"{if_path}: no PRN list in the sidecar: give the PRNs to track (--prn)")
    missing = [p for p in prns if p not in ephs]
    if missing:
        raise ConfigError(f"no ephemeris for PRN {missing}")
    file_start = {"week": int(week), "tow_s": float(tow0)}
    if t_h > 0.0:
        src, imu, t_h = _from_handover(src, imu, t_h, dur)
        tow0, week = float(src.start_tow_s), int(src.start_week)
    eng = UltratightEngine(src, imu, ephs, [int(p) for p in prns], week, tow0, method=method,
                           options=options, init_state=init_state, rng=rng, duration_s=dur - t_h)
    res = eng.run()
    if t_h > 0.0:
        res.t_start = res.t_start + t_h
        res.nav_t = res.nav_t + t_h
        if res.sins:
            res.sins["t_s"] = res.sins["t_s"] + t_h
    res.info["startup_source"] = source
    res.info["t_offset_s"] = float(t_h)
    res.info["handover"] = (hand or {}).get("startup", {"source": source, "handover_t_s": float(t_h)})
    res.info["if_file_start"] = file_start          # the result's times count from this receiver time
    t_mid = file_start["tow_s"] + t_h + 0.5 * res.duration_s
    res.info["sat_pos_e"] = [np.asarray(sat_state(ephs[int(p)], np.array([t_mid]))[0][0]).tolist() for p in prns]
    return res


def _file_ephemerides(if_path, nav_path, gen_cfg, week, tow0):
    """``(nav, ephs)`` of a recording: the RINEX file's ephemerides valid at the start (``nav`` the
    parsed file) or, for a generator file on the nominal constellation, the nominal ones (``nav``
    None)."""
    if nav_path is not None:
        nav = read_rinex_nav(nav_path)
        return nav, nav.select_all(week, tow0)
    if gen_cfg is not None and gen_cfg.get("satellites", {}).get("source", "nominal") == "nominal":
        return None, nominal_ephemerides(week, tow0)
    raise ConfigError(f"{if_path}: no ephemerides: give a RINEX navigation file (--ephemeris)")


def _startup(src, imu, imu_path, nav_or_ephs, ephs, prns, startup, init_state, overrides, start_s, handover,
             gen_cfg, startup_errors, rng):
    """The initial state of a recording's run (:func:`run_ultratight_on_files`, "Initial state"):
    ``(source, hand, t_h, init_state, prns)`` — the start-up source's name, the scalar or flags
    hand-over (or None), its time (s since the first sample), the state and the PRNs to track."""
    from ultratight.receiver.deep import handover as ho
    tr = getattr(imu, "truth", None)
    has_truth = bool(tr) and "llh" in tr
    t_h = 0.0
    source = "init-state"
    hand = None
    if init_state is not None:
        t_h = start_s
    elif all(k in overrides for k in ("llh", "vel_l", "q_lb")):
        hand = ho.flags_state(overrides, start_s)
        source = ho.STARTUP_FLAGS
    elif startup == ho.STARTUP_TRUTH or (startup == "auto" and has_truth and start_s == 0.0 and not overrides):
        if not has_truth:
            raise ConfigError(f"{imu_path}: start-up {ho.STARTUP_TRUTH} needs the truth in the IMU file (none here)")
        if start_s != 0.0:
            raise ConfigError(f"start-up {ho.STARTUP_TRUTH} starts at the first sample: --start not supported")
        source = ho.STARTUP_TRUTH
        rcv = (gen_cfg or {}).get("receiver", {})
        truth0 = {"llh": np.asarray(tr["llh"][0]), "vel_l": np.asarray(tr["vel_l"][0]),
                  "q_lb": np.asarray(tr["q_lb"][0]), "clk_bias_m": float(rcv.get("clock_bias_m", 0.0)),
                  "clk_drift_mps": float(rcv.get("clock_drift_mps", 0.0))}
        init_state = perturb_state(truth0, startup_errors or StartupErrors(), rng)
    else:
        hand = ho.scalar_handover(src, imu, tightmod.imu_errors_from_meta(imu), nav_or_ephs,
                                  prns, start_s=start_s, cfg=handover, overrides=overrides)
        source = ho.STARTUP_SCALAR
        if not prns:
            # every satellite the scalar pass kept tracking (not only the hand-over fix's)
            prns = [p for p in hand["startup"]["scalar_pass"]["tracked"] if p in ephs]
    if hand is not None:
        t_h = hand["t_s"]
        init_state = {k: hand[k] for k in ("llh", "vel_l", "q_lb", "clk_bias_m", "clk_drift_mps", "sigmas",
                                           "code_phase_chips") if k in hand}
    return source, hand, t_h, init_state, prns


def _from_handover(src, imu, t_h, dur):
    """The IF source and IMU data seen from the hand-over time ``t_h`` on (rounded to an IMU stamp):
    ``(src, imu, t_h)``."""
    from ultratight.receiver.deep import handover as ho
    dt_imu = 1.0 / float(imu.rate_hz)
    t_h = float(getattr(imu, "t0", 0.0)) + round((t_h - float(getattr(imu, "t0", 0.0))) / dt_imu) * dt_imu
    if t_h >= dur - 2 * dt_imu:
        raise ConfigError(f"start-up at t = {t_h:.3f} s leaves no record to process (usable {dur:.3f} s)")
    n0 = int(round(t_h * src.fs_hz))
    return ho.SourceWindow(src, n0), ho.imu_window(imu, t_h), t_h


def write_result_h5(path, res, extra_attrs=None):
    """Write an :class:`EngineResult` to HDF5 (built in memory, written under a unique temporary
    name, then renamed; schema in docs/ultratight.md). Disk errors raise OutputError."""

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
        for k, v in (res.sins or {}).items():
            f.create_dataset(f"sins/{k}", data=np.asarray(v), compression="gzip", compression_opts=1, shuffle=True)
        for k, v in (("t_start_s", res.t_start), ("doppler_hz", res.doppler_hz),
                     ("code_phase_chips", res.code_phase_chips), ("amplitude", res.amp), ("mode", res.mode),
                     ("nav_t_s", res.nav_t), ("nav_pos_e", res.nav_pos_e), ("nav_vel_e", res.nav_vel_e),
                     ("nav_clk", res.nav_clk), ("nav_sigma_doppler_hz", res.nav_sigma_doppler_hz)):
            f.create_dataset(k, data=np.asarray(v), compression="gzip", compression_opts=1, shuffle=True)
        if getattr(res, "bit_source", None) is not None:
            f.create_dataset("bit_source", data=np.asarray(res.bit_source), compression="gzip", compression_opts=1)

    return write_h5_atomic(path, build)
