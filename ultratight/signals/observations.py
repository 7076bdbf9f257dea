"""What a GNSS receiver hands on to an integration filter, in one form whatever file it came from.

* :class:`GnssFixes` — the receiver's own solution (loose coupling): position, velocity and their
  σ per epoch, with a quality code (RTKLIB's ``Q``: 1 fixed, 2 float, 3 SBAS, 4 DGPS, 5 single,
  6 PPP).  Read from RTKLIB ``.pos``, NMEA GGA/RMC/GST or u-blox NAV-PVT.
* :class:`RawEpochs` — raw GPS L1 C/A measurements (tight coupling): pseudorange, Doppler, C/N0
  per satellite and epoch, stored flat (CSR: epoch ``k`` holds rows ``start[k]:start[k+1]``).
  Read from RINEX 2/3 observations or u-blox RXM-RAWX.  A row's pseudorange may be the
  dual-frequency ionosphere-free combination of L1 C/A with a second signal (``iono_free_f2_hz``
  > 0, :func:`iono_free_combination`); Doppler, C/N0 and carrier phase stay those of L1 C/A.

Time is **GPS time in continuous seconds since the GPS epoch** (1980-01-06 00:00:00 GPST,
``week * 604800 + tow``) everywhere in these containers; :func:`gps_seconds` and
:func:`week_tow` convert.  Doppler follows the RINEX / u-blox sign: positive while the satellite
approaches (range rate = −λ·D).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SECONDS_PER_WEEK = 604800.0
F_L1_HZ = 1575.42e6
F_L2_HZ = 1227.60e6
F_L5_HZ = 1176.45e6
# RTKLIB solution quality codes
Q_FIX, Q_FLOAT, Q_SBAS, Q_DGPS, Q_SINGLE, Q_PPP = 1, 2, 3, 4, 5, 6
QUALITY_NAMES = {Q_FIX: "fix", Q_FLOAT: "float", Q_SBAS: "sbas", Q_DGPS: "dgps", Q_SINGLE: "single",
                 Q_PPP: "ppp"}


def gps_seconds(week, tow_s):
    """Continuous GPS seconds of (week, seconds of week)."""
    return np.asarray(week, dtype=float) * SECONDS_PER_WEEK + np.asarray(tow_s, dtype=float)


def iono_free_combination(pr1_m, pr2_m, f2_hz, f1_hz=F_L1_HZ):
    """The ionosphere-free pseudorange ``(γ P1 − P2) / (γ − 1)``, ``γ = (f1 / f2)²``: the first-order
    ionospheric delay (∝ 1/f²) cancels (IS-GPS-200 §20.3.3.3.3.3 for L1/L2)."""
    g = (float(f1_hz) / np.asarray(f2_hz, dtype=float)) ** 2
    return (g * np.asarray(pr1_m, dtype=float) - np.asarray(pr2_m, dtype=float)) / (g - 1.0)


def iono_free_noise_factor(f2_hz, f1_hz=F_L1_HZ):
    """σ of :func:`iono_free_combination` over the σ of each of its two (independent, equally noisy)
    pseudoranges: ``√(γ² + 1) / (γ − 1)`` (2.98 for L1/L2, 2.59 for L1/L5); 1 where ``f2_hz`` is 0
    or NaN (a single-frequency row)."""
    f2 = np.asarray(f2_hz, dtype=float)
    ok = np.isfinite(f2) & (f2 > 0.0)
    g = (float(f1_hz) / np.where(ok, f2, 1.0)) ** 2
    return np.where(ok, np.sqrt(g * g + 1.0) / np.where(ok, g - 1.0, 1.0), 1.0)


def week_tow(t_gps):
    """(week, seconds of week) of continuous GPS seconds (arrays or scalars)."""
    t = np.asarray(t_gps, dtype=float)
    week = np.floor(t / SECONDS_PER_WEEK)
    return week.astype(int), t - week * SECONDS_PER_WEEK


@dataclass
class GnssFixes:
    """A GNSS solution series (loose-coupling input), one row per epoch.

    ``llh``: latitude, longitude (rad), ellipsoidal height (m); ``vel_enu`` (m/s) and the σ arrays
    are NaN where the source gives none; ``sigma_pos_enu`` (m) / ``sigma_vel_enu`` (m/s) are 1σ
    per axis (east, north, up)."""
    t: np.ndarray                 # (n,) continuous GPS seconds
    llh: np.ndarray               # (n, 3)
    vel_enu: np.ndarray           # (n, 3)
    sigma_pos_enu: np.ndarray     # (n, 3)
    sigma_vel_enu: np.ndarray     # (n, 3)
    quality: np.ndarray           # (n,) int, RTKLIB Q codes
    n_sat: np.ndarray | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def n(self):
        return int(self.t.shape[0])

    def subset(self, keep):
        """A copy holding the rows where ``keep`` (bool mask or indices) selects."""
        return GnssFixes(self.t[keep], self.llh[keep], self.vel_enu[keep], self.sigma_pos_enu[keep],
                         self.sigma_vel_enu[keep], self.quality[keep],
                         None if self.n_sat is None else self.n_sat[keep], self.source, dict(self.meta))


@dataclass
class RawEpochs:
    """Raw GPS L1 C/A measurements (tight-coupling input), flat per (epoch, satellite) row.

    Rows of epoch k: ``start[k]:start[k+1]``.  ``pr_m`` / ``doppler_hz`` / ``cn0_dbhz`` /
    ``phase_cyc`` are NaN where the source has no such value.

    ``iono_free_f2_hz`` (optional): per row, the second frequency of an ionosphere-free ``pr_m``
    (:func:`iono_free_combination` with L1; the satellite's inter-signal corrections applied, so the
    row takes the L1 C/A satellite clock with −T_GD like any other); 0 for a single-frequency L1 C/A
    row; None: every row is single frequency.  ``pr_l1_m`` (optional): the L1 C/A pseudorange as
    measured where ``pr_m`` is a combination."""
    t: np.ndarray                 # (n_epochs,) receive time, continuous GPS seconds (receiver clock)
    start: np.ndarray             # (n_epochs + 1,) int
    prn: np.ndarray               # (m,) int
    pr_m: np.ndarray              # (m,)
    doppler_hz: np.ndarray        # (m,) positive while approaching
    cn0_dbhz: np.ndarray          # (m,)
    phase_cyc: np.ndarray | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)
    iono_free_f2_hz: np.ndarray | None = None
    pr_l1_m: np.ndarray | None = None

    def iono_free_rows(self):
        """(m,) bool: the row's pseudorange is an ionosphere-free combination."""
        if self.iono_free_f2_hz is None:
            return np.zeros(self.prn.shape[0], dtype=bool)
        f2 = np.asarray(self.iono_free_f2_hz, dtype=float)
        return np.isfinite(f2) & (f2 > 0.0)

    @property
    def n_epochs(self):
        return int(self.t.shape[0])

    def epoch(self, k):
        """slice of the rows of epoch k."""
        return slice(int(self.start[k]), int(self.start[k + 1]))

    def epoch_index(self):
        """(m,) epoch number of every row."""
        return np.repeat(np.arange(self.n_epochs), np.diff(self.start))
