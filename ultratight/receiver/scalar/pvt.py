"""Single-epoch position, velocity and time (PVT) from pseudoranges and Dopplers.

* Position + receiver clock bias: iterated weighted least squares (Gauss-Newton)
  on ``rho_i = |R3(w_e tau_i) r_s,i - r| + b`` where ``r_s,i`` is the satellite
  ECEF position at its transmit time and ``R3(w_e tau)`` rotates it into the ECEF
  frame of the receive time (Earth rotation during signal transit, "Sagnac").
* Velocity + clock drift: linear least squares on range rates
  ``rr_i = u_i . (v_s,i - v) + d`` (``u_i`` unit line of sight receiver->satellite).
* Weights: ``sigma_i = sigma / max(sin(elev), SIN_ELEV_FLOOR)`` (optional), so the
  covariance reported is ``(H^T W H)^-1`` in m^2 (and (m/s)^2) given the a-priori sigmas,
  scaled by nothing (the RAIM test checks the a-priori sigmas are believable).
* Elevation mask: applied once a position is known (the first iteration from the
  Earth's centre cannot compute elevations).
* DOPs from the unweighted geometry, in the local ENU frame at the solution.
* RAIM-style check: the weighted residual sum of squares is chi-square with
  ``n - 4`` degrees of freedom; when it exceeds the ``p_fa`` threshold and at least
  six satellites are used, every single-satellite exclusion is tried and the one
  passing with the smallest statistic is kept (one bad satellite excluded).

* Atmospheric delays (optional ``delays``, a function (receiver position, satellite positions)
  -> (n,) metres, e.g. :func:`atmosphere_delays`): evaluated at the unweighted first solution
  (or ``x0``) and subtracted from the pseudoranges; the solution is repeated with the delays at
  the new position while the position moves by more than ``DELAY_REEVAL_M`` (a 10 m position change
  moves a delay by well under 1 mm).

Inputs are already corrected for the satellite clock:
``pseudorange_m = c (t_rx - t_tx,sat-clock) + c dt_sat`` and
``range_rate_mps = -lambda f_D + c d(dt_sat)/dt``.
"""

import functools
from dataclasses import dataclass, field

import numpy as np

from ultratight.chi2 import chdtri
from ultratight.constants import C, OMEGA_E
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh, elev_azim
# the scalar receiver's fix records import the elevation/azimuth function from here by this name

# state indices of the position solution
POS = slice(0, 3)
CLK = 3
N_STATE = 4
SIN_ELEV_FLOOR = 0.1
MAX_ITER = 12
CONV_TOL_M = 1e-4
DELAY_REEVAL_M = 10.0


@dataclass
class PvtSolution:
    valid: bool
    pos_e: np.ndarray                  # (3,) m
    clk_bias_m: float                  # c * receiver clock bias, m
    cov_pos_clk: np.ndarray            # (4,4) m^2, order [x, y, z, c*dt]
    llh: np.ndarray                    # [lat_rad, lon_rad, h_m]
    used: np.ndarray                   # (n,) bool: satellites used in the final solution
    residuals_m: np.ndarray            # (n,) pseudorange residuals (nan where not used)
    elev_rad: np.ndarray               # (n,) elevations at the solution
    dops: dict = field(default_factory=dict)   # gdop, pdop, hdop, vdop, tdop
    vel_e: np.ndarray | None = None    # (3,) m/s
    clk_drift_mps: float = float("nan")
    cov_vel_drift: np.ndarray | None = None
    rr_residuals_mps: np.ndarray | None = None
    raim_stat: float = float("nan")
    raim_threshold: float = float("nan")
    raim_ok: bool = True
    excluded: list = field(default_factory=list)
    delays_m: np.ndarray | None = None   # (n,) atmospheric delays subtracted (None: no model)
    n_iter: int = 0
    message: str = ""


@functools.lru_cache(maxsize=256)
def _chi2_threshold(p_fa, dof):
    return float(chdtri(dof, p_fa))


