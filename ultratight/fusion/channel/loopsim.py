"""Closed-loop run of a per-channel prefilter bank against the correlator-level simulator.

:func:`run_closed_loop` steps a prefilter bank (:class:`ultratight.fusion.channel.prefilter.PrefilterBank`
or :class:`ultratight.fusion.channel.pbkf.PbKfBank`) epoch by epoch on the outputs of
:class:`ultratight.signals.synth.corrsim.CorrSim` and closes the inner loop through
:class:`ultratight.fusion.channel.innerloop.InnerLoop` (optionally with the outer-loop Doppler aiding of the
simulated truth), logging true vs estimated Doppler and code phase — the inner loop of the
double-loop structure of Zhao et al. 2014 (Fig. 1; see docs/references.md) without the IF stage.
Used by the prefilter tests and benchmarks.
"""

from __future__ import annotations

import numpy as np

from ultratight.fusion.channel.innerloop import InnerLoop
from ultratight.fusion.channel.prefilter_model import IA, IDA, IF, ITAU
from ultratight.signals.synth.corrsim import TWO_PI, CorrSim, SimScenario


def run_closed_loop(sc: SimScenario, bank, rng: np.random.Generator, law=None, aiding=True,
                    use_aid=None, bits_known=True, init_err=None, truth=None, on_epoch=None):
    """Run a prefilter bank + inner-loop law against the correlator-level simulator.

    ``bank``: PrefilterBank or PbKfBank (n_ch channels, already reset/initialised);
    ``law``: InnerLoop (default: full feedback); ``aiding``: feed the outer-loop Doppler
    prediction (truth.aid_hz) forward; ``use_aid``: arbitration mask (n_ch,) or None;
    ``bits_known``: pass the true data bits (else the bank decides them);
    ``init_err``: dict(code_err_chips, phase_err_rad, freq_err_hz) for the NCO start.
    Returns a dict of (N, n_ch) logs: t (interval start), dopp_true_hz (mean over the
    interval), dopp_est_hz (NCO + posterior df, da), dopp_err_hz, code_err_chips (true code
    error at the interval start minus the posterior dtau), nco_dopp_err_hz (NCO freq - true),
    true_dtau, true_dphi, nis, theta, flags.
    """
    sim = CorrSim(sc, rng, truth=truth)
    n = sim.n
    N = sim.N
    T = sim.T
    if law is None:
        law = InnerLoop(n, T=T)
    sim.init_nco(**(init_err or {}))
    tr = sim.truth
    if aiding:
        # the NCO starts on the interval-0 Doppler: the aiding history starts there too
        rate0 = (tr.aid_hz[1] - tr.aid_hz[0]) / sim.T if N > 1 else np.zeros(n)
        law.prime_aiding(bank, tr.aid_hz[0], rate0)
    log = {k: np.zeros((N, n)) for k in ("dopp_true_hz", "dopp_est_hz", "code_err_chips", "nco_dopp_err_hz",
                                         "true_dtau", "true_dphi", "nis", "theta", "amp_est")}
    log["flags"] = np.zeros((N, n), dtype=np.int64)
    bits = None
    for k in range(N):
        z = sim.outputs()
        if bits_known:
            bits = tr.bits[k]
        f_nco = sim.nco.carr_freq.copy()
        bank.step(z, bits)
        xp = bank.x_post
        log["dopp_true_hz"][k] = tr.freq_mid[k]
        log["dopp_est_hz"][k] = f_nco + (xp[:, IF] + 0.5 * T * xp[:, IDA]) / TWO_PI
        log["nco_dopp_err_hz"][k] = f_nco - tr.freq_mid[k]
        log["true_dtau"][k] = sim.err[:, 0]
        log["true_dphi"][k] = sim.err[:, 1]
        log["code_err_chips"][k] = sim.err[:, 0] - xp[:, ITAU]
        log["nis"][k] = bank.nis
        log["theta"][k] = bank.theta
        log["flags"][k] = bank.flags
        log["amp_est"][k] = xp[:, IA]
        if k + 1 < N:
            aid = tr.aid_hz[k + 1] if aiding else None
            law.apply(bank, sim.nco, aid, use_aid)
            sim.advance()
        if on_epoch is not None:
            on_epoch(k, sim, bank)
    log["t"] = tr.t[:-1]
    log["dopp_err_hz"] = log["dopp_est_hz"] - log["dopp_true_hz"]
    return log
