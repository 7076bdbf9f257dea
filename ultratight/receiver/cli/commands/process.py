"""``ultratight process``: run the receiver on an IF file.

``--mode scalar`` (default): the scalar receiver (acquisition -> tracking -> LNAV -> PVT).
``--mode ultratight --imu IMU.h5 [--method M]``: the ultra-tight GPS/INS engine
(:func:`ultratight.receiver.deep.recordings.run_ultratight_on_files`) on the IF file and a recorded IMU
file (HDF5 or CSV) whose time axis starts at the first IF sample; it starts from the scalar
receiver's first fixes on the same file, the ``--init-*`` flags or (generated files) the
perturbed truth (``--startup``, :mod:`ultratight.receiver.deep.handover`), and writes the SINS-rate
solution as CSV / KML / NMEA and RINEX observations of its channels
(:mod:`ultratight.receiver.deep.outputs`).
"""

import math
import sys

from ultratight.io_guard import json_clean, json_dumps, note_partial

HELP = ("run the GPS receiver on an IF file: scalar (acquisition, tracking, LNAV, PVT) or, with --mode ultratight "
        "--imu, the ultra-tight GPS/INS engine")

MODES = ("scalar", "ultratight")
DYNAMICS = ("normal", "high")
# acquisition defaults per --dynamics: (--acq-min-cn0 dB-Hz, --acq-coherent ms, --acq-noncoherent)
ACQ_DEFAULTS = {"normal": (37.0, 10, 1), "high": (25.0, 5, 16)}


def _acq_defaults(args):
    """Fill the acquisition flags left out with the defaults of ``--dynamics``."""
    cn0, coh, nc = ACQ_DEFAULTS[getattr(args, "dynamics", "normal") or "normal"]
    if args.acq_min_cn0 is None:
        args.acq_min_cn0 = cn0
    if args.acq_coherent is None:
        args.acq_coherent = coh
    if args.acq_noncoherent is None:
        args.acq_noncoherent = nc


class _EngineMethods:
    """The ultra-tight methods of the registry (:mod:`ultratight.receiver.deep.methods`; the ones that
    use IMU data -- ``scalar`` is this command's scalar mode) as argparse ``choices``, imported only
    when argparse needs them (a given --method, --help), so that building the CLI parser stays cheap."""

    def _methods(self):
        from ultratight.receiver.deep.methods import REGISTRY
        return [m for m, spec in REGISTRY.items() if spec.needs_imu]

    def __iter__(self):
        return iter(self._methods())

    def __contains__(self, item):
        return item in self._methods()


def _prn_list(text):
    """``1,3,7-12`` -> [1, 3, 7, ..., 12]; ConfigError for anything but decimal PRNs 1..32."""
    from ultratight.errors import ConfigError

    def num(tok):
        tok = tok.strip()
        if not tok.isdigit() or not tok.isascii():
            raise ConfigError(f"--prn: {tok!r} is not a PRN number (expected e.g. 1,3,7-12 with PRNs 1..32)")
        v = int(tok)
        if not 1 <= v <= 32:
            raise ConfigError(f"--prn: PRN must be in 1..32, got {v}")
        return v

    out = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-", 1)
            lo, hi = num(a), num(b)
            if lo > hi:
                raise ConfigError(f"--prn: range {part!r} is empty (first PRN > last)")
            out.extend(range(lo, hi + 1))
        else:
            out.append(num(part))
    if not out:
        raise ConfigError(f"--prn: no PRN given in {text!r}")
    if len(set(out)) != len(out):
        raise ConfigError(f"--prn: PRN listed twice in {text!r}")
    return out


