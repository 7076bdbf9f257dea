"""IMU synthesis, sensor error models, unit conversions and IMU file I/O.

IMU data are *increments*: sample k covers the interval (t[k] - dt, t[k]] and holds
``dtheta_b[k] = int omega_ib_b dt`` (rad) and ``dv_b[k] = int f_b dt`` (m/s), both
integrated in the (rotating) body frame, exactly what strapdown gyros and
accelerometers deliver and what :mod:`ultratight.ins.sins` (two-sample coning and
sculling) expects.  Body frame FLU (x forward, y left, z up).

Ideal increments are computed from the analytic trajectory by 8-point
Gauss-Legendre quadrature per interval (split at the trajectory's segment
breakpoints), with the specific force ``f_b = C_bl (C_le a_e + 2 omega_ie x v_l - g_l)``
using the same normal gravity :func:`ultratight.ins.earth.gravity_l` as the
mechanisation, so an error-free SINS reproduces the trajectory.

Sensor error model per axis (all in SI inside, see :class:`ImuErrors`)::

    dtheta_meas = (I + S_g + M_g) dtheta + (b_g + b_gm,k) dt + n_g,k,   n_g,k ~ N(0, arw^2 dt)
    dv_meas     = (I + S_a + M_a) dv     + (b_a + b_am,k) dt + n_a,k,   n_a,k ~ N(0, vrw^2 dt)

then quantised with the residual carried over (sum-preserving).  ``b_gm`` is a
first-order Gauss-Markov process (steady-state sigma, correlation time tau) sampled
at the IMU rate.  Datasheet units at the boundary: deg/h, deg/sqrt(h), ug,
ug/sqrt(Hz), ppm (see the ``*_TO_SI`` constants and docs/ins.md).
"""

import csv
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
from scipy.signal import lfilter

from ultratight.constants import OMEGA_E, WGS84_A
from ultratight.errors import ConfigError, InputFileError
from ultratight.ins.attitude import dcm_to_quat_vec
from ultratight.ins.earth import dcm_ecef_from_enu_vec, ecef_to_llh_batch, gravity_l
from ultratight.io_guard import atomic_path, read_text_input, write_h5_atomic

# ------------------------------------------------------------------ unit conversions
G0 = 9.80665                                  # standard gravity, m/s^2 (for ug / g units only)
DPH_TO_RADPS = math.pi / 180.0 / 3600.0       # deg/h -> rad/s
DPRH_TO_RADPRS = math.pi / 180.0 / 60.0       # deg/sqrt(h) -> rad/sqrt(s)
UG_TO_MPS2 = 1e-6 * G0                        # micro-g -> m/s^2
UGPRHZ_TO_MPSPRS = 1e-6 * G0                  # ug/sqrt(Hz) -> (m/s^2)/sqrt(Hz) = (m/s)/sqrt(s)
PPM = 1e-6
MRAD = 1e-3
URAD = 1e-6


@dataclass
class ImuErrors:
    """Sensor errors in SI.  Vectors are per body axis (x, y, z)."""
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))        # rad/s
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))       # m/s^2
    gyro_arw: np.ndarray = field(default_factory=lambda: np.zeros(3))         # rad/sqrt(s)
    accel_vrw: np.ndarray = field(default_factory=lambda: np.zeros(3))        # (m/s)/sqrt(s)
    gyro_gm_sigma: np.ndarray = field(default_factory=lambda: np.zeros(3))    # rad/s
    gyro_gm_tau: float = math.inf                                             # s
    accel_gm_sigma: np.ndarray = field(default_factory=lambda: np.zeros(3))   # m/s^2
    accel_gm_tau: float = math.inf                                            # s
    gyro_sf: np.ndarray = field(default_factory=lambda: np.zeros(3))          # dimensionless
    accel_sf: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_misalign: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))   # rad, off-diag
    accel_misalign: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    gyro_quant: float = 0.0                                                   # rad per LSB of dtheta
    accel_quant: float = 0.0                                                  # m/s per LSB of dv
    preset: str = "custom"

    def is_ideal(self):
        arrs = [self.gyro_bias, self.accel_bias, self.gyro_arw, self.accel_vrw, self.gyro_gm_sigma,
                self.accel_gm_sigma, self.gyro_sf, self.accel_sf, self.gyro_misalign, self.accel_misalign]
        return all(not np.any(a) for a in arrs) and self.gyro_quant == 0.0 and self.accel_quant == 0.0

    def to_dict(self):
        out = {}
        for k, v in self.__dict__.items():
            out[k] = v.tolist() if isinstance(v, np.ndarray) else (None if v == math.inf else v)
        return out


