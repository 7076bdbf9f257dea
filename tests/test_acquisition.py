"""Acquisition on synthetic signals with known PRN, Doppler, code phase and C/N0."""

import dataclasses
import math

import numpy as np
import pytest

from ultratight.constants import CA_LEN, F_CA, F_L1
from ultratight.errors import ConfigError
from ultratight.receiver.dsp.acquisition import acquire, cell_threshold
from ultratight.receiver.dsp.correlator import CorrelatorBank, estimate_sigma_arm
from ultratight.signals.ca_code import ca_code
from ultratight.signals.corr_model import amplitude_from_cn0, signal_amplitude


def make_signal(sats, fs, n, rng, if_hz=0.0, complex_sampling=True, sigma=1.0, data_bits=False):
    """Sum of C/A signals (prn, doppler_hz, code_phase0_chips, cn0_dbhz) in white noise."""
    t = np.arange(n) / fs
    x = np.zeros(n, dtype=complex if complex_sampling else float)
    for prn, fd, cp0, cn0 in sats:
        a = float(signal_amplitude(cn0, fs, sigma, complex_sampling))
        p = cp0 + t * F_CA * (1.0 + fd / F_L1)
        c = ca_code(prn)[np.floor(p).astype(np.int64) % CA_LEN].astype(float)
        if data_bits:
            bits = rng.choice([-1.0, 1.0], size=int(n / fs / 0.02) + 2)
            c = c * bits[np.floor(t / 0.02 + rng.uniform()).astype(np.int64)]
        ph = 2 * np.pi * (if_hz + fd) * t + rng.uniform(0, 2 * np.pi)
        x += a * c * (np.exp(1j * ph) if complex_sampling else np.cos(ph))
    if complex_sampling:
        x += sigma * (rng.standard_normal(n) + 1j * rng.standard_normal(n))
        return x.astype(np.complex64)
    x += sigma * rng.standard_normal(n)
    return x.astype(np.float32)


def code_err(a, b):
    return (a - b + CA_LEN / 2) % CA_LEN - CA_LEN / 2


SATS = [(3, 2345.6, 512.3, 46.0), (14, -7321.0, 11.8, 41.0), (27, 9012.0, 1000.4, 38.0)]


def test_all_prns_complex_4mhz():
    rng = np.random.default_rng(101)
    fs = 4.0e6
    x = make_signal(SATS, fs, int(fs * 0.012), rng, data_bits=True)
    res = acquire(x, fs, 0.0, True, coherent_ms=1, noncoherent=10)
    assert [r.prn for r in res] == list(range(1, 33))
    det = {r.prn: r for r in res if r.detected}
    assert set(det) == {s[0] for s in SATS}
    for prn, fd, cp0, cn0 in SATS:
        r = det[prn]
        assert abs(r.doppler_hz - fd) < 30.0, (prn, r.doppler_hz)
        assert abs(code_err(r.code_phase_chips, cp0)) < 0.06, (prn, r.code_phase_chips)
        # C/N0 from 10 x 1 ms power sums: sd of the estimate ~ sqrt((4 + 4 A^2)/10)/A^2 (relative)
        a2 = float(amplitude_from_cn0(cn0, 1e-3)) ** 2
        sd_db = 10 / math.log(10) * math.sqrt((4 + 4 * a2) / 10) / a2
        assert r.cn0_dbhz == pytest.approx(cn0, abs=3 * sd_db + 0.3), (prn, r.cn0_dbhz, sd_db)
        assert r.metric > r.threshold and r.sample_index == 0
    for r in res:
        if not r.detected:
            assert r.metric <= r.threshold and math.isnan(r.cn0_dbhz)


def test_results_do_not_depend_on_the_threads():
    """The PRNs are searched on one thread per allowed core by default; one thread (``workers=1``) and
    two give the same results, field by field, in PRN order."""
    rng = np.random.default_rng(7)
    fs = 2.6e6
    x = make_signal(SATS, fs, int(fs * 0.012), rng)
    one = acquire(x, fs, 0.0, True, noncoherent=10, workers=1)
    two = acquire(x, fs, 0.0, True, noncoherent=10, workers=2)
    assert [r.prn for r in two] == list(range(1, 33))
    for a, b in zip(one, two, strict=True):
        np.testing.assert_equal(dataclasses.asdict(a), dataclasses.asdict(b))     # NaN C/N0 where not detected
    assert {3, 14} <= {r.prn for r in two if r.detected}      # the 46 and 41 dB-Hz ones: not trivial


