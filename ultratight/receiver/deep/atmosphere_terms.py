"""Ionospheric and tropospheric delays in the double loop's predictions (docs/ultratight.md, "Atmosphere").

The outer loop (:class:`ultratight.receiver.deep.outer_loop.OuterLoop`) predicts each channel's code
phase, pseudorange and Doppler from the corrected SINS and the ephemeris; those predictions are both
the NCO aiding and the reference the tracking estimates are differenced against (the tight filter's
pseudorange and pseudorange-rate residuals).  :class:`PredictionDelays` adds the L1 delays of an
:class:`ultratight.signals.atmosphere.AtmosphereModel` (broadcast Klobuchar ionosphere ``I``,
Saastamoinen troposphere ``T``; the scalar receiver's model) to them:

* code (pseudorange, transmit time, code phase): delayed by ``I + T``;
* carrier (Doppler aiding, pseudorange-rate reference): the phase is *advanced* by ``I`` and delayed
  by ``T`` (first-order ionosphere), so the carrier range rate gets ``d(T - I)/dt``; the code rate
  gets ``d(T + I)/dt``.

The delays change slowly (the geometry over seconds, the troposphere with the height): they are
evaluated at the SINS antenna position and the satellites' elevation/azimuth at each tight-filter
update (:meth:`PredictionDelays.refresh`, 10 Hz by default) and carried linearly in time between
refreshes, the rates from the delays a refresh interval ahead (antenna moved along the SINS velocity,
satellites along their orbits).  A delay that
the model switches off inside that interval (the standard atmosphere's height limit, a satellite at
the horizon) gets no rate.
"""

import math

import numpy as np

from ultratight.constants import C
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh
from ultratight.signals.atmosphere import AtmosphereModel
from ultratight.signals.lnav_message import quantise_iono

REFRESH_S = 0.1          # forward-difference step of the delay rates (one tight-filter interval)


class PredictionDelays:
    """Per-channel atmospheric delays of the outer loop's predictions (module docstring)."""

    def __init__(self, model, n_ch, signal, source=None):
        self.model = model
        self.signal = signal
        self.source = source
        self.t_ref = None
        self.code_m = np.zeros(n_ch)          # I + T at t_ref
        self.code_rate = np.zeros(n_ch)       # d(I + T)/dt
        self.carr_rate = np.zeros(n_ch)       # d(T - I)/dt
        self.iono_m = np.zeros(n_ch)
        self.tropo_m = np.zeros(n_ch)
        self.n_refresh = 0

    def _delays(self, pos_e, los_e, tow_s):
        llh = np.asarray(ecef_to_llh(np.asarray(pos_e, dtype=float).copy()))
        enu = np.asarray(los_e, dtype=float) @ np.asarray(dcm_ecef_from_enu(llh[0], llh[1]))
        el = np.arcsin(np.clip(enu[:, 2], -1.0, 1.0))
        az = np.arctan2(enu[:, 0], enu[:, 1])
        with np.errstate(invalid="ignore"):   # the standard atmosphere above its domain: NaN, then 0
            return self.model.delays_m(llh[0], llh[1], llh[2], el, az, tow_s)

    def refresh(self, t, tow_true_s, pos_e, vel_e, los_e, los_next_e):
        """The delays at receiver time ``t`` (s since the first sample; GPS time ``tow_true_s``) for the
        antenna at ``pos_e`` moving with ``vel_e``, the unit lines of sight ``los_e`` (n_ch, 3) and
        ``los_next_e`` those :data:`REFRESH_S` later at ``pos_e + vel_e REFRESH_S`` (the satellites'
        motion moves a low elevation's tropospheric delay by up to ~0.05 m/s)."""
        i0, t0 = self._delays(pos_e, los_e, tow_true_s)
        p1 = np.asarray(pos_e, dtype=float) + np.asarray(vel_e, dtype=float) * REFRESH_S
        i1, t1 = self._delays(p1, los_next_e, tow_true_s + REFRESH_S)
        # a delay the model switches on or off within the step (height limit, horizon): no rate
        di = np.where((i0 == 0.0) != (i1 == 0.0), 0.0, (i1 - i0) / REFRESH_S)
        dt = np.where((t0 == 0.0) != (t1 == 0.0), 0.0, (t1 - t0) / REFRESH_S)
        self.iono_m, self.tropo_m = i0, t0
        self.code_m = i0 + t0
        self.code_rate = dt + di
        self.carr_rate = dt - di
        self.t_ref = float(t)
        self.n_refresh += 1

    def apply(self, pr, t):
        """Add the delays to an outer-loop prediction dict ``pr`` (MultiLightTime.solve keys) at
        receiver time ``t``; returns ``pr``."""
        sgl = self.signal
        d = self.code_m + self.code_rate * (t - self.t_ref)
        rr_geo = pr["range_rate_mps"]
        pr["pseudorange_m"] = pr["pseudorange_m"] + d
        pr["t_tx_tow"] = pr["t_tx_tow"] - d / C
        pr["code_phase_chips"] = np.mod(pr["code_phase_chips"] - d / sgl.chip_m, float(sgl.code_length))
        pr["range_rate_mps"] = rr_geo + self.carr_rate
        pr["doppler_hz"] = -pr["range_rate_mps"] / sgl.wavelength_m
        pr["code_rate_cps"] = sgl.code_rate_cps(-(rr_geo + self.code_rate) / sgl.wavelength_m)
        return pr

    def describe(self):
        """The model as the scalar receiver records it, plus where alpha/beta came from and the
        refresh of the delays."""
        return {**self.model.describe(), "iono_source": self.source if self.model.iono_active else None,
                "iono_option": self.model.iono, "tropo_option": self.model.tropo,
                "refresh": "every tight-filter update, linear in time between (rates over "
                           f"{REFRESH_S:g} s along the SINS velocity)",
                "n_refresh": self.n_refresh,
                "last_iono_m": [round(float(v), 4) for v in self.iono_m],
                "last_tropo_m": [round(float(v), 4) for v in self.tropo_m]}


