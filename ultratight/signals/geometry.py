"""Receiver–satellite geometry: elevation/azimuth, visibility, and the light-time solution.

Conventions (all times are GPS system time, seconds of week, unless named otherwise):

* ``t_rx`` is the true GPS time of reception.  The receiver clock reads ``t_rx + b/c`` where
  ``b = rx_clk_bias_m`` (so a positive bias makes pseudoranges longer).
* The light-time equation ``c·τ = |R3(Ω_E·τ)·r_sat(t_rx − τ) − r_rx(t_rx)|`` is solved by
  fixed-point iteration (contraction factor |v_sat|/c ≈ 1e-5; iterated until the update is < 1e-12 s, so the
  remaining error is < 1e-16 s; warm-started from the previous sample).
  ``R3(θ)`` rotates the satellite's ECEF position at transmission into the ECEF frame of the
  reception epoch (Sagnac correction).
* ``pseudorange_m = c·τ + b − c·Δt_sv(t_tx)`` (no ionosphere / troposphere), i.e.
  ``c·(receiver-clock reception time − satellite-clock transmission time)``.
* ``t_tx_tow`` = satellite-clock transmission time ``t_tx + Δt_sv`` = the time carried by the
  arriving signal (C/A code epochs and LNAV bit edges are aligned to it).
* ``code_phase_chips = (t_tx_tow · 1.023e6) mod 1023`` — the C/A code phase (chips into the
  current code period) of the signal arriving at ``t_rx``.  Its precision is limited by the
  float64 resolution of a TOW (~6e-11 s ≈ 6e-5 chips).
* All outputs are functions of the *true* reception time ``t_rx``.  The code phase depends only
  on the arriving signal (not on the receiver clock): it advances at
  ``F_CA·(1 − (range_rate − rx_clk_drift)/c)`` chips/s.  The carrier phase is the phase after
  mixing with the receiver-clock LO, so it contains ``−b/λ``.  A generator whose sample clock is
  the receiver clock takes sample k at receiver time ``t0 + k/fs``, i.e. true time
  ``t_rx = t0 + k/fs − b/c``.
* ``range_rate_mps = d(pseudorange)/d(t_rx)`` exactly (derivative of the light-time solution,
  including the Sagnac rate, the satellite clock drift (scaled by dt_tx/dt_rx) and the receiver
  clock drift ``rx_clk_drift_mps``).
* ``doppler_hz = −range_rate_mps / λ_L1``: positive when the satellite approaches.
* ``carrier_phase_cycles = −pseudorange_m / λ_L1``: the phase of the received L1 carrier
  relative to a nominal 1575.42 MHz oscillator driven by the receiver clock,
  ``F_L1·(t_sv_tx − t_rcv)`` (no ionosphere, so no code–carrier divergence).  Hence
  ``d(carrier_phase_cycles)/dt = doppler_hz`` exactly.  A generator producing complex baseband
  uses ``exp(j·2π·carrier_phase_cycles)``.
"""

import math

import numpy as np
from numba import njit

from ultratight.constants import C, CA_LEN, F_CA, LAMBDA_L1, OMEGA_E, WGS84_A, WGS84_B, WGS84_E2
from ultratight.signals.ephemeris import eph_params, sat_state, state_scalar

LIGHT_TIME_MAX_ITER = 8      # max fixed-point iterations of the light-time equation
LIGHT_TIME_TOL_S = 1e-12     # stop when the update is below this (next update ~1e-5 smaller)
NOMINAL_TAU_S = 0.075        # starting guess of the signal travel time, s


def _geodetic_lat_lon(pos_e):
    """Vectorised geodetic latitude/longitude (rad) of ECEF points (n,3)."""
    x, y, z = pos_e[..., 0], pos_e[..., 1], pos_e[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(6):
        s = np.sin(lat)
        rn = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
        c_lat = np.cos(lat)
        h = np.where(np.abs(c_lat) > 1e-9, p / np.where(np.abs(c_lat) > 1e-9, c_lat, 1.0) - rn,
                     np.abs(z) - rn * (1.0 - WGS84_E2))
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * rn / (rn + h)))
    return lat, lon


