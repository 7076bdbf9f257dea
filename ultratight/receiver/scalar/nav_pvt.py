"""The scalar receiver's stages after tracking: navigation bits and decoding per channel
(:class:`NavBitStage`), the observables of an observation epoch (:class:`ObservableStage`) and its
position / velocity / clock solution (:class:`PvtStage`, ephemerides from
:func:`ephemeris_lookup` or the decoded navigation message).

Receiver time ``t_rx(s) = t0 + s/fs`` (receiver clock): ``t0`` is set when the first channel knows
its transmit time (``t0 = t_tx + RX_T0_OFFSET_S``) and steered by the clock-bias estimate at the
first fix and whenever |bias| exceeds ``CLOCK_STEER_S``.
"""

import math

import numpy as np

from ultratight.constants import C
from ultratight.receiver.dsp.tracking_layout import FL_BIT_DONE, FL_BIT_SYNC, R_BIT, R_IP, RI_EPOCH, RI_FLAGS, RI_PTR
from ultratight.receiver.scalar.observables import observe, pseudorange
from ultratight.ins.earth import elev_azim
from ultratight.receiver.scalar.pvt import atmosphere_delays, solve_pvt
from ultratight.signals.atmosphere import AtmosphereModel
from ultratight.signals.ephemeris import sat_state

RX_T0_OFFSET_S = 0.075       # initial guess of the signal travel time
CLOCK_STEER_S = 1e-3         # re-steer the receiver time when |bias| exceeds this
PRE_SYNC_KEEP = 30000        # 1 ms prompts kept per channel before bit sync (for the earliest bits)


