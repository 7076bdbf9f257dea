"""Tracking-error metrics of Zhao et al. 2014, §3 (Table 3 / Table 4) against the generator's truth.

Tracking error of a channel at an epoch = the receiver's *estimate* minus the truth at the
same instant:

* Doppler estimate  = carrier NCO frequency (minus IF) + prefilter frequency-error estimate
  ``df/(2 pi)`` — the value the tracking loop believes the incoming Doppler is;
* code-phase estimate = code NCO phase + prefilter code-error estimate ``dtau``.

The code estimate refers to the start of the 1 ms integration, the Doppler estimate to its
middle (see :func:`tracking_errors`); the truth, which the generator logs on its own 1 ms
grid, is interpolated to those instants (seconds since the first sample).  Code phases are unwrapped
before interpolation and the difference is wrapped to (-511.5, 511.5] chips.

Loss of lock (per channel): the 20 ms (one LNAV bit) running mean of the Doppler error
exceeds ``LOCK_DOPPLER_HZ`` in magnitude or that of the code error exceeds
``LOCK_CODE_CHIPS``; the time of the first such window is reported.  A method has
*diverged* in a segment (the paper's "\\" entries) when any channel has lost lock by
the end of that segment.
"""

import numpy as np

from ultratight.signals.signal import GPS_L1CA

SEGMENTS_S = ((0.0, 20.0), (20.0, 40.0), (40.0, 60.0))
LOCK_DOPPLER_HZ = 10.0        # 20 ms mean |Doppler error| above this -> lock lost
LOCK_CODE_CHIPS = 0.5         # 20 ms mean |code error| above this -> lock lost
LOCK_WINDOW_S = 0.020

# Zhao et al. 2014, Table 3 (one channel, #4) and Table 4 (run time, s).  None = diverged ("\").
PAPER_TABLE3 = {
    "pb-kf-utc": {"doppler_rms_hz": [1.8706, 1.3339, None], "code_rms_chips": [0.0182, 0.0271, 0.2379]},
    "dlb-ukf": {"doppler_rms_hz": [0.9153, 1.0574, None], "code_rms_chips": [0.0128, 0.0277, 0.2413]},
    "dlb-ckf": {"doppler_rms_hz": [0.5345, 0.7375, 1.5053], "code_rms_chips": [0.0123, 0.0245, 0.0474]},
    "dlb-rackf": {"doppler_rms_hz": [0.1125, 0.1220, 0.2455], "code_rms_chips": [0.0091, 0.0060, 0.0077]},
}
PAPER_TABLE4_S = {"pb-kf-utc": 0.083102, "dlb-ukf": 1.835400, "dlb-ckf": 0.723903, "dlb-rackf": 0.954322}


def wrap_chips(d, signal=GPS_L1CA):
    """Wrap a code-phase difference to [-L/2, L/2) (L: the signal's code length, 1023 for C/A)."""
    n_code = signal.code_length
    return (np.asarray(d) + 0.5 * n_code) % n_code - 0.5 * n_code


def unwrap_chips(t, cp, signal=GPS_L1CA):
    """Continuous code phase (chips) from a series modulo the code length sampled at times ``t`` (n,).

    Between samples the code advances by about ``f_chip * dt`` chips (rows one code period apart
    advance by a whole period), so the unwrapping removes the nominal advance first, wraps the
    remainder to +-L/2 chips and adds the nominal advance back.  ``cp`` is (n,) or (n, n_ch).
    """
    n_code = signal.code_length
    t = np.asarray(t, dtype=float)
    cp = np.asarray(cp, dtype=float)
    nominal = signal.chip_rate_hz * np.diff(t)
    if cp.ndim == 2:
        nominal = nominal[:, None]
    d = np.diff(cp, axis=0) - nominal
    d = (d + 0.5 * n_code) % n_code - 0.5 * n_code
    out = np.empty_like(cp)
    out[0] = cp[0]
    out[1:] = cp[0] + np.cumsum(d + nominal, axis=0)
    return out


def interp_truth(t_truth, y_truth, t_query):
    """Per-channel linear interpolation of truth ``y_truth`` (n_t, n_ch) at ``t_query`` (n_q, n_ch).

    Queries outside the truth time span give NaN (never extrapolated).
    """
    t_truth = np.asarray(t_truth, dtype=float)
    y_truth = np.asarray(y_truth, dtype=float)
    t_query = np.asarray(t_query, dtype=float)
    out = np.full(t_query.shape, np.nan)
    for ch in range(t_query.shape[1]):
        tq = t_query[:, ch]
        ok = np.isfinite(tq) & (tq >= t_truth[0]) & (tq <= t_truth[-1])
        out[ok, ch] = np.interp(tq[ok], t_truth, y_truth[:, ch])
    return out


