"""``ultratight scenario``: generate (or reuse) IMU + truth, stream (or cache) the IF, run each method,
paper metrics.

Cache: the generated files live in ``OUT/cache/<key>/`` where ``key`` is a hash of the
resolved scenario configuration (including the seed and any overrides) and the package
version, so a rerun with the same configuration reuses the data and any change regenerates it.

IF samples: by default (``cache=False``) the cache entry holds the truth, IMU and trajectory only, and the IF
is generated in memory, the samples of the IF file bit for bit: once per run, here, into a shared-memory
ring that the run's methods read at the same time, one worker process each (:mod:`ultratight.signals.synth.
ifring`, with several methods and the default workers), or by each method from its own generator
(:class:`ultratight.signals.synth.ifstream.GeneratedIf`, produced block by block on a worker thread while the
method tracks); ``cache=True`` (``--cache``) writes the IF file into the entry and the methods read it.

Per run (seed ``seed + r``) and method the engine runs on the *same* samples; the tracking errors are
estimate minus the generator's truth (``<stem>.truth.h5``, docs/generator.md) interpolated at each channel's
integration start (see :mod:`ultratight.receiver.cli.metrics`). The engine's own randomness (hot-start
errors) is seeded by the run seed, so every method of a run starts from the same perturbed INS state.

Outputs in ``OUT``: ``results.h5`` (per run and method: estimates, errors, arbitration modes,
navigation solution; attributes with the resolved configuration) and ``metrics.json``; PNG
figures like the paper's Fig. 4–7 when matplotlib is installed.
"""

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from ultratight import __version__, io_guard
from ultratight.errors import ConfigError
from ultratight.ins.imu_data import read_imu_h5
from ultratight.ins.trajectory import build_trajectory
from ultratight.io_guard import atomic_path, json_clean, note_complete, output_error, write_text_atomic
from ultratight.receiver.cli import metrics as M
from ultratight.receiver.dsp.burst import PLACE_IF, event_place
from ultratight.receiver.deep.options import EngineOptions, monitor_mode
from ultratight.receiver.deep.atmosphere_terms import scenario_model
from ultratight.receiver.deep.compile_ahead import compile_ahead
from ultratight.receiver.deep.engine import UltratightEngine
from ultratight.receiver.deep.methods import check_method, method_spec
from ultratight.receiver.deep.scalar_reference import run_scalar  # noqa: F401 (public here too)
from ultratight.receiver.cli.scenario_config import IMU_DEFAULTS, load_scenario
from ultratight.receiver.deep.startup import StartupErrors, perturb_state
from ultratight.cores import plan
from ultratight.receiver.cli.first_run import (drop_if_file, first_compilation, note_warm_cache, warm_cache_known,
                                               warm_key, write_if_ahead)
from ultratight.receiver.cli.scenario_data import (CACHE_VERSION, DATA_MODEL, NoSharedMemory,  # noqa: F401
                                                   _cache_lock, _cfg_key, _generator_cfg, load_truth,
                                                   prepare_data, shared_run_data)
from ultratight.receiver.cli.scenario_results import (SCHEMA, deflate_pool, pack_result,  # noqa: F401 (SCHEMA: public here)
                                                      write_results_h5)
from ultratight.receiver.cli.workers import (WorkerPool, check_workers, fix_mmap_threshold, process_age_s,
                                             release_heap, streaming_heap, warm_up)
from ultratight.signals.constellation import ephemerides_for
from ultratight.signals.synth.generator import generation_estimate
from ultratight.signals.recording.iffile import open_if
from ultratight.signals.synth.ifring import RingIf
from ultratight.signals.synth.ifstream import GeneratedIf

def open_source(paths, cfg):
    """The IF source of a run's data: the cached file (``paths["if"]``) or, without one, the generator of
    ``cfg`` and ``paths["if_seed"]`` in memory (:class:`ultratight.signals.synth.ifstream.GeneratedIf`), or
    read from the run's shared ring (``paths["if_ring"]``, :class:`ultratight.signals.synth.ifring.RingIf`)."""
    if "if" in paths:
        return open_if(paths["if"])
    if "if_seed" not in paths:
        raise ConfigError("scenario data: neither an IF file nor the seed of a streamed IF")
    c = _generator_cfg(cfg)
    if "if_ring" in paths:
        return RingIf(c, int(paths["if_seed"]), paths["if_ring"], int(paths["if_consumer"]))
    return GeneratedIf(c, int(paths["if_seed"]))


