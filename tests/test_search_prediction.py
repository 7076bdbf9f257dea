"""The all-in-view search from what the receiver knows: with a fix and ephemerides, only the PRNs
predicted above the mask and not tracked are searched, around their predicted Doppler; the search's
runs and CPU share are reported in the summary (``process --json``)."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
C_LIGHT = 299792458.0
WEEK, TOW = 2190, 569026.0                     # static-open-sky-atmosphere's start
# the generated files carry no atmosphere (the receiver's corrections are off: not the subject here)
NO_SKY = {"atmosphere.iono": "off", "atmosphere.tropo": "off", "atmosphere.broadcast": False}
LAT, LON, H = 41.275, 1.987, 50.0


def _ecef(lat_deg, lon_deg, h):
    """Geodetic -> ECEF (WGS-84), written out here."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    e2 = WGS84_F * (2.0 - WGS84_F)
    n = WGS84_A / math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
    return np.array([(n + h) * math.cos(lat) * math.cos(lon), (n + h) * math.cos(lat) * math.sin(lon),
                     (n * (1.0 - e2) + h) * math.sin(lat)])


def _enu_rows(lat_deg, lon_deg):
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def _elevations(ephs, rx, tow, lat_deg=LAT, lon_deg=LON):
    """Elevation (deg) of every satellite at the receiver: ECEF -> ENU by the rotation above, satellite
    states at the nominal 75 ms signal travel time before ``tow``."""
    from ultratight.signals.ephemeris import sat_state
    enu = _enu_rows(lat_deg, lon_deg)
    out = {}
    for p, e in ephs.items():
        d = enu @ (sat_state(e, tow - 0.075)[0][0] - rx)
        out[p] = math.degrees(math.asin(d[2] / np.linalg.norm(d)))
    return out


def _doppler(eph, rx, vel, drift_mps, tow, wavelength):
    """First-order Doppler: the line-of-sight relative velocity plus the receiver clock drift (m/s)
    minus the satellite clock drift, over the wavelength."""
    from ultratight.signals.ephemeris import sat_state
    pos, v, _clk, sdrift = sat_state(eph, tow - 0.075)
    los = pos[0] - rx
    los /= np.linalg.norm(los)
    rate = los @ (v[0] - vel) + drift_mps - C_LIGHT * float(sdrift[0])
    return -rate / wavelength


@pytest.mark.parametrize("mask_deg,tow", [(5.0, TOW), (30.0, TOW + 1800.0)])
def test_plan_holds_exactly_the_untracked_satellites_above_the_mask(mask_deg, tow):
    from ultratight.receiver.scalar.search_plan import PREDICTED_WINDOW_HZ, plan_search
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.signal import GPS_L1CA
    lam = GPS_L1CA.wavelength_m
    ephs = nominal_ephemerides(WEEK, tow)
    del ephs[7], ephs[30]                                    # two PRNs without an ephemeris
    rx = _ecef(LAT, LON, H)
    vel = np.array([12.0, -7.0, 0.5])                        # a moving receiver, m/s ECEF
    drift = 150.0                                            # receiver clock drift, m/s (~790 Hz)
    el = _elevations(ephs, rx, tow)
    assert min(abs(v - mask_deg) for v in el.values()) > 0.05   # no satellite on the mask edge
    above = sorted(p for p, v in el.items() if v >= mask_deg)
    assert len(above) >= 4
    tracked = set(above[::2])                                # every other one has a channel running
    idle = [p for p in range(1, 33) if p not in tracked]
    fix = {"pos_e": rx, "vel_e": vel, "clk_drift_mps": drift, "gps_week": WEEK, "gps_tow_s": tow,
           "sigma_vel_mps": 0.1}
    plan = plan_search(idle, ephs.get, fix, 0.0, mask_deg, lam, 10e3)
    assert sorted(plan.predicted) == [p for p in above if p not in tracked]
    assert sorted(plan.below_mask) == sorted(p for p, v in el.items() if v < mask_deg and p not in tracked)
    assert sorted(plan.unpredicted) == [7, 30]
    assert plan.window_hz == pytest.approx(PREDICTED_WINDOW_HZ + 3 * 0.1 / lam)
    for p, d in plan.predicted.items():
        # the light-time solution differs from the first-order form by well under 1 Hz
        assert d == pytest.approx(_doppler(ephs[p], rx, vel, drift, tow, lam), abs=1.0), p


