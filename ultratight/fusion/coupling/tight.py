"""Tight SINS/GPS integration filter, 17 error states (Fang 2017, §1), cascaded behind the
per-channel prefilters of the ultra-tight receiver (Zhao et al. 2014 Fig. 1; see docs/references.md).

State (error state, **estimate minus truth**, the convention of ``ultratight.ins.error_model``)::

    ATT   0:3   attitude error (rad, ENU, psi-angle)
    VEL   3:6   velocity error (m/s, ENU)
    POS   6:9   position error (lat rad, lon rad, h m)
    BG    9:12  gyro bias error (rad/s)
    BA   12:15  accelerometer bias error (m/s^2)
    CLK_B  15   receiver clock bias error (m)
    CLK_D  16   receiver clock drift error (m/s)

The layout and the time-update matrices (F, G, discretisation) come from the SINS error model
of :mod:`ultratight.ins.error_model`; this module adds the GPS measurement model and the choice
of estimator.

Measurements (Fang 2017 eqs. 4–5), one pair per tracked channel, formed by the engine from the
*decimated* prefilter outputs (code NCO + code error estimate, carrier NCO + frequency error
estimate) minus the SINS/ephemeris/clock predictions::

    dz_pr_i  = rho_INS,i - rho_meas,i   = -e_i . dr  + db      (m)
    dz_prr_i = rhodot_INS,i - rhodot_meas,i = -e_i . dv + dd    (m/s)

with ``e_i`` the unit line of sight receiver -> satellite and ``dr``/``dv`` the INS position and
velocity errors (position error mapped from (lat, lon, h) to ENU metres by the radii of
curvature).  The model is linear in the error state, so "EKF" is the Kalman update with this
H; the UKF/CKF cores evaluate the same h through their point sets (same result on a linear h,
at a higher cost — provided for completeness and cross-checking); "iakf" is the improved
adaptive KF of Fang 2017 (:class:`ultratight.fusion.estimators.adaptive.IAKF`, GDOP-based R and windowed Q).

Robustness: before the update each measurement's standardised innovation
``|r_i| / sqrt(S_ii)`` is tested against ``gate_sigma``; rejected rows are dropped for this
update (counted in ``n_rejected``).  This protects the SINS against a prefilter that lost lock
or a noise burst the prefilter's covariance does not reflect.
"""

import numpy as np

from ultratight.errors import FilterError
from ultratight.fusion.estimators import filters
from ultratight.fusion.estimators.adaptive import IAKF, gdop as gdop_fn
from ultratight.ins import error_model as em
from ultratight.ins import imu as imu_mod
from ultratight.ins.attitude import skew
from ultratight.ins.earth import llh_increment_scale, radii
# M_pos of measurement_matrix (ENU metres = M_pos @ (dlat, dlon, dh)); the engine builds it as
# tight.pos_error_to_enu(lat, h, rm, rn)
from ultratight.ins.earth import llh_increment_to_enu as pos_error_to_enu  # noqa: F401

# the 17-state layout is the INS error model's (one definition)
from ultratight.ins.error_model import ATT, BA, BG, POS, VEL  # noqa: F401  (re-exported)
from ultratight.ins.error_model import CLK as CLK_B
from ultratight.ins.error_model import DRIFT as CLK_D
from ultratight.ins.error_model import N17 as NX

CLK = slice(CLK_B, CLK_D + 1)
STATE_NAMES = ("phi_e", "phi_n", "phi_u", "dv_e", "dv_n", "dv_u", "dlat", "dlon", "dh",
               "bg_x", "bg_y", "bg_z", "ba_x", "ba_y", "ba_z", "dclk_b_m", "dclk_d_mps")

CORES = ("ekf", "ukf", "ckf", "iakf")


