"""Scalar tracking: FLL-assisted Costas PLL, carrier-aided DLL, C/N0, lock indicators, bit sync.

The signal is a :class:`ultratight.signals.signal.SignalDescription` (default GPS L1 C/A): its
code (length ``L`` chips at ``f_chip``), carrier ``f_carrier`` and code periods per data bit reach
the kernel as parameters (``prm[P_CODE_LEN]``, ``prm[P_CHIP_RATE]``, ``prm[P_CARRIER]``, the width
of the bit-sync histogram); an epoch is one code period (1 ms for C/A).

All per-epoch work runs in one numba call per IF block (:func:`_track_block`): for every
active channel it integrates code periods with the correlator kernel of
:mod:`ultratight.receiver.dsp.correlator` (E/P/L, normalised per
:mod:`ultratight.signals.corr_model`: unit noise per arm, prompt amplitude
``A = sqrt(2 C/N0 T)``), runs the discriminators and loop filters, updates the NCOs,
and writes one record per epoch.  Python only handles blocks (≈10 Hz).

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
* Pull-in mode (after (re)acquisition): wide PLL + FLL assist, 1 ms. Track mode (after the
  phase-lock indicator has held for ``lock_s``): track bandwidths, and after bit sync the
  coherent integration grows to ``coh_ms`` (aligned to bit edges; the effective PLL
  bandwidth is capped at ``max_bnt / T`` to keep the discrete loop stable).
* C/N0: the outputs have unit noise per arm, so ``E[I_P^2 + Q_P^2] = 2 + 2 C/N0 T``; the
  estimate over ``cn0_win_ms`` epochs is ``(mean P - 2)/(2 T)``, smoothed exponentially in dB
  (the moments/M2M4 estimator, which needs no noise reference, is :func:`cn0_m2m4`).
* Phase-lock indicator ``PLI = LP((I^2 - Q^2)/n) / (LP((I^2 + Q^2)/n) - 2)`` ≈ cos(2 dphi) on the
  coherent sums of ``n`` epochs (noise bias removed with the known unit noise), low-pass time
  constant ``pli_tau_s``.
* Loss of lock: C/N0 estimate below ``cn0_lost_dbhz`` for ``lost_s`` -> channel mode LOST and
  deactivated (the pipeline re-acquires it).
* Bit sync: sign changes of the per-period I_P counted in one bin per code period of a bit (20 for
  C/A: epoch mod 20); declared when the largest
  bin leads the second by ``bs_margin`` and stands 6 sigma above the mean of the others (Poisson
  noise transitions; works before phase lock too: a
  residual beat adds transitions to every bin alike).  Coherent integration then grows to
  ``coh_ms`` in both modes (the FLL then sees the higher SNR of the longer sums).

The per-epoch logic (:func:`_epoch_update`) is split into small numba functions (C/N0, mode,
bit sync, coherent sums, PLI, bandwidths, loop filters) compiled into the block kernel; the
per-sample correlation loops (:func:`_integrate_pel`, ``correlator.integrate_channel``) are the
hot path and stay single functions.
"""

import math
from dataclasses import dataclass, asdict

import numpy as np
from numba import njit, prange

from ultratight.errors import ConfigError
from ultratight.receiver.dsp.correlator import (COS_LUT, LUT_BITS, LUT_SIZE, SIN_LUT, CorrelatorBank, integrate_channel,
                                            nco_fixed_point, period_samples, tap_fixed_point)
from ultratight.signals.signal import GPS_L1CA

# channel modes
MODE_OFF, MODE_PULL, MODE_TRACK, MODE_LOST = 0, 1, 2, 3

# float state columns (sf)
(F_DOPP, F_PLL_X, F_PLL_Y, F_DLL_Z, F_PREV_I, F_PREV_Q, F_AIP, F_AQP, F_AIE, F_AQE, F_AIL, F_AQL,
 F_AT, F_CN0_P, F_CN0_T, F_CN0_DB, F_PLI_N, F_PLI_D, F_PLI, F_BIT_SUM, F_LOCK_T, F_UNLOCK_T,
 F_LOW_T, F_CARR_ACC, F_LAST_I, F_DLL_ERR, F_PLL_ERR, F_FLL_ERR, F_DLL_U) = range(29)
N_SF = 29
# int state columns (si)
(S_MODE, S_EPOCH, S_BIT_PHASE, S_NTRANS, S_HAVE_PREV, S_ACC_N, S_CN0_N, S_BIT_N, S_CN0_VALID,
 S_ACC_COH) = range(10)
N_SI = 10

# parameter vector (prm)
(P_PULL_PLL_BW, P_PULL_FLL_BW, P_PULL_DLL_BW, P_TRK_PLL_BW, P_TRK_FLL_BW, P_TRK_DLL_BW, P_PLL_ORDER,
 P_DLL_ORDER, P_COH_MS, P_SPACING, P_CN0_WIN, P_CN0_LOST, P_LOST_S, P_PLI_LOCK, P_LOCK_S, P_UNLOCK_S,
 P_BS_MARGIN, P_PLI_TAU, P_MAX_BNT, P_CN0_ALPHA, P_WEAK_DBHZ, P_PULL_COH_MS, P_WEAK_LONG_COH_MS,
 P_WEAK_PLL_BW, P_PEL, P_BS_ENERGY, P_CODE_LEN, P_CHIP_RATE, P_CARRIER) = range(29)
N_PRM = 29          # the last three: the signal's code length (chips), chip rate and carrier (Hz)

# record columns: float (rf) and int (ri)
(R_CODE_PHASE, R_CODE_RATE, R_CARR_ACC, R_DOPP, R_IP, R_QP, R_IE, R_QE, R_IL, R_QL, R_CN0, R_PLI,
 R_DLL_ERR, R_PLL_ERR, R_FLL_ERR, R_BIT) = range(16)
N_RF = 16
REC_F_NAMES = ("code_phase_chips", "code_rate_cps", "carr_acc_cycles", "doppler_hz", "I_P", "Q_P", "I_E",
               "Q_E", "I_L", "Q_L", "cn0_dbhz", "pli", "dll_err_chips", "pll_err_cycles", "fll_err_hz",
               "bit_soft")