def truth_initial_state(cfg):
    """True INS/clock state at t = 0 from the scenario trajectory."""
    traj = build_trajectory(cfg.get("trajectory", {"kind": "static"}), cfg.get("receiver", {}),
                            float(cfg["duration_s"]))
    k = traj.kinematics(np.zeros(1))
    rcv = cfg.get("receiver", {})
    return {"llh": k["llh"][0], "vel_l": k["vel_l"][0], "q_lb": k["q_lb"][0],
            "clk_bias_m": float(rcv.get("clock_bias_m", 0.0)),
            "clk_drift_mps": float(rcv.get("clock_drift_mps", 0.0))}


STARTUP_KIND = "truth-perturbed (assisted)"


def run_settings(cfg, startup_errors=None):
    """How the runs of a scenario start and what their IMU is, for the tables, ``metrics.json`` and
    ``results.h5``: the start-up (:func:`run_method`: the scenario truth at t = 0 plus the errors of
    :class:`ultratight.receiver.deep.startup.StartupErrors`, channels predicted from that state and
    the ephemeris, assisted data bits) and the IMU declaration (a sensor drawn from it per run; the
    filters are tuned from the declaration)."""
    errs = startup_errors or StartupErrors()
    imu = None
    if isinstance(cfg.get("imu"), dict):
        from ultratight.ins.imu import imu_errors_from_config
        decl = imu_errors_from_config(cfg["imu"])
        imu = {"preset": decl.preset, "bias_reading": decl.bias_reading,
               "sensor": "drawn per run from the declaration (truth file group imu_errors)",
               "filter_tuning": "the declaration (IMU file meta errors)"}
    return {"startup": {"kind": STARTUP_KIND, "sigmas": errs.as_dict()}, "imu": imu}


def run_settings_text(settings):
    """The table lines of :func:`run_settings`."""
    st = settings["startup"]
    sg = st["sigmas"]
    text = (f"start-up: {st['kind']}: truth at t = 0 plus 1-sigma errors position {sg['pos_m']:g} m, velocity "
            f"{sg['vel_mps']:g} m/s, attitude {sg['att_deg']:g} deg, clock {sg['clk_bias_m']:g} m / "
            f"{sg['clk_drift_mps']:g} m/s; channels predicted from that state and the ephemeris, assisted bits")
    imu = settings.get("imu")
    if imu:
        how = ("stated bias magnitudes, random signs" if imu["bias_reading"] == "stated"
               else "1-sigma figures")
        text += (f"\nIMU: preset {imu['preset']} ({how}); the sensor drawn per run from the declaration, "
                 "filters tuned from the declaration")
    return text


def engine_options_for(cfg, options=None, seed=0):
    """EngineOptions for a scenario: ``options`` (default EngineOptions()) with the scenario's
    ``[engine]`` table applied (e.g. its noise-floor estimator) and its noise events that act inside
    the receiver (:mod:`ultratight.receiver.dsp.burst`; their noise drawn from ``seed``)."""
    opt = options or EngineOptions()
    eng = cfg.get("engine") or {}
    opt = dataclasses.replace(opt, **eng) if eng else opt
    inside = [dict(ev) for ev in cfg.get("noise_events", []) or [] if event_place(ev) != PLACE_IF]
    return dataclasses.replace(opt, noise_events=inside, noise_seed=int(seed)) if inside else opt


def run_method(paths, cfg, method, seed, options=None, startup_errors=None, duration_s=None):
    """Run one method on a run's data (:func:`prepare_data`: the IF file, or the IF streamed from the
    generator); returns (EngineResult, truth dict)."""
    spec = method_spec(method)
    options = engine_options_for(cfg, options, seed)
    # what the method reads of the truth (satellites, time base): given while the truth is still being
    # written (scenario_data.shared_run_data), else from the file
    truth = paths.get("truth_head") or load_truth(paths["truth"])
    if not spec.scalar and "imu" not in paths:
        raise ConfigError(f"method {method!r} needs the scenario's IMU data; the scenario has no [imu] table")
    src = open_source(paths, cfg)
    try:
        if list(getattr(src, "prns", truth["prn"])) != list(truth["prn"]):
            raise ConfigError(f"{src.path}: satellites {src.prns} differ from the truth file's {truth['prn']} "
                              f"({paths['truth']})")
        ephs = ephemerides_for(cfg)
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
        errs = startup_errors or StartupErrors()
        init = perturb_state(truth_initial_state(cfg), errs, rng)
        if spec.scalar:
            res = run_scalar(src, truth["prn"], ephs, truth["week"], truth["tow0_s"], init, duration_s)
        else:
            imu = read_imu_h5(paths["imu"])
            # the scenario's [atmosphere] as the receiver knows it (broadcast coefficients, no generator truth)
            eng = UltratightEngine(src, imu, ephs, truth["prn"], truth["week"], truth["tow0_s"], method=method,
                                   options=options or EngineOptions(), init_state=init, rng=rng,
                                   duration_s=duration_s, atmosphere=scenario_model(cfg), iono_source="scenario")
            res = eng.run()
    finally:
        src.close()
    return res, truth


