"""PVT against an independent inertial-frame light-time computation (circular orbits)."""

import numpy as np
import pytest
from scipy.stats import chi2

from ultratight.constants import C, OMEGA_E
from ultratight.ins.earth import elev_azim as elevations, llh_to_ecef
from ultratight.receiver.scalar.pvt import solve_pvt, dops

R_ORBIT = 26_560e3
N_ORBIT = np.sqrt(3.986005e14 / R_ORBIT ** 3)


def _rot3(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])   # inertial -> rotating


class Constellation:
    """Circular orbits in an inertial frame aligned with ECEF at t = 0."""

    def __init__(self, n, rng, rx_pos_e):
        self.incl = np.radians(55.0) + 0.0 * np.arange(n)
        self.raan = rng.uniform(0, 2 * np.pi, n)
        self.u0 = rng.uniform(0, 2 * np.pi, n)
        self.rx = rx_pos_e

    def pos_i(self, k, t):
        u = self.u0[k] + N_ORBIT * t
        ci, si = np.cos(self.incl[k]), np.sin(self.incl[k])
        cO, sO = np.cos(self.raan[k]), np.sin(self.raan[k])
        xo, yo = R_ORBIT * np.cos(u), R_ORBIT * np.sin(u)
        return np.array([xo * cO - yo * ci * sO, xo * sO + yo * ci * cO, yo * si])

    def pos_e(self, k, t):
        return _rot3(OMEGA_E * t) @ self.pos_i(k, t)

    def measure(self, k, t_rx, rx_pos_e, rx_vel_e=np.zeros(3)):
        """Geometric range by inertial light time; transmit-time ECEF sat state."""
        def rng_at(t):
            r_rx_i = _rot3(OMEGA_E * t).T @ (rx_pos_e + rx_vel_e * (t - t_rx))
            tau = 0.07
            for _ in range(10):
                tau = np.linalg.norm(self.pos_i(k, t - tau) - r_rx_i) / C
            return tau * C, tau
        rho, tau = rng_at(t_rx)
        h = 1e-3
        rr = (rng_at(t_rx + h)[0] - rng_at(t_rx - h)[0]) / (2 * h)
        t_tx = t_rx - tau
        sp = self.pos_e(k, t_tx)
        sv = (self.pos_e(k, t_tx + h) - self.pos_e(k, t_tx - h)) / (2 * h)
        return rho, rr, sp, sv


def _scene(seed, rx_llh_deg=(36.81, 118.0, 76.0), n_want=8):
    rng = np.random.default_rng(seed)
    rx = llh_to_ecef(np.radians(rx_llh_deg[0]), np.radians(rx_llh_deg[1]), rx_llh_deg[2])
    con = Constellation(60, rng, rx)
    # pick visible satellites
    vis = []
    for k in range(60):
        el, _ = elevations(rx, con.pos_e(k, 0.0)[None, :])
        if el[0] > np.radians(10):
            vis.append(k)
    assert len(vis) >= n_want
    return rx, con, vis[:n_want]


def _measurements(rx, con, sats, vel=np.zeros(3), bias=12345.6, drift=-3.2):
    out = [con.measure(k, 100.0, rx, vel) for k in sats]
    pr = np.array([o[0] for o in out]) + bias
    rr = np.array([o[1] for o in out]) + drift
    sp = np.array([o[2] for o in out])
    sv = np.array([o[3] for o in out])
    return pr, rr, sp, sv


def test_noise_free_position_velocity_exact():
    rx, con, sats = _scene(1)
    vel = np.array([20.0, -5.0, 1.0])
    pr, rr, sp, sv = _measurements(rx, con, sats, vel)
    sol = solve_pvt(sp, pr, sv, rr, mask_deg=0.0)
    assert sol.valid and sol.raim_ok and not sol.excluded
    assert np.linalg.norm(sol.pos_e - rx) < 1e-3
    assert abs(sol.clk_bias_m - 12345.6) < 1e-3
    assert np.linalg.norm(sol.vel_e - vel) < 2e-3
    assert abs(sol.clk_drift_mps + 3.2) < 2e-3
    assert np.all(np.abs(sol.residuals_m[sol.used]) < 1e-3)


