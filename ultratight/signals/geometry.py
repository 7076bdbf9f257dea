"""Receiver–satellite geometry: visibility and the package's one home of the light-time solution —
per satellite over many receive times (:func:`light_time`, the exact broadcast ephemeris) and for
all channels at one receive time (:class:`MultiLightTime`, tabulated satellite states; the outer
loop's 100 Hz predictions).  Elevation/azimuth and the ENU frame come from
:mod:`ultratight.ins.earth`.

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

All-channel form (:class:`MultiLightTime`, same equations: the fixed-point step and the
observables are the same compiled functions as :func:`light_time`'s).  Speed: each satellite's
ephemeris state is tabulated once per run on a 0.5 s grid (:class:`SatTable`, one vectorised
``sat_state`` call per PRN) and evaluated by cubic Hermite interpolation (position+velocity,
error < 1 µm), and the iteration starts from the previous call's travel time (2 iterations by
default).  tests/test_engine.py checks it against :func:`light_time`.
"""

import math

import numpy as np
from numba import njit

from ultratight.constants import C, CA_LEN, F_CA, LAMBDA_L1, OMEGA_E, WGS84_A, WGS84_B
from ultratight.errors import ConfigError
from ultratight.ins.earth import elev_azim, elev_azim_rows
from ultratight.signals.ephemeris import eph_params, sat_state, state_scalar
from ultratight.signals.signal import GPS_L1CA

LIGHT_TIME_MAX_ITER = 8      # max fixed-point iterations of the light-time equation
LIGHT_TIME_TOL_S = 1e-12     # stop when the update is below this (next update ~1e-5 smaller)
NOMINAL_TAU_S = 0.075        # starting guess of the signal travel time, s
SAT_GRID_S = 0.5             # MultiLightTime: satellite-state tabulation step, s
MULTI_LT_ITER = 2            # MultiLightTime: fixed-point iterations per call (warm-started)


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
        if el_deg >= mask_deg and los_clears_earth(rx, pos):
            out.append((int(prn), el_deg))
    out.sort(key=lambda pe: -pe[1])
    if max_count is not None:
        out = out[: int(max_count)]
    return out if return_elev else [p for p, _ in out]


def los_clears_earth(rx, sat):
    """False when the straight segment receiver→satellite passes through the WGS-84 ellipsoid
    (tested exactly by scaling z by a/b, which maps the ellipsoid onto a sphere of radius a)."""
    k = np.array([1.0, 1.0, WGS84_A / WGS84_B])
    r0 = rx * k
    d = (sat - rx) * k
    t = -np.dot(r0, d) / np.dot(d, d)
    t = min(max(t, 0.0), 1.0)
    return np.linalg.norm(r0 + t * d) >= WGS84_A - 1.0     # 1 m slack for receivers on the surface


# ------------------------------------------------------------------ the light-time equations
# Layout of a satellite state at transmission: [x, y, z, vx, vy, vz, clk_s, clk_drift] (ECEF of the
# transmission epoch).  OBS_* index the observables written by _observables.
OBS_PR, OBS_PR_DOT, OBS_T_SV, OBS_T_TX, OBS_RANGE = 0, 1, 2, 3, 4
OBS_POS = 5                  # satellite position (3), ECEF of the reception epoch
OBS_VEL = 8                  # satellite velocity (3), same frame
OBS_LOS = 11                 # unit line of sight receiver -> satellite (3)
N_OBS = 14


@njit(cache=True)
def _travel_time(x, y, z, tau, rx0, rx1, rx2):
    """One fixed-point step of the light-time equation: ``|R3(Ω_E·τ)·r_sat − r_rx| / c`` for the
    satellite position (x, y, z) at the transmission time t_rx − τ."""
    th = OMEGA_E * tau
    c = math.cos(th)
    s = math.sin(th)
    dx = c * x + s * y - rx0
    dy = -s * x + c * y - rx1
    dz = z - rx2
    return math.sqrt(dx * dx + dy * dy + dz * dz) / C


