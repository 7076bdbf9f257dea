"""Receiver–satellite geometry: elevation/azimuth, visibility, and the light-time solution.

Conventions (all times are GPS system time, seconds of week, unless named otherwise):

* ``t_rx`` is the true GPS time of reception.  The receiver clock reads ``t_rx + b/c`` where
  ``b = rx_clk_bias_m`` (so a positive bias makes pseudoranges longer).
* The light-time equation ``c·τ = |R3(Ω_E·τ)·r_sat(t_rx − τ) − r_rx(t_rx)|`` is solved by
  fixed-point iteration (contraction factor |v_sat|/c ≈ 1e-5; 4 iterations reach < 1e-15 s).
  ``R3(θ)`` rotates the satellite's ECEF position at transmission into the ECEF frame of the
  reception epoch (Sagnac correction).
* ``pseudorange_m = c·τ + b − c·Δt_sv(t_tx)`` (no ionosphere / troposphere), i.e.
  ``c·(receiver-clock reception time − satellite-clock transmission time)``.
* ``t_tx_tow`` = satellite-clock transmission time ``t_tx + Δt_sv`` = the time carried by the
  arriving signal (C/A code epochs and LNAV bit edges are aligned to it).
* ``code_phase_chips = (t_tx_tow · 1.023e6) mod 1023`` — the C/A code phase (chips into the
  current code period) of the signal arriving at ``t_rx``.  Its precision is limited by the
  float64 resolution of a TOW (~6e-11 s ≈ 6e-5 chips).
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

import numpy as np

from ultratight.constants import C, CA_LEN, F_CA, LAMBDA_L1, OMEGA_E, WGS84_A, WGS84_E2
from ultratight.signals.ephemeris import sat_state

LIGHT_TIME_ITER = 4          # fixed-point iterations of the light-time equation
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
    (a high receiver sees satellites below its local horizon; the Earth is not checked as an
    occluder beyond the mask — choose the mask accordingly).  Unhealthy ephemerides are skipped.
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
    """False when the straight line receiver→satellite passes through the Earth (sphere of
    radius WGS84_B·0.999 used conservatively)."""
    d = sat - rx
    t = -np.dot(rx, d) / np.dot(d, d)
    if t <= 0.0 or t >= 1.0:
        return True
    closest = rx + t * d
    return np.linalg.norm(closest) > 6356752.0


def _rot_z(theta, v):
    """Rotate vectors v (n,3) by R3(theta): x' = x cos + y sin, y' = −x sin + y cos."""
    c, s = np.cos(theta), np.sin(theta)
    out = np.empty_like(v)
    out[:, 0] = c * v[:, 0] + s * v[:, 1]
    out[:, 1] = -s * v[:, 0] + c * v[:, 1]
    out[:, 2] = v[:, 2]
    return out


def light_time(eph, rx_pos_e, rx_vel_e, week, t_rx_tow, rx_clk_bias_m=0.0, rx_clk_drift_mps=0.0):
    """Signal observables of satellite ``eph`` at receiver positions/velocities for n receive times.

    ``rx_pos_e``, ``rx_vel_e``: (n,3) or (3,) ECEF at the true receive times ``t_rx_tow`` (n,)
    (GPS s of week ``week``; ``week`` is accepted for interface symmetry — the ephemeris
    evaluation wraps time differences within ±half a week).  Receiver clock bias/drift in metres
    and m/s (scalar or (n,)).  Returns a dict of (n,) / (n,3) arrays, see the module docstring:
    pseudorange_m, range_rate_mps, doppler_hz, code_phase_chips, carrier_phase_cycles, t_tx_tow,
    t_tx_gps, tau_s, range_m, sat_pos_e (rotated into the ECEF frame of t_rx), sat_vel_e (same),
    sat_clk_bias_s, sat_clk_drift, los_e (unit receiver→satellite), elev_rad, azim_rad.
    """
    t_rx = np.atleast_1d(np.asarray(t_rx_tow, dtype=np.float64))
    n = t_rx.shape[0]
    rx = np.broadcast_to(np.asarray(rx_pos_e, dtype=np.float64), (n, 3))
    rv = np.broadcast_to(np.asarray(rx_vel_e, dtype=np.float64), (n, 3))
    tau = np.full(n, NOMINAL_TAU_S)
    for _ in range(LIGHT_TIME_ITER):
        pos = sat_state(eph, t_rx - tau)[0]
        d = _rot_z(OMEGA_E * tau, pos) - rx
        tau = np.sqrt(np.einsum("ij,ij->i", d, d)) / C
    t_tx = t_rx - tau
    pos, vel, clk, clk_dot = sat_state(eph, t_tx)
    theta = OMEGA_E * tau
    pos_r = _rot_z(theta, pos)
    vel_r = _rot_z(theta, vel)
    d = pos_r - rx
    rng = np.sqrt(np.einsum("ij,ij->i", d, d))
    los = d / rng[:, None]
    # d/dθ R3(θ)·r = (−x sinθ + y cosθ, −x cosθ − y sinθ, 0) = R3(θ)·(y, −x, 0)
    dpos_dtheta = _rot_z(theta, np.stack((pos[:, 1], -pos[:, 0], np.zeros(n)), axis=-1))
    a_term = np.einsum("ij,ij->i", los, vel_r - rv)
    b_term = np.einsum("ij,ij->i", los, vel_r - OMEGA_E * dpos_dtheta)
    rng_dot = a_term / (1.0 + b_term / C)       # exact derivative of the light-time range
    tau_dot = rng_dot / C
    bias_m = np.broadcast_to(np.asarray(rx_clk_bias_m, dtype=np.float64), (n,))
    drift_mps = np.broadcast_to(np.asarray(rx_clk_drift_mps, dtype=np.float64), (n,))
    pr = rng + bias_m - C * clk
    pr_dot = rng_dot + drift_mps - C * clk_dot * (1.0 - tau_dot)
    t_sv = t_tx + clk
    code_phase = np.mod(t_sv * F_CA, float(CA_LEN))
    elev, azim = elev_azim(rx, pos_r)
    return {
        "pseudorange_m": pr,
        "range_rate_mps": pr_dot,
        "doppler_hz": -pr_dot / LAMBDA_L1,
        "code_phase_chips": code_phase,
        "carrier_phase_cycles": -pr / LAMBDA_L1,
        "t_tx_tow": t_sv,
        "t_tx_gps": t_tx,
        "tau_s": tau,
        "range_m": rng,
        "sat_pos_e": pos_r,
        "sat_vel_e": vel_r,
        "sat_clk_bias_s": clk,
        "sat_clk_drift": clk_dot,
        "los_e": los,
        "elev_rad": elev,
        "azim_rad": azim,
    }
