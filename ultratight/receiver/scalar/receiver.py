"""The scalar receiver: a pipeline of stages from IF samples to position fixes.

:class:`ScalarReceiver` is built from stages with array interfaces, each usable alone:

1. acquisition / assistance and channel allocation (:mod:`ultratight.receiver.scalar.channels`:
   :func:`~ultratight.receiver.scalar.channels.acquire_signals`, with
   :func:`ultratight.receiver.dsp.acquisition.acquire` in two stages or assistance records, and
   :func:`~ultratight.receiver.scalar.channels.allocate_channels`); with ``dynamics = "high"`` every
   channel then starts from a Doppler-rate search (:func:`~ultratight.receiver.scalar.channels.search_rate`:
   :func:`ultratight.receiver.dsp.acquisition.doppler_rate_search`) that presets the PLL's rate;
2. the IF block stream (:class:`ultratight.receiver.dsp.blockstream.BlockStream`, with the per-arm
   noise estimate);
3. the scalar tracking bank (:class:`ultratight.receiver.dsp.tracking.ScalarTracker`: FLL-assisted PLL,
   DLL, C/N0, lock and bit-sync in one numba kernel per block);
4. bit synchronisation + navigation decoding (:class:`ultratight.receiver.scalar.nav_pvt.NavBitStage`,
   the decoder the signal description names: :func:`ultratight.receiver.scalar.navdecode.channel_nav`);
5. observables (:class:`~ultratight.receiver.scalar.nav_pvt.ObservableStage`) and 6. PVT
   (:class:`~ultratight.receiver.scalar.nav_pvt.PvtStage`);
7. outputs (:class:`ultratight.receiver.scalar.recording.Recorder`: HDF5 stream, RINEX observations,
   in-memory epoch series).

This module holds the receiver itself (:class:`ScalarReceiver`: set-up, the block loop,
re-acquisition and the search of idle PRNs, the end of a run) and :func:`process`; the run's
options and result are :mod:`ultratight.receiver.scalar.process_config`.

Every stage takes a :class:`ultratight.signals.signal.SignalDescription` (default GPS L1 C/A)
instead of signal constants. :func:`process` builds and runs a :class:`ScalarReceiver` on an opened
:class:`ultratight.signals.recording.iffile.IfSource` (or a path) and returns a :class:`ProcessResult`; it is
what ``ultratight process`` runs (``record_epochs=True`` keeps the per-channel, per-epoch Doppler /
code phase estimates with their sample indices in memory: ``result.epochs[prn]``). The scenario's
``scalar`` method does not call :func:`process`: :func:`ultratight.receiver.deep.scalar_reference.run_scalar`
runs the same tracking bank over the same block stream from hot-start predictions (no acquisition,
navigation decoding or PVT).

Streaming: the file is read through the block stream in blocks of ``block_ms`` (default 200 ms)
where the channels need samples (they stop, re-acquire and restart anywhere), tracking runs in one
numba call per block, per-epoch series are appended to the HDF5 output as they come (nothing
per-epoch is kept in memory unless ``record_epochs``), so the memory use does not depend on the
file length.

Receiver time: ``t_rx(s) = t0 + s/fs`` (receiver clock).  ``t0`` is set when the first channel
knows its transmit time (``t0 = t_tx + 75 ms``) and is steered by the clock-bias estimate at the
first fix (and whenever |bias| exceeds 1 ms); reported fix times are GPS time
``t_rx - bias/c``.

Atmosphere (``ProcessConfig.iono`` / ``tropo``, :mod:`ultratight.signals.atmosphere`): the PVT
removes the Klobuchar ionospheric delay once broadcast coefficients are known — from the RINEX
navigation header given as ephemerides, else from the first subframe 4 page 18 decoded on any
channel — and the Saastamoinen tropospheric delay (standard atmosphere, ``tropo_mapping``).
The satellite clock correction includes ``-T_GD`` (:func:`ultratight.signals.ephemeris.sat_state`).
The options and the coefficients used are recorded in the summary (``corrections``), the HDF5
root attributes and every other output.
"""

import contextlib
import math
import time
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import replace

import numba
import numpy as np

