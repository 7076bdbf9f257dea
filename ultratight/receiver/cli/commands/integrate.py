"""``ultratight integrate``: INS/GNSS integration of recorded logs (docs/integrate.md).

An IMU log (the project's CSV/HDF5 with its declaration, an RTKLIB-tagged raw log, the ``_sf`` CSV,
the KF-GINS text layout) and a GNSS log — a solution for loose coupling (RTKLIB ``.pos``, NMEA, u-blox
NAV-PVT) or raw observations for tight coupling (RINEX 2/3 observations + navigation, u-blox
RXM-RAWX + RXM-SFRBX) — go through the error-state filter of :mod:`ultratight.fusion.gins` with one of
the seed filters as its core; ``--outage``/``--outages`` remove GNSS over windows and ``--reference``
evaluates the drift through them (:mod:`ultratight.fusion.gins.evaluation`).
"""

import sys

HELP = ("INS/GNSS integration of recorded IMU and GNSS logs (loose or tight), with simulated GNSS outages "
        "evaluated against a reference")

COUPLINGS = ("loose", "tight")
FILTERS = ("kf", "akf", "iakf", "chi2-newton", "afm-aukf")
IMU_FORMATS = ("auto", "csv", "h5", "rtklib-raw", "sf", "kf-gins")
GNSS_FORMATS = ("auto", "pos", "nmea", "ubx", "rinex")
OUTPUT_FLAGS = (("--out", "out"), ("--csv", "csv"), ("--kml", "kml"), ("--nmea", "nmea"), ("--plot", "plot"))
DEFAULT_RATE_HZ = 10.0
# flag -> datasheet key of ultratight.ins.imu_noise (optional keys: scale factor and cross-axis, 1 sigma)
SCALE_FLAGS = (("--imu-gyro-scale-factor", "gyro_scale_factor_pct",
                "gyro scale-factor error, %% (1 sigma; default: the grade's, docs/gins.md)"),
               ("--imu-gyro-cross-axis", "gyro_cross_axis_pct", "gyro cross-axis sensitivity, %% (1 sigma)"),
               ("--imu-accel-scale-factor", "accel_scale_factor_pct", "accelerometer scale-factor error, %% (1 sigma)"),
               ("--imu-accel-cross-axis", "accel_cross_axis_pct", "accelerometer cross-axis sensitivity, %% (1 sigma)"))


