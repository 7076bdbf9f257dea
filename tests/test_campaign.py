"""``ultratight campaign`` (docs/campaign.md): Dask campaigns equal sequential runs exactly, on a
LocalCluster, through a scheduler address, and after an interruption and ``--resume``."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.io_guard import json_clean
from ultratight.receiver.cli import campaign as C
from ultratight.receiver.cli import experiments
from ultratight.receiver.cli import main

SCENARIO = "paper-robust-flight"
DURATION = 30.0
RUNS = 4
SEED = 17


def _strip_timing(o):
    if isinstance(o, dict):
        return {k: _strip_timing(v) for k, v in o.items() if k not in C.TIMING_KEYS}
    if isinstance(o, list):
        return [_strip_timing(v) for v in o]
    return o


def _figures(js):
    """What a campaign reports that must be reproducible: metrics and the experiment's tables."""
    return _strip_timing({"metrics": C.reproducible(js["metrics"]), "summary": js["summary"],
                          "run_seeds": js["run_seeds"]})


@pytest.fixture(scope="module")
def client():
    pytest.importorskip("distributed")
    cl, cluster, where = C.start_client(workers=2)       # the campaign's own LocalCluster (processes=True)
    assert where == "LocalCluster of 2 worker(s) x 1 thread"
    yield cl
    cl.close()
    cluster.close()


@pytest.fixture(scope="module")
def sequential():
    """The same runs, sequentially in this process: the aggregate and tables of a sequential run."""
    path, raw, mod = experiments.resolve(SCENARIO)
    cfg = mod.load(path, raw, {"duration_s": DURATION})
    methods = list(mod.DEFAULT_METHODS)
    results = [mod.run_one(cfg, methods, s) for s in C.run_seeds(SEED, RUNS)]
    js = {"metrics": json_clean(C.aggregate(results)), "summary": json_clean(mod.summarize(cfg, results)["json"]),
          "run_seeds": C.run_seeds(SEED, RUNS)}
    return _figures(js)


@pytest.fixture(scope="module")
def local_campaign(client, tmp_path_factory):
    out = tmp_path_factory.mktemp("campaign") / "full"
    res = C.run_campaign(SCENARIO, runs=RUNS, seed=SEED, out_dir=out, overrides={"duration_s": DURATION},
                         progress=False, client=client)
    return out, res


def test_run_seeds_follow_seedsequence_spawn():
    seeds = C.run_seeds(5, 3)
    kids = np.random.SeedSequence(5).spawn(3)
    assert seeds == [int(k.generate_state(1, dtype=np.uint32)[0]) for k in kids]
    assert C.run_seeds(5, 6)[:3] == seeds            # run i does not depend on --runs
    assert len(set(C.run_seeds(5, 50))) == 50


def test_run_file_round_trip_is_lossless(tmp_path):
    res = {"seed": 3, "methods": {"a/b": {"x": np.arange(5.0) / 3, "n": np.int64(4), "f": 0.1, "i": 2, "ok": True,
                                          "lst": [0.1, 0.2], "mixed": [None, 1.5], "t": (1, 2), "s": "txt",
                                          "none": None, "empty": [], "m": np.eye(3, dtype=np.int8)}},
           "sweep": {"5/kf": {"v": np.float64(np.nan)}}}
    p = tmp_path / "run.h5"
    C.write_run(p, res, index=0, seed=3, key="k", elapsed_s=1.0)
    back, attrs = C.read_run(p, "k")
    assert list(back) == list(res) and list(back["methods"]["a/b"]) == list(res["methods"]["a/b"])
    a, b = back["methods"]["a/b"], res["methods"]["a/b"]
    assert np.array_equal(a["x"], b["x"]) and a["x"].dtype == b["x"].dtype
    assert a["n"] == 4 and type(a["n"]) is np.int64
    assert (a["f"], a["i"], a["ok"], a["lst"], a["mixed"], a["t"], a["s"], a["none"], a["empty"]) == \
           (0.1, 2, True, [0.1, 0.2], [None, 1.5], (1, 2), "txt", None, [])
    assert type(a["f"]) is float and type(a["i"]) is int and type(a["ok"]) is bool
    assert np.array_equal(a["m"], b["m"]) and a["m"].dtype == np.int8
    assert np.isnan(back["sweep"]["5/kf"]["v"])
    assert C.read_run(p, "other") is None                      # another campaign's file
    p.write_bytes(p.read_bytes()[:200])                        # a truncated file
    assert C.read_run(p, "k") is None
    assert not list(tmp_path.glob(".*tmp*"))                   # no temporary file left


