"""What the forward pass stores (:class:`Storage`) and the :class:`GinsResult` built from it
(:func:`assemble`), smoothed when asked (:mod:`ultratight.fusion.gins.smoother`).

Per IMU sample from the alignment sample on: the SINS state as propagated (before the feedback
of its node).  Per covariance node: the state, bias and clock estimates after the feedback, the
covariance diagonal and attitude block before and after the updates, the error state fed back and,
when smoothing, Φ, P⁻ and P⁺.  Per GNSS epoch: the update log.

Reported σ: position east/north/up from the metre position block, velocity ENU, attitude roll /
pitch / yaw from the ENU attitude-error block resolved along and across the heading (roll: the
component about the horizontal forward axis, pitch: about the horizontal right axis, yaw: about up).
"""

from __future__ import annotations

import numpy as np

from ultratight.fusion.gins.consider import consider_smoother
from ultratight.fusion.gins.options import GinsResult, in_windows
from ultratight.fusion.gins.smoother import rts_backward, sample_corrections
from ultratight.ins import error_model as em
from ultratight.ins.attitude import dcm_to_quat_vec, quat_to_dcm_vec, rotvec_to_dcm_vec
from ultratight.ins.earth import radii


class Storage:
    """Arrays the forward pass fills (module docstring)."""

    def __init__(self, imu, j0, nodes, ns, smooth, n_epochs):
        n = imu.n - j0
        self.j0 = j0
        self.t = np.asarray(imu.t[j0:], float)
        self.q = np.empty((n, 4))
        self.v = np.empty((n, 3))
        self.p = np.empty((n, 3))
        K = len(nodes)
        self.node_j = np.asarray(nodes, int)
        self.node_t = np.asarray(imu.t, float)[self.node_j]
        self.x_post = np.empty((K, 10))
        self.bias_post = np.empty((K, 6))
        self.clk_post = np.empty((K, 2))
        self.d_prior = np.empty((K, ns))
        self.d_post = np.empty((K, ns))
        self.a_prior = np.empty((K, 3, 3))
        self.a_post = np.empty((K, 3, 3))
        self.dx = np.zeros((K, ns))
        self.smooth = bool(smooth)
        if self.smooth:
            self.Phi = np.empty((K, ns, ns))
            self.P_prior = np.empty((K, ns, ns))
            self.P_post = np.empty((K, ns, ns))
        self.log = {"t": np.full(n_epochs, np.nan), "used": np.zeros(n_epochs, bool),
                    "n_rows": np.zeros(n_epochs, int), "nis": np.full(n_epochs, np.nan),
                    "rejected": np.zeros(n_epochs, bool), "quality": np.full(n_epochs, -1, int),
                    "reason": [""] * n_epochs}
        self.n_zupt = 0
        self.n_nhc = 0
        self.cons = None            # when smoothing with considered errors: :class:`ConsiderNodes`

    def node_post(self, c, x, bias, clk, P, dx, P_prior, Phi, Pt, Pt_prior):
        """Node c after its updates: the design filter's P (posterior) and P_prior (what the
        smoother needs), and the reported covariances Pt / Pt_prior (of the filter's actual error,
        :mod:`ultratight.fusion.gins.consider`)."""
        if c == 0:
            self.q[0], self.v[0], self.p[0] = x[0:4], x[4:7], x[7:10]
        self.x_post[c] = x[0:10]
        self.bias_post[c] = bias
        self.clk_post[c] = clk
        self.d_prior[c] = np.diag(Pt_prior)
        self.d_post[c] = np.diag(Pt)
        self.a_prior[c] = Pt_prior[em.ATT, em.ATT]
        self.a_post[c] = Pt[em.ATT, em.ATT]
        self.dx[c] = dx
        if self.smooth:
            self.Phi[c], self.P_prior[c], self.P_post[c] = Phi, P_prior, P

    def node_consider(self, c, cc):
        """Node c's considered covariances and composite update (:class:`ConsiderNodes`), when smoothing."""
        if not (self.smooth and cc.on):
            return
        if self.cons is None:
            self.cons = ConsiderNodes(len(self.node_j), self.d_post.shape[1], cc.pss)
        self.cons.store(c, cc)

    def epoch(self, k, t, used, n_rows, nis, rejected, quality, reason):
        lg = self.log
        lg["t"][k], lg["used"][k], lg["n_rows"][k], lg["nis"][k] = t, used, n_rows, nis
        lg["rejected"][k], lg["quality"][k], lg["reason"][k] = rejected, quality, reason


class ConsiderNodes:
    """Per covariance node, what :func:`ultratight.fusion.gins.consider.consider_smoother` needs."""

    def __init__(self, K, n, pss):
        m = pss.size
        self.pss = pss
        self.Pt, self.Pts = np.empty((K, n, n)), np.zeros((K, n, m))
        self.L, self.J, self.N = np.tile(np.eye(n), (K, 1, 1)), np.zeros((K, n, m)), np.zeros((K, n, n))
        self.G, self.Q = np.zeros((K, n, m)), np.zeros((K, n, n))

    def store(self, c, cc):
        self.Pt[c], self.Pts[c] = cc.Pt, cc.Pts
        if c > 0:
            self.L[c], self.J[c], self.N[c], self.G[c], self.Q[c] = cc.L, cc.J, cc.N, cc.G, cc.Q


def euler_from_q(q):
    """(n, 3) roll, pitch, yaw (yaw clockwise from north in [0, 2π)) of q_lb (FLU body -> ENU)."""
    C = quat_to_dcm_vec(q)
    roll = np.arctan2(C[:, 2, 1], C[:, 2, 2])
    pitch = np.arcsin(np.clip(C[:, 2, 0], -1.0, 1.0))
    yaw = np.mod(0.5 * np.pi - np.arctan2(C[:, 1, 0], C[:, 0, 0]), 2.0 * np.pi)
    return np.column_stack([roll, pitch, yaw])


