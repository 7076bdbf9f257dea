"""The work of ``ultratight integrate`` (:mod:`ultratight.receiver.cli.commands.integrate`): read the logs,
check them against each other, run the filter, evaluate, write the outputs.

Positions in every output file are those of the **antenna** (the GNSS reference point, the point an
RTK reference gives): the filter's IMU position plus ``C_lb`` times the lever arm.  The CSV adds the
attitude, the sensor-bias estimates and the σ.  Outputs are written atomically; nothing is written
when the inputs are refused.
"""

import math
import time

import numpy as np

from ultratight.errors import ConfigError, InputFileError
from ultratight.io_guard import json_clean, json_dumps

DEG = math.pi / 180.0
CSV_COLUMNS = ("gps_week", "gps_tow_s", "lat_deg", "lon_deg", "h_m", "vel_e_mps", "vel_n_mps", "vel_u_mps",
               "roll_deg", "pitch_deg", "yaw_deg", "sigma_e_m", "sigma_n_m", "sigma_u_m", "sigma_ve_mps",
               "sigma_vn_mps", "sigma_vu_mps", "sigma_roll_deg", "sigma_pitch_deg", "sigma_yaw_deg",
               "gyro_bias_x_dps", "gyro_bias_y_dps", "gyro_bias_z_dps", "accel_bias_x_mps2", "accel_bias_y_mps2",
               "accel_bias_z_mps2", "clock_m", "clock_drift_mps", "in_outage")


# ------------------------------------------------------------------ checks
def _check_numbers(args):
    for flag, v in (("--heading", args.heading), ("--rate", args.rate)):
        if v is not None and not math.isfinite(v):
            raise ConfigError(f"{flag} must be a finite number, got {v}")
    if args.mount is not None and not all(math.isfinite(v) for v in args.mount):
        raise ConfigError(f"--mount needs three finite angles (deg), got {' '.join(map(str, args.mount))}")
    if args.lever_arm is not None and not all(math.isfinite(v) and abs(v) < 100.0 for v in args.lever_arm):
        raise ConfigError("--lever-arm needs three finite numbers below 100 m")
    args.gate_p = _gate(args.gate)
    if args.rate < 0.0:
        raise ConfigError(f"--rate must be >= 0 Hz (0: every IMU sample), got {args.rate:g}")
    if args.outage_keep_sats < 0:
        raise ConfigError(f"--outage-keep-sats must be >= 0, got {args.outage_keep_sats}")
    if args.outage_keep_sats and args.coupling != "tight":
        raise ConfigError("--outage-keep-sats keeps satellites of raw observations: it needs --coupling tight")
    if args.outages and args.outage:
        raise ConfigError("give --outages EVERY:LENGTH or --outage START:LENGTH windows, not both")
    from ultratight.fusion.gins import evaluation as ev
    for s in args.outage:
        ev.parse_outage(s)
    if args.outages:
        ev.parse_outages_every(args.outages)
    if args.reference_geoid is not None and not (args.reference and math.isfinite(args.reference_geoid)
                                                 and abs(args.reference_geoid) < 200.0):
        raise ConfigError("--reference-geoid needs --reference and a finite undulation below 200 m")
    if args.plot and not args.reference:
        raise ConfigError("--plot draws the error against --reference: give --reference REF.pos")
    if args.nav and args.coupling != "tight":
        raise ConfigError("--nav is the navigation data of raw observations: it needs --coupling tight")


def _gate(text):
    if str(text).strip().lower() in ("off", "none"):
        return None
    try:
        p = float(text)
    except ValueError:
        p = math.nan
    if not 0.0 < p < 1.0:
        raise ConfigError(f"--gate {text!r}: a false-alarm probability in (0, 1), or off")
    return p


def _imu_tag(args):
    from pathlib import Path
    if args.imu_tag:
        return args.imu_tag
    auto = Path(str(args.imu) + ".tag")
    return str(auto) if auto.exists() else None


