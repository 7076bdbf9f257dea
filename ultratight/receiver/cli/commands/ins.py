"""``ultratight ins``: free-inertial SINS run on a scenario's synthetic IMU or on an IMU file."""

HELP = "free-inertial SINS run on a scenario (synthetic IMU) or an IMU file; errors vs truth"


def add_arguments(parser):
    parser.add_argument("source", metavar="SCENARIO_OR_IMU_FILE",
                        help="scenario name / TOML path, or an IMU file (.h5/.hdf5 or .csv)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--rate", type=float, default=None, help="IMU rate for synthesis, Hz (default: "
                        "the scenario's imu.rate_hz or 100)")
    parser.add_argument("--duration", type=float, default=None, help="run only the first S seconds")
    parser.add_argument("--errors", default=None,
                        help="IMU error preset for synthesis (ideal, paper, navigation, tactical, mems); "
                             "default: the scenario's [imu] table")
    parser.add_argument("--seed", type=int, default=None, help="seed for the IMU noise (default: scenario's)")
    parser.add_argument("--save-imu", default=None, metavar="PATH",
                        help="also write the synthesised IMU (HDF5) to PATH")
    parser.add_argument("--init-llh", type=float, nargs=3, default=None, metavar=("LAT_DEG", "LON_DEG", "H_M"),
                        help="initial position for an IMU file without truth")
    parser.add_argument("--init-vel", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("E", "N", "U"),
                        help="initial ENU velocity (m/s) for an IMU file without truth")
    parser.add_argument("--init-att", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                        metavar=("ROLL", "PITCH", "YAW"),
                        help="initial attitude (deg; yaw clockwise from north) for an IMU file without truth")
    from ultratight.receiver.cli.commands import imu_flags
    imu_flags.add_arguments(parser)


def _load_scenario(name):
    """Scenario dict of a built-in name or TOML path (ConfigError when neither)."""
    from ultratight.receiver.cli.scenario_config import load_scenario
    return load_scenario(name)


def _check_args(args, src, path, is_file):
    """Checks of the command line (one-line ConfigError naming the flag)."""
    import math

    from ultratight import io_guard
    from ultratight.errors import ConfigError
    from ultratight.receiver.cli.scenario_config import MAX_IMU_RATE_HZ

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ConfigError(f"--duration must be a finite number > 0, got {args.duration}")
    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0):
        raise ConfigError(f"--rate must be a finite number > 0, got {args.rate}")
    if args.rate is not None and args.rate > MAX_IMU_RATE_HZ:
        raise ConfigError(f"--rate {args.rate:g} Hz exceeds the IMU rate cap of {MAX_IMU_RATE_HZ:g} Hz")
    if args.seed is not None and args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {args.seed}")
    for flag, vals in (("--init-llh", args.init_llh), ("--init-vel", args.init_vel), ("--init-att", args.init_att)):
        if vals is not None and not all(math.isfinite(v) for v in vals):
            raise ConfigError(f"{flag} must be finite numbers, got {' '.join(str(v) for v in vals)}")
    if args.init_llh is not None:
        lat, lon, h = args.init_llh
        if not (-90 <= lat <= 90 and -180 <= lon <= 360 and -1e4 <= h <= 1e8):
            raise ConfigError(f"--init-llh: latitude in [-90, 90] deg, longitude in [-180, 360] deg, height in "
                              f"[-1e4, 1e8] m; got {lat} {lon} {h}")
    inputs = [("SOURCE", src)] if (path.exists() or "/" in src) else []
    if is_file:
        io_guard.check_input_file(path, "IMU file")
    io_guard.check_io(inputs, [("--save-imu", args.save_imu)])


def _synthesize(args, src):
    """``(imu, label, preset)`` synthesised from a scenario's trajectory and [imu] table."""
    from pathlib import Path

    import numpy as np

    from ultratight import io_guard
    from ultratight.ins import imu as imu_mod
    from ultratight.ins.imu_data import write_imu_h5
    from ultratight.ins.trajectory import build_trajectory

    cfg = _load_scenario(src)
    duration = float(args.duration if args.duration is not None else cfg.get("duration_s", 60.0))
    traj = build_trajectory(cfg.get("trajectory", {"kind": "static"}), cfg["receiver"], duration)
    imu_cfg = dict(cfg.get("imu") or {"preset": "paper", "rate_hz": 100.0})
    if args.errors is not None:
        imu_cfg = {"preset": args.errors, "rate_hz": imu_cfg.get("rate_hz", 100.0)}
    if args.rate is not None:
        imu_cfg["rate_hz"] = args.rate
    rate = float(imu_cfg.get("rate_hz", 100.0))
    # synthesis holds ~40 float64 per IMU sample (increments, truth, quadrature) plus the SINS output
    io_guard.check_memory(duration * rate * 8 * 60, f"an IMU of {duration:g} s at {rate:g} Hz")
    if args.save_imu:
        io_guard.check_disk(Path(args.save_imu).parent, duration * rate * 8 * 20, f"--save-imu {args.save_imu}")
    errors = imu_mod.imu_errors_from_config(imu_cfg)
    seed = int(args.seed if args.seed is not None else cfg.get("seed", 1))
    lever = imu_cfg.get("lever_arm_m")
    imu = imu_mod.synthesize_imu(traj, rate, errors, np.random.default_rng(seed), duration_s=duration,
                                 lever_arm_b=None if lever is None else np.asarray(lever, float))
    if args.save_imu:
        write_imu_h5(args.save_imu, imu, {"scenario": cfg.get("name", src), "seed": seed})
    return imu, cfg.get("name", src), errors.preset