def test_no_fix_or_no_ephemeris_means_no_prediction():
    from ultratight.receiver.scalar.search_plan import plan_search, predicted_window_hz
    from ultratight.signals.constellation import nominal_ephemerides
    ephs = nominal_ephemerides(WEEK, TOW)
    plan = plan_search([3, 5, 9], ephs.get, None, 0.0, 5.0, 0.19, 10e3)
    assert plan.unpredicted == [3, 5, 9] and not plan.predicted and not plan.below_mask
    fix = {"pos_e": _ecef(LAT, LON, H), "vel_e": np.zeros(3), "clk_drift_mps": 0.0, "gps_week": WEEK,
           "gps_tow_s": TOW, "sigma_vel_mps": 0.0}
    assert plan_search([3, 5], lambda p: None, fix, 0.0, 5.0, 0.19, 10e3).unpredicted == [3, 5]
    # an old fix widens the window by 10 m/s^2 per second of age, never beyond the full search
    assert predicted_window_hz(fix, 2.0, 0.2, 10e3) == pytest.approx(500.0 + 20.0 / 0.2)
    assert predicted_window_hz(fix, 1e4, 0.2, 10e3) == 10e3


@pytest.fixture(scope="module")
def short_file(tmp_path_factory):
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.synth.generator import generate
    cfg = load_scenario("static-open-sky", {"duration_s": 3.0, "frontend.fs_hz": 2.0e6, "satellites.max_count": 6,
                                            "time.tow_s": 518400.0, **NO_SKY})
    files = generate(cfg, tmp_path_factory.mktemp("search"), "s", progress=False)
    with __import__("h5py").File(files["truth"], "r") as f:
        prns = [int(p) for p in f.attrs["prn"]]
    return files, prns


def test_coarse_search_before_a_fix_and_its_cpu_share(short_file):
    """No fix in 3 s: every search is the coarse one, on the PRNs the cold start did not find, at
    twice the predicted search's interval."""
    from ultratight.receiver.scalar.process_config import ProcessConfig
    from ultratight.receiver.scalar.receiver import process
    files, prns = short_file
    res = process(files["if"], ProcessConfig(search_every_s=0.5, iono="off", tropo="off"))
    assert not res.fixes
    s = res.summary()["search"]
    started = {c["prn"] for c in res.channels if c["started"]}
    assert started == set(prns)
    # coarse searches every 1.0 s of the ~3 s run (the last one needs 50 ms of file left)
    assert s["coarse_runs"] == 2 and s["predicted_runs"] == 0 and s["runs"] == 2 == res.searches
    assert s["coarse_prns"] == 2 * (32 - len(prns)) and s["predicted"] == [] and s["below_mask"] == []
    assert 0.0 < s["cpu_s"] <= res.cpu_s and s["share_of_cpu"] == pytest.approx(s["cpu_s"] / res.cpu_s, abs=1e-3)


