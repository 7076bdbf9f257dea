"""Scenario configuration: TOML files in ``ultratight/data/scenarios``, defaults, overrides, validation.

``load_scenario(name_or_path, overrides)`` returns a plain dict with every field of the
schema documented in docs/ultratight.md (the tables ``time``, ``receiver``, ``trajectory``,
``satellites``, ``noise_events``, ``frontend``, ``nav`` and optionally ``imu``) filled with
defaults and checked. Tables this module does not know (used by other stages) pass through
unchanged. The optional ``[engine]`` table fixes receiver settings that belong to the
scenario's definition (``noise_tau_s``: the engine's noise-floor estimator, ``inf`` = calibrated
at start-up); ``ultratight scenario`` applies it to every method and leaves it out of the
data-cache key.

``overrides`` is a dict whose keys are either dotted paths (``{"frontend.fs_hz": 2e6,
"duration_s": 5}``) or nested tables (``{"frontend": {"fs_hz": 2e6}}``); ``None`` values are
ignored, so CLI flags can be passed straight through.

Relative paths (``satellites.rinex``) resolve against the shared data directory:
``$ULTRATIGHT_DATA`` if set, else ``../shared/data`` beside the repository; the resolved
absolute path is stored as ``satellites.rinex_path``.
"""

import math
from pathlib import Path

from ultratight.config import (apply_overrides, check_known_keys, check_number, deep_merge,  # noqa: F401
                               list_scenarios, locate_scenario, read_toml, shared_data_dir)
from ultratight.errors import ConfigError
from ultratight.receiver.cli.scenario_schema import ENGINE_KEYS, check_raw  # noqa: F401 (public here)
from ultratight.receiver.dsp.burst import validate_place
from ultratight.signals.atmosphere import IONO_MODELS, MAPPINGS, TROPO_MODELS
from ultratight.signals.synth.frontend import FrontEnd
from ultratight.signals.recording.iffile import FORMATS, check_bits_for_format
from ultratight.signals.lnav import NAV_DATA_MODES

# limits (docs/reliability.md); the declared key schema is in ultratight.receiver.cli.scenario_schema
MIN_FS_HZ = 1.023e6            # the receiver needs at least the C/A chipping rate
MAX_FS_HZ = 100e6
MIN_NOISE_FACTOR = 1e-3
MAX_NOISE_FACTOR = 1000.0      # 60 dB above the nominal noise: beyond, the signal quantises to nothing
MAX_IMU_RATE_HZ = 10000.0

DEFAULTS = {
    "description": "",
    "duration_s": 60.0,
    "seed": 1,
    "time": {"week": 2190, "tow_s": 518400.0},
    "receiver": {"clock_bias_m": 0.0, "clock_drift_mps": 0.0},
    "trajectory": {"kind": "static"},
    "satellites": {"source": "nominal", "rinex": "rinex/brdc0010.22n", "prns": [], "max_count": 12,
                   "mask_deg": 5.0, "cn0_dbhz": 45.0},
    "noise_events": [],
    "frontend": {"fs_hz": 4.0e6, "if_hz": 0.0, "sampling": "complex", "format": "ci8", "bits": 8,
                 "inversion": False, "filter_bw_hz": 0.0, "filter_order": 4},
    "nav": {"data_bits": True},
}
IMU_DEFAULTS = {"preset": "paper", "rate_hz": 100.0}


def load_scenario(name_or_path, overrides=None):
    """Load, complete and validate a scenario (see module doc). Raises ConfigError."""
    path = locate_scenario(name_or_path)
    raw = read_toml(path)
    check_raw(raw, str(path))           # unknown tables/keys are errors (declared schema)
    cfg = deep_merge(DEFAULTS, raw)
    cfg.setdefault("name", path.stem)
    if "imu" in cfg:
        cfg["imu"] = {**IMU_DEFAULTS, **cfg["imu"]}
    cfg = apply_overrides(cfg, overrides)
    if "imu" in cfg and isinstance(cfg["imu"], dict):
        cfg["imu"] = {**IMU_DEFAULTS, **cfg["imu"]}
    cfg["source_file"] = str(path)
    _resolve_trajectory_file(cfg, path)
    validate(cfg)
    return cfg


def _resolve_trajectory_file(cfg, toml_path):
    """``[trajectory] kind = "file"``: the path resolved against the TOML's directory, the file read
    and checked (one-line errors naming its line), its SHA-256 recorded (so caches see a changed
    file) and ``[receiver]`` lat/lon/h set to its first position."""
    import hashlib

    from ultratight.errors import InputFileError
    from ultratight.ins.trajectory import load_file_motion

    tr = cfg.get("trajectory")
    if not isinstance(tr, dict) or tr.get("kind") != "file":
        return
    p = tr.get("path")
    if not isinstance(p, str) or not p:
        raise ConfigError(f"{toml_path}: trajectory: kind = \"file\" needs path = \"...\"")
    fp = Path(p)
    if not fp.is_absolute():
        fp = (Path(toml_path).parent / fp).resolve()
    tr["path"] = str(fp)
    try:
        fm = load_file_motion(tr)
        tr["file_sha256"] = hashlib.sha256(fp.read_bytes()).hexdigest()
    except InputFileError as exc:
        raise ConfigError(str(exc)) from None
    dur = cfg.get("duration_s")
    if isinstance(dur, (int, float)) and not isinstance(dur, bool) and dur > fm.duration_s + 1e-6:
        raise ConfigError(f"trajectory file {fp}: covers {fm.duration_s:.6g} s, shorter than duration_s = {dur:g} s")
    rcv = cfg.setdefault("receiver", {})
    rcv["lat_deg"], rcv["lon_deg"], rcv["h_m"] = math.degrees(fm.lat0), math.degrees(fm.lon0), float(fm.h0)


