"""RINEX navigation reader: the real 2.11 file, a RINEX 3 file made from it, corrupt variants."""

import math

import numpy as np
import pytest

from ultratight.errors import NavDataError
from ultratight.signals.rinex import read_rinex_nav

RINEX3_HEADER = (
    "     3.04           N: GNSS NAV DATA    M: MIXED            RINEX VERSION / TYPE\n"
    "test                test                20220102 000000 UTC PGM / RUN BY / DATE\n"
    "GPSA   1.2110E-08 -7.4510E-09 -5.9600E-08  1.1920E-07       IONOSPHERIC CORR\n"
    "GPSB   1.1670E+05 -2.4580E+05 -6.5540E+04  1.1140E+06       IONOSPHERIC CORR\n"
    "    18                                                      LEAP SECONDS\n"
    "                                                            END OF HEADER\n"
)
GLONASS_RECORD = (
    "R01 2022 01 01 00 15 00 7.827021181583E-06 0.000000000000E+00 5.184000000000E+05\n"
    "     1.000000000000E+04 1.000000000000E+00 0.000000000000E+00 0.000000000000E+00\n"
    "     1.000000000000E+04 1.000000000000E+00 0.000000000000E+00 1.000000000000E+00\n"
    "     1.000000000000E+04 1.000000000000E+00 0.000000000000E+00 0.000000000000E+00\n"
)


def _records_v2(path):
    lines = path.read_text().splitlines()
    start = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    return lines[:start], [lines[i:i + 8] for i in range(start, len(lines), 8)]


def _to_v3(record):
    """Reformat one RINEX 2.11 GPS record (8 lines) into RINEX 3 layout."""
    l0 = record[0].ljust(79)
    prn, yy, mo, dd, hh, mi, ss = (l0[0:2], l0[2:5], l0[5:8], l0[8:11], l0[11:14], l0[14:17], l0[17:22])
    head = (f"G{int(prn):02d} {2000 + int(yy):04d} {int(mo):02d} {int(dd):02d} {int(hh):02d} "
            f"{int(mi):02d} {int(float(ss)):02d}")
    out = [head + l0[22:79]]
    for ln in record[1:]:
        out.append(" " + ln.rstrip())            # 3X -> 4X: the 19-character fields shift by one
    return out


@pytest.fixture(scope="module")
def nav(rinex_path):
    return read_rinex_nav(rinex_path)


def test_reads_real_rinex2(nav, rinex_path):
    assert nav.version == 2.0
    assert nav.prns == list(range(1, 33))
    assert nav.leap_seconds == 18
    assert nav.ion_alpha == pytest.approx((0.1211e-7, -0.7451e-8, -0.5960e-7, 0.1192e-6))
    assert nav.utc["wnt"] == 2191 and nav.utc["a0"] == pytest.approx(0.279396772385e-08)
    e = nav.ephemerides[1][0]
    # values of the first record, copied by hand from the file
    assert (e.prn, e.week, e.toe, e.toc, e.iode, e.iodc) == (1, 2190, 518400.0, 518400.0, 39, 39)
    assert e.af0 == 0.469126738608e-03 and e.af1 == -0.100044417195e-10
    assert e.crs == -0.141125e3 and e.delta_n == 0.398838041777e-08 and e.m0 == -0.624294238235
    assert e.sqrt_a == 0.515367499542e4 and e.e == 0.112181392033e-1
    assert e.omega_dot == -0.813355308085e-08 and e.tgd == 0.512227416039e-08
    assert e.tx_tow == 511218.0 and e.fit_interval_h == 4.0 and e.sv_health == 0
    for prn, lst in nav.ephemerides.items():
        keys = [(x.week, x.toe) for x in lst]
        assert keys == sorted(keys)
        assert all(x.prn == prn for x in lst)


def test_select_nearest_healthy_within_fit(nav):
    for tow in (518400.0, 518400.0 + 3000.0, 518400.0 + 5 * 3600.0 + 100.0):
        e = nav.select(5, 2190, tow)
        assert e is not None
        cands = [x for x in nav.ephemerides[5] if x.healthy and abs(x.toe - tow) <= 7200.0]
        assert abs(e.toe - tow) == min(abs(x.toe - tow) for x in cands)
    assert nav.select(5, 2190, 100000.0) is None          # days before the file: out of fit
    assert nav.select(40, 2190, 518400.0) is None
    all_ = nav.select_all(2190, 518400.0 + 3600.0)
    assert len(all_) >= 28