def rotate_sagnac(sat_pos_e, tau_s):
    """Rotate ECEF vectors (n,3) from their transmit-time frame to the receive-time frame."""
    th = OMEGA_E * np.asarray(tau_s, dtype=float)
    c, s = np.cos(th), np.sin(th)
    out = np.empty_like(sat_pos_e, dtype=float)
    out[:, 0] = c * sat_pos_e[:, 0] + s * sat_pos_e[:, 1]
    out[:, 1] = -s * sat_pos_e[:, 0] + c * sat_pos_e[:, 1]
    out[:, 2] = sat_pos_e[:, 2]
    return out


def dops(rx_pos_e, los_e):
    """GDOP/PDOP/HDOP/VDOP/TDOP from unit line-of-sight vectors (n,3) (receiver -> satellite)."""
    n = los_e.shape[0]
    if n < N_STATE:
        return {k: float("inf") for k in ("gdop", "pdop", "hdop", "vdop", "tdop")}
    llh = ecef_to_llh(np.asarray(rx_pos_e, dtype=float))
    C_el = dcm_ecef_from_enu(llh[0], llh[1])
    H = np.empty((n, N_STATE))
    H[:, :3] = -(los_e @ C_el)          # ENU components
    H[:, 3] = 1.0
    try:
        Q = np.linalg.inv(H.T @ H)
    except np.linalg.LinAlgError:
        return {k: float("inf") for k in ("gdop", "pdop", "hdop", "vdop", "tdop")}
    d = np.diag(Q)
    return {
        "gdop": float(np.sqrt(np.sum(d))),
        "pdop": float(np.sqrt(d[0] + d[1] + d[2])),
        "hdop": float(np.sqrt(d[0] + d[1])),
        "vdop": float(np.sqrt(d[2])),
        "tdop": float(np.sqrt(d[3])),
    }


def _wls_position(sat_pos_e, pr, sigma, x0, mask):
    """Gauss-Newton WLS on the satellites in `mask`. Returns (x (4,), cov, resid (n,), los (n,3), n_iter, ok)."""
    x = np.array(x0, dtype=float)
    idx = np.flatnonzero(mask)
    los = np.zeros((sat_pos_e.shape[0], 3))
    resid = np.full(sat_pos_e.shape[0], np.nan)
    cov = np.full((N_STATE, N_STATE), np.nan)
    if idx.size < N_STATE:
        return x, cov, resid, los, 0, False
    S = sat_pos_e[idx]
    y = pr[idx]
    w = 1.0 / sigma[idx] ** 2
    ok = False
    it = 0
    for it in range(1, MAX_ITER + 1):
        rng0 = np.linalg.norm(S - x[POS], axis=1)
        Sr = rotate_sagnac(S, rng0 / C)
        d = Sr - x[POS]
        rng = np.linalg.norm(d, axis=1)
        u = d / rng[:, None]
        H = np.empty((idx.size, N_STATE))
        H[:, :3] = -u
        H[:, 3] = 1.0
        r = y - (rng + x[CLK])
        HtW = H.T * w
        N = HtW @ H
        try:
            dx = np.linalg.solve(N, HtW @ r)
        except np.linalg.LinAlgError:
            return x, cov, resid, los, it, False
        x += dx
        if np.linalg.norm(dx) < CONV_TOL_M:
            ok = True
            break
    # final residuals / geometry at the solution
    rng0 = np.linalg.norm(S - x[POS], axis=1)
    Sr = rotate_sagnac(S, rng0 / C)
    d = Sr - x[POS]
    rng = np.linalg.norm(d, axis=1)
    u = d / rng[:, None]
    H = np.empty((idx.size, N_STATE))
    H[:, :3] = -u
    H[:, 3] = 1.0
    resid[idx] = y - (rng + x[CLK])
    los[idx] = u
    try:
        cov = np.linalg.inv((H.T * w) @ H)
        cov = 0.5 * (cov + cov.T)
    except np.linalg.LinAlgError:
        ok = False
    return x, cov, resid, los, it, ok and np.all(np.isfinite(x))