def ephemeris_lookup(ephemerides):
    """Normalise --ephemeris input to a function (prn, week, tow) -> Ephemeris | None."""
    if ephemerides is None:
        return lambda prn, week, tow: None
    if hasattr(ephemerides, "select"):
        def f(prn, week, tow):
            if week is None:
                lst = ephemerides.ephemerides.get(int(prn), [])
                if not lst:
                    return None
                week = lst[len(lst) // 2].week
            return ephemerides.select(prn, week, tow)
        return f
    return lambda prn, week, tow: ephemerides.get(int(prn))


class NavBitStage:
    """Bit synchronisation + navigation decoding of every channel: the epoch records of a block in,
    the channel's navigation state (:func:`ultratight.receiver.scalar.navdecode.channel_nav`) out.

    Before the tracking kernel declares bit sync, the 1-code-period prompts are kept (at most
    ``PRE_SYNC_KEEP`` per channel); at the sync they are summed over the whole bits ending at the
    first bit the kernel forms, so the earliest bits reach the decoder too."""

    def __init__(self, navs, signal, fs, start_sample):
        self.navs = navs
        self.signal = signal
        self.fs = fs
        self.start_sample = start_sample
        self.pre_ip = [[] for _ in navs]
        self.pre_ep = [[] for _ in navs]

    def restart(self, ch):
        self.navs[ch].reset()
        self.pre_ip[ch], self.pre_ep[ch] = [], []

    def feed(self, ch, f_ch, i_ch, info):
        """The records (rows of R_* / RI_* columns) of channel ``ch``; updates ``info`` (bit_sync,
        bit_sync_s, tow_s, ephemeris_s)."""
        if not info["bit_sync"]:
            self._before_sync(ch, f_ch, i_ch, info)
        bits = np.flatnonzero(i_ch[:, RI_FLAGS] & FL_BIT_DONE)
        if bits.size:
            nav = self.navs[ch]
            now_ep = int(i_ch[-1, RI_EPOCH])
            nav.feed(f_ch[bits, R_BIT], i_ch[bits, RI_EPOCH] - (self.signal.codes_per_bit - 1), now_ep)
            t_now = (int(i_ch[-1, RI_PTR]) - self.start_sample) / self.fs
            if info["tow_s"] is None and nav.has_time:
                info["tow_s"] = t_now
            if info["ephemeris_s"] is None and nav.ephemeris is not None:
                info["ephemeris_s"] = t_now

    def _before_sync(self, ch, f_ch, i_ch, info):
        synced = np.flatnonzero(i_ch[:, RI_FLAGS] & FL_BIT_SYNC)
        self.pre_ip[ch].append(f_ch[:, R_IP].copy())
        self.pre_ep[ch].append(i_ch[:, RI_EPOCH].copy())
        if synced.size:
            info["bit_sync"] = True
            info["bit_sync_s"] = (int(i_ch[synced[0], RI_PTR]) - self.start_sample) / self.fs
            # bits before the sync: sum the buffered prompts over whole bits ending at the first
            # bit the tracking kernel forms (it starts at the sync epoch)
            e1 = int(i_ch[synced[0], RI_EPOCH])
            ip_all = np.concatenate(self.pre_ip[ch])
            ep_all = np.concatenate(self.pre_ep[ch])
            per_bit = self.signal.codes_per_bit
            starts = e1 - per_bit * np.arange((e1 - ep_all[0]) // per_bit, 0, -1)
            if starts.size and np.all(np.diff(ep_all) == 1):
                idx = (starts - ep_all[0])[:, None] + np.arange(per_bit)[None, :]
                self.navs[ch].feed(ip_all[idx].sum(axis=1), starts, e1)
            self.pre_ip[ch], self.pre_ep[ch] = [], []
        elif sum(a.size for a in self.pre_ip[ch]) > PRE_SYNC_KEEP:
            self.pre_ip[ch].pop(0)
            self.pre_ep[ch].pop(0)


class ObservableStage:
    """Observables at a common receive sample: the channels' epoch histories and navigation states
    in; transmit times, pseudoranges (raw and carrier smoothed), Doppler, carrier phase, C/N0 and
    lock flags out (:func:`ultratight.receiver.scalar.observables.observe`).

    Receiver time ``t_rx(s) = t0 + s/fs``: ``t0`` is set when the first channel knows its transmit
    time (``t0 = t_tx + RX_T0_OFFSET_S``) and moved by :meth:`steer`."""

    def __init__(self, hists, navs, prns, fs, start_sample, h_samp, smoother, signal):
        self.hists, self.navs, self.prns = hists, navs, prns
        self.fs, self.start_sample, self.h_samp = fs, start_sample, h_samp
        self.smoother = smoother
        self.signal = signal
        self.rx_t0 = None                 # receiver time of sample 0 (s of week)

    def epoch(self, s_obs):
        """``(row, obs)`` at sample ``s_obs``, or None while no channel knows its transmit time;
        ``row`` holds arrays over the channels, ``obs`` the per-channel observe() dicts."""
        obs = [observe(h, nv, s_obs, self.h_samp, self.signal) for h, nv in zip(self.hists, self.navs)]
        ttx = np.array([o["t_tx_sv"] if o is not None else np.nan for o in obs])
        if self.rx_t0 is None:
            if not np.isfinite(ttx).any():
                return None
            self.rx_t0 = float(np.nanmax(ttx)) + RX_T0_OFFSET_S - s_obs / self.fs
        t_rx = self.rx_t0 + s_obs / self.fs
        row = {"sample_index": int(s_obs), "t_s": (s_obs - self.start_sample) / self.fs, "t_rx": t_rx,
               "prn": list(self.prns), "t_tx_sv": ttx,
               "pseudorange_m": pseudorange(t_rx, ttx),
               "doppler_hz": np.array([o["doppler_hz"] if o else np.nan for o in obs]),
               "carrier_cycles": np.array([o["carrier_cycles"] if o else np.nan for o in obs]),
               "cn0_dbhz": np.array([o["cn0_dbhz"] if o else np.nan for o in obs]),
               "code_phase_chips": np.array([o["code_phase_chips"] if o else np.nan for o in obs]),
               "pll_lock": np.array([bool(o and o["pll_lock"]) for o in obs])}
        return row, obs

    def smooth(self, row):
        """Carrier-smoothed pseudoranges (Hatch filter) of ``row``."""
        return self.smoother.update(row["pseudorange_m"], row["carrier_cycles"], row["pll_lock"])

    def steer(self, bias_m):
        """Move the receiver time scale by the clock bias ``bias_m`` (towards GPS time)."""
        self.rx_t0 -= bias_m / C
        self.smoother.shift(-bias_m)


class PvtStage:
    """Satellite states and the position / velocity / clock solution of one observation epoch:
    transmit times, pseudoranges and Doppler (arrays over the channels) in, a fix dict out
    (:func:`ultratight.receiver.scalar.pvt.solve_pvt`, atmosphere per ``ProcessConfig.iono`` /
    ``tropo``). Ephemerides come from ``eph_of`` (RINEX / caller) or the channel's decoded
    navigation message."""

    def __init__(self, cfg, eph_of, navs, prns, ref_week, ephemerides, signal):
        self.cfg, self.eph_of, self.navs, self.prns = cfg, eph_of, navs, prns
        self.signal = signal
        self.week_known = ref_week
        self.last_x = None
        self.used_ephs = {}          # (prn, week, toe, iode) -> Ephemeris used by the PVT
        self.corrections = {}
        nav_iono = None
        if cfg.iono == "klobuchar" and getattr(ephemerides, "ion_alpha", None) and \
                getattr(ephemerides, "ion_beta", None):
            nav_iono = (tuple(ephemerides.ion_alpha), tuple(ephemerides.ion_beta), "rinex")
        self.iono = nav_iono
        self._model = None
        self.atmosphere_model()      # records the options in .corrections from the start

    def atmosphere_model(self):
        """The AtmosphereModel of this epoch (the ionosphere starts when coefficients are known)."""
        cfg = self.cfg
        if cfg.iono == "klobuchar" and self.iono is None:
            for nv in self.navs:
                io = nv.decoder.iono
                if io is not None:
                    self.iono = (tuple(io.alpha), tuple(io.beta), "lnav")
                    self._model = None
                    break
        if self._model is None:
            a, b, src = self.iono if self.iono is not None else (None, None, None)
            self._model = AtmosphereModel(cfg.iono, a, b, cfg.tropo, cfg.tropo_mapping)
            self.corrections = {**self._model.describe(), "iono_source": src,
                                "iono_option": cfg.iono, "tropo_option": cfg.tropo}
        return self._model

    def satellite_states(self, obs, ttx, pr):
        """``(sat_pos, sat_vel, corrected pseudorange, range rate)`` (arrays over the channels, NaN
        where a channel has no lock, no transmit time or no ephemeris)."""
        n = len(obs)
        sp = np.full((n, 3), np.nan)
        sv = np.full((n, 3), np.nan)
        prc = np.full(n, np.nan)
        rr = np.full(n, np.nan)
        for ch in range(n):
            o = obs[ch]
            if o is None or not np.isfinite(ttx[ch]) or not o["pll_lock"]:
                continue
            if self.week_known is None and self.navs[ch].decoder.week is not None:
                self.week_known = self.navs[ch].decoder.week
            eph = self.eph_of(self.prns[ch], self.week_known, ttx[ch])
            if eph is None:
                eph = self.navs[ch].ephemeris
            if eph is None:
                continue
            # state at the satellite-clock time, moved to GPS time t_gps = t_sv - clk (|clk| < 1 ms:
            # the linear step leaves < 1 um of position error)
            self.used_ephs[(eph.prn, eph.week, eph.toe, eph.iode)] = eph
            p_, v_, clk, drift = sat_state(eph, ttx[ch])
            p_ = p_ - v_ * float(clk[0])
            sp[ch] = p_[0]
            sv[ch] = v_[0]
            prc[ch] = pr[ch] + C * float(clk[0])
            rr[ch] = -self.signal.wavelength_m * o["doppler_hz"] + C * float(drift[0])
        return sp, sv, prc, rr

    def solve(self, row, obs, pr, steer, sigma_factor=None):
        """The fix of this epoch, or None (fewer than 4 satellites, no solution, or the first solution
        / a clock bias beyond CLOCK_STEER_S, which ``steer(bias_m)`` removes from the time scale);
        returns ``(fix, sol, parts)``. ``sigma_factor``: per channel, a factor on the pseudoranges'
        a-priori sigma (:func:`ultratight.receiver.scalar.observables.noise_weights`)."""
        sp, sv, prc, rr = self.satellite_states(obs, row["t_tx_sv"], pr)
        if np.isfinite(prc).sum() < 4:
            return None
        model = self.atmosphere_model()
        parts = {}
        sigma_pr = self.cfg.sigma_pr_m if sigma_factor is None else self.cfg.sigma_pr_m * sigma_factor
        sol = solve_pvt(sp, prc, sv, rr, sigma_pr_m=sigma_pr, sigma_rr_mps=self.cfg.sigma_rr_mps,
                        x0=self.last_x, mask_deg=self.cfg.mask_deg,
                        delays=atmosphere_delays(model, row["t_rx"], parts) if model.active else None)
        if not sol.valid or sol.vel_e is None:
            return None
        if self.last_x is None or abs(sol.clk_bias_m) > CLOCK_STEER_S * C:
            # steer the receiver time scale to GPS time and re-solve on the next epoch
            steer(sol.clk_bias_m)
            self.last_x = np.r_[sol.pos_e, 0.0]
            return None
        self.last_x = np.r_[sol.pos_e, sol.clk_bias_m]
        return self._fix(row, sol, sp, model), sol, parts

    def _fix(self, row, sol, sp, model):
        n = sp.shape[0]
        fin = np.all(np.isfinite(sp), axis=1)
        el_all, az_all = np.full(n, np.nan), np.full(n, np.nan)
        if fin.any():
            el_all[fin], az_all[fin] = elev_azim(sol.pos_e, sp[fin])
        sv_list = [{"prn": self.prns[j], "elev_deg": math.degrees(el_all[j]),
                    "azim_deg": math.degrees(az_all[j]) % 360.0, "cn0_dbhz": float(row["cn0_dbhz"][j]),
                    "used": bool(sol.used[j]), "resid_m": float(sol.residuals_m[j])} for j in np.flatnonzero(fin)]
        llh_deg = [math.degrees(sol.llh[0]), math.degrees(sol.llh[1]), float(sol.llh[2])]
        return {"t_s": row["t_s"], "sample_index": row["sample_index"], "gps_week": self.week_known,
                "gps_tow_s": row["t_rx"] - sol.clk_bias_m / C, "pos_e": sol.pos_e, "vel_e": sol.vel_e,
                "llh_deg": llh_deg, "clk_bias_m": sol.clk_bias_m, "clk_drift_mps": sol.clk_drift_mps,
                "pdop": sol.dops.get("pdop", float("nan")), "gdop": sol.dops.get("gdop", float("nan")),
                "hdop": sol.dops.get("hdop", float("nan")), "vdop": sol.dops.get("vdop", float("nan")),
                "n_used": int(sol.used.sum()), "raim_ok": sol.raim_ok,
                "excluded_prn": [self.prns[j] for j in sol.excluded],
                "used_prn": [self.prns[j] for j in np.flatnonzero(sol.used)],
                "sigma_pos_m": float(np.sqrt(np.trace(sol.cov_pos_clk[:3, :3]))),
                "sigma_vel_mps": (float(np.sqrt(np.trace(sol.cov_vel_drift[:3, :3])))
                                  if sol.cov_vel_drift is not None else float("nan")),
                "iono": "klobuchar" if model.iono_active else "off", "tropo": self.cfg.tropo, "sv": sv_list}