@njit(cache=True)
def _observables(sat, tau, t_rx, rx0, rx1, rx2, rv0, rv1, rv2, bias_m, drift_mps, obs):
    """Observables (OBS_* layout) at the true reception time ``t_rx`` of the signal that left the
    satellite, whose state at t_rx − τ is ``sat``, for a receiver at (rx, rv) with clock bias /
    drift (m, m/s): Sagnac rotation into the reception frame, range, exact range rate (Sagnac rate
    included), pseudorange and its rate (satellite clock drift scaled by dt_tx/dt_rx)."""
    t_tx = t_rx - tau
    th = OMEGA_E * tau
    c = math.cos(th)
    s = math.sin(th)
    x, y, z = sat[0], sat[1], sat[2]
    px = c * x + s * y
    py = -s * x + c * y
    vx = c * sat[3] + s * sat[4]
    vy = -s * sat[3] + c * sat[4]
    vz = sat[5]
    dx = px - rx0
    dy = py - rx1
    dz = z - rx2
    rng = math.sqrt(dx * dx + dy * dy + dz * dz)
    ux = dx / rng
    uy = dy / rng
    uz = dz / rng
    # d/dθ R3(θ)·r = R3(θ)·(y, −x, 0)
    gx = c * y - s * x
    gy = -s * y - c * x
    a_term = ux * (vx - rv0) + uy * (vy - rv1) + uz * (vz - rv2)
    b_term = ux * (vx - OMEGA_E * gx) + uy * (vy - OMEGA_E * gy) + uz * vz
    rng_dot = a_term / (1.0 + b_term / C)
    clk = sat[6]
    clk_dot = sat[7]
    obs[OBS_PR] = rng + bias_m - C * clk
    obs[OBS_PR_DOT] = rng_dot + drift_mps - C * clk_dot * (1.0 - rng_dot / C)
    obs[OBS_T_SV] = t_tx + clk
    obs[OBS_T_TX] = t_tx
    obs[OBS_RANGE] = rng
    obs[OBS_POS] = px
    obs[OBS_POS + 1] = py
    obs[OBS_POS + 2] = z
    obs[OBS_VEL] = vx
    obs[OBS_VEL + 1] = vy
    obs[OBS_VEL + 2] = vz
    obs[OBS_LOS] = ux
    obs[OBS_LOS + 1] = uy
    obs[OBS_LOS + 2] = uz


@njit(cache=True)
def _light_time_kernel(p, rx, rv, t_rx, bias_m, drift_mps, tau_out, clk_out, obs_out):
    """Per-sample light-time solution with the exact ephemeris ``p``; see :func:`light_time`."""
    buf = np.empty(8)
    tau = NOMINAL_TAU_S
    for k in range(t_rx.shape[0]):
        # warm start from the previous sample (consecutive samples have nearly equal τ)
        if k == 0 or abs(t_rx[k] - t_rx[k - 1]) > 1.0:
            tau = NOMINAL_TAU_S
        for _ in range(LIGHT_TIME_MAX_ITER):
            state_scalar(p, t_rx[k] - tau, buf)
            tau_new = _travel_time(buf[0], buf[1], buf[2], tau, rx[k, 0], rx[k, 1], rx[k, 2])
            delta = tau - tau_new
            tau = tau_new
            if abs(delta) < LIGHT_TIME_TOL_S:
                break
        # buf holds the state at t_rx − τ_old = (t_rx − τ) − δ with |δ| < 1e-12 s: move it to
        # t_rx − τ to first order (the neglected term is ~acc·δ²/2 < 1e-24 m)
        for j in range(3):
            buf[j] += buf[3 + j] * delta
        buf[6] += buf[7] * delta
        _observables(buf, tau, t_rx[k], rx[k, 0], rx[k, 1], rx[k, 2], rv[k, 0], rv[k, 1], rv[k, 2],
                     bias_m[k], drift_mps[k], obs_out[k])
        tau_out[k] = tau
        clk_out[k, 0] = buf[6]
        clk_out[k, 1] = buf[7]


