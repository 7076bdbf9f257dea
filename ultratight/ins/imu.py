"""IMU synthesis, sensor error models and unit conversions.

IMU data are *increments* (:class:`ultratight.ins.imu_data.ImuData`, which also holds the IMU
file readers and writers): sample k covers the interval (t[k] - dt, t[k]] and holds
``dtheta_b[k] = int omega_ib_b dt`` (rad) and ``dv_b[k] = int f_b dt`` (m/s), both
integrated in the (rotating) body frame, exactly what strapdown gyros and
accelerometers deliver and what :mod:`ultratight.ins.sins` (two-sample coning and
sculling) expects.  Body frame FLU (x forward, y left, z up).

Ideal increments are computed from the analytic trajectory by 8-point
Gauss-Legendre quadrature per interval (split at the trajectory's segment
breakpoints), with the specific force ``f_b = C_bl (C_le a_e + 2 omega_ie x v_l - g_l)``
using the same normal gravity :func:`ultratight.ins.earth.gravity_l` as the
mechanisation, so an error-free SINS reproduces the trajectory.  The ideal increments are checked
against the sensor range (:func:`check_limits`: ``gyro_range_dps``, ``accel_range_g``,
``angular_accel_max_dps2`` of the ``[imu]`` table, defaults 2000 deg/s, 50 g, 5e4 deg/s^2).

Sensor error model per axis (all in SI inside, see :class:`ImuErrors`)::

    dtheta_meas = (I + S_g + M_g) dtheta + (b_g + b_gm,k) dt + n_g,k,   n_g,k ~ N(0, arw^2 dt)
    dv_meas     = (I + S_a + M_a) dv     + (b_a + b_am,k) dt + n_a,k,   n_a,k ~ N(0, vrw^2 dt)

then quantised with the residual carried over (sum-preserving).  ``b_gm`` is a
first-order Gauss-Markov process (steady-state sigma, correlation time tau) sampled
at the IMU rate.  Datasheet units at the boundary: deg/h, deg/sqrt(h), ug,
ug/sqrt(Hz), ppm (see the ``*_TO_SI`` constants and docs/ins.md).

**Declaration and realisation.**  A preset or an ``[imu]`` table is the *declaration* of a sensor,
what its datasheet says; one run's sensor is a *realisation* of it (:func:`realise_errors`, drawn
from the run's generator, so a seed always gives the same sensor and two seeds two sensors):

* turn-on biases ``b_g``, ``b_a``: with ``bias_reading = "sigma"`` (the grades ``navigation``,
  ``tactical``, ``mems`` and custom figures) the declared figure is the 1-sigma of the turn-on
  bias over a population of sensors, ``b ~ N(0, sigma^2)`` per axis -- a datasheet's bias
  (repeatability) figure; with ``bias_reading = "stated"`` (preset ``paper``: Zhao et al. 2014,
  §3 state *the* bias, 0.01 deg/h and 30 ug) the stated value is the magnitude, with a random sign
  per axis and run, ``b = s |value|``, ``s = +-1`` equally likely -- the paper gives a value, not a
  spread, and a fixed sign on every axis in every run would be a sensor no population has;
* scale factors ``S``: ``N(0, sigma^2)`` per axis; misalignments ``M``: ``N(0, sigma^2)`` per
  off-diagonal element (the diagonal stays 0);
* white noise (ARW/VRW), Gauss-Markov bias instability and quantisation are processes already
  random per run: they are applied as declared.

The IMU file carries the declaration only (``meta["errors"]``, :meth:`ImuErrors.to_dict`:
1-sigma biases or the stated magnitudes, densities, scale factor and misalignment sigmas,
``bias_reading``), so a receiver tunes its filters from the datasheet and never from the drawn
values; the realisation is kept in :attr:`ImuData.errors_realised` for the truth side (the
generator writes it into the truth file).
"""

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from ultratight.constants import OMEGA_E, WGS84_A
from ultratight.errors import ConfigError
from ultratight.ins.attitude import dcm_to_quat_vec
from ultratight.ins.earth import dcm_ecef_from_enu_vec, ecef_to_llh_batch, gravity_l
from ultratight.ins.imu_data import ImuData
# the HDF5 reader and writer are also imported from here by ultratight.receiver.cli.scenario_runner
# and ultratight.receiver.cli.commands.ins

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
    # how the bias figures read (module doc): "sigma" (1-sigma of the turn-on bias), "stated" (a paper's
    # stated value: the magnitude, random sign per axis and run) or "realised" (the drawn values of one run)
    bias_reading: str = "sigma"
    # sensor range (check_limits): angular rate (rad/s), specific force (m/s^2), angular acceleration
    gyro_range: float = math.radians(2000.0)
    accel_range: float = 50.0 * 9.80665
    angular_accel_max: float = math.radians(5.0e4)

    def is_ideal(self):
        arrs = [self.gyro_bias, self.accel_bias, self.gyro_arw, self.accel_vrw, self.gyro_gm_sigma,
                self.accel_gm_sigma, self.gyro_sf, self.accel_sf, self.gyro_misalign, self.accel_misalign]
        return all(not np.any(a) for a in arrs) and self.gyro_quant == 0.0 and self.accel_quant == 0.0

    def to_dict(self):
        out = {}
        for k, v in self.__dict__.items():
            out[k] = v.tolist() if isinstance(v, np.ndarray) else (None if v == math.inf else v)
        return out


