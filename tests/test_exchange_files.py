"""RINEX 3.04 observation/navigation and NMEA 0183 output of ``ultratight process``, checked by
independent tools: georinex reads our RINEX back (every observation matches the HDF5 output),
RTKLIB (pyrtklib) positions our RINEX obs+nav with the same corrections and agrees with our PVT,
and our own RINEX navigation reader reads the navigation file back."""

import math
import warnings

import h5py
import numpy as np
import pytest

from ultratight.constants import C

ALPHA = (1.211e-08, -7.451e-09, -5.960e-08, 1.192e-07)
BETA = (1.167e+05, -2.458e+05, -6.554e+04, 1.114e+06)


@pytest.fixture(scope="module")
def run12(tmp_path_factory):
    """12 s of static-open-sky-atmosphere at 2 MHz (seed 1), processed with the nominal ephemerides
    and the broadcast ionosphere given as a navigation file (fixes from ~8 s).  55 dB-Hz: with a
    Hatch filter only seconds old the code noise at 45 dB-Hz is ~1 m, and RTKLIB's weights (with
    ionosphere/troposphere model variances) differ from ours, which would turn noise into
    solution differences; the 60 s 45 dB-Hz comparison is the slow test below."""
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.synth.generator import generate
    from ultratight.signals.lnav_message import quantise_iono
    from ultratight.signals.rinex import NavData

    d = tmp_path_factory.mktemp("x12")
    cfg = load_scenario("static-open-sky-atmosphere", {"duration_s": 12.0, "frontend.fs_hz": 2.0e6,
                                                            "satellites.cn0_dbhz": 55.0})
    files = generate(cfg, d, "s12", progress=False)
    week, tow0 = cfg["time"]["week"], cfg["time"]["tow_s"]
    qa, qb = quantise_iono(ALPHA, BETA)
    nav = NavData(path="nominal", version=3.04,
                  ephemerides={p: [e] for p, e in nominal_ephemerides(week, tow0).items()},
                  ion_alpha=qa, ion_beta=qb, leap_seconds=18)
    out = {k: d / f"o.{k}" for k in ("h5", "obs", "nav", "nmea")}
    res = process(files["if"], ProcessConfig(n_channels=14), ephemerides=nav, out_path=out["h5"],
                  rinex_obs_path=out["obs"], rinex_nav_path=out["nav"], nmea_path=out["nmea"])
    assert len(res.fixes) > 20 and res.corrections["iono_source"] == "rinex"
    return res, out, files


def test_rinex_obs_read_back_by_georinex(run12):
    gr = pytest.importorskip("georinex", reason="georinex not installed")
    res, out, _ = run12
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        obs = gr.load(out["obs"])
    assert obs.attrs["version"] == pytest.approx(3.04) and obs.attrs["interval"] == pytest.approx(0.1)
    assert np.allclose(obs.attrs["position"], res.position_median()[0], atol=1e-3)
    with h5py.File(out["h5"], "r") as f:
        t_rx = f["observables/t_rx_tow_s"][:]
        pr = f["observables/pseudorange_smoothed_m"][:]
        carr = f["observables/carrier_cycles"][:]
        dop = f["observables/doppler_hz"][:]
        cn0 = f["observables/cn0_dbhz"][:]
        lock = f["observables/pll_lock"][:]
    prns = [c["prn"] for c in res.channels]
    week = res.fixes[0]["gps_week"]
    t0 = np.datetime64("1980-01-06T00:00:00", "ns") + np.timedelta64(week * 7, "D")
    tow = (obs.time.values - t0) / np.timedelta64(1, "ns") * 1e-9
    k = np.array([np.argmin(np.abs(t_rx - t)) for t in tow])
    assert np.max(np.abs(t_rx[k] - tow)) < 1e-6           # epoch times to the RINEX 0.1 us
    n_checked = 0
    for j, prn in enumerate(prns):
        sv = f"G{prn:02d}"
        g = obs.sel(sv=sv)
        ok = np.isfinite(pr[k, j])
        assert np.array_equal(np.isfinite(g["C1C"].values), ok)
        assert np.allclose(g["C1C"].values[ok], pr[k, j][ok], atol=5e-4)
        assert np.allclose(g["D1C"].values[ok], dop[k, j][ok], atol=5e-4)
        assert np.allclose(g["S1C"].values[ok], cn0[k, j][ok], atol=5e-4)
        ph = ok & lock[k, j]
        dphi = g["L1C"].values[ph] - carr[k, j][ph]     # the resolved half cycle: 0 or 0.5
        assert np.all(np.minimum(np.abs(dphi), np.abs(dphi - 0.5)) < 5e-4)
        n_checked += ok.sum()
    assert n_checked > 200


