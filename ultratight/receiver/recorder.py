"""Recorder of the ultra-tight engine: per-epoch tracking estimates and the navigation solution
at every tight-filter update, and the :class:`EngineResult` built from them."""

from dataclasses import dataclass

import numpy as np


@dataclass
class EngineResult:
    method: str
    prns: list
    t_start: np.ndarray          # (n_ep, n_ch) s since the first sample
    doppler_hz: np.ndarray       # (n_ep, n_ch) estimate (NCO + prefilter)
    code_phase_chips: np.ndarray  # (n_ep, n_ch) estimate (NCO + prefilter), modulo the code length
    amp: np.ndarray              # (n_ep, n_ch) prefilter amplitude estimate
    mode: np.ndarray             # (n_ep, n_ch) int8 MODE_*
    nav_t: np.ndarray            # (n_nav,) tight-update times
    nav_pos_e: np.ndarray        # (n_nav, 3)
    nav_vel_e: np.ndarray
    nav_clk: np.ndarray          # (n_nav, 2) bias m, drift m/s
    nav_sigma_doppler_hz: np.ndarray  # (n_nav, n_ch)
    runtime_s: float
    duration_s: float
    info: dict
    bit_source: np.ndarray = None   # (n_ep, n_ch) int8 source of each epoch's data bit (receiver.wipeoff BIT_*)


class EpochRecorder:
    """Per-epoch arrays (written by the compiled epoch stages, :func:`ultratight.receiver.epochs.epoch_post`)
    for at most ``n_ep_max`` epochs of ``n_ch`` channels, and the navigation log."""

    def __init__(self, n_ep_max, n_ch):
        self.n_ep_max = int(n_ep_max)
        self.n_ch = int(n_ch)
        self.t = np.full((n_ep_max, n_ch), np.nan)
        self.f = np.full((n_ep_max, n_ch), np.nan)
        self.cp = np.full((n_ep_max, n_ch), np.nan)
        self.a = np.full((n_ep_max, n_ch), np.nan)
        self.mode = np.zeros((n_ep_max, n_ch), dtype=np.int8)
        self.nav = {"t": [], "pos_e": [], "vel_e": [], "clk": [], "sig": []}

    def log_nav(self, t, pos_e, vel_e, clk_b, clk_d, sig_dopp):
        """The navigation state after a tight update (SINS time ``t``)."""
        self.nav["t"].append(t)
        self.nav["pos_e"].append(np.array(pos_e, dtype=float))
        self.nav["vel_e"].append(np.array(vel_e, dtype=float))
        self.nav["clk"].append([clk_b, clk_d])
        self.nav["sig"].append(np.array(sig_dopp, dtype=float))

    def result(self, method, prns, n_ep, runtime_s, code_period_s, info):
        """The :class:`EngineResult` of the first ``n_ep`` epochs."""
        n = int(n_ep)
        nav = self.nav
        return EngineResult(
            method=method, prns=list(prns), t_start=self.t[:n], doppler_hz=self.f[:n],
            code_phase_chips=self.cp[:n], amp=self.a[:n], mode=self.mode[:n],
            nav_t=np.asarray(nav["t"]), nav_pos_e=np.asarray(nav["pos_e"]).reshape(-1, 3),
            nav_vel_e=np.asarray(nav["vel_e"]).reshape(-1, 3), nav_clk=np.asarray(nav["clk"]).reshape(-1, 2),
            nav_sigma_doppler_hz=np.asarray(nav["sig"]).reshape(-1, self.n_ch), runtime_s=runtime_s,
            duration_s=n * code_period_s, info=info)
