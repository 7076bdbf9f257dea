"""The tight measurement model of recorded raw observations (ultratight.fusion.gins.tight_meas)
against observables of the project's generator (ultratight.signals.synth.obssim: the light-time
solution of the broadcast ephemeris, Sagnac, satellite and receiver clocks), with the atmosphere of
AtmosphereModel added in the test: at the truth the innovations vanish, a position/velocity error
shows as −e·δr / −e·δv, the clock comes back, the elevation selection and the noise model follow
their documented forms."""

import datetime
import math
import types

import numpy as np
import pytest

from ultratight.constants import C, LAMBDA_L1
from ultratight.errors import ConfigError, FilterError
from ultratight.fusion.gins.tight_meas import TightMeasurements, TightNoise
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh_batch, elev_azim, llh_to_ecef
from ultratight.signals.atmosphere import AtmosphereModel
from ultratight.signals.constellation import nominal_ephemerides
from ultratight.signals.ephemeris import sat_state
from ultratight.signals.obs_geometry import sat_states
from ultratight.signals.observations import RawEpochs, gps_seconds
from ultratight.signals.rinex import NavData
from ultratight.signals.synth.obssim import simulate_observables

WEEK, TOW0 = 2380, 302400.0 + 13 * 3600.0        # local afternoon at 7° E: a Klobuchar daytime delay
ALPHA = (1.1176e-8, 7.4506e-9, -5.9605e-8, -5.9605e-8)
BETA = (90112.0, 0.0, -196608.0, -65536.0)
LLH0 = (math.radians(45.2), math.radians(7.1), 320.0)
VEL_E = np.array([12.0, -7.0, 3.0])               # m/s, ECEF, straight line
CLK0_M, DRIFT_MPS = 3.0e4, 150.0                  # 100 µs and 0.5 ppm: t_rcv differs from true time
DT_EPOCH = 0.25
N_EPOCHS = 21
H_RATE = 0.5                                      # central difference of the delays for the Doppler


def _ephemerides():
    """Nominal constellation with non-zero clock polynomials, T_GD and eccentricity (relativistic term)."""
    out = {}
    for prn, e in nominal_ephemerides(WEEK, TOW0).items():
        out[prn] = e.copy(af0=1.0e-4 * (prn - 16) / 16, af1=2.0e-11 * (-1) ** prn, af2=1e-18, tgd=4.7e-9,
                          e=0.004 + 1e-4 * prn, omega=0.3 * prn)
    return out


def _truth(t):
    p0 = llh_to_ecef(*LLH0)
    pos = p0 + np.outer(t, VEL_E)
    vel = np.broadcast_to(VEL_E, pos.shape).copy()
    return pos, vel, CLK0_M + DRIFT_MPS * t, np.full(t.shape, DRIFT_MPS)


def _delays(obs, pos, t, atmo):
    """(n, k) Klobuchar and Saastamoinen code delays of the generator's geometry at the epochs t."""
    llh = ecef_to_llh_batch(pos)
    el, az = elev_azim(pos[:, None, :], obs.sat_pos_e)
    iono, tropo = atmo.delays_m(llh[:, 0:1], llh[:, 1:2], llh[:, 2:3], el, az, TOW0 + t[:, None])
    return np.where(el > 0, iono, 0.0), np.where(el > 0, tropo, 0.0)


def _states(raw, ephs):
    """The satellite-state contract of ultratight.signals.obs_geometry, written here independently:
    ephemeris at t_tx = t_rcv − ρ/c − Δt_sv(t_tx), no Sagnac rotation."""
    m = raw.prn.shape[0]
    pos, vel = np.empty((m, 3)), np.empty((m, 3))
    clk, drift = np.empty(m), np.empty(m)
    t_rcv = np.repeat(raw.t, np.diff(raw.start)) - WEEK * 604800.0
    for i in range(m):
        eph = ephs[int(raw.prn[i])]
        t_sv = t_rcv[i] - raw.pr_m[i] / C
        t_tx = t_sv
        for _ in range(4):
            t_tx = t_sv - sat_state(eph, t_tx)[2][0]
        p, v, c, d = sat_state(eph, t_tx)
        pos[i], vel[i], clk[i], drift[i] = p[0], v[0], C * c[0], C * d[0]
    return types.SimpleNamespace(pos_e=pos, vel_e=vel, clk_m=clk, drift_mps=drift, valid=np.ones(m, bool))


