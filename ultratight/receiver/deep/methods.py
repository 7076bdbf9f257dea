"""The receiver's tracking methods: one registry of specs, each naming its tracking bank and loop structure.

=============  ==========  =============  =============================================================
method         bank        loop           what it is
=============  ==========  =============  =============================================================
``pb-kf-utc``  ``pbkf``    ``outer``      single-loop baseline: discriminators into a linear KF per
                                          channel (:mod:`ultratight.fusion.channel.pbkf`); the NCOs follow the
                                          outer loop (SINS prediction) only
``dlb-ukf``    ``ukf``     ``double``     double loop: each channel's prefilter
``dlb-ckf``    ``ckf``     ``double``     (:class:`ultratight.fusion.channel.prefilter.PrefilterBank` of that
``dlb-rackf``  ``rackf``   ``double``     kind) closes its own inner loop every epoch; the outer loop
                                          feeds the SINS-predicted Doppler increments forward
``dlb-rackf-`` ``rackf``   ``double``     the same with the RACKF of the paper's Algorithm 1 as printed
``paper``                                 (Huber + adaptive factor only every correction period, the
                                          single-epoch statistic of eq. 38); ``dlb-rackf`` is the
                                          project's variant (Huber every epoch, windowed statistic)
``scalar``     ``scalar``  ``scalar``     the scalar DLL/PLL/FLL channels of :mod:`ultratight.receiver.dsp.tracking`
                                          (no INS), from the same hot-start predictions
=============  ==========  =============  =============================================================

A new method is one entry here (plus its bank, if new: :mod:`ultratight.receiver.deep.tracking_banks`). The engine
(:mod:`ultratight.receiver.deep.engine`) reads only the spec: which bank to build, whether the
inner loop runs (``double``) or the NCOs follow the outer loop alone (``outer``), and whether the
method runs through the scalar pipeline instead (``scalar``).
"""

from dataclasses import dataclass, field

from ultratight.errors import ConfigError

LOOPS = ("outer", "double", "scalar")


@dataclass(frozen=True)
class MethodSpec:
    name: str
    bank: str                 # "pbkf", a PrefilterBank kind ("ukf", "ckf", "rackf") or "scalar"
    loop: str                 # "outer" (NCOs on the outer loop only), "double" (inner + outer) or "scalar"
    description: str = ""
    bank_options: dict = field(default_factory=dict)   # bank parameters of this method (override the options)

    def __post_init__(self):
        if self.loop not in LOOPS:
            raise ConfigError(f"method {self.name!r}: loop must be one of {', '.join(LOOPS)}, got {self.loop!r}")

    @property
    def double_loop(self):
        """The tracking bank closes its own inner loop (the NCOs take its corrections)."""
        return self.loop == "double"

    @property
    def scalar(self):
        """Runs through the scalar tracking pipeline (no INS, no IMU data)."""
        return self.loop == "scalar"

    @property
    def needs_imu(self):
        return not self.scalar


REGISTRY = {s.name: s for s in (
    MethodSpec("pb-kf-utc", "pbkf", "outer", "discriminators + linear KF per channel, NCOs on the outer loop"),
    MethodSpec("dlb-ukf", "ukf", "double", "double loop, UKF prefilters"),
    MethodSpec("dlb-ckf", "ckf", "double", "double loop, CKF prefilters"),
    MethodSpec("dlb-rackf", "rackf", "double", "double loop, robust adaptive CKF prefilters"),
    MethodSpec("dlb-rackf-paper", "rackf", "double",
               "double loop, RACKF as Algorithm 1 of Zhao et al. 2014: robust and adaptive corrections "
               "only every correction period, adaptive statistic of the epoch alone (eq. 38)",
               bank_options={"robust_mode": "period", "adaptive_stat": "epoch"}),
    MethodSpec("scalar", "scalar", "scalar", "scalar DLL/PLL/FLL tracking, no INS"),
)}

METHODS = tuple(REGISTRY)
DEFAULT_METHOD = "dlb-rackf"


def check_method(method):
    """The method name, or ConfigError naming the registered ones."""
    if not isinstance(method, str) or method not in REGISTRY:
        raise ConfigError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    return method


def method_spec(method):
    """The :class:`MethodSpec` of a registered method (ConfigError for an unknown name)."""
    return REGISTRY[check_method(method)]