def _check_numbers(args):
    """Finite, in-range numeric flags (before any file is opened)."""
    from ultratight.errors import ConfigError
    _acq_defaults(args)
    for flag, v in (("--fs", args.fs), ("--if", args.if_hz), ("--start", args.start),
                    ("--duration", args.duration), ("--obs-rate", args.obs_rate), ("--pll-bw", args.pll_bw),
                    ("--acq-min-cn0", args.acq_min_cn0), ("--doppler-range", args.doppler_range),
                    ("--mask", args.mask)):
        if v is not None and not math.isfinite(v):
            raise ConfigError(f"{flag} must be a finite number, got {v}")
    if args.start is not None and args.start < 0:
        raise ConfigError(f"--start must be >= 0 s, got {args.start}")
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration must be > 0 s, got {args.duration}")
    if args.fs is not None and not args.fs > 0:
        raise ConfigError(f"--fs must be a positive sampling rate in Hz, got {args.fs}")
    if args.pll_bw is not None and not args.pll_bw > 0:
        raise ConfigError(f"--pll-bw must be > 0 Hz, got {args.pll_bw}")
    if getattr(args, "threads", None) is not None and args.threads < 1:
        raise ConfigError(f"--threads must be an integer >= 1, got {args.threads}")
    if not args.doppler_range > 0:
        raise ConfigError(f"--doppler-range must be > 0 Hz, got {args.doppler_range}")
    if not 0.0 <= args.mask < 90.0:
        raise ConfigError(f"--mask must be an elevation in [0, 90) deg, got {args.mask:g}")
    if not 1 <= args.acq_coherent <= 10:
        raise ConfigError(f"--acq-coherent must be in 1..10 ms, got {args.acq_coherent}")
    if not 1 <= args.acq_noncoherent <= 1000:
        raise ConfigError(f"--acq-noncoherent must be in 1..1000, got {args.acq_noncoherent}")


# every output flag of this command (flag, argparse dest): checked before any work
OUTPUT_FLAGS = (("--out", "out"), ("--csv", "csv"), ("--kml", "kml"), ("--rinex-obs", "rinex_obs"),
                ("--rinex-nav", "rinex_nav"), ("--nmea", "nmea"))


def _check_file_flags(args):
    """``--fs/--if/--format`` against the file's JSON sidecar (or a ``--meta`` JSON file): without one,
    ``--fs`` and ``--format`` go together; beside one, a flag may only repeat the value it states
    (a different value is a conflict between two descriptions of the same recording)."""
    from ultratight.errors import ConfigError
    from ultratight.signals.recording.iffile import read_sidecar, sidecar_path
    from ultratight.signals.recording.metadata_check import load_json_metadata
    if args.meta is None:
        side, name = read_sidecar(args.iffile), f"sidecar {sidecar_path(args.iffile).name}"
    elif str(args.meta).lower().endswith(".json"):
        side, name = load_json_metadata(args.meta), f"--meta file {args.meta}"
    else:
        side, name = None, None
    if side is None and args.meta is None and (args.fs is None) != (args.fmt is None):
        raise ConfigError("give both --fs and --format (and --if, default 0) when the file has no sidecar")
    side = side or {}
    num = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
    for flag, given, key in (("--fs", args.fs, "fs_hz"), ("--if", args.if_hz, "if_hz"),
                             ("--format", args.fmt, "format")):
        stated = side.get(key)
        if given is None or stated is None:
            continue
        if key == "format":
            if str(given) != str(stated):
                raise ConfigError(f"--format {given} conflicts with the {name}, which states format = {stated}: "
                                  f"drop --format or correct the {name.split()[0]}")
        elif num(stated) and not math.isclose(float(given), float(stated), rel_tol=1e-12, abs_tol=1e-6):
            raise ConfigError(f"{flag} {given:g} Hz conflicts with the {name}, which states {key} = {stated:g} Hz: "
                              f"drop {flag} or correct the {name.split()[0]}")
    fs, where = (args.fs, "--fs") if args.fs is not None else (side.get("fs_hz"), f"fs_hz of the {name}")
    if args.if_hz is not None and num(fs) and abs(args.if_hz) >= fs:
        raise ConfigError(f"--if {args.if_hz:g} Hz must be smaller in magnitude than the sampling rate "
                          f"({where}: {fs:g} Hz)")


