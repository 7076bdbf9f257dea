"""Air-data physics (Duan et al. 2024): standard atmosphere, flush air-data sensing (FADS), air data.

* :mod:`ultratight.airdata.atmosphere` — ICAO standard atmosphere through the ``ambiance`` library
  (pressure, temperature, density, speed of sound; altitude of a pressure), optional constant wind.
* :mod:`ultratight.airdata.fads` — port layout, the Whitmore pressure model with the subsonic /
  supersonic (Rayleigh pitot) impact pressure, the per-epoch Gauss–Newton inversion with its
  covariance, the "direct" FADS altitude error curve, and air data (α, β, Mach) from a velocity and
  an attitude.

Frames: the paper's East–South–Down navigation frame ("n", x East, y South, z Down) and the
body frame x nose, y right wing, z down. This package sits beside :mod:`ultratight.ins` and imports
nothing of the project but :mod:`ultratight.errors`.
"""
