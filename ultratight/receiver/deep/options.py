"""The engine's parameters: :class:`EngineOptions` (every field recorded in the outputs), the
per-channel loop modes logged per epoch, the aided prefilters' process noise and the signal-monitor
modes (docs/ultratight.md)."""

from dataclasses import asdict, dataclass, field

from ultratight.cores import stage_threads
from ultratight.errors import ConfigError

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
    # noise events inside the receiver (receiver.dsp.burst): [[noise_events]] entries whose place is
    # "correlator" or "filter-r" ("if" ones are the generator's), and the seed of the correlator noise
    noise_events: list = field(default_factory=list)
    noise_seed: int = 0
    startup: dict = field(default_factory=dict)   # StartupErrors overrides
    threads: int = 0                     # epoch-stage threads: 0 = the allowed cores (epoch_threads), 1 = one, k = k
    # navigation-data bits (receiver.deep.bitsources): assisted | decoded | blind | path of a bit file
    bits: str = "assisted"
    # integrity monitor (receiver.deep.integrity, docs/ultratight.md "Integrity"): overrides of its
    # thresholds (IntegrityThresholds fields) and whether the run stops when the solution is lost:
    # True stops, False only records, None lets the caller decide (the engine alone records;
    # recordings.run_ultratight_on_files stops and re-initialises from a new scalar fix)
    integrity: dict = field(default_factory=dict)
    integrity_stop: object = None

    def as_dict(self):
        return asdict(self)


def epoch_threads(requested, n_channels=None):
    """Threads for the compiled epoch stages (:func:`ultratight.cores.stage_threads`: ``requested``
    when > 0, else the allowed cores; at most one per channel and the size of numba's pool)."""
    return stage_threads(requested, n_channels)