# presets in datasheet units (keys as in the scenario [imu] table)
PRESETS = {
    "ideal": {},
    # Zhao et al. 2014, §3: gyro bias 0.01 deg/h, gyro white noise 0.005 deg/h taken as the 1-sigma of the
    # angular-rate samples at the IMU rate; accelerometer bias 30 ug, white noise 3 ug (1 sigma/sample).
    "paper": {"gyro_bias_dph": 0.01, "gyro_noise_dph": 0.005, "accel_bias_ug": 30.0, "accel_noise_ug": 3.0},
    # navigation grade (ring-laser class)
    "navigation": {"gyro_bias_dph": 0.003, "gyro_arw_dprh": 0.002, "gyro_bi_dph": 0.002,
                   "gyro_bi_tau_s": 3600.0, "accel_bias_ug": 25.0, "accel_vrw_ugrhz": 10.0,
                   "accel_bi_ug": 10.0, "accel_bi_tau_s": 3600.0, "gyro_sf_ppm": 5.0, "accel_sf_ppm": 50.0},
    # tactical grade (FOG / good MEMS)
    "tactical": {"gyro_bias_dph": 1.0, "gyro_arw_dprh": 0.1, "gyro_bi_dph": 0.5, "gyro_bi_tau_s": 300.0,
                 "accel_bias_ug": 1000.0, "accel_vrw_ugrhz": 60.0, "accel_bi_ug": 100.0,
                 "accel_bi_tau_s": 300.0, "gyro_sf_ppm": 300.0, "accel_sf_ppm": 300.0,
                 "gyro_misalign_mrad": 0.5, "accel_misalign_mrad": 0.5},
    # consumer MEMS
    "mems": {"gyro_bias_dph": 200.0, "gyro_arw_dprh": 0.5, "gyro_bi_dph": 10.0, "gyro_bi_tau_s": 100.0,
             "accel_bias_ug": 10000.0, "accel_vrw_ugrhz": 150.0, "accel_bi_ug": 500.0,
             "accel_bi_tau_s": 100.0, "gyro_sf_ppm": 5000.0, "accel_sf_ppm": 5000.0,
             "gyro_misalign_mrad": 2.0, "accel_misalign_mrad": 2.0,
             "gyro_quant_urad": 1.0, "accel_quant_mmps": 0.1},
}

_KNOWN_KEYS = {
    "preset", "rate_hz", "gyro_bias_dph", "accel_bias_ug", "gyro_noise_dph", "gyro_arw_dprh",
    "accel_noise_ug", "accel_vrw_ugrhz", "gyro_bi_dph", "gyro_bi_tau_s", "accel_bi_ug", "accel_bi_tau_s",
    "gyro_sf_ppm", "accel_sf_ppm", "gyro_misalign_mrad", "accel_misalign_mrad", "gyro_quant_urad",
    "accel_quant_mmps", "seed", "file", "lever_arm_m",
}


def _axes(value, key):
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"imu.{key}: expected a number or a list of 3 numbers, got {value!r}") from None
    if a.ndim == 0:
        a = np.full(3, float(a))
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"imu.{key}: expected a number or a list of 3 finite numbers, got {value!r}")
    return a


def _misalign(value, key):
    a = np.asarray(value, dtype=float)
    if a.ndim == 0:
        m = np.full((3, 3), float(a))
        np.fill_diagonal(m, 0.0)
        return m
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ConfigError(f"imu.{key}: expected a number (all off-diagonal terms) or a 3x3 list, got {value!r}")
    return a.copy()


def imu_errors_from_config(imu_cfg):
    """:class:`ImuErrors` from a scenario ``[imu]`` table (preset + overrides, datasheet units).

    White noise can be given either as a datasheet random walk (``gyro_arw_dprh`` deg/sqrt(h),
    ``accel_vrw_ugrhz`` ug/sqrt(Hz)) or, as in the paper, as the 1-sigma of the rate samples
    at the IMU rate (``gyro_noise_dph``, ``accel_noise_ug``; needs ``rate_hz``, default 100):
    ``arw = sigma_sample / sqrt(rate_hz)``.
    """
    imu_cfg = dict(imu_cfg or {})
    preset = imu_cfg.get("preset", "ideal")
    if preset not in PRESETS:
        raise ConfigError(f"imu.preset must be one of {', '.join(PRESETS)}; got {preset!r}")
    unknown = sorted(set(imu_cfg) - _KNOWN_KEYS)
    if unknown:
        raise ConfigError(f"imu: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(_KNOWN_KEYS))}")
    cfg = dict(PRESETS[preset])
    cfg.update({k: v for k, v in imu_cfg.items() if k != "preset"})
    rate = float(cfg.get("rate_hz", 100.0))
    if not rate > 0.0:
        raise ConfigError(f"imu.rate_hz must be > 0, got {rate}")
    e = ImuErrors(preset=preset)
    e.gyro_bias = _axes(cfg.get("gyro_bias_dph", 0.0), "gyro_bias_dph") * DPH_TO_RADPS
    e.accel_bias = _axes(cfg.get("accel_bias_ug", 0.0), "accel_bias_ug") * UG_TO_MPS2
    if "gyro_noise_dph" in cfg and "gyro_arw_dprh" in cfg:
        raise ConfigError("imu: give gyro_noise_dph or gyro_arw_dprh, not both")
    if "accel_noise_ug" in cfg and "accel_vrw_ugrhz" in cfg:
        raise ConfigError("imu: give accel_noise_ug or accel_vrw_ugrhz, not both")
    if "gyro_noise_dph" in cfg:
        e.gyro_arw = _axes(cfg["gyro_noise_dph"], "gyro_noise_dph") * DPH_TO_RADPS / math.sqrt(rate)
    else:
        e.gyro_arw = _axes(cfg.get("gyro_arw_dprh", 0.0), "gyro_arw_dprh") * DPRH_TO_RADPRS
    if "accel_noise_ug" in cfg:
        e.accel_vrw = _axes(cfg["accel_noise_ug"], "accel_noise_ug") * UG_TO_MPS2 / math.sqrt(rate)
    else:
        e.accel_vrw = _axes(cfg.get("accel_vrw_ugrhz", 0.0), "accel_vrw_ugrhz") * UGPRHZ_TO_MPSPRS
    e.gyro_gm_sigma = _axes(cfg.get("gyro_bi_dph", 0.0), "gyro_bi_dph") * DPH_TO_RADPS
    e.accel_gm_sigma = _axes(cfg.get("accel_bi_ug", 0.0), "accel_bi_ug") * UG_TO_MPS2
    e.gyro_gm_tau = float(cfg.get("gyro_bi_tau_s", math.inf))
    e.accel_gm_tau = float(cfg.get("accel_bi_tau_s", math.inf))
    for key, tau, sig in (("gyro_bi_tau_s", e.gyro_gm_tau, e.gyro_gm_sigma),
                          ("accel_bi_tau_s", e.accel_gm_tau, e.accel_gm_sigma)):
        if not tau > 0.0:
            raise ConfigError(f"imu.{key} must be > 0, got {tau}")
        if np.any(sig) and not math.isfinite(tau):
            raise ConfigError(f"imu.{key} is needed with a bias-instability sigma")
    e.gyro_sf = _axes(cfg.get("gyro_sf_ppm", 0.0), "gyro_sf_ppm") * PPM
    e.accel_sf = _axes(cfg.get("accel_sf_ppm", 0.0), "accel_sf_ppm") * PPM
    e.gyro_misalign = _misalign(cfg.get("gyro_misalign_mrad", 0.0), "gyro_misalign_mrad") * MRAD
    e.accel_misalign = _misalign(cfg.get("accel_misalign_mrad", 0.0), "accel_misalign_mrad") * MRAD
    e.gyro_quant = float(cfg.get("gyro_quant_urad", 0.0)) * URAD
    e.accel_quant = float(cfg.get("accel_quant_mmps", 0.0)) * 1e-3
    if e.gyro_quant < 0 or e.accel_quant < 0:
        raise ConfigError("imu: quantisation steps must be >= 0")
    return e