def _check_paths(args):
    from ultratight import io_guard
    from ultratight.ins import imu_decl
    ins = [("--imu", args.imu), ("--gnss", args.gnss)]
    for flag, p in (("--imu-tag", args.imu_tag), ("--nav", args.nav), ("--reference", args.reference)):
        if p is not None:
            ins.append((flag, p))
    for flag, p in ins:
        io_guard.check_input_file(p, f"{flag} file")
    companions = [("IMU sidecar", str(imu_decl.sidecar_path(args.imu))), ("IMU time tag", str(args.imu) + ".tag"),
                  ("GNSS time tag", str(args.gnss) + ".tag")]
    from ultratight.receiver.cli.commands.integrate import OUTPUT_FLAGS
    io_guard.check_io(ins + companions, [(flag, getattr(args, dest)) for flag, dest in OUTPUT_FLAGS],
                      companions=companions)


# ------------------------------------------------------------------ inputs
def _read_imu(args):
    from ultratight.ins.imu_logs import read_imu_log
    from ultratight.receiver.cli.commands import imu_flags
    ov = imu_flags.overrides(args, lever_arm=False)
    imu = read_imu_log(args.imu, fmt=args.imu_format, declaration_overrides=ov, tag=_imu_tag(args),
                       gps_week=args.gps_week, mount_deg=args.mount)
    lever = imu_flags.lever_arm_flu(args)
    if lever is not None:
        imu.lever_arm_b = np.asarray(lever, float)
    return imu


def _noise(args):
    from ultratight.ins import imu_decl
    from ultratight.receiver.cli.commands import imu_flags
    try:
        dec = imu_decl.resolve_declaration(args.imu, {})
    except (ConfigError, InputFileError):
        dec = None
    from ultratight.receiver.cli.commands.integrate import SCALE_FLAGS
    flags = imu_flags.noise_flags(args)
    flags.update({key: getattr(args, flag[2:].replace("-", "_"), None) for flag, key, _t in SCALE_FLAGS})
    try:
        return imu_decl.resolve_noise(dec, grade=getattr(args, "imu_grade", None), **flags)
    except ConfigError as exc:
        raise ConfigError(f"{exc} (the filter is tuned from the IMU's declared noise: --imu-grade or the "
                          "--imu-*-noise/-bias flags, or the sidecar's noise table)") from None


def _gnss_kind(args):
    """'pos' | 'nmea' | 'ubx' | 'rinex' of the GNSS file (declared or recognised)."""
    from ultratight.receiver.io.solution_files import sniff_format
    seen = sniff_format(args.gnss)
    if seen is None:
        with open(args.gnss, "rb") as fh:
            head = fh.read(4096)
        if b"RINEX VERSION / TYPE" in head:
            seen = "rinex"
        elif head[:2] == b"\xb5\x62":
            seen = "ubx"
    fmt = args.gnss_format
    if fmt == "auto":
        if seen is None:
            raise InputFileError(f"{args.gnss}: not a GNSS log this command knows (RTKLIB .pos, NMEA, u-blox UBX, "
                                 "RINEX observations)")
        return seen
    if seen is not None and seen != fmt:
        raise InputFileError(f"{args.gnss}: declared --gnss-format {fmt} but the content looks like {seen}")
    return fmt


def _read_gnss(args):
    """(fixes, tight, t_gnss, source line) for the coupling asked."""
    kind = _gnss_kind(args)
    if args.coupling == "loose":
        if kind == "rinex":
            raise ConfigError(f"{args.gnss}: RINEX observations are raw measurements: use --coupling tight "
                              "(or run 'ultratight spp' and couple its solution loosely)")
        from ultratight.receiver.io.solution_files import read_gnss
        fixes = read_gnss(args.gnss, fmt=kind, leap_s=args.leap_seconds, gps_week=args.gps_week,
                          date=args.date)
        if fixes.n == 0:
            raise InputFileError(f"{args.gnss}: no GNSS epoch in the file")
        return fixes, None, fixes.t, f"{kind} solution, {fixes.n} epochs"
    if kind not in ("rinex", "ubx"):
        raise ConfigError(f"{args.gnss}: tight coupling needs raw observations (RINEX observations or a u-blox log "
                          f"with RXM-RAWX), not a {kind} solution")
    raw, nav = _raw_and_nav(args, kind)
    from ultratight.fusion.gins.tight_meas import TightMeasurements
    tight = TightMeasurements(raw, nav)
    return None, tight, raw.t, f"{kind} raw observations, {raw.n_epochs} epochs, {len(nav.prns)} ephemeris PRNs"