(RI_PTR, RI_N, RI_EPOCH, RI_MODE, RI_FLAGS) = range(5)
N_RI = 5
REC_I_NAMES = ("sample_index", "n_samples", "epoch", "mode", "flags")
# flags
FL_BIT_DONE, FL_BIT_SYNC, FL_PLL_LOCK, FL_LOOP_UPD = 1, 2, 4, 8

A2, A3, B3 = math.sqrt(2.0), 1.1, 2.4
PLI_MIN_POWER = 0.1     # LP signal power (A^2 per epoch, ~17 dB-Hz at 1 ms) below which PLI = 0
CN0_FLOOR_LIN = 1.0     # 0 dB-Hz: reported when the power estimate is at or below the noise


@dataclass
class TrackingConfig:
    """Loop parameters (bandwidths are noise bandwidths Bn in Hz)."""
    pull_pll_bw_hz: float = 18.0
    pull_fll_bw_hz: float = 10.0
    pull_dll_bw_hz: float = 2.0
    track_pll_bw_hz: float = 15.0
    track_fll_bw_hz: float = 0.0
    track_dll_bw_hz: float = 0.5
    pll_order: int = 3
    dll_order: int = 1
    coh_ms: int = 1                 # coherent integration after bit sync (1, 2, 4, 5, 10 or 20)
    spacing_chips: float = 1.0
    cn0_win_ms: int = 100
    cn0_lost_dbhz: float = 22.0
    lost_s: float = 1.0
    pli_lock: float = 0.5
    lock_s: float = 0.1
    unlock_s: float = 0.5
    bs_margin: int = 25
    pli_tau_s: float = 0.25
    max_bnt: float = 0.15
    cn0_alpha: float = 0.3
    weak_dbhz: float = 32.0         # C/N0 below which a channel counts as weak: ...
    weak_coh_ms: int = 5            # ... coherent sums of this length before bit sync,
    weak_long_coh_ms: int = 20      # ... bit-synchronised sums of this length after bit sync,
    weak_pll_bw_hz: float = 5.0     # ... and at most this PLL bandwidth
    fast_el: bool = True            # 1-chip spacing: prompt + (E-L) kernel and dot-product DLL
    bs_energy: bool = False         # also the bit-energy bit sync (max sum of |bit sums|, 6-sigma test)

    @classmethod
    def for_dynamics(cls, dynamics="normal", **overrides):
        """The loop parameters of a dynamics profile (:data:`DYNAMICS_PROFILES`) with ``overrides``."""
        if dynamics not in DYNAMICS_PROFILES:
            raise ConfigError(f"--dynamics must be one of {', '.join(DYNAMICS_PROFILES)}, got {dynamics!r}")
        return cls(**{**DYNAMICS_PROFILES[dynamics], **overrides})

    def validate(self):
        if self.coh_ms not in (1, 2, 4, 5, 10, 20) or self.weak_long_coh_ms not in (1, 2, 4, 5, 10, 20):
            raise ConfigError(f"tracking coh_ms must be one of 1, 2, 4, 5, 10, 20 (divides a 20 ms bit), "
                              f"got {self.coh_ms}")
        if self.pll_order not in (2, 3) or self.dll_order not in (1, 2):
            raise ConfigError(f"tracking pll_order must be 2 or 3 and dll_order 1 or 2, "
                              f"got {self.pll_order}, {self.dll_order}")
        for k, v in asdict(self).items():
            if k.endswith("_bw_hz") and not (0.0 <= v <= 100.0):
                raise ConfigError(f"tracking {k} must be in [0, 100] Hz, got {v}")
        if not 0.0 < self.spacing_chips < 2.0:
            raise ConfigError(f"tracking spacing_chips must be in (0, 2), got {self.spacing_chips}")

    def params(self, signal=GPS_L1CA):
        """The kernel's parameter vector: these loop parameters and the ``signal``'s code length,
        chip rate and carrier (a :class:`ultratight.signals.signal.SignalDescription`)."""
        p = np.zeros(N_PRM)
        p[P_PULL_PLL_BW] = self.pull_pll_bw_hz
        p[P_PULL_FLL_BW] = self.pull_fll_bw_hz
        p[P_PULL_DLL_BW] = self.pull_dll_bw_hz
        p[P_TRK_PLL_BW] = self.track_pll_bw_hz
        p[P_TRK_FLL_BW] = self.track_fll_bw_hz
        p[P_TRK_DLL_BW] = self.track_dll_bw_hz
        p[P_PLL_ORDER] = self.pll_order
        p[P_DLL_ORDER] = self.dll_order
        p[P_COH_MS] = self.coh_ms
        p[P_SPACING] = self.spacing_chips
        p[P_CN0_WIN] = self.cn0_win_ms
        p[P_CN0_LOST] = self.cn0_lost_dbhz
        p[P_LOST_S] = self.lost_s
        p[P_PLI_LOCK] = self.pli_lock
        p[P_LOCK_S] = self.lock_s
        p[P_UNLOCK_S] = self.unlock_s
        p[P_BS_MARGIN] = self.bs_margin
        p[P_PLI_TAU] = self.pli_tau_s
        p[P_MAX_BNT] = self.max_bnt
        p[P_CN0_ALPHA] = self.cn0_alpha
        p[P_WEAK_DBHZ] = self.weak_dbhz
        p[P_PULL_COH_MS] = self.weak_coh_ms
        p[P_WEAK_LONG_COH_MS] = self.weak_long_coh_ms
        p[P_WEAK_PLL_BW] = self.weak_pll_bw_hz
        p[P_PEL] = 1.0 if (self.fast_el and self.spacing_chips == 1.0) else 0.0
        p[P_BS_ENERGY] = 1.0 if self.bs_energy else 0.0
        p[P_CODE_LEN] = signal.code_length
        p[P_CHIP_RATE] = signal.chip_rate_hz
        p[P_CARRIER] = signal.carrier_hz
        return p


