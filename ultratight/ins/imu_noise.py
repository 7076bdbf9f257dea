"""An IMU's declared noise: what a filter is tuned from when it integrates a recorded log.

:class:`ImuNoise` holds the four random processes of the usual inertial error model (Groves 2013
§4.4; IEEE Std 952 names) in SI units, plus the initial uncertainty of the turn-on biases:

==================  =============================  =========================================
field               SI unit                        datasheet unit (CLI, sidecar)
==================  =============================  =========================================
gyro_arw            rad/s/√Hz (= rad/√s)           °/s/√Hz   (``gyro_noise_dps_rthz``)
accel_vrw           m/s²/√Hz (= m/s/√s)            µg/√Hz    (``accel_noise_ug_rthz``)
gyro_bias_rw        rad/s²/√Hz (= rad/s/√s)        °/s²/√Hz  (``gyro_bias_rw_dps2_rthz``)
accel_bias_rw       m/s³/√Hz (= m/s²/√s)           µg/s/√Hz  (``accel_bias_rw_ug_rthz``)
gyro_bias_sigma     rad/s                          °/s       (``gyro_bias_dps``)
accel_bias_sigma    m/s²                           m/s²      (``accel_bias_mps2``)
gyro_sf             1 (fraction)                   %         (``gyro_scale_factor_pct``)
gyro_cross          1 (fraction)                   %         (``gyro_cross_axis_pct``)
accel_sf            1 (fraction)                   %         (``accel_scale_factor_pct``)
accel_cross         1 (fraction)                   %         (``accel_cross_axis_pct``)
==================  =============================  =========================================

A grade (:data:`GRADES`) gives every field; declared values replace the grade's one by one.

The last four are the 1σ of the sensors' constant scale-factor error (per axis) and cross-axis
sensitivity (per pair of axes: the share of the rate / specific force along axis j that axis i
reads, the axis misalignment and non-orthogonality together): what a datasheet's "sensitivity
tolerance" and "cross-axis sensitivity" rows state.  They are optional (:data:`OPTIONAL_KEYS`): a
declaration without them takes them from its grade, or — without a grade — from the grade whose
turn-on gyro bias σ lies nearest (on a log scale) to the declared one (:func:`nearest_grade`: the
turn-on bias is what tells a consumer part from a tactical one).  0 leaves a term out.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from ultratight.errors import ConfigError

G0 = 9.80665
DEG = math.pi / 180.0
UG = 1e-6 * G0

# datasheet key -> (field, factor to SI)
DATASHEET_KEYS = {
    "gyro_noise_dps_rthz": ("gyro_arw", DEG),
    "accel_noise_ug_rthz": ("accel_vrw", UG),
    "gyro_bias_rw_dps2_rthz": ("gyro_bias_rw", DEG),
    "accel_bias_rw_ug_rthz": ("accel_bias_rw", UG),
    "gyro_bias_dps": ("gyro_bias_sigma", DEG),
    "accel_bias_mps2": ("accel_bias_sigma", 1.0),
}
# optional datasheet keys (0 allowed): scale factor and cross-axis sensitivity, % (1σ)
OPTIONAL_KEYS = {
    "gyro_scale_factor_pct": ("gyro_sf", 0.01),
    "gyro_cross_axis_pct": ("gyro_cross", 0.01),
    "accel_scale_factor_pct": ("accel_sf", 0.01),
    "accel_cross_axis_pct": ("accel_cross", 0.01),
}
ALL_KEYS = {**DATASHEET_KEYS, **OPTIONAL_KEYS}

# typical figures per grade, datasheet units (Groves 2013 Table 4.1 orders of magnitude).  Scale
# factor and cross-axis sensitivity (1σ, %): Groves 2013 §4.4.2 orders of magnitude for navigation
# (10 ppm), tactical (300 ppm) and industrial MEMS (0.3 % / 0.1 %) parts; the consumer figures are a
# consumer part's datasheet rows read as 1σ: accelerometer sensitivity tolerance ±0.5 % and
# cross-axis sensitivity ±2 % (TDK InvenSense ICM-20948, DS-000189 rev. 1.3, Table 2), gyro ±1 %
# and ±1 % (the low end of the ±1–3 % sensitivity and ±1–2 % cross-axis that consumer gyro
# datasheets state).  A datasheet's "typical ±" spreads parts, it does not bound them: read as 1σ.
GRADES = {
    "navigation": {"gyro_noise_dps_rthz": 0.002 / 60.0, "accel_noise_ug_rthz": 10.0,
                   "gyro_bias_rw_dps2_rthz": 1e-7, "accel_bias_rw_ug_rthz": 0.1,
                   "gyro_bias_dps": 0.01 / 3600.0, "accel_bias_mps2": 50e-6 * G0,
                   "gyro_scale_factor_pct": 1e-3, "gyro_cross_axis_pct": 1e-3,
                   "accel_scale_factor_pct": 1e-3, "accel_cross_axis_pct": 1e-3},
    "tactical": {"gyro_noise_dps_rthz": 0.1 / 60.0, "accel_noise_ug_rthz": 60.0,
                 "gyro_bias_rw_dps2_rthz": 1e-5, "accel_bias_rw_ug_rthz": 5.0,
                 "gyro_bias_dps": 5.0 / 3600.0, "accel_bias_mps2": 1e-3 * G0,
                 "gyro_scale_factor_pct": 0.03, "gyro_cross_axis_pct": 0.03,
                 "accel_scale_factor_pct": 0.03, "accel_cross_axis_pct": 0.03},
    "mems": {"gyro_noise_dps_rthz": 0.5 / 60.0, "accel_noise_ug_rthz": 150.0,
             "gyro_bias_rw_dps2_rthz": 1e-4, "accel_bias_rw_ug_rthz": 20.0,
             "gyro_bias_dps": 200.0 / 3600.0, "accel_bias_mps2": 1e-2 * G0,
             "gyro_scale_factor_pct": 0.3, "gyro_cross_axis_pct": 0.1,
             "accel_scale_factor_pct": 0.3, "accel_cross_axis_pct": 0.1},
    "consumer": {"gyro_noise_dps_rthz": 0.01, "accel_noise_ug_rthz": 150.0,
                 "gyro_bias_rw_dps2_rthz": 1e-4, "accel_bias_rw_ug_rthz": 20.0,
                 "gyro_bias_dps": 0.5, "accel_bias_mps2": 0.3,
                 "gyro_scale_factor_pct": 1.0, "gyro_cross_axis_pct": 1.0,
                 "accel_scale_factor_pct": 0.5, "accel_cross_axis_pct": 2.0},
}


@dataclass(frozen=True)
class ImuNoise:
    """Declared IMU noise in SI units (see the module table)."""
    gyro_arw: float
    accel_vrw: float
    gyro_bias_rw: float
    accel_bias_rw: float
    gyro_bias_sigma: float
    accel_bias_sigma: float
    source: str = ""
    gyro_sf: float = 0.0
    gyro_cross: float = 0.0
    accel_sf: float = 0.0
    accel_cross: float = 0.0

    def to_datasheet(self):
        """dict of the datasheet keys (the sidecar's ``noise`` table) and ``source``."""
        d = asdict(self)
        out = {key: d[name] / f for key, (name, f) in ALL_KEYS.items()}
        out["source"] = self.source
        return out


def imu_noise(grade=None, **declared):
    """:class:`ImuNoise` of ``grade`` with the declared datasheet values (keys of
    :data:`DATASHEET_KEYS`, None = not declared) put over it.  Without a grade every key must be
    declared.  ConfigError names a wrong grade, an unknown key or a value that is not a positive
    finite number."""
    unknown = sorted(set(declared) - set(ALL_KEYS))
    if unknown:
        raise ConfigError(f"IMU noise: unknown key(s) {', '.join(unknown)}; known: {', '.join(ALL_KEYS)}")
    given = {k: v for k, v in declared.items() if v is not None}
    for k, v in given.items():
        zero_ok = k in OPTIONAL_KEYS
        try:
            ok = math.isfinite(float(v)) and (float(v) >= 0.0 if zero_ok else float(v) > 0.0)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ConfigError(f"IMU noise {k} must be a {'non-negative' if zero_ok else 'positive'} number, "
                              f"got {v!r}")
    if grade is not None and grade not in GRADES:
        raise ConfigError(f"IMU grade must be one of {', '.join(GRADES)}, got {grade!r}")
    base = dict(GRADES[grade]) if grade else {}
    missing = sorted(set(DATASHEET_KEYS) - set(base) - set(given))
    if missing:
        raise ConfigError(f"IMU noise: declare {', '.join(missing)} or give a grade ({', '.join(GRADES)})")
    base.update({k: float(v) for k, v in given.items()})
    parts = ([f"grade {grade}"] if grade else []) + ([f"declared {', '.join(sorted(given))}"] if given else [])
    if not grade and not set(OPTIONAL_KEYS) <= set(given):
        near = nearest_grade(base["gyro_bias_dps"])
        base = {**{k: GRADES[near][k] for k in OPTIONAL_KEYS}, **base}
        parts.append(f"scale factor and cross-axis of grade {near} (nearest turn-on gyro bias)")
    si = {name: base[key] * f for key, (name, f) in ALL_KEYS.items()}
    return ImuNoise(source="; ".join(parts), **si)


def nearest_grade(gyro_bias_dps):
    """The grade whose turn-on gyro bias σ lies nearest to ``gyro_bias_dps`` on a log scale."""
    return min(GRADES, key=lambda g: abs(math.log(GRADES[g]["gyro_bias_dps"] / float(gyro_bias_dps))))


# a bias random walk as the error-state model's first-order Gauss-Markov bias: over this correlation
# time the process is a random walk to within exp(-t / tau) (an hour: longer than any run it tunes)
RW_AS_GM_TAU_S = 3600.0


def error_model_of(noise, tau_s=RW_AS_GM_TAU_S):
    """The declared noise as :class:`ultratight.ins.imu.ImuErrors`, the model the ultra-tight
    engine's 17-state filter is tuned from (``errors`` of an IMU file's metadata): white noise
    ARW / VRW as they are, the turn-on bias as its 1σ, the bias random walk q as a Gauss-Markov
    bias of correlation time ``tau_s`` whose driving PSD 2σ²/τ equals q² (σ = q √(τ/2)).  A
    declaration states no scale factor or misalignment: none is modelled."""
    import numpy as np

    from ultratight.ins.imu import ImuErrors

    k = math.sqrt(tau_s / 2.0)
    return ImuErrors(gyro_bias=np.full(3, noise.gyro_bias_sigma), accel_bias=np.full(3, noise.accel_bias_sigma),
                     gyro_arw=np.full(3, noise.gyro_arw), accel_vrw=np.full(3, noise.accel_vrw),
                     gyro_gm_sigma=np.full(3, noise.gyro_bias_rw * k), gyro_gm_tau=float(tau_s),
                     accel_gm_sigma=np.full(3, noise.accel_bias_rw * k), accel_gm_tau=float(tau_s),
                     preset=f"declared ({noise.source})" if noise.source else "declared")