# ------------------------------------------------------------------------------------------
# validation
# ------------------------------------------------------------------------------------------
def _num(cfg, dotted, lo=None, hi=None, lo_open=False, integer=False):
    d = cfg
    parts = dotted.split(".")
    for p in parts[:-1]:
        d = d.get(p, {})
    return check_number(d.get(parts[-1]), dotted, lo=lo, hi=hi, lo_open=lo_open, integer=integer)


def _table(cfg, name):
    t = cfg.get(name)
    if not isinstance(t, dict):
        raise ConfigError(f"[{name}] must be a table, got {type(t).__name__}")
    return t


def validate(cfg):
    """Check a completed scenario dict; raises ConfigError naming the field."""
    _num(cfg, "duration_s", lo=0, lo_open=True)
    _num(cfg, "seed", lo=0, integer=True)
    cfg["seed"] = int(cfg["seed"])
    _table(cfg, "time")
    _num(cfg, "time.week", lo=0, integer=True)
    _num(cfg, "time.tow_s", lo=0, hi=604800.0)
    if cfg["time"]["tow_s"] >= 604800.0:
        raise ConfigError(f"time.tow_s must be < 604800, got {cfg['time']['tow_s']}")
    rcv = _table(cfg, "receiver")
    for k in ("lat_deg", "lon_deg"):
        if k not in rcv:
            raise ConfigError(f"receiver.{k} is required")
    _num(cfg, "receiver.lat_deg", lo=-90, hi=90)
    _num(cfg, "receiver.lon_deg", lo=-180, hi=360)
    rcv.setdefault("h_m", 0.0)
    _num(cfg, "receiver.h_m", lo=-1e4, hi=1e8)
    _num(cfg, "receiver.clock_bias_m")
    _num(cfg, "receiver.clock_drift_mps")
    _table(cfg, "trajectory")
    _validate_satellites(cfg, _table(cfg, "satellites"))
    _validate_noise_events(cfg.get("noise_events", []))
    _validate_frontend(cfg, _table(cfg, "frontend"))
    nav = _table(cfg, "nav")
    if not isinstance(nav.get("data_bits"), bool):
        raise ConfigError(f"nav.data_bits must be true or false, got {nav.get('data_bits')!r}")
    if "data" in nav and nav["data"] not in NAV_DATA_MODES:
        raise ConfigError(f"nav.data must be one of {', '.join(NAV_DATA_MODES)}, got {nav['data']!r}")
    if "imu" in cfg:
        _table(cfg, "imu")
        _num(cfg, "imu.rate_hz", lo=0, lo_open=True, hi=MAX_IMU_RATE_HZ)
        la = cfg["imu"].get("lever_arm_m")
        if la is not None and (not isinstance(la, list) or len(la) != 3 or
                               any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x)
                                   or abs(x) > 1e3 for x in la)):
            raise ConfigError(f"imu.lever_arm_m must be a list of 3 numbers (m, FLU body, IMU -> antenna, "
                              f"|x| <= 1000), got {la!r}")
    if "atmosphere" in cfg:
        _validate_atmosphere(_table(cfg, "atmosphere"))
    if "engine" in cfg:
        _validate_engine(_table(cfg, "engine"))
    return cfg


def _validate_satellites(cfg, sat):
    if sat.get("source") not in ("nominal", "rinex"):
        raise ConfigError(f"satellites.source must be 'nominal' or 'rinex', got {sat.get('source')!r}")
    if sat["source"] == "rinex":
        rp = Path(str(sat.get("rinex", "")))
        if not rp.is_absolute():
            rp = shared_data_dir() / rp
        if not rp.is_file():
            raise ConfigError(f"satellites.rinex: file not found: {rp}")
        sat["rinex_path"] = str(rp)
    prns = sat.get("prns", [])
    if not isinstance(prns, list) or any(isinstance(p, bool) or not isinstance(p, int) or not 1 <= p <= 32
                                         for p in prns):
        raise ConfigError(f"satellites.prns must be a list of integers 1..32, got {prns!r}")
    if len(set(prns)) != len(prns):
        raise ConfigError(f"satellites.prns has duplicates: {prns!r}")
    _num(cfg, "satellites.max_count", lo=1, hi=32, integer=True)
    if sat.get("horizon_deg") is not None:
        _num(cfg, "satellites.horizon_deg", lo=-90, hi=90)
    _num(cfg, "satellites.mask_deg", lo=-90, hi=90)
    cn0 = sat.get("cn0_dbhz")
    vals = cn0 if isinstance(cn0, list) else [cn0]
    for v in vals:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 80.0:
            raise ConfigError(f"satellites.cn0_dbhz must be a number (or list) in [0, 80] dB-Hz, got {cn0!r}")
    if isinstance(cn0, list) and len(cn0) != len(prns):
        raise ConfigError("satellites.cn0_dbhz as a list needs satellites.prns of the same length")


