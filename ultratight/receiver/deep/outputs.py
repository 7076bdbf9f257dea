"""Outputs of ``process --mode ultratight``: the SINS-rate navigation solution as CSV / KML / NMEA
(the scalar receiver's writers, :mod:`ultratight.receiver.io.outputs` and :mod:`ultratight.receiver.io.nmea`),
RINEX observations of the ultra-tight channels (:mod:`ultratight.receiver.io.rinex_out`) and the
summary fields (lock-lost channels, bit strategy per channel, navigation figures).

Times: an :class:`ultratight.receiver.deep.recorder.EngineResult` holds seconds since the first sample of
the IF file; the receiver time of ``t`` is the IF start TOW + t (``info["if_file_start"]``) and GPS time
is receiver time - clock bias / c. Layout of the files: docs/process.md, "Ultra-tight outputs".
"""

import json
import math

import numpy as np

from ultratight import __version__
from ultratight.constants import C
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
from ultratight.io_guard import write_h5_atomic
from ultratight.receiver.io.outputs import write_table_csv

NMEA_KML_RATE_HZ = 10.0     # NMEA / KML rows: every SINS row at this rate
RINEX_RATE_HZ = 10.0        # RINEX observation epochs

CSV_COLS = ("t_s", "gps_week", "gps_tow_s", "x_m", "y_m", "z_m", "lat_deg", "lon_deg", "h_m", "ve_mps", "vn_mps",
            "vu_mps", "roll_deg", "pitch_deg", "yaw_deg", "clk_bias_m", "clk_drift_mps", "sigma_e_m", "sigma_n_m",
            "sigma_u_m", "sigma_ve_mps", "sigma_vn_mps", "sigma_vu_mps", "sigma_att_e_deg", "sigma_att_n_deg",
            "sigma_att_u_deg", "sigma_clk_bias_m", "sigma_clk_drift_mps", "integrity")
# the last column: integrity state of the row (0 ok, 1 degraded, 2 lost; receiver.deep.integrity)


def _start(res):
    st = (res.info or {}).get("if_file_start") or {}
    return st.get("week"), st.get("tow_s")


def nav_rows(res):
    """The SINS-rate solution as arrays: dict of (n,) / (n, k) arrays incl. ECEF position/velocity
    and GPS week / time of week (None when the IF start time is unknown)."""
    s = res.sins
    llh = np.asarray(s["llh"], float)
    n = llh.shape[0]
    pos_e = np.empty((n, 3))
    vel_e = np.empty((n, 3))
    for i in range(n):
        pos_e[i] = llh_to_ecef(llh[i, 0], llh[i, 1], llh[i, 2])
        vel_e[i] = np.asarray(dcm_ecef_from_enu(llh[i, 0], llh[i, 1])) @ s["vel_l"][i]
    week, tow0 = _start(res)
    gps = None if tow0 is None else tow0 + s["t_s"] - s["clk"][:, 0] / C
    return {"t_s": s["t_s"], "pos_e": pos_e, "vel_e": vel_e, "llh": llh, "vel_l": s["vel_l"], "euler": s["euler"],
            "clk": s["clk"], "sig_pos": s["sigma_pos_l_m"], "sig_vel": s["sigma_vel_l_mps"],
            "sig_att": s["sigma_att_rad"], "sig_clk": s["sigma_clk"], "week": week, "gps_tow_s": gps,
            "integrity": np.asarray(s.get("integrity_state", np.zeros(n, np.int8)), dtype=int),
            "assisted": list((res.info or {}).get("assisted") or [])}


def write_solution_csv(path, rows):
    """The SINS-rate solution as CSV (columns CSV_COLS; angles in degrees, sigmas 1-sigma)."""
    def values(i):
        return [rows["t_s"][i], rows["week"], None if rows["gps_tow_s"] is None else rows["gps_tow_s"][i],
                *rows["pos_e"][i], math.degrees(rows["llh"][i, 0]), math.degrees(rows["llh"][i, 1]), rows["llh"][i, 2],
                *rows["vel_l"][i], *np.degrees(rows["euler"][i]), *rows["clk"][i], *rows["sig_pos"][i],
                *rows["sig_vel"][i], *np.degrees(rows["sig_att"][i]), *rows["sig_clk"][i], int(rows["integrity"][i])]

    write_table_csv(path, CSV_COLS, (values(i) for i in range(rows["t_s"].shape[0])), digits=12,
                    comment=f"ultratight {__version__} process --mode ultratight: SINS-rate navigation solution"
                            + "".join(f"; ASSISTED: {a}" for a in rows.get("assisted") or ()))


