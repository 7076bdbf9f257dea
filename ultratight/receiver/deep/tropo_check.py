"""Does the recording carry a troposphere? A model test on the start-up's scalar fixes.

The receiver subtracts the Saastamoinen troposphere from every pseudorange by default, as a real sky
needs. A simulator that puts no troposphere on its signals then gets the model's delays taken away
from pseudoranges that never had them: fitted by position and clock they are absorbed mostly as
height — on a pad at 28.5° N with ten satellites from 8° to 61°, slant delays of 2.8–18.6 m move
the fix 17 m and the clock 16 m, and leave a residual signature of only 1.7 m RMS.  That signature
is what this test looks for, on the fixes the hand-over uses (docs/ultratight.md, "Start-up without
truth"):

* per fix with at least ``MIN_SATS`` satellites used, the post-fit residuals ``r`` as the scalar
  receiver's weighted least squares left them (troposphere subtracted) and the signature ``P d`` the
  model leaves in them when the signal has none: ``d`` the modelled slant delays, ``P = I - H G`` the
  weighted projector onto the residual space, ``G = (H' W H)^-1 H' W`` with the fix's weights
  (``sin^2 E``, floored as the PVT does) and ``H = [-u, 1]``;
* the mean of each over the fixes per satellite (noise averages out, a model error does not), and
  the share ``k`` of the signature the mean residuals hold, ``r = -k P d + noise`` fitted by least
  squares over the satellites, with its 1-sigma from the scatter left (``scale``, ``scale_sigma``;
  for information also ``rms_with_m`` and ``rms_without_m``, the RMS of the mean residuals with and
  without the correction);
* the troposphere is declared **absent** when ``k > 0.3`` and ``k - 3 sigma > 0`` (the residuals hold
  the signature, significantly), **present** when ``k < 0.3`` and ``k + 3 sigma < 1``, **undecided**
  otherwise (too few fixes or satellites, or noise as large as the signature) — then the correction
  stays on.

With a troposphere in the signal the mean residuals are noise and ``k`` is near 0; the 3-sigma
margins keep a noisy or short start-up from switching the correction off.  When absent, the fix moves by the
mean of ``G d`` over the fixes (``shift_e``, ``shift_clk_m``): the solution the scalar receiver would
have given without the correction.
"""

import math

import numpy as np

from ultratight.ins.earth import dcm_ecef_from_enu
from ultratight.receiver.scalar.pvt import SIN_ELEV_FLOOR
from ultratight.signals.atmosphere import saastamoinen_delay_m

MIN_SATS = 6            # two redundant pseudoranges at least
MIN_FIXES = 10          # per satellite
SCALE_SPLIT = 0.3       # the fitted share of the signature that separates absent from present


def _fix_terms(f, mapping_name):
    """``(prns, r, P d, G d)`` of one fix (module docstring), or None with too few satellites."""
    sv = [s for s in f.get("sv") or [] if s.get("used") and math.isfinite(float(s.get("resid_m", math.nan)))]
    if len(sv) < MIN_SATS:
        return None
    lat, lon, h = math.radians(f["llh_deg"][0]), math.radians(f["llh_deg"][1]), float(f["llh_deg"][2])
    el = np.radians([s["elev_deg"] for s in sv])
    az = np.radians([s["azim_deg"] for s in sv])
    u_l = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=1)
    H = np.column_stack([-(u_l @ np.asarray(dcm_ecef_from_enu(lat, lon)).T), np.ones(len(sv))])
    w = np.maximum(np.sin(el), SIN_ELEV_FLOOR) ** 2
    G = np.linalg.solve((H.T * w) @ H, H.T * w)
    d = np.asarray(saastamoinen_delay_m(lat, h, el, mapping_name), float)
    gd = G @ d
    return [int(s["prn"]) for s in sv], np.array([float(s["resid_m"]) for s in sv]), d - H @ gd, gd


def troposphere_test(fixes, mapping_name="cosz"):
    """The model test of the module docstring on ``fixes`` (scalar fixes with ``sv`` entries carrying
    ``resid_m``, ``llh_deg``): a JSON-able dict with ``troposphere`` (absent | present | undecided),
    ``scale`` and ``scale_sigma`` (how much of the signature the residuals hold: 1 = all of it),
    ``rms_with_m``, ``rms_without_m``, ``fixes``, ``satellites`` and, when absent, ``shift_e`` (ECEF,
    m) and ``shift_clk_m`` (the fix without the correction minus the fix with it)."""
    acc, shifts = {}, []
    for f in fixes:
        t = _fix_terms(f, mapping_name)
        if t is None:
            continue
        prns, r, sig, gd = t
        shifts.append(gd)
        for p, a, b in zip(prns, r, sig):
            s = acc.setdefault(p, [0.0, 0.0, 0])
            s[0] += a
            s[1] += b
            s[2] += 1
    means = np.array([(s[0] / s[2], s[1] / s[2]) for s in acc.values() if s[2] >= MIN_FIXES]).reshape(-1, 2)
    out = {"troposphere": "undecided", "fixes": len(shifts), "satellites": int(means.shape[0])}
    if means.shape[0] < MIN_SATS or not np.any(means[:, 1]):
        return out
    r, sig = means[:, 0], means[:, 1]
    k = -float(r @ sig) / float(sig @ sig)                  # r = -k P d + noise
    noise = float(np.sqrt(np.sum((r + k * sig) ** 2) / max(r.size - 1, 1)))
    k_sigma = noise / float(np.sqrt(sig @ sig))
    out.update(scale=round(k, 3), scale_sigma=round(k_sigma, 3), rms_with_m=round(float(np.sqrt(np.mean(r ** 2))), 3),
               rms_without_m=round(float(np.sqrt(np.mean((r + sig) ** 2))), 3))
    if k > SCALE_SPLIT and k - 3.0 * k_sigma > 0.0:
        mean_shift = np.mean(shifts, axis=0)
        out.update(troposphere="absent", shift_e=mean_shift[:3].tolist(), shift_clk_m=float(mean_shift[3]))
    elif k < SCALE_SPLIT and k + 3.0 * k_sigma < 1.0:
        out["troposphere"] = "present"
    return out