BIAS_READINGS = ("sigma", "stated")
# the bias reading of each preset when the [imu] table does not name one (module doc)
PRESET_BIAS_READING = {"paper": "stated"}

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

# the keys of a scenario's [imu] table (preset, rate, datasheet figures, seed, file, lever arm)
CONFIG_KEYS = {
    "preset", "rate_hz", "gyro_bias_dph", "accel_bias_ug", "gyro_noise_dph", "gyro_arw_dprh",
    "accel_noise_ug", "accel_vrw_ugrhz", "gyro_bi_dph", "gyro_bi_tau_s", "accel_bi_ug", "accel_bi_tau_s",
    "gyro_sf_ppm", "accel_sf_ppm", "gyro_misalign_mrad", "accel_misalign_mrad", "gyro_quant_urad",
    "accel_quant_mmps", "seed", "file", "lever_arm_m", "gyro_range_dps", "accel_range_g", "angular_accel_max_dps2",
    "bias_reading",
}
# sensor range defaults (datasheet units): a MEMS gyro's +-2000 deg/s, a +-50 g accelerometer, and an
# angular acceleration no vehicle body reaches (the rate steps of the "turns" kind at 100 Hz: ~4e3)
RANGE_DEFAULTS = {"gyro_range_dps": 2000.0, "accel_range_g": 50.0, "angular_accel_max_dps2": 5.0e4}


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

    The result is the *declaration* (module doc): bias, scale-factor and misalignment figures are
    1-sigma values (or, ``bias_reading = "stated"``, the stated bias magnitudes); one run's sensor is
    drawn from it by :func:`realise_errors`.
    """
    imu_cfg = dict(imu_cfg or {})
    preset = imu_cfg.get("preset", "ideal")
    if preset not in PRESETS:
        raise ConfigError(f"imu.preset must be one of {', '.join(PRESETS)}; got {preset!r}")
    unknown = sorted(set(imu_cfg) - CONFIG_KEYS)
    if unknown:
        raise ConfigError(f"imu: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(CONFIG_KEYS))}")
    cfg = dict(PRESETS[preset])
    cfg.update({k: v for k, v in imu_cfg.items() if k != "preset"})
    rate = float(cfg.get("rate_hz", 100.0))
    if not rate > 0.0:
        raise ConfigError(f"imu.rate_hz must be > 0, got {rate}")
    reading = cfg.get("bias_reading", PRESET_BIAS_READING.get(preset, "sigma"))
    if reading not in BIAS_READINGS:
        raise ConfigError(f"imu.bias_reading must be one of {', '.join(BIAS_READINGS)}; got {reading!r}")
    e = ImuErrors(preset=preset, bias_reading=reading)
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
    rng_cfg = {k: cfg.get(k, v) for k, v in RANGE_DEFAULTS.items()}
    for k, v in rng_cfg.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            raise ConfigError(f"imu.{k} must be a number > 0, got {v!r}")
    e.gyro_range = math.radians(float(rng_cfg["gyro_range_dps"]))
    e.accel_range = float(rng_cfg["accel_range_g"]) * G0
    e.angular_accel_max = math.radians(float(rng_cfg["angular_accel_max_dps2"]))
    return e


def check_limits(dtheta, dv, rate_hz, errors=None):
    """ConfigError (one line: the time and the value) when ideal increments at ``rate_hz`` exceed the
    sensor range of ``errors`` (defaults of :class:`ImuErrors` when None): the mean angular rate
    or specific force of an interval on a body axis, or the change of the mean rate between two
    intervals per second (angular acceleration).  A trajectory beyond them is no vehicle's."""
    lim = errors if errors is not None else ImuErrors()
    w = np.asarray(dtheta) * rate_hz
    f = np.asarray(dv) * rate_hz
    alpha = np.diff(w, axis=0) * rate_hz
    checks = (("angular rate", w, lim.gyro_range, math.degrees(1.0), "deg/s", "gyro range", "gyro_range_dps"),
              ("specific force", f, lim.accel_range, 1.0 / G0, "g", "accelerometer range", "accel_range_g"),
              ("angular acceleration", alpha, lim.angular_accel_max, math.degrees(1.0), "deg/s^2",
               "angular acceleration limit", "angular_accel_max_dps2"))
    for name, x, top, unit, uname, what, key in checks:
        if x.size == 0:
            continue
        over = np.flatnonzero(np.max(np.abs(x), axis=1) > top)
        if over.size:
            k = int(over[0])
            ax = int(np.argmax(np.abs(x[k])))
            raise ConfigError(f"IMU {name} {x[k, ax] * unit:.6g} {uname} on body axis {'xyz'[ax]} at t = "
                              f"{(k + 1) / rate_hz:.6g} s is beyond the {what} {top * unit:.6g} {uname} "
                              f"(imu.{key}): the trajectory is no vehicle's")


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


