"""Recorder of the ultra-tight engine: per-epoch tracking estimates, the navigation solution
at every tight-filter update and at every SINS step (the SINS-rate solution with the 1-sigma of
the integration filter's covariance), and the :class:`EngineResult` built from them."""

from dataclasses import dataclass, field

import numpy as np

from ultratight.fusion.coupling.tight import ATT, CLK_B, CLK_D, POS, VEL
from ultratight.ins.attitude import quat_to_euler
from ultratight.ins.earth import llh_increment_scale, radii

# per-update integrity record (EngineResult.nav_integrity; receiver.deep.integrity.IntegrityMonitor.last)
INTEGRITY_KEYS = ("state", "nis", "dof", "limit", "gated_frac", "disagree_frac", "flags")


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
    # the SINS-rate navigation solution (EpochRecorder.sins_arrays): t_s, llh, vel_l, q_lb, euler,
    # clk and the 1-sigma of the integration filter (pos ENU m, vel ENU m/s, att ENU rad, clk m, m/s)
    sins: dict = field(default_factory=dict)
    bit_source: np.ndarray = None   # (n_ep, n_ch) int8 source of each epoch's data bit (receiver.dsp.wipeoff BIT_*)
    # per tight update (rows of nav_t), the integrity monitor (receiver.deep.integrity): state (0 ok,
    # 1 degraded, 2 lost), window NIS, its degrees of freedom and chi-square limit, share of gated rows,
    # share of disagreeing channels, failure flags
    nav_integrity: dict = field(default_factory=dict)