@dataclass
class ImuData:
    """Increment IMU data.  ``t[k]`` is the END of interval k; the run starts at ``t0``."""
    t: np.ndarray
    dtheta_b: np.ndarray
    dv_b: np.ndarray
    rate_hz: float
    t0: float = 0.0
    truth: dict | None = None        # optional: t, llh, vel_l, q_lb at t0 and every t[k]
    meta: dict = field(default_factory=dict)
    lever_arm_b: np.ndarray = field(default_factory=lambda: np.zeros(3))   # IMU -> antenna, FLU, m

    @property
    def n(self):
        return self.t.shape[0]

    @property
    def dt(self):
        return 1.0 / self.rate_hz


# ------------------------------------------------------------------ synthesis
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)


def body_signals(traj, t, lever_arm_b=None):
    """True angular rate omega_ib_b and specific force f_b (FLU body) at times t: two (n, 3) arrays.

    With ``lever_arm_b`` the specific force is that of the point ``antenna - C_eb l`` less the
    angular-acceleration term (see :func:`ideal_increments`): minus the centripetal
    ``w x (w x l)`` and with the normal gravity at the IMU's height."""
    k = traj.kinematics(t, extras=False)
    llh = k["llh"]
    g = np.empty_like(llh)
    for i in range(llh.shape[0]):
        g[i] = gravity_l(llh[i, 0], llh[i, 2])
    lat = llh[:, 0]
    w_ie = np.zeros_like(llh)
    w_ie[:, 1] = OMEGA_E * np.cos(lat)
    w_ie[:, 2] = OMEGA_E * np.sin(lat)
    f_l = k["acc_l"] + 2.0 * np.cross(w_ie, k["vel_l"]) - g
    w = k["omega_ib_b"]
    if lever_arm_b is not None:
        lb = np.asarray(lever_arm_b, float)
        # gravity at the IMU point d = -C_lb l from the antenna: the antenna's plus the gradient
        # (vertical: normal gravity's d g/d h; horizontal: the direction turns by d_h / r, -g/r d_h)
        d_l = -np.einsum("nij,j->ni", k["C_lb"], lb)
        dgdh = (gravity_l(lat[0], llh[0, 2] + 0.5) - gravity_l(lat[0], llh[0, 2] - 0.5))
        g_over_r = -g[:, 2] / (WGS84_A + llh[:, 2])
        dg = d_l[:, 2:3] * dgdh[None, :]
        dg[:, :2] -= g_over_r[:, None] * d_l[:, :2]
        f_l = f_l - dg
        f_b = np.einsum("nji,nj->ni", k["C_lb"], f_l) - np.cross(w, np.cross(w, lb))
        return w, f_b
    f_b = np.einsum("nji,nj->ni", k["C_lb"], f_l)
    return w, f_b


