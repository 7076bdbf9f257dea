"""High-dynamic start of the scalar receiver (process --dynamics high).

* the Doppler-rate search (receiver.acquisition.doppler_rate_search) on a synthetic chirp with
  random data bits and noise at 30 dB-Hz, against the Doppler and rate it was made with;
* on paper-highdyn (100 m/s^2 East from t = 0) at 30 dB-Hz: acquisition + rate search of all 13
  satellites against the generator's truth;
* the scalar hand-over pass of the ultra-tight start-up (receiver.handover.scalar_pass) on
  the same recording: every satellite acquired and tracked to 12 s, a hand-over fix inside the
  window, fixes within their stated sigmas of the true trajectory.
"""

import math
import re

import h5py
import numpy as np
import pytest

from ultratight.receiver.dsp.acquisition import acquire, doppler_rate_search
from ultratight.receiver.cli import main
from ultratight.signals.signal import GPS_L1CA

FS_HZ = 2.046e6
CN0_DBHZ = 30.0


class _ArraySource:
    """A complex baseband sample array seen as an IF source."""

    def __init__(self, x, fs_hz):
        self.x = x
        self.fs_hz = fs_hz
        self.if_hz = 0.0
        self.is_complex = True
        self.n_samples = x.shape[0]

    def read(self, start, count):
        return self.x[start:start + count]


def _chirp_signal(prn, f0, rate, cp0, cn0_dbhz, seconds, seed):
    """C/A signal with Doppler f0 + rate t, code phase cp0 at sample 0, random 50 bit/s data, unit
    complex noise per arm: C/N0 = A^2 fs / 2."""
    rng = np.random.default_rng(seed)
    n = int(seconds * FS_HZ)
    t = np.arange(n) / FS_HZ
    code = np.asarray(GPS_L1CA.code(prn), float)
    cyc = f0 * t + 0.5 * rate * t * t
    chips = cp0 + GPS_L1CA.chip_rate_hz * (t + cyc / GPS_L1CA.carrier_hz)
    bit_edge0 = rng.uniform(0.0, 0.02)
    bits = rng.choice([-1.0, 1.0], size=int(seconds / 0.02) + 2)
    d = bits[np.floor((t + bit_edge0) / 0.02).astype(int)]
    amp = math.sqrt(2.0 * 10.0 ** (cn0_dbhz / 10.0) / FS_HZ)
    s = amp * d * code[np.floor(chips).astype(np.int64) % 1023] * np.exp(2j * np.pi * (cyc + rng.uniform()))
    noise = rng.standard_normal(n) + 1j * rng.standard_normal(n)
    return (s + noise).astype(np.complex64)


@pytest.mark.parametrize("rate,df_acq,seed", [(525.0, 60.0, 1), (-300.0, -110.0, 2), (0.0, 20.0, 3)])
def test_rate_search_recovers_doppler_and_rate(rate, df_acq, seed):
    """From a Doppler off by an acquisition-like error (up to 110 Hz, beyond the 100 Hz alias of
    5 ms squared sums), the search returns the Doppler to 1.5 Hz and the rate to 25 Hz/s."""
    f0, cp0 = 2345.6, 321.3
    src = _ArraySource(_chirp_signal(7, f0, rate, cp0, CN0_DBHZ, 0.45, seed), FS_HZ)
    r = doppler_rate_search(src, 7, f0 + df_acq, cp0, 0, span_s=0.4)
    assert abs(r.doppler_hz - f0) < 1.5, (r.doppler_hz - f0)
    assert abs(r.rate_hz_s - rate) < 25.0, (r.rate_hz_s, rate)
    assert r.metric > 10.0


def test_rate_search_noise_only_metric_is_low():
    """No signal: the surface peak over its mean stays at the level of the largest of its cells
    (exponential cells: ~ln(cells) ~ 13), below the 30 dB-Hz signal's (> 10 with margin 2x)."""
    rng = np.random.default_rng(9)
    n = int(0.45 * FS_HZ)
    x = (rng.standard_normal(n) + 1j * rng.standard_normal(n)).astype(np.complex64)
    r = doppler_rate_search(_ArraySource(x, FS_HZ), 7, 1000.0, 100.0, 0, span_s=0.4)
    sig = doppler_rate_search(_ArraySource(_chirp_signal(7, 1000.0, 400.0, 100.0, 33.0, 0.45, 4), FS_HZ),
                              7, 1010.0, 100.0, 0, span_s=0.4)
    assert sig.metric > 2.0 * r.metric