@njit(cache=True)
def _first_order_recursion(drive, phi):
    """``y[k] = phi y[k-1] + drive[k]`` down the columns of ``drive`` (``y[0] = drive[0]``), in that order of
    operations (no fused multiply-add): the values of ``scipy.signal.lfilter([1], [1, -phi], ...)``, bit for
    bit (tests/test_ins_sins.py), without importing scipy.signal (about a second, on the critical path of
    every scenario start)."""
    out = np.empty_like(drive)
    n, m = drive.shape
    for j in range(m):
        y = 0.0
        for k in range(n):
            y = phi * y + drive[k, j]
            out[k, j] = y
    return out


def _gauss_markov(rng, n, sigma, tau, dt):
    """First-order Gauss-Markov samples (n, 3), stationary start, steady-state std sigma."""
    out = np.zeros((n, 3))
    if not np.any(sigma) or n == 0:
        return out
    phi = math.exp(-dt / tau)
    drive = rng.standard_normal((n, 3)) * (sigma * math.sqrt(1.0 - phi * phi))
    x0 = rng.standard_normal(3) * sigma
    drive[0] = x0
    return _first_order_recursion(drive, phi)


def _quantise(x, q):
    if q <= 0.0:
        return x
    c = np.cumsum(x, axis=0)
    cq = np.round(c / q) * q
    out = np.diff(cq, axis=0, prepend=np.zeros((1, 3)))
    return out


