"""CLI flags that declare an IMU file's conventions (override its sidecar key by key; see
:mod:`ultratight.ins.imu_decl` and docs/imu-declaration.md), shared by ``process --mode ultratight``
and ``ins``."""


def add_arguments(p):
    g = p.add_argument_group("IMU declaration (override the IMU sidecar IMU.csv.json)")
    g.add_argument("--imu-kind", choices=("rates", "increments"), default=None,
                   help="rates (averages over the interval ending at t) or increments")
    g.add_argument("--imu-axes", default=None, metavar="AXES",
                   help="the file's x, y, z axes as three letters of F/B, L/R, U/D (e.g. FRD, FLU, RFU)")
    g.add_argument("--imu-gyro-unit", default=None, metavar="U", help="rad/s, deg/s (rates); rad, deg (increments)")
    g.add_argument("--imu-accel-unit", default=None, metavar="U", help="m/s^2, g (rates); m/s (increments)")
    g.add_argument("--imu-rate", type=float, default=None, metavar="HZ", help="declared IMU rate (checked)")
    g.add_argument("--imu-time-ref", choices=("run", "gps_tow"), default=None,
                   help="stamps in seconds since the IF start (run) or GPS seconds of week (gps_tow)")
    g.add_argument("--imu-week", type=int, default=None, metavar="WEEK", help="GPS week of gps_tow stamps")
    g.add_argument("--imu-time-offset", type=float, default=None, metavar="S",
                   help="seconds added to every IMU stamp (IMU clock offset)")
    g.add_argument("--lever-arm", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="lever arm IMU -> antenna in the declared IMU axes, m")
    g.add_argument("--imu-no-check", action="store_true", help="skip the stationary sanity check")


def overrides(args):
    """The sidecar keys given on the command line (dict; empty when none)."""
    out = {"kind": args.imu_kind, "axes": args.imu_axes, "gyro_unit": args.imu_gyro_unit,
           "accel_unit": args.imu_accel_unit, "rate_hz": args.imu_rate, "time_ref": args.imu_time_ref,
           "gps_week": args.imu_week, "time_offset_s": args.imu_time_offset,
           "lever_arm_m": list(args.lever_arm) if args.lever_arm is not None else None,
           "check": False if args.imu_no_check else None}
    return {k: v for k, v in out.items() if v is not None}
