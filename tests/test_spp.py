"""Satellite states per observation row (ultratight.signals.obs_geometry) against the light-time
closed form, and ``ultratight spp`` on the GEONET station 0759: against the surveyed coordinate and
against RTKLIB's single-point solution of the same files (pyrtklib), its CSV and JSON outputs and its
one-line errors."""

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ultratight.constants import OMEGA_E, C
from ultratight.receiver.cli.main import main
from ultratight.signals.ephemeris import sat_state
from ultratight.signals.obs_geometry import sat_states
from ultratight.signals.observations import RawEpochs, gps_seconds

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
GEONET = DATA / "rinex-geonet"
OBS, NAV = GEONET / "07590920.05o", GEONET / "07590920.05n"
STATION_0759 = np.array([-3976219.5082, 3382372.5671, 3652512.9849])   # data README (survey authority)
MASK_DEG = 5.0


def _need(*paths):
    for p in paths:
        if not p.exists():
            pytest.skip(f"shared data not found: {p}")


def _nav():
    _need(NAV)
    from ultratight.signals.rinex import read_rinex_nav
    return read_rinex_nav(NAV)


# ------------------------------------------------------------------------------ obs_geometry
def _light_time(eph, rx, t_rx_gps):
    """True GPS transmit time of a signal received at ``rx`` at GPS time ``t_rx_gps`` (continuous
    seconds): the fixed point of tau = |R3(w tau) r_s(t - tau) - rx| / c, written out here."""
    base = eph.week * 604800.0
    tau = 0.07
    for _ in range(20):
        p = sat_state(eph, t_rx_gps - tau - base)[0][0]
        th = OMEGA_E * tau
        pr = np.array([math.cos(th) * p[0] + math.sin(th) * p[1], -math.sin(th) * p[0] + math.cos(th) * p[1], p[2]])
        tau = np.linalg.norm(pr - rx) / C
    return t_rx_gps - tau


def test_sat_states_match_the_light_time_closed_form():
    """Pseudoranges built from the true transmit times (receiver clock 0.3 ms fast): the rows' transmit
    times, positions, velocities and clock corrections are the ephemeris at that time (float seconds
    since 1980 resolve 0.12 us: < 1 mm of satellite motion)."""
    nav = _nav()
    week, t_rx = 1316, gps_seconds(1316, 519000.0)
    bias_s = 3.0e-4
    prns = [3, 7, 8, 11, 19, 20, 24, 28]
    rows = []
    for prn in prns:
        eph = nav.select(prn, week, 519000.0)
        t_tx = _light_time(eph, STATION_0759, t_rx)
        clk = sat_state(eph, t_tx - eph.week * 604800.0)[2][0]
        rows.append((eph, t_tx, C * ((t_rx + bias_s) - (t_tx + clk))))
    raw = RawEpochs(t=np.array([t_rx + bias_s]), start=np.array([0, len(prns)]), prn=np.array(prns),
                    pr_m=np.array([r[2] for r in rows]), doppler_hz=np.full(len(prns), np.nan),
                    cn0_dbhz=np.full(len(prns), np.nan))
    st = sat_states(raw, nav)
    assert st.valid.all()
    for i, (eph, t_tx, _) in enumerate(rows):
        p, v, clk, drift = sat_state(eph, t_tx - eph.week * 604800.0)
        assert abs(st.t_tx[i] - t_tx) < 1e-6
        assert np.linalg.norm(st.pos_e[i] - p[0]) < 1e-3 and np.linalg.norm(st.vel_e[i] - v[0]) < 1e-6
        assert abs(st.clk_m[i] - C * clk[0]) < 1e-6 and abs(st.drift_mps[i] - C * drift[0]) < 1e-9
        assert st.iode[i] == eph.iode
    # no Sagnac rotation inside: the geometric range needs the caller's rotation
    tau = (t_rx - np.array([r[1] for r in rows]))
    unrot = np.linalg.norm(st.pos_e - STATION_0759, axis=1) / C
    assert np.all(np.abs(unrot - tau) > 1e-9)


