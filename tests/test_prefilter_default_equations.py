"""The prefilters as the receiver ships them, equation by equation over a run of epochs.

``tests/test_prefilter.py`` checks single updates and the paper-literal RACKF (``adaptive_stat="epoch",
robust_mode="period"``).  Here the bank is built with the engine's defaults (``EngineOptions``:
``robust_mode="every"``, ``rackf_kwargs`` -> ``adaptive_stat="window"``, the DLB process noise, Huber
c, correction period) and stepped over 260 epochs of simulated I/Q from a fixed seed — with single-tap
outliers, a noise burst, a filter-R noise event, data-bit changes, a frequency step and a constant
offset on every tap — against a plain numpy transcription of Zhao et al. 2014, §2.1–2.3 (eqs. 2–3, 9–18, 20–23, 37–40,
Algorithm 1) with the two documented deviations of the RACKF (``prefilter_kernels`` docstring, docs/prefilter.md):
the windowed adaptive statistic with its significance test and the held measurement-noise scale.

Nothing of the reference comes from the package but the configuration values (the options) and the
physical constants: the process model is discretised by quadrature of the continuous model, the
tap noise covariance is built from the autocorrelation triangle, the Huber conditioning test uses
leading principal minors.  Compared per epoch: the predicted state and covariance, the posterior
state, innovation, NIS, the Huber factors and equivalent noise R_bar, the adaptive factor theta and
the held noise scale lam, and the status flags.
"""

import math

import numpy as np
import pytest

from ultratight.constants import BETA_CODE_CARRIER, T_CA
from ultratight.fusion.channel import prefilter as pf
from ultratight.fusion.channel import prefilter_model as pm
from ultratight.receiver.deep.options import EngineOptions

T = T_CA
N, M = 5, 6
SPACING = 1.0
N_EPOCHS = 260                          # correction epochs 0, 50, ..., 250
OUTLIER_EPOCHS = (20, 71, 133, 177)     # one tap hit by +15 sigma
BURST = (55, 100)                       # noise x2.5 on every tap -> held noise scale at epoch 100
R_EVENT = (160, 166)                    # filter-R noise event: rscale 4 (and noise x2)
FREQ_STEP_EPOCH = 120                   # truth frequency step (Hz)
FREQ_STEP_HZ = 8.0
OFFSET = (201, 251)                     # a constant offset on every tap (not modulated by the data bit)
OFFSET_SIGMA = 2.0


# ---------------------------------------------------------------- model, from SPEC eqs. 2-3
def tri(t):
    return np.maximum(0.0, 1.0 - np.abs(t))


def taps(spacing=SPACING):
    return np.array([0.0, -spacing / 2, spacing / 2])           # P, E, L


def noise_cov(spacing=SPACING):
    """Unit noise per arm, taps d apart share R(d) of it; I and Q independent."""
    d = taps(spacing)
    r3 = tri(d[:, None] - d[None, :])
    R = np.zeros((M, M))
    R[:3, :3] = r3
    R[3:, 3:] = r3
    return R


def h(x, D):
    """Eq. 3 with the code error at mid-interval (state at the interval start)."""
    A, tau, phi, f = x[0], x[1], x[2], x[3]
    s = f * T / 2
    snc = math.sin(s) / s if s != 0.0 else 1.0
    Rv = tri(tau + BETA_CODE_CARRIER * s + taps())
    ang = s + phi
    return A * D * snc * np.concatenate([Rv * math.cos(ang), Rv * math.sin(ang)])


def discrete_model(q):
    """Eq. 2 over one epoch: Phi = exp(F T) (F nilpotent: I + F T + F^2 T^2/2) and
    Q = int_0^T Phi(s) G diag(q) G^T Phi(s)^T ds by 3-node Gauss-Legendre (exact: degree-4 integrand)."""
    b = BETA_CODE_CARRIER
    F = np.zeros((N, N))
    F[1, 3], F[2, 3], F[3, 4] = b, 1.0, 1.0
    G = np.eye(N)
    G[1, 2] = b                                  # d dtau/dt = beta df + w_tau + beta w_phi
    Qc = G @ np.diag([q["q_amp"], q["q_tau"], q["q_phi"], q["q_f"], q["q_a"]]) @ G.T

    def phi(s):
        return np.eye(N) + F * s + F @ F * s * s / 2

    u, w = np.polynomial.legendre.leggauss(3)
    Qd = sum(wi * T / 2 * phi(T / 2 * (ui + 1)) @ Qc @ phi(T / 2 * (ui + 1)).T for ui, wi in zip(u, w))
    return phi(T), 0.5 * (Qd + Qd.T)


