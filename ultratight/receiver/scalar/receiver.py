"""The scalar receiver: a pipeline of stages from IF samples to position fixes.

:class:`ScalarReceiver` is built from stages with array interfaces, each usable alone:

1. acquisition / assistance (:func:`acquire_signals`: :func:`ultratight.receiver.dsp.acquisition.acquire`
   in two stages, or assistance records) and channel allocation (:func:`allocate_channels`); with
   ``dynamics = "high"`` every channel then starts from a Doppler-rate search (:func:`search_rate`:
   :func:`ultratight.receiver.dsp.acquisition.doppler_rate_search`) that presets the PLL's rate;
2. the IF block stream (:class:`ultratight.receiver.dsp.blockstream.BlockStream`, with the per-arm
   noise estimate);
3. the scalar tracking bank (:class:`ultratight.receiver.dsp.tracking.ScalarTracker`: FLL-assisted PLL,
   DLL, C/N0, lock and bit-sync in one numba kernel per block);
4. bit synchronisation + navigation decoding (:class:`NavBitStage`, the decoder the signal
   description names: :func:`ultratight.receiver.scalar.navdecode.channel_nav`);
5. observables (:class:`ObservableStage`) and 6. PVT (:class:`PvtStage`);
7. outputs (:class:`Recorder`: HDF5 stream, RINEX observations, in-memory epoch series).

Every stage takes a :class:`ultratight.signals.signal.SignalDescription` (default GPS L1 C/A)
instead of signal constants. :func:`process` builds and runs a :class:`ScalarReceiver` on an opened
:class:`ultratight.signals.recording.iffile.IfSource` (or a path) and returns a :class:`ProcessResult`; it is
what ``ultratight process`` runs (``record_epochs=True`` keeps the per-channel, per-epoch Doppler /
code phase estimates with their sample indices in memory: ``result.epochs[prn]``). The scenario's
``scalar`` method does not call :func:`process`: :func:`ultratight.receiver.cli.scenario_runner.run_scalar`
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

import math
import time
from dataclasses import asdict, dataclass, field, replace

import numba
import numpy as np
from tqdm import tqdm

from ultratight import __version__
from ultratight.constants import C
from ultratight.errors import ConfigError, InputFileError, UltratightError
from ultratight.ins.earth import ecef_to_llh
from ultratight.receiver.dsp.acquisition import AcqResult, acquire, doppler_rate_search
from ultratight.receiver.dsp.blockstream import BlockStream
from ultratight.receiver.scalar.navdecode import channel_nav
from ultratight.receiver.io.nmea import DEFAULT_LEAP_S, write_nmea
from ultratight.receiver.scalar.observables import CarrierSmoother, ChannelHistory, observe, pseudorange
from ultratight.receiver.io.outputs import H5Stream, write_csv, write_kml
from ultratight.receiver.scalar.pvt import atmosphere_delays, elevations, solve_pvt
from ultratight.receiver.io.rinex_out import RinexObsWriter, write_rinex_nav
from ultratight.receiver.dsp.tracking import ScalarTracker
from ultratight.receiver.dsp.tracking_config import TrackingConfig
from ultratight.receiver.dsp.tracking_layout import (
    FL_BIT_DONE, FL_BIT_SYNC, FL_PLL_LOCK, MODE_LOST, MODE_TRACK, R_BIT, R_CN0, R_CODE_PHASE, R_DOPP, R_IP,
    REC_F_NAMES, REC_I_NAMES, RI_EPOCH, RI_FLAGS, RI_MODE, RI_PTR, S_MODE)
from ultratight.cores import stage_threads
from ultratight.signals.atmosphere import IONO_MODELS, MAPPINGS, TROPO_MODELS, AtmosphereModel
from ultratight.signals.ephemeris import sat_state
from ultratight.signals.recording.iffile import open_if
from ultratight.signals.signal import GPS_L1CA

RX_T0_OFFSET_S = 0.075       # initial guess of the signal travel time
CLOCK_STEER_S = 1e-3         # re-steer the receiver time when |bias| exceeds this
SIGMA_SAMPLES = 65536        # samples used per block for the noise-power estimate
DYNAMICS = ("normal", "high")
STAGE2_HZ = 400.0            # half-width of the declared (long coherent) search around stage 1
RELEASE_EVERY = 20           # blocks between releases of the processed part of the file mapping
MIRROR_RATIO = 0.1           # see _spectrum_check
PRE_SYNC_KEEP = 30000        # 1 ms prompts kept per channel before bit sync (for the earliest bits)


class NoSignalError(UltratightError):
    """No satellite acquired in the file (wrong parameters, wrong I/Q convention, no signal)."""


@dataclass
class ProcessConfig:
    n_channels: int | None = None       # None: all in view (one channel per searched PRN, periodic search)
    prns: list | None = None
    duration_s: float | None = None
    start_s: float = 0.0
    obs_rate_hz: float = 10.0
    block_ms: int = 200
    mask_deg: float = 5.0
    doppler_range_hz: float = 10e3
    acq_coherent_ms: int = 10           # coherent FFT search length (cut to the file length)
    acq_noncoherent: int = 1            # non-coherent sums of coherent blocks
    acq_looks: int | None = None        # looks at consecutive blocks, best kept per PRN (None: 1 for
                                        # snapshots < 1 s, else 2 - see _acquire)
    acq_pfa: float = 1e-3
    acq_min_cn0_dbhz: float = 37.0      # declare only when the peak C/N0 (metric-1)/T_coh reaches this
    doppler_window_s: float = 0.05      # half-width h of the centred Doppler difference
    sigma_pr_m: float = 3.0
    smoothing_s: float = 100.0          # Hatch-filter window for the pseudoranges (0: none)
    sigma_rr_mps: float = 0.05
    reacquire: bool = True
    reacq_retry_s: float = 1.0
    search_every_s: float = 15.0        # all-in-view: search again for the PRNs not tracked
    iono: str = "klobuchar"             # klobuchar | off (klobuchar applies once alpha/beta are known)
    tropo: str = "saastamoinen"         # saastamoinen | off
    tropo_mapping: str = "cosz"         # mapping function of the Saastamoinen model
    record_epochs: bool = False
    parallel: bool | None = None        # spread channels over numba threads (None: when >= 1.25 cores are available)
    threads: int | None = None          # threads for that (None: numba's pool); 1 = parallel False
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    dynamics: str = "normal"            # normal | high: Doppler-rate search after every acquisition (docs/process.md)
    rate_span_s: float = 0.4            # high dynamics: span of the Doppler-rate search

    def validate(self, source):
        if self.dynamics not in DYNAMICS:
            raise ConfigError(f"--dynamics must be one of {', '.join(DYNAMICS)}, got {self.dynamics!r}")
        if self.n_channels is not None and not 1 <= int(self.n_channels) <= 32:
            raise ConfigError(f"--channels must be in 1..32, got {self.n_channels}")
        if self.threads is not None and not (int(self.threads) == self.threads and self.threads >= 1):
            raise ConfigError(f"--threads must be an integer >= 1, got {self.threads}")
        if not self.search_every_s > 0:
            raise ConfigError(f"search interval must be > 0 s, got {self.search_every_s}")
        if not 0.1 <= self.obs_rate_hz <= 50.0:
            raise ConfigError(f"observation rate must be in [0.1, 50] Hz, got {self.obs_rate_hz}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ConfigError(f"--duration must be > 0 s, got {self.duration_s}")
        if self.start_s < 0:
            raise ConfigError(f"start must be >= 0 s, got {self.start_s}")
        if self.prns is not None:
            for p in self.prns:
                if not 1 <= int(p) <= 32:
                    raise ConfigError(f"--prn: PRN must be in 1..32, got {p}")
        if not 10 <= self.block_ms <= 1000:
            raise ConfigError(f"block_ms must be in [10, 1000], got {self.block_ms}")
        if self.iono not in IONO_MODELS:
            raise ConfigError(f"--iono must be one of {', '.join(IONO_MODELS)}, got {self.iono!r}")
        if self.tropo not in TROPO_MODELS:
            raise ConfigError(f"--tropo must be one of {', '.join(TROPO_MODELS)}, got {self.tropo!r}")
        if self.tropo_mapping not in MAPPINGS:
            raise ConfigError(f"tropospheric mapping must be one of {', '.join(MAPPINGS)}, got {self.tropo_mapping!r}")
        if self.doppler_window_s * self.obs_rate_hz > 0.5 + 1e-9:
            self.doppler_window_s = 0.5 / self.obs_rate_hz
        if self.doppler_range_hz >= 0.5 * source.fs_hz:
            self.doppler_range_hz = 0.45 * source.fs_hz
        self.tracking.validate()


@dataclass
class ProcessResult:
    input: dict
    acquisition: list                  # AcqResult of every PRN searched
    channels: list                     # per channel dict: prn, locked_fraction, losses, tow_s, eph_s ...
    fixes: list                        # per fix dict (see docs/process.md)
    observations: list                # per obs epoch dict (compact)
    signal_s: float = 0.0
    wall_s: float = 0.0
    interrupted: bool = False
    out_path: str | None = None
    epochs: dict = field(default_factory=dict)   # prn -> dict of arrays (record_epochs)
    warnings: list = field(default_factory=list)
    corrections: dict = field(default_factory=dict)   # atmosphere options and coefficients used
    searches: int = 0                  # all-in-view searches run after the first acquisition

    @property
    def realtime_factor(self):
        return self.wall_s / self.signal_s if self.signal_s > 0 else float("nan")

    @property
    def first_fix_s(self):
        return self.fixes[0]["t_s"] if self.fixes else None

    def position_median(self):
        if not self.fixes:
            return None, None
        pos = np.median(np.array([f["pos_e"] for f in self.fixes]), axis=0)
        llh = ecef_to_llh(pos.copy())
        return pos, [math.degrees(llh[0]), math.degrees(llh[1]), float(llh[2])]

    def summary(self):
        pos, llh = self.position_median()
        tracked = [c["prn"] for c in self.channels if c["tracked"]]
        return {
            "input": self.input,
            "acquired": [{"prn": a.prn, "doppler_hz": round(a.doppler_hz, 2),
                          "code_phase_chips": round(a.code_phase_chips, 3),
                          "cn0_dbhz": round(a.cn0_dbhz, 2), "peak_cn0_dbhz": round(a.peak_cn0_dbhz, 2),
                          "metric": round(a.metric, 2)}
                         for a in self.acquisition if a.detected],
            "detected_below_cn0_floor": [{"prn": a.prn, "doppler_hz": round(a.doppler_hz, 2),
                                          "cn0_dbhz": round(a.cn0_dbhz, 2), "peak_cn0_dbhz": round(a.peak_cn0_dbhz, 2),
                                          "metric": round(a.metric, 2)}
                                         for a in self.acquisition if getattr(a, "weak", False)],
            "tracked": tracked,
            "channels": self.channels,
            "fixes": len(self.fixes),
            "first_fix_s": self.first_fix_s,
            "position_ecef_m": None if pos is None else [float(v) for v in pos],
            "position_llh": llh,
            "velocity_ecef_mps": (None if not self.fixes else
                                  [float(v) for v in np.median([f["vel_e"] for f in self.fixes], axis=0)]),
            "signal_s": self.signal_s,
            "wall_s": round(self.wall_s, 3),
            "realtime_factor": round(self.realtime_factor, 4) if self.signal_s > 0 else None,
            "interrupted": self.interrupted,
            "warnings": self.warnings,
            "corrections": self.corrections,
            "searches": self.searches,
            "version": __version__,
            "out": self.out_path,
        }


_F64_FIELDS = ("code_phase_chips", "code_rate_cps", "carr_acc_cycles", "doppler_hz")
_SMALL_INT = {"n_samples": np.int32, "mode": np.int8, "flags": np.int8}
TRACK_DTYPE = np.dtype([(n, _SMALL_INT.get(n, np.int64)) for n in REC_I_NAMES] +
                       [(n, np.float64 if n in _F64_FIELDS else np.float32) for n in REC_F_NAMES])


def tracking_rows(rf, ri):
    """Structured rows (TRACK_DTYPE) of one channel's epoch records."""
    out = np.empty(rf.shape[0], dtype=TRACK_DTYPE)
    for j, n in enumerate(REC_I_NAMES):
        out[n] = ri[:, j]
    for j, n in enumerate(REC_F_NAMES):
        out[n] = rf[:, j]
    return out


