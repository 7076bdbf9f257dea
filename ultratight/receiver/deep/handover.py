"""Start-up of the ultra-tight engine without truth: the hand-over from the scalar receiver.

A recording as a user has it (IF file, IMU file, navigation file, no truth) gives the engine no
initial state. This module builds one (docs/ultratight.md, "Start-up without truth"):

* **Position, velocity, clock** from the scalar receiver (:class:`ultratight.receiver.scalar.receiver.
  ScalarReceiver`) run over the first seconds of the same file (``HandoverConfig.window_s`` from the
  start ``start_s``). The hand-over fix is the first of ``settle_fixes`` consecutive fixes with at
  least ``min_sats`` satellites that has a next fix (for the acceleration). The scalar pass corrects
  the ionosphere / troposphere with the engine's model (``atmosphere``: the same Klobuchar
  coefficients and Saastamoinen troposphere, or none), so that the hand-over fix and the engine's
  predictions agree.
  The engine's clock bias refers to the IF file's time scale (receiver time of sample ``s`` =
  sidecar start TOW + s/fs): ``b = c (tow0 + t_fix - t_gps,fix)``, the drift is the fix's.
* **Hand-over time**: the IMU stamp nearest to the fix (the engine's SINS starts on an IMU
  stamp); position and velocity are moved there with the fix velocity and the GNSS acceleration
  (at most half an IMU interval).
* **Attitude** as the solution of Wahba's problem for two vector observations (SVD solution,
  Markley 1988), with the covariance ``P = (sum_i w_i (I - n_i n_i'))^-1`` (rad^2, local ENU
  error angles; w_i = 1/sigma_i^2, sigma_i the angular uncertainty of vector i; Shuster & Oh 1981):

  - *still* (GNSS speed below ``still_speed_mps`` and a steady specific force over ``still_s``
    before the hand-over): levelling (mean specific force against the gravity vector) and
    gyro-compassing (mean angular rate against the Earth rate). The heading sigma is
    ``~ sigma_gyro / (omega_ie cos(lat))``; when it exceeds ``max_heading_sigma_deg`` (IMU grade too
    low, e.g. MEMS gyros with 200 deg/h bias vs the 15 deg/h Earth rate) the start-up stops with
    a one-line error asking for ``--init-att`` or for motion;
  - *moving* (GNSS speed above ``move_speed_mps``): the specific force ``f_l = dv/dt + (2 w_ie +
    w_en) x v - g_l`` (GNSS acceleration from the fixes one obs interval either side) against the
    IMU's mean specific force over the same interval, and the velocity direction against the body
    x axis (nose), with an assumed sideslip / angle-of-attack sigma ``sideslip_deg``, and the body
    y axis (left wing) against the horizontal left of the velocity banked by the coordinated-turn
    angle ``atan(v_h psi_dot / g)`` (0 in straight flight; psi_dot the turn rate of the GNSS
    velocity), sigma ``bank_sigma_deg``. Without the bank pair the rotation about the specific
    force is fixed only to ``sideslip_deg / angle(f, v)``: 37 deg on paper-highdyn at 10 g, where f
    and v are 5.6 deg apart, beyond what the tight filter's small-angle error model can correct
    (measured: its roll went to -64 deg within a second of a hand-over at 19.6 s). A vehicle that
    flies rolled (a spinning missile) needs ``--init-att``.
* Stated covariances: position from the fix covariance (3-D sigma per axis), velocity from the
  fix velocity covariance, clock from the fix, attitude from Wahba's covariance; they set the
  tight filter's initial covariance (:func:`ultratight.fusion.coupling.tight.initial_covariance`).

``--init-llh / --init-vel / --init-att`` (degrees, metres, m/s) override the corresponding parts
(sigmas ``FLAG_SIGMAS``). All three given (and no scalar pass wanted): the engine starts at the
start time from them, the clock taken as zero (the sidecar start time taken as GPS time).
"""

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from ultratight.constants import C
from ultratight.errors import ConfigError, InputFileError
from ultratight.ins.attitude import dcm_to_euler, dcm_to_quat, euler_to_dcm, quat_to_dcm
from ultratight.ins.earth import dcm_ecef_from_enu, earth_rate_l, ecef_to_llh, gravity_l, transport_rate_l
from ultratight.ins.imu_data import ImuData
from ultratight.receiver.dsp.tracking_layout import MODE_TRACK
from ultratight.signals.signal import GPS_L1CA

STARTUP_SCALAR = "scalar-fix"
STARTUP_FLAGS = "init-flags"
STARTUP_TRUTH = "truth-perturbed"
STARTUP_SOURCES = (STARTUP_SCALAR, STARTUP_FLAGS, STARTUP_TRUTH)

# 1-sigma of a state given by --init-* flags (per axis), and of the clock when no scalar pass ran
FLAG_SIGMAS = {"pos_m": 10.0, "vel_mps": 0.5, "att_deg": 1.0, "clk_bias_m": 30.0, "clk_drift_mps": 1.0}
WEEK_S = 604800.0