# Loop profiles by receiver dynamics (``process --dynamics``). ``high``: a start under a constant
# line-of-sight acceleration (paper-highdyn: 10 g, up to ~525 Hz/s Doppler rate) at 30 dB-Hz. The
# channels start from a Doppler-rate search (receiver.acquisition.doppler_rate_search: Doppler
# within ~1 Hz, rate within ~10 Hz/s), so the third-order PLL's rate integrator holds the rate from
# the first epoch and its zero steady-state error under constant acceleration does the rest
# (Kaplan & Hegarty ch. 5). What the profile changes against ``normal``:
# * FLL assist in pull-in 2 Hz instead of 10 Hz: the frequency is already within ~1 Hz; a 10 Hz
#   cross-product FLL on 30 dB-Hz sums adds Hz-level noise that walks the PLL out of lock;
# * a 1 Hz FLL assist kept in track mode: it pulls a slipping PLL back before the C/N0 test drops
#   the channel;
# * bit sync also by bit energy (_bit_sync_energy): at 30 dB-Hz the sign-change histogram needs
#   5-7 s of phase lock for its 6-sigma test, the energy test ~1-2 s (the 1 ms amplitudes, not only
#   their signs), so the first subframe of the file is decoded;
# * weak signals (< weak_dbhz) use 10 ms coherent sums before bit sync (a bit edge spoils at most one
#   of two) and a PLL bandwidth cap of 12 Hz instead of 5 Hz: 5 Hz (w0 = 6.4 rad/s) leaves a rate
#   error of 10 Hz/s as a 0.25-cycle transient and no margin for the rate changes of the geometry,
#   12 Hz at 10 ms keeps B_n T = 0.12 (stable) and the thermal jitter at 30 dB-Hz near 7 deg.
DYNAMICS_PROFILES = {
    "normal": {},
    "high": {"pull_fll_bw_hz": 2.0, "track_fll_bw_hz": 1.0, "weak_coh_ms": 10, "weak_pll_bw_hz": 12.0,
             "bs_energy": True},
}


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


# ------------------------------------------------------------------------------ per-epoch logic
@njit(cache=True)
def _cn0_update(ch, p, t_ep, sf, si, prm):
    """C/N0 from the prompt power ``p`` with the unit-noise reference: ``(mean P - 2)/(2 T)`` over
    ``cn0_win_ms`` epochs, smoothed exponentially in dB."""
    sf[ch, F_CN0_P] += p
    sf[ch, F_CN0_T] += t_ep
    si[ch, S_CN0_N] += 1
    if si[ch, S_CN0_N] >= prm[P_CN0_WIN]:
        nwin = si[ch, S_CN0_N]
        tbar = sf[ch, F_CN0_T] / nwin
        lin = (sf[ch, F_CN0_P] / nwin - 2.0) / (2.0 * tbar)
        if lin < CN0_FLOOR_LIN:
            lin = CN0_FLOOR_LIN
        db = 10.0 * math.log10(lin)
        if si[ch, S_CN0_VALID] == 0:
            sf[ch, F_CN0_DB] = db
            si[ch, S_CN0_VALID] = 1
        else:
            sf[ch, F_CN0_DB] += prm[P_CN0_ALPHA] * (db - sf[ch, F_CN0_DB])
        sf[ch, F_CN0_P] = 0.0
        sf[ch, F_CN0_T] = 0.0
        si[ch, S_CN0_N] = 0


@njit(cache=True)
def _mode_update(ch, mode, t_ep, sf, si, prm):
    """Pull-in / track / lost transitions; returns (mode, flags with FL_PLL_LOCK)."""
    flags = 0
    if mode == MODE_PULL and sf[ch, F_LOCK_T] >= prm[P_LOCK_S]:
        mode = MODE_TRACK
    elif mode == MODE_TRACK and sf[ch, F_UNLOCK_T] >= prm[P_UNLOCK_S]:
        mode = MODE_PULL
    if mode == MODE_TRACK and (si[ch, S_CN0_VALID] == 0 or sf[ch, F_CN0_DB] >= prm[P_CN0_LOST]):
        flags |= FL_PLL_LOCK
    # loss of lock (code): C/N0 too low for too long
    if si[ch, S_CN0_VALID] == 1 and sf[ch, F_CN0_DB] < prm[P_CN0_LOST]:
        sf[ch, F_LOW_T] += t_ep
    else:
        sf[ch, F_LOW_T] = 0.0
    if sf[ch, F_LOW_T] >= prm[P_LOST_S]:
        mode = MODE_LOST
    return mode, flags


@njit(cache=True)
def _bit_sync_energy(ch, ip, epoch, bse, cpb):
    """Bit-energy bit synchronisation: the bit-edge phase k maximising ``E_k = sum |S_k|`` over the
    sums ``S_k`` of the 1 ms prompts I_P of every bit-long window starting at an epoch = k (mod cpb)
    (the maximum-likelihood edge of a phase-locked BPSK signal, Kaplan & Hegarty ch. 5 / van Dierendonck).
    Two phases k1, k2 that are m epochs apart differ by m epochs in and m out of each window: the
    noise of ``|S_k1| - |S_k2|`` is at most ``sqrt(2 m)`` per window (unit noise per arm), so k1 is
    declared when, after N >= 25 windows, ``E_k1 - E_k2 >= 6 sqrt(2 m N)`` for every other k2.

    ``bse[ch]``: running sums (cpb), energies (cpb), epochs seen. Returns the edge phase or -1."""
    n_e = bse[ch, 2 * cpb]
    k = epoch % cpb
    found = -1
    if n_e >= cpb:
        bse[ch, cpb + k] += abs(bse[ch, k])
        nb = n_e // cpb
        if nb >= 25:
            k1 = 0
            for j in range(cpb):
                if bse[ch, cpb + j] > bse[ch, cpb + k1]:
                    k1 = j
            ok = True
            for j in range(cpb):
                if j == k1:
                    continue
                m = abs(j - k1)
                if cpb - m < m:
                    m = cpb - m
                if bse[ch, cpb + k1] - bse[ch, cpb + j] < 6.0 * math.sqrt(2.0 * m * nb):
                    ok = False
                    break
            if ok:
                found = k1
    bse[ch, k] = 0.0
    for j in range(cpb):
        bse[ch, j] += ip
    bse[ch, 2 * cpb] = n_e + 1.0
    return found


