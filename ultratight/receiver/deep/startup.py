"""Assisted hot start of the ultra-tight receiver.

The receiver starts from an *initial INS state with errors*, not from truth:

* position, velocity, attitude and receiver clock bias/drift are the scenario truth at
  t = 0 plus zero-mean Gaussian errors drawn from the run's ``numpy.random.Generator``
  with the standard deviations of :class:`StartupErrors` (documented defaults below, a
  hot start from a preceding precise solution);
* each channel's initial code phase and Doppler are *predicted* from that perturbed state
  and the broadcast ephemeris through :func:`ultratight.signals.geometry.light_time`
  (no acquisition, no truth);
* navigation-data wipe-off uses the LNAV bits re-encoded from the same ephemeris by
  :func:`ultratight.signals.lnav.nav_bits` ("assisted bits"); the mode actually used is
  recorded (``"assisted-bits"`` or ``"none"`` when the ephemeris cannot be encoded).

Errors are 1-sigma per axis (position in ENU, velocity in ENU, attitude roll/pitch/yaw).
"""

from dataclasses import asdict, dataclass

import numpy as np

from ultratight.constants import C
from ultratight.ins.attitude import quat_mult, quat_normalize, rotvec_to_quat
from ultratight.ins.earth import llh_increment_scale, radii
from ultratight.signals.geometry import light_time
from ultratight.signals.lnav import nav_bits
from ultratight.signals.signal import GPS_L1CA

WIPEOFF_ASSISTED = "assisted-bits"
WIPEOFF_NONE = "none"


@dataclass
class StartupErrors:
    """1-sigma initial errors of the assisted hot start (see module docstring)."""

    pos_m: float = 0.5           # per ENU axis
    vel_mps: float = 0.02        # per ENU axis
    att_deg: float = 0.01        # roll, pitch, yaw
    clk_bias_m: float = 0.5
    clk_drift_mps: float = 0.02

    def as_dict(self):
        return asdict(self)


def perturb_state(truth0, errors, rng):
    """Initial INS/clock state = truth + errors (the hot start never sees the truth itself).

    ``truth0``: dict with ``llh`` (lat, lon rad, h m), ``vel_l`` (ENU m/s), ``q_lb``
    (body->ENU, scalar first), ``clk_bias_m``, ``clk_drift_mps``.  Position errors are drawn
    in ENU metres, attitude errors as a small rotation of the local frame
    (``C_lb,est = (I - [phi x]) C_lb``, the convention of ``ultratight.ins.error_model``).
    Returns a dict with the same keys plus ``err_pos_l``, ``err_vel_l``, ``err_att``,
    ``err_clk`` (the drawn errors, estimate minus truth) and ``sigmas``.
    """
    d_pos_l = rng.normal(0.0, errors.pos_m, 3)
    d_vel_l = rng.normal(0.0, errors.vel_mps, 3)
    d_att = rng.normal(0.0, np.deg2rad(errors.att_deg), 3)
    d_b = rng.normal(0.0, errors.clk_bias_m)
    d_d = rng.normal(0.0, errors.clk_drift_mps)
    lat, lon, h = (float(v) for v in truth0["llh"])
    rm, rn = radii(lat)
    s_n, s_e, s_u = llh_increment_scale(lat, h, rm, rn)
    llh = np.array([lat + d_pos_l[1] / s_n, lon + d_pos_l[0] / s_e, h + d_pos_l[2] / s_u])
    q_true = np.asarray(truth0["q_lb"], dtype=float)
    q_est = np.asarray(quat_normalize(quat_mult(rotvec_to_quat(-d_att), q_true)))
    return {
        "llh": llh,
        "vel_l": np.asarray(truth0["vel_l"], dtype=float) + d_vel_l,
        "q_lb": q_est,
        "clk_bias_m": float(truth0.get("clk_bias_m", 0.0)) + d_b,
        "clk_drift_mps": float(truth0.get("clk_drift_mps", 0.0)) + d_d,
        "err_pos_l": d_pos_l, "err_vel_l": d_vel_l, "err_att": d_att, "err_clk": np.array([d_b, d_d]),
        "sigmas": errors.as_dict(),
    }


