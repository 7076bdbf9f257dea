"""Validation of IF metadata: JSON sidecars (and ``--meta`` JSON) before :class:`IfSource` uses them.

:func:`load_json_metadata` reads a sidecar as strict UTF-8 JSON and :func:`check_sidecar` checks
the type and range of every field :func:`ultratight.signals.recording.iffile.open_if` reads, raising
:class:`ultratight.errors.FormatError` naming the file and field (never a bare ``TypeError``,
``ValueError`` or ``UnicodeDecodeError``). Unknown fields pass through (they are provenance).
"""

import json
import math

import numpy as np

from ultratight.errors import FormatError
from ultratight.signals.recording.sampleformat import get_format

MAX_METADATA_BYTES = 64 * 1024 * 1024      # a sidecar is a small JSON object; refuse anything huge


def _reject_constant(name):
    raise ValueError(f"non-standard JSON constant {name}")


def load_json_metadata(path):
    """The JSON object in ``path`` (FormatError on unreadable, non-UTF-8, invalid or non-object JSON)."""
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_METADATA_BYTES + 1)
    except OSError as exc:
        raise FormatError(f"{path}: cannot read JSON metadata ({exc.strerror or exc})") from None
    if len(data) > MAX_METADATA_BYTES:
        raise FormatError(f"{path}: JSON metadata larger than {MAX_METADATA_BYTES} bytes; not a sidecar")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not a JSON sidecar (byte {exc.start} is not UTF-8 text)") from None
    try:
        info = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise FormatError(f"{path}: unreadable JSON sidecar ({' '.join(str(exc).split())[:200]})") from None
    if not isinstance(info, dict):
        raise FormatError(f"{path}: a JSON sidecar must be an object {{...}}, got {type(info).__name__}")
    return check_sidecar(info, path)


def _number(info, key, path, positive=False, nonneg=False, integer=False):
    v = info.get(key)
    if v is None:
        return
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise FormatError(f"{path}: sidecar field {key!r} must be a number, got {v!r}")
    if not math.isfinite(v):
        raise FormatError(f"{path}: sidecar field {key!r} must be finite, got {v!r}")
    if integer and int(v) != v:
        raise FormatError(f"{path}: sidecar field {key!r} must be an integer, got {v!r}")
    if positive and not v > 0:
        raise FormatError(f"{path}: sidecar field {key!r} must be > 0, got {v!r}")
    if nonneg and v < 0:
        raise FormatError(f"{path}: sidecar field {key!r} must be >= 0, got {v!r}")


def check_sidecar(info, path):
    """Check the fields of a sidecar dict (module doc); returns it unchanged."""
    if not isinstance(info, dict):
        raise FormatError(f"{path}: metadata must be a JSON object, got {type(info).__name__}")
    fmt = info.get("format")
    if fmt is not None and not isinstance(fmt, str):
        raise FormatError(f"{path}: sidecar field 'format' must be a format name, got {fmt!r}")
    if fmt is not None:
        get_format(fmt)
    _number(info, "fs_hz", path, positive=True)
    _number(info, "if_hz", path)
    _number(info, "n_samples", path, nonneg=True, integer=True)
    _number(info, "start_week", path, nonneg=True, integer=True)
    _number(info, "start_tow_s", path, nonneg=True)
    _number(info, "bits", path, nonneg=True, integer=True)
    if info.get("start_tow_s") is not None and info["start_tow_s"] >= 604800.0:
        raise FormatError(f"{path}: sidecar field 'start_tow_s' must be < 604800 s, got {info['start_tow_s']!r}")
    if info.get("fs_hz") is not None and info.get("if_hz") is not None and abs(info["if_hz"]) >= info["fs_hz"]:
        raise FormatError(f"{path}: sidecar if_hz {info['if_hz']!r} must be smaller in magnitude than fs_hz "
                          f"{info['fs_hz']!r}")
    for key in ("iq_conj", "inversion", "is_complex", "iq_swap"):
        v = info.get(key)
        if v is not None and not isinstance(v, bool):
            raise FormatError(f"{path}: sidecar field {key!r} must be true or false, got {v!r}")
    dt = info.get("dtype")
    if dt is not None:
        try:
            ok = isinstance(dt, str) and np.dtype(dt).kind in "iuf"
        except TypeError:
            ok = False
        if not ok:
            raise FormatError(f"{path}: sidecar field 'dtype' must be a numeric dtype name, got {dt!r}")
    prn = info.get("prn")
    if prn is not None and (not isinstance(prn, list) or any(isinstance(p, bool) or not isinstance(p, int)
                                                              or not 1 <= p <= 32 for p in prn)):
        raise FormatError(f"{path}: sidecar field 'prn' must be a list of PRNs 1..32, got {prn!r}")
    gen = info.get("generator")
    if gen is not None and not isinstance(gen, dict):
        raise FormatError(f"{path}: sidecar field 'generator' must be an object, got {type(gen).__name__}")
    return info