@dataclass
class HandoverConfig:
    """Parameters of the scalar-to-ultra-tight hand-over (see module docstring)."""

    window_s: float = 20.0          # scalar pass length from the start: LNAV time of week (<= 6 s + sync),
    #                                 a settled fix and a still receiver's fix_avg_s of averaging
    min_sats: int = 5               # satellites in the hand-over fix
    settle_fixes: int = 3           # consecutive fixes ending at the hand-over fix
    still_s: float = 1.0            # still interval for levelling / gyro-compassing (at least)
    still_max_s: float = 10.0       # ... and at most: the longest still stretch before the hand-over
    fix_avg_s: float = 10.0         # a still receiver hands over the mean of its fixes over this span ...
    fix_avg_min_s: float = 3.0      # ... or over the still fixes it has when motion or the pass end comes
    #                                 first, if they span at least this (else the settled fix alone)
    still_speed_mps: float = 0.2
    still_force_mps2: float = 0.1   # largest deviation of 0.1 s mean specific force magnitudes
    move_speed_mps: float = 3.0
    accel_half_s: float = 0.1       # GNSS acceleration / IMU mean: +- this around the hand-over
    sideslip_deg: float = 3.0       # body x axis vs velocity direction, 1 sigma
    max_heading_sigma_deg: float = 30.0   # gyro-compassing worse than this: refused (give --init-att)
    warn_heading_sigma_deg: float = 5.0   # ... worse than this: a warning (the filter refines it in motion)
    bank_sigma_deg: float = 2.0     # moving: bank vs the coordinated-turn bank, 1 sigma (see docs)
    acq_min_cn0_dbhz: float = 37.0  # scalar pass acquisition (the process flags)
    acq_noncoherent: int = 1
    acq_coherent_ms: int = 10
    doppler_range_hz: float = 10e3
    dynamics: str = "normal"        # scalar pass loop profile and Doppler-rate search (process --dynamics)
    # no acquisition setting given and the pass tracks fewer than min_sats: once more with the
    # weak-signal acquisition (WEAK_ACQUISITION: 5 ms x 16 non-coherent, C/N0 floor 25 dB-Hz)
    weak_retry: bool = True
    # the troposphere correction was not asked for explicitly: test whether the recording carries one
    # (receiver.deep.tropo_check) and switch the correction off for the run when it does not
    tropo_check: bool = True

    def as_dict(self):
        return asdict(self)


# ------------------------------------------------------------------ flags
def parse_triplet(text, flag):
    """``"A,B,C"`` or ``["A", "B", "C"]`` (or a mix) -> three finite floats; ConfigError naming
    ``flag`` otherwise."""
    if isinstance(text, (list, tuple)):
        text = ",".join(str(t) for t in text)
    parts = [p.strip() for p in str(text).replace(" ", ",").split(",") if p.strip()]
    if len(parts) != 3:
        raise ConfigError(f"{flag}: expected three numbers, got {text!r}")
    out = []
    for p in parts:
        try:
            v = float(p)
        except ValueError:
            raise ConfigError(f"{flag}: {p!r} is not a number (in {text!r})") from None
        if not math.isfinite(v):
            raise ConfigError(f"{flag}: {p!r} is not a finite number")
        out.append(v)
    return out


def parse_init_flags(init_llh=None, init_vel=None, init_att=None):
    """The ``--init-*`` flags -> dict with any of ``llh`` (rad, rad, m), ``vel_l`` (ENU m/s),
    ``q_lb``; ConfigError on malformed or impossible values."""
    out = {}
    if init_llh is not None:
        lat, lon, h = parse_triplet(init_llh, "--init-llh")
        if not -90.0 <= lat <= 90.0:
            raise ConfigError(f"--init-llh: latitude must be in [-90, 90] deg, got {lat}")
        if not -180.0 <= lon <= 360.0:
            raise ConfigError(f"--init-llh: longitude must be in [-180, 360] deg, got {lon}")
        if not -1e4 <= h <= 1e6:
            raise ConfigError(f"--init-llh: height must be in [-10000, 1000000] m, got {h}")
        out["llh"] = np.array([math.radians(lat), math.radians(lon), h])
    if init_vel is not None:
        v = np.array(parse_triplet(init_vel, "--init-vel"))
        if np.linalg.norm(v) > 2e4:
            raise ConfigError(f"--init-vel: speed {np.linalg.norm(v):.0f} m/s is beyond 20 km/s")
        out["vel_l"] = v
    if init_att is not None:
        r, p, y = parse_triplet(init_att, "--init-att")
        if not -90.0 <= p <= 90.0:
            raise ConfigError(f"--init-att: pitch must be in [-90, 90] deg, got {p}")
        out["q_lb"] = np.asarray(dcm_to_quat(euler_to_dcm(math.radians(r), math.radians(p), math.radians(y))))
    return out