def geodetic_llh(pos_e):
    """Vectorised geodetic latitude, longitude (rad) and ellipsoidal height (m) of ECEF points."""
    pos = np.asarray(pos_e, dtype=np.float64)
    lat, lon = _geodetic_lat_lon(pos)
    p = np.hypot(pos[..., 0], pos[..., 1])
    s = np.sin(lat)
    rn = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
    c_lat = np.cos(lat)
    h = np.where(np.abs(c_lat) > 1e-9, p / np.where(np.abs(c_lat) > 1e-9, c_lat, 1.0) - rn,
                 np.abs(pos[..., 2]) - rn * (1.0 - WGS84_E2))
    return lat, lon, h


def enu_basis(rx_pos_e):
    """Local east, north, up unit vectors (each (n,3) or (3,)) at ECEF position(s)."""
    rx = np.asarray(rx_pos_e, dtype=np.float64)
    lat, lon = _geodetic_lat_lon(rx)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    east = np.stack((-so, co, np.zeros_like(so)), axis=-1)
    north = np.stack((-sl * co, -sl * so, cl), axis=-1)
    up = np.stack((cl * co, cl * so, sl), axis=-1)
    return east, north, up


def elev_azim(rx_pos_e, sat_pos_e):
    """Elevation and azimuth (rad) of satellite(s) seen from receiver(s); broadcasting (…,3).

    Elevation is measured from the local geodetic horizon (negative below it); azimuth is
    clockwise from north in [0, 2π)."""
    rx = np.asarray(rx_pos_e, dtype=np.float64)
    d = np.asarray(sat_pos_e, dtype=np.float64) - rx
    east, north, up = enu_basis(rx)
    de = np.sum(d * east, axis=-1)
    dn = np.sum(d * north, axis=-1)
    du = np.sum(d * up, axis=-1)
    elev = np.arctan2(du, np.hypot(de, dn))
    az = np.mod(np.arctan2(de, dn), 2.0 * np.pi)
    return elev, az


def _ephs_items(ephs):
    if isinstance(ephs, dict):
        return list(ephs.items())
    return [(e.prn, e) for e in ephs]


def visible_prns(ephs, rx_pos_e, week, tow_s, mask_deg, max_count=None, return_elev=False):
    """PRNs whose elevation at (week, tow_s) is >= ``mask_deg``, highest elevation first.

    ``ephs``: dict prn -> Ephemeris (or an iterable of Ephemeris).  ``mask_deg`` may be negative
    (a high receiver sees satellites below its local horizon); lines of sight that pass through
    the WGS-84 ellipsoid are always excluded.  Positions are evaluated at ``tow_s − 0.075 s``
    (nominal signal travel time).  Unhealthy ephemerides are skipped.
    ``max_count`` keeps the highest ones.  With ``return_elev`` returns a list of (prn, elev_deg).
    """
    rx = np.asarray(rx_pos_e, dtype=np.float64).reshape(3)
    out = []
    for prn, eph in _ephs_items(ephs):
        if eph is None or not eph.healthy:
            continue
        pos = sat_state(eph, tow_s - NOMINAL_TAU_S)[0][0]
        el, _ = elev_azim(rx, pos)
        el_deg = float(np.degrees(el))
        if el_deg >= mask_deg and _earth_clear(rx, pos):
            out.append((int(prn), el_deg))
    out.sort(key=lambda pe: -pe[1])
    if max_count is not None:
        out = out[: int(max_count)]
    return out if return_elev else [p for p, _ in out]


def _earth_clear(rx, sat):
    """False when the straight segment receiver→satellite passes through the WGS-84 ellipsoid
    (tested exactly by scaling z by a/b, which maps the ellipsoid onto a sphere of radius a)."""
    k = np.array([1.0, 1.0, WGS84_A / WGS84_B])
    r0 = rx * k
    d = (sat - rx) * k
    t = -np.dot(r0, d) / np.dot(d, d)
    t = min(max(t, 0.0), 1.0)
    return np.linalg.norm(r0 + t * d) >= WGS84_A - 1.0     # 1 m slack for receivers on the surface


WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)     # second eccentricity squared


@njit(cache=True)
def _geodetic_sincos(x, y, z):
    """sin/cos of geodetic latitude and longitude (Bowring's closed form: latitude error
    < 1e-9 rad up to LEO heights — ample for elevation angles).  Poles give lon = 0."""
    p = math.sqrt(x * x + y * y)
    if p < 1e-3:
        return (1.0 if z >= 0.0 else -1.0), 0.0, 0.0, 1.0
    so = y / p
    co = x / p
    th = math.atan2(z * WGS84_A, p * WGS84_B)
    st = math.sin(th)
    ct = math.cos(th)
    num = z + WGS84_EP2 * WGS84_B * st * st * st
    den = p - WGS84_E2 * WGS84_A * ct * ct * ct
    hyp = math.sqrt(num * num + den * den)
    return num / hyp, den / hyp, so, co


@njit(cache=True)
def _light_time_kernel(p, rx, rv, t_rx, bias_m, drift_mps, out, out3):
    """Per-sample light-time solution; see :func:`light_time` (columns documented there)."""
    buf = np.empty(8)
    tau = NOMINAL_TAU_S
    for k in range(t_rx.shape[0]):
        # warm start from the previous sample (consecutive samples have nearly equal τ)
        if k == 0 or abs(t_rx[k] - t_rx[k - 1]) > 1.0:
            tau = NOMINAL_TAU_S
        for _ in range(LIGHT_TIME_MAX_ITER):
            state_scalar(p, t_rx[k] - tau, buf)
            th = OMEGA_E * tau
            c = math.cos(th)
            s = math.sin(th)
            dx = c * buf[0] + s * buf[1] - rx[k, 0]
            dy = -s * buf[0] + c * buf[1] - rx[k, 1]
            dz = buf[2] - rx[k, 2]
            tau_new = math.sqrt(dx * dx + dy * dy + dz * dz) / C
            delta = tau - tau_new
            tau = tau_new
            if abs(delta) < LIGHT_TIME_TOL_S:
                break
        # buf holds the state at t_rx − τ_old = (t_rx − τ) − δ with |δ| < 1e-12 s: move it to
        # t_rx − τ to first order (the neglected term is ~acc·δ²/2 < 1e-24 m)
        for j in range(3):
            buf[j] += buf[3 + j] * delta
        buf[6] += buf[7] * delta
        t_tx = t_rx[k] - tau
        th = OMEGA_E * tau
        c = math.cos(th)
        s = math.sin(th)
        x, y, z = buf[0], buf[1], buf[2]
        px = c * x + s * y
        py = -s * x + c * y
        vx = c * buf[3] + s * buf[4]
        vy = -s * buf[3] + c * buf[4]
        vz = buf[5]
        dx = px - rx[k, 0]
        dy = py - rx[k, 1]
        dz = z - rx[k, 2]
        rng = math.sqrt(dx * dx + dy * dy + dz * dz)
        ux = dx / rng
        uy = dy / rng
        uz = dz / rng
        # d/dθ R3(θ)·r = R3(θ)·(y, −x, 0)
        gx = c * y - s * x
        gy = -s * y - c * x
        a_term = ux * (vx - rv[k, 0]) + uy * (vy - rv[k, 1]) + uz * (vz - rv[k, 2])
        b_term = ux * (vx - OMEGA_E * gx) + uy * (vy - OMEGA_E * gy) + uz * vz
        rng_dot = a_term / (1.0 + b_term / C)
        clk = buf[6]
        clk_dot = buf[7]
        pr = rng + bias_m[k] - C * clk
        pr_dot = rng_dot + drift_mps[k] - C * clk_dot * (1.0 - rng_dot / C)
        t_sv = t_tx + clk
        sl, cl, so, co = _geodetic_sincos(rx[k, 0], rx[k, 1], rx[k, 2])
        de = -so * dx + co * dy
        dn = -sl * co * dx - sl * so * dy + cl * dz
        du = cl * co * dx + cl * so * dy + sl * dz
        out[k, 0] = pr
        out[k, 1] = pr_dot
        out[k, 2] = t_sv
        out[k, 3] = t_tx
        out[k, 4] = tau
        out[k, 5] = rng
        out[k, 6] = clk
        out[k, 7] = clk_dot
        out[k, 8] = math.atan2(du, math.sqrt(de * de + dn * dn))
        az = math.atan2(de, dn)
        out[k, 9] = az + 2.0 * math.pi if az < 0.0 else az
        out3[k, 0, 0] = px
        out3[k, 0, 1] = py
        out3[k, 0, 2] = z
        out3[k, 1, 0] = vx
        out3[k, 1, 1] = vy
        out3[k, 1, 2] = vz
        out3[k, 2, 0] = ux
        out3[k, 2, 1] = uy
        out3[k, 2, 2] = uz