def errors_vs_truth(res, truth):
    """Doppler and code-phase errors of ``res`` against ``truth`` (:func:`ultratight.receiver.cli.metrics.
    tracking_errors`); the truth's unwrapped code phase is kept in ``truth`` for the run's next method."""
    if "code_phase_unwrapped" not in truth:
        truth["code_phase_unwrapped"] = M.unwrap_chips(truth["t_s"], truth["code_phase_chips"])
    return M.tracking_errors(res.t_start, res.doppler_hz, res.code_phase_chips, truth["t_s"],
                             truth["doppler_hz"], truth["code_phase_chips"],
                             code_truth_unwrapped=truth["code_phase_unwrapped"])


def scenario_config(name, methods, runs=1, duration_s=None, fs_hz=None, overrides=None):
    """The resolved scenario configuration of a ``run_scenario`` call (methods and overrides checked;
    a scenario without ``[imu]`` gets the default IMU when an ultra-tight method runs)."""
    for m in methods:
        check_method(m)
    if int(runs) < 1:
        raise ConfigError(f"--runs must be >= 1, got {runs}")
    ov = dict(overrides or {})
    if duration_s is not None:
        if not duration_s > 0:
            raise ConfigError(f"--duration must be > 0 s, got {duration_s}")
        ov["duration_s"] = float(duration_s)
    if fs_hz is not None:
        ov["frontend.fs_hz"] = float(fs_hz)
    cfg = load_scenario(name, ov)
    if any(m != "scalar" for m in methods) and "imu" not in cfg:
        # the ultra-tight methods run on an IMU: a scenario without [imu] gets the default one
        cfg["imu"] = dict(IMU_DEFAULTS)
    return cfg


def run_scenario(name, methods=("dlb-rackf",), runs=1, seed=None, out_dir="scenario_out", duration_s=None,
                 fs_hz=None, channel=0, plots=True, progress=True, options=None, overrides=None, workers=None,
                 cache=False):
    """Every method on every run's data, the paper's tables, ``metrics.json``, ``results.h5`` and figures
    (module docstring); ``cache``: write the IF files into the cache and read them (else streamed)."""
    cfg = scenario_config(name, methods, runs, duration_s, fs_hz, overrides)
    workers = check_workers(workers)
    base_seed = int(cfg.get("seed", 0) if seed is None else seed)
    if base_seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {base_seed}")
    if isinstance(channel, bool) or not isinstance(channel, int) or channel < 0:
        raise ConfigError(f"--channel must be an integer >= 0, got {channel}")
    out = Path(out_dir)
    _check_out_dir(out, cfg, int(runs), bool(cache))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(out, exc, "cannot create output directory") from None
    fix_mmap_threshold()        # per-epoch result arrays return to the system when freed
    phases = {"start_up_s": process_age_s()}     # the command's split (metrics.json "command_timing_s")
    packed = {}                 # results.h5's arrays, compressed on threads as each result comes in
    with deflate_pool() as deflater:
        try:
            per, raw = _run_all(cfg, methods, int(runs), base_seed, out, channel, progress, options, workers,
                                bool(cache), packed=(packed, deflater), phases=phases)
            return _report(name, cfg, methods, int(runs), base_seed, out, channel, plots, options, per, raw, packed,
                           phases)
        except BaseException:
            deflater.shutdown(wait=False, cancel_futures=True)
            raise


WARM_S = 0.5     # s of signal each method runs in one worker before the jobs start (_warm_methods)
# what does not change the kernels a run compiles (first_run.warm_key): its length, seed, name and text
RUN_ONLY_KEYS = ("duration_s", "seed", "name", "description")