# ------------------------------------------------------------------ attitude
def wahba(pairs):
    """Attitude from vector pairs ``[(n_l, b_b, sigma_rad), ...]`` (unit vectors in the local and body
    frames and the angular 1-sigma of the pair): ``(C_lb, P_att)`` with P_att the error-angle
    covariance (rad^2, local frame). SVD solution of Wahba's problem (Markley 1988)."""
    B = np.zeros((3, 3))
    info = np.zeros((3, 3))
    for n, b, s in pairs:
        n = np.asarray(n, float) / np.linalg.norm(n)
        b = np.asarray(b, float) / np.linalg.norm(b)
        w = 1.0 / s ** 2
        B += w * np.outer(n, b)
        info += w * (np.eye(3) - np.outer(n, n))
    U, _, Vt = np.linalg.svd(B)
    d = np.linalg.det(U) * np.linalg.det(Vt)
    C_lb = U @ np.diag([1.0, 1.0, d]) @ Vt
    P = np.linalg.inv(info)
    return C_lb, 0.5 * (P + P.T)


def _mean_sigma(bias, gm_sigma, white, T):
    """Effective per-axis 1-sigma of a sensor mean over T s: bias (+ in-run Gauss-Markov) and white
    noise (its random-walk coefficient over T)."""
    per_axis = [np.linalg.norm(np.asarray(v, float)) / math.sqrt(3.0) for v in (bias, gm_sigma, white)]
    return math.sqrt(per_axis[0] ** 2 + per_axis[1] ** 2 + per_axis[2] ** 2 / max(T, 1e-3))


def _gyro_sigma(imu_errors, T):
    """Effective 1-sigma (rad/s) of a gyro mean over T s."""
    e = imu_errors
    return _mean_sigma(e.gyro_bias, e.gyro_gm_sigma, e.gyro_arw, T)


def _accel_sigma(imu_errors, T):
    """Effective 1-sigma (m/s^2) of an accelerometer mean over T s."""
    e = imu_errors
    return _mean_sigma(e.accel_bias, e.accel_gm_sigma, e.accel_vrw, T)


def _imu_mean(imu, t0, t1):
    """Mean angular rate and specific force (body) over the IMU intervals inside [t0, t1]."""
    t = np.asarray(imu.t, float)
    dt = 1.0 / float(imu.rate_hz)
    sel = (t - dt >= t0 - 1e-9) & (t <= t1 + 1e-9)
    if sel.sum() < 1:
        return None, None
    T = sel.sum() * dt
    return np.asarray(imu.dtheta_b)[sel].sum(axis=0) / T, np.asarray(imu.dv_b)[sel].sum(axis=0) / T


def _still(imu, t_h, cfg):
    """True when the specific force is steady over ``still_s`` before ``t_h`` (0.1 s means)."""
    t0 = t_h - cfg.still_s
    if t0 < float(getattr(imu, "t0", 0.0)) - 1e-9:
        return False
    n = max(1, int(round(cfg.still_s / 0.1)))
    mags = []
    for k in range(n):
        _, f = _imu_mean(imu, t0 + k * cfg.still_s / n, t0 + (k + 1) * cfg.still_s / n)
        if f is None:
            return False
        mags.append(np.linalg.norm(f))
    return float(np.ptp(mags)) <= 2.0 * cfg.still_force_mps2


def _still_span(imu, t_h, cfg):
    """The longest still stretch before ``t_h`` in whole ``still_s`` steps, at most ``still_max_s``
    (gyro-compassing averages the white noise over it)."""
    T = cfg.still_s
    while T + cfg.still_s <= cfg.still_max_s + 1e-9 and _still(imu, t_h, replace(cfg, still_s=T + cfg.still_s)):
        T += cfg.still_s
    return T


def coordinated_left(vel_l, acc_l, g):
    """Unit vector (local ENU) of the body's left (y) axis of a vehicle in coordinated flight along
    ``vel_l`` with acceleration ``acc_l``: the horizontal left of the velocity, banked about the
    velocity by ``atan(v_h psi_dot / g)`` (right turn: right wing down)."""
    v = np.asarray(vel_l, float)
    up = np.array([0.0, 0.0, 1.0])
    left = np.cross(up, v)
    left /= np.linalg.norm(left)
    vh2 = v[0] ** 2 + v[1] ** 2
    psi_dot = (v[0] * acc_l[1] - v[1] * acc_l[0]) / vh2 if vh2 > 0 else 0.0   # left turn positive
    bank = math.atan2(math.sqrt(vh2) * -psi_dot, g)            # right turn -> positive roll
    fwd = v / np.linalg.norm(v)
    # rotate the left vector about the forward axis by the roll (FLU: +roll takes y towards z)
    return math.cos(bank) * left + math.sin(bank) * np.cross(fwd, left)


