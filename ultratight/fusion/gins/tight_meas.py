"""Tight INS/GNSS measurement model on recorded raw GPS observations (``ultratight integrate
--coupling tight``): per epoch of a :class:`ultratight.signals.observations.RawEpochs`, the
pseudorange and pseudorange-rate innovations of an antenna position/velocity/clock estimate, their
lines of sight and their σ.  A row's pseudorange is L1 C/A or, where the RawEpochs says so
(``iono_free_f2_hz``, e.g. a dual-frequency u-blox log), the ionosphere-free combination of L1 C/A
with L2C or L5; Doppler is always L1's.  See docs/gins-tight.md.

Satellite states come from :func:`ultratight.signals.obs_geometry.sat_states` — one row per
RawEpochs row: ECEF position/velocity at the transmit time, satellite clock ``clk_m`` (af0/af1/af2,
relativistic term, −T_GD; metres) and its drift, *without* the Sagnac rotation.  This module adds
the receiver-dependent part, in the conventions of :mod:`ultratight.signals.geometry` (the same
equations its light-time solution evaluates, vectorised here over the satellites of one epoch)::

    τ      = |R3(Ω_E τ) r_s − r| / c                 (two fixed-point steps from |r_s − r| / c)
    ρ̂      = |R3(Ω_E τ) r_s − r| + b − clk_s + I + T
    ρ̂̇      = e·(R3 v_s − v) / (1 + e·(R3 v_s − Ω_E g) / c) + d − ḋclk_s (1 − ρ̇/c) − İ + Ṫ

with ``e`` the unit line of sight receiver → satellite in the ECEF frame of reception,
``g = R3 (y_s, −x_s, 0)`` (the derivative of the rotation with respect to its angle: the Sagnac
rate), ``b``/``d`` the receiver clock bias (m) and drift (m/s), ``I`` the Klobuchar ionospheric
group delay (none on a combined row: the combination has removed it, to first order) and ``T`` the
Saastamoinen tropospheric delay of
:class:`ultratight.signals.atmosphere.AtmosphereModel` (broadcast alpha/beta from the navigation
data).  The Doppler is the rate of the *carrier* phase, so the ionosphere enters it with the
opposite sign of the code (``−İ``); the delay rates are forward differences over
:data:`ATMO_RATE_DT_S` of the delays along the receiver's and satellite's motion (at most about a
centimetre per second at a 10° mask, mostly the troposphere).  The measured range rate is
``−λ_L1 · D`` (RawEpochs Doppler is positive while the satellite approaches).

Innovations are **predicted minus measured** (the convention of
:mod:`ultratight.fusion.coupling.tight`), so for an estimate ``r̂ = r + δr``, ``v̂ = v + δv``::

    dz_pr ≈ −e·δr + δb          dz_rr ≈ −e·δv + δd

Time: ``RawEpochs.t`` is the receiver-clock reading at reception; the position and velocity passed
to :meth:`TightMeasurements.rows` are those of the antenna at the true reception time
``t[k] − b/c`` (for a 1 ms clock bias and 30 m/s that is 3 cm along the path).  The satellite states
do not depend on it (their transmit time comes from the pseudorange itself).

Rows dropped by :meth:`TightMeasurements.rows`: no valid satellite state (ephemeris missing,
unhealthy, outside its fit interval), no pseudorange, a PRN outside ``sats``, C/N0 below
``cn0_min_dbhz`` (rows without C/N0 are kept), elevation below ``mask_deg``.  A position less than
5000 km from the Earth's centre (the start of a least-squares iteration from zero) has no horizon:
every row is returned with a NaN elevation, no atmosphere and the zenith σ.  A row whose Doppler
is missing keeps its pseudorange: ``dz_rr`` is NaN, ``sigma_rr`` is ``inf`` and ``rr_ok`` is False
(use ``rr_ok`` to select the rate rows).

Noise (:class:`TightNoise`, 1σ, every coefficient overridable; a scalar ``sigma_pr_m`` /
``sigma_rr_mps`` replaces the model by a constant)::

    σ_pr² = k² (a² + (b / sin E)² + c² 10^((C0 − C/N0)/10)) + (k_I I)² + (σ_T / (sin E + 0.1))²
    σ_D²  = d² + f² 10^((C0 − C/N0)/10)            (Hz);  σ_rr = λ_L1 σ_D

The first two code terms are the elevation model of RTKLIB (Takasu, RTKLIB 2.4.2 manual,
Appendix E.6: a = b = 0.3 m, i.e. its 0.003 m phase error times the code/phase ratio 100), the
third the thermal-noise law (variance ∝ 1/(C/N0)) with c = 0.5 m at C0 = 45 dB-Hz, the last two
the residual errors of the broadcast ionosphere (half of the Klobuchar delay, when it is applied)
and of the Saastamoinen model (0.3 m zenith, when it is applied), as in the same appendix.  Doppler:
d = 0.1 Hz (about 2 cm/s, the order of a u-blox receiver's reported Doppler σ at strong signals plus
the unmodelled antenna jitter) and f = 0.15 Hz at 45 dB-Hz (0.48 Hz ≈ 9 cm/s at 35 dB-Hz).
Without a C/N0 the C/N0 terms take their value at C0.

``k`` is 1 on an L1 C/A row.  On an ionosphere-free row ``(γ P1 − P2)/(γ − 1)``, ``γ = (f1/f2)²``, the
code terms (noise and multipath of each frequency, taken independent and equal) are multiplied by
``k = √(γ² + 1)/(γ − 1)`` (:func:`ultratight.signals.observations.iono_free_noise_factor`: 2.98 with
L2C, 2.59 with L5), and the ionosphere term is absent (``I = 0``: the combination leaves no ionosphere
residual to first order; the higher orders are centimetres).  The troposphere is the same on both
frequencies and so in the combination: its term is unchanged.  The C/N0 used is L1's.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields

import numpy as np

from ultratight.constants import LAMBDA_L1, OMEGA_E, C
from ultratight.errors import ConfigError, FilterError
from ultratight.ins.earth import ecef_to_llh, elev_azim, enu_frames
from ultratight.signals.atmosphere import AtmosphereModel
from ultratight.signals.obs_geometry import sat_states
from ultratight.signals.observations import iono_free_noise_factor, week_tow

ATMO_RATE_DT_S = 1.0          # forward-difference step of the atmospheric delay rates, s
SAGNAC_ITER = 2               # fixed-point steps of the travel time (each gains a factor ~1e-5)
SIN_EL_FLOOR = 0.05           # sin E floor of the noise model (about 2.9°; masks below it are rare)
HORIZON_MIN_RADIUS_M = 5.0e6  # closer to the Earth's centre: no horizon (mask and atmosphere skipped)
SPP_MAX_ITER = 12
SPP_TOL_M = 1e-4
MIN_SATS_FIX = 4


@dataclass(frozen=True)
class TightNoise:
    """Coefficients of the measurement noise model (module docstring)."""
    pr_a_m: float = 0.3
    pr_b_m: float = 0.3
    pr_cn0_m: float = 0.5
    iono_frac: float = 0.5
    tropo_zenith_m: float = 0.3
    dop_a_hz: float = 0.1
    dop_cn0_hz: float = 0.15
    cn0_ref_dbhz: float = 45.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if not (_is_number(v) and v >= 0.0):
                raise ConfigError(f"tight measurement noise: {f.name} must be a finite number >= 0, got {v!r}")

    def cn0_factor(self, cn0_dbhz):
        """10^((C0 − C/N0)/10); 1 where C/N0 is missing."""
        cn0 = np.asarray(cn0_dbhz, dtype=float)
        return np.where(np.isfinite(cn0), 10.0 ** ((self.cn0_ref_dbhz - np.where(np.isfinite(cn0), cn0, 0.0))
                                                     / 10.0), 1.0)

    def sigma_pr(self, elev_rad, cn0_dbhz, iono_m, tropo_active, code_factor=1.0):
        """σ of the pseudorange (module docstring); ``code_factor`` multiplies the code terms (a, b, c):
        :func:`ultratight.signals.observations.iono_free_noise_factor` for a combined row."""
        s = np.maximum(np.sin(np.asarray(elev_rad, dtype=float)), SIN_EL_FLOOR)
        code = self.pr_a_m ** 2 + (self.pr_b_m / s) ** 2 + self.pr_cn0_m ** 2 * self.cn0_factor(cn0_dbhz)
        var = (np.asarray(code_factor, dtype=float) ** 2 * code
               + (self.iono_frac * np.asarray(iono_m, dtype=float)) ** 2)
        if tropo_active:
            var = var + (self.tropo_zenith_m / (s + 0.1)) ** 2
        return np.sqrt(var)

    def sigma_rr(self, cn0_dbhz):
        var_hz = self.dop_a_hz ** 2 + self.dop_cn0_hz ** 2 * self.cn0_factor(cn0_dbhz)
        return LAMBDA_L1 * np.sqrt(var_hz)


@dataclass
class TightRows:
    """The usable rows of one epoch (module docstring); arrays of length n."""
    dz_pr: np.ndarray          # predicted − measured pseudorange, m
    dz_rr: np.ndarray          # predicted − measured range rate, m/s (NaN without Doppler)
    los_e: np.ndarray          # (n, 3) unit receiver → satellite, ECEF of reception
    sigma_pr: np.ndarray       # m
    sigma_rr: np.ndarray       # m/s (inf without Doppler)
    prn: np.ndarray
    elev_rad: np.ndarray
    azim_rad: np.ndarray
    rr_ok: np.ndarray          # bool: the rate row is usable
    cn0_dbhz: np.ndarray
    iono_m: np.ndarray         # code delays applied to the prediction
    tropo_m: np.ndarray
    row: np.ndarray            # indices into the RawEpochs rows

    @property
    def n(self):
        return int(self.dz_pr.shape[0])


@dataclass
class EpochFix:
    """Single-epoch least-squares solution of :meth:`TightMeasurements.spp`."""
    ok: bool
    pos_e: np.ndarray
    vel_e: np.ndarray
    clk_m: float
    drift_mps: float
    n_pr: int
    n_rr: int
    pdop: float
    rms_pr_m: float
    rms_rr_mps: float
    reason: str = ""


def sagnac_rotate(vec_e, tau_s):
    """ECEF vectors (n, 3) of the transmit epoch expressed in the ECEF frame of reception, ``τ``
    later: ``R3(Ω_E τ) v``."""
    th = OMEGA_E * np.asarray(tau_s, dtype=float)
    c, s = np.cos(th), np.sin(th)
    out = np.empty_like(np.asarray(vec_e, dtype=float))
    out[:, 0] = c * vec_e[:, 0] + s * vec_e[:, 1]
    out[:, 1] = -s * vec_e[:, 0] + c * vec_e[:, 1]
    out[:, 2] = vec_e[:, 2]
    return out


def _is_number(v):
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def _vec3(x, what):
    v = np.asarray(x, dtype=float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise FilterError(f"tight measurements: {what} must be 3 finite numbers, got {x!r}")
    return v


def _load_states(raw, nav, states):
    if states is None:
        states = sat_states(raw, nav)
    m = int(raw.prn.shape[0])
    shapes = {"pos_e": (m, 3), "vel_e": (m, 3), "clk_m": (m,), "drift_mps": (m,), "valid": (m,)}
    for name, shape in shapes.items():
        arr = getattr(states, name, None)
        if arr is None or np.shape(arr) != shape:
            raise ConfigError(f"tight measurements: satellite states field {name!r} must have shape {shape}, "
                              f"got {None if arr is None else np.shape(arr)}")
    return states


class TightMeasurements:
    """Pseudorange / range-rate rows of recorded raw observations for the tight 17-state filter.

    ``raw``: RawEpochs; ``nav``: the navigation data (its ``ion_alpha``/``ion_beta`` feed the
    Klobuchar model); ``mask_deg``: elevation mask; ``iono``: "klobuchar" or "off"; ``tropo``:
    "saastamoinen" or "off"; ``sigma_pr_m``/``sigma_rr_mps``: constant σ replacing the model;
    ``cn0_min_dbhz``: rows below it are dropped; ``sats``: PRNs to use (None: all); ``noise``: a
    :class:`TightNoise`; ``states``: satellite states with the fields of
    ``obs_geometry.SatStates`` (default: computed from ``raw`` and ``nav``).  ``warnings``: lines
    the caller should show the user (e.g. no Klobuchar coefficients in the navigation data, so no
    ionosphere model); ``info``: the settings and row counts."""

    def __init__(self, raw, nav, *, mask_deg=10.0, iono="klobuchar", tropo="saastamoinen",
                 sigma_pr_m=None, sigma_rr_mps=None, cn0_min_dbhz=None, sats=None, noise=None, states=None):
        if not (_is_number(mask_deg) and -90.0 <= mask_deg <= 90.0):
            raise ConfigError(f"tight measurements: mask_deg must be a number within [-90, 90], got {mask_deg!r}")
        if cn0_min_dbhz is not None and not _is_number(cn0_min_dbhz):
            raise ConfigError(f"tight measurements: cn0_min_dbhz must be a finite number, got {cn0_min_dbhz!r}")
        for name, v in (("sigma_pr_m", sigma_pr_m), ("sigma_rr_mps", sigma_rr_mps)):
            if v is not None and not (_is_number(v) and v > 0.0):
                raise ConfigError(f"tight measurements: {name} must be a finite number > 0, got {v!r}")
        self.raw = raw
        self.nav = nav
        self.t = np.asarray(raw.t, dtype=float).copy()
        self.mask_rad = math.radians(float(mask_deg))
        self.atmo = AtmosphereModel(iono=iono, alpha=getattr(nav, "ion_alpha", None),
                                    beta=getattr(nav, "ion_beta", None), tropo=tropo)
        self.noise = TightNoise() if noise is None else noise
        if not isinstance(self.noise, TightNoise):
            raise ConfigError(f"tight measurements: noise must be a TightNoise, got {type(noise).__name__}")
        self.sigma_pr_m = sigma_pr_m
        self.sigma_rr_mps = sigma_rr_mps
        self.states = _load_states(raw, nav, states)
        prn = np.asarray(raw.prn)
        usable = np.asarray(self.states.valid, dtype=bool) & np.isfinite(raw.pr_m)
        usable &= np.all(np.isfinite(self.states.pos_e), axis=1) & np.isfinite(self.states.clk_m)
        if sats is not None:
            usable &= np.isin(prn, np.asarray(list(sats), dtype=int))
        if cn0_min_dbhz is not None:
            cn0 = np.asarray(raw.cn0_dbhz, dtype=float)
            usable &= ~(cn0 < float(cn0_min_dbhz))            # rows without C/N0 pass
        self.usable = usable
        f2 = getattr(raw, "iono_free_f2_hz", None)
        if f2 is not None and np.shape(f2) != prn.shape:
            raise ConfigError(f"tight measurements: iono_free_f2_hz must have one value per row {prn.shape}, "
                              f"got {np.shape(f2)}")
        self.iono_free = np.zeros(prn.shape[0], dtype=bool) if f2 is None else raw.iono_free_rows()
        self.code_factor = np.ones(prn.shape[0]) if f2 is None else iono_free_noise_factor(f2)
        self.rr_meas = -LAMBDA_L1 * np.asarray(raw.doppler_hz, dtype=float)
        self.rr_meas[~np.all(np.isfinite(self.states.vel_e), axis=1)] = np.nan
        self.warnings = []
        single = usable & ~self.iono_free
        if iono == "klobuchar" and not self.atmo.iono_active and single.any():
            self.warnings.append("the navigation data hold no Klobuchar coefficients: ionosphere not modelled")
        dropped = int(getattr(raw, "meta", {}).get("rows_single_frequency_dropped", 0) or 0)
        if dropped:
            self.warnings.append(f"{dropped} GPS L1 C/A rows left out: no {raw.meta.get('iono_free_pair', 'second')} "
                                 "pseudorange for the ionosphere-free combination")
        if not usable.any():
            self.warnings.append("no observation row has a valid satellite state and a pseudorange")
        self.info = {"mask_deg": float(mask_deg), "atmosphere": self.atmo.describe(),
                     "signals": str(getattr(raw, "meta", {}).get("signal", "GPS L1 C/A")),
                     "ionosphere": self._iono_line(usable), "rows": int(prn.shape[0]), "usable_rows": int(usable.sum())}

    def _iono_line(self, usable):
        """How the rows' ionosphere is handled (the summary's line)."""
        n_if, n_single = int((usable & self.iono_free).sum()), int((usable & ~self.iono_free).sum())
        parts = []
        if n_if:
            parts.append(f"{n_if} rows ionosphere-free (dual frequency)")
        if n_single:
            parts.append(f"{n_single} single-frequency rows with the "
                         + ("broadcast Klobuchar model" if self.atmo.iono_active else "ionosphere not modelled"))
        return "; ".join(parts) or "no usable rows"

    @property
    def n_epochs(self):
        return int(self.t.shape[0])

    def _epoch_rows(self, k):
        if not 0 <= int(k) < self.n_epochs:
            raise FilterError(f"tight measurements: epoch {k} outside 0..{self.n_epochs - 1}")
        sl = self.raw.epoch(int(k))
        idx = np.arange(sl.start, sl.stop)
        return idx[self.usable[sl]]

    # ------------------------------------------------------------------ geometry
    def _geometry(self, idx, pos, vel):
        """Range, line of sight, geometric range rate (no clocks, no atmosphere) and the rotated
        satellite position/velocity of rows ``idx`` for the receiver at (pos, vel)."""
        st = self.states
        s = np.asarray(st.pos_e, dtype=float)[idx]
        vs = np.asarray(st.vel_e, dtype=float)[idx]
        tau = np.linalg.norm(s - pos, axis=1) / C
        for _ in range(SAGNAC_ITER):
            tau = np.linalg.norm(sagnac_rotate(s, tau) - pos, axis=1) / C
        sr = sagnac_rotate(s, tau)
        vr = sagnac_rotate(vs, tau)
        d = sr - pos
        rng = np.linalg.norm(d, axis=1)
        u = d / rng[:, None]
        th = OMEGA_E * tau
        c, sn = np.cos(th), np.sin(th)
        g = np.stack([c * s[:, 1] - sn * s[:, 0], -sn * s[:, 1] - c * s[:, 0], np.zeros(len(idx))], axis=1)
        a_term = np.einsum("ij,ij->i", u, vr - vel)
        b_term = np.einsum("ij,ij->i", u, vr - OMEGA_E * g)
        rng_dot = a_term / (1.0 + b_term / C)
        return rng, u, rng_dot, sr, vr

    def _atmosphere(self, pos, vel, sr, vr, tow, single):
        """(elev, azim, iono_m, tropo_m, carrier-phase delay rate m/s) for the receiver at pos; NaN
        elevations and no delays deep inside the Earth (a cold least-squares start)."""
        if np.linalg.norm(pos) < HORIZON_MIN_RADIUS_M:
            z = np.zeros(sr.shape[0])
            return np.full_like(z, np.nan), np.full_like(z, np.nan), z, z, z
        frames = enu_frames(pos)
        el, az = elev_azim(pos, sr, frames)
        el, az = np.atleast_1d(el), np.atleast_1d(az)
        if not self.atmo.active:
            z = np.zeros_like(el)
            return el, az, z, z, z
        lat, lon, h = ecef_to_llh(pos)
        dt = ATMO_RATE_DT_S
        pos2 = pos + vel * dt
        el2, az2 = elev_azim(pos2, sr + vr * dt)
        lat2, lon2, h2 = ecef_to_llh(pos2)
        # the troposphere is 0 outside its standard atmosphere's heights (evaluated, then discarded)
        with np.errstate(invalid="ignore"):
            iono, tropo = self.atmo.delays_m(lat, lon, h, el, az, tow)
            iono2, tropo2 = self.atmo.delays_m(lat2, lon2, h2, np.atleast_1d(el2), np.atleast_1d(az2), tow + dt)
        iono, iono2 = np.where(single, iono, 0.0), np.where(single, iono2, 0.0)    # combined rows: none
        rate = (-(iono2 - iono) + (tropo2 - tropo)) / dt
        return el, az, np.atleast_1d(iono), np.atleast_1d(tropo), np.atleast_1d(rate)

    def _predict(self, k, idx, pos, vel):
        """Clock-free predictions of rows ``idx``: dict of pr (m), rr (m/s), los, elev, azim, iono, tropo."""
        rng, u, rng_dot, sr, vr = self._geometry(idx, pos, vel)
        tow = float(week_tow(self.t[k])[1])
        el, az, iono, tropo, atmo_rate = self._atmosphere(pos, vel, sr, vr, tow, ~self.iono_free[idx])
        st = self.states
        pr = rng - np.asarray(st.clk_m, dtype=float)[idx] + iono + tropo
        rr = rng_dot - np.asarray(st.drift_mps, dtype=float)[idx] * (1.0 - rng_dot / C) + atmo_rate
        return {"pr": pr, "rr": rr, "los": u, "elev": el, "azim": az, "iono": iono, "tropo": tropo}

    def _sigmas(self, idx, elev, iono):
        cn0 = np.asarray(self.raw.cn0_dbhz, dtype=float)[idx]
        if self.sigma_pr_m is None:
            sig_pr = self.noise.sigma_pr(elev, cn0, iono, self.atmo.tropo != "off", self.code_factor[idx])
        else:
            sig_pr = np.full(idx.shape[0], float(self.sigma_pr_m))
        if self.sigma_rr_mps is None:
            sig_rr = self.noise.sigma_rr(cn0) * np.ones(idx.shape[0])
        else:
            sig_rr = np.full(idx.shape[0], float(self.sigma_rr_mps))
        return sig_pr, sig_rr, cn0

    # ------------------------------------------------------------------ the interface
    def rows(self, k, pos_e, vel_e, clk_m, drift_mps, keep=None):
        """:class:`TightRows` of epoch ``k`` for the antenna at ``pos_e``/``vel_e`` (ECEF, true
        reception time) with receiver clock bias ``clk_m`` (m) and drift ``drift_mps`` (m/s);
        ``keep``: only the ``keep`` highest satellites (None: all)."""
        pos = _vec3(pos_e, "pos_e")
        vel = _vec3(vel_e, "vel_e")
        if not (math.isfinite(clk_m) and math.isfinite(drift_mps)):
            raise FilterError(f"tight measurements: clock must be finite, got {clk_m!r}, {drift_mps!r}")
        if keep is not None and not (int(keep) == keep and keep >= 0):
            raise FilterError(f"tight measurements: keep must be a whole number >= 0, got {keep!r}")
        idx = self._epoch_rows(k)
        if idx.size == 0:
            return self._empty()
        p = self._predict(k, idx, pos, vel)
        cold = bool(np.isnan(p["elev"]).all())
        sel = np.ones(idx.size, dtype=bool) if cold else p["elev"] >= self.mask_rad
        if keep is not None and int(sel.sum()) > int(keep):
            order = np.argsort(-np.where(sel, p["elev"], -np.inf), kind="stable")
            sel = np.zeros_like(sel)
            sel[order[: int(keep)]] = True
        idx = idx[sel]
        p = {key: v[sel] for key, v in p.items()}
        sig_pr, sig_rr, cn0 = self._sigmas(idx, np.where(np.isnan(p["elev"]), 0.5 * math.pi, p["elev"]),
                                           p["iono"])
        dz_pr = p["pr"] + float(clk_m) - np.asarray(self.raw.pr_m, dtype=float)[idx]
        dz_rr = p["rr"] + float(drift_mps) - self.rr_meas[idx]
        rr_ok = np.isfinite(dz_rr)
        sig_rr = np.where(rr_ok, sig_rr, np.inf)
        return TightRows(dz_pr=dz_pr, dz_rr=dz_rr, los_e=p["los"], sigma_pr=sig_pr, sigma_rr=sig_rr,
                         prn=np.asarray(self.raw.prn)[idx].astype(int), elev_rad=p["elev"], azim_rad=p["azim"],
                         rr_ok=rr_ok, cn0_dbhz=cn0, iono_m=p["iono"], tropo_m=p["tropo"], row=idx)

    @staticmethod
    def _empty():
        z = np.zeros(0)
        return TightRows(dz_pr=z, dz_rr=z.copy(), los_e=np.zeros((0, 3)), sigma_pr=z.copy(), sigma_rr=z.copy(),
                         prn=np.zeros(0, dtype=int), elev_rad=z.copy(), azim_rad=z.copy(),
                         rr_ok=np.zeros(0, dtype=bool), cn0_dbhz=z.copy(), iono_m=z.copy(), tropo_m=z.copy(),
                         row=np.zeros(0, dtype=int))

    def initial_clock(self, k, pos_e, vel_e):
        """(clk_m, drift_mps) of epoch ``k`` by weighted least squares at a known antenna
        position/velocity: the weighted mean of the clock-free residuals, after dropping rows more
        than 5σ from their median (a multipath or cycle-slip row does not pull the start).
        (nan, nan) without rows; the drift is nan without Doppler."""
        r = self.rows(k, pos_e, vel_e, 0.0, 0.0)
        return _robust_mean(-r.dz_pr, r.sigma_pr), _robust_mean(-r.dz_rr[r.rr_ok], r.sigma_rr[r.rr_ok])

    def spp(self, k, pos0_e=None):
        """Single-point fix of epoch ``k`` from its own observations (:class:`EpochFix`): Gauss–Newton
        on the pseudoranges for position and clock (first without mask and atmosphere from
        ``pos0_e`` — default the Earth's centre — then with both and the σ of the noise model),
        then weighted least squares on the range rates for velocity and drift.  No fault
        exclusion: a start for the filter, not a navigation solution."""
        idx = self._epoch_rows(k)
        pos = np.zeros(3) if pos0_e is None else _vec3(pos0_e, "pos0_e")
        if idx.size < MIN_SATS_FIX:
            return _no_fix(pos, f"{idx.size} usable pseudoranges (need {MIN_SATS_FIX})")
        try:
            return self._spp(k, idx, pos)
        except np.linalg.LinAlgError:
            return _no_fix(pos, "singular satellite geometry")

    def _spp(self, k, idx, pos):
        pr = np.asarray(self.raw.pr_m, dtype=float)
        clk = 0.0
        for _ in range(SPP_MAX_ITER):                  # coarse: geometry and clocks only
            rng, u, _, _, _ = self._geometry(idx, pos, np.zeros(3))
            dx, _ = _wls(-u, pr[idx] - (rng - self.states.clk_m[idx] + clk), np.ones(idx.size))
            pos, clk = pos + dx[:3], clk + dx[3]
            if np.linalg.norm(dx) < 1.0:
                break
        vel, drift = np.zeros(3), 0.0
        for _ in range(SPP_MAX_ITER):                  # fine: mask, atmosphere, weights
            r = self.rows(k, pos, vel, clk, drift)
            if r.n < MIN_SATS_FIX:
                return _no_fix(pos, f"{r.n} pseudoranges above the mask (need {MIN_SATS_FIX})")
            dx, cov = _wls(-r.los_e, -r.dz_pr, 1.0 / r.sigma_pr ** 2)
            pos, clk = pos + dx[:3], clk + dx[3]
            if np.linalg.norm(dx) < SPP_TOL_M:
                break
        for _ in range(2):                              # the rate model is linear up to ~1e-6
            r = self.rows(k, pos, vel, clk, drift)
            ok = r.rr_ok
            if ok.sum() < MIN_SATS_FIX:
                vel, drift = np.full(3, np.nan), np.nan
                break
            dv, _ = _wls(-r.los_e[ok], -r.dz_rr[ok], 1.0 / r.sigma_rr[ok] ** 2)
            vel, drift = vel + dv[:3], drift + dv[3]
        r = self.rows(k, pos, np.nan_to_num(vel), clk, 0.0 if not math.isfinite(drift) else drift)
        pdop = float(np.sqrt(np.trace(cov[:3, :3]))) if cov is not None else float("nan")
        rr = r.dz_rr[r.rr_ok]
        return EpochFix(ok=True, pos_e=pos, vel_e=vel, clk_m=float(clk), drift_mps=float(drift), n_pr=r.n,
                        n_rr=int(r.rr_ok.sum()), pdop=pdop, rms_pr_m=float(np.sqrt(np.mean(r.dz_pr ** 2))),
                        rms_rr_mps=float(np.sqrt(np.mean(rr ** 2))) if rr.size else float("nan"))


def _robust_mean(x, sigma):
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return float("nan")
    w = 1.0 / np.asarray(sigma, dtype=float) ** 2
    ok = np.abs(x - np.median(x)) <= 5.0 * np.asarray(sigma, dtype=float)
    if not ok.any():
        ok = np.ones_like(ok)
    return float(np.sum(w[ok] * x[ok]) / np.sum(w[ok]))


def _wls(G, y, w):
    """Weighted least squares of y ≈ [G 1] x; returns (x (4,), unweighted-geometry covariance
    (H^T H)^-1 (4, 4) for the DOP)."""
    H = np.concatenate([G, np.ones((G.shape[0], 1))], axis=1)
    HtW = H.T * w
    x = np.linalg.solve(HtW @ H, HtW @ y)
    return x, np.linalg.inv(H.T @ H)


def _no_fix(pos, reason):
    nan3 = np.full(3, np.nan)
    return EpochFix(ok=False, pos_e=nan3, vel_e=nan3.copy(), clk_m=float("nan"), drift_mps=float("nan"), n_pr=0,
                    n_rr=0, pdop=float("nan"), rms_pr_m=float("nan"), rms_rr_mps=float("nan"), reason=reason)
