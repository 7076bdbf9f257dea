"""Satellite states for recorded raw observations: one row per row of :class:`RawEpochs`.

``sat_states(raw, nav) -> SatStates`` evaluates, for every (epoch, satellite) row, the broadcast
ephemeris (:mod:`ultratight.signals.ephemeris`, IS-GPS-200 Table 20-IV; or a CNAV set of
:mod:`ultratight.signals.cnav`, Table 30-II, which evaluates itself through its ``state`` method) at the signal's
**transmit time in GPS time**:

    t_sv = t_rx − ρ / c                (satellite-clock time of transmission; exact, since the
                                        pseudorange is c·(t_rx − t_sv) whatever the receiver clock)
    t_tx = t_sv − Δt_sv(t_tx)          (iterated: Δt_sv changes by < 1e-12 s between iterations)

and returns the satellite ECEF position and velocity at ``t_tx``, the satellite clock correction
``clk_m = c·Δt_sv`` (af0 + af1·dt + af2·dt² + relativistic term − T_GD: the L1 C/A user's
correction) and its drift ``drift_mps = c·dΔt_sv/dt``.  With these, the pseudorange corrected for
the satellite clock is ``ρ + clk_m`` and the range rate from the Doppler ``−λ·D + drift_mps``.

**No Earth-rotation (Sagnac) correction is applied**: the positions are in the ECEF frame of the
transmit time.  The caller rotates them into the frame of the receive time with its own receiver
position (``R3(ω_e·τ)``, τ = |r_sat − r_rx| / c, e.g.
:func:`ultratight.receiver.scalar.pvt.rotate_sagnac`, which :func:`solve_pvt` applies itself).

``valid`` is False where no ephemeris is found for the row's PRN and time, the ephemeris is
unhealthy or the time is outside its fit interval (:meth:`NavData.select` rules: healthy, within
the fit interval, toe nearest), or the pseudorange is not finite; invalid rows hold NaN.
Elevations are not computed here (they need the receiver position).
"""

from dataclasses import dataclass

import numpy as np

from ultratight.constants import C
from ultratight.signals.ephemeris import eph_params, sat_state
from ultratight.signals.observations import SECONDS_PER_WEEK

CLOCK_ITERATIONS = 3


@dataclass
class SatStates:
    """Satellite states of the rows of a :class:`RawEpochs` (module doc); NaN where not valid."""
    pos_e: np.ndarray          # (m, 3) m, ECEF at transmit time (frame of the transmit time)
    vel_e: np.ndarray          # (m, 3) m/s
    clk_m: np.ndarray          # (m,) m, c * satellite clock correction (incl. relativistic, -TGD)
    drift_mps: np.ndarray      # (m,) m/s, c * its rate
    valid: np.ndarray          # (m,) bool
    t_tx: np.ndarray | None = None     # (m,) transmit time, continuous GPS seconds
    iode: np.ndarray | None = None     # (m,) IODE of the ephemeris used (-1: none)


def _half_fit_s(eph):
    """Half the fit interval (s), as :func:`ultratight.signals.ephemeris.in_fit_interval` takes it."""
    return 0.5 * (eph.fit_interval_h if eph.fit_interval_h > 0 else 4.0) * 3600.0


def _eph_times(ephs):
    return np.array([e.week * SECONDS_PER_WEEK + e.toe for e in ephs])


def select_rows(ephs, t):
    """Index into ``ephs`` (one PRN's ephemerides) of the set :meth:`NavData.select` would choose
    at each continuous GPS time of ``t`` (healthy, in its fit interval, toe nearest); -1 where none."""
    t = np.asarray(t, dtype=float)
    out = np.full(t.shape, -1, dtype=np.int64)
    if not ephs or t.size == 0:
        return out
    toe = _eph_times(ephs)
    half = np.array([_half_fit_s(e) for e in ephs])
    healthy = np.array([e.healthy for e in ephs])
    dt = np.abs(t[:, None] - toe[None, :])
    ok = (dt <= half[None, :]) & healthy[None, :]
    dt = np.where(ok, dt, np.inf)
    j = np.argmin(dt, axis=1)
    has = np.isfinite(dt[np.arange(t.size), j])
    out[has] = j[has]
    return out


def _evaluate(eph, t_sv):
    """(pos, vel, clk_s, drift) of ``eph`` at the transmit times whose satellite-clock readings are
    ``t_sv`` (continuous GPS seconds): the clock iteration of the module doc."""
    if hasattr(eph, "state"):                   # a CNAV set (ultratight.signals.cnav.CnavEphemeris)
        state = eph.state
    else:
        p = eph_params(eph)

        def state(tw):
            return sat_state(p, tw)
    base = eph.week * SECONDS_PER_WEEK
    clk = np.zeros_like(t_sv)
    for _ in range(CLOCK_ITERATIONS):
        _, _, clk, _ = state(t_sv - clk - base)
    t = t_sv - clk
    pos, vel, clk, drift = state(t - base)
    return pos, vel, clk, drift, t


def sat_states(raw, nav):
    """:class:`SatStates` of every row of ``raw`` (:class:`RawEpochs`) from ``nav`` (a
    :class:`ultratight.signals.rinex.NavData`, or anything with an ``ephemerides`` dict prn ->
    list of Ephemeris)."""
    m = int(raw.prn.shape[0])
    pos = np.full((m, 3), np.nan)
    vel = np.full((m, 3), np.nan)
    clk_m = np.full(m, np.nan)
    drift = np.full(m, np.nan)
    t_tx = np.full(m, np.nan)
    iode = np.full(m, -1, dtype=np.int64)
    valid = np.zeros(m, dtype=bool)
    t_rx = np.repeat(np.asarray(raw.t, dtype=float), np.diff(raw.start))
    pr = np.asarray(raw.pr_m, dtype=float)
    finite = np.isfinite(pr) & np.isfinite(t_rx)
    t_sv = np.where(finite, t_rx - np.where(finite, pr, 0.0) / C, np.nan)
    prns = np.asarray(raw.prn)
    for prn in np.unique(prns[finite]):
        ephs = nav.ephemerides.get(int(prn), [])
        rows = np.flatnonzero((prns == prn) & finite)
        sel = select_rows(ephs, t_sv[rows])
        for j in np.unique(sel[sel >= 0]):
            r = rows[sel == j]
            p_, v_, c_, d_, t_ = _evaluate(ephs[j], t_sv[r])
            # the fit-interval test at the transmit time itself (the selection used t_sv)
            keep = np.abs(t_ - _eph_times([ephs[j]])[0]) <= _half_fit_s(ephs[j])
            r, p_, v_, c_, d_, t_ = r[keep], p_[keep], v_[keep], c_[keep], d_[keep], t_[keep]
            pos[r], vel[r], clk_m[r], drift[r], t_tx[r] = p_, v_, C * c_, C * d_, t_
            iode[r] = ephs[j].iode
            valid[r] = True
    return SatStates(pos, vel, clk_m, drift, valid, t_tx, iode)
