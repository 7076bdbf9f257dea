"""The compiled epoch runner of the ultra-tight engine (receiver.epochs): the epochs it runs with the
channels spread over threads, and those it runs one at a time, give the same results; the stop
conditions come at the same epochs as a one-epoch loop's; the NCO interface is explicit."""

import numpy as np
import pytest

from ultratight.errors import FilterError
from ultratight.fusion.channel.innerloop import InnerLoop
from ultratight.fusion.channel.prefilter import PrefilterBank
from ultratight.receiver.deep.options import EngineOptions, epoch_threads
from ultratight.receiver.cli.scenario_config import load_scenario
from ultratight.receiver.cli.scenario_runner import prepare_data, run_method
from ultratight.signals.nco import NcoBank

CUT = {"duration_s": 1.2, "frontend.fs_hz": 2.046e6, "satellites.max_count": 4}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    cfg = load_scenario("paper-highdyn", CUT)
    paths, _ = prepare_data(cfg, 5, tmp_path_factory.mktemp("epochs"))
    return cfg, paths


@pytest.mark.parametrize("method", ["dlb-rackf", "pb-kf-utc"])
def test_threads_give_the_serial_results(data, method):
    cfg, paths = data
    serial, _ = run_method(paths, cfg, method, 5, options=EngineOptions(threads=1))
    par, _ = run_method(paths, cfg, method, 5, options=EngineOptions(threads=2))
    assert serial.info["threads"] == 1
    assert par.info["threads"] == min(2, __import__("numba").config.NUMBA_NUM_THREADS)
    assert serial.doppler_hz.shape[0] > 1000
    for k in ("t_start", "doppler_hz", "code_phase_chips", "amp", "mode", "nav_pos_e", "nav_vel_e", "nav_clk"):
        np.testing.assert_array_equal(getattr(par, k), getattr(serial, k), err_msg=k)
    assert par.info["n_tight_updates"] == serial.info["n_tight_updates"] > 5


def test_every_epoch_through_the_one_epoch_path_gives_the_same_results(data):
    """The lock monitor in 'gate' mode sends every epoch through the one-epoch path; with thresholds
    it never crosses it changes nothing, so the results equal the compiled runner's."""
    cfg, paths = data
    fast, _ = run_method(paths, cfg, "dlb-ckf", 5, options=EngineOptions(threads=1))
    slow, _ = run_method(paths, cfg, "dlb-ckf", 5, options=EngineOptions(threads=1, monitor_gates_tight=True,
                                                                         lock_off_dbhz=-40.0))
    assert slow.info["timing_s"]["epochs"] == 0.0 and fast.info["timing_s"]["epochs"] > 0.0
    for k in ("doppler_hz", "code_phase_chips", "nav_pos_e", "nav_clk"):
        np.testing.assert_allclose(slow.__dict__[k], fast.__dict__[k], rtol=0, atol=1e-12, err_msg=k)


def test_epoch_threads_policy():
    assert epoch_threads(1) == 1
    assert epoch_threads(64) >= 1
    assert epoch_threads(0) in (1, __import__("numba").config.NUMBA_NUM_THREADS)


def test_inner_loop_takes_an_nco_bank_only():
    bank = PrefilterBank(2, kind="ckf")
    bank.reset([0, 1])
    law = InnerLoop(2)

    class Lookalike:
        code_phase = np.zeros(2)
        code_rate = np.zeros(2)
        carr_phase = np.zeros(2)
        carr_freq = np.zeros(2)

    with pytest.raises(FilterError, match="NcoBank"):
        law.apply(bank, Lookalike())
    nco = NcoBank(2, if_hz=0.0, chip_rate_hz=1.023e6)
    bank.x[:, 3] = 2 * np.pi * 5.0
    law.apply(bank, nco)
    np.testing.assert_allclose(nco.carr_freq, 5.0)
    np.testing.assert_allclose(nco.code_rate, 1.023e6 * (1 + 5.0 / 1575.42e6))


def test_scalar_receiver_threads_give_the_serial_results(tmp_path):
    """`process` with its channels spread over threads gives the one-thread fixes and tracking."""
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.recording.iffile import open_if
    # the scenario without atmosphere (the receiver's corrections are off) and at TOW 518400, a frame
    # start, so that the time of week is decoded at ~7.3 s and the 8.5 s give fixes
    cfg = load_scenario("static-open-sky", {"duration_s": 8.5, "frontend.fs_hz": 2.046e6, "satellites.max_count": 5,
                                            "time.tow_s": 518400.0, "atmosphere.iono": "off",
                                            "atmosphere.tropo": "off", "atmosphere.broadcast": False})
    paths, _ = prepare_data(cfg, 2, tmp_path)
    ephs = nominal_ephemerides(int(cfg["time"]["week"]), float(cfg["time"]["tow_s"]))
    runs = []
    for par in (False, True):
        pc = ProcessConfig(n_channels=5, record_epochs=True, iono="off", tropo="off", acq_min_cn0_dbhz=30.0,
                           parallel=par)
        runs.append(process(open_if(paths["if"]), pc, ephemerides=ephs))
    one, two = runs
    assert len(one.fixes) > 3 and len(one.fixes) == len(two.fixes)
    for a, b in zip(one.fixes, two.fixes):
        np.testing.assert_array_equal(a["pos_e"], b["pos_e"])
    assert sorted(one.epochs) == sorted(two.epochs)
    for prn in one.epochs:
        np.testing.assert_array_equal(one.epochs[prn]["doppler_hz"], two.epochs[prn]["doppler_hz"])


def test_the_kernels_compiled_ahead_are_the_ones_the_engine_calls(data):
    """receiver.deep.compile_ahead declares the epoch chain's signatures (a second worker compiles them
    on a first run): its records are those run_epochs is called with, and after a run nothing it
    declares needs compiling — each is the engine's own entry in numba's cache."""
    from numba.core import event

    from ultratight.receiver.deep import compile_ahead, epochs

    cfg, paths = data
    run_method(paths, cfg, "dlb-rackf", 5, options=EngineOptions(threads=1))
    # run_epochs(k_ep, src, corr, wipe, bank, outer, window, rec, law, sig, burst)
    assert [tuple(s[1:]) for s in epochs.run_epochs.signatures] == [compile_ahead._records()]

    compiled = []

    class Counter(event.Listener):
        def on_start(self, ev):
            compiled.append(ev.data["dispatcher"].py_func.__name__)

        def on_end(self, ev):
            pass

    counter = Counter()
    event.register("numba:compile", counter)
    try:
        for fn, sig in compile_ahead.kernels():
            fn.compile(sig)
    finally:
        event.unregister("numba:compile", counter)
    assert compiled == []
    assert len(compile_ahead.kernels()) == 4
