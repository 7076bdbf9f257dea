"""Outputs of the scalar receiver: :class:`Recorder` writes a run as it comes (the HDF5 stream with
its schema in docs/process.md, the RINEX observation file, the in-memory epoch series);
:func:`finish_hdf5` closes the HDF5 output and :func:`write_exchange_files` writes the RINEX
observation / navigation and NMEA files at the end of a complete run.
"""

from dataclasses import asdict

import numpy as np

from ultratight import __version__
from ultratight.receiver.dsp.tracking_layout import (R_CN0, R_CODE_PHASE, R_DOPP, REC_F_NAMES, REC_I_NAMES, RI_EPOCH,
                                                     RI_FLAGS, RI_MODE, RI_PTR)
from ultratight.receiver.io.nmea import DEFAULT_LEAP_S, write_nmea
from ultratight.receiver.io.rinex_out import RinexObsWriter, write_rinex_nav

_F64_FIELDS = ("code_phase_chips", "code_rate_cps", "carr_acc_cycles", "doppler_hz")
_SMALL_INT = {"n_samples": np.int32, "mode": np.int8, "flags": np.int8}
TRACK_DTYPE = np.dtype([(n, _SMALL_INT.get(n, np.int64)) for n in REC_I_NAMES] +
                       [(n, np.float64 if n in _F64_FIELDS else np.float32) for n in REC_F_NAMES])


def tracking_rows(rf, ri):
    """Structured rows (TRACK_DTYPE) of one channel's epoch records."""
    out = np.empty(rf.shape[0], dtype=TRACK_DTYPE)
    for j, n in enumerate(REC_I_NAMES):
        out[n] = ri[:, j]
    for j, n in enumerate(REC_F_NAMES):
        out[n] = rf[:, j]
    return out


class Recorder:
    """Outputs of a run as they come: the HDF5 stream (``out_path``, schema in docs/process.md), the
    RINEX observation writer and, with ``record_epochs``, the per-channel epoch series in memory."""

    EPOCH_KEYS = ("sample_index", "epoch", "doppler_hz", "code_phase_chips", "cn0_dbhz", "mode", "flags")

    def __init__(self, out_path, rinex_obs_path, cfg, source, prns):
        self.n_ch = len(prns)
        self.writer = None
        self.rinex_obs = None
        try:
            self._open(out_path, rinex_obs_path, cfg, source, prns)
        except BaseException:
            self.abort()        # an error or an interruption while opening: no temporary file stays
            raise

    def abort(self):
        """Remove the outputs' temporary files (the targets are left as they were)."""
        for w in (self.writer, self.rinex_obs):
            if w is not None:
                w.abort()

    def _open(self, out_path, rinex_obs_path, cfg, source, prns):
        if out_path:
            from ultratight.receiver.io.outputs import H5Stream     # h5py loads only for an HDF5 output
            self.writer = H5Stream(out_path)
        self.epochs = {p: {k: [] for k in self.EPOCH_KEYS} for p in prns} if cfg.record_epochs else {}
        self.restarts = [0] * len(prns)        # re-acquisitions per channel at the previous RINEX epoch
        if rinex_obs_path:
            self.rinex_obs = RinexObsWriter(rinex_obs_path, 1.0 / cfg.obs_rate_hz, comments=[
                f"ultratight {__version__} process: iono={cfg.iono} tropo={cfg.tropo} "
                f"({cfg.tropo_mapping}), mask {cfg.mask_deg:g} deg",
                ("C1C carrier smoothed (Hatch filter, %g s window)" % cfg.smoothing_s) if cfg.smoothing_s > 0
                else "C1C raw code pseudorange",
                f"input {source.path}"])

    def acquisition(self, acq):
        w = self.writer
        if w is None:
            return
        w.write("acquisition/prn", np.array([a.prn for a in acq], dtype=np.int16))
        w.write("acquisition/doppler_hz", np.array([a.doppler_hz for a in acq]))
        w.write("acquisition/code_phase_chips", np.array([a.code_phase_chips for a in acq]))
        w.write("acquisition/cn0_dbhz", np.array([a.cn0_dbhz for a in acq]))
        w.write("acquisition/metric", np.array([a.metric for a in acq]))
        w.write("acquisition/threshold", np.array([a.threshold for a in acq]))
        w.write("acquisition/detected", np.array([a.detected for a in acq]))
        w.write("acquisition/sample_index", np.array([a.sample_index for a in acq], dtype=np.int64))

    def tracking(self, prn, f_ch, i_ch):
        """One channel's new epoch records."""
        if self.writer is not None:
            self.writer.append(f"tracking/prn{prn:02d}", tracking_rows(f_ch, i_ch))
        if self.epochs:
            e = self.epochs[prn]
            e["sample_index"].append(i_ch[:, RI_PTR].copy())
            e["epoch"].append(i_ch[:, RI_EPOCH].copy())
            e["doppler_hz"].append(f_ch[:, R_DOPP].copy())
            e["code_phase_chips"].append(f_ch[:, R_CODE_PHASE].copy())
            e["cn0_dbhz"].append(f_ch[:, R_CN0].copy())
            e["mode"].append(i_ch[:, RI_MODE].copy())
            e["flags"].append(i_ch[:, RI_FLAGS].copy())

    def observables(self, row, smoothed=None):
        w = self.writer
        if w is None:
            return
        w.append("observables/sample_index", np.array([row["sample_index"]], dtype=np.int64))
        w.append("observables/t_s", np.array([row["t_s"]]))
        w.append("observables/t_rx_tow_s", np.array([row["t_rx"]]))
        for k in ("pseudorange_m", "doppler_hz", "carrier_cycles", "cn0_dbhz", "code_phase_chips"):
            w.append(f"observables/{k}", row[k][None, :])
        w.append("observables/pll_lock", row["pll_lock"][None, :])

    def smoothed(self, pr):
        if self.writer is not None:
            self.writer.append("observables/pseudorange_smoothed_m", pr[None, :])

    def rinex_epoch(self, week, row, pr, navs, chinfo):
        sats = []
        for ch, info in enumerate(chinfo):
            nreacq = info["reacquisitions"]
            half = navs[ch].decoder.inverted is None
            sats.append({"prn": info["prn"], "pr_m": pr[ch],
                         "phase_cycles": row["carrier_cycles"][ch] + (0.5 if navs[ch].decoder.inverted else 0.0),
                         "doppler_hz": row["doppler_hz"][ch], "cn0_dbhz": row["cn0_dbhz"][ch],
                         "lock": bool(row["pll_lock"][ch]), "continuous": nreacq == self.restarts[ch],
                         "half_cycle": half})
            self.restarts[ch] = nreacq
        self.rinex_obs.add_epoch(week, row["t_rx"], sats)

    def fix(self, fix, sol, parts):
        w = self.writer
        if w is None:
            return
        n_ch = self.n_ch
        w.append("pvt/t_s", np.array([fix["t_s"]]))
        w.append("pvt/sample_index", np.array([fix["sample_index"]], dtype=np.int64))
        w.append("pvt/gps_tow_s", np.array([fix["gps_tow_s"]]))
        w.append("pvt/pos_e", sol.pos_e[None, :])
        w.append("pvt/vel_e", sol.vel_e[None, :])
        w.append("pvt/llh_deg", np.array([fix["llh_deg"]]))
        w.append("pvt/clk_bias_m", np.array([sol.clk_bias_m]))
        w.append("pvt/clk_drift_mps", np.array([sol.clk_drift_mps]))
        w.append("pvt/cov_pos_clk", sol.cov_pos_clk[None])
        w.append("pvt/cov_vel_drift", sol.cov_vel_drift[None])
        w.append("pvt/dop", np.array([[fix["gdop"], fix["pdop"], fix["hdop"], fix["vdop"]]]))
        w.append("pvt/n_used", np.array([fix["n_used"]], dtype=np.int16))
        w.append("pvt/raim_ok", np.array([sol.raim_ok]))
        used = np.zeros(n_ch, dtype=bool)
        used[sol.used] = True
        w.append("pvt/used", used[None, :])
        for k in ("iono_m", "tropo_m"):
            v = np.asarray(parts.get(k, np.full(n_ch, np.nan)), dtype=float) * np.ones(n_ch)
            w.append(f"pvt/{k}", v[None, :])

    def epoch_arrays(self):
        """The recorded epoch series as arrays (prn -> name -> array)."""
        for e in self.epochs.values():
            for k in list(e):
                e[k] = np.concatenate(e[k]) if e[k] else np.zeros(0)
        return self.epochs