def _eph_lookup(ephemerides):
    """Normalise --ephemeris input to a function (prn, week, tow) -> Ephemeris | None."""
    if ephemerides is None:
        return lambda prn, week, tow: None
    if hasattr(ephemerides, "select"):
        def f(prn, week, tow):
            if week is None:
                lst = ephemerides.ephemerides.get(int(prn), [])
                if not lst:
                    return None
                week = lst[len(lst) // 2].week
            return ephemerides.select(prn, week, tow)
        return f
    return lambda prn, week, tow: ephemerides.get(int(prn))


def _peak_cn0(metric, coh_ms):
    return 10.0 * math.log10(max(metric - 1.0, 1e-12) / (coh_ms * 1e-3))


def _acquire(source, cfg, start_sample, signal=GPS_L1CA):
    """Cold-start search; each result gets ``peak_cn0_dbhz = 10 log10((metric - 1) / T_coh)``.

    The CFAR metric is peak / noise floor of the search surface, whose mean under a signal is
    ``1 + C/N0 T_coh`` per coherent block, so the peak gives a C/N0 figure that is independent of the
    refinement (the same definition PocketSDR uses for its acquisition threshold).

    A 10 ms coherent block containing a data-bit transition near its middle loses most of its
    peak; bit edges are 20 ms apart, so a second look one block later cannot be hit as well.  By
    default recordings of 1 s or more get two looks; shorter snapshots get one look (the reference
    lists of shared/data/README.md were made so: on the 0.5 s PocketSDR IQ file a second look also
    declares PRN 18, a real satellite at ~38-40 dB-Hz that the list does not show)."""
    avail_ms = int((source.n_samples - start_sample) / source.fs_hz * 1000.0)
    if avail_ms < 1:
        raise InputFileError(f"{source.path}: only {source.n_samples - start_sample} samples "
                             f"({(source.n_samples - start_sample) / source.fs_hz * 1e3:.3f} ms) from the start "
                             f"sample; need at least 1 ms (one {signal.name} code period) to acquire")
    coh = max(1, min(int(cfg.acq_coherent_ms), avail_ms))
    nc = max(1, min(int(cfg.acq_noncoherent), avail_ms // coh))
    prns = cfg.prns if cfg.prns else None
    n_blk = int(round(coh * nc * 1e-3 * source.fs_hz))
    looks = cfg.acq_looks if cfg.acq_looks is not None else (2 if avail_ms >= 1000 else 1)
    looks = 2 if (looks > 1 and avail_ms >= 2 * coh * nc) else 1
    # stage 1: cheap full search (1 ms coherent, up to 10 non-coherent): candidate PRNs and Dopplers
    if nc > 1:
        # weak-signal settings: the full search at the requested integration (a 1 ms first stage
        # would lose the coherent gain)
        res = acquire(source, prns=prns, doppler_range_hz=cfg.doppler_range_hz, coherent_ms=coh,
                      noncoherent=nc, pfa=cfg.acq_pfa, start_sample=start_sample, signal=signal)
    else:
        nc1 = max(1, min(avail_ms, 10))
        res = acquire(source, prns=prns, doppler_range_hz=cfg.doppler_range_hz, coherent_ms=1,
                      noncoherent=nc1, pfa=cfg.acq_pfa, start_sample=start_sample, signal=signal)
    if nc == 1 and coh > 1:
        # stage 2: the declared search (coh ms coherent) only for the candidates, in a window of
        # +-STAGE2_HZ around their stage-1 Doppler; a second look one block later for long files
        # (a data-bit edge can cancel one 10 ms block, never two consecutive ones: edges are 20 ms apart)
        cand = [a.prn for a in res if a.detected]
        if cand:
            ctr = {a.prn: a.doppler_hz for a in res if a.detected}
            by_prn = {}
            for look in range(looks):
                r2 = acquire(source, prns=cand, doppler_center_hz=ctr, doppler_range_hz=STAGE2_HZ,
                             coherent_ms=coh, noncoherent=nc, pfa=cfg.acq_pfa,
                             start_sample=start_sample + look * n_blk, signal=signal)
                for b in r2:
                    if b.prn not in by_prn or b.metric > by_prn[b.prn].metric:
                        by_prn[b.prn] = b
                # the next look only for candidates still short of the declaration floor
                cand = [p for p in cand if not (by_prn[p].detected and
                                                _peak_cn0(by_prn[p].metric, coh) >= cfg.acq_min_cn0_dbhz)]
                if not cand:
                    break
            res = [by_prn.get(a.prn, a) for a in res]
    for a in res:
        a.peak_cn0_dbhz = _peak_cn0(a.metric, coh)
        a.coherent_ms = coh
        a.noncoherent = nc
    return res


def _assisted(a, start_sample):
    """An acquisition-like record from an assistance dict (prn, doppler_hz, code_phase_chips,
    sample_index, optional cn0_dbhz)."""
    cn0 = float(a.get("cn0_dbhz", math.nan))
    r = AcqResult(prn=int(a["prn"]), doppler_hz=float(a["doppler_hz"]), code_phase_chips=float(a["code_phase_chips"]),
                  cn0_dbhz=cn0, metric=math.inf, detected=True, threshold=0.0,
                  sample_index=int(a.get("sample_index", start_sample)))
    r.peak_cn0_dbhz = math.inf        # assisted channels are not subject to the acquisition C/N0 floor
    r.coherent_ms = 0
    r.noncoherent = 0
    return r


def search_rate(source, a, cfg, stop_sample, signal=GPS_L1CA):
    """High dynamics: the Doppler and Doppler rate of the detected acquisition ``a`` by
    :func:`ultratight.receiver.dsp.acquisition.doppler_rate_search` over ``cfg.rate_span_s`` (shorter
    before ``stop_sample``); sets ``a.doppler_hz`` and ``a.rate_hz_s``. Normal dynamics, assisted
    records, or too few samples left: ``a.rate_hz_s`` = None (the loop starts without a rate)."""
    a.rate_hz_s = None
    if cfg.dynamics != "high" or not a.detected or not math.isfinite(a.metric):
        return a
    span = min(cfg.rate_span_s, (stop_sample - a.sample_index) / source.fs_hz)
    if span < 0.05:
        return a
    r = doppler_rate_search(source, a.prn, a.doppler_hz, a.code_phase_chips, a.sample_index, span_s=span,
                            signal=signal)
    a.doppler_acq_hz = a.doppler_hz
    a.doppler_hz = r.doppler_hz
    a.rate_hz_s = r.rate_hz_s
    return a


# ------------------------------------------------------------------------------ stages
def acquire_signals(source, cfg, start_sample, assist=None, signal=GPS_L1CA):
    """Acquisition / assistance stage: one :class:`ultratight.receiver.dsp.acquisition.AcqResult` per
    PRN searched (``assist``: records replacing the search). Detections below the C/N0 floor are
    marked ``weak`` and not ``detected``; raises :class:`NoSignalError` when none is left."""
    if assist is not None:
        acq = [_assisted(a, start_sample) for a in assist]
    else:
        acq = _acquire(source, cfg, start_sample, signal)
    for a in acq:
        if a.detected and not (a.peak_cn0_dbhz >= cfg.acq_min_cn0_dbhz):
            a.weak = True                # passed the false-alarm test, below the C/N0 floor
            a.detected = False
    if not any(a.detected for a in acq):
        fs = source.fs_hz
        raise NoSignalError(
            f"no satellites acquired in {source.path} (format {source.fmt}, fs {fs:g} Hz, IF {source.if_hz:g} Hz, "
            f"{'complex' if source.is_complex else 'real'} samples, iq_conj={bool(getattr(source, '_conj', False))}, "
            f"Doppler +-{cfg.doppler_range_hz:g} Hz, {acq[0].coherent_ms} ms coherent x {acq[0].noncoherent}, "
            f"C/N0 floor {cfg.acq_min_cn0_dbhz:g} dB-Hz; below the floor: "
            f"{[a.prn for a in acq if getattr(a, 'weak', False)] or 'none'}). "
            f"Hint: check --fs/--if/--format; for complex files try --iq-conj (I - jQ spectrum inversion); "
            f"for real files check the IF sign/LO side")
    return acq


def allocate_channels(acq, cfg, signal=GPS_L1CA):
    """Channel allocation: ``(found, idle_prns)`` - the acquisitions that start a channel now
    (strongest first, at most ``n_channels``) and, all in view (``n_channels`` None), the searched
    PRNs that get a channel for a later search."""
    found = sorted([a for a in acq if a.detected], key=lambda a: -a.metric)
    if cfg.n_channels is not None:
        return found[:cfg.n_channels], []
    searched = [int(p) for p in (cfg.prns or signal.prns)]
    got = {a.prn for a in found}
    return found, [p for p in dict.fromkeys(searched) if p not in got]


def _channel_info(prn, acq=None, start_sample=0, fs=1.0):
    return {"prn": prn, "epochs": 0, "locked_epochs": 0, "losses": 0, "reacquisitions": 0,
            "tow_s": None, "ephemeris_s": None, "cn0_dbhz": None, "tracked": False,
            "next_retry": None, "bit_sync": False, "bit_sync_s": None, "started": acq is not None,
            "acquired_s": None if acq is None else (acq.sample_index - start_sample) / fs}


class NavBitStage:
    """Bit synchronisation + navigation decoding of every channel: the epoch records of a block in,
    the channel's navigation state (:func:`ultratight.receiver.scalar.navdecode.channel_nav`) out.

    Before the tracking kernel declares bit sync, the 1-code-period prompts are kept (at most
    ``PRE_SYNC_KEEP`` per channel); at the sync they are summed over the whole bits ending at the
    first bit the kernel forms, so the earliest bits reach the decoder too."""

    def __init__(self, navs, signal, fs, start_sample):
        self.navs = navs
        self.signal = signal
        self.fs = fs
        self.start_sample = start_sample
        self.pre_ip = [[] for _ in navs]
        self.pre_ep = [[] for _ in navs]

    def restart(self, ch):
        self.navs[ch].reset()
        self.pre_ip[ch], self.pre_ep[ch] = [], []

    def feed(self, ch, f_ch, i_ch, info):
        """The records (rows of R_* / RI_* columns) of channel ``ch``; updates ``info`` (bit_sync,
        bit_sync_s, tow_s, ephemeris_s)."""
        if not info["bit_sync"]:
            self._before_sync(ch, f_ch, i_ch, info)
        bits = np.flatnonzero(i_ch[:, RI_FLAGS] & FL_BIT_DONE)
        if bits.size:
            nav = self.navs[ch]
            now_ep = int(i_ch[-1, RI_EPOCH])
            nav.feed(f_ch[bits, R_BIT], i_ch[bits, RI_EPOCH] - (self.signal.codes_per_bit - 1), now_ep)
            t_now = (int(i_ch[-1, RI_PTR]) - self.start_sample) / self.fs
            if info["tow_s"] is None and nav.has_time:
                info["tow_s"] = t_now
            if info["ephemeris_s"] is None and nav.ephemeris is not None:
                info["ephemeris_s"] = t_now

    def _before_sync(self, ch, f_ch, i_ch, info):
        synced = np.flatnonzero(i_ch[:, RI_FLAGS] & FL_BIT_SYNC)
        self.pre_ip[ch].append(f_ch[:, R_IP].copy())
        self.pre_ep[ch].append(i_ch[:, RI_EPOCH].copy())
        if synced.size:
            info["bit_sync"] = True
            info["bit_sync_s"] = (int(i_ch[synced[0], RI_PTR]) - self.start_sample) / self.fs
            # bits before the sync: sum the buffered prompts over whole bits ending at the first
            # bit the tracking kernel forms (it starts at the sync epoch)
            e1 = int(i_ch[synced[0], RI_EPOCH])
            ip_all = np.concatenate(self.pre_ip[ch])
            ep_all = np.concatenate(self.pre_ep[ch])
            per_bit = self.signal.codes_per_bit
            starts = e1 - per_bit * np.arange((e1 - ep_all[0]) // per_bit, 0, -1)
            if starts.size and np.all(np.diff(ep_all) == 1):
                idx = (starts - ep_all[0])[:, None] + np.arange(per_bit)[None, :]
                self.navs[ch].feed(ip_all[idx].sum(axis=1), starts, e1)
            self.pre_ip[ch], self.pre_ep[ch] = [], []
        elif sum(a.size for a in self.pre_ip[ch]) > PRE_SYNC_KEEP:
            self.pre_ip[ch].pop(0)
            self.pre_ep[ch].pop(0)


class ObservableStage:
    """Observables at a common receive sample: the channels' epoch histories and navigation states
    in; transmit times, pseudoranges (raw and carrier smoothed), Doppler, carrier phase, C/N0 and
    lock flags out (:func:`ultratight.receiver.scalar.observables.observe`).

    Receiver time ``t_rx(s) = t0 + s/fs``: ``t0`` is set when the first channel knows its transmit
    time (``t0 = t_tx + RX_T0_OFFSET_S``) and moved by :meth:`steer`."""

    def __init__(self, hists, navs, prns, fs, start_sample, h_samp, smoother, signal):
        self.hists, self.navs, self.prns = hists, navs, prns
        self.fs, self.start_sample, self.h_samp = fs, start_sample, h_samp
        self.smoother = smoother
        self.signal = signal
        self.rx_t0 = None                 # receiver time of sample 0 (s of week)

    def epoch(self, s_obs):
        """``(row, obs)`` at sample ``s_obs``, or None while no channel knows its transmit time;
        ``row`` holds arrays over the channels, ``obs`` the per-channel observe() dicts."""
        obs = [observe(h, nv, s_obs, self.h_samp, self.signal) for h, nv in zip(self.hists, self.navs)]
        ttx = np.array([o["t_tx_sv"] if o is not None else np.nan for o in obs])
        if self.rx_t0 is None:
            if not np.isfinite(ttx).any():
                return None
            self.rx_t0 = float(np.nanmax(ttx)) + RX_T0_OFFSET_S - s_obs / self.fs
        t_rx = self.rx_t0 + s_obs / self.fs
        row = {"sample_index": int(s_obs), "t_s": (s_obs - self.start_sample) / self.fs, "t_rx": t_rx,
               "prn": list(self.prns), "t_tx_sv": ttx,
               "pseudorange_m": pseudorange(t_rx, ttx),
               "doppler_hz": np.array([o["doppler_hz"] if o else np.nan for o in obs]),
               "carrier_cycles": np.array([o["carrier_cycles"] if o else np.nan for o in obs]),
               "cn0_dbhz": np.array([o["cn0_dbhz"] if o else np.nan for o in obs]),
               "code_phase_chips": np.array([o["code_phase_chips"] if o else np.nan for o in obs]),
               "pll_lock": np.array([bool(o and o["pll_lock"]) for o in obs])}
        return row, obs

    def smooth(self, row):
        """Carrier-smoothed pseudoranges (Hatch filter) of ``row``."""
        return self.smoother.update(row["pseudorange_m"], row["carrier_cycles"], row["pll_lock"])

    def steer(self, bias_m):
        """Move the receiver time scale by the clock bias ``bias_m`` (towards GPS time)."""
        self.rx_t0 -= bias_m / C
        self.smoother.shift(-bias_m)


class PvtStage:
    """Satellite states and the position / velocity / clock solution of one observation epoch:
    transmit times, pseudoranges and Doppler (arrays over the channels) in, a fix dict out
    (:func:`ultratight.receiver.scalar.pvt.solve_pvt`, atmosphere per ``ProcessConfig.iono`` /
    ``tropo``). Ephemerides come from ``eph_of`` (RINEX / caller) or the channel's decoded
    navigation message."""

    def __init__(self, cfg, eph_of, navs, prns, ref_week, ephemerides, signal):
        self.cfg, self.eph_of, self.navs, self.prns = cfg, eph_of, navs, prns
        self.signal = signal
        self.week_known = ref_week
        self.last_x = None
        self.used_ephs = {}          # (prn, week, toe, iode) -> Ephemeris used by the PVT
        self.corrections = {}
        nav_iono = None
        if cfg.iono == "klobuchar" and getattr(ephemerides, "ion_alpha", None) and \
                getattr(ephemerides, "ion_beta", None):
            nav_iono = (tuple(ephemerides.ion_alpha), tuple(ephemerides.ion_beta), "rinex")
        self.iono = nav_iono
        self._model = None
        self.atmosphere_model()      # records the options in .corrections from the start

    def atmosphere_model(self):
        """The AtmosphereModel of this epoch (the ionosphere starts when coefficients are known)."""
        cfg = self.cfg
        if cfg.iono == "klobuchar" and self.iono is None:
            for nv in self.navs:
                io = nv.decoder.iono
                if io is not None:
                    self.iono = (tuple(io.alpha), tuple(io.beta), "lnav")
                    self._model = None
                    break
        if self._model is None:
            a, b, src = self.iono if self.iono is not None else (None, None, None)
            self._model = AtmosphereModel(cfg.iono, a, b, cfg.tropo, cfg.tropo_mapping)
            self.corrections = {**self._model.describe(), "iono_source": src,
                                "iono_option": cfg.iono, "tropo_option": cfg.tropo}
        return self._model

    def satellite_states(self, obs, ttx, pr):
        """``(sat_pos, sat_vel, corrected pseudorange, range rate)`` (arrays over the channels, NaN
        where a channel has no lock, no transmit time or no ephemeris)."""
        n = len(obs)
        sp = np.full((n, 3), np.nan)
        sv = np.full((n, 3), np.nan)
        prc = np.full(n, np.nan)
        rr = np.full(n, np.nan)
        for ch in range(n):
            o = obs[ch]
            if o is None or not np.isfinite(ttx[ch]) or not o["pll_lock"]:
                continue
            if self.week_known is None and self.navs[ch].decoder.week is not None:
                self.week_known = self.navs[ch].decoder.week
            eph = self.eph_of(self.prns[ch], self.week_known, ttx[ch])
            if eph is None:
                eph = self.navs[ch].ephemeris
            if eph is None:
                continue
            # state at the satellite-clock time, moved to GPS time t_gps = t_sv - clk (|clk| < 1 ms:
            # the linear step leaves < 1 um of position error)
            self.used_ephs[(eph.prn, eph.week, eph.toe, eph.iode)] = eph
            p_, v_, clk, drift = sat_state(eph, ttx[ch])
            p_ = p_ - v_ * float(clk[0])
            sp[ch] = p_[0]
            sv[ch] = v_[0]
            prc[ch] = pr[ch] + C * float(clk[0])
            rr[ch] = -self.signal.wavelength_m * o["doppler_hz"] + C * float(drift[0])
        return sp, sv, prc, rr

    def solve(self, row, obs, pr, steer):
        """The fix of this epoch, or None (fewer than 4 satellites, no solution, or the first solution
        / a clock bias beyond CLOCK_STEER_S, which ``steer(bias_m)`` removes from the time scale);
        returns ``(fix, sol, parts)``."""
        sp, sv, prc, rr = self.satellite_states(obs, row["t_tx_sv"], pr)
        if np.isfinite(prc).sum() < 4:
            return None
        model = self.atmosphere_model()
        parts = {}
        sol = solve_pvt(sp, prc, sv, rr, sigma_pr_m=self.cfg.sigma_pr_m, sigma_rr_mps=self.cfg.sigma_rr_mps,
                        x0=self.last_x, mask_deg=self.cfg.mask_deg,
                        delays=atmosphere_delays(model, row["t_rx"], parts) if model.active else None)
        if not sol.valid or sol.vel_e is None:
            return None
        if self.last_x is None or abs(sol.clk_bias_m) > CLOCK_STEER_S * C:
            # steer the receiver time scale to GPS time and re-solve on the next epoch
            steer(sol.clk_bias_m)
            self.last_x = np.r_[sol.pos_e, 0.0]
            return None
        self.last_x = np.r_[sol.pos_e, sol.clk_bias_m]
        return self._fix(row, sol, sp, model), sol, parts

    def _fix(self, row, sol, sp, model):
        n = sp.shape[0]
        fin = np.all(np.isfinite(sp), axis=1)
        el_all, az_all = np.full(n, np.nan), np.full(n, np.nan)
        if fin.any():
            el_all[fin], az_all[fin] = elevations(sol.pos_e, sp[fin])
        sv_list = [{"prn": self.prns[j], "elev_deg": math.degrees(el_all[j]),
                    "azim_deg": math.degrees(az_all[j]) % 360.0, "cn0_dbhz": float(row["cn0_dbhz"][j]),
                    "used": bool(sol.used[j])} for j in np.flatnonzero(fin)]
        llh_deg = [math.degrees(sol.llh[0]), math.degrees(sol.llh[1]), float(sol.llh[2])]
        return {"t_s": row["t_s"], "sample_index": row["sample_index"], "gps_week": self.week_known,
                "gps_tow_s": row["t_rx"] - sol.clk_bias_m / C, "pos_e": sol.pos_e, "vel_e": sol.vel_e,
                "llh_deg": llh_deg, "clk_bias_m": sol.clk_bias_m, "clk_drift_mps": sol.clk_drift_mps,
                "pdop": sol.dops.get("pdop", float("nan")), "gdop": sol.dops.get("gdop", float("nan")),
                "hdop": sol.dops.get("hdop", float("nan")), "vdop": sol.dops.get("vdop", float("nan")),
                "n_used": int(sol.used.sum()), "raim_ok": sol.raim_ok,
                "excluded_prn": [self.prns[j] for j in sol.excluded],
                "used_prn": [self.prns[j] for j in np.flatnonzero(sol.used)],
                "sigma_pos_m": float(np.sqrt(np.trace(sol.cov_pos_clk[:3, :3]))),
                "sigma_vel_mps": (float(np.sqrt(np.trace(sol.cov_vel_drift[:3, :3])))
                                  if sol.cov_vel_drift is not None else float("nan")),
                "iono": "klobuchar" if model.iono_active else "off", "tropo": self.cfg.tropo, "sv": sv_list}


class Recorder:
    """Outputs of a run as they come: the HDF5 stream (``out_path``, schema in docs/process.md), the
    RINEX observation writer and, with ``record_epochs``, the per-channel epoch series in memory."""

    EPOCH_KEYS = ("sample_index", "epoch", "doppler_hz", "code_phase_chips", "cn0_dbhz", "mode", "flags")

    def __init__(self, out_path, rinex_obs_path, cfg, source, prns):
        self.n_ch = len(prns)
        self.writer = H5Stream(out_path) if out_path else None
        self.epochs = {p: {k: [] for k in self.EPOCH_KEYS} for p in prns} if cfg.record_epochs else {}
        self.restarts = [0] * len(prns)        # re-acquisitions per channel at the previous RINEX epoch
        self.rinex_obs = None
        if rinex_obs_path:
            self.rinex_obs = RinexObsWriter(rinex_obs_path, 1.0 / cfg.obs_rate_hz, comments=[
                f"ultratight {__version__} process: iono={cfg.iono} tropo={cfg.tropo} "
                f"({cfg.tropo_mapping}), mask {cfg.mask_deg:g} deg",
                ("C1C carrier smoothed (Hatch filter, %g s window)" % cfg.smoothing_s) if cfg.smoothing_s > 0
                else "C1C raw code pseudorange",
                f"input {source.path}"])

    def acquisition(self, acq):
        w = self.writer
        if w is None:
            return
        w.write("acquisition/prn", np.array([a.prn for a in acq], dtype=np.int16))
        w.write("acquisition/doppler_hz", np.array([a.doppler_hz for a in acq]))
        w.write("acquisition/code_phase_chips", np.array([a.code_phase_chips for a in acq]))
        w.write("acquisition/cn0_dbhz", np.array([a.cn0_dbhz for a in acq]))
        w.write("acquisition/metric", np.array([a.metric for a in acq]))
        w.write("acquisition/threshold", np.array([a.threshold for a in acq]))
        w.write("acquisition/detected", np.array([a.detected for a in acq]))
        w.write("acquisition/sample_index", np.array([a.sample_index for a in acq], dtype=np.int64))

    def tracking(self, prn, f_ch, i_ch):
        """One channel's new epoch records."""
        if self.writer is not None:
            self.writer.append(f"tracking/prn{prn:02d}", tracking_rows(f_ch, i_ch))
        if self.epochs:
            e = self.epochs[prn]
            e["sample_index"].append(i_ch[:, RI_PTR].copy())
            e["epoch"].append(i_ch[:, RI_EPOCH].copy())
            e["doppler_hz"].append(f_ch[:, R_DOPP].copy())
            e["code_phase_chips"].append(f_ch[:, R_CODE_PHASE].copy())
            e["cn0_dbhz"].append(f_ch[:, R_CN0].copy())
            e["mode"].append(i_ch[:, RI_MODE].copy())
            e["flags"].append(i_ch[:, RI_FLAGS].copy())

    def observables(self, row, smoothed=None):
        w = self.writer
        if w is None:
            return
        w.append("observables/sample_index", np.array([row["sample_index"]], dtype=np.int64))
        w.append("observables/t_s", np.array([row["t_s"]]))
        w.append("observables/t_rx_tow_s", np.array([row["t_rx"]]))
        for k in ("pseudorange_m", "doppler_hz", "carrier_cycles", "cn0_dbhz", "code_phase_chips"):
            w.append(f"observables/{k}", row[k][None, :])
        w.append("observables/pll_lock", row["pll_lock"][None, :])

    def smoothed(self, pr):
        if self.writer is not None:
            self.writer.append("observables/pseudorange_smoothed_m", pr[None, :])

    def rinex_epoch(self, week, row, pr, navs, chinfo):
        sats = []
        for ch, info in enumerate(chinfo):
            nreacq = info["reacquisitions"]
            half = navs[ch].decoder.inverted is None
            sats.append({"prn": info["prn"], "pr_m": pr[ch],
                         "phase_cycles": row["carrier_cycles"][ch] + (0.5 if navs[ch].decoder.inverted else 0.0),
                         "doppler_hz": row["doppler_hz"][ch], "cn0_dbhz": row["cn0_dbhz"][ch],
                         "lock": bool(row["pll_lock"][ch]), "continuous": nreacq == self.restarts[ch],
                         "half_cycle": half})
            self.restarts[ch] = nreacq
        self.rinex_obs.add_epoch(week, row["t_rx"], sats)

    def fix(self, fix, sol, parts):
        w = self.writer
        if w is None:
            return
        n_ch = self.n_ch
        w.append("pvt/t_s", np.array([fix["t_s"]]))
        w.append("pvt/sample_index", np.array([fix["sample_index"]], dtype=np.int64))
        w.append("pvt/gps_tow_s", np.array([fix["gps_tow_s"]]))
        w.append("pvt/pos_e", sol.pos_e[None, :])
        w.append("pvt/vel_e", sol.vel_e[None, :])
        w.append("pvt/llh_deg", np.array([fix["llh_deg"]]))
        w.append("pvt/clk_bias_m", np.array([sol.clk_bias_m]))
        w.append("pvt/clk_drift_mps", np.array([sol.clk_drift_mps]))
        w.append("pvt/cov_pos_clk", sol.cov_pos_clk[None])
        w.append("pvt/cov_vel_drift", sol.cov_vel_drift[None])
        w.append("pvt/dop", np.array([[fix["gdop"], fix["pdop"], fix["hdop"], fix["vdop"]]]))
        w.append("pvt/n_used", np.array([fix["n_used"]], dtype=np.int16))
        w.append("pvt/raim_ok", np.array([sol.raim_ok]))
        used = np.zeros(n_ch, dtype=bool)
        used[sol.used] = True
        w.append("pvt/used", used[None, :])
        for k in ("iono_m", "tropo_m"):
            v = np.asarray(parts.get(k, np.full(n_ch, np.nan)), dtype=float) * np.ones(n_ch)
            w.append(f"pvt/{k}", v[None, :])

    def epoch_arrays(self):
        """The recorded epoch series as arrays (prn -> name -> array)."""
        for e in self.epochs.values():
            for k in list(e):
                e[k] = np.concatenate(e[k]) if e[k] else np.zeros(0)
        return self.epochs


class ScalarReceiver:
    """The scalar receiver: a pipeline of stages with array interfaces.

    acquisition / assistance (:func:`acquire_signals`) -> channel allocation
    (:func:`allocate_channels`) -> IF block stream (:class:`ultratight.receiver.dsp.blockstream.BlockStream`,
    with the noise estimate) -> scalar tracking bank (:class:`ultratight.receiver.dsp.tracking.ScalarTracker`)
    -> bit synchronisation + navigation decoding (:class:`NavBitStage`) -> observables
    (:class:`ObservableStage`) -> PVT (:class:`PvtStage`) -> outputs (:class:`Recorder`).

    Every stage takes the signal description ``signal`` (default GPS L1 C/A) instead of signal
    constants. :meth:`run` returns a :class:`ProcessResult`; :func:`process` builds and runs one.
    """

    def __init__(self, source, config=None, ephemerides=None, signal=GPS_L1CA):
        if not hasattr(source, "read"):
            source = open_if(source)
        self.source = source
        self.signal = signal
        self.cfg = cfg = config or ProcessConfig()
        cfg.validate(source)
        self.ephemerides = ephemerides
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
        if cfg.threads is not None:
            n_thr = stage_threads(cfg.threads)
            parallel = n_thr > 1
            if parallel:
                numba.set_num_threads(n_thr)
        else:
            parallel = (stage_threads(0) > 1) if cfg.parallel is None else bool(cfg.parallel)
        self.tracker = ScalarTracker(n_ch, fs, src.if_hz, src.is_complex, cfg.tracking,
                                     max_rows=int(cfg.block_ms * 1.1) + 8, parallel=parallel, signal=sig)
        self.chinfo = []
        for ch, a in enumerate(found):
            search_rate(src, a, cfg, self.stop, sig)
            self.tracker.start_channel(ch, a.prn, a.code_phase_chips, a.doppler_hz, a.sample_index, a.cn0_dbhz,
                                       a.rate_hz_s)
            self.chinfo.append(_channel_info(a.prn, a, self.start_sample, fs))
        self.chinfo += [_channel_info(p) for p in idle_prns]
        prns = [c["prn"] for c in self.chinfo]
        self.navs = [channel_nav(sig, p, src.start_week) for p in prns]
        self.hists = [ChannelHistory(fs) for _ in prns]
        self.navbits = NavBitStage(self.navs, sig, fs, self.start_sample)
        smoother = CarrierSmoother(n_ch, cfg.smoothing_s * cfg.obs_rate_hz, wavelength_m=sig.wavelength_m)
        h_samp = int(round(cfg.doppler_window_s * fs))
        self.observables = ObservableStage(self.hists, self.navs, prns, fs, self.start_sample, h_samp, smoother, sig)
        self.pvt = PvtStage(cfg, _eph_lookup(self.ephemerides), self.navs, prns, src.start_week,
                            self.ephemerides, sig)
        self.recorder = Recorder(out_path, rinex_obs_path, cfg, src, prns)
        self.obs_step = fs / cfg.obs_rate_hz
        self.k_obs = int(math.ceil((self.start_sample + h_samp + 1) / self.obs_step))
        self.h_samp = h_samp
        self.search = {"next": self.start_sample + int(cfg.search_every_s * fs), "runs": 0}

    # ----------------------------------------------------------------- per block
    def _track_block(self, s):
        """Track every active channel through the block starting at sample ``s``; False at the end."""
        n_read = min(self.block_len + self.margin, self.stop - s)
        recs = self.tracker.track_at(self.stream, s, n_read, SIGMA_SAMPLES, self.margin, self.stop)
        if recs is None:
            return False
        rf, ri, nr = recs
        self.n_blocks_done += 1
        if self.n_blocks_done % RELEASE_EVERY == 0:
            self.stream.release(s - self.margin)          # keeps the resident set flat on long files
        for ch in range(self.n_ch):
            m = int(nr[ch])
            if m:
                self._channel_records(ch, rf[ch, :m], ri[ch, :m])
        return True

    def _channel_records(self, ch, f_ch, i_ch):
        info = self.chinfo[ch]
        self.hists[ch].append(f_ch, i_ch)
        info["epochs"] += f_ch.shape[0]
        info["locked_epochs"] += int(np.count_nonzero(i_ch[:, RI_FLAGS] & FL_PLL_LOCK))
        self.recorder.tracking(info["prn"], f_ch, i_ch)
        self.navbits.feed(ch, f_ch, i_ch, info)
        st = self.tracker.state
        if st.si[ch, S_MODE] == MODE_LOST:
            info["losses"] += 1
            self.tracker.stop_channel(ch)
            st.si[ch, S_MODE] = MODE_LOST

    def _observation_epochs(self):
        """Observables / PVT at every observation epoch fully covered by every active channel."""
        ends = [self.hists[ch].end_sample for ch in range(self.n_ch) if self.tracker.active[ch]]
        limit = min(ends) if ends else max(h.end_sample for h in self.hists)
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
        out = self.pvt.solve(row, obs, pr, self.observables.steer)
        if out is not None:
            fix, sol, parts = out
            self.fixes.append(fix)
            self.recorder.fix(fix, sol, parts)

    # ----------------------------------------------------------------- re-acquisition / search
    def _reacquire(self, ch, now_sample):
        info = self.chinfo[ch]
        if info["next_retry"] is not None and now_sample < info["next_retry"]:
            return
        n_need = int(self.fs * self.signal.code_period_s * 10) + 1
        if now_sample + n_need >= self.stop:
            info["next_retry"] = self.stop          # nothing left to search
            return
        last_d = float(self.tracker.state.sf[ch, 0])
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
        """All in view: search the PRNs without a channel running; start the ones found."""
        idle = [ch for ch in range(self.n_ch) if not self.chinfo[ch]["started"]]
        if not idle or now_sample < self.search["next"]:
            return
        self.search["next"] = now_sample + int(self.cfg.search_every_s * self.fs)
        if now_sample + int(0.05 * self.fs) >= self.stop:
            return
        scfg = replace(self.cfg, prns=[self.chinfo[ch]["prn"] for ch in idle], acq_looks=1)
        res = _acquire(self.source, scfg, int(now_sample), self.signal)
        self.search["runs"] += 1
        by_prn = {self.chinfo[ch]["prn"]: ch for ch in idle}
        for a in res:
            if not (a.detected and a.peak_cn0_dbhz >= self.cfg.acq_min_cn0_dbhz):
                continue
            ch = by_prn[a.prn]
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
        tracker = self.tracker
        if self.cfg.reacquire:
            for ch in range(self.n_ch):
                if not tracker.active[ch] and tracker.state.si[ch, S_MODE] == MODE_LOST:
                    self._reacquire(ch, self.hists[ch].end_sample if self.hists[ch].end_sample > 0 else s)
        if self.all_in_view:
            self._search_idle(max(h.end_sample for h in self.hists))
        self._observation_epochs()

    # ----------------------------------------------------------------- run
    def run(self, out_path=None, csv_path=None, kml_path=None, progress=False, run_config=None, assist=None,
            rinex_obs_path=None, rinex_nav_path=None, nmea_path=None):
        """Run the pipeline over the file; arguments as :func:`process`."""
        t_wall0 = time.perf_counter()
        self.acq = acquire_signals(self.source, self.cfg, self.start_sample, assist, self.signal)
        self._build(self.acq, out_path, rinex_obs_path)
        self.fixes, self.observations = [], []
        self.n_blocks_done = 0
        result = ProcessResult(self.input_info, self.acq, [], self.fixes, self.observations,
                               out_path=str(out_path) if out_path else None, epochs=self.recorder.epochs)
        result.corrections = self.pvt.corrections
        bar = _progress_bar(self.stop - self.start_sample, self.fs) if progress else None
        done_s = 0.0
        complete = False
        try:
            self.recorder.acquisition(self.acq)
            while True:
                s = self._next_sample()
                if s is None or s + self.margin >= self.stop or not self._track_block(s):
                    break
                self._after_block(s)
                new_done = (max(h.end_sample for h in self.hists) - self.start_sample) / self.fs
                if bar is not None and new_done > done_s:
                    bar.update(round(new_done - done_s, 3))
                    el = time.perf_counter() - t_wall0
                    bar.set_postfix_str(f"rtf {el / max(new_done, 1e-9):.3f}, fixes {len(self.fixes)}", refresh=False)
                done_s = max(done_s, new_done)
            complete = True
        except KeyboardInterrupt:
            result.interrupted = True
            raise
        finally:
            if self.recorder.rinex_obs is not None and not complete:
                self.recorder.rinex_obs.abort()
            if bar is not None:
                bar.close()
            result.signal_s = max(done_s, 0.0)
            result.wall_s = time.perf_counter() - t_wall0
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
        result.searches = self.search["runs"]
        result.warnings = _spectrum_check(self.hists, self.tracker, self.input_info, signal=self.signal)
        if self.cfg.record_epochs:
            result.epochs = self.recorder.epoch_arrays()
        writer = self.recorder.writer
        if writer is not None:
            try:
                if complete or result.interrupted:
                    _finish_writer(writer, result, self.cfg, run_config)
                else:
                    writer.abort()
            except Exception:
                writer.abort()
                raise
        if complete:
            if csv_path:
                write_csv(csv_path, self.fixes)
            if kml_path:
                write_kml(kml_path, self.fixes, options=result.corrections)
            _write_exchange_files(result, self.cfg, self.navs, self.ephemerides, self.pvt.used_ephs,
                                  self.pvt.iono, self.recorder.rinex_obs, rinex_nav_path, nmea_path)


def _progress_bar(n_samples, fs):
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


def _write_exchange_files(result, cfg, navs, ephemerides, used_ephs, iono, rinex_obs, rinex_nav_path, nmea_path):
    """RINEX observation / navigation and NMEA files at the end of a complete run."""
    pos, _ = result.position_median()
    if rinex_obs is not None:
        rinex_obs.finish(pos)
    utc = next((nv.decoder.iono for nv in navs if nv.decoder.iono is not None), None)
    leap = utc.dt_ls if utc is not None else getattr(ephemerides, "leap_seconds", None)
    if rinex_nav_path:
        ephs = list(used_ephs.values()) + [nv.ephemeris for nv in navs if nv.ephemeris is not None]
        write_rinex_nav(rinex_nav_path, ephs, iono=None if iono is None else iono[:2], leap_seconds=leap,
                        comments=[f"ultratight {__version__} process: ephemerides "
                                  f"{'from ' + str(getattr(ephemerides, 'path', 'the caller')) if ephemerides is not None else 'decoded from the signal'}"])
    if nmea_path:
        write_nmea(nmea_path, result.fixes, leap_s=DEFAULT_LEAP_S if leap is None else leap,
                   options={"iono": result.corrections.get("iono", cfg.iono), "tropo": cfg.tropo})


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


def _finish_writer(writer, result, cfg, run_config):
    conf = asdict(cfg)
    writer.flush()                 # datasets exist before their attributes are set
    writer.attrs("/", config=conf, run_config=run_config or {}, input=result.input,
                 corrections=result.corrections,
                 signal_s=result.signal_s, wall_s=result.wall_s, interrupted=result.interrupted)
    for c in result.channels:
        writer.attrs(f"tracking/prn{c['prn']:02d}", **{k: (-1 if v is None else v) for k, v in c.items()
                                                       if k != "prn"}, prn=c["prn"])
    writer.finish(complete=not result.interrupted, summary=result.summary())
