"""The double-loop ultra-tight receiver engine (Zhao et al. 2014, Fig. 1).

Stages, in the order of the paper's Fig. 1 (each a module of its own, arrays in and out)::

    IF block stream (receiver.dsp.blockstream, noise sigma per block)
      ─► correlator bank (receiver.dsp.correlator; its NCOs: signals.nco.NcoBank)
      ─► data wipe-off (receiver.dsp.wipeoff)
      ─► tracking bank (fusion.channel.prefilter / fusion.channel.pbkf, chosen by the method's spec in
         receiver.deep.methods; the inner loop, 1 kHz)
      ─► inner-loop NCO command (fusion.channel.innerloop; aiding increments from the outer loop
         when the arbitration allows)
      ─► residuals vs the SINS predictions ─► averaging decimator (fusion.coupling.rateconv.ResidualDecimator, 10 Hz)
      ─► tight 17-state filter (fusion.coupling.tight) ⇄ SINS + clock (receiver.deep.sins_clock, 100 Hz, feedback)
      ─► outer loop (receiver.deep.outer_loop: 100 Hz predictions, CIC to 1 kHz) ─► aiding of the next epochs
      ─► recorder (receiver.deep.recorder); lock monitor (receiver.dsp.lockmon, optional)

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
* ``scalar``: the scalar tracking pipeline of receiver.dsp.tracking (no INS), for reference;
  :meth:`UltratightEngine.run` hands it to :func:`ultratight.receiver.deep.scalar_reference.run_scalar`.

Arbitration (double loop, logged per channel per epoch in ``mode``): after every tight
update the 1-sigma of each channel's predicted Doppler is computed from the tight filter
covariance, ``sigma_i = sqrt(u_i' P_vv u_i + P_dd - 2 u_i' P_vd) / lambda`` (velocity /
clock-drift block projected on the line of sight, :func:`ultratight.fusion.coupling.tight.doppler_sigma_hz`).
A channel uses the combined command (outer prediction + inner correction, ``MODE_COMBINED``) while
``sigma_i < arbitration_sigma_hz``, otherwise the inner loop alone (``MODE_INNER``). PB-KF-UTC
is always ``MODE_OUTER``.

Atmosphere (optional ``atmosphere``, an :class:`ultratight.signals.atmosphere.AtmosphereModel`): the
outer loop's predictions -- NCO aiding and the references of the tight filter's residuals -- carry the
ionospheric and tropospheric delays, refreshed at every tight update
(:mod:`ultratight.receiver.deep.atmosphere_terms`); without one they are geometric.

Tracking estimates recorded per channel per epoch (for the paper's metrics): the Doppler
``carr_freq - IF + df/2pi`` and the code phase ``code_phase + dtau`` at the *start* of the
integration interval (the prefilter state refers to the interval start; see
ultratight.fusion.channel.prefilter), with their time ``t_start`` (s since the first sample).
References: docs/references.md.
"""

import math
import time
from dataclasses import replace

import numba
import numpy as np

from ultratight.constants import C
from ultratight.errors import ConfigError, DivergenceError, FilterError
from ultratight.fusion.coupling import tight as tightmod
from ultratight.fusion.channel.innerloop import InnerLoop
from ultratight.fusion.channel.prefilter import IF as PREFILTER_IF
from ultratight.fusion.coupling.rateconv import ResidualDecimator
from ultratight.ins.earth import llh_increment_to_enu, radii
from ultratight.receiver.deep import epochs
from ultratight.receiver.deep.atmosphere_terms import inactive_description
from ultratight.receiver.dsp.blockstream import BlockStream, NoiseFloor
from ultratight.receiver.dsp.burst import burst_all, make_burst
from ultratight.receiver.dsp.correlator import CorrelatorBank
from ultratight.receiver.deep.integrity import LOST, IntegrityMonitor, IntegrityThresholds
from ultratight.receiver.deep.epochs import (CONTINUE, END, ERR_BANK, ERR_CORR, NEED_IF, NEED_SINS, TIGHT,
                                        correlate, epoch_gate, epoch_post, run_epochs, run_epochs_threaded)