def test_aggregate_t_interval_and_spread():
    runs = [{"seed": s, "methods": {"m": {"v": v, "vec": np.array([v, 2 * v]), "series": np.arange(100.0)}}}
            for s, v in ((1, 1.0), (2, 2.0), (3, 6.0))]
    agg = C.aggregate(runs)
    assert "methods/m/series" not in agg and "seed" not in agg
    v = agg["methods/m/v"]
    sd = np.std([1.0, 2.0, 6.0], ddof=1)
    half = 4.302652729911275 * sd / np.sqrt(3)                 # t(0.975, 2)
    assert v["n"] == 3 and v["mean"] == pytest.approx(3.0) and v["std"] == pytest.approx(sd)
    assert v["ci95"] == pytest.approx([3.0 - half, 3.0 + half]) and (v["min"], v["max"]) == (1.0, 6.0)
    assert agg["methods/m/vec"]["max"] == [6.0, 12.0]


def test_local_cluster_campaign_equals_sequential_runs(local_campaign, sequential):
    out, res = local_campaign
    assert _figures(res["json"]) == sequential
    on_disk = json.loads((out / "campaign.json").read_text())
    assert _figures(on_disk) == sequential
    assert sorted(p.name for p in (out / "runs").iterdir()) == [f"run-{i:05d}.h5" for i in range(RUNS)]
    assert res["json"]["timing"]["computed_runs"] == RUNS


def test_local_cluster_workers_are_single_threaded_processes(client):
    info = client.scheduler_info()["workers"]
    assert len(info) == 2 and all(w["nthreads"] == 1 for w in info.values())
    env = client.run(lambda: (os.environ.get("NUMBA_NUM_THREADS"), os.getpid()))
    assert {v[0] for v in env.values()} == {"1"}
    assert len({v[1] for v in env.values()} | {os.getpid()}) == 3        # two processes besides this one


def test_cli_on_scheduler_address_json(client, local_campaign, tmp_path, capsys):
    rc = main(["campaign", SCENARIO, "--runs", str(RUNS), "--seed", str(SEED), "--duration", str(DURATION),
               "--scheduler", client.scheduler.address, "--out", str(tmp_path / "c"), "--json", "--quiet"])
    assert rc == 0
    js = json.loads(capsys.readouterr().out)
    assert _figures(js) == _figures(local_campaign[1]["json"])


def test_resume_after_a_subset_and_a_damaged_file(client, local_campaign, tmp_path):
    out = tmp_path / "c"
    kw = dict(seed=SEED, out_dir=out, overrides={"duration_s": DURATION}, progress=False, client=client)
    C.run_campaign(SCENARIO, runs=2, **kw)
    C.run_path(out, 1).write_bytes(b"not hdf5")               # a damaged file is run again
    res = C.run_campaign(SCENARIO, runs=RUNS, resume=True, **kw)
    assert res["json"]["timing"]["computed_runs"] == RUNS - 1
    assert _figures(res["json"]) == _figures(local_campaign[1]["json"])