@njit(cache=True)
def _bit_sync(ch, ip, epoch, mode, sf, si, hist, prm, bse):
    """Bit synchronisation (sign-change histogram over the ``hist.shape[1]`` code periods of a data
    bit) and the bit sums after it; returns (bit phase or -1, flags, soft bit)."""
    cpb = hist.shape[1]
    flags = 0
    bit_soft = 0.0
    bph = si[ch, S_BIT_PHASE]
    if bph < 0 and mode != MODE_LOST:
        if sf[ch, F_LAST_I] != 0.0 and (ip > 0.0) != (sf[ch, F_LAST_I] > 0.0):
            b = epoch % cpb
            hist[ch, b] += 1
            si[ch, S_NTRANS] += 1
            m1 = 0
            m2 = 0
            kbest = 0
            for k in range(cpb):
                h = hist[ch, k]
                if h > m1:
                    m2 = m1
                    m1 = h
                    kbest = k
                elif h > m2:
                    m2 = h
            # the other bins collect noise transitions (Poisson, mean mu): the edge bin must stand
            # 6 sigma above them and lead the runner-up by the margin
            mu = (si[ch, S_NTRANS] - m1) / (cpb - 1.0)
            if m1 - m2 >= prm[P_BS_MARGIN] and m1 - mu >= 6.0 * math.sqrt(max(mu, 1.0)):
                bph = kbest
                si[ch, S_BIT_PHASE] = bph
                si[ch, S_BIT_N] = -1      # wait for the next bit edge
    if bph < 0 and mode != MODE_LOST and prm[P_BS_ENERGY] > 0.0:
        kb = _bit_sync_energy(ch, ip, epoch, bse, cpb)
        if kb >= 0:
            bph = kb
            si[ch, S_BIT_PHASE] = bph
            si[ch, S_BIT_N] = -1
    sf[ch, F_LAST_I] = ip
    if bph >= 0:
        flags |= FL_BIT_SYNC
        pos = (epoch - bph) % cpb
        if pos == 0:
            sf[ch, F_BIT_SUM] = 0.0
            si[ch, S_BIT_N] = 0
        if si[ch, S_BIT_N] >= 0:
            sf[ch, F_BIT_SUM] += ip
            si[ch, S_BIT_N] += 1
            if pos == cpb - 1 and si[ch, S_BIT_N] == cpb:
                flags |= FL_BIT_DONE
                bit_soft = sf[ch, F_BIT_SUM]
    return bph, flags, bit_soft


@njit(cache=True)
def _coherent_length(ch, bph, weak, si, prm):
    """Coherent integration (epochs) and its reference epoch for this epoch."""
    coh = 1
    ref = 0
    if bph >= 0:
        coh = int(prm[P_COH_MS])
        ref = bph
        if weak and prm[P_WEAK_LONG_COH_MS] > coh:
            coh = int(prm[P_WEAK_LONG_COH_MS])     # bit-synchronised long integration for weak signals
    elif weak:
        # weak signal before bit sync: short coherent sums (a bit edge spoils at most one of them)
        # give the FLL/PLL a usable SNR per update
        coh = int(prm[P_PULL_COH_MS])
    return coh, ref


@njit(cache=True)
def _accumulate(ch, o, t_ep, epoch, coh, ref, sf, si, acc7):
    """Coherent sums of ``coh`` epochs aligned to ``ref``; fills ``acc7`` = [I_P, Q_P, I_E, Q_E, I_L,
    Q_L, T] of the sum and returns True when the sum is complete (a loop update is due)."""
    ip, ie, il, qp, qe, ql = o[0], o[1], o[2], o[3], o[4], o[5]
    if coh <= 1:
        si[ch, S_ACC_N] = 0
        acc7[0], acc7[1], acc7[2], acc7[3], acc7[4], acc7[5], acc7[6] = ip, qp, ie, qe, il, ql, t_ep
        return True
    if (epoch - ref) % coh == 0:
        sf[ch, F_AIP] = 0.0
        sf[ch, F_AQP] = 0.0
        sf[ch, F_AIE] = 0.0
        sf[ch, F_AQE] = 0.0
        sf[ch, F_AIL] = 0.0
        sf[ch, F_AQL] = 0.0
        sf[ch, F_AT] = 0.0
        si[ch, S_ACC_N] = 0
        si[ch, S_ACC_COH] = coh
    elif si[ch, S_ACC_COH] != coh:
        # the integration length changed mid-way: no update until the next boundary
        si[ch, S_ACC_N] = -(1 << 30)
        si[ch, S_ACC_COH] = coh
    sf[ch, F_AIP] += ip
    sf[ch, F_AQP] += qp
    sf[ch, F_AIE] += ie
    sf[ch, F_AQE] += qe
    sf[ch, F_AIL] += il
    sf[ch, F_AQL] += ql
    sf[ch, F_AT] += t_ep
    si[ch, S_ACC_N] += 1
    acc7[0], acc7[1], acc7[2], acc7[3], acc7[4], acc7[5], acc7[6] = (
        sf[ch, F_AIP], sf[ch, F_AQP], sf[ch, F_AIE], sf[ch, F_AQE], sf[ch, F_AIL], sf[ch, F_AQL], sf[ch, F_AT])
    return si[ch, S_ACC_N] == coh


@njit(cache=True)
def _pli_update(ch, cip, cqp, tc, n_acc, sf, prm):
    """Phase-lock indicator LP(I^2 - Q^2) / (LP(I^2 + Q^2) - 2 n) on sums of n unit-noise epochs
    (~ cos 2 dphi) and the lock / unlock timers."""
    a = tc / prm[P_PLI_TAU]
    if a > 1.0:
        a = 1.0
    sf[ch, F_PLI_N] += a * ((cip * cip - cqp * cqp) / n_acc - sf[ch, F_PLI_N])
    sf[ch, F_PLI_D] += a * ((cip * cip + cqp * cqp) / n_acc - 2.0 - sf[ch, F_PLI_D])
    den = sf[ch, F_PLI_D]
    pli = sf[ch, F_PLI_N] / den if den > PLI_MIN_POWER else 0.0     # no signal power: no lock
    sf[ch, F_PLI] = pli
    if pli > prm[P_PLI_LOCK]:
        sf[ch, F_LOCK_T] += tc
        sf[ch, F_UNLOCK_T] = 0.0
    else:
        sf[ch, F_UNLOCK_T] += tc
        sf[ch, F_LOCK_T] = 0.0


