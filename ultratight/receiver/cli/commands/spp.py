"""``ultratight spp OBS [NAV]``: single-point positioning on recorded GPS L1 C/A observations.

OBS is a RINEX 2.x/3.x observation file (:mod:`ultratight.signals.rinex_obs`) or a u-blox UBX log
(:mod:`ultratight.signals.ubx`, RXM-RAWX); NAV a RINEX navigation file, optional with a UBX log (its
RXM-SFRBX subframes give the ephemerides: LNAV from L1 C/A, CNAV from L2C/L5 for the satellites without
a complete LNAV set; Klobuchar coefficients from subframe 4 page 18 or a CNAV type 30).  With a UBX log
holding GPS L2C (or L5) pseudoranges, ``--signals auto`` (default) positions on the L1 C/A + L2C
ionosphere-free combination; ``--signals l1`` on L1 C/A alone.  The per-epoch solution is :func:`ultratight.receiver.scalar.spp.run_spp`; ``--csv``
writes the fixes with the columns of ``ultratight process --csv``, ``--json`` prints the summary.
"""

import math
import sys

HELP = "single-point positions from recorded observations (RINEX obs or u-blox UBX) and broadcast ephemerides"

UBX_SYNC = b"\xb5\x62"


def add_arguments(p):
    p.add_argument("obs", metavar="OBS", help="RINEX observation file or u-blox .ubx log (RXM-RAWX)")
    p.add_argument("nav", metavar="NAV", nargs="?", default=None,
                   help="RINEX navigation file (optional with a .ubx log: its RXM-SFRBX subframes are decoded)")
    p.add_argument("--csv", metavar="OUT.csv", help="write the fixes as CSV (the columns of process --csv)")
    p.add_argument("--json", action="store_true", help="print one JSON summary object on stdout")
    p.add_argument("--mask", type=float, default=5.0, metavar="DEG", help="elevation mask (default 5 deg)")
    p.add_argument("--iono", choices=("klobuchar", "off"), default="klobuchar",
                   help="ionosphere: broadcast Klobuchar from the navigation header or subframe 4 page 18 "
                        "(default) or off")
    p.add_argument("--signals", choices=("auto", "l1"), default="auto",
                   help="u-blox log: auto = the ionosphere-free L1 C/A + L2C (or L5) combination when the log has "
                        "a second frequency (default); l1 = L1 C/A only (RINEX observations: always L1 C/A)")
    p.add_argument("--tropo", choices=("saastamoinen", "off"), default="saastamoinen",
                   help="troposphere: Saastamoinen with a standard atmosphere (default) or off")
    p.add_argument("--no-raim", action="store_true", help="no RAIM exclusion of a faulty satellite")
    p.add_argument("--code", choices=("C1", "P1"), default="C1",
                   help="RINEX pseudorange: C1 (C/A code, RINEX 3 C1C; default) or P1 (RINEX 3 C1W)")
    p.add_argument("--reference", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="reference ECEF position (m): the summary gives the errors' RMS against it")
    p.add_argument("--reference-header", action="store_true",
                   help="use the RINEX header's APPROX POSITION XYZ as the reference")


def obs_kind(path):
    """"ubx" or "rinex" from the file's first bytes; InputFileError when it is neither."""
    from ultratight.errors import InputFileError
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read observation file: {exc.strerror or exc}") from None
    first = head.split(b"\n", 1)[0]
    if b"RINEX VERSION" in first[60:]:
        return "rinex"
    if UBX_SYNC in head:
        return "ubx"
    raise InputFileError(f"{path}: neither a RINEX observation file (no 'RINEX VERSION / TYPE' first line) nor "
                         "a u-blox UBX log (no UBX sync characters)")


def _check_args(args):
    from ultratight import io_guard
    from ultratight.errors import ConfigError
    if not (math.isfinite(args.mask) and 0.0 <= args.mask < 90.0):
        raise ConfigError(f"--mask must be an elevation in [0, 90) deg, got {args.mask:g}")
    if args.reference is not None:
        if not all(math.isfinite(v) for v in args.reference):
            raise ConfigError("--reference must be three finite numbers (ECEF X Y Z, m)")
        if not 6.0e6 <= math.sqrt(sum(v * v for v in args.reference)) <= 1.0e7:
            raise ConfigError("--reference: an ECEF position (m) near the Earth's surface is expected, got "
                              f"{' '.join(f'{v:g}' for v in args.reference)}")
        if args.reference_header:
            raise ConfigError("give either --reference X Y Z or --reference-header, not both")
    io_guard.check_input_file(args.obs, "OBS file")
    if args.nav is not None:
        io_guard.check_input_file(args.nav, "NAV file")
    io_guard.check_io([("OBS", args.obs), ("NAV", args.nav)], [("--csv", args.csv)])