class EpochRecorder:
    """Per-epoch arrays (written by the compiled epoch stages, :func:`ultratight.receiver.deep.epochs.epoch_post`)
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
        self.integ = {k: [] for k in INTEGRITY_KEYS}
        self.sins = []                     # rows: t, llh (3), vel_l (3), q_lb (4), clk b, d
        self.sins_sig = []                 # rows: sigma pos ENU (3), vel (3), att (3), clk b, d
        self.sins_state = []               # integrity state of each SINS row (held between updates)
        self.sigma_now = np.full(11, np.nan)
        self.state_now = 0

    def set_sigma(self, P, llh):
        """The 1-sigma of the integration filter's covariance ``P`` (tight.NX states) that the SINS
        rows carry until the next update: position ENU (m), velocity ENU (m/s), attitude (rad,
        ENU error angles), clock bias (m) and drift (m/s)."""
        lat, _, h = (float(v) for v in llh)
        rm, rn = radii(lat)
        d = np.sqrt(np.maximum(np.diag(P), 0.0))
        p = d[POS]
        s = np.empty(11)
        s_n, s_e, s_u = llh_increment_scale(lat, h, rm, rn)
        s[0] = p[1] * s_e
        s[1] = p[0] * s_n
        s[2] = p[2] * s_u
        s[3:6] = d[VEL]
        s[6:9] = d[ATT]
        s[9] = d[CLK_B]
        s[10] = d[CLK_D]
        self.sigma_now = s

    def log_sins(self, t, x, clk_b, clk_d, replace=False):
        """The SINS state vector ``x`` (ultratight.ins.sins layout: q_lb, vel_l, llh) at time ``t``;
        ``replace``: overwrite the last row (the same step after a feedback)."""
        row = np.empty(13)
        row[0] = t
        row[1:4] = x[7:10]
        row[4:7] = x[4:7]
        row[7:11] = x[0:4]
        row[11] = clk_b
        row[12] = clk_d
        if replace and self.sins:
            self.sins[-1] = row
            self.sins_sig[-1] = self.sigma_now.copy()
            self.sins_state[-1] = self.state_now
        else:
            self.sins.append(row)
            self.sins_sig.append(self.sigma_now.copy())
            self.sins_state.append(self.state_now)

    def sins_arrays(self):
        """The SINS-rate solution as arrays (see EngineResult.sins)."""
        a = np.asarray(self.sins, float).reshape(-1, 13)
        s = np.asarray(self.sins_sig, float).reshape(-1, 11)
        eul = np.array([quat_to_euler(q) for q in a[:, 7:11]]).reshape(-1, 3)
        return {"t_s": a[:, 0], "llh": a[:, 1:4], "vel_l": a[:, 4:7], "q_lb": a[:, 7:11], "euler": eul,
                "clk": a[:, 11:13], "sigma_pos_l_m": s[:, 0:3], "sigma_vel_l_mps": s[:, 3:6],
                "sigma_att_rad": s[:, 6:9], "sigma_clk": s[:, 9:11],
                "integrity_state": np.asarray(self.sins_state, dtype=np.int8)}

    def log_integrity(self, state, last):
        """The integrity monitor's state and test figures (``IntegrityMonitor.last``) of the tight
        update just logged; the state is held on the SINS rows until the next update."""
        self.state_now = int(state)
        self.integ["state"].append(int(state))
        for k in INTEGRITY_KEYS[1:]:
            self.integ[k].append(last.get(k, np.nan))

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
            duration_s=n * code_period_s, info=info, sins=self.sins_arrays(),
            nav_integrity={k: np.asarray(v, dtype=np.int8 if k in ("state", "flags") else float)
                           for k, v in self.integ.items()})


_COUNTERS = ("n_epochs", "n_tight_updates", "n_tight_rejected", "n_feedback", "n_phase_inits", "n_lock_lost_events",
             "n_prefilter_restarts")


def join_results(parts, t_h):
    """One :class:`EngineResult` of engine runs one after the other on the same record (a run
    re-initialised after its solution was lost; ``receiver.deep.recordings``): run ``k`` started at
    ``t_h[k]`` s after the first sample of the file and its times count from there. The per-epoch,
    navigation, SINS and integrity rows are concatenated in time, every time moved to count from
    ``t_h[0]`` (the integrity times of ``info["integrity"]`` from the first sample of the file);
    ``info`` is the first run's with the counters summed, the last run's bit record, ``segments``
    (per run: start and end time, first epoch row, first transmit-time code-period count) and the
    integrity of the whole: final state of the last run, worst of all, the first degraded / lost
    times, ``lost_at_s`` of the last run, ``reinit_at_s`` and ``n_reinit``."""
    first = parts[0]
    cat = lambda get: np.concatenate([np.asarray(get(p)) for p in parts], axis=0)   # noqa: E731
    moved = [float(t) - float(t_h[0]) for t in t_h]
    info = dict(first.info)
    for k in _COUNTERS:
        if all(k in p.info for p in parts):
            info[k] = int(sum(p.info[k] for p in parts))
    info["bits"] = parts[-1].info.get("bits", info.get("bits"))
    segs, row = [], 0
    for p, t0, dt in zip(parts, t_h, moved):
        segs.append({"t_start_s": float(t0), "t_end_s": float(t0) + float(p.duration_s), "first_epoch": row,
                     "first_period_count": p.info.get("first_period_count")})
        row += np.asarray(p.t_start).shape[0]
    info["segments"] = segs
    info["integrity"] = _joined_integrity([p.info.get("integrity") or {} for p in parts], t_h)
    sins = {}
    if all(p.sins for p in parts):
        for k in first.sins:
            sins[k] = np.concatenate([np.asarray(p.sins[k]) + (dt if k == "t_s" else 0) for p, dt in zip(parts, moved)],
                                     axis=0)
    nav_int = {}
    if all(p.nav_integrity for p in parts):
        nav_int = {k: cat(lambda p, k=k: p.nav_integrity[k]) for k in first.nav_integrity}
    bits = None if any(p.bit_source is None for p in parts) else cat(lambda p: p.bit_source)
    return EngineResult(
        method=first.method, prns=list(first.prns),
        t_start=np.concatenate([np.asarray(p.t_start) + dt for p, dt in zip(parts, moved)], axis=0),
        doppler_hz=cat(lambda p: p.doppler_hz), code_phase_chips=cat(lambda p: p.code_phase_chips),
        amp=cat(lambda p: p.amp), mode=cat(lambda p: p.mode),
        nav_t=np.concatenate([np.asarray(p.nav_t) + dt for p, dt in zip(parts, moved)]),
        nav_pos_e=cat(lambda p: p.nav_pos_e), nav_vel_e=cat(lambda p: p.nav_vel_e), nav_clk=cat(lambda p: p.nav_clk),
        nav_sigma_doppler_hz=cat(lambda p: p.nav_sigma_doppler_hz), runtime_s=float(sum(p.runtime_s for p in parts)),
        duration_s=float(sum(p.duration_s for p in parts)), info=info, sins=sins, bit_source=bits,
        nav_integrity=nav_int)


def _joined_integrity(recs, t_h):
    """The integrity record of runs one after the other (:func:`join_results`), times from the first
    sample of the file."""
    def at(v, t0):
        return None if v is None else float(v) + float(t0)

    order = ("ok", "degraded", "lost")
    out = dict(recs[-1])
    out["worst"] = max((r.get("worst", "ok") for r in recs), key=order.index)
    for k in ("first_degraded_s", "first_lost_s"):
        out[k] = next((at(r.get(k), t0) for r, t0 in zip(recs, t_h) if r.get(k) is not None), None)
    out["lost_at_s"] = at(recs[-1].get("lost_at_s"), t_h[-1])
    out["reinit_at_s"] = [at(r.get("lost_at_s"), t0) for r, t0 in zip(recs[:-1], t_h[:-1])]
    out["handover_at_s"] = [float(t) for t in t_h]
    out["n_reinit"] = len(recs) - 1
    return out
