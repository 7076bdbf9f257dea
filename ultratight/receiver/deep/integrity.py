"""Integrity of the ultra-tight navigation solution: does the solution still agree with the
measurements? (docs/ultratight.md, "Integrity").

At every tight-filter update (10 Hz) :meth:`IntegrityMonitor.update` runs three tests on what the
update received — the decimated residuals ``dz_pr``/``dz_prr`` of each channel against the outer
loop's SINS predictions, the rows the engine offered (``valid``), the prior covariance and the
measurement matrix of :func:`ultratight.fusion.coupling.tight.measurement_matrix`:

1. **Windowed NIS test** (Bar-Shalom, Li & Kirubarajan 2001, §5.4): the normalised innovation
   squared ``r' S^-1 r`` (``S = H P H' + R`` from the prior covariance) of the rows the filter's gate
   accepted, less the channels that disagree on their own (test 3: a single channel's fault is not the
   solution's), summed over the updates of the last ``window_s``, against the chi-square quantile of
   the summed degrees of freedom, ``chdtri(dof, alpha)``. Under a consistent filter the sum is
   chi-square with that many degrees of freedom, so one window fails with probability ``alpha``.
2. **Gated rows**: the share of the offered rows the filter's own innovation gate rejected over the
   same window; a filter that throws most of its measurements away is not consistent whatever the
   NIS of the rest says.
3. **Channels against the solution**: each channel's code and Doppler residual standardised by its
   prior innovation sigma, ``sqrt(H_i P H_i' + R_i)``; a channel disagrees beyond ``channel_k``. When
   at least ``channel_frac`` of the channels, and at least ``channel_min`` of them, disagree at the
   same update, the navigation solution is wrong, not the channels (a filter that follows a wrong
   solution keeps the channels that agree with it and gates the others out).

An update *fails* when any test fails; a failure is *gross* when most rows were gated out, most
channels disagree, or the window NIS exceeds ``nis_gross`` times its quantile (innovations twice the
sigma the filter claims). States, with hysteresis: ``ok`` -> ``degraded`` after ``degraded_s`` of
consecutive failing updates; ``degraded`` -> ``lost`` once the gross failures since the state was
last ``ok`` add up to ``lost_s`` (short passes do not reset the count); back to ``ok`` after
``recover_s`` of consecutive passing updates. A filter a little overconfident (NIS over its
quantile, not grossly) is ``degraded`` -- its sigma is inflated -- but not ``lost``. An update
without any row to test (every channel below the amplitude threshold) counts towards ``degraded``
(the solution is unverified) but never makes it ``lost`` on its own.

While the state is not ``ok``, and at any update that fails a test, the reported 1-sigma is made
to cover the error (:meth:`IntegrityMonitor.cover`): scaled by ``sqrt(NIS / dof)`` of the window;
the position and velocity sigmas floored by a snapshot least-squares solution of the SINS error
from every offered code and Doppler residual (gated ones included), the position sigma also by the
velocity snapshots integrated since the failures began; and, once a failure is gross, by what a
misdirected specific force can do since then, ``|f| tau^2`` and ``2 |f| tau`` (acceleration error up
to ``2 |f|``). The last bound is needed because channels aided by a wrong solution follow part of
its error: their residuals show only some of it (a 90 degree axis error in a 2 g turn: 150 m off
while the residuals suggest 15 m).
"""

import math
from collections import deque
from dataclasses import asdict, dataclass, fields

import numpy as np

from ultratight.chi2 import chdtri
from ultratight.errors import ConfigError
from ultratight.fusion.coupling.tight import measurement_matrix

OK, DEGRADED, LOST = 0, 1, 2
STATE_NAMES = ("ok", "degraded", "lost")

# bits of the per-update failure flags (result dataset integrity/fail)
FAIL_NIS = 1          # window NIS above the chi-square quantile
FAIL_GATED = 2        # most offered rows gated out over the window
FAIL_CHANNELS = 4     # most channels disagree with the solution at this update
UNTESTED = 8          # no row offered at this update (nothing to test)
FAIL_NIS_GROSS = 16   # window NIS above nis_gross times the quantile
OUTLIER = 32          # a channel disagrees (not a failure by itself: it makes the sigma cover its residual)
GROSS = FAIL_GATED | FAIL_CHANNELS | FAIL_NIS_GROSS
FAILED = FAIL_NIS | UNTESTED | GROSS