def attitude_at(imu, imu_errors, t_h, llh, vel_l, acc_l, sig_acc, cfg):
    """``(q_lb, P_att, method, note)`` at the hand-over time ``t_h`` (module docstring)."""
    lat, _, h = (float(v) for v in llh)
    speed = float(np.linalg.norm(vel_l))
    g_l = np.asarray(gravity_l(lat, h))
    if speed <= cfg.still_speed_mps and _still(imu, t_h, cfg):
        T = _still_span(imu, t_h, cfg)
        w_b, f_b = _imu_mean(imu, t_h - T, t_h)
        s_f = max(_accel_sigma(imu_errors, T), 1e-4) / np.linalg.norm(g_l)
        w_ie = np.asarray(earth_rate_l(lat))
        s_w = max(_gyro_sigma(imu_errors, T), 1e-9) / np.linalg.norm(w_ie)
        C_lb, P = wahba([(-g_l, f_b, s_f), (w_ie, w_b, s_w)])
        sig_head = math.degrees(math.sqrt(P[2, 2]))
        if sig_head > cfg.max_heading_sigma_deg:
            gb = math.degrees(_gyro_sigma(imu_errors, T)) * 3600.0
            raise ConfigError(
                f"start-up: the receiver is still at the hand-over but gyro-compassing gives a heading sigma of "
                f"{sig_head:.0f} deg (gyro sigma {gb:.3g} deg/h over {T:g} s vs the horizontal Earth rate "
                f"{math.degrees(w_ie[1]) * 3600.0:.3g} deg/h): give the heading with --init-att ROLL,PITCH,YAW")
        note = "" if sig_head <= cfg.warn_heading_sigma_deg else (
            f"start-up: gyro-compassing over {T:g} s gives a heading sigma of {sig_head:.0f} deg (the filter "
            "refines it once the vehicle accelerates; --init-att gives it)")
        return np.asarray(dcm_to_quat(C_lb)), P, "levelling+gyro-compass", note
    if speed >= cfg.move_speed_mps:
        w_b, f_b = _imu_mean(imu, t_h - cfg.accel_half_s, t_h + cfg.accel_half_s)
        if f_b is None:
            raise InputFileError("start-up: no IMU data around the hand-over time")
        w_ie = np.asarray(earth_rate_l(lat))
        w_en = np.asarray(transport_rate_l(lat, h, np.asarray(vel_l, float)))
        f_l = acc_l + np.cross(2.0 * w_ie + w_en, vel_l) - g_l
        T = 2.0 * cfg.accel_half_s
        s_f = math.hypot(sig_acc, _accel_sigma(imu_errors, T)) / np.linalg.norm(f_l)
        s_v = math.radians(cfg.sideslip_deg)
        left_l = coordinated_left(vel_l, acc_l, float(np.linalg.norm(g_l)))
        C_lb, P = wahba([(f_l, f_b, s_f), (vel_l, np.array([1.0, 0.0, 0.0]), s_v),
                         (left_l, np.array([0.0, 1.0, 0.0]), math.radians(cfg.bank_sigma_deg))])
        return np.asarray(dcm_to_quat(C_lb)), P, "specific-force+velocity-heading+coordinated-bank", ""
    raise ConfigError(f"start-up: at the hand-over (t = {t_h:.2f} s) the speed is {speed:.2f} m/s: neither still "
                      f"(<= {cfg.still_speed_mps} m/s for {cfg.still_s} s, for levelling) nor moving (>= "
                      f"{cfg.move_speed_mps} m/s, for a velocity heading): give --init-att ROLL,PITCH,YAW")


# ------------------------------------------------------------------ the scalar pass
class _EphemeridesWithIono:
    """Ephemerides (a RINEX :class:`NavData` or a PRN -> Ephemeris dict) seen with the Klobuchar
    coefficients of the engine's model (the scalar receiver reads ``ion_alpha``/``ion_beta``)."""

    def __init__(self, base, alpha, beta):
        self._base = base
        self.ion_alpha = tuple(alpha)
        self.ion_beta = tuple(beta)

    def __getattr__(self, name):
        return getattr(self._base, name)

    def __getitem__(self, key):
        return self._base[key]

    def __contains__(self, key):
        return key in self._base

    def __iter__(self):
        return iter(self._base)

    def __len__(self):
        return len(self._base)


def _scalar_atmosphere(ephemerides, atmosphere):
    """``(iono, tropo, mapping, ephemerides)`` of the scalar pass for the engine's model ``atmosphere``
    (None: no corrections): the ionosphere only with the model's coefficients, which the scalar
    receiver then reads from the ephemerides object."""
    if atmosphere is None:
        return "off", "off", "cosz", ephemerides
    iono = "klobuchar" if atmosphere.iono_active else "off"
    if iono != "off" and ephemerides is not None:
        ephemerides = _EphemeridesWithIono(ephemerides, atmosphere.alpha, atmosphere.beta)
    return iono, atmosphere.tropo, atmosphere.mapping, ephemerides


