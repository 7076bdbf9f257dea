"""Signal descriptions: what a receiver stage needs to know about the signal it processes.

A :class:`SignalDescription` gathers the carrier, the ranging code (chip rate, length,
generator, PRNs, secondary code), the data-bit period and the correlator taps of one signal.
GPS L1 C/A (IS-GPS-200, sections 3.2-3.3) is the one instance, :data:`GPS_L1CA`; a second
signal (Galileo E1, BeiDou B1I) is a new description plus its code generator and navigation
decoder, and a stage that takes a description instead of importing constants does not change.
"""

from dataclasses import dataclass, field
from typing import Callable

from ultratight.constants import C, CA_LEN, CODE_PER_BIT, F_CA, F_L1
from ultratight.signals.ca_code import PRNS, ca_code


@dataclass(frozen=True)
class SignalDescription:
    name: str
    carrier_hz: float              # nominal carrier frequency
    chip_rate_hz: float            # primary-code chip rate
    code_length: int               # chips per primary-code period
    code: Callable                 # prn -> one period of the primary code, +-1 (numpy array)
    prns: tuple                    # the valid PRN numbers
    codes_per_bit: int             # primary-code periods per data bit (1: data on every period)
    secondary_code: tuple = ()     # +-1 chips of the secondary code (empty: none)
    navigation: str = ""           # the navigation message the data bits carry
    tap_spacing_chips: float = 1.0  # early-late spacing of the correlators
    extra: dict = field(default_factory=dict)

    @property
    def code_period_s(self):
        return self.code_length / self.chip_rate_hz

    @property
    def bit_period_s(self):
        return self.codes_per_bit * self.code_period_s

    @property
    def wavelength_m(self):
        return C / self.carrier_hz

    @property
    def chip_m(self):
        return C / self.chip_rate_hz

    @property
    def code_carrier_ratio(self):
        """Chips of code per cycle of carrier: the code Doppler is this times the carrier Doppler."""
        return self.chip_rate_hz / self.carrier_hz

    def code_rate_cps(self, doppler_hz):
        """Code rate (chips/s) matching a carrier Doppler (Hz)."""
        return self.chip_rate_hz * (1.0 + doppler_hz / self.carrier_hz)

    def bit_index(self, period_count, period0):
        """Index of the data bit holding the code period ``period_count`` (integer counts of code
        periods since a bit edge ``period0``; ints or int arrays)."""
        return (period_count - period0) // self.codes_per_bit


GPS_L1CA = SignalDescription(
    name="GPS L1 C/A", carrier_hz=F_L1, chip_rate_hz=F_CA, code_length=CA_LEN, code=ca_code, prns=PRNS,
    codes_per_bit=CODE_PER_BIT, navigation="LNAV", tap_spacing_chips=1.0)
