"""Options and result of the INS/GNSS filter for recorded logs (:func:`ultratight.fusion.gins.runner.run_gins`).

:class:`GinsOptions` holds every choice of a run; each default is documented beside it and in
docs/gins.md.  :func:`check_options` refuses a bad value with one ConfigError line naming it.
:class:`GinsResult` is the solution at every IMU sample from the alignment epoch on.

Choices a user may meet on real data (docs/gins.md gives the reasons):

* ``quality_factor``: the receiver's σ is multiplied by this factor per RTKLIB quality code
  before it enters R (fixed 1, float 5, single 5, others 5): RTKLIB's float and single σ are the
  formal covariance of a float / code solution and are known to be optimistic.
* ``pos_sigma_floor_m`` / ``vel_sigma_floor_mps``: lower bounds of the σ entering R (2 cm, 3 cm/s)
  — they stand for what the receiver's σ leaves out (multipath, the epoch-to-epoch correlation of
  an RTK solution); ``vel_sigma_default_mps`` (0.1 m/s) is used when the source has a velocity
  but no velocity σ.
* ``gate_p``: χ² gating of the whole GNSS epoch's normalised innovation squared at false-alarm
  probability p (default 1e-3); ``gate_release``: after this many consecutive rejected epochs the
  next one is used whatever its NIS (the filter, not the GNSS, is then the likely culprit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ultratight.errors import ConfigError
from ultratight.ins.imu_noise import ImuNoise

COUPLINGS = ("loose", "tight")
FILTERS = ("kf", "akf", "iakf", "chi2-newton", "afm-aukf")
TIGHT_FILTERS = ("kf", "afm-aukf")
DEFAULT_QUALITY_FACTOR = {1: 1.0, 2: 5.0, 5: 5.0}


@dataclass
class GinsOptions:
    """Choices of one INS/GNSS run (see the module docstring and docs/gins.md)."""
    coupling: str = "loose"                 # "loose" | "tight"
    filter: str = "kf"                      # see FILTERS
    noise: ImuNoise = None                  # required: the declared IMU noise (Q and the bias σ)
    lever_arm_b: np.ndarray = field(default_factory=lambda: np.zeros(3))   # IMU -> antenna, FLU, m
    heading_deg: float | None = None        # heading at the end of the levelling window (else GNSS course)
    heading_speed_mps: float = 1.0          # GNSS horizontal speed above which the course gives the heading
    zupt: bool = False
    nhc: bool = False
    smooth: bool = False
    gate_p: float | None = 1e-3             # χ² false-alarm probability of the epoch gate (None: no gate)
    outages: tuple = ()                     # ((t_start, t_end), ...) GPS s: GNSS removed inside
    outage_keep_sats: int = 0               # tight only: satellites kept during outages (highest elevation)
    # --- propagation
    cov_rate_hz: float = 10.0               # covariance propagation rate (Φ accumulated over the IMU samples)
    # --- alignment and still detection
    still_window_s: float = 1.0             # window of the still detector and of the static levelling
    still_k: float = 3.0                    # thresholds = still_k x the declared noise of the window statistic
    align_search_s: float = 60.0            # the levelling window is looked for in the first align_search_s
    level_max_s: float = 10.0               # longest levelling window (the first still run, cut here)
    heading_sigma_floor_deg: float = 1.0    # heading σ floor (the forward axis is only roughly along the path)
    # --- GNSS weighting
    quality_factor: dict = field(default_factory=lambda: dict(DEFAULT_QUALITY_FACTOR))
    other_quality_factor: float = 5.0       # factor for quality codes not in quality_factor
    pos_sigma_floor_m: float = 0.02
    vel_sigma_floor_mps: float = 0.03
    vel_sigma_default_mps: float = 0.1
    use_velocity: bool = True               # loose: use the GNSS velocity when the source has it
    gate_release: int = 4
    # --- aiding (ZUPT / NHC)
    aid_interval_s: float = 0.25            # ZUPT / NHC pseudo-measurements at most this often
    zupt_sigma_mps: float = 0.02
    nhc_sigma_mps: float = 0.1
    nhc_min_speed_mps: float = 0.0          # NHC only above this speed (0: always)
    # --- cores
    akf_window: int = 20                    # innovation window of the AKF / IAKF (epochs)
    chi2_alpha: float = 0.01                # per-dimension χ² significance (chi2-newton, Cai et al. 2020)
    newton_delta: float = 4.0               # improvement factor δ of the Newton replacement
    afm_alpha: float = 0.05                 # per-innovation χ²₁ significance of the fading (Sun et al. 2012)
    # --- tight
    clock_psd: tuple = (0.1, 0.01)          # receiver clock bias (m²/s) and drift (m²/s³) white-noise PSD
    clock_sigma0: tuple = (30.0, 1.0)       # initial clock σ (m, m/s) around meas.initial_clock


@dataclass
class GinsResult:
    """INS/GNSS solution at every IMU sample after the alignment epoch.

    ``euler_rad``: roll, pitch, yaw (yaw clockwise from north; FRD body, NED navigation frame
    angles, the same numbers as the project's FLU/ENU Euler convention); ``sigma_att_rad`` the 1σ of
    roll, pitch, yaw (the horizontal attitude errors resolved along / across the heading);
    ``clock`` (n, 2) clock bias (m) and drift (m/s) for tight coupling, else None.  ``updates``:
    per-GNSS-epoch arrays ``t, used, n_rows, nis, rejected, quality`` and ``reason`` (one line per
    epoch, empty when used).  ``forward``: the forward solution when ``smoothed``."""
    t: np.ndarray
    llh: np.ndarray
    vel_enu: np.ndarray
    euler_rad: np.ndarray
    sigma_pos_enu: np.ndarray
    sigma_vel_enu: np.ndarray
    sigma_att_rad: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    clock: np.ndarray | None
    in_outage: np.ndarray
    smoothed: bool = False
    forward: "GinsResult | None" = None
    updates: dict = field(default_factory=dict)
    alignment: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    @property
    def n(self):
        return int(self.t.shape[0])


def _positive(name, v, allow_zero=False):
    try:
        ok = math.isfinite(float(v)) and (float(v) >= 0.0 if allow_zero else float(v) > 0.0)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ConfigError(f"gins: {name} must be a {'non-negative' if allow_zero else 'positive'} number, got {v!r}")


def check_options(o, fixes=None, tight=None):
    """Refuse a bad option with one ConfigError line; returns the outages as an (k, 2) array."""
    if o.coupling not in COUPLINGS:
        raise ConfigError(f"gins: coupling must be one of {', '.join(COUPLINGS)}, got {o.coupling!r}")
    if o.filter not in FILTERS:
        raise ConfigError(f"gins: filter must be one of {', '.join(FILTERS)}, got {o.filter!r}")
    if o.coupling == "tight" and o.filter not in TIGHT_FILTERS:
        raise ConfigError(f"gins: filter {o.filter!r} needs a fixed measurement dimension; with tight coupling "
                          f"use one of {', '.join(TIGHT_FILTERS)}")
    if not isinstance(o.noise, ImuNoise):
        raise ConfigError("gins: the IMU noise declaration (ImuNoise) is required")
    lever = np.asarray(o.lever_arm_b, float).reshape(-1)
    if lever.shape != (3,) or not np.all(np.isfinite(lever)):
        raise ConfigError(f"gins: lever_arm_b must be 3 finite numbers (m), got {o.lever_arm_b!r}")
    if o.coupling == "loose" and fixes is None:
        raise ConfigError("gins: loose coupling needs GNSS fixes")
    if o.coupling == "tight" and tight is None:
        raise ConfigError("gins: tight coupling needs the raw measurements")
    for name in ("heading_speed_mps", "cov_rate_hz", "still_window_s", "still_k", "align_search_s", "level_max_s",
                 "pos_sigma_floor_m", "vel_sigma_floor_mps", "vel_sigma_default_mps", "aid_interval_s",
                 "zupt_sigma_mps", "nhc_sigma_mps", "chi2_alpha", "newton_delta", "afm_alpha",
                 "heading_sigma_floor_deg", "other_quality_factor"):
        _positive(name, getattr(o, name))
    _positive("nhc_min_speed_mps", o.nhc_min_speed_mps, allow_zero=True)
    if o.gate_p is not None and not (0.0 < float(o.gate_p) < 1.0):
        raise ConfigError(f"gins: gate_p must lie in (0, 1) or be None, got {o.gate_p!r}")
    if o.heading_deg is not None:
        try:
            ok = math.isfinite(float(o.heading_deg))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ConfigError(f"gins: heading_deg must be a finite number (degrees from north), got {o.heading_deg!r}")
    if int(o.akf_window) < 1 or int(o.gate_release) < 1 or int(o.outage_keep_sats) < 0:
        raise ConfigError("gins: akf_window and gate_release must be >= 1 and outage_keep_sats >= 0")
    try:
        out = np.asarray(o.outages, float).reshape(-1, 2)
    except ValueError:
        raise ConfigError(f"gins: outages must be (t_start, t_end) pairs, got {o.outages!r}") from None
    if out.size and (not np.all(np.isfinite(out)) or np.any(out[:, 1] <= out[:, 0])):
        raise ConfigError("gins: every outage needs finite t_start < t_end (GPS seconds)")
    return out


def in_windows(t, windows):
    """bool mask of the times ``t`` inside any (t_start, t_end) window (both ends included)."""
    t = np.asarray(t, float)
    mask = np.zeros(t.shape, bool)
    for a, b in np.asarray(windows, float).reshape(-1, 2):
        mask |= (t >= a) & (t <= b)
    return mask
