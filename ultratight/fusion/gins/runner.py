"""INS/GNSS integration of recorded logs: :func:`run_gins` (``ultratight integrate``).

Closed-loop error-state filter (15 states loose, 17 tight; :mod:`ultratight.ins.error_model`
layout, position block in metres north/east/up as in
:mod:`ultratight.fusion.coupling.integration`):

* **Alignment** (:mod:`ultratight.fusion.gins.alignment`): the filter and the result start at
  the alignment epoch.
* **Propagation**: the SINS (:func:`ultratight.ins.sins.sins_step`) at every IMU sample with its
  own interval length and the bias estimates removed from the increments; the covariance at
  ``cov_rate_hz`` (10 Hz): Φ and Q_d over each covariance step from the state at the step's end
  and the step's mean specific force
  (:func:`ultratight.fusion.coupling.integration.discrete_model`, second-order Φ, trapezoidal Q_d).
  Covariance steps also end at the IMU sample nearest each GNSS epoch.  Q from ImuNoise only:
  gyro ARW², accelerometer VRW², gyro and accelerometer bias random-walk PSDs; clock PSDs for
  tight coupling (``clock_psd``).
* **Reported covariance** (:mod:`ultratight.fusion.gins.consider`): the covariance of the
  filter's actual error with the sensors' scale-factor and cross-axis errors (ImuNoise
  ``gyro_sf``, ``gyro_cross``, ``accel_sf``, ``accel_cross``) considered, propagated beside the
  design covariance with the filter's own gains; the reported σ and the χ² gate use it.
* **Updates** (:mod:`ultratight.fusion.gins.updates`, :mod:`ultratight.fusion.gins.cores`) at the
  node of each GNSS epoch (the position predicted to the epoch's time with the velocity), then
  ZUPT / NHC at most every ``aid_interval_s``; the error state is fed back after the updates of a
  node (attitude, velocity, position into the SINS state, biases into the bias estimates, clock)
  and reset.
* **Outages**: GNSS epochs inside ``outages`` are not used (tight: ``outage_keep_sats``
  highest-elevation satellites kept); samples inside are marked ``in_outage``.
* **Smoother** (:mod:`ultratight.fusion.gins.smoother`) when ``smooth``.
* Output per IMU sample between covariance nodes: the SINS state (forward), σ from the prior
  covariance of the closing node (the posterior at the node's own sample).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ultratight.errors import ConfigError
from ultratight.fusion.coupling.integration import discrete_model, imu_psd, pos_scale
from ultratight.fusion.gins import alignment, results, updates
from ultratight.fusion.gins.consider import ConsiderCovariance
from ultratight.fusion.gins.cores import make_core
from ultratight.fusion.gins.options import check_options, in_windows
from ultratight.ins import error_model as em
from ultratight.ins.attitude import quat_to_dcm
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
from ultratight.ins.sins import sins_step


@njit(cache=True)
def propagate(x, dtheta, dv, dts, j_from, j_to, bias, out_q, out_v, out_p, i_off):
    """SINS from sample j_from to j_to − 1 with the bias estimates removed; writes the state after
    each sample to the outputs at index j − i_off; returns the summed compensated (dθ, dv)."""
    a = np.empty(3)
    b = np.empty(3)
    s = np.zeros(6)
    for j in range(j_from, j_to):
        for i in range(3):
            a[i] = dtheta[j, i] - bias[i] * dts[j]
            b[i] = dv[j, i] - bias[3 + i] * dts[j]
            s[i] += a[i]
            s[3 + i] += b[i]
        sins_step(x, a, b, dts[j])
        out_q[j - i_off] = x[0:4]
        out_v[j - i_off] = x[4:7]
        out_p[j - i_off] = x[7:10]
    return s


def _schedule(imu, j0, src, opts):
    """(node sample indices, {node: [epoch indices]}, per-epoch reason for epochs never reached)."""
    n = imu.n
    dt_med = float(np.median(np.diff(imu.t))) if n > 1 else 1.0 / imu.rate_hz
    step = max(1, int(round(1.0 / (opts.cov_rate_hz * dt_med))))
    by_node = {}
    reason = [""] * src.n
    for k in range(src.n):
        tk = src.t[k]
        if tk <= imu.t[j0]:
            reason[k] = "before the alignment epoch"
            continue
        if tk > imu.t[-1] + 0.5 * dt_med:
            reason[k] = "after the IMU log"
            continue
        j = int(np.searchsorted(imu.t, tk))
        j = j if j < n and (j == 0 or abs(imu.t[j] - tk) <= abs(imu.t[j - 1] - tk)) else j - 1
        by_node.setdefault(max(j, j0 + 1), []).append(k)
    grid = np.arange(j0 + step, n, step)
    g = np.array(sorted(by_node), int)
    if g.size:      # a grid node within half a step of a GNSS node is dropped (the GNSS node replaces it)
        i = np.clip(np.searchsorted(g, grid), 1, g.size - 1) if g.size > 1 else np.zeros(grid.size, int)
        near = np.minimum(np.abs(grid - g[i]), np.abs(grid - g[np.maximum(i - 1, 0)]))
        grid = grid[near > step // 2]
    nodes = np.unique(np.concatenate([[j0], grid, g, [n - 1]]).astype(int))
    return nodes, by_node, reason


class GinsRun:
    """One forward pass (state, core, storage); :func:`run_gins` drives it node by node."""

    def __init__(self, imu, opts, src, al, outages, still):
        self.imu, self.o, self.src, self.al = imu, opts, src, al
        self.outages, self.still = outages, still
        self.tight = src.kind == "tight"
        self.ns = em.N17 if self.tight else em.N15
        nz = opts.noise
        self.q_psd = imu_psd(nz.gyro_arw, nz.accel_vrw, nz.gyro_bias_rw ** 2, nz.accel_bias_rw ** 2, self.ns)
        self.dts = alignment.sample_dt(imu)
        self.x = al.x_sins.copy()
        self.bias = al.bias.copy()
        self.clk = np.zeros(2)
        P0 = al.P0
        if self.tight:
            P0 = np.zeros((self.ns, self.ns))
            P0[:em.N15, :em.N15] = al.P0
            P0[em.CLK, em.CLK], P0[em.DRIFT, em.DRIFT] = np.asarray(opts.clock_sigma0, float) ** 2
            pos_e = np.asarray(llh_to_ecef(*self.x[7:10]), float)
            clk0 = src.initial_clock(al.info["epoch"], pos_e, dcm_ecef_from_enu(self.x[7], self.x[8]) @ self.x[4:7])
            self.clk[:] = np.where(np.isfinite(clk0), clk0, 0.0)
        m_gnss = 6 if (not self.tight and self._has_velocity()) else 3
        self.core = make_core(opts.filter, P0, opts, m_gnss)
        self.consider = ConsiderCovariance(nz, self.core.P, opts.nhc_sigma_mps if opts.nhc else None)
        self.consider.track = bool(opts.smooth)
        self.nodes, self.by_node, self.reason = _schedule(imu, al.j0, src, opts)
        self.store = results.Storage(imu, al.j0, self.nodes, self.ns, opts.smooth, src.n)
        self.store.node_post(0, self.x, self.bias, self.clk, self.core.P, np.zeros(self.ns), self.core.P,
                             np.eye(self.ns), self.core.P, self.core.P)
        self.store.node_consider(0, self.consider)
        self.next_aid = -np.inf
        self.n_rejected_run = 0
        self.row_runs = {}

    def _has_velocity(self):
        return bool(self.o.use_velocity and np.any(np.all(np.isfinite(self.src.fx.vel_enu), axis=1)))

    def step(self, c):
        """Covariance node c: propagate from node c−1, update, feed back, store."""
        a, b = int(self.nodes[c - 1]), int(self.nodes[c])
        st = self.store
        s = propagate(self.x, self.imu.dtheta_b, self.imu.dv_b, self.dts, a + 1, b + 1, self.bias,
                      st.q, st.v, st.p, self.al.j0)
        T = float(self.imu.t[b] - self.imu.t[a])
        self.omega_b = s[0:3] / T
        self.clk[0] += self.clk[1] * T
        clock_qd = None
        if self.tight:
            Sb, Sd = self.o.clock_psd
            clock_qd = np.array([[Sb * T + Sd * T ** 3 / 3.0, Sd * T ** 2 / 2.0], [Sd * T ** 2 / 2.0, Sd * T]])
        if getattr(self.core, "wants_basis", False):
            Phi, Qd, B, Qf = discrete_model(self.x, s[3:6] / T, T, self.q_psd, self.ns, clock_qd, basis=True)
            self.core.predict(Phi, Qd, (B, Qf))
        else:
            Phi, Qd = discrete_model(self.x, s[3:6] / T, T, self.q_psd, self.ns, clock_qd)
            self.core.predict(Phi, Qd)
        self.consider.predict(Phi, Qd, quat_to_dcm(self.x[0:4]), s[0:3], s[3:6])
        P_prior = self.core.P
        Pt_prior = self.consider.covariance(P_prior)
        updated = False
        self.core.prior_used = None
        for k in self.by_node.get(b, ()):
            updated |= self.gnss_update(k, b)
            if self.core.prior_used is not None:
                P_prior = self.core.prior_used
        updated |= self.aid_updates(b)
        dx = self.core.x.copy()
        if updated:
            self.feedback(dx)
        st.node_post(c, self.x, self.bias, self.clk, self.core.P, dx, P_prior, Phi,
                     self.consider.covariance(self.core.P), Pt_prior)
        st.node_consider(c, self.consider)

    def feedback(self, dx):
        """Closed-loop reset: the error state into the SINS state, bias and clock estimates."""
        d = dx.copy()
        d[em.POS] = d[em.POS] / pos_scale(self.x[7], self.x[9])
        if self.tight:
            self.clk -= d[em.CLK:em.DRIFT + 1]
        em.feedback_and_reset(self.x, d, self.bias)
        self.core.reset()

    def gnss_update(self, k, b):
        """GNSS epoch k at node b; returns whether it was used (the update log gets its reason)."""
        t_k = float(self.src.t[k])
        log = self.store
        out = bool(in_windows([t_k], self.outages)[0])
        keep = None
        if out and (not self.tight or self.o.outage_keep_sats == 0):
            self.core.gap()
            log.epoch(k, t_k, False, 0, np.nan, False, -1, "outage")
            return False
        if out:
            keep = int(self.o.outage_keep_sats)
        rows = self._rows(k, b, keep)
        if rows is None:
            log.epoch(k, t_k, False, 0, np.nan, False, -1, "no measurement")
            return False
        z, H, R, quality = rows
        p = None if self.core.own_gate else self.o.gate_p
        mask, nis, why = updates.gate(z - H @ self.core.x, H, self.core.gate_R(R),
                                      self.consider.covariance(self.core.P), p, per_row=self.tight)
        if self.tight:
            mask, why = self._release_rows(quality, mask, why)
            quality = -1
        elif not mask.all() and self.n_rejected_run >= self.o.gate_release:
            mask[:] = True
            why = f"used after {self.n_rejected_run} rejected epochs ({why})"
        if not mask.any():
            self.n_rejected_run += 1
            log.epoch(k, t_k, False, z.shape[0], nis, True, quality, why)
            return False
        self.n_rejected_run = 0
        z, H, R = z[mask], H[mask], R[np.ix_(mask, mask)]
        P_before = self.core.P
        self.core.update_gnss(z, H, R)
        self.consider.update(self.core.prior_used if self.core.prior_used is not None else P_before, H,
                             self.core.gate_R(R))
        log.epoch(k, t_k, True, z.shape[0], nis, not mask.all(), quality, why)
        return True

    def _release_rows(self, keys, mask, why):
        """Tight gate release: a row (PRN and kind) rejected in ``gate_release`` consecutive epochs is
        used in the next one (its count restarts)."""
        runs = self.row_runs
        for i, key in enumerate(keys):
            key = int(key)
            if mask[i]:
                runs[key] = 0
            elif runs.get(key, 0) >= self.o.gate_release:
                mask[i] = True
                runs[key] = 0
                why += f"; row {key} used after {self.o.gate_release} rejections"
            else:
                runs[key] = runs.get(key, 0) + 1
        return mask, why

    def _rows(self, k, b, keep):
        if self.tight:
            return self.src.rows(k, self.x, self.clk, self.omega_b, self.o.lever_arm_b, keep=keep)
        fix = self.src.fix(k)
        if fix is None:
            return None
        z, H, R = updates.loose_rows(fix, self.x, self.omega_b, self.o.lever_arm_b, float(self.imu.t[b]))
        return z, H, R, fix.quality

    def aid_updates(self, b):
        """ZUPT (still IMU) and NHC at most every aid_interval_s; returns whether one was made."""
        o = self.o
        if not (o.zupt or o.nhc) or self.imu.t[b] < self.next_aid:
            return False
        self.next_aid = self.imu.t[b] + o.aid_interval_s - 1e-9
        rows, nhc = None, False
        if o.zupt and self.still[b]:
            rows = updates.zupt_rows(self.x, o.zupt_sigma_mps, self.ns)
            self.store.n_zupt += 1
        elif o.nhc and np.linalg.norm(self.x[4:7]) >= o.nhc_min_speed_mps:
            rows, nhc = updates.nhc_rows(self.x, o.nhc_sigma_mps, self.ns), True
            self.store.n_nhc += 1
        if rows is None:
            return False
        P_before = self.core.P
        self.core.update_aid(*rows)
        self.consider.update(P_before, rows[1], rows[2], nhc=nhc)
        return True


def _source(opts, fixes, tight):
    if opts.coupling == "loose":
        if fixes.n < 1:
            raise ConfigError("gins: the GNSS fixes are empty")
        return updates.LooseSource(fixes, opts)
    return updates.TightSource(tight, opts)


def run_gins(imu, options, fixes=None, tight=None, progress=None):
    """INS/GNSS solution of a recorded IMU log with GNSS fixes (loose) or raw measurements
    (``tight``: the tight measurement object) -> :class:`ultratight.fusion.gins.options.GinsResult`.
    ``progress(fraction)`` is called now and then when given."""
    outages = check_options(options, fixes, tight)
    if imu.n < 3:
        raise ConfigError(f"gins: the IMU log has {imu.n} samples; need at least 3")
    src = _source(options, fixes, tight)
    al, still = alignment.align(imu, options, src)
    run = GinsRun(imu, options, src, al, outages, still)
    for k, why in enumerate(run.reason):
        if why:
            run.store.epoch(k, float(src.t[k]), False, 0, np.nan, False, -1, why)
    n_nodes = len(run.nodes)
    for c in range(1, n_nodes):
        run.step(c)
        if progress is not None and c % 500 == 0:
            progress(c / n_nodes)
    res = results.assemble(run, outages)
    if progress is not None:
        progress(1.0)
    return res
