"""Truth flight of the paper-fads scenario (Duan et al. 2024, §2): profile, attitude and ideal IMU.

This project's choices (the paper gives none): heading East at constant latitude (V_y = 0), wings level
(zero bank about the velocity); climb 0–``t_climb`` from ``h0`` to ``h_cruise`` with Mach ``mach0`` →
``mach_cruise``, cruise, descent to ``h_end`` with Mach → ``mach_end``; altitude and ground speed
follow quintic smoothsteps (zero rate and acceleration at the phase joints, so the specific force
is continuous) between the end speeds ``M a(h)``; in cruise (isothermal above 11 km) the Mach is
exact. α = α₀ + α₁ sin(2πt/P_α), β = β₁ sin(2πt/P_β). Attitude ``C_bn = Ry(γ) C_bw(α, β)ᵀ``-chain:
the wind axes are the velocity axes (flight-path angle γ = asin(ḣ/V), track East, no wind), and the
body is rotated from them by α and β, so pitch = γ + α exactly when β = 0 (the chosen "pitch = flight-path
angle + α"); with β ≠ 0 a small roll appears (≈ β·sin γ, under 0.07° here).

IMU truth (body frame x nose, y right, z down): ``f_b = C_nb (V̇_n − g_n + (2ω_ie + ω_en) × V_n)``,
``ω_ib_b = ω_nb_b + C_nb (ω_ie + ω_en)`` in ESD (the air-data filter's mechanization run backwards),
integrated over each IMU interval by 3-point Gauss–Legendre quadrature into increments
(Δθ, Δv), the form :func:`ultratight.ins.imu.apply_errors` corrupts. Time derivatives are central
differences (δ = 1 ms) of the analytic profile (error < 1e-8 m/s², rad/s).
"""

import math

import numpy as np
from numba import njit

from ultratight.airdata import atmosphere
from ultratight.airdata.frames import dcm_to_euler, euler_to_dcm, wind_axes_dcm
from ultratight.constants import OMEGA_E
from ultratight.errors import ConfigError
from ultratight.ins.earth import gravity_nu, radii

_GL3_X, _GL3_W = np.polynomial.legendre.leggauss(3)
_DIFF_S = 1e-3

DEFAULT_PROFILE = {
    "lat_deg": 30.0, "lon_deg": 103.0, "duration_s": 1000.0,
    "t_climb_s": 300.0, "t_descent_s": 700.0,
    "h0_m": 1000.0, "h_cruise_m": 20000.0, "h_end_m": 1000.0,
    "mach0": 1.0, "mach_cruise": 8.0, "mach_end": 1.0,
    "aoa0_deg": 2.0, "aoa_amp_deg": 1.0, "aoa_period_s": 60.0,
    "sideslip_amp_deg": 0.5, "sideslip_period_s": 45.0,
}


def _smooth(u):
    u = np.clip(u, 0.0, 1.0)
    return u ** 3 * (10.0 - 15.0 * u + 6.0 * u * u)


def _dsmooth(u):
    inside = (u > 0.0) & (u < 1.0)
    return np.where(inside, 30.0 * u * u * (1.0 - u) ** 2, 0.0)


@njit(cache=True)
def gravity_esd_batch(lat, h):
    """Normal gravity in ESD (n, 3): [0, −g_N, −g_U] of :func:`ultratight.ins.earth.gravity_nu`."""
    out = np.zeros((lat.shape[0], 3))
    for i in range(lat.shape[0]):
        gn, gu = gravity_nu(lat[i], h[i])
        out[i, 1] = -gn
        out[i, 2] = -gu
    return out