def test_without_sagnac_would_be_wrong():
    # The Earth-rotation correction matters at the tens-of-metres level: check that a solver
    # fed ECEF positions rotated back (no rotation) differs, i.e. the correction is really used.
    rx, con, sats = _scene(2)
    pr, rr, sp, sv = _measurements(rx, con, sats)
    tau = (pr - 12345.6) / C
    # pre-rotated positions + zero-rotation would equal; moving sats by their own Sagnac gives ~20 m error
    sp_wrong = np.array([_rot3(-OMEGA_E * t) @ p for t, p in zip(tau, sp)])
    sol = solve_pvt(sp_wrong, pr, mask_deg=0.0)
    assert np.linalg.norm(sol.pos_e - rx) > 5.0


def test_noisy_covariance_consistent():
    rx, con, sats = _scene(3)
    pr0, rr0, sp, sv = _measurements(rx, con, sats)
    rng = np.random.default_rng(7)
    sigma = 3.0
    errs, nees = [], []
    for _ in range(200):
        pr = pr0 + rng.normal(0, sigma, pr0.size)
        sol = solve_pvt(sp, pr, mask_deg=0.0, elev_weight=False, sigma_pr_m=sigma, raim=False)
        e = np.r_[sol.pos_e - rx, sol.clk_bias_m - 12345.6]
        nees.append(e @ np.linalg.solve(sol.cov_pos_clk, e))
        errs.append(e)
    # NEES of a 4-d Gaussian has mean 4
    assert 3.3 < np.mean(nees) < 4.7
    # covariance = sigma^2 (H^T H)^-1  ->  its trace^0.5 / sigma = GDOP
    g = np.sqrt(np.trace(sol.cov_pos_clk)) / sigma
    assert abs(g - sol.dops["gdop"]) < 1e-6


def test_raim_excludes_one_bad_satellite():
    rx, con, sats = _scene(4, n_want=8)
    pr, rr, sp, sv = _measurements(rx, con, sats)
    rng = np.random.default_rng(11)
    pr = pr + rng.normal(0, 1.0, pr.size)
    pr[5] += 150.0
    sol = solve_pvt(sp, pr, mask_deg=0.0, sigma_pr_m=1.0, elev_weight=False)
    assert sol.excluded == [5]
    assert not sol.used[5]
    # after the exclusion the error is the 1 m noise through the 7-satellite geometry:
    # e ~ N(0, sigma^2 Q), Q = (H^T H)^-1 from the line-of-sight vectors computed here, so
    # e^T Q^-1 e / sigma^2 ~ chi2(3); 99.99 % quantile 21.1 (this draw: 0.64; |e| 1.1 m, PDOP 2.84)
    Q = _pos_dop_matrix(rx, sp[np.arange(sp.shape[0]) != 5])
    e = sol.pos_e - rx
    assert e @ np.linalg.solve(Q, e) < chi2.ppf(1.0 - 1e-4, 3), (e, np.sqrt(np.trace(Q)))
    bad = solve_pvt(sp, pr, mask_deg=0.0, sigma_pr_m=1.0, elev_weight=False, raim=False)
    assert not bad.raim_ok
    assert np.linalg.norm(bad.pos_e - rx) > np.linalg.norm(sol.pos_e - rx)


def _pos_dop_matrix(rx, sat_pos_e):
    """Position block of (H^T H)^-1, H = [-u_i, 1] from the unit vectors receiver -> satellite."""
    d = sat_pos_e - rx
    u = d / np.linalg.norm(d, axis=1)[:, None]
    H = np.hstack([-u, np.ones((u.shape[0], 1))])
    return np.linalg.inv(H.T @ H)[:3, :3]


