"""Peer benchmark: ``ultratight process`` with its defaults beside GNSS-SDR on the same generated file.

    python benchmarks/bench_vs_gnss_sdr.py [--quick] [--json OUT.json] [--duration S] [--workdir DIR]
                                           [--gnss-sdr PATH] [--seed N]

Generates (once, cached in ``--workdir``) the ``static-open-sky-atmosphere`` scenario (Klobuchar
ionosphere and Saastamoinen troposphere in the signals, 13 satellites above 5 deg, 45 dB-Hz) as
complex int8 I/Q at 2.6 MHz, ``--duration`` seconds (60 s; 40 s with ``--quick``, enough for both
receivers' first fix), seed 1 (``--seed``: another draw).  Then, in the same run and one after the
other:

* GNSS-SDR (the ``gnss-sdr`` binary, e.g. from the Debian package ``gnss-sdr``) with a configuration
  this script writes: file signal source read as interleaved int8 I/Q (``ibyte``) at 2.6 MHz, 8 GPS
  L1 C/A channels (PCPS acquisition ±10 kHz, DLL/PLL tracking), RTKLIB single-point PVT at 10 Hz
  with the broadcast ionosphere, Saastamoinen troposphere and a 5 deg elevation mask (the
  receiver's own mask; GNSS-SDR's default is 15 deg), RINEX, KML and NMEA outputs in a temporary
  folder;
* ``ultratight process FILE --json --nmea OUT`` with every other option at its default (all in
  view), after a 1 s run of the same file that loads the numba cache (kept out of the figures).

Figures per receiver: wall time, CPU time (user + system of the process and its threads, from
``os.wait4``) and CPU share, the fixes in its NMEA GGA sentences (both receivers write them, so both
positions are read the same way), the first fix (signal time), and the position error against the
generator's truth: RMS of the 3-D error over every fix, and the horizontal / vertical error of the
median position.  ``wall_ratio`` = ultratight's wall time / GNSS-SDR's.

Without the ``gnss-sdr`` binary the benchmark prints one line saying so and writes
``{"skipped": reason}``; it never installs anything.
"""

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import add_common_args, finish

SCENARIO = "static-open-sky-atmosphere"
FS_HZ = 2.6e6
CHANNELS = 8
MASK_DEG = 5.0
LEAP_S = 18                      # GPS - UTC since 2017-01-01 (the NMEA times are UTC)


def ensure_file(workdir, duration, seed=1):
    """The generated file (IF path, sidecar JSON, truth HDF5) and the generator's summary (with
    ``cached``: the file was there from an earlier run)."""
    stem = Path(workdir) / (f"{SCENARIO}-{int(duration)}s-{FS_HZ / 1e6:g}MHz" + ("" if seed == 1 else f"-seed{seed}"))
    summary = Path(str(stem) + ".generate.json")
    cached = summary.is_file() and all(Path(p).is_file() for p in json.loads(summary.read_text())["files"].values())
    if not cached:
        r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", SCENARIO,
                            "--duration", str(duration), "--fs", str(FS_HZ), "--format", "ci8", "--seed", str(seed),
                            "--out", str(stem), "--no-progress", "--json"], check=True, capture_output=True, text=True)
        summary.write_text(r.stdout)
    gen = json.loads(summary.read_text())
    gen["cached"] = cached
    return gen["files"]["if"], gen["files"]["meta"], gen["files"]["truth"], gen


