"""Measurement rows of the INS/GNSS filter: loose GNSS fixes, tight pseudorange / range-rate,
zero-velocity (ZUPT) and non-holonomic (NHC) pseudo-measurements, and the χ² gate.

Error state: :mod:`ultratight.ins.error_model`'s layout with the position block in metres
(north, east, up), as :func:`ultratight.fusion.coupling.integration.discrete_model` carries it.
Every row is "prediction minus measurement" = H δx − v (estimate minus truth).

Loose (:func:`loose_rows`): the antenna position predicted at the GNSS epoch,
``r_ant = r + v (t_gnss − t_node) + C_lb l`` (ENU metres against the fix), and when the source
has a velocity ``v_ant = v + C_lb (ω_ib_b × l)``::

    δr_ant = P δpos_NEU + [l_l ×] φ                      (P: N, E, U -> E, N, U)
    δv_ant = δv + [a_l ×] φ − C_lb [l ×] b_g             (a_l = C_lb (ω × l))

R is diagonal from the fix's σ columns: ``σ = max(σ_col, floor) × factor(quality)`` (options
module: floors 2 cm / 3 cm/s, factor 1 fixed, 5 float and single); a velocity without σ gets
``vel_sigma_default_mps``.

Tight (:class:`TightSource`): the rows of the tight measurement object (``meas.rows``) at the
antenna's ECEF position and velocity, H from :func:`ultratight.fusion.coupling.tight.measurement_matrix`
with the lines of sight in ENU and the lever arm; R = diag(σ_pr², σ_rr²).

ZUPT: ``z = v`` (the velocity should be zero), H = [0 I 0 …], σ ``zupt_sigma_mps``.
NHC: the body lateral and vertical velocities ``v_b = C_lbᵀ v`` should be zero:
``δv_b = C_lbᵀ δv − C_lbᵀ [v ×] φ`` (rows y and z of the FLU body), σ ``nhc_sigma_mps``.

χ² gate (:func:`gate`): NIS = yᵀ (H P Hᵀ + R)⁻¹ y against the χ²(m) quantile at the false-alarm
probability ``gate_p``; loose coupling gates the whole epoch, tight coupling each row (χ²(1)),
so one bad satellite does not cost the epoch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ultratight.chi2 import chdtri
from ultratight.fusion.coupling.tight import measurement_matrix
from ultratight.fusion.estimators.guards import symmetrize
from ultratight.ins import error_model as em
from ultratight.constants import OMEGA_E
from ultratight.ins.attitude import quat_to_dcm, skew
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh, llh_to_ecef, radii

P_NEU_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Fix:
    """One GNSS epoch as the filter uses it (σ after floors and quality factors)."""
    t: float
    llh: np.ndarray
    vel_enu: np.ndarray        # NaN when absent / not used
    sig_pos: np.ndarray        # E, N, U (m)
    sig_vel: np.ndarray        # E, N, U (m/s)
    quality: int


class LooseSource:
    """GNSS fixes (:class:`ultratight.signals.observations.GnssFixes`) as :class:`Fix` per epoch."""
    kind = "loose"

    def __init__(self, fixes, opts):
        self.fx = fixes
        self.o = opts
        self.t = np.asarray(fixes.t, float)
        self.n = int(self.t.shape[0])

    def factor(self, q):
        return float(self.o.quality_factor.get(int(q), self.o.other_quality_factor))

    def fix(self, k):
        fx, o = self.fx, self.o
        llh = np.asarray(fx.llh[k], float)
        if not np.all(np.isfinite(llh)):
            return None
        f = self.factor(fx.quality[k])
        sp = np.asarray(fx.sigma_pos_enu[k], float)
        sp = np.where(np.isfinite(sp), np.maximum(sp, o.pos_sigma_floor_m), max(1.0, o.pos_sigma_floor_m)) * f
        v = np.asarray(fx.vel_enu[k], float) if o.use_velocity else np.full(3, np.nan)
        sv = np.asarray(fx.sigma_vel_enu[k], float)
        sv = np.where(np.isfinite(sv), np.maximum(sv, o.vel_sigma_floor_mps), o.vel_sigma_default_mps) * f
        return Fix(float(self.t[k]), llh, v if np.all(np.isfinite(v)) else np.full(3, np.nan), sp, sv,
                   int(fx.quality[k]))


def enu_offset(llh_a, llh_b):
    """ENU metres of llh_a − llh_b (small differences; radii at llh_b)."""
    rm, rn = radii(llh_b[0])
    d = np.asarray(llh_a, float) - np.asarray(llh_b, float)
    return np.array([d[1] * (rn + llh_b[2]) * math.cos(llh_b[0]), d[0] * (rm + llh_b[2]), d[2]])


def cross3(a, b):
    """a × b of two 3-vectors (the products and differences of np.cross, without its general-shape
    set-up, which cost more than the arithmetic at every GNSS epoch)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def loose_rows(fix, x, omega_b, lever_b, t_node):
    """(z, H, R) of a loose GNSS epoch (module docstring) at the SINS state ``x`` of time ``t_node``."""
    C = quat_to_dcm(x[0:4])
    lever_b = np.asarray(lever_b, float)
    l_l = C @ lever_b
    v = x[4:7]
    z_pos = enu_offset(x[7:10], fix.llh) + v * (fix.t - t_node) + l_l
    rows = [z_pos]
    Hp = np.zeros((3, em.N15))
    Hp[:, em.POS] = P_NEU_TO_ENU
    Hp[:, em.ATT] = skew(l_l)
    Hs, sig = [Hp], [fix.sig_pos]
    if np.all(np.isfinite(fix.vel_enu)):
        a_l = C @ cross3(omega_b, lever_b)
        rows.append(v + a_l - fix.vel_enu)
        Hv = np.zeros((3, em.N15))
        Hv[:, em.VEL] = np.eye(3)
        Hv[:, em.ATT] = skew(a_l)
        Hv[:, em.BG] = -C @ skew(lever_b)
        Hs.append(Hv)
        sig.append(fix.sig_vel)
    return np.concatenate(rows), np.vstack(Hs), np.diag(np.concatenate(sig) ** 2)