def test_sat_states_validity():
    """Invalid rows: unknown PRN, NaN pseudorange, a time outside every fit interval, an unhealthy
    set; valid rows keep their values."""
    nav = _nav()
    eph3 = nav.select(3, 1316, 519000.0)
    sick = eph3.copy(sv_health=1)
    nav.ephemerides[3] = [sick]                   # PRN 3: only an unhealthy set
    t = gps_seconds(1316, 519000.0)
    raw = RawEpochs(t=np.array([t, t + 3 * 86400.0]), start=np.array([0, 4, 5]), prn=np.array([7, 31, 8, 3, 7]),
                    pr_m=np.array([2.2e7, 2.2e7, np.nan, 2.2e7, 2.2e7]), doppler_hz=np.zeros(5),
                    cn0_dbhz=np.zeros(5))
    st = sat_states(raw, nav)
    assert st.valid.tolist() == [True, False, False, False, False]
    assert np.all(np.isnan(st.pos_e[1:])) and np.all(np.isnan(st.clk_m[1:])) and np.all(np.isfinite(st.pos_e[0]))
    assert 2.5e7 < np.linalg.norm(st.pos_e[0]) < 2.7e7


# ---------------------------------------------------------------------------------- the command
def rtklib_spp(obs, nav, pos_path, mask_deg=MASK_DEG):
    """RTKLIB (pyrtklib, postpos) single-point solution of the same files, configured as ours: single
    point mode, GPS only, one frequency (L1; RINEX 2 C1 is its first L1 code), broadcast ephemerides,
    broadcast (Klobuchar) ionosphere, Saastamoinen troposphere, the same elevation mask; RTKLIB's
    own weighting (its default error model and variances of the models) and no RAIM FDE (ours
    excluded no satellite on this file).  Rows: GPS week, tow, ECEF x, y, z."""
    p = pytest.importorskip("pyrtklib", reason="pyrtklib (RTKLIB binding, test dependency) not installed")
    popt, sopt, fopt = p.prcopt_default, p.solopt_default, p.filopt_t()
    popt.mode = 0                   # PMODE_SINGLE
    popt.navsys = 1                 # SYS_GPS
    popt.nf = 1                     # L1 only
    popt.sateph = 0                 # broadcast ephemeris
    popt.ionoopt = 1                # IONOOPT_BRDC (Klobuchar)
    popt.tropopt = 1                # TROPOPT_SAAS
    popt.elmin = math.radians(mask_deg)
    sopt.posf = 1                   # ECEF
    sopt.times = 0                  # GPST
    sopt.timef = 0                  # week / tow
    sopt.timeu = 3
    out = str(pos_path)
    oc = p.Arr1Dchar(len(out) + 1)
    for i, ch in enumerate(out):
        oc[i] = ch
    rc = p.postpos(p.gtime_t(), p.gtime_t(), 0.0, 0.0, popt, sopt, fopt, [str(obs), str(nav)], 2, oc, "", "")
    assert rc == 0
    return np.array([[float(v) for v in ln.split()[:5]] for ln in open(out) if not ln.startswith("%")])


def _run(argv, capsys):
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.fixture(scope="module")
def geonet_run(tmp_path_factory):
    _need(OBS, NAV)
    d = tmp_path_factory.mktemp("spp")
    csv_path = d / "fixes.csv"
    import contextlib
    import io
    buf_out, buf_err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(buf_out), contextlib.redirect_stderr(buf_err):
        rc = main(["spp", str(OBS), str(NAV), "--json", "--reference-header", "--mask", str(MASK_DEG),
                   "--csv", str(csv_path)])
    assert rc == 0, buf_err.getvalue()
    return json.loads(buf_out.getvalue()), csv_path, d