def _highdyn(tmp_path_factory, name, duration_s):
    from ultratight.config import locate_scenario
    d = tmp_path_factory.mktemp(name)
    txt, n = re.subn(r"\[\[noise_events\]\][^\[]*", "", locate_scenario("paper-highdyn").read_text())
    assert n == 1
    (d / "hd.toml").write_text(txt)
    assert main(["generate", str(d / "hd.toml"), "--duration", str(duration_s), "--fs", str(FS_HZ), "--cn0",
                 str(CN0_DBHZ), "--out", str(d / "hd"), "--no-progress"]) == 0
    return d / "hd"


@pytest.fixture(scope="module")
def short_rec(tmp_path_factory):
    return _highdyn(tmp_path_factory, "hd30_short", 1.0)


def test_highdyn_acquisition_and_rate_against_truth(short_rec):
    """paper-highdyn at 30 dB-Hz, 10 g from t = 0: the high-dynamics acquisition (5 ms x 16, floor
    25 dB-Hz) finds all 13 satellites; the rate search puts each within 2 Hz and 30 Hz/s of the
    generator's Doppler and Doppler rate (up to ~525 Hz/s)."""
    from ultratight.signals.recording.iffile import open_if
    src = open_if(str(short_rec) + ".ci16")
    with h5py.File(str(short_rec) + ".truth.h5") as tr:
        prns = [int(p) for p in tr.attrs["prn"]]
        ts, dop = tr["t_s"][()], tr["doppler_hz"][()]
    res = acquire(src, prns=prns, doppler_range_hz=10e3, coherent_ms=5, noncoherent=16, pfa=1e-3)
    assert all(a.detected for a in res), [a.prn for a in res if not a.detected]
    rates = []
    for a in res:
        j = prns.index(a.prn)
        r = doppler_rate_search(src, a.prn, a.doppler_hz, a.code_phase_chips, a.sample_index, span_s=0.4)
        t0 = a.sample_index / src.fs_hz
        true_rate = np.polyfit(ts[(ts >= t0) & (ts < t0 + 0.4)], dop[(ts >= t0) & (ts < t0 + 0.4), j], 1)[0]
        assert abs(r.doppler_hz - np.interp(t0, ts, dop[:, j])) < 2.0, a.prn
        assert abs(r.rate_hz_s - true_rate) < 30.0, (a.prn, r.rate_hz_s, true_rate)
        rates.append(true_rate)
    assert max(np.abs(rates)) > 450.0          # the scenario does stress the loops