def scalar_pass(source, ephemerides, prns, start_s, cfg, atmosphere=None):
    """Run the scalar receiver over ``window_s`` from ``start_s``: its :class:`ProcessResult`
    (atmospheric corrections of the engine's model ``atmosphere``, none when None)."""
    from ultratight.receiver.scalar.process_config import NoSignalError, ProcessConfig
    from ultratight.receiver.scalar.receiver import process
    from ultratight.receiver.dsp.tracking_config import TrackingConfig

    avail = source.n_samples / source.fs_hz - start_s
    iono, tropo, mapping, ephemerides = _scalar_atmosphere(ephemerides, atmosphere)
    pc = ProcessConfig(prns=list(prns) if prns else None, start_s=float(start_s), record_epochs=True,
                       duration_s=max(min(cfg.window_s, avail), 1e-3), iono=iono, tropo=tropo,
                       tropo_mapping=mapping,
                       acq_min_cn0_dbhz=cfg.acq_min_cn0_dbhz, acq_noncoherent=cfg.acq_noncoherent,
                       acq_coherent_ms=cfg.acq_coherent_ms, doppler_range_hz=cfg.doppler_range_hz,
                       dynamics=cfg.dynamics, tracking=TrackingConfig.for_dynamics(cfg.dynamics))
    weak = cfg.weak_retry and cfg.dynamics == "normal" and all(
        getattr(cfg, k) in (None, HandoverConfig.__dataclass_fields__[k].default) for k in WEAK_ACQUISITION)
    try:
        res = process(source, pc, ephemerides=ephemerides)
        res.pass_duration_s = pc.duration_s
        if not weak or sum(1 for c in res.channels if c["tracked"]) >= cfg.min_sats:
            return res
    except NoSignalError as exc:
        if not weak:
            raise NoFixError(f"start-up: the scalar pass over {pc.duration_s:g} s from t = {start_s:g} s found no "
                             f"fix: {exc}") from None
    # weak signals: bit sync and the first subframe take longer, the pass gets a longer window
    pc = replace(pc, duration_s=max(min(WEAK_WINDOW_FACTOR * cfg.window_s, avail), 1e-3), **WEAK_ACQUISITION)
    try:
        res = process(source, pc, ephemerides=ephemerides)
    except NoSignalError as exc:
        raise NoFixError(f"start-up: the scalar pass over {pc.duration_s:g} s from t = {start_s:g} s found no "
                         f"fix, also with the weak-signal acquisition: {exc}") from None
    res.pass_duration_s = pc.duration_s
    res.warnings = list(getattr(res, "warnings", []) or []) + [
        "start-up: too few satellites at the default acquisition; the scalar pass ran again with the "
        f"weak-signal acquisition (5 ms x 16, C/N0 floor 25 dB-Hz) over {pc.duration_s:g} s"]
    return res


# the weak-signal acquisition of the start-up's second scalar pass (HandoverConfig.weak_retry)
WEAK_ACQUISITION = {"acq_min_cn0_dbhz": 25.0, "acq_noncoherent": 16, "acq_coherent_ms": 5}
WEAK_WINDOW_FACTOR = 1.5        # ... over this many window_s (30 s by default)


class NoFixError(ConfigError):
    """The scalar start-up pass found no usable fix."""


def _imu_point(imu, pos_e, C_el, q_lb):
    """LLH of the IMU point of an antenna fix ``pos_e`` (ECEF): the lever arm IMU -> antenna
    (``imu.lever_arm_b``, FLU) away along the hand-over attitude ``q_lb``, ``p_imu = p_ant - C_el C_lb l``
    (the rotation term w x l of the velocity is left to the filter: under 0.1 m/s for 1 rad/s at 0.1 m)."""
    lever = getattr(imu, "lever_arm_b", None)
    lever = np.zeros(3) if lever is None else np.asarray(lever, float)
    return np.asarray(ecef_to_llh((pos_e - C_el @ (quat_to_dcm(np.asarray(q_lb, float)) @ lever)).copy()))