def measurement_matrix(los_l, M_pos, lever=None):
    """H (2m, 17) for pseudorange rows then pseudorange-rate rows.

    ``los_l`` (m,3): unit line of sight receiver -> satellite in ENU; ``M_pos`` from
    :func:`ultratight.ins.earth.llh_increment_to_enu`.  ``lever`` = ``(C_lb, l_l, a_l, w_ie_l)``
    when the antenna is not at the IMU (lever arm ``l`` IMU -> antenna, ``l_l = C_lb l``,
    ``a_l = C_lb (omega_ib_b x l)``, Earth rate ``w_ie_l``, all ENU): the predictions are made at
    ``r + C_lb l`` and ``v + C_lb (omega_ib_b x l) - w_ie x C_lb l``; with
    ``C_lb_est = (I - [phi x]) C_lb`` and the residual gyro bias ``bg`` in ``omega_est``::

        d r_ant = d r + [l_l x] phi
        d v_ant = d v + ([a_l x] - [w_ie_l x][l_l x]) phi - C_lb [l x] bg

    so the pseudorange rows gain ``-e^T [l_l x]`` on ATT and the rate rows
    ``-e^T ([a_l x] - [w_ie_l x][l_l x])`` on ATT and ``e^T C_lb [l x]`` on BG.
    """
    los_l = np.asarray(los_l, dtype=float)
    m = los_l.shape[0]
    H = np.zeros((2 * m, NX))
    H[:m, POS] = -los_l @ M_pos
    H[:m, CLK_B] = 1.0
    H[m:, VEL] = -los_l
    H[m:, CLK_D] = 1.0
    if lever is not None:
        C_lb, l_l, a_l, w_ie_l = lever
        l_b = C_lb.T @ l_l
        H[:m, ATT] = -los_l @ skew(l_l)
        H[m:, ATT] = -los_l @ (skew(a_l) - skew(w_ie_l) @ skew(l_l))
        H[m:, BG] = los_l @ (C_lb @ skew(l_b))
    return H


def doppler_sigma_hz(P, los_l, wavelength):
    """1-sigma of the predicted Doppler of each channel from the filter covariance.

    sigma_i^2 = u_i^T P_vv u_i + P_dd - 2 u_i^T P_vd with u_i the ENU line of sight, divided by
    the wavelength (the projection of the velocity/clock-drift block of P on each LOS) — the
    arbitration statistic of the double loop.
    """
    P = np.asarray(P)
    u = np.asarray(los_l)
    Pvv = P[VEL, VEL]
    Pvd = P[VEL, CLK_D]
    var = np.einsum("ij,jk,ik->i", u, Pvv, u) + P[CLK_D, CLK_D] - 2.0 * (u @ Pvd)
    return np.sqrt(np.maximum(var, 0.0)) / wavelength


def code_sigma_m(P, los_l, M_pos):
    """1-sigma of the predicted pseudorange of each channel (m) from the covariance."""
    P = np.asarray(P)
    Hp = -np.asarray(los_l) @ M_pos
    Ppp = P[POS, POS]
    Ppb = P[POS, CLK_B]
    var = np.einsum("ij,jk,ik->i", Hp, Ppp, Hp) + P[CLK_B, CLK_B] + 2.0 * (Hp @ Ppb)
    return np.sqrt(np.maximum(var, 0.0))