def light_time(eph, rx_pos_e, rx_vel_e, week, t_rx_tow, rx_clk_bias_m=0.0, rx_clk_drift_mps=0.0,
               rx_frames=None):
    """Signal observables of satellite ``eph`` at receiver positions/velocities for n receive times.

    ``rx_pos_e``, ``rx_vel_e``: (n,3) or (3,) ECEF at the true receive times ``t_rx_tow`` (n,)
    (GPS s of week ``week``; ``week`` is accepted for interface symmetry — the ephemeris
    evaluation wraps time differences within ±half a week).  Receiver clock bias/drift in metres
    and m/s (scalar or (n,)).  Returns a dict of (n,) / (n,3) arrays, see the module docstring:
    pseudorange_m, range_rate_mps, doppler_hz, code_phase_chips, carrier_phase_cycles, t_tx_tow,
    t_tx_gps, tau_s, range_m, sat_pos_e (rotated into the ECEF frame of t_rx), sat_vel_e (same),
    sat_clk_bias_s, sat_clk_drift, los_e (unit receiver→satellite), elev_rad, azim_rad.
    Numba kernels: the light-time solution, then :func:`ultratight.ins.earth.elev_azim` (one
    geodetic latitude per receiver position), which adds about a third to its cost — unless the
    caller passes the receivers' ``rx_frames`` (:func:`ultratight.ins.earth.enu_frames` of
    ``rx_pos_e``), computed once for all satellites.
    """
    rx = _Receivers(rx_pos_e, rx_vel_e, t_rx_tow, rx_clk_bias_m, rx_clk_drift_mps)
    return rx.solve(eph if isinstance(eph, np.ndarray) else eph_params(eph), rx_pos_e, rx_frames)


def light_time_many(params, rx_pos_e, rx_vel_e, t_rx_tow, rx_clk_bias_m=0.0, rx_clk_drift_mps=0.0,
                    rx_frames=None):
    """:func:`light_time` of several satellites (``params``: their :func:`ultratight.signals.ephemeris.
    eph_params` arrays or ephemerides) at the same receivers: the receivers' arrays are prepared once,
    so the per-satellite cost is mostly the kernel's (pass ``rx_frames``, as to :func:`light_time`);
    every value is the one :func:`light_time` gives."""
    rx = _Receivers(rx_pos_e, rx_vel_e, t_rx_tow, rx_clk_bias_m, rx_clk_drift_mps)
    return [rx.solve(p if isinstance(p, np.ndarray) else eph_params(p), rx_pos_e, rx_frames) for p in params]


class _Receivers:
    """The receive times, positions, velocities and clocks of :func:`light_time` as contiguous arrays."""

    def __init__(self, rx_pos_e, rx_vel_e, t_rx_tow, rx_clk_bias_m, rx_clk_drift_mps):
        self.t = np.ascontiguousarray(np.atleast_1d(np.asarray(t_rx_tow, dtype=np.float64)))
        n = self.t.shape[0]
        self.pos = np.ascontiguousarray(np.broadcast_to(np.asarray(rx_pos_e, dtype=np.float64), (n, 3)))
        self.vel = np.ascontiguousarray(np.broadcast_to(np.asarray(rx_vel_e, dtype=np.float64), (n, 3)))
        self.bias = np.ascontiguousarray(np.broadcast_to(np.asarray(rx_clk_bias_m, dtype=np.float64), (n,)))
        self.drift = np.ascontiguousarray(np.broadcast_to(np.asarray(rx_clk_drift_mps, dtype=np.float64), (n,)))

    def solve(self, p, rx_pos_e, rx_frames):
        """The observables dict of the satellite of parameters ``p`` (:func:`light_time`)."""
        n = self.t.shape[0]
        tau = np.empty(n)
        clk = np.empty((n, 2))
        obs = np.empty((n, N_OBS))
        _light_time_kernel(p, self.pos, self.vel, self.t, self.bias, self.drift, tau, clk, obs)
        pr = obs[:, OBS_PR]
        pr_dot = obs[:, OBS_PR_DOT]
        t_sv = obs[:, OBS_T_SV]
        sat_pos = obs[:, OBS_POS:OBS_POS + 3]
        if rx_frames is not None and np.ndim(rx_pos_e) == 2 and rx_frames.shape[0] == n \
                and rx_frames.flags.c_contiguous:
            elev, azim = elev_azim_rows(rx_frames, self.pos, np.ascontiguousarray(sat_pos))
        else:
            elev, azim = elev_azim(rx_pos_e, sat_pos, rx_frames)
        return {
            "pseudorange_m": pr,
            "range_rate_mps": pr_dot,
            "doppler_hz": -pr_dot / LAMBDA_L1,
            "code_phase_chips": np.mod(t_sv * F_CA, float(CA_LEN)),
            "carrier_phase_cycles": -pr / LAMBDA_L1,
            "t_tx_tow": t_sv,
            "t_tx_gps": obs[:, OBS_T_TX],
            "tau_s": tau,
            "range_m": obs[:, OBS_RANGE],
            "sat_pos_e": sat_pos,
            "sat_vel_e": obs[:, OBS_VEL:OBS_VEL + 3],
            "sat_clk_bias_s": clk[:, 0],
            "sat_clk_drift": clk[:, 1],
            "los_e": obs[:, OBS_LOS:OBS_LOS + 3],
            "elev_rad": elev,
            "azim_rad": azim,
        }


