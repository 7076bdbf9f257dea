"""The double-loop ultra-tight receiver engine (seed 000 Fig. 1, SPEC §1).

Data flow per 1 ms epoch (Python orchestrates; every stage is one batched call for all
channels)::

    IF block ─► CorrelatorBank.step ─► data wipe-off (assisted LNAV bits)
             ─► PrefilterBank.step (inner loop, 1 kHz)  ─► InnerLoop.apply (NCO feedback,
                 outer-loop Doppler increments when the arbitration allows)
             ─► residuals vs the SINS prediction ─► averaging decimator (10 Hz)
             ─► tight 17-state filter ⇄ SINS (100 Hz, feedback) ─► OuterLoop (100 Hz
                 predictions, CIC to 1 kHz) ─► aiding of the next epochs

Methods (all on the same IF/IMU data):

* ``dlb-rackf`` (default), ``dlb-ckf``, ``dlb-ukf``: double loop — each channel's prefilter
  (helper G's numba bank) closes its own inner loop every epoch; the outer loop feeds the
  SINS-predicted Doppler *increments* forward into the carrier NCO (the code NCO rate is
  slaved to the carrier, so it is aided too).
* ``pb-kf-utc``: single loop baseline — discriminator outputs into a linear KF per channel
  (``ultratight.fusion.pbkf``); the NCOs are driven by the outer loop only (absolute
  SINS-predicted Doppler and code phase, no inner loop).
* ``scalar``: helper F's scalar tracking pipeline (no INS), for reference.

Arbitration (double loop, logged per channel per epoch in ``mode``): after every tight
update the 1-sigma of each channel's predicted Doppler is computed from the tight filter
covariance, ``sigma_i = sqrt(u_i' P_vv u_i + P_dd - 2 u_i' P_vd) / lambda`` (velocity /
clock-drift block projected on the line of sight, :func:`ultratight.fusion.tight.doppler_sigma_hz`),
and propagated between updates with the filter's time update.  A channel uses the combined
command (outer prediction + inner correction, ``MODE_COMBINED``) while ``sigma_i <
arbitration_sigma_hz`` and the outer loop is healthy (no divergence flag), otherwise the inner
loop alone (``MODE_INNER``).  PB-KF-UTC is always ``MODE_OUTER``.

Tracking estimates recorded per channel per epoch (for the paper's metrics): the Doppler
``carr_freq - IF + df/2pi`` and the code phase ``code_phase + dtau`` at the *start* of the
integration interval (the prefilter state refers to the interval start; see
ultratight.fusion.prefilter), with their time ``t_start`` (s since the first sample).
"""

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ultratight.constants import C, CA_LEN, CHIP_M, F_CA, F_L1, LAMBDA_L1, T_CA
from ultratight.errors import ConfigError, InputFileError

METHODS = ("pb-kf-utc", "dlb-ukf", "dlb-ckf", "dlb-rackf", "scalar")
DEFAULT_METHOD = "dlb-rackf"

MODE_INNER = 0
MODE_COMBINED = 1
MODE_OUTER = 2

# process noise of the aided prefilters (same for the three DLB methods; densities of eq. 2)
DLB_PREFILTER_Q = {
    "q_amp": 2.5e-3,     # amplitude random walk
    "q_tau": 1e-8,       # chips^2/s: code-carrier divergence (none in the simulation: small)
    "q_phi": 0.01,       # rad^2/s
    "q_f": 1.0,          # rad^2/s^3: aiding error drift (INS velocity / clock-drift error rate)
    "q_a": 10.0,         # rad^2/s^5: residual LOS jerk after aiding (IMU-CIC timing residuals)
}


def check_method(method):
    if method not in METHODS:
        raise ConfigError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    return method