def _load(args):
    """(format, RawEpochs, NavData)."""
    from ultratight.errors import ConfigError, InputFileError
    from ultratight.signals.rinex import read_rinex_nav
    kind = obs_kind(args.obs)
    if kind == "ubx" and args.code != "C1":
        raise ConfigError("--code applies to RINEX observations (a UBX log gives the C/A code)")
    if kind == "ubx":
        from ultratight.signals.ubx import read_ubx
        log = read_ubx(args.obs, signals=args.signals)
        raw, nav = log.raw, log.nav
        if raw.n_epochs == 0:
            raise InputFileError(f"{args.obs}: the UBX log holds no RXM-RAWX epoch")
        if args.nav is not None:
            nav = read_rinex_nav(args.nav)
        elif not nav.ephemerides:
            raise InputFileError(f"{args.obs}: no complete GPS ephemeris in the log's RXM-SFRBX subframes; "
                                 "give a RINEX navigation file NAV")
    else:
        from ultratight.signals.rinex_obs import read_rinex_obs
        if args.nav is None:
            raise ConfigError("a RINEX observation file needs a navigation file: ultratight spp OBS NAV")
        raw = read_rinex_obs(args.obs, code=args.code)
        nav = read_rinex_nav(args.nav)
        if raw.n_epochs == 0:
            raise InputFileError(f"{args.obs}: the file holds no observation epoch")
    return kind, raw, nav


def _reference(args, raw):
    from ultratight.errors import ConfigError
    if args.reference is not None:
        return list(args.reference), "--reference"
    if args.reference_header:
        xyz = raw.meta.get("approx_position_xyz")
        if not xyz or sum(v * v for v in xyz) < 1.0:
            raise ConfigError(f"--reference-header: {args.obs} has no APPROX POSITION XYZ in its header")
        return list(xyz), "header"
    return None, None


def _no_overlap(args, raw, nav):
    from ultratight.errors import InputFileError
    from ultratight.signals.observations import week_tow
    spans = [(e.week, e.toe) for lst in nav.ephemerides.values() for e in lst]
    w0, t0 = week_tow(raw.t[0])
    w1, t1 = week_tow(raw.t[-1])
    nav_txt = (f"ephemerides with toe from week {min(spans)[0]} {min(spans)[1]:.0f} s to week {max(spans)[0]} "
               f"{max(spans)[1]:.0f} s" if spans else "no GPS ephemeris")
    return InputFileError(f"no overlap of observations and navigation data: {args.obs} spans week {w0} "
                          f"{t0:.0f} s to week {w1} {t1:.0f} s, {args.nav or 'the RXM-SFRBX subframes'} hold "
                          f"{nav_txt} (none healthy and within its fit interval at any epoch)")


def run(args):
    from ultratight.io_guard import json_clean, json_dumps
    from ultratight.receiver.scalar.spp import SppConfig, run_spp, summary

    _check_args(args)
    kind, raw, nav = _load(args)
    ref, ref_src = _reference(args, raw)
    res = run_spp(raw, nav, SppConfig(mask_deg=args.mask, iono=args.iono, tropo=args.tropo,
                                      raim=not args.no_raim))
    if res.n_epochs_with_states == 0:
        raise _no_overlap(args, raw, nav)
    if args.csv:
        _write_csv(args, res)
    summ = summary(res, ref, ref_src)
    summ = {"obs": str(args.obs), "obs_format": kind, "nav": str(args.nav) if args.nav else "RXM-SFRBX",
            "satellites_with_ephemeris": sorted(int(p) for p in nav.ephemerides), **summ, "csv": args.csv}
    for w in summ["warnings"]:
        print(f"ultratight spp: warning: {w}", file=sys.stderr)
    if args.json:
        print(json_dumps(json_clean(summ)))
    else:
        _print_human(summ)
    return 0


def _write_csv(args, res):
    from ultratight.errors import UltratightError
    from ultratight.io_guard import output_error
    from ultratight.receiver.io.outputs import write_csv
    rows = []
    for f in res.fixes:
        r = dict(f)
        r["pos_e"] = [float(v) for v in f["pos_e"]]
        r["vel_e"] = [float(v) for v in f["vel_e"]]
        rows.append(r)
    try:
        write_csv(args.csv, rows)
    except UltratightError:
        raise
    except OSError as exc:
        raise output_error(args.csv, exc) from None


def _print_human(s):
    print(f"observations: {s['obs']} ({s['obs_format']}), navigation: {s['nav']}")
    print(f"epochs: {s['epochs']}, with ephemerides: {s['epochs_with_ephemeris']}, fixes: {s['fixes']}")
    c = s.get("corrections") or {}
    if c.get("signals"):
        print(f"signals: {c['signals']}; ionosphere: {c.get('ionosphere')}")
    if s["mean_position_llh"]:
        lat, lon, h = s["mean_position_llh"]
        x, y, z = s["mean_position_ecef_m"]
        print(f"mean position: {lat:.8f} deg, {lon:.8f} deg, {h:.3f} m (ECEF {x:.3f} {y:.3f} {z:.3f} m)")
        d = s["dop"]
        print(f"mean DOP: GDOP {d['gdop']:.2f}, PDOP {d['pdop']:.2f}, HDOP {d['hdop']:.2f}, VDOP {d['vdop']:.2f}; "
              f"satellites used {s['mean_satellites_used']:.1f}")
    r = s.get("reference")
    if r:
        e, n, u = r["rms_enu_m"]
        print(f"against the reference ({r['source']}): RMS 3D {r['rms_3d_m']:.3f} m, horizontal "
              f"{r['rms_horizontal_m']:.3f} m (E {e:.3f}, N {n:.3f}, U {u:.3f} m)")
    if s["csv"]:
        print(f"wrote {s['csv']}")
