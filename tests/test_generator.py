"""IF generator against its own logged truth, with an independent correlator written here.

Satellites are stand-in circular-orbit ephemerides built in this file (no dependence on the
constellation module); the receiver trajectory comes from ultratight.ins.trajectory.
"""

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest

from ultratight.constants import CA_LEN, F_CA, F_L1, LAMBDA_L1, OMEGA_E
from ultratight.errors import ConfigError
from ultratight.ins.trajectory import build_trajectory
from ultratight.signals.ca_code import ca_code
from ultratight.signals.ephemeris import Ephemeris
from ultratight.signals.synth import generator
from ultratight.signals.synth.generator import generate
from ultratight.signals.synth.synthesis import SignalPlan, eval_poly
from ultratight.signals.recording.iffile import open_if

TOW0 = 518400.0
WEEK = 2190


def stand_in_eph(prn, dlon_deg, inc_deg=0.0, raan_deg=0.0):
    """Circular orbit whose satellite is near longitude dlon_deg (equator) at TOW0."""
    return Ephemeris(prn=prn, week=WEEK, toe=TOW0, toc=TOW0, sqrt_a=math.sqrt(26560e3), e=0.0,
                     i0=math.radians(inc_deg), omega0=math.radians(raan_deg), omega=0.0,
                     m0=math.radians(dlon_deg - raan_deg) + OMEGA_E * TOW0, af0=1e-5, af1=1e-11)


def base_cfg(**kw):
    cfg = {"duration_s": 1.0, "seed": 7, "time": {"week": WEEK, "tow_s": TOW0},
           "receiver": {"lat_deg": 0.0, "lon_deg": 0.0, "h_m": 100.0},
           "trajectory": {"kind": "static"},
           "satellites": {"cn0_dbhz": [35.0, 45.0, 45.0]},
           "frontend": {"fs_hz": 4e6, "if_hz": 0.0, "sampling": "complex", "format": "ci8", "bits": 8},
           "nav": {"data_bits": False}}
    for k, v in kw.items():
        if isinstance(v, dict) and isinstance(cfg.get(k), dict):
            cfg[k] = {**cfg[k], **v}
        else:
            cfg[k] = v
    return cfg


EPHS = [stand_in_eph(5, -35.0), stand_in_eph(12, 15.0, 55.0, 20.0), stand_in_eph(24, 40.0, 30.0, -10.0)]


def epoch_outputs(src, truth, s, n_epochs, prn=None, dtau=0.0, ddop=0.0, chunk=100):
    """Prompt correlation per row (interval) with a linear replica from the row's truth."""
    fs, L = src.fs_hz, int(truth.attrs["samples_per_row"])
    prn = int(truth.attrs["prn"][s]) if prn is None else prn
    code = ca_code(prn).astype(np.float64)
    t = np.arange(L) / fs
    out = np.empty(n_epochs, complex)
    for j0 in range(0, n_epochs, chunk):
        m = min(chunk, n_epochs - j0)
        x = src.read(j0 * L, m * L).reshape(m, L)
        cp = truth["code_phase_chips"][j0:j0 + m, s][:, None]
        dop = truth["doppler_hz"][j0:j0 + m, s][:, None] + ddop
        ph0 = truth["carrier_phase_cycles"][j0:j0 + m, s][:, None]
        n0 = ((j0 + np.arange(m)) * L)[:, None]
        chips = cp + dtau + F_CA * (1.0 + dop / F_L1) * t
        rep = code[np.floor(chips).astype(np.int64) % CA_LEN]
        ph = 2 * np.pi * (np.mod(src.if_hz * (n0 + np.arange(L)) / fs, 1.0) + np.mod(ph0, 1.0) + dop * t)
        out[j0:j0 + m] = np.sum(x * rep * np.exp(-1j * ph), axis=1)
    return out


def normalised(src, truth, s, n_epochs, **kw):
    """Prompt outputs scaled to unit noise per arm (noise measured with an absent PRN)."""
    p = epoch_outputs(src, truth, s, n_epochs, **kw)
    noise = epoch_outputs(src, truth, s, n_epochs, prn=32)
    sig_arm = np.sqrt(np.mean(np.abs(noise) ** 2) / 2.0)
    return p / sig_arm


def cn0_estimate(p_norm, t_int=1e-3):
    return 10 * np.log10((np.mean(np.abs(p_norm) ** 2) - 2.0) / (2.0 * t_int))