@dataclass
class EngineOptions:
    """Parameters of the engine (all recorded in the outputs)."""

    tight_rate_hz: float = 10.0          # integration-filter (decimated) rate
    tight_core: str = "ekf"              # ekf | ukf | ckf | iakf
    arbitration_sigma_hz: float = 2.0    # combined command when predicted Doppler 1-sigma < this
    prefilter_q: dict = field(default_factory=lambda: dict(DLB_PREFILTER_Q))
    rackf_period: int = 50               # RACKF robust-adaptive correction period, epochs
    huber_c: float = 1.5
    robust_mode: str = "period"
    cn0_init_dbhz: float = 25.0          # assumed C/N0 for the prefilters' initial amplitude
    block_ms: int = 10                   # IF read block (noise estimate granularity)
    cic_order: int = 3
    pr_sigma_floor_m: float = 3.0        # tight filter pseudorange noise floor
    prr_sigma_floor_mps: float = 0.05    # tight filter pseudorange-rate noise floor
    meas_corr_factor: float = 10.0       # inflation of prefilter variances (correlated outputs)
    amp_min: float = 0.15                # channels below this amplitude estimate skip the update
    gate_sigma: float = 5.0
    clock_q_drift: float = 1e-4          # (m/s)^2/s clock drift random walk in the tight filter
    startup: dict = field(default_factory=dict)   # StartupErrors overrides

    def as_dict(self):
        return asdict(self)


@dataclass
class EngineResult:
    method: str
    prns: list
    t_start: np.ndarray          # (n_ep, n_ch) s since the first sample
    doppler_hz: np.ndarray       # (n_ep, n_ch) estimate (NCO + prefilter)
    code_phase_chips: np.ndarray  # (n_ep, n_ch) estimate (NCO + prefilter), mod 1023
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


# ---------------------------------------------------------------------------------------
# SINS + clock wrapper (helper C's mechanisation; feedback of the tight filter's error state)
# ---------------------------------------------------------------------------------------
class InsClock:
    """Corrected SINS (helper C's ``sins_step``) plus receiver-clock estimates."""

    def __init__(self, q_lb, vel_l, llh, clk_bias_m, clk_drift_mps):
        from ultratight.ins import sins
        self._sins = sins
        self.x = sins.make_state(q_lb, vel_l, llh)
        self.clk_b = float(clk_bias_m)
        self.clk_d = float(clk_drift_mps)
        self.bg = np.zeros(3)        # estimated gyro bias (rad/s), removed from the increments
        self.ba = np.zeros(3)        # estimated accelerometer bias (m/s^2)
        self.f_b = np.zeros(3)       # last specific force (body), for the error model
        self.w_b = np.zeros(3)

    def step(self, dtheta, dv, dt):
        dth = dtheta - self.bg * dt
        dvc = dv - self.ba * dt
        self.f_b = dvc / dt
        self.w_b = dth / dt
        self._sins.sins_step(self.x, dth, dvc, dt)
        self.clk_b += self.clk_d * dt

    @property
    def llh(self):
        return self.x[7:10]

    @property
    def vel_l(self):
        return self.x[4:7]

    @property
    def q_lb(self):
        return self.x[0:4]

    def pos_vel_e(self):
        from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
        lat, lon, h = self.x[7], self.x[8], self.x[9]
        C_el = dcm_ecef_from_enu(lat, lon)
        return np.asarray(llh_to_ecef(lat, lon, h)), C_el @ self.x[4:7], C_el

    def feedback(self, dx):
        """Apply the tight filter's error state (estimate minus truth) and clear it."""
        from ultratight.fusion import tight
        from ultratight.ins import error_model
        error_model.apply_feedback(self.x, dx)      # attitude, velocity, position (helper C)
        self.bg += dx[tight.BG]
        self.ba += dx[tight.BA]
        self.clk_b -= dx[tight.CLK_B]
        self.clk_d -= dx[tight.CLK_D]


