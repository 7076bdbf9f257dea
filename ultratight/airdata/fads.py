"""Flush air-data sensing (FADS): port pressures, their inversion, and air data (for Duan et al. 2024).

Pressure model (Whitmore et al., AIAA 98-0201, the paper's ref. [13])::

    p_i = q_c [cos² θ_i + ε sin² θ_i] + p_∞
    cos θ_i = cos α cos β cos λ_i + sin β sin φ_i sin λ_i + sin α cos β cos φ_i sin λ_i

λ_i cone angle, φ_i clock angle of port i (φ = 0 on the windward side at positive α, φ = 90° on
the right at positive β); ε = 0 (modified Newtonian, this project's choice). Impact pressure q_c of Mach M
(:func:`impact_ratio`): subsonic isentropic ``q_c/p_∞ = (1 + 0.2 M²)^3.5 − 1``; supersonic Rayleigh
pitot ``(q_c + p_∞)/p_∞ = K M⁷ / (7 M² − 1)^2.5`` with K = 1.2^3.5 · 6^2.5 = 166.9216 (the usual
166.92 rounded), which makes the two branches continuous with a continuous slope at M = 1.

Inversion (:func:`invert`): per epoch, Gauss–Newton on y = (α, β, q_c, p_∞) over all ports
(vectorised over epochs), started from the α = β = 0 linear least-squares solution; covariance
``σ_p² (JᵀJ)⁻¹``. Derived (:func:`derived`): M from q_c/p_∞, FADS altitude h_F = standard-atmosphere
altitude of p_∞, V_air = M a(h_F), and the air velocity in ESD ``V_F = C_bn V_air [cos α cos β,
sin β, sin α cos β]`` with the INS attitude (no wind), with first-order covariances.

"Direct" altitude mode (:func:`direct_altitude_sigma`): ``h_F = h + N(0, σ_F(h)²)`` with σ_F
log-linear from 1 m at 0 km to 100 m at 20 km (the paper's Fig. 3 range; its shape is not given).
"""

import numpy as np

from ultratight.airdata import atmosphere
from ultratight.airdata.frames import wind_axes_dcm
from ultratight.errors import ConfigError

RAYLEIGH_K = 1.2 ** 3.5 * 6.0 ** 2.5        # 166.9216: continuity of q_c/p_inf at M = 1
# state of the inversion
I_ALPHA, I_BETA, I_QC, I_PINF = 0, 1, 2, 3


def default_ports():
    """Port layout (this project's choice; the paper gives none): nose + cones 20° and 40° at clock
    0/90/180/270° → (cone λ, clock φ) in rad, (9,) each."""
    cone = [0.0] + [20.0] * 4 + [40.0] * 4
    clock = [0.0] + [0.0, 90.0, 180.0, 270.0] * 2
    return np.radians(cone), np.radians(clock)


