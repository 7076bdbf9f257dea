"""Compiled building blocks of the scalar tracking loops: discriminators, loop filters, and the
one-pass prompt / early-minus-late integration with its half-chip code tables.

The block kernel (:mod:`ultratight.receiver.dsp.tracking_block`) calls them once per code period
(discriminators and filters once per complete coherent sum).

Loops (standard discrete forms, Kaplan & Hegarty "Understanding GPS", ch. 5, with
trapezoidal integrators; ``w0`` natural frequency in rad/s, phase in cycles, frequency in Hz):

* Costas discriminator ``e_p = atan(Q_P / I_P) / 2pi`` (cycles, data-bit insensitive).
* FLL cross/dot discriminator between consecutive coherent sums
  ``e_f = atan(cross / dot) / (2 pi T)`` (Hz, two-quadrant: data-bit insensitive).
* PLL order 2 with 1st-order FLL assist:
  ``x += T (w0p^2 e_p + w0f e_f)``; ``f = x + a2 w0p e_p``;  ``w0p = Bn/0.53``, ``w0f = 4 Bn_f``.
* PLL order 3 with 2nd-order FLL assist:
  ``y += T (w0p^3 e_p + w0f^2 e_f)``; ``x += T (y + a3 w0p^2 e_p + a2 w0f e_f)``;
  ``f = x + b3 w0p e_p``;  ``w0p = Bn/0.7845``, ``w0f = Bn_f/0.53``, a2 = sqrt 2, a3 = 1.1, b3 = 2.4.
* DLL: normalised early-minus-late envelope ``dtau = (1 - D/2)(|E| - |L|)/(|E| + |L|)`` (chips,
  input minus replica; exact inside the linear range for a triangle correlation), carrier aided:
  ``code_rate = f_chip (1 + f/f_carrier) + u`` with ``u = 4 Bn dtau`` (order 1) or
  ``z += T w0^2 dtau``; ``u = z + a2 w0 dtau`` (order 2).

The per-sample correlation (:func:`integrate_pel`: prompt and early-minus-late in one pass) is the
hot path: vectorised over 64-bit code windows (:func:`_pel_block`, as
``correlator.integrate_channel``), with :func:`_integrate_pel` on the half-chip tables where a chip
table is not all +-1.
"""

import math

import numpy as np
from numba import njit

from ultratight.receiver.dsp.chipbits import chip_at, code_window
from ultratight.receiver.dsp.correlator import _tap_shift, _window_block
from ultratight.signals.signal import GPS_L1CA

A2, A3, B3 = math.sqrt(2.0), 1.1, 2.4

# The scalar tracking's carrier table: 2**TRK_LUT_BITS float32 cos/sin entries at bin centres, indexed
# by the top bits of the 32-bit carrier phase (as the correlator's, which has 2**14). 2048 entries
# (the generator's size) fit the L1 data cache with their interleaved copy; the correlator's 16384
# do not, and the look-ups then waited on the L2: the prompt / E-L pass went from 0.49 to 0.86 G
# samples/s on one core (AMD EPYC Zen 3, 2.6 MHz complex). The phase quantisation is uniform
# within +-pi/2048 (+-0.09 deg): a correlation loss below 1e-6 dB.
TRK_LUT_BITS = 11
TRK_LUT_SIZE = 1 << TRK_LUT_BITS
_TRK_ANG = 2.0 * np.pi * (np.arange(TRK_LUT_SIZE) + 0.5) / TRK_LUT_SIZE
TRK_COS_LUT = np.cos(_TRK_ANG).astype(np.float32)
TRK_SIN_LUT = np.sin(_TRK_ANG).astype(np.float32)
_CS_LUT = np.empty(2 * TRK_LUT_SIZE, dtype=np.float32)     # interleaved cos, sin (for _integrate_pel)
_CS_LUT[0::2] = TRK_COS_LUT
_CS_LUT[1::2] = TRK_SIN_LUT


# ------------------------------------------------------------------------------ discriminators
@njit(cache=True)
def costas_disc(i, q):
    """Costas (two-quadrant arctangent) phase error in cycles, in [-1/4, 1/4]."""
    if i == 0.0:
        return 0.25 if q > 0.0 else (-0.25 if q < 0.0 else 0.0)
    return math.atan(q / i) / (2.0 * math.pi)


@njit(cache=True)
def fll_disc(i1, q1, i2, q2, t):
    """Cross/dot frequency error (Hz) between sums (i1,q1) then (i2,q2) spaced t s (two-quadrant)."""
    cross = i1 * q2 - q1 * i2
    dot = i1 * i2 + q1 * q2
    if dot == 0.0:
        return 0.0
    return math.atan(cross / dot) / (2.0 * math.pi * t)


@njit(cache=True)
def dll_disc(ie, qe, il, ql, spacing):
    """Normalised early-minus-late envelope: code error (chips, input minus replica)."""
    e = math.sqrt(ie * ie + qe * qe)
    l = math.sqrt(il * il + ql * ql)
    if e + l == 0.0:
        return 0.0
    return (1.0 - 0.5 * spacing) * (e - l) / (e + l)


