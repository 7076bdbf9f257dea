"""Single-point positioning on recorded raw observations (``ultratight spp``).

:func:`run_spp` takes GPS L1 C/A observations (:class:`ultratight.signals.observations.RawEpochs`,
from RINEX or u-blox RXM-RAWX) and broadcast ephemerides (:class:`ultratight.signals.rinex.NavData`,
from a RINEX navigation file or decoded RXM-SFRBX subframes) and solves every epoch with the
receiver's PVT (:func:`ultratight.receiver.scalar.pvt.solve_pvt`: WLS with elevation weights,
elevation mask, RAIM exclusion, Sagnac rotation, and the atmosphere of
:class:`ultratight.signals.atmosphere.AtmosphereModel`: broadcast Klobuchar ionosphere when the
coefficients are known, Saastamoinen troposphere).

Rows whose pseudorange is a dual-frequency ionosphere-free combination
(``RawEpochs.iono_free_rows``, e.g. a u-blox log with L2C read by :func:`ultratight.signals.ubx.read_ubx`)
get no ionosphere model and their a-priori σ multiplied by
:func:`ultratight.signals.observations.iono_free_noise_factor` (≈ 3 for L1/L2); the fixes and the
summary's ``corrections`` say which signals and ionosphere handling were used.

Per row the satellite states come from :func:`ultratight.signals.obs_geometry.sat_states`; the
pseudorange corrected for the satellite clock is ``ρ + clk_m`` and the range rate ``−λ·D +
drift_mps`` (velocity only when at least four Doppler values are present).  The fixes are dicts with
the keys of the scalar receiver's fixes, so :func:`ultratight.receiver.io.outputs.write_csv` writes
them with the same columns as ``ultratight process --csv``; ``t_s`` counts seconds from the first
observation epoch and ``gps_week``/``gps_tow_s`` give the GPS time of the fix (receive time minus
the estimated receiver clock bias).
"""

import math
from dataclasses import dataclass, field

import numpy as np

from ultratight.constants import C
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh
from ultratight.receiver.scalar.pvt import atmosphere_delays, solve_pvt
from ultratight.signals.atmosphere import AtmosphereModel
from ultratight.signals.obs_geometry import sat_states
from ultratight.signals.observations import (
    SECONDS_PER_WEEK,
    iono_free_noise_factor,
    week_tow,
)
from ultratight.signals.signal import GPS_L1CA

SIGMA_PR_M = 3.0
SIGMA_RR_MPS = 0.1


@dataclass
class SppConfig:
    mask_deg: float = 5.0
    iono: str = "klobuchar"          # "klobuchar" | "off"
    tropo: str = "saastamoinen"      # "saastamoinen" | "off"
    raim: bool = True
    sigma_pr_m: float = SIGMA_PR_M
    sigma_rr_mps: float = SIGMA_RR_MPS


@dataclass
class SppResult:
    fixes: list                      # fix dicts (module doc)
    n_epochs: int
    n_epochs_with_states: int        # epochs with at least one satellite state
    corrections: dict
    warnings: list = field(default_factory=list)

    def positions(self):
        return np.array([f["pos_e"] for f in self.fixes]).reshape(-1, 3)


def atmosphere_for(nav, cfg):
    """(AtmosphereModel, warnings): Klobuchar needs the navigation data's alpha/beta."""
    warn = []
    alpha, beta = getattr(nav, "ion_alpha", None), getattr(nav, "ion_beta", None)
    if cfg.iono == "klobuchar" and (alpha is None or beta is None):
        warn.append("no ionospheric coefficients (alpha/beta) in the navigation data: ionosphere not corrected")
    model = AtmosphereModel(cfg.iono, alpha, beta, cfg.tropo, "cosz")
    return model, warn


def run_spp(raw, nav, cfg=None):
    """Solve every epoch of ``raw`` with ``nav`` (module doc); returns :class:`SppResult`."""
    cfg = cfg or SppConfig()
    states = sat_states(raw, nav)
    combined = raw.iono_free_rows()
    model, warn = atmosphere_for(nav, cfg)
    if combined.all() and raw.prn.size:
        warn = [w for w in warn if "ionospheric coefficients" not in w]       # none needed
    factor = iono_free_noise_factor(raw.iono_free_f2_hz) if raw.iono_free_f2_hz is not None else np.ones(raw.prn.size)
    prc = np.where(states.valid, raw.pr_m + states.clk_m, np.nan)
    rr = np.where(states.valid, -GPS_L1CA.wavelength_m * raw.doppler_hz + states.drift_mps, np.nan)
    fixes, last_x, n_states = [], None, 0
    t0 = float(raw.t[0]) if raw.n_epochs else 0.0
    for k in range(raw.n_epochs):
        sl = raw.epoch(k)
        ok = states.valid[sl]
        if ok.any():
            n_states += 1
        if ok.sum() < 4:
            continue
        _, tow = week_tow(raw.t[k])
        sol = solve_pvt(states.pos_e[sl][ok], prc[sl][ok], states.vel_e[sl][ok], rr[sl][ok],
                        sigma_pr_m=cfg.sigma_pr_m * factor[sl][ok], sigma_rr_mps=cfg.sigma_rr_mps, x0=last_x,
                        mask_deg=cfg.mask_deg, raim=cfg.raim,
                        delays=_delays(model, float(tow), ~combined[sl][ok]) if model.active else None)
        if not sol.valid:
            continue
        last_x = np.r_[sol.pos_e, sol.clk_bias_m]
        fixes.append(_fix(raw, k, t0, sol, raw.prn[sl][ok], raw.cn0_dbhz[sl][ok], model, cfg,
                          bool(combined[sl][ok].any())))
    if n_states and not fixes:
        warn.append(f"no fix: no epoch has a solution with four satellites (valid ephemeris and pseudorange) "
                    f"above the {cfg.mask_deg:g} deg mask")
    corr = {**model.describe(), "mask_deg": cfg.mask_deg, "raim": cfg.raim,
            "signals": str(raw.meta.get("signal", "GPS L1 C/A")), "ionosphere": _iono_line(combined, model)}
    return SppResult(fixes, raw.n_epochs, n_states, corr, warn)