def zupt_rows(x, sigma, n_states):
    """(z, H, R) of a zero-velocity update."""
    H = np.zeros((3, n_states))
    H[:, em.VEL] = np.eye(3)
    return x[4:7].copy(), H, np.eye(3) * sigma ** 2


def nhc_rows(x, sigma, n_states):
    """(z, H, R) of the non-holonomic constraint (body lateral and vertical velocity zero)."""
    C = quat_to_dcm(x[0:4])
    v = x[4:7]
    Ct = C.T[1:3]
    H = np.zeros((2, n_states))
    H[:, em.VEL] = Ct
    H[:, em.ATT] = -Ct @ skew(v)
    return Ct @ v, H, np.eye(2) * sigma ** 2


def nis_of(z, H, R, P):
    """(NIS, S) of the rows against the prior covariance ``P``."""
    S = symmetrize(H @ P @ H.T + R)
    return float(z @ np.linalg.solve(S, z)), S


@lru_cache(maxsize=64)
def chi2_threshold(p, dof):
    """χ²(dof) quantile exceeded with probability p."""
    return float(chdtri(dof, p))


def gate(z, H, R, P, p, per_row=False):
    """(keep mask, NIS, reason) of the χ² gate (module docstring); p None = no gate."""
    nis, S = nis_of(z, H, R, P)
    m = z.shape[0]
    if p is None:
        return np.ones(m, bool), nis, ""
    if per_row:
        stat = z * z / np.diag(S)
        thr = chi2_threshold(p, 1)
        keep = stat <= thr
        reason = "" if keep.all() else f"chi2 rows {np.flatnonzero(~keep).tolist()} above {thr:.1f} (p={p:g})"
        return keep, nis, reason
    thr = chi2_threshold(p, m)
    if nis > thr:
        return np.zeros(m, bool), nis, f"chi2 NIS {nis:.1f} > {thr:.1f} (p={p:g}, {m} rows)"
    return np.ones(m, bool), nis, ""