@njit(cache=True)
def dll_disc_dot(i_el, q_el, i_p, q_p):
    """Dot-product power discriminator for 1 chip spacing, made exact for a triangle correlation.

    ``D = ((I_E - I_L) I_P + (Q_E - Q_L) Q_P) / (I_P^2 + Q_P^2)`` does not depend on the carrier
    phase; for |dtau| < 1/2, ``D = 2 dtau / (1 - |dtau|)``, inverted as ``dtau = D / (2 + |D|)``."""
    p2 = i_p * i_p + q_p * q_p
    if p2 == 0.0:
        return 0.0
    d = (i_el * i_p + q_el * q_p) / p2
    return d / (2.0 + abs(d))


# ------------------------------------------------------------------------------ loop filters
@njit(cache=True)
def pll_fll_update(st, ep, ef, t, bn_p, bn_f, order):
    """One update of the FLL-assisted PLL; st = [x (Hz), y (Hz/s)] updated in place; returns f (Hz)."""
    x = st[0]
    y = st[1]
    if order == 2:
        w0p = bn_p / 0.53
        w0f = 4.0 * bn_f
        xn = x + t * (w0p * w0p * ep + w0f * ef)
        f = 0.5 * (x + xn) + A2 * w0p * ep
        st[0] = xn
        return f
    w0p = bn_p / 0.7845
    w0f = bn_f / 0.53
    yn = y + t * (w0p * w0p * w0p * ep + w0f * w0f * ef)
    xn = x + t * (0.5 * (y + yn) + A3 * w0p * w0p * ep + A2 * w0f * ef)
    f = 0.5 * (x + xn) + B3 * w0p * ep
    st[0] = xn
    st[1] = yn
    return f


@njit(cache=True)
def dll_update(z, dtau, t, bn, order):
    """DLL filter: returns (u chips/s, new integrator z)."""
    if order == 1:
        return 4.0 * bn * dtau, z
    w0 = bn / 0.53
    zn = z + t * w0 * w0 * dtau
    return 0.5 * (z + zn) + A2 * w0 * dtau, zn


# ------------------------------------------------------------------------------ prompt / E-L integration
@njit(cache=True, fastmath={"reassoc", "contract"})
def _pel_block(buf, is_complex, off, m, w, u, cstep, ph, phstep, s_p, t_p, s_e, t_e, cos_lut, sin_lut):
    """float32 sums ``(I_P, I_EL, Q_P, Q_EL)`` over the ``m`` samples from buffer offset ``off``, the
    chips read from the 64-bit code window ``w`` exactly as the correlator's three-tap block
    (:func:`ultratight.receiver.dsp.correlator._epl_block`: ``u``, ``s_*``, ``t_*`` the same): the
    prompt chip and the early minus the late chip (-2, 0 or 2, as the half-chip table of
    :func:`_integrate_pel`).  Its own kernel so that only these four sums are reassociated (LLVM
    splits each over the lanes of 8-wide float32 vectors)."""
    shift = 32 - TRK_LUT_BITS
    mask = TRK_LUT_SIZE - 1
    one = np.uint64(1)
    flip = np.uint32(0x80000000)
    ip = np.float32(0.0); idl = np.float32(0.0)
    qp = np.float32(0.0); qd = np.float32(0.0)
    if is_complex:
        for kk in range(m):
            j = np.uint64(2 * (off + kk))
            xr = buf[j]
            xi = buf[j + one]
            li = np.uint64((ph + kk * phstep) >> shift) & np.uint64(mask)
            c = cos_lut[li]
            s = sin_lut[li]
            bi = xr * c + xi * s
            bq = xi * c - xr * s
            v = np.uint32(w >> (u >> np.uint64(32)))
            lo = np.uint32(u) ^ flip
            cP = chip_at(v, s_p, lo, t_p)
            cD = chip_at(v, s_e, lo, t_e) - chip_at(v, 31, 0, 0)
            ip += bi * cP; idl += bi * cD
            qp += bq * cP; qd += bq * cD
            u += cstep
        return ip, idl, qp, qd
    for kk in range(m):
        xr = buf[np.uint64(off + kk)]
        li = np.uint64((ph + kk * phstep) >> shift) & np.uint64(mask)
        bi = xr * cos_lut[li]
        bq = -xr * sin_lut[li]
        v = np.uint32(w >> (u >> np.uint64(32)))
        lo = np.uint32(u) ^ flip
        cP = chip_at(v, s_p, lo, t_p)
        cD = chip_at(v, s_e, lo, t_e) - chip_at(v, 31, 0, 0)
        ip += bi * cP; idl += bi * cD
        qp += bq * cP; qd += bq * cD
        u += cstep
    return ip, idl, qp, qd