def solve_pvt(sat_pos_e, pseudorange_m, sat_vel_e=None, range_rate_mps=None, *,
              sigma_pr_m=3.0, sigma_rr_mps=0.1, x0=None, mask_deg=5.0, elev_weight=True,
              raim=True, p_fa=1e-4, delays=None):
    """Position/clock (and velocity/drift when range rates are given) at one receive epoch.

    sat_pos_e, sat_vel_e: (n,3) satellite ECEF states at transmit time (m, m/s);
    pseudorange_m, range_rate_mps: (n,) corrected for satellite clock (see module doc);
    sigma_pr_m, sigma_rr_mps: scalar or (n,) a-priori 1-sigma at zenith;
    x0: optional initial [x, y, z, c*dt] (default: Earth centre, 0);
    delays: optional function (rx_pos_e (3,), sat_pos_e (n,3)) -> (n,) delays (m) to remove.
    Non-finite measurements are ignored. Returns a :class:`PvtSolution`.
    """
    sat_pos_e = np.asarray(sat_pos_e, dtype=float).reshape(-1, 3)
    pr = np.asarray(pseudorange_m, dtype=float).ravel()
    n = pr.size
    sig0 = np.broadcast_to(np.asarray(sigma_pr_m, dtype=float), (n,)).copy()
    finite = np.isfinite(pr) & np.all(np.isfinite(sat_pos_e), axis=1)
    x = np.zeros(N_STATE) if x0 is None else np.asarray(x0, dtype=float).copy()
    empty = PvtSolution(False, x[POS].copy(), float(x[CLK]), np.full((4, 4), np.nan),
                        np.full(3, np.nan), np.zeros(n, bool), np.full(n, np.nan), np.full(n, np.nan))
    if finite.sum() < N_STATE:
        empty.message = f"only {int(finite.sum())} usable pseudoranges (need 4)"
        return empty
    # 1) unweighted, unmasked solution to get a position (elevations)
    if x0 is None or np.linalg.norm(x[POS]) < 1e6:
        x, _, _, _, _, ok = _wls_position(sat_pos_e, pr, np.ones(n), x, finite)
        if not ok:
            empty.message = "least squares did not converge"
            return empty
    elev, _ = elev_azim(x[POS], sat_pos_e)
    mask = finite & (elev >= np.radians(mask_deg))
    sigma = sig0 / np.maximum(np.sin(elev), SIN_ELEV_FLOOR) if elev_weight else sig0
    pr_raw, d_atm = pr, None
    at = x[POS].copy()
    for _ in range(3):
        if delays is not None:
            d_atm = np.where(finite, np.asarray(delays(at, sat_pos_e), dtype=float), 0.0)
            pr = pr_raw - d_atm
        x, cov, resid, los, n_iter, ok = _wls_position(sat_pos_e, pr, sigma, x, mask)
        if delays is None or not ok or np.linalg.norm(x[POS] - at) < DELAY_REEVAL_M:
            break
        at = x[POS].copy()
    if not ok:
        empty.message = f"least squares failed with {int(mask.sum())} satellites above the {mask_deg} deg mask"
        return empty
    excluded = []
    stat = float(np.nansum((resid / sigma) ** 2))
    dof = int(mask.sum()) - N_STATE
    thr = _chi2_threshold(p_fa, dof) if dof > 0 else float("inf")
    raim_ok = stat <= thr
    if raim and not raim_ok and dof >= 2:
        best = None
        for j in np.flatnonzero(mask):
            m2 = mask.copy()
            m2[j] = False
            x2, cov2, res2, los2, it2, ok2 = _wls_position(sat_pos_e, pr, sigma, x, m2)
            if not ok2:
                continue
            s2 = float(np.nansum((res2 / sigma) ** 2))
            t2 = _chi2_threshold(p_fa, dof - 1)
            if s2 <= t2 and (best is None or s2 < best[0]):
                best = (s2, t2, j, x2, cov2, res2, los2, it2, m2)
        if best is not None:
            stat, thr, j, x, cov, resid, los, n_iter, mask = best
            excluded = [int(j)]
            raim_ok = True
            # residual of the excluded satellite against the new solution, for reporting
    elev, _ = elev_azim(x[POS], sat_pos_e)
    sol = PvtSolution(True, x[POS].copy(), float(x[CLK]), cov, ecef_to_llh(x[POS].copy()), mask.copy(),
                      resid, elev, dops(x[POS], los[mask]), raim_stat=stat, raim_threshold=thr,
                      raim_ok=bool(raim_ok), excluded=excluded, delays_m=d_atm, n_iter=n_iter)
    if range_rate_mps is not None and sat_vel_e is not None:
        _solve_velocity(sol, sat_pos_e, np.asarray(sat_vel_e, dtype=float).reshape(-1, 3),
                        np.asarray(range_rate_mps, dtype=float).ravel(), sigma_rr_mps, elev_weight)
    return sol