def fix_dicts(res, rows, rate_hz=NMEA_KML_RATE_HZ):
    """Fix dicts (the scalar receiver's layout: t_s, gps_week, gps_tow_s, pos_e, vel_e, llh_deg, DOPs,
    used_prn, sv) of every SINS row at ``rate_hz``; DOPs of the engine's channels from the satellite
    positions at the middle of the run (``info["sat_pos_e"]``; satellites move a few km in a minute)."""
    from ultratight.receiver.scalar.pvt import dops

    t = rows["t_s"]
    if t.size == 0:
        return []
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    step = max(1, int(round(1.0 / (rate_hz * dt))))
    los = _los(res, rows)
    out = []
    for i in range(0, t.size, step):
        d = dops(rows["pos_e"][i].copy(), los[i]) if los is not None and los.shape[1] >= 4 else {}
        out.append({"t_s": float(t[i]), "gps_week": rows["week"],
                    "gps_tow_s": None if rows["gps_tow_s"] is None else float(rows["gps_tow_s"][i]),
                    "pos_e": rows["pos_e"][i], "vel_e": rows["vel_e"][i],
                    "llh_deg": [math.degrees(rows["llh"][i, 0]), math.degrees(rows["llh"][i, 1]),
                                float(rows["llh"][i, 2])],
                    "n_used": len(res.prns), "used_prn": list(res.prns),
                    "pdop": float(d.get("pdop", 0.0)), "hdop": float(d.get("hdop", 0.0)),
                    "vdop": float(d.get("vdop", 0.0)), "sv": []})
    return out


def _los(res, rows):
    """Unit lines of sight (n_rows, n_ch, 3) from the satellite positions the engine logged, or None."""
    sat = (res.info or {}).get("sat_pos_e")
    if sat is None:
        return None
    sat = np.asarray(sat, float)
    d = sat[None, :, :] - rows["pos_e"][:, None, :]
    return d / np.linalg.norm(d, axis=2, keepdims=True)


def lock_lost_channels(res, amp_min=None, window_ms=None):
    """PRNs whose channel lost lock: coasting epochs (signal monitor) or an amplitude estimate below
    the engine's ``amp_min`` (the tight filter's own threshold) for ``lock_window_ms`` consecutive
    epochs after the start-up phase initialisation."""
    from ultratight.receiver.deep.options import MODE_COAST

    opt = (res.info or {}).get("options", {})
    amp_min = float(opt.get("amp_min", 0.15)) if amp_min is None else amp_min
    win = int(opt.get("lock_window_ms", 300)) if window_ms is None else int(window_ms)
    skip = int(opt.get("phase_init_ms", 40)) + 20
    mode = np.asarray(res.mode)
    amp = np.asarray(res.amp)[skip:]
    lost = []
    for c, prn in enumerate(res.prns):
        if np.any(mode[:, c] == MODE_COAST):
            lost.append(int(prn))
            continue
        low = ~(np.abs(amp[:, c]) > amp_min)
        if low.size >= win and np.convolve(low.astype(int), np.ones(win, int), "valid").max() >= win:
            lost.append(int(prn))
    return lost


def bit_strategy(res):
    """{PRN: data-bit strategy}: the engine's per-channel strategy (``info["bits"]``), else its
    wipe-off source mode."""
    per_ch = ((res.info or {}).get("bits") or {}).get("channel_strategy")
    if per_ch:
        return {str(int(p)): str(m) for p, m in zip(res.prns, per_ch)}
    mode = (res.info or {}).get("wipeoff_mode")
    if isinstance(mode, (list, tuple)):
        return {str(int(p)): str(m) for p, m in zip(res.prns, mode)}
    return {str(int(p)): str(mode) for p in res.prns}


def integrity_summary(res):
    """The run's integrity (``info["integrity"]``, receiver.deep.integrity; docs/ultratight.md
    "Integrity"): final state, worst state, first degraded / lost times and the time a lost solution
    stopped the run (s since the first sample of the file), re-initialisations and their times, and
    ``line``: one sentence for the summary. None for a result without the monitor (scalar reference)."""
    integ = (res.info or {}).get("integrity")
    if not integ:
        return None
    out = {k: integ.get(k) for k in ("state", "worst", "first_degraded_s", "first_lost_s", "lost_at_s", "n_reinit")}
    out["reinit_at_s"] = list(integ.get("reinit_at_s") or [])
    if out["state"] == "lost":
        out["line"] = (f"integrity lost at t = {out['lost_at_s']:.1f} s: the navigation solution left the "
                       f"measurements; {out['n_reinit']} re-initialisation(s) from a scalar fix, no solution after "
                       "that time")
    elif out["worst"] != "ok":
        t_bad = out["first_lost_s"] if out["worst"] == "lost" else out["first_degraded_s"]
        out["line"] = (f"integrity {out['state']} at the end (worst {out['worst']} from t = {t_bad:.1f} s; "
                       f"{out['n_reinit']} re-initialisation(s) from a scalar fix)")
    else:
        out["line"] = "integrity ok"
    return out