def _check_paths(args):
    """Inputs readable, outputs writable and distinct from every input (io_guard.check_io)."""
    from ultratight import io_guard
    from ultratight.ins import imu_decl
    from ultratight.signals.recording.iffile import sidecar_path
    io_guard.check_input_file(args.iffile, "IF file")
    inputs = [("IFFILE", args.iffile), ("sidecar", str(sidecar_path(args.iffile)))]
    for flag, p in (("--meta", args.meta), ("--imu", getattr(args, "imu", None)), ("--ephemeris", args.ephemeris)):
        if p is not None:
            io_guard.check_input_file(p, f"{flag} file")
            inputs.append((flag, p))
    companions = [("sidecar", str(sidecar_path(args.iffile)))]
    if getattr(args, "imu", None) is not None:
        inputs.append(("IMU sidecar", str(imu_decl.sidecar_path(args.imu))))
        companions.append(("IMU sidecar", str(imu_decl.sidecar_path(args.imu))))
    bits = getattr(args, "bits", None)
    if bits:
        from ultratight.receiver.deep.bitsources import STRATEGIES
        if bits not in STRATEGIES:
            inputs.append(("--bits", bits))
    io_guard.check_io(inputs, [(flag, getattr(args, dest, None)) for flag, dest in OUTPUT_FLAGS],
                      companions=companions)