def tracking_errors(t_start, doppler_est_hz, code_est_chips, t_truth, doppler_truth_hz, code_truth_chips,
                    doppler_offset_s=0.5e-3, code_truth_unwrapped=None):
    """Doppler (Hz) and code-phase (chips) tracking errors at the estimate epochs.

    ``t_start``, ``doppler_est_hz``, ``code_est_chips``: (n_ep, n_ch) estimates and the start
    times of their integrations (s since the first sample); ``t_truth`` (n_t,), ``*_truth``
    (n_t, n_ch) from the truth file.  The code phase is compared at the interval start (where
    the code NCO phase and the prefilter's code error refer); the Doppler estimate (constant
    NCO frequency + the prefilter's frequency error, which the I/Q of eq. 3 measure as the
    interval mean) is compared with the truth at ``t_start + doppler_offset_s`` (the middle of
    the 1 ms interval: at 20 g the Doppler moves ~0.5 Hz within half a millisecond).
    ``code_truth_unwrapped``: :func:`unwrap_chips` of the truth's code phase when the caller has it
    (one truth, several methods).
    """
    d_true = interp_truth(t_truth, doppler_truth_hz, np.asarray(t_start) + doppler_offset_s)
    if code_truth_unwrapped is None:
        code_truth_unwrapped = unwrap_chips(t_truth, code_truth_chips)
    cp_true = interp_truth(t_truth, code_truth_unwrapped, t_start)
    d_err = np.asarray(doppler_est_hz, dtype=float) - d_true
    c_err = wrap_chips(np.asarray(code_est_chips, dtype=float) - cp_true)
    return d_err, c_err


def segments_for(duration_s, segments=SEGMENTS_S):
    """The paper's segments clipped to a run of ``duration_s`` (segments past the end are kept
    with zero length so tables keep three columns)."""
    return tuple((a, min(b, max(a, duration_s))) for a, b in segments)


def segment_rms(t, err, segments=SEGMENTS_S, channel=None):
    """RMS of ``err`` (n_ep, n_ch) in each segment [a, b): over all channels, or one channel.

    Returns an (n_seg,) array (NaN for an empty segment).  Non-finite errors are ignored.
    """
    t = np.asarray(t, dtype=float)
    err = np.asarray(err, dtype=float)
    if channel is not None:
        t = t[:, channel:channel + 1]
        err = err[:, channel:channel + 1]
    out = np.full(len(segments), np.nan)
    finite = np.isfinite(err)
    for i, (a, b) in enumerate(segments):
        m = (t >= a) & (t < b) & finite
        if m.any():
            out[i] = float(np.sqrt(np.mean(err[m] ** 2)))
    return out


def _running_mean(x, n):
    """Trailing running mean over n samples along axis 0 (NaN-aware: NaN treated as 0 weight)."""
    x = np.asarray(x, dtype=float)
    ok = np.isfinite(x)
    xs = np.where(ok, x, 0.0)
    c = np.cumsum(np.vstack([np.zeros((1,) + x.shape[1:]), xs]), axis=0)
    k = np.cumsum(np.vstack([np.zeros((1,) + x.shape[1:]), ok.astype(float)]), axis=0)
    n = max(1, min(n, x.shape[0]))
    s = c[n:] - c[:-n]
    w = k[n:] - k[:-n]
    with np.errstate(invalid="ignore", divide="ignore"):
        m = s / w
    head = np.full((n - 1,) + x.shape[1:], np.nan)
    return np.vstack([head, m])


def loss_of_lock(t, doppler_err, code_err, epoch_s=1e-3, doppler_hz=LOCK_DOPPLER_HZ,
                 code_chips=LOCK_CODE_CHIPS, window_s=LOCK_WINDOW_S):
    """Per channel time (s) of the first loss of lock, NaN when the channel kept lock."""
    n = max(1, int(round(window_s / epoch_s)))
    md = np.abs(_running_mean(doppler_err, n))
    mc = np.abs(_running_mean(code_err, n))
    bad = (md > doppler_hz) | (mc > code_chips)
    t = np.asarray(t, dtype=float)
    out = np.full(bad.shape[1], np.nan)
    for ch in range(bad.shape[1]):
        idx = np.flatnonzero(bad[:, ch])
        if idx.size:
            out[ch] = t[idx[0], ch]
    return out


