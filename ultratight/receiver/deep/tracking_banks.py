"""Tracking banks of the ultra-tight engine: one factory per bank named by a method's spec
(:mod:`ultratight.receiver.deep.methods`), building the bank and the view the compiled epoch stages
take (:class:`ultratight.receiver.deep.epochs.Bank`).

Every bank offers the same protocol: ``step(z, bits)`` (one epoch of correlator outputs
``[I_P, I_E, I_L, Q_P, Q_E, Q_L]``, data-bit signs), ``correct(dx)``, ``reset(channels, x0, P0)``,
``describe()``, the state ``x`` / posterior ``x_post`` in the layout ``[A, dtau, dphi, df, da]``,
the covariance ``P`` with the code / frequency indices ``P_ITAU`` / ``P_IF``, ``active``,
``n_resets`` and ``packed`` (its state as buffers for the compiled stages). A new bank is a class
with that protocol, a compiled epoch function dispatched in
:func:`ultratight.receiver.deep.epochs.epoch_channel`, and an entry in :data:`FACTORIES`.
"""

import math

import numpy as np

from ultratight.fusion.channel import pbkf

from ultratight.fusion.channel import prefilter
from ultratight.receiver.deep.epochs import BANK_PBKF, BANK_PREFILTER, Bank


def _pbkf_bank(n_ch, opt, spec, init_sigmas, signal):
    bank = pbkf.PbKfBank(n_ch, cn0_dbhz_init=opt.cn0_init_dbhz)
    bank.reset(np.arange(n_ch))
    return bank


def _prefilter_bank(n_ch, opt, spec, init_sigmas, signal):
    """A PrefilterBank of the spec's kind, started with the hot-start sigmas: code from the tight
    filter's position/clock covariance (+ margin), Doppler 3 sigma + 0.5 Hz, rate 2 Hz/s."""
    kind = spec.bank
    kwargs = dict(opt.rackf_kwargs) if kind == "rackf" else {}
    kwargs.update(opt.prefilter_kwargs)
    kwargs.update(spec.bank_options)
    robust_mode = kwargs.pop("robust_mode", opt.robust_mode)
    bank = prefilter.PrefilterBank(n_ch, kind=kind, q=opt.prefilter_q, huber_c=opt.huber_c,
                                   correction_period=opt.rackf_period, robust_mode=robust_mode,
                                   cn0_dbhz_init=opt.cn0_init_dbhz, **kwargs)
    sig_code_chips, sig_dopp_hz = init_sigmas
    P_init = np.zeros((n_ch, 5, 5))
    base = prefilter.default_initial_covariance(opt.cn0_init_dbhz, signal.code_period_s)
    for ch in range(n_ch):
        P_init[ch] = base
        P_init[ch, 1, 1] = (sig_code_chips[ch] + opt.code_sigma_margin_chips) ** 2
        P_init[ch, 3, 3] = (2 * math.pi * (3.0 * sig_dopp_hz[ch] + 0.5)) ** 2
        P_init[ch, 4, 4] = (2 * math.pi * 2.0) ** 2
    bank.reset(np.arange(n_ch), P0=P_init)
    return bank


FACTORIES = {"pbkf": _pbkf_bank, **{k: _prefilter_bank for k in prefilter.KINDS}}


def make_tracking_bank(spec, n_ch, opt, init_sigmas, signal):
    """The tracking bank of a method spec for ``n_ch`` channels (``opt``: EngineOptions;
    ``init_sigmas``: hot-start code (chips) and Doppler (Hz) 1-sigma per channel)."""
    return FACTORIES[spec.bank](n_ch, opt, spec, init_sigmas, signal)


def restart_covariance(bank, chans, x0, opt, signal):
    """Covariance of channels restarted on a coherent phase estimate (start-up initialisation or a
    lock-monitor restart): amplitude 30 %, code as before (+ margin), phase 0.5 rad, frequency and
    rate from the options. None for banks that restart on their own initial covariance."""
    if isinstance(bank, pbkf.PbKfBank):
        return None
    base = prefilter.default_initial_covariance(opt.cn0_init_dbhz, signal.code_period_s)
    P0 = np.zeros((len(chans), 5, 5))
    for i, c in enumerate(chans):
        P0[i] = base
        P0[i, 0, 0] = (0.3 * x0[i, 0]) ** 2
        P0[i, 1, 1] = bank.P[c, 1, 1] + opt.code_sigma_margin_chips ** 2
        P0[i, 2, 2] = 0.5 ** 2
        P0[i, 3, 3] = (2 * math.pi * opt.reinit_sigma_f_hz) ** 2
        P0[i, 4, 4] = (2 * math.pi * opt.reinit_sigma_a_hzps) ** 2
    return P0


def bank_view(bank):
    """The :class:`ultratight.receiver.deep.epochs.Bank` tuple of a bank (views of its own buffers)."""
    if isinstance(bank, pbkf.PbKfBank):
        fbuf, ibuf, n_prm, n_tab = bank.packed
        return Bank(BANK_PBKF, 0, fbuf, ibuf, n_prm, n_tab, bank.x, bank.x_post, bank.P, bank.P_ITAU, bank.P_IF,
                    bank.active_flags, *prefilter.empty_kernel_arrays())
    kind, fbuf, ibuf = bank.packed
    return Bank(BANK_PREFILTER, kind, fbuf, ibuf, 0, 0, bank.x, bank.x_post, bank.P, bank.P_ITAU, bank.P_IF,
                bank.active_flags, *bank.kernel_arrays())