def _iono_line(combined, model):
    n_if, n = int(combined.sum()), int(combined.size)
    single = "Klobuchar (broadcast)" if model.iono_active else "not corrected"
    if n_if == 0:
        return f"single frequency, {single}"
    if n_if == n:
        return "ionosphere-free dual-frequency combination (no model)"
    return f"ionosphere-free combination on {n_if} of {n} rows; the others {single}"


def _delays(model, tow, single):
    """:func:`atmosphere_delays` with the ionosphere only on the rows where ``single`` (single frequency)."""
    parts = {}
    f = atmosphere_delays(model, tow, parts)

    def g(rx_pos_e, sat_pos_e):
        total = f(rx_pos_e, sat_pos_e)
        return total - np.where(single, 0.0, np.asarray(parts["iono_m"], dtype=float))
    return g


def _fix(raw, k, t0, sol, prns, cn0, model, cfg, combined=False):
    t_gps = float(raw.t[k]) - sol.clk_bias_m / C
    week = math.floor(t_gps / SECONDS_PER_WEEK)
    vel = sol.vel_e if sol.vel_e is not None else np.full(3, np.nan)
    sv = [{"prn": int(p), "elev_deg": math.degrees(e), "cn0_dbhz": float(c), "used": bool(u)}
          for p, e, c, u in zip(prns, sol.elev_rad, cn0, sol.used)]
    return {"t_s": float(raw.t[k]) - t0, "gps_week": week, "gps_tow_s": t_gps - week * SECONDS_PER_WEEK,
            "pos_e": sol.pos_e.copy(), "vel_e": np.asarray(vel, dtype=float),
            "llh_deg": [math.degrees(sol.llh[0]), math.degrees(sol.llh[1]), float(sol.llh[2])],
            "clk_bias_m": sol.clk_bias_m, "clk_drift_mps": sol.clk_drift_mps,
            "pdop": sol.dops.get("pdop", float("nan")), "gdop": sol.dops.get("gdop", float("nan")),
            "hdop": sol.dops.get("hdop", float("nan")), "vdop": sol.dops.get("vdop", float("nan")),
            "n_used": int(sol.used.sum()), "raim_ok": bool(sol.raim_ok),
            "excluded_prn": [int(prns[j]) for j in sol.excluded],
            "used_prn": [int(p) for p in prns[sol.used]],
            "iono": "iono-free" if combined else "klobuchar" if model.iono_active else "off", "tropo": cfg.tropo,
            "sv": sv}


def enu_errors(positions, reference):
    """(n, 3) east/north/up differences (m) of ECEF ``positions`` from the ECEF ``reference``."""
    ref = np.asarray(reference, dtype=float)
    llh = ecef_to_llh(ref.copy())
    return (np.asarray(positions, dtype=float) - ref) @ dcm_ecef_from_enu(llh[0], llh[1])


def summary(res, reference=None, reference_source=None):
    """The ``--json`` summary of a run: epochs, fixes, mean position, DOPs and, with a reference
    ECEF position, the errors' RMS (3D, horizontal, per ENU axis) and mean."""
    pos = res.positions()
    out = {"epochs": res.n_epochs, "epochs_with_ephemeris": res.n_epochs_with_states, "fixes": len(res.fixes),
           "corrections": res.corrections, "warnings": list(res.warnings)}
    if not res.fixes:
        return {**out, "mean_position_ecef_m": None, "mean_position_llh": None, "dop": None, "reference": None}
    mean = pos.mean(axis=0)
    llh = ecef_to_llh(mean.copy())
    out["mean_position_ecef_m"] = [float(v) for v in mean]
    out["mean_position_llh"] = [math.degrees(llh[0]), math.degrees(llh[1]), float(llh[2])]
    out["first_fix_gps"] = [res.fixes[0]["gps_week"], res.fixes[0]["gps_tow_s"]]
    out["last_fix_gps"] = [res.fixes[-1]["gps_week"], res.fixes[-1]["gps_tow_s"]]
    out["mean_satellites_used"] = float(np.mean([f["n_used"] for f in res.fixes]))
    out["raim_exclusions"] = int(sum(len(f["excluded_prn"]) for f in res.fixes))
    out["dop"] = {k: float(np.nanmean([f[k] for f in res.fixes])) for k in ("gdop", "pdop", "hdop", "vdop")}
    out["reference"] = None
    if reference is not None:
        d = enu_errors(pos, reference)
        out["reference"] = {
            "ecef_m": [float(v) for v in reference], "source": reference_source,
            "rms_3d_m": float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))),
            "rms_horizontal_m": float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)))),
            "rms_enu_m": [float(v) for v in np.sqrt(np.mean(d ** 2, axis=0))],
            "mean_enu_m": [float(v) for v in d.mean(axis=0)],
            "max_3d_m": float(np.max(np.linalg.norm(d, axis=1)))}
    return out