class TightSource:
    """The tight measurement object (``meas.t``, ``meas.rows``, ``meas.initial_clock``) seen by the filter.

    :meth:`fix` gives a least-squares position/velocity per epoch (Gauss–Newton on the rows,
    ≥ 4 satellites) for the alignment; :meth:`rows` the 17-state (z, H, R)."""
    kind = "tight"

    def __init__(self, meas, opts):
        self.m = meas
        self.o = opts
        self.t = np.asarray(meas.t, float)
        self.n = int(self.t.shape[0])

    def fix(self, k, iters=8):
        """:class:`Fix` of epoch k: the object's own single-point fix (``spp``) when it has one, else
        Gauss–Newton on the rows from the Earth's centre; None without four satellites."""
        if hasattr(self.m, "spp"):
            f = self.m.spp(k)
            if not f.ok or not np.all(np.isfinite(f.pos_e)):
                return None
            pos, vel = np.asarray(f.pos_e, float), np.asarray(f.vel_e, float)
        else:
            pos, vel = self._lsq(k, iters)
            if pos is None:
                return None
        llh = np.asarray(ecef_to_llh(pos), float)
        C_el = dcm_ecef_from_enu(llh[0], llh[1])
        r = self.m.rows(k, pos, np.nan_to_num(vel), 0.0, 0.0)
        A = np.hstack([np.asarray(r.los_e, float), np.ones((len(r.dz_pr), 1))])
        G = np.linalg.pinv(A.T @ A)
        dop = np.sqrt(np.maximum(np.diag(C_el.T @ G[:3, :3] @ C_el), 0.0))
        ok = np.isfinite(np.asarray(r.sigma_rr, float))
        s_rr = float(np.median(np.asarray(r.sigma_rr, float)[ok])) if ok.any() else np.inf
        v_enu = C_el.T @ vel if np.all(np.isfinite(vel)) else np.full(3, np.nan)
        return Fix(float(self.t[k]), llh, v_enu, dop * float(np.median(r.sigma_pr)), dop * s_rr, 5)

    def _lsq(self, k, iters):
        pos, vel = np.zeros(3), np.zeros(3)
        clk = drift = 0.0
        for _ in range(iters):
            r = self.m.rows(k, pos, vel, clk, drift)
            if r is None or len(r.dz_pr) < 4:
                return None, None
            A = np.hstack([-np.asarray(r.los_e), np.ones((len(r.dz_pr), 1))])
            d = np.linalg.lstsq(A, np.asarray(r.dz_pr, float), rcond=None)[0]
            pos, clk = pos - d[:3], clk - d[3]
            ok = np.isfinite(np.asarray(r.dz_rr, float))
            if ok.sum() >= 4:
                dv = np.linalg.lstsq(A[ok], np.asarray(r.dz_rr, float)[ok], rcond=None)[0]
                vel, drift = vel - dv[:3], drift - dv[3]
        return pos, vel

    def initial_clock(self, k, pos_e, vel_e):
        return self.m.initial_clock(k, pos_e, vel_e)

    def rows(self, k, x, clk, omega_b, lever_b, keep=None):
        """(z, H, R, keys) of epoch k at the SINS state ``x`` (antenna through the lever arm), or None;
        ``keys`` name the rows (+PRN pseudorange, −PRN range rate)."""
        C = quat_to_dcm(x[0:4])
        lever_b = np.asarray(lever_b, float)
        l_l = C @ lever_b
        a_l = C @ cross3(omega_b, lever_b)
        C_el = dcm_ecef_from_enu(x[7], x[8])
        pos_e = np.asarray(llh_to_ecef(x[7], x[8], x[9]), float) + C_el @ l_l
        vel_e = C_el @ (x[4:7] + a_l)
        r = self.m.rows(k, pos_e, vel_e, float(clk[0]), float(clk[1]), keep=keep)
        if r is None or len(r.dz_pr) == 0:
            return None
        los_l = np.asarray(r.los_e, float) @ C_el
        w_ie_l = np.array([0.0, OMEGA_E * math.cos(x[7]), OMEGA_E * math.sin(x[7])])
        H = measurement_matrix(los_l, P_NEU_TO_ENU, lever=(C, l_l, a_l, w_ie_l))
        z = np.concatenate([np.asarray(r.dz_pr, float), np.asarray(r.dz_rr, float)])
        sig = np.concatenate([np.asarray(r.sigma_pr, float), np.asarray(r.sigma_rr, float)])
        ok = np.isfinite(z) & np.isfinite(sig)          # a row without Doppler keeps its pseudorange only
        prn = np.asarray(r.prn, int)
        keys = np.concatenate([prn, -prn])[ok]          # +PRN pseudorange row, −PRN range-rate row
        return z[ok], H[ok], np.diag(sig[ok] ** 2), keys