@njit(cache=True)
def _bandwidths(ch, mode, weak, tc, sf, si, prm):
    """Noise bandwidths (PLL, FLL, DLL) of this update: mode, FLL SNR scaling, weak-signal and
    stability caps."""
    if mode == MODE_TRACK:
        bn_p, bn_f, bn_d = prm[P_TRK_PLL_BW], prm[P_TRK_FLL_BW], prm[P_TRK_DLL_BW]
    else:
        bn_p, bn_f, bn_d = prm[P_PULL_PLL_BW], prm[P_PULL_FLL_BW], prm[P_PULL_DLL_BW]
    if mode != MODE_TRACK and si[ch, S_CN0_VALID] == 1:
        # the cross-product FLL's noise variance grows like 1/(C/N0 T)^2 at low SNR and then
        # drags the PLL off lock: scale the assist bandwidth by the squared per-update SNR
        # relative to 10 (40 dB-Hz at 1 ms)
        snr = 10.0 ** (sf[ch, F_CN0_DB] / 10.0) * tc / 10.0
        if snr < 1.0:
            bn_f = bn_f * snr * snr
    if weak and bn_p > prm[P_WEAK_PLL_BW]:
        bn_p = prm[P_WEAK_PLL_BW]
    cap = prm[P_MAX_BNT] / tc
    if bn_p > cap:
        bn_p = cap
    if bn_f > cap:
        bn_f = cap
    return bn_p, bn_f, bn_d


@njit(cache=True)
def _loop_update(ch, mode, weak, n_acc, acc7, sf, si, prm, tmp2):
    """Discriminators and loop filters on a complete coherent sum; returns (doppler_hz, u)."""
    cip, cqp, cie, cqe, cil, cql, tc = acc7[0], acc7[1], acc7[2], acc7[3], acc7[4], acc7[5], acc7[6]
    _pli_update(ch, cip, cqp, tc, n_acc, sf, prm)
    ep = costas_disc(cip, cqp)
    ef = 0.0
    if si[ch, S_HAVE_PREV] == 1:
        ef = fll_disc(sf[ch, F_PREV_I], sf[ch, F_PREV_Q], cip, cqp, tc)
    sf[ch, F_PREV_I] = cip
    sf[ch, F_PREV_Q] = cqp
    si[ch, S_HAVE_PREV] = 1
    if prm[P_PEL] > 0.0:
        dtau = dll_disc_dot(cie, cqe, cip, cqp)      # cie, cqe hold E - L
    else:
        dtau = dll_disc(cie, cqe, cil, cql, prm[P_SPACING])
    bn_p, bn_f, bn_d = _bandwidths(ch, mode, weak, tc, sf, si, prm)
    tmp2[0] = sf[ch, F_PLL_X]
    tmp2[1] = sf[ch, F_PLL_Y]
    dopp = pll_fll_update(tmp2, ep, ef, tc, bn_p, bn_f, int(prm[P_PLL_ORDER]))
    sf[ch, F_PLL_X] = tmp2[0]
    sf[ch, F_PLL_Y] = tmp2[1]
    u, z = dll_update(sf[ch, F_DLL_Z], dtau, tc, bn_d, int(prm[P_DLL_ORDER]))
    sf[ch, F_DLL_Z] = z
    sf[ch, F_DOPP] = dopp
    sf[ch, F_DLL_U] = u
    sf[ch, F_DLL_ERR] = dtau
    sf[ch, F_PLL_ERR] = ep
    sf[ch, F_FLL_ERR] = ef
    return dopp, u


@njit(cache=True)
def _epoch_update(ch, o, t_ep, sf, si, hist, prm, tmp2, acc7, bse):
    """Bookkeeping + loops for one channel after one code-period epoch with outputs o[0:6]
    (C/N0, mode, bit sync, coherent sums, then the loops when a sum is complete).

    ``tmp2`` (2) and ``acc7`` (7) are scratch arrays. Returns (doppler_hz, code_rate_corr, flags, bit_soft)."""
    ip, qp = o[0], o[3]
    epoch = si[ch, S_EPOCH]
    _cn0_update(ch, ip * ip + qp * qp, t_ep, sf, si, prm)
    mode, flags = _mode_update(ch, si[ch, S_MODE], t_ep, sf, si, prm)
    bph, fl_bit, bit_soft = _bit_sync(ch, ip, epoch, mode, sf, si, hist, prm, bse)
    flags |= fl_bit
    weak = si[ch, S_CN0_VALID] == 1 and sf[ch, F_CN0_DB] < prm[P_WEAK_DBHZ]
    coh, ref = _coherent_length(ch, bph, weak, si, prm)
    do_upd = _accumulate(ch, o, t_ep, epoch, coh, ref, sf, si, acc7)
    dopp = sf[ch, F_DOPP]
    u = sf[ch, F_DLL_U]
    if do_upd and mode != MODE_LOST:
        flags |= FL_LOOP_UPD
        n_acc = si[ch, S_ACC_N] if coh > 1 else 1
        dopp, u = _loop_update(ch, mode, weak, n_acc, acc7, sf, si, prm, tmp2)
    si[ch, S_MODE] = mode
    si[ch, S_EPOCH] = epoch + 1
    return dopp, u, flags, bit_soft


@njit(cache=True)
def _integrate_pel(buf, is_complex, off, n, tab, cp_fix0, cstep, ph0, phstep, lut, acc):
    """Prompt and early-minus-late (1 chip spacing) sums in one pass.

    With taps at +-1/2 chip, the prompt chip and the E-L code value are both functions of the
    half-chip index ``h = floor(2 p)`` of the replica phase: ``P = c(h >> 1)``,
    ``E - L = c((h + 1) >> 1) - c((h - 1) >> 1)``; both come from one interleaved table
    ``tab[2h], tab[2h+1]`` (one index, four multiply-adds per sample instead of three code look-ups
    and six).  ``lut`` interleaves the correlator's cos/sin tables.  ``acc`` receives
    [I_P, I_EL, 0, Q_P, Q_EL, 0] (raw sums). Unsigned indices, as in ``correlator.integrate_channel``."""
    shift = 32 - LUT_BITS
    mask = LUT_SIZE - 1
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


