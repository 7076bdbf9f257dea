"""PVT against an independent inertial-frame light-time computation (circular orbits)."""

import numpy as np
import pytest

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
    assert np.linalg.norm(sol.pos_e - rx) < 10.0
    bad = solve_pvt(sp, pr, mask_deg=0.0, sigma_pr_m=1.0, elev_weight=False, raim=False)
    assert not bad.raim_ok
    assert np.linalg.norm(bad.pos_e - rx) > np.linalg.norm(sol.pos_e - rx)


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
    # H = [[-e_i, 1]]; closed form by hand via numpy on the ENU geometry
    H = np.array([[0, 0, -1, 1], [0, -1, 0, 1], [-np.sin(2 * np.pi / 3), -np.cos(2 * np.pi / 3), 0, 1],
                  [-np.sin(4 * np.pi / 3), -np.cos(4 * np.pi / 3), 0, 1]])
    Q = np.linalg.inv(H.T @ H)
    assert d["hdop"] == pytest.approx(np.sqrt(Q[0, 0] + Q[1, 1]))
    assert d["vdop"] == pytest.approx(np.sqrt(Q[2, 2]))
    # symmetric horizontal geometry: east and north variances equal
    assert Q[0, 0] == pytest.approx(Q[1, 1])