def _still_fixes(fixes, k, fs, cfg):
    """A receiver still at the settled fix ``k`` hands over at fix ``j``, the last of the consecutive
    still fixes from ``k`` (speed <= ``still_speed_mps`` or within 3 sigma of the fix's velocity
    noise, at least ``min_sats`` satellites, a next fix for the acceleration) that span at most
    ``fix_avg_s``: fewer when motion or the end of the pass comes first, but at least
    ``fix_avg_min_s``; their mean velocity must be under ``still_speed_mps``. Returns ``(j, mean ECEF position, sigma, the fixes
    used)``, sigma (1-sigma per axis) being the largest ENU scatter of the fixes about their mean
    (their errors are correlated over the loops' time constants: the scatter, not the scatter /
    sqrt(n)); ``(k, None, 0.0, None)`` when the receiver moves at ``k`` or its still fixes span less
    than ``fix_avg_min_s``. The caller averages the fixes' clock biases too: the clock and the
    height err together, and one averaged without the other would leave the engine's first
    pseudorange residuals a common bias.

    Why 10 s: the engine's tracking channels carry the hand-over's code error a long time (their code
    estimate is carrier-aided and averages everything since the start), so the hand-over error decays
    slowly at low C/N0; on the rocket-launch pad at 30 dB-Hz the 3 s mean left the run 3.1 m 3D RMS,
    the 10 s mean 1.3 m (docs/ultratight.md "Start-up without truth")."""
    def still(f):       # within the fix's own velocity noise (3 sigma) of rest
        lim = max(cfg.still_speed_mps, 3.0 * float(f.get("sigma_vel_mps", 0.0)))
        return float(np.linalg.norm(f["vel_e"])) <= lim and f["n_used"] >= cfg.min_sats

    t = [f["sample_index"] / fs for f in fixes]
    if not still(fixes[k]):
        return k, None, 0.0, None
    j_end = None
    for j in range(k, len(fixes) - 1):
        if not still(fixes[j]) or t[j] - t[k] > cfg.fix_avg_s + 1e-9:
            break
        if fixes[j + 1]["n_used"] >= cfg.min_sats:
            j_end = j
    if j_end is None or t[j_end] - t[k] < cfg.fix_avg_min_s - 1e-9:
        return k, None, 0.0, None
    used = fixes[k:j_end + 1]
    if float(np.linalg.norm(np.mean([f["vel_e"] for f in used], axis=0))) > cfg.still_speed_mps:
        return k, None, 0.0, None        # creeping: the fixes' noise hid a steady velocity
    P = np.array([f["pos_e"] for f in used], float)
    mean = P.mean(axis=0)
    llh = ecef_to_llh(mean.copy())
    enu = (P - mean) @ np.asarray(dcm_ecef_from_enu(llh[0], llh[1]))
    return j_end, mean, float(np.max(np.sqrt(np.mean(enu ** 2, axis=0)))), used


def _engine_clock(f, fs, tow0, week0, t_at):
    """The engine's clock bias (m) at ``t_at`` (s of the IF file) from scalar fix ``f``: the IF file's
    receiver time against GPS time, ``c (tow0 + t_fix - t_gps,fix)``, carried along the fix's drift."""
    t_fix = f["sample_index"] / fs
    gps = float(f["gps_tow_s"]) + WEEK_S * ((f["gps_week"] or week0) - week0)
    return C * (tow0 + t_fix - gps) + float(f["clk_drift_mps"]) * (t_at - t_fix)


def pick_fix(fixes, obs_step_s, cfg):
    """Index of the hand-over fix (module docstring) or None."""
    run = 0
    for k, f in enumerate(fixes):
        ok = f["n_used"] >= cfg.min_sats
        cont = k > 0 and abs(f["t_s"] - fixes[k - 1]["t_s"] - obs_step_s) < 0.25 * obs_step_s
        run = (run + 1 if cont else 1) if ok else 0
        nxt = k + 1 < len(fixes) and abs(fixes[k + 1]["t_s"] - f["t_s"] - obs_step_s) < 0.25 * obs_step_s \
            and fixes[k + 1]["n_used"] >= cfg.min_sats
        if run >= cfg.settle_fixes and nxt and k >= 1:
            return k
    return None


