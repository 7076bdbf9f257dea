"""The scalar receiver's stages take a signal description, not GPS constants.

A made-up second signal (2046-chip random codes at 2.046 Mchip/s on a 1561.098 MHz carrier, four
PRNs, 10 code periods per data bit) is synthesised here independently of the project's generator:
complex baseband ``a c(p(t)) exp(j 2 pi theta(t)) + n`` with the code phase coherent with the
carrier (``p = p0 + f_chip t + (f_chip / f_carrier)(theta - theta0)``), unit noise per component.
Acquisition must find its PRN, Doppler and code phase; the scalar tracking bank must lock on it
with 1 ms (2046-chip) epochs and follow the code and carrier of the truth. The stages' modules
import no GPS signal constant.
"""

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.receiver.dsp.acquisition import AcqResult, acquire
from ultratight.receiver.scalar.navdecode import ChannelNav, channel_nav
from ultratight.receiver.scalar.channels import allocate_channels
from ultratight.receiver.scalar.process_config import ProcessConfig
from ultratight.receiver.dsp.tracking import ScalarTracker
from ultratight.receiver.dsp.tracking_layout import (FL_PLL_LOCK, MODE_PULL, P_DOPP, R_CODE_PHASE, R_CODE_RATE, R_DOPP,
                                                 RI_FLAGS, RI_N, RI_PTR, STATE_NAMES)
from ultratight.signals.signal import GPS_L1CA, SignalDescription

FS = 5.0e6
CARRIER = 1561.098e6
CHIP_RATE = 2.046e6
N_CHIPS = 2046


def stub_code(prn):
    """A fixed random +-1 code per PRN (seeded by the PRN)."""
    return np.where(np.random.default_rng(1000 + int(prn)).random(N_CHIPS) < 0.5, -1.0, 1.0)


STUB = SignalDescription(name="stub 2046-chip", carrier_hz=CARRIER, chip_rate_hz=CHIP_RATE, code_length=N_CHIPS,
                         code=stub_code, prns=(1, 2, 3, 4), codes_per_bit=10, navigation="none")


def synth(dur, prn, cn0, fd, p0, theta0=0.3, seed=5):
    rng = np.random.default_rng(seed)
    n = int(round(FS * dur))
    t = np.arange(n) / FS
    theta = theta0 + fd * t
    p = p0 + CHIP_RATE * t + (CHIP_RATE / CARRIER) * (theta - theta0)
    c = stub_code(prn)[np.floor(p).astype(np.int64) % N_CHIPS]
    a = math.sqrt(2.0 * 10 ** (cn0 / 10) / FS)
    x = (a * c * np.exp(2j * np.pi * theta)).astype(np.complex64)
    x += (rng.normal(size=n) + 1j * rng.normal(size=n)).astype(np.complex64)
    return x, p


@pytest.fixture(scope="module")
def stub_signal():
    return synth(1.2, prn=3, cn0=47.0, fd=1234.0, p0=777.25)


def test_acquisition_takes_the_description(stub_signal):
    x, p = stub_signal
    res = acquire(x, fs_hz=FS, if_hz=0.0, prns=None, coherent_ms=1, noncoherent=10, signal=STUB)
    assert [r.prn for r in res] == [1, 2, 3, 4]                 # the description's PRNs
    found = [r for r in res if r.detected]
    assert [r.prn for r in found] == [3]
    r = found[0]
    assert abs(r.doppler_hz - 1234.0) < 30.0
    # code phase at the first sample, in the stub's 2046 chips
    err = (r.code_phase_chips - p[0] + N_CHIPS / 2) % N_CHIPS - N_CHIPS / 2
    assert abs(err) < 0.25
    # the GPS C/A description searches other codes: nothing is found in the same samples
    assert not any(g.detected for g in acquire(x, fs_hz=FS, if_hz=0.0, prns=[1, 2, 3, 4], coherent_ms=1,
                                               noncoherent=10, signal=GPS_L1CA))
    with pytest.raises(ConfigError, match="PRN"):
        acquire(x, fs_hz=FS, if_hz=0.0, prns=[5], signal=STUB)