def inactive_description(model=None):
    """The ``atmosphere`` record of a run whose predictions carry no atmospheric terms (no model, or
    one with both parts off / the ionosphere without coefficients)."""
    m = model if model is not None else AtmosphereModel()
    return {**m.describe(), "iono_source": None, "iono_option": m.iono, "tropo_option": m.tropo}


def receiver_model(iono="klobuchar", tropo="saastamoinen", alpha=None, beta=None, mapping_name="cosz"):
    """The receiver's :class:`AtmosphereModel` (``iono``/``tropo`` as the scalar receiver's
    ``--iono``/``--tropo``; the ionosphere is active only with broadcast ``alpha``/``beta``)."""
    return AtmosphereModel(iono=iono, alpha=alpha, beta=beta, tropo=tropo, mapping_name=mapping_name)


def broadcast_of_generator(gen_cfg):
    """``(alpha, beta)`` a receiver decodes from a generated signal's subframe 4 page 18 (the
    scenario's ``[atmosphere]`` table with ``broadcast = true``, quantised as transmitted), or
    ``(None, None)`` when the signal carries none.  Nothing else of the table (the generator's
    ``iono_scale``, its mapping function) is known to a receiver."""
    atm = (gen_cfg or {}).get("atmosphere") if isinstance(gen_cfg, dict) else None
    if not isinstance(atm, dict) or not atm.get("broadcast", False):
        return None, None
    a, b = atm.get("alpha"), atm.get("beta")
    if not (isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and len(a) == 4 and len(b) == 4):
        return None, None
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in list(a) + list(b)):
        return None, None
    qa, qb = quantise_iono(tuple(float(v) for v in a), tuple(float(v) for v in b))
    return qa, qb


def scenario_model(cfg):
    """The receiver's model for a scenario run (``ultratight scenario``): None when the scenario's
    generator applies no atmosphere (no ``[atmosphere]`` table, or both parts off); otherwise the
    scalar receiver's models for the parts the generator applied, the ionosphere with the broadcast
    coefficients only (:func:`broadcast_of_generator`) and the receiver's own mapping function."""
    atm = cfg.get("atmosphere") if isinstance(cfg, dict) else None
    if not isinstance(atm, dict) or (atm.get("iono", "off") == "off" and atm.get("tropo", "off") == "off"):
        return None
    alpha, beta = broadcast_of_generator(cfg)
    return receiver_model(iono="klobuchar" if atm.get("iono", "off") != "off" else "off",
                          tropo="saastamoinen" if atm.get("tropo", "off") != "off" else "off",
                          alpha=alpha, beta=beta)