from ultratight.receiver.dsp.lockmon import LockMonitor, amplitude_threshold
from ultratight.receiver.deep.methods import DEFAULT_METHOD, check_method, method_spec
from ultratight.receiver.deep.options import MODE_COAST, MODE_COMBINED, MODE_INNER, MODE_OUTER, EngineOptions, epoch_threads
from ultratight.receiver.deep.outer_loop import OuterLoop, SinsFollower
from ultratight.receiver.deep.recorder import EpochRecorder
from ultratight.receiver.deep.scalar_reference import run_scalar
from ultratight.receiver.deep.sins_clock import InsClock
from ultratight.receiver.deep.bitsources import bit_source, check_strategy, decoded_from_pass
from ultratight.receiver.deep.startup import first_period_ms, predict_channels
from ultratight.receiver.deep.tracking_banks import bank_view, make_tracking_bank, restart_covariance
from ultratight.receiver.dsp.wipeoff import BIT_SOURCE_NAMES, DataWipeoff
from ultratight.signals.signal import GPS_L1CA

__all__ = ["UltratightEngine", "EpochState"]

PEND_EPOCHS = 256   # most epochs the compiled runner runs before summing their residuals

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
        # wall seconds per part of the run; "if_read": getting the next IF block (with a streamed IF,
        # waiting for its generator)
        self.timing = {"epochs": 0.0, "special_epochs": 0.0, "sins_outer": 0.0, "tight": 0.0, "if_read": 0.0}

    def special(self, opt):
        """The next epoch needs the one-epoch path (start-up initialisation or the lock monitor)."""
        return self.init_left > 0 or opt.lock_monitor or opt.monitor_gates_tight