def gnss_sdr_config(path, out_dir, fs_hz, channels=CHANNELS):
    """The GNSS-SDR configuration of the run (INI text)."""
    fs = int(round(fs_hz))
    return "\n".join([
        "[GNSS-SDR]",
        f"GNSS-SDR.internal_fs_sps={fs}",
        "SignalSource.implementation=File_Signal_Source",
        f"SignalSource.filename={path}",
        "SignalSource.item_type=ibyte",
        f"SignalSource.sampling_frequency={fs}",
        "SignalSource.samples=0",
        "SignalSource.repeat=false",
        "SignalSource.enable_throttle_control=false",
        "SignalConditioner.implementation=Signal_Conditioner",
        "DataTypeAdapter.implementation=Ibyte_To_Complex",
        "InputFilter.implementation=Pass_Through",
        "InputFilter.item_type=gr_complex",
        "Resampler.implementation=Pass_Through",
        "Resampler.item_type=gr_complex",
        "Channel.signal=1C",
        f"Channels_1C.count={channels}",
        "Channels.in_acquisition=1",
        "Acquisition_1C.implementation=GPS_L1_CA_PCPS_Acquisition",
        "Acquisition_1C.item_type=gr_complex",
        "Acquisition_1C.coherent_integration_time_ms=1",
        "Acquisition_1C.pfa=0.01",
        "Acquisition_1C.doppler_max=10000",
        "Acquisition_1C.doppler_step=250",
        "Tracking_1C.implementation=GPS_L1_CA_DLL_PLL_Tracking",
        "Tracking_1C.item_type=gr_complex",
        "Tracking_1C.pll_bw_hz=35.0",
        "Tracking_1C.dll_bw_hz=2.0",
        "Tracking_1C.early_late_space_chips=0.5",
        "TelemetryDecoder_1C.implementation=GPS_L1_CA_Telemetry_Decoder",
        "Observables.implementation=Hybrid_Observables",
        "PVT.implementation=RTKLIB_PVT",
        "PVT.positioning_mode=Single",
        "PVT.output_rate_ms=100",
        "PVT.display_rate_ms=1000",
        "PVT.iono_model=Broadcast",
        "PVT.trop_model=Saastamoinen",
        f"PVT.elevation_mask={MASK_DEG:g}",
        f"PVT.output_path={out_dir}",
        "PVT.nmea_output_file_enabled=true",
        "PVT.nmea_dump_filename=gnss_sdr_pvt.nmea",
        "PVT.nmea_rate_ms=100",
        "PVT.flag_nmea_tty_port=false",
        "PVT.flag_rtcm_server=false",
        "PVT.flag_rtcm_tty_port=false",
        "PVT.kml_output_enabled=true",
        "PVT.rinex_output_enabled=true",
        "PVT.gpx_output_enabled=false",
        "PVT.geojson_output_enabled=false",
        "PVT.xml_output_enabled=false",
        "",
    ])


