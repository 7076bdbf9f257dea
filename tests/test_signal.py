"""Signal description: GPS L1 C/A figures from IS-GPS-200, and the receiver stages that take a
description use its data-bit period instead of a hard-wired 20 ms."""

import numpy as np
import pytest

from ultratight.constants import CA_LEN, F_CA, F_L1, LAMBDA_L1
from ultratight.signals.ca_code import ca_code
from ultratight.signals.signal import GPS_L1CA, SignalDescription


def test_gps_l1ca_description():
    s = GPS_L1CA
    assert (s.carrier_hz, s.chip_rate_hz, s.code_length) == (F_L1, F_CA, CA_LEN)
    assert s.code_period_s == pytest.approx(1e-3) and s.bit_period_s == pytest.approx(0.02)
    assert s.wavelength_m == pytest.approx(LAMBDA_L1) and s.chip_m == pytest.approx(293.05, abs=0.01)
    assert s.code_rate_cps(1540.0) == pytest.approx(F_CA + 1.0)      # 1540 carrier cycles per chip
    np.testing.assert_array_equal(s.code(7), ca_code(7))
    assert s.prns == tuple(range(1, 33)) and s.secondary_code == ()
    np.testing.assert_array_equal(s.bit_index(np.array([100, 119, 120, 99]), 100), [0, 0, 1, -1])


def test_bit_wipeoff_follows_the_description():
    """A stub signal with 4 code periods per bit: the wipe-off indexes bits every 4 ms."""
    from ultratight.receiver.deep.startup import BitWipeoff
    stub = SignalDescription("stub", F_L1, F_CA, CA_LEN, ca_code, (1,), codes_per_bit=4)
    w = BitWipeoff({}, [1], 2190, 518400.0, 0.1, signal=stub)      # no ephemeris: bits stay +1
    w.bits[0] = np.arange(w.bits.shape[1]) % 2 * 2 - 1
    ms = w.t0_ms[0] + np.arange(12)
    np.testing.assert_array_equal(w.signs(ms[:, None])[:, 0], np.repeat([-1.0, 1.0, -1.0], 4))
    assert w.t0_ms[0] % 4 == 0


@pytest.mark.parametrize("module", ["ultratight.receiver.deep.engine", "ultratight.receiver.deep.startup"])
def test_stages_take_the_signal_from_its_description(module):
    """The engine and the start-up stage read carrier, chip rate, code length and bit period from
    a SignalDescription, not from the GPS L1 C/A constants."""
    import importlib
    import inspect
    import re
    src = inspect.getsource(importlib.import_module(module))
    for name in ("F_L1", "F_CA", "CA_LEN", "T_CA", "CHIP_M", "LAMBDA_L1", "CODE_PER_BIT", "1575.42e6"):
        assert not re.search(r"\b" + re.escape(name) + r"\b", src), name