class TightFilter:
    """17-state error-state filter with a selectable core (see module docstring).

    ``predict(Phi, Qd)`` then ``update(dz_pr, dz_prr, los_l, M_pos, r_pr, r_prr, valid)`` returns
    the estimated error state ``dx`` (17,) to feed back to the SINS/clock; the caller then calls
    :meth:`reset` (closed-loop error state: x = 0 after feedback).
    """

    def __init__(self, P0, core="ekf", gate_sigma=5.0, iakf_window=20, ukf_alpha=1.0, ukf_beta=2.0,
                 ukf_kappa=0.0):
        if core not in CORES:
            raise FilterError(f"tight filter core {core!r}: expected one of {CORES}")
        P0 = np.asarray(P0, dtype=float)
        if P0.shape != (NX, NX):
            raise FilterError(f"tight filter P0: expected shape ({NX}, {NX}), got {P0.shape}")
        self.core = core
        self.x = np.zeros(NX)
        self.P = 0.5 * (P0 + P0.T)
        self.gate_sigma = float(gate_sigma)
        self.iakf_window = int(iakf_window)
        self.ukf = dict(alpha=ukf_alpha, beta=ukf_beta, kappa=ukf_kappa)
        self._iakf = None
        self._Q = None
        self.n_updates = 0
        self.n_rejected = 0
        self.last_nis = np.nan
        self.last_used = 0

    def predict(self, Phi, Qd):
        Phi = np.asarray(Phi, dtype=float)
        Qd = np.asarray(Qd, dtype=float)
        self._Q = Qd
        if self._iakf is not None:
            self._iakf.P = self.P
            self._iakf.x = self.x
            if not self._iakf.adapt_q or len(self._iakf.qterms) < self._iakf.N:
                self._iakf.Q = Qd
            self.x, self.P = self._iakf.predict(Phi)
            return
        self.x = Phi @ self.x
        P = Phi @ self.P @ Phi.T + Qd
        self.P = 0.5 * (P + P.T)

    def reset(self):
        """Closed-loop feedback done: the error state returns to zero (P unchanged)."""
        self.x[:] = 0.0
        if self._iakf is not None:
            self._iakf.x = self.x.copy()

    def update(self, dz_pr, dz_prr, los_l, M_pos, r_pr, r_prr, valid=None, gdop=None, lever=None):
        """Measurement update; returns dx (17,) (zeros when nothing was usable).  ``lever``: see
        :func:`measurement_matrix`."""
        dz_pr = np.asarray(dz_pr, dtype=float)
        dz_prr = np.asarray(dz_prr, dtype=float)
        m = dz_pr.shape[0]
        if valid is None:
            valid = np.ones(m, dtype=bool)
        valid = np.asarray(valid, dtype=bool) & np.isfinite(dz_pr) & np.isfinite(dz_prr)
        z = np.concatenate([dz_pr, dz_prr])
        H = measurement_matrix(los_l, M_pos, lever)
        Rd = np.concatenate([np.broadcast_to(r_pr, (m,)), np.broadcast_to(r_prr, (m,))]).astype(float)
        use = np.concatenate([valid, valid])
        if self.core == "iakf":
            return self._update_iakf(z, H, Rd, use, los_l, gdop)
        # per-row innovation gate (rows treated one at a time against the prior)
        S_diag = np.einsum("ij,jk,ik->i", H, self.P, H) + Rd
        r = z - H @ self.x
        with np.errstate(invalid="ignore"):
            ok = use & (np.abs(r) <= self.gate_sigma * np.sqrt(S_diag))
        self.n_rejected += int(np.sum(use & ~ok))
        self.last_used = int(ok.sum())
        if not ok.any():
            return np.zeros(NX)
        z, H, R = z[ok], H[ok], np.diag(Rd[ok])
        if self.core == "ekf":
            x, P, nis = _kf_update(self.x, self.P, z, H, R)
        else:
            hfun = (lambda X: X @ H.T)
            if self.core == "ukf":
                res = filters.ukf_update(self.x, self.P, z, hfun, R, vectorized=True, **self.ukf)
            else:
                res = filters.ckf_update(self.x, self.P, z, hfun, R, vectorized=True)
            x, P, nis = res.x, res.P, res.nis
        self.x, self.P = x, P
        self.last_nis = nis
        self.n_updates += 1
        return self.x.copy()

    def _update_iakf(self, z, H, Rd, use, los_l, gdop):
        m2 = z.shape[0]
        m = m2 // 2
        if self._iakf is None:
            self._iakf = IAKF(self.x, self.P, self._Q if self._Q is not None else np.eye(NX) * 1e-12,
                              np.diag(Rd), pr_rows=np.arange(m), prr_rows=np.arange(m, m2),
                              pos_clk_idx=[6, 7, 8, CLK_B], vel_drift_idx=[3, 4, 5, CLK_D],
                              window=self.iakf_window)
        # rows not usable: zero H and residual (the fixed-size IAKF keeps them, without effect)
        H = np.where(use[:, None], H, 0.0)
        z = np.where(use, z, 0.0)
        los_l = np.asarray(los_l, dtype=float)
        if gdop is None:
            lv = los_l[use[:m]]
            gdop = gdop_fn(lv) if lv.shape[0] >= 4 else 10.0
        self._iakf.x, self._iakf.P = self.x, self.P
        # the line-of-sight matrix (eqs. 17–19, geometry of the least-squares R estimate) and GDOP (eq. 20)
        res = self._iakf.update(z, H, los_unit=los_l, gdop_pr=gdop)
        self.x, self.P = self._iakf.x.copy(), self._iakf.P.copy()
        self.last_nis = res.nis
        self.last_used = int(use.sum())
        self.n_updates += 1
        return self.x.copy()


def _kf_update(x, P, z, H, R):
    """Joseph-form Kalman update (numpy; small fixed sizes, no validation overhead)."""
    PHt = P @ H.T
    S = H @ PHt + R
    S = 0.5 * (S + S.T)
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise FilterError("tight filter: innovation covariance not positive definite") from None
    Linv = np.linalg.inv(L)
    Sinv = Linv.T @ Linv
    K = PHt @ Sinv
    r = z - H @ x
    xn = x + K @ r
    IKH = np.eye(x.shape[0]) - K @ H
    Pn = IKH @ P @ IKH.T + K @ R @ K.T
    Pn = 0.5 * (Pn + Pn.T)
    y = Linv @ r
    return xn, Pn, float(y @ y)