# ---------------------------------------------------------------------------------------
# the engine
# ---------------------------------------------------------------------------------------
class UltratightEngine:
    """Runs one method over an IF source + IMU data (see module docstring)."""

    def __init__(self, source, imu, ephs, prns, week, tow0_s, method=DEFAULT_METHOD, options=None,
                 init_state=None, rng=None, duration_s=None):
        self.method = check_method(method)
        self.opt = options or EngineOptions()
        self.src = source
        self.imu = imu
        self.ephs = ephs
        self.prns = [int(p) for p in prns]
        self.week = int(week)
        self.tow0 = float(tow0_s)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.fs = float(source.fs_hz)
        self.if_hz = float(source.if_hz)
        avail = source.n_samples / self.fs
        imu_end = float(imu.t[-1])
        self.duration_s = min(avail, imu_end) if duration_s is None else min(float(duration_s), avail, imu_end)
        if init_state is None:
            raise ConfigError("engine: an initial INS state (init_state) is required for the hot start")
        self.init_state = init_state

    def run(self, progress=False):
        if self.method == "scalar":
            raise ConfigError("method 'scalar' runs through helper F's pipeline "
                              "(ultratight.receiver.scenario_runner.run_scalar)")
        from ultratight.fusion import tight as tightmod
        from ultratight.fusion.innerloop import InnerLoop
        from ultratight.receiver.correlator import CorrelatorBank, estimate_sigma_arm
        from ultratight.receiver.outer_loop import OuterLoop
        from ultratight.receiver.startup import BitWipeoff, first_period_ms, predict_channels

        opt = self.opt
        t_wall0 = time.perf_counter()
        n_ch = len(self.prns)
        fs = self.fs
        st = self.init_state
        rows = np.arange(n_ch)

        # ---- SINS + clock from the (perturbed) initial state
        ins = InsClock(st["q_lb"], st["vel_l"], st["llh"], st["clk_bias_m"], st["clk_drift_mps"])
        self.imu_noise = tightmod.imu_errors_from_meta(self.imu)
        imu_dt = 1.0 / float(self.imu.rate_hz)
        imu_t = np.asarray(self.imu.t, dtype=float)
        imu_dth = np.asarray(self.imu.dtheta_b, dtype=float)
        imu_dv = np.asarray(self.imu.dv_b, dtype=float)
        k_imu = 0                                  # next IMU sample to apply
        t_sins = float(getattr(self.imu, "t0", 0.0))

        # ---- hot start predictions (from the perturbed state, not truth)
        pos_e, vel_e, C_el = ins.pos_vel_e()
        pred0 = predict_channels(self.ephs, self.prns, self.week, self.tow0, pos_e, vel_e,
                                 ins.clk_b, ins.clk_d)
        bank = CorrelatorBank(self.prns, fs, self.if_hz, self.src.is_complex)
        for ch, prn in enumerate(self.prns):
            bank.init_channel(ch, prn, pred0["code_phase_chips"][ch], pred0["doppler_hz"][ch], 0,
                              carr_phase_cycles=0.0, align=True)
        ms = first_period_ms(pred0["t_tx_tow"], pred0["code_phase_chips"])
        wipe = BitWipeoff(self.ephs, self.prns, self.week, self.tow0, self.duration_s + 1.0)

        # ---- tight filter
        P0 = tightmod.initial_covariance(ins.llh, st.get("sigmas", {}), self.imu_noise)
        tf = tightmod.TightFilter(P0, core=opt.tight_core, gate_sigma=opt.gate_sigma)
        lat, lon, h = ins.llh
        from ultratight.ins.earth import radii
        rm, rn = radii(lat)
        M_pos = tightmod.pos_error_to_enu(lat, h, rm, rn)

        # ---- outer loop (100 Hz predictions -> CIC -> 1 kHz)
        outer = OuterLoop(self.ephs, self.prns, self.week, self.tow0, self.duration_s + 0.5,
                          rate_hz=1.0 / imu_dt, cic_order=opt.cic_order)
        pr_now = outer.predict(t_sins, pos_e, vel_e, ins.clk_b, ins.clk_d)
        los_l = pr_now["los_e"] @ C_el
        sig_dopp = tightmod.doppler_sigma_hz(tf.P, los_l, LAMBDA_L1)
        outer.prime(t_sins, pos_e, vel_e, np.zeros(3), ins.clk_b, ins.clk_d)
        # aiding for the first SINS interval: direct predictions
        for j in range(outer.ratio + 1):
            pj = outer.predict(t_sins + j * 1e-3, pos_e, vel_e, ins.clk_b, ins.clk_d)
            outer.aid_doppler[j] = pj["doppler_hz"]
            outer.aid_code_rate[j] = pj["code_rate_cps"]
        outer.push(t_sins, pos_e, vel_e, np.zeros(3), ins.clk_b, ins.clk_d)   # covers [10, 20) ms
        # exact predictions at SINS epochs for the residuals: ring of (t, cp, rate, f)
        ring_n = 64
        ring_t = np.full(ring_n, np.nan)
        ring_cp = np.zeros((ring_n, n_ch))
        ring_r = np.zeros((ring_n, n_ch))
        ring_f = np.zeros((ring_n, n_ch))
        ring_k = 0

        def ring_put(t, pr):
            nonlocal ring_k
            i = ring_k % ring_n
            ring_t[i] = t
            ring_cp[i] = pr["code_phase_chips"]
            ring_r[i] = pr["code_rate_cps"]
            ring_f[i] = pr["doppler_hz"]
            ring_k += 1

        ring_put(t_sins, pr_now)
        vel_e_prev = vel_e.copy()

        # ---- prefilters + inner loop
        if self.method == "pb-kf-utc":
            from ultratight.fusion import pbkf
            pref = pbkf.make_bank(n_ch) if hasattr(pbkf, "make_bank") else pbkf.PbkfBank(n_ch)
            inner = None
        else:
            from ultratight.fusion.prefilter import PrefilterBank, default_initial_covariance
            kind = self.method.split("-", 1)[1]
            pref = PrefilterBank(n_ch, kind=kind, q=opt.prefilter_q, huber_c=opt.huber_c,
                                 correction_period=opt.rackf_period, robust_mode=opt.robust_mode,
                                 cn0_dbhz_init=opt.cn0_init_dbhz)
            sig_code_chips = tightmod.code_sigma_m(tf.P, los_l, M_pos) / CHIP_M
            P_init = np.zeros((n_ch, 5, 5))
            base = default_initial_covariance(opt.cn0_init_dbhz, T_CA)
            for ch in range(n_ch):
                P_init[ch] = base
                P_init[ch, 1, 1] = (3.0 * sig_code_chips[ch] + 0.01) ** 2
                P_init[ch, 3, 3] = (2 * math.pi * (3.0 * sig_dopp[ch] + 0.5)) ** 2
                P_init[ch, 4, 4] = (2 * math.pi * 2.0) ** 2
            pref.reset(rows, P0=P_init)
            inner = InnerLoop(n_ch, T=T_CA, if_hz=self.if_hz)

        # ---- records
        n_ep_max = int(self.duration_s * 1000.0 * 1.001) + 8
        rec_t = np.full((n_ep_max, n_ch), np.nan)
        rec_f = np.full((n_ep_max, n_ch), np.nan)
        rec_cp = np.full((n_ep_max, n_ch), np.nan)
        rec_a = np.full((n_ep_max, n_ch), np.nan)
        rec_mode = np.zeros((n_ep_max, n_ch), dtype=np.int8)
        nav = {"t": [], "pos_e": [], "vel_e": [], "clk": [], "sig": []}

        # ---- decimator accumulators (window of the tight filter)
        t_upd_step = 1.0 / opt.tight_rate_hz
        t_next_upd = t_upd_step
        acc_n = np.zeros(n_ch)
        acc_cp = np.zeros(n_ch)
        acc_f = np.zeros(n_ch)
        acc_pt = np.zeros(n_ch)
        acc_pf = np.zeros(n_ch)
        acc_a = np.zeros(n_ch)

        # ---- IF buffer
        blk = int(round(opt.block_ms * 1e-3 * fs))
        n_total = int(min(self.src.n_samples, round(self.duration_s * fs)))
        n_blocks = n_total // blk + 2
        sigma_blk = np.full(n_blocks, np.nan)
        buf = np.zeros(0, dtype=np.complex64 if self.src.is_complex else np.float32)
        buf_start = 0
        per_max = int(math.ceil(fs * T_CA * 1.001)) + 4
        use_aid = np.ones(n_ch, dtype=bool)
        mode_now = np.full(n_ch, MODE_OUTER if self.method == "pb-kf-utc" else MODE_COMBINED, dtype=np.int8)
        two_pi = 2.0 * math.pi
        k_ep = 0
        n_feedback = 0
        timing = {"correlate": 0.0, "prefilter": 0.0, "sins_outer": 0.0, "tight": 0.0}

        while True:
            sp = bank.sample_ptr
            hi = int(sp.max()) + per_max
            if hi > n_total or k_ep >= n_ep_max:
                break
            buf_end = buf_start + buf.shape[0]
            if hi > buf_end:
                lo = int(sp.min())
                keep = buf[max(0, lo - buf_start):]
                new_start = buf_end
                new = []
                while buf_end < hi:
                    x = self.src.read(buf_end, blk)
                    b_idx = buf_end // blk
                    if x.shape[0] == 0:
                        break
                    if b_idx < n_blocks:
                        sigma_blk[b_idx] = estimate_sigma_arm(x, self.src.is_complex)
                    new.append(x)
                    buf_end += x.shape[0]
                del new_start
                buf = np.concatenate([keep] + new) if new else keep
                buf_start = buf_end - buf.shape[0]
                if hi > buf_end:
                    break
            # ---- SINS + outer loop run ahead so the aiding of the next interval exists
            tw = time.perf_counter()
            j_need = int((sp.max() + per_max) / fs * 1000.0) + 2
            while outer.n_filled <= j_need and k_imu < imu_t.shape[0]:
                dt = imu_t[k_imu] - t_sins
                ins.step(imu_dth[k_imu], imu_dv[k_imu], dt)
                t_sins = imu_t[k_imu]
                k_imu += 1
                pos_e, vel_e, C_el = ins.pos_vel_e()
                acc_e = (vel_e - vel_e_prev) / dt
                vel_e_prev = vel_e
                ring_put(t_sins, outer.predict(t_sins, pos_e, vel_e, ins.clk_b, ins.clk_d))
                outer.push(t_sins, pos_e, vel_e, acc_e, ins.clk_b, ins.clk_d)
            timing["sins_outer"] += time.perf_counter() - tw

            # ---- correlate one period per channel
            tw = time.perf_counter()
            cp0 = bank.code_phase.copy()
            f0 = bank.carr_freq.copy()
            bidx = np.minimum(sp // blk, n_blocks - 1)
            sig = sigma_blk[bidx]
            out, t_start, n_s = bank.step(buf, buf_start, sig)
            if np.any(n_s <= 0):
                raise InputFileError(f"{self.src.path}: correlator could not integrate channels "
                                     f"{np.flatnonzero(n_s <= 0).tolist()} (buffer management)")
            timing["correlate"] += time.perf_counter() - tw
            tw = time.perf_counter()
            D = wipe.signs(ms)
            ms += 1
            z = out[:, :6]
            pref.step(z, bits=D)
            xp = pref.x_post
            tk = t_start / fs
            f_meas = f0 - self.if_hz + xp[:, 3] / two_pi
            cp_meas = cp0 + xp[:, 1]
            rec_t[k_ep] = tk
            rec_f[k_ep] = f_meas
            rec_cp[k_ep] = np.mod(cp_meas, CA_LEN)
            rec_a[k_ep] = xp[:, 0]
            rec_mode[k_ep] = mode_now

            # ---- residuals vs the exact SINS predictions (linear between SINS epochs)
            i1 = (ring_k - 1) % ring_n
            t_last = ring_t[i1]
            # index of the SINS epoch just before tk (SINS is ahead of the correlator)
            back = np.floor((t_last - tk) / imu_dt).astype(np.int64) + 1
            back = np.clip(back, 1, ring_n - 1)
            ia = (ring_k - 1 - back) % ring_n
            ib = (ia + 1) % ring_n
            ta = ring_t[ia]
            w = (tk - ta) / imu_dt
            cp_pred = ring_cp[ia, rows] + ring_r[ia, rows] * (tk - ta)
            f_pred = ring_f[ia, rows] + w * (ring_f[ib, rows] - ring_f[ia, rows])
            r_cp = np.mod(cp_meas - cp_pred + 0.5 * CA_LEN, CA_LEN) - 0.5 * CA_LEN
            r_f = f_meas - f_pred
            win = tk < t_next_upd
            acc_n += win
            acc_cp += np.where(win, r_cp, 0.0)
            acc_f += np.where(win, r_f, 0.0)
            acc_a += np.where(win, xp[:, 0], 0.0)
            Pd = pref.P
            acc_pt += np.where(win, Pd[:, 1, 1], 0.0)
            acc_pf += np.where(win, Pd[:, 3, 3], 0.0)

            # ---- NCO commands for the next interval
            t_next_mid = (bank.sample_ptr + 0.5 * fs * T_CA) / fs
            u = t_next_mid * 1000.0
            j = np.floor(u).astype(np.int64)
            j = np.clip(j, 0, outer.n_filled - 2)
            fr = u - j
            aid = outer.aid_doppler[j, rows] * (1.0 - fr) + outer.aid_doppler[j + 1, rows] * fr
            if inner is not None:
                inner.apply(pref, bank, aid_doppler_hz=aid, use_aid=use_aid)
            else:
                self._outer_only_nco(bank, pref, aid, t_next_mid, ins, outer)
            timing["prefilter"] += time.perf_counter() - tw

            # ---- tight filter update at the decimated rate, once every channel passed t_next_upd
            if tk.min() >= t_next_upd:
                tw = time.perf_counter()
                t_u = t_next_upd
                ok = acc_n > 0
                nn = np.maximum(acc_n, 1)
                m_cp = acc_cp / nn
                m_f = acc_f / nn
                m_a = acc_a / nn
                dz_pr = CHIP_M * m_cp
                dz_prr = LAMBDA_L1 * m_f
                var_pr = CHIP_M ** 2 * (acc_pt / nn) * opt.meas_corr_factor + opt.pr_sigma_floor_m ** 2
                var_prr = (LAMBDA_L1 / two_pi) ** 2 * (acc_pf / nn) * opt.meas_corr_factor \
                    + opt.prr_sigma_floor_mps ** 2
                valid = ok & (m_a > opt.amp_min)
                pos_e, vel_e, C_el = ins.pos_vel_e()
                lat, lon, h = ins.llh
                rm, rn = radii(lat)
                M_pos = tightmod.pos_error_to_enu(lat, h, rm, rn)
                los_l = ring_los(outer, pos_e, vel_e, ins, t_sins) @ C_el
                Phi, Qd = tightmod.phi_q(ins, t_upd_step, self.imu_noise, opt.clock_q_drift)
                tf.predict(Phi, Qd)
                dx = tf.update(dz_pr, dz_prr, los_l, M_pos, var_pr, var_prr, valid)
                if np.any(dx != 0.0):
                    ins.feedback(dx)
                    tf.reset()
                    n_feedback += 1
                    # keep the residual predictions consistent with the corrected SINS
                    pos_e, vel_e, C_el = ins.pos_vel_e()
                    pr_fix = outer.predict(t_sins, pos_e, vel_e, ins.clk_b, ins.clk_d)
                    i1 = (ring_k - 1) % ring_n
                    dcp = np.mod(pr_fix["code_phase_chips"] - ring_cp[i1] + 0.5 * CA_LEN, CA_LEN) - 0.5 * CA_LEN
                    dfp = pr_fix["doppler_hz"] - ring_f[i1]
                    ring_cp += dcp
                    ring_f += dfp
                    ring_r[i1] = pr_fix["code_rate_cps"]
                    vel_e_prev = vel_e.copy()
                sig_dopp = tightmod.doppler_sigma_hz(tf.P, los_l, LAMBDA_L1)
                if inner is not None:
                    use_aid = (sig_dopp < opt.arbitration_sigma_hz)
                    mode_now = np.where(use_aid, MODE_COMBINED, MODE_INNER).astype(np.int8)
                nav["t"].append(t_u)
                nav["pos_e"].append(pos_e.copy())
                nav["vel_e"].append(vel_e.copy())
                nav["clk"].append([ins.clk_b, ins.clk_d])
                nav["sig"].append(sig_dopp.copy())
                # start the next window with the epochs already past t_next_upd
                acc_n[:] = 0
                acc_cp[:] = 0
                acc_f[:] = 0
                acc_pt[:] = 0
                acc_pf[:] = 0
                acc_a[:] = 0
                t_next_upd += t_upd_step
                timing["tight"] += time.perf_counter() - tw
            k_ep += 1
            if progress and k_ep % 5000 == 0:
                print(f"  {self.method}: {k_ep / 1000.0:6.1f} s", flush=True)

        runtime = time.perf_counter() - t_wall0
        n = k_ep
        info = {
            "options": self.opt.as_dict(),
            "wipeoff_mode": wipe.mode,
            "n_epochs": n,
            "n_tight_updates": tf.n_updates,
            "n_tight_rejected": tf.n_rejected,
            "n_feedback": n_feedback,
            "timing_s": timing,
            "prefilter": pref.describe() if hasattr(pref, "describe") else {},
            "prefilter_resets": np.asarray(getattr(pref, "n_resets", np.zeros(n_ch))).tolist(),
            "arbitration_rule": "combined when sigma_doppler_i = sqrt(u'Pvv u + Pdd - 2u'Pvd)/lambda < "
                                f"{opt.arbitration_sigma_hz} Hz (tight filter P), else inner loop alone",
            "startup": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                        for k, v in st.items() if k.startswith("err_") or k == "sigmas"},
        }
        return EngineResult(
            method=self.method, prns=list(self.prns), t_start=rec_t[:n], doppler_hz=rec_f[:n],
            code_phase_chips=rec_cp[:n], amp=rec_a[:n], mode=rec_mode[:n],
            nav_t=np.asarray(nav["t"]), nav_pos_e=np.asarray(nav["pos_e"]).reshape(-1, 3),
            nav_vel_e=np.asarray(nav["vel_e"]).reshape(-1, 3), nav_clk=np.asarray(nav["clk"]).reshape(-1, 2),
            nav_sigma_doppler_hz=np.asarray(nav["sig"]).reshape(-1, n_ch), runtime_s=runtime,
            duration_s=n * T_CA, info=info)

    def _outer_only_nco(self, bank, pref, aid, t_next_mid, ins, outer):
        raise NotImplementedError


def ring_los(outer, pos_e, vel_e, ins, t):
    """Unit lines of sight (ECEF) at the current SINS state."""
    return outer.predict(t, pos_e, vel_e, ins.clk_b, ins.clk_d)["los_e"]
