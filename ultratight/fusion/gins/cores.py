"""Estimation cores of the INS/GNSS filter (``filter=``): the seed filters of
:mod:`ultratight.fusion.estimators` behind one interface for the closed-loop error-state filter.

Every core carries the error state ``x`` and covariance ``P``; ``predict(Phi, Q, basis)`` is the
time update over one covariance step, ``update_gnss(z, H, R)`` the GNSS epoch (where the cores
differ), ``update_aid(z, H, R)`` the ZUPT / NHC pseudo-measurements (always the Joseph-form
Kalman update: their R is a declared constraint, not a noise to adapt), ``reset()`` zeroes the
error state after the feedback.  ``prior_used`` is the prior covariance of the last GNSS update
(the faded one for ``afm-aukf``), which the smoother stores.

``kf``
    Joseph-form Kalman update (:func:`ultratight.fusion.estimators.filters.kf_update`).
``akf``
    Fang 2017's innovation-based AKF (:class:`ultratight.fusion.estimators.adaptive.AKF`) with R
    adapted from the window of the last ``akf_window`` GNSS innovations (eq. 8; the window restarts
    after an outage, whose first innovations carry the inertial drift, not R) and Q kept at the
    declaration (the IMU declaration is what Q is tuned from; eq. 14's Q̂ would be estimated at
    the GNSS interval while Q is applied at the covariance rate).  The window needs a fixed
    measurement dimension: an epoch with another number of rows (e.g. no velocity) is a KF update.
``iakf``
    Loose reading of Fang 2017's IAKF (:class:`ultratight.fusion.estimators.adaptive.IAKF`): the
    paper's GDOP selection and GDOP-weighted R (eqs. 16–25) are tight-coupling constructs (best
    four satellites); in loose coupling the receiver's per-epoch σ already carries the geometry,
    so R is the fix's σ (not adapted) and what remains is eq. 26: Q̂ windowed over
    ``akf_window`` epochs, projected on the model's noise structure (the white gyro and
    accelerometer noises, diagonal fit) and capped at the declared noise.  The projected noise
    PSDs are re-applied to each covariance step's own basis (steps have different lengths).
``chi2-newton``
    Cai et al. 2020: per-dimension χ² detection (eq. 15, significance ``chi2_alpha``) with the
    faulty innovations replaced by the Newton extrapolation of the last four used ones divided by
    δ = ``newton_delta`` (eqs. 21–28;
    :func:`ultratight.fusion.estimators.robust.chi2_newton_kf_update`, replacements that fail the
    test themselves set to zero, and a dimension flagged in ``gate_release`` consecutive epochs used
    unchanged — a persistent "fault" is the filter's own error, which replacing would hide from it;
    both are this project's additions to the paper, as in ``ChiSquareNewton``).  Its detection
    takes the place of the χ² epoch gate, which is not applied in front of it (screening twice
    rejects whole epochs for what the detector has already replaced).
``afm-aukf``
    Sun et al. 2012's adaptive fading matrix applied to the error-state filter (the model here is
    linear, so the sigma-point equivalents of eqs. 11–12 are the exact H, A = H P′ Hᵀ, B = S − A):
    P′ is the covariance propagated without process noise since the last update, Ω from the
    per-innovation χ²₁ test at ``afm_alpha`` (eqs. 5–6), S = (H′ᵀH′)⁻¹ H′ᵀ Ω H′ on the measured
    columns (position, velocity and clock states, eqs. 7–10), P⁻_f = S ⊙ P′ + (P⁻ − P′) (eq. 13),
    then the Kalman update with P⁻_f; an epoch with fewer rows than measured columns (a tight
    epoch with few satellites) does not determine S (eq. 9) and is not faded (the scalar factor
    λ of eq. 1 compounds epoch after epoch there: tried, σ of hundreds of metres in 15 s)
    (:func:`ultratight.fusion.estimators.adaptive.fading_matrix`, :func:`apply_fading`).
"""

from __future__ import annotations

import numpy as np

from ultratight.chi2 import chdtri
from ultratight.fusion.estimators.adaptive import AKF, IAKF, apply_fading, fading_matrix
from ultratight.fusion.estimators.filters import kf_update
from ultratight.fusion.estimators.guards import symmetrize
from ultratight.fusion.estimators.robust import ChiSquareNewton, chi2_newton_kf_update
from ultratight.ins import error_model as em


class KfCore:
    """Joseph-form Kalman filter (``kf``) and the base of the others."""
    name = "kf"
    own_gate = False        # True: the core screens its GNSS rows itself (no χ² epoch gate in front)

    def __init__(self, P0, opts, m_gnss=6):
        self.x = np.zeros(P0.shape[0])
        self.P = symmetrize(np.asarray(P0, float))
        self.o = opts
        self.prior_used = None
        self.n_faulty = 0

    def predict(self, Phi, Q, basis=None):
        self.x = Phi @ self.x
        self.P = symmetrize(Phi @ self.P @ Phi.T + Q)

    def reset(self):
        self.x[:] = 0.0

    def _kf(self, z, H, R):
        res = kf_update(self.x, self.P, z, H, R)
        self.x, self.P = res.x, res.P
        return {"nis": res.nis}

    def update_aid(self, z, H, R):
        return self._kf(z, H, R)

    def gate_R(self, R):
        """The R this core's GNSS update will use (the χ² gate tests against it)."""
        return R

    def gap(self):
        """A GNSS epoch was not used (outage): the windowed cores restart their windows."""

    def update_gnss(self, z, H, R):
        self.prior_used = self.P
        return self._kf(z, H, R)