def test_rinex_nav_read_back(run12):
    from ultratight.signals.rinex import read_rinex_nav
    from ultratight.signals.lnav_message import quantise_iono
    res, out, _ = run12
    nav = read_rinex_nav(out["nav"])
    qa, qb = quantise_iono(ALPHA, BETA)
    assert np.allclose(nav.ion_alpha, qa, rtol=1e-4) and np.allclose(nav.ion_beta, qb, rtol=1e-4)
    assert set(nav.prns) >= {c["prn"] for c in res.channels if c["tracked"]}
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.ephemeris import sat_state
    ref = nominal_ephemerides(2190, 569026.0)
    for prn in nav.prns:
        e = nav.ephemerides[prn][0]
        p1 = sat_state(e, 569030.0)[0]
        p0 = sat_state(ref[prn], 569030.0)[0]
        assert np.linalg.norm(p1 - p0) < 1e-3            # 12 significant digits: < 1 mm
    gr = pytest.importorskip("georinex", reason="georinex not installed")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gn = gr.load(out["nav"])
    assert np.allclose(gn.attrs["ionospheric_corr_GPS"], list(qa) + list(qb), rtol=1e-4)
    for prn in nav.prns:
        v = gn.sel(sv=f"G{prn:02d}")["sqrtA"].values
        assert np.nanmax(np.abs(v - nav.ephemerides[prn][0].sqrt_a)) < 1e-6


def rtklib_spp(obs_path, nav_path, pos_path):
    """Single-point positions (GPS week, tow, x, y, z) of RTKLIB (pyrtklib) with broadcast
    ionosphere, Saastamoinen troposphere and a 5 deg mask: the corrections our PVT applies."""
    p = pytest.importorskip("pyrtklib", reason="pyrtklib (RTKLIB binding) not installed")
    popt, sopt, fopt = p.prcopt_default, p.solopt_default, p.filopt_t()
    popt.mode = 0                       # single point positioning
    popt.ionoopt = 1                    # broadcast (Klobuchar)
    popt.tropopt = 1                    # Saastamoinen
    popt.elmin = math.radians(5.0)
    popt.navsys = 1                     # GPS
    sopt.posf = 1                       # ECEF
    sopt.times = 0                      # GPS time
    sopt.timef = 0                      # week and time of week
    sopt.timeu = 3
    oc = p.Arr1Dchar(len(str(pos_path)) + 1)
    for i, ch in enumerate(str(pos_path)):
        oc[i] = ch
    rc = p.postpos(p.gtime_t(), p.gtime_t(), 0.0, 0.0, popt, sopt, fopt, [str(obs_path), str(nav_path)], 2,
                   oc, "", "")
    assert rc == 0
    return np.array([[float(v) for v in ln.split()[:5]] for ln in open(pos_path) if not ln.startswith("%")])


def rtklib_differences(sol, fixes):
    """|RTKLIB - ours| (m) at our fix epochs that RTKLIB also solved (same GPS time to 1 ms)."""
    out = []
    for f in fixes:
        j = np.argmin(np.abs(sol[:, 1] - f["gps_tow_s"]))
        if abs(sol[j, 1] - f["gps_tow_s"]) < 1e-3:
            out.append(np.linalg.norm(sol[j, 2:5] - np.asarray(f["pos_e"])))
    return np.array(out)


def test_rtklib_reads_and_positions_our_rinex(run12, tmp_path):
    """Both solutions on the 12 s file: RTKLIB solves every epoch we solve from our RINEX alone,
    and both agree with the truth and with each other at the level docs/process.md states for this
    file: in the first seconds after acquisition the code has ~1 m transients, which the two
    weightings map into positions up to 1.0 m apart (the 60 s run below: 0.25 m)."""
    res, out, files = run12
    sol = rtklib_spp(out["obs"], out["nav"], tmp_path / "rtk.pos")
    d = rtklib_differences(sol, res.fixes)
    assert d.size == len(res.fixes)
    with h5py.File(files["truth"], "r") as f:
        tp = f["pos_e"][0]
    err_rtk = np.linalg.norm(sol[:, 2:5] - tp, axis=1)
    err_ours = np.array([np.linalg.norm(np.asarray(f["pos_e"]) - tp) for f in res.fixes])
    rms_rtk, rms_ours = np.sqrt(np.mean(err_rtk ** 2)), np.sqrt(np.mean(err_ours ** 2))
    print(f"\n12 s: RTKLIB vs truth RMS {rms_rtk:.3f} m, ours {rms_ours:.3f} m, |RTKLIB - ours| max {d.max():.3f} m")
    # docs/process.md (RTKLIB row): on this 12 s file the two solutions are up to 1.0 m apart.
    # Seed 1 (this file): 0.998 m; seeds 1-4: 1.00-1.07 m (RMS 0.73-0.80 m). Bound 1.5 x 1.0 m.
    assert d.max() <= 1.5, d.max()
    # against the truth, both at the ~1 m of the code transients docs/process.md states for this
    # file. Seed 1: RTKLIB 1.01 m, ours 1.46 m; seeds 1-4: RTKLIB 0.50-1.01 m, ours 1.03-1.46 m.
    # Bounds 1.5 x 1 m (RTKLIB) and 2 x 1 m (ours, whose Hatch filter is only seconds old here)
    assert rms_rtk <= 1.5, rms_rtk
    assert rms_ours <= 2.0, rms_ours