def _raw_and_nav(args, kind):
    from ultratight.signals.rinex import read_rinex_nav
    nav = read_rinex_nav(args.nav) if args.nav else None
    if kind == "ubx":
        from ultratight.signals.ubx import read_ubx
        log = read_ubx(args.gnss, signals=getattr(args, "signals", "auto"))
        raw = log.raw
        if nav is None:
            nav = log.nav
    else:
        from ultratight.signals.rinex_obs import read_rinex_obs
        raw = read_rinex_obs(args.gnss)
        if nav is None:
            raise ConfigError(f"{args.gnss}: RINEX observations need --nav NAV (the broadcast ephemerides)")
    if raw is None or raw.n_epochs == 0:
        raise InputFileError(f"{args.gnss}: no raw GPS L1 C/A observation epoch in the file")
    if nav is None or not nav.prns:
        raise InputFileError(f"{args.gnss}: no broadcast ephemeris (give --nav NAV)")
    return raw, nav


def _check_overlap(imu, t_gnss, args):
    from ultratight.signals.observations import week_tow
    a0, a1 = float(imu.t0), float(imu.t[-1])
    b0, b1 = float(np.min(t_gnss)), float(np.max(t_gnss))
    if b1 < a0 or b0 > a1 or min(a1, b1) - max(a0, b0) < 1.0:
        w0, s0 = week_tow(a0)
        w1, s1 = week_tow(b0)
        raise InputFileError(f"the IMU log {args.imu} (GPS week {w0}, seconds {s0:.1f}-{s0 + a1 - a0:.1f}) and the "
                             f"GNSS log {args.gnss} (week {w1}, seconds {s1:.1f}-{s1 + b1 - b0:.1f}) do not overlap "
                             "in time (check --imu-time-offset, --gps-week and the time tags)")


# ------------------------------------------------------------------ outputs
def antenna_llh(res, lever_b):
    """(n, 3) antenna lat, lon, h of a GinsResult: IMU position + C_lb · lever arm (ENU → llh)."""
    from ultratight.ins.attitude import euler_to_dcm_vec
    from ultratight.ins.earth import radii
    lever_b = np.asarray(lever_b, float)
    if not np.any(lever_b):
        return res.llh.copy()
    C = euler_to_dcm_vec(res.euler_rad[:, 0], res.euler_rad[:, 1], res.euler_rad[:, 2])
    d = C @ lever_b                                   # (n, 3) ENU
    rm, rn = np.vectorize(radii)(res.llh[:, 0])
    out = res.llh.copy()
    out[:, 0] += d[:, 1] / (rm + res.llh[:, 2])
    out[:, 1] += d[:, 0] / ((rn + res.llh[:, 2]) * np.cos(res.llh[:, 0]))
    out[:, 2] += d[:, 2]
    return out


def _decimate(t, rate):
    if rate <= 0.0:
        return np.arange(t.size)
    k = np.floor((t - t[0]) * rate + 1e-6)
    first = np.ones(t.size, bool)
    first[1:] = k[1:] != k[:-1]
    return np.flatnonzero(first)


def _as_fixes(res, llh_ant, idx, coupling):
    from ultratight.signals.observations import GnssFixes
    q = np.where(res.in_outage[idx], 5, 2)
    return GnssFixes(res.t[idx], llh_ant[idx], res.vel_enu[idx], res.sigma_pos_enu[idx], res.sigma_vel_enu[idx],
                     q.astype(int), None, "ultratight integrate", {"mode": f"ins/gnss {coupling}"})


def _write_csv(path, res, llh_ant, idx):
    from ultratight.receiver.io.outputs import write_table_csv
    from ultratight.signals.observations import week_tow
    week, tow = week_tow(res.t[idx])
    clk = res.clock[idx] if res.clock is not None else np.full((idx.size, 2), np.nan)
    cols = [week, tow, llh_ant[idx, 0] / DEG, llh_ant[idx, 1] / DEG, llh_ant[idx, 2]]
    cols += [res.vel_enu[idx, j] for j in range(3)] + [res.euler_rad[idx, j] / DEG for j in range(3)]
    cols += [res.sigma_pos_enu[idx, j] for j in range(3)] + [res.sigma_vel_enu[idx, j] for j in range(3)]
    cols += [res.sigma_att_rad[idx, j] / DEG for j in range(3)] + [res.gyro_bias[idx, j] / DEG for j in range(3)]
    cols += [res.accel_bias[idx, j] for j in range(3)] + [clk[:, 0], clk[:, 1], res.in_outage[idx].astype(int)]
    write_table_csv(path, CSV_COLUMNS, list(zip(*cols)),
                    comment="ultratight integrate: antenna position (WGS-84; heights in the datum of the GNSS input), ENU velocity, "
                            "attitude (yaw clockwise from north), 1-sigma, bias estimates (body FLU)")