def test_predicted_search_finds_the_signals_around_their_prediction(short_file):
    """The two-stage search with its first stage in +-500 Hz around a prediction 150 Hz off: the
    satellites in the file are declared at their true Doppler and code phase, an absent PRN is not."""
    import h5py

    from ultratight.receiver.scalar.channels import predicted_search
    from ultratight.receiver.scalar.process_config import ProcessConfig
    from ultratight.signals.recording.iffile import open_if
    files, prns = short_file
    src = open_if(files["if"])
    start = int(0.5 * src.fs_hz)
    with h5py.File(files["truth"], "r") as f:
        row = int(np.searchsorted(f["sample_index"][:], start))
        dopp = {p: float(f["doppler_hz"][row, k]) for k, p in enumerate(prns)}
        code = {p: float(f["code_phase_chips"][row, k]) for k, p in enumerate(prns)}
        s_row = int(f["sample_index"][row])
    absent = next(p for p in range(1, 33) if p not in prns)
    centres = {**{p: d + 150.0 for p, d in dopp.items()}, absent: 1000.0}
    res = predicted_search(src, ProcessConfig(), start, centres, 500.0)
    assert [a.prn for a in res] == list(centres)
    by = {a.prn: a for a in res}
    assert not by[absent].detected
    for p in prns:
        a = by[p]
        assert a.detected and a.peak_cn0_dbhz >= 37.0, p
        assert a.doppler_hz == pytest.approx(dopp[p], abs=25.0), p
        # code phase at the result's sample, from the truth's code rate (1.023 MHz, Doppler-scaled)
        exp = (code[p] + (a.sample_index - s_row) / src.fs_hz * 1.023e6 * (1 + dopp[p] / 1575.42e6)) % 1023.0
        err = (a.code_phase_chips - exp + 511.5) % 1023.0 - 511.5
        assert abs(err) < 0.5, (p, a.code_phase_chips, exp)


def test_process_json_reports_the_search(short_file):
    files, _ = short_file
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "process", files["if"], "--json",
                        "--no-progress", "--duration", "1", "--iono", "off", "--tropo", "off"], capture_output=True, text=True,
                       timeout=300, check=False)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    s = d["search"]
    assert {"runs", "predicted_runs", "coarse_runs", "predicted_prns", "coarse_prns", "predicted", "below_mask",
            "cpu_s", "share_of_cpu"} <= set(s)
    assert s["runs"] == 0 == d["searches"] and s["cpu_s"] == 0.0 and s["share_of_cpu"] == 0.0   # 15 s default
    assert d["cpu_s"] > 0


def test_receiver_searches_the_predicted_satellites_only(tmp_path):
    """With the constellation's ephemerides given and 6 of the satellites in view in the signal: after
    the first fix the periodic search covers exactly the other satellites above the mask (predicted),
    never the ones below it, and the coarse search only the PRNs without an ephemeris."""
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.receiver.scalar.process_config import ProcessConfig
    from ultratight.receiver.scalar.receiver import process
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.synth.generator import generate
    cfg = load_scenario("static-open-sky", {"duration_s": 10.0, "frontend.fs_hz": 2.0e6, "satellites.max_count": 6,
                                            "time.tow_s": 518400.0, **NO_SKY})
    files = generate(cfg, tmp_path, "p", progress=False)
    week, tow = int(cfg["time"]["week"]), float(cfg["time"]["tow_s"])
    ephs = nominal_ephemerides(week, tow)
    del ephs[30]
    import h5py
    with h5py.File(files["truth"], "r") as f:
        prns = [int(p) for p in f.attrs["prn"]]
        rx = np.asarray(f["pos_e"][0])
    res = process(files["if"], ProcessConfig(search_every_s=1.0, iono="off", tropo="off"), ephemerides=ephs)
    assert res.fixes and res.first_fix_s < 9.0
    s = res.summary()["search"]
    assert s["predicted_runs"] >= 1
    # independent elevations at the time of the last search (within 1 s of the end)
    t_last = tow + res.signal_s
    el = _elevations(ephs, rx, t_last, cfg["receiver"]["lat_deg"], cfg["receiver"]["lon_deg"])
    assert min(abs(v - 5.0) for v in el.values()) > 0.05
    assert s["predicted"] == sorted(p for p, v in el.items() if v >= 5.0 and p not in prns)
    assert s["below_mask"] == sorted(p for p, v in el.items() if v < 5.0)
    # the coarse search (every 2 s) covers the 26 PRNs without a channel before the fix, PRN 30 alone
    # (no ephemeris) after it
    n_idle = 32 - len(prns)
    n_before = (s["coarse_prns"] - s["coarse_runs"]) // (n_idle - 1)
    assert s["coarse_prns"] == n_before * n_idle + (s["coarse_runs"] - n_before) and s["coarse_runs"] > n_before
    assert {c["prn"] for c in res.channels if c["started"]} == set(prns)