def _start_warm_up(pool, cfg, methods, seed, options, threads, progress, out):
    """Compile once (:func:`ultratight.receiver.cli.workers.warm_up`): each method on ``WARM_S`` s of data of
    its own (a data cache entry of its own in ``out``, reused by later runs, prepared here first so that the
    compilation starts early), in one worker while this process generates the runs' data; the other workers
    then load the kernels from numba's cache. A future of the kernels compiled, or None when the short data
    cannot be made (the jobs proper meet and report the failure)."""
    short = dict(cfg, duration_s=min(WARM_S, float(cfg["duration_s"])))
    try:
        paths, _ = prepare_data(short, seed, out, progress=False, cache_if=False)
    except Exception:
        return None
    return pool.start(_warm_methods, paths, short, methods, seed, options, threads, progress)


def _warm_methods(paths, short, methods, seed, options, threads, progress):
    try:
        n = warm_up(_warm_method, [(paths, short, m, seed, options, threads, short["duration_s"])
                                   for m in dict.fromkeys(methods)], progress=progress)
    except Exception:
        n = 0
    release_heap()
    return n


def _warm_method(paths, cfg, method, seed, options, threads, duration_s):
    opt = dataclasses.replace(engine_options_for(cfg, options), threads=int(threads))
    run_method(paths, cfg, method, seed, options=opt, duration_s=duration_s)


def _method_job(paths, cfg, method, seed, options, threads=1):
    """One method on one run's data in a worker process, on ``threads`` numba threads (the plan's)."""
    opt = dataclasses.replace(engine_options_for(cfg, options), threads=int(threads))
    res, _truth = run_method(paths, cfg, method, seed, options=opt)
    release_heap()
    return res


def _run_all(cfg, methods, runs, base_seed, out, channel, progress, options, workers=None, cache=False,
             packed=None, phases=None):
    """Every method on every run's data: per-run summaries and raw (result, errors) per (run, method);
    ``packed`` = (dict, thread pool): each result's ``results.h5`` entry is packed into the dict on the
    pool as it comes in (:func:`ultratight.receiver.cli.scenario_results.pack_result`).

    The data of every run are prepared first, here (``cache``: with the IF files); then the (run, method)
    jobs run in worker processes (:mod:`ultratight.receiver.cli.workers`), as many as :func:`ultratight.cores.
    plan` gives (at least one), so this process, which collects the results and writes the outputs, never
    holds an engine's working memory as well; ``workers`` = 1 runs them here, one after the other. Streamed,
    with the default workers and several methods, a run's IF is generated once, here, into a ring the run's
    methods read at the same time, one worker process each (:mod:`ultratight.signals.synth.ifring`; on the
    first run after an install written into the cache while the kernels compile instead,
    :mod:`ultratight.receiver.cli.first_run`; one method on two or more cores: so on every run); otherwise
    every method streams its own copy. The results do not depend on where a job ran nor on where its samples
    came from. A streamed IF keeps a core busy beside the engines: it is reserved (:func:`ultratight.cores.
    plan`). ``phases`` (dict): + ``data_s`` (before the first method), ``methods_s`` (then to the last)."""
    n_jobs = runs * len(methods)
    shared = not cache and workers is None and len(methods) > 1
    here = workers is not None and int(workers) == 1
    n_workers, threads, ahead = _worker_plan(cfg, len(methods), runs, out, options, workers, cache, shared, progress)
    per_job = {}
    keys = [(r, m) for r in range(runs) for m in methods]
    truths = {}

    def done(i, res):
        r, m = keys[i]
        if r not in truths:                  # one truth per run, shared by its methods
            truths[r] = load_truth(all_paths[r]["truth"])
        per_job[i] = _summarize_method(res, truths[r], channel, base_seed + r)
        if packed is not None:
            packed[0][(r, m)] = pack_result(*per_job[i][1], packed[1])
        if progress:
            _print_method_line(m, None if runs == 1 else base_seed + r, per_job[i][0], res)

    first = not here and first_compilation()         # numba's cache lacks the engine: a first run
    # the workers start (and import the engine) while this process generates the data
    # the workers are not waited for at the end: they end while this process writes the outputs
    with WorkerPool(max(n_workers, 2) if first else n_workers, preload=(__name__,), processes=not here,
                    threads=threads, join_on_exit=False, fork=True) as pool:
        if first:           # the epoch chain's late part compiled in a second worker meanwhile
            pool.start(compile_ahead)
        # several workers would compile the same kernels: compiled by one first, meanwhile the data (on a
        # first run also with one worker, which would otherwise start compiling once the data are made);
        # not when a run of this kind completed since the sources last changed (its kernels are cached)
        kind = warm_key(methods, threads, options, {k: v for k, v in cfg.items() if k not in RUN_ONLY_KEYS})
        warm = _start_warm_up(pool, cfg, methods, base_seed, options, threads, progress, out) \
            if (n_workers > 1 and not warm_cache_known(kind)) or first else None
        ring = shared and not ahead          # each run's data made with its ring (_map_shared)
        t_data = time.perf_counter()
        all_paths = [None] * runs if ring else [
            _prepare_run(cfg, r, runs, base_seed + r, out, channel, progress, cache or ahead, shared)
            for r in range(runs)]
        tail = (options,) + (() if here else (threads,))
        t_methods = time.perf_counter()
        if progress and not here:
            how = ", the IF read from the cache" if ahead else ", the IF generated once per run and shared" * shared
            print(f"{n_jobs} method run(s) in {n_workers} worker process(es) of {threads} thread(s){how}", flush=True)
        try:
            if ring:            # the warm-up waited for once the first run's ring produces
                _map_shared(pool, cfg, methods, base_seed, out, channel, progress, tail, all_paths, done,
                            ready=warm.result if warm is not None else None)
            else:
                if warm is not None:
                    warm.result()
                jobs = [(all_paths[r], cfg, m, base_seed + r) + tail for r, m in keys]
                pool.map(_method_here if here else _method_job, jobs, on_done=done)
            if not here:
                note_warm_cache(kind)
            (phases if phases is not None else {}).update(data_s=t_methods - t_data,
                                                          methods_s=time.perf_counter() - t_methods)
        finally:
            if ahead:
                drop_if_file(all_paths[0], _cache_lock, CACHE_VERSION)
    per = {m: [] for m in methods}
    raw = {}
    for i, (r, m) in enumerate(keys):
        per[m].append(per_job[i][0])
        raw[(r, m)] = per_job[i][1]
    return per, raw