def timed(cmd, cwd=None, stdout_path=None):
    """Run ``cmd``; (wall s, CPU s = user + system of it and its threads, return code, stdout text)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        proc = subprocess.Popen(cmd, stdout=fo, stderr=fe, stdin=subprocess.DEVNULL, text=True, cwd=cwd)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read(), fe.read()
    rc = os.waitstatus_to_exitcode(status)
    if stdout_path:
        Path(stdout_path).write_text(out + err)
    return wall, usage.ru_utime + usage.ru_stime, rc, out, err


def read_gga(path):
    """(UTC seconds of day, lat deg, lon deg, ellipsoidal height m, satellites used) of every GGA
    sentence with a fix (quality > 0) in an NMEA file; height = altitude + geoid separation."""
    rows = []
    for line in Path(path).read_text(errors="replace").splitlines():
        body = line.strip().split("*")[0]
        f = body.split(",")
        if len(f) < 12 or not f[0].endswith("GGA") or not f[2] or not f[6] or int(f[6] or 0) == 0:
            continue
        hms = f[1]
        tod = int(hms[0:2]) * 3600 + int(hms[2:4]) * 60 + float(hms[4:])
        lat = (int(f[2][:2]) + float(f[2][2:]) / 60.0) * (1 if f[3] == "N" else -1)
        lon = (int(f[4][:3]) + float(f[4][3:]) / 60.0) * (1 if f[5] == "E" else -1)
        h = float(f[9] or 0.0) + float(f[11] or 0.0)
        rows.append((tod, lat, lon, h, int(f[7] or 0)))
    return rows


def position_errors(rows, truth_e, start_tow_s):
    """Figures of the GGA fixes ``rows`` against the static truth position ``truth_e`` (ECEF)."""
    from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh, llh_to_ecef

    if not rows:
        return {"fixes": 0, "first_fix_s": None, "pos_err_rms_m": None, "median_err_h_m": None,
                "median_err_v_m": None, "sats_used_median": None}
    P = np.array([llh_to_ecef(math.radians(r[1]), math.radians(r[2]), r[3]) for r in rows])
    d = P - truth_e
    llh = ecef_to_llh(np.asarray(truth_e, dtype=float).copy())
    C = dcm_ecef_from_enu(llh[0], llh[1])
    med = np.median(P, axis=0) - truth_e
    enu = med @ C
    start_tod = (start_tow_s - LEAP_S) % 86400.0
    return {"fixes": len(rows), "first_fix_s": round((rows[0][0] - start_tod) % 86400.0, 2),
            "pos_err_rms_m": float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))),
            "pos_err_p95_m": float(np.percentile(np.linalg.norm(d, axis=1), 95)),
            "median_err_h_m": float(math.hypot(enu[0], enu[1])), "median_err_v_m": float(enu[2]),
            "sats_used_median": float(np.median([r[4] for r in rows]))}


def run_gnss_sdr(exe, path, tmp):
    out_dir = Path(tmp) / "gnss-sdr"
    out_dir.mkdir()
    conf = out_dir / "run.conf"
    conf.write_text(gnss_sdr_config(path, out_dir, FS_HZ))
    wall, cpu, rc, out, err = timed([exe, f"--config_file={conf}", f"--log_dir={out_dir}"], cwd=out_dir,
                                    stdout_path=out_dir / "console.txt")
    nmea = sorted(out_dir.glob("*.nmea"))
    r = {"wall_s": wall, "cpu_s": cpu, "returncode": rc, "nmea": [p.name for p in nmea],
         "kml": [p.name for p in out_dir.glob("*.kml")], "rinex": sorted(p.name for p in out_dir.glob("GSDR*"))}
    if rc != 0:
        r["error"] = (err.strip().splitlines() or out.strip().splitlines() or ["(no output)"])[-1]
    r["_rows"] = read_gga(nmea[0]) if nmea else []
    return r


def run_ultratight(path, tmp):
    nmea = Path(tmp) / "ultratight.nmea"
    base = [sys.executable, "-m", "ultratight.receiver.cli", "process", path, "--json", "--no-progress"]
    timed(base + ["--duration", "1"])                    # numba cache load, outside the figures
    wall, cpu, rc, out, err = timed(base + ["--nmea", str(nmea)])
    r = {"wall_s": wall, "cpu_s": cpu, "returncode": rc}
    if rc != 0:
        r["error"] = (err.strip().splitlines() or ["(no output)"])[-1]
        r["_rows"] = []
        return r
    summ = json.loads(out)
    r["tracked"] = len(summ.get("tracked", []))
    r["search"] = summ.get("search")
    r["_rows"] = read_gga(nmea) if nmea.is_file() else []
    return r


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--duration", type=float, default=None, help="file length, s (60; --quick 40)")
    ap.add_argument("--workdir", default=os.path.join(tempfile.gettempdir(), "ultratight-bench-vs-gnss-sdr"))
    ap.add_argument("--gnss-sdr", default="gnss-sdr", help="the GNSS-SDR binary (default: gnss-sdr on PATH)")
    ap.add_argument("--seed", type=int, default=1, help="the generator's seed (1: the benchmark's file; others: "
                                                        "other draws of the same sky and noise level)")
    args = ap.parse_args()
    if args.seed < 0:
        ap.error(f"--seed must be >= 0, got {args.seed}")
    exe = shutil.which(args.gnss_sdr)
    if exe is None:
        reason = f"{args.gnss_sdr} not found on PATH (the Debian package gnss-sdr provides it): peer benchmark skipped"
        print(reason)
        finish(args, {"skipped": reason})
        return 0
    duration = args.duration or (40.0 if args.quick else 60.0)
    os.makedirs(args.workdir, exist_ok=True)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    path, meta, truth, gen = ensure_file(args.workdir, duration, args.seed)
    t_gen = time.perf_counter() - t0
    import h5py

    with h5py.File(truth, "r") as f:
        truth_e = np.asarray(f["pos_e"][0], dtype=float)
    start_tow = float(json.loads(Path(meta).read_text())["start_tow_s"])
    with tempfile.TemporaryDirectory() as tmp:
        gs = run_gnss_sdr(exe, os.path.abspath(path), tmp)
        ut = run_ultratight(os.path.abspath(path), tmp)
    rep = {"scenario": SCENARIO, "duration_s": duration, "seed": args.seed, "fs_hz": FS_HZ, "format": "ci8 (int8 I/Q)",
           "satellites": len(gen["prns"]), "generate_s": None if gen["cached"] else round(t_gen, 2),
           "file_cached": gen["cached"], "gnss_sdr_binary": exe,
           "gnss_sdr_channels": CHANNELS, "load_avg_1m_start": round(load0, 2)}
    for name, r in (("gnss_sdr", gs), ("ultratight", ut)):
        rows = r.pop("_rows")
        r.update(position_errors(rows, truth_e, start_tow))
        r["cpu_percent"] = round(100.0 * r["cpu_s"] / r["wall_s"], 1) if r["wall_s"] > 0 else None
        r["wall_s"], r["cpu_s"] = round(r["wall_s"], 2), round(r["cpu_s"], 2)
        rep[name] = r
    rep["wall_ratio"] = round(ut["wall_s"] / gs["wall_s"], 3) if gs["wall_s"] > 0 else None
    rep["cpu_ratio"] = round(ut["cpu_s"] / gs["cpu_s"], 3) if gs["cpu_s"] > 0 else None
    _print(rep)
    finish(args, rep)
    return 0


def _print(rep):
    def g(v, fmt):
        return "n/a" if v is None else format(v, fmt)
    print(f"{rep['scenario']} {rep['duration_s']:g} s (seed {rep['seed']}), {rep['fs_hz'] / 1e6:g} MHz "
          f"{rep['format']}, "
          f"{rep['satellites']} satellites ("
          + ("generated earlier" if rep["file_cached"] else f"generated in {rep['generate_s']} s")
          + f"; load average at the start {rep['load_avg_1m_start']:.2f})")
    print(f"{'receiver':<32} {'wall s':>7} {'CPU s':>7} {'CPU %':>6} {'fixes':>6} {'1st fix s':>9} "
          f"{'RMS 3-D m':>9} {'median H m':>10} {'median V m':>10}")
    for name, label in (("gnss_sdr", f"GNSS-SDR ({rep['gnss_sdr_channels']} channels)"),
                        ("ultratight", "ultratight process (defaults)")):
        r = rep[name]
        print(f"{label:<32} {r['wall_s']:>7.2f} {r['cpu_s']:>7.2f} {g(r['cpu_percent'], '.0f'):>6} {r['fixes']:>6} "
              f"{g(r['first_fix_s'], '.1f'):>9} {g(r['pos_err_rms_m'], '.2f'):>9} {g(r['median_err_h_m'], '.2f'):>10} "
              f"{g(r['median_err_v_m'], '.2f'):>10}" + (f"  ERROR: {r['error']}" if r.get("error") else ""))
    print(f"wall ratio ultratight / GNSS-SDR: {g(rep['wall_ratio'], '.2f')} (CPU ratio {g(rep['cpu_ratio'], '.2f')})")


if __name__ == "__main__":
    sys.exit(main())