_CS_LUT = np.empty(2 * LUT_SIZE, dtype=np.float32)
_CS_LUT[0::2] = COS_LUT
_CS_LUT[1::2] = SIN_LUT


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


@njit(cache=True)
def _track_channel(ch, buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                   code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                   sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse):
    """Closed-loop tracking of channel ``ch`` through the buffer (see :func:`_track_block`)."""
    n_taps = tap_off.shape[0]
    tap_fix = tap_fixed_point(tap_off)
    acc = np.zeros(2 * n_taps)
    o = np.zeros(6)
    tmp2 = np.zeros(2)
    acc7 = np.zeros(7)
    code_len = prm[P_CODE_LEN]
    chip_rate = prm[P_CHIP_RATE]
    carrier = prm[P_CARRIER]
    max_rows = rec_f.shape[1]
    while active[ch] and n_rec[ch] < max_rows:
        dp = code_rate[ch] / fs
        n = period_samples(code_phase[ch], dp, code_len)
        off = sample_ptr[ch] - buf_start
        if off < 0 or off + n > n_buf or sample_ptr[ch] + n > stop_sample:
            break
        cp_fix0, cstep, ph0, phstep = nco_fixed_point(code_phase[ch], pad, dp, carr_phase[ch], carr_freq[ch], fs)
        if prm[P_PEL] > 0.0:
            _integrate_pel(buf, is_complex, off, n, half_tab[ch], cp_fix0, cstep, ph0, phstep, _CS_LUT, acc)
        else:
            integrate_channel(buf, is_complex, off, n, code_ext[ch], cp_fix0, cstep, ph0, phstep,
                              tap_fix, COS_LUT, SIN_LUT, acc)
        scale = 1.0 / (sigma_arm[ch] * np.sqrt(n))
        for t in range(3):
            o[t] = acc[t] * scale
            o[3 + t] = acc[n_taps + t] * scale
        r = n_rec[ch]
        rec_i[ch, r, RI_PTR] = sample_ptr[ch]
        rec_i[ch, r, RI_N] = n
        rec_i[ch, r, RI_EPOCH] = si[ch, S_EPOCH]
        rec_f[ch, r, R_CODE_PHASE] = code_phase[ch]
        rec_f[ch, r, R_CODE_RATE] = code_rate[ch]
        rec_f[ch, r, R_CARR_ACC] = sf[ch, F_CARR_ACC]
        rec_f[ch, r, R_DOPP] = carr_freq[ch] - if_hz
        # advance NCOs exactly (as the correlator bank does)
        code_phase[ch] = code_phase[ch] + n * dp - code_len
        ph = carr_phase[ch] + n * (carr_freq[ch] / fs)
        carr_phase[ch] = ph - np.floor(ph)
        sf[ch, F_CARR_ACC] += n * ((carr_freq[ch] - if_hz) / fs)
        sample_ptr[ch] = sample_ptr[ch] + n
        t_ep = n / fs
        dopp, u, flags, bit_soft = _epoch_update(ch, o, t_ep, sf, si, hist, prm, tmp2, acc7, bse)
        carr_freq[ch] = if_hz + dopp
        code_rate[ch] = chip_rate * (1.0 + dopp / carrier) + u
        rec_f[ch, r, R_IP] = o[0]
        rec_f[ch, r, R_QP] = o[3]
        rec_f[ch, r, R_IE] = o[1]
        rec_f[ch, r, R_QE] = o[4]
        rec_f[ch, r, R_IL] = o[2]
        rec_f[ch, r, R_QL] = o[5]
        rec_f[ch, r, R_CN0] = sf[ch, F_CN0_DB] if si[ch, S_CN0_VALID] else np.nan
        rec_f[ch, r, R_PLI] = sf[ch, F_PLI]
        rec_f[ch, r, R_DLL_ERR] = sf[ch, F_DLL_ERR]
        rec_f[ch, r, R_PLL_ERR] = sf[ch, F_PLL_ERR]
        rec_f[ch, r, R_FLL_ERR] = sf[ch, F_FLL_ERR]
        rec_f[ch, r, R_BIT] = bit_soft
        rec_i[ch, r, RI_MODE] = si[ch, S_MODE]
        rec_i[ch, r, RI_FLAGS] = flags
        n_rec[ch] = r + 1
        if si[ch, S_MODE] == MODE_LOST:
            active[ch] = False


@njit(cache=True)
def _track_block(buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                 code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                 sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse):
    """Closed-loop tracking of every active channel over the buffer (see module docstring).

    A channel stops when its next period would pass the buffer end or ``stop_sample``, or when its
    record rows are full; ``n_rec[ch]`` counts the rows written (appended after existing ones)."""
    for ch in range(code_phase.shape[0]):
        _track_channel(ch, buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                       code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                       sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse)


@njit(cache=True, parallel=True)
def _track_block_par(buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                     code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                     sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse):
    """:func:`_track_block` with channels spread over threads (channels are independent)."""
    for ch in prange(code_phase.shape[0]):
        _track_channel(ch, buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                       code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                       sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse)


# ------------------------------------------------------------------------------ estimators (numpy)
def cn0_power(i_p, q_p, t_int):
    """C/N0 (dB-Hz) from prompt outputs with unit noise per arm: (mean P - 2)/(2T)."""
    p = np.mean(np.asarray(i_p) ** 2 + np.asarray(q_p) ** 2)
    lin = max((p - 2.0) / (2.0 * t_int), CN0_FLOOR_LIN)
    return 10.0 * np.log10(lin)