# ------------------------------------------------------------------ all channels at one receive time

class SatTable:
    """Satellite states of several PRNs tabulated on a ``step_s`` grid over [tow_start_s, tow_end_s]
    (plus margins), for :class:`MultiLightTime`."""

    def __init__(self, ephs, prns, tow_start_s, tow_end_s, step_s=SAT_GRID_S):
        self.prns = list(prns)
        self.t0 = float(tow_start_s) - 2.0 * step_s - 0.2
        n = int(np.ceil((float(tow_end_s) + 0.2 + 2.0 * step_s - self.t0) / step_s)) + 2
        self.h = float(step_s)
        t = self.t0 + np.arange(n) * self.h
        nch = len(self.prns)
        self.pos = np.empty((nch, n, 3))
        self.vel = np.empty((nch, n, 3))
        self.clk = np.empty((nch, n))
        self.clk_dot = np.empty((nch, n))
        for i, prn in enumerate(self.prns):
            if prn not in ephs:
                raise ConfigError(f"outer loop: no ephemeris for PRN {prn}")
            p, v, b, d = sat_state(ephs[prn], t)
            self.pos[i], self.vel[i], self.clk[i], self.clk_dot[i] = p, v, b, d
        self.n = n


@njit(cache=True)
def _hermite_pos_vel(tab_p, tab_v, i, k, s, h, out):
    """Cubic Hermite position/velocity of table row i at node k, fraction s, into out[0:6]."""
    s2 = s * s
    s3 = s2 * s
    h00 = 2 * s3 - 3 * s2 + 1
    h10 = s3 - 2 * s2 + s
    h01 = -2 * s3 + 3 * s2
    h11 = s3 - s2
    d00 = 6 * s2 - 6 * s
    d10 = 3 * s2 - 4 * s + 1
    d11 = 3 * s2 - 2 * s
    for a in range(3):
        p0 = tab_p[i, k, a]
        p1 = tab_p[i, k + 1, a]
        v0 = tab_v[i, k, a] * h
        v1 = tab_v[i, k + 1, a] * h
        out[a] = h00 * p0 + h10 * v0 + h01 * p1 + h11 * v1
        out[3 + a] = (d00 * p0 + d10 * v0 - d00 * p1 + d11 * v1) / h


@njit(cache=True)
def _table_node(t, t0, h, n):
    """(node k, fraction s) of time t on the table grid, k clamped to [0, n − 2]."""
    u = (t - t0) / h
    k = int(math.floor(u))
    if k < 0:
        k = 0
    if k > n - 2:
        k = n - 2
    return k, u - k