def light_time(eph, rx_pos_e, rx_vel_e, week, t_rx_tow, rx_clk_bias_m=0.0, rx_clk_drift_mps=0.0):
    """Signal observables of satellite ``eph`` at receiver positions/velocities for n receive times.

    ``rx_pos_e``, ``rx_vel_e``: (n,3) or (3,) ECEF at the true receive times ``t_rx_tow`` (n,)
    (GPS s of week ``week``; ``week`` is accepted for interface symmetry — the ephemeris
    evaluation wraps time differences within ±half a week).  Receiver clock bias/drift in metres
    and m/s (scalar or (n,)).  Returns a dict of (n,) / (n,3) arrays, see the module docstring:
    pseudorange_m, range_rate_mps, doppler_hz, code_phase_chips, carrier_phase_cycles, t_tx_tow,
    t_tx_gps, tau_s, range_m, sat_pos_e (rotated into the ECEF frame of t_rx), sat_vel_e (same),
    sat_clk_bias_s, sat_clk_drift, los_e (unit receiver→satellite), elev_rad, azim_rad.
    Numba kernel: about 0.1 µs… 0.3 µs per evaluation.
    """
    t_rx = np.ascontiguousarray(np.atleast_1d(np.asarray(t_rx_tow, dtype=np.float64)))
    n = t_rx.shape[0]
    rx = np.ascontiguousarray(np.broadcast_to(np.asarray(rx_pos_e, dtype=np.float64), (n, 3)))
    rv = np.ascontiguousarray(np.broadcast_to(np.asarray(rx_vel_e, dtype=np.float64), (n, 3)))
    bias = np.ascontiguousarray(np.broadcast_to(np.asarray(rx_clk_bias_m, dtype=np.float64), (n,)))
    drift = np.ascontiguousarray(np.broadcast_to(np.asarray(rx_clk_drift_mps, dtype=np.float64), (n,)))
    p = eph if isinstance(eph, np.ndarray) else eph_params(eph)
    out = np.empty((n, 10))
    out3 = np.empty((n, 3, 3))
    _light_time_kernel(p, rx, rv, t_rx, bias, drift, out, out3)
    pr = out[:, 0]
    pr_dot = out[:, 1]
    t_sv = out[:, 2]
    return {
        "pseudorange_m": pr,
        "range_rate_mps": pr_dot,
        "doppler_hz": -pr_dot / LAMBDA_L1,
        "code_phase_chips": np.mod(t_sv * F_CA, float(CA_LEN)),
        "carrier_phase_cycles": -pr / LAMBDA_L1,
        "t_tx_tow": t_sv,
        "t_tx_gps": out[:, 3],
        "tau_s": out[:, 4],
        "range_m": out[:, 5],
        "sat_pos_e": out3[:, 0, :],
        "sat_vel_e": out3[:, 1, :],
        "sat_clk_bias_s": out[:, 6],
        "sat_clk_drift": out[:, 7],
        "los_e": out3[:, 2, :],
        "elev_rad": out[:, 8],
        "azim_rad": out[:, 9],
    }
