"""The start-up's troposphere model test (receiver.deep.tropo_check) on fixes of the project's own PVT
(receiver.scalar.pvt.solve_pvt) from pseudoranges built here: with the Saastamoinen delays in them it
says present, without them absent, and its shift moves a corrected fix onto the fix solve_pvt gives
without the correction; a handful of satellites or fixes says undecided."""

import math

import numpy as np
import pytest

from ultratight.ins.earth import ecef_to_llh, elev_azim, llh_to_ecef
from ultratight.receiver.deep.tropo_check import troposphere_test
from ultratight.receiver.scalar.pvt import atmosphere_delays, rotate_sagnac, solve_pvt
from ultratight.signals.atmosphere import AtmosphereModel
from ultratight.signals.constellation import nominal_ephemerides
from ultratight.signals.ephemeris import sat_state

LLH = (math.radians(28.5), math.radians(-80.6), 5.0)
TOW = 518026.0
MODEL = AtmosphereModel(tropo="saastamoinen", mapping_name="cosz")


def _sky(mask_deg=5.0):
    rx = np.asarray(llh_to_ecef(*LLH), float)
    sats = []
    for eph in nominal_ephemerides(2190, TOW).values():
        p = np.asarray(sat_state(eph, np.array([TOW]))[0][0], float)
        if math.degrees(float(elev_azim(rx, p)[0])) > mask_deg:
            sats.append(p)
    return rx, np.array(sats)


def _fixes(with_tropo_in_signal, n=60, sigma=0.5, seed=5, n_sats=None):
    """``n`` fixes of solve_pvt (troposphere subtracted, as the receiver does) from pseudoranges with
    (or without) the model's delays, white noise ``sigma``; and the fixes without the correction."""
    rx, sp = _sky()
    sp = sp[:n_sats] if n_sats else sp
    rng = np.random.default_rng(seed)
    el, _ = elev_azim(rx, sp)
    d = np.asarray(MODEL.delays_m(LLH[0], LLH[1], LLH[2], el, np.zeros_like(el), TOW)[1])
    out, plain = [], []
    rho = np.linalg.norm(sp - rx, axis=1)
    for _ in range(3):          # the range in the receive-time frame (the Earth turns during the flight)
        rho = np.linalg.norm(rotate_sagnac(sp, rho / 299792458.0) - rx, axis=1)
    for _ in range(n):
        pr = rho + 30.0 + rng.normal(0.0, sigma, len(sp))
        if with_tropo_in_signal:
            pr = pr + d
        sol = solve_pvt(sp, pr, delays=atmosphere_delays(MODEL, TOW), raim=False)
        plain.append(solve_pvt(sp, pr, raim=False))
        e, a = elev_azim(sol.pos_e, sp)
        llh = ecef_to_llh(sol.pos_e.copy())
        out.append({"llh_deg": [math.degrees(llh[0]), math.degrees(llh[1]), float(llh[2])], "pos_e": sol.pos_e,
                    "clk_bias_m": sol.clk_bias_m,
                    "sv": [{"prn": j + 1, "elev_deg": math.degrees(e[j]), "azim_deg": math.degrees(a[j]) % 360.0,
                            "used": bool(sol.used[j]), "resid_m": float(sol.residuals_m[j])} for j in range(len(sp))]})
    return out, plain


def test_a_signal_without_troposphere_is_found_and_the_fix_moved_to_the_uncorrected_one():
    fixes, plain = _fixes(False)
    t = troposphere_test(fixes)
    assert t["troposphere"] == "absent", t
    assert t["scale"] == pytest.approx(1.0, abs=3 * t["scale_sigma"] + 0.02) and t["scale_sigma"] < 0.1
    assert t["rms_with_m"] > 1.0 and t["rms_without_m"] < 0.3 * t["rms_with_m"]
    moved = np.mean([f["pos_e"] for f in fixes], axis=0) + np.asarray(t["shift_e"])
    target = np.mean([s.pos_e for s in plain], axis=0)
    shift = np.linalg.norm(t["shift_e"])
    assert shift > 5.0                                        # metres of height: what the test is for
    assert np.linalg.norm(moved - target) < 0.02 * shift      # linearised: within 2 % of the move
    clk = np.mean([f["clk_bias_m"] for f in fixes]) + t["shift_clk_m"]
    assert clk == pytest.approx(np.mean([s.clk_bias_m for s in plain]), abs=0.02 * abs(t["shift_clk_m"]))


@pytest.mark.parametrize("sigma", [0.5, 3.0])
def test_a_signal_with_troposphere_is_never_taken_for_one_without(sigma):
    t = troposphere_test(_fixes(True, sigma=sigma)[0])
    assert t["troposphere"] in ("present", "undecided") and "shift_e" not in t
    assert abs(t["scale"]) < 3 * t["scale_sigma"] + 0.02
    if sigma == 0.5:
        assert t["troposphere"] == "present"


def test_too_few_satellites_or_fixes_is_undecided():
    assert troposphere_test(_fixes(False, n_sats=5)[0])["troposphere"] == "undecided"
    assert troposphere_test(_fixes(False, n=5)[0])["troposphere"] == "undecided"
    assert troposphere_test([])["troposphere"] == "undecided"
