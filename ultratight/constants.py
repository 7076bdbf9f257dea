"""Physical and GPS L1 C/A constants (SI units).

Sources (see docs/references.md): IS-GPS-200D (speed of light, GPS value of GM, Earth rotation rate,
relativistic constant F) and WGS-84 (ellipsoid).
"""

import math

C = 299792458.0                       # speed of light, m/s
F_L1 = 1575.42e6                      # L1 carrier, Hz
LAMBDA_L1 = C / F_L1                  # L1 wavelength, m
F_CA = 1.023e6                        # C/A chip rate, Hz
CA_LEN = 1023                         # chips per C/A period
T_CA = CA_LEN / F_CA                  # C/A code period, s (1 ms)
CHIP_M = C / F_CA                     # one chip in metres
CODE_PER_BIT = 20                     # C/A periods per LNAV bit
BIT_RATE = 50.0                       # LNAV bit rate, bit/s
BETA_CODE_CARRIER = F_CA / (2.0 * math.pi * F_L1)   # chips/s per rad/s of carrier (Zhao et al. 2014, eq. 2)

GM = 3.986005e14                      # WGS-84 value of GM used by GPS, m^3/s^2
OMEGA_E = 7.2921151467e-5             # Earth rotation rate, rad/s
F_REL = -4.442807633e-10              # relativistic constant F, s/sqrt(m)

WGS84_A = 6378137.0                   # semi-major axis, m
WGS84_F = 1.0 / 298.257223563         # flattening
WGS84_B = WGS84_A * (1.0 - WGS84_F)   # semi-minor axis, m
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared

SECONDS_PER_WEEK = 604800.0
GPS_WEEK_ROLLOVER = 1024