def nav_summary(res):
    """First / last SINS-rate row and the final 1-sigma (for the --json summary)."""
    s = res.sins
    if not s or len(s["t_s"]) == 0:
        return None
    last = -1
    lat, lon, h = s["llh"][last]
    return {"rows": int(len(s["t_s"])), "t0_s": float(s["t_s"][0]), "t1_s": float(s["t_s"][last]),
            "rate_hz": float(round(1.0 / np.median(np.diff(s["t_s"])), 6)) if len(s["t_s"]) > 1 else None,
            "final_llh": [math.degrees(lat), math.degrees(lon), float(h)],
            "final_vel_enu_mps": [float(v) for v in s["vel_l"][last]],
            "final_euler_deg": [float(v) for v in np.degrees(s["euler"][last])],
            "final_sigma_pos_enu_m": [float(v) for v in s["sigma_pos_l_m"][last]],
            "final_sigma_vel_enu_mps": [float(v) for v in s["sigma_vel_l_mps"][last]]}


def rinex_epochs(res, rate_hz=RINEX_RATE_HZ, code_length=1023.0, chip_rate=1.023e6, wavelength=C / 1575.42e6):
    """Observation epochs of the ultra-tight channels: list of (t_s, [sat dicts]) at ``rate_hz`` in
    receiver time. Code pseudorange ``c (t_rx - t_tx)`` from each channel's transmit time (the
    code-period count of the epoch + the tracked code phase), Doppler from the tracking estimate,
    both interpolated to the common epoch; no carrier phase (not accumulated by the engine)."""
    info = res.info or {}
    n0 = info.get("first_period_count")
    week, tow0 = _start(res)
    if n0 is None or tow0 is None:
        return []
    t = np.asarray(res.t_start, float)
    cp = np.asarray(res.code_phase_chips, float)
    f = np.asarray(res.doppler_hz, float)
    n_ep = t.shape[0]
    T = code_length / chip_rate
    half = 0.5 * code_length
    lost = set(lock_lost_channels(res))
    skip = int(info.get("options", {}).get("phase_init_ms", 40)) + 20
    out = []
    if n_ep <= skip + 2:
        return out
    t_lo = np.nanmax(t[skip]) if np.isfinite(t[skip]).any() else np.nan
    t_hi = np.nanmin(t[-1])
    k0 = math.ceil((tow0 + t_lo) * rate_hz)
    k1 = math.floor((tow0 + t_hi) * rate_hz)
    count, seg = _period_counts(info, n_ep, len(res.prns))
    ttx_ch = []
    for c in range(len(res.prns)):
        frac = np.mod(cp[:, c] + half, code_length) - half
        ttx_ch.append(count[:, c] * T + frac / chip_rate)
    for k in range(k0, k1 + 1):
        t_rx = k / rate_hz
        ts = t_rx - tow0
        sats = []
        for c, prn in enumerate(res.prns):
            if int(prn) in lost:
                continue
            tc = t[:, c]
            j = int(np.searchsorted(tc, ts))
            if j >= n_ep or j - seg[1][j] <= skip or seg[0][j - 1] != seg[0][j]:
                continue
            w = (ts - tc[j - 1]) / (tc[j] - tc[j - 1])
            ttx = ttx_ch[c][j - 1] + w * (ttx_ch[c][j] - ttx_ch[c][j - 1])
            dop = f[j - 1, c] + w * (f[j, c] - f[j - 1, c])
            sats.append({"prn": int(prn), "pr_m": C * (t_rx - ttx), "phase_cycles": float("nan"),
                         "doppler_hz": float(dop), "cn0_dbhz": float("nan"), "lock": False})
        out.append((t_rx, sats))
    return out


def _period_counts(info, n_ep, n_ch):
    """Per epoch row and channel the transmit-time code-period count of the epoch, and per row the
    run it belongs to and its first row (a re-initialised result is several runs one after the other,
    ``info["segments"]``; each run counts from its own ``first_period_count``)."""
    segs = info.get("segments") or [{"first_epoch": 0, "first_period_count": info.get("first_period_count")}]
    count = np.empty((n_ep, n_ch))
    seg_id = np.zeros(n_ep, dtype=int)
    seg_row0 = np.zeros(n_ep, dtype=int)
    for i, sg in enumerate(segs):
        r0 = int(sg["first_epoch"])
        r1 = int(segs[i + 1]["first_epoch"]) if i + 1 < len(segs) else n_ep
        count[r0:r1] = np.asarray(sg["first_period_count"], float)[None, :] + np.arange(r1 - r0)[:, None]
        seg_id[r0:r1] = i
        seg_row0[r0:r1] = r0
    return count, (seg_id, seg_row0)


