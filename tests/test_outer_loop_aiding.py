"""OuterLoop.aiding_at: the 1 kHz Doppler aiding of each channel at its own time, linear between grid
points and clamped to the filled part of the grid."""

import numpy as np

from ultratight.receiver.deep.outer_loop import OuterLoop
from ultratight.signals.constellation import nominal_ephemerides


def test_aiding_at_interpolates_each_channel_on_the_grid():
    ol = OuterLoop(nominal_ephemerides(2190, 518400.0), [31, 20], 2190, 518400.0, 0.1)
    ol.aid_doppler[:10] = np.stack([np.arange(10) * 2.0, 100.0 - np.arange(10)], 1)
    ol.n_filled = 10
    np.testing.assert_allclose(ol.aiding_at(np.array([2.5e-3, 4.25e-3])), [5.0, 95.75])
    np.testing.assert_allclose(ol.aiding_at(np.array([0.0, 9.0e-3])), [0.0, 91.0])   # last pair held
    np.testing.assert_allclose(ol.aiding_at(np.array([-1e-3, 20e-3])), [-2.0, 80.0])  # clamped grid index