def test_real_if_non_multiple_rate_and_start_sample():
    rng = np.random.default_rng(7)
    fs, if_hz = 5.3e6, 1.3e6
    sats = [(8, -1234.0, 700.25, 45.0)]
    start = 12345
    x = make_signal(sats, fs, int(fs * 0.02), rng, if_hz=if_hz, complex_sampling=False)
    res = acquire(x, fs, if_hz, False, prns=[8, 9], coherent_ms=2, noncoherent=4, start_sample=start)
    r8, r9 = res
    assert r8.detected and not r9.detected
    assert abs(r8.doppler_hz + 1234.0) < 20.0
    # code phase refers to sample `start`
    cp_start = 700.25 + start / fs * F_CA * (1 - 1234.0 / F_L1)
    assert abs(code_err(r8.code_phase_chips, cp_start)) < 0.06
    assert r8.sample_index == start
    assert r8.cn0_dbhz == pytest.approx(45.0, abs=1.0)


def test_lag_drift_compensation_long_noncoherent():
    """fs*1ms not an integer: the peak drifts ~0.5 sample per block; 20 blocks still find a weak signal."""
    rng = np.random.default_rng(8)
    fs = 4.0925e6
    sats = [(21, 8800.0, 333.3, 36.0)]
    x = make_signal(sats, fs, int(fs * 0.021), rng)
    r = acquire(x, fs, 0.0, True, prns=[21], coherent_ms=1, noncoherent=20)[0]
    assert r.detected
    assert abs(code_err(r.code_phase_chips, 333.3)) < 0.1
    assert abs(r.doppler_hz - 8800.0) < 40.0


def test_high_decimated_rate():
    rng = np.random.default_rng(9)
    fs, if_hz = 16.368e6, 4.092e6
    sats = [(5, 4100.0, 77.7, 44.0)]
    x = make_signal(sats, fs, int(fs * 0.011), rng, if_hz=if_hz, complex_sampling=False)
    r = acquire(x, fs, if_hz, False, prns=[5, 6], coherent_ms=1, noncoherent=10)
    assert r[0].detected and not r[1].detected
    assert abs(code_err(r[0].code_phase_chips, 77.7)) < 0.08
    assert abs(r[0].doppler_hz - 4100.0) < 30.0
    assert r[0].cn0_dbhz == pytest.approx(44.0, abs=1.5)   # boxcar decimation loss < 0.5 dB


def test_assisted_window():
    rng = np.random.default_rng(10)
    fs = 4.0e6
    sats = [(11, 8100.0, 250.0, 42.0), (19, -6400.0, 40.0, 42.0)]
    x = make_signal(sats, fs, int(fs * 0.011), rng)
    pred = {11: 8000.0, 19: -5000.0}
    res = acquire(x, fs, 0.0, True, prns=[11, 19], doppler_center_hz=pred, doppler_range_hz=500.0)
    r11, r19 = res
    assert r11.detected and abs(r11.doppler_hz - 8100.0) < 30.0
    assert r11.n_doppler_bins <= 3                   # +-500 Hz at 667 Hz bins
    assert not r19.detected                          # truth (-6400 Hz) outside the -5000 +- 500 Hz window
    res = acquire(x, fs, 0.0, True, prns=[19], doppler_center_hz=pred, doppler_range_hz={19: 1500.0})
    assert res[0].detected and abs(res[0].doppler_hz + 6400.0) < 30.0


def test_noise_only_false_alarm_rate():
    """With pfa = 0.2 per search, noise-only searches alarm at most ~pfa (Sidak bound is conservative)."""
    rng = np.random.default_rng(12)
    fs, n_trials = 2.046e6, 150
    alarms = 0
    for _ in range(n_trials):
        x = (rng.standard_normal(2046 * 3) + 1j * rng.standard_normal(2046 * 3)).astype(np.complex64)
        r = acquire(x, fs, 0.0, True, prns=[1], doppler_range_hz=1000.0, coherent_ms=1, noncoherent=3,
                    pfa=0.2, refine=False)[0]
        alarms += r.detected
    rate = alarms / n_trials
    # binomial sd at p=0.2 over 150 trials is 0.033
    assert 0.03 <= rate <= 0.27, rate