def ideal_increments(traj, edges, lever_arm_b=None):
    """Exact (8-point Gauss-Legendre per smooth piece) increments over [edges[k], edges[k+1]].

    With ``lever_arm_b`` (FLU, m; IMU -> antenna, the trajectory being the antenna's) the
    increments are those of an IMU at ``antenna - C_eb l``: rigid body, ``f_imu = f_ant - w' x l
    - w x (w x l)`` with ``w = omega_ib_b``; the ``w' x l`` term integrates exactly to
    ``(w(t_k+1) - w(t_k)) x l``, the centripetal term by the same quadrature (the gravitation
    difference over the lever arm by its gradient: normal gravity's vertical d g/d h, ~3e-6 s^-2,
    and -g/r across)."""
    edges = np.asarray(edges, dtype=float)
    bps = traj.breakpoints()
    bps = bps[(bps > edges[0]) & (bps < edges[-1])]
    pts = np.union1d(edges, bps)
    owner = np.searchsorted(edges, pts[:-1], side="right") - 1        # IMU interval of each piece
    a, b = pts[:-1], pts[1:]
    half = 0.5 * (b - a)
    mid = 0.5 * (a + b)
    tq = (mid[:, None] + half[:, None] * _GL_X[None, :]).ravel()
    dth = np.zeros((len(edges) - 1, 3))
    dv = np.zeros((len(edges) - 1, 3))
    chunk = 200000
    w_all = np.empty((tq.size, 3))
    f_all = np.empty((tq.size, 3))
    for s in range(0, tq.size, chunk):
        w_all[s:s + chunk], f_all[s:s + chunk] = body_signals(traj, tq[s:s + chunk], lever_arm_b)
    wts = (half[:, None] * _GL_W[None, :]).ravel()[:, None]
    pw = (w_all * wts).reshape(-1, len(_GL_X), 3).sum(axis=1)
    pf = (f_all * wts).reshape(-1, len(_GL_X), 3).sum(axis=1)
    np.add.at(dth, owner, pw)
    np.add.at(dv, owner, pf)
    if lever_arm_b is not None:
        w_edge = traj.kinematics(edges, extras=False)["omega_ib_b"]
        dv -= np.cross(np.diff(w_edge, axis=0), np.asarray(lever_arm_b, float))
    return dth, dv


def lever_arm_truth(k, lever_arm_b):
    """Truth of the IMU point from the antenna's kinematics ``k`` (Trajectory.kinematics, with
    q_lb) and the lever arm IMU -> antenna ``lever_arm_b`` (FLU, m): llh, vel_l, q_lb."""
    lb = np.asarray(lever_arm_b, float)
    C_el = dcm_ecef_from_enu_vec(k["llh"][:, 0], k["llh"][:, 1])
    C_eb = C_el @ k["C_lb"]
    pos = k["pos_e"] - np.einsum("nij,j->ni", C_eb, lb)
    vel = k["vel_e"] - np.einsum("nij,nj->ni", C_eb, np.cross(k["omega_eb_b"], lb))
    llh = ecef_to_llh_batch(pos)
    C_el_i = dcm_ecef_from_enu_vec(llh[:, 0], llh[:, 1])
    vel_l = np.einsum("nji,nj->ni", C_el_i, vel)
    C_lb = np.transpose(C_el_i, (0, 2, 1)) @ C_eb
    return llh, vel_l, dcm_to_quat_vec(C_lb)


def _gauss_markov(rng, n, sigma, tau, dt):
    """First-order Gauss-Markov samples (n, 3), stationary start, steady-state std sigma."""
    out = np.zeros((n, 3))
    if not np.any(sigma) or n == 0:
        return out
    phi = math.exp(-dt / tau)
    drive = rng.standard_normal((n, 3)) * (sigma * math.sqrt(1.0 - phi * phi))
    x0 = rng.standard_normal(3) * sigma
    drive[0] = x0
    for ax in range(3):
        out[:, ax] = lfilter([1.0], [1.0, -phi], drive[:, ax])
    return out


def _quantise(x, q):
    if q <= 0.0:
        return x
    c = np.cumsum(x, axis=0)
    cq = np.round(c / q) * q
    out = np.diff(cq, axis=0, prepend=np.zeros((1, 3)))
    return out


def apply_errors(dtheta, dv, errors, rng, dt):
    """Corrupt ideal increments with ``errors`` (see module doc); returns new arrays."""
    n = dtheta.shape[0]
    Mg = np.eye(3) + np.diag(errors.gyro_sf) + errors.gyro_misalign
    Ma = np.eye(3) + np.diag(errors.accel_sf) + errors.accel_misalign
    dth = dtheta @ Mg.T + errors.gyro_bias * dt
    dvm = dv @ Ma.T + errors.accel_bias * dt
    if rng is None:
        rng = np.random.default_rng(0)
    if np.any(errors.gyro_arw):
        dth = dth + rng.standard_normal((n, 3)) * (errors.gyro_arw * math.sqrt(dt))
    if np.any(errors.accel_vrw):
        dvm = dvm + rng.standard_normal((n, 3)) * (errors.accel_vrw * math.sqrt(dt))
    dth = dth + _gauss_markov(rng, n, errors.gyro_gm_sigma, errors.gyro_gm_tau, dt) * dt
    dvm = dvm + _gauss_markov(rng, n, errors.accel_gm_sigma, errors.accel_gm_tau, dt) * dt
    return _quantise(dth, errors.gyro_quant), _quantise(dvm, errors.accel_quant)