def add_arguments(p):
    g = p.add_argument_group("inputs")
    g.add_argument("--imu", required=True, metavar="IMU", help="IMU log (see --imu-format)")
    g.add_argument("--imu-format", choices=IMU_FORMATS, default="auto",
                   help="IMU log layout (default: recognised from the file)")
    g.add_argument("--imu-tag", default=None, metavar="TAG",
                   help="RTKLIB time-tag file of a raw log (default: IMU.tag when it exists)")
    g.add_argument("--gps-week", type=int, default=None, metavar="WEEK",
                   help="GPS week of logs stamped in seconds of week (KF-GINS layout)")
    g.add_argument("--gnss", required=True, metavar="GNSS", help="GNSS log (see --gnss-format)")
    g.add_argument("--gnss-format", choices=GNSS_FORMATS, default="auto",
                   help="pos (RTKLIB solution), nmea, ubx (u-blox: NAV-PVT loose, RXM-RAWX tight), rinex "
                        "(observations, tight) (default: recognised from the file)")
    g.add_argument("--nav", default=None, metavar="NAV",
                   help="RINEX navigation file (tight coupling on RINEX observations; optional with a .ubx)")
    g.add_argument("--signals", choices=("auto", "l1"), default="auto",
                   help="u-blox raw log, tight coupling: auto (GPS L1 C/A + L2C, else L5, ionosphere-free when "
                        "the log has them; satellites without the second pseudorange left out) or l1 (L1 C/A "
                        "as measured, every satellite) (default auto; docs/spp.md)")
    g.add_argument("--date", default=None, metavar="YYYY-MM-DD",
                   help="UTC date of an NMEA log without RMC sentences")
    g.add_argument("--leap-seconds", type=int, default=18, metavar="S",
                   help="GPS-UTC for NMEA input (default 18, the value since 2017-01-01)")
    f = p.add_argument_group("filter")
    f.add_argument("--coupling", choices=COUPLINGS, default="loose")
    f.add_argument("--filter", choices=FILTERS, default="kf", help="the filter core (default: kf)")
    f.add_argument("--mount", type=float, nargs=3, default=None, metavar=("ROLL", "PITCH", "YAW"),
                   help="IMU mounting angles, deg: rotates the declared IMU axes into the body frame (FRD)")
    f.add_argument("--heading", type=float, default=None, metavar="DEG",
                   help="initial heading (deg clockwise from north; default: from the GNSS velocity)")
    f.add_argument("--zupt", action="store_true", help="zero-velocity updates while the IMU is still")
    f.add_argument("--nhc", action="store_true", help="non-holonomic constraint (vehicles: no side/up velocity)")
    f.add_argument("--smooth", action="store_true", help="RTS smoother over the whole run (post-processing)")
    f.add_argument("--gate", default="1e-3", metavar="P|off",
                   help="chi-square gate of each GNSS epoch at false-alarm probability P (default 1e-3; off: none)")
    e = p.add_argument_group("evaluation")
    e.add_argument("--outage", action="append", default=[], metavar="START:LENGTH",
                   help="remove GNSS from START (GPS seconds of week) for LENGTH s; repeatable")
    e.add_argument("--outages", default=None, metavar="EVERY:LENGTH",
                   help="remove GNSS for LENGTH s every EVERY s (from EVERY s after the start)")
    e.add_argument("--outage-keep-sats", type=int, default=0, metavar="N",
                   help="tight coupling: satellites kept during the outages (highest elevation; default 0)")
    e.add_argument("--reference", default=None, metavar="REF.pos",
                   help="RTKLIB .pos reference (fixed epochs count): drift per outage, RMS, 3-sigma consistency")
    e.add_argument("--reference-geoid", type=float, default=None, metavar="N",
                   help="the reference's heights are above mean sea level with geoid undulation N (m): "
                        "ellipsoidal = reference + N (for a reference that is not ellipsoidal)")
    o = p.add_argument_group("outputs")
    o.add_argument("--out", default=None, metavar="OUT.pos", help="RTKLIB .pos solution (position, velocity, sigma)")
    o.add_argument("--csv", default=None, metavar="F", help="CSV: position, velocity, attitude, biases, sigma")
    o.add_argument("--kml", default=None, metavar="F", help="KML track")
    o.add_argument("--nmea", default=None, metavar="F", help="NMEA GGA/RMC")
    o.add_argument("--plot", default=None, metavar="PNG",
                   help="figure of the error against --reference with the outages shaded (plot extra)")
    o.add_argument("--rate", type=float, default=DEFAULT_RATE_HZ, metavar="HZ",
                   help=f"output rate of the files (default {DEFAULT_RATE_HZ:g} Hz; 0 = every IMU sample)")
    o.add_argument("--json", action="store_true", help="print the summary as JSON")
    o.add_argument("--quiet", action="store_true", help="no progress line")
    from ultratight.receiver.cli.commands import imu_flags
    imu_flags.add_arguments(p)
    imu_flags.add_noise_arguments(p)
    n = next(g for g in p._action_groups if g.title and g.title.startswith("IMU noise"))
    for flag, _key, text in SCALE_FLAGS:
        n.add_argument(flag, type=float, default=None, metavar="PCT", help=text)
    for a in p._actions:        # integrate takes the lever arm in body axes (after --mount), not in the file's
        if "--lever-arm" in a.option_strings:
            a.help = "lever arm IMU -> antenna in body axes forward-right-down (after --mount), m"
        if "--quiet" in a.option_strings:
            a.help = "no progress line on stderr (it is only shown on a terminal, and not with --json)"


def run(args):
    from ultratight.receiver.cli.integrate_run import run_integrate
    return run_integrate(args, sys.stdout, sys.stderr)
