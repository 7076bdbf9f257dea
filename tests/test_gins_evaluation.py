"""The outage evaluation (ultratight.fusion.gins.evaluation) on closed-form cases: windows from the
command-line forms, and drift / RMS / 3σ figures of a solution built as the reference plus known
ENU offsets."""

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.fusion.gins import evaluation as ev
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh, llh_to_ecef
from ultratight.signals.observations import GnssFixes, gps_seconds

WEEK = 2381


def _offset(llh, enu):
    p = np.asarray(llh_to_ecef(*llh)) + dcm_ecef_from_enu(llh[0], llh[1]) @ np.asarray(enu, float)
    return ecef_to_llh(p)


def test_outage_flags_parse_and_refuse():
    assert ev.parse_outage("408664.75:14.75") == (408664.75, 14.75)
    assert ev.parse_outages_every("180:60") == (180.0, 60.0)
    for bad in ("1:2:3", "a:1", "10:-1", "700000:5", "nan:1"):
        with pytest.raises(ConfigError, match="--outage"):
            ev.parse_outage(bad)
    with pytest.raises(ConfigError, match="shorter than EVERY"):
        ev.parse_outages_every("60:60")


def test_windows_fall_on_the_data_week_and_every_form_fits_inside():
    t0, t1 = gps_seconds(WEEK, 408600.0), gps_seconds(WEEK, 408734.0)
    w = ev.outage_windows(t0, t1, outages=[(408710.0, 14.5), (408664.75, 14.75)])
    assert w == [(gps_seconds(WEEK, 408664.75), gps_seconds(WEEK, 408679.5)),
                 (gps_seconds(WEEK, 408710.0), gps_seconds(WEEK, 408724.5))]
    w = ev.outage_windows(t0, t0 + 700.0, every=(180.0, 60.0))
    assert [(a - t0, b - t0) for a, b in w] == [(180.0, 240.0), (360.0, 420.0), (540.0, 600.0)]
    with pytest.raises(ConfigError, match="does not overlap"):
        ev.outage_windows(t0, t1, outages=[(1000.0, 10.0)])
    with pytest.raises(ConfigError, match="overlap"):
        ev.outage_windows(t0, t1, outages=[(408650.0, 20.0), (408660.0, 5.0)])
    with pytest.raises(ConfigError, match="no window fits"):
        ev.outage_windows(t0, t1, every=(180.0, 60.0))


def test_drift_rms_and_3sigma_of_known_offsets():
    llh0 = np.array([np.radians(40.0967), np.radians(-105.1472), 1601.0])
    t = gps_seconds(WEEK, 408600.0) + np.arange(0.0, 100.0, 0.01)       # solution at 100 Hz
    tr = gps_seconds(WEEK, 408600.0) + np.arange(0.0, 100.0, 0.25)      # reference at 4 Hz
    ref_llh = np.array([_offset(llh0, [0.5 * k, 0.1 * k, 0.0]) for k in range(tr.size)])
    q = np.ones(tr.size, int)
    q[10:20] = 2                                                        # float epochs do not count
    ref = GnssFixes(tr, ref_llh, np.full((tr.size, 3), np.nan), np.full((tr.size, 3), np.nan),
                    np.full((tr.size, 3), np.nan), q)
    # the solution: the reference track, plus a drift growing linearly inside the windows
    windows = [(tr[0] + 20.0, tr[0] + 30.0), (tr[0] + 60.0, tr[0] + 70.0)]
    grow = np.zeros((t.size, 3))
    for (a, b), (dh, dv) in zip(windows, [(3.0, 1.0), (4.0, -2.0)]):
        m = (t >= a) & (t <= b)
        frac = (t[m] - a) / (b - a)
        grow[m] = np.column_stack([0.6 * dh * frac, 0.8 * dh * frac, dv * frac])
    ref_pos = np.array([np.interp(t, tr, ref_llh[:, j]) for j in range(3)]).T
    llh = np.array([_offset(ref_pos[i], grow[i]) for i in range(t.size)])
    sigma = np.full((t.size, 3), 0.5)
    out, series = ev.evaluate(t, llh, sigma, ref, windows)
    assert out["reference_fixed_epochs"] == int(np.sum(q == 1))
    recs = out["outages"]
    assert [r["max_h_m"] for r in recs] == pytest.approx([3.0, 4.0], abs=1e-3)
    assert [r["max_v_m"] for r in recs] == pytest.approx([1.0, 2.0], abs=1e-3)
    assert out["outage_max_h_rms_m"] == pytest.approx(np.sqrt((9.0 + 16.0) / 2), abs=1e-3)
    assert out["outage_max_v_rms_m"] == pytest.approx(np.sqrt((1.0 + 4.0) / 2), abs=1e-3)
    assert out["rms_outside_h_m"] == pytest.approx(0.0, abs=1e-3)
    # inside 3σ = 1.5 m on every axis: east 0.6·3·f, north 0.8·3·f ≤ 1.5 while f ≤ 0.625 (window 1), ...
    inside = series["in_outage"]
    expect = np.all(np.abs(series["err_enu"][inside]) <= 1.5, axis=1).mean()
    assert out["within_3sigma"] == pytest.approx(expect)
    assert 0.2 < out["within_3sigma"] < 0.8