def test_highdyn_30dbhz_scalar_handover(tmp_path_factory):
    """The scalar pass of the ultra-tight start-up at 30 dB-Hz under 10 g (--dynamics high): all 13
    satellites acquired and tracked to the end of the 12 s window (Doppler within 5 Hz RMS of the
    truth over its last second), a hand-over fix (3 consecutive fixes, >= 5 satellites) inside
    the window, and the fixes within 3 stated sigmas of the true trajectory, their RMS at the
    figures docs/process.md measures on this recording."""
    from ultratight.receiver.deep.handover import HandoverConfig, pick_fix, scalar_pass
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.recording.iffile import open_if
    base = _highdyn(tmp_path_factory, "hd30_long", 13.0)
    src = open_if(str(base) + ".ci16")
    cfg = HandoverConfig(dynamics="high", acq_min_cn0_dbhz=25.0, acq_coherent_ms=5, acq_noncoherent=16)
    res = scalar_pass(src, nominal_ephemerides(src.start_week, src.start_tow_s), None, 0.0, cfg)
    with h5py.File(str(base) + ".truth.h5") as tr, h5py.File(str(base) + ".traj.h5") as g:
        prns = [int(p) for p in tr.attrs["prn"]]
        ts, dop = tr["t_s"][()], tr["doppler_hz"][()]
        tt, pos_t, vel_t = g["t"][()], g["pos_e"][()], g["vel_e"][()]
    chans = {c["prn"]: c for c in res.channels}
    assert sorted(p for p, c in chans.items() if c["tracked"]) == sorted(prns)
    for p in prns:
        e = res.epochs[p]
        t = e["sample_index"] / src.fs_hz
        assert t[-1] > 11.9 and chans[p]["losses"] == 0, p
        late = t > t[-1] - 1.0
        err = e["doppler_hz"][late] - np.interp(t[late], ts, dop[:, prns.index(p)])
        assert np.sqrt(np.mean(err ** 2)) < 5.0, p
    k = pick_fix(res.fixes, 0.1, cfg)
    assert k is not None and res.fixes[k]["t_s"] < 12.0
    f = res.fixes
    tf = np.array([x["sample_index"] / src.fs_hz for x in f])
    pe = np.array([x["pos_e"] for x in f]) - np.stack([np.interp(tf, tt, pos_t[:, i]) for i in range(3)], 1)
    ve = np.array([x["vel_e"] for x in f]) - np.stack([np.interp(tf, tt, vel_t[:, i]) for i in range(3)], 1)
    e_p, e_v = np.linalg.norm(pe, axis=1), np.linalg.norm(ve, axis=1)
    sp, sv = np.array([x["sigma_pos_m"] for x in f]), np.array([x["sigma_vel_mps"] for x in f])
    assert np.all(e_p < 3.0 * sp), (e_p.max(), sp.min())
    assert np.all(e_v < 3.0 * sv), (e_v.max(), sv.min())
    # docs/process.md "High dynamics", measured table, 30 dB-Hz row: fix errors vs truth position 5.0 m
    # RMS, velocity 0.13 m/s RMS (47 fixes).  This run (seed 1): 5.04 m, 0.130 m/s; seeds 1-3: 5.0-7.5 m,
    # 0.130-0.153 m/s.  Bounds = documented x 1.8 (9.0 m, 0.234 m/s): above every seed, a doubling breaks them
    assert np.sqrt(np.mean(e_p ** 2)) < 1.8 * 5.0, np.sqrt(np.mean(e_p ** 2))
    assert np.sqrt(np.mean(e_v ** 2)) < 1.8 * 0.13, np.sqrt(np.mean(e_v ** 2))


def _energy_sync(ip, cpb=20):
    from ultratight.receiver.dsp.tracking_block import _bit_sync_energy
    bse = np.zeros((1, 2 * cpb + 1))
    for e, v in enumerate(ip):
        k = _bit_sync_energy(0, float(v), e, bse, cpb)
        if k >= 0:
            return k, e
    return -1, len(ip)


@pytest.mark.parametrize("edge,cn0", [(7, 30.0), (0, 27.5), (19, 25.0)])
def test_bit_energy_sync_finds_the_edge(edge, cn0):
    """1 ms prompts of a phase-locked 50 bit/s signal (A = sqrt(2 C/N0 T), unit noise) with bit
    edges at epochs = edge (mod 20): the energy test declares that edge, within the time its 6-sigma
    rule predicts (N >= 18 / (m A^2 p^2) bits, p ~ 0.5 transitions per bit: 1.3 s at 30 dB-Hz,
    4 s at 25) plus margin."""
    rng = np.random.default_rng(int(cn0 * 10) + edge)
    n = 12000
    bits = rng.choice([-1.0, 1.0], size=n // 20 + 2)
    a = math.sqrt(2.0 * 10.0 ** (cn0 / 10.0) * 1e-3)
    e = np.arange(n)
    ip = a * bits[(e - edge + 20) // 20] + rng.standard_normal(n)
    k, at = _energy_sync(ip)
    assert k == edge
    assert at < {30.0: 2500, 27.5: 4000, 25.0: 7000}[cn0], at


def test_bit_energy_sync_not_declared_on_noise_or_unmodulated_carrier():
    """No signal, or a carrier without data transitions (every offset has the same energy): no edge
    is declared in 20 s."""
    rng = np.random.default_rng(11)
    assert _energy_sync(rng.standard_normal(20000))[0] == -1
    assert _energy_sync(1.4 + rng.standard_normal(20000))[0] == -1