@pytest.fixture(scope="module")
def gen_complex(tmp_path_factory):
    d = tmp_path_factory.mktemp("gen")
    res = generate(base_cfg(), d, "c", ephemerides=EPHS, progress=False)
    src = open_if(res["if"])
    truth = h5py.File(res["truth"], "r")
    yield res, src, truth
    truth.close()
    src.close()


def test_outputs_and_sidecar(gen_complex):
    res, src, truth = gen_complex
    assert src.fmt == "ci8" and src.n_samples == 4_000_000
    assert src.start_week == WEEK and src.start_tow_s == TOW0
    assert truth["code_phase_chips"].shape == (1000, 3)
    assert list(truth.attrs["prn"]) == [5, 12, 24]
    assert "config_json" in truth.attrs and "version" in truth.attrs
    np.testing.assert_array_equal(truth["sample_index"][:3], [0, 4000, 8000])
    assert set(res) >= {"if", "meta", "truth", "summary"}


@pytest.mark.parametrize("s,cn0", [(0, 35.0), (1, 45.0), (2, 45.0)])
def test_cn0_matches_configuration(gen_complex, s, cn0):
    _, src, truth = gen_complex
    p = normalised(src, truth, s, 1000)
    est = cn0_estimate(p)
    assert abs(est - cn0) < 0.5, est
    # truth carrier phase: the prompt sits on the I axis (no data bits here)
    assert abs(np.angle(np.mean(p))) < 0.05


def test_peak_at_truth_code_and_doppler(gen_complex):
    _, src, truth = gen_complex
    s, n = 1, 100
    grid = np.arange(-0.06, 0.0601, 0.005)
    mag = [abs(np.sum(epoch_outputs(src, truth, s, n, dtau=d))) for d in grid]
    assert abs(grid[int(np.argmax(mag))]) <= 0.02
    # Doppler: coherent sum over 200 ms with a residual frequency offset
    n = 200
    p = epoch_outputs(src, truth, s, n)
    t = np.arange(n) * 1e-3
    fgrid = np.arange(-40.0, 40.01, 0.5)
    spec = [abs(np.sum(p * np.exp(-2j * np.pi * f * t))) for f in fgrid]
    assert abs(fgrid[int(np.argmax(spec))]) <= 10.0


def test_truth_doppler_is_carrier_rate(gen_complex):
    _, _, truth = gen_complex
    ph = truth["carrier_phase_cycles"][:, 0]
    dop = truth["doppler_hz"][:, 0]
    rate = np.diff(ph) / 1e-3
    np.testing.assert_allclose(rate, 0.5 * (dop[1:] + dop[:-1]), atol=1e-3)
    pr = truth["pseudorange_m"][:, 0]
    np.testing.assert_allclose(ph, -pr / LAMBDA_L1, rtol=0, atol=1e-6)


def test_reproducible_with_seed(tmp_path):
    cfg = base_cfg(duration_s=0.01)
    a = generate(cfg, tmp_path, "a", ephemerides=EPHS, progress=False)
    b = generate(cfg, tmp_path, "b", ephemerides=EPHS, progress=False)
    c = generate(cfg, tmp_path, "c", seed=8, ephemerides=EPHS, progress=False)
    assert a["if"].read_bytes() == b["if"].read_bytes()
    assert a["if"].read_bytes() != c["if"].read_bytes()


def test_truth_rows_held_and_written_in_batches_equal_row_by_block(tmp_path, monkeypatch):
    """The truth writer holds rows and writes them in batches: the file is the same whatever the
    batch size (here one block per write against the default), to the last bit."""
    cfg = base_cfg(duration_s=0.35)
    a = generate(cfg, tmp_path, "a", ephemerides=EPHS, progress=False, write_if=False)
    monkeypatch.setattr(generator._TruthWriter, "FLUSH_ROWS", 1)
    b = generate(cfg, tmp_path, "b", ephemerides=EPHS, progress=False, write_if=False)
    with h5py.File(a["truth"], "r") as fa, h5py.File(b["truth"], "r") as fb:
        assert set(fa) == set(fb) and fa["t_s"].shape[0] == 350
        for k in fa:
            np.testing.assert_array_equal(fa[k][()], fb[k][()])


