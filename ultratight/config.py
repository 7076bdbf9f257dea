"""Configuration files every layer reads: the built-in scenario folder, TOML reading, overrides,
and the checks of keys and numbers that give one-line errors naming the key.

A scenario's schema belongs to whoever runs it (the IF-level one:
``ultratight.receiver.cli.scenario_config``; each paper experiment's ``load``); what they share
lives here. Relative data paths resolve against the shared data directory: ``$ULTRATIGHT_DATA``
if set, else ``../shared/data`` beside the repository.
"""

import copy
import difflib
import math
import os
import tomllib
from pathlib import Path

from ultratight.errors import ConfigError


def scenario_dir():
    """The built-in scenarios (package data ``ultratight/data/scenarios/*.toml``)."""
    return Path(__file__).resolve().parent / "data" / "scenarios"


def list_scenarios():
    """Names of the built-in scenarios (sorted)."""
    return sorted(p.stem for p in scenario_dir().glob("*.toml"))


def shared_data_dir():
    """``$ULTRATIGHT_DATA``, else ``../shared/data`` beside the repository."""
    env = os.environ.get("ULTRATIGHT_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def deep_merge(base, upd):
    """A deep copy of ``base`` with the tables of ``upd`` merged in (``upd`` wins)."""
    out = copy.deepcopy(base)
    for k, v in upd.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def apply_overrides(cfg, overrides):
    """``cfg`` with ``overrides`` applied in place: keys are dotted paths (``"frontend.fs_hz"``) or
    nested tables; ``None`` values are ignored, so CLI flags can be passed straight through."""
    for key, val in (overrides or {}).items():
        if val is None:
            continue
        if isinstance(val, dict) and "." not in key:
            cfg[key] = deep_merge(cfg.get(key, {}) if isinstance(cfg.get(key), dict) else {}, val)
            continue
        parts = key.split(".")
        d = cfg
        for p in parts[:-1]:
            if not isinstance(d.get(p), dict):
                d[p] = {}
            d = d[p]
        d[parts[-1]] = val
    return cfg


def read_toml(path):
    """The raw TOML dict of a scenario file (ConfigError on unreadable or invalid TOML)."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML ({exc})") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read scenario file ({exc.strerror})") from None


def locate_scenario(name_or_path):
    """Path of a built-in scenario name or of a TOML file (ConfigError when neither exists)."""
    s = str(name_or_path)
    p = Path(s)
    if s.endswith(".toml") or os.sep in s or p.is_file():
        if not p.is_file():
            raise ConfigError(f"scenario file not found: {p}")
        return p
    cand = scenario_dir() / f"{s}.toml"
    if not cand.is_file():
        raise ConfigError(f"unknown scenario {s!r}; known scenarios: {', '.join(list_scenarios()) or '(none)'}")
    return cand


def check_known_keys(table, allowed, where):
    """Refuse keys of ``table`` not in ``allowed`` (a did-you-mean names the closest one).

    ``where`` names the table in the message (``"[imu]"``, ``"top level"``)."""
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        k = unknown[0]
        near = difflib.get_close_matches(k, list(allowed), n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else f"; expected one of {', '.join(sorted(allowed))}"
        raise ConfigError(f"{where}: unknown key {k!r}{hint}")


def check_number(v, name, lo=None, hi=None, lo_open=False, integer=False):
    """``v`` as a checked configuration number (ConfigError naming ``name``): a real number, finite,
    an integer when asked, inside ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``). Returns ``v``."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{name} must be a number, got {v!r}")
    if not math.isfinite(v):
        raise ConfigError(f"{name} must be finite, got {v!r}")
    if integer and int(v) != v:
        raise ConfigError(f"{name} must be an integer, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise ConfigError(f"{name} must be {'>' if lo_open else '>='} {lo}, got {v!r}")
    if hi is not None and v > hi:
        raise ConfigError(f"{name} must be <= {hi}, got {v!r}")
    return v
