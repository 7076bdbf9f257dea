"""Analytic vehicle trajectories (truth for the IF generator, IMU synthesis and tests).

Motion is described in the **fixed local tangent frame l0**: the ENU frame at
the start point (lat0, lon0, h0), attached to the Earth.  Positions in l0 are
piecewise polynomials (or arcs for the turning kind) of time, so position,
velocity, acceleration and jerk are exact closed forms; ECEF follows by a
constant rotation and offset, ``pos_e = r0_e + C_el0 @ p_l0`` (exact, sub-mm,
vectorised).

Because l0 is a plane tangent to the ellipsoid at the start, a vehicle moving
horizontally in l0 gains ellipsoidal height ~ d^2 / (2 R): for the
paper-highdyn flight (~180 km east, ~7 km north in 60 s) this is ~2.6 km over
60 s (computed exactly by :meth:`Trajectory.kinematics`).  The "ENU
accelerations" of Zhao et al. 2014, Table 2, are interpreted in l0 (see docs/references.md).

Trajectory kinds (``[trajectory]`` table of a scenario, see docs/ins.md):

* ``"static"``: stays at the start point.
* ``"segments"``: piecewise constant jerk (Zhao et al. 2014, Table 2).  ``vel0_enu_mps``;
  ``segments = [{t0, acc_enu, jerk_enu}, ...]``: from ``t0`` to the next
  segment's ``t0`` the l0 acceleration is ``acc_enu + jerk_enu * (t - t0)``.
  The first segment must start at t0 = 0.  Acceleration may jump between
  segments (velocity and position are continuous).
* ``"swing"``: a swinging base (swing table, ship at anchor): static position,
  sinusoidal Euler angles ``att = att0_deg + swing_amp_deg * sin(2 pi t /
  swing_period_s + swing_phase_deg)`` per axis [roll, pitch, yaw] (defaults, a
  choice of this project for Sun et al. 2012 §4.2–4.3, which give none: ±10° / 8 s,
  ±8° / 6 s, ±5° / 10 s, phases 0).  The body rate is the exact Euler-rate map,
  so the IMU increments (Gauss–Legendre integrals of the rate and specific force)
  are exact, coning and sculling included.
* ``"file"``: positions from a file (``path``, relative to the scenario TOML; ``frame = "ecef" |
  "llh"``; a ``t,x,y,z`` / ``t,lat,lon,h`` CSV at >= 1 Hz or an NMEA GGA log, optionally with
  ``roll, pitch, yaw`` columns), smoothed by a C2 cubic smoothing spline with cut-off
  ``smoothing_hz`` (default 1 Hz; 0 = interpolating); see :mod:`ultratight.ins.trajfile` and
  docs/trajectory-files.md.  The start point is the file's first position (``[receiver]``
  lat/lon/h are not used); attitude ``"file"`` (the file's Euler angles, the default when it
  has them) or ``"velocity"`` (the default otherwise) or ``"fixed"``.  Along the velocity the
  attitude is held at rest: the velocity gives it only above ``hold_speed_mps`` (default 0.5 m/s),
  the changes between held and along the velocity are slews limited by ``slew_rate_dps`` and
  ``slew_accel_dps2`` (:func:`ultratight.ins.trajfile.held_velocity_attitude`).
* ``"turns"``: horizontal ground/air vehicle.  ``speed0_mps``, ``heading0_deg``
  (clockwise from north); ``segments = [{t0, turn_rate_dps, acc_mps2 | speed_mps}]``:
  constant turn rate (positive = turning right, heading increasing) and
  constant tangential acceleration ``acc_mps2`` or, equivalently, the speed
  ``speed_mps`` reached at the segment's end.  Lateral acceleration is
  ``speed * turn_rate`` (30 m/s at 37.5 deg/s = 2 g).

Attitude modes (``attitude`` key):

* ``"velocity"``: body x along the velocity (along the acceleration, then the
  jerk, while the speed is zero), body y horizontal in l0 (wings level, roll 0).
* ``"fixed"``: ``att0_deg = [roll, pitch, yaw]`` w.r.t. l0, constant.
* ``"rates"``: starts at ``att0_deg``; each segment may carry
  ``rate_dps = [wx, wy, wz]``, constant body angular rates w.r.t. l0.

Body frame FLU (x forward, y left, z up); Euler convention in
:mod:`ultratight.ins.attitude`.  Attitude reported by :meth:`kinematics` is
relative to the local ENU frame at the *current* position (``C_lb``), which is
what the SINS carries.
"""

import json
import math
import os

import h5py
import numpy as np

from ultratight.constants import OMEGA_E, WGS84_A, WGS84_E2
from ultratight.errors import ConfigError
from ultratight.io_guard import atomic_path
from ultratight.ins.attitude import (dcm_to_quat_vec, euler_to_dcm, euler_to_dcm_vec,
                                     rotvec_to_dcm, rotvec_to_dcm_vec)