def _worker_plan(cfg, n_methods, runs, out, options, workers, cache, shared, progress):
    """(workers, threads per worker, whether the IF is written ahead on this first run: first_run)."""
    n_jobs = runs * n_methods
    cores = plan(n_methods if shared else n_jobs, workers=n_methods if shared else workers,
                 threads=getattr(options, "threads", None), reserved=0 if cache else 1)
    single = n_methods == 1 and workers is None and not cache
    ahead = write_if_ahead(runs, cores.workers, shared, generation_estimate(_generator_cfg(cfg))["if_bytes"], out,
                           single=single)
    if ahead:                   # the methods read a file, as with --cache: one worker per core
        cores = plan(n_jobs, threads=getattr(options, "threads", None))
        if progress:
            why = ("one method: the IF is written into the cache first and the method reads it on every core"
                   if single else "numba's cache is empty (the first run after an install): the IF is written into "
                   "the cache while the kernels compile")
            print(f"{why}, and removed after the run", flush=True)
    return cores.workers, cores.threads, ahead


def _print_method_line(m, seed, summ, res):
    print(f"  {m:10s} {'' if seed is None else f'(seed {seed}) '}Doppler RMS "
          f"{np.round(summ['doppler_rms_hz'], 4).tolist()} Hz, code RMS "
          f"{np.round(summ['code_rms_chips'], 4).tolist()} chip, lost {summ['lock_lost_channels']}, "
          f"{res.runtime_s:.1f} s (real-time factor {summ['realtime_factor']:.3f})", flush=True)


def _map_shared(pool, cfg, methods, base_seed, out, channel, progress, tail, all_paths, done, ready=None):
    """Run by run (``all_paths``: a slot per run, filled here): the run's data and IF ring
    (:func:`ultratight.receiver.cli.scenario_data.shared_run_data`: the ring produced in this process, which
    writes the run's truth meanwhile), its methods' jobs (``(paths, cfg, method, seed) + tail``) at the
    same time, each reading the ring as one consumer; results handed to ``done`` with their job index
    once the run's truth is complete. Without shared memory every method generates its own copy.
    ``ready``: called before the first jobs are handed out (the warm-up's result), while the first
    run's ring already produces."""
    n, runs = len(methods), len(all_paths)
    for r in range(runs):
        seed = base_seed + r

        def on_done(j, res, r=r):
            done(r * n + j, res)

        try:
            _run_shared(pool, cfg, methods, r, seed, out, channel, progress, tail, all_paths, on_done, ready)
        except NoSharedMemory as exc:       # a full or missing /dev/shm
            print(f"ultratight scenario: no shared memory for the IF ({exc}); each method generates its own "
                  f"copy", file=sys.stderr, flush=True)
            all_paths[r] = _prepare_run(cfg, r, runs, seed, out, channel, progress)
            if ready is not None:
                ready()
            pool.map(_method_job, [(all_paths[r], cfg, m, seed) + tail for m in methods], on_done=on_done)
        ready = None