def _att_sigma(A, yaw):
    s, c = np.sin(yaw), np.cos(yaw)
    fwd = np.column_stack([s, c, np.zeros_like(s)])
    rgt = np.column_stack([c, -s, np.zeros_like(s)])
    vr = np.einsum("ni,nij,nj->n", fwd, A, fwd)
    vp = np.einsum("ni,nij,nj->n", rgt, A, rgt)
    return np.sqrt(np.maximum(np.column_stack([vr, vp, A[:, 2, 2]]), 0.0))


def _pos_scale_vec(llh):
    rm, rn = np.vectorize(radii)(llh[:, 0])
    return np.column_stack([rm + llh[:, 2], (rn + llh[:, 2]) * np.cos(llh[:, 0]), np.ones(llh.shape[0])])


def _make(st, q, v, p, bias, clk, dvar, A, in_out, tight, smoothed, forward=None):
    eul = euler_from_q(q)
    sd = np.sqrt(np.maximum(dvar, 0.0))
    return GinsResult(t=st.t.copy(), llh=p, vel_enu=v, euler_rad=eul, sigma_pos_enu=sd[:, [7, 6, 8]],
                      sigma_vel_enu=sd[:, 3:6], sigma_att_rad=_att_sigma(A, eul[:, 2]), gyro_bias=bias[:, 0:3],
                      accel_bias=bias[:, 3:6], clock=clk if tight else None, in_outage=in_out, smoothed=smoothed,
                      forward=forward)


def _forward(st, chunk, at_node, tight, in_out):
    q, v, p = st.q.copy(), st.v.copy(), st.p.copy()
    xs = st.x_post[chunk[at_node]]
    q[at_node], v[at_node], p[at_node] = xs[:, 0:4], xs[:, 4:7], xs[:, 7:10]
    prev = np.maximum(chunk - 1, 0)
    bias = np.where(at_node[:, None], st.bias_post[chunk], st.bias_post[prev])
    clk = st.clk_post[prev].copy()
    clk[:, 0] += clk[:, 1] * (st.t - st.node_t[prev])
    clk[at_node] = st.clk_post[chunk[at_node]]
    dvar = np.where(at_node[:, None], st.d_post[chunk], st.d_prior[chunk])
    A = np.where(at_node[:, None, None], st.a_post[chunk], st.a_prior[chunk])
    return _make(st, q, v, p, bias, clk, dvar, A, in_out, tight, False)


def _smoothed(st, chunk, tight, in_out, fwd):
    ds, Ps = rts_backward(st.Phi, st.P_prior, st.P_post, st.dx)
    corr = sample_corrections(st.node_t, ds, st.dx, st.t, chunk)
    C = rotvec_to_dcm_vec(corr[:, em.ATT]) @ quat_to_dcm_vec(st.q)
    q = dcm_to_quat_vec(C)
    v = st.v - corr[:, em.VEL]
    p = st.p - corr[:, em.POS] / _pos_scale_vec(st.p)
    prev = np.maximum(chunk - 1, 0)
    bias = st.bias_post[prev] + corr[:, 9:15]
    clk = st.clk_post[prev].copy()
    clk[:, 0] += clk[:, 1] * (st.t - st.node_t[prev])
    if tight:
        clk -= corr[:, em.CLK:em.DRIFT + 1]
    span = st.node_t[chunk] - st.node_t[prev]
    w = np.where(span > 0, (st.t - st.node_t[prev]) / np.where(span > 0, span, 1.0), 1.0)[:, None]
    if st.cons is not None:         # the σ of the smoothed solution's actual error (considered errors)
        Ps = consider_smoother(st.Phi, st.P_prior, st.P_post, st.cons)
    dP = np.einsum("kii->ki", Ps)
    dvar = (1 - w) * dP[prev] + w * dP[chunk]
    Aa = Ps[:, em.ATT, em.ATT]
    A = (1 - w[:, :, None]) * Aa[prev] + w[:, :, None] * Aa[chunk]
    res = _make(st, q, v, p, bias, clk, dvar, A, in_out, tight, True, forward=fwd)
    res.meta["smoothed_node_sigma_pos_enu"] = np.sqrt(np.maximum(dP[:, [7, 6, 8]], 0.0))
    return res


def assemble(run, outages):
    """The :class:`GinsResult` of a finished forward pass (smoothed when the options say so)."""
    st = run.store
    j = np.arange(st.j0, st.j0 + st.t.shape[0])
    chunk = np.searchsorted(st.node_j, j)
    at_node = st.node_j[chunk] == j
    in_out = in_windows(st.t, outages)
    res = _forward(st, chunk, at_node, run.tight, in_out)
    if st.smooth:
        res = _smoothed(st, chunk, run.tight, in_out, res)
    log = dict(st.log)
    log["reason"] = list(log["reason"])
    res.updates = log
    res.alignment = dict(run.al.info)
    o = run.o
    res.meta = {**res.meta, "options": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in vars(o).items()
                                        if k != "noise"},
                "noise": o.noise.to_datasheet(), "noise_source": o.noise.source,
                "counts": {"imu_samples": int(st.t.shape[0]), "nodes": int(st.node_j.shape[0]),
                           "epochs": int(len(log["t"])), "used": int(np.sum(log["used"])),
                           "rejected": int(np.sum(log["rejected"])), "zupt": st.n_zupt, "nhc": st.n_nhc,
                           "faulty_dims": int(getattr(run.core, "n_faulty", 0))}}
    if res.forward is not None:
        res.forward.updates, res.forward.alignment, res.forward.meta = res.updates, res.alignment, res.meta
    return res