def synthesize_imu(traj, rate_hz, errors=None, rng=None, duration_s=None, with_truth=True, lever_arm_b=None):
    """IMU increments along ``traj`` at ``rate_hz`` with ``errors`` (None = ideal).

    ``rng``: numpy Generator (required when the errors are random).  Returns :class:`ImuData`
    whose ``truth`` holds t, llh, vel_l, q_lb at the interval edges (t0 = 0 and every t[k]).
    ``lever_arm_b`` (FLU, m): the IMU sits at ``antenna - C_eb l`` where ``traj`` is the
    antenna's path; the increments and ``truth`` (llh, vel_l, q_lb) are then the IMU point's,
    ``truth["llh_antenna"]``/``truth["vel_l_antenna"]`` the antenna's, and ``lever_arm_b`` is
    recorded in the data.
    """
    lever = None
    if lever_arm_b is not None and np.any(np.asarray(lever_arm_b, float)):
        lever = np.asarray(lever_arm_b, float).reshape(3)
    rate_hz = float(rate_hz)
    if not rate_hz > 0.0:
        raise ConfigError(f"IMU rate must be > 0 Hz, got {rate_hz}")
    duration = traj.duration_s if duration_s is None else float(duration_s)
    n = int(math.floor(duration * rate_hz + 1e-9))
    if n < 1:
        raise ConfigError(f"IMU run of {duration} s at {rate_hz} Hz has no samples")
    edges = np.arange(n + 1) / rate_hz
    dth, dv = ideal_increments(traj, edges, lever)
    if errors is not None and not errors.is_ideal():
        dth, dv = apply_errors(dth, dv, errors, rng, 1.0 / rate_hz)
    truth = None
    if with_truth:
        k = traj.kinematics(edges)
        truth = {"t": edges, "llh": k["llh"], "vel_l": k["vel_l"], "q_lb": k["q_lb"]}
        if lever is not None:
            truth["llh_antenna"], truth["vel_l_antenna"] = truth["llh"], truth["vel_l"]
            truth["llh"], truth["vel_l"], truth["q_lb"] = lever_arm_truth(k, lever)
    meta = {"errors": (errors or ImuErrors(preset="ideal")).to_dict()}
    return ImuData(t=edges[1:].copy(), dtheta_b=dth, dv_b=dv, rate_hz=rate_hz, t0=0.0, truth=truth, meta=meta,
                   lever_arm_b=np.zeros(3) if lever is None else lever)


# ------------------------------------------------------------------ HDF5 I/O
IMU_H5_FORMAT = "ultratight-imu"
IMU_H5_VERSION = 1


def write_imu_h5(path, imu, meta=None):
    """Write :class:`ImuData` to HDF5 (layout in docs/ins.md); built in memory, written under a
    unique temporary name, then renamed (disk errors raise OutputError)."""
    allmeta = dict(imu.meta or {})
    allmeta.update(meta or {})

    def build(f):
        f.attrs["format"] = IMU_H5_FORMAT
        f.attrs["version"] = IMU_H5_VERSION
        f.attrs["rate_hz"] = float(imu.rate_hz)
        f.attrs["t0_s"] = float(imu.t0)
        f.attrs["body_frame"] = "FLU (x forward, y left, z up)"
        f.attrs["meta_json"] = json.dumps(allmeta, default=str)
        if np.any(imu.lever_arm_b):
            f.attrs["lever_arm_b_m"] = np.asarray(imu.lever_arm_b, float)
        f.create_dataset("t", data=np.asarray(imu.t, float))
        f["t"].attrs["units"] = "s (end of each increment interval)"
        f.create_dataset("dtheta_b", data=np.asarray(imu.dtheta_b, float))
        f["dtheta_b"].attrs["units"] = "rad"
        f.create_dataset("dv_b", data=np.asarray(imu.dv_b, float))
        f["dv_b"].attrs["units"] = "m/s"
        if imu.truth is not None:
            g = f.create_group("truth")
            g.attrs["description"] = "true state at t0 and at every t: llh (rad, rad, m), vel_l ENU m/s, " \
                                     "q_lb scalar-first body->ENU"
            for key in ("t", "llh", "vel_l", "q_lb", "llh_antenna", "vel_l_antenna"):
                if key in imu.truth:
                    g.create_dataset(key, data=np.asarray(imu.truth[key], float))

    write_h5_atomic(path, build)


def _float_array(f, key, path):
    ds = f[key]
    if not hasattr(ds, "dtype") or ds.dtype.kind not in "iuf":
        raise InputFileError(f"{path}: dataset /{key} must hold numbers, not {getattr(ds, 'dtype', type(ds))}")
    return np.asarray(ds[()], dtype=float)


def _attr_number(f, key, path, default=None):
    if key not in f.attrs:
        if default is not None:
            return default
        raise InputFileError(f"{path}: missing attribute {key!r}")
    v = f.attrs[key]
    try:
        v = float(np.asarray(v).reshape(-1)[0]) if np.asarray(v).size == 1 else None
    except (TypeError, ValueError):
        v = None
    if v is None or not math.isfinite(v):
        raise InputFileError(f"{path}: attribute {key!r} must be a finite number, got {f.attrs[key]!r}")
    return v