def test_spp_0759_against_the_survey_and_rtklib(geonet_run):
    """3D RMS against the surveyed coordinate <= 5 m, and not worse than RTKLIB's on the same files
    by more than 10 %.  Measured (2026-11-26): ours 1.371 m (horizontal 0.446 m, up 1.296 m),
    RTKLIB 2.321 m; the two solutions differ per epoch by the RMS printed here (1.29 m): different
    weights, ours sigma/sin(el), RTKLIB's error model with the ionosphere/troposphere model variances
    (the next test gives our solver RTKLIB's weights and finds RTKLIB's solution)."""
    summ, _, d = geonet_run
    assert summ["fixes"] == summ["epochs"] == 120
    ref = summ["reference"]
    assert ref["source"] == "header" and np.allclose(ref["ecef_m"], STATION_0759)
    rms = ref["rms_3d_m"]
    sol = rtklib_spp(OBS, NAV, d / "rtk.pos")
    assert sol.shape[0] == 120
    err = np.linalg.norm(sol[:, 2:5] - STATION_0759, axis=1)
    rms_rtk = float(np.sqrt(np.mean(err ** 2)))
    ours = _csv_rows(geonet_run[1])
    tow = np.array([float(r["gps_tow_s"]) for r in ours])
    xyz = np.array([[float(r[k]) for k in ("x_m", "y_m", "z_m")] for r in ours])
    diff = []
    for i, t in enumerate(tow):
        j = np.argmin(np.abs(sol[:, 1] - t))
        assert abs(sol[j, 1] - t) < 0.01
        diff.append(np.linalg.norm(sol[j, 2:5] - xyz[i]))
    diff = np.array(diff)
    print(f"\n0759 SPP 3D RMS vs survey: ours {rms:.3f} m (horizontal {ref['rms_horizontal_m']:.3f} m), "
          f"RTKLIB {rms_rtk:.3f} m; |ours - RTKLIB| RMS {np.sqrt(np.mean(diff ** 2)):.3f} m, max {diff.max():.3f} m")
    assert rms <= 5.0
    assert rms <= 1.1 * rms_rtk
    assert rms_rtk <= 5.0          # the reference solution itself is a sound one on this file


def _csv_rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_spp_csv_has_the_columns_of_process(geonet_run, tmp_path):
    from ultratight.receiver.io.outputs import write_csv
    summ, csv_path, _ = geonet_run
    write_csv(tmp_path / "empty.csv", [])
    process_cols = (tmp_path / "empty.csv").read_text().splitlines()[0]
    text = csv_path.read_text().splitlines()
    assert text[0] == process_cols
    rows = _csv_rows(csv_path)
    assert len(rows) == summ["fixes"] == 120
    assert rows[0]["iono"] == "klobuchar" and rows[0]["tropo"] == "saastamoinen"
    mean = np.mean([[float(r[k]) for k in ("x_m", "y_m", "z_m")] for r in rows], axis=0)
    assert np.allclose(mean, summ["mean_position_ecef_m"], atol=1e-3)
    assert int(rows[0]["gps_week"]) == 1316 and abs(float(rows[0]["gps_tow_s"]) - 518400.0) < 1e-3
    assert float(rows[1]["t_s"]) == 30.0
    assert summ["dop"]["pdop"] > 1.0 and summ["mean_satellites_used"] > 6


def test_spp_reference_flag_and_mask(capsys):
    _need(OBS, NAV)
    rc, out, err = _run(["spp", str(OBS), str(NAV), "--json", "--reference", *map(str, STATION_0759 + [0, 0, 100.0])],
                        capsys)
    assert rc == 0, err
    s = json.loads(out)
    # the reference 100 m above the station (in z): the mean error moves by that much
    assert abs(s["reference"]["rms_3d_m"] - 100.0) < 5.0
    rc, out, err = _run(["spp", str(OBS), str(NAV), "--json", "--mask", "15", "--iono", "off", "--tropo", "off"],
                        capsys)
    assert rc == 0, err
    s = json.loads(out)
    assert s["corrections"]["iono"] == "off" and s["corrections"]["mask_deg"] == 15.0
    assert s["reference"] is None and s["fixes"] > 0


