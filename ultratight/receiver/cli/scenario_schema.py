"""Declared schema of the IF-level scenario TOML (docs/ultratight.md, docs/reliability.md).

:func:`check_raw` runs on the TOML as written, before defaults are merged, so that a typo
(``durration_s``, ``[imu_]``, ``noise_facter``) is an error with a did-you-mean instead of a
silently ignored key. Value ranges are checked afterwards by
:func:`ultratight.receiver.cli.scenario_config.validate` (which also applies the limits below).

Tables in :data:`PASS_THROUGH_TABLES` belong to other stages, which check their keys. A top-level
``experiment`` key is accepted; a scenario naming another experiment than the IF-level one is left
to that experiment's module (its ``load`` validates its own schema).
"""

from ultratight.config import check_known_keys
from ultratight.errors import ConfigError
from ultratight.ins import trajectory
from ultratight.ins.imu import CONFIG_KEYS as _IMU_KNOWN_KEYS

# receiver settings a scenario may fix (the ultra-tight engine's EngineOptions fields); they do not
# change the generated data, only how the scenario is processed
ENGINE_KEYS = ("noise_tau_s", "lock_monitor", "monitor_gates_tight", "bits")

TOP_LEVEL_KEYS = ("name", "description", "duration_s", "seed", "experiment")
TABLES = {
    "time": ("week", "tow_s"),
    "receiver": ("lat_deg", "lon_deg", "h_m", "clock_bias_m", "clock_drift_mps"),
    "trajectory": ("kind", "attitude", "att0_deg", "vel0_enu_mps", "speed0_mps", "heading0_deg", "segments",
                   "swing_amp_deg", "swing_period_s", "swing_phase_deg"),
    "satellites": ("source", "rinex", "prns", "max_count", "mask_deg", "cn0_dbhz"),
    "frontend": ("fs_hz", "if_hz", "sampling", "format", "bits", "inversion", "filter_bw_hz", "filter_order",
                 "gain", "headroom"),
    "nav": ("data_bits", "data"),
    "engine": ENGINE_KEYS,
    "imu": None,          # the known keys of ultratight.ins.imu
}
ARRAY_TABLES = {"noise_events": ("t0_s", "t1_s", "noise_factor", "place")}
TRAJECTORY_SEGMENT_KEYS = ("t0", "acc_enu", "jerk_enu", "turn_rate_dps", "acc_mps2", "speed_mps", "rate_dps")
PASS_THROUGH_TABLES = ("atmosphere",)



def _imu_keys():
    return tuple(sorted(_IMU_KNOWN_KEYS))


def _declared(name, keys):
    """``keys`` plus any the stage itself declares (``ultratight.ins.trajectory.CONFIG_KEYS`` ...)."""
    if name == "trajectory":
        return tuple(keys) + tuple(getattr(trajectory, "CONFIG_KEYS", ()))
    return keys


def check_raw(raw, where="scenario"):
    """ConfigError (with did-you-mean) for unknown tables/keys or wrong table types in a raw TOML dict."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: a scenario must be a TOML table")
    if raw.get("experiment") not in (None, "if-double-loop"):
        return raw               # another experiment's scenario: its module validates its schema
    allowed = set(TOP_LEVEL_KEYS) | set(TABLES) | set(ARRAY_TABLES) | set(PASS_THROUGH_TABLES)
    check_known_keys(raw, allowed, f"{where}: top level")
    for name, keys in TABLES.items():
        if name not in raw:
            continue
        t = raw[name]
        if not isinstance(t, dict):
            raise ConfigError(f"{where}: [{name}] must be a table, got {type(t).__name__}")
        check_known_keys(t, _imu_keys() if name == "imu" else _declared(name, keys), f"{where}: [{name}]")
    segs = (raw.get("trajectory") or {}).get("segments") if isinstance(raw.get("trajectory"), dict) else None
    if segs is not None:
        if not isinstance(segs, list) or not all(isinstance(s, dict) for s in segs):
            raise ConfigError(f"{where}: trajectory.segments must be an array of tables")
        for i, s in enumerate(segs):
            check_known_keys(s, TRAJECTORY_SEGMENT_KEYS, f"{where}: trajectory.segments[{i}]")
    for name, keys in ARRAY_TABLES.items():
        if name not in raw:
            continue
        arr = raw[name]
        if not isinstance(arr, list) or not all(isinstance(e, dict) for e in arr):
            raise ConfigError(f"{where}: {name} must be an array of tables [[{name}]]")
        for i, e in enumerate(arr):
            check_known_keys(e, keys, f"{where}: {name}[{i}]")
    for name in PASS_THROUGH_TABLES:
        if name in raw and not isinstance(raw[name], dict):
            raise ConfigError(f"{where}: [{name}] must be a table, got {type(raw[name]).__name__}")
    return raw
