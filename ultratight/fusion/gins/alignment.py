"""Initial alignment of a recorded IMU log and the still detector (ZUPT and levelling).

Still detector (:func:`still_flags`): over a centred window of ``still_window_s`` the three
statistics of a body at rest are compared with what the declared noise (ImuNoise) allows:

* the standard deviation of |f| (specific-force magnitude, per sample) below ``k σ_f`` with
  σ_f = VRW/√dt the declared white noise of one sample;
* the standard deviation of each gyro axis below ``k σ_ω`` (σ_ω = ARW/√dt);
* |mean |f| − g| (g the normal gravity at the first GNSS fix) below ``k σ_f/√N + 3.29 σ_ba`` and
  |mean ω| below ``k σ_ω/√N + 4.03 σ_bg + ω_ie`` (the turn-on biases may shift the means: 3.29 and
  4.03 are the 99.9 % quantiles of a one-axis Gaussian and of the norm of a three-axis one; the
  Earth rate adds up to 15 °/h).

The thresholds follow from the declaration only; a log recorded through a low-pass filter shows
less noise than declared, which makes the detector stricter, not looser.

Alignment (:func:`align`):

1. **Levelling**: the first still run of at least ``still_window_s`` within ``align_search_s``,
   at most ``level_max_s`` long (else the first window, marked ``level-moving``) gives roll and pitch from the mean specific force f̄ (FLU body):
   ``roll = atan2(f̄_y, f̄_z)``, ``pitch = atan2(f̄_x, √(f̄_y² + f̄_z²))``.
2. **Gyro bias at rest**: the window mean of the gyro minus the Earth rate is a measurement of the
   turn-on bias with the noise ARW/√T; it is combined with the declared σ_bg (Bayes, scalar per
   axis), so a MEMS part's bias is moved only as far as the window supports.  The Earth rate is
   removed with the heading found in step 4 (its horizontal part needs it).
3. **Attitude carried** from the window's end to the alignment epoch by integrating the
   bias-compensated gyro increments (Earth and transport rates neglected over these seconds).
4. **Heading**: the given ``heading_deg`` (it is the heading at the end of the levelling window;
   the alignment epoch is then the first GNSS epoch after that window), or the GNSS course
   ``atan2(v_E, v_N)`` at the first epoch after the levelling window whose horizontal speed
   exceeds ``heading_speed_mps``.  **Assumption: the body's forward axis points along the path**
   (no crab or side-slip; a handheld or vehicle-mounted unit facing the direction of travel).
   Heading σ = max(σ_vh / speed, ``heading_sigma_floor_deg``) with σ_vh the horizontal
   velocity σ; the roll and pitch are kept from step 3.
5. **Position/velocity** from the GNSS at that epoch, moved from the antenna to the IMU through
   the lever arm (r_IMU = r_ant − C_lb l; the velocity's ω × l term is neglected) and to the
   nearest IMU sample's time with the GNSS velocity; the filter starts after that sample.
6. **Initial covariance**: attitude from the levelling (tilt from the accelerometer bias σ and
   the window noise, correlated with the accelerometer-bias states exactly as the levelling
   makes them: the tilt absorbs the horizontal bias, φ_E = −(C_lb b_a)_N/g, φ_N = (C_lb b_a)_E/g),
   heading as in step 4, position and velocity from the GNSS σ (with the floors and quality
   factors of the loose update), biases from the declaration (gyro: the step-2 posterior).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ultratight.constants import OMEGA_E
from ultratight.errors import ConfigError
from ultratight.ins import error_model as em
from ultratight.ins.attitude import (dcm_to_euler, dcm_to_quat, euler_to_dcm, quat_mult, quat_normalize,
                                     quat_to_dcm, rotvec_to_quat)
from ultratight.ins.earth import gravity_l, radii
from ultratight.ins.imu_noise import G0
from ultratight.fusion.gins.updates import enu_offset
from ultratight.ins.sins import make_state


# allowance for the turn-on biases in the window means: the 99.9 % quantiles of |N(0, 1)| (3.29)
# and of the norm of a 3-axis N(0, I) (√χ²₃ = 4.03), times the declared bias σ
BIAS_K1 = 3.29
BIAS_K3 = 4.03


def sample_dt(imu):
    """(n,) actual length of every IMU interval (t[k] − t[k−1], the first from t0)."""
    t = np.asarray(imu.t, float)
    return np.diff(t, prepend=float(imu.t0) if imu.t0 < t[0] else t[0] - 1.0 / imu.rate_hz)


def _window_mean(x, w):
    """Centred moving mean of ``x`` (n,) or (n, k) over ``w`` samples (edges: the part inside)."""
    x = np.asarray(x, float)
    flat = x.reshape(x.shape[0], -1)
    c = np.vstack([np.zeros((1, flat.shape[1])), np.cumsum(flat, axis=0)])
    n = x.shape[0]
    lo = np.clip(np.arange(n) - w // 2, 0, n)
    hi = np.clip(lo + w, 0, n)
    lo = np.clip(hi - w, 0, n)
    out = (c[hi] - c[lo]) / np.maximum(hi - lo, 1)[:, None]
    return out.reshape(x.shape)


def still_flags(imu, noise, window_s=1.0, k=3.0, g=G0):
    """bool (n,): IMU sample inside a still window (module docstring: thresholds from the declared
    noise); ``g`` the local gravity magnitude (m/s²)."""
    dts = sample_dt(imu)
    dt = float(np.median(dts))
    w = max(3, int(round(window_s / dt)))
    f = imu.dv_b / dts[:, None]
    om = imu.dtheta_b / dts[:, None]
    fm = np.linalg.norm(f, axis=1)
    s_f = noise.accel_vrw / math.sqrt(dt)
    s_w = noise.gyro_arw / math.sqrt(dt)
    m_f = _window_mean(fm, w)
    sd_f = np.sqrt(np.maximum(_window_mean(fm * fm, w) - m_f ** 2, 0.0))
    m_w = _window_mean(om, w)
    sd_w = np.sqrt(np.maximum(_window_mean(om * om, w) - m_w ** 2, 0.0))
    still = sd_f < k * s_f
    still &= np.all(sd_w < k * s_w, axis=1)
    still &= np.abs(m_f - g) < k * s_f / math.sqrt(w) + BIAS_K1 * noise.accel_bias_sigma
    still &= np.linalg.norm(m_w, axis=1) < k * s_w / math.sqrt(w) + BIAS_K3 * noise.gyro_bias_sigma + OMEGA_E
    return still


def level(f_mean_b):
    """(roll, pitch) rad of a body at rest from its mean specific force (FLU body, m/s²)."""
    fx, fy, fz = (float(v) for v in f_mean_b)
    return math.atan2(fy, fz), math.atan2(fx, math.hypot(fy, fz))


@dataclass
class Alignment:
    """Result of :func:`align`: the filter starts after IMU sample ``j0`` (time ``t``) with the
    SINS state ``x_sins``, bias estimates ``bias`` [bg, ba], covariance ``P0`` (15 states,
    position block N, E, U metres) and ``info`` (what the GinsResult reports)."""
    j0: int
    t: float
    x_sins: np.ndarray
    bias: np.ndarray
    P0: np.ndarray
    info: dict = field(default_factory=dict)


def _level_window(still, dts, t_rel, window_s, search_s, max_s):
    """(start, stop, method) sample range of the levelling window: the first still run of at least
    ``window_s`` within ``search_s``, at most ``max_s`` long."""
    w = max(3, int(round(window_s / float(np.median(dts)))))
    w_max = max(w, int(round(max_s / float(np.median(dts)))))
    n = still.shape[0]
    cand = np.flatnonzero(still[: max(w, np.searchsorted(t_rel, search_s))])
    if cand.size:
        runs = np.split(cand, np.flatnonzero(np.diff(cand) > 1) + 1)
        long_runs = [r for r in runs if r.size >= w]
        if long_runs:
            r = long_runs[0]
            return int(r[0]), int(min(r[-1] + 1, r[0] + w_max)), "static-level"
    return 0, min(w, n), "level-moving"


def _carry_attitude(C, dtheta, bg, dts):
    """C_lb carried through the increments (bias-compensated, Earth rate neglected)."""
    q = dcm_to_quat(C)
    for k in range(dtheta.shape[0]):
        q = quat_mult(q, rotvec_to_quat(np.ascontiguousarray(dtheta[k] - bg * dts[k])))
    return quat_to_dcm(quat_normalize(q))


def _gyro_bias_at_rest(om_mean, T, C_lb, lat, noise):
    """Posterior gyro bias and its σ from the window mean (module docstring, step 2)."""
    w_ie_b = C_lb.T @ np.array([0.0, OMEGA_E * math.cos(lat), OMEGA_E * math.sin(lat)])
    r = noise.gyro_arw ** 2 / max(T, 1e-9)
    s0 = noise.gyro_bias_sigma ** 2
    gain = s0 / (s0 + r)
    return gain * (om_mean - w_ie_b), math.sqrt(s0 * r / (s0 + r))


def _initial_covariance(C_lb, sig_tilt_noise, sig_yaw, fix_sig_pos, fix_sig_vel, sig_bg, noise):
    """P0 (15) of the module docstring, step 6 (position N, E, U metres)."""
    P = np.zeros((em.N15, em.N15))
    sba = noise.accel_bias_sigma
    J = np.zeros((3, 3))
    J[0] = -C_lb[1] / G0
    J[1] = C_lb[0] / G0
    Pba = sba ** 2 * np.eye(3)
    P[em.BA, em.BA] = Pba
    P[em.ATT, em.ATT] = J @ Pba @ J.T + np.diag([sig_tilt_noise ** 2, sig_tilt_noise ** 2, sig_yaw ** 2])
    P[em.ATT, em.BA] = J @ Pba
    P[em.BA, em.ATT] = (J @ Pba).T
    P[em.BG, em.BG] = sig_bg ** 2 * np.eye(3)
    sp = np.asarray(fix_sig_pos, float)          # E, N, U
    P[em.POS, em.POS] = np.diag(np.array([sp[1], sp[0], sp[2]]) ** 2)
    P[em.VEL, em.VEL] = np.diag(np.asarray(fix_sig_vel, float) ** 2)
    return P


def _fix_velocity(source, k, fix):
    """(ENU velocity, its σ) of epoch k: the source's, else the difference of the positions of
    epochs k−1 and k over Δt ≤ 5 s (σ from both positions' σ), else NaN."""
    v = fix.vel_enu
    if np.all(np.isfinite(v)):
        return v, fix.sig_vel
    prev = source.fix(k - 1) if k > 0 else None
    dt = float(source.t[k] - source.t[k - 1]) if k > 0 else 0.0
    if prev is None or not 0.0 < dt <= 5.0:
        return np.full(3, np.nan), np.full(3, np.inf)
    return enu_offset(fix.llh, prev.llh) / dt, np.hypot(fix.sig_pos, prev.sig_pos) / dt


def _heading_epoch(source, t_after, opts):
    """(epoch index, heading rad, heading σ rad, velocity, velocity σ) of the alignment epoch (step 4)."""
    floor = math.radians(opts.heading_sigma_floor_deg)
    for k in range(source.n):
        if source.t[k] < t_after:
            continue
        fix = source.fix(k)
        if fix is None:
            continue
        v, sv = _fix_velocity(source, k, fix)
        if opts.heading_deg is not None:
            return k, math.radians(float(opts.heading_deg)), floor, v, sv
        speed = math.hypot(v[0], v[1]) if np.all(np.isfinite(v[:2])) else 0.0
        if speed > opts.heading_speed_mps:
            svh = math.hypot(sv[0], sv[1])
            return k, math.atan2(v[0], v[1]), max(svh / speed, floor), v, sv
    raise ConfigError(f"gins: no GNSS epoch after the levelling window with a horizontal speed above "
                      f"{opts.heading_speed_mps:g} m/s to give the heading; give the heading (heading_deg)")


def align(imu, opts, source):
    """The alignment of the module docstring -> :class:`Alignment`."""
    noise = opts.noise
    dts = sample_dt(imu)
    first = next((f for f in (source.fix(i) for i in range(min(source.n, 50))) if f is not None), None)
    g = float(np.linalg.norm(gravity_l(first.llh[0], first.llh[2]))) if first is not None else G0
    still = still_flags(imu, noise, opts.still_window_s, opts.still_k, g)
    a, b, method = _level_window(still, dts, imu.t - imu.t[0], opts.still_window_s, opts.align_search_s,
                                 opts.level_max_s)
    T = float(np.sum(dts[a:b]))
    f_mean = imu.dv_b[a:b].sum(axis=0) / T
    om_mean = imu.dtheta_b[a:b].sum(axis=0) / T
    roll, pitch = level(f_mean)
    k, yaw, sig_yaw, vel, sig_vel = _heading_epoch(source, float(imu.t[b - 1]), opts)
    fix = source.fix(k)
    j0 = min(max(int(np.argmin(np.abs(imu.t - source.t[k]))), b - 1), imu.n - 2)
    C0 = euler_to_dcm(roll, pitch, 0.0 if opts.heading_deg is None else yaw)
    bg, sig_bg = _gyro_bias_at_rest(om_mean, T, C0, fix.llh[0], noise)
    C = _carry_attitude(C0, imu.dtheta_b[b:j0 + 1], bg, dts[b:j0 + 1])
    e = dcm_to_euler(C)
    if opts.heading_deg is None:     # the course replaces the carried yaw; the Earth-rate part of the bias
        C = euler_to_dcm(e[0], e[1], yaw)
        bg, sig_bg = _gyro_bias_at_rest(om_mean, T, euler_to_dcm(roll, pitch, yaw - e[2]), fix.llh[0], noise)
        e[2] = yaw
    lever_l = C @ np.asarray(opts.lever_arm_b, float)
    vel = np.where(np.isfinite(vel), vel, 0.0)
    sig_vel = np.where(np.isfinite(sig_vel), sig_vel, max(1.0, opts.heading_speed_mps))
    d_enu = vel * (float(imu.t[j0]) - float(source.t[k])) - lever_l     # to the IMU sample's time and point
    llh = np.asarray(fix.llh, float).copy()
    rm, rn = radii(llh[0])
    llh += np.array([d_enu[1] / (rm + llh[2]), d_enu[0] / ((rn + llh[2]) * math.cos(llh[0])), d_enu[2]])
    x = make_state(dcm_to_quat(C), vel, llh)
    sig_tilt_noise = noise.accel_vrw / math.sqrt(T) / G0
    P0 = _initial_covariance(C, sig_tilt_noise, sig_yaw, fix.sig_pos, sig_vel, sig_bg, noise)
    info = {"method": method + ("+given-heading" if opts.heading_deg is not None else "+gnss-course"),
            "t": float(imu.t[j0]), "epoch": int(k), "roll": float(e[0]), "pitch": float(e[1]), "yaw": float(e[2]),
            "level_roll": roll, "level_pitch": pitch, "still_window": (float(imu.t[a] - dts[a]), float(imu.t[b - 1])),
            "sigma_yaw_rad": float(sig_yaw), "gyro_bias0": bg.tolist(), "sigma_gyro_bias0": float(sig_bg),
            "f_mean_minus_g": float(np.linalg.norm(f_mean) - g)}
    return Alignment(j0=j0, t=float(imu.t[j0]), x_sins=x, bias=np.concatenate([bg, np.zeros(3)]), P0=P0,
                     info=info), still