def _validate_noise_events(evs):
    if not isinstance(evs, list):
        raise ConfigError("noise_events must be an array of tables [[noise_events]]")
    for i, ev in enumerate(evs):
        for k in ("t0_s", "t1_s", "noise_factor"):
            if k not in ev:
                raise ConfigError(f"noise_events[{i}].{k} is required")
            v = ev[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"noise_events[{i}].{k} must be a number, got {v!r}")
        if not ev["t0_s"] < ev["t1_s"]:
            raise ConfigError(f"noise_events[{i}]: t0_s must be < t1_s")
        if not MIN_NOISE_FACTOR <= ev["noise_factor"] <= MAX_NOISE_FACTOR:
            raise ConfigError(f"noise_events[{i}].noise_factor must be in [{MIN_NOISE_FACTOR:g}, "
                              f"{MAX_NOISE_FACTOR:g}] (x the nominal noise std), got {ev['noise_factor']!r}")
        validate_place(ev, i)


def _validate_frontend(cfg, fe):
    if fe.get("format") not in FORMATS:
        raise ConfigError(f"frontend.format: unknown IF sample format {fe.get('format')!r}; "
                          f"expected one of {', '.join(FORMATS)}")
    _num(cfg, "frontend.fs_hz", lo=MIN_FS_HZ, hi=MAX_FS_HZ)
    _num(cfg, "frontend.if_hz")
    _num(cfg, "frontend.bits", integer=True)
    FrontEnd.from_config(fe)       # raises ConfigError for impossible combinations
    if FORMATS[fe["format"]].is_complex != (fe.get("sampling") == "complex"):
        raise ConfigError(f"frontend.format {fe['format']!r} does not match frontend.sampling "
                          f"{fe.get('sampling')!r}")
    check_bits_for_format(fe["format"], fe["bits"])


def _validate_engine(eng):
    unknown = sorted(set(eng) - set(ENGINE_KEYS))
    if unknown:
        raise ConfigError(f"[engine]: unknown key(s) {', '.join(unknown)}; expected {', '.join(ENGINE_KEYS)}")
    if "noise_tau_s" in eng:
        v = eng["noise_tau_s"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
            raise ConfigError(f"engine.noise_tau_s must be >= 0 s (or inf), got {v!r}")
        eng["noise_tau_s"] = float(v)
    for k in ("lock_monitor", "monitor_gates_tight"):
        if k in eng and not isinstance(eng[k], bool):
            raise ConfigError(f"engine.{k} must be true or false, got {eng[k]!r}")
    if "bits" in eng and not (isinstance(eng["bits"], str) and eng["bits"]):
        raise ConfigError(f"engine.bits must be assisted, decoded, blind or a bit file path, got {eng['bits']!r}")


# [atmosphere] (opt-in): delays the generator applies (ultratight.signals.atmosphere); the default
# broadcast coefficients are those of the IGS broadcast file of 2022-01-01 (brdc0010.22n header)
ATMOSPHERE_DEFAULTS = {"iono": "off", "tropo": "off", "tropo_mapping": "cosz", "iono_scale": 1.0,
                       "alpha": [1.211e-08, -7.451e-09, -5.960e-08, 1.192e-07],
                       "beta": [1.167e+05, -2.458e+05, -6.554e+04, 1.114e+06], "broadcast": True}


def _validate_atmosphere(atm):
    check_known_keys(atm, ATMOSPHERE_DEFAULTS, "[atmosphere]")
    for k, v in ATMOSPHERE_DEFAULTS.items():
        atm.setdefault(k, list(v) if isinstance(v, list) else v)
    for key, allowed in (("iono", IONO_MODELS), ("tropo", TROPO_MODELS), ("tropo_mapping", MAPPINGS)):
        if atm[key] not in allowed:
            raise ConfigError(f"atmosphere.{key} must be one of {', '.join(allowed)}, got {atm[key]!r}")
    v = atm["iono_scale"]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 10.0:
        raise ConfigError(f"atmosphere.iono_scale must be a number in [0, 10], got {v!r}")
    atm["iono_scale"] = float(v)
    for key in ("alpha", "beta"):
        v = atm[key]
        if (not isinstance(v, list) or len(v) != 4 or
                any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in v)):
            raise ConfigError(f"atmosphere.{key} must be a list of 4 numbers (Klobuchar coefficients), got {v!r}")
        atm[key] = [float(x) for x in v]
    if not isinstance(atm["broadcast"], bool):
        raise ConfigError(f"atmosphere.broadcast must be true or false, got {atm['broadcast']!r}")