def predict_channels(ephs, prns, week, tow_rx_s, pos_e, vel_e, clk_bias_m, clk_drift_mps, signal=GPS_L1CA):
    """Predicted code phase (chips), Doppler (Hz) and transmit time for each PRN.

    ``tow_rx_s`` is the *receiver-clock* time of the sample the prediction refers to; the
    true reception time used in the light-time solution is ``tow_rx_s - clk_bias_m / c``.
    Returns dict of (n_ch,) arrays: code_phase_chips, doppler_hz, t_tx_tow, code_rate_cps.
    """
    t_true = float(tow_rx_s) - float(clk_bias_m) / C
    n = len(prns)
    cp = np.empty(n)
    dop = np.empty(n)
    ttx = np.empty(n)
    for i, prn in enumerate(prns):
        r = light_time(ephs[prn], pos_e, vel_e, week, np.array([t_true]), clk_bias_m, clk_drift_mps)
        cp[i] = r["code_phase_chips"][0]
        dop[i] = r["doppler_hz"][0]
        ttx[i] = r["t_tx_tow"][0]
    return {"code_phase_chips": cp, "doppler_hz": dop, "t_tx_tow": ttx,
            "code_rate_cps": signal.code_rate_cps(dop)}


class BitWipeoff:
    """Assisted navigation-data bits per channel, indexed by the transmit-time millisecond count.

    ``bits[ch]`` holds ±1 bits starting at transmit time ``t0_ms[ch]`` ms (a multiple of the
    signal's data-bit period, ``signal.bit_period_s``: 20 ms for GPS L1 C/A); :meth:`signs` gives
    the bit of the code period that *starts* at transmit millisecond ``ms`` (int64 array).
    """

    def __init__(self, ephs, prns, week, tow_start_s, duration_s, signal=GPS_L1CA):
        self.mode = WIPEOFF_ASSISTED
        self.signal = signal
        t_bit = signal.bit_period_s
        n_bits = int(np.ceil(duration_s / t_bit)) + 20
        t0 = np.floor(tow_start_s / t_bit) * t_bit - 10 * t_bit
        self.t0_ms = np.full(len(prns), int(round(t0 * 1000.0)), dtype=np.int64)
        self.bits = np.ones((len(prns), n_bits), dtype=np.int8)
        try:
            for i, prn in enumerate(prns):
                self.bits[i] = np.asarray(nav_bits(ephs[prn], week, t0, n_bits), dtype=np.int8)
        except Exception as exc:  # noqa: BLE001 - recorded, tracking then runs without wipe-off
            self.mode = WIPEOFF_NONE
            self.error = f"{type(exc).__name__}: {exc}"
            self.bits[:] = 1
        self._rows = np.arange(len(prns))

    def signs(self, ms):
        k = self.signal.bit_index(np.asarray(ms, dtype=np.int64), self.t0_ms)
        k = np.clip(k, 0, self.bits.shape[1] - 1)
        return self.bits[self._rows, k].astype(np.float64)


def first_period_ms(t_tx_tow, code_phase_chips, signal=GPS_L1CA):
    """Transmit-time count of code periods (milliseconds for GPS L1 C/A) of the first *full* code
    period after the start.

    The correlator aligns each channel to its next code-period start, whose transmit
    time is ``floor(t_tx / T) + 1`` periods (T = ``signal.code_period_s``; consistent with the
    predicted code phase).
    """
    per_s = 1.0 / signal.code_period_s
    ms = np.floor(np.asarray(t_tx_tow) * per_s).astype(np.int64)
    # guard the rounding at a period boundary: the code phase says how far into it we are
    frac = np.asarray(code_phase_chips) / signal.code_length
    ms_fix = np.round(np.asarray(t_tx_tow) * per_s - frac).astype(np.int64)
    return np.where(np.abs(ms - ms_fix) <= 1, ms_fix, ms) + 1