def cn0_m2m4(i_p, q_p, t_int):
    """Moments (M2M4) C/N0 estimator (dB-Hz), needs no noise reference (complex signal, real noise arms).

    M2 = E|z|^2 = S + N, M4 = E|z|^4 = S^2 + 4 S N + 2 N^2 (N = total noise power of both arms)
    -> S = sqrt(2 M2^2 - M4), N = M2 - S; C/N0 = S/(N T) with N = 2 (per-arm unit variance) ...
    normalised form: C/N0 = (S/N)/T."""
    z2 = np.asarray(i_p) ** 2 + np.asarray(q_p) ** 2
    m2 = np.mean(z2)
    m4 = np.mean(z2 * z2)
    s = math.sqrt(max(2.0 * m2 * m2 - m4, 0.0))
    n = m2 - s
    if s <= 0.0 or n <= 0.0:
        return float("nan")
    return 10.0 * math.log10(s / n / t_int)


# ------------------------------------------------------------------------------ channel bank state
STATE_NAMES = ("doppler_hz", "pll_x_hz", "pll_y_hz_s", "dll_z_cps", "prev_I", "prev_Q", "acc_I_P", "acc_Q_P",
               "acc_I_E", "acc_Q_E", "acc_I_L", "acc_Q_L", "acc_t_s", "cn0_power_sum", "cn0_time_s", "cn0_dbhz",
               "pli_num", "pli_den", "pli", "bit_sum", "lock_t_s", "unlock_t_s", "low_cn0_t_s",
               "carrier_acc_cycles", "last_I_P", "dll_err_chips", "pll_err_cycles", "fll_err_hz", "dll_u_cps")
"""Names of the float loop-state columns ``TrackingState.sf`` (indices ``F_*``; the first four are
the loop filters' states)."""
assert len(STATE_NAMES) == N_SF
P_DOPP, P_PLL_X, P_PLL_Y, P_DLL_Z = F_DOPP, F_PLL_X, F_PLL_Y, F_DLL_Z   # state indices of the loop filters


class TrackingState:
    """Loop state of ``n_ch`` channels (arrays for the numba kernel) plus record buffers.

    ``sf`` (n_ch, N_SF) float state (columns ``F_*``, names :data:`STATE_NAMES`), ``si`` (n_ch, N_SI)
    int state (``S_*``), ``hist`` (n_ch, codes per bit) bit-edge histogram, ``prm`` the kernel
    parameters (:meth:`TrackingConfig.params` with the signal's code length, chip rate and carrier),
    ``rec_f`` / ``rec_i`` / ``n_rec`` the records of the last block (columns ``R_*`` / ``RI_*``)."""

    def __init__(self, n_ch, config=None, max_rows=256, signal=GPS_L1CA):
        self.config = config or TrackingConfig()
        self.config.validate()
        self.prm = self.config.params(signal)
        self.sf = np.zeros((n_ch, N_SF))
        self.si = np.zeros((n_ch, N_SI), dtype=np.int64)
        self.hist = np.zeros((n_ch, int(signal.codes_per_bit)), dtype=np.int64)
        # bit-energy sync: running window sums, energies, epochs seen (see _bit_sync_energy)
        self.bse = np.zeros((n_ch, 2 * int(signal.codes_per_bit) + 1))
        self.rec_f = np.zeros((n_ch, max_rows, N_RF))
        self.rec_i = np.zeros((n_ch, max_rows, N_RI), dtype=np.int64)
        self.n_rec = np.zeros(n_ch, dtype=np.int64)

    def reset_channel(self, ch, doppler_hz, cn0_dbhz=None, rate_hz_s=None):
        """(Re)start a channel in pull-in mode with the acquisition Doppler (and C/N0 when known);
        ``rate_hz_s`` (a Doppler-rate search) presets the third-order loop's rate integrator."""
        self.sf[ch] = 0.0
        self.si[ch] = 0
        self.hist[ch] = 0
        self.bse[ch] = 0.0
        self.sf[ch, F_DOPP] = doppler_hz
        self.sf[ch, F_PLL_X] = doppler_hz
        if rate_hz_s is not None and np.isfinite(rate_hz_s):
            self.sf[ch, F_PLL_Y] = rate_hz_s
        if cn0_dbhz is not None and np.isfinite(cn0_dbhz):
            self.sf[ch, F_CN0_DB] = cn0_dbhz
            self.si[ch, S_CN0_VALID] = 1
        self.si[ch, S_MODE] = MODE_PULL
        self.si[ch, S_BIT_PHASE] = -1

    def mode(self, ch):
        return int(self.si[ch, S_MODE])

    def cn0_dbhz(self, ch):
        return float(self.sf[ch, F_CN0_DB]) if self.si[ch, S_CN0_VALID] else float("nan")