def read_imu_h5(path):
    """Read an IMU HDF5 file written by :func:`write_imu_h5` (InputFileError on problems: missing
    or malformed datasets/attributes, non-finite increments or stamps)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: IMU file not found")
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            if isinstance(fmt, bytes):
                fmt = fmt.decode("utf-8", "replace")
            if fmt != IMU_H5_FORMAT:
                raise InputFileError(f"{path}: not an ultratight IMU HDF5 file (attribute format = "
                                     f"{fmt!r}, expected {IMU_H5_FORMAT!r})")
            for key in ("t", "dtheta_b", "dv_b"):
                if key not in f or not isinstance(f[key], h5py.Dataset):
                    raise InputFileError(f"{path}: missing dataset /{key}")
            t = _float_array(f, "t", path)
            dth = _float_array(f, "dtheta_b", path)
            dv = _float_array(f, "dv_b", path)
            rate = _attr_number(f, "rate_hz", path)
            if not rate > 0:
                raise InputFileError(f"{path}: attribute rate_hz must be > 0 Hz, got {rate}")
            t0 = _attr_number(f, "t0_s", path, default=float(t.reshape(-1)[0] - 1.0 / rate) if t.size else 0.0)
            raw_meta = f.attrs.get("meta_json", "{}")
            if isinstance(raw_meta, bytes):
                raw_meta = raw_meta.decode("utf-8", "replace")
            try:
                meta = json.loads(raw_meta) if isinstance(raw_meta, str) else None
            except ValueError:
                meta = None
            if not isinstance(meta, dict):
                raise InputFileError(f"{path}: attribute meta_json is not a JSON object")
            lever = np.zeros(3)
            if "lever_arm_b_m" in f.attrs:
                lever = np.asarray(f.attrs["lever_arm_b_m"], dtype=float).reshape(-1)
                if lever.shape != (3,) or not np.all(np.isfinite(lever)):
                    raise InputFileError(f"{path}: attribute lever_arm_b_m must be 3 finite numbers (m)")
            truth = None
            if "truth" in f:
                if not isinstance(f["truth"], h5py.Group):
                    raise InputFileError(f"{path}: /truth must be a group")
                truth = {k: _float_array(f["truth"], k, path) for k in f["truth"].keys()}
    except InputFileError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise InputFileError(f"{path}: cannot read HDF5 ({' '.join(str(exc).split())[:200]})") from None
    if t.ndim != 1:
        raise InputFileError(f"{path}: /t must be one-dimensional, got shape {t.shape}")
    if dth.shape != (t.size, 3) or dv.shape != (t.size, 3):
        raise InputFileError(f"{path}: dtheta_b {dth.shape} / dv_b {dv.shape} do not match t ({t.size},)")
    for name, arr in (("dtheta_b", dth), ("dv_b", dv)):
        bad = np.argwhere(~np.isfinite(arr))
        if bad.size:
            raise InputFileError(f"{path}: sample {int(bad[0][0])}: {name} is not a finite number (NaN/inf)")
    _check_stamps(t, path, first_row=0, what="sample")
    if truth is not None:
        need = {"t": (t.size + 1,), "llh": (t.size + 1, 3), "vel_l": (t.size + 1, 3), "q_lb": (t.size + 1, 4)}
        for k, shp in need.items():
            if k in truth and (truth[k].shape[1:] != shp[1:] or not np.all(np.isfinite(truth[k]))):
                raise InputFileError(f"{path}: /truth/{k} has shape {truth[k].shape} or non-finite values")
        if not all(k in truth for k in ("llh", "vel_l", "q_lb")) or min(truth[k].shape[0] for k in
                                                                          ("llh", "vel_l", "q_lb")) < 1:
            raise InputFileError(f"{path}: /truth needs llh, vel_l and q_lb with at least one row")
    return ImuData(t=t, dtheta_b=dth, dv_b=dv, rate_hz=rate, t0=t0, truth=truth, meta=meta, lever_arm_b=lever)


# ------------------------------------------------------------------ CSV import
# accepted columns: time, then either rates or increments, with a unit suffix or (units declared in
# the IMU sidecar / flags, ultratight.ins.imu_decl) without one
_TIME_COLS = {"t_s": 1.0}
_RATE_UNITS = {"radps": "rad/s", "dps": "deg/s"}
_ACC_UNITS = {"mps2": "m/s^2", "g": "g"}
_DTH_UNITS = {"rad": "rad", "deg": "deg"}
_DV_UNITS = {"mps": "m/s"}
GAP_FACTOR = 1.5        # an interval longer than 1.5 x the median is a gap


def _check_stamps(t, path, first_row, what="row"):
    if t.size == 0:
        raise InputFileError(f"{path}: no IMU samples")
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise InputFileError(f"{path}: {what} {first_row + int(bad[0])}: time stamp is not a finite number")
    if t.size < 2:
        return None
    d = np.diff(t)
    nonpos = np.nonzero(d <= 0.0)[0]
    if nonpos.size:
        i = int(nonpos[0]) + 1
        kind = "duplicate" if d[i - 1] == 0.0 else "out-of-order"
        raise InputFileError(f"{path}: {what} {first_row + i}: {kind} time stamp t = {float(t[i]):.9g} s "
                             f"(previous {float(t[i - 1]):.9g} s); stamps must increase strictly")
    med = float(np.median(d))
    gaps = np.nonzero(d > GAP_FACTOR * med)[0]
    if gaps.size:
        i = int(gaps[0]) + 1
        raise InputFileError(f"{path}: {what} {first_row + i}: gap of {d[i - 1]:.6g} s before t = {float(t[i]):.9g} s "
                             f"(nominal interval {med:.6g} s); split the file or fill the gap")
    return med


def read_imu_csv(path, declaration=None):
    """Read a user IMU CSV file (layout in docs/ins.md, docs/imu-declaration.md) -> :class:`ImuData`.

    First non-comment line: header ``t_s`` plus either rates ``gx_<u>, gy_<u>, gz_<u>`` (u: radps,
    dps) and ``ax_<u>, ay_<u>, az_<u>`` (u: mps2, g) -- averages over the interval ending at t -- or
    increments ``dthx_<u>, dthy_<u>, dthz_<u>`` (u: rad, deg) and ``dvx_mps, dvy_mps, dvz_mps``;
    without the ``_<u>`` suffix the units come from ``declaration``.  Lines starting with ``#`` are
    comments.  ``declaration`` (:class:`ultratight.ins.imu_decl.ImuDeclaration`; default: the
    sidecar ``PATH.json`` when present, else the internal convention) gives axes, units, rate,
    time reference, lever arm; it is applied here and checked by the stationary sanity check.
    Problems raise InputFileError naming the line or the likely mistake.
    """
    from ultratight.ins import imu_decl

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: IMU CSV file not found")
    if declaration is None:
        declaration = imu_decl.resolve_declaration(path)
    text = read_text_input(path, "IMU CSV", "text CSV file")
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines())]
    lines = [(i, ln) for i, ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputFileError(f"{path}: empty IMU CSV file")
    hdr_line, hdr = lines[0]
    try:
        cols = [c.strip().lower() for c in next(csv.reader([hdr]))]
    except (csv.Error, StopIteration) as exc:
        raise InputFileError(f"{path}: line {hdr_line}: unreadable CSV header ({exc})") from None
    idx = {c: i for i, c in enumerate(cols)}
    if "t_s" not in idx:
        raise InputFileError(f"{path}: line {hdr_line}: header needs a 't_s' column (seconds); got {cols}")

    def find(prefixes, units, kind):
        """(column indices, unit names or None per axis) of the three columns, or None."""
        out_i, out_u = [], []
        for p in prefixes:
            hits = [c for c in cols if c == p or c.startswith(p + "_")]
            if not hits:
                return None
            c = hits[0]
            u = c[len(p) + 1:] if c != p else None
            if u is not None and u not in units:
                raise InputFileError(f"{path}: line {hdr_line}: column {c!r} has unknown unit {u!r} for "
                                     f"{kind}; allowed: {', '.join(p + '_' + k for k in units)} (or {p!r} with "
                                     f"the unit declared in the IMU sidecar)")
            out_i.append(idx[c])
            out_u.append(units[u] if u is not None else None)
        return out_i, out_u

    g = find(("gx", "gy", "gz"), _RATE_UNITS, "angular rate")
    a = find(("ax", "ay", "az"), _ACC_UNITS, "specific force")
    dth = find(("dthx", "dthy", "dthz"), _DTH_UNITS, "angle increment")
    dvv = find(("dvx", "dvy", "dvz"), _DV_UNITS, "velocity increment")
    if g and a:
        mode, gcols, acols = "rates", g, a
    elif dth and dvv:
        mode, gcols, acols = "increments", dth, dvv
    else:
        raise InputFileError(f"{path}: line {hdr_line}: header must have t_s and either gx_/gy_/gz_ + "
                             f"ax_/ay_/az_ rate columns or dthx_/dthy_/dthz_ + dvx_/dvy_/dvz_ increment "
                             f"columns (with unit suffixes, or without and the units declared); got {cols}")
    hdr_units = []
    for what, (_, us) in (("gyro", gcols), ("accelerometer", acols)):
        if len(set(us)) > 1 and None in us:
            raise InputFileError(f"{path}: line {hdr_line}: {what} columns mix unit suffixes and bare names")
        hdr_units.append(us)
    gyro_unit, accel_unit, kind = imu_decl.units_for(declaration, mode, hdr_units[0][0], hdr_units[1][0], path)
    gsc = np.array([imu_decl.GYRO_UNITS[u or gyro_unit][0] for u in hdr_units[0]])
    asc = np.array([imu_decl.ACCEL_UNITS[u or accel_unit][0] for u in hdr_units[1]])
    ci = gcols[0] + acols[0]
    rows = lines[1:]
    if len(rows) < 2:
        raise InputFileError(f"{path}: need at least 2 data lines, got {len(rows)}")
    n = len(rows)
    data = np.empty((n, 7))
    line_no = np.empty(n, dtype=int)
    want = [idx["t_s"]] + ci
    for r, (ln, text) in enumerate(rows):
        try:
            fields = next(csv.reader([text]))
        except (csv.Error, StopIteration) as exc:
            raise InputFileError(f"{path}: line {ln}: unreadable CSV line ({exc})") from None
        line_no[r] = ln
        if len(fields) != len(cols):
            raise InputFileError(f"{path}: line {ln}: {len(fields)} fields, header has {len(cols)}")
        for j, c in enumerate(want):
            try:
                v = float(fields[c])
            except ValueError:
                raise InputFileError(f"{path}: line {ln}: column {cols[c]!r}: {fields[c]!r} is not a number") \
                    from None
            if not math.isfinite(v):
                raise InputFileError(f"{path}: line {ln}: column {cols[c]!r} is {fields[c].strip()} "
                                     f"(NaN/inf not allowed)")
            data[r, j] = v
    t = data[:, 0] + declaration.time_offset_s
    try:
        med = _check_stamps(t, path, 0, what="row")
    except InputFileError as exc:
        # translate the row index into the file line number
        msg = str(exc)
        m = re.search(r"row (\d+):", msg)
        if m:
            msg = msg.replace(f"row {m.group(1)}:", f"line {line_no[int(m.group(1))]}:")
        raise InputFileError(msg) from None
    if declaration.rate_hz is not None and abs(declaration.rate_hz * med - 1.0) > 0.01:
        raise InputFileError(f"{path}: declared rate {declaration.rate_hz:g} Hz ({declaration.source}) but the "
                             f"stamps are {1.0 / med:.6g} Hz apart")
    report = {"checked": False, "reason": "check disabled in the declaration"}
    if declaration.check:
        report = imu_decl.stationary_check(data[:, 4:7], data[:, 1:4], med, declaration, accel_unit, gyro_unit,
                                           kind, path)
    vals = data[:, 1:] * np.concatenate([gsc, asc])
    dts = np.diff(t, prepend=t[0] - med)
    if mode == "rates":
        vals = vals * dts[:, None]
    M = declaration.M
    meta = {"source": str(path), "csv_mode": "rate" if mode == "rates" else "increment",
            "declaration": declaration.to_dict(), "declaration_source": declaration.source,
            "sanity_check": report}
    t0 = float(t[0] - med)
    if declaration.time_ref == "gps_tow":
        meta["start_tow_s"] = t0
        if declaration.gps_week is not None:
            meta["start_week"] = int(declaration.gps_week)
        t = t - t0
        t0 = 0.0
    return ImuData(t=t.copy(), dtheta_b=vals[:, :3] @ M.T, dv_b=vals[:, 3:] @ M.T, rate_hz=1.0 / med,
                   t0=t0, truth=None, meta=meta, lever_arm_b=declaration.lever_arm_b())


def write_imu_csv(path, imu, declaration=None):
    """Write increments as CSV (t_s, dthx_rad, ..., dvz_mps) -- the format read_imu_csv reads.

    With ``declaration`` (:class:`ultratight.ins.imu_decl.ImuDeclaration`: kind, axes, units, time
    reference and offset) the data are written in that convention under bare column names, the
    lever arm of ``imu`` in the declared axes, and the declaration as the sidecar ``PATH.json``."""
    from ultratight.ins import imu_decl

    if declaration is None:
        with atomic_path(path) as tmp:
            with open(tmp, "w") as fh:
                fh.write("# ultratight IMU increments, body frame FLU; t_s = end of interval\n")
                fh.write("t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps\n")
                for k in range(imu.n):
                    fh.write(f"{imu.t[k]:.9f}," + ",".join(f"{x:.17g}" for x in imu.dtheta_b[k]) + "," +
                             ",".join(f"{x:.17g}" for x in imu.dv_b[k]) + "\n")
        return None
    dec = declaration
    kind = dec.kind or "increments"
    gu = dec.gyro_unit or ("rad/s" if kind == "rates" else "rad")
    au = dec.accel_unit or ("m/s^2" if kind == "rates" else "m/s")
    M = dec.M
    dth = imu.dtheta_b @ M / imu_decl.GYRO_UNITS[gu][0]       # v_file = M^T v_FLU
    dv = imu.dv_b @ M / imu_decl.ACCEL_UNITS[au][0]
    t = np.asarray(imu.t, float)
    if kind == "rates":
        dts = np.diff(t, prepend=float(imu.t0))
        dth, dv = dth / dts[:, None], dv / dts[:, None]
    if dec.time_ref == "gps_tow":
        t = t + float(imu.meta.get("start_tow_s", 0.0))
    t = t - dec.time_offset_s
    names = ("gx,gy,gz,ax,ay,az" if kind == "rates" else "dthx,dthy,dthz,dvx,dvy,dvz")
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            fh.write(f"# ultratight IMU {kind}, axes {dec.axes if isinstance(dec.axes, str) else 'matrix'}, "
                     f"units in the sidecar {imu_decl.sidecar_path(path).name}\n")
            fh.write("t_s," + names + "\n")
            for k in range(t.shape[0]):
                fh.write(f"{t[k]:.9f}," + ",".join(f"{x:.17g}" for x in dth[k]) + "," +
                         ",".join(f"{x:.17g}" for x in dv[k]) + "\n")
    out = imu_decl.ImuDeclaration(kind=kind, axes=dec.axes, gyro_unit=gu, accel_unit=au,
                                  rate_hz=float(imu.rate_hz), time_ref=dec.time_ref, gps_week=dec.gps_week,
                                  time_offset_s=dec.time_offset_s, lever_arm_m=M.T @ np.asarray(imu.lever_arm_b),
                                  check=dec.check)
    return imu_decl.write_sidecar(path, out)


# ------------------------------------------------------------------ Allan deviation (for tests/benchmarks)
def allan_deviation(y, dt, taus):
    """Overlapping Allan deviation of rate samples ``y`` (n,) at cluster times ``taus`` (s)."""
    y = np.asarray(y, float)
    theta = np.concatenate([[0.0], np.cumsum(y) * dt])
    out = np.empty(len(taus))
    for i, tau in enumerate(taus):
        m = int(round(tau / dt))
        if m < 1 or 2 * m >= theta.size:
            out[i] = np.nan
            continue
        d = theta[2 * m:] - 2.0 * theta[m:-m] + theta[:-2 * m]
        out[i] = math.sqrt(np.mean(d * d) / (2.0 * (m * dt) ** 2))
    return out