def realise_errors(spec, rng):
    """One run's sensor drawn from the declaration ``spec`` (module doc): an :class:`ImuErrors` with
    the drawn biases, scale factors and misalignments (``bias_reading = "realised"``) and the
    declared noise processes.

    Draws from ``rng`` in a fixed order, each group only when its declared figure is non-zero: gyro
    bias (3), accelerometer bias (3), gyro and accelerometer scale factor (3 each), gyro and
    accelerometer misalignment (the 6 off-diagonal elements each).  With ``bias_reading = "stated"``
    the bias draw's sign times the stated magnitude is the bias.  ``spec`` already realised is
    returned as it is."""
    if spec.bias_reading == "realised":
        return spec
    if spec.bias_reading not in BIAS_READINGS:
        raise ConfigError(f"imu: bias_reading must be one of {', '.join(BIAS_READINGS)}; got {spec.bias_reading!r}")
    out = ImuErrors(**{k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in spec.__dict__.items()})
    out.bias_reading = "realised"
    for name in ("gyro_bias", "accel_bias"):
        fig = np.asarray(getattr(spec, name), float)
        if np.any(fig):
            z = rng.standard_normal(3)
            setattr(out, name, np.where(z < 0.0, -1.0, 1.0) * np.abs(fig) if spec.bias_reading == "stated"
                    else z * fig)
    for name in ("gyro_sf", "accel_sf"):
        fig = np.asarray(getattr(spec, name), float)
        if np.any(fig):
            setattr(out, name, rng.standard_normal(3) * fig)
    off = ~np.eye(3, dtype=bool)
    for name in ("gyro_misalign", "accel_misalign"):
        fig = np.asarray(getattr(spec, name), float)
        if np.any(fig[off]):
            m = np.zeros((3, 3))
            m[off] = rng.standard_normal(6) * fig[off]
            setattr(out, name, m)
    return out


def apply_errors(dtheta, dv, errors, rng, dt):
    """Corrupt ideal increments with ``errors`` as given (one run's sensor: :func:`realise_errors`
    draws it from a declaration; see module doc); returns new arrays."""
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
    """IMU increments along ``traj`` at ``rate_hz`` of a sensor declared by ``errors`` (None = ideal).

    ``rng``: numpy Generator: the run's sensor is drawn from it (:func:`realise_errors`: biases, scale
    factors, misalignments), then the noise.  ``meta["errors"]`` holds the declaration
    (:meth:`ImuErrors.to_dict`), the drawn sensor is ``errors_realised`` (truth side; never written
    into the IMU file).  The ideal increments are checked
    against the sensor range of ``errors`` (:func:`check_limits`, ConfigError beyond it).  Returns :class:`ImuData`
    whose ``truth`` holds t, llh, vel_l, q_lb at the interval edges (t0 = 0 and every t[k]).
    ``lever_arm_b`` (FLU, m): the IMU sits at ``antenna - C_eb l`` where ``traj`` is the
    antenna's path; the increments and ``truth`` (llh, vel_l, q_lb) are then the IMU point's,
    ``truth["llh_antenna"]``/``truth["vel_l_antenna"]`` the antenna's, and ``lever_arm_b`` is
    recorded in the data.
    """
    if errors is not None and errors.bias_reading == "realised":
        raise ConfigError("synthesize_imu: errors must be a declaration (a preset or [imu] figures), "
                          "not a drawn sensor")
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
    check_limits(dth, dv, rate_hz, errors)
    realised = None
    if errors is not None and not errors.is_ideal():
        if rng is None:
            rng = np.random.default_rng(0)
        realised = realise_errors(errors, rng)
        dth, dv = apply_errors(dth, dv, realised, rng, 1.0 / rate_hz)
    truth = None
    if with_truth:
        k = traj.kinematics(edges)
        truth = {"t": edges, "llh": k["llh"], "vel_l": k["vel_l"], "q_lb": k["q_lb"]}
        if lever is not None:
            truth["llh_antenna"], truth["vel_l_antenna"] = truth["llh"], truth["vel_l"]
            truth["llh"], truth["vel_l"], truth["q_lb"] = lever_arm_truth(k, lever)
    spec = errors or ImuErrors(preset="ideal")
    meta = {"errors": spec.to_dict()}
    return ImuData(t=edges[1:].copy(), dtheta_b=dth, dv_b=dv, rate_hz=rate_hz, t0=0.0, truth=truth, meta=meta,
                   lever_arm_b=np.zeros(3) if lever is None else lever,
                   errors_realised=(realised or spec).to_dict())


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