@pytest.mark.slow
@pytest.mark.ci
def test_rtklib_agrees_with_our_pvt_60s(tmp_path):
    """Acceptance: the 60 s static-open-sky-atmosphere run (45 dB-Hz, seed 1, everything from
    the signal): RTKLIB on our RINEX obs+nav agrees with our PVT within 0.32 m at every epoch (1.2 x the
    documented 0.266 m: RTKLIB weights by elevation alone, ours also by each channel's code noise)."""
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.synth.generator import generate
    files = generate(load_scenario("static-open-sky-atmosphere"), tmp_path, "s60", progress=False)
    obs, nav = tmp_path / "o.obs", tmp_path / "o.nav"
    res = process(files["if"], ProcessConfig(), rinex_obs_path=obs, rinex_nav_path=nav)
    sol = rtklib_spp(obs, nav, tmp_path / "rtk.pos")
    d = rtklib_differences(sol, res.fixes)
    print(f"\n60 s: {d.size} common epochs of {len(res.fixes)} fixes, |RTKLIB - ours| max {d.max():.3f} m, "
          f"RMS {np.sqrt(np.mean(d ** 2)):.3f} m")
    assert d.size == len(res.fixes) and d.max() <= 0.32


def _nmea_ok(line):
    assert line.startswith("$") and line[-3] == "*"
    body, cs = line[1:-3], line[-2:]
    x = 0
    for ch in body:
        x ^= ord(ch)
    return f"{x:02X}" == cs


def test_nmea_sentences(run12):
    res, out, _ = run12
    raw = open(out["nmea"], newline="").read()
    assert raw.endswith("\r\n")
    lines = raw.split("\r\n")[:-1]
    assert all(_nmea_ok(ln) for ln in lines)
    assert lines[0].startswith("$PUTGT,") and "iono=klobuchar" in lines[0] and "tropo=saastamoinen" in lines[0]
    gga = [ln for ln in lines if ln.startswith("$GPGGA")]
    rmc = [ln for ln in lines if ln.startswith("$GPRMC")]
    gsa = [ln for ln in lines if ln.startswith("$GPGSA")]
    assert len(gga) == len(rmc) == len(gsa) == len(res.fixes)
    f0 = res.fixes[0]
    fld = gga[0][:-3].split(",")
    lat = int(fld[2][:2]) + float(fld[2][2:]) / 60.0
    lon = int(fld[4][:3]) + float(fld[4][3:]) / 60.0
    assert fld[3] == "N" and fld[5] == "E" and fld[6] == "1" and int(fld[7]) == f0["n_used"]
    assert lat == pytest.approx(f0["llh_deg"][0], abs=2e-7) and lon == pytest.approx(f0["llh_deg"][1], abs=2e-7)
    assert float(fld[9]) == pytest.approx(f0["llh_deg"][2], abs=1e-3)
    # UTC = GPS - 18 s: 2022-01-01 (week 2190, Saturday) 14:04:xx
    tow_utc = f0["gps_tow_s"] - 18.0
    sod = tow_utc % 86400.0
    hh, mm, ss = int(fld[1][:2]), int(fld[1][2:4]), float(fld[1][4:])
    assert hh * 3600 + mm * 60 + ss == pytest.approx(sod, abs=0.006)
    assert rmc[0].split(",")[9] == "010122"
    g = gsa[0][:-3].split(",")
    assert sorted(int(x) for x in g[3:15] if x) == sorted(f0["used_prn"][:12])
    gsv = [ln for ln in lines if ln.startswith("$GPGSV")]
    n_view = int(gsv[0].split(",")[3])
    assert n_view == len(f0["sv"]) and int(gsv[0].split(",")[1]) == math.ceil(n_view / 4)