def _solve_velocity(sol, sat_pos_e, sat_vel_e, rr, sigma_rr_mps, elev_weight):
    n = rr.size
    m = sol.used & np.isfinite(rr) & np.all(np.isfinite(sat_vel_e), axis=1)
    sol.rr_residuals_mps = np.full(n, np.nan)
    if m.sum() < N_STATE:
        return
    idx = np.flatnonzero(m)
    rng0 = np.linalg.norm(sat_pos_e[idx] - sol.pos_e, axis=1)
    tau = rng0 / C
    Sr = rotate_sagnac(sat_pos_e[idx], tau)
    Vr = rotate_sagnac(sat_vel_e[idx], tau)
    d = Sr - sol.pos_e
    u = d / np.linalg.norm(d, axis=1)[:, None]
    sig = np.broadcast_to(np.asarray(sigma_rr_mps, dtype=float), (n,))[idx]
    if elev_weight:
        sig = sig / np.maximum(np.sin(sol.elev_rad[idx]), SIN_ELEV_FLOOR)
    w = 1.0 / sig ** 2
    H = np.empty((idx.size, N_STATE))
    H[:, :3] = -u
    H[:, 3] = 1.0
    HtW = H.T * w
    try:
        cov = np.linalg.inv(HtW @ H)
    except np.linalg.LinAlgError:
        return
    # d/dt [R3(w tau) r_s(t - tau)] = R3' w tau_dot r_s + R3 v_s (1 - tau_dot); tau_dot = (rr - drift)/c
    # is taken from a first pass (mm/s-level terms).
    th = OMEGA_E * tau
    dRr = np.stack([-np.sin(th) * sat_pos_e[idx, 0] + np.cos(th) * sat_pos_e[idx, 1],
                    -np.cos(th) * sat_pos_e[idx, 0] - np.sin(th) * sat_pos_e[idx, 1],
                    np.zeros(idx.size)], axis=1) * OMEGA_E
    tau_dot = np.zeros(idx.size)
    for _ in range(2):
        y = rr[idx] - np.sum(u * (Vr * (1.0 - tau_dot)[:, None] + dRr * tau_dot[:, None]), axis=1)
        x = cov @ (HtW @ y)
        tau_dot = (rr[idx] - x[3]) / C
    sol.vel_e = x[:3].copy()
    sol.clk_drift_mps = float(x[3])
    sol.cov_vel_drift = 0.5 * (cov + cov.T)
    sol.rr_residuals_mps[idx] = y - H @ x


def atmosphere_delays(model, tow_s, parts=None):
    """A ``delays`` function for :func:`solve_pvt` from an
    :class:`ultratight.signals.atmosphere.AtmosphereModel` at GPS time ``tow_s``; when ``parts``
    (a dict) is given, the last evaluation's ``iono_m`` and ``tropo_m`` arrays are stored in it."""
    def f(rx_pos_e, sat_pos_e):
        llh = ecef_to_llh(np.asarray(rx_pos_e, dtype=float).copy())
        el, az = elev_azim(rx_pos_e, sat_pos_e)
        iono, tropo = model.delays_m(llh[0], llh[1], llh[2], el, az, tow_s)
        if parts is not None:
            parts["iono_m"], parts["tropo_m"] = iono, tropo
        return iono + tropo
    return f
