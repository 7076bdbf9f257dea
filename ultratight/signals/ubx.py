"""u-blox binary logs (UBX): raw GPS measurements, broadcast ephemerides and the receiver's own fixes,
parsed with pyubx2.

* :func:`read_ubx` → :class:`UbxLog` with
  - ``raw``: :class:`RawEpochs` from UBX-RXM-RAWX, one row per GPS L1 C/A measurement (gnssId 0,
    sigId 0): time ``week·604800 + rcvTow`` (receiver clock, continuous GPS seconds), ``prMes`` where the
    tracking status says the pseudorange is valid (``prValid``), ``cpMes`` where the carrier phase is
    (``cpValid``; cycles as the receiver gives them, no half-cycle correction), ``doMes`` (Hz, positive
    while approaching, the RINEX sign) and ``cno`` (dB-Hz); with ``signals="auto"`` (default) the
    pseudoranges are the ionosphere-free combination described under "Signals";
  - ``pr2``: the same message's L2C (sigId 3 L2 CL, else 4 L2 CM) and L5 (sigId 7 L5 Q, else 6 L5 I)
    pseudoranges beside each L1 C/A row (NaN where absent; aligned with ``raw`` when ``signals="l1"``);
  - ``nav``: :class:`ultratight.signals.rinex.NavData`: the ephemerides decoded from UBX-RXM-SFRBX GPS
    L1 C/A subframes by :class:`ultratight.signals.lnav.LnavDecoder`, and for each satellite without a
    complete LNAV set the CNAV set of its L2 CM / L5 I messages (sigId 4 / 6,
    :class:`ultratight.signals.cnav.CnavDecoder`); Klobuchar coefficients from subframe 4 page 18, else
    from a CNAV type 30;
  - ``group_delays``: per PRN the T_GD and inter-signal corrections of its latest CNAV type 30; ``cnav``:
    the CNAV decoders;
  - ``nav_pvt``: the parsed UBX-NAV-PVT messages (pyubx2 objects, in file order).
* :func:`nav_pvt_messages` yields the NAV-PVT messages alone.

Signals.  When the log holds GPS L2C pseudoranges (else L5), ``signals="auto"`` replaces each L1 C/A
pseudorange by the ionosphere-free combination with that signal
(:func:`ultratight.signals.observations.iono_free_combination`) plus the satellite's group-delay term
``c (ISC_2 − γ ISC_L1C/A)/(1 − γ)``, ``γ = (f1/f2)²`` (IS-GPS-200 §30.3.3.3.1.1.2; ISC_L5Q5 of IS-GPS-705
for L5; zero without a type 30 of that satellite), so that the row takes the L1 C/A user's satellite
clock ``Δt_sv − T_GD`` like a single-frequency row.  Rows without the second pseudorange, or whose
satellite's CNAV type 10 marks that signal bad, are left out (``raw.meta["rows_single_frequency_dropped"]``):
a mix of single- and dual-frequency rows would put the receiver's own L1–L2 group delay into the
single-frequency ones.  ``raw.iono_free_f2_hz`` marks the combined rows, ``raw.pr_l1_m`` keeps their
measured L1 C/A pseudorange, ``raw.meta["signal"]`` names the pair; Doppler, C/N0 and carrier phase stay
L1's.  ``signals="l1"``: L1 C/A pseudoranges as measured.

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

from ultratight.constants import C
from ultratight.errors import InputFileError
from ultratight.signals.cnav import CnavDecoder, sfrbx_cnav_bits
from ultratight.signals.lnav import LnavDecoder
from ultratight.signals.lnav_message import SUBFRAME_WORDS, WORD_BITS
from ultratight.signals.observations import (
    F_L1_HZ,
    F_L2_HZ,
    F_L5_HZ,
    RawEpochs,
    gps_seconds,
    iono_free_combination,
)
from ultratight.signals.rinex import NavData

GPS_GNSS_ID = 0
L1CA_SIG_ID = 0
# RXM-RAWX GPS sigId -> (band, pilot code): L2 CL / CM, L5 Q / I (u-blox receiver description)
SECOND_SIGNALS = {3: ("L2C", True), 4: ("L2C", False), 7: ("L5", True), 6: ("L5", False)}
CNAV_SIG_IDS = (4, 6)                  # RXM-SFRBX GPS L2 CM and L5 I: CNAV messages
CNAV_WORDS = 10
BAND_FREQ_HZ = {"L2C": F_L2_HZ, "L5": F_L5_HZ}
ISC_KEY = {"L2C": "isc_l2c", "L5": "isc_l5q5"}
SIGNALS_CHOICES = ("auto", "l1")
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
    group_delays: dict = field(default_factory=dict)    # prn -> CNAV type 30 T_GD and ISCs (s)
    cnav: dict = field(default_factory=dict)            # prn -> CnavDecoder
    pr2: dict = field(default_factory=dict)             # "L2C"/"L5" -> (m,) beside the L1 C/A rows (module doc)


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
    """Flat rows of the RXM-RAWX epochs read so far: one per GPS L1 C/A measurement, with the same
    satellite's L2C and L5 pseudoranges of the same message beside it (NaN where absent)."""

    def __init__(self):
        self.t, self.start = [], [0]
        self.prn, self.pr, self.dop, self.cn0, self.ph = [], [], [], [], []
        self.pr2 = {"L2C": [], "L5": []}
        self.leap = None
        self.week = None

    def add(self, msg):
        t = float(gps_seconds(msg.week, msg.rcvTow))
        if self.t and t <= self.t[-1]:
            return                      # repeated or out-of-order epoch
        if self.week is None:
            self.week, self.leap = int(msg.week), int(msg.leapS)
        l1, other = [], {}
        for i in range(1, int(msg.numMeas) + 1):
            s = f"_{i:02d}"
            if getattr(msg, "gnssId" + s) != GPS_GNSS_ID:
                continue
            sig, sv = getattr(msg, "sigId" + s, 0), int(getattr(msg, "svId" + s))
            if sig == L1CA_SIG_ID:
                l1.append((sv, s))
            elif sig in SECOND_SIGNALS and getattr(msg, "prValid" + s):
                band, pilot = SECOND_SIGNALS[sig]
                if pilot or (sv, band) not in other:          # the pilot (dataless) code first
                    other[(sv, band)] = float(getattr(msg, "prMes" + s))
        for sv, s in l1:
            self.prn.append(sv)
            self.pr.append(float(getattr(msg, "prMes" + s)) if getattr(msg, "prValid" + s) else np.nan)
            self.ph.append(float(getattr(msg, "cpMes" + s)) if getattr(msg, "cpValid" + s) else np.nan)
            self.dop.append(float(getattr(msg, "doMes" + s)))
            self.cn0.append(float(getattr(msg, "cno" + s)))
            for band, lst in self.pr2.items():
                lst.append(other.get((sv, band), np.nan))
        self.t.append(t)
        self.start.append(len(self.prn))

    def epochs(self, path):
        return RawEpochs(t=np.asarray(self.t, dtype=float), start=np.asarray(self.start, dtype=np.int64),
                         prn=np.asarray(self.prn, dtype=np.int64), pr_m=np.asarray(self.pr, dtype=float),
                         doppler_hz=np.asarray(self.dop, dtype=float), cn0_dbhz=np.asarray(self.cn0, dtype=float),
                         phase_cyc=np.asarray(self.ph, dtype=float), source=str(path),
                         meta={"format": "ubx", "leap_seconds": self.leap, "signal": "GPS L1 C/A"})