def scalar_handover(source, imu, imu_errors, ephemerides, prns, start_s=0.0, cfg=None, overrides=None,
                    atmosphere=None):
    """The hand-over state from the scalar receiver's first fixes (module docstring).

    Returns a dict: ``t_s`` (hand-over time, s since the first IF sample, on an IMU stamp),
    ``llh``, ``vel_l``, ``q_lb``, ``clk_bias_m``, ``clk_drift_mps`` (engine conventions),
    ``sigmas`` (StartupErrors-like, plus ``att_cov_rad2``), ``startup`` (a JSON-able description).
    Raises :class:`NoFixError` when the pass gives no usable fix.
    """
    cfg = cfg or HandoverConfig()
    overrides = overrides or {}
    res = scalar_pass(source, ephemerides, prns, start_s, cfg, atmosphere)
    obs_step = 0.1
    k = pick_fix(res.fixes, obs_step, cfg)
    if k is None:
        raise NoFixError(f"start-up: the scalar pass over {res.pass_duration_s:g} s from t = {start_s:g} s gave "
                         f"{len(res.fixes)} fixes, none of {cfg.settle_fixes} consecutive ones with >= "
                         f"{cfg.min_sats} satellites (tracked: {[c['prn'] for c in res.channels if c['tracked']]}); "
                         "give --init-llh/--init-vel/--init-att or a longer/later window (--start)")
    fs = float(source.fs_hz)
    k, still_pos, still_sig, still_used = _still_fixes(res.fixes, k, fs, cfg)
    fx, fp, fn = res.fixes[k], res.fixes[k - 1], res.fixes[k + 1]
    t_fix = fx["sample_index"] / fs
    dt_imu = 1.0 / float(imu.rate_hz)
    t0_imu = float(getattr(imu, "t0", 0.0))
    t_h = t0_imu + round((t_fix - t0_imu) / dt_imu) * dt_imu
    d = t_h - t_fix
    dtv = fn["sample_index"] / fs - fp["sample_index"] / fs
    acc_e = (np.asarray(fn["vel_e"]) - np.asarray(fp["vel_e"])) / dtv
    pos_e = np.asarray(fx["pos_e"], float) + np.asarray(fx["vel_e"], float) * d + 0.5 * acc_e * d * d
    tro = _tropo_test(still_used or res.fixes[max(0, k - 29):k + 1], atmosphere, cfg)
    shift = np.r_[tro["shift_e"], tro["shift_clk_m"]] if tro["troposphere"] == "absent" else np.zeros(4)
    pos_e = (pos_e if still_pos is None else still_pos) + shift[:3]
    vel_e = np.asarray(fx["vel_e"], float) + acc_e * d
    llh = np.asarray(ecef_to_llh(pos_e.copy()))
    C_el = np.asarray(dcm_ecef_from_enu(llh[0], llh[1]))
    vel_l = C_el.T @ vel_e
    acc_l = C_el.T @ acc_e
    sig_vel = float(fx.get("sigma_vel_mps", 0.1))
    sig_acc = math.sqrt(2.0) * sig_vel / dtv
    tow0, week0 = float(source.start_tow_s), int(source.start_week)
    clk_b = float(np.mean([_engine_clock(f, fs, tow0, week0, t_h) for f in (still_used or [fx])])) + shift[3]
    clk_d = float(fx["clk_drift_mps"])
    state = {"llh": llh, "vel_l": vel_l, "code_phase_chips": channel_code_phases(res, round(t_h * fs), fs)}
    given = sorted(k_ for k_ in ("llh", "vel_l", "q_lb") if k_ in overrides)
    state.update({k_: overrides[k_] for k_ in ("llh", "vel_l") if k_ in overrides})
    sig_pos = max(float(fx["sigma_pos_m"]) / math.sqrt(3.0), still_sig)
    sigmas = {"pos_m": sig_pos if "llh" not in overrides else FLAG_SIGMAS["pos_m"],
              "vel_mps": max(sig_vel / math.sqrt(3.0), 0.01) if "vel_l" not in overrides else FLAG_SIGMAS["vel_mps"],
              "clk_bias_m": float(fx["sigma_pos_m"]), "clk_drift_mps": max(sig_vel, 0.01)}
    note = ""
    if "q_lb" in overrides:
        q, P_att, att_method = overrides["q_lb"], np.eye(3) * math.radians(FLAG_SIGMAS["att_deg"]) ** 2, "init-att"
    else:
        q, P_att, att_method, note = attitude_at(imu, imu_errors, t_h, state["llh"], state["vel_l"], acc_l, sig_acc,
                                              cfg)
    if "llh" not in overrides:
        state["llh"] = _imu_point(imu, pos_e, C_el, q)
    sigmas["att_deg"] = float(math.degrees(math.sqrt(np.max(np.diag(P_att)))))
    sigmas["att_cov_rad2"] = P_att.tolist()
    state.update({"q_lb": np.asarray(q, float), "clk_bias_m": float(clk_b), "clk_drift_mps": clk_d,
                  "sigmas": sigmas})
    eul = np.degrees(dcm_to_euler(quat_to_dcm(state["q_lb"])))
    state["t_s"] = float(t_h)
    state["warnings"] = [w for w in getattr(res, "warnings", None) or () if w.startswith("start-up:")] + (
        [note] if note else []) + ([TROPO_ABSENT.format(**tro)] if tro["troposphere"] == "absent" else [])
    state["troposphere"] = tro
    state["startup"] = {
        "source": STARTUP_SCALAR, "overridden_by_flags": given, "handover_t_s": float(t_h),
        "scalar_pass": {"start_s": float(start_s), "window_s": float(res.pass_duration_s), "fixes": len(res.fixes),
                        "first_fix_s": None if not res.fixes else float(res.fixes[0]["sample_index"] / fs),
                        "fix_t_s": float(t_fix), "n_used": int(fx["n_used"]), "used_prn": list(fx["used_prn"]),
                        "tracked": [c["prn"] for c in res.channels if c["tracked"]],
                        "corrections": dict(getattr(res, "corrections", {}) or {})},
        "attitude_method": att_method, "euler_deg": [float(v) for v in eul],
        "sigmas": {k_: v for k_, v in sigmas.items() if k_ != "att_cov_rad2"},
        "att_sigma_deg": [float(v) for v in np.degrees(np.sqrt(np.diag(P_att)))],
        "config": cfg.as_dict(), "troposphere": tro,
    }
    return state