def write_rinex_obs(path, res, rate_hz=RINEX_RATE_HZ):
    """RINEX 3.04 observations (C1C, D1C) of the ultra-tight channels (see :func:`rinex_epochs`)."""
    from ultratight.receiver.io.rinex_out import RinexObsWriter

    week, _ = _start(res)
    w = RinexObsWriter(path, 1.0 / rate_hz, comments=[
        f"ultratight {__version__} process --mode ultratight ({res.method})",
        # one 60-character COMMENT line per assisted part: its tag, the parenthesis of the summary's line
        *(f"ASSISTED run: {a[a.rfind('(') + 1:-1] if a.endswith(')') else a}"
          for a in (res.info or {}).get("assisted") or ()),
        "C1C: code pseudorange of the ultra-tight channels",
        "D1C: Doppler estimate of the ultra-tight channels",
        "L1C, S1C: not produced by the ultra-tight engine"])
    try:
        n = 0
        for t_rx, sats in rinex_epochs(res, rate_hz):
            w.add_epoch(week, t_rx, sats)
            n += 1
        pos = None
        if res.sins and len(res.sins["t_s"]):
            lat, lon, h = res.sins["llh"][len(res.sins["t_s"]) // 2]
            pos = np.asarray(llh_to_ecef(lat, lon, h))
        w.finish(pos)
    except BaseException:
        w.abort()
        raise
    return n


def write_files(res, csv_path=None, kml_path=None, nmea_path=None, rinex_obs_path=None):
    """The requested files of one ultra-tight run."""
    if not (csv_path or kml_path or nmea_path or rinex_obs_path):
        return
    from ultratight.receiver.io.nmea import DEFAULT_LEAP_S, write_nmea
    from ultratight.receiver.io.outputs import write_kml

    rows = nav_rows(res)
    if csv_path:
        write_solution_csv(csv_path, rows)
    if kml_path or nmea_path:
        fixes = fix_dicts(res, rows)
        opts = {"mode": "ultratight", "method": res.method, "startup": (res.info or {}).get("startup_source"),
                **({"ASSISTED": " + ".join(rows["assisted"])} if rows["assisted"] else {})}
        if kml_path:
            write_kml(kml_path, fixes, name="ultratight ultra-tight track", options=opts)
        if nmea_path:
            write_nmea(nmea_path, fixes, leap_s=DEFAULT_LEAP_S, options=opts)
    if rinex_obs_path:
        write_rinex_obs(rinex_obs_path, res)


def write_result_h5(path, res, extra_attrs=None):
    """Write an :class:`EngineResult` to HDF5 (built in memory, written under a unique temporary
    name, then renamed; schema in docs/ultratight.md). Disk errors raise OutputError."""

    def build(f):
        f.attrs["schema"] = "ultratight engine result v1 (docs/ultratight.md)"
        f.attrs["version"] = __version__
        f.attrs["method"] = res.method
        f.attrs["prn"] = np.asarray(res.prns, dtype=np.int64)
        f.attrs["runtime_s"] = float(res.runtime_s)
        f.attrs["duration_s"] = float(res.duration_s)
        f.attrs["info_json"] = json.dumps(res.info, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
        atm = (res.info or {}).get("atmosphere")
        if atm:
            f.attrs["atmosphere_json"] = json.dumps(atm)       # the receiver's model (docs/ultratight.md)
        for k, v in (extra_attrs or {}).items():
            f.attrs[k] = v
        for k, v in (res.sins or {}).items():
            f.create_dataset(f"sins/{k}", data=np.asarray(v), compression="gzip", compression_opts=1, shuffle=True)
        for k, v in (("t_start_s", res.t_start), ("doppler_hz", res.doppler_hz),
                     ("code_phase_chips", res.code_phase_chips), ("amplitude", res.amp), ("mode", res.mode),
                     ("nav_t_s", res.nav_t), ("nav_pos_e", res.nav_pos_e), ("nav_vel_e", res.nav_vel_e),
                     ("nav_clk", res.nav_clk), ("nav_sigma_doppler_hz", res.nav_sigma_doppler_hz)):
            f.create_dataset(k, data=np.asarray(v), compression="gzip", compression_opts=1, shuffle=True)
        for k, v in (getattr(res, "nav_integrity", None) or {}).items():
            f.create_dataset(f"integrity/{k}", data=np.asarray(v), compression="gzip", compression_opts=1)
        if getattr(res, "bit_source", None) is not None:
            f.create_dataset("bit_source", data=np.asarray(res.bit_source), compression="gzip", compression_opts=1)

    return write_h5_atomic(path, build)
