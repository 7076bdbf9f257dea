"""Navigation-data bit sources of the ultra-tight engine (``--bits`` / ``[engine] bits``).

Every source gives the data wipe-off stage (:mod:`ultratight.receiver.dsp.wipeoff`) ``bits``
(n_ch, n_bits) int8 — +1 / -1 a known bit (logic 0 = +1), 0 unknown — starting at transmit time
``t0_ms`` (ms of the GPS week of the IF start, a bit edge) per channel, the strategy ``code`` per
channel and ``mode`` (a name for the records):

* ``assisted``: the LNAV message re-encoded from the ephemeris
  (:class:`ultratight.receiver.deep.startup.BitWipeoff`). Right only for signals whose whole message is
  that encoding — the project's own generated data with ``nav.data = "lnav"``; a real satellite's
  subframes 4-5, TLM and reserved fields are not in the ephemeris, so about half the bits of such
  a frame would be wrong.
* ``decoded`` (:func:`decoded_from_pass`): a blind pass of the engine over the same IF file; the
  LNAV decoder reads that pass's per-bit soft decisions; the bits of every word whose parity
  checks — with the polarity of its subframe's preamble — are known, all others unknown (the
  engine decides those blind).
* ``decoded-scalar`` (:func:`decoded_source`): the same from a scalar pass (the project's scalar
  receiver, :class:`ultratight.receiver.scalar.receiver.ScalarReceiver`, started on the hot-start
  predictions instead of an acquisition). It decodes only while the scalar receiver keeps lock
  (on paper-highdyn at 30 dB-Hz it lost every channel in the noise burst and decoded nothing).
* ``blind``: every bit unknown.
* a file path (:func:`file_source`): external bits in the CSV format of :func:`write_bits_csv`
  (docs/process.md, "Data bits"): one row per bit ``prn,week,tow_s,bit`` with ``tow_s`` the bit's
  start in satellite (transmit) time, a multiple of 20 ms, and ``bit`` +1 / -1 (logic 0 / 1) or 0
  (unknown); bits not in the file are unknown.
"""

import csv
from pathlib import Path

import numpy as np

from ultratight.constants import SECONDS_PER_WEEK
from ultratight.errors import ConfigError, InputFileError
from ultratight.io_guard import read_text_input
from ultratight.receiver.deep.startup import BitWipeoff
from ultratight.receiver.dsp.wipeoff import BIT_ASSISTED, BIT_BLIND, BIT_DECODED, BIT_FILE, BIT_NONE  # noqa: F401
from ultratight.signals.lnav import SUBFRAME_BITS, WORD_BITS, decode_bits
from ultratight.signals.signal import GPS_L1CA

STRATEGIES = ("assisted", "decoded", "decoded-scalar", "blind")
BITS_FILE_HEADER = ("prn", "week", "tow_s", "bit")
MARGIN_BITS = 10            # bits of the rows before the start (as BitWipeoff)


def check_strategy(value):
    """``(name, path)``: name one of :data:`STRATEGIES` or ``"file"`` (then ``path`` the bit file).
    Raises ConfigError for an empty value or a missing file, InputFileError for a malformed one (read
    here, before any processing)."""
    if not isinstance(value, str) or not value:
        raise ConfigError(f"--bits: expected assisted, decoded, blind or a bit file, got {value!r}")
    if value in STRATEGIES:
        return value, None
    p = Path(value)
    if not p.is_file():
        raise ConfigError(f"--bits: {value!r} is neither assisted, decoded, blind nor an existing bit file")
    read_bits_csv(p)
    return "file", p


class BitRows:
    """A bit source: ``bits`` (n_ch, n_bits) int8, ``t0_ms`` (n_ch,), ``code`` (n_ch,), ``mode``,
    ``strategy`` and ``info`` (a dict for the records)."""

    def __init__(self, n_ch, tow_start_s, duration_s, code, mode, signal=GPS_L1CA):
        t_bit = signal.bit_period_s
        self.n_bits = int(np.ceil(duration_s / t_bit)) + 2 * MARGIN_BITS
        t0 = np.floor(tow_start_s / t_bit) * t_bit - MARGIN_BITS * t_bit
        self.bit0 = int(round(t0 / t_bit))                  # bit index of week of column 0
        self.t0_ms = np.full(n_ch, int(round(t0 * 1000.0)), dtype=np.int64)
        self.bits = np.zeros((n_ch, self.n_bits), dtype=np.int8)
        self.code = np.full(n_ch, code, dtype=np.int8)
        self.mode = mode
        self.strategy = mode
        self.info = {}

    def put(self, ch, bit_index, values):
        """Known bits (±1) at absolute bit indices of the week (those outside the rows are dropped)."""
        j = np.asarray(bit_index, dtype=np.int64) - self.bit0
        ok = (j >= 0) & (j < self.n_bits)
        self.bits[ch, j[ok]] = np.asarray(values, dtype=np.int8)[ok]

    def known_fraction(self):
        return [round(float(np.mean(r != 0)), 4) for r in self.bits]