def summarize(t, doppler_err, code_err, segments=SEGMENTS_S, channel=0, epoch_s=1e-3):
    """All paper metrics of one run as a JSON-ready dict."""
    lost = loss_of_lock(t, doppler_err, code_err, epoch_s=epoch_s)
    seg_div = [bool(np.any(lost < b)) for (_, b) in segments]
    return {
        "doppler_rms_hz": segment_rms(t, doppler_err, segments).tolist(),
        "code_rms_chips": segment_rms(t, code_err, segments).tolist(),
        "doppler_rms_hz_channel": segment_rms(t, doppler_err, segments, channel).tolist(),
        "code_rms_chips_channel": segment_rms(t, code_err, segments, channel).tolist(),
        "lock_lost_time_s": [None if not np.isfinite(x) else float(x) for x in lost],
        "lock_lost_channels": int(np.sum(np.isfinite(lost))),
        "segment_diverged": seg_div,
        "diverged": bool(any(seg_div)),
    }


def _fmt(v, nd, missing="-"):
    if v is None or not np.isfinite(v):
        return missing.rjust(8)
    return f"{v:8.{nd}f}"


def _num(v):
    return float("nan") if v is None else float(v)


def format_tables(method_results, segments=SEGMENTS_S, paper=True):
    """Text tables (ours beside the paper's Table 3 / Table 4) for people.

    ``method_results``: {method: {"doppler_rms_hz": [..], "code_rms_chips": [..],
    "segment_diverged": [..], "runtime_s": float, "realtime_factor": float}}; the real-time
    factor is wall-clock seconds per signal second (< 1: faster than real time).
    """
    seg_lbl = "  ".join(f"{a:g}-{b:g}s".rjust(8) for a, b in segments)
    lines = ["Doppler tracking error RMS (Hz), all channels" + ("  | paper Table 3 (one channel)" if paper else ""),
             f"{'method':12s}{seg_lbl}" + (f"  | {seg_lbl}" if paper else "")]
    for key, nd in (("doppler_rms_hz", 4), ("code_rms_chips", 4)):
        if key == "code_rms_chips":
            lines += ["", "Code phase tracking error RMS (chips), all channels"
                      + ("  | paper Table 3 (one channel)" if paper else ""),
                      f"{'method':12s}{seg_lbl}" + (f"  | {seg_lbl}" if paper else "")]
        for m, r in method_results.items():
            div = r.get("segment_diverged", [False] * len(segments))
            vals = [("\\" if div[i] else "-").rjust(8) if not np.isfinite(_num(r[key][i])) else
                    (_fmt(r[key][i], nd) + ("\\" if div[i] else "")) for i in range(len(segments))]
            row = f"{m:12s}" + "  ".join(vals)
            if paper and m in PAPER_TABLE3:
                row += "  | " + "  ".join(_fmt(v, nd, "\\") for v in PAPER_TABLE3[m][key])
            lines.append(row)
    lines += ["", "A trailing '\\' marks a segment in which some channel lost lock ('\\' alone: no value).",
              "", "Lock and run time" + ("  | paper Table 4 (s)" if paper else ""),
              f"{'method':12s}{'lost ch':>8s}{'run s':>9s}{'RT factor':>11s}"]
    for m, r in method_results.items():
        row = (f"{m:12s}{r.get('lock_lost_channels', 0):8d}{r.get('runtime_s', float('nan')):9.2f}"
               f"{r.get('realtime_factor', float('nan')):11.3f}")
        if paper and m in PAPER_TABLE4_S:
            row += f"  | {PAPER_TABLE4_S[m]:.4f}"
        lines.append(row)
    return "\n".join(lines)


def plot_envelope(t, y, buckets=1024):
    """``(t, y)`` thinned for drawing a line: per bucket of consecutive points, its first, smallest,
    largest and last point, in time order (the M4 aggregation of Jugel et al. 2014, "M4: a
    visualization-oriented time series data aggregation", PVLDB 7(10)) — drawn as a line, it covers
    the pixels the whole series covers when there are at least as many buckets as pixel columns
    (an 8-inch figure at 110 dpi has fewer than 900).
    A bucket holding non-finite values also keeps its first one (the line's gap stays); series of
    fewer than three points per bucket are returned unchanged."""
    t = np.asarray(t)
    y = np.asarray(y, dtype=float)
    n = y.size
    k = -(-n // int(buckets))
    if k < 3:
        return t, y
    m = (n // k) * k
    yb = y[:m].reshape(-1, k)
    bad = ~np.isfinite(yb)
    base = np.arange(0, m, k)
    idx = [base, base + k - 1, base + np.where(bad, np.inf, yb).argmin(axis=1),
           base + np.where(bad, -np.inf, yb).argmax(axis=1), np.arange(m, n)]
    has_bad = bad.any(axis=1)
    if has_bad.any():
        idx.append((base + bad.argmax(axis=1))[has_bad])
    sel = np.unique(np.concatenate(idx))
    return t[sel], y[sel]
