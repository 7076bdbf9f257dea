"""IF sample files: formats (objects in :mod:`ultratight.signals.recording.sampleformat`), JSON sidecar,
ION GNSS SDR metadata XML, streaming reader, writer.

Formats (``FORMATS``; all little-endian unless an ION XML says otherwise)
--------------------------------------------------------------------------
=============  =========================================================================
``i8``         real, int8 per sample
``i16``        real, int16 per sample
``f32``        real, float32 per sample
``ci8``        complex, int8 I then int8 Q per sample
``ci16``       complex, int16 I then int16 Q
``cf32``       complex, float32 I then float32 Q (numpy complex64 layout)
``i2packed``   real, 2 bits per sample, 4 samples per byte, first sample in the most
               significant bits (bits 7-6), then 5-4, 3-2, 1-0
``ci2packed``  complex, 2 bits per component, 2 samples per byte: I0 (bits 7-6),
               Q0 (5-4), I1 (3-2), Q1 (1-0)
``i4packed``   real, 4 bits per sample (read only)
``ci4packed``  complex, 4 bits per component (read only)
=============  =========================================================================

Packed formats are read in any layout of :class:`ultratight.signals.recording.packing.PackedLayout`
(bit order within a word, word size and byte order, sign-magnitude / two's complement / offset
binary / sign-only encoding): from the ``packing`` argument, the sidecar's ``packing`` object or
an ION XML; the defaults are the layout described here.

2-bit code (sign-magnitude): bit 1 = sign (1 = negative), bit 0 = magnitude
(1 = large). Codes 0, 1, 2, 3 mean +1, +3, -1, -3 (the front-end levels of
:mod:`ultratight.signals.synth.frontend`). Packed files may end with padding samples
(code 0); the sidecar's ``n_samples`` gives the true count.

Sidecar ``<file>.json`` (written for every file we write; found automatically)::

    {"format": "ci8", "fs_hz": 4e6, "if_hz": 0.0, "is_complex": true,
     "iq_conj": false, "inversion": false, "n_samples": 240000000,
     "start_week": 2190, "start_tow_s": 518400.0, "bits": 8,
     "generator": {...resolved configuration...}, "version": "0.1.0"}

Conventions on reading: ``iq_conj = True`` (argument or sidecar) returns
``x = I - jQ``. ``inversion = True`` in a sidecar means the spectrum is mirrored:
for complex data it is the same as ``iq_conj``; for *real* data the reader
multiplies sample ``n`` by ``(-1)**n`` (a shift by fs/2, which mirrors the spectrum)
and reports ``if_hz' = fs/2 - if_hz``, so consumers always see a non-inverted
signal and never need to know.

ION GNSS SDR Metadata Standard XML (``meta=path.xml``; see docs/references.md): a single stream in a
single lump/chunk/block is supported. Sample rate = system ``freqbase`` x stream
``ratefactor`` (units from the ``format`` attribute: Hz/kHz/MHz/GHz), IF from the band's
``translatedfreq``, sample type from ``quantization``/``packedbits``/``format``
(IF, IFn, IQ, IQn, QI, QIn) /``encoding`` (TC/INT8/INT16 two's complement, FP
float; for 2- and 4-bit packed samples SM sign-magnitude, TC, OB offset binary, SIGN sign only)
and the chunk ``endian`` (not applied to packed samples, which are read byte-wise); ``inverted`` or the
``n`` suffix formats set inversion; the file is the ``<file><url>`` relative
to the XML when ``path`` is None.
"""

import mmap
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ultratight import __version__
from ultratight.errors import FormatError, InputFileError
from ultratight.io_guard import StagedFile, check_input_file, check_interrupted, json_dumps
from ultratight.signals.recording.metadata_check import check_sidecar, load_json_metadata
from ultratight.signals.recording.packing import ION_ENCODINGS
# the format registry lives in sampleformat (metadata_check and sigmf_io need it without this module);
# FORMATS and check_bits_for_format are part of this module's interface too
from ultratight.signals.recording.sampleformat import FORMATS, check_bits_for_format, get_format  # noqa: F401


def sidecar_path(path):
    return Path(str(path) + ".json")