@njit(cache=True)
def nav_rates_esd(lat, h, vel):
    """Earth rate ω_ie and transport rate ω_en in ESD, (n, 3) each (the air-data filter's mechanization)."""
    n = lat.shape[0]
    wie = np.zeros((n, 3))
    wen = np.zeros((n, 3))
    for i in range(n):
        rm, rn = radii(lat[i])
        wie[i, 1] = -OMEGA_E * math.cos(lat[i])
        wie[i, 2] = -OMEGA_E * math.sin(lat[i])
        wen[i, 0] = vel[i, 1] / (rm + h[i])
        wen[i, 1] = -vel[i, 0] / (rn + h[i])
        wen[i, 2] = -vel[i, 0] * math.tan(lat[i]) / (rn + h[i])
    return wie, wen


class Flight:
    """The analytic flight; ``profile`` is a dict of :data:`DEFAULT_PROFILE` keys (SI inside)."""

    def __init__(self, profile=None):
        p = dict(DEFAULT_PROFILE)
        p.update(profile or {})
        self.profile = p
        self.lat0 = math.radians(p["lat_deg"])
        self.lon0 = math.radians(p["lon_deg"])
        self.duration_s = float(p["duration_s"])
        self.t1, self.t2 = float(p["t_climb_s"]), float(p["t_descent_s"])
        if not 0.0 < self.t1 <= self.t2 < self.duration_s:
            raise ConfigError("flight: need 0 < t_climb_s <= t_descent_s < duration_s")
        self.h = (p["h0_m"], p["h_cruise_m"], p["h_end_m"])
        if min(self.h) < 0.0 or max(self.h) > 30000.0:
            raise ConfigError("flight: altitudes must be within 0–30 km")
        a = atmosphere.speed_of_sound(np.array(self.h))
        self.v = tuple(float(m * s) for m, s in zip((p["mach0"], p["mach_cruise"], p["mach_end"]), a))
        if min(p["mach0"], p["mach_cruise"], p["mach_end"]) <= 0.3:
            raise ConfigError("flight: Mach numbers must be > 0.3")
        self.aoa = (math.radians(p["aoa0_deg"]), math.radians(p["aoa_amp_deg"]), float(p["aoa_period_s"]))
        self.beta = (math.radians(p["sideslip_amp_deg"]), float(p["sideslip_period_s"]))

    # ------------------------------------------------------------------ profile
    def _phase(self, t, y0, y1, y2):
        t = np.asarray(t, float)
        u1 = t / self.t1
        u2 = (t - self.t2) / (self.duration_s - self.t2)
        y = np.where(t < self.t2, y0 + (y1 - y0) * _smooth(u1), y1 + (y2 - y1) * _smooth(u2))
        dy = np.where(t < self.t2, (y1 - y0) * _dsmooth(u1) / self.t1,
                      (y2 - y1) * _dsmooth(u2) / (self.duration_s - self.t2))
        return y, dy

    def altitude(self, t):
        return self._phase(t, *self.h)

    def angles(self, t):
        """α, β (rad) at t."""
        t = np.asarray(t, float)
        a0, a1, pa = self.aoa
        b1, pb = self.beta
        return a0 + a1 * np.sin(2 * np.pi * t / pa), b1 * np.sin(2 * np.pi * t / pb)

    def vel_att(self, t):
        """ESD ground velocity (n, 3), altitude (n,) and C_bn (n, 3, 3) at t (no wind)."""
        t = np.atleast_1d(np.asarray(t, float))
        h, hdot = self.altitude(t)
        speed, _ = self._phase(t, *self.v)
        vel = np.stack([np.sqrt(speed ** 2 - hdot ** 2), np.zeros_like(t), -hdot], axis=1)
        gamma = np.arcsin(hdot / speed)
        alpha, beta = self.angles(t)
        C_vn = euler_to_dcm(gamma, np.zeros_like(t), np.zeros_like(t))       # velocity axes -> n
        C_bn = C_vn @ wind_axes_dcm(alpha, beta)                              # body -> wind -> n
        return vel, h, C_bn

    def body_signals(self, t):
        """True specific force f_b and angular rate ω_ib_b (n, 3) each at times t."""
        t = np.atleast_1d(np.asarray(t, float))
        d = _DIFF_S
        vel, h, C = self.vel_att(t)
        vp, _, Cp = self.vel_att(t + d)
        vm, _, Cm = self.vel_att(t - d)
        vdot = (vp - vm) / (2 * d)
        Cdot = (Cp - Cm) / (2 * d)
        Om = np.transpose(C, (0, 2, 1)) @ Cdot                                 # [ω_nb_b ×]
        w_nb = 0.5 * np.stack([Om[:, 2, 1] - Om[:, 1, 2], Om[:, 0, 2] - Om[:, 2, 0],
                               Om[:, 1, 0] - Om[:, 0, 1]], axis=1)
        lat = np.full(t.shape, self.lat0)
        wie, wen = nav_rates_esd(lat, h, vel)
        g = gravity_esd_batch(lat, h)
        f_n = vdot - g + np.cross(2.0 * wie + wen, vel)
        f_b = np.einsum("nji,nj->ni", C, f_n)
        w_ib = w_nb + np.einsum("nji,nj->ni", C, wie + wen)
        return f_b, w_ib

    # ------------------------------------------------------------------ sampled truth
    def truth(self, t):
        """dict: t, lon, lat, h, vel (n, 3), pitch/yaw/roll, C_bn, alpha, beta at times t (grid from 0)."""
        t = np.atleast_1d(np.asarray(t, float))
        vel, h, C = self.vel_att(t)
        pitch, yaw, roll = dcm_to_euler(C)
        alpha, beta = self.angles(t)
        return {"t": t, "lon": self.longitude(t), "lat": np.full(t.shape, self.lat0), "h": h, "vel": vel,
                "pitch": pitch, "yaw": yaw, "roll": roll, "C_bn": C, "alpha": alpha, "beta": beta}

    def longitude(self, t):
        """λ(t) = λ0 + ∫ V_x / ((R_N + h) cos L) dt (3-point Gauss–Legendre on a 0.1 s grid)."""
        t = np.atleast_1d(np.asarray(t, float))
        step = 0.1
        n = int(math.ceil(max(t.max(), 0.0) / step)) + 1
        edges = np.arange(n + 1) * step
        tq = (0.5 * (edges[:-1] + edges[1:]))[:, None] + 0.5 * step * _GL3_X[None, :]
        vel, h, _ = self.vel_att(tq.ravel())
        _, rn = radii(self.lat0)
        rate = (vel[:, 0] / ((rn + h) * math.cos(self.lat0))).reshape(tq.shape)
        cum = np.concatenate([[0.0], np.cumsum((rate * (0.5 * step * _GL3_W)).sum(axis=1))])
        # within an interval: 3-point quadrature from the interval start to t
        k = np.clip(np.floor(t / step).astype(int), 0, n - 1)
        a = edges[k]
        half = 0.5 * (t - a)
        tq2 = (a + half)[:, None] + half[:, None] * _GL3_X[None, :]
        v2, h2, _ = self.vel_att(tq2.ravel())
        r2 = (v2[:, 0] / ((rn + h2) * math.cos(self.lat0))).reshape(tq2.shape)
        return self.lon0 + cum[k] + (r2 * (half[:, None] * _GL3_W)).sum(axis=1)

    def imu_increments(self, rate_hz, duration_s=None):
        """Ideal (Δθ_b, Δv_b) (n, 3) over intervals (k/rate, (k+1)/rate], n = duration · rate."""
        n = int(round((self.duration_s if duration_s is None else duration_s) * rate_hz))
        dt = 1.0 / rate_hz
        mid = (np.arange(n) + 0.5) * dt
        tq = (mid[:, None] + 0.5 * dt * _GL3_X[None, :]).ravel()
        f_b, w_b = self.body_signals(tq)
        w = (0.5 * dt * _GL3_W)[None, :, None]
        return (w_b.reshape(n, 3, 3) * w).sum(axis=1), (f_b.reshape(n, 3, 3) * w).sum(axis=1)