from ultratight.cores import stage_threads
from ultratight.errors import InputFileError
from ultratight.receiver.dsp.acquisition import acquire
from ultratight.receiver.dsp.blockstream import BlockStream
from ultratight.receiver.dsp.tracking import ScalarTracker
from ultratight.receiver.dsp.tracking_layout import (F_DOPP, FL_PLL_LOCK, MODE_LOST, MODE_TRACK, RI_FLAGS, RI_N, RI_PTR,
                                                     S_MODE)
from ultratight.receiver.scalar.channels import (acquire_signals, allocate_channels, channel_info, cold_search,
                                                 predicted_search, search_rate)
from ultratight.receiver.scalar.nav_pvt import NavBitStage, ObservableStage, PvtStage, ephemeris_lookup
from ultratight.receiver.scalar.navdecode import channel_nav
from ultratight.receiver.scalar.observables import NOISE_WINDOW_S, CarrierSmoother, ChannelHistory, noise_weights
from ultratight.receiver.scalar.process_config import ProcessConfig, ProcessResult
from ultratight.receiver.scalar.recording import Recorder, finish_hdf5, write_exchange_files
from ultratight.receiver.scalar.search_plan import plan_search
from ultratight.signals.recording.iffile import open_if
from ultratight.signals.signal import GPS_L1CA

SIGMA_SAMPLES = 65536        # samples used per block for the noise-power estimate
RELEASE_EVERY = 20           # blocks between releases of the processed part of the file mapping
MIRROR_RATIO = 0.1           # see _spectrum_check


