"""Earth model: normal gravity against independent formulas, radii, LLH <-> ECEF."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from numpy.polynomial import legendre

from ultratight.constants import OMEGA_E, WGS84_A, WGS84_E2
from ultratight.ins.earth import (WGS84_GM_EARTH, dcm_ecef_from_enu, earth_rate_l, ecef_to_llh, gravity_free_air,
                                  gravity_l, llh_to_ecef, normal_gravity, radii, transport_rate_l)


def somigliana(lat):
    """WGS-84 Somigliana closed form (NIMA TR8350.2 eq. 4-1, defining constants of Table 3.4)."""
    ge, k = 9.7803253359, 0.00193185265241
    s2 = math.sin(lat) ** 2
    return ge * (1.0 + k * s2) / math.sqrt(1.0 - WGS84_E2 * s2)


# normal-field zonal harmonics of the WGS-84 level ellipsoid (Heiskanen & Moritz 2-92)
_J2 = 0.484166774985e-3 * math.sqrt(5.0)
_J = [_J2] + [(-1) ** (n + 1) * 3.0 * WGS84_E2 ** n / ((2 * n + 1) * (2 * n + 3)) * (1 - n + 5 * n * _J2 / WGS84_E2)
              for n in range(2, 7)]


def _potential(r):
    x, y, z = r
    rr = math.sqrt(x * x + y * y + z * z)
    s = z / rr
    v = 1.0
    for n, jn in enumerate(_J, 1):
        c = np.zeros(2 * n + 1)
        c[-1] = 1.0
        v -= jn * (WGS84_A / rr) ** (2 * n) * legendre.legval(s, c)
    return WGS84_GM_EARTH / rr * v + 0.5 * OMEGA_E ** 2 * (x * x + y * y)


def harmonic_gravity_enu(lat, lon, h):
    """Gradient of the J2..J12 normal potential + centrifugal (4th-order central differences)."""
    r = llh_to_ecef(lat, lon, h)
    g = np.zeros(3)
    d = 20.0
    for i in range(3):
        e = np.zeros(3)
        e[i] = d
        g[i] = (-_potential(r + 2 * e) + 8 * _potential(r + e) - 8 * _potential(r - e) + _potential(r - 2 * e)) \
            / (12 * d)
    return dcm_ecef_from_enu(lat, lon).T @ g


@pytest.mark.parametrize("lat_deg", [0.0, 15.0, 28.246, 45.0, 63.0, 89.9, -37.0])
def test_sea_level_gravity_matches_somigliana(lat_deg):
    lat = math.radians(lat_deg)
    assert abs(normal_gravity(lat, 0.0) - somigliana(lat)) < 1e-6
    g = gravity_l(lat, 0.0)
    assert abs(g[1]) < 1e-8 and g[0] == 0.0      # on the ellipsoid, normal gravity is along the normal


@pytest.mark.parametrize("lat_deg,h", [(0.0, 0.0), (28.246, 50e3), (28.246, 0.0), (60.0, 100e3), (-40.0, 30e3),
                                       (80.0, 50e3)])
def test_gravity_vector_matches_spherical_harmonic_field(lat_deg, h):
    lat = math.radians(lat_deg)
    ref = harmonic_gravity_enu(lat, 0.7, h)
    # documented accuracy: the closed form is exact for the normal field; < 1e-8 m/s^2 vs this reference
    assert np.max(np.abs(gravity_l(lat, h) - ref)) < 1e-8


def test_free_air_series_error_at_50km_is_as_documented():
    # docs/ins.md: the 2nd-order free-air series is 1e-5 .. 2.1e-5 m/s^2 off at 50 km; ours is exact
    for lat_deg in (0.0, 28.246, 90.0):
        lat = math.radians(lat_deg)
        ref = np.linalg.norm(harmonic_gravity_enu(lat, 0.0, 50e3))
        diff = gravity_free_air(lat, 50e3) - ref
        assert 1e-5 < diff < 2.1e-5
        assert abs(normal_gravity(lat, 50e3) - ref) < 1e-8


@pytest.mark.parametrize("lat_deg", [0.0, 28.246, 70.0])
def test_radii_of_curvature_from_geometry(lat_deg):
    lat, lon, h = math.radians(lat_deg), 0.3, 1234.0
    rm, rn = radii(lat)
    d = 1e-5      # truncation ~ R d^2 / 6 ~ 1e-4 m, rounding ~ eps R / d ~ 1e-4 m
    dr_dlat = (llh_to_ecef(lat + d, lon, h) - llh_to_ecef(lat - d, lon, h)) / (2 * d)
    dr_dlon = (llh_to_ecef(lat, lon + d, h) - llh_to_ecef(lat, lon - d, h)) / (2 * d)
    assert abs(np.linalg.norm(dr_dlat) - (rm + h)) < 1e-3
    assert abs(np.linalg.norm(dr_dlon) - (rn + h) * math.cos(lat)) < 1e-3


def test_earth_and_transport_rates():
    lat = math.radians(28.246)
    w = earth_rate_l(lat)
    C = dcm_ecef_from_enu(lat, 1.0)
    assert np.allclose(C @ w, [0.0, 0.0, OMEGA_E], atol=1e-18)
    # transport rate: rotation of the ENU frame moving north at 100 m/s is -vN/(M+h) about east
    rm, rn = radii(lat)
    wt = transport_rate_l(lat, 500.0, np.array([0.0, 100.0, 0.0]))
    assert np.allclose(wt, [-100.0 / (rm + 500.0), 0.0, 0.0])
    # moving east: d(lon)/dt = vE / ((N+h) cos lat) about the polar axis
    wt = transport_rate_l(lat, 500.0, np.array([50.0, 0.0, 0.0]))
    lon_rate = 50.0 / ((rn + 500.0) * math.cos(lat))
    assert np.allclose(C @ wt, [0.0, 0.0, lon_rate], atol=1e-15)


@settings(max_examples=200, deadline=None)
@given(st.floats(-89.9, 89.9), st.floats(-180, 180), st.floats(-1000.0, 120e3))
def test_llh_ecef_round_trip(lat_deg, lon_deg, h):
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    llh = ecef_to_llh(llh_to_ecef(lat, lon, h))
    assert abs(llh[0] - lat) < 1e-12
    assert abs(math.remainder(llh[1] - lon, 2 * math.pi)) < 1e-12
    assert abs(llh[2] - h) < 1e-6