def _initial_state(args, src, truth):
    """SINS initial state: the truth's first sample, else --init-llh / --init-vel / --init-att."""
    import math

    import numpy as np

    from ultratight.errors import ConfigError
    from ultratight.ins.attitude import euler_to_quat
    from ultratight.ins.sins import make_state

    if truth is not None:
        return make_state(truth["q_lb"][0], truth["vel_l"][0], truth["llh"][0])
    if args.init_llh is None:
        raise ConfigError(f"{src}: the IMU file carries no truth; give the initial state with "
                          "--init-llh LAT_DEG LON_DEG H_M (and --init-vel, --init-att)")
    lat, lon, h = args.init_llh
    r, p, y = (math.radians(a) for a in args.init_att)
    return make_state(euler_to_quat(r, p, y), np.array(args.init_vel, float),
                      np.array([math.radians(lat), math.radians(lon), h]))


def _errors_vs_truth(out, q, v, p, truth, n, dt):
    """Navigation errors against the truth into ``out``; returns the printed table rows."""
    import numpy as np

    from ultratight.ins.sins import nav_errors

    m = min(n + 1, truth["llh"].shape[0])
    dpos, dvel, datt = nav_errors(q[:m], v[:m], p[:m], truth["q_lb"][:m], truth["vel_l"][:m], truth["llh"][:m])
    pe = np.linalg.norm(dpos, axis=1)
    ve = np.linalg.norm(dvel, axis=1)
    ae = np.degrees(np.linalg.norm(datt, axis=1))
    out.update({
        "final_pos_err_m": float(pe[-1]), "final_vel_err_mps": float(ve[-1]),
        "final_att_err_deg": float(ae[-1]), "max_pos_err_m": float(pe.max()),
        "max_vel_err_mps": float(ve.max()), "max_att_err_deg": float(ae.max()),
        "final_pos_err_enu_m": dpos[-1].tolist(), "final_vel_err_enu_mps": dvel[-1].tolist(),
    })
    step = max(1, (m - 1) // 10)
    return [(k * dt, pe[k], ve[k], ae[k]) for k in list(range(0, m, step)) + ([m - 1] if (m - 1) % step else [])]


def _print_human(out, table, v, label, n, imu, preset, run_time):
    import numpy as np

    print(f"ultratight ins: {label}  ({n} IMU steps at {imu.rate_hz:g} Hz"
          + (f", errors '{preset}'" if preset else "") + ")")
    print(f"mechanisation: {run_time * 1e3:.1f} ms ({out['steps_per_s'] / 1e6:.2f} M steps/s)")
    if table:
        print(f"{'t (s)':>9} {'pos err (m)':>14} {'vel err (m/s)':>14} {'att err (deg)':>14}")
        for t, a, b, c in table:
            print(f"{t:9.2f} {a:14.6g} {b:14.6g} {c:14.6g}")
    else:
        lat, lon, h = out["final_llh_deg_m"]
        print(f"final position: lat {lat:.8f} deg, lon {lon:.8f} deg, h {h:.3f} m; "
              f"velocity ENU {np.round(v[-1], 4).tolist()} m/s (no truth in file)")


def run(args):
    import math
    import time
    from pathlib import Path

    import numpy as np

    from ultratight import io_guard
    from ultratight.errors import ConfigError
    from ultratight.ins import imu_decl
    from ultratight.ins.sins import sins_run
    from ultratight.receiver.cli.commands import imu_flags

    src = args.source
    path = Path(src)
    is_file = path.suffix.lower() in (".h5", ".hdf5", ".csv") and (path.exists() or "/" in src)
    _check_args(args, src, path, is_file)
    preset = None
    if is_file:
        if args.errors is not None or args.rate is not None:
            raise ConfigError("--errors/--rate apply to scenario synthesis, not to an IMU file")
        imu = imu_decl.read_imu_file(path, imu_flags.overrides(args))
        label = str(path)
    else:
        if imu_flags.overrides(args):
            raise ConfigError("the --imu-*/--lever-arm flags declare an IMU file, not a scenario's synthetic IMU")
        imu, label, preset = _synthesize(args, src)
    n = imu.n
    if args.duration is not None and is_file:
        n = int(np.searchsorted(imu.t, imu.t0 + args.duration + 1e-9, side="right"))
        if n < 1:
            raise ConfigError(f"--duration {args.duration} s holds no IMU sample")
    dt = 1.0 / imu.rate_hz
    truth = imu.truth
    x0 = _initial_state(args, src, truth)
    dth = np.ascontiguousarray(imu.dtheta_b[:n])
    dv = np.ascontiguousarray(imu.dv_b[:n])
    sins_run(x0, dth[:2], dv[:2], dt)          # compile / warm up outside the timing
    t0 = time.perf_counter()
    q, v, p = sins_run(x0, dth, dv, dt)
    run_time = time.perf_counter() - t0
    out = {
        "source": label, "imu_rate_hz": imu.rate_hz, "duration_s": n * dt, "n_steps": int(n),
        "errors_preset": preset, "run_time_s": run_time, "steps_per_s": n / run_time if run_time > 0 else None,
        "final_llh_deg_m": [math.degrees(p[-1, 0]), math.degrees(p[-1, 1]), float(p[-1, 2])],
        "final_vel_enu_mps": v[-1].tolist(),
    }
    if is_file and "declaration" in (imu.meta or {}):
        out["imu_declaration"] = imu.meta["declaration"]
        out["sanity_check"] = imu.meta.get("sanity_check")
    table = _errors_vs_truth(out, q, v, p, truth, n, dt) if truth is not None else []
    if args.json:
        print(io_guard.json_dumps(out, indent=2))
        return 0
    _print_human(out, table, v, label, n, imu, preset, run_time)
    return 0