class ScalarReceiver:
    """The scalar receiver: a pipeline of stages with array interfaces.

    acquisition / assistance (:func:`~ultratight.receiver.scalar.channels.acquire_signals`) -> channel
    allocation (:func:`~ultratight.receiver.scalar.channels.allocate_channels`) -> IF block stream
    (:class:`ultratight.receiver.dsp.blockstream.BlockStream`, with the noise estimate) -> scalar
    tracking bank (:class:`ultratight.receiver.dsp.tracking.ScalarTracker`) -> bit synchronisation +
    navigation decoding (:class:`~ultratight.receiver.scalar.nav_pvt.NavBitStage`) -> observables
    (:class:`~ultratight.receiver.scalar.nav_pvt.ObservableStage`) -> PVT
    (:class:`~ultratight.receiver.scalar.nav_pvt.PvtStage`) -> outputs
    (:class:`~ultratight.receiver.scalar.recording.Recorder`).

    Every stage takes the signal description ``signal`` (default GPS L1 C/A) instead of signal
    constants. :meth:`run` returns a :class:`ProcessResult`; :func:`process` builds and runs one.

    ``log_nav_bits``: every channel's navigation state keeps the soft bits it is fed with their
    start epochs (:attr:`ultratight.receiver.scalar.navdecode.ChannelNav.log`, a list of
    ``(soft bits, start epochs)`` per feed, across re-acquisitions), for a caller that reads the
    decoded bit stream after :meth:`run` (``rx.navs``).
    """

    def __init__(self, source, config=None, ephemerides=None, signal=GPS_L1CA, log_nav_bits=False):
        if not hasattr(source, "read"):
            source = open_if(source)
        self.source = source
        self.signal = signal
        self.cfg = cfg = config or ProcessConfig()
        cfg.validate(source)
        self.ephemerides = ephemerides
        self.log_nav_bits = bool(log_nav_bits)
        self.fs = fs = source.fs_hz
        self.start_sample = int(round(cfg.start_s * fs))
        self.stop = source.n_samples if cfg.duration_s is None else min(
            source.n_samples, self.start_sample + int(round(cfg.duration_s * fs)))
        if self.stop - self.start_sample < int(fs * signal.code_period_s) + 2:
            raise InputFileError(f"{source.path}: {max(0, self.stop - self.start_sample)} samples to process "
                                 f"(< one {signal.code_period_s * 1e3:g} ms code period at fs = {fs} Hz)")
        self.input_info = {"path": str(source.path), "format": source.fmt, "fs_hz": fs, "if_hz": source.if_hz,
                           "is_complex": source.is_complex, "iq_conj": bool(getattr(source, "_conj", False)),
                           "n_samples": int(source.n_samples), "start_week": source.start_week,
                           "start_tow_s": source.start_tow_s}

    # ----------------------------------------------------------------- set-up
    def _build(self, acq, out_path, rinex_obs_path):
        """Channels and stages from the acquisitions."""
        cfg, fs, src, sig = self.cfg, self.fs, self.source, self.signal
        found, idle_prns = allocate_channels(acq, cfg, sig)
        self.all_in_view = cfg.n_channels is None
        self.n_ch = n_ch = len(found) + len(idle_prns)
        self.block_len = int(round(cfg.block_ms * 1e-3 * fs))
        self.margin = int(math.ceil(2.2e-3 * fs))
        self.stream = BlockStream(src, self.block_len, on_zero=1.0)
        if cfg.threads is not None or cfg.parallel is None:
            n_thr = stage_threads(cfg.threads or 0, n_ch)
            parallel = n_thr > 1
            if parallel:
                numba.set_num_threads(n_thr)
        else:
            parallel = bool(cfg.parallel)
        self.tracker = ScalarTracker(n_ch, fs, src.if_hz, src.is_complex, cfg.tracking,
                                     max_rows=int(cfg.block_ms * 1.1) + 8, parallel=parallel, signal=sig)
        self.chinfo = []
        for ch, a in enumerate(found):
            search_rate(src, a, cfg, self.stop, sig)
            self.tracker.start_channel(ch, a.prn, a.code_phase_chips, a.doppler_hz, a.sample_index, a.cn0_dbhz,
                                       a.rate_hz_s)
            self.chinfo.append(channel_info(a.prn, a, self.start_sample, fs))
        self.chinfo += [channel_info(p) for p in idle_prns]
        prns = [c["prn"] for c in self.chinfo]
        self.navs = [channel_nav(sig, p, src.start_week) for p in prns]
        if self.log_nav_bits:
            for nav in self.navs:
                nav.log = []
        self.hists = [ChannelHistory(fs) for _ in prns]
        self.navbits = NavBitStage(self.navs, sig, fs, self.start_sample)
        smoother = CarrierSmoother(n_ch, cfg.smoothing_s * cfg.obs_rate_hz, wavelength_m=sig.wavelength_m,
                                   noise_epochs=max(1, round(NOISE_WINDOW_S * cfg.obs_rate_hz)))
        h_samp = int(round(cfg.doppler_window_s * fs))
        self.observables = ObservableStage(self.hists, self.navs, prns, fs, self.start_sample, h_samp, smoother, sig)
        self.pvt = PvtStage(cfg, ephemeris_lookup(self.ephemerides), self.navs, prns, src.start_week,
                            self.ephemerides, sig)
        self.recorder = Recorder(out_path, rinex_obs_path, cfg, src, prns)
        self.obs_step = fs / cfg.obs_rate_hz
        self.k_obs = int(math.ceil((self.start_sample + h_samp + 1) / self.obs_step))
        self.h_samp = h_samp
        self.search = {"next": self.start_sample + int(cfg.search_every_s * fs),
                       "next_coarse": self.start_sample + int(cfg.coarse_interval_s * fs),
                       "predicted_runs": 0, "coarse_runs": 0, "predicted_prns": 0, "coarse_prns": 0,
                       "predicted": [], "below_mask": [], "cpu_s": 0.0}

    # ----------------------------------------------------------------- per block
    def _read_track(self, s):
        """Track every active channel through the block starting at sample ``s`` (read from the
        stream); the records, or None at the end. Touches only the stream and the tracking bank."""
        n_read = min(self.block_len + self.margin, self.stop - s)
        return self.tracker.track_at(self.stream, s, n_read, SIGMA_SAMPLES, self.margin, self.stop)

    def _block_done(self, s, recs):
        """What must follow a block before the next one is tracked: the file mapping released now and
        then, and the channels that lost lock in the block stopped."""
        self.n_blocks_done += 1
        if self.n_blocks_done % RELEASE_EVERY == 0:
            self.stream.release(s - self.margin)          # keeps the resident set flat on long files
        nr, st = recs[2], self.tracker.state
        for ch in range(self.n_ch):
            if nr[ch] and st.si[ch, S_MODE] == MODE_LOST:
                self.chinfo[ch]["losses"] += 1
                self.tracker.stop_channel(ch)
                st.si[ch, S_MODE] = MODE_LOST

    def _take_records(self, recs):
        """Hand the block's records to the channels' histories, decoders and outputs."""
        rf, ri, nr = recs
        for ch in range(self.n_ch):
            m = int(nr[ch])
            if m:
                info = self.chinfo[ch]
                f_ch, i_ch = rf[ch, :m], ri[ch, :m]
                self.hists[ch].append(f_ch, i_ch)
                info["epochs"] += m
                info["locked_epochs"] += int(np.count_nonzero(i_ch[:, RI_FLAGS] & FL_PLL_LOCK))
                self.recorder.tracking(info["prn"], f_ch, i_ch)
                self.navbits.feed(ch, f_ch, i_ch, info)

    def _after_block_due(self, s, recs):
        """Whether the re-acquisition or the search after the block at ``s`` may act (:meth:`_after_block`
        with the block's records handed over); when not, the records can wait until the next block is
        being tracked."""
        tracker = self.tracker
        if not tracker.active.any():
            return True
        ri, nr = recs[1], recs[2]
        ends = [int(ri[ch, nr[ch] - 1, RI_PTR] + ri[ch, nr[ch] - 1, RI_N]) if nr[ch] else self.hists[ch].end_sample
                for ch in range(self.n_ch)]
        if self.cfg.reacquire and any(self._lost(ch) and self._retry_due(ch, ends[ch] if ends[ch] > 0 else s)
                                      for ch in range(self.n_ch)):
            return True
        return self.all_in_view and self._search_due(max(ends))

    def _lost(self, ch):
        """Channel ``ch`` lost lock and was stopped (re-acquisition may restart it)."""
        return not self.tracker.active[ch] and self.tracker.state.si[ch, S_MODE] == MODE_LOST

    def _retry_due(self, ch, now_sample):
        retry = self.chinfo[ch]["next_retry"]
        return retry is None or now_sample >= retry

    def _search_due(self, now_sample):
        """The periodic search's time has come at ``now_sample`` and some PRN has no channel running."""
        srch = self.search
        return now_sample >= min(srch["next"], srch["next_coarse"]) and not all(c["started"] for c in self.chinfo)

    def _observation_limit(self):
        """The sample every active channel's history has reached (the observation epochs up to it are
        complete)."""
        ends = [self.hists[ch].end_sample for ch in range(self.n_ch) if self.tracker.active[ch]]
        return min(ends) if ends else max(h.end_sample for h in self.hists)

    def _observation_epochs(self, limit):
        """Observables / PVT at every observation epoch before ``limit`` (:meth:`_observation_limit`)."""
        while True:
            s_obs = int(round(self.k_obs * self.obs_step))
            if s_obs + self.h_samp + 1 >= limit:
                break
            self._observation_epoch(s_obs)
            self.k_obs += 1

    def _observation_epoch(self, s_obs):
        got = self.observables.epoch(s_obs)
        if got is None:
            return
        row, obs = got
        self.observations.append({k: row[k] for k in ("t_s", "sample_index")})
        self.recorder.observables(row)
        pr = row["pseudorange_m"]
        if self.cfg.smoothing_s > 0:
            pr = self.observables.smooth(row)
            self.recorder.smoothed(pr)
        if self.recorder.rinex_obs is not None and self.pvt.week_known is not None:
            self.recorder.rinex_epoch(self.pvt.week_known, row, pr, self.navs, self.chinfo)
        factor = None
        if self.cfg.smoothing_s > 0 and self.cfg.noise_weights:
            factor = noise_weights(self.observables.smoother.code_noise_m())
        out = self.pvt.solve(row, obs, pr, self.observables.steer, factor)
        if out is not None:
            fix, sol, parts = out
            self.fixes.append(fix)
            self.recorder.fix(fix, sol, parts)

    # ----------------------------------------------------------------- re-acquisition / search
    def _reacquire(self, ch, now_sample):
        info = self.chinfo[ch]
        if not self._retry_due(ch, now_sample):
            return
        n_need = int(self.fs * self.signal.code_period_s * 10) + 1
        if now_sample + n_need >= self.stop:
            info["next_retry"] = self.stop          # nothing left to search
            return
        last_d = float(self.tracker.state.sf[ch, F_DOPP])
        res = acquire(self.source, prns=[info["prn"]], doppler_center_hz=last_d,
                      doppler_range_hz=min(1000.0, 0.45 * self.fs - abs(last_d)), noncoherent=10,
                      pfa=self.cfg.acq_pfa, start_sample=int(now_sample), signal=self.signal)[0]
        if res.detected:
            search_rate(self.source, res, self.cfg, self.stop, self.signal)
            self.tracker.start_channel(ch, info["prn"], res.code_phase_chips, res.doppler_hz, res.sample_index,
                                       res.cn0_dbhz, res.rate_hz_s)
            self.navbits.restart(ch)
            info["bit_sync"] = False
            info["reacquisitions"] += 1
            info["next_retry"] = None
        else:
            info["next_retry"] = now_sample + int(self.cfg.reacq_retry_s * self.fs)

    def _search_idle(self, now_sample):
        """All in view: search the PRNs without a channel running and start the ones found.

        With a fix, the PRNs an ephemeris predicts above the mask are searched every
        ``search_every_s`` around their predicted Doppler, the ones it predicts below the mask are
        not searched, and the others (no ephemeris, or no fix yet) get the coarse full search every
        ``coarse_search_every_s`` (:mod:`ultratight.receiver.scalar.search_plan`)."""
        srch, fs = self.search, self.fs
        if not self._search_due(now_sample) or now_sample + int(0.05 * fs) >= self.stop:
            return
        idle = [ch for ch in range(self.n_ch) if not self.chinfo[ch]["started"]]
        c0 = time.process_time()
        plan = self._search_plan([self.chinfo[ch]["prn"] for ch in idle], now_sample)
        found = []
        if now_sample >= srch["next"]:
            srch["next"] = now_sample + int(self.cfg.search_every_s * fs)
            if plan.predicted:
                found += predicted_search(self.source, self.cfg, int(now_sample), plan.predicted, plan.window_hz,
                                          self.signal)
                srch["predicted_runs"] += 1
                srch["predicted_prns"] += len(plan.predicted)
        if now_sample >= srch["next_coarse"]:
            srch["next_coarse"] = now_sample + int(self.cfg.coarse_interval_s * fs)
            if plan.unpredicted:
                scfg = replace(self.cfg, prns=plan.unpredicted, acq_looks=1)
                found += cold_search(self.source, scfg, int(now_sample), self.signal)
                srch["coarse_runs"] += 1
                srch["coarse_prns"] += len(plan.unpredicted)
        srch["predicted"], srch["below_mask"] = sorted(plan.predicted), sorted(plan.below_mask)
        by_prn = {self.chinfo[ch]["prn"]: ch for ch in idle}
        for a in found:
            if a.detected and a.peak_cn0_dbhz >= self.cfg.acq_min_cn0_dbhz:
                self._start_found(by_prn[a.prn], a)
        srch["cpu_s"] += time.process_time() - c0

    def _search_plan(self, prns, now_sample):
        """The :class:`~ultratight.receiver.scalar.search_plan.SearchPlan` of ``prns`` at ``now_sample``
        from the latest fix and the ephemerides known (``--ephemeris``, else decoded on a channel)."""
        fix = self.fixes[-1] if self.fixes else None
        if fix is None:
            return plan_search(prns, lambda p: None, None, 0.0, self.cfg.mask_deg, self.signal.wavelength_m,
                               self.cfg.doppler_range_hz)
        age = (now_sample - fix["sample_index"]) / self.fs
        tow = float(fix["gps_tow_s"]) + age
        ch_of = {c["prn"]: ch for ch, c in enumerate(self.chinfo)}

        def eph_of(prn):
            eph = self.pvt.eph_of(prn, fix["gps_week"], tow)
            return eph if eph is not None else self.navs[ch_of[prn]].ephemeris
        return plan_search(prns, eph_of, fix, age, self.cfg.mask_deg, self.signal.wavelength_m,
                           self.cfg.doppler_range_hz)

    def _start_found(self, ch, a):
        """Start channel ``ch`` on the periodic search's detection ``a``."""
        search_rate(self.source, a, self.cfg, self.stop, self.signal)
        self.tracker.start_channel(ch, a.prn, a.code_phase_chips, a.doppler_hz, a.sample_index, a.cn0_dbhz,
                                   a.rate_hz_s)
        self.chinfo[ch]["started"] = True
        self.chinfo[ch]["acquired_s"] = (a.sample_index - self.start_sample) / self.fs
        self.acq.append(a)

    def _next_sample(self):
        """The next sample the tracking bank needs, after re-acquiring lost channels when none is
        active; None at the end of the run."""
        tracker, chinfo = self.tracker, self.chinfo
        while True:
            s = tracker.next_needed_sample()
            if s is not None:
                return s
            # every channel lost: try re-acquiring at the furthest point reached
            far = max((h.end_sample for h in self.hists), default=self.start_sample)
            if not self.cfg.reacquire or far + self.margin >= self.stop:
                return None
            nxt = min((c["next_retry"] or far) for c in chinfo if c["started"])
            for ch in range(self.n_ch):
                if chinfo[ch]["started"]:
                    self._reacquire(ch, max(far, nxt))
            if tracker.next_needed_sample() is None:
                if all(c["next_retry"] is not None and c["next_retry"] + self.margin >= self.stop
                       for c in chinfo if c["started"]):
                    return None
                continue
            return tracker.next_needed_sample()

    def _after_block(self, s):
        """Re-acquisition and the search of idle PRNs after the block at ``s``; returns the limit of the
        block's observation epochs (:meth:`_observation_epochs`, run while the next block is tracked)."""
        if self.cfg.reacquire:
            for ch in range(self.n_ch):
                if self._lost(ch):
                    self._reacquire(ch, self.hists[ch].end_sample if self.hists[ch].end_sample > 0 else s)
        if self.all_in_view:
            self._search_idle(max(h.end_sample for h in self.hists))
        return self._observation_limit()

    def _blocks(self, bar, t_wall0):
        """The block loop. The tracking of a block (compiled, the GIL released) runs on a second
        thread while this one hands over the records of the block before and computes their
        observation epochs: those read only the channels' histories, decoders and the limit taken
        before the block (nothing the tracking writes). The channels that lost lock are stopped, and
        when the re-acquisition or the search may act after a block (:meth:`_after_block_due`) its
        records go in and they run, before the next block is tracked, so every search still sees
        every fix before it and the results are those of the sequential order (``--threads 1``: that
        order, on this thread)."""
        pending = None          # observation limit of the block before, its epochs not yet computed
        held = None             # records of the block before, not yet handed over
        one_thread = self.cfg.threads == 1          # --threads 1: everything on this thread, in order
        with contextlib.nullcontext() if one_thread else \
                ThreadPoolExecutor(max_workers=1, thread_name_prefix="tracking") as pool:
            while True:
                waiting = held is not None or pending is not None
                if waiting and (one_thread or self.tracker.next_needed_sample() is None):
                    self._hand_over(held, pending, bar, t_wall0)   # before re-acquiring (it counts restarts)
                    held = pending = None
                s = self._next_sample()
                if s is None or s + self.margin >= self.stop:
                    break
                if one_thread:
                    recs = self._read_track(s)
                else:
                    job = pool.submit(self._read_track, s)
                    try:
                        if held is not None or pending is not None:
                            self._hand_over(held, pending, bar, t_wall0)
                            held = pending = None
                    finally:
                        wait([job])
                    recs = job.result()
                if recs is None:
                    break
                self._block_done(s, recs)
                if one_thread or self._after_block_due(s, recs):
                    self._take_records(recs)
                    pending = self._after_block(s)
                    self._progress(bar, t_wall0)
                else:
                    held = recs
        if held is not None or pending is not None:
            self._hand_over(held, pending, bar, t_wall0)

    def _hand_over(self, held, pending, bar, t_wall0):
        """The held block's records (then the limit of its observation epochs), and the epochs."""
        if held is not None:
            self._take_records(held)
            pending = self._observation_limit()
            self._progress(bar, t_wall0)
        if pending is not None:
            self._observation_epochs(pending)

    def _progress(self, bar, t_wall0):
        new_done = (max(h.end_sample for h in self.hists) - self.start_sample) / self.fs
        if bar is not None and new_done > self.done_s:
            bar.update(round(new_done - self.done_s, 3))
            el = time.perf_counter() - t_wall0
            bar.set_postfix_str(f"rtf {el / max(new_done, 1e-9):.3f}, fixes {len(self.fixes)}", refresh=False)
        self.done_s = max(self.done_s, new_done)

    # ----------------------------------------------------------------- run
    def run(self, out_path=None, csv_path=None, kml_path=None, progress=False, run_config=None, assist=None,
            rinex_obs_path=None, rinex_nav_path=None, nmea_path=None):
        """Run the pipeline over the file; arguments as :func:`process`."""
        t_wall0, t_cpu0 = time.perf_counter(), time.process_time()
        self.acq = acquire_signals(self.source, self.cfg, self.start_sample, assist, self.signal)
        self.recorder = None
        bar = None
        try:
            self._build(self.acq, out_path, rinex_obs_path)
            self.fixes, self.observations = [], []
            self.n_blocks_done = 0
            result = ProcessResult(self.input_info, self.acq, [], self.fixes, self.observations,
                                   out_path=str(out_path) if out_path else None, epochs=self.recorder.epochs)
            result.corrections = self.pvt.corrections
            bar = _progress_bar(self.stop - self.start_sample, self.fs) if progress else None
        except BaseException:
            # an error or an interruption before the run loop: the outputs opened so far go
            if self.recorder is not None:
                self.recorder.abort()
            if bar is not None:
                bar.close()
            raise
        self.done_s = 0.0          # seconds of signal processed (kept on an interruption)
        complete = False
        try:
            self.recorder.acquisition(self.acq)
            self._blocks(bar, t_wall0)
            complete = True
        except KeyboardInterrupt:
            result.interrupted = True
            raise
        finally:
            if self.recorder.rinex_obs is not None and not complete:
                self.recorder.rinex_obs.abort()
            if bar is not None:
                bar.close()
            result.signal_s = max(self.done_s, 0.0)
            result.wall_s = time.perf_counter() - t_wall0
            result.cpu_s = time.process_time() - t_cpu0
            self._finish(result, complete, run_config, csv_path, kml_path, rinex_nav_path, nmea_path)
        return result

    def _channel_summaries(self):
        tracker = self.tracker
        for ch, info in enumerate(self.chinfo):
            info["locked_fraction"] = round(info["locked_epochs"] / info["epochs"], 4) if info["epochs"] else 0.0
            info["tracked"] = bool(info["locked_fraction"] >= 0.5 or
                                   (tracker.active[ch] and tracker.state.si[ch, S_MODE] == MODE_TRACK))
            cn = tracker.state.cn0_dbhz(ch)
            info["cn0_dbhz"] = None if not np.isfinite(cn) else round(cn, 2)
            info.pop("next_retry", None)
        return self.chinfo

    def _finish(self, result, complete, run_config, csv_path, kml_path, rinex_nav_path, nmea_path):
        """Channel summaries, warnings and the outputs (partial HDF5 output on an interruption)."""
        result.channels = self._channel_summaries()
        result.corrections = self.pvt.corrections
        srch = self.search
        result.search = {"runs": srch["predicted_runs"] + srch["coarse_runs"], "predicted_runs": srch["predicted_runs"],
                         "coarse_runs": srch["coarse_runs"], "predicted_prns": srch["predicted_prns"],
                         "coarse_prns": srch["coarse_prns"], "predicted": srch["predicted"],
                         "below_mask": srch["below_mask"], "cpu_s": srch["cpu_s"]}
        result.searches = result.search["runs"]
        result.warnings = _spectrum_check(self.hists, self.tracker, self.input_info, signal=self.signal)
        if self.cfg.record_epochs:
            result.epochs = self.recorder.epoch_arrays()
        writer = self.recorder.writer
        if writer is not None:
            try:
                if complete or result.interrupted:
                    finish_hdf5(writer, result, self.cfg, run_config)
                else:
                    writer.abort()
            except Exception:
                writer.abort()
                raise
        if complete:
            if csv_path or kml_path:
                from ultratight.receiver.io.outputs import write_csv, write_kml   # (h5py loads with them)
            if csv_path:
                write_csv(csv_path, self.fixes)
            if kml_path:
                write_kml(kml_path, self.fixes, options=result.corrections)
            write_exchange_files(result, self.cfg, self.navs, self.ephemerides, self.pvt.used_ephs,
                                  self.pvt.iono, self.recorder.rinex_obs, rinex_nav_path, nmea_path)
            rinex = self.recorder.rinex_obs
            if rinex is not None and rinex.first is None:
                n = len(self.observations)
                why = "the run formed no observation epoch" if n == 0 else \
                    f"none of its {n} observation epoch(s) has a known GPS week and time of week"
                result.warnings.append(f"--rinex-obs {rinex.path} not written: {why}")


