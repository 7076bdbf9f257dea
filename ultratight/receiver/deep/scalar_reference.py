"""The scenario's ``scalar`` method: the scalar tracking bank (FLL-assisted PLL, DLL;
:class:`ultratight.receiver.dsp.tracking.ScalarTracker`, no INS) over the IF block stream, started from
the same hot-start predictions as the ultra-tight methods — the reference the paper's tables put
beside them. The engine hands a ``scalar`` method spec here (:mod:`ultratight.receiver.deep.methods`)."""

import time

import numpy as np

from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
from ultratight.receiver.dsp.blockstream import BlockStream
from ultratight.receiver.deep.recorder import EngineResult
from ultratight.receiver.deep.startup import predict_channels
from ultratight.receiver.dsp.tracking import ScalarTracker
from ultratight.receiver.dsp.tracking_layout import REC_F_NAMES, REC_I_NAMES
from ultratight.signals.signal import GPS_L1CA


def run_scalar(src, prns, ephs, week, tow0, init, duration_s=None, block_ms=100):
    """The scalar tracking bank (:class:`ultratight.receiver.dsp.tracking.ScalarTracker`, no INS) over the
    IF block stream from the same hot-start predictions as the ultra-tight methods; returns an
    EngineResult-like record of the per-epoch NCO Doppler and code phase."""
    t0 = time.perf_counter()
    n_ch = len(prns)
    fs = src.fs_hz
    lat, lon, h = init["llh"]
    pos = np.array(llh_to_ecef(lat, lon, h))
    vel = dcm_ecef_from_enu(lat, lon) @ np.asarray(init["vel_l"])
    pr = predict_channels(ephs, prns, week, tow0, pos, vel, init["clk_bias_m"], init["clk_drift_mps"])
    trk = ScalarTracker(n_ch, fs, src.if_hz, src.is_complex, max_rows=block_ms + 8, signal=GPS_L1CA)
    for ch, prn in enumerate(prns):
        trk.start_channel(ch, prn, pr["code_phase_chips"][ch], pr["doppler_hz"][ch], 0, 20.0)
    dur = src.duration_s if duration_s is None else min(duration_s, src.duration_s)
    n_total = int(dur * fs)
    blk = int(round(block_ms * 1e-3 * fs))
    i_cp, i_f = REC_F_NAMES.index("code_phase_chips"), REC_F_NAMES.index("doppler_hz")
    i_s = REC_I_NAMES.index("sample_index")
    rows_t, rows_f, rows_c = [[] for _ in range(n_ch)], [[] for _ in range(n_ch)], [[] for _ in range(n_ch)]
    for rf, ri, nr in trk.track_aligned(BlockStream(src, blk, sigma_stop=n_total), n_total):
        for ch in range(n_ch):
            k = nr[ch]
            rows_t[ch].append(ri[ch, :k, i_s] / fs)
            rows_f[ch].append(rf[ch, :k, i_f])
            rows_c[ch].append(rf[ch, :k, i_cp])
    n = min(sum(len(x) for x in rows_t[ch]) for ch in range(n_ch))
    cat = lambda rows: np.stack([np.concatenate(r)[:n] for r in rows], axis=1)  # noqa: E731
    t = cat(rows_t)
    empty = np.zeros((0, 3))
    return EngineResult(method="scalar", prns=list(prns), t_start=t, doppler_hz=cat(rows_f),
                        code_phase_chips=np.mod(cat(rows_c), float(GPS_L1CA.code_length)), amp=np.full(t.shape, np.nan),
                        mode=np.zeros(t.shape, dtype=np.int8), nav_t=np.zeros(0), nav_pos_e=empty,
                        nav_vel_e=empty, nav_clk=np.zeros((0, 2)), nav_sigma_doppler_hz=np.zeros((0, n_ch)),
                        runtime_s=time.perf_counter() - t0, duration_s=n * GPS_L1CA.code_period_s,
                        info={"pipeline": "receiver.dsp.tracking ScalarTracker (FLL-assisted PLL, DLL), no INS"})