def test_raim_position_rms_is_pdop_times_sigma():
    """100 noise draws with a 150 m fault on satellite 5: RAIM excludes it every time and the RMS
    position error is the closed form sigma * PDOP of the remaining 7 (2.84 m at sigma = 1 m).
    |e|^2 / sigma^2 is a sum of chi2(1) weighted by the eigenvalues of Q; with the Satterthwaite
    approximation (scale tr Q, nu = (tr Q)^2 / tr Q^2 per draw, 100 nu over the draws) the mean
    square lies in the 99.9 % chi-square interval: RMS in [2.36, 3.34] m.  Measured: seed 11
    2.63 m, seeds 1-5 2.55-2.87 m; a doubled error (5.7 m) or a missed exclusion breaks it."""
    rx, con, sats = _scene(4, n_want=8)
    pr0, rr, sp, sv = _measurements(rx, con, sats)
    Q = _pos_dop_matrix(rx, sp[np.arange(sp.shape[0]) != 5])
    rng = np.random.default_rng(11)
    n, sigma = 100, 1.0
    e2 = []
    for _ in range(n):
        pr = pr0 + rng.normal(0, sigma, pr0.size)
        pr[5] += 150.0
        sol = solve_pvt(sp, pr, mask_deg=0.0, sigma_pr_m=sigma, elev_weight=False)
        assert sol.excluded == [5]
        e2.append(np.sum((sol.pos_e - rx) ** 2))
    c = np.trace(Q)
    nu = n * c ** 2 / np.trace(Q @ Q)
    lo, hi = (sigma * np.sqrt(c * chi2.ppf(p, nu) / nu) for p in (1e-3, 1.0 - 1e-3))
    assert lo < np.sqrt(np.mean(e2)) < hi, (np.sqrt(np.mean(e2)), lo, hi)


def test_elevation_mask_and_too_few():
    rx, con, sats = _scene(5, n_want=8)
    pr, rr, sp, sv = _measurements(rx, con, sats)
    el, _ = elevations(rx, sp)
    mask_deg = float(np.degrees(np.sort(el)[2])) + 0.01   # drops the three lowest satellites
    sol = solve_pvt(sp, pr, mask_deg=mask_deg)
    assert sol.used.sum() == 5
    assert not sol.used[np.argsort(el)[:3]].any()
    assert np.linalg.norm(sol.pos_e - rx) < 1e-3
    few = solve_pvt(sp[:3], pr[:3])
    assert not few.valid and "need 4" in few.message


def test_dops_closed_form():
    # four satellites: zenith + three at elevation 0 spaced 120 deg in azimuth
    rx = llh_to_ecef(0.0, 0.0, 0.0)
    # at lat=lon=0, ENU = (y, z, x) in ECEF
    los = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, np.sin(2 * np.pi / 3), np.cos(2 * np.pi / 3)],
                    [0, np.sin(4 * np.pi / 3), np.cos(4 * np.pi / 3)]])
    d = dops(rx, los)
    # by hand, H = [-e_i, 1] with ENU unit vectors up, north, and azimuth 120 / 240 deg on the horizon:
    # H^T H = [[3/2, 0, 0, 0], [0, 3/2, 0, 0], [0, 0, 1, -1], [0, 0, -1, 4]]
    # -> (H^T H)^-1 diagonal 2/3, 2/3, 4/3, 1/3: HDOP = VDOP = sqrt(4/3), PDOP = sqrt(8/3),
    # TDOP = sqrt(1/3), GDOP = sqrt(3)
    want = {"hdop": np.sqrt(4 / 3), "vdop": np.sqrt(4 / 3), "pdop": np.sqrt(8 / 3), "tdop": np.sqrt(1 / 3),
            "gdop": np.sqrt(3.0)}
    for k, v in want.items():
        assert d[k] == pytest.approx(v, rel=1e-12), k
    # the same geometry at another place (40 N, 100 W): the ENU rotation inside dops must not matter
    lat, lon = np.radians(40.0), np.radians(-100.0)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    C_el = np.array([[-so, -sl * co, cl * co], [co, -sl * so, cl * so], [0.0, cl, sl]])   # columns E, N, U
    enu = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [np.sin(2 * np.pi / 3), np.cos(2 * np.pi / 3), 0.0],
                    [np.sin(4 * np.pi / 3), np.cos(4 * np.pi / 3), 0.0]])
    d2 = dops(llh_to_ecef(lat, lon, 300.0), enu @ C_el.T)
    for k, v in want.items():
        assert d2[k] == pytest.approx(v, rel=1e-9), k
