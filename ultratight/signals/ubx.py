"""u-blox binary logs (UBX): raw GPS L1 C/A measurements, broadcast ephemerides and the receiver's
own fixes, parsed with pyubx2.

* :func:`read_ubx` → :class:`UbxLog` with
  - ``raw``: :class:`RawEpochs` from UBX-RXM-RAWX, GPS L1 C/A only (gnssId 0, sigId 0): time
    ``week·604800 + rcvTow`` (receiver clock, continuous GPS seconds), ``prMes`` where the tracking
    status says the pseudorange is valid (``prValid``), ``cpMes`` where the carrier phase is
    (``cpValid``; cycles as the receiver gives them, no half-cycle correction), ``doMes`` (Hz,
    positive while approaching, the RINEX sign) and ``cno`` (dB-Hz);
  - ``nav``: :class:`ultratight.signals.rinex.NavData` of the ephemerides and Klobuchar coefficients
    decoded from UBX-RXM-SFRBX GPS L1 C/A subframes by :class:`ultratight.signals.lnav.LnavDecoder`;
  - ``nav_pvt``: the parsed UBX-NAV-PVT messages (pyubx2 objects, in file order).
* :func:`nav_pvt_messages` yields the NAV-PVT messages alone.

RXM-SFRBX words (u-blox receiver description, "Broadcast navigation data", GPS L1 C/A): ten 32-bit
words per subframe, each holding one 30-bit LNAV word in bits 29..0 (D1 in bit 29; bits 31..30 are
not navigation data).  The receiver hands on the 24 data bits of a word already re-complemented
(source bits) when the previous word's D30 was 1, and the whole 30-bit word with them (parity bits
included).  :func:`sfrbx_transmitted_bits` undoes that (the previous transmitted D30* decides, and
word 1 follows a word 10 whose last two bits are 0 by design, IS-GPS-200 §20.3.5.2), so the bits fed
to the decoder are the ones the satellite sent and the decoder's parity check (Table 20-XIV) applies
unchanged.  Subframes of one satellite are fed in file order, each as one aligned 300-bit block.

Anything that is not a UBX log (no UBX message at all) raises one
:class:`ultratight.errors.InputFileError` line; checksum errors in a UBX log are counted in
``UbxLog.counts["checksum_errors"]`` and skipped.
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ultratight.errors import InputFileError
from ultratight.signals.lnav import LnavDecoder
from ultratight.signals.lnav_message import SUBFRAME_WORDS, WORD_BITS
from ultratight.signals.observations import RawEpochs, gps_seconds
from ultratight.signals.rinex import NavData

GPS_GNSS_ID = 0
L1CA_SIG_ID = 0
WORD_MASK = (1 << WORD_BITS) - 1
UBX_SYNC = b"\xb5\x62"
MAX_CONSECUTIVE_FAILURES = 1000


@dataclass
class UbxLog:
    """What :func:`read_ubx` reads (module doc)."""
    path: str
    raw: RawEpochs
    nav: NavData
    nav_pvt: list = field(default_factory=list)
    counts: dict = field(default_factory=dict)          # messages per identity, checksum errors
    subframes: dict = field(default_factory=dict)       # prn -> list of DecodedSubframe


def sfrbx_transmitted_bits(dwrd):
    """300 transmitted LNAV bits (uint8, D1 of word 1 first) of one RXM-SFRBX GPS L1 C/A subframe
    given as its ten 32-bit words (module doc)."""
    if len(dwrd) != SUBFRAME_WORDS:
        raise ValueError(f"a GPS L1 C/A subframe has {SUBFRAME_WORDS} words, got {len(dwrd)}")
    bits = np.empty(SUBFRAME_WORDS * WORD_BITS, dtype=np.uint8)
    d30s = 0
    for k, w in enumerate(dwrd):
        w30 = (int(w) & WORD_MASK) ^ (WORD_MASK if d30s else 0)
        for j in range(WORD_BITS):
            bits[k * WORD_BITS + j] = (w30 >> (WORD_BITS - 1 - j)) & 1
        d30s = w30 & 1
    return bits


def _messages(path, counts):
    """(identity, message) of every UBX message with a good checksum; counts per identity."""
    from pyubx2 import UBXReader
    from pyubx2.ubxtypes_core import ERR_LOG, UBX_PROTOCOL, VALCKSUM
    try:
        fh = open(path, "rb")     # noqa: SIM115 - closed by the with block below (a generator)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read u-blox file: {exc.strerror or exc}") from None
    with fh:
        def damaged(_exc):
            counts["checksum_errors"] = counts.get("checksum_errors", 0) + 1

        rdr = UBXReader(fh, protfilter=UBX_PROTOCOL, validate=VALCKSUM, quitonerror=ERR_LOG, errorhandler=damaged)
        failures = 0
        while True:
            try:
                raw, msg = rdr.read()
                failures = 0
            except Exception as exc:        # noqa: BLE001 - pyubx2 parse errors: a damaged message, skipped
                counts["checksum_errors"] = counts.get("checksum_errors", 0) + 1
                failures += 1
                if failures > MAX_CONSECUTIVE_FAILURES:
                    raise InputFileError(f"{path}: unreadable u-blox log at byte {fh.tell()}: "
                                         f"{' '.join(str(exc).split())[:200]}") from None
                continue
            if raw is None:
                return
            if msg is None:
                counts["checksum_errors"] = counts.get("checksum_errors", 0) + 1
                continue
            ident = getattr(msg, "identity", "?")
            counts[ident] = counts.get(ident, 0) + 1
            yield ident, msg


def nav_pvt_messages(path):
    """The parsed UBX-NAV-PVT messages of a u-blox log, in file order (pyubx2 objects: ``iTOW``,
    ``lat``, ``lon``, ``height``, ``velN`` ... with pyubx2's scaling)."""
    _check_ubx(path)
    for ident, msg in _messages(path, {}):
        if ident == "NAV-PVT":
            yield msg


def _check_ubx(path):
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read u-blox file: {exc.strerror or exc}") from None
    if UBX_SYNC not in head:
        raise InputFileError(f"{path}: not a u-blox UBX log (no UBX sync characters 0xB5 0x62 in its first "
                             f"{len(head)} bytes)")


class _RawxRows:
    """Flat rows of the RXM-RAWX epochs read so far."""

    def __init__(self):
        self.t, self.start = [], [0]
        self.prn, self.pr, self.dop, self.cn0, self.ph = [], [], [], [], []
        self.leap = None
        self.week = None

    def add(self, msg):
        t = float(gps_seconds(msg.week, msg.rcvTow))
        if self.t and t <= self.t[-1]:
            return                      # repeated or out-of-order epoch
        if self.week is None:
            self.week, self.leap = int(msg.week), int(msg.leapS)
        for i in range(1, int(msg.numMeas) + 1):
            s = f"_{i:02d}"
            if getattr(msg, "gnssId" + s) != GPS_GNSS_ID or getattr(msg, "sigId" + s, 0) != L1CA_SIG_ID:
                continue
            self.prn.append(int(getattr(msg, "svId" + s)))
            self.pr.append(float(getattr(msg, "prMes" + s)) if getattr(msg, "prValid" + s) else np.nan)
            self.ph.append(float(getattr(msg, "cpMes" + s)) if getattr(msg, "cpValid" + s) else np.nan)
            self.dop.append(float(getattr(msg, "doMes" + s)))
            self.cn0.append(float(getattr(msg, "cno" + s)))
        self.t.append(t)
        self.start.append(len(self.prn))

    def epochs(self, path):
        return RawEpochs(t=np.asarray(self.t, dtype=float), start=np.asarray(self.start, dtype=np.int64),
                         prn=np.asarray(self.prn, dtype=np.int64), pr_m=np.asarray(self.pr, dtype=float),
                         doppler_hz=np.asarray(self.dop, dtype=float), cn0_dbhz=np.asarray(self.cn0, dtype=float),
                         phase_cyc=np.asarray(self.ph, dtype=float), source=str(path),
                         meta={"format": "ubx", "leap_seconds": self.leap, "signal": "GPS L1 C/A"})


class _SfrbxNav:
    """Per-PRN LNAV decoders fed with the RXM-SFRBX GPS L1 C/A subframes."""

    def __init__(self):
        self.decoders = {}
        self.ephs = {}
        self.iono = None
        self.iono_prn = None

    def add(self, msg, ref_week):
        if msg.gnssId != GPS_GNSS_ID or getattr(msg, "sigId", 0) != L1CA_SIG_ID or msg.numWords != SUBFRAME_WORDS:
            return
        prn = int(msg.svId)
        dec = self.decoders.get(prn)
        if dec is None:
            dec = self.decoders[prn] = LnavDecoder(prn=prn, ref_week=ref_week)
        dec.feed(sfrbx_transmitted_bits([getattr(msg, f"dwrd_{k:02d}") for k in range(1, SUBFRAME_WORDS + 1)]))
        eph = dec.ephemeris
        if eph is not None:
            lst = self.ephs.setdefault(prn, [])
            if not any(e.iode == eph.iode and e.toe == eph.toe and e.week == eph.week for e in lst):
                lst.append(eph.copy(tx_tow=dec.ephemeris_tx_tow))
        if dec.iono is not None and self.iono is None:
            self.iono, self.iono_prn = dec.iono, prn

    def nav_data(self, path):
        ephs = {p: sorted(lst, key=lambda e: (e.week, e.toe)) for p, lst in self.ephs.items()}
        io = self.iono
        return NavData(path=str(path), version=0.0, ephemerides=ephs,
                       ion_alpha=None if io is None else tuple(io.alpha),
                       ion_beta=None if io is None else tuple(io.beta),
                       utc=None if io is None else {"a0": io.a0, "a1": io.a1, "tot": io.tot, "wnt": io.wnt},
                       leap_seconds=None if io is None else io.dt_ls)


def read_ubx(path):
    """RXM-RAWX, RXM-SFRBX and NAV-PVT of a u-blox log (module doc); returns :class:`UbxLog`."""
    _check_ubx(path)
    counts = {}
    rows, nav, pvt = _RawxRows(), _SfrbxNav(), []
    pending = []                        # SFRBX before the first RAWX (the week is not known yet)
    for ident, msg in _messages(path, counts):
        if ident == "RXM-RAWX":
            rows.add(msg)
            for m in pending:
                nav.add(m, rows.week)
            pending = []
        elif ident == "RXM-SFRBX":
            if rows.week is None:
                pending.append(msg)
            else:
                nav.add(msg, rows.week)
        elif ident == "NAV-PVT":
            pvt.append(msg)
    for m in pending:
        nav.add(m, None)
    if not counts or set(counts) == {"checksum_errors"}:
        raise InputFileError(f"{path}: not a u-blox UBX log (no UBX message with a valid checksum)")
    subframes = {p: list(d.subframes) for p, d in nav.decoders.items()}
    return UbxLog(str(path), rows.epochs(path), nav.nav_data(path), pvt, counts, subframes)