@njit(cache=True)
def _multi_light_time_kernel(t0, h, n, pos, vel, clk, clkd, rx, rv, t_rx, bias, drift, iters, tau,
                             out_pr, out_prdot, out_cp, out_ttx, out_los, chip_rate, code_len):
    """Light-time solution for every row of the table at one receive time (the equations of
    :func:`light_time`); code phases for a code of ``code_len`` chips at ``chip_rate`` chips/s."""
    sat = np.empty(8)
    obs = np.empty(N_OBS)
    for i in range(pos.shape[0]):
        ta = tau[i]
        for _ in range(iters):
            k, s = _table_node(t_rx - ta, t0, h, n)
            _hermite_pos_vel(pos, vel, i, k, s, h, sat)
            ta = _travel_time(sat[0], sat[1], sat[2], ta, rx[0], rx[1], rx[2])
        tau[i] = ta
        k, s = _table_node(t_rx - ta, t0, h, n)
        _hermite_pos_vel(pos, vel, i, k, s, h, sat)
        # clock (Hermite with the drift)
        s2 = s * s
        s3 = s2 * s
        sat[6] = (2 * s3 - 3 * s2 + 1) * clk[i, k] + (s3 - 2 * s2 + s) * clkd[i, k] * h \
            + (-2 * s3 + 3 * s2) * clk[i, k + 1] + (s3 - s2) * clkd[i, k + 1] * h
        sat[7] = ((6 * s2 - 6 * s) * clk[i, k] + (3 * s2 - 4 * s + 1) * clkd[i, k] * h
                  - (6 * s2 - 6 * s) * clk[i, k + 1] + (3 * s2 - 2 * s) * clkd[i, k + 1] * h) / h
        _observables(sat, ta, t_rx, rx[0], rx[1], rx[2], rv[0], rv[1], rv[2], bias, drift, obs)
        out_pr[i] = obs[OBS_PR]
        out_prdot[i] = obs[OBS_PR_DOT]
        out_ttx[i] = obs[OBS_T_SV]
        out_cp[i] = (obs[OBS_T_SV] * chip_rate) % code_len
        out_los[i, 0] = obs[OBS_LOS]
        out_los[i, 1] = obs[OBS_LOS + 1]
        out_los[i, 2] = obs[OBS_LOS + 2]


class MultiLightTime:
    """All-channel light-time solution on a :class:`SatTable` (see the module docstring); keeps each
    channel's travel time between calls as the next call's starting point."""

    def __init__(self, table, signal=GPS_L1CA):
        self.table = table
        self.signal = signal
        self.tau = np.full(len(table.prns), NOMINAL_TAU_S)
        n = len(table.prns)
        self._pr = np.empty(n)
        self._prd = np.empty(n)
        self._cp = np.empty(n)
        self._ttx = np.empty(n)
        self._los = np.empty((n, 3))

    def solve(self, rx_pos_e, rx_vel_e, t_rx_true_tow, clk_bias_m=0.0, clk_drift_mps=0.0, iters=MULTI_LT_ITER):
        """Observables of every channel at the true receive time ``t_rx_true_tow``: pseudorange_m,
        range_rate_mps, doppler_hz, code_phase_chips, code_rate_cps, t_tx_tow, los_e."""
        tb = self.table
        _multi_light_time_kernel(tb.t0, tb.h, tb.n, tb.pos, tb.vel, tb.clk, tb.clk_dot,
                                 np.ascontiguousarray(rx_pos_e, dtype=np.float64),
                                 np.ascontiguousarray(rx_vel_e, dtype=np.float64), float(t_rx_true_tow),
                                 float(clk_bias_m), float(clk_drift_mps), int(iters), self.tau,
                                 self._pr, self._prd, self._cp, self._ttx, self._los,
                                 float(self.signal.chip_rate_hz), float(self.signal.code_length))
        doppler = -self._prd / self.signal.wavelength_m
        return {
            "pseudorange_m": self._pr.copy(), "range_rate_mps": self._prd.copy(), "doppler_hz": doppler,
            "code_phase_chips": self._cp.copy(), "code_rate_cps": self.signal.code_rate_cps(doppler),
            "t_tx_tow": self._ttx.copy(), "los_e": self._los.copy(),
        }