def assisted_source(ephs, prns, week, tow_start_s, duration_s, signal=GPS_L1CA):
    src = BitWipeoff(ephs, prns, week, tow_start_s, duration_s, signal=signal)
    src.code = np.full(len(prns), BIT_NONE if src.mode == "none" else BIT_ASSISTED, dtype=np.int8)
    src.strategy = "assisted"
    src.info = {"note": "LNAV re-encoded from the ephemeris: valid only for data whose whole message is that "
                        "encoding (the project's generated data with nav.data = lnav)"}
    return src


def blind_source(n_ch, tow_start_s, duration_s, signal=GPS_L1CA):
    return BitRows(n_ch, tow_start_s, duration_s, BIT_BLIND, "blind", signal)


# ----------------------------------------------------------------------------------- bit files
def write_bits_csv(path, prns, week, bit0, bits):
    """Write bits in the external bit-file format: ``bits`` (n_prn, n) ±1/0, column k of row i the bit
    of PRN ``prns[i]`` starting at GPS week ``week``, TOW ``(bit0 + k) * 20 ms`` (satellite time)."""
    with open(path, "w", newline="") as f:
        f.write("# ultratight data bits v1: one row per bit; tow_s = bit start (satellite time), "
                "bit = +1 (logic 0), -1 (logic 1) or 0 (unknown)\n")
        w = csv.writer(f)
        w.writerow(BITS_FILE_HEADER)
        per_week = int(round(SECONDS_PER_WEEK / GPS_L1CA.bit_period_s))
        for i, prn in enumerate(prns):
            for k, b in enumerate(np.asarray(bits[i])):
                kk = int(bit0) + k
                wk, kw = int(week) + kk // per_week, kk % per_week
                w.writerow((int(prn), wk, f"{kw * GPS_L1CA.bit_period_s:.2f}", int(b)))