def test_unhealthy_is_skipped(nav):
    unhealthy = [(p, x) for p, lst in nav.ephemerides.items() for x in lst if not x.healthy]
    for prn, x in unhealthy:
        sel = nav.select(prn, x.week, x.toe)
        assert sel is None or sel.healthy


def test_rinex3_equals_rinex2(rinex_path, nav, tmp_path):
    _, recs = _records_v2(rinex_path)
    text = RINEX3_HEADER
    chosen = recs[:3] + recs[100:102]
    for k, r in enumerate(chosen):
        text += "\n".join(_to_v3(r)) + "\n"
        if k == 1:
            text += GLONASS_RECORD
    p = tmp_path / "test.22p"
    p.write_text(text)
    nav3 = read_rinex_nav(p)
    assert nav3.version == 3.04
    assert nav3.ion_beta == pytest.approx((1.167e5, -2.458e5, -6.554e4, 1.114e6))
    assert nav3.leap_seconds == 18
    n3 = sum(len(v) for v in nav3.ephemerides.values())
    assert n3 == 5
    for prn, lst in nav3.ephemerides.items():
        for e3 in lst:
            e2 = next(x for x in nav.ephemerides[prn] if x.toe == e3.toe and x.iode == e3.iode)
            for name, v2 in e2.as_dict().items():
                v3 = getattr(e3, name)
                assert v3 == v2 or (isinstance(v2, float) and math.isnan(v2) and math.isnan(v3)), name


def _write_variant(rinex_path, tmp_path, mutate):
    lines = rinex_path.read_text().splitlines()
    lines = mutate(lines)
    p = tmp_path / "bad.22n"
    p.write_text("\n".join(lines) + "\n")
    return p


def test_corrupt_number_names_file_line_field(rinex_path, tmp_path):
    hdr, _ = _records_v2(rinex_path)
    target = len(hdr) + 8 + 2          # third line of the second record: cuc, e, cus, sqrt_a
    def mutate(lines):
        ln = lines[target].ljust(79)
        lines[target] = ln[:22] + " 0.1121813920X3D-01" + ln[41:]
        return lines
    p = _write_variant(rinex_path, tmp_path, mutate)
    with pytest.raises(NavDataError) as ei:
        read_rinex_nav(p)
    msg = str(ei.value)
    assert "bad.22n" in msg and f"line {target + 1}" in msg and "'e'" in msg


def test_truncated_record(rinex_path, tmp_path):
    def mutate(lines):
        return lines[:-3]
    p = _write_variant(rinex_path, tmp_path, mutate)
    n_lines = len(rinex_path.read_text().splitlines()) - 3
    with pytest.raises(NavDataError) as ei:
        read_rinex_nav(p)
    msg = str(ei.value)
    assert "bad.22n" in msg and "truncated" in msg and f"line {n_lines + 1}" in msg


def test_missing_mandatory_field_and_header(rinex_path, tmp_path):
    hdr, _ = _records_v2(rinex_path)
    target = len(hdr) + 3               # toe line of the first record
    def blank_toe(lines):
        ln = lines[target].ljust(79)
        lines[target] = ln[:3] + " " * 19 + ln[22:]
        return lines
    with pytest.raises(NavDataError, match=rf"line {target + 1}: field 'toe'"):
        read_rinex_nav(_write_variant(rinex_path, tmp_path, blank_toe))
    with pytest.raises(NavDataError, match="END OF HEADER"):
        read_rinex_nav(_write_variant(rinex_path, tmp_path,
                                      lambda ls: [x for x in ls if "END OF HEADER" not in x]))


def test_selected_positions_are_continuous_across_toe(nav):
    """Consecutive ephemerides of one satellite agree at their boundary to a few metres."""
    from ultratight.signals.ephemeris import sat_state
    lst = [x for x in nav.ephemerides[7] if x.healthy]
    for a, b in zip(lst, lst[1:]):
        if b.toe - a.toe != 7200.0:
            continue
        t = 0.5 * (a.toe + b.toe)
        d = np.linalg.norm(sat_state(a, t)[0] - sat_state(b, t)[0])
        assert d < 10.0


def test_wrong_file_type_and_version(rinex_path, tmp_path):
    def glonass(lines):
        lines[0] = lines[0][:20] + "G" + lines[0][21:]
        return lines
    with pytest.raises(NavDataError, match="line 1: field 'file type'"):
        read_rinex_nav(_write_variant(rinex_path, tmp_path, glonass))
    def v4(lines):
        lines[0] = "     4.00" + lines[0][9:]
        return lines
    with pytest.raises(NavDataError, match="version"):
        read_rinex_nav(_write_variant(rinex_path, tmp_path, v4))