def _write_outputs(args, res, llh_ant):
    from ultratight.receiver.io.solution_files import write_kml, write_nmea, write_pos
    idx = _decimate(res.t, args.rate)
    fx = _as_fixes(res, llh_ant, idx, args.coupling)
    written = []
    if args.out:
        write_pos(args.out, fx, program="ultratight integrate")
        written.append(args.out)
    if args.csv:
        _write_csv(args.csv, res, llh_ant, idx)
        written.append(args.csv)
    if args.kml:
        write_kml(args.kml, fx, name=f"ultratight integrate ({args.coupling}, {args.filter})")
        written.append(args.kml)
    if args.nmea:
        write_nmea(args.nmea, fx, leap_s=args.leap_seconds)
        written.append(args.nmea)
    return written


# ------------------------------------------------------------------ the run
def _options(args, noise, imu, windows):
    from ultratight.fusion.gins.options import GinsOptions
    return GinsOptions(coupling=args.coupling, filter=args.filter, noise=noise,
                       lever_arm_b=np.asarray(imu.lever_arm_b, float), heading_deg=args.heading,
                       zupt=args.zupt, nhc=args.nhc, smooth=args.smooth, gate_p=args.gate_p, outages=tuple(windows),
                       outage_keep_sats=args.outage_keep_sats)


def _windows(args, imu, t_gnss):
    from ultratight.fusion.gins import evaluation as ev
    outs = [ev.parse_outage(s) for s in args.outage]
    every = ev.parse_outages_every(args.outages) if args.outages else None
    if not outs and every is None:
        return []
    t_first = max(float(imu.t0), float(np.min(t_gnss)))
    return ev.outage_windows(t_first, float(np.max(t_gnss)), outages=outs, every=every)


def _progress(args, err):
    """A progress callback writing one updated line on a terminal (None when quiet, --json or no tty)."""
    if args.quiet or args.json or not getattr(err, "isatty", lambda: False)():
        return None

    def show(fraction):
        end = "\n" if fraction >= 1.0 else ""
        print(f"\rintegrate: filter {100.0 * fraction:5.1f} %", end=end, file=err, flush=True)
    return show


def run_integrate(args, out, err):
    t_start = time.perf_counter()
    _check_numbers(args)
    _check_paths(args)
    noise = _noise(args)
    imu = _read_imu(args)
    fixes, tight, t_gnss, source = _read_gnss(args)
    for w in getattr(tight, "warnings", None) or []:
        print(f"ultratight integrate: warning: {w}", file=err)
    _check_overlap(imu, t_gnss, args)
    windows = _windows(args, imu, t_gnss)
    ref = None
    if args.reference:
        from ultratight.receiver.io.solution_files import read_pos
        ref = read_pos(args.reference)
        if args.reference_geoid is not None:
            ref.llh[:, 2] += args.reference_geoid
    opts = _options(args, noise, imu, windows)
    from ultratight.fusion.gins.runner import run_gins
    t_read = time.perf_counter() - t_start
    res = run_gins(imu, opts, fixes=fixes, tight=tight, progress=_progress(args, err))
    t_filter = time.perf_counter() - t_start - t_read
    llh_ant = antenna_llh(res, imu.lever_arm_b)
    evaluation = series = None
    if ref is not None:
        from ultratight.fusion.gins.evaluation import evaluate
        evaluation, series = evaluate(res.t, llh_ant, res.sigma_pos_enu, ref, windows)
        if res.forward is not None:
            fwd = res.forward
            evaluation["forward"], _ = evaluate(fwd.t, antenna_llh(fwd, imu.lever_arm_b), fwd.sigma_pos_enu, ref,
                                                windows)
    written = _write_outputs(args, res, llh_ant)
    if args.plot:
        from ultratight.receiver.cli.integrate_plot import plot_errors
        plot_errors(args.plot, series, windows, f"ultratight integrate: {args.coupling}, {args.filter}"
                    + (", smoothed" if res.smoothed else ""))
        written.append(args.plot)
    summary = _summary(args, imu, noise, source, tight, res, windows, evaluation, written,
                       {"read_s": t_read, "filter_s": t_filter, "total_s": time.perf_counter() - t_start})
    if args.json:
        print(json_dumps(summary, indent=1), file=out)
    else:
        _print_human(summary, out)
    return 0


