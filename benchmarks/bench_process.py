"""Benchmark ``ultratight process`` (the scalar receiver) end to end.

    python benchmarks/bench_process.py [--quick] [--json OUT.json] [--duration S] [--fs HZ] [--workdir DIR]

Generates (once, cached in ``--workdir``) a static-open-sky file of ``--duration`` seconds
(60 s; 20 s with ``--quick``, enough for a first fix) of complex int8 I/Q at ``--fs`` (2.6 MHz by default; the scenario's
native 4 MHz with ``--fs 4e6``) — the speed reference: the scenario without its ``[atmosphere]`` table and
from TOW 518400, as the documented figures were measured (:func:`vacuum_scenario`) — then runs the receiver with 8 channels in fresh subprocesses: the
default (channels on numba's threads when cores are free), one thread (``ProcessConfig(parallel=False)``)
and the baseline commit (``--baseline``, default the receiver before it was rebuilt from stages, run
from an export of that commit with its defaults; not with ``--quick``); every code version first
runs 1 s of the file (numba compilation or cache loading stays out of the figures):

* ``realtime_factor``: wall time / signal time of the full run (acquisition, numba cache load,
  tracking, decoding, PVT, HDF5 output included; goal <= 0.1 on the 2-core reference machine);
  ``cpu_realtime_factor``: the same with the process's CPU time (user + system), which does not
  depend on what else the machine is running;
* ``maxrss_*_mb``: peak resident set size (``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of the
  child) for a 10 s cut and for the full file: memory must not grow with the run length
  (goal: equal within 10 %);
* ``wall_ratio_baseline`` / ``wall_ratio_one_thread``: the default's wall time over the baseline's
  and over one thread's (same file, same run);
* the fixes and the position / velocity error against the generator's truth (full run).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import add_baseline_arg, add_common_args, baseline_env, finish

CHILD = r"""
import json, resource, sys, time
import numpy as np, h5py
try:
    from ultratight.receiver.scalar.process_config import ProcessConfig
    from ultratight.receiver.scalar.receiver import process
    from ultratight.signals.recording.iffile import open_if
except ImportError:   # a --baseline commit from before the package was split by role
    from ultratight.receiver.process import ProcessConfig, process
    from ultratight.signals.iffile import open_if