# ------------------------------------------------------------------------------------------
# ION GNSS SDR metadata XML
# ------------------------------------------------------------------------------------------
_FREQ_UNITS = {"hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}


def _strip_ns(root):
    for el in root.iter():
        if isinstance(el.tag, str) and "}" in el.tag:
            el.tag = el.tag.split("}", 1)[1]
        el.tag = el.tag.lower() if isinstance(el.tag, str) else el.tag
    return root


def _freq(el, what, xml_path):
    if el is None or el.text is None:
        return None
    unit = (el.get("format") or "Hz").strip().lower()
    if unit not in _FREQ_UNITS:
        raise FormatError(f"{xml_path}: unknown frequency unit {unit!r} for <{what}>")
    try:
        return float(el.text) * _FREQ_UNITS[unit]
    except ValueError:
        raise FormatError(f"{xml_path}: <{what}> is not a number: {el.text!r}") from None


def parse_ion_metadata(xml_path):
    """Parse a single-stream ION GNSS SDR metadata XML file into sidecar-like fields.

    Malformed values (``<ratefactor>x``, ``<quantization>thirtytwo``, non-finite rates) raise
    FormatError naming the file."""
    try:
        info = _parse_ion_metadata(xml_path)
    except (ValueError, TypeError, AttributeError, RecursionError, UnicodeError) as exc:
        if isinstance(exc, FormatError):
            raise
        raise FormatError(f"{xml_path}: malformed ION metadata ({' '.join(str(exc).split())[:200]})") from None
    fs = info["fs_hz"]
    if not (np.isfinite(fs) and fs > 0):
        raise FormatError(f"{xml_path}: sample rate (freqbase x ratefactor) must be > 0 Hz, got {fs}")
    if not np.isfinite(info["if_hz"]):
        raise FormatError(f"{xml_path}: <translatedfreq> must be finite, got {info['if_hz']}")
    check_sidecar({k: info[k] for k in ("fs_hz", "if_hz")}, xml_path)
    return info


def _parse_ion_metadata(xml_path):
    xml_path = Path(xml_path)
    if not xml_path.is_file():
        raise InputFileError(f"metadata file not found: {xml_path}")
    try:
        root = _strip_ns(ET.parse(xml_path).getroot())
    except ET.ParseError as exc:
        raise FormatError(f"{xml_path}: not valid XML ({exc})") from None
    streams = [s for s in root.iter("stream") if s.find("quantization") is not None]
    lump_streams = [s for s in root.iter("lump") for s in s.findall("stream")]
    if len({id(s) for s in lump_streams}) > 1:
        raise FormatError(f"{xml_path}: {len(lump_streams)} streams in the lump; only one stream is supported")
    if not streams:
        raise FormatError(f"{xml_path}: no <stream> with <quantization> found")
    st = lump_streams[0] if lump_streams and lump_streams[0].find("quantization") is not None else streams[0]

    def txt(el, tag, default=None):
        e = el.find(tag)
        return e.text.strip() if e is not None and e.text else default

    quant = int(txt(st, "quantization", "0"))
    packed = int(txt(st, "packedbits", "0"))
    fmt = (txt(st, "format", "IF") or "IF").upper()
    enc = (txt(st, "encoding", "TC") or "TC").upper()
    ratefactor = float(txt(st, "ratefactor", "1"))
    freqbase = None
    for el in root.iter("freqbase"):
        freqbase = _freq(el, "freqbase", xml_path)
        break
    if freqbase is None:
        raise FormatError(f"{xml_path}: no <freqbase> (system sample rate) found")
    band = st.find("band")
    if_hz = _freq(band.find("translatedfreq"), "translatedfreq", xml_path) if band is not None else 0.0
    inverted = False
    if band is not None and txt(band, "inverted", "false").lower() in ("true", "1", "yes"):
        inverted = True
    if fmt.endswith("N"):
        inverted = True
        fmt = fmt[:-1]
    if fmt not in ("IF", "IQ", "QI"):
        raise FormatError(f"{xml_path}: unsupported stream <format> {fmt!r} (expected IF, IQ, QI or with n)")
    is_complex = fmt in ("IQ", "QI")
    endian = "<"
    for el in root.iter("endian"):
        if el.text and el.text.strip().lower() == "big":
            endian = ">"
    comp_bits = packed // 2 if is_complex else packed
    if enc == "FP" or enc.startswith("FLOAT"):
        if quant != 32:
            raise FormatError(f"{xml_path}: floating-point quantization {quant} not supported (expected 32)")
        name, dtype = ("cf32" if is_complex else "f32"), endian + "f4"
    elif quant in (1, 2, 3, 4) and comp_bits in (2, 4) and enc in ION_ENCODINGS:
        name, dtype = ("c" if is_complex else "") + f"i{comp_bits}packed", "u1"
    elif quant in (1, 2, 3, 4, 5, 6, 7, 8) and comp_bits == 8 and enc in ("TC", "INT8", "SM"):
        name, dtype = ("ci8" if is_complex else "i8"), "i1"
    elif quant <= 16 and comp_bits == 16 and enc in ("TC", "INT16"):
        name, dtype = ("ci16" if is_complex else "i16"), endian + "i2"
    else:
        raise FormatError(
            f"{xml_path}: unsupported sample layout (quantization={quant}, packedbits={packed}, "
            f"format={fmt}, encoding={enc})")
    url = None
    for f in root.iter("file"):
        url = txt(f, "url")
        if url:
            break
    packing = None
    if get_format(name).packed:
        # the encoding comes from the XML; samples are read byte by byte, first sample in the high
        # bits (the chunk's sizeword / endian are not applied to packed samples: give --word-size,
        # --endian and --packing for other layouts)
        packing = {"bits": comp_bits, "encoding": ION_ENCODINGS[enc] if quant > 1 else "sign"}
    return {"format": name, "dtype": dtype, "fs_hz": freqbase * ratefactor, "if_hz": if_hz or 0.0, "packing": packing,
            "is_complex": is_complex, "iq_swap": fmt == "QI", "inversion": inverted, "bits": quant,
            "data_file": str(xml_path.parent / url) if url else None}


# ------------------------------------------------------------------------------------------
# reader
# ------------------------------------------------------------------------------------------
def iter_blocks(source, block_len, start=0, stop=None):
    """``(start_index, samples)`` over consecutive blocks of ``block_len`` samples of ``source`` (an
    object with ``n_samples`` and ``read(start, count)``), from ``start`` to ``stop`` (default the end)."""
    block_len = int(block_len)
    if block_len <= 0:
        raise ValueError("block_len must be > 0")
    stop = source.n_samples if stop is None else min(int(stop), source.n_samples)
    pos = int(start)
    while pos < stop:
        n = min(block_len, stop - pos)
        yield pos, source.read(pos, n)
        pos += n


def orient(raw, start, is_complex, iq_swap=False, conj=False, alt_sign=False):
    """Decoded float32 components ``raw`` of the samples from ``start`` as the readers return them:
    complex64 (complex formats; I/Q swapped back, conjugated) or float32 (real formats; sample ``n``
    times ``(-1)**n`` for a mirrored spectrum). Works in place on ``raw``."""
    if is_complex:
        if iq_swap:
            raw = raw.reshape(-1, 2)[:, ::-1].copy().reshape(-1)
        x = raw.view(np.complex64)
        if conj:
            raw[1::2] *= -1.0
        return x
    if alt_sign:
        first = start & 1
        raw[(1 - first)::2] *= -1.0
    return raw


class IfSource:
    """A sampled-IF file opened for streaming reads (memory-mapped; nothing is loaded whole).

    Attributes: ``path, fmt, fs_hz, if_hz, is_complex, n_samples, duration_s, start_week,
    start_tow_s, meta`` (the sidecar dict, or ``{}``). ``read`` returns complex64 (complex
    formats) or float32 (real formats). ``release(upto_sample)`` drops already-read pages from
    the resident set (call it now and then when streaming through a long file).
    """

    def __init__(self, path, fmt, fs_hz, if_hz, iq_conj=False, inversion=False, start_week=None,
                 start_tow_s=None, n_samples=None, dtype=None, iq_swap=False, meta=None, packing=None):
        self.path = Path(path)
        self.spec = get_format(fmt)
        self.fmt = self.spec.name
        self.fs_hz = float(fs_hz)
        if not np.isfinite(self.fs_hz) or self.fs_hz <= 0:
            raise FormatError(f"{self.path}: sample rate must be > 0 Hz, got {fs_hz}")
        self.is_complex = self.spec.is_complex
        self.meta = dict(meta or {})
        self.start_week = start_week
        self.start_tow_s = start_tow_s
        self._iq_swap = bool(iq_swap)
        self._conj = bool(iq_conj) != bool(inversion and self.is_complex)
        self._alt_sign = bool(inversion and not self.is_complex)
        if_hz = float(if_hz)
        self.file_if_hz = if_hz
        self.if_hz = self.fs_hz / 2.0 - if_hz if self._alt_sign else if_hz
        if not self.path.is_file():
            check_input_file(self.path, "IF file")
        size = self.path.stat().st_size
        spec = self.spec
        self.packing = spec.layout(packing, self.path)
        total = spec.count(size, self.packing, self.path)
        self.warnings = []
        if n_samples is not None:
            if n_samples > total:
                # a truncated recording: the data are what they are -- use what is there, say so
                self.warnings.append(f"{self.path}: truncated recording: the metadata state {int(n_samples)} "
                                     f"samples but the file holds {total}; processing the {total} present")
            else:
                total = int(n_samples)
        self.n_samples = int(total)
        self.duration_s = self.n_samples / self.fs_hz
        dt = np.dtype(dtype or spec.dtype)
        self._mm = np.memmap(self.path, dtype=dt, mode="r") if size > 0 else np.zeros(0, dt)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        mm = getattr(self, "_mm", None)
        if isinstance(mm, np.memmap) and mm._mmap is not None:
            mm._mmap.close()
        self._mm = None

    def release(self, upto_sample):
        """Drop the mapped pages holding samples ``[0, upto_sample)`` from this process's resident set.

        Pages of a read-only file mapping stay resident (and count in RSS) once read, so a reader
        streaming through a long file would otherwise grow to the file size. This calls
        ``madvise(MADV_DONTNEED)`` on the whole pages before ``upto_sample`` (the page cache keeps
        the data). Later ``read`` calls stay correct, also for released samples (they are read
        back from the file). Returns the number of bytes released; 0 (and nothing done) when the
        file is empty or closed, the platform has no ``madvise``, or ``upto_sample <= 0``.
        """
        raw = getattr(self._mm, "_mmap", None)
        if raw is None or not hasattr(raw, "madvise") or not hasattr(mmap, "MADV_DONTNEED"):
            return 0
        upto = min(int(upto_sample), self.n_samples)
        if upto <= 0:
            return 0
        nbytes = self.spec.nbytes(upto, self.packing)
        # np.memmap maps from the page boundary at or below its offset; here the offset is 0
        start = int(getattr(self._mm, "offset", 0) or 0)
        end = min((start + nbytes) // mmap.PAGESIZE * mmap.PAGESIZE, len(raw))
        if end <= 0:
            return 0
        try:
            raw.madvise(mmap.MADV_DONTNEED, 0, end)
        except (OSError, ValueError):
            return 0
        return end

    def __repr__(self):
        return (f"IfSource({str(self.path)!r}, fmt={self.fmt!r}, fs_hz={self.fs_hz}, if_hz={self.if_hz}, "
                f"n_samples={self.n_samples})")

    def read(self, start, count):
        """Samples ``[start, start+count)`` (clipped to the file end) as complex64 / float32."""
        start = int(start)
        if start < 0:
            raise ValueError("start must be >= 0")
        count = max(0, min(int(count), self.n_samples - start))
        raw = self.spec.decode(self._mm, start, count, self.packing)
        return orient(raw, start, self.is_complex, self._iq_swap, self._conj, self._alt_sign)

    def blocks(self, block_len, start=0, stop=None):
        """Iterate ``(start_index, samples)`` over consecutive blocks of ``block_len`` samples."""
        return iter_blocks(self, block_len, start, stop)


def read_sidecar(path):
    """The JSON sidecar of ``path`` as a dict, or None if absent."""
    sp = sidecar_path(path)
    if not sp.is_file():
        return None
    return load_json_metadata(sp)


def open_if(path=None, meta=None, fs_hz=None, if_hz=None, fmt=None, iq_conj=False, packing=None):
    """Open an IF file. Parameters come from (in rising priority) the sidecar ``<path>.json``
    or ``meta`` (a JSON sidecar, an ION XML or a SigMF ``.sigmf-meta`` path; a ``path`` ending in
    ``.sigmf-meta`` / ``.sigmf-data`` is read as SigMF, :mod:`ultratight.signals.recording.sigmf_io`), then
    the explicit arguments.

    Raises InputFileError (missing file) or FormatError (unknown format, size not a whole
    number of samples, no sidecar and no ``fmt``/``fs_hz``).
    """
    info = {}
    if meta is None and path is not None and str(path).lower().endswith((".sigmf-meta", ".sigmf-data")):
        meta = path                       # a SigMF recording named by either of its files
        path = None
    if meta is not None:
        mp = Path(meta)
        if not mp.is_file() and not str(mp).lower().endswith(".sigmf-data"):
            check_input_file(mp, "metadata file")
        if str(mp).lower().endswith((".sigmf-meta", ".sigmf-data")):
            from ultratight.signals.recording.sigmf_io import read_sigmf   # sigmf + jsonschema: 0.15 s

            info = read_sigmf(mp)
            if path is None:
                path = info["data_file"]
        elif mp.suffix.lower() == ".xml":
            info = parse_ion_metadata(mp)
            if path is None:
                if not info.get("data_file"):
                    raise FormatError(f"{mp}: no <file><url> and no data path given")
                path = info["data_file"]
        else:
            info = load_json_metadata(mp)
    if path is None:
        raise InputFileError("no IF file given")
    path = Path(path)
    if not path.is_file():
        check_input_file(path, "IF file")
    if meta is None:
        info = read_sidecar(path) or {}
    given = {k: v for k, v in info.items() if v is not None}     # a field given as null is not given
    fmt = fmt or given.get("format")
    fs = fs_hz if fs_hz is not None else given.get("fs_hz")
    if fmt is None or fs is None:
        why = "the metadata lacks the sample format or rate" if info else \
            f"no sidecar {sidecar_path(path).name} or metadata"
        raise FormatError(f"{path}: {why}; give the sample format and rate (fmt=/--format and fs_hz=/--fs)")
    ifh = if_hz if if_hz is not None else given.get("if_hz", 0.0)
    spec = get_format(fmt)
    same_format = given.get("format") == spec.name
    return IfSource(path, spec.name, fs, ifh, iq_conj=bool(iq_conj) or bool(given.get("iq_conj", False)),
                    inversion=bool(given.get("inversion", False)), start_week=given.get("start_week"),
                    start_tow_s=given.get("start_tow_s"),
                    n_samples=given.get("n_samples") if same_format else None,
                    dtype=given.get("dtype") if same_format else None, iq_swap=given.get("iq_swap", False),
                    meta=info, packing={**(given.get("packing") or {}), **(packing or {})} if spec.packed else None)


# ------------------------------------------------------------------------------------------
# writer
# ------------------------------------------------------------------------------------------
class IfWriter:
    """Streaming writer: ``write(samples)`` blocks, then ``close()`` renames the temp file and
    writes the sidecar; ``abort()`` (or an exception inside ``with``) removes everything.

    Integer formats round and clip the given float/complex values; 2-bit formats store
    each component's nearest level of {-3, -1, +1, +3} (see the module doc).
    """

    def __init__(self, path, fmt, fs_hz, if_hz=0.0, iq_conj=False, inversion=False, start_week=None,
                 start_tow_s=None, bits=None, extra=None):
        self.path = Path(path)
        self.spec = get_format(fmt)
        if not self.spec.writable:
            raise FormatError(f"{self.path}: format {fmt!r} is read only (no writer for "
                              f"{self.spec.packed_bits}-bit packed samples)")
        self.fs_hz = float(fs_hz)
        self.if_hz = float(if_hz)
        self.sidecar = {"format": self.spec.name, "fs_hz": self.fs_hz, "if_hz": self.if_hz,
                        "is_complex": self.spec.is_complex, "iq_conj": bool(iq_conj),
                        "inversion": bool(inversion), "start_week": start_week,
                        "start_tow_s": start_tow_s, "bits": bits}

        self.sidecar["version"] = __version__
        if extra:
            self.sidecar.update(extra)
        self.n_samples = 0
        self._enc = self.spec.encoder()
        self._data = StagedFile(self.path)
        self._side = StagedFile(sidecar_path(self.path))
        self._f = open(self._data.tmp, "wb")
        self._closed = False

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def write(self, x, exact=False):
        """Append samples. ``exact=True`` promises the values are already integers inside the
        format's range (e.g. quantiser output), which skips rounding and clipping."""
        check_interrupted()
        spec = self.spec
        x = np.asarray(x)
        if spec.is_complex:
            comps = np.ascontiguousarray(x, dtype=np.complex64).view(np.float32)
        else:
            if np.iscomplexobj(x):
                raise FormatError(f"{self.path}: complex samples given for real format {spec.name}")
            comps = np.ascontiguousarray(x, dtype=np.float32).reshape(-1)
        self.n_samples += comps.size // spec.comps
        self._f.write(self._enc.encode(comps, exact))

    def close(self):
        if self._closed:
            return
        self._f.write(self._enc.flush())
        self._f.close()
        self.sidecar["n_samples"] = int(self.n_samples)
        with open(self._side.tmp, "w") as f:
            f.write(json_dumps(self.sidecar, indent=1))     # strict JSON: a non-finite value is null
        self._data.commit()
        self._side.commit()
        self._closed = True

    def abort(self):
        if self._closed:
            return
        try:
            self._f.close()
        finally:
            self._data.discard()
            self._side.discard()
            self._closed = True


def write_if(path, samples, fmt, fs_hz, if_hz=0.0, **kw):
    """Write a whole array (convenience wrapper around :class:`IfWriter`). Returns the path."""
    with IfWriter(path, fmt, fs_hz, if_hz, **kw) as w:
        w.write(samples)
    return Path(path)
