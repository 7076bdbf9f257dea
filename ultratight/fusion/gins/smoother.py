"""Fixed-interval Rauch–Tung–Striebel smoothing of the closed-loop error-state filter.

The forward filter feeds its error estimate back into the nominal (SINS state, bias and clock
estimates) after every update and restarts from δx = 0.  At covariance node k it stores the
transition Φ_k (from node k−1), the prior P⁻_k (the prior actually used: the faded one for
``afm-aukf``), the posterior P⁺_k and the error state δx_k it fed back (zero without an update).
With the nominal changing at every feedback, each node has two nominals: N⁻_k before and N⁺_k
after the feedback, N⁺_k = N⁻_k − δx_k (estimate minus truth), so an error δ relative to N⁺_k
is δ + δx_k relative to N⁻_k.  The forward means are zero relative to their own nominals
(x⁺_k = 0 relative to N⁺_k, x⁻_{k+1} = Φ x⁺_k = 0 relative to N⁻_{k+1}), and the backward pass is::

    C_k   = P⁺_k Φ_{k+1}ᵀ (P⁻_{k+1})⁻¹
    δs_k  = C_k (δs_{k+1} + δx_{k+1})                   (relative to N⁺_k)
    Ps_k  = P⁺_k + C_k (Ps_{k+1} − P⁻_{k+1}) C_kᵀ

from δs_K = 0, Ps_K = P⁺_K at the last node.  Between two nodes the nominal is the forward
SINS run from N⁺_{k−1} to N⁻_k; the smoothed correction of an IMU sample there is the linear
interpolation in time of δs_{k−1} and δs_k + δx_k (the error is smooth over one covariance
step, 50 ms at the default 20 Hz).  The position block is in metres (north, east, up).
"""

from __future__ import annotations

import numpy as np

from ultratight.fusion.estimators.guards import symmetrize


def rts_backward(Phi, P_prior, P_post, dx):
    """(δs (K, n), Ps (K, n, n)) of the module's backward pass over K nodes.

    ``Phi[k]`` maps node k−1 to node k (``Phi[0]`` unused), ``P_prior[k]`` / ``P_post[k]`` the
    prior / posterior covariance at node k, ``dx[k]`` the error state fed back at node k."""
    K, n = dx.shape
    ds = np.zeros((K, n))
    Ps = np.empty((K, n, n))
    Ps[-1] = P_post[-1]
    for k in range(K - 2, -1, -1):
        Pp = P_prior[k + 1]
        try:
            C = np.linalg.solve(Pp, Phi[k + 1] @ P_post[k]).T     # P⁺ Φᵀ (P⁻)⁻¹ with P⁻ symmetric
        except np.linalg.LinAlgError:
            C = P_post[k] @ Phi[k + 1].T @ np.linalg.pinv(Pp)
        ds[k] = C @ (ds[k + 1] + dx[k + 1])
        Ps[k] = symmetrize(P_post[k] + C @ (Ps[k + 1] - Pp) @ C.T)
    return ds, Ps


def sample_corrections(node_t, ds, dx, t, chunk):
    """(n_samples, n) smoothed corrections of the samples relative to the pre-feedback nominal.

    ``chunk[i]`` is the node that closes the interval holding sample i (0 for the first sample,
    the alignment node); the correction is (1 − w) δs_{c−1} + w (δs_c + δx_c), w the time fraction."""
    c = np.asarray(chunk, int)
    prev = np.maximum(c - 1, 0)
    span = node_t[c] - node_t[prev]
    w = np.where(span > 0, (t - node_t[prev]) / np.where(span > 0, span, 1.0), 1.0)
    w = np.clip(w, 0.0, 1.0)[:, None]
    return (1.0 - w) * ds[prev] + w * (ds[c] + dx[c])