def _progress_bar(n_samples, fs):
    from tqdm import tqdm
    return tqdm(total=round(n_samples / fs, 1), unit="s", desc="process",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s signal "
                           "[{elapsed}<{remaining}{postfix}]", leave=False)


def process(source, config=None, ephemerides=None, out_path=None, csv_path=None, kml_path=None,
            progress=False, run_config=None, assist=None, rinex_obs_path=None, rinex_nav_path=None,
            nmea_path=None, signal=GPS_L1CA):
    """Run the scalar receiver on ``source`` (IfSource or path); returns a :class:`ProcessResult`.

    Builds a :class:`ScalarReceiver` and runs it.  ``ephemerides``: None (decode from the signal),
    a RINEX :class:`NavData` or dict prn -> Ephemeris.  ``assist``: optional list of dicts (prn,
    doppler_hz, code_phase_chips, sample_index, cn0_dbhz) replacing the acquisition (warm start,
    e.g. from a scenario's truth or a prediction).  ``out_path``: HDF5 output (schema in
    docs/process.md); ``rinex_obs_path`` / ``rinex_nav_path``: RINEX 3.04 observation / navigation
    files (:mod:`ultratight.receiver.io.rinex_out`); ``nmea_path``: NMEA 0183 sentences
    (:mod:`ultratight.receiver.io.nmea`).  ``signal``: the signal description (default GPS L1 C/A).
    KeyboardInterrupt stops the run, writes a partial output (root attribute ``complete = False``)
    and re-raises.
    """
    rx = ScalarReceiver(source, config, ephemerides, signal)
    return rx.run(out_path=out_path, csv_path=csv_path, kml_path=kml_path, progress=progress,
                  run_config=run_config, assist=assist, rinex_obs_path=rinex_obs_path,
                  rinex_nav_path=rinex_nav_path, nmea_path=nmea_path)