def finish_hdf5(writer, result, cfg, run_config):
    """The HDF5 output's attributes (configuration, input, corrections, channel summaries) and
    summary; ``complete = False`` after an interruption."""
    conf = asdict(cfg)
    writer.flush()                 # datasets exist before their attributes are set
    writer.attrs("/", config=conf, run_config=run_config or {}, input=result.input,
                 corrections=result.corrections,
                 signal_s=result.signal_s, wall_s=result.wall_s, interrupted=result.interrupted)
    for c in result.channels:
        writer.attrs(f"tracking/prn{c['prn']:02d}", **{k: (-1 if v is None else v) for k, v in c.items()
                                                       if k != "prn"}, prn=c["prn"])
    writer.finish(complete=not result.interrupted, summary=result.summary())


def write_exchange_files(result, cfg, navs, ephemerides, used_ephs, iono, rinex_obs, rinex_nav_path, nmea_path):
    """RINEX observation / navigation and NMEA files at the end of a complete run."""
    pos, _ = result.position_median()
    if rinex_obs is not None:
        rinex_obs.finish(pos)
    utc = next((nv.decoder.iono for nv in navs if nv.decoder.iono is not None), None)
    leap = utc.dt_ls if utc is not None else getattr(ephemerides, "leap_seconds", None)
    if rinex_nav_path:
        ephs = list(used_ephs.values()) + [nv.ephemeris for nv in navs if nv.ephemeris is not None]
        write_rinex_nav(rinex_nav_path, ephs, iono=None if iono is None else iono[:2], leap_seconds=leap,
                        comments=[f"ultratight {__version__} process: ephemerides "
                                  f"{'from ' + str(getattr(ephemerides, 'path', 'the caller')) if ephemerides is not None else 'decoded from the signal'}"])
    if nmea_path:
        write_nmea(nmea_path, result.fixes, leap_s=DEFAULT_LEAP_S if leap is None else leap,
                   options={"iono": result.corrections.get("iono", cfg.iono), "tropo": cfg.tropo})