class AkfCore(KfCore):
    """Fang 2017 AKF, R adapted (module docstring)."""
    name = "akf"

    def __init__(self, P0, opts, m_gnss=6):
        super().__init__(P0, opts)
        self.f = None

    def gate_R(self, R):
        f = self.f
        return f.R if f is not None and f.R.shape == R.shape and len(f.eps) >= f.N else R

    def gap(self):
        if self.f is not None:      # the first innovations after a gap carry the inertial drift, not R
            self.f.eps.clear()

    def update_gnss(self, z, H, R):
        self.prior_used = self.P
        if self.f is None:
            self.f = AKF(self.x, self.P, np.eye(self.P.shape[0]), R, window=self.o.akf_window, adapt_q=False,
                         adapt_r=True)
        if self.f.R.shape != R.shape:
            return self._kf(z, H, R)
        if len(self.f.eps) < self.f.N:
            self.f.R = R            # the given R until eq. 8 has a full window
        self.f.x, self.f.P = self.x, self.P
        res = self.f.update(z, H)
        self.x, self.P = self.f.x.copy(), self.f.P.copy()
        return {"nis": res.nis}


class IakfCore(KfCore):
    """Fang 2017 IAKF, loose reading (module docstring)."""
    name = "iakf"
    wants_basis = True

    def __init__(self, P0, opts, m_gnss=6):
        super().__init__(P0, opts)
        n, m = self.P.shape[0], int(m_gnss)
        self.f = IAKF(self.x, self.P, np.eye(n), np.eye(m), pr_rows=np.arange(min(3, m)),
                      prr_rows=np.arange(min(3, m), m), pos_clk_idx=[6, 7, 8], vel_drift_idx=[3, 4, 5],
                      window=opts.akf_window, adapt_r=False, r_source="correction", q_structure="model-diag", start="growing",
                      q_ceiling=True)

    def predict(self, Phi, Q, basis=None):
        B, Qf = basis
        f = self.f
        f.q_basis, f.q_fixed, f.Q_given = B, Qf, Q
        f.Q = symmetrize(Qf + np.tensordot(f.q_w, B, axes=1)) if f.q_w is not None else Q
        f.x, f.P = self.x, self.P
        self.x, self.P = f.predict(Phi)

    def update_gnss(self, z, H, R):
        self.prior_used = self.P
        if self.f.R.shape != R.shape:
            return self._kf(z, H, R)
        self.f.R = R
        self.f.x, self.f.P = self.x, self.P
        res = self.f.update(z, H, gdop_pr=1.0)      # GDOP unused: R is not adapted in the loose reading
        self.x, self.P = self.f.x.copy(), self.f.P.copy()
        return {"nis": res.nis}


class Chi2NewtonCore(KfCore):
    """Cai et al. 2020 χ² detection + Newton replacement (module docstring)."""
    name = "chi2-newton"
    own_gate = True

    def __init__(self, P0, opts, m_gnss=6):
        super().__init__(P0, opts)
        self.det = None

    def update_gnss(self, z, H, R):
        self.prior_used = self.P
        if self.det is None:
            self.det = ChiSquareNewton(z.shape[0], alpha=self.o.chi2_alpha, delta=self.o.newton_delta, guard=True,
                                       release_after=self.o.gate_release)
        if self.det.m != z.shape[0]:
            return self._kf(z, H, R)
        before = self.det.n_faults
        res = chi2_newton_kf_update(self.x, self.P, z, H, R, self.det)
        self.n_faulty += self.det.n_faults - before
        self.x, self.P = res.x, res.P
        return {"nis": res.nis, "faulty": int(np.sum(res.info["faulty"]))}


class AfmCore(KfCore):
    """Sun et al. 2012 adaptive fading matrix on the error-state filter (module docstring)."""
    name = "afm-aukf"

    def __init__(self, P0, opts, m_gnss=6):
        super().__init__(P0, opts)
        self.Pn = self.P.copy()          # P′: propagated without process noise since the last update
        self.threshold = float(chdtri(1, opts.afm_alpha))

    def predict(self, Phi, Q, basis=None):
        super().predict(Phi, Q)
        self.Pn = symmetrize(Phi @ self.Pn @ Phi.T)

    def _measured_cols(self):
        n = self.P.shape[0]
        cols = list(range(em.VEL.start, em.POS.stop))
        return cols + ([em.CLK, em.DRIFT] if n == em.N17 else [])

    def update_gnss(self, z, H, R):
        y = z - H @ self.x
        A = symmetrize(H @ self.Pn @ H.T)
        B = symmetrize(H @ self.P @ H.T + R) - A
        cols = self._measured_cols()
        if z.shape[0] >= len(cols):     # fewer rows than measured states do not determine S (eq. 9)
            self.P = apply_fading(self.P, self.Pn, fading_matrix(y, A, B, H, self.threshold, nonzero_cols=cols))
        self.prior_used = self.P
        out = self._kf(z, H, R)
        self.Pn = self.P.copy()
        return out

    def update_aid(self, z, H, R):
        out = self._kf(z, H, R)
        self.Pn = self.P.copy()
        return out


CORE_CLASSES = {"kf": KfCore, "akf": AkfCore, "iakf": IakfCore, "chi2-newton": Chi2NewtonCore, "afm-aukf": AfmCore}


def make_core(name, P0, opts, m_gnss=6):
    """The core ``name`` (one of :data:`ultratight.fusion.gins.options.FILTERS`); ``m_gnss`` the GNSS
    rows of an epoch (the dimension the windowed cores expect)."""
    return CORE_CLASSES[name](P0, opts, m_gnss)
