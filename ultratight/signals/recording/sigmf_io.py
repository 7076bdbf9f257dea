"""SigMF recordings (Signal Metadata Format, https://sigmf.org, specification v1.x; see docs/references.md) as IF input,
and SigMF metadata for the files the generator writes.

Reading (:func:`read_sigmf`, through the ``sigmf`` package): one channel, the first capture
segment.  ``core:datatype`` -> our sample format (``DATATYPES``: ci8, ci16_le/be, cf32_le/be,
ri8, ri16_le/be, rf32_le/be), ``core:sample_rate`` -> fs, and the capture's ``core:frequency``
(the frequency of the recording's 0 Hz) -> ``if_hz = F_L1 - core:frequency``: 0 for a complex
recording centred on L1; for real samples the LO frequency (a negative result, a high-side LO,
means a mirrored spectrum and is read as such).  The data file is the compliant
``<name>.sigmf-data`` or the non-conforming dataset named in ``core:dataset``.  Recording
conventions SigMF has no field for are read from this package's extension namespace
``ultratight`` when present: ``ultratight:iq_conj`` (the front end delivers ``I - jQ``),
``ultratight:start_week`` / ``ultratight:start_tow_s`` (GPS time of the first sample).

Writing (:func:`write_sigmf_meta`): ``<stem>.sigmf-meta`` beside an IF file, naming it in
``core:dataset`` (SigMF non-conforming dataset, so the file keeps its name and its JSON sidecar).
"""

import json
from pathlib import Path

from sigmf import sigmffile
from sigmf.error import SigMFError

from ultratight import __version__
from ultratight.constants import F_L1
from ultratight.errors import FormatError, InputFileError
from ultratight.io_guard import write_text_atomic
from ultratight.signals.recording.sampleformat import get_format

META_EXT = ".sigmf-meta"
DATA_EXT = ".sigmf-data"
SIGMF_VERSION = "1.2.0"
# SigMF datatype -> (our format name, numpy dtype of one stored component)
DATATYPES = {
    "ci8": ("ci8", "i1"), "ci16_le": ("ci16", "<i2"), "ci16_be": ("ci16", ">i2"),
    "cf32_le": ("cf32", "<f4"), "cf32_be": ("cf32", ">f4"),
    "ri8": ("i8", "i1"), "ri16_le": ("i16", "<i2"), "ri16_be": ("i16", ">i2"),
    "rf32_le": ("f32", "<f4"), "rf32_be": ("f32", ">f4"),
}
FORMAT_TO_DATATYPE = {"ci8": "ci8", "ci16": "ci16_le", "cf32": "cf32_le", "i8": "ri8", "i16": "ri16_le",
                      "f32": "rf32_le"}


def is_sigmf(path):
    return str(path).lower().endswith((META_EXT, DATA_EXT))


def meta_path_of(path):
    p = Path(path)
    if str(p).lower().endswith(DATA_EXT):
        return p.with_name(p.name[: -len(DATA_EXT)] + META_EXT)
    return p


def read_sigmf(path):
    """Sidecar-like dict (format, dtype, fs_hz, if_hz, is_complex, iq_conj, inversion, start_week,
    start_tow_s, data_file, sigmf) of a SigMF recording given by its ``.sigmf-meta`` or
    ``.sigmf-data`` path."""
    meta = meta_path_of(path)
    if not meta.is_file():
        raise InputFileError(f"SigMF metadata file not found: {meta}")
    try:
        rec = sigmffile.fromfile(str(meta), skip_checksum=True)
    except (SigMFError, json.JSONDecodeError, OSError, ValueError) as exc:
        raise FormatError(f"{meta}: not a readable SigMF recording ({exc})") from None
    g = rec.get_global_info() if hasattr(rec, "get_global_info") else rec._metadata["global"]
    dt = g.get("core:datatype")
    if dt not in DATATYPES:
        raise FormatError(f"{meta}: core:datatype {dt!r} not supported; expected one of {', '.join(DATATYPES)}")
    if int(g.get("core:num_channels", 1)) != 1:
        raise FormatError(f"{meta}: core:num_channels = {g.get('core:num_channels')}; only 1 is supported")
    fs = g.get("core:sample_rate")
    if not isinstance(fs, (int, float)) or not fs > 0:
        raise FormatError(f"{meta}: core:sample_rate must be a positive number, got {fs!r}")
    caps = rec.get_captures()
    freq = caps[0].get("core:frequency") if caps else None
    if freq is None:
        raise FormatError(f"{meta}: the first capture has no core:frequency (needed for the IF)")
    name, dtype = DATATYPES[dt]
    is_complex = get_format(name).is_complex
    if_hz = F_L1 - float(freq)
    inversion = False
    if not is_complex and if_hz < 0:
        if_hz, inversion = -if_hz, True
    data = rec.data_file
    if data is None or not Path(data).is_file():
        raise InputFileError(f"{meta}: SigMF dataset not found (neither {meta.stem}{DATA_EXT} nor core:dataset)")
    return {"format": name, "dtype": dtype, "fs_hz": float(fs), "if_hz": if_hz, "is_complex": is_complex,
            "iq_conj": bool(g.get("ultratight:iq_conj", False)), "inversion": inversion,
            "start_week": g.get("ultratight:start_week"), "start_tow_s": g.get("ultratight:start_tow_s"),
            "data_file": str(data), "sigmf": str(meta)}


def write_sigmf_meta(data_path, fmt, fs_hz, if_hz=0.0, iq_conj=False, inversion=False, start_week=None,
                     start_tow_s=None, description="", extra=None):
    """Write ``<stem>.sigmf-meta`` describing the IF file ``data_path`` (atomic); returns its path.
    A mirrored spectrum (``inversion``) is written as ``ultratight:iq_conj`` for complex samples
    and as a high-side LO (``core:frequency = F_L1 + if_hz``) for real ones.  Formats without a
    SigMF datatype (the packed 2-bit ones) raise FormatError."""
    data_path = Path(data_path)
    if fmt not in FORMAT_TO_DATATYPE:
        raise FormatError(f"SigMF has no datatype for the {fmt!r} sample format "
                          f"(supported: {', '.join(FORMAT_TO_DATATYPE)})")
    is_complex = get_format(fmt).is_complex
    if inversion and is_complex:
        iq_conj = not iq_conj
    freq = F_L1 + float(if_hz) if (inversion and not is_complex) else F_L1 - float(if_hz)
    g = {"core:datatype": FORMAT_TO_DATATYPE[fmt], "core:sample_rate": float(fs_hz), "core:version": SIGMF_VERSION,
         "core:num_channels": 1, "core:dataset": data_path.name, "core:recorder": f"ultratight {__version__}",
         "core:description": description or "GPS L1 C/A IF samples",
         "core:extensions": [{"name": "ultratight", "version": __version__, "optional": True}],
         "ultratight:iq_conj": bool(iq_conj)}
    if start_week is not None:
        g["ultratight:start_week"] = int(start_week)
    if start_tow_s is not None:
        g["ultratight:start_tow_s"] = float(start_tow_s)
    for k, v in (extra or {}).items():
        g[f"ultratight:{k}"] = v
    doc = {"global": g, "captures": [{"core:sample_start": 0, "core:frequency": freq}],
           "annotations": []}
    stem = data_path.name.rsplit(".", 1)[0]
    meta = data_path.with_name(stem + META_EXT)
    write_text_atomic(meta, json.dumps(doc, indent=1))
    return meta