class _SfrbxNav:
    """Per-PRN LNAV decoders fed with the RXM-SFRBX GPS L1 C/A subframes and CNAV decoders fed with the
    L2 CM / L5 I messages."""

    def __init__(self):
        self.decoders = {}
        self.cnav = {}
        self.ephs = {}
        self.iono = None
        self.iono_prn = None

    def add(self, msg, ref_week):
        if msg.gnssId != GPS_GNSS_ID:
            return
        sig = getattr(msg, "sigId", 0)
        if sig in CNAV_SIG_IDS and msg.numWords == CNAV_WORDS:
            prn = int(msg.svId)
            dec = self.cnav.get(prn)
            if dec is None:
                dec = self.cnav[prn] = CnavDecoder(prn, ref_week=ref_week)
            dec.feed(sfrbx_cnav_bits([getattr(msg, f"dwrd_{k:02d}") for k in range(1, CNAV_WORDS + 1)]))
            return
        if sig != L1CA_SIG_ID or msg.numWords != SUBFRAME_WORDS:
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

    def health(self):
        """prn -> the L1/L2/L5 health bits of the satellite's latest CNAV type 10."""
        out = {}
        for p, d in self.cnav.items():
            if d.mt10:
                f, _ = d.mt10[max(d.mt10)]
                out[p] = int(f["health"])
        return out

    def group_delays(self):
        """prn -> the T_GD and ISCs of the satellite's latest CNAV type 30 (seconds; None: not available)."""
        return {p: dict(d.group_delays) for p, d in self.cnav.items() if d.group_delays is not None}

    def nav_data(self, path):
        """NavData: the LNAV ephemerides; a CNAV set for each satellite without one; Klobuchar from
        subframe 4 page 18, else from a CNAV type 30."""
        ephs = {p: sorted(lst, key=lambda e: (e.week, e.toe)) for p, lst in self.ephs.items()}
        for p, dec in self.cnav.items():
            if p not in ephs and dec.ephemerides:
                ephs[p] = sorted(dec.ephemerides, key=lambda e: (e.week, e.toe))
        io = self.iono
        alpha = beta = None
        if io is not None:
            alpha, beta = tuple(io.alpha), tuple(io.beta)
        else:
            cn = [d.iono for _, d in sorted(self.cnav.items()) if d.iono is not None]
            if cn:
                alpha, beta = cn[0]
        return NavData(path=str(path), version=0.0, ephemerides=ephs, ion_alpha=alpha, ion_beta=beta,
                       utc=None if io is None else {"a0": io.a0, "a1": io.a1, "tot": io.tot, "wnt": io.wnt},
                       leap_seconds=None if io is None else io.dt_ls)

    def sources(self):
        """What the navigation data came from (the summary's lines)."""
        lnav = sorted(self.ephs)
        cnav = sorted(p for p, d in self.cnav.items() if p not in self.ephs and d.ephemerides)
        iono = ("LNAV subframe 4 page 18" if self.iono is not None else
                "CNAV type 30" if any(d.iono is not None for d in self.cnav.values()) else None)
        return {"lnav_ephemeris_prns": lnav, "cnav_ephemeris_prns": cnav, "klobuchar": iono,
                "cnav_messages": int(sum(d.accepted for d in self.cnav.values())),
                "cnav_rejected": int(sum(d.rejected for d in self.cnav.values()))}