# ---------------------------------------------------------------------------------------------
# time update from the SINS error model (ultratight.ins.error_model), initial covariance, IMU noise
# ---------------------------------------------------------------------------------------------
def imu_errors_from_meta(imu):
    """The *declared* IMU model (:class:`ultratight.ins.imu.ImuErrors`) from an IMU file's metadata:
    generator-written files carry the declaration of the sensor (``meta["errors"]``: 1-sigma turn-on
    biases or a paper's stated magnitudes, noise densities, scale-factor and misalignment sigmas;
    the drawn sensor of the run is truth and is not in the file, see :mod:`ultratight.ins.imu`);
    files without it use the "paper" preset of Zhao et al. 2014, §3."""
    d = (getattr(imu, "meta", None) or {}).get("errors")
    if isinstance(d, dict):
        e = imu_mod.ImuErrors()
        for k, v in d.items():
            if not hasattr(e, k):
                continue
            cur = getattr(e, k)
            if isinstance(cur, np.ndarray):
                setattr(e, k, np.asarray(v, dtype=float))
            elif k.endswith("_tau"):
                setattr(e, k, float("inf") if v is None else float(v))
            else:
                setattr(e, k, v)
        return e
    return imu_mod.imu_errors_from_config({"preset": "paper", "rate_hz": float(getattr(imu, "rate_hz", 100.0))})


def phi_q(ins, dt, imu_errors, clock_q_drift=1e-4, clock_q_bias=1e-4, bias_floor=(1e-16, 1e-14)):
    """(Phi, Qd) of the 17-state model over dt at the current SINS state (F, G, Qc of ultratight.ins.error_model).

    Phi: second-order Taylor series of exp(F dt) (``error_model.discretize_taylor``); Qd by the
    trapezoidal rule ``(Phi G Qc G^T Phi^T + G Qc G^T) dt / 2``, positive semi-definite by
    construction (the Van Loan ``error_model.discretize`` is exact but costs a 34x34 matrix exponential,
    ~15 ms, per tight update).  ``ins`` has ``q_lb``, ``vel_l``, ``llh``, ``f_b``."""
    F = em.F_matrix(ins.q_lb, ins.vel_l, ins.llh, ins.f_b, n_states=em.N17)
    G = em.G_matrix(ins.q_lb, n_states=em.N17)
    q = em.noise_psd(imu_errors, n_states=em.N17, clock_psd=(clock_q_bias, clock_q_drift))
    # constant (random-constant) biases: a tiny driving noise keeps them estimable
    q[em.NOISE_BG] = np.maximum(q[em.NOISE_BG], bias_floor[0])
    q[em.NOISE_BA] = np.maximum(q[em.NOISE_BA], bias_floor[1])
    Phi, _ = em.discretize_taylor(F, G, q, dt)
    GQG = (G * q) @ G.T
    Qd = 0.5 * (Phi @ GQG @ Phi.T + GQG) * dt
    return Phi, 0.5 * (Qd + Qd.T)


def initial_covariance(llh, sigmas, imu_errors):
    """P0 (17x17) of the hot start: ``sigmas`` dict (StartupErrors fields: pos_m, vel_mps,
    att_deg, clk_bias_m, clk_drift_mps; optional ``att_cov_rad2``, a 3x3 attitude covariance that
    replaces att_deg); bias sigmas from the declared IMU model (:func:`imu_errors_from_meta`: the
    1-sigma turn-on bias, or the magnitude a paper states), at least a small floor -- never from the
    biases a simulation drew for the run."""
    lat, h = float(llh[0]), float(llh[2])
    rm, rn = radii(lat)
    s_pos = float(sigmas.get("pos_m", 1.0))
    P = np.zeros((NX, NX))
    P[ATT, ATT] = np.eye(3) * np.deg2rad(float(sigmas.get("att_deg", 0.01))) ** 2
    if sigmas.get("att_cov_rad2") is not None:
        # a full attitude covariance (rad^2, ENU error angles), e.g. of a Wahba alignment
        P[ATT, ATT] = 0.5 * (np.asarray(sigmas["att_cov_rad2"], float) + np.asarray(sigmas["att_cov_rad2"], float).T)
    P[VEL, VEL] = np.eye(3) * float(sigmas.get("vel_mps", 0.05)) ** 2
    m_per_lat, m_per_lon, _ = llh_increment_scale(lat, h, rm, rn)
    P[6, 6] = (s_pos / m_per_lat) ** 2
    P[7, 7] = (s_pos / m_per_lon) ** 2
    P[8, 8] = s_pos ** 2
    bg = np.maximum(np.abs(np.asarray(imu_errors.gyro_bias, float)), np.deg2rad(0.001) / 3600.0)
    ba = np.maximum(np.abs(np.asarray(imu_errors.accel_bias, float)), 1e-5)
    P[BG, BG] = np.diag(bg ** 2)
    P[BA, BA] = np.diag(ba ** 2)
    P[CLK_B, CLK_B] = float(sigmas.get("clk_bias_m", 1.0)) ** 2
    P[CLK_D, CLK_D] = float(sigmas.get("clk_drift_mps", 0.05)) ** 2
    return P