def _run_shared(pool, cfg, methods, r, seed, out, channel, progress, tail, all_paths, on_done, ready):
    t0 = time.perf_counter()
    def waiting(lock_path):
        if progress:
            print(f"run {r + 1}/{len(all_paths)} seed {seed}: another run is writing the same data "
                  f"({lock_path.with_suffix('')}); waiting for it", flush=True)

    with shared_run_data(cfg, seed, out, len(methods), waiting) as data:
        all_paths[r] = data.paths
        _check_channel(channel, len(data.paths["truth_head"]["prn"]))
        if progress:
            what = "data reused" if data.reused else "IMU generated"
            print(f"run {r + 1}/{len(all_paths)} seed {seed}: {what} ({time.perf_counter() - t0:.1f} s; the IF"
                  f"{'' if data.reused else ' and the truth'} generated in memory while the methods run, once for "
                  f"all)", flush=True)

        def finished(j, res):
            data.complete()               # the run's truth, written by the ring's producer
            on_done(j, res)

        with streaming_heap():          # the ring's blocks reuse heap memory (workers.streaming_heap)
            data.ring.start()
            if ready is not None:
                ready()
            jobs = [(dict(data.paths, if_ring=data.ring.name, if_consumer=j), cfg, m, seed) + tail
                    for j, m in enumerate(methods)]
            pool.map(_method_job, jobs, on_done=finished)


def _check_channel(channel, n_ch):
    if channel >= n_ch:
        raise ConfigError(f"--channel {channel}: the scenario has {n_ch} channel(s) (0..{n_ch - 1})")


def _method_here(paths, cfg, method, seed, options):
    res, _truth = run_method(paths, cfg, method, seed, options=options)
    release_heap()              # the engine's working memory, before the next method runs here
    return res


def _prepare_run(cfg, r, runs, seed, out, channel, progress, cache=False, shared=False):
    """The data of run ``r`` (generated or reused), its channel count checked against ``channel``."""
    t0 = time.perf_counter()
    made = set()
    paths, cached = prepare_data(cfg, seed, out, progress=progress, cache_if=cache, made=made)
    release_heap()              # the generator's working memory (this process keeps the results)
    _check_channel(channel, len(load_truth(paths["truth"])["prn"]))
    if progress:
        what = (", the IF generated" if cached and "if" in made else "") if cache else (
            ", truth and IMU: the IF is generated in memory, " + ("once for all methods" if shared
                                                                  else "for each method"))
        print(f"run {r + 1}/{runs} seed {seed}: data {'reused' if cached else 'generated'} "
              f"({time.perf_counter() - t0:.1f} s{what})", flush=True)
    return dict(paths, if_written="if" in made) if "if" in paths else paths    # if_written: first_run.drop_if_file


def _summarize_method(res, truth, channel, seed):
    """The per-run summary of one method's result and its (result, Doppler error, code error)."""
    d_err, c_err = errors_vs_truth(res, truth)
    summ = M.summarize(res.t_start, d_err, c_err, M.SEGMENTS_S, channel=channel)
    summ["runtime_s"] = res.runtime_s
    summ["timing_s"] = dict(res.info.get("timing_s", {}))     # the engine's split of it (docs/ultratight.md)
    # wall-clock seconds per signal second (as `ultratight process`): < 1 = faster than real time
    summ["realtime_factor"] = res.runtime_s / res.duration_s if res.duration_s > 0 else float("nan")
    summ["seed"] = seed
    return summ, (res, d_err, c_err)