@dataclass
class IntegrityThresholds:
    """The monitor's thresholds (``EngineOptions.integrity`` overrides any of them)."""

    window_s: float = 1.0          # sliding window of the NIS sum and of the gated-row share
    alpha: float = 1e-3            # false-alarm probability of one window's chi-square test
    nis_gross: float = 4.0         # a window NIS over this multiple of the quantile is a gross failure
    reject_frac: float = 0.5       # fail when more than this share of the window's offered rows was gated out
    channel_k: float = 3.0         # a channel disagrees when a standardised residual exceeds this
    channel_frac: float = 1.0 / 3.0  # fail when at least this share of the tested channels disagree ...
    channel_min: int = 3           # ... and at least this many (fewer: a channel fault, left out of the NIS)
    degraded_s: float = 1.0        # consecutive failing time before ``degraded``
    lost_s: float = 4.0            # failing time accumulated while degraded before ``lost``
    recover_s: float = 3.0         # consecutive passing time before ``ok`` again
    max_reinit: int = 3            # re-initialisations of a recording's run before it stops lost

    @classmethod
    def from_options(cls, overrides):
        known = {f.name for f in fields(cls)}
        bad = sorted(set(overrides or {}) - known)
        if bad:
            raise ConfigError(f"unknown integrity threshold(s) {bad}; expected some of {sorted(known)}")
        th = cls(**dict(overrides or {}))
        if not (0.0 < th.alpha < 1.0 and th.window_s > 0.0 and 0.0 < th.reject_frac <= 1.0
                and 0.0 < th.channel_frac <= 1.0 and th.channel_k > 0.0 and th.degraded_s >= 0.0
                and th.lost_s > 0.0 and th.recover_s > 0.0 and th.max_reinit >= 0):
            raise ConfigError(f"integrity thresholds out of range: {asdict(th)}")
        return th


def snapshot_error(dz, var, los_l):
    """Weighted least squares of ``dz_i = -e_i . d + b`` (``e_i`` ENU unit lines of sight, ``var_i`` the
    variances): ``(d, sigma_d)`` — the ENU error ``d`` of the SINS antenna position (from code residuals)
    or velocity (from Doppler residuals) with its 1-sigma per axis, or None with fewer than 5 rows."""
    dz = np.asarray(dz, float)
    ok = np.isfinite(dz) & np.isfinite(var) & (np.asarray(var) > 0.0)
    if ok.sum() < 5:
        return None
    G = np.hstack([-np.asarray(los_l, float)[ok], np.ones((int(ok.sum()), 1))])
    w = 1.0 / np.sqrt(np.asarray(var, float)[ok])
    A = G * w[:, None]
    try:
        N_inv = np.linalg.inv(A.T @ A)
    except np.linalg.LinAlgError:
        return None
    x = N_inv @ (A.T @ (dz[ok] * w))
    return x[:3], np.sqrt(np.maximum(np.diag(N_inv)[:3], 0.0))