def iono_free_rows(raw, pr2, group_delays, health):
    """A copy of ``raw`` (L1 C/A rows) with ionosphere-free pseudoranges (module doc, "Signals")."""
    band = next((b for b in ("L2C", "L5") if np.isfinite(pr2[b]).any()), None)
    if band is None:
        return raw
    f2 = BAND_FREQ_HZ[band]
    g = (F_L1_HZ / f2) ** 2
    p2 = np.asarray(pr2[band], dtype=float)
    isc1 = np.array([(group_delays.get(int(p)) or {}).get("isc_l1ca") or 0.0 for p in raw.prn])
    isc2 = np.array([(group_delays.get(int(p)) or {}).get(ISC_KEY[band]) or 0.0 for p in raw.prn])
    bit = 1 if band == "L2C" else 0                     # type 10 health bits L1, L2, L5
    bad = np.array([bool((health.get(int(p), 0) >> bit) & 1) for p in raw.prn], dtype=bool)
    pr = iono_free_combination(raw.pr_m, p2, f2) + C * (isc2 - g * isc1) / (1.0 - g)
    keep = np.isfinite(pr) & ~bad
    k_of = np.repeat(np.arange(raw.n_epochs), np.diff(raw.start))
    start = np.concatenate([[0], np.cumsum(np.bincount(k_of[keep], minlength=raw.n_epochs))]).astype(np.int64)
    with_isc = sorted(int(p) for p in np.unique(raw.prn) if int(p) in group_delays)
    meta = {**raw.meta, "signal": f"GPS L1 C/A + {band} ionosphere-free",
            "iono_free_pair": band, "rows_single_frequency_dropped": int((~keep).sum()),
            "inter_signal_corrections": {"from": "CNAV type 30", "prns": with_isc}}
    return RawEpochs(t=raw.t.copy(), start=start, prn=raw.prn[keep], pr_m=pr[keep], doppler_hz=raw.doppler_hz[keep],
                     cn0_dbhz=raw.cn0_dbhz[keep], phase_cyc=raw.phase_cyc[keep], source=raw.source, meta=meta,
                     iono_free_f2_hz=np.full(int(keep.sum()), f2), pr_l1_m=raw.pr_m[keep].copy())


def read_ubx(path, signals="auto"):
    """RXM-RAWX, RXM-SFRBX and NAV-PVT of a u-blox log (module doc); returns :class:`UbxLog`.
    ``signals``: "auto" (the ionosphere-free combination when the log has GPS L2C or L5
    pseudoranges) or "l1" (L1 C/A pseudoranges as measured)."""
    if signals not in SIGNALS_CHOICES:
        raise ValueError(f"signals must be one of {', '.join(SIGNALS_CHOICES)}, got {signals!r}")
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
    raw, nd = rows.epochs(path), nav.nav_data(path)
    raw.meta["navigation"] = nav.sources()
    pr2 = {b: np.asarray(v, dtype=float) for b, v in rows.pr2.items()}
    raw.meta["second_frequency_rows"] = {b: int(np.isfinite(v).sum()) for b, v in pr2.items()}
    if signals == "auto":
        raw = iono_free_rows(raw, pr2, nav.group_delays(), nav.health())
    return UbxLog(str(path), raw, nd, pvt, counts, subframes, nav.group_delays(), nav.cnav, pr2)
