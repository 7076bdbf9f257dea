"""CLI flags that declare an IMU file's conventions (override its sidecar key by key; see
:mod:`ultratight.ins.imu_decl` and docs/imu-declaration.md), shared by ``process --mode ultratight``,
``ins`` and ``integrate``; the IMU noise flags (:func:`add_noise_arguments`, docs/integrate-inputs.md)."""

# flag -> datasheet key of ultratight.ins.imu_noise
NOISE_FLAGS = (("--imu-gyro-noise", "gyro_noise_dps_rthz", "DEG/S/RTHZ", "gyro angle random walk, deg/s/rtHz"),
               ("--imu-accel-noise", "accel_noise_ug_rthz", "UG/RTHZ", "accelerometer velocity random walk, ug/rtHz"),
               ("--imu-gyro-bias-rw", "gyro_bias_rw_dps2_rthz", "DEG/S2/RTHZ",
                "gyro bias random walk, deg/s^2/rtHz"),
               ("--imu-accel-bias-rw", "accel_bias_rw_ug_rthz", "UG/S/RTHZ",
                "accelerometer bias random walk, ug/s/rtHz"),
               ("--imu-gyro-bias", "gyro_bias_dps", "DEG/S", "initial gyro bias uncertainty (1 sigma), deg/s"),
               ("--imu-accel-bias", "accel_bias_mps2", "M/S2",
                "initial accelerometer bias uncertainty (1 sigma), m/s^2"))


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


def overrides(args, lever_arm=True):
    """The sidecar keys given on the command line (dict; empty when none).  ``lever_arm=False``
    leaves ``--lever-arm`` out (a command that takes it in body axes: :func:`lever_arm_flu`)."""
    out = {"kind": args.imu_kind, "axes": args.imu_axes, "gyro_unit": args.imu_gyro_unit,
           "accel_unit": args.imu_accel_unit, "rate_hz": args.imu_rate, "time_ref": args.imu_time_ref,
           "gps_week": args.imu_week, "time_offset_s": args.imu_time_offset,
           "lever_arm_m": list(args.lever_arm) if args.lever_arm is not None and lever_arm else None,
           "check": False if args.imu_no_check else None}
    return {k: v for k, v in out.items() if v is not None}


def lever_arm_flu(args):
    """``--lever-arm X Y Z`` read in body axes FRD (as ``integrate`` takes it) -> FLU (m); None when
    not given."""
    if args.lever_arm is None:
        return None
    from ultratight.ins.imu_logs import lever_arm_frd_to_flu
    return lever_arm_frd_to_flu(args.lever_arm)


def add_noise_arguments(p):
    """The IMU noise flags (override the sidecar's ``noise`` table key by key, over a grade)."""
    from ultratight.ins.imu_noise import GRADES
    g = p.add_argument_group("IMU noise (override the sidecar's noise table; docs/integrate-inputs.md)")
    g.add_argument("--imu-grade", choices=tuple(GRADES), default=None,
                   help="typical figures of a grade for every value not declared")
    for flag, _key, metavar, text in NOISE_FLAGS:
        g.add_argument(flag, type=float, default=None, metavar=metavar, help=text)


def noise_flags(args):
    """The datasheet values given on the command line (dict of ultratight.ins.imu_noise keys)."""
    return {key: getattr(args, flag[2:].replace("-", "_")) for flag, key, _m, _t in NOISE_FLAGS
            if getattr(args, flag[2:].replace("-", "_"), None) is not None}


def resolve_noise(args, declaration=None):
    """The ImuNoise of the flags over the sidecar's ``noise`` table (``declaration``) over the grade."""
    from ultratight.ins.imu_decl import resolve_noise as resolve
    return resolve(declaration, grade=getattr(args, "imu_grade", None), **noise_flags(args))