def test_noise_only_no_detection_all_prns():
    rng = np.random.default_rng(13)
    x = (rng.standard_normal(40000) + 1j * rng.standard_normal(40000)).astype(np.complex64)
    res = acquire(x, 4.0e6, 0.0, True, coherent_ms=1, noncoherent=10)
    assert not any(r.detected for r in res)
    assert all(r.k_eff == pytest.approx(10.0, rel=0.1) for r in res)


def test_cell_threshold_closed_form():
    # K = 1: the cell metric is exponential, P(X > t) = exp(-t)
    pfa, m = 1e-3, 10000
    pc = 1 - (1 - pfa) ** (1 / m)
    assert cell_threshold(pfa, m, 1) == pytest.approx(-math.log(pc), rel=1e-9)
    # K = 2: P(X > t) = exp(-2t)(1 + 2t) for chi2(4)/4
    t = cell_threshold(pfa, m, 2)
    assert math.exp(-2 * t) * (1 + 2 * t) == pytest.approx(pc, rel=1e-6)


def test_acquisition_initialises_correlator():
    """Acquisition output (code phase at sample_index, Doppler) puts the correlator on the peak."""
    rng = np.random.default_rng(14)
    fs = 4.0e6
    sats = [(3, 2345.6, 512.3, 48.0)]
    x = make_signal(sats, fs, int(fs * 0.03), rng)
    r = acquire(x, fs, 0.0, True, prns=[3], coherent_ms=1, noncoherent=10)[0]
    bank = CorrelatorBank([3], fs, 0.0, True)
    bank.init_channel(0, 3, r.code_phase_chips, r.doppler_hz, r.sample_index)
    out, _, _, nd = bank.run_epochs(x, 0, estimate_sigma_arm(x, True), max_epochs=20)
    z = out[0, :nd[0]]
    p_pow = np.mean(z[:, 0] ** 2 + z[:, 3] ** 2) - 2.0
    a = float(amplitude_from_cn0(48.0, 1e-3))
    assert 10 * np.log10(p_pow / a ** 2) == pytest.approx(0.0, abs=1.0)
    e_pow = np.mean(z[:, 1] ** 2 + z[:, 4] ** 2)
    l_pow = np.mean(z[:, 2] ** 2 + z[:, 5] ** 2)
    assert abs(e_pow - l_pow) / (e_pow + l_pow) < 0.15    # centred on the peak


@pytest.mark.parametrize("kwargs,word", [
    (dict(fs_hz=0.0), "fs_hz"), (dict(fs_hz=-1.0), "fs_hz"),
    (dict(coherent_ms=11), "coherent_ms"), (dict(coherent_ms=1.5), "coherent_ms"),
    (dict(coherent_ms=0), "coherent_ms"), (dict(noncoherent=0), "noncoherent"),
    (dict(noncoherent=20), "too short"), (dict(pfa=0.0), "pfa"), (dict(pfa=1.5), "pfa"),
    (dict(prns=[33]), "PRN"), (dict(doppler_range_hz=-5.0), "doppler_range_hz"),
    (dict(doppler_range_hz=3e6), "fs/2"), (dict(doppler_center_hz={1: 0.0}), "missing"),
])
def test_bad_parameters(kwargs, word):
    x = np.ones(40000, np.complex64)
    args = dict(fs_hz=4.0e6, if_hz=0.0, is_complex=True, prns=[1, 2], coherent_ms=1, noncoherent=10)
    args.update(kwargs)
    with pytest.raises(ConfigError, match=word):
        acquire(x, **args)


def test_real_input_needs_if():
    with pytest.raises(ConfigError, match="if_hz"):
        acquire(np.ones(40000, np.float32), 4.0e6, 0.0, False, prns=[1])