def _simulate(atmosphere=True, noise=(0.0, 0.0), seed=0):
    """RawEpochs, nav, states and the truth of a moving receiver; the pseudoranges carry I + T, the
    Doppler the carrier-phase rate −İ + Ṫ (central differences over ±H_RATE of the generator's
    geometry)."""
    ephs = _ephemerides()
    t = np.arange(N_EPOCHS) * DT_EPOCH
    atmo = AtmosphereModel("klobuchar" if atmosphere else "off", ALPHA, BETA,
                           "saastamoinen" if atmosphere else "off")
    sims = {}
    for h in (-H_RATE, 0.0, H_RATE):
        pos, vel, b, d = _truth(t + h)
        obs = simulate_observables(ephs, WEEK, TOW0, t + h, pos, vel, b, d, np.random.default_rng(seed),
                                   sigma_pr_m=noise[0], sigma_prr_mps=noise[1], mask_deg=0.0)
        sims[h] = (obs, *_delays(obs, pos, t + h, atmo))
    obs, iono, tropo = sims[0.0]
    rate = (-(sims[H_RATE][1] - sims[-H_RATE][1]) + (sims[H_RATE][2] - sims[-H_RATE][2])) / (2 * H_RATE)
    pr = obs.pr_m + iono + tropo
    rr = obs.prr_mps + rate
    vis = obs.visible
    pos, vel, b, d = _truth(t)
    raw = RawEpochs(t=gps_seconds(WEEK, TOW0 + t) + b / C,
                    start=np.concatenate([[0], np.cumsum(vis.sum(axis=1))]),
                    prn=np.broadcast_to(obs.prns, vis.shape)[vis], pr_m=pr[vis], doppler_hz=-rr[vis] / LAMBDA_L1,
                    cn0_dbhz=(35.0 + 12.0 * np.sin(obs.elev_rad))[vis])
    nav = NavData(path="test", version=3.04, ephemerides={p: [e] for p, e in ephs.items()}, ion_alpha=ALPHA,
                  ion_beta=BETA)
    truth = dict(pos=pos, vel=vel, clk=b, drift=d, iono=iono[vis], tropo=tropo[vis], elev=obs.elev_rad[vis],
                 los=obs.los_e[vis])
    return raw, nav, _states(raw, ephs), truth


@pytest.fixture(scope="module")
def sim():
    return _simulate()


@pytest.fixture(scope="module")
def sim_vacuum():
    return _simulate(atmosphere=False)