def test_sigterm_then_resume_gives_the_uninterrupted_figures(local_campaign, tmp_path):
    out = tmp_path / "c"
    cmd = [sys.executable, "-m", "ultratight.receiver.cli", "campaign", SCENARIO, "--runs", str(RUNS), "--seed",
           str(SEED), "--duration", str(DURATION), "--workers", "1", "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not C.run_path(out, 0).exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "interrupted by SIGTERM" in err
    done = len(list((out / "runs").glob("run-*.h5")))
    assert 1 <= done < RUNS
    assert not (out / "campaign.json").exists()
    rc = subprocess.run(cmd + ["--resume", "--json"], capture_output=True, text=True, timeout=300)
    assert rc.returncode == 0, rc.stderr
    js = json.loads(rc.stdout)
    assert js["timing"]["computed_runs"] == RUNS - done
    assert _figures(js) == _figures(local_campaign[1]["json"])


def _dask_cli():
    exe = Path(sys.executable).with_name("dask")
    return str(exe) if exe.exists() else shutil.which("dask")


@pytest.mark.skipif(_dask_cli() is None, reason="the dask command-line tool (dask[distributed]) is not installed")
def test_scale_out_recipe_scheduler_and_two_worker_processes(local_campaign, tmp_path):
    dask = _dask_cli()
    env = dict(os.environ, **C.WORKER_ENV)
    sfile = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sfile)], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 60
        while not sfile.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.2)
        address = json.loads(sfile.read_text())["address"]
        for _ in range(2):
            procs.append(subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-dashboard"], env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        from distributed import Client
        with Client(address, timeout=30) as cl:
            cl.wait_for_workers(2, timeout=60)
            assert len(cl.scheduler_info()["workers"]) == 2
        res = C.run_campaign(SCENARIO, runs=RUNS, seed=SEED, out_dir=tmp_path / "c", scheduler=address,
                             overrides={"duration_s": DURATION}, progress=False)
        assert res["json"]["timing"]["where"] == f"scheduler {address}"
        assert _figures(res["json"]) == _figures(local_campaign[1]["json"])
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def test_user_errors_are_one_line(tmp_path, capsys):
    for argv, text in ((["--workers", "0"], "--workers must be an integer"),
                       (["--scheduler", "tcp://127.0.0.1:9"], "cannot connect within"),
                       (["--runs", "0"], "--runs must be an integer >= 1")):
        args = ["campaign", SCENARIO, "--runs", "2", "--out", str(tmp_path / "o"), "--quiet",
                "--connect-timeout", "2"] + argv
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert text in err and len(err.splitlines()) == 1, err
    assert main(["campaign", "no-such-scenario", "--runs", "2", "--quiet"]) == 2
    assert "unknown scenario" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="exclude each other"):
        C.run_campaign(SCENARIO, runs=1, workers=1, scheduler="tcp://127.0.0.1:9", out_dir=tmp_path / "x")


def _if_equal_to_run_scenario(tmp_path, methods):
    from ultratight.receiver.cli import if_double_loop as X
    from ultratight.receiver.cli.scenario_runner import run_scenario
    seed = 11
    ref = run_scenario("static-open-sky", methods=methods, runs=1, seed=seed, out_dir=tmp_path / "s",
                       duration_s=0.5, plots=False, progress=False)
    path, raw, mod = experiments.resolve("static-open-sky")
    assert mod is X
    cfg = X.with_data_dir(X.load(path, raw, {"duration_s": 0.5}), tmp_path / "s")
    summ = X.summarize(cfg, [X.run_one(cfg, methods, seed)])
    assert _strip_timing(summ["json"]["methods"]) == _strip_timing(ref["json"]["methods"])
    assert len(list((tmp_path / "s" / "cache").iterdir())) == 2     # one entry (+ its lock): the cache is shared


def test_if_level_run_one_and_summarize_match_run_scenario(tmp_path):
    _if_equal_to_run_scenario(tmp_path, ["scalar"])


@pytest.mark.slow
def test_if_level_run_one_and_summarize_match_run_scenario_double_loop(tmp_path):
    _if_equal_to_run_scenario(tmp_path, ["dlb-rackf", "pb-kf-utc"])


@pytest.mark.slow
def test_if_level_campaign_equals_sequential(client, tmp_path):
    path, raw, mod = experiments.resolve("static-open-sky")
    methods = ["dlb-rackf"]
    res = C.run_campaign("static-open-sky", runs=2, seed=3, methods=methods, out_dir=tmp_path / "c",
                         overrides={"duration_s": 0.5}, progress=False, client=client)
    cfg = mod.with_data_dir(mod.load(path, raw, {"duration_s": 0.5}), tmp_path / "c")
    results = [mod.run_one(cfg, methods, s) for s in C.run_seeds(3, 2)]       # reuses the cached data
    seq = {"metrics": json_clean(C.aggregate(results)), "summary": json_clean(mod.summarize(cfg, results)["json"]),
           "run_seeds": C.run_seeds(3, 2)}
    assert _figures(res["json"]) == _figures(seq)
