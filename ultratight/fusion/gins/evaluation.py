"""Outage evaluation of an INS/GNSS solution against a reference, the way the field reports it.

Protocol (Tang et al. 2023, KF-GINS, Table 2; Niu et al. for OB_GINS): GNSS is removed over chosen
windows; for each window the *largest* horizontal and the largest vertical error of the solution
against the reference inside the window are taken ("drift"), and their RMS over the windows is the
figure of merit.  Besides: the horizontal RMS outside the windows, and the fraction of the
reference epochs inside windows whose error lies within the solution's own 3σ (each of east, north,
up inside ``3 σ`` of that axis) — whether the filter knows how wrong it is.

Windows
-------
* ``--outage START:LENGTH`` — START in GPS seconds of week (the inputs' time scale), LENGTH in s;
  repeatable.  The week is the one of the data (the first IMU sample), so a window given as seconds
  of week falls on the data's week.
* ``--outages EVERY:LENGTH`` — a window of LENGTH s every EVERY s, the first EVERY s after the
  filter's start, as long as the window ends before the last GNSS epoch.

Reference: an RTKLIB solution; only its fixed epochs (Q = 1) count.  The solution is interpolated
linearly in time (IMU rate) to the reference epochs; errors are ENU at the reference point, metres.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from ultratight.errors import ConfigError
from ultratight.fusion.gins.options import in_windows
from ultratight.ins.earth import dcm_ecef_from_enu_vec, llh_to_ecef_batch
from ultratight.signals.observations import Q_FIX, SECONDS_PER_WEEK, week_tow


def _pair(text, flag, names):
    parts = str(text).split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a, b = float(parts[0]), float(parts[1])
    except ValueError:
        raise ConfigError(f"{flag} {text!r}: expected {names[0]}:{names[1]} (two numbers, seconds)") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise ConfigError(f"{flag} {text!r}: {names[0]} and {names[1]} must be finite")
    if b <= 0.0:
        raise ConfigError(f"{flag} {text!r}: {names[1]} must be positive")
    return a, b


def parse_outage(text):
    """``START:LENGTH`` -> (start_tow_s, length_s); START in [0, 604800)."""
    start, length = _pair(text, "--outage", ("START", "LENGTH"))
    if not 0.0 <= start < SECONDS_PER_WEEK:
        raise ConfigError(f"--outage {text!r}: START is GPS seconds of week, in [0, 604800)")
    return start, length


def parse_outages_every(text):
    """``EVERY:LENGTH`` -> (every_s, length_s) with LENGTH < EVERY."""
    every, length = _pair(text, "--outages", ("EVERY", "LENGTH"))
    if length >= every:
        raise ConfigError(f"--outages {text!r}: LENGTH must be shorter than EVERY (GNSS between the outages)")
    return every, length


def outage_windows(t_first, t_last, outages=(), every=None):
    """Windows ``[(t0, t1), ...]`` in continuous GPS seconds, sorted.

    ``outages``: (start_tow_s, length_s) pairs, placed in the week of ``t_first``; ``every``:
    (every_s, length_s) from :func:`parse_outages_every`; ``t_first``/``t_last``: the filter's start and
    the last GNSS epoch.  ConfigError when a window lies outside the data or windows overlap."""
    week, _ = week_tow(t_first)
    wins = []
    for start, length in outages:
        t0 = float(week) * SECONDS_PER_WEEK + start
        if t0 < t_first - 0.5 * SECONDS_PER_WEEK:
            t0 += SECONDS_PER_WEEK
        if t0 + length <= t_first or t0 >= t_last:
            raise ConfigError(f"--outage {start:g}:{length:g}: the window does not overlap the data "
                              f"(seconds of week {week_tow(t_first)[1]:.2f} to {week_tow(t_last)[1]:.2f})")
        wins.append((t0, t0 + length))
    if every is not None:
        e, length = every
        t0 = t_first + e
        while t0 + length <= t_last:
            wins.append((t0, t0 + length))
            t0 += e
        if not wins:
            raise ConfigError(f"--outages {e:g}:{length:g}: no window fits between the filter's start and the "
                              f"last GNSS epoch ({t_last - t_first:.1f} s)")
    wins.sort()
    for (a0, a1), (b0, _) in itertools.pairwise(wins):
        if b0 < a1:
            raise ConfigError(f"outage windows overlap (seconds of week {week_tow(a0)[1]:.2f}–"
                              f"{week_tow(a1)[1]:.2f} and {week_tow(b0)[1]:.2f})")
    return wins


def enu_errors(llh_sol, llh_ref):
    """(n, 3) ENU error (solution minus reference) at the reference points, m."""
    d = llh_to_ecef_batch(np.asarray(llh_sol, float)) - llh_to_ecef_batch(np.asarray(llh_ref, float))
    c = dcm_ecef_from_enu_vec(llh_ref[:, 0], llh_ref[:, 1])      # (n, 3, 3) ECEF <- ENU
    return np.einsum("nji,nj->ni", c, d)


def _interp(t_out, t, y):
    return np.column_stack([np.interp(t_out, t, y[:, j]) for j in range(y.shape[1])])


def evaluate(t, llh, sigma_enu, ref, windows):
    """Errors of a solution (``t``, ``llh`` at the reference point, ``sigma_enu`` 1σ) against the fixed
    epochs of ``ref`` (a GnssFixes) -> dict (the ``evaluation`` block of the JSON summary) and the
    per-epoch arrays (``series``: t, err_enu, sigma_enu, in_outage) for plots."""
    keep = (ref.quality == Q_FIX) & (ref.t >= t[0]) & (ref.t <= t[-1])
    if not np.any(keep):
        raise ConfigError("--reference: no fixed (Q = 1) epoch lies inside the solution's time span")
    rt = ref.t[keep]
    err = enu_errors(_interp(rt, t, llh), ref.llh[keep])
    sig = _interp(rt, t, sigma_enu)
    inside = in_windows(rt, windows)
    h = np.hypot(err[:, 0], err[:, 1])
    records = []
    for t0, t1 in windows:
        m = (rt >= t0) & (rt <= t1)
        rec = {"start_tow_s": float(week_tow(t0)[1]), "length_s": float(t1 - t0), "reference_epochs": int(m.sum())}
        if m.any():
            within = np.all(np.abs(err[m]) <= 3.0 * sig[m], axis=1)
            rec.update(max_h_m=float(h[m].max()), max_v_m=float(np.abs(err[m, 2]).max()),
                       end_h_m=float(h[m][-1]), within_3sigma=float(within.mean()))
        records.append(rec)
    hit = [r for r in records if "max_h_m" in r]
    out = {"reference_fixed_epochs": int(keep.sum()), "outages": records,
           "outage_max_h_rms_m": _rms([r["max_h_m"] for r in hit]),
           "outage_max_v_rms_m": _rms([r["max_v_m"] for r in hit]),
           "rms_outside_h_m": _rms(h[~inside]), "rms_outside_v_m": _rms(err[~inside, 2]),
           "within_3sigma": (float(np.all(np.abs(err[inside]) <= 3.0 * sig[inside], axis=1).mean())
                             if inside.any() else None)}
    series = {"t": rt, "err_enu": err, "sigma_enu": sig, "in_outage": inside}
    return out, series


def _rms(x):
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x ** 2))) if x.size else None