def well_conditioned(A, rel_min):
    """Every squared Cholesky pivot (ratio of successive leading principal minors) above
    ``rel_min`` times its diagonal element."""
    prev = 1.0
    for j in range(A.shape[0]):
        det = np.linalg.det(A[:j + 1, :j + 1])
        if not det / prev > rel_min * A[j, j]:
            return False
        prev = det
    return True


# ---------------------------------------------------------------- reference filter
class RefFilter:
    """One channel of the CKF / UKF / RACKF (robust every epoch, adaptive on correction epochs)."""

    def __init__(self, kind, x0, P0, q, huber_c=1.5, period=50, stat="window", ksig=3.0, theta_min=1e-3,
                 phi_sigma_max=0.8, ukf=(0.5, 2.0, 0.0), rb_rel_pivot_min=0.1):
        self.kind, self.c, self.period, self.stat = kind, huber_c, period, stat
        self.ksig, self.theta_min, self.phi_var_max = ksig, theta_min, phi_sigma_max ** 2
        self.min_win = max(2, period // 2)
        self.rb_min = rb_rel_pivot_min
        self.x, self.P = np.array(x0, float), np.array(P0, float)
        self.Phi, self.Qd = discrete_model(q)
        self.R = noise_cov()
        self.lam = 1.0
        self._clear_window()
        al, be, ka = ukf
        lam_ut = al * al * (N + ka) - N
        self.ut = (math.sqrt(N + lam_ut), lam_ut / (N + lam_ut), lam_ut / (N + lam_ut) + 1 - al * al + be,
                   1 / (2 * (N + lam_ut)))
        self.k = 0

    def _clear_window(self):
        self.w = {"trp": 0.0, "rw": 0.0, "full": 0.0, "expl": 0.0, "trR": 0.0, "cnt": 0.0, "isum": np.zeros(M)}

    def points(self, x, P):
        """Cubature points x +- sqrt(n) S e_j (equal weights), or the scaled sigma points."""
        S = np.linalg.cholesky(0.5 * (P + P.T))
        if self.kind == "ukf":
            sc, wm0, wc0, wi = self.ut
            pts = np.vstack([x, x + sc * S.T, x - sc * S.T])
            wm = np.r_[wm0, np.full(2 * N, wi)]
            wc = np.r_[wc0, np.full(2 * N, wi)]
            return pts, wm, wc
        pts = np.vstack([x + math.sqrt(N) * S.T, x - math.sqrt(N) * S.T])
        w = np.full(2 * N, 1.0 / (2 * N))
        return pts, w, w

    def moments(self, x, P, D):
        """Eqs. 11-13 (no R) and the cross-covariance of eq. 14."""
        pts, wm, wc = self.points(x, P)
        Z = np.array([h(p, D) for p in pts])
        zh = wm @ Z
        dZ, dX = Z - zh, pts - x
        return zh, (wc[:, None] * dZ).T @ dZ, (wc[:, None] * dX).T @ dZ

    def huber(self, r, Pzz0, lam):
        """Eqs. 20-23: factors gamma_i = max(1, |r_i| / (c sigma_i)), sigma_i from eq. 13 (std);
        R_bar_ij = R_ij max(gamma_i, gamma_j), the bifactor sqrt(gamma_i gamma_j) when that is
        ill-conditioned."""
        g = np.maximum(1.0, np.abs(r) / (self.c * np.sqrt(np.diag(Pzz0) + lam * np.diag(self.R))))
        if np.all(g == 1.0):
            return g, lam * self.R
        Rb = lam * self.R * np.maximum(g[:, None], g[None, :])
        if not well_conditioned(Rb, self.rb_min):
            Rb = lam * self.R * np.sqrt(np.outer(g, g))
        return g, Rb

    def adapt(self, r, zh, Pzz0, Rb, g, D, rs):
        """Windowed statistics (eq. 38 summed over the correction period) and the held noise scale;
        returns (sum of tr(P_zz), window statistic or 0 when not significant) on correction epochs."""
        w = self.w
        w["trp"] += np.trace(Pzz0 + Rb)
        w["rw"] += np.sum((r / g) ** 2)
        w["full"] += r @ r
        w["expl"] += np.trace(Pzz0) + 2 * zh @ zh
        w["trR"] += rs * np.trace(self.R)
        w["isum"] += D * r / g
        w["cnt"] += 1
        if self.k % self.period != 0:
            return None
        cnt = w["cnt"]
        marg = 1 + self.ksig * math.sqrt(2 / (M * cnt))                  # chi-square, 6 cnt dof
        if self.stat == "mean":
            stat, marg_th = w["isum"] @ w["isum"], 1 + self.ksig * math.sqrt(2 / M)   # 6 dof
        else:
            stat, marg_th = w["rw"], marg
        if cnt < self.min_win or stat <= marg_th * w["trp"]:
            stat = 0.0
        lam_new = (w["full"] - w["expl"]) / w["trR"]
        self.lam = lam_new if (cnt >= self.min_win and lam_new > marg) else 1.0
        trp = w["trp"]
        self._clear_window()
        return trp, stat

    def step(self, z, bit, rs):
        """Measurement update (eqs. 9-17 / Algorithm 1) then prediction; returns what was computed."""
        x, P = self.x, self.P
        D = bit if bit != 0 else (-1.0 if z @ h(x, 1.0) < 0 else 1.0)   # decision-directed bit
        zh, Pzz0, Pxz = self.moments(x, P, D)
        r = z - zh
        out = {"theta": 1.0, "robust": False, "gamma": np.ones(M), "lam_used": 1.0}
        th = 1.0
        if self.kind == "rackf":
            lam = max(1.0, self.lam) * rs
            g, Rb = self.huber(r, Pzz0, lam)
            out.update(gamma=g, Rb=Rb, robust=bool(np.any(g > 1.0)), lam_used=lam)
            res = self.adapt(r, zh, Pzz0, Rb, g, D, rs)
            if res is not None and res[1] > res[0]:                           # eq. 37
                th = max(res[0] / res[1], self.theta_min)
                zh, Pzz0, Pxz = self.moments(x, P / th, D)                     # eq. 40, redo 11, 12
                r = z - zh
            Pzz = Pzz0 + Rb                                                    # eq. 18
        else:
            Pzz = Pzz0 + rs * self.R
        K = Pxz @ np.linalg.inv(Pzz)                                           # eqs. 15-17
        xp = x + K @ r
        Pp = P / th - K @ Pzz @ K.T
        out.update(theta=th, innov=r, nis=r @ np.linalg.solve(Pzz, r), x_post=xp)
        self.x = self.Phi @ xp                                                 # eqs. 4-8 (linear)
        Pn = self.Phi @ Pp @ self.Phi.T + self.Qd
        Pn = 0.5 * (Pn + Pn.T)
        if Pn[2, 2] > self.phi_var_max:          # phase-sigma cap, phase decorrelated
            Pn[2, :] = 0.0
            Pn[:, 2] = 0.0
            Pn[2, 2] = self.phi_var_max
            out["phase_capped"] = True
        self.P = Pn
        self.k += 1
        return out


# ---------------------------------------------------------------- scenario
def scenario(seed=20261126):
    """Truth states, I/Q, bits and R scale per epoch (fixed seed)."""
    rng = np.random.default_rng(seed)
    Phi, _ = discrete_model({"q_amp": 0.0, "q_tau": 0.0, "q_phi": 0.0, "q_f": 0.0, "q_a": 0.0})
    L = np.linalg.cholesky(noise_cov())
    xt = np.array([1.4, 0.06, 0.4, 2 * np.pi * 2.0, 2 * np.pi * 4.0])
    zs, bits, rss = [], [], []
    for k in range(N_EPOCHS):
        if k == FREQ_STEP_EPOCH:
            xt = xt + np.array([0, 0, 0, 2 * np.pi * FREQ_STEP_HZ, 0])
        D = 1.0 if (k // 20) % 2 == 0 else -1.0
        sig = 2.5 if BURST[0] <= k < BURST[1] else (2.0 if R_EVENT[0] <= k < R_EVENT[1] else 1.0)
        z = h(xt, D) + sig * (L @ rng.standard_normal(M))
        if k in OUTLIER_EPOCHS:
            z[1 + k % 5] += 15.0
        if OFFSET[0] <= k < OFFSET[1]:
            z += OFFSET_SIGMA
        zs.append(z)
        bits.append(D)
        rss.append(4.0 if R_EVENT[0] <= k < R_EVENT[1] else 1.0)
        xt = Phi @ xt
    return np.array(zs), np.array(bits), np.array(rss)


X0 = np.array([1.2, 0.0, 0.0, 0.0, 0.0])
P0 = np.diag([0.2 ** 2, 0.1 ** 2, 0.5 ** 2, (2 * np.pi * 5.0) ** 2, (2 * np.pi * 10.0) ** 2])


def shipped_bank(kind, **over):
    """A one-channel bank built like the engine builds it (receiver.deep.tracking_banks)."""
    opt = EngineOptions()
    kwargs = dict(opt.rackf_kwargs) if kind == "rackf" else {}
    kwargs.update(over)
    bank = pf.PrefilterBank(1, kind=kind, q=opt.prefilter_q, huber_c=opt.huber_c,
                            correction_period=opt.rackf_period, robust_mode=opt.robust_mode, **kwargs)
    bank.reset([0], x0=X0, P0=P0)
    return bank, opt


def work_rows(bank):
    """The Huber factors and R_bar of the last channel update (the bank's work arrays)."""
    fb = bank.packed[1]
    o = pm.packed_float_offsets(bank.n_ch)
    W1 = fb[o[pm.FSEG_W1]:o[pm.FSEG_W2]].reshape(pm.N_W1, M)
    W2 = fb[o[pm.FSEG_W2]:o[pm.FSEG_END]].reshape(pm.N_W2, M, M)
    return W1[pm.W1_GAMMA].copy(), W2[pm.W2_RBAR].copy()


def held_noise_scale(bank):
    """The RACKF's held measurement-noise scale lam of channel 0 (its accumulator row)."""
    fb = bank.packed[1]
    o = pm.packed_float_offsets(bank.n_ch)
    return fb[o[pm.FSEG_ACC] + pm.ACC_LAM]


def close_state(a, b, P, rel=1e-9):
    """|a - b| within rel of (|b| + its 1-sigma), per component."""
    tol = rel * (np.abs(b) + np.sqrt(np.diag(P)))
    return np.all(np.abs(a - b) <= tol), np.max(np.abs(a - b) / tol)


def close_cov(A, B, rel=1e-9):
    """Entries within rel of sqrt(B_ii B_jj) (correlation scale)."""
    s = np.sqrt(np.outer(np.diag(B), np.diag(B)))
    return np.all(np.abs(A - B) <= rel * s), np.max(np.abs(A - B) / s)


def run_against_reference(kind, bits_known, **over):
    bank, opt = shipped_bank(kind, **over)
    stat = bank.adaptive_stat
    ref = RefFilter(kind, X0, P0, opt.prefilter_q, huber_c=opt.huber_c, period=opt.rackf_period, stat=stat,
                    ksig=bank.adapt_ksig, theta_min=bank.theta_min, phi_sigma_max=bank.phi_sigma_max,
                    ukf=(bank.ukf_params["alpha"], bank.ukf_params["beta"], bank.ukf_params["kappa"]))
    zs, bits, rss = scenario()
    seen = {"robust": 0, "theta": [], "lam": [], "bifactor": 0, "capped": 0}
    for k in range(N_EPOCHS):
        b = bits[k] if bits_known else 0.0
        bank.step(zs[k][None, :], np.array([b]), np.array([rss[k]]))
        o = ref.step(zs[k], b, rss[k])
        where = f"{kind}/{stat} epoch {k}"
        assert not bank.diverged[0], where
        assert not bank.flags[0] & pm.FLAG_CHOL_GUARD, where
        ok, e = close_state(bank.x_post[0], o["x_post"], ref.P)
        assert ok, f"{where}: posterior state off by {e:.2g} x tolerance"
        ok, e = close_state(bank.x[0], ref.x, ref.P)
        assert ok, f"{where}: predicted state off by {e:.2g} x tolerance"
        ok, e = close_cov(bank.P[0], ref.P)
        assert ok, f"{where}: predicted covariance off by {e:.2g} x tolerance"
        np.testing.assert_allclose(bank.innov[0], o["innov"], rtol=1e-9, atol=1e-9 * np.abs(o["innov"]).max(),
                                   err_msg=where)
        assert bank.nis[0] == pytest.approx(o["nis"], rel=1e-9), where
        assert bank.theta[0] == pytest.approx(o["theta"], rel=1e-9), where
        assert bool(bank.flags[0] & pm.FLAG_THETA) == (o["theta"] < 1.0), where
        if kind == "rackf":
            g, Rb = work_rows(bank)
            np.testing.assert_allclose(g, o["gamma"], rtol=1e-9, err_msg=where)
            np.testing.assert_allclose(Rb, o["Rb"], rtol=1e-9, atol=1e-12, err_msg=where)
            assert bool(bank.flags[0] & pm.FLAG_ROBUST) == o["robust"], where
            lam_bank = max(1.0, held_noise_scale(bank))
            assert lam_bank == pytest.approx(max(1.0, ref.lam), rel=1e-9), where
            seen["robust"] += o["robust"]
            if o["robust"]:
                G = np.maximum(o["gamma"][:, None], o["gamma"][None, :])
                seen["bifactor"] += not np.allclose(o["Rb"], o["lam_used"] * ref.R * G)
            if k % opt.rackf_period == 0:
                seen["lam"].append(ref.lam)
            if o["theta"] < 1:
                seen["theta"].append((k, o["theta"]))
        seen["capped"] += o.get("phase_capped", False)
    return seen


def test_engine_defaults_are_the_ones_checked_here():
    """The configuration this file checks is what the engine builds (robust every epoch, windowed statistic)."""
    opt = EngineOptions()
    assert opt.robust_mode == "every"
    assert opt.rackf_kwargs.get("adaptive_stat") == "window"
    bank, _ = shipped_bank("rackf")
    assert (bank.robust_mode, bank.adaptive_stat, bank.correction_period) == ("every", "window", 50)


@pytest.mark.parametrize("stat,bits_known,theta_epochs", [
    ("window", True, [250]), ("window", False, []), ("mean", True, [150]), ("mean", False, [100, 250])])
def test_default_rackf_matches_reference_over_epochs(stat, bits_known, theta_epochs):
    """``window``: the engine's default; ``mean``: the bank's own default. Known bits and
    decision-directed bits."""
    seen = run_against_reference("rackf", bits_known, adaptive_stat=stat)
    # the branches of the update were exercised: Huber steps (outliers, burst, offset) with both the
    # max rule and its bifactor fallback, a held noise scale after the burst window, and the
    # adaptive factor with its eq. 40 redraw where the window statistic is significant
    assert seen["robust"] >= 100 and seen["bifactor"] >= 10, seen
    lam = seen["lam"]                                                      # epochs 0, 50, ..., 250
    assert lam[0] == 1.0 and lam[1] == 1.0 and lam[2] > 3.0, lam
    assert [k for k, _ in seen["theta"]] == theta_epochs, seen["theta"]


@pytest.mark.parametrize("kind", ["ckf", "ukf"])
def test_default_ckf_ukf_match_reference_over_epochs(kind):
    """CKF and UKF take none of the robust/adaptive options; the engine's process noise and the phase cap."""
    run_against_reference(kind, True)