def _nis(r, S):
    """Normalised innovation squared ``r' S^-1 r`` (0 without rows)."""
    if r.size == 0:
        return 0.0
    try:
        L = np.linalg.cholesky(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        return float(r @ np.linalg.pinv(S) @ r)
    y = np.linalg.solve(L, r)
    return float(y @ y)


class IntegrityMonitor:
    """The tests and states of the module docstring, one call of :meth:`update` per tight update."""

    def __init__(self, thresholds=None, rate_hz=10.0):
        self.th = thresholds or IntegrityThresholds()
        self.dt = 1.0 / float(rate_hz)
        n_win = max(1, int(round(self.th.window_s * rate_hz)))
        self.win = deque(maxlen=n_win)        # per update: (nis, dof, offered rows, gated rows)
        self.state = OK
        self.worst = OK
        self.fail_run = 0.0                   # consecutive failing time
        self.pass_run = 0.0                   # consecutive passing time
        self.bad_s = 0.0                      # failing time since the last recovery
        self.first_degraded_s = None
        self.first_lost_s = None
        self.lost_at_s = None
        self.last = {}
        self.ratio = 1.0                      # window NIS / dof (>= 1 when it inflates the sigma)
        self.t_gross = None                   # time of the first gross failure since the state was ok
        self.outlier = None                   # largest code and Doppler residual of a disagreeing channel
        self.snap_pos = None
        self.snap_vel = None
        self.drift = np.zeros(3)              # position error the velocity snapshots add up to since ``ok``

    # ---------------------------------------------------------------- the tests of one update
    def update(self, t, dz_pr, dz_prr, var_pr, var_prr, valid, los_l, M_pos, P_prior, gate_sigma, gated, lever=None):
        """Tests after the tight update at time ``t`` (s): ``dz_*``/``var_*``/``valid``/``los_l``/``M_pos``/
        ``lever`` as the filter's ``update`` received them, ``P_prior`` its covariance before the update,
        ``gate_sigma`` its innovation gate and ``gated`` the rows the gate rejected in this update.
        Returns the state (OK, DEGRADED, LOST)."""
        valid = np.asarray(valid, bool) & np.isfinite(dz_pr) & np.isfinite(dz_prr)
        offered = 2 * int(valid.sum())
        gated = int(gated)
        H = measurement_matrix(los_l, M_pos, lever)
        z = np.concatenate([dz_pr, dz_prr])
        S = H @ P_prior @ H.T + np.diag(np.concatenate([np.broadcast_to(var_pr, valid.shape),
                                                        np.broadcast_to(var_prr, valid.shape)]))
        u = np.abs(z) / np.sqrt(np.maximum(np.diag(S), 1e-300))
        m = valid.shape[0]
        out_ch = (u[:m] > self.th.channel_k) | (u[m:] > self.th.channel_k)
        n_ch, n_out = int(valid.sum()), int((out_ch & valid).sum())
        frac = n_out / n_ch if n_ch else 0.0
        # the rows the filter accepted (its gate), without the channels that disagree on their own
        # (fewer than channel_min: a channel fault, not the solution's): NIS over the rest
        keep = valid & ~out_ch if n_out < self.th.channel_min else valid
        out = out_ch & valid
        self.outlier = (float(np.max(np.abs(dz_pr[out]))), float(np.max(np.abs(dz_prr[out])))) if n_out else None
        rows = np.concatenate([keep, keep]) & (u <= gate_sigma)
        nis, dof = _nis(z[rows], S[np.ix_(rows, rows)]), int(rows.sum())
        self.win.append((nis, dof, offered, gated))
        nis_w = sum(w[0] for w in self.win)
        dof_w = sum(w[1] for w in self.win)
        off_w = sum(w[2] for w in self.win)
        gat_w = sum(w[3] for w in self.win)
        limit = float(chdtri(dof_w, self.th.alpha)) if dof_w > 0 else float("nan")
        flags = 0
        if dof_w > 0 and nis_w > limit:
            flags |= FAIL_NIS
            if nis_w > self.th.nis_gross * limit:
                flags |= FAIL_NIS_GROSS
        if off_w > 0 and gat_w > self.th.reject_frac * off_w:
            flags |= FAIL_GATED
        if n_out >= self.th.channel_min and frac >= self.th.channel_frac - 1e-12:
            flags |= FAIL_CHANNELS
        if offered == 0:
            flags |= UNTESTED
        if n_out:
            flags |= OUTLIER
        self.ratio = max(1.0, nis_w / dof_w) if dof_w > 0 else 1.0
        self.last = {"nis": nis_w, "dof": dof_w, "limit": limit, "gated_frac": gat_w / off_w if off_w else 0.0,
                     "disagree_frac": frac, "flags": flags}
        self._step(t, flags)
        if self.state == OK and not flags & ~UNTESTED:
            self.drift[:] = 0.0
            self.snap_pos = self.snap_vel = None
            return self.state
        if self.outlier is not None:
            self.drift += self.outlier[1] * self.dt
        # the error the residuals show (for the reported sigma, :meth:`cover`)
        self.snap_pos = snapshot_error(dz_pr, np.where(valid, var_pr, np.nan), los_l)
        self.snap_vel = snapshot_error(dz_prr, np.where(valid, var_prr, np.nan), los_l)
        if self.snap_vel is not None:
            self.drift += (np.abs(self.snap_vel[0]) + self.snap_vel[1]) * self.dt
        return self.state

    def _step(self, t, flags):
        """The state machine of the module docstring."""
        th, dt = self.th, self.dt
        if flags & FAILED:
            self.fail_run += dt
            self.pass_run = 0.0
        else:
            self.pass_run += dt
            self.fail_run = 0.0
            if self.state == OK:
                self.bad_s = 0.0
        if flags & GROSS:
            self.bad_s += dt
            if self.t_gross is None:
                self.t_gross = float(t) - dt
        if self.state == OK and self.fail_run >= th.degraded_s - 1e-9:
            self.state = DEGRADED
            if self.first_degraded_s is None:
                self.first_degraded_s = float(t)
        elif self.state == DEGRADED and self.bad_s >= th.lost_s - 1e-9:
            self.state = LOST
            if self.first_lost_s is None:
                self.first_lost_s = float(t)
            self.lost_at_s = float(t)
        elif self.state != OK and self.pass_run >= th.recover_s - 1e-9:
            self.state = OK
            self.bad_s = 0.0
        if self.state == OK and not flags & FAILED:
            self.t_gross = None
        self.worst = max(self.worst, self.state)

    # ---------------------------------------------------------------- the reported sigma
    def cover(self, sigma, t, f_b):
        """The recorder's 1-sigma row (pos ENU, vel ENU, att, clk bias, drift;
        :meth:`ultratight.receiver.deep.recorder.EpochRecorder.set_sigma`) made to cover the error
        the residuals show while the state is not ``ok`` or the update failed a test (module docstring);
        unchanged otherwise."""
        if self.state == OK and not self.last.get("flags", 0) & ~UNTESTED:
            return sigma
        if self.outlier is not None:
            # a channel that disagrees: either it is wrong or the solution is off by its residual
            sigma = np.array(sigma, dtype=float)
            sigma[0:3] = np.maximum(sigma[0:3], self.outlier[0])
            sigma[3:6] = np.maximum(sigma[3:6], self.outlier[1])
        s = np.asarray(sigma, float) * math.sqrt(self.ratio)
        for sl, snap in ((slice(0, 3), self.snap_pos), (slice(3, 6), self.snap_vel)):
            if snap is not None:
                d, sd = snap
                s[sl] = np.maximum(s[sl], np.abs(d) + sd)
        s[0:3] = np.maximum(s[0:3], self.drift)
        if self.t_gross is not None:
            # a solution that fails grossly may be off by what a misdirected specific force does:
            # up to 2 |f| of acceleration error since the failures began (the residuals of channels
            # aided by that solution show only part of it)
            tau = max(float(t) - self.t_gross, 0.0)
            s[0:3] = np.maximum(s[0:3], float(np.linalg.norm(f_b)) * tau * tau)
            s[3:6] = np.maximum(s[3:6], 2.0 * float(np.linalg.norm(f_b)) * tau)
        return s

    # ---------------------------------------------------------------- the record
    def summary(self, n_reinit=0):
        """``info["integrity"]``: final and worst state, first degraded / lost times (s since the
        engine's start), the time the state last became lost when the run ends lost (else None; with
        ``integrity_stop`` the run ends there), re-initialisations, thresholds."""
        return {"state": STATE_NAMES[self.state], "worst": STATE_NAMES[self.worst],
                "first_degraded_s": self.first_degraded_s, "first_lost_s": self.first_lost_s,
                "lost_at_s": self.lost_at_s if self.state == LOST else None, "n_reinit": int(n_reinit),
                "thresholds": asdict(self.th)}
