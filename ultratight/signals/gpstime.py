"""GPS time: week / time-of-week arithmetic and week-rollover handling.

GPS time is kept as (full week number, seconds of week).  Times inside the
navigation algorithms are seconds of week (TOW); differences between two TOWs
are wrapped into [-302400, 302400) s as IS-GPS-200D §20.3.3.4.3 prescribes for
``tk`` ("if tk > 302400, subtract 604800; if tk < -302400, add 604800").
"""

import datetime

import numpy as np

from ultratight.constants import GPS_WEEK_ROLLOVER, SECONDS_PER_WEEK

HALF_WEEK = SECONDS_PER_WEEK / 2.0


def wrap_week_diff(dt):
    """Wrap a time difference (s, scalar or array) into [-302400, 302400)."""
    dt = np.asarray(dt, dtype=np.float64)
    out = dt - SECONDS_PER_WEEK * np.floor((dt + HALF_WEEK) / SECONDS_PER_WEEK)
    return out if out.ndim else float(out)


def normalize(week, tow_s):
    """Bring (week, tow) into the canonical range 0 <= tow < 604800; returns (int week, float tow)."""
    w_off = np.floor(tow_s / SECONDS_PER_WEEK)
    return int(week) + int(w_off), float(tow_s - w_off * SECONDS_PER_WEEK)


def to_seconds(week, tow_s):
    """Continuous GPS seconds since the GPS epoch (1980-01-06 00:00:00)."""
    return np.asarray(week, dtype=np.float64) * SECONDS_PER_WEEK + np.asarray(tow_s, dtype=np.float64)


def from_seconds(t_s):
    """Continuous GPS seconds -> (int week, float tow)."""
    week = int(np.floor(t_s / SECONDS_PER_WEEK))
    return week, float(t_s - week * SECONDS_PER_WEEK)


def full_week(week_mod, ref_week):
    """Resolve a truncated week number (10-bit LNAV WN) to the full week closest to ``ref_week``.

    ``week_mod`` is the week modulo 1024 (as broadcast in subframe 1); ``ref_week`` is any full
    week known to lie within ±512 weeks of the true one (e.g. from the system clock or a
    scenario).  Returns the full week ``w`` with ``w % 1024 == week_mod`` nearest to ``ref_week``.
    """
    week_mod = int(week_mod) % GPS_WEEK_ROLLOVER
    base = int(ref_week) - int(ref_week) % GPS_WEEK_ROLLOVER
    best = None
    for cand in (base - GPS_WEEK_ROLLOVER + week_mod, base + week_mod, base + GPS_WEEK_ROLLOVER + week_mod):
        if best is None or abs(cand - ref_week) < abs(best - ref_week):
            best = cand
    return best


def week_of_nearby(ref_week, ref_tow_s, tow_s):
    """Full week of a TOW ``tow_s`` that lies within half a week of (ref_week, ref_tow_s)."""
    dt = wrap_week_diff(tow_s - ref_tow_s)
    w, _ = normalize(ref_week, ref_tow_s + dt)
    return w


def datetime_to_gps(year, month, day, hour=0, minute=0, second=0.0):
    """Calendar date/time *in GPS time* (no leap seconds applied) -> (week, tow)."""

    epoch = datetime.datetime(1980, 1, 6)
    d = datetime.datetime(int(year), int(month), int(day), int(hour), int(minute)) - epoch
    t = d.days * 86400.0 + d.seconds + float(second)
    return from_seconds(t)