def _report(name, cfg, methods, runs, base_seed, out, channel, plots, options, per, raw, packed=None, phases=None):
    """metrics.json, results.h5 (``packed``: its entries packed so far), figures and the text tables of a
    scenario run; ``phases``: the command's split so far (``command_timing_s``)."""
    dur = float(cfg["duration_s"])
    segs = M.SEGMENTS_S
    agg = aggregate_methods(cfg, per, raw, methods, channel)
    mon = monitor_mode(options or EngineOptions())
    settings = run_settings(cfg)
    js = {"scenario": cfg.get("name", str(name)), "seed": base_seed, "runs": runs, "duration_s": dur,
          "segments_s": [list(x) for x in segs], "channel": channel,
          "methods": {m: {k: agg[m][k] for k in METHOD_METRICS} for m in methods}, "monitor": mon,
          "startup": settings["startup"], "imu": settings["imu"],
          "per_run": per, "version": __version__, "paper_table3": M.PAPER_TABLE3, "paper_table4_s": M.PAPER_TABLE4_S,
          "command_timing_s": dict(phases or {})}
    mpath = out / "metrics.json"
    write_text_atomic(mpath, json.dumps(json_clean(js), indent=2))
    note_complete(mpath)
    hpath = out / "results.h5"
    # each (run, method) is dropped once in the file's image, but for what the figures draw (run 0)
    write_results_h5(hpath, cfg, run_settings(cfg), raw, methods, runs, base_seed, consume=True,
                     keep={(0, m) for m in methods} if plots else (), packed=packed)
    note_complete(hpath)
    figs = make_plots(out, raw, methods, channel) if plots else []
    text = M.format_tables(agg, segs) + "\n" + (
        f"\n{runs} run(s), seeds {base_seed}..{base_seed + runs - 1}; RMS over all channels and runs; "
        "'\\' = lock lost (diverged) in that segment.")
    text += f"\nsignal monitor: {mon}\n" + run_settings_text(settings) + noise_event_text(agg, methods)
    return {"json": json_clean({k: js[k] for k in ("scenario", "seed", "runs", "monitor", "startup", "imu",
                                                   "methods")}),
            "text": text,
            "metrics_path": str(mpath), "h5_path": str(hpath), "figures": figs}


# the per-method metrics of metrics.json (and of a campaign's summary)
METHOD_METRICS = ("doppler_rms_hz", "code_rms_chips", "diverged", "lock_lost_channels", "runtime_s",
                  "realtime_factor", "doppler_rms_hz_channel", "code_rms_chips_channel", "segment_diverged",
                  "noise_events")


def aggregate_methods(cfg, per, raw, methods, channel):
    """:func:`aggregate` of every method, with its RMS inside each noise event (:func:`event_rms`)."""
    agg = {m: aggregate(per[m], raw, m, M.SEGMENTS_S, channel) for m in methods}
    events = event_windows(cfg, float(cfg["duration_s"]))
    for m in methods:
        agg[m]["noise_events"] = event_rms(raw, m, events)
    return agg


def _f(v):
    return "-" if v is None or not np.isfinite(v) else f"{v:.4f}"


def noise_event_text(agg, methods):
    """One line per method and noise event: Doppler RMS inside it and before it, code RMS."""
    text = ""
    for m in methods:
        for ev in agg[m]["noise_events"]:
            text += (f"\n{m:10s} noise x{ev['noise_factor']:g} over {ev['t0_s']:g}-{ev['t1_s']:g} s: Doppler RMS "
                     f"{_f(ev['doppler_rms_hz'])} Hz (before: {_f(ev['doppler_rms_hz_before'])} Hz), code RMS "
                     f"{_f(ev['code_rms_chips'])} chip")
    return text


def event_windows(cfg, dur):
    """The scenario's noise events clipped to the run: list of (t0, t1, factor)."""
    out = []
    for ev in cfg.get("noise_events", []) or []:
        a, b = float(ev["t0_s"]), min(float(ev["t1_s"]), dur)
        if b > a:
            out.append((a, b, float(ev.get("noise_factor", 1.0))))
    return out


def event_rms(raw, method, events):
    """RMS over all channels and runs of the tracking errors during each noise event and over the
    same length just before it (the paper's "gross error" window vs the quiet level)."""
    keys = [k for k in raw if k[1] == method]
    t = np.concatenate([raw[k][0].t_start for k in keys], axis=0)
    d = np.concatenate([raw[k][1] for k in keys], axis=0)
    c = np.concatenate([raw[k][2] for k in keys], axis=0)
    res = []
    for a, b, fac in events:
        pre = (max(0.0, a - (b - a)), a)
        dr = M.segment_rms(t, d, [(a, b), pre])
        cr = M.segment_rms(t, c, [(a, b)])
        res.append({"t0_s": a, "t1_s": b, "noise_factor": fac, "doppler_rms_hz": float(dr[0]),
                    "doppler_rms_hz_before": float(dr[1]), "code_rms_chips": float(cr[0])})
    return res


_RMS_KEYS = ("doppler_rms_hz", "code_rms_chips", "doppler_rms_hz_channel", "code_rms_chips_channel")