TROPO_ABSENT = ("start-up: the pseudoranges fit without a troposphere (per-satellite mean residuals {rms_without_m} m "
                "RMS) far better than with the Saastamoinen model ({rms_with_m} m): the recording carries none (a "
                "simulator's?); the troposphere correction is off for this run (--tropo saastamoinen keeps it)")


def _tropo_test(fixes, atmosphere, cfg):
    """The troposphere model test (:mod:`ultratight.receiver.deep.tropo_check`) on the hand-over's
    fixes, when the correction is on by default (``cfg.tropo_check``); else ``not tested``."""
    if not cfg.tropo_check or atmosphere is None or getattr(atmosphere, "tropo", "off") == "off":
        return {"troposphere": "not tested"}
    from ultratight.receiver.deep.tropo_check import troposphere_test

    return troposphere_test(fixes, getattr(atmosphere, "mapping", "cosz"))


def channel_code_phases(res, n0, fs, signal=GPS_L1CA, max_gap_s=0.05):
    """{PRN: code phase (chips) at sample ``n0``} of the scalar channels tracking there (from the
    recorded epochs: the replica's code phase at the epoch start moved on at the carrier-aided code
    rate of the channel's Doppler)."""
    code_length = float(signal.code_length)
    out = {}
    for prn, e in (res.epochs or {}).items():
        s = np.asarray(e.get("sample_index", []), dtype=np.int64)
        if s.size == 0:
            continue
        k = int(np.searchsorted(s, n0, side="right")) - 1
        if k < 0 or (n0 - s[k]) / fs > max_gap_s or int(e["mode"][k]) != MODE_TRACK:
            continue
        rate = signal.code_rate_cps(e["doppler_hz"][k])
        out[int(prn)] = float((e["code_phase_chips"][k] + (n0 - s[k]) / fs * rate) % code_length)
    return out


def flags_state(overrides, t_s=0.0):
    """The start state from all three ``--init-*`` flags (clock zero, module docstring)."""
    st = {"llh": overrides["llh"], "vel_l": overrides["vel_l"], "q_lb": overrides["q_lb"],
          "clk_bias_m": 0.0, "clk_drift_mps": 0.0, "sigmas": dict(FLAG_SIGMAS), "t_s": float(t_s)}
    st["startup"] = {"source": STARTUP_FLAGS, "handover_t_s": float(t_s), "sigmas": dict(FLAG_SIGMAS),
                     "note": "clock bias/drift taken as zero: the sidecar start time is taken as GPS time"}
    return st


# ------------------------------------------------------------------ starting the engine later
class SourceWindow:
    """An IF source seen from sample ``n0`` on (the engine's sample 0 = the file's ``n0``)."""

    def __init__(self, src, n0):
        self._src = src
        self.n0 = int(n0)
        self.n_samples = int(src.n_samples) - self.n0
        if self.n_samples <= 0:
            raise InputFileError(f"{src.path}: the start sample {self.n0} is beyond the file ({src.n_samples} samples)")
        self.duration_s = self.n_samples / float(src.fs_hz)
        tow = float(src.start_tow_s) + self.n0 / float(src.fs_hz)
        week = int(src.start_week)
        while tow >= WEEK_S:
            tow -= WEEK_S
            week += 1
        self.start_tow_s, self.start_week = tow, week

    def __getattr__(self, name):
        return getattr(self._src, name)

    def read(self, start, count):
        return self._src.read(int(start) + self.n0, count)

    def release(self, upto_sample):
        return self._src.release(int(upto_sample) + self.n0)


def imu_window(imu, t_s):
    """The IMU data from time ``t_s`` (an IMU stamp) on, on a time axis starting at 0."""
    t = np.asarray(imu.t, float)
    dt = 1.0 / float(imu.rate_hz)
    k0 = int(np.searchsorted(t, t_s + 0.5 * dt))
    if k0 >= t.size - 1 or abs(t[k0] - dt - t_s) > 1e-6:
        raise InputFileError(f"IMU data do not continue at t = {t_s:.6f} s (the hand-over time)")
    meta = dict(getattr(imu, "meta", None) or {})
    if "start_tow_s" in meta:
        meta["start_tow_s"] = float(meta["start_tow_s"]) + t_s
    meta.pop("config_json", None)
    return ImuData(t=t[k0:] - t_s, dtheta_b=np.asarray(imu.dtheta_b)[k0:], dv_b=np.asarray(imu.dv_b)[k0:],
                   rate_hz=imu.rate_hz, t0=0.0, truth=None, meta=meta,
                   lever_arm_b=np.asarray(getattr(imu, "lever_arm_b", None) if getattr(imu, "lever_arm_b", None)
                                          is not None else np.zeros(3), float).copy())