from ultratight.ins.earth import (dcm_ecef_from_enu, dcm_ecef_from_enu_vec, ecef_to_llh_batch,
                                  llh_to_ecef)

KINDS = ("static", "segments", "turns", "swing", "file")
ATTITUDE_MODES = ("velocity", "fixed", "rates", "swing", "file")
# keys of the [trajectory] table beyond the scenario schema's own list (kind = "file")
CONFIG_KEYS = ("path", "frame", "smoothing_hz", "hold_speed_mps", "slew_rate_dps", "slew_accel_dps2")
# swinging-base defaults (a choice of this project; Sun et al. 2012 give none): [roll, pitch, yaw]
SWING_AMP_DEG = (10.0, 8.0, 5.0)
SWING_PERIOD_S = (8.0, 6.0, 10.0)
_SPEED_EPS = 1e-9     # m/s: below this the velocity direction is taken from acc / jerk


def _vec3(value, field):
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(f"trajectory: {field} must be a list of 3 numbers, got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"trajectory: {field} must be a list of 3 finite numbers, got {value!r}")
    return arr


def _num(value, field):
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"trajectory: {field} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ConfigError(f"trajectory: {field} must be finite, got {value!r}")
    return x


class Trajectory:
    """Analytic trajectory; build with :func:`build_trajectory`.

    Attributes: ``duration_s``, ``lat0``, ``lon0``, ``h0`` (rad, rad, m),
    ``r0_e`` (ECEF start point), ``C_el0`` (l0 -> ECEF), ``kind``,
    ``attitude_mode``, ``config`` (the normalised configuration dict).
    """

    def __init__(self, kind, lat0, lon0, h0, duration_s, attitude_mode, att0, config):
        self.kind = kind
        self.lat0, self.lon0, self.h0 = float(lat0), float(lon0), float(h0)
        self.duration_s = float(duration_s)
        self.attitude_mode = attitude_mode
        self.att0 = np.asarray(att0, float)
        self.C_l0b0 = euler_to_dcm(self.att0[0], self.att0[1], self.att0[2])
        self.r0_e = llh_to_ecef(self.lat0, self.lon0, self.h0)
        self.C_el0 = dcm_ecef_from_enu(self.lat0, self.lon0)
        self.config = config
        # earth rate expressed in l0 (constant)
        self.omega_ie_l0 = self.C_el0.T @ np.array([0.0, 0.0, OMEGA_E])
        # segment tables, filled by the builder
        self.seg_t0 = np.zeros(1)
        self.seg_p0 = np.zeros((1, 3))
        self.seg_v0 = np.zeros((1, 3))
        self.seg_a0 = np.zeros((1, 3))
        self.seg_j0 = np.zeros((1, 3))
        # turns kind: per segment complex position, speed, angle from east (ccw), ccw rate, tangential acc
        self.turn_z0 = np.zeros(1, complex)
        self.turn_s0 = np.zeros(1)
        self.turn_alpha0 = np.zeros(1)
        self.turn_om = np.zeros(1)
        self.turn_acc = np.zeros(1)
        self.up_l0 = 0.0
        # rates attitude mode
        self.rate_t0 = np.zeros(1)
        self.rate_w = np.zeros((1, 3))
        self.rate_C0 = self.C_l0b0[None].copy()
        # swing attitude mode: amplitudes (rad), angular frequencies (rad/s), phases (rad)
        self.swing_amp = np.zeros(3)
        self.swing_w = np.zeros(3)
        self.swing_phase = np.zeros(3)
        # file kind: the smoothed position log (ultratight.ins.trajfile.FileMotion) and, along the
        # velocity, the spline of the held / slewed Euler angles w.r.t. l0 and its knots
        self.file_motion = None
        self.held_att = None
        self.held_att_rate = None
        self.held_att_knots = np.zeros(0)

    # ------------------------------------------------------------------ local-frame motion
    def _seg_index(self, t, t0s):
        idx = np.searchsorted(t0s, t, side="right") - 1
        return np.clip(idx, 0, len(t0s) - 1)

    def local_motion(self, t):
        """Position, velocity, acceleration, jerk in l0: four (n, 3) arrays."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if self.kind == "turns":
            return self._turn_motion(t)
        if self.kind == "file":
            return self.file_motion.motion(t)
        i = self._seg_index(t, self.seg_t0)
        dt = (t - self.seg_t0[i])[:, None]
        p0, v0, a0, j0 = self.seg_p0[i], self.seg_v0[i], self.seg_a0[i], self.seg_j0[i]
        p = p0 + dt * (v0 + dt * (a0 / 2.0 + dt * j0 / 6.0))
        v = v0 + dt * (a0 + dt * j0 / 2.0)
        a = a0 + dt * j0
        return p, v, a, j0.copy()

    def _turn_motion(self, t):
        i = self._seg_index(t, self.seg_t0)
        dt = t - self.seg_t0[i]
        s0, al0, om, acc = self.turn_s0[i], self.turn_alpha0[i], self.turn_om[i], self.turn_acc[i]
        x = om * dt
        small = np.abs(x) < 1e-2
        # I(T) = int_0^T (s0 + acc tau) exp(i om tau) dtau
        series = np.zeros_like(dt, dtype=complex)
        term = np.ones_like(dt, dtype=complex)       # (i om T)^k / k!
        for k in range(9):
            series += term * (s0 * dt / (k + 1) + acc * dt * dt / (k + 2))
            term = term * (1j * x) / (k + 1)
        om_safe = np.where(small, 1.0, om)
        e = np.exp(1j * x)
        iw = 1j * om_safe
        closed = s0 * (e - 1.0) / iw + acc * (dt * e / iw - (e - 1.0) / (iw * iw))
        integ = np.where(small, series, closed)
        rot = np.exp(1j * al0)
        z = self.turn_z0[i] + rot * integ
        s = s0 + acc * dt
        ea = np.exp(1j * (al0 + x))
        vz = s * ea
        az = (acc + 1j * om * s) * ea
        jz = (2j * om * acc - om * om * s) * ea
        n = t.shape[0]
        p = np.empty((n, 3))
        v = np.zeros((n, 3))
        a = np.zeros((n, 3))
        j = np.zeros((n, 3))
        p[:, 0], p[:, 1], p[:, 2] = z.real, z.imag, self.up_l0
        v[:, 0], v[:, 1] = vz.real, vz.imag
        a[:, 0], a[:, 1] = az.real, az.imag
        j[:, 0], j[:, 1] = jz.real, jz.imag
        return p, v, a, j

    # ------------------------------------------------------------------ public queries
    def pos_vel_e(self, t):
        """ECEF position and velocity (m, m/s), each (n, 3), at t = seconds since start."""
        p, v, _, _ = self.local_motion(t)
        return self.r0_e + p @ self.C_el0.T, v @ self.C_el0.T

    def attitude_l0(self, t, motion=None):
        """C_l0b (n, 3, 3) and body angular rate w.r.t. l0, omega_l0b_b (n, 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        n = t.shape[0]
        if self.attitude_mode == "fixed":
            return np.broadcast_to(self.C_l0b0, (n, 3, 3)).copy(), np.zeros((n, 3))
        if self.attitude_mode == "swing":
            return self._swing_attitude(t)
        if self.attitude_mode == "file":
            return self._file_attitude(t, motion)
        if self.held_att is not None:
            tt = np.clip(t, 0.0, self.file_motion.duration_s)
            return _euler_attitude(self.held_att(tt), self.held_att_rate(tt))
        if self.attitude_mode == "rates":
            i = self._seg_index(t, self.rate_t0)
            dt = (t - self.rate_t0[i])[:, None]
            w = self.rate_w[i]
            C = self.rate_C0[i] @ rotvec_to_dcm_vec(w * dt)
            return C, w.copy()
        _, v, a, j = motion if motion is not None else self.local_motion(t)
        return self._velocity_attitude(v, a, j)

    def swing_euler(self, t):
        """Swing-mode Euler angles [roll, pitch, yaw] (rad) and their rates, two (n, 3) arrays."""
        t = np.atleast_1d(np.asarray(t, dtype=float))[:, None]
        arg = self.swing_w[None, :] * t + self.swing_phase[None, :]
        return self.att0[None, :] + self.swing_amp * np.sin(arg), self.swing_amp * self.swing_w * np.cos(arg)

    def _swing_attitude(self, t):
        return _euler_attitude(*self.swing_euler(t))

    def _file_attitude(self, t, motion):
        """The file's Euler angles (w.r.t. the local ENU frame at the current position) -> C_l0b and
        omega_l0b_b = omega_lb_b + C_bl omega_el_l (l0 is Earth-fixed, so omega_l0l = omega_el)."""
        C_lb, w_lb = _euler_attitude(*self.file_motion.euler(t))
        p, v, _, _ = motion if motion is not None else self.local_motion(t)
        pos_e = self.r0_e + p @ self.C_el0.T
        llh = ecef_to_llh_batch(pos_e)
        C_el = dcm_ecef_from_enu_vec(llh[:, 0], llh[:, 1])
        C_l0l = np.einsum("ji,njk->nik", self.C_el0, C_el)
        vel_l = np.einsum("nji,nj->ni", C_el, v @ self.C_el0.T)
        lat, h = llh[:, 0], llh[:, 2]
        w2 = 1.0 - WGS84_E2 * np.sin(lat) ** 2
        rn = WGS84_A / np.sqrt(w2)
        rm = WGS84_A * (1.0 - WGS84_E2) / (w2 * np.sqrt(w2))
        # transport rate omega_el_l (as ultratight.ins.earth.transport_rate_l, vectorised)
        w_el = np.stack([-vel_l[:, 1] / (rm + h), vel_l[:, 0] / (rn + h), vel_l[:, 0] * np.tan(lat) / (rn + h)],
                        axis=1)
        return C_l0l @ C_lb, w_lb + np.einsum("nji,nj->ni", C_lb, w_el)

    def _velocity_attitude(self, v, a, j):
        v = v.copy()
        a = a.copy()
        speed = np.linalg.norm(v, axis=1)
        stopped = speed < _SPEED_EPS
        # near v = 0 the direction of v(t) ~ a dt + j dt^2/2 is that of a (+ j dt / 2)
        v[stopped] = a[stopped]
        a[stopped] = 0.5 * j[stopped]
        speed = np.linalg.norm(v, axis=1)
        stopped2 = speed < _SPEED_EPS
        v[stopped2] = j[stopped2]
        a[stopped2] = 0.0
        speed = np.linalg.norm(v, axis=1)
        undefined = speed < _SPEED_EPS
        vh = np.hypot(v[:, 0], v[:, 1])
        vertical = vh < 1e-12 * np.maximum(speed, 1.0)
        vh_s = np.where(vertical, 1.0, vh)
        yaw = np.where(vertical, self.att0[2], np.arctan2(v[:, 0], v[:, 1]))
        yaw_rate = np.where(vertical, 0.0, (v[:, 1] * a[:, 0] - v[:, 0] * a[:, 1]) / vh_s ** 2)
        pitch = np.arctan2(v[:, 2], vh)
        vh_dot = np.where(vertical, 0.0, (v[:, 0] * a[:, 0] + v[:, 1] * a[:, 1]) / vh_s)
        sp2 = np.where(undefined, 1.0, speed ** 2)
        pitch_rate = (vh * a[:, 2] - v[:, 2] * vh_dot) / sp2
        roll = np.zeros_like(yaw)
        yaw = np.where(undefined, self.att0[2], yaw)
        pitch = np.where(undefined, self.att0[1], pitch)
        roll = np.where(undefined, self.att0[0], roll)
        yaw_rate = np.where(undefined, 0.0, yaw_rate)
        pitch_rate = np.where(undefined, 0.0, pitch_rate)
        C = euler_to_dcm_vec(roll, pitch, yaw)
        # C = Rz(pi/2 - yaw) Ry(-pitch) (roll 0): omega_b = (-yaw' sin p, -pitch', -yaw' cos p)
        w = np.empty_like(v)
        w[:, 0] = -yaw_rate * np.sin(pitch)
        w[:, 1] = -pitch_rate
        w[:, 2] = -yaw_rate * np.cos(pitch)
        return C, w

    def kinematics(self, t, extras=True):
        """Full truth at times t (s since start).  Returns a dict of arrays:

        ``t``; ``pos_e, vel_e, acc_e`` (ECEF, Earth-relative, acc = d2 pos_e/dt2);
        ``llh`` (lat rad, lon rad, h m); ``vel_l, acc_l`` (local ENU at the current
        position); ``pos_l0, vel_l0, acc_l0, jerk_l0`` (start tangent frame);
        ``C_lb`` (body -> current ENU), ``q_lb``, ``euler`` ([roll, pitch, yaw] rad);
        ``omega_ib_b`` (inertial body rate, rad/s), ``omega_eb_b`` (Earth-relative).
        With ``extras=False`` the quaternion and Euler angles are skipped (faster).
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        motion = self.local_motion(t)
        p, v, a, j = motion
        Ce = self.C_el0
        pos_e = self.r0_e + p @ Ce.T
        vel_e = v @ Ce.T
        acc_e = a @ Ce.T
        llh = ecef_to_llh_batch(pos_e)
        C_el = dcm_ecef_from_enu_vec(llh[:, 0], llh[:, 1])
        C_le = np.transpose(C_el, (0, 2, 1))
        vel_l = np.einsum("nij,nj->ni", C_le, vel_e)
        acc_l = np.einsum("nij,nj->ni", C_le, acc_e)
        C_l0b, w_l0b_b = self.attitude_l0(t, motion)
        C_ll0 = C_le @ Ce
        C_lb = C_ll0 @ C_l0b
        # omega_ib_b = omega_l0b_b + C_b,l0 omega_ie_l0  (l0 is Earth-fixed)
        w_ie_b = np.einsum("nji,j->ni", C_l0b, self.omega_ie_l0)
        out = {
            "t": t, "pos_e": pos_e, "vel_e": vel_e, "acc_e": acc_e, "llh": llh,
            "vel_l": vel_l, "acc_l": acc_l,
            "pos_l0": p, "vel_l0": v, "acc_l0": a, "jerk_l0": j,
            "C_lb": C_lb, "omega_eb_b": w_l0b_b, "omega_ib_b": w_l0b_b + w_ie_b, "C_l0b": C_l0b,
        }
        if extras:
            out["q_lb"] = dcm_to_quat_vec(C_lb)
            out["euler"] = _euler_vec(C_lb)
        return out

    def breakpoints(self):
        """Times (s) where acceleration or angular rate may be discontinuous."""
        if self.kind == "file":
            # C2 spline: acceleration continuous, jerk steps at the knots
            k = np.union1d(self.file_motion.knots, self.held_att_knots)
            return k[(k > 0.0) & (k < self.duration_s)].copy()
        tb = list(self.seg_t0[1:])
        if self.attitude_mode == "rates":
            tb += list(self.rate_t0[1:])
        return np.unique(np.array([x for x in tb if 0.0 < x < self.duration_s], dtype=float))

    def save_h5(self, path_or_group, rate_hz):
        """Write the truth sampled at ``rate_hz`` over [0, duration_s] (HDF5, see docs/ins.md)."""
        rate_hz = float(rate_hz)
        if not (rate_hz > 0.0):
            raise ConfigError(f"trajectory rate_hz must be > 0, got {rate_hz}")
        n = int(math.floor(self.duration_s * rate_hz + 1e-9)) + 1
        t = np.arange(n) / rate_hz
        k = self.kinematics(t)

        def _write(g):
            g.attrs["kind"] = self.kind
            g.attrs["attitude_mode"] = self.attitude_mode
            g.attrs["lat0_rad"] = self.lat0
            g.attrs["lon0_rad"] = self.lon0
            g.attrs["h0_m"] = self.h0
            g.attrs["duration_s"] = self.duration_s
            g.attrs["rate_hz"] = rate_hz
            g.attrs["config_json"] = json.dumps(self.config)
            g.attrs["frames"] = ("pos_e/vel_e/acc_e ECEF m, m/s, m/s^2; llh rad,rad,m; vel_l ENU at current "
                                 "position; q_lb scalar-first body(FLU)->ENU; euler roll,pitch,yaw rad; "
                                 "omega_ib_b rad/s")
            for key in ("t", "pos_e", "vel_e", "acc_e", "llh", "vel_l", "acc_l", "q_lb", "euler",
                        "omega_ib_b"):
                if key in g:
                    del g[key]
                g.create_dataset(key, data=k[key])

        if isinstance(path_or_group, (str, os.PathLike)):
            with atomic_path(path_or_group) as tmp:
                with h5py.File(tmp, "w") as f:
                    _write(f)
        else:
            _write(path_or_group)


def _euler_attitude(e, de):
    """C_lb (n, 3, 3) and body rate omega_lb_b (n, 3) from Euler angles [roll, pitch, yaw] (n, 3)
    and their time derivatives (the exact Euler-rate map)."""
    roll, pitch = e[:, 0], e[:, 1]
    sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
    dr, dp, dy = de[:, 0], de[:, 1], de[:, 2]
    # C_lb = Rz(pi/2 - yaw) Ry(-pitch) Rx(roll) (FLU body, ENU): the Euler-rate map of the
    # equivalent NED/FRD yaw-pitch-roll sequence, FRD -> FLU flips the y and z components
    w = np.empty((e.shape[0], 3))
    w[:, 0] = dr - dy * sp
    w[:, 1] = -(dp * cr + dy * sr * cp)
    w[:, 2] = dp * sr - dy * cr * cp
    return euler_to_dcm_vec(roll, pitch, e[:, 2]), w


def _euler_vec(C):
    roll = np.arctan2(C[:, 2, 1], C[:, 2, 2])
    pitch = np.arcsin(np.clip(C[:, 2, 0], -1.0, 1.0))
    yaw = np.mod(0.5 * np.pi - np.arctan2(C[:, 1, 0], C[:, 0, 0]), 2.0 * np.pi)
    return np.stack([roll, pitch, yaw], axis=1)


def _segments_list(traj_cfg, kind):
    segs = traj_cfg.get("segments")
    if not segs:
        raise ConfigError(f"trajectory: kind = \"{kind}\" needs a non-empty 'segments' list")
    if not isinstance(segs, (list, tuple)) or not all(isinstance(s, dict) for s in segs):
        raise ConfigError("trajectory: 'segments' must be a list of tables {t0 = ..., ...}")
    t0 = np.array([_num(s.get("t0", float("nan")), f"segments[{i}].t0") for i, s in enumerate(segs)])
    if t0[0] != 0.0:
        raise ConfigError(f"trajectory: segments[0].t0 must be 0, got {t0[0]}")
    bad = np.nonzero(np.diff(t0) <= 0.0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        raise ConfigError(f"trajectory: segments[{i}].t0 = {t0[i]} must be greater than segments[{i-1}].t0 "
                          f"= {t0[i-1]} (strictly increasing)")
    return segs, t0


def build_trajectory(traj_cfg, receiver_cfg, duration_s):
    """Build a :class:`Trajectory` from a scenario's ``[trajectory]`` and ``[receiver]`` tables."""
    traj_cfg = dict(traj_cfg or {})
    receiver_cfg = dict(receiver_cfg or {})
    duration_s = _num(duration_s, "duration_s")
    if duration_s <= 0.0:
        raise ConfigError(f"duration_s must be > 0, got {duration_s}")
    kind = traj_cfg.get("kind", "static")
    if kind not in KINDS:
        raise ConfigError(f"trajectory.kind must be one of {', '.join(KINDS)}; got {kind!r}")
    fmotion, lat_deg, lon_deg, h_m = _start_point(kind, traj_cfg, receiver_cfg, duration_s)
    mode = _attitude_mode(kind, traj_cfg, fmotion)
    att0 = np.radians(_vec3(traj_cfg.get("att0_deg", [0.0, 0.0, 0.0]), "att0_deg"))
    if kind == "turns" and "att0_deg" not in traj_cfg:
        att0[2] = math.radians(_num(traj_cfg.get("heading0_deg", 0.0), "heading0_deg"))
    config = {"kind": kind, "attitude": mode, "lat_deg": lat_deg, "lon_deg": lon_deg, "h_m": h_m,
              "duration_s": duration_s, "trajectory": _jsonable(traj_cfg)}
    tr = Trajectory(kind, math.radians(lat_deg), math.radians(lon_deg), h_m, duration_s, mode, att0, config)

    if kind == "file":
        tr.file_motion = fmotion
        tr.seg_t0 = np.zeros(1)
        if mode == "velocity":
            _set_held_attitude(tr, traj_cfg)
    elif kind == "static":
        if mode == "velocity":
            tr.attitude_mode = "fixed"
    elif kind == "swing":
        _set_swing(tr, traj_cfg)
    elif kind == "segments":
        _set_segments(tr, traj_cfg)
    else:  # turns
        _set_turns(tr, traj_cfg, duration_s)
    if tr.attitude_mode == "rates":
        _set_rate_attitude(tr, traj_cfg)
    return tr


def _start_point(kind, traj_cfg, receiver_cfg, duration_s):
    """(FileMotion or None, lat_deg, lon_deg, h_m) of the start point: the file's first position for
    ``kind = "file"`` (which must cover ``duration_s``), else the ``[receiver]`` table's."""
    fmotion = None
    if kind == "file":
        fmotion = load_file_motion(traj_cfg)
        if duration_s > fmotion.duration_s + 1e-6:
            raise ConfigError(f"trajectory file {traj_cfg['path']}: covers {fmotion.duration_s:.6g} s, shorter than "
                              f"duration_s = {duration_s:g} s")
        lat_deg, lon_deg, h_m = math.degrees(fmotion.lat0), math.degrees(fmotion.lon0), fmotion.h0
    else:
        try:
            lat_deg = _num(receiver_cfg["lat_deg"], "receiver.lat_deg")
            lon_deg = _num(receiver_cfg["lon_deg"], "receiver.lon_deg")
            h_m = _num(receiver_cfg.get("h_m", 0.0), "receiver.h_m")
        except KeyError as exc:
            raise ConfigError(f"receiver: missing field {exc.args[0]!r} (need lat_deg, lon_deg, h_m)") from None
    if not -90.0 <= lat_deg <= 90.0:
        raise ConfigError(f"receiver.lat_deg must be in [-90, 90], got {lat_deg}")
    return fmotion, lat_deg, lon_deg, h_m


def _attitude_mode(kind, traj_cfg, fmotion):
    """The ``attitude`` of a ``[trajectory]`` table (default by kind), checked against the kind."""
    default_mode = {"static": "fixed", "swing": "swing"}.get(kind, "velocity")
    if fmotion is not None and fmotion.att is not None:
        default_mode = "file"
    mode = traj_cfg.get("attitude", default_mode)
    if (kind == "swing") != (mode == "swing"):
        raise ConfigError(f"trajectory.attitude = {mode!r} does not go with kind = {kind!r} "
                          "(the swing attitude belongs to kind = \"swing\" only)")
    if mode == "file" and (fmotion is None or fmotion.att is None):
        raise ConfigError("trajectory.attitude = \"file\" needs kind = \"file\" and a file with roll, pitch, yaw "
                          "columns")
    if mode == "rates" and kind == "file":
        raise ConfigError("trajectory.attitude = \"rates\" does not go with kind = \"file\" (use \"velocity\", "
                          "\"fixed\" or the file's own attitude columns)")
    if mode not in ATTITUDE_MODES:
        raise ConfigError(f"trajectory.attitude must be one of {', '.join(ATTITUDE_MODES)}; got {mode!r}")
    return mode


def _set_held_attitude(tr, traj_cfg):
    """Attitude along the file's velocity with holds at rest (``hold_speed_mps``, ``slew_rate_dps``,
    ``slew_accel_dps2``); before the first motion ``att0_deg`` when the table gives it."""
    from ultratight.ins import trajfile as tf

    lim = {}
    for key, default in (("hold_speed_mps", tf.DEFAULT_HOLD_SPEED_MPS), ("slew_rate_dps", tf.DEFAULT_SLEW_RATE_DPS),
                         ("slew_accel_dps2", tf.DEFAULT_SLEW_ACCEL_DPS2)):
        lim[key] = _num(traj_cfg.get(key, default), key)
        if not lim[key] > 0.0:
            raise ConfigError(f"trajectory.{key} must be > 0, got {lim[key]}")
    att0 = tr.att0 if "att0_deg" in traj_cfg else None
    spline, grid = tf.held_velocity_attitude(tr.file_motion, att0, lim["hold_speed_mps"], lim["slew_rate_dps"],
                                             lim["slew_accel_dps2"])
    tr.held_att, tr.held_att_rate, tr.held_att_knots = spline, spline.derivative(1), grid


def _set_swing(tr, traj_cfg):
    """Swing amplitudes, angular frequencies and phases of a ``kind = "swing"`` trajectory."""
    amp = np.radians(_vec3(traj_cfg.get("swing_amp_deg", SWING_AMP_DEG), "swing_amp_deg"))
    per = _vec3(traj_cfg.get("swing_period_s", SWING_PERIOD_S), "swing_period_s")
    if np.any(per <= 0.0):
        raise ConfigError(f"trajectory: swing_period_s must be > 0 on every axis, got {per.tolist()}")
    if np.any(np.abs(np.degrees(tr.att0[1]) + np.degrees(np.abs(amp[1]))) >= 89.0):
        raise ConfigError("trajectory: att0_deg[1] + swing_amp_deg[1] must stay below 89 deg of pitch "
                          "(Euler singularity)")
    tr.swing_amp = amp
    tr.swing_w = 2.0 * np.pi / per
    tr.swing_phase = np.radians(_vec3(traj_cfg.get("swing_phase_deg", [0.0, 0.0, 0.0]), "swing_phase_deg"))


def _set_segments(tr, traj_cfg):
    """Segment tables (start time, position, velocity, acceleration, jerk in l0) of a
    ``kind = "segments"`` trajectory: constant jerk per segment, position and velocity carried."""
    segs, t0 = _segments_list(traj_cfg, "segments")
    n = len(segs)
    v0 = _vec3(traj_cfg.get("vel0_enu_mps", [0.0, 0.0, 0.0]), "vel0_enu_mps")
    P = np.zeros((n, 3))
    V = np.zeros((n, 3))
    A = np.zeros((n, 3))
    J = np.zeros((n, 3))
    V[0] = v0
    for i, s in enumerate(segs):
        A[i] = _vec3(s.get("acc_enu", [0.0, 0.0, 0.0]), f"segments[{i}].acc_enu")
        J[i] = _vec3(s.get("jerk_enu", [0.0, 0.0, 0.0]), f"segments[{i}].jerk_enu")
        if i > 0:
            d = t0[i] - t0[i - 1]
            P[i] = P[i - 1] + d * (V[i - 1] + d * (A[i - 1] / 2.0 + d * J[i - 1] / 6.0))
            V[i] = V[i - 1] + d * (A[i - 1] + d * J[i - 1] / 2.0)
    tr.seg_t0, tr.seg_p0, tr.seg_v0, tr.seg_a0, tr.seg_j0 = t0, P, V, A, J


def _set_turns(tr, traj_cfg, duration_s):
    """Per-segment start position (complex, l0 east + j north), speed, direction, turn rate and
    tangential acceleration of a ``kind = "turns"`` trajectory, each segment's end carried to the next."""
    segs, t0 = _segments_list(traj_cfg, "turns")
    n = len(segs)
    # initial speed: speed0_mps, else the first segment's speed_mps, else 0
    s0 = traj_cfg.get("speed0_mps", segs[0].get("speed_mps", 0.0))
    s0 = _num(s0, "speed0_mps")
    heading0 = math.radians(_num(traj_cfg.get("heading0_deg", math.degrees(tr.att0[2])), "heading0_deg"))
    Z = np.zeros(n, complex)
    S = np.zeros(n)
    AL = np.zeros(n)
    OM = np.zeros(n)
    AC = np.zeros(n)
    S[0] = s0
    AL[0] = 0.5 * math.pi - heading0
    ends = np.append(t0[1:], max(duration_s, t0[-1]))
    for i, s in enumerate(segs):
        OM[i] = -math.radians(_num(s.get("turn_rate_dps", 0.0), f"segments[{i}].turn_rate_dps"))
        d = ends[i] - t0[i]
        if "acc_mps2" in s and "speed_mps" in s:
            raise ConfigError(f"trajectory: segments[{i}] gives both acc_mps2 and speed_mps; give one")
        if "acc_mps2" in s:
            AC[i] = _num(s["acc_mps2"], f"segments[{i}].acc_mps2")
        elif "speed_mps" in s:
            target = _num(s["speed_mps"], f"segments[{i}].speed_mps")
            AC[i] = (target - S[i]) / d if d > 0 else 0.0
        if S[i] + AC[i] * d < -1e-9:
            raise ConfigError(f"trajectory: speed becomes negative in segments[{i}]")
        if i + 1 < n:
            tmp = Trajectory.__new__(Trajectory)
            tmp.seg_t0 = np.array([0.0])
            tmp.turn_z0, tmp.turn_s0 = np.array([Z[i]]), np.array([S[i]])
            tmp.turn_alpha0, tmp.turn_om, tmp.turn_acc = np.array([AL[i]]), np.array([OM[i]]), \
                np.array([AC[i]])
            tmp.up_l0 = 0.0
            p_end, _, _, _ = Trajectory._turn_motion(tmp, np.array([d]))
            Z[i + 1] = p_end[0, 0] + 1j * p_end[0, 1]
            S[i + 1] = S[i] + AC[i] * d
            AL[i + 1] = AL[i] + OM[i] * d
    tr.seg_t0 = t0
    tr.turn_z0, tr.turn_s0, tr.turn_alpha0, tr.turn_om, tr.turn_acc = Z, S, AL, OM, AC


def _set_rate_attitude(tr, traj_cfg):
    """Body-rate tables of the ``attitude = "rates"`` mode: per segment its start time, constant
    rate and the attitude at its start."""
    segs = traj_cfg.get("segments") or [{"t0": 0.0}]
    rt0 = np.array([_num(s.get("t0", 0.0), f"segments[{i}].t0") for i, s in enumerate(segs)])
    W = np.array([np.radians(_vec3(s.get("rate_dps", [0.0, 0.0, 0.0]), f"segments[{i}].rate_dps"))
                  for i, s in enumerate(segs)])
    C0 = np.empty((len(segs), 3, 3))
    C0[0] = tr.C_l0b0
    for i in range(1, len(segs)):
        C0[i] = C0[i - 1] @ rotvec_to_dcm(W[i - 1] * (rt0[i] - rt0[i - 1]))
    tr.rate_t0, tr.rate_w, tr.rate_C0 = rt0, W, C0


def load_file_motion(traj_cfg):
    """:class:`ultratight.ins.trajfile.FileMotion` of a ``kind = "file"`` table (``path``, ``frame``,
    ``smoothing_hz``); ConfigError for bad keys, InputFileError (naming file and line) for bad files."""
    from ultratight.ins.trajfile import DEFAULT_SMOOTHING_HZ, FRAMES, FileMotion, read_position_log

    path = traj_cfg.get("path")
    if not isinstance(path, str) or not path:
        raise ConfigError("trajectory: kind = \"file\" needs path = \"...\" (CSV or NMEA GGA log)")
    frame = traj_cfg.get("frame", "ecef")
    if frame not in FRAMES:
        raise ConfigError(f"trajectory.frame must be one of {', '.join(FRAMES)}; got {frame!r}")
    sm = _num(traj_cfg.get("smoothing_hz", DEFAULT_SMOOTHING_HZ), "smoothing_hz")
    if sm < 0.0:
        raise ConfigError(f"trajectory.smoothing_hz must be >= 0 (0 = interpolating spline), got {sm}")
    return FileMotion(read_position_log(path, frame), sm)


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


PAPER_HIGHDYN_TRAJECTORY = {
    "kind": "segments",
    "vel0_enu_mps": [0.0, 0.0, 0.0],
    "attitude": "velocity",
    "att0_deg": [0.0, 0.0, 0.0],
    "segments": [
        {"t0": 0.0, "acc_enu": [100.0, 4.0, 0.0], "jerk_enu": [0.0, 0.0, 0.0]},
        {"t0": 20.0, "acc_enu": [100.0, 4.0, 0.0], "jerk_enu": [100.0, 0.0, 0.0]},
        {"t0": 21.0, "acc_enu": [200.0, 4.0, 0.0], "jerk_enu": [0.0, 0.0, 0.0]},
        {"t0": 40.0, "acc_enu": [200.0, 4.0, 0.0], "jerk_enu": [-400.0, 0.0, 0.0]},
        {"t0": 41.0, "acc_enu": [-200.0, 4.0, 0.0], "jerk_enu": [0.0, 0.0, 0.0]},
    ],
}
PAPER_HIGHDYN_RECEIVER = {"lat_deg": 28.2460, "lon_deg": 102.0266, "h_m": 50000.0}