path, truth, dur, out = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
opts = {"one": {"parallel": False}, "default": {}}[sys.argv[5]]
t0 = time.perf_counter()
r0 = resource.getrusage(resource.RUSAGE_SELF)
# the generated file has no atmosphere (vacuum_scenario): no corrections (8 channels: the speed reference)
res = process(open_if(path), ProcessConfig(n_channels=8, duration_s=dur, iono="off", tropo="off", **opts), out_path=out)
wall = time.perf_counter() - t0
r1 = resource.getrusage(resource.RUSAGE_SELF)
cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
d = {"wall_s": wall, "cpu_s": cpu, "cpu_realtime_factor": cpu / res.signal_s, "signal_s": res.signal_s, "realtime_factor": wall / res.signal_s,
     "fixes": len(res.fixes), "first_fix_s": res.first_fix_s, "tracked": len([c for c in res.channels if c["tracked"]]),
     "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
if res.fixes:
    T = h5py.File(truth, "r")
    P = np.array([f["pos_e"] for f in res.fixes]); V = np.array([f["vel_e"] for f in res.fixes])
    d["pos_err_rms_m"] = float(np.sqrt(np.mean(np.sum((P - T["pos_e"][0]) ** 2, axis=1))))
    d["vel_err_rms_mps"] = float(np.sqrt(np.mean(np.sum((V - T["vel_e"][0]) ** 2, axis=1))))
print(json.dumps(d))
"""


def vacuum_scenario(workdir):
    """The shipped static-open-sky scenario written to ``workdir`` without its ``[atmosphere]`` table and
    starting at TOW 518400 (a frame start: first fix at 18 s): the file the speed figures are measured on."""
    import re
    from ultratight.config import locate_scenario

    text = locate_scenario("static-open-sky").read_text()
    head, sep, rest = text.partition("\n[atmosphere]\n")
    if sep:                                        # cut the table (up to the next one, if any)
        nxt = rest.find("\n[")
        text = head + "\n" + (rest[nxt + 1:] if nxt >= 0 else "")
    path = Path(workdir) / "static-open-sky-vacuum.toml"
    path.write_text(re.sub(r"(?m)^tow_s = .*$", "tow_s = 518400.0", text))
    return path


def ensure_file(workdir, duration, fs):
    stem = Path(workdir) / f"static-open-sky-vacuum-{int(duration)}s-{fs / 1e6:g}MHz"
    meta = Path(str(stem) + ".ci8.json")
    if not meta.is_file():
        subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", str(vacuum_scenario(workdir)),
                        "--duration", str(duration), "--fs", str(fs), "--format", "ci8", "--out", str(stem),
                        "--no-progress", "--json"], check=True, capture_output=True, text=True)
    return str(stem) + ".ci8", str(stem) + ".truth.h5"


def run_child(path, truth, duration, out, threads="default", env=None, cwd=None):
    r = subprocess.run([sys.executable, "-c", CHILD, path, truth, str(duration), out, threads],
                       capture_output=True, text=True, check=True, env=env, cwd=cwd)
    return json.loads(r.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--fs", type=float, default=2.6e6)
    ap.add_argument("--workdir", default=os.path.join(tempfile.gettempdir(), "ultratight-bench-process"))
    add_baseline_arg(ap)
    args = ap.parse_args()
    duration = args.duration or (20.0 if args.quick else 60.0)
    os.makedirs(args.workdir, exist_ok=True)
    t0 = time.perf_counter()
    path, truth = ensure_file(args.workdir, duration, args.fs)
    t_gen = time.perf_counter() - t0
    out = os.path.join(args.workdir, "bench_out.h5")
    path, truth, out = (os.path.abspath(p) for p in (path, truth, out))
    # warm the numba cache so that the figures show steady-state behaviour
    run_child(path, truth, 1.0, out)
    run_child(path, truth, 1.0, out, "one")
    full = run_child(path, truth, duration, out)            # the default: threads when cores are free
    one = run_child(path, truth, duration, out, "one")      # ProcessConfig(parallel=False)
    short = run_child(path, truth, min(10.0, duration), out)
    base = None
    with tempfile.TemporaryDirectory() as tmp:
        if not args.quick and args.baseline.lower() != "none":
            env, base_name = baseline_env(args.baseline, tmp)
            if env is None:
                print(f"{base_name}: measuring without it")
            else:
                run_child(path, truth, 1.0, out, env=env, cwd=tmp)
                base = run_child(path, truth, duration, out, env=env, cwd=tmp)
    rep = {
        "fs_hz": args.fs, "format": "ci8", "channels": 8, "duration_s": duration,
        "generate_s": round(t_gen, 2),
        "realtime_factor": round(full["realtime_factor"], 4),
        "wall_s": round(full["wall_s"], 2),
        "wall_one_thread_s": round(one["wall_s"], 2),
        "realtime_factor_one_thread": round(one["realtime_factor"], 4),
        "wall_ratio_one_thread": round(full["wall_s"] / one["wall_s"], 3),
        "cpu_s": round(full["cpu_s"], 2),
        "cpu_realtime_factor": round(full["cpu_realtime_factor"], 4),
        "signal_s": full["signal_s"],
        "fixes": full["fixes"], "first_fix_s": full["first_fix_s"], "tracked": full["tracked"],
        "pos_err_rms_m": full.get("pos_err_rms_m"), "vel_err_rms_mps": full.get("vel_err_rms_mps"),
        "maxrss_10s_mb": round(short["maxrss_mb"], 1),
        f"maxrss_{int(duration)}s_mb": round(full["maxrss_mb"], 1),
        "maxrss_ratio": round(full["maxrss_mb"] / short["maxrss_mb"], 3),
        "realtime_factor_10s": round(short["realtime_factor"], 4),
    }
    print(f"ultratight process, static-open-sky {duration:g} s, {args.fs / 1e6:g} MHz ci8, 8 channels "
          f"(fresh process each run)")
    if base is not None:
        rep["baseline"] = base_name
        rep["wall_baseline_s"] = round(base["wall_s"], 2)
        rep["wall_ratio_baseline"] = round(full["wall_s"] / base["wall_s"], 3)
        rep["baseline_fixes"] = base["fixes"]
        rep["baseline_pos_err_rms_m"] = base.get("pos_err_rms_m")
    print(f"real-time factor {rep['realtime_factor']:.3f} (CPU {rep['cpu_realtime_factor']:.3f}; goal <= 0.1), "
          f"{rep['wall_s']:.2f} s; 10 s cut {rep['realtime_factor_10s']:.3f}; one thread "
          f"{rep['realtime_factor_one_thread']:.3f}, {rep['wall_one_thread_s']:.2f} s (default / one thread "
          f"{rep['wall_ratio_one_thread']:.2f})")
    if base is not None:
        print(f"baseline ({base_name}): {rep['wall_baseline_s']:.2f} s, {base['fixes']} fixes; default / baseline "
              f"{rep['wall_ratio_baseline']:.2f} of the wall time")
    def g3(v):
        return "n/a" if v is None else f"{v:.3g}"
    print(f"fixes {rep['fixes']}, first fix {rep['first_fix_s']} s, tracked {rep['tracked']}, "
          f"position RMS {g3(rep['pos_err_rms_m'])} m, velocity RMS {g3(rep['vel_err_rms_mps'])} m/s")
    print(f"peak RSS: 10 s {rep['maxrss_10s_mb']} MB, {int(duration)} s {rep[f'maxrss_{int(duration)}s_mb']} MB "
          f"(ratio {rep['maxrss_ratio']})")
    finish(args, rep)

if __name__ == "__main__":
    main()