def add_arguments(p):
    p.add_argument("iffile", metavar="IFFILE", help="IF sample file")
    p.add_argument("--mode", choices=MODES, default="scalar",
                   help="scalar receiver (default) or ultratight GPS/INS engine (needs --imu)")
    p.add_argument("--imu", metavar="IMU", help="IMU file (HDF5 or .csv) for --mode ultratight")
    p.add_argument("--bits", metavar="STRATEGY", default=None,
                   help="--mode ultratight: navigation-data bits: decoded (default; parity-checked LNAV words "
                        "decoded from a blind pass over the same file, blind elsewhere), decoded-scalar (words from a "
                        "scalar-receiver pass), blind (per-bit decisions), a bit file (CSV, docs/process.md) or "
                        "assisted (re-encoded from the ephemeris: the project's own generated LNAV only; the summary "
                        "and every output then say the run was assisted)")
    p.add_argument("--method", choices=_EngineMethods(), default=None, metavar="METHOD",
                   help="ultra-tight method (--mode ultratight): %(choices)s (default: the engine's DEFAULT_METHOD, "
                        "dlb-rackf)")
    p.add_argument("--meta", metavar="SIDECAR", help="JSON sidecar, ION GNSS SDR metadata XML or SigMF .sigmf-meta "
                                                      "(default: IFFILE.json when present; an IFFILE ending in "
                                                      ".sigmf-meta/.sigmf-data is read as SigMF)")
    _add_file_arguments(p)
    _add_receiver_arguments(p)
    _add_output_arguments(p)
    _add_startup_arguments(p)
    p.add_argument("--json", action="store_true", help="print one JSON summary object on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from ultratight.receiver.cli.commands import imu_flags
    imu_flags.add_arguments(p)
    imu_flags.add_noise_arguments(p)


def _add_file_arguments(p):
    """The IF file's parameters when no sidecar gives them."""
    p.add_argument("--fs", type=float, metavar="HZ", help="sampling rate (Hz)")
    p.add_argument("--if", dest="if_hz", type=float, metavar="HZ", help="intermediate frequency (Hz), 0 = baseband")
    p.add_argument("--format", dest="fmt", metavar="FMT",
                   help="sample format: i8, i16, f32, ci8, ci16, cf32, i2packed, ci2packed, i4packed, ci4packed")
    p.add_argument("--packing", choices=("msb-first", "lsb-first"),
                   help="packed formats: the first sample in the high or the low bits of a word (default msb-first)")
    p.add_argument("--encoding", choices=("sign-magnitude", "twos-complement", "offset-binary", "sign"),
                   help="packed formats: sample encoding (default sign-magnitude)")
    p.add_argument("--word-size", type=int, choices=(1, 2, 4, 8), metavar="BYTES",
                   help="packed formats: word size in bytes, 1, 2, 4 or 8 (default 1)")
    p.add_argument("--endian", choices=("little", "big"), help="packed formats: byte order of a word (default little)")
    p.add_argument("--iq-conj", action="store_true", help="read complex samples as I - jQ (inverted spectrum)")


def _add_receiver_arguments(p):
    """Ephemerides, satellites, channels and threads, time span, tracking, acquisition, PVT."""
    p.add_argument("--ephemeris", metavar="RINEX", help="RINEX navigation file (default: decode from the signal)")
    p.add_argument("--prn", metavar="LIST", help="PRNs to search, e.g. 1,3,7-12 (default: all 32)")
    p.add_argument("--channels", type=int, default=None, metavar="N",
                   help="tracking channels (default: all in view - every satellite acquired is tracked; the "
                        "others are searched again every 15 s around their predicted Doppler once ephemerides and "
                        "a fix are known, every 30 s in full before; with N, the N strongest, no periodic search)")
    p.add_argument("--threads", type=int, default=None, metavar="K",
                   help="threads of the channel stages and the acquisition (default: one per core this process "
                        "may use, at most one per channel; 1: everything on one thread)")
    p.add_argument("--duration", type=float, metavar="S", help="process only the first S seconds")
    p.add_argument("--start", type=float, default=0.0, metavar="S", help="skip the first S seconds")
    p.add_argument("--obs-rate", type=float, default=10.0, metavar="HZ",
                   help="observables / PVT rate, 0.1-50 Hz (default 10)")
    p.add_argument("--coh-ms", type=int, default=1, metavar="MS",
                   help="coherent integration after bit sync: 1, 2, 4, 5, 10 or 20 ms (default 1)")
    p.add_argument("--pll-bw", type=float, default=None, metavar="HZ", help="PLL noise bandwidth in track mode")
    p.add_argument("--dynamics", choices=DYNAMICS, default="normal",
                   help="receiver dynamics: normal (default) or high - a Doppler-rate search after every "
                        "acquisition starts the third-order PLL with the rate, the high-dynamic loop profile "
                        "(tracking_config.DYNAMICS_PROFILES) and weak-signal acquisition defaults (5 ms x 16, floor "
                        "25 dB-Hz); for starts under acceleration at low C/N0 (docs/process.md)")
    p.add_argument("--acq-min-cn0", type=float, default=None, metavar="DBHZ",
                   help="declare an acquisition only when its peak C/N0, 10 log10((metric-1)/T_coh), reaches "
                        "this (default 37 dB-Hz, 25 with --dynamics high; 0 keeps every detection passing the "
                        "false-alarm test)")
    p.add_argument("--acq-coherent", type=int, default=None, metavar="MS",
                   help="acquisition coherent integration, 1-10 ms (default 10, 5 with --dynamics high; cut to "
                        "the file length)")
    p.add_argument("--acq-noncoherent", type=int, default=None, metavar="K",
                   help="acquisition non-coherent sums (default 1, 16 with --dynamics high; raise for weak "
                        "signals)")
    p.add_argument("--doppler-range", type=float, default=10e3, metavar="HZ",
                   help="acquisition Doppler search half-width (default 10 kHz)")
    p.add_argument("--mask", type=float, default=5.0, metavar="DEG", help="elevation mask (default 5 deg)")
    p.add_argument("--iono", choices=("klobuchar", "off"), default=None,
                   help="ionospheric correction: broadcast Klobuchar model (default; applied once alpha/beta "
                        "are known from subframe 4 page 18 or the --ephemeris RINEX header; --mode ultratight: "
                        "from the RINEX header or a generated file's sidecar) or off")
    p.add_argument("--tropo", choices=("saastamoinen", "off"), default=None,
                   help="tropospheric correction: Saastamoinen with a standard atmosphere (default) or off "
                        "(--mode ultratight: in the engine's predictions and its scalar start-up)")


def _add_output_arguments(p):
    """Output files."""
    p.add_argument("--out", metavar="OUT.h5", help="HDF5 output (schema in docs/process.md)")
    p.add_argument("--csv", metavar="OUT.csv", help="also write the fixes as CSV")
    p.add_argument("--rinex-obs", metavar="OUT.obs", help="also write RINEX 3.04 observations (C1C L1C D1C S1C)")
    p.add_argument("--rinex-nav", metavar="OUT.nav", help="also write the ephemerides used as RINEX 3.04 navigation")
    p.add_argument("--nmea", metavar="OUT.nmea", help="also write NMEA 0183 GGA/RMC/GSA/GSV per fix")
    p.add_argument("--kml", metavar="OUT.kml", help="also write the track as KML")


def _add_startup_arguments(p):
    """The ultra-tight mode's start-up."""
    p.add_argument("--startup", choices=("auto", "scalar-fix", "truth-perturbed"), default="auto",
                   help="--mode ultratight: initial state from the scalar receiver's first fixes on the same file "
                        "(scalar-fix), or auto (default: --init-* flags when all three are given, else scalar-fix); "
                        "truth-perturbed (assisted, generated files only: the IMU file's truth perturbed, the "
                        "sidecar's PRN list; the summary and every output say so); --start S starts the scalar pass "
                        "at S. The --init-* flags take three numbers: --init-llh -33.87 151.21 40 (or "
                        "-33.87,151.21,40)")
    # three numbers, as `ultratight ins` takes them (LAT LON H) or comma-separated (LAT,LON,H)
    p.add_argument("--init-llh", nargs="+", metavar="LAT LON H",
                   help="--mode ultratight: initial position (deg, deg, m)")
    p.add_argument("--init-vel", nargs="+", metavar="VE VN VU", help="--mode ultratight: initial ENU velocity (m/s)")
    p.add_argument("--init-att", nargs="+", metavar="ROLL PITCH YAW",
                   help="--mode ultratight: initial attitude (deg; yaw from north, FLU body)")


def run(args):
    from ultratight.errors import ConfigError

    _check_numbers(args)
    _check_paths(args)
    if getattr(args, "mode", "scalar") == "ultratight":
        return _run_ultratight(args)
    if getattr(args, "imu", None):
        raise ConfigError("--imu is only used with --mode ultratight")
    from ultratight.receiver.cli.commands import imu_flags
    if imu_flags.overrides(args) or imu_flags.noise_flags(args) or getattr(args, "imu_grade", None):
        raise ConfigError("the --imu-*/--lever-arm flags declare the IMU file of --mode ultratight")
    ut_only = [f for f, on in (("--init-llh", getattr(args, "init_llh", None)),
                               ("--init-vel", getattr(args, "init_vel", None)),
                               ("--init-att", getattr(args, "init_att", None)),
                               ("--startup", getattr(args, "startup", "auto") != "auto")) if on]
    if ut_only:
        raise ConfigError(f"{', '.join(ut_only)} only used with --mode ultratight")
    if getattr(args, "bits", None):
        raise ConfigError("--bits is only used with --mode ultratight")
    args.iono = args.iono or "klobuchar"           # defaults of the scalar receiver (recorded resolved)
    args.tropo = args.tropo or "saastamoinen"
    from ultratight.signals.recording.iffile import open_if
    from ultratight.receiver.dsp.tracking_config import TrackingConfig
    from ultratight.receiver.scalar.process_config import NoSignalError, ProcessConfig
    from ultratight.receiver.scalar.receiver import process

    _check_file_flags(args)
    packing = {k: v for k, v in (("order", args.packing), ("encoding", args.encoding),
                                 ("word_bytes", args.word_size), ("endian", args.endian)) if v is not None}
    source = open_if(args.iffile, meta=args.meta, fs_hz=args.fs, if_hz=args.if_hz, fmt=args.fmt, packing=packing,
                     iq_conj=args.iq_conj)
    if source.n_samples == 0:
        from ultratight.errors import InputFileError
        raise InputFileError(f"{args.iffile}: the file holds no samples")
    if not source.is_complex and source.if_hz == 0.0:
        raise ConfigError(f"{args.iffile}: real samples need a non-zero --if (the IF of the front end)")
    tcfg = TrackingConfig.for_dynamics(args.dynamics, coh_ms=args.coh_ms)
    if args.pll_bw is not None:
        tcfg.track_pll_bw_hz = args.pll_bw
    cfg = ProcessConfig(n_channels=args.channels, prns=_prn_list(args.prn) if args.prn else None,
                        duration_s=args.duration, start_s=args.start, obs_rate_hz=args.obs_rate,
                        mask_deg=args.mask, acq_min_cn0_dbhz=args.acq_min_cn0,
                        acq_coherent_ms=args.acq_coherent, acq_noncoherent=args.acq_noncoherent,
                        doppler_range_hz=args.doppler_range, tracking=tcfg, iono=args.iono, tropo=args.tropo,
                        dynamics=args.dynamics, threads=args.threads)
    eph = None
    if args.ephemeris:
        from ultratight.signals.rinex import read_rinex_nav
        eph = read_rinex_nav(args.ephemeris)
    progress = not args.no_progress and not args.json and sys.stderr.isatty()
    run_config = {k: v for k, v in vars(args).items() if not k.startswith("_")}
    if args.out:
        note_partial(args.out)          # reported by the CLI only if the file exists
    try:
        res = process(source, cfg, ephemerides=eph, out_path=args.out, csv_path=args.csv, kml_path=args.kml,
                      progress=progress, run_config=run_config, rinex_obs_path=args.rinex_obs,
                      rinex_nav_path=args.rinex_nav, nmea_path=args.nmea)
    except OSError as exc:
        _raise_output_error(exc, args)
    except NoSignalError as exc:
        if args.json:
            print(json_dumps({"acquired": [], "tracked": [], "fixes": 0, "first_fix_s": None,
                              "position_ecef_m": None, "position_llh": None, "error": str(exc)}))
        raise
    summ = json_clean(res.summary())
    for w in list(getattr(source, "warnings", [])) + list(res.warnings):
        print(f"ultratight process: warning: {w}", file=sys.stderr)
    if args.json:
        print(json_dumps(summ))
    else:
        _print_human(summ)
    return 0


def _raise_output_error(exc, args):
    """An OSError while writing: one line naming the outputs and the cause (full disk, ...)."""
    from ultratight.errors import UltratightError
    from ultratight.io_guard import output_error
    if isinstance(exc, UltratightError):
        raise exc
    outs = [getattr(args, dest) for _, dest in OUTPUT_FLAGS if getattr(args, dest, None)]
    raise output_error(", ".join(outs) or "output", exc) from None


def _run_ultratight(args):
    """``--mode ultratight``: the engine on IFFILE + IMU; summary on stdout, result HDF5 with --out."""
    from ultratight.errors import ConfigError
    from ultratight.receiver.deep.bitsources import check_strategy
    from ultratight.receiver.deep.methods import DEFAULT_METHOD
    from ultratight.receiver.deep.options import EngineOptions
    from ultratight.receiver.deep.recordings import run_ultratight_on_files
    from ultratight.receiver.deep.outputs import write_result_h5

    if not args.imu:
        raise ConfigError("--mode ultratight needs --imu IMU.h5")
    from ultratight.receiver.deep.handover import HandoverConfig, parse_init_flags

    overrides = parse_init_flags(args.init_llh, args.init_vel, args.init_att)
    ignored = [flag for flag, on in (("--fs", args.fs is not None), ("--if", args.if_hz is not None),
                                     ("--format", args.fmt is not None), ("--iq-conj", args.iq_conj),
                                     ("--rinex-nav", args.rinex_nav), ("--packing", args.packing),
                                     ("--encoding", args.encoding), ("--word-size", args.word_size),
                                     ("--endian", args.endian))
               if on]
    if ignored:
        raise ConfigError(f"{', '.join(ignored)} not supported with --mode ultratight (the IF parameters come "
                          "from the sidecar / --meta)")
    args.iono = args.iono or "klobuchar"           # the scalar receiver's defaults (recorded resolved)
    tropo_check = args.tropo is None               # not asked for: the start-up tests the recording for one
    args.tropo = args.tropo or "saastamoinen"
    prns = _prn_list(args.prn) if args.prn else None
    hcfg = HandoverConfig(acq_min_cn0_dbhz=args.acq_min_cn0, acq_noncoherent=args.acq_noncoherent,
                          acq_coherent_ms=args.acq_coherent, doppler_range_hz=args.doppler_range,
                          dynamics=args.dynamics, tropo_check=tropo_check)
    from ultratight.receiver.cli.commands import imu_flags
    imu_decl = imu_flags.overrides(args)
    noise = {**({"grade": args.imu_grade} if args.imu_grade else {}), **imu_flags.noise_flags(args)}
    bits = args.bits or "decoded"
    check_strategy(bits)
    if args.out:
        note_partial(args.out)
    from ultratight.receiver.cli.first_run import compiling_ahead
    with compiling_ahead():             # a first run: the engine's epoch chain compiled beside it
        res = run_ultratight_on_files(args.iffile, args.imu, method=args.method or DEFAULT_METHOD, meta=args.meta,
                                      nav_path=args.ephemeris, prns=prns, duration_s=args.duration,
                                      startup=args.startup, init_overrides=overrides, start_s=args.start,
                                      handover=hcfg, imu_declaration=imu_decl,
                                      options=EngineOptions(bits=bits, threads=args.threads or 0),
                                      iono=args.iono, tropo=args.tropo, imu_noise=noise or None)
    from ultratight.receiver.deep import outputs as ut_outputs
    try:
        if args.out:
            write_result_h5(args.out, res, extra_attrs={"assisted": "; ".join(res.info.get("assisted") or [])
                                                        or "no"})
        ut_outputs.write_files(res, csv_path=args.csv, kml_path=args.kml, nmea_path=args.nmea,
                               rinex_obs_path=args.rinex_obs)
    except OSError as exc:
        _raise_output_error(exc, args)
    summ = _ultratight_summary(res, args)
    for w in summ["warnings"]:
        print(f"ultratight process: warning: {w}", file=sys.stderr)
    if args.json:
        print(json_dumps(summ))
    else:
        _print_ultratight_summary(summ, args)
    integ = summ.get("integrity")
    if integ and integ["state"] == "lost":
        # the run finished, its solution did not: status 3 (docs/reliability.md)
        print(f"ultratight process: {integ['line']}", file=sys.stderr)
        return 3
    return 0


def _ultratight_summary(res, args):
    """The ``--mode ultratight`` run summary (the ``--json`` object)."""
    import numpy as np

    from ultratight.receiver.deep import outputs as ut_outputs
    info = res.info or {}
    mode = np.asarray(res.mode)
    return {
        "mode": "ultratight",
        "method": res.method,
        "prns": [int(p) for p in res.prns],
        "duration_s": float(res.duration_s),
        "runtime_s": float(res.runtime_s),
        # wall-clock seconds per signal second, as in the scalar summary (< 1: faster than real time)
        "realtime_factor": float(res.runtime_s / res.duration_s) if res.duration_s > 0 else None,
        "n_epochs": int(info.get("n_epochs", mode.shape[0])),
        "n_tight_updates": info.get("n_tight_updates"),
        "lock_losses": info.get("n_lock_lost_events"),
        "prefilter_restarts": info.get("n_prefilter_restarts"),
        "lock_lost_channels": ut_outputs.lock_lost_channels(res),
        "bits": ut_outputs.bit_strategy(res),
        "startup": info.get("handover", {}).get("source"),
        "handover": info.get("handover"),
        "nav": ut_outputs.nav_summary(res),
        "bit_strategy": (info.get("bits") or {}).get("strategy"),
        "blind_fraction": _blind_fraction(res),
        "atmosphere": info.get("atmosphere"),
        "integrity": ut_outputs.integrity_summary(res),
        # the parts of the run the generator's knowledge assisted (empty on a user's files; docs/process.md)
        "assisted": list(info.get("assisted") or []),
        "warnings": list(info.get("warnings") or []),
        "out": args.out,
        "files": {k: v for k, v in (("csv", args.csv), ("kml", args.kml), ("nmea", args.nmea),
                                    ("rinex_obs", args.rinex_obs)) if v},
    }


def _print_ultratight_summary(summ, args):
    """The ``--mode ultratight`` summary as text lines on stdout."""
    if summ["assisted"]:
        print(f"ASSISTED run: {'; '.join(summ['assisted'])}")
    print(f"ultratight {summ['method']}: PRN {', '.join(str(p) for p in summ['prns'])}")
    rtf = summ["realtime_factor"]
    print(f"signal {summ['duration_s']:.2f} s in {summ['runtime_s']:.2f} s "
          f"(real-time factor {rtf:.3g})" if rtf is not None else
          f"signal {summ['duration_s']:.2f} s")
    print(f"tight updates: {summ['n_tight_updates']}, lock losses: {summ['lock_losses']}, "
          f"prefilter restarts: {summ['prefilter_restarts']}")
    ho = summ["handover"] or {}
    print(f"start-up: {summ['startup']} at t = {ho.get('handover_t_s', 0.0):.2f} s; channels lost: "
          f"{summ['lock_lost_channels'] or 'none'}")
    print(f"data bits: {summ['bit_strategy']}; blind fraction per channel: {summ['blind_fraction']}")
    if summ.get("integrity"):
        print(summ["integrity"]["line"])
    if args.out:
        print(f"output: {args.out}")


def _blind_fraction(res):
    """Per channel, the fraction of epochs whose data bit was a blind decision."""
    import numpy as np

    from ultratight.receiver.dsp.wipeoff import BIT_BLIND
    b = getattr(res, "bit_source", None)
    if b is None or len(b) == 0:
        return None
    return [round(float(v), 4) for v in np.mean(np.asarray(b) == BIT_BLIND, axis=0)]


def _print_human(s):
    inp = s["input"]
    print(f"input: {inp['path']} ({inp['format']}, fs {inp['fs_hz']:g} Hz, IF {inp['if_hz']:g} Hz)")
    print("acquired: " + ", ".join(f"PRN {a['prn']} ({a['doppler_hz']:+.0f} Hz, {a['cn0_dbhz']:.1f} dB-Hz)"
                                   for a in s["acquired"]))
    print(f"tracked: {s['tracked']}")
    for c in s["channels"]:
        if not c.get("started", True):
            continue
        print(f"  PRN {c['prn']:2d}: locked {100 * c['locked_fraction']:.0f}%, C/N0 {c['cn0_dbhz']} dB-Hz, "
              f"TOW at {c['tow_s']} s, ephemeris at {c['ephemeris_s']} s, losses {c['losses']}")
    print(f"fixes: {s['fixes']}, first fix at {s['first_fix_s']} s")
    if s["position_llh"]:
        lat, lon, h = s["position_llh"]
        print(f"median position: {lat:.7f} deg, {lon:.7f} deg, {h:.2f} m")
    print(f"signal {s['signal_s']:.2f} s in {s['wall_s']:.2f} s (real-time factor {s['realtime_factor']})")
    if s["out"]:
        print(f"output: {s['out']}")
