"""Observable-level GNSS simulation (no IF samples): pseudoranges, pseudorange rates and
position/velocity fixes for the integration experiments of Fang 2017 and Cai et al. 2020.

For a trajectory (ECEF position/velocity per epoch) and a set of ephemerides (a RINEX navigation
file or the nominal constellation), per satellite and epoch:

* the noise-free pseudorange and pseudorange rate come from the light-time solution of
  :func:`ultratight.signals.geometry.light_time` (Sagnac, satellite clock, receiver clock);
* the receiver clock is the two-state model (bias b in m, drift d in m/s) driven by the
  oscillator h-parameters (Brown & Hwang, *Introduction to Random Signals and Applied Kalman
  Filtering*, 4th ed., §9.3): white frequency noise S_f = h0/2 and random-walk frequency noise
  S_g = 2π² h₋₂ (s²/s and s²/s³, times c² for metres).  Discrete step Δt:
  ``Q = c² [[S_f Δt + S_g Δt³/3, S_g Δt²/2], [S_g Δt²/2, S_g Δt]]``;
* white noise of σ_ρ, σ_ρ̇ is added; satellites below the elevation mask (or behind the Earth)
  are flagged invisible;
* optional gross errors (Cai et al. 2020, §4.1): at every ``period_s``-th epoch (t = period, 2·period, …) the
  noise of the chosen components is amplified, ``V ← m·V`` (mode "scale", this project's choice) or
  ``V ← V + m·σ·sign(V)`` (mode "add").

For loose coupling, :func:`gnss_fixes` gives GNSS position/velocity solutions either as
truth + white noise of the paper's σ (``mode="truth"``, the paper's own description, Cai et al.
2020, §4.1) or as the epoch-wise least-squares fix of the simulated observables (``mode="lsq"``,
Gauss–Newton on ρ for position/clock, linear least squares on ρ̇ for velocity/drift).

Everything is vectorised over epochs (the light-time kernel is numba, one call per satellite);
every random draw comes from the ``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ultratight.constants import C
from ultratight.errors import ConfigError
from ultratight.ins.earth import dcm_ecef_from_enu_vec, ecef_to_llh_batch, enu_frames
from ultratight.signals.geometry import light_time, los_clears_earth

GROSS_MODES = ("scale", "add")


@dataclass
class GrossErrors:
    """Gross errors injected into the measurement noise (Cai et al. 2020, §4.1).

    ``factor`` m; ``period_s``: every epoch whose time is a positive multiple of it;
    ``components``: indices into the measurement vector the experiment defines (all when None);
    ``mode``: "scale" (V ← m·V) or "add" (V ← V + m·σ·sign V)."""
    factor: float = 20.0
    period_s: float = 10.0
    components: tuple | None = None
    mode: str = "scale"

    def __post_init__(self):
        if not (math.isfinite(self.factor) and self.factor >= 0.0):
            raise ConfigError(f"gross.factor must be a finite number >= 0, got {self.factor}")
        if not (math.isfinite(self.period_s) and self.period_s > 0.0):
            raise ConfigError(f"gross.period_s must be > 0, got {self.period_s}")
        if self.mode not in GROSS_MODES:
            raise ConfigError(f"gross.mode must be one of {', '.join(GROSS_MODES)}, got {self.mode!r}")

    def epochs(self, t):
        """Boolean mask of the epochs (times t, s since start) that carry a gross error."""
        t = np.asarray(t, dtype=float)
        k = np.round(t / self.period_s)
        return (k >= 1) & (np.abs(t - k * self.period_s) < 1e-6)

    def apply(self, t, noise, sigma):
        """Noise array (n, m) with the gross errors applied (a copy); ``sigma`` (m,) per component."""
        out = np.array(noise, dtype=float, copy=True)
        rows = self.epochs(t)
        cols = np.arange(out.shape[1]) if self.components is None else np.asarray(self.components, int)
        if not rows.any() or cols.size == 0:
            return out
        sub = out[np.ix_(rows, cols)]
        if self.mode == "scale":
            sub = self.factor * sub
        else:
            sub = sub + self.factor * np.asarray(sigma, float)[cols] * np.where(sub >= 0.0, 1.0, -1.0)
        out[np.ix_(rows, cols)] = sub
        return out


# ------------------------------------------------------------------ receiver clock
def clock_q(dt, h0=2e-19, h_m2=2e-20):
    """Discrete process noise (2x2, m², m²/s, m²/s²) of the two-state clock over dt (module doc)."""
    sf = 0.5 * h0 * C * C
    sg = 2.0 * math.pi ** 2 * h_m2 * C * C
    return np.array([[sf * dt + sg * dt ** 3 / 3.0, sg * dt ** 2 / 2.0],
                     [sg * dt ** 2 / 2.0, sg * dt]])


def simulate_clock(n, dt, bias0_m, drift0_mps, rng, h0=2e-19, h_m2=2e-20):
    """Receiver clock bias (m) and drift (m/s) at n epochs spaced dt (first = the initial values)."""
    Q = clock_q(dt, h0, h_m2)
    L = np.linalg.cholesky(Q + 1e-30 * np.eye(2))
    w = rng.standard_normal((max(n - 1, 0), 2)) @ L.T
    b = np.empty(n)
    d = np.empty(n)
    b[0], d[0] = bias0_m, drift0_mps
    # x_{k+1} = [[1, dt], [0, 1]] x_k + w_k, written as cumulative sums (vectorised)
    d[1:] = drift0_mps + np.cumsum(w[:, 1])
    b[1:] = bias0_m + np.cumsum(d[:-1] * dt + w[:, 0])
    return b, d


# ------------------------------------------------------------------ observables
@dataclass
class Observables:
    """Simulated observables, arrays (n epochs, k satellites); ``visible`` masks the usable ones.

    ``pr_m``/``prr_mps``: measured (with noise, gross errors, receiver clock);
    ``pr_true_m``/``prr_true_mps``: noise-free; ``noise_pr``/``noise_prr``: the noise actually
    added (Cai et al. 2020's V_k for the paper-literal reading); ``sat_pos_e``/``sat_vel_e`` (n, k, 3):
    satellite state at transmission in the ECEF frame of reception (what a receiver computes from
    the ephemeris); ``sat_clk_m``/``sat_clk_drift_mps``: satellite clock correction times c;
    ``los_e`` (n, k, 3) unit receiver → satellite; ``elev_rad``; ``clk_bias_m``/``clk_drift_mps`` (n,)
    the true receiver clock."""
    t: np.ndarray
    prns: np.ndarray
    pr_m: np.ndarray
    prr_mps: np.ndarray
    pr_true_m: np.ndarray
    prr_true_mps: np.ndarray
    noise_pr: np.ndarray
    noise_prr: np.ndarray
    sat_pos_e: np.ndarray
    sat_vel_e: np.ndarray
    sat_clk_m: np.ndarray
    sat_clk_drift_mps: np.ndarray
    los_e: np.ndarray
    elev_rad: np.ndarray
    visible: np.ndarray
    clk_bias_m: np.ndarray
    clk_drift_mps: np.ndarray
    info: dict = field(default_factory=dict)


def simulate_observables(ephs, week, tow0_s, t, pos_e, vel_e, clk_bias_m, clk_drift_mps, rng,
                         sigma_pr_m=2.0, sigma_prr_mps=0.1, mask_deg=10.0, gross=None):
    """Pseudoranges and rates of all ephemerides in ``ephs`` (dict prn -> Ephemeris) at the epochs
    ``t`` (s since the run start at GPS (week, tow0_s)) for a receiver at ``pos_e``/``vel_e``
    (n, 3) ECEF with clock ``clk_bias_m``/``clk_drift_mps`` (n,).  ``gross``: :class:`GrossErrors`
    whose components index [pseudorange, rate] (0, 1) or None.  Returns :class:`Observables`."""
    t = np.asarray(t, dtype=float)
    n = t.shape[0]
    prns = np.array(sorted(int(p) for p, e in (ephs.items() if isinstance(ephs, dict) else
                                              ((e.prn, e) for e in ephs)) if e is not None and e.healthy))
    if prns.size == 0:
        raise ConfigError("observable simulation: no healthy ephemeris")
    if not (sigma_pr_m >= 0.0 and sigma_prr_mps >= 0.0):
        raise ConfigError(f"observable noise sigmas must be >= 0, got {sigma_pr_m}, {sigma_prr_mps}")
    eph_by = ephs if isinstance(ephs, dict) else {e.prn: e for e in ephs}
    k = prns.size
    shape = (n, k)
    # filled satellite by satellite in (k, n) layout (contiguous writes), returned as (n, k) views
    pr, prr, elev, sclk, sdrift = (np.empty((k, n)) for _ in range(5))
    spos, svel, los = (np.empty((k, n, 3)) for _ in range(3))
    tow = tow0_s + t
    frames = enu_frames(pos_e) if np.shape(pos_e) == (n, 3) else None     # shared by every satellite
    for j, prn in enumerate(prns):
        o = light_time(eph_by[int(prn)], pos_e, vel_e, week, tow, clk_bias_m, clk_drift_mps, frames)
        pr[j] = o["pseudorange_m"]
        prr[j] = o["range_rate_mps"]
        elev[j] = o["elev_rad"]
        sclk[j] = o["sat_clk_bias_s"]
        sdrift[j] = o["sat_clk_drift"]
        spos[j] = o["sat_pos_e"]
        svel[j] = o["sat_vel_e"]
        los[j] = o["los_e"]
    pr, prr, elev = pr.T, prr.T, elev.T
    sclk, sdrift = C * sclk.T, C * sdrift.T
    spos, svel, los = (a.transpose(1, 0, 2) for a in (spos, svel, los))
    visible = elev >= math.radians(mask_deg)
    if mask_deg < 0.0:       # below the local horizon: the line of sight must clear the Earth
        for i, j in zip(*np.nonzero(visible)):
            visible[i, j] = los_clears_earth(pos_e[i], spos[i, j])
    npr = rng.standard_normal(shape) * sigma_pr_m
    nprr = rng.standard_normal(shape) * sigma_prr_mps
    if gross is not None and gross.factor != 1.0:
        cols = (0, 1) if gross.components is None else tuple(gross.components)
        every_sat = replace(gross, components=None)
        if 0 in cols:
            npr = every_sat.apply(t, npr, np.full(k, sigma_pr_m))
        if 1 in cols:
            nprr = every_sat.apply(t, nprr, np.full(k, sigma_prr_mps))
    return Observables(t=t, prns=prns, pr_m=pr + npr, prr_mps=prr + nprr, pr_true_m=pr, prr_true_mps=prr,
                       noise_pr=npr, noise_prr=nprr, sat_pos_e=spos, sat_vel_e=svel, sat_clk_m=sclk,
                       sat_clk_drift_mps=sdrift, los_e=los, elev_rad=elev, visible=visible,
                       clk_bias_m=np.broadcast_to(np.asarray(clk_bias_m, float), (n,)).copy(),
                       clk_drift_mps=np.broadcast_to(np.asarray(clk_drift_mps, float), (n,)).copy(),
                       info={"sigma_pr_m": sigma_pr_m, "sigma_prr_mps": sigma_prr_mps, "mask_deg": mask_deg})


def predict_observables(sat_pos_e, sat_vel_e, sat_clk_m, sat_clk_drift_mps, pos_e, vel_e, clk_b, clk_d):
    """Pseudorange/rate a receiver predicts from a position/velocity/clock estimate (one epoch,
    k satellites): ρ̂ = |r_sat − r| + b − c·Δt_sv, ρ̂̇ = u·(v_sat − v) + d − c·Δṫ_sv, u = unit
    receiver → satellite.  Returns (rho, rhodot, u (k, 3)).  The Sagnac rotation is in sat_pos_e
    (reception frame); the neglected Sagnac-rate and 1/(1 + ρ̇/c) terms are < 1 cm/s."""
    d = sat_pos_e - pos_e
    rng_ = np.linalg.norm(d, axis=-1)
    u = d / rng_[..., None]
    rho = rng_ + clk_b - sat_clk_m
    rhodot = np.sum(u * (sat_vel_e - vel_e), axis=-1) + clk_d - sat_clk_drift_mps
    return rho, rhodot, u


def lsq_fixes(obs, pos0_e, iterations=6):
    """Epoch-wise least-squares position/clock (Gauss–Newton on ρ) and velocity/drift (ρ̇) fixes.

    Returns (pos_e (n,3), vel_e (n,3), clk_b (n,), clk_d (n,), ok (n,) bool: ≥ 4 satellites).
    Vectorised over epochs (invisible satellites get zero weight)."""
    n, k = obs.pr_m.shape
    w = obs.visible.astype(float)
    ok = obs.visible.sum(axis=1) >= 4
    x = np.zeros((n, 4))
    x[:, :3] = np.asarray(pos0_e, float)
    for _ in range(iterations):
        rho, _, u = predict_observables(obs.sat_pos_e, obs.sat_vel_e, obs.sat_clk_m, obs.sat_clk_drift_mps,
                                        x[:, None, :3], 0.0, x[:, 3:4], 0.0)
        H = np.concatenate([-u, np.ones((n, k, 1))], axis=-1) * w[..., None]
        r = (obs.pr_m - rho) * w
        HtH = np.einsum("nki,nkj->nij", H, H) + np.eye(4) * 1e-9
        x = x + np.linalg.solve(HtH, np.einsum("nki,nk->ni", H, r)[..., None])[..., 0]
    _, rhodot0, u = predict_observables(obs.sat_pos_e, obs.sat_vel_e, obs.sat_clk_m, obs.sat_clk_drift_mps,
                                        x[:, None, :3], 0.0, 0.0, 0.0)
    H = np.concatenate([-u, np.ones((n, k, 1))], axis=-1) * w[..., None]
    HtH = np.einsum("nki,nkj->nij", H, H) + np.eye(4) * 1e-9
    v = np.linalg.solve(HtH, np.einsum("nki,nk->ni", H, (obs.prr_mps - rhodot0) * w)[..., None])[..., 0]
    return x[:, :3], v[:, :3], x[:, 3], v[:, 3], ok


def fix_noise_scale(n, sigma_llh, sigma_vel_mps):
    """(n, 6) σ of the fix noise [dlat, dlon, dh, dvE, dvN, dvU]: ``sigma_llh`` = (σ_lat rad,
    σ_lon rad, σ_h m) as the paper states them (Cai et al. 2020: 0.00015° in latitude and longitude),
    ``sigma_vel_mps`` (E, N, U)."""
    scale = np.empty((int(n), 6))
    scale[:, :3] = np.asarray(sigma_llh, float)
    scale[:, 3:] = np.asarray(sigma_vel_mps, float)
    return scale


def gnss_fixes(mode, rng, llh_true, vel_true_l, sigma_llh, sigma_vel_mps, gross=None, t=None, obs=None):
    """GNSS position/velocity solutions for loose coupling, as (llh (n,3) rad/m, vel_l (n,3) ENU,
    noise (n,6) = [dlat, dlon, dh, dvE, dvN, dvU] actually added (rad, rad, m, m/s)).

    ``mode="truth"``: truth + white noise of σ = ``sigma_llh`` (lat rad, lon rad, h m) and
    ``sigma_vel_mps`` (E, N, U), the paper's (Cai et al. 2020, §4.1) description; gross errors (components
    index the six entries) then apply to that noise.  ``mode="lsq"``: the least-squares fix of
    ``obs`` (its gross errors are those of the observables)."""
    llh_true = np.asarray(llh_true, float)
    vel_true_l = np.asarray(vel_true_l, float)
    n = llh_true.shape[0]
    if mode == "truth":
        scale = fix_noise_scale(n, sigma_llh, sigma_vel_mps)
        noise = rng.standard_normal((n, 6))
        if gross is not None:
            noise = gross.apply(t, noise, np.ones(6))     # in σ units: "add" adds m·σ
        noise = noise * scale
        return llh_true + noise[:, :3], vel_true_l + noise[:, 3:], noise
    if mode == "lsq":
        if obs is None:
            raise ConfigError("gnss_fixes: mode 'lsq' needs simulated observables")
        pos_e, vel_e, _, _, ok = lsq_fixes(obs, obs.info.get("pos0_e", np.zeros(3)))
        llh = ecef_to_llh_batch(pos_e)
        C_el = dcm_ecef_from_enu_vec(llh[:, 0], llh[:, 1])
        vel_l = np.einsum("nji,nj->ni", C_el, vel_e)
        llh[~ok] = np.nan
        vel_l[~ok] = np.nan
        noise = np.concatenate([llh - llh_true, vel_l - vel_true_l], axis=1)
        return llh, vel_l, noise
    raise ConfigError(f"gnss mode must be 'truth' or 'lsq', got {mode!r}")


def gdop_best4(los, visible=None):
    """Best-4 satellite subset by GDOP (Fang 2017 §3.1, eqs. 16–20), vectorised over subsets.

    ``los`` (k, 3) unit vectors (any frame; the sign convention does not change GDOP);
    returns (indices (4,) into los, GDOP).  Subsets with a singular geometry are skipped."""
    from itertools import combinations
    los = np.asarray(los, float)
    idx = np.arange(los.shape[0]) if visible is None else np.flatnonzero(visible)
    if idx.size < 4:
        raise ConfigError(f"best-4 selection needs at least 4 satellites, got {idx.size}")
    subs = np.array(list(combinations(idx, 4)))
    Hs = np.concatenate([los[subs], np.ones(subs.shape + (1,))], axis=-1)       # eq. 18 rows [e, 1]
    HtH = np.einsum("ski,skj->sij", Hs, Hs)
    det = np.linalg.det(HtH)
    good = np.abs(det) > 1e-12
    tr = np.full(subs.shape[0], np.inf)
    tr[good] = np.trace(np.linalg.inv(HtH[good]), axis1=1, axis2=2)              # eq. 19
    best = int(np.argmin(tr))
    return subs[best], float(np.sqrt(tr[best]))                                  # eq. 20