def test_innovations_vanish_at_the_truth(sim):
    raw, nav, states, truth = sim
    meas = TightMeasurements(raw, nav, states=states)
    assert np.array_equal(meas.t, raw.t)
    n_rows = 0
    for k in range(raw.n_epochs):
        r = meas.rows(k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
        assert r.n >= 6
        # 1 mm: RawEpochs' continuous GPS seconds resolve 0.24 µs, i.e. 0.2 mm of range at 800 m/s;
        # the rates agree to 0.01 mm/s (the delay rates: forward vs central differences)
        assert np.max(np.abs(r.dz_pr)) < 1e-3, k
        assert np.max(np.abs(r.dz_rr)) < 1e-4, k
        # the atmosphere of the prediction is AtmosphereModel's at the generator's geometry
        assert np.allclose(r.iono_m, truth["iono"][r.row], atol=1e-5)
        assert np.allclose(r.tropo_m, truth["tropo"][r.row], atol=1e-5)
        assert np.allclose(r.elev_rad, truth["elev"][r.row], atol=1e-7)
        assert np.allclose(r.los_e, truth["los"][r.row], atol=1e-9)
        n_rows += r.n
    assert n_rows > 6 * raw.n_epochs
    # the test is not vacuous: the delays are metres and the rows above the mask carry them
    assert np.max(truth["iono"]) > 3.0 and np.min(r.tropo_m) > 2.0


def test_atmosphere_enters_with_its_sign(sim):
    """Without the atmosphere in the model the innovations are exactly minus the delays (code) and
    minus the carrier delay rate (Doppler, ionosphere with the opposite sign)."""
    raw, nav, states, truth = sim
    full = TightMeasurements(raw, nav, states=states)
    bare = TightMeasurements(raw, nav, states=states, iono="off", tropo="off")
    k = 7
    args = (k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
    rf, rb = full.rows(*args), bare.rows(*args)
    assert np.array_equal(rf.row, rb.row)
    assert np.allclose(rb.dz_pr, -(truth["iono"][rb.row] + truth["tropo"][rb.row]), atol=1e-3)
    assert np.all(rb.iono_m == 0.0) and np.all(rb.tropo_m == 0.0)
    # the Doppler difference is the carrier delay rate: millimetres per second, not zero
    assert 1e-4 < np.max(np.abs(rb.dz_rr)) < 0.02
    assert np.max(np.abs(rf.dz_rr)) < 1e-3


def test_position_velocity_clock_errors_map_through_the_line_of_sight(sim_vacuum):
    raw, nav, states, truth = sim_vacuum
    meas = TightMeasurements(raw, nav, states=states, iono="off", tropo="off")
    k = 10
    d_r = 10.0 * np.array([0.48, -0.6, 0.64])           # 10 m along a known direction
    d_v = 0.5 * np.array([-0.36, 0.48, 0.8])
    r0 = meas.rows(k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
    r1 = meas.rows(k, truth["pos"][k] + d_r, truth["vel"][k], truth["clk"][k] + 25.0, truth["drift"][k])
    r2 = meas.rows(k, truth["pos"][k], truth["vel"][k] + d_v, truth["clk"][k], truth["drift"][k] - 3.0)
    assert np.array_equal(r0.row, r1.row) and np.array_equal(r0.row, r2.row)
    assert np.max(np.abs(r0.dz_pr)) < 1e-3
    # second-order term |δr|² / (2ρ) < 3 µm; the 1/(1 + ρ̇/c) factor on δv < 1e-5 relative
    assert np.allclose(r1.dz_pr, -r0.los_e @ d_r + 25.0, atol=1e-4)
    assert np.max(np.abs(r1.dz_pr - 25.0)) > 5.0                   # the geometry part is metres
    assert np.allclose(r2.dz_rr, -r0.los_e @ d_v - 3.0, atol=1e-5)
    assert np.array_equal(r2.dz_pr, r0.dz_pr)
    # a position error turns the line of sight: the rate changes by |v_sat − v| |δr| / ρ ≲ 2 mm/s
    assert np.max(np.abs(r1.dz_rr - r0.dz_rr)) < 2e-3


def test_initial_clock_recovers_the_clock(sim):
    raw, nav, states, truth = sim
    meas = TightMeasurements(raw, nav, states=states)
    for k in (0, 9, raw.n_epochs - 1):
        clk, drift = meas.initial_clock(k, truth["pos"][k], truth["vel"][k])
        assert clk == pytest.approx(truth["clk"][k], abs=1e-3)
        assert drift == pytest.approx(truth["drift"][k], abs=1e-3)
    # one pseudorange 300 m long (multipath, a wrong millisecond) does not pull the clock
    bad = raw.pr_m.copy()
    k = 4
    bad[raw.start[k] + 1] += 300.0
    raw_bad = RawEpochs(raw.t, raw.start, raw.prn, bad, raw.doppler_hz, raw.cn0_dbhz)
    clk, _ = TightMeasurements(raw_bad, nav, states=states).initial_clock(k, truth["pos"][k], truth["vel"][k])
    assert clk == pytest.approx(truth["clk"][k], abs=1e-3)


def test_initial_clock_with_noise_within_its_sigma():
    raw, nav, states, truth = _simulate(noise=(1.0, 0.05), seed=3)
    meas = TightMeasurements(raw, nav, states=states, sigma_pr_m=1.0, sigma_rr_mps=0.05)
    err_b, err_d = [], []
    for k in range(raw.n_epochs):
        clk, drift = meas.initial_clock(k, truth["pos"][k], truth["vel"][k])
        n = meas.rows(k, truth["pos"][k], truth["vel"][k], clk, drift).n
        err_b.append((clk - truth["clk"][k]) * math.sqrt(n) / 1.0)
        err_d.append((drift - truth["drift"][k]) * math.sqrt(n) / 0.05)
    # standardised errors of the mean: unit variance (21 samples: the RMS lies in [0.6, 1.5] at 99.9 %)
    assert 0.6 < np.sqrt(np.mean(np.square(err_b))) < 1.5
    assert 0.6 < np.sqrt(np.mean(np.square(err_d))) < 1.5


def test_keep_selects_the_highest_satellites(sim):
    raw, nav, states, truth = sim
    meas = TightMeasurements(raw, nav, states=states)
    k = 3
    args = (k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
    full = meas.rows(*args)
    for n in (1, 4, 5):
        r = meas.rows(*args, keep=n)
        assert r.n == n
        assert set(r.prn) == set(full.prn[np.argsort(-full.elev_rad)[:n]])
        assert np.array_equal(r.dz_pr, full.dz_pr[np.isin(full.prn, r.prn)])
    assert meas.rows(*args, keep=full.n + 3).n == full.n
    assert meas.rows(*args, keep=0).n == 0


def test_rows_dropped_and_doppler_missing(sim):
    raw, nav, states, truth = sim
    k = 5
    sl = raw.epoch(k)
    args = (k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
    base = TightMeasurements(raw, nav, states=states, mask_deg=0.0).rows(*args)
    assert base.n == sl.stop - sl.start
    assert np.min(base.elev_rad) < math.radians(10.0)            # some rows for the mask to drop
    masked = TightMeasurements(raw, nav, states=states).rows(*args)
    assert set(masked.row) == set(base.row[base.elev_rad >= math.radians(10.0)])
    # no ephemeris state, no pseudorange, low C/N0, PRN not selected, no Doppler
    valid = states.valid.copy()
    valid[sl.start] = False
    pr, dop = raw.pr_m.copy(), raw.doppler_hz.copy()
    pr[sl.start + 1] = np.nan
    dop[sl.start + 2] = np.nan
    raw2 = RawEpochs(raw.t, raw.start, raw.prn, pr, dop, raw.cn0_dbhz)
    st2 = types.SimpleNamespace(**{**vars(states), "valid": valid})
    cn0_cut = float(np.sort(raw.cn0_dbhz[sl])[1]) + 1e-9         # drops the two weakest rows
    skip_prn = int(raw.prn[sl.start + 3])
    sats = [p for p in range(1, 33) if p != skip_prn]
    r = TightMeasurements(raw2, nav, states=st2, mask_deg=0.0, cn0_min_dbhz=cn0_cut, sats=sats).rows(*args)
    weak = set(np.arange(sl.start, sl.stop)[raw.cn0_dbhz[sl] < cn0_cut])
    dropped = {sl.start, sl.start + 1, sl.start + 3} | weak
    assert set(r.row) == set(range(sl.start, sl.stop)) - dropped
    j = np.flatnonzero(r.row == sl.start + 2)
    if sl.start + 2 not in dropped:
        assert not r.rr_ok[j[0]] and np.isnan(r.dz_rr[j[0]]) and np.isinf(r.sigma_rr[j[0]])
        assert abs(r.dz_pr[j[0]]) < 1e-3
    assert r.rr_ok.sum() == r.n - (0 if sl.start + 2 in dropped else 1)


def test_noise_model_closed_form(sim):
    raw, nav, states, truth = sim
    noise = TightNoise()
    meas = TightMeasurements(raw, nav, states=states, mask_deg=0.0)
    k = 2
    r = meas.rows(k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
    s = np.sin(r.elev_rad)
    f = 10.0 ** ((45.0 - r.cn0_dbhz) / 10.0)
    var_pr = 0.3 ** 2 + (0.3 / s) ** 2 + 0.5 ** 2 * f + (0.5 * r.iono_m) ** 2 + (0.3 / (s + 0.1)) ** 2
    assert np.allclose(r.sigma_pr, np.sqrt(var_pr), rtol=1e-12)
    assert np.allclose(r.sigma_rr, LAMBDA_L1 * np.sqrt(0.1 ** 2 + 0.15 ** 2 * f), rtol=1e-12)
    # lower and weaker satellites weigh less
    lo, hi = np.argmin(r.elev_rad), np.argmax(r.elev_rad)
    assert r.sigma_pr[lo] > 2.0 * r.sigma_pr[hi] and r.sigma_rr[lo] > r.sigma_rr[hi]
    # missing C/N0: the C/N0 terms at the reference
    assert noise.sigma_rr(np.nan) == pytest.approx(LAMBDA_L1 * math.hypot(0.1, 0.15))
    # overrides
    rc = TightMeasurements(raw, nav, states=states, mask_deg=0.0, sigma_pr_m=2.5, sigma_rr_mps=0.07).rows(
        k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
    assert np.all(rc.sigma_pr == 2.5) and np.all(rc.sigma_rr == 0.07)
    rn = TightMeasurements(raw, nav, states=states, mask_deg=0.0, noise=TightNoise(pr_a_m=1.0, pr_b_m=0.0,
                           pr_cn0_m=0.0, iono_frac=0.0, tropo_zenith_m=0.0)).rows(
        k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
    assert np.allclose(rn.sigma_pr, 1.0)


def test_spp_recovers_the_truth(sim):
    raw, nav, states, truth = sim
    meas = TightMeasurements(raw, nav, states=states)
    for k in (0, 12):
        fix = meas.spp(k)
        assert fix.ok, fix.reason
        assert np.linalg.norm(fix.pos_e - truth["pos"][k]) < 1e-3
        assert np.linalg.norm(fix.vel_e - truth["vel"][k]) < 1e-3
        assert fix.clk_m == pytest.approx(truth["clk"][k], abs=1e-3)
        assert fix.drift_mps == pytest.approx(truth["drift"][k], abs=1e-3)
        assert 1.0 < fix.pdop < 10.0 and fix.rms_pr_m < 1e-3
    three = TightMeasurements(raw, nav, states=states, sats=list(np.unique(raw.prn))[:3]).spp(0)
    assert not three.ok and "need 4" in three.reason and np.all(np.isnan(three.pos_e))


def test_bad_input_is_one_clear_error(sim):
    raw, nav, states, truth = sim
    with pytest.raises(ConfigError, match="ionosphere model"):
        TightMeasurements(raw, nav, states=states, iono="nequick")
    with pytest.raises(ConfigError, match="mask_deg"):
        TightMeasurements(raw, nav, states=states, mask_deg=float("nan"))
    with pytest.raises(ConfigError, match="mask_deg"):
        TightMeasurements(raw, nav, states=states, mask_deg=None)
    with pytest.raises(ConfigError, match="cn0_min_dbhz"):
        TightMeasurements(raw, nav, states=states, cn0_min_dbhz="high")
    with pytest.raises(ConfigError, match="sigma_pr_m"):
        TightMeasurements(raw, nav, states=states, sigma_pr_m=-1.0)
    with pytest.raises(ConfigError, match="pr_b_m"):
        TightNoise(pr_b_m=float("inf"))
    short = types.SimpleNamespace(**{**vars(states), "clk_m": states.clk_m[:-1]})
    with pytest.raises(ConfigError, match="clk_m"):
        TightMeasurements(raw, nav, states=short)
    meas = TightMeasurements(raw, nav, states=states)
    with pytest.raises(FilterError, match="epoch"):
        meas.rows(raw.n_epochs, truth["pos"][0], truth["vel"][0], 0.0, 0.0)
    with pytest.raises(FilterError, match="pos_e"):
        meas.rows(0, [np.nan, 0.0, 0.0], truth["vel"][0], 0.0, 0.0)


def test_with_the_satellite_states_of_obs_geometry(sim):
    """The default states (ultratight.signals.obs_geometry.sat_states) agree with the test's own
    transmit-time evaluation and give the same zero innovations."""
    raw, nav, states, truth = sim
    st = sat_states(raw, nav)
    assert st.valid.all()
    # 1 mm: the transmit time in continuous GPS seconds resolves 0.24 µs (satellites move 3.9 km/s)
    assert np.max(np.abs(st.pos_e - states.pos_e)) < 1e-3
    assert np.max(np.abs(st.clk_m - states.clk_m)) < 1e-3
    meas = TightMeasurements(raw, nav)
    for k in (0, raw.n_epochs - 1):
        r = meas.rows(k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
        assert r.n >= 6
        assert np.max(np.abs(r.dz_pr)) < 2e-3 and np.max(np.abs(r.dz_rr)) < 1e-4


# ------------------------------------------------------------------ the real u-blox log
# walk_0827 (shared/data/README.md): RXM-RAWX at 4 Hz, RXM-SFRBX, NAV-PVT; gnss_1730_sf.pos is the
# receiver's own RTK solution (its lat/lon equal NAV-PVT's).  Its height column equals NAV-PVT's
# hMSL (height above mean sea level), not the ellipsoidal height: the test adds the geoid
# undulation the receiver states in the same messages (NAV-PVT height − hMSL = −21.39 m here).
WALK = "real-imu-gnss/walk_0827"
GPS_EPOCH = datetime.datetime(1980, 1, 6)


def _read_pos(path):
    """(t GPS s, lat deg, lon deg, height m, Q, vn, ve, vu) rows of an RTKLIB .pos file (GPST)."""
    out = []
    for line in path.read_text().splitlines():
        if line.startswith("%") or not line.strip():
            continue
        f = line.split()
        t = (datetime.datetime.strptime(f[0] + " " + f[1], "%Y/%m/%d %H:%M:%S.%f") - GPS_EPOCH).total_seconds()
        out.append([t, float(f[2]), float(f[3]), float(f[4]), float(f[5]), float(f[15]), float(f[16]), float(f[17])])
    return np.array(out)


@pytest.fixture(scope="module")
def walk(shared_data):
    ubx = pytest.importorskip("ultratight.signals.ubx")
    folder = shared_data / WALK
    if not (folder / "gnss_1730.ubx").is_file() or not (folder / "gnss_1730_sf.pos").is_file():
        pytest.skip(f"walk_0827 data not found in {folder}")
    log = ubx.read_ubx(folder / "gnss_1730.ubx", signals="l1")      # the L1 C/A rows as recorded
    pos = _read_pos(folder / "gnss_1730_sf.pos")
    undulation = np.array([(m.height - m.hMSL) / 1000.0 for m in log.nav_pvt])
    assert np.ptp(undulation) < 0.01
    ref = []                                   # (k, pos_e, vel_e, speed) at the fixed epochs
    for row in pos[pos[:, 4] == 1]:
        k = int(np.argmin(np.abs(log.raw.t - row[0])))
        assert abs(log.raw.t[k] - row[0]) < 0.01          # epochs match within the receiver clock
        lat, lon = math.radians(row[1]), math.radians(row[2])
        p_e = llh_to_ecef(lat, lon, row[3] + undulation[0])
        v_e = dcm_ecef_from_enu(lat, lon) @ np.array([row[6], row[5], row[7]])
        ref.append((k, p_e, v_e, math.hypot(row[5], row[6])))
    return log, ref


def test_real_ublox_prediction_equals_rtklib(walk, shared_data):
    """The predicted pseudorange (broadcast orbit and clock with T_GD, Sagnac, Saastamoinen) of the
    u-blox log equals RTKLIB's (satpos + geodist + tropmodel on RTKLIB's own decoding of the
    same file) to 1 mm at the RTK positions."""
    p = pytest.importorskip("pyrtklib", reason="pyrtklib (RTKLIB binding) not installed")
    log, ref = walk
    rraw = p.raw_t()
    p.init_raw(rraw, p.STRFMT_UBX)
    for b in (shared_data / WALK / "gnss_1730.ubx").read_bytes():
        p.input_ubx(rraw, b)
    nav_r = rraw.nav
    ephs = {nav_r.eph[i].sat: nav_r.eph[i] for i in range(nav_r.n) if 1 <= nav_r.eph[i].sat <= 32}
    # the L1 C/A rows of the satellites with an LNAV set (RTKLIB decodes LNAV only); no ionosphere
    # model on either side
    meas = TightMeasurements(log.raw, log.nav, iono="off", sats=sorted(ephs))
    n = 0
    for k, p_e, _, _ in ref[::60]:
        r = meas.rows(k, p_e, np.zeros(3), 0.0, 0.0)
        rr, llh = p.Arr1Ddouble(3), p.Arr1Ddouble(3)
        for a in range(3):
            rr[a] = p_e[a]
        p.ecef2pos(rr, llh)
        week = int(log.raw.t[k] // 604800)
        t_rcv = p.gpst2time(week, log.raw.t[k] - week * 604800)
        for j in range(r.n):
            prn, pr = int(r.prn[j]), float(log.raw.pr_m[r.row[j]])
            t_tx = p.timeadd(t_rcv, -pr / C)
            t_tx = p.timeadd(t_tx, -p.eph2clk(t_tx, ephs[prn]))
            rs, dts, var, svh = p.Arr1Ddouble(6), p.Arr1Ddouble(2), p.Arr1Ddouble(1), p.Arr1Dint(1)
            p.satpos(t_tx, t_rcv, prn, 0, nav_r, rs, dts, var, svh)
            e, azel = p.Arr1Ddouble(3), p.Arr1Ddouble(2)
            rng = p.geodist(rs, rr, e)
            p.satazel(llh, e, azel)
            pred = rng - C * (dts[0] - ephs[prn].tgd[0]) + p.tropmodel(t_rcv, llh, azel, 0.7)
            assert r.dz_pr[j] + pr == pytest.approx(pred, abs=1e-3)
            # RTKLIB's line of sight is not rotated by Ω_E τ ≈ 5e-6 rad (it adds Sagnac as a range term)
            assert r.elev_rad[j] == pytest.approx(azel[1], abs=1e-5)
            n += 1
    assert n >= 20


def test_real_ublox_residuals_at_rtk_positions(walk):
    """At the fixed RTK epochs, after the clock of initial_clock: pseudorange residuals of metres,
    Doppler residuals of centimetres per second (static start) to decimetres (walking; the
    reference velocity is the receiver's filtered NAV-PVT velocity).  Measured (2026-11-26): RMS
    4.98 m over 1396 rows (four satellites with a complete ephemeris in the 134 s log, no
    Klobuchar page, so no ionosphere model), Doppler 0.167 m/s, 0.0184 m/s while static, clock
    slope against the Doppler drift 0.061 m/s; the bounds are 1.2 × those."""
    log, ref = walk
    # the four satellites with a complete LNAV set in the log, without an ionosphere model, as measured
    meas = TightMeasurements(log.raw, log.nav, iono="off", sats=[10, 23, 27, 32])
    pr, rr, rr_static, clock = [], [], [], []
    for k, p_e, v_e, speed in ref:
        clk, d = meas.initial_clock(k, p_e, v_e)
        clock.append((log.raw.t[k], clk, d))
        r = meas.rows(k, p_e, v_e, clk, d)
        assert r.n >= 4
        pr.append(r.dz_pr)
        rr.append(r.dz_rr[r.rr_ok])
        if speed < 0.05:
            rr_static.append(r.dz_rr[r.rr_ok])
    pr, rr, rr_static = (np.concatenate(x) for x in (pr, rr, rr_static))
    rms = (lambda x: float(np.sqrt(np.mean(x ** 2))))
    assert pr.size > 1000 and rr_static.size > 100
    assert 1.0 < rms(pr) < 6.0
    assert rms(rr) < 0.2
    assert rms(rr_static) < 0.022
    # the Doppler drift is the rate of the pseudorange clock (signs and units of the range-rate
    # model): over 10 s spans, the bias slope and the mean drift agree (the oscillator runs from
    # −60 to −81 m/s over the log)
    t, b, d = np.array(clock).T
    j = np.searchsorted(t, t + 10.0)
    i = np.flatnonzero((j < t.size) & (np.abs(t[np.minimum(j, t.size - 1)] - t - 10.0) < 0.01))
    slope = (b[j[i]] - b[i]) / (t[j[i]] - t[i])
    mean_d = np.array([np.mean(d[a:c + 1]) for a, c in zip(i, j[i])])
    assert i.size > 100 and np.ptp(d) > 10.0
    assert rms(slope - mean_d) < 0.075


def test_missing_klobuchar_coefficients_are_reported(sim):
    raw, nav, states, truth = sim
    bare_nav = NavData(path="test", version=3.04, ephemerides=nav.ephemerides)
    meas = TightMeasurements(raw, bare_nav, states=states)
    assert any("Klobuchar" in w for w in meas.warnings)
    assert not TightMeasurements(raw, nav, states=states).warnings
    k = 1
    r = meas.rows(k, truth["pos"][k], truth["vel"][k], truth["clk"][k], truth["drift"][k])
    assert np.all(r.iono_m == 0.0) and np.all(r.tropo_m > 2.0)
    assert np.allclose(r.dz_pr, -truth["iono"][r.row], atol=1e-3)


def test_rows_serve_a_cold_least_squares_start(sim):
    """From the Earth's centre (no horizon: every row, NaN elevation, no atmosphere) a Gauss–Newton
    iteration on the rows alone converges to the truth."""
    raw, nav, states, truth = sim
    meas = TightMeasurements(raw, nav, states=states)
    k = 8
    r = meas.rows(k, np.zeros(3), np.zeros(3), 0.0, 0.0)
    sl = raw.epoch(k)
    assert r.n == sl.stop - sl.start and np.all(np.isnan(r.elev_rad)) and np.all(r.iono_m == 0.0)
    assert np.all(np.isfinite(r.sigma_pr)) and np.all(np.isfinite(r.dz_pr))
    pos, clk = np.zeros(3), 0.0
    for _ in range(10):
        r = meas.rows(k, pos, truth["vel"][k], clk, truth["drift"][k])
        A = np.hstack([-r.los_e, np.ones((r.n, 1))])
        d = np.linalg.lstsq(A, r.dz_pr, rcond=None)[0]
        pos, clk = pos - d[:3], clk - d[3]
    assert np.linalg.norm(pos - truth["pos"][k]) < 1e-3 and clk == pytest.approx(truth["clk"][k], abs=1e-3)