def aggregate(summaries, raw, method, segs, channel):
    """Combine runs: RMS over all channels and runs (from the raw errors), lock figures summed. One run's
    RMS are its summary's (:func:`_summarize_method` computed them from the same errors and segments)."""
    seg_div = [any(s["segment_diverged"][i] for s in summaries) for i in range(len(segs))]
    keys = [k for k in raw if k[1] == method]
    if len(keys) == 1 and len(summaries) == 1 and tuple(segs) == tuple(M.SEGMENTS_S):
        rms = {k: list(summaries[0][k]) for k in _RMS_KEYS}
    else:
        t = np.concatenate([raw[k][0].t_start for k in keys], axis=0)
        d = np.concatenate([raw[k][1] for k in keys], axis=0)
        c = np.concatenate([raw[k][2] for k in keys], axis=0)
        rms = {"doppler_rms_hz": M.segment_rms(t, d, segs).tolist(),
               "code_rms_chips": M.segment_rms(t, c, segs).tolist(),
               "doppler_rms_hz_channel": M.segment_rms(t, d, segs, channel).tolist(),
               "code_rms_chips_channel": M.segment_rms(t, c, segs, channel).tolist()}
    return {
        **rms,
        "diverged": bool(any(seg_div)),
        "segment_diverged": seg_div,
        "lock_lost_channels": int(sum(s["lock_lost_channels"] for s in summaries)),
        "runtime_s": float(np.mean([s["runtime_s"] for s in summaries])),
        "realtime_factor": float(np.mean([s["realtime_factor"] for s in summaries])),
    }


def _check_out_dir(out, cfg, runs, cache=True):
    """--out: a directory (existing or creatable) with room for the runs' data (estimate; the IF files
    only with ``cache``)."""
    io_guard.check_path_length(out, "--out")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a directory")
    io_guard.check_output_path(out / "metrics.json", "--out", create_parent=True)
    est = generation_estimate(cfg)
    if_bytes = est["if_bytes"] if cache else 0.0
    io_guard.check_disk(out, runs * (if_bytes + est["truth_bytes"] + 2 * est["imu_bytes"]),
                        f"the data of {runs} run(s) of {cfg['duration_s']:g} s")
    # the truth (HDF5 written as it is generated) must fit the file-size limit
    io_guard.check_file_size(est["truth_bytes"], f"the truth file of a run of {cfg['duration_s']:g} s")
    io_guard.check_memory(est["memory_bytes"], f"a run of {cfg['duration_s']:g} s")


def make_plots(out, raw, methods, channel):
    """Paper-style figures (Fig. 4–7): Doppler and code-phase error of one channel vs time (Agg canvas
    without pyplot, curves through :func:`ultratight.receiver.cli.metrics.plot_envelope`, one draw)."""
    try:                        # matplotlib: optional dependency (the "plot" extra)
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return []
    figs = []
    pairs = [("fig4_doppler_pbkf_vs_rackf.png", ("pb-kf-utc", "dlb-rackf"), 1, "Doppler error (Hz)"),
             ("fig5_code_pbkf_vs_rackf.png", ("pb-kf-utc", "dlb-rackf"), 2, "code phase error (chips)"),
             ("fig6_doppler_dlb.png", ("dlb-ukf", "dlb-ckf", "dlb-rackf"), 1, "Doppler error (Hz)"),
             ("fig7_code_dlb.png", ("dlb-ukf", "dlb-ckf", "dlb-rackf"), 2, "code phase error (chips)")]
    for name, ms, idx, ylabel in pairs:
        have = [m for m in ms if (0, m) in raw]
        if not have:
            continue
        fig = Figure(figsize=(8, 4))
        fig.subplots_adjust(left=0.1, right=0.98, bottom=0.12, top=0.92)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
        for m in have:
            res = raw[(0, m)][0]
            err = raw[(0, m)][idx]
            ax.plot(*M.plot_envelope(res.t_start[:, channel], err[:, channel]), lw=0.5, label=m)
        ax.set_xlabel("time (s)")
        ax.set_ylabel(ylabel)
        ax.set_title(f"channel {channel} (PRN {raw[(0, have[0])][0].prns[channel]}), run 0")
        ax.grid(True, alpha=0.3)
        ax.legend()
        p = Path(out) / name
        with atomic_path(p) as tmp:
            fig.savefig(tmp, format="png", dpi=110)
        figs.append(str(p))
    return figs