def test_tracking_takes_the_description(stub_signal):
    x, p = stub_signal
    tr = ScalarTracker(1, FS, 0.0, True, signal=STUB)
    assert tr.state.hist.shape == (1, 10)                       # bit-sync bins: codes per bit
    d = tr.describe()
    assert d["signal"] == STUB.name and d["track_pll_bw_hz"] == 15.0
    # start 100 Hz and 0.2 chip off the truth
    tr.start_channel(0, 3, (p[0] + 0.2) % N_CHIPS, 1134.0, 0, 45.0)
    rows_f, rows_i = [], []
    bl = int(0.1 * FS)
    while True:
        s = tr.next_needed_sample()
        if s is None or s >= len(x) - 12000:
            break
        rf, ri, nr = tr.run(x[s:s + bl], s, 1.0)
        rows_f.append(rf[0, :nr[0]])
        rows_i.append(ri[0, :nr[0]])
    rf, ri = np.concatenate(rows_f), np.concatenate(rows_i)
    # one record per 2046-chip period (1 ms: ~5000 samples at 5 MHz)
    assert np.all(np.abs(ri[:, RI_N] - FS * N_CHIPS / CHIP_RATE) <= 1)
    late = ri[:, RI_PTR] > 0.8 * FS
    assert late.sum() > 200 and np.all(ri[late, RI_FLAGS] & FL_PLL_LOCK)
    assert np.sqrt(np.mean((rf[late, R_DOPP] - 1234.0) ** 2)) < 3.0
    # the replica's code phase at each period start against the truth at that sample (chips of 2046)
    cp_err = (rf[late, R_CODE_PHASE] - p[ri[late, RI_PTR]] + N_CHIPS / 2) % N_CHIPS - N_CHIPS / 2
    assert np.sqrt(np.mean(cp_err ** 2)) < 0.05
    # the code NCO is aided by the stub's code/carrier ratio (the DLL correction averages ~0); L1's
    # ratio would leave 1234 Hz x (2.046e6/1561.098e6 - 1.023e6/1575.42e6) = 0.82 chip/s to the DLL
    aided = CHIP_RATE * (1.0 + rf[late, R_DOPP] / CARRIER)
    assert abs(np.mean(rf[late, R_CODE_RATE] - aided)) < 0.2
    # bank vocabulary: correct moves the NCO and loop frequency, reset restarts the loops in pull-in
    f0, d0 = tr.nco.carr_freq[0], tr.state.sf[0, P_DOPP]
    tr.correct([[2.5, 0.0]])
    assert tr.nco.carr_freq[0] == f0 + 2.5 and tr.state.sf[0, P_DOPP] == d0 + 2.5
    tr.reset([0], x0=[1200.0])
    assert tr.state.sf[0, P_DOPP] == 1200.0 and tr.state.mode(0) == MODE_PULL
    assert tr.STATE_NAMES[tr.P_DOPP] == STATE_NAMES[P_DOPP] == "doppler_hz"
    with pytest.raises(ConfigError, match="channel index"):
        tr.reset([1])


def test_channel_allocation_alone():
    def acq(prn, metric, detected=True):
        return AcqResult(prn=prn, doppler_hz=0.0, code_phase_chips=0.0, cn0_dbhz=45.0, metric=metric,
                         detected=detected, threshold=1.0, sample_index=0)
    res = [acq(1, 5.0), acq(2, 9.0), acq(3, 2.0, False), acq(4, 7.0)]
    found, idle = allocate_channels(res, ProcessConfig(n_channels=2), STUB)
    assert [a.prn for a in found] == [2, 4] and idle == []
    found, idle = allocate_channels(res, ProcessConfig(n_channels=None), STUB)
    assert [a.prn for a in found] == [2, 4, 1] and idle == [3]     # all in view: the description's PRNs


def test_navigation_decoder_by_name():
    nav = channel_nav(GPS_L1CA, 7)
    assert isinstance(nav, ChannelNav) and nav.prn == 7
    with pytest.raises(ConfigError, match="no navigation decoder for stub"):
        channel_nav(STUB, 3)


SIGNAL_CONSTANTS = {"F_L1", "F_CA", "CA_LEN", "T_CA", "CODE_PER_BIT", "LAMBDA_L1"}
RECEIVER = Path(__file__).resolve().parents[1] / "ultratight" / "receiver"
# every stage of the scalar receiver and the DSP it is built from, its writers and the runners
STAGE_MODULES = tuple(sorted(str(p.relative_to(RECEIVER).with_suffix("")) for room in ("dsp", "scalar", "io")
                             for p in (RECEIVER / room).glob("*.py") if p.name != "__init__.py")) + (
    "cli/metrics", "cli/scenario_runner", "cli/scenario_config", "cli/campaign")


@pytest.mark.parametrize("name", STAGE_MODULES)
def test_stage_modules_import_no_gps_signal_constant(name):
    path = RECEIVER / f"{name}.py"
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == "ultratight.constants":
            assert not SIGNAL_CONSTANTS & {a.name for a in node.names}, f"{name}.py imports {ast.dump(node)}"