def test_noise_event_lowers_effective_cn0(tmp_path):
    cfg = base_cfg(duration_s=0.6, satellites={"cn0_dbhz": 45.0},
                   noise_events=[{"t0_s": 0.3, "t1_s": 0.6, "noise_factor": 4.0}])
    res = generate(cfg, tmp_path, "ev", ephemerides=EPHS[1:2], progress=False)
    with open_if(res["if"]) as src, h5py.File(res["truth"], "r") as truth:
        cn0 = truth["cn0_dbhz"][:, 0]
        assert np.allclose(cn0[:300], 45.0) and np.allclose(cn0[300:], 45.0 - 20 * np.log10(4.0))
        p = epoch_outputs(src, truth, 0, 600)
        noise = epoch_outputs(src, truth, 0, 600, prn=32)
        # each half normalised by its own noise level (the AGC rescales the quantiser input)
        for sl in (slice(0, 300), slice(300, 600)):
            sig = np.sqrt(np.mean(np.abs(noise[sl]) ** 2) / 2)
            est = cn0_estimate(p[sl] / sig)
            assert abs(est - cn0[sl][0]) < 0.6, (sl, est)


def test_fixed_gain_keeps_the_noise_burst_in_the_samples(tmp_path):
    """frontend.gain = "fixed": no AGC, the headroom defaults to the loudest noise event, and
    the file's sample power rises by factor^2 during the event (the AGC would hold it)."""
    ev = [{"t0_s": 0.1, "t1_s": 0.2, "noise_factor": 4.0}]
    fe = {"format": "ci16", "bits": 16, "gain": "fixed"}
    sats = {"cn0_dbhz": 45.0}
    res = generate(base_cfg(duration_s=0.2, frontend=fe, noise_events=ev, satellites=sats), tmp_path, "fx",
                   ephemerides=EPHS[1:2], progress=False)
    meta = json.loads(Path(res["meta"]).read_text())
    assert meta["frontend"]["gain"] == "fixed" and meta["frontend"]["headroom"] == 4.0
    assert meta["frontend"]["noise_lsb"] == pytest.approx(8191.75 / 4.0)
    agc = generate(base_cfg(duration_s=0.2, frontend={"format": "ci16", "bits": 16}, noise_events=ev,
                            satellites={"cn0_dbhz": 45.0}),
                   tmp_path, "agc", ephemerides=EPHS[1:2], progress=False)
    n = 400_000
    with open_if(res["if"]) as a, open_if(agc["if"]) as b:
        pa = [np.mean(np.abs(a.read(s0, n)) ** 2) for s0 in (0, n)]
        pb = [np.mean(np.abs(b.read(s0, n)) ** 2) for s0 in (0, n)]
    assert pa[1] / pa[0] == pytest.approx(16.0, rel=0.02)
    assert pa[0] == pytest.approx(2 * (8191.75 / 4.0) ** 2, rel=0.02)
    assert pb[1] / pb[0] == pytest.approx(1.0, rel=0.02)


def test_real_if_with_inversion(tmp_path):
    cfg = base_cfg(duration_s=0.4, satellites={"cn0_dbhz": 45.0},
                   frontend={"fs_hz": 10e6, "if_hz": 2.3e6, "sampling": "real", "format": "i8",
                             "bits": 8, "inversion": True})
    res = generate(cfg, tmp_path, "r", ephemerides=EPHS[:1], progress=False)
    with open_if(res["if"]) as src, h5py.File(res["truth"], "r") as truth:
        assert src.if_hz == pytest.approx(5e6 - 2.3e6)
        p = normalised(src, truth, 0, 400)
        assert abs(cn0_estimate(p) - 45.0) < 0.5
        assert abs(np.angle(np.mean(p))) < 0.05


def test_complex_inversion_and_2bit(tmp_path):
    cfg = base_cfg(duration_s=0.4, satellites={"cn0_dbhz": 45.0},
                   frontend={"format": "ci2packed", "bits": 2, "inversion": True})
    res = generate(cfg, tmp_path, "q", ephemerides=EPHS[:1], progress=False)
    with open_if(res["if"]) as src, h5py.File(res["truth"], "r") as truth:
        x = src.read(0, 1000)
        assert set(np.unique(x.real)) <= {-3.0, -1.0, 1.0, 3.0}
        p = normalised(src, truth, 0, 400)
        # 2-bit quantisation with thresholds at 1 sigma loses ~0.55 dB
        assert abs(cn0_estimate(p) - (45.0 - 0.55)) < 0.5
        assert abs(np.angle(np.mean(p))) < 0.05


