"""What a run of the scalar receiver takes and gives: its options (:class:`ProcessConfig`), its
result (:class:`ProcessResult`) and the error of a file without any acquired satellite
(:class:`NoSignalError`)."""

import math
from dataclasses import dataclass, field

import numpy as np

from ultratight import __version__
from ultratight.errors import ConfigError, UltratightError
from ultratight.ins.earth import ecef_to_llh
from ultratight.receiver.dsp.tracking_config import TrackingConfig
from ultratight.signals.atmosphere import IONO_MODELS, MAPPINGS, TROPO_MODELS

DYNAMICS = ("normal", "high")


class NoSignalError(UltratightError):
    """No satellite acquired in the file (wrong parameters, wrong I/Q convention, no signal)."""


MAX_DOPPLER_FRACTION = 0.45     # --doppler-range: at most this fraction of the sampling rate
COARSE_FACTOR = 2.0             # the coarse all-in-view search runs at this multiple of search_every_s


@dataclass
class ProcessConfig:
    """Options of a scalar-receiver run (``ultratight process``; docs/process.md)."""
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
                                        # snapshots < 1 s, else 2 - see channels.cold_search)
    acq_pfa: float = 1e-3
    acq_min_cn0_dbhz: float = 37.0      # declare only when the peak C/N0 (metric-1)/T_coh reaches this
    doppler_window_s: float = 0.05      # half-width h of the centred Doppler difference
    sigma_pr_m: float = 3.0
    smoothing_s: float = 100.0          # Hatch-filter window for the pseudoranges (0: none)
    noise_weights: bool = True          # pseudorange sigmas scaled by each channel's measured code noise
                                        # (observables.noise_weights; needs the smoothing)
    sigma_rr_mps: float = 0.05
    reacquire: bool = True
    reacq_retry_s: float = 1.0
    search_every_s: float = 15.0        # all-in-view: search again for the PRNs not tracked (predicted search)
    coarse_search_every_s: float | None = None   # the full search of PRNs without a prediction (None: 2 x
                                                 # search_every_s; see search_plan)
    iono: str = "klobuchar"             # klobuchar | off (klobuchar applies once alpha/beta are known)
    tropo: str = "saastamoinen"         # saastamoinen | off
    tropo_mapping: str = "cosz"         # mapping function of the Saastamoinen model
    record_epochs: bool = False
    parallel: bool | None = None        # spread channels over numba threads (None: cores.plan, > 1 allowed core)
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
        if self.coarse_search_every_s is not None and not self.coarse_search_every_s > 0:
            raise ConfigError(f"coarse search interval must be > 0 s, got {self.coarse_search_every_s}")
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
        top = MAX_DOPPLER_FRACTION * source.fs_hz
        if not 0 < self.doppler_range_hz <= top:
            raise ConfigError(f"--doppler-range must be in (0, {top:.6g}] Hz at fs = {source.fs_hz:.6g} Hz (at most "
                              f"{MAX_DOPPLER_FRACTION:g} fs: the search stays inside the sampled band), "
                              f"got {self.doppler_range_hz:.6g}")
        if not 0.0 <= self.mask_deg < 90.0:
            raise ConfigError(f"--mask must be an elevation in [0, 90) deg, got {self.mask_deg:g}")
        self.tracking.validate()

    @property
    def coarse_interval_s(self):
        """Interval of the coarse full search (PRNs without a prediction): ``coarse_search_every_s``,
        by default twice ``search_every_s``."""
        if self.coarse_search_every_s is not None:
            return float(self.coarse_search_every_s)
        return COARSE_FACTOR * float(self.search_every_s)


@dataclass
class ProcessResult:
    """What a run gives: acquisitions, channel summaries, fixes, observation epochs, timing and
    warnings (:meth:`summary`: the JSON summary of ``ultratight process``)."""
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
    search: dict = field(default_factory=dict)   # the periodic search: runs, predicted_runs, cpu_s, ...
    cpu_s: float = 0.0                 # the run's CPU time (time.process_time: every thread of the process)

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

    def search_summary(self):
        """The periodic all-in-view search's figures: runs (predicted + coarse), the PRNs searched by
        each (summed over the runs), the PRNs of the last plan predicted above the mask (``predicted``)
        and below it (``below_mask``), its CPU time and its share of the run's (docs/process.md)."""
        d = dict(self.search) or {"runs": self.searches, "predicted_runs": 0, "coarse_runs": 0, "predicted_prns": 0,
                                  "coarse_prns": 0, "predicted": [], "below_mask": [], "cpu_s": 0.0}
        cpu = float(d.get("cpu_s", 0.0))
        d["cpu_s"] = round(cpu, 3)
        d["share_of_cpu"] = round(cpu / self.cpu_s, 4) if self.cpu_s > 0 else None
        return d

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
            "search": self.search_summary(),
            "cpu_s": round(self.cpu_s, 3),
            "version": __version__,
            "out": self.out_path,
        }
