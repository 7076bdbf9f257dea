"""The all-in-view search plan of the scalar receiver: which PRNs without a channel to search, and
where in Doppler.

Once the receiver has a position fix and an ephemeris of a PRN (from ``--ephemeris`` or decoded
on a channel), the PRN is *predicted*: its elevation at the receiver
(:func:`ultratight.signals.geometry.visible_prns`, the generator's visibility test: elevation
>= the PVT mask, line of sight clear of the ellipsoid, healthy ephemeris) decides whether it is
searched at all, and its Doppler (:func:`ultratight.signals.geometry.light_time`: the satellite
velocity and the receiver velocity of the fix projected on the line of sight, the satellite clock
drift and the receiver clock drift of the fix) centres a narrow search window.  PRNs without an
ephemeris (or every PRN before the first fix) have no prediction and keep the coarse full search,
at a lower rate (:class:`ultratight.receiver.scalar.process_config.ProcessConfig`
``coarse_search_every_s``).

Window half-width (:func:`predicted_window_hz`)::

    W = PREDICTED_WINDOW_HZ + (3 sigma_v + a_max * age) / lambda         (capped at --doppler-range)

``PREDICTED_WINDOW_HZ`` = 500 Hz is half a bin of the search's first stage (its bins are 667 Hz
apart at 1 ms coherent: the window always holds the bin nearest to a signal within 167 Hz of the
prediction) plus 167 Hz for what the fix does not give: the receiver clock drift moving between the
fix and the search (a TCXO's 0.1 ppm is 158 Hz at L1) and the Doppler of a position error (at most
|v_sat| / range ≈ 3.9 km/s / 20 200 km = 1.9e-4 m/s per metre: 1 Hz per km).  ``sigma_v`` is the
fix's velocity standard deviation (``sigma_vel_mps``) and ``age`` the time since the fix, with
``a_max`` = ``ACCEL_MAX_MPS2`` (10 m/s², a vehicle braking hard; 52.5 Hz per second of age).  With
the 10 Hz fixes of a static or slow receiver the window is ±500–510 Hz: one or two first-stage bins
instead of the 30 of the ±10 kHz cold search; the second stage (10 ms coherent, ±400 Hz around the
first stage's Doppler) runs only for the PRNs the first stage detects.
"""

import math
from dataclasses import dataclass, field

import numpy as np

from ultratight.signals.geometry import light_time, visible_prns

PREDICTED_WINDOW_HZ = 500.0       # base half-width of the predicted search window
ACCEL_MAX_MPS2 = 10.0             # line-of-sight acceleration bound since the fix
SIGMA_K = 3.0                     # sigmas of the fix's velocity in the window


@dataclass
class SearchPlan:
    """One periodic search: ``predicted`` {prn: predicted Doppler, Hz} searched in ±``window_hz``;
    ``below_mask`` PRNs predicted below the mask (not searched); ``unpredicted`` PRNs without a
    prediction (no fix yet, or no ephemeris: the coarse search's)."""
    predicted: dict = field(default_factory=dict)
    window_hz: float = 0.0
    below_mask: list = field(default_factory=list)
    unpredicted: list = field(default_factory=list)


def predicted_window_hz(fix, age_s, wavelength_m, doppler_range_hz):
    """Half-width (Hz) of the predicted search window (module docstring), at most ``doppler_range_hz``."""
    sig_v = float(fix.get("sigma_vel_mps", math.nan))
    if not math.isfinite(sig_v):
        sig_v = 0.0
    w = PREDICTED_WINDOW_HZ + (SIGMA_K * sig_v + ACCEL_MAX_MPS2 * max(0.0, age_s)) / wavelength_m
    return min(w, float(doppler_range_hz))


def plan_search(prns, ephemeris_of, fix, age_s, mask_deg, wavelength_m, doppler_range_hz):
    """The :class:`SearchPlan` of the PRNs ``prns`` (those without a running channel).

    ``ephemeris_of(prn)``: the PRN's Ephemeris or None; ``fix``: the receiver's latest PVT fix (dict
    with ``pos_e``, ``vel_e``, ``clk_drift_mps``, ``gps_week``, ``gps_tow_s``, ``sigma_vel_mps``) or
    None; ``age_s``: signal time from the fix to the search.  Elevation and Doppler are evaluated at
    the fix's GPS time plus ``age_s``, at the fix's position."""
    prns = [int(p) for p in prns]
    if fix is None or fix.get("gps_week") is None:
        return SearchPlan(unpredicted=prns)
    ephs = {p: ephemeris_of(p) for p in prns}
    known = {p: e for p, e in ephs.items() if e is not None and e.healthy}
    if not known:
        return SearchPlan(unpredicted=prns)
    week, tow = int(fix["gps_week"]), float(fix["gps_tow_s"]) + max(0.0, age_s)
    pos = np.asarray(fix["pos_e"], dtype=np.float64)
    vel = np.asarray(fix["vel_e"], dtype=np.float64)
    drift = float(fix.get("clk_drift_mps", 0.0))
    above = set(visible_prns(known, pos, week, tow, mask_deg))
    plan = SearchPlan(window_hz=predicted_window_hz(fix, age_s, wavelength_m, doppler_range_hz))
    for p in prns:
        if p not in known:
            plan.unpredicted.append(p)
        elif p not in above:
            plan.below_mask.append(p)
        else:
            lt = light_time(known[p], pos, vel, week, np.array([tow]), rx_clk_drift_mps=drift)
            plan.predicted[p] = float(lt["range_rate_mps"][0]) / -wavelength_m
    return plan