def _spectrum_check(hists, tracker, input_info, min_doppler_hz=800.0, signal=GPS_L1CA):
    """Detect a mirrored spectrum (wrong I/Q convention or IF sign) from code-carrier consistency.

    The code NCO is carrier aided, ``code_rate = f_chip (1 + f_D/f_carrier) + u`` (the signal's chip
    rate and carrier); with the right convention the DLL correction ``u`` averages ~0, with a
    mirrored spectrum the tracked Doppler has the wrong sign and ``u`` must supply
    ``-2 f_D f_chip/f_carrier`` (the narrow DLL only partly
    manages: measured ratios 0.07-0.44 on a 0.5 s real file read mirrored, |ratio| < 0.05 read
    right; a majority of channels above MIRROR_RATIO flags the file)."""
    f_chip, f_carr = signal.chip_rate_hz, signal.carrier_hz
    votes, ratios = 0, []
    for ch, h in enumerate(hists):
        if h.ptr.size < 200:
            continue
        lock = (h.flags & FL_PLL_LOCK) > 0
        if lock.sum() < 100:
            continue
        d = float(np.median(h.dopp[lock]))
        if abs(d) < min_doppler_hz:
            continue
        u = float(np.mean(h.code_rate[lock] - f_chip * (1.0 + h.dopp[lock] / f_carr)))
        r = u / (-2.0 * d * f_chip / f_carr)
        ratios.append(round(r, 2))
        votes += r > MIRROR_RATIO
    if len(ratios) >= 2 and votes > len(ratios) / 2:
        hint = ("try --iq-conj" if input_info["is_complex"] else "check the IF sign / LO side (spectral inversion)")
        return [f"code and carrier Dopplers disagree in sign on {votes} of {len(ratios)} channels "
                f"(code-rate correction / mirrored expectation = {ratios}): the spectrum looks inverted "
                f"(iq_conj={input_info['iq_conj']}); {hint}"]
    return []