def _summary(args, imu, noise, source, tight, res, windows, evaluation, written, timing):
    from ultratight.signals.observations import week_tow
    upd = res.updates or {}
    used = np.asarray(upd.get("used", []), bool)
    rejected = np.asarray(upd.get("rejected", []), bool)
    return json_clean({
        "command": "integrate", "coupling": args.coupling, "filter": args.filter, "smoothed": bool(res.smoothed),
        "imu": {"file": str(args.imu), "samples": int(imu.n),
                "rate_hz": float(imu.n / max(float(imu.t[-1] - imu.t0), 1e-9)),
                "noise": noise.to_datasheet(), "lever_arm_flu_m": np.asarray(imu.lever_arm_b, float).tolist(),
                "mount_deg": list(args.mount) if args.mount else None},
        "gnss": {"file": str(args.gnss), "source": source, "epochs_used": int(used.sum()),
                 "epochs_rejected": int(rejected.sum()), "warnings": list(getattr(tight, "warnings", None) or []),
                 # tight: the signals and the ionosphere handling of the observation rows (fusion.gins.tight_meas)
                 "signals": (getattr(tight, "info", None) or {}).get("signals"),
                 "ionosphere": (getattr(tight, "info", None) or {}).get("ionosphere")},
        "gate_p": args.gate_p, "zupt": bool(args.zupt), "nhc": bool(args.nhc),
        "reference_geoid_m": args.reference_geoid,
        "start_tow_s": float(week_tow(res.t[0])[1]) if res.n else None,
        "end_tow_s": float(week_tow(res.t[-1])[1]) if res.n else None,
        "alignment": res.alignment, "outage_windows_tow_s": [[float(week_tow(a)[1]), float(b - a)] for a, b in windows],
        "evaluation": evaluation, "outputs": written, "timing_s": timing,
        "position_point": "antenna (IMU position + C_lb x lever arm)"})


def _print_human(s, out):
    print(f"integrate: {s['coupling']} coupling, filter {s['filter']}{', smoothed' if s['smoothed'] else ''}; "
          f"IMU {s['imu']['samples']} samples at {s['imu']['rate_hz']:.1f} Hz; GNSS {s['gnss']['source']}, "
          f"{s['gnss']['epochs_used']} used, {s['gnss']['epochs_rejected']} rejected", file=out)
    if s.get("start_tow_s") is not None:
        print(f"solution: GPS seconds of week {s['start_tow_s']:.2f} to {s['end_tow_s']:.2f}", file=out)
    ev = s.get("evaluation")
    if ev:
        for k, r in enumerate(ev["outages"], 1):
            if "max_h_m" in r:
                print(f"outage {k}: {r['start_tow_s']:.2f} +{r['length_s']:.2f} s: largest drift "
                      f"{r['max_h_m']:.2f} m horizontal, {r['max_v_m']:.2f} m vertical; "
                      f"{100 * r['within_3sigma']:.0f} % inside 3 sigma", file=out)
        if ev.get("outage_max_h_rms_m") is not None:
            print(f"RMS over outages of the largest drift: {ev['outage_max_h_rms_m']:.2f} m horizontal, "
                  f"{ev['outage_max_v_rms_m']:.2f} m vertical; inside 3 sigma {100 * ev['within_3sigma']:.0f} %",
                  file=out)
        if ev.get("rms_outside_h_m") is not None:
            print(f"RMS outside outages: {ev['rms_outside_h_m']:.3f} m horizontal "
                  f"({ev['reference_fixed_epochs']} fixed reference epochs)", file=out)
    for p in s["outputs"]:
        print(f"wrote {p}", file=out)
    print(f"time: {s['timing_s']['total_s']:.2f} s (reading {s['timing_s']['read_s']:.2f} s, filter "
          f"{s['timing_s']['filter_s']:.2f} s)", file=out)