def ports_from_config(cone_deg, clock_deg):
    """(cone, clock) in rad from the scenario's degree lists; ConfigError naming the field when wrong."""
    try:
        cone = np.asarray(cone_deg, dtype=float).reshape(-1)
        clock = np.asarray(clock_deg, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError("fads.cone_deg and fads.clock_deg must be lists of numbers (deg)") from None
    if cone.shape != clock.shape or cone.size < 4:
        raise ConfigError("fads.cone_deg and fads.clock_deg must be lists of the same length (>= 4 ports)")
    if not (np.all(np.isfinite(cone)) and np.all(np.isfinite(clock))) or np.any(cone < 0) or np.any(cone >= 90):
        raise ConfigError("fads.cone_deg must be finite angles in [0, 90) deg")
    return np.radians(cone), np.radians(clock)


# ------------------------------------------------------------------ impact pressure (pitot)

def impact_ratio(mach):
    """q_c / p_∞ as a function of Mach (subsonic isentropic; supersonic Rayleigh pitot)."""
    m = np.asarray(mach, dtype=float)
    sub = (1.0 + 0.2 * m * m) ** 3.5 - 1.0
    msup = np.maximum(m, 1.0)
    sup = RAYLEIGH_K * msup ** 7 / (7.0 * msup * msup - 1.0) ** 2.5 - 1.0
    out = np.where(m < 1.0, sub, sup)
    return float(out) if out.ndim == 0 else out


def impact_ratio_dmach(mach):
    """d(q_c/p_∞)/dM of :func:`impact_ratio`."""
    m = np.asarray(mach, dtype=float)
    sub = 3.5 * (1.0 + 0.2 * m * m) ** 2.5 * 0.4 * m
    ms = np.maximum(m, 1.0)
    d = 7.0 * ms * ms - 1.0
    sup = RAYLEIGH_K * (7.0 * ms ** 6 / d ** 2.5 - 35.0 * ms ** 8 / d ** 3.5)
    out = np.where(m < 1.0, sub, sup)
    return float(out) if out.ndim == 0 else out


def mach_from_impact_ratio(ratio, iters=30):
    """Inverse of :func:`impact_ratio` (closed form below M = 1, Newton above)."""
    r = np.asarray(ratio, dtype=float)
    if np.any(~np.isfinite(r)) or np.any(r < 0):
        raise ValueError("impact pressure ratio must be finite and >= 0")
    m = np.sqrt(5.0 * ((r + 1.0) ** (2.0 / 7.0) - 1.0))      # isentropic (exact when subsonic)
    sup = r >= impact_ratio(1.0)
    if np.any(sup):
        ms = np.maximum(np.atleast_1d(m)[np.atleast_1d(sup)], 1.0)
        rs = np.atleast_1d(r)[np.atleast_1d(sup)]
        for _ in range(iters):
            step = (impact_ratio(ms) - rs) / impact_ratio_dmach(ms)
            ms = np.maximum(ms - step, 1.0)
            if np.all(np.abs(step) < 1e-14 * ms):
                break
        m = np.atleast_1d(m).copy()
        m[np.atleast_1d(sup)] = ms
        m = m.reshape(r.shape)
    return float(m) if np.ndim(m) == 0 else m


# ------------------------------------------------------------------ port pressures

def _cos_theta(alpha, beta, cone, clock):
    """cos θ_i (n, m) and its derivatives w.r.t. α and β."""
    a = np.asarray(alpha, float)[..., None]
    b = np.asarray(beta, float)[..., None]
    sa, ca, sb, cb = np.sin(a), np.cos(a), np.sin(b), np.cos(b)
    sl, cl, sf, cf = np.sin(cone), np.cos(cone), np.sin(clock), np.cos(clock)
    c = ca * cb * cl + sb * sf * sl + sa * cb * cf * sl
    dc_da = -sa * cb * cl + ca * cb * cf * sl
    dc_db = -ca * sb * cl + cb * sf * sl - sa * sb * cf * sl
    return c, dc_da, dc_db


def port_pressures(alpha, beta, qc, p_inf, cone, clock, eps=0.0):
    """Whitmore model: (n, m) port pressures for epochs (n,) of α, β (rad), q_c, p_∞ (Pa)."""
    c, _, _ = _cos_theta(alpha, beta, cone, clock)
    shape = (1.0 - eps) * c * c + eps
    return np.asarray(qc, float)[..., None] * shape + np.asarray(p_inf, float)[..., None]


def _model_and_jacobian(y, cone, clock, eps):
    c, dca, dcb = _cos_theta(y[:, I_ALPHA], y[:, I_BETA], cone, clock)
    qc = y[:, I_QC][:, None]
    shape = (1.0 - eps) * c * c + eps
    p = qc * shape + y[:, I_PINF][:, None]
    J = np.empty(p.shape + (4,))
    J[..., I_ALPHA] = qc * (1.0 - eps) * 2.0 * c * dca
    J[..., I_BETA] = qc * (1.0 - eps) * 2.0 * c * dcb
    J[..., I_QC] = shape
    J[..., I_PINF] = 1.0
    return p, J


def invert(p_meas, cone, clock, sigma_pa, eps=0.0, iters=25, tol=1e-13):
    """Gauss–Newton inversion of port pressures (n, m) → (y (n, 4) = α, β, q_c, p_∞; cov (n, 4, 4)).

    Converged when every epoch's relative step is below ``tol``; raises ValueError when the
    geometry is singular (fewer than 4 independent ports)."""
    p = np.atleast_2d(np.asarray(p_meas, dtype=float))
    n, m = p.shape
    if m != cone.size:
        raise ValueError(f"{m} port pressures for {cone.size} ports")
    # start: α = β = 0 → linear least squares in (q_c, p_∞)
    A = np.stack([(1.0 - eps) * np.cos(cone) ** 2 + eps, np.ones(m)], axis=1)
    sol, *_ = np.linalg.lstsq(A, p.T, rcond=None)
    y = np.zeros((n, 4))
    y[:, I_QC], y[:, I_PINF] = sol[0], sol[1]
    scale = np.array([1.0, 1.0, 0.0, 0.0])
    for _ in range(iters):
        pm, J = _model_and_jacobian(y, cone, clock, eps)
        r = p - pm
        JtJ = np.einsum("nki,nkj->nij", J, J)
        Jtr = np.einsum("nki,nk->ni", J, r)
        dy = np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
        y = y + dy
        ref = scale + np.abs(y) * (1.0 - scale) + 1.0 * (1.0 - scale)
        if np.all(np.abs(dy) <= tol * ref):
            break
    _, J = _model_and_jacobian(y, cone, clock, eps)
    cov = sigma_pa ** 2 * np.linalg.inv(np.einsum("nki,nkj->nij", J, J))
    return y, cov


def derived(y, cov, C_bn=None):
    """Mach, FADS altitude, airspeed (and ESD air velocity with attitude ``C_bn`` (n, 3, 3)).

    Returns a dict of arrays ``mach``, ``h_m``, ``tas_mps``, their variances ``var_mach``,
    ``var_h``, ``var_tas`` and, with ``C_bn``, ``vel_n`` (n, 3) and ``cov_vel_n`` (n, 3, 3)."""
    qc, pinf = y[:, I_QC], y[:, I_PINF]
    ratio = qc / pinf
    mach = mach_from_impact_ratio(np.maximum(ratio, 0.0))
    h = atmosphere.altitude_from_pressure(pinf)
    a = atmosphere.speed_of_sound(h)
    dh = 1.0
    da_dh = (atmosphere.speed_of_sound(h + dh) - atmosphere.speed_of_sound(h - dh)) / (2 * dh)
    dM_dr = 1.0 / impact_ratio_dmach(mach)
    dh_dp = 1.0 / atmosphere.dpressure_dh(h)
    # Jacobians w.r.t. y = (α, β, q_c, p_∞)
    n = y.shape[0]
    Jm = np.zeros((n, 4))
    Jm[:, I_QC] = dM_dr / pinf
    Jm[:, I_PINF] = -dM_dr * qc / pinf ** 2
    Jh = np.zeros((n, 4))
    Jh[:, I_PINF] = dh_dp
    Jv = a[:, None] * Jm + (mach * da_dh)[:, None] * Jh
    tas = mach * a
    out = {"mach": mach, "h_m": h, "tas_mps": tas,
           "var_mach": np.einsum("ni,nij,nj->n", Jm, cov, Jm),
           "var_h": np.einsum("ni,nij,nj->n", Jh, cov, Jh),
           "var_tas": np.einsum("ni,nij,nj->n", Jv, cov, Jv)}
    if C_bn is not None:
        Cw = wind_axes_dcm(y[:, I_ALPHA], y[:, I_BETA])
        d = Cw[:, 0, :]                                       # airflow direction in body axes
        v_b = tas[:, None] * d
        # d(v_b)/d(α, β, V): columns
        sa, ca = np.sin(y[:, I_ALPHA]), np.cos(y[:, I_ALPHA])
        sb, cb = np.sin(y[:, I_BETA]), np.cos(y[:, I_BETA])
        G = np.zeros((n, 3, 4))
        G[:, :, I_ALPHA] = tas[:, None] * np.stack([-sa * cb, np.zeros(n), ca * cb], axis=1)
        G[:, :, I_BETA] = tas[:, None] * np.stack([-ca * sb, cb, -sa * sb], axis=1)
        G += d[:, :, None] * Jv[:, None, :]
        cov_b = G @ cov @ np.transpose(G, (0, 2, 1))
        out["vel_n"] = np.einsum("nij,nj->ni", C_bn, v_b)
        out["cov_vel_n"] = C_bn @ cov_b @ np.transpose(C_bn, (0, 2, 1))
        out["vel_b"] = v_b
        out["cov_vel_b"] = cov_b
    return out


def direct_altitude_sigma(h_m, sigma0_m=1.0, sigma1_m=100.0, h1_m=20000.0, shape="log-linear"):
    """σ_F(h) from ``sigma0_m`` at 0 m to ``sigma1_m`` at ``h1_m`` (h clipped to [0, h1]).

    ``shape`` "log-linear" (this project's choice: log σ linear in h, the growth of a pressure altitude's
    error, dh/dp ∝ 1/ρ) or "linear" (σ linear in h); the paper gives only the end values."""
    s = np.clip(np.asarray(h_m, float), 0.0, h1_m) / h1_m
    if shape == "log-linear":
        out = sigma0_m * (sigma1_m / sigma0_m) ** s
    elif shape == "linear":
        out = sigma0_m + (sigma1_m - sigma0_m) * s
    else:
        raise ConfigError(f"FADS altitude curve shape must be 'log-linear' or 'linear', got {shape!r}")
    return float(out) if out.ndim == 0 else out


# ------------------------------------------------------------------ air data from a navigation solution

def air_data(vel_n, C_bn, h_m, wind_n=None):
    """α, β (rad), Mach, true airspeed (m/s) from ESD velocity (n, 3), attitude C_bn (n, 3, 3) and altitude.

    Post-processing of Duan et al. 2024 (Fig. 1): ``v_b = C_nb (V − W)``, ``α = atan2(v_b,z, v_b,x)``,
    ``β = asin(v_b,y / |v_b|)``, ``Ma = |v_b| / a(h)`` (W = 0 as the paper)."""
    v = np.asarray(vel_n, float)
    if wind_n is not None:
        v = v - np.asarray(wind_n, float)
    v_b = np.einsum("nji,nj->ni", C_bn, v)
    speed = np.linalg.norm(v_b, axis=1)
    alpha = np.arctan2(v_b[:, 2], v_b[:, 0])
    beta = np.arcsin(np.clip(v_b[:, 1] / speed, -1.0, 1.0))
    mach = speed / atmosphere.speed_of_sound(h_m)
    return {"alpha": alpha, "beta": beta, "mach": mach, "tas_mps": speed}