@pytest.mark.parametrize("case", ["missing", "obs_is_nav", "nav_is_obs", "no_nav", "no_overlap", "text",
                                  "csv_is_input", "both_refs"])
def test_spp_errors_are_one_line(case, tmp_path, capsys):
    _need(OBS, NAV)
    text = tmp_path / "notes.txt"
    text.write_text("not a GNSS file\n")
    brdc = DATA / "rinex" / "brdc0010.22n"
    argv = {
        "missing": ["spp", str(tmp_path / "none.obs"), str(NAV)],
        "obs_is_nav": ["spp", str(NAV), str(NAV)],
        "nav_is_obs": ["spp", str(OBS), str(OBS)],
        "no_nav": ["spp", str(OBS)],
        "no_overlap": ["spp", str(OBS), str(brdc)],
        "text": ["spp", str(text), str(NAV)],
        "csv_is_input": ["spp", str(OBS), str(NAV), "--csv", str(NAV)],
        "both_refs": ["spp", str(OBS), str(NAV), "--reference-header", "--reference", "1", "2", "3"],
    }[case]
    if case == "no_overlap":
        _need(brdc)
    before = NAV.stat().st_mtime
    rc, out, err = _run(argv, capsys)
    assert rc == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ultratight spp: error: "), err
    expect = {"missing": "OBS file not found", "obs_is_nav": "expected 'O' (observation data)",
              "nav_is_obs": "expected 'N' (GPS navigation)", "no_nav": "needs a navigation file",
              "no_overlap": "no overlap of observations and navigation data", "text": "neither a RINEX observation",
              "csv_is_input": "refusing to overwrite an input file", "both_refs": "--reference"}[case]
    assert expect in lines[0]
    assert NAV.stat().st_mtime == before


URA_M = (2.4, 3.4, 4.85, 6.85, 9.65, 13.65, 24.0, 48.0, 96.0, 192.0, 384.0, 768.0, 1536.0, 3072.0, 6144.0)


def test_with_rtklibs_weights_our_solution_is_rtklibs(tmp_path):
    """The whole difference between the two solutions is the weighting.  Our rows (sat_states), the
    Klobuchar and Saastamoinen delays and solve_pvt, weighted with RTKLIB 2.4.3's pseudorange variance
    (its single-point error model with the prcopt defaults: eratio 100, a = b = 0.003 m, so
    100^2 (a^2 + b^2 / sin El), plus the URA variance of the ephemeris, 0.3^2 m^2 code bias,
    (0.5 I_Klobuchar)^2 and (0.3 / (sin El + 0.1))^2), elevations at the surveyed point: every epoch
    within 1 cm of RTKLIB's (measured 0.17 mm RMS)."""
    from ultratight.ins.earth import ecef_to_llh, elev_azim
    from ultratight.receiver.scalar.pvt import atmosphere_delays, solve_pvt
    from ultratight.signals.atmosphere import AtmosphereModel
    from ultratight.signals.rinex_obs import read_rinex_obs
    nav = _nav()
    raw = read_rinex_obs(OBS)
    sol = rtklib_spp(OBS, NAV, tmp_path / "rtk.pos")
    st = sat_states(raw, nav)
    model = AtmosphereModel("klobuchar", nav.ion_alpha, nav.ion_beta, "saastamoinen")
    llh = ecef_to_llh(STATION_0759.copy())
    diff = []
    for k in range(raw.n_epochs):
        sl = raw.epoch(k)
        ok = st.valid[sl]
        s, pr = st.pos_e[sl][ok], raw.pr_m[sl][ok] + st.clk_m[sl][ok]
        tow = float(raw.t[k] % 604800.0)
        el, az = elev_azim(STATION_0759, s)
        iono, _ = model.delays_m(llh[0], llh[1], llh[2], el, az, tow)
        ura = np.array([URA_M[nav.select(int(p), 1316, tow).ura_index] for p in raw.prn[sl][ok]])
        var = 100.0 ** 2 * (0.003 ** 2 + 0.003 ** 2 / np.sin(el)) + ura ** 2 + 0.3 ** 2 + (0.5 * iono) ** 2 \
            + (0.3 / (np.sin(el) + 0.1)) ** 2
        fix = solve_pvt(s, pr, sigma_pr_m=np.sqrt(var), elev_weight=False, mask_deg=MASK_DEG, raim=False,
                        delays=atmosphere_delays(model, tow))
        j = np.argmin(np.abs(sol[:, 1] - (tow - fix.clk_bias_m / C)))
        diff.append(np.linalg.norm(fix.pos_e - sol[j, 2:5]))
    diff = np.array(diff)
    print(f"\n0759 with RTKLIB's weights: |ours - RTKLIB| RMS {1e3 * np.sqrt(np.mean(diff ** 2)):.3f} mm, "
          f"max {1e3 * diff.max():.3f} mm over {diff.size} epochs")
    assert diff.size == 120 and diff.max() < 0.01