def test_nav_bits_follow_transmit_time(tmp_path, monkeypatch):
    """Data bits come from lnav.nav_bits aligned to the satellite transmit time: a stand-in
    nav_bits with a known pattern must show up, bit for bit, in 20 ms coherent sums."""
    pattern = np.random.default_rng(3).choice(np.array([-1, 1], np.int8), size=10000)

    def nav_bits(eph, week, tow_start_s, n_bits):
        k0 = int(round(tow_start_s / 0.02)) - int(TOW0 / 0.02) + 5000
        return pattern[k0:k0 + n_bits]

    monkeypatch.setattr(generator, "nav_bits", nav_bits)     # the generator's lnav.nav_bits
    cfg = base_cfg(duration_s=0.3, satellites={"cn0_dbhz": 45.0}, nav={"data_bits": True})
    res = generate(cfg, tmp_path, "nb", ephemerides=EPHS[1:2], progress=False)
    with open_if(res["if"]) as src, h5py.File(res["truth"], "r") as truth:
        p = epoch_outputs(src, truth, 0, 300)
        tx = truth["t_tx_tow_s"][:, 0]
        cp = truth["code_phase_chips"][:, 0]
        epoch = np.rint((tx - cp / F_CA) / 1e-3).astype(np.int64)
        want = pattern[epoch // 20 - int(TOW0 / 0.02) + 5000]
        np.testing.assert_array_equal(truth["nav_bit"][:, 0], want)
        # the prompt's sign follows the bit (epochs whose code period straddles a bit edge excluded)
        edge = np.diff(want, prepend=want[0]) != 0
        ok = ~(edge | np.roll(edge, -1))
        assert np.all(np.sign(p.real[ok]) == want[ok])
        assert len(np.unique(want)) == 2


def test_interpolation_exact_for_high_dynamics():
    """Quadratic interpolation over 1 ms vs direct light-time at random sample times, paper flight
    (20 g, 40 g/s jerk at 40-41 s): carrier < 1 mm, code < 3e-4 chips (TOW float resolution)."""
    traj_cfg = {"kind": "segments", "vel0_enu_mps": [0.0, 0.0, 0.0], "attitude": "velocity",
                "segments": [{"t0": 0.0, "acc_enu": [100.0, 4.0, 0.0], "jerk_enu": [0.0, 0.0, 0.0]},
                             {"t0": 20.0, "acc_enu": [100.0, 4.0, 0.0], "jerk_enu": [100.0, 0.0, 0.0]},
                             {"t0": 21.0, "acc_enu": [200.0, 4.0, 0.0], "jerk_enu": [0.0, 0.0, 0.0]},
                             {"t0": 40.0, "acc_enu": [200.0, 4.0, 0.0], "jerk_enu": [-400.0, 0.0, 0.0]},
                             {"t0": 41.0, "acc_enu": [-200.0, 4.0, 0.0], "jerk_enu": [0.0, 0.0, 0.0]}]}
    traj = build_trajectory(traj_cfg, {"lat_deg": 0.0, "lon_deg": 0.0, "h_m": 50000.0}, 60.0)
    fs = 4e6
    plan = SignalPlan(EPHS, 20.0, traj, WEEK, TOW0, fs, 0.0, True, clock_bias_m=3e4,
                      clock_drift_mps=50.0)
    rng = np.random.default_rng(0)
    worst_c, worst_p = 0.0, 0.0
    for t_s in (19.9995, 20.4, 40.0, 40.7, 55.0):
        j0 = int(t_s * 1000)
        coefs, _, starts, _ = plan.coefficients(j0, 3)
        i = rng.uniform(0, plan.L, size=(3, 20))
        pos = (j0 + np.arange(3))[:, None] * plan.L + i
        geo, _ = plan.geometry(pos.ravel())
        for s, g in enumerate(geo):
            code, carr = eval_poly(coefs[:, s, None, :], i)
            d_code = code - (g["code_phase_chips"].reshape(3, 20))
            d_code = (d_code + CA_LEN / 2) % CA_LEN - CA_LEN / 2
            direct_carr = g["carrier_phase_cycles"].reshape(3, 20) - starts[s]["carrier_phase_cycles"][:, None]
            d_carr = (carr - (coefs[:, s, None, 3] - 2**20)) - direct_carr
            worst_c = max(worst_c, np.max(np.abs(d_code)))
            worst_p = max(worst_p, np.max(np.abs(d_carr)) * LAMBDA_L1)
    assert worst_p < 1e-3, worst_p
    assert worst_c < 3e-4, worst_c


def test_bad_config(tmp_path):
    with pytest.raises(ConfigError, match="complex"):
        generate(base_cfg(frontend={"format": "i8"}), tmp_path, "x", ephemerides=EPHS, progress=False)
    with pytest.raises(ConfigError, match="bits"):
        generate(base_cfg(frontend={"format": "ci2packed", "bits": 8}), tmp_path, "x", ephemerides=EPHS,
                 progress=False)
    assert list(tmp_path.iterdir()) == []


def test_failure_leaves_no_files(tmp_path, monkeypatch):
    calls = {"n": 0}
    orig = generator._synth_complex

    def boom(*a):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return orig(*a)

    monkeypatch.setattr(generator, "_synth_complex", boom)
    with pytest.raises(KeyboardInterrupt):
        generate(base_cfg(duration_s=0.3), tmp_path, "x", ephemerides=EPHS, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_kernel_matches_direct_per_sample_synthesis():
    """The numba kernel's samples (no noise) against a direct evaluation of the signal model
    with a light-time solution at every sample, for a receiver under 20 g with jerk."""
    traj = build_trajectory({"kind": "segments", "vel0_enu_mps": [300.0, 0.0, 0.0], "attitude": "velocity",
                             "segments": [{"t0": 0.0, "acc_enu": [200.0, 4.0, 0.0],
                                           "jerk_enu": [-400.0, 0.0, 0.0]}]},
                            {"lat_deg": 0.0, "lon_deg": 0.0, "h_m": 1000.0}, 1.0)
    fs = 4.092e6
    plan = SignalPlan(EPHS, [45.0, 40.0, 50.0], traj, WEEK, TOW0, fs, 0.0, True, clock_bias_m=-2e4,
                      clock_drift_mps=30.0)
    bits_pattern = np.array([1, -1], np.int8)     # every bit edge flips the sign
    plan.bits = {int(p): (int(np.floor((TOW0 - 0.2) / 0.02)), np.tile(bits_pattern, 100)) for p in plan.prns}
    # pick a window in which satellite 0's data bit changes (bit edges every 20 C/A periods)
    _, ep_all, _, _ = plan.coefficients(300, 40)
    j0 = 300 + int(np.nonzero((ep_all[:, 0] + 1) % 20 == 0)[0][0]) - 1
    n_int = 3
    coefs, ep, _, _ = plan.coefficients(j0, n_int)
    bits = plan.bit_values(ep)
    out = np.zeros((n_int * plan.L, 2), np.float32)
    generator._synth_complex(out, plan.L, n_int, plan.codes, coefs, np.broadcast_to(plan.amp, (n_int, 3)).astype(np.float32),
                     bits, generator.COS_LUT, generator.SIN_LUT)
    got = out[:, 0] + 1j * out[:, 1]
    n = j0 * plan.L + np.arange(n_int * plan.L)
    geo, _ = plan.geometry(n.astype(float))
    want = np.zeros(len(n), complex)
    seen_bits = []
    for s, gk in enumerate(geo):
        chip = np.floor(gk["code_phase_chips"]).astype(int) % CA_LEN
        epoch = np.rint((gk["t_tx_tow"] - gk["code_phase_chips"] / F_CA) / 1e-3).astype(np.int64)
        first, b = plan.bits[int(plan.prns[s])]
        d = b[epoch // 20 - first]
        seen_bits.append(set(np.unique(d)))
        want += plan.amp[s] * d * ca_code(int(plan.prns[s]))[chip] * np.exp(2j * np.pi * gk["carrier_phase_cycles"])
    err = np.abs(got - want)
    # away from chip edges the only error is the 2048-entry phase table (<= pi/2048 rad)
    tol = 1.2 * np.sum(plan.amp) * np.pi / 2048
    bad = err > tol
    assert np.mean(bad) < 2e-3, np.mean(bad)
    assert np.mean(err) < 0.5 * tol
    assert seen_bits[0] == {-1, 1}