def test_predicted_doppler_matches_range_rate():
    """Assisted-mode centres: Doppler = -d(pseudorange)/dt / lambda (finite difference, nominal constellation)."""
    from ultratight.constants import LAMBDA_L1
    from ultratight.ins.earth import llh_to_ecef
    from ultratight.receiver.dsp.acquisition import predicted_doppler
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.geometry import light_time, visible_prns
    week, tow = 2190, 518400.0
    ephs = nominal_ephemerides(week, tow)
    pos = np.asarray(llh_to_ecef(np.radians(40.0), np.radians(3.0), 100.0), dtype=float)
    vis = visible_prns(ephs, pos, week, tow, 5.0)
    assert len(vis) >= 4
    pred = predicted_doppler(ephs, pos, week, tow, prns=vis)
    for p in vis:
        lt = light_time(ephs[p], np.stack([pos, pos]), np.zeros((2, 3)), week, np.array([tow - 0.5, tow + 0.5]))
        rr = float(np.diff(np.asarray(lt["pseudorange_m"]))[0])
        assert pred[p] == pytest.approx(-rr / LAMBDA_L1, abs=1.0)
        assert abs(pred[p]) < 6000.0


def test_cw_interference_is_excised():
    """A CW tone as strong as the whole noise: excised, the signal is still found, no false alarm."""
    rng = np.random.default_rng(15)
    fs = 4.0e6
    n = int(fs * 0.011)
    x = make_signal([(3, 2345.6, 512.3, 42.0)], fs, n, rng)
    t = np.arange(n) / fs
    x = (x + 1.0 * np.exp(2j * np.pi * 300000.0 * t)).astype(np.complex64)   # tone power = noise power
    res = acquire(x, fs, 0.0, True, prns=[3, 4, 5, 6], coherent_ms=1, noncoherent=10)
    assert [r.detected for r in res] == [True, False, False, False]
    assert 1 <= res[0].n_excised_bins <= 40          # the tone and its leakage in the 1/3-bin-mixed spectra
    assert abs(res[0].doppler_hz - 2345.6) < 30.0
    assert abs(code_err(res[0].code_phase_chips, 512.3)) < 0.06
    # C/N0 from the cleaned signal: the tone does not count as noise (it would bias C/N0 by -1.8 dB)
    a2 = float(amplitude_from_cn0(42.0, 1e-3)) ** 2
    sd_db = 10 / math.log(10) * math.sqrt((4 + 4 * a2) / 10) / a2
    assert res[0].cn0_dbhz == pytest.approx(42.0, abs=3 * sd_db + 0.3)


@pytest.mark.parametrize("frontend", [
    {"frontend.bits": 2},
    {"frontend.sampling": "real", "frontend.if_hz": 4.092e6, "frontend.fs_hz": 16.368e6,
     "frontend.format": "i8", "frontend.bits": 2},
])
def test_generator_scenario_truth(tmp_path, frontend):
    """The project's IF generator (2-bit, all visible satellites at 40 dB-Hz): the detected set is the
    truth set and Doppler / code phase match the logged truth at sample 0."""
    import h5py

    from ultratight.receiver.cli import scenario_config as scen
    from ultratight.signals.recording import iffile
    from ultratight.signals.synth import generator as gen
    cfg = scen.load_scenario("static-open-sky", {"duration_s": 0.012, "satellites.cn0_dbhz": 40.0, **frontend})
    paths = gen.generate(cfg, tmp_path, "acq", seed=3, progress=False)
    res = acquire(iffile.open_if(paths["if"]))
    with h5py.File(paths["truth"], "r") as f:
        prns = [int(p) for p in f.attrs["prn"]]
        cp_true = f["code_phase_chips"][0]
        fd_true = f["doppler_hz"][0]
    assert {r.prn for r in res if r.detected} == set(prns)
    for r in res:
        if r.prn in prns:
            k = prns.index(r.prn)
            assert abs(r.doppler_hz - fd_true[k]) < 40.0, (r.prn, r.doppler_hz, fd_true[k])
            assert abs(code_err(r.code_phase_chips, cp_true[k])) < 0.08, (r.prn, r.code_phase_chips, cp_true[k])
            assert 36.0 < r.cn0_dbhz < 42.0                 # 40 dB-Hz minus the 2-bit loss, +- noise