def test_spp_on_a_ubx_log_without_nav(capsys, tmp_path):
    """A u-blox log alone: the ephemerides come from its RXM-SFRBX subframes (LNAV for PRNs 10, 23, 27,
    32; CNAV for 8, 18, 24, whose LNAV subframes are incomplete); by default the pseudoranges are the
    L1 C/A + L2C ionosphere-free combination (no model, no warning); ``--signals l1`` takes L1 C/A with
    the Klobuchar coefficients of a CNAV type 30.  Velocities from the Doppler are in the CSV."""
    ubx = DATA / "real-imu-gnss" / "walk_0827" / "gnss_1730.ubx"
    _need(ubx)
    pytest.importorskip("pyubx2", reason="pyubx2 not installed")
    out_csv = tmp_path / "walk.csv"
    rc, out, err = _run(["spp", str(ubx), "--json", "--csv", str(out_csv)], capsys)
    assert rc == 0, err
    s = json.loads(out)
    assert s["obs_format"] == "ubx" and s["nav"] == "RXM-SFRBX"
    assert s["satellites_with_ephemeris"] == [8, 10, 18, 23, 24, 27, 32] and s["epochs"] == 536
    assert s["fixes"] >= 500
    assert s["corrections"]["signals"] == "GPS L1 C/A + L2C ionosphere-free"
    assert s["corrections"]["ionosphere"] == "ionosphere-free dual-frequency combination (no model)"
    assert err.strip() == ""
    rows = _csv_rows(out_csv)
    assert len(rows) == s["fixes"] and rows[0]["iono"] == "iono-free"
    speed = np.array([math.hypot(float(r["vx_mps"]), float(r["vy_mps"])) for r in rows])
    assert np.all(np.isfinite(speed))
    rc, out, err = _run(["spp", str(ubx), "--json", "--signals", "l1"], capsys)
    s = json.loads(out)
    assert rc == 0 and err.strip() == "" and s["corrections"]["signals"] == "GPS L1 C/A"
    assert s["corrections"]["iono"] == "klobuchar"
    assert s["corrections"]["ionosphere"] == "single frequency, Klobuchar (broadcast)"
    rc, out, err = _run(["spp", str(ubx), "--code", "P1"], capsys)
    assert rc == 2 and "--code applies to RINEX observations" in err


def test_spp_without_a_fix_warns(capsys):
    _need(OBS, NAV)
    rc, out, err = _run(["spp", str(OBS), str(NAV), "--json", "--mask", "80"], capsys)
    assert rc == 0
    s = json.loads(out)
    assert s["fixes"] == 0 and s["epochs_with_ephemeris"] == 120 and s["mean_position_ecef_m"] is None
    assert "no fix: no epoch has a solution with four satellites" in err and len(err.strip().splitlines()) == 1
