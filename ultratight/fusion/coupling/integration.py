"""Loose (15-state) and tight (17-state) SINS/GNSS integration runners with pluggable cores
(Fang 2017: tight SINS/GPS with AKF/IAKF; Cai et al. 2020: loose SINS/GNSS with the χ² +
Newton robust KF).

Error state: the layout of :mod:`ultratight.ins.error_model` (ATT, VEL, POS, BG, BA [, CLK,
DRIFT]), with one change of units inside the filters: the position block is carried in metres
(north, east, up) instead of (dlat, dlon, dh), ``x_m = T x`` with T = diag(…, M + h,
(N + h) cos L, 1, …).  Φ and Q are transformed as T Φ T⁻¹ and T Q Tᵀ.  This makes the Fang 2017
GDOP noise sum (eq. 25: "position terms in metres") and the Cai et al. 2020 measurement (6 × 15,
H = [I₆ 0] on POS, VEL, eq. 8) direct, and keeps P well scaled.  The position row order (N, E,
U) is the printed order of Table 1 (latitude, longitude, height).

Sign convention (estimate minus truth, as the error model): the measurement is always
"SINS prediction minus GNSS measurement", z = H δx − v:

* tight (Fang 2017 eqs. 4–5): ``z_ρ = ρ_SINS − ρ_G = −u·δr + δt_u − v``,
  ``z_ρ̇ = ρ̇_SINS − ρ̇_G = −u·δv + δt_ru − v`` with u the unit line of sight receiver → satellite
  (the paper prints no H; this project's −e_jᵀ with e_j satellite → receiver, written the other way round);
* loose (Cai et al. 2020 eq. 8, printed Z = r_GNSS − r_SINS = −(this)): ``z = [r_SINS − r_GNSS;
  v_SINS − v_GNSS] = [δr; δv] − v``.

The runner closes the loop after every update: position/velocity/attitude are corrected in the
SINS state, gyro/accelerometer bias estimates accumulate and compensate later increments, the
clock estimate is corrected, and the core's error state returns to zero
(:func:`ultratight.ins.error_model.feedback_and_reset`).

Cores (by name, :data:`CORES`):

``kf``          Joseph-form Kalman filter with fixed Q, R (Cai et al. 2020 eqs. 1–5).
``akf``         innovation-based adaptive KF, window N (Fang 2017 eqs. 6–15,
                :class:`ultratight.fusion.estimators.adaptive.AKF`), started from the given Q, R.
``akf0``        the AKF started from the *true* noise (Fang 2017's AKF0); by default the
                alternative reading of the paper ("fixed true Q, R": ``akf0_adaptive = False``),
                the literal one (eq. 15 still adapting) with ``akf0_adaptive = True``.
``iakf``        improved AKF (Fang 2017 eqs. 16–26, :class:`ultratight.fusion.estimators.adaptive.IAKF`) with
                the best-4 GDOP selection of §3.1 (tight only).  Defaults (docs/integration-
                experiments.md): R̂ and Q̂ from the first epoch over the terms available
                (``iakf_start="growing"``), eq. 26 projected onto the eq. 3 noise structure
                (``"model-diag"``) and capped at the given noise (``iakf_q_ceiling``).
``chi2-newton`` Cai et al. 2020's per-dimension χ² detection with Newton-extrapolated replacement,
                this project's implementable reading (innovation as the proxy of V, §3,
                :func:`ultratight.fusion.estimators.robust.chi2_newton_kf_update`).
``chi2-newton-lit`` the paper-literal reading: Z′(i) = Z(i) − V(i) + V′(i) with the stored noise
                realisations (simulation only).
``ins-only``    free inertial from the same start (no update; P still propagated).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ultratight.chi2 import chdtri
from ultratight.errors import ConfigError
from ultratight.fusion.estimators.adaptive import AKF, IAKF
from ultratight.fusion.estimators.filters import kf_update
from ultratight.fusion.estimators.guards import symmetrize
from ultratight.fusion.estimators.robust import ChiSquareNewton, chi2_newton_kf_update, newton_coefficients
from ultratight.ins import error_model as em
from ultratight.ins.attitude import dcm_to_rotvec, quat_mult, quat_to_dcm, rotvec_to_quat
from ultratight.ins.earth import dcm_ecef_from_enu, llh_increment_scale, radii
from ultratight.ins.sins import make_state, sins_run_final, state_pos_vel_e
from ultratight.signals.synth.obssim import gdop_best4, predict_observables

ATT, VEL, POS, BG, BA = em.ATT, em.VEL, em.POS, em.BG, em.BA
CLK, DRIFT = em.CLK, em.DRIFT

CORES = ("kf", "akf", "akf0", "iakf", "chi2-newton", "chi2-newton-lit", "ins-only")


# --------------------------------------------------------------------------- cores
class _Core:
    """Common interface: ``predict(Phi, Q)``, ``update(z, H, R, aux) -> info``, ``reset()``."""
    adaptive = False

    def __init__(self, P0):
        self.x = np.zeros(P0.shape[0])
        self.P = symmetrize(np.asarray(P0, float))
        self.n_faults = 0
        self.n_screened = 0

    def predict(self, Phi, Q):
        self.x = Phi @ self.x
        self.P = symmetrize(Phi @ self.P @ Phi.T + Q)

    def reset(self):
        self.x[:] = 0.0

    def update(self, z, H, R, aux):
        res = kf_update(self.x, self.P, z, H, R)       # Cai et al. 2020 eqs. 1–5 (Joseph)
        self.x, self.P = res.x, res.P
        return {"nis": res.nis}


class KFCore(_Core):
    pass


class InsOnlyCore(_Core):
    def update(self, z, H, R, aux):
        return {"nis": np.nan}


class AKFCore(_Core):
    """Fang 2017 AKF (eqs. 6–15); Q adapted by eq. 14, R by eq. 8 once N innovations exist."""
    adaptive = True

    def __init__(self, P0, Q0, R0, window=20, adapt=True):
        super().__init__(P0)
        self.f = AKF(self.x, self.P, Q0, R0, window=window, adapt_q=adapt, adapt_r=adapt)
        self._Q_given = not adapt

    def predict(self, Phi, Q):
        if self._Q_given or len(self.f.eps) < self.f.N:
            self.f.Q = Q        # the given Q until eq. 14 has a full window
        self.f.x, self.f.P = self.x, self.P
        self.x, self.P = self.f.predict(Phi)

    def update(self, z, H, R, aux):
        if self._Q_given:
            self.f.R = R
        self.f.x, self.f.P = self.x, self.P
        res = self.f.update(z, H)
        self.x, self.P = self.f.x.copy(), self.f.P.copy()
        return {"nis": res.nis}


class IAKFCore(_Core):
    """Fang 2017 IAKF (eqs. 16–26): R from GDOP (eqs. 24–25), Q windowed (eq. 26); ``start``,
    ``q_structure`` and ``q_ceiling`` as :class:`ultratight.fusion.estimators.adaptive.IAKF`."""
    adaptive = True

    def __init__(self, P0, Q0, R0, m_sat, window=20, r_source="lsq", adapt_q=True, q_structure="model-diag",
                 start="growing", q_ceiling=True):
        super().__init__(P0)
        self.f = IAKF(self.x, self.P, Q0, R0, pr_rows=np.arange(m_sat), prr_rows=np.arange(m_sat, 2 * m_sat),
                      pos_clk_idx=[6, 7, 8, CLK], vel_drift_idx=[3, 4, 5, DRIFT], window=window,
                      r_source=r_source, adapt_q=adapt_q, q_structure=q_structure, start=start,
                      q_ceiling=q_ceiling and adapt_q)
        self.wants_q_basis = adapt_q and q_structure != "full"

    def set_q_basis(self, B, Q_fixed):
        self.f.q_basis, self.f.q_fixed = B, Q_fixed

    def predict(self, Phi, Q):
        self.f.Q_given = Q      # the given Q of this step (the ceiling of the projected Q estimate)
        if not self.f.adapt_q or not self.f.ready(len(self.f.qterms)):
            self.f.Q = Q        # the given Q until eq. 26 has its terms (always, without Q adaptation)
        self.f.x, self.f.P = self.x, self.P
        self.x, self.P = self.f.predict(Phi)

    def update(self, z, H, R, aux):
        self.f.x, self.f.P = self.x, self.P
        res = self.f.update(z, H, los_unit=aux["los_e"], gdop_pr=aux.get("gdop"))
        self.x, self.P = self.f.x.copy(), self.f.P.copy()
        return {"nis": res.nis}


class Chi2NewtonCore(_Core):
    """Cai et al. 2020: per-dimension χ² (eq. 15) + Newton replacement (eqs. 21–28), both readings."""

    def __init__(self, P0, m, alpha=0.01, delta=4.0, order=4, literal=False, guard=True, release_after=None,
                 weight_replacements=False):
        super().__init__(P0)
        self.det = ChiSquareNewton(m, alpha=alpha, delta=delta, order=order, guard=guard,
                                   release_after=None if literal else release_after,
                                   weight_replacements=weight_replacements and not literal)
        self.literal = literal
        self._hist = []          # literal reading: the noise values actually used, newest last

    def update(self, z, H, R, aux):
        self.n_screened += z.shape[0]
        if not self.literal:
            before = self.det.n_faults
            res = chi2_newton_kf_update(self.x, self.P, z, H, R, self.det)
            self.n_faults += self.det.n_faults - before
            self.x, self.P = res.x, res.P
            return {"nis": res.nis, "faulty": res.info["faulty"]}
        # paper-literal: detect on the innovation (eqs. 10–16), replace the stored noise sample
        v = np.asarray(aux["noise"], float)            # the noise as it enters z
        zhat = H @ self.x
        D = symmetrize(H @ self.P @ H.T + R)           # eq. 13
        J = z - zhat                                   # eq. 10
        faulty = J * J / np.diag(D) > self.det.threshold   # eqs. 15–16
        used = v.copy()
        if faulty.any():
            if len(self._hist) >= self.det.order:
                M = newton_coefficients(self.det.order)
                ext = M @ np.array(self._hist[::-1][: self.det.order]) / self.det.delta   # eqs. 23, 27
                if self.det.guard:      # a replacement that itself fails the test is dropped (ChiSquareNewton)
                    ext = np.where(ext * ext / np.diag(D) > self.det.threshold, 0.0, ext)
                used[faulty] = ext[faulty]
                z = z - v + used                           # eqs. 24, 28: Z' = Z − V + V'
            else:
                keep = ~faulty                             # fewer than 4 past epochs: drop (this project's choice)
                z, H, R = z[keep], H[keep], R[np.ix_(keep, keep)]
            self.n_faults += int(faulty.sum())
        self._hist.append(used)
        if z.shape[0]:
            res = kf_update(self.x, self.P, z, H, R)
            self.x, self.P = res.x, res.P
        return {"nis": np.nan, "faulty": faulty}


def make_core(name, P0, Q0, R0, *, window=20, m_sat=4, alpha=0.01, delta=4.0, akf0_adaptive=False,
              iakf_r_source="lsq", iakf_adapt_q=True, iakf_q_structure="model-diag", iakf_start="growing",
              iakf_q_ceiling=True, newton_guard=True, release_after=None, weight_replacements=False):
    """A core by name (see the module docstring); Q0/R0 are the *given* noise (true or wrong)."""
    if name == "kf":
        return KFCore(P0)
    if name == "ins-only":
        return InsOnlyCore(P0)
    if name == "akf":
        return AKFCore(P0, Q0, R0, window=window, adapt=True)
    if name == "akf0":
        return AKFCore(P0, Q0, R0, window=window, adapt=bool(akf0_adaptive))
    if name == "iakf":
        return IAKFCore(P0, Q0, R0, m_sat, window=window, r_source=iakf_r_source, adapt_q=iakf_adapt_q,
                        q_structure=iakf_q_structure, start=iakf_start, q_ceiling=iakf_q_ceiling)
    if name in ("chi2-newton", "chi2-newton-lit"):
        return Chi2NewtonCore(P0, R0.shape[0], alpha=alpha, delta=delta, literal=name.endswith("-lit"),
                              guard=newton_guard, release_after=release_after,
                              weight_replacements=weight_replacements)
    raise ConfigError(f"unknown integration core {name!r}; expected one of {', '.join(CORES)}")


# --------------------------------------------------------------------------- model functions
def pos_scale(lat, h):
    """T_pos (3,): metres (N, E, U) per (dlat, dlon, dh) at (lat, h)
    (:func:`ultratight.ins.earth.llh_increment_scale` at the radii of ``lat``)."""
    rm, rn = radii(lat)
    return llh_increment_scale(lat, h, rm, rn)


def discrete_model(sins_x, f_b, dt, q_psd, n_states, clock_qd=None, basis=False):
    """(Φ, Q_d) of the error model over dt at the SINS state, position block in metres.

    Φ: second-order Taylor series of exp(F dt); Q_d by the trapezoidal rule
    (Φ G Q_c Gᵀ Φᵀ + G Q_c Gᵀ) dt/2 (as :func:`ultratight.fusion.coupling.tight.phi_q`); the clock block,
    when given, is the exact discrete clock noise ``clock_qd`` (2 × 2).

    ``basis=True`` also returns the noise structure of Fang 2017 eq. 3 (W = gyro 3, accelerometer
    3 [, clock bias, clock drift] white noises): ``(Φ, Q_d, B, Q_fixed)`` with B (k, n, n) the
    discretised Q of each of these noises alone at unit PSD (same rule; the clock pair of
    δṫ_u = δt_ru + w_tu, δṫ_ru = w_tru exactly: dt·e_u e_uᵀ and [[dt³/3, dt²/2], [dt²/2, dt]])
    and Q_fixed the rest of Q_d (the bias-driving floors of :func:`imu_psd`, not part of W)."""
    q_lb, vel, llh = sins_x[0:4], sins_x[4:7], sins_x[7:10]
    F = em.F_matrix(q_lb, vel, llh, f_b, n_states=n_states)
    G = em.G_matrix(q_lb, n_states=n_states)
    Phi = em.taylor_phi(F, dt)
    GQG = (G * q_psd) @ G.T
    Qd = 0.5 * (Phi @ GQG @ Phi.T + GQG) * dt
    if clock_qd is not None:
        Qd[CLK:DRIFT + 1, CLK:DRIFT + 1] = clock_qd
    T = np.ones(n_states)
    T[POS] = pos_scale(llh[0], llh[2])
    W = T[:, None] * T[None, :]
    Phi_m = Phi * T[:, None] / T[None, :]
    Qd = symmetrize(Qd * W)
    if not basis:
        return Phi_m, Qd
    cols = list(range(em.NOISE_GYRO.start, em.NOISE_ACCEL.stop))
    Gw = G[:, cols]
    PG = Phi @ Gw
    B = 0.5 * dt * (np.einsum("ik,jk->kij", PG, PG) + np.einsum("ik,jk->kij", Gw, Gw))
    qf = np.asarray(q_psd, float).copy()
    qf[cols] = 0.0
    if n_states == em.N17:
        qf[em.NOISE_CLK] = qf[em.NOISE_DRIFT] = 0.0
        Bc = np.zeros((2, n_states, n_states))
        Bc[0, CLK, CLK] = dt
        Bc[1, CLK, CLK], Bc[1, CLK, DRIFT], Bc[1, DRIFT, CLK], Bc[1, DRIFT, DRIFT] = dt**3 / 3, dt**2 / 2, dt**2 / 2, dt
        B = np.concatenate([B, Bc])
    GQf = (G * qf) @ G.T
    Qf = 0.5 * (Phi @ GQf @ Phi.T + GQf) * dt
    if n_states == em.N17:
        Qf[CLK:DRIFT + 1, CLK:DRIFT + 1] = 0.0
    return Phi_m, Qd, B * W[None], symmetrize(Qf * W)


def imu_psd(gyro_white, accel_white, gyro_bias_floor=1e-18, accel_bias_floor=1e-14, n_states=15):
    """Diagonal noise PSD (NOISE_* order): gyro / accel white noise as rad/√s, (m/s)/√s (per axis
    or scalar); the random-constant biases get a tiny driving noise (floors, PSD) that keeps them
    estimable, as in :func:`ultratight.fusion.coupling.tight.phi_q`."""
    q = np.zeros(em.NW15 if n_states == 15 else em.NW17)
    q[em.NOISE_GYRO] = np.broadcast_to(np.asarray(gyro_white, float) ** 2, (3,))
    q[em.NOISE_ACCEL] = np.broadcast_to(np.asarray(accel_white, float) ** 2, (3,))
    q[em.NOISE_BG] = gyro_bias_floor
    q[em.NOISE_BA] = accel_bias_floor
    return q


# --------------------------------------------------------------------------- runner
@dataclass
class RunInput:
    """Everything a run needs (shared by all methods of one seed).

    ``t_imu`` edges (n_imu + 1,) and increments ``dtheta``/``dv`` (n_imu, 3) with errors;
    ``t_gnss`` (n_ep,) update times (multiples of the IMU step); truth at ``t_gnss``:
    ``truth_llh``, ``truth_vel``, ``truth_q`` and the true biases ``bias_true`` [bg, ba] (6,),
    true clock ``clk_true`` (n_ep, 2) for tight runs; ``x0_est`` the initial SINS state
    (truth + initial errors), ``clk0_est`` (2,)."""
    t_imu: np.ndarray
    dtheta: np.ndarray
    dv: np.ndarray
    t_gnss: np.ndarray
    truth_llh: np.ndarray
    truth_vel: np.ndarray
    truth_q: np.ndarray
    bias_true: np.ndarray
    x0_est: np.ndarray
    clk_true: np.ndarray | None = None
    clk0_est: np.ndarray | None = None


def _true_error(x_sins, bias_est, clk_est, k, inp, n_states):
    """Full error state of the corrected solution against truth (position in metres N, E, U)."""
    e = np.zeros(n_states)
    Ce = quat_to_dcm(x_sins[0:4])
    Ct = quat_to_dcm(inp.truth_q[k])
    e[ATT] = dcm_to_rotvec(Ct @ Ce.T)
    e[VEL] = x_sins[4:7] - inp.truth_vel[k]
    e[POS] = (x_sins[7:10] - inp.truth_llh[k]) * pos_scale(inp.truth_llh[k, 0], inp.truth_llh[k, 2])
    # the bias error states are the residual biases of the compensated increments (true − estimate)
    e[BG] = inp.bias_true[0:3] - bias_est[0:3]
    e[BA] = inp.bias_true[3:6] - bias_est[3:6]
    if n_states == em.N17:
        e[CLK] = clk_est[0] - inp.clk_true[k, 0]
        e[DRIFT] = clk_est[1] - inp.clk_true[k, 1]
    return e


def run_integration(kind, core, inp, meas_fn, q_psd, clock_qd=None):
    """Closed-loop run of one core: returns a dict of per-epoch arrays (errors vs truth, NEES, …).

    ``kind``: "loose" (15 states) or "tight" (17 states).  ``meas_fn(k, x_sins, clk_est) ->
    (z, H, R, aux)`` builds the epoch-k measurement (metre-scaled position states) or returns None
    (no update)."""
    n_states = em.N15 if kind == "loose" else em.N17
    t0 = time.perf_counter()
    dt_imu = float(inp.t_imu[1] - inp.t_imu[0])
    x = inp.x0_est.copy()
    bias_est = np.zeros(6)
    clk = np.zeros(2) if inp.clk0_est is None else np.asarray(inp.clk0_est, float).copy()
    n_ep = inp.t_gnss.shape[0]
    err = np.empty((n_ep, n_states))
    sig = np.empty((n_ep, n_states))
    nees = np.empty(n_ep)
    nis = np.full(n_ep, np.nan)
    n_faulty = np.zeros(n_ep, dtype=int)
    i_prev = 0
    t_prev = float(inp.t_imu[0])
    for k in range(n_ep):
        i_next = int(round((inp.t_gnss[k] - inp.t_imu[0]) / dt_imu))
        dth = inp.dtheta[i_prev:i_next] - bias_est[0:3] * dt_imu
        dvv = inp.dv[i_prev:i_next] - bias_est[3:6] * dt_imu
        dt = float(inp.t_gnss[k]) - t_prev
        if i_next > i_prev:
            x = sins_run_final(x, np.ascontiguousarray(dth), np.ascontiguousarray(dvv), dt_imu)
            f_b = dvv.sum(axis=0) / dt
        else:
            f_b = np.zeros(3)
        clk[0] += clk[1] * dt
        if getattr(core, "wants_q_basis", False):
            Phi, Qd, Bq, Qf = discrete_model(x, f_b, dt, q_psd, n_states, clock_qd, basis=True)
            core.set_q_basis(Bq, Qf)
        else:
            Phi, Qd = discrete_model(x, f_b, dt, q_psd, n_states, clock_qd)
        core.predict(Phi, Qd)
        m = meas_fn(k, x, clk)
        if m is not None and not isinstance(core, InsOnlyCore):
            z, H, R, aux = m
            info = core.update(z, H, R, aux)
            nis[k] = info.get("nis", np.nan)
            if "faulty" in info:
                n_faulty[k] = int(np.sum(info["faulty"]))
            # closed-loop feedback (position block back to radians/metres)
            dx = core.x.copy()
            dx[POS] = dx[POS] / pos_scale(x[7], x[9])
            if n_states == em.N17:
                clk -= dx[CLK:DRIFT + 1]
            em.feedback_and_reset(x, dx, bias_est)
            core.reset()
        e = _true_error(x, bias_est, clk, k, inp, n_states)
        err[k] = e
        sig[k] = np.sqrt(np.maximum(np.diag(core.P), 0.0))
        try:
            L = np.linalg.cholesky(core.P)
            y = np.linalg.solve(L, e)
            nees[k] = float(y @ y)
        except np.linalg.LinAlgError:
            nees[k] = np.nan
        i_prev, t_prev = i_next, float(inp.t_gnss[k])
    return {"t": inp.t_gnss.copy(), "err": err, "sigma": sig, "nees": nees, "nis": nis, "n_faulty": n_faulty,
            "n_faults": int(core.n_faults), "n_screened": int(core.n_screened),
            "runtime_s": time.perf_counter() - t0}


def nees_band(n_states, p=0.95):
    """Two-sided χ²(n) band holding a consistent single-run NEES with probability p."""
    a = 0.5 * (1.0 - p)
    return float(chdtri(n_states, 1.0 - a)), float(chdtri(n_states, a))


# --------------------------------------------------------------------------- measurement builders
def tight_measurement_fn(obs, r_pr, r_prr, select_best4=True):
    """``meas_fn`` for the tight runner: best-4 GDOP satellites (Fang 2017 §3.1) of the visible
    ones, pseudorange then pseudorange-rate rows; ``r_pr``/``r_prr`` the variances a core is given.
    ``aux`` holds ``los_e`` (4, 3) and ``gdop`` (eq. 20) for the IAKF."""
    def fn(k, x_sins, clk):
        vis = obs.visible[k]
        if vis.sum() < 4:
            return None
        pos_e, vel_e = state_pos_vel_e(x_sins)
        rho, rhodot, u = predict_observables(obs.sat_pos_e[k], obs.sat_vel_e[k], obs.sat_clk_m[k],
                                             obs.sat_clk_drift_mps[k], pos_e, vel_e, clk[0], clk[1])
        if select_best4:
            idx, g = gdop_best4(u, vis)
        else:
            idx = np.flatnonzero(vis)
            g = np.nan
        m = idx.size
        C_el = dcm_ecef_from_enu(x_sins[7], x_sins[8])
        u_l = u[idx] @ C_el                       # ENU components of the line of sight
        H = np.zeros((2 * m, em.N17))
        H[:m, POS] = -u_l[:, [1, 0, 2]]            # position states (N, E, U) metres
        H[:m, CLK] = 1.0
        H[m:, VEL] = -u_l
        H[m:, DRIFT] = 1.0
        z = np.concatenate([rho[idx] - obs.pr_m[k, idx], rhodot[idx] - obs.prr_mps[k, idx]])
        R = np.diag(np.concatenate([np.full(m, r_pr), np.full(m, r_prr)]))
        return z, H, R, {"los_e": u[idx], "gdop": g, "prns": obs.prns[idx]}
    return fn


def loose_measurement_fn(gnss_llh, gnss_vel, noise, R):
    """``meas_fn`` for the loose runner: z = [r_SINS − r_GNSS (N, E, U m); v_SINS − v_GNSS]
    (Cai et al. 2020 eq. 8 with the sign of this module), ``aux["noise"]`` the noise as it enters z."""
    H = np.zeros((6, em.N15))
    H[0:3, POS] = np.eye(3)
    H[3:6, VEL] = np.eye(3)

    def fn(k, x_sins, clk):
        if not np.all(np.isfinite(gnss_llh[k])):
            return None
        T = pos_scale(x_sins[7], x_sins[9])
        z = np.concatenate([(x_sins[7:10] - gnss_llh[k]) * T, x_sins[4:7] - gnss_vel[k]])
        Tn = pos_scale(gnss_llh[k, 0], gnss_llh[k, 2])
        v = -np.concatenate([noise[k, :3] * Tn, noise[k, 3:]])
        return z, H, R, {"noise": v}
    return fn


def initial_state(truth_q, truth_vel, truth_llh, att_err_rad, vel_err, pos_err_m):
    """SINS initial state = truth + the given initial errors (attitude rotation vector, ENU
    velocity, N/E/U metres), in the convention of the error model."""
    q = quat_mult(rotvec_to_quat(-np.asarray(att_err_rad, float)), np.asarray(truth_q, float))
    T = pos_scale(truth_llh[0], truth_llh[2])
    return make_state(q, np.asarray(truth_vel) + vel_err, np.asarray(truth_llh) + np.asarray(pos_err_m) / T)
