"""INS/GNSS filter for recorded logs (ultratight.fusion.gins): alignment, the loose and tight
filter with every core, ZUPT, NHC, the χ² gate and the RTS smoother, against the truth of the
project's own trajectory generator and IMU synthesis (seeded)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.fusion.gins.alignment import level, still_flags
from ultratight.fusion.gins.options import FILTERS, GinsOptions
from ultratight.fusion.gins.runner import run_gins
from ultratight.fusion.gins.updates import enu_offset
from ultratight.ins.attitude import euler_to_dcm, quat_to_dcm_vec
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef, radii
from ultratight.ins.imu import ImuErrors, synthesize_imu
from ultratight.ins.imu_noise import imu_noise
from ultratight.ins.trajectory import build_trajectory
from ultratight.signals.observations import GnssFixes

T0 = 1.4e9                      # GPS seconds of the synthetic logs' start
LEVER = np.array([0.5, 0.2, 1.0])
SITE = {"lat_deg": 40.0, "lon_deg": -105.0, "h_m": 1600.0}
VEHICLE = {"kind": "turns", "speed0_mps": 0.0, "heading0_deg": 30.0,
           "segments": [{"t0": 0.0, "acc_mps2": 0.0}, {"t0": 10.0, "speed_mps": 10.0},
                        {"t0": 20.0, "turn_rate_dps": 6.0}, {"t0": 35.0, "acc_mps2": 0.0},
                        {"t0": 50.0, "turn_rate_dps": -5.0}, {"t0": 65.0, "speed_mps": 15.0},
                        {"t0": 80.0, "turn_rate_dps": 4.0}]}
SIG_P, SIG_V = 0.03, 0.02       # GNSS noise of the synthetic fixes (m, m/s), declared in the fixes


def _log(traj_cfg, duration, seed, grade="tactical", lever=LEVER, gnss_hz=5.0):
    """(ImuData, GnssFixes, ImuNoise, ImuErrors, trajectory): IMU declared with the grade's turn-on
    bias σ and white noise, its constant biases drawn by the synthesis (``bias_reading`` "sigma"); the
    returned ImuErrors holds the drawn sensor (the truth); fixes of the antenna with seeded white noise."""
    traj = build_trajectory(traj_cfg, SITE, duration)
    noise = imu_noise(grade)
    rng = np.random.default_rng(seed)
    spec = ImuErrors(gyro_bias=np.full(3, noise.gyro_bias_sigma), accel_bias=np.full(3, noise.accel_bias_sigma),
                     gyro_arw=np.full(3, noise.gyro_arw), accel_vrw=np.full(3, noise.accel_vrw))
    imu = synthesize_imu(traj, 100.0, spec, rng, lever_arm_b=lever)
    drawn = imu.errors_realised
    err = ImuErrors(gyro_bias=np.asarray(drawn["gyro_bias"], float), accel_bias=np.asarray(drawn["accel_bias"], float),
                    gyro_arw=spec.gyro_arw, accel_vrw=spec.accel_vrw)
    imu.t = imu.t + T0
    imu.t0 = T0
    tg = np.arange(1.0 / gnss_hz, duration + 1e-9, 1.0 / gnss_hz)
    k = traj.kinematics(tg)
    llh = k["llh"].copy()
    rm, rn = radii(llh[0, 0])
    e = rng.standard_normal((tg.size, 3)) * SIG_P
    llh[:, 0] += e[:, 1] / (rm + llh[:, 2])
    llh[:, 1] += e[:, 0] / ((rn + llh[:, 2]) * np.cos(llh[:, 0]))
    llh[:, 2] += e[:, 2]
    vel = k["vel_l"] + rng.standard_normal((tg.size, 3)) * SIG_V
    fx = GnssFixes(tg + T0, llh, vel, np.full((tg.size, 3), SIG_P), np.full((tg.size, 3), SIG_V),
                   np.ones(tg.size, int))
    return imu, fx, noise, err, traj


def _errors(imu, res):
    """(position error ENU m, velocity error m/s) of every result sample against the IMU truth."""
    j0 = imu.n - res.n
    tl, tv = imu.truth["llh"][j0 + 1:], imu.truth["vel_l"][j0 + 1:]
    dp = np.array([enu_offset(res.llh[i], tl[i]) for i in range(res.n)])
    return dp, res.vel_enu - tv


def _opts(noise, **kw):
    kw.setdefault("lever_arm_b", LEVER)
    return GinsOptions(noise=noise, **kw)


@pytest.fixture(scope="module")
def vehicle():
    return _log(VEHICLE, 100.0, seed=3)


@pytest.fixture(scope="module")
def smoothed_run(vehicle):
    imu, fx, noise, _, _ = vehicle
    return run_gins(imu, _opts(noise, smooth=True, outages=((T0 + 70.0, T0 + 85.0),)), fixes=fx)


def test_static_levelling_closed_form():
    # f_b = C_lbᵀ (0, 0, g) for a body at rest: roll and pitch come back exactly
    for roll, pitch in ((0.1, -0.2), (-0.5, 0.3), (0.0, 0.0), (2.5, 1.2)):
        f = euler_to_dcm(roll, pitch, 1.0).T @ np.array([0.0, 0.0, 9.8])
        r, p = level(f)
        assert r == pytest.approx(roll, abs=1e-12) and p == pytest.approx(pitch, abs=1e-12)


def test_alignment_levels_a_still_start(vehicle, smoothed_run):
    imu, _, noise, err, traj = vehicle
    al = smoothed_run.alignment
    assert al["method"] == "static-level+gnss-course"
    # the still window lies in the first 10 s (the vehicle stands still); levelling error is the
    # accelerometer bias over g (the tilt absorbs it) — within 4σ of the declared bias
    assert al["still_window"][1] - T0 <= 10.0 + 0.5
    true = traj.kinematics(np.array([1.0]))["euler"][0]
    bound = 4.0 * noise.accel_bias_sigma / 9.8 + 1e-4
    assert abs(al["level_roll"] - true[0]) < bound and abs(al["level_pitch"] - true[1]) < bound
    # heading from the GNSS course at the first epoch above heading_speed_mps, the body along the path
    assert math.degrees(al["yaw"]) == pytest.approx(30.0, abs=3.0 * math.degrees(al["sigma_yaw_rad"]))


def test_still_detector_thresholds_from_declared_noise(vehicle):
    imu, _, noise, _, _ = vehicle
    still = still_flags(imu, noise, 1.0, 3.0, g=9.7966)     # normal gravity at 40°, 1600 m
    t = imu.t - T0
    assert still[(t > 1.0) & (t < 9.0)].all()          # at rest
    assert not still[(t > 11.0) & (t < 34.0)].any()    # accelerating at 1 m/s², then turning at 6 °/s
    # (cruising straight at constant speed is, to a noise-free synthetic IMU, the same as rest)


def test_forward_error_inside_3_sigma(vehicle, smoothed_run):
    imu, _, _, _, _ = vehicle
    fwd = smoothed_run.forward
    dp, dv = _errors(imu, fwd)
    settled = fwd.t - T0 > 15.0
    # a consistent filter: 99.7 % of a Gaussian error inside 3σ (per axis, samples correlated)
    assert np.mean(np.abs(dp[settled]) < 3.0 * fwd.sigma_pos_enu[settled]) > 0.99
    assert np.mean(np.abs(dv[settled]) < 3.0 * fwd.sigma_vel_enu[settled]) > 0.99
    assert np.all(np.abs(dp[settled]) < 5.0 * fwd.sigma_pos_enu[settled])
    assert fwd.in_outage.sum() > 0 and not fwd.smoothed


def test_smoother_beats_forward_through_outage(vehicle, smoothed_run):
    imu, _, _, err, _ = vehicle
    res = smoothed_run
    assert res.smoothed and res.forward is not None
    m = res.in_outage
    dpf, _ = _errors(imu, res.forward)
    dps, _ = _errors(imu, res)
    hf = np.hypot(dpf[m, 0], dpf[m, 1]).max()
    hs = np.hypot(dps[m, 0], dps[m, 1]).max()
    assert hs < 0.5 * hf
    # its σ is below the forward σ and still covers its error
    assert np.all(res.sigma_pos_enu[m] <= res.forward.sigma_pos_enu[m] + 1e-12)
    assert np.mean(np.abs(dps[m]) < 3.0 * res.sigma_pos_enu[m]) > 0.95
    # the gyro biases are estimated (tactical grade, turns): within 3σ of the truth at the end
    assert np.all(np.abs(res.forward.gyro_bias[-1] - err.gyro_bias) < 1e-4)


def test_zupt_holds_a_still_imu():
    still_cfg = {"kind": "static", "att0_deg": [2.0, -1.0, 40.0]}
    imu, fx, noise, _, _ = _log(still_cfg, 80.0, seed=5, grade="mems", lever=np.zeros(3))
    outage = ((T0 + 15.0, T0 + 80.0),)
    kw = dict(lever_arm_b=np.zeros(3), heading_deg=40.0, outages=outage)
    free = run_gins(imu, _opts(noise, **kw), fixes=fx)
    held = run_gins(imu, _opts(noise, zupt=True, **kw), fixes=fx)
    _, dvf = _errors(imu, free)
    _, dvh = _errors(imu, held)
    m = held.in_outage
    assert held.meta["counts"]["zupt"] > 200
    assert held.alignment["method"] == "static-level+given-heading"
    assert math.degrees(held.alignment["yaw"]) == pytest.approx(40.0, abs=0.1)   # carried over 0.2 s at most
    assert np.abs(dvh[m]).max() < 0.05                 # ZUPT σ 0.02 m/s
    assert np.abs(dvf[m]).max() > 5.0 * np.abs(dvh[m]).max()


def _body_errors(imu, res):
    """(velocity error, position error) in the true body frame FLU."""
    j0 = imu.n - res.n
    C = quat_to_dcm_vec(imu.truth["q_lb"][j0 + 1:])
    dp, dv = _errors(imu, res)
    return np.einsum("nji,nj->ni", C, dv), np.einsum("nji,nj->ni", C, dp)


def test_nhc_on_a_vehicle():
    # a MEMS IMU in a car (no side-slip, no bank): NHC keeps the body lateral and vertical velocity
    # errors at its σ (0.1 m/s) through a 30 s outage where the free inertial drifts
    imu, fx, noise, _, _ = _log(VEHICLE, 100.0, seed=6, grade="mems", lever=np.zeros(3))
    kw = dict(lever_arm_b=np.zeros(3), outages=((T0 + 60.0, T0 + 90.0),))
    plain = run_gins(imu, _opts(noise, **kw), fixes=fx)
    nhc = run_gins(imu, _opts(noise, nhc=True, **kw), fixes=fx)
    m = nhc.in_outage
    vp, pp = _body_errors(imu, plain)
    vn, pn = _body_errors(imu, nhc)
    assert nhc.meta["counts"]["nhc"] > 100
    assert np.abs(vn[m, 1:]).max() < 0.1 and np.abs(vn[m, 1:]).max() < 0.5 * np.abs(vp[m, 1:]).max()
    assert np.abs(pn[m, 1]).max() < 0.5 * np.abs(pp[m, 1]).max()      # cross-track


def test_chi2_gate_rejects_a_50_m_outlier(vehicle):
    imu, fx, noise, _, _ = vehicle
    bad = fx.subset(np.arange(fx.n))
    k = int(np.argmin(np.abs(bad.t - (T0 + 40.0))))
    bad.llh[k, 0] += 50.0 / 6.37e6                      # 50 m north
    res = run_gins(imu, _opts(noise), fixes=bad)
    assert res.updates["rejected"][k] and not res.updates["used"][k]
    assert res.updates["reason"][k].startswith("chi2 NIS")
    assert res.updates["used"][k - 1] and res.updates["used"][k + 1]
    dp, _ = _errors(imu, res)
    near = np.abs(res.t - bad.t[k]) < 1.0
    assert np.abs(dp[near]).max() < 0.3
    ungated = run_gins(imu, _opts(noise, gate_p=None), fixes=bad)
    assert np.abs(_errors(imu, ungated)[0][near]).max() > 1.0
    # chi2-newton screens the rows itself (no epoch gate in front): the outlier's dimensions replaced
    cn = run_gins(imu, _opts(noise, filter="chi2-newton"), fixes=bad)
    assert cn.updates["used"][k] and cn.meta["counts"]["faulty_dims"] >= 1
    assert np.abs(_errors(imu, cn)[0][near]).max() < 0.3


@pytest.mark.parametrize("name", FILTERS)
def test_every_core_runs(vehicle, name):
    imu, fx, noise, _, _ = vehicle
    res = run_gins(imu, _opts(noise, filter=name, outages=((T0 + 70.0, T0 + 75.0),)), fixes=fx)
    dp, dv = _errors(imu, res)
    settled = res.t - T0 > 15.0
    assert np.all(np.isfinite(res.llh)) and np.all(np.isfinite(res.sigma_pos_enu))
    assert np.abs(dp[settled]).max() < 0.5 and np.abs(dv[settled]).max() < 0.2
    u = res.updates
    usable = (u["t"] > res.t[0]) & ~((u["t"] >= T0 + 70.0) & (u["t"] <= T0 + 75.0))
    assert u["used"].sum() >= 0.9 * usable.sum()


@pytest.mark.parametrize("name", ["kf", "akf", "chi2-newton"])
def test_position_only_fixes(vehicle, name):
    # a source without velocity (NMEA GGA): 3-row updates, the heading from two positions
    imu, fx, noise, _, _ = vehicle
    pos_only = fx.subset(np.arange(fx.n))
    pos_only.vel_enu[:] = np.nan
    pos_only.sigma_vel_enu[:] = np.nan
    res = run_gins(imu, _opts(noise, filter=name), fixes=pos_only)
    assert set(res.updates["n_rows"][res.updates["used"]]) == {3}
    assert math.degrees(res.alignment["yaw"]) == pytest.approx(30.0, abs=3.0 * math.degrees(res.alignment["sigma_yaw_rad"]))
    dp, dv = _errors(imu, res)
    settled = res.t - T0 > 20.0
    assert np.abs(dp[settled]).max() < 0.5 and np.abs(dv[settled]).max() < 0.3


class StandInTight:
    """Tight measurements of a synthetic log: eight static satellites 20 000 km away, a drifting
    receiver clock, seeded noise; the interface of the tight measurement object."""

    def __init__(self, traj, t_rel, seed):
        self.t = t_rel + T0
        self.t_rel = t_rel
        self.traj = traj
        rng = np.random.default_rng(seed)
        k0 = traj.kinematics(np.array([0.0]))
        C = dcm_ecef_from_enu(*k0["llh"][0, :2])
        az = np.radians([10, 60, 110, 170, 220, 280, 330, 0])
        el = np.radians([15, 40, 70, 25, 55, 20, 35, 85])
        u = np.column_stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
        self.elev = el
        self.sat = k0["pos_e"][0] + 2.0e7 * u @ C.T
        pos, vel = traj.pos_vel_e(t_rel)
        self.clk = 3.0e4 + 50.0 * t_rel
        self.pr = np.linalg.norm(self.sat[None] - pos[:, None], axis=2) + self.clk[:, None] \
            + rng.standard_normal((t_rel.size, 8)) * 1.0
        los = (self.sat[None] - pos[:, None]) / np.linalg.norm(self.sat[None] - pos[:, None], axis=2)[..., None]
        self.rr = -np.einsum("kij,kj->ki", los, vel) + 50.0 + rng.standard_normal((t_rel.size, 8)) * 0.05

    def rows(self, k, pos_e, vel_e, clk_m, drift_mps, keep=None):
        d = self.sat - np.asarray(pos_e)
        r = np.linalg.norm(d, axis=1)
        los = d / r[:, None]
        sel = np.argsort(-self.elev)[:keep] if keep else np.arange(8)
        return SimpleNamespace(dz_pr=(r + clk_m - self.pr[k])[sel], dz_rr=(-los @ vel_e + drift_mps - self.rr[k])[sel],
                               los_e=los[sel], sigma_pr=np.full(sel.size, 1.0), sigma_rr=np.full(sel.size, 0.05),
                               prn=np.arange(1, 9)[sel], elev_rad=self.elev[sel])

    def initial_clock(self, k, pos_e, vel_e):
        r = self.rows(k, pos_e, vel_e, 0.0, 0.0)
        return -float(np.mean(r.dz_pr)), -float(np.mean(r.dz_rr))


@pytest.mark.parametrize("name", ["kf", "afm-aukf"])
def test_tight_with_a_stand_in(vehicle, name):
    imu, _, noise, _, traj = vehicle
    meas = StandInTight(traj, np.arange(0.2, 100.0 + 1e-9, 0.2), seed=7)
    res = run_gins(imu, _opts(noise, coupling="tight", filter=name, outages=((T0 + 70.0, T0 + 85.0),),
                              outage_keep_sats=2), tight=meas)
    dp, dv = _errors(imu, res)
    settled = (res.t - T0 > 20.0) & ~res.in_outage
    assert np.abs(dp[settled]).max() < 2.0 and np.abs(dv[settled]).max() < 0.2
    assert np.mean(np.abs(dp[settled]) < 3.0 * res.sigma_pos_enu[settled]) > 0.95
    clk_true = 3.0e4 + 50.0 * (res.t - T0)
    assert np.abs(res.clock[settled, 0] - clk_true[settled]).max() < 3.0
    out = (res.updates["t"] > T0 + 70.0) & (res.updates["t"] < T0 + 85.0)
    assert np.all(res.updates["n_rows"][out] == 4)     # two satellites kept: their two rows each


def test_bad_options_one_line():
    noise = imu_noise("tactical")
    fx = GnssFixes(np.array([1.0]), np.zeros((1, 3)), np.zeros((1, 3)), np.ones((1, 3)), np.ones((1, 3)),
                   np.ones(1, int))
    imu = SimpleNamespace(n=10)
    for kw, word in ((dict(filter="ekf"), "filter"), (dict(coupling="deep"), "coupling"),
                     (dict(outages=((5.0, 1.0),)), "outage"), (dict(gate_p=2.0), "gate_p"),
                     (dict(coupling="tight", filter="akf"), "tight")):
        with pytest.raises(ConfigError, match=word):
            run_gins(imu, GinsOptions(noise=noise, **kw), fixes=fx, tight=object())
    with pytest.raises(ConfigError, match="noise"):
        run_gins(imu, GinsOptions(), fixes=fx)
