"""GPS CNAV messages (L2C on L2 CM, L5 on L5 I): CRC-24Q check, ephemeris (message types 10 and 11),
clock (types 30-37), group delays and Klobuchar coefficients (type 30), per IS-GPS-200 §30.3 and
IS-GPS-705 (the L5 inter-signal corrections of type 30).

A message is 300 bits, most significant first: 8-bit preamble 10001011, 6-bit PRN, 6-bit type,
17-bit TOW count (×6 s: the satellite time at the start of the *next* message), alert flag, the
type's fields, and 24 CRC-24Q parity bits over the first 276 (§30.3.5: generator
``g(X) = 1 + X + X³ + X⁴ + X⁵ + X⁶ + X⁷ + X¹⁰ + X¹¹ + X¹⁴ + X¹⁷ + X¹⁸ + X²³ + X²⁴``, seed 0; the CRC of
all 300 bits of a good message is 0).  :func:`parse_message` refuses a bad preamble or CRC.

Fields (first bit numbered 1, scale factor of the last bit, ``*`` two's complement):

* type 10 (Figure 30-1, Table 30-I): WN 39/13, L1/L2/L5 health 52/3, t_op 55/11 ×300, URA_oe 66/5*,
  t_oe 71/11 ×300, ΔA 82/26* 2⁻⁹ m (from A_REF = 26 559 710 m), Ȧ 108/25* 2⁻²¹ m/s,
  Δn₀ 133/17* 2⁻⁴⁴ sc/s, Δṅ₀ 150/23* 2⁻⁵⁷ sc/s², M₀ 173/33* 2⁻³² sc, e 206/33 2⁻³⁴, ω 239/33* 2⁻³² sc;
* type 11 (Figure 30-2): t_oe 39/11 ×300, Ω₀ 50/33* 2⁻³² sc, i₀ 83/33* 2⁻³² sc,
  ΔΩ̇ 116/17* 2⁻⁴⁴ sc/s (from Ω̇_REF = −2.6e-9 sc/s), i̇ 133/15* 2⁻⁴⁴ sc/s, C_is 148/16* 2⁻³⁰,
  C_ic 164/16* 2⁻³⁰, C_rs 180/24* 2⁻⁸ m, C_rc 204/24* 2⁻⁸ m, C_us 228/21* 2⁻³⁰, C_uc 249/21* 2⁻³⁰;
* types 30-37 (Figure 30-3, Table 30-III): t_op 39/11 ×300, URA_oc 50/5*, URA_oc1 55/3, URA_oc2 58/3,
  t_oc 61/11 ×300, a_f0 72/26* 2⁻³⁵ s, a_f1 98/20* 2⁻⁴⁸, a_f2 118/10* 2⁻⁶⁰;
* type 30 also (Table 30-IV, Table 20-X): T_GD 128/13*, ISC_L1C/A 141/13*, ISC_L2C 154/13*,
  ISC_L5I5 167/13*, ISC_L5Q5 180/13* (all 2⁻³⁵ s; 1000000000000 = not available), α₀…α₃ 193/8* 2⁻³⁰,
  2⁻²⁷, 2⁻²⁴, 2⁻²⁴ and β₀…β₃ 225/8* 2¹¹, 2¹⁴, 2¹⁶, 2¹⁶ (the LNAV Klobuchar units).

:class:`CnavDecoder` (one per satellite) keeps the latest of each; :attr:`CnavDecoder.ephemerides` pairs
a type 10 and a type 11 of the same t_oe with a clock message of t_oc = t_oe into a
:class:`CnavEphemeris`.  Its :meth:`CnavEphemeris.state` evaluates Table 30-II (semi-major axis
``A_k = A₀ + Ȧ t_k``, mean motion ``n₀ + Δn₀ + ½ Δṅ₀ t_k``, node rate ``Ω̇_REF + ΔΩ̇``) and the clock of
§20.3.3.3.3.1 for the L1 C/A user, ``a_f0 + a_f1 dt + a_f2 dt² + F e √A_k sin E_k − T_GD`` (the same
convention as :func:`ultratight.signals.ephemeris.sat_state`); velocity and clock drift are central
differences over ±0.5 s (the truncation error is below 1e-5 m/s for a GPS orbit).  Its fit interval
is 3 h (§30.3.3.1.1).

Week: type 10 carries the 13-bit week of the start of the data set's transmission; t_oe may lie in the
next week, so the ephemeris week is the one that puts t_oe nearest the message's own transmission time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ultratight.constants import F_REL, GM, OMEGA_E

MESSAGE_BITS = 300
CRC_BITS = 24
PREAMBLE = 0b10001011
CRC24Q_POLY = 0x1864CFB              # g(X) of §30.3.5.1 with the X^24 term
GPS_PI = 3.1415926535898
A_REF_M = 26559710.0
OMEGA_DOT_REF_SC = -2.6e-9           # semicircles/s
FIT_INTERVAL_H = 3.0
GROUP_DELAY_NA = -(1 << 12)          # the 13-bit pattern 1000000000000 as a two's complement value
VEL_STEP_S = 0.5
KEPLER_ITER = 12
SECONDS_PER_WEEK = 604800.0
HALF_WEEK = 302400.0

# (name, first bit, length, signed, scale)
MT10_FIELDS = (("wn", 39, 13, False, 1.0), ("health", 52, 3, False, 1.0), ("top", 55, 11, False, 300.0),
               ("ura_oe", 66, 5, True, 1.0), ("toe", 71, 11, False, 300.0), ("delta_a", 82, 26, True, 2.0 ** -9),
               ("a_dot", 108, 25, True, 2.0 ** -21), ("delta_n0", 133, 17, True, 2.0 ** -44 * GPS_PI),
               ("delta_n0_dot", 150, 23, True, 2.0 ** -57 * GPS_PI), ("m0", 173, 33, True, 2.0 ** -32 * GPS_PI),
               ("e", 206, 33, False, 2.0 ** -34), ("omega", 239, 33, True, 2.0 ** -32 * GPS_PI))
MT11_FIELDS = (("toe", 39, 11, False, 300.0), ("omega0", 50, 33, True, 2.0 ** -32 * GPS_PI),
               ("i0", 83, 33, True, 2.0 ** -32 * GPS_PI), ("delta_omega_dot", 116, 17, True, 2.0 ** -44 * GPS_PI),
               ("idot", 133, 15, True, 2.0 ** -44 * GPS_PI), ("cis", 148, 16, True, 2.0 ** -30),
               ("cic", 164, 16, True, 2.0 ** -30), ("crs", 180, 24, True, 2.0 ** -8), ("crc", 204, 24, True, 2.0 ** -8),
               ("cus", 228, 21, True, 2.0 ** -30), ("cuc", 249, 21, True, 2.0 ** -30))
CLOCK_FIELDS = (("top", 39, 11, False, 300.0), ("ura_oc", 50, 5, True, 1.0), ("ura_oc1", 55, 3, False, 1.0),
                ("ura_oc2", 58, 3, False, 1.0), ("toc", 61, 11, False, 300.0), ("af0", 72, 26, True, 2.0 ** -35),
                ("af1", 98, 20, True, 2.0 ** -48), ("af2", 118, 10, True, 2.0 ** -60))
GROUP_DELAY_FIELDS = (("tgd", 128), ("isc_l1ca", 141), ("isc_l2c", 154), ("isc_l5i5", 167), ("isc_l5q5", 180))
KLOBUCHAR_FIELDS = (("alpha", 193, (-30, -27, -24, -24)), ("beta", 225, (11, 14, 16, 16)))
CLOCK_TYPES = range(30, 38)


def crc24q(bits):
    """CRC-24Q (§30.3.5.1) of a 0/1 sequence: the remainder of m(X)·X²⁴ divided by g(X), as an int whose
    most significant of 24 bits is p1."""
    r = 0
    for b in bits:
        r = (r << 1) | (int(b) & 1)
        if r & (1 << CRC_BITS):
            r ^= CRC24Q_POLY
    for _ in range(CRC_BITS):
        r <<= 1
        if r & (1 << CRC_BITS):
            r ^= CRC24Q_POLY
    return r


def field_value(bits, first, length, signed=False):
    """Integer of ``length`` bits from bit number ``first`` (1-based, most significant first)."""
    v = 0
    for b in bits[first - 1:first - 1 + length]:
        v = (v << 1) | (int(b) & 1)
    if signed and v >> (length - 1):
        v -= 1 << length
    return v


def sfrbx_cnav_bits(dwrd):
    """The 300 message bits of one u-blox RXM-SFRBX GPS CNAV message (ten 32-bit words, most significant
    bit first; the tenth word holds the last 12 bits in its 12 most significant bits)."""
    if len(dwrd) != 10:
        raise ValueError(f"a GPS CNAV message has 10 words, got {len(dwrd)}")
    bits = np.empty(MESSAGE_BITS, dtype=np.uint8)
    for k, w in enumerate(dwrd):
        n = 32 if k < 9 else MESSAGE_BITS - 9 * 32
        for j in range(n):
            bits[32 * k + j] = (int(w) >> (31 - j)) & 1
    return bits


@dataclass
class CnavMessage:
    prn: int
    msg_type: int
    tow_s: float                 # satellite time at the start of the next message, s of week
    alert: int
    fields: dict


class CnavError(ValueError):
    """A CNAV message that fails its preamble, length or CRC check."""


def parse_message(bits):
    """:class:`CnavMessage` of 300 bits (module doc); :class:`CnavError` on a bad length, preamble or CRC."""
    bits = np.asarray(bits, dtype=np.uint8).reshape(-1)
    if bits.size != MESSAGE_BITS:
        raise CnavError(f"a CNAV message has {MESSAGE_BITS} bits, got {bits.size}")
    if field_value(bits, 1, 8) != PREAMBLE:
        raise CnavError("CNAV preamble is not 10001011")
    if crc24q(bits[:MESSAGE_BITS - CRC_BITS]) != field_value(bits, MESSAGE_BITS - CRC_BITS + 1, CRC_BITS):
        raise CnavError("CNAV CRC-24Q check failed")
    mt = field_value(bits, 15, 6)
    out = {}
    table = MT10_FIELDS if mt == 10 else MT11_FIELDS if mt == 11 else CLOCK_FIELDS if mt in CLOCK_TYPES else ()
    for name, first, n, signed, scale in table:
        out[name] = field_value(bits, first, n, signed) * scale
    if mt == 30:
        for name, first in GROUP_DELAY_FIELDS:
            v = field_value(bits, first, 13, True)
            out[name] = None if v == GROUP_DELAY_NA else v * 2.0 ** -35
        for name, first, exps in KLOBUCHAR_FIELDS:
            out[name] = tuple(field_value(bits, first + 8 * j, 8, True) * 2.0 ** e for j, e in enumerate(exps))
    return CnavMessage(prn=field_value(bits, 9, 6), msg_type=mt, tow_s=field_value(bits, 21, 17) * 6.0,
                       alert=int(bits[37]), fields=out)


def _wrap(dt):
    return np.where(dt > HALF_WEEK, dt - SECONDS_PER_WEEK, np.where(dt < -HALF_WEEK, dt + SECONDS_PER_WEEK, dt))


@dataclass
class CnavEphemeris:
    """A CNAV ephemeris + clock set (module doc); angles in radians, times in seconds of ``week``.
    Duck-types the fields :func:`ultratight.signals.obs_geometry.select_rows` reads (``week``, ``toe``,
    ``fit_interval_h``, ``healthy``, ``iode``)."""
    prn: int
    week: int
    toe: float
    toc: float
    delta_a: float
    a_dot: float
    delta_n0: float
    delta_n0_dot: float
    m0: float
    e: float
    omega: float
    omega0: float
    i0: float
    delta_omega_dot: float
    idot: float
    cis: float
    cic: float
    crs: float
    crc: float
    cus: float
    cuc: float
    af0: float
    af1: float
    af2: float
    tgd: float = 0.0
    isc: dict = field(default_factory=dict)      # isc_l1ca, isc_l2c, isc_l5i5, isc_l5q5 (s) when broadcast
    health: int = 0                             # bits L1, L2, L5 (most significant first); 0 = signal OK
    ura_oe: int = 0
    fit_interval_h: float = FIT_INTERVAL_H
    iode: int = -1                              # CNAV has no IODE
    source: str = "CNAV"

    @property
    def healthy(self):
        """The L1 signal is OK (the L1 C/A user's test; :meth:`signal_ok` for the others)."""
        return self.signal_ok("L1")

    def signal_ok(self, band):
        """Health bit of ``band`` ("L1", "L2" or "L5") of type 10 (§30.3.3.1.1.2) is 0."""
        return not (self.health >> {"L1": 2, "L2": 1, "L5": 0}[band]) & 1

    def _position(self, t):
        """(pos (n, 3), sin E, A_k) at GPS times ``t`` (seconds of ``week``)."""
        tk = _wrap(np.asarray(t, dtype=float) - self.toe)
        a0 = A_REF_M + self.delta_a
        ak = a0 + self.a_dot * tk
        n = math.sqrt(GM / a0 ** 3) + self.delta_n0 + 0.5 * self.delta_n0_dot * tk
        mk = self.m0 + n * tk
        ek = mk.copy()
        for _ in range(KEPLER_ITER):
            ek = ek - (ek - self.e * np.sin(ek) - mk) / (1.0 - self.e * np.cos(ek))
        nu = np.arctan2(math.sqrt(1.0 - self.e ** 2) * np.sin(ek), np.cos(ek) - self.e)
        phi = nu + self.omega
        s2, c2 = np.sin(2.0 * phi), np.cos(2.0 * phi)
        u = phi + self.cus * s2 + self.cuc * c2
        r = ak * (1.0 - self.e * np.cos(ek)) + self.crs * s2 + self.crc * c2
        inc = self.i0 + self.idot * tk + self.cis * s2 + self.cic * c2
        om = self.omega0 + (OMEGA_DOT_REF_SC * GPS_PI + self.delta_omega_dot - OMEGA_E) * tk - OMEGA_E * self.toe
        xp, yp = r * np.cos(u), r * np.sin(u)
        pos = np.stack([xp * np.cos(om) - yp * np.cos(inc) * np.sin(om),
                        xp * np.sin(om) + yp * np.cos(inc) * np.cos(om), yp * np.sin(inc)], axis=-1)
        return pos, np.sin(ek), ak

    def _clock(self, t, sin_e, ak):
        dt = _wrap(np.asarray(t, dtype=float) - self.toc)
        return (self.af0 + dt * (self.af1 + dt * self.af2) + F_REL * self.e * np.sqrt(ak) * sin_e - self.tgd)

    def state(self, t):
        """(pos (n, 3) m, vel (n, 3) m/s, clock (n,) s, clock drift (n,) s/s) at GPS times ``t`` (seconds of
        ``week``, an array): ECEF at ``t``, the L1 C/A user's clock correction (module doc)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        pos, se, ak = self._position(t)
        p1, s1, a1 = self._position(t + VEL_STEP_S)
        p0, s0, a0 = self._position(t - VEL_STEP_S)
        vel = (p1 - p0) / (2.0 * VEL_STEP_S)
        clk = self._clock(t, se, ak)
        drift = (self._clock(t + VEL_STEP_S, s1, a1) - self._clock(t - VEL_STEP_S, s0, a0)) / (2.0 * VEL_STEP_S)
        return pos, vel, clk, drift


def _week_of(toe, tx_week, tx_tow):
    """The week number that puts ``toe`` nearest the transmission time (tx_week, tx_tow)."""
    dt = toe - tx_tow
    return tx_week + (1 if dt < -HALF_WEEK else -1 if dt > HALF_WEEK else 0)


class CnavDecoder:
    """CNAV messages of one satellite (module doc).  ``ref_week``: the full GPS week of the log (resolves
    the 13-bit week of type 10; None keeps it modulo 8192).  ``feed(bits)`` returns the parsed
    :class:`CnavMessage` or None (counted in ``rejected``)."""

    def __init__(self, prn, ref_week=None):
        self.prn = int(prn)
        self.ref_week = ref_week
        self.mt10 = {}          # toe -> (fields, week)
        self.mt11 = {}          # toe -> fields
        self.clocks = {}        # toc -> fields
        self.group_delays = None
        self.iono = None        # (alpha, beta) of the latest type 30
        self.accepted = 0
        self.rejected = 0
        self.types = {}

    def feed(self, bits):
        try:
            msg = parse_message(bits)
        except CnavError:
            self.rejected += 1
            return None
        if msg.prn != self.prn:
            self.rejected += 1
            return None
        self.accepted += 1
        self.types[msg.msg_type] = self.types.get(msg.msg_type, 0) + 1
        f = msg.fields
        if msg.msg_type == 10:
            wn = int(f["wn"])
            if self.ref_week is not None:
                wn = self.ref_week - ((self.ref_week - wn) % 8192)
            self.mt10[f["toe"]] = (f, _week_of(f["toe"], wn, msg.tow_s))
        elif msg.msg_type == 11:
            self.mt11[f["toe"]] = f
        elif msg.msg_type in CLOCK_TYPES:
            self.clocks[f["toc"]] = f
            if msg.msg_type == 30:
                self.group_delays = {k: f[k] for k, _ in GROUP_DELAY_FIELDS}
                self.iono = (f["alpha"], f["beta"])
        return msg

    @property
    def ephemerides(self):
        """:class:`CnavEphemeris` of every t_oe with a type 10, a type 11 and a clock of t_oc = t_oe."""
        out = []
        gd = self.group_delays or {}
        for toe in sorted(self.mt10):
            if toe not in self.mt11 or toe not in self.clocks:
                continue
            f10, week = self.mt10[toe]
            f11, clk = self.mt11[toe], self.clocks[toe]
            kw = {k: f10[k] for k in ("delta_a", "a_dot", "delta_n0", "delta_n0_dot", "m0", "e", "omega")}
            kw.update({k: f11[k] for k in ("omega0", "i0", "delta_omega_dot", "idot", "cis", "cic", "crs", "crc",
                                           "cus", "cuc")})
            kw.update({k: clk[k] for k in ("af0", "af1", "af2")})
            out.append(CnavEphemeris(prn=self.prn, week=week, toe=toe, toc=clk["toc"], tgd=gd.get("tgd") or 0.0,
                                     isc={k: v for k, v in gd.items() if k != "tgd" and v is not None},
                                     health=int(f10["health"]), ura_oe=int(f10["ura_oe"]), **kw))
        return out