def read_bits_csv(path):
    """``{prn: (week (n,), tow_s (n,), bit (n,))}`` of a bit file; InputFileError naming the file and
    line for anything that is not the format."""
    path = Path(path)
    out = {}
    text = read_text_input(path, "bit file", kind="bit file (CSV text)")
    rows = (ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#"))
    reader = csv.reader(rows)
    header = next(reader, None)
    if header is None or tuple(h.strip() for h in header) != BITS_FILE_HEADER:
        raise InputFileError(f"{path}: bit file header must be {','.join(BITS_FILE_HEADER)}, got "
                             f"{None if header is None else ','.join(header)!r}")
    t_bit = GPS_L1CA.bit_period_s
    for n, row in enumerate(reader, start=2):
        try:
            prn, week, tow, bit = int(row[0]), int(row[1]), float(row[2]), int(row[3])
        except (ValueError, IndexError):
            raise InputFileError(f"{path}: data row {n}: expected prn,week,tow_s,bit, got {','.join(row)!r}") \
                from None
        if not 1 <= prn <= 63 or week < 0 or not 0.0 <= tow < SECONDS_PER_WEEK or bit not in (-1, 0, 1):
            raise InputFileError(f"{path}: data row {n}: PRN 1..63, week >= 0, 0 <= tow_s < 604800, bit in "
                                 f"-1/0/1 expected, got {','.join(row)!r}")
        if abs(tow / t_bit - round(tow / t_bit)) > 1e-6:
            raise InputFileError(f"{path}: data row {n}: tow_s {tow!r} is not a bit edge (multiple of "
                                 f"{t_bit * 1e3:g} ms)")
        out.setdefault(prn, ([], [], []))
        out[prn][0].append(week)
        out[prn][1].append(tow)
        out[prn][2].append(bit)
    return {p: tuple(np.asarray(v) for v in cols) for p, cols in out.items()}


def file_source(path, prns, week, tow_start_s, duration_s, signal=GPS_L1CA):
    data = read_bits_csv(path)
    rows = BitRows(len(prns), tow_start_s, duration_s, BIT_FILE, "file", signal)
    per_week = int(round(SECONDS_PER_WEEK / signal.bit_period_s))
    for ch, prn in enumerate(prns):
        if prn not in data:
            continue
        wk, tow, bit = data[prn]
        k = (wk - int(week)) * per_week + np.rint(tow / signal.bit_period_s).astype(np.int64)
        rows.put(ch, k, bit)
    rows.info = {"path": str(path), "prns_in_file": sorted(int(p) for p in data)}
    return rows


# ----------------------------------------------------------------------------------- decoded
def known_words(soft, tow_ref_s, prn=0, bit_index0=None):
    """Known transmitted bits of a contiguous stream of soft bits (sign = bit, any polarity):
    ``(bit index (n,), ±1 (n,))`` of the words whose parity checks, with the polarity of their
    subframe's preamble (module docstring); bit indices count 20 ms bits from the start of the GPS
    week of ``tow_ref_s``, a TOW near the stream (resolves the week roll-over). ``bit_index0``: the
    bit index of ``soft[0]`` when the stream's timing is known; a subframe whose TOW disagrees with it
    gives no known bit.

    Polarity: words before the first word failing parity in a subframe take that subframe's
    polarity, words after the last failing one the next subframe's; a subframe with no failing word
    whose successor has the other polarity (a slip at a word edge) gives no known bit."""
    soft = np.asarray(soft, dtype=float)
    dec = decode_bits(soft, prn=prn)
    hard = (soft < 0).astype(np.int8)             # logic 1 where the soft bit is negative
    sfs = dec.subframes
    by_start = {sf.start_bit: sf for sf in sfs}
    idx, val = [], []
    for sf in sfs:
        if sf.tow_s is None:
            continue
        nxt = by_start.get(sf.start_bit + SUBFRAME_BITS)
        inv0 = int(sf.inverted)
        inv1 = None if nxt is None else int(nxt.inverted)
        bad = sf.bad_words
        tow = float(sf.tow_s)
        if tow - tow_ref_s > SECONDS_PER_WEEK / 2:
            tow -= SECONDS_PER_WEEK
        elif tow_ref_s - tow > SECONDS_PER_WEEK / 2:
            tow += SECONDS_PER_WEEK
        k_sf = int(round(tow / GPS_L1CA.bit_period_s))
        if bit_index0 is not None and k_sf != int(bit_index0) + sf.start_bit:
            continue
        for w in range(10):
            if sf.words[w] is None:
                continue
            if not bad:
                if inv1 is not None and inv1 != inv0:
                    continue
                inv = inv0
            elif w + 1 < min(bad):
                inv = inv0
            elif w + 1 > max(bad) and inv1 is not None:
                inv = inv1
            else:
                continue
            a = sf.start_bit + w * WORD_BITS
            if a < 0 or a + WORD_BITS > len(hard):
                continue
            logic = hard[a:a + WORD_BITS] ^ inv
            idx.append(k_sf + w * WORD_BITS + np.arange(WORD_BITS))
            val.append(1 - 2 * logic.astype(np.int8))
    if not idx:
        return np.zeros(0, np.int64), np.zeros(0, np.int8)
    return np.concatenate(idx).astype(np.int64), np.concatenate(val)


def _stream_runs(log, per_bit):
    """Contiguous runs ``(soft bits, start epochs)`` of a channel's log of fed bits."""
    if not log:
        return []
    soft = np.concatenate([s for s, _ in log])
    ep = np.concatenate([e for _, e in log])
    cut = np.flatnonzero(np.diff(ep) != per_bit) + 1
    return [(s, e) for s, e in zip(np.split(soft, cut), np.split(ep, cut)) if len(s)]


def decoded_source(src, prns, ephs, week, tow_start_s, duration_s, pred0, cn0_dbhz=30.0, signal=GPS_L1CA):
    """The ``decoded-scalar`` bit source (``week``: of the IF start, unused: the decoded TOWs are
    placed relative to ``tow_start_s``): the scalar receiver over the same IF source ``src`` (first
    ``duration_s``), started on the hot-start predictions ``pred0`` (code phase, Doppler at sample 0;
    :func:`ultratight.receiver.deep.startup.predict_channels`), its navigation decoders' soft bits turned
    into known words (:func:`known_words`)."""
    from ultratight.receiver.scalar.receiver import ProcessConfig, ScalarReceiver   # the scalar receiver (heavy import)

    assist = [{"prn": int(p), "doppler_hz": float(pred0["doppler_hz"][i]),
               "code_phase_chips": float(pred0["code_phase_chips"][i]), "sample_index": 0,
               "cn0_dbhz": float(cn0_dbhz)} for i, p in enumerate(prns)]
    cfg = ProcessConfig(n_channels=len(prns), prns=[int(p) for p in prns], duration_s=float(duration_s),
                        smoothing_s=0.0)
    rx = ScalarReceiver(src, cfg, ephemerides={int(p): ephs[p] for p in prns}, signal=signal, log_nav_bits=True)
    rx.run(assist=assist)
    rows = BitRows(len(prns), tow_start_s, duration_s, BIT_DECODED, "decoded-scalar", signal)
    navs = {nav.prn: nav for nav in rx.navs}
    n_words = []
    for ch, prn in enumerate(prns):
        nav = navs.get(int(prn))
        n_k = 0
        for soft, _ep in _stream_runs(nav.log if nav is not None else [], signal.codes_per_bit):
            k, v = known_words(soft, tow_start_s, prn=int(prn))
            rows.put(ch, k, v)
            n_k += len(k)
        n_words.append(n_k // WORD_BITS)
    rows.info = {"scalar_pass": {"channels": [{k: c.get(k) for k in ("prn", "locked_fraction", "losses",
                                                                      "reacquisitions")}
                                              for c in rx.chinfo]},
                 "decoded_words": n_words, "known_fraction": rows.known_fraction()}
    return rows


def decoded_from_pass(wipe, prns, tow_start_s, duration_s, signal=GPS_L1CA):
    """The ``decoded`` bit source from a blind pass of the engine over the same file: ``wipe`` is that
    pass's :class:`ultratight.receiver.dsp.wipeoff.DataWipeoff`, whose ``soft`` columns (one per bit, the
    rows of a :class:`BitRows` of the same start and duration) hold the per-bit projection sums; the
    LNAV decoder reads them and the parity-checked words (:func:`known_words`, with the pass's own bit
    timing as a check) become known bits."""
    rows = BitRows(len(prns), tow_start_s, duration_s, BIT_DECODED, "decoded", signal)
    if wipe.soft.shape != rows.bits.shape or int(wipe.t0_ms[0]) != int(rows.t0_ms[0]):
        raise ConfigError("decoded bits: the decoding pass has another bit layout")
    n_words = []
    for ch, prn in enumerate(prns):
        s = wipe.soft[ch]
        nz = np.flatnonzero(s != 0.0)
        n_k = 0
        if nz.size:
            a, b = int(nz[0]), int(nz[-1]) + 1
            k, v = known_words(s[a:b], tow_start_s, prn=int(prn), bit_index0=rows.bit0 + a)
            rows.put(ch, k, v)
            n_k = len(k)
        n_words.append(n_k // WORD_BITS)
    rows.info = {"decoded_words": n_words, "known_fraction": rows.known_fraction()}
    return rows


def bit_source(strategy, path, *, src, ephs, prns, week, tow_start_s, duration_s, pred0, cn0_dbhz=30.0,
               signal=GPS_L1CA):
    """The bit source of a strategy (:func:`check_strategy`; ``decoded`` is built by the engine from a
    blind pass, :func:`decoded_from_pass`)."""
    if strategy == "assisted":
        return assisted_source(ephs, prns, week, tow_start_s, duration_s, signal)
    if strategy == "blind":
        return blind_source(len(prns), tow_start_s, duration_s, signal)
    if strategy == "file":
        return file_source(path, prns, week, tow_start_s, duration_s, signal)
    if strategy == "decoded-scalar":
        return decoded_source(src, prns, ephs, week, tow_start_s, duration_s, pred0, cn0_dbhz, signal)
    raise ConfigError(f"unknown bit strategy {strategy!r}")


__all__ = ["STRATEGIES", "check_strategy", "bit_source", "write_bits_csv", "read_bits_csv", "known_words",
           "BitRows"]
