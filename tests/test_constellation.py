"""Nominal constellation: slot table, orbit geometry at the slot-table epoch (checked in an
inertial frame built here), repeat period, continuity across toe, validity as LNAV data."""

import math

import numpy as np
import pytest

from ultratight.signals.constellation import (ALL_SLOTS, SLOTS, nominal_ephemerides,
                                              repeat_period_s, slot_of_prn)
from ultratight.signals.ephemeris import sat_state
from ultratight.signals.lnav_message import quantise

WE = 7.2921151467e-5
GHA = math.radians((18 + 36 / 60 + 14.4 / 3600) * 15)
EPOCH_WEEK, EPOCH_TOW = 703, 345600.0       # 1993-07-01 00:00 GPS: 4925 days after 1980-01-06 = week 703 + 4 d


def test_slot_table():
    assert len(SLOTS) == 24 and len(ALL_SLOTS) == 32
    planes = {}
    for name, raan, u in SLOTS:
        planes.setdefault(name[0], set()).add(raan)
    assert sorted(planes) == list("ABCDEF")
    raans = [planes[p].pop() for p in "ABCDEF"]
    assert all(len(v) == 0 for v in planes.values())       # one RAAN per plane
    assert np.allclose(np.diff(np.mod(np.array(raans) - raans[0], 360.0)), [60.0] * 5)
    # spot values from SPS PS Table 3-1 / 3.2-1
    assert slot_of_prn(1) == ("A1", 272.847, 268.126)
    assert slot_of_prn(15) == ("D3", 92.847, 35.156)
    assert slot_of_prn(24) == ("F4", 212.847, 135.346)
    us = {(raan, u) for _, raan, u in ALL_SLOTS}
    assert len(us) == 32
    with pytest.raises(ValueError):
        slot_of_prn(33)


def test_geometry_at_slot_epoch():
    ephs = nominal_ephemerides(EPOCH_WEEK, EPOCH_TOW)
    for prn, eph in ephs.items():
        _, raan_deg, u_deg = slot_of_prn(prn)
        pos = sat_state(eph, EPOCH_TOW)[0][0]
        # ECEF -> inertial at the epoch: rotate by the Greenwich hour angle about z
        c, s = math.cos(GHA), math.sin(GHA)
        eci = np.array([c * pos[0] - s * pos[1], s * pos[0] + c * pos[1], pos[2]])
        om, u, i = math.radians(raan_deg), math.radians(u_deg), math.radians(55.0)
        expect = np.array([math.cos(om) * math.cos(u) - math.sin(om) * math.sin(u) * math.cos(i),
                           math.sin(om) * math.cos(u) + math.cos(om) * math.sin(u) * math.cos(i),
                           math.sin(u) * math.sin(i)])
        assert np.linalg.norm(pos) == pytest.approx(26559.7e3, abs=1e-3)
        assert np.allclose(eci / np.linalg.norm(eci), expect, atol=1e-12)


def test_repeat_period_and_continuity():
    week, tow = 2190, 518400.0 + 1234.0
    e1 = nominal_ephemerides(week, tow)
    period = repeat_period_s()
    assert period == pytest.approx(86154.0, abs=10.0)
    e2 = nominal_ephemerides(week, tow + period)
    e3 = nominal_ephemerides(week, tow + 1900.0)      # next toe (rounded to the hour)
    assert e3[1].toe != e1[1].toe
    for prn in e1:
        p1 = sat_state(e1[prn], tow)[0][0]
        p2 = sat_state(e2[prn], tow + period)[0][0]
        assert np.linalg.norm(p1 - p2) < 1e-3
        p3 = sat_state(e3[prn], tow + 1000.0)[0][0]
        p1b = sat_state(e1[prn], tow + 1000.0)[0][0]
        assert np.linalg.norm(p3 - p1b) < 1e-3
    # distinct satellites, healthy, representable in LNAV, deterministic
    pos = np.array([sat_state(e, tow)[0][0] for e in e1.values()])
    d = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=-1) + np.eye(32) * 1e9
    assert d.min() > 1.0e6
    for e in e1.values():
        assert e.healthy and e.toe % 16 == 0
        q = quantise(e)
        assert np.linalg.norm(sat_state(q, tow)[0][0] - sat_state(e, tow)[0][0]) < 1.0
    assert nominal_ephemerides(week, tow) == e1


def test_week_crossing_toe():
    e = nominal_ephemerides(2190, 604790.0)
    assert all(x.week == 2191 and x.toe == 0.0 for x in e.values())
    e_prev = nominal_ephemerides(2190, 604790.0 - 3600.0)
    for prn in e:
        # evaluate both at TOW 604000 of week 2190 (tk wraps for the week-2191 set)
        assert np.linalg.norm(sat_state(e[prn], 604000.0)[0][0]
                              - sat_state(e_prev[prn], 604000.0)[0][0]) < 1e-3