@njit(cache=True)
def integrate_pel(buf, is_complex, off, n, code_ext, unit, tab, cp_fix0, cstep, ph0, phstep, tap_fix, acc):
    """Prompt and early-minus-late sums of one code period, ``acc`` as :func:`_integrate_pel`.

    With a chip table of +-1 entries (``unit``: :func:`ultratight.receiver.dsp.chipbits.unit_chips`
    of ``code_ext``) and taps ``tap_fix`` = [P, E, L] at 0, +1/2, -1/2 chip: float32 sums over
    stretches whose chips fit one 64-chip window (:func:`_pel_block`, vectorised), each flushed to
    float64 -- the same chips as the half-chip table, the sums in another order (float32 rounding);
    otherwise :func:`_integrate_pel` on the half-chip table ``tab``."""
    blk = _window_block(tap_fix, cstep) if unit else 0
    if blk == 0:
        _integrate_pel(buf, is_complex, off, n, tab, cp_fix0, cstep, ph0, phstep, _CS_LUT, acc)
        return
    d_l = tap_fix[2]
    s_p, t_p = _tap_shift(tap_fix[0] - d_l)
    s_e, t_e = _tap_shift(tap_fix[1] - d_l)
    ip64 = 0.0
    id64 = 0.0
    qp64 = 0.0
    qd64 = 0.0
    k = 0
    while k < n:
        m = min(blk, n - k)
        cpk = cp_fix0 + k * cstep + d_l
        j0 = cpk >> 32
        ip, idl, qp, qd = _pel_block(buf, is_complex, off + k, m, code_window(code_ext, j0),
                                     np.uint64(cpk - (j0 << 32)), np.uint64(cstep), ph0 + k * phstep, phstep,
                                     s_p, t_p, s_e, t_e, TRK_COS_LUT, TRK_SIN_LUT)
        ip64 += ip
        id64 += idl
        qp64 += qp
        qd64 += qd
        k += m
    acc[0] = ip64
    acc[1] = id64
    acc[2] = 0.0
    acc[3] = qp64
    acc[4] = qd64
    acc[5] = 0.0


@njit(cache=True)
def _integrate_pel(buf, is_complex, off, n, tab, cp_fix0, cstep, ph0, phstep, lut, acc):
    """Prompt and early-minus-late (1 chip spacing) sums in one pass.

    With taps at +-1/2 chip, the prompt chip and the E-L code value are both functions of the
    half-chip index ``h = floor(2 p)`` of the replica phase: ``P = c(h >> 1)``,
    ``E - L = c((h + 1) >> 1) - c((h - 1) >> 1)``; both come from one interleaved table
    ``tab[2h], tab[2h+1]`` (one index, four multiply-adds per sample instead of three code look-ups
    and six).  ``lut`` interleaves the correlator's cos/sin tables.  ``acc`` receives
    [I_P, I_EL, 0, Q_P, Q_EL, 0] (raw sums). Unsigned indices, as in ``correlator.integrate_channel``."""
    shift = 32 - TRK_LUT_BITS
    mask = TRK_LUT_SIZE - 1
    one = np.uint64(1)
    cp = cp_fix0
    ph = ph0
    ip64 = 0.0
    id64 = 0.0
    qp64 = 0.0
    qd64 = 0.0
    k = 0
    while k < n:
        kend = min(k + 1024, n)
        ip = np.float32(0.0)
        idl = np.float32(0.0)
        qp = np.float32(0.0)
        qd = np.float32(0.0)
        if is_complex:
            for kk in range(k, kend):
                j = np.uint64(2 * (off + kk))
                xr = buf[j]
                xi = buf[j + one]
                li = np.uint64(2 * ((ph >> shift) & mask))
                c = lut[li]
                sn = lut[li + one]
                bi = xr * c + xi * sn
                bq = xi * c - xr * sn
                h = np.uint64(2 * (cp >> 31))
                cP = tab[h]
                cD = tab[h + one]
                ip += bi * cP
                qp += bq * cP
                idl += bi * cD
                qd += bq * cD
                cp += cstep
                ph += phstep
        else:
            for kk in range(k, kend):
                xr = buf[np.uint64(off + kk)]
                li = np.uint64(2 * ((ph >> shift) & mask))
                bi = xr * lut[li]
                bq = -xr * lut[li + one]
                h = np.uint64(2 * (cp >> 31))
                cP = tab[h]
                cD = tab[h + one]
                ip += bi * cP
                qp += bq * cP
                idl += bi * cD
                qd += bq * cD
                cp += cstep
                ph += phstep
        ip64 += ip
        id64 += idl
        qp64 += qp
        qd64 += qd
        k = kend
    acc[0] = ip64
    acc[1] = id64
    acc[2] = 0.0
    acc[3] = qp64
    acc[4] = qd64
    acc[5] = 0.0




def half_chip_tables(prn, pad, signal=GPS_L1CA):
    """Interleaved [P, E-L] float32 table over half-chip indices of the padded code of ``prn`` of
    ``signal`` (see _integrate_pel)."""
    code = np.asarray(signal.code(int(prn))).astype(np.float32)
    n_code = signal.code_length
    nh = 2 * (n_code + 2 * pad)
    h = np.arange(nh)

    def chip(i):                      # padded chip i (i counts from -pad)
        return code[(i - pad) % n_code]

    tab = np.empty(2 * nh, dtype=np.float32)
    tab[0::2] = chip(h >> 1)
    tab[1::2] = chip((h + 1) >> 1) - chip((h - 1) >> 1)
    return tab
