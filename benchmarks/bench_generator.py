"""Benchmark the IF generator.

    python benchmarks/bench_generator.py [--quick] [--json OUT.json] [--duration S]

Figures:
* ``kernel_msat_per_s``: the numba synthesis kernel alone (13 satellites, 4 MHz complex),
  million satellite-samples per second on one core;
* ``*_per_cpu_s``: the same per second of process CPU time (robust when the machine is
  shared);
* ``end_to_end_*``: ``generate()`` on the paper-highdyn scenario (13 satellites, 4 MHz ci8,
  noise, quantisation, file + truth + IMU writing) for ``--duration`` seconds (60 s by default,
  5 s with ``--quick``), wall time and satellite-samples per second;
* the time split (geometry, kernel, noise, quantise+write) measured on 1 s of signal.
"""

import argparse
import os
import tempfile
import time

import numpy as np

from _common import add_common_args, finish


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--duration", type=float, default=None, help="end-to-end seconds (default 60; 5 with --quick)")
    args = ap.parse_args()
    duration = args.duration or (5.0 if args.quick else 60.0)

    from ultratight.ins.trajectory import build_trajectory
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.synth import generator as g
    from ultratight.signals.synth.frontend import FrontEnd

    cfg = load_scenario("paper-highdyn", {"duration_s": duration})
    traj = build_trajectory(cfg["trajectory"], cfg["receiver"], duration)
    p0, _ = traj.pos_vel_e(np.zeros(1))
    ephs, cn0 = g._ephemerides(cfg, p0[0])
    fs = cfg["frontend"]["fs_hz"]
    plan = g.SignalPlan(ephs, cn0, traj, cfg["time"]["week"], cfg["time"]["tow_s"], fs, 0.0, True)
    nsat, L, B = len(ephs), plan.L, g.BLOCK_INTERVALS
    t0 = time.perf_counter()
    g.set_nav_bits(plan, 1.0, True)
    t_nav = time.perf_counter() - t0

    # split on 1 s (10 blocks)
    t_geo = t_ker = t_noise = t_q = 0.0
    rng = np.random.default_rng(1)
    fe = FrontEnd(fs)
    buf = np.empty(B * L * 2, np.float32)
    amps = np.broadcast_to(plan.amp, (B, nsat)).astype(np.float32)
    # compile outside the timing
    coefs, ep, _, _ = plan.coefficients(0, B)
    bits = plan.bit_values(ep)
    g._synth_complex(buf.reshape(-1, 2), L, B, plan.codes, coefs, amps, bits, g.COS_LUT, g.SIN_LUT)
    n_blocks = 10
    c_ker = 0.0
    for b in range(n_blocks):
        t = time.perf_counter()
        coefs, ep, _, _ = plan.coefficients(b * B, B)
        bits = plan.bit_values(ep)
        t_geo += time.perf_counter() - t
        t = time.perf_counter()
        rng.standard_normal(out=buf, dtype=np.float32)
        t_noise += time.perf_counter() - t
        t = time.perf_counter()
        c = time.process_time()
        g._synth_complex(buf.reshape(-1, 2), L, B, plan.codes, coefs, amps, bits, g.COS_LUT, g.SIN_LUT)
        t_ker += time.perf_counter() - t
        c_ker += time.process_time() - c
        t = time.perf_counter()
        y = fe.quantize_block(buf.view(np.complex64), 1.0)
        y.view(np.float32).astype(np.int8).tobytes()
        t_q += time.perf_counter() - t
    n_ss = n_blocks * B * L * nsat
    kernel_rate = n_ss / t_ker / 1e6

    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        c = time.process_time()
        res = g.generate(cfg, d, "bench", progress=False)
        t_e2e = time.perf_counter() - t
        cpu_e2e = time.process_time() - c
        size = os.path.getsize(res["if"])
    n_samp = int(round(duration * fs))
    out = {
        "satellites": nsat, "fs_hz": fs, "format": cfg["frontend"]["format"],
        "kernel_msat_per_s": kernel_rate,
        "kernel_msat_per_cpu_s": n_ss / c_ker / 1e6,
        "split_per_signal_second_s": {"geometry": t_geo, "kernel": t_ker, "noise": t_noise,
                                      "quantise_pack": t_q, "nav_bits_setup": t_nav},
        "end_to_end_duration_s": duration,
        "end_to_end_wall_s": t_e2e,
        "end_to_end_cpu_s": cpu_e2e,
        "end_to_end_msat_per_s": n_samp * nsat / t_e2e / 1e6,
        "end_to_end_msat_per_cpu_s": n_samp * nsat / cpu_e2e / 1e6,
        "end_to_end_realtime_factor": t_e2e / duration,
        "if_file_bytes": size,
    }
    sp = out["split_per_signal_second_s"]
    print(f"paper-highdyn, {nsat} satellites, {fs / 1e6:g} MHz {out['format']}")
    print(f"synthesis kernel: {kernel_rate:.1f} M satellite-samples/s ({out['kernel_msat_per_cpu_s']:.1f} per CPU s)")
    print(f"1 s of signal: geometry {sp['geometry']:.2f} s, kernel {sp['kernel']:.2f} s, noise {sp['noise']:.2f} s, "
          f"quantise+pack {sp['quantise_pack']:.2f} s")
    print(f"generate() {duration:g} s: {t_e2e:.1f} s wall, {cpu_e2e:.1f} s CPU, real-time factor "
          f"{out['end_to_end_realtime_factor']:.2f}, {out['end_to_end_msat_per_s']:.1f} M satellite-samples/s")
    finish(args, out)

if __name__ == "__main__":
    main()