class ScalarTracker:
    """The scalar tracking bank: code/carrier NCOs + FLL-assisted PLL and DLL per channel.

    The vocabulary of the ultra-tight prefilter banks (``fusion.prefilter.PrefilterBank``,
    ``fusion.pbkf.PbKfBank``): :meth:`reset` (channels, optional initial state), :meth:`describe`
    (the loop parameters), :data:`STATE_NAMES` and the indices ``P_DOPP``, ``P_PLL_X``,
    ``P_PLL_Y``, ``P_DLL_Z`` of the recorded loop state; :meth:`run` is its ``step`` over a block.
    Unlike the prefilter banks, whose ``step`` takes correlator outputs, the scalar loops take the
    IF samples: correlation and loop update are one fused numba kernel per block
    (:func:`_track_block`), which keeps the 1 ms loop closure inside compiled code (speed).

    ``signal``: the :class:`ultratight.signals.signal.SignalDescription` tracked (code, chip rate,
    carrier, codes per data bit; default GPS L1 C/A). ``channels`` start with :meth:`start_channel`
    (from acquisition); each :meth:`run` tracks every active channel through the buffer and returns
    the new epoch records ``(rec_f (n_ch, rows, N_RF), rec_i (n_ch, rows, N_RI), n_rec (n_ch,))``
    (copies).
    """

    def __init__(self, n_ch, fs_hz, if_hz, is_complex, config=None, max_rows=256, parallel=False,
                 signal=GPS_L1CA):
        self.parallel = bool(parallel) and n_ch > 1
        self.config = config or TrackingConfig()
        self.signal = signal
        # the channels' NCOs and code tables: a correlator bank of the signal (its kernels' layout);
        # the fused tracking kernel integrates, the bank's own step is not used
        self.nco = CorrelatorBank([signal.prns[0]] * n_ch, fs_hz, if_hz, is_complex,
                                  spacing_chips=self.config.spacing_chips, signal=signal)
        self.state = TrackingState(n_ch, self.config, max_rows, signal)
        self.fs_hz = float(fs_hz)
        self.if_hz = float(if_hz)
        self.is_complex = bool(is_complex)
        self.n_ch = n_ch
        nh = 2 * (signal.code_length + 2 * self.nco.pad)
        self.half_tab = np.zeros((n_ch, 2 * nh), dtype=np.float32)

    @property
    def active(self):
        return self.nco.active

    def describe(self):
        """The loop parameters (TrackingConfig fields) and the signal tracked."""
        return {**asdict(self.config), "signal": self.signal.name, "channels": self.n_ch,
                "fs_hz": self.fs_hz, "if_hz": self.if_hz}

    STATE_NAMES = STATE_NAMES
    P_DOPP, P_PLL_X, P_PLL_Y, P_DLL_Z = P_DOPP, P_PLL_X, P_PLL_Y, P_DLL_Z

    def _channels(self, channels):
        ch = np.atleast_1d(np.asarray(channels, dtype=np.int64))
        if ch.size and (ch.min() < 0 or ch.max() >= self.n_ch):
            raise ConfigError(f"scalar tracking: channel index out of range 0..{self.n_ch - 1}: {ch}")
        return ch

    def reset(self, channels, x0=None, P0=None):
        """Restart ``channels`` in pull-in mode from their current NCO Doppler, or from ``x0``
        (per channel: Doppler in Hz); ``P0`` is accepted for the bank protocol (the scalar loops
        carry no covariance)."""
        for k, ch in enumerate(self._channels(channels)):
            d = float(self.nco.carr_freq[ch] - self.if_hz) if x0 is None else float(np.atleast_1d(x0)[k])
            self.state.reset_channel(int(ch), d)

    def correct(self, dx):
        """Apply external corrections ``dx`` (n_ch, 2): [Doppler (Hz), code phase (chips)] per channel
        to the NCOs and the carrier loop's frequency states (an aided scalar loop)."""
        dx = np.asarray(dx, dtype=float).reshape(self.n_ch, 2)
        if not np.all(np.isfinite(dx)):
            raise ConfigError("scalar tracking: corrections must be finite")
        self.nco.carr_freq += dx[:, 0]
        self.state.sf[:, F_DOPP] += dx[:, 0]
        self.state.sf[:, F_PLL_X] += dx[:, 0]
        self.nco.code_phase += dx[:, 1]

    def start_channel(self, ch, prn, code_phase_chips, doppler_hz, sample_index, cn0_dbhz=None, rate_hz_s=None):
        """Start (or restart) channel ``ch`` from an acquisition result valid at ``sample_index``
        (``rate_hz_s``: the Doppler rate there, when searched)."""
        self.nco.init_channel(ch, int(prn), code_phase_chips, doppler_hz, int(sample_index))
        self.half_tab[ch] = half_chip_tables(prn, self.nco.pad, self.signal)
        self.state.reset_channel(ch, float(doppler_hz), cn0_dbhz, rate_hz_s)

    def stop_channel(self, ch):
        self.nco.active[ch] = False
        self.state.si[ch, S_MODE] = MODE_OFF

    def next_needed_sample(self):
        """Smallest sample_ptr of the active channels (None if none is active)."""
        if not self.nco.active.any():
            return None
        return int(self.nco.sample_ptr[self.nco.active].min())

    def run(self, buf, buf_start, sigma_arm, stop_sample=None):
        b = self.nco
        st = self.state
        if self.is_complex:
            raw = np.ascontiguousarray(buf, dtype=np.complex64).view(np.float32)
        else:
            raw = np.ascontiguousarray(buf, dtype=np.float32)
        n_buf = int(np.asarray(buf).shape[0])
        stop = np.int64(buf_start + n_buf if stop_sample is None else stop_sample)
        sig = np.broadcast_to(np.asarray(sigma_arm, dtype=float), (self.n_ch,)).copy()
        st.n_rec[:] = 0
        fn = _track_block_par if self.parallel else _track_block
        fn(raw, self.is_complex, np.int64(buf_start), np.int64(n_buf), stop, b.code_ext,
           b.pad, b.active, b.sample_ptr, b.code_phase, b.code_rate, b.carr_phase, b.carr_freq,
           self.fs_hz, self.if_hz, b.tap_offsets_chips, sig, st.sf, st.si, st.hist, st.prm,
           st.rec_f, st.rec_i, st.n_rec, self.half_tab, st.bse)
        m = int(st.n_rec.max()) if st.n_rec.size else 0
        return st.rec_f[:, :m].copy(), st.rec_i[:, :m].copy(), st.n_rec.copy()

    step = run

    def track_at(self, stream, start, count, head, min_samples, stop_sample):
        """Track through ``count`` samples of ``stream`` (:class:`ultratight.receiver.dsp.blockstream.BlockStream`)
        read at ``start``, normalised by the noise estimate of their first ``head`` samples (the
        scalar receiver: channels stop, re-acquire and restart anywhere). Returns the records as
        :meth:`run`, or None when fewer than ``min_samples`` samples are left."""
        buf, sigma_arm = stream.read_at(start, count, head)
        if buf.shape[0] < min_samples:
            return None
        return self.run(buf, start, sigma_arm, stop_sample=stop_sample)

    def track_aligned(self, stream, n_total):
        """Track through the aligned blocks ``[k L, (k + 1) L)`` of ``stream`` up to sample ``n_total``,
        each normalised by its own noise estimate; yields the records of every block (as :meth:`run`).
        The samples a channel still needs before a block stay in the stream's buffer."""
        blk = stream.block_len
        start = 0
        while start < n_total:
            lo = self.next_needed_sample()
            if lo is None:
                return
            lo = min(lo, start)
            stream.ensure(start + blk, keep_from=lo)
            buf, lo = stream.view(lo)
            if buf.shape[0] == 0:
                return
            sig = float(stream.sigma_at(start))
            yield self.run(buf, lo, sig, stop_sample=min(start + blk, n_total))
            start += blk