class UltratightEngine:
    """Runs one method over an IF source + IMU data (see module docstring)."""

    def __init__(self, source, imu, ephs, prns, week, tow0_s, method=DEFAULT_METHOD, options=None,
                 init_state=None, rng=None, duration_s=None, signal=GPS_L1CA, atmosphere=None, iono_source=None):
        self.method = check_method(method)
        # receiver's ionosphere/troposphere model of the predictions (receiver.deep.atmosphere_terms;
        # None: geometric predictions) and where its broadcast coefficients came from
        self.atmosphere = atmosphere
        self.iono_source = iono_source
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
                steady = run_epochs_threaded if self.threads > 1 else run_epochs
                status, st.k_ep, info = steady(st.k_ep, *self._stage_views(st))
                st.timing["epochs"] += time.perf_counter() - tw
                self._check_status(status, info)
            if status == NEED_IF:
                tw = time.perf_counter()
                more = self._read_if()
                st.timing["if_read"] += time.perf_counter() - tw
                if not more:
                    break
            if status == END:
                break
            if status == NEED_SINS:
                self._advance_sins(st)
            elif status == TIGHT:
                self._tight_update(st)
                if self.integ.state == LOST and self.opt.integrity_stop:
                    break           # the solution left the measurements: the caller re-initialises
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
        self.outer = OuterLoop(self.ephs, self.prns, self.week, self.tow0, self.duration_s + 0.5, signal=sgl,
                               rate_hz=1.0 / self.imu_dt, cic_order=opt.cic_order, atmosphere=self.atmosphere,
                               iono_source=self.iono_source)
        # hot start predictions (from the perturbed state, not truth)
        pos_e, vel_e, C_el = self.ins.antenna_pos_vel_e()
        pred0 = predict_channels(self.ephs, self.prns, self.week, self.tow0, pos_e, vel_e,
                                 self.ins.clk_b, self.ins.clk_d, signal=sgl)
        self._delay_pred0(pred0, pos_e, vel_e)
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
        self.integ = IntegrityMonitor(IntegrityThresholds.from_options(opt.integrity), opt.tight_rate_hz)
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

    def _delay_pred0(self, pred0, pos_e, vel_e):
        """The hot start's code phases and transmit times with the atmospheric code delay (the
        outer loop's model at the first sample; nothing without one)."""
        atm = self.outer.atmo
        if atm is None:
            return
        self.outer.refresh_atmosphere(0.0, pos_e, vel_e, self.ins.clk_b, self.ins.clk_d)
        d = atm.code_m
        pred0["code_phase_chips"] = np.mod(pred0["code_phase_chips"] - d / self.signal.chip_m,
                                           float(self.signal.code_length))
        pred0["t_tx_tow"] = pred0["t_tx_tow"] - d / C

    def _build_tracking(self, es, los_l):
        """Tracking bank + inner loop, and the NCOs at the aiding of each channel's first interval."""
        opt, sgl = self.opt, self.signal
        n_ch = len(self.prns)
        lat, _, h = self.ins.llh
        rm, rn = radii(lat)
        M_pos = llh_increment_to_enu(lat, h, rm, rn)
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
        self.threads = epoch_threads(opt.threads, n_ch)
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
        decisions go through the LNAV decoder (receiver.deep.bitsources.decoded_from_pass)."""
        t0 = time.perf_counter()
        first = UltratightEngine(self.src, self.imu, self.ephs, self.prns, self.week, self.tow0, method=self.method,
                                 options=replace(self.opt, bits="blind", integrity_stop=False),
                                 init_state=self.init_state, rng=self.rng,
                                 duration_s=self.duration_s, signal=self.signal, atmosphere=self.atmosphere,
                                 iono_source=self.iono_source)
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
        M_pos = llh_increment_to_enu(lat, h, rm, rn)
        los_l = self.follow.los_e() @ C_el
        Phi, Qd = tightmod.phi_q(ins, self.dec.step_s, self.imu_noise, opt.clock_q_drift)
        self.tf.predict(Phi, Qd)
        P_prior, n_rej0, lever = self.tf.P.copy(), self.tf.n_rejected, ins.lever_terms()
        dx = self.tf.update(m["dz_pr"], m["dz_prr"], los_l, M_pos, m["var_pr"], m["var_prr"], valid, lever=lever)
        dfp_all = np.zeros(len(self.prns))
        if np.any(dx != 0.0):
            ins.feedback(dx)
            self.tf.reset()
            st.counts["n_feedback"] += 1
            dfp_all = self.follow.apply_correction(sgl.code_length, self.spec.double_loop)
        self.follow.refresh_atmosphere()        # the delays at the updated SINS, carried to the next update
        # integrity (receiver.deep.integrity): tests of this update; the reported sigma covers the error
        state = self.integ.update(self.follow.t, m["dz_pr"], m["dz_prr"], m["var_pr"], m["var_prr"], valid, los_l,
                                  M_pos, P_prior, self.tf.gate_sigma, self.tf.n_rejected - n_rej0, lever)
        st.sig_dopp = tightmod.doppler_sigma_hz(self.tf.P, los_l, sgl.wavelength_m)
        self.rec.set_sigma(self.tf.P, ins.llh)
        self.rec.sigma_now = self.integ.cover(self.rec.sigma_now, self.follow.t, ins.f_b)
        self.rec.log_integrity(state, self.integ.last)
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
            "integrity": self.integ.summary(),
            **st.counts,
            "timing_s": st.timing,
            "threads": self.threads,
            "prefilter": self.pref.describe(),
            "prefilter_resets": np.asarray(self.pref.n_resets).tolist(),
            "arbitration_rule": "combined when sigma_doppler_i = sqrt(u'Pvv u + Pdd - 2u'Pvd)/lambda < "
                                f"{opt.arbitration_sigma_hz} Hz (tight filter P), else inner loop alone",
            "atmosphere": (self.outer.atmo.describe() if self.outer.atmo is not None
                           else inactive_description(self.atmosphere)),
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

