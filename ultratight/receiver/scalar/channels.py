"""Acquisition hand-off of the scalar receiver: the cold-start search in two stages
(:func:`cold_search`), assistance records, the acquisition stage (:func:`acquire_signals`), the
channel allocation (:func:`allocate_channels`), the Doppler-rate search that starts every channel
under high dynamics (:func:`search_rate`) and the per-channel summary (:func:`channel_info`).

The receiver (:class:`ultratight.receiver.scalar.receiver.ScalarReceiver`) calls them at the start
and again when it re-acquires a lost channel or searches the PRNs without a channel (all in view).
"""

import math

from ultratight.errors import InputFileError
from ultratight.receiver.dsp.acquisition import AcqResult, acquire, doppler_rate_search
from ultratight.receiver.scalar.process_config import MAX_DOPPLER_FRACTION, NoSignalError
from ultratight.signals.signal import GPS_L1CA

STAGE2_HZ = 400.0            # half-width of the declared (long coherent) search around stage 1


def _peak_cn0(metric, coh_ms):
    return 10.0 * math.log10(max(metric - 1.0, 1e-12) / (coh_ms * 1e-3))


def _search_threads(cfg):
    """Threads of a search: ``--threads`` when given, else every allowed core (:func:`acquire`'s default)."""
    return int(cfg.threads) if cfg.threads else -1


def cold_search(source, cfg, start_sample, signal=GPS_L1CA, centres=None, half_width_hz=None):
    """Cold-start search; each result gets ``peak_cn0_dbhz = 10 log10((metric - 1) / T_coh)``.

    The CFAR metric is peak / noise floor of the search surface, whose mean under a signal is
    ``1 + C/N0 T_coh`` per coherent block, so the peak gives a C/N0 figure that is independent of the
    refinement (the same definition PocketSDR uses for its acquisition threshold).

    A 10 ms coherent block containing a data-bit transition near its middle loses most of its
    peak; bit edges are 20 ms apart, so a second look one block later cannot be hit as well.  By
    default recordings of 1 s or more get two looks; shorter snapshots get one look (the reference
    lists of shared/data/README.md were made so: on the 0.5 s PocketSDR IQ file a second look also
    declares PRN 18, a real satellite at ~38-40 dB-Hz that the list does not show).

    ``centres`` {prn: Hz} and ``half_width_hz`` ({prn: Hz} or Hz): the PRNs searched and the first
    stage's window around each centre (:func:`predicted_search`); default the PRNs of ``cfg`` in
    +-``cfg.doppler_range_hz``."""
    coh, nc, looks = _search_lengths(source, cfg, start_sample, signal)
    avail_ms = int((source.n_samples - start_sample) / source.fs_hz * 1000.0)
    if centres is None:
        prns, ctr, rng = (cfg.prns if cfg.prns else None), 0.0, cfg.doppler_range_hz
    else:
        prns, ctr, rng = list(centres), centres, half_width_hz
    # stage 1: cheap search (1 ms coherent, up to 10 non-coherent): candidate PRNs and Dopplers
    if nc > 1:
        # weak-signal settings: the full search at the requested integration (a 1 ms first stage
        # would lose the coherent gain)
        res = acquire(source, prns=prns, doppler_center_hz=ctr, doppler_range_hz=rng, coherent_ms=coh,
                      noncoherent=nc, pfa=cfg.acq_pfa, start_sample=start_sample, signal=signal,
                      workers=_search_threads(cfg))
    else:
        nc1 = max(1, min(avail_ms, 10))
        res = acquire(source, prns=prns, doppler_center_hz=ctr, doppler_range_hz=rng, coherent_ms=1,
                      noncoherent=nc1, pfa=cfg.acq_pfa, start_sample=start_sample, signal=signal,
                      workers=_search_threads(cfg))
    if nc == 1 and coh > 1:
        # stage 2: the declared search (coh ms coherent) only for the candidates, in a window of
        # +-STAGE2_HZ around their stage-1 Doppler; a second look one block later for long files
        cand = [a.prn for a in res if a.detected]
        if cand:
            by_prn = _declared_search(source, cfg, {a.prn: a.doppler_hz for a in res if a.detected}, STAGE2_HZ,
                                      start_sample, coh, nc, looks, signal)
            res = [by_prn.get(a.prn, a) for a in res]
    return _annotate(res, coh, nc)


def _annotate(res, coh, nc):
    for a in res:
        a.peak_cn0_dbhz = _peak_cn0(a.metric, coh)
        a.coherent_ms = coh
        a.noncoherent = nc
    return res


def _search_lengths(source, cfg, start_sample, signal):
    """``(coh, nc, looks)`` of a search at ``start_sample``: the configured coherent length and
    non-coherent count cut to the samples left, and the looks (2 for recordings of 1 s or more)."""
    avail_ms = int((source.n_samples - start_sample) / source.fs_hz * 1000.0)
    if avail_ms < 1:
        raise InputFileError(f"{source.path}: only {source.n_samples - start_sample} samples "
                             f"({(source.n_samples - start_sample) / source.fs_hz * 1e3:.3f} ms) from the start "
                             f"sample; need at least 1 ms (one {signal.name} code period) to acquire")
    coh = max(1, min(int(cfg.acq_coherent_ms), avail_ms))
    nc = max(1, min(int(cfg.acq_noncoherent), avail_ms // coh))
    looks = cfg.acq_looks if cfg.acq_looks is not None else (2 if avail_ms >= 1000 else 1)
    looks = 2 if (looks > 1 and avail_ms >= 2 * coh * nc) else 1
    return coh, nc, looks


def _declared_search(source, cfg, centres, half_width_hz, start_sample, coh, nc, looks, signal):
    """The declared search (``coh`` ms coherent x ``nc``) of the PRNs of ``centres`` {prn: Hz} in
    +-``half_width_hz`` around their centre; {prn: best AcqResult over the looks}.  A data-bit edge
    can cancel one 10 ms block, never two consecutive ones (edges are 20 ms apart): the next look,
    one block later, only for the PRNs still short of the declaration floor."""
    n_blk = int(round(coh * nc * 1e-3 * source.fs_hz))
    cand = list(centres)
    by_prn = {}
    for look in range(looks):
        r2 = acquire(source, prns=cand, doppler_center_hz={p: centres[p] for p in cand},
                     doppler_range_hz=half_width_hz, coherent_ms=coh, noncoherent=nc, pfa=cfg.acq_pfa,
                     start_sample=start_sample + look * n_blk, signal=signal, workers=_search_threads(cfg))
        for b in r2:
            if b.prn not in by_prn or b.metric > by_prn[b.prn].metric:
                by_prn[b.prn] = b
        cand = [p for p in cand if not (by_prn[p].detected and
                                        _peak_cn0(by_prn[p].metric, coh) >= cfg.acq_min_cn0_dbhz)]
        if not cand:
            break
    return by_prn


def predicted_search(source, cfg, start_sample, centres, half_width_hz, signal=GPS_L1CA):
    """The search of PRNs whose Doppler is predicted (all in view with a fix and ephemerides,
    :mod:`ultratight.receiver.scalar.search_plan`): :func:`cold_search`'s two stages with the first
    one in +-``half_width_hz`` around ``centres`` {prn: Hz} (kept inside ``MAX_DOPPLER_FRACTION`` fs)
    instead of the whole band; one result per PRN, in the order of ``centres``."""
    top = MAX_DOPPLER_FRACTION * source.fs_hz
    ctr = {int(p): max(-top, min(top, float(d))) for p, d in centres.items()}
    width = {p: max(0.0, min(float(half_width_hz), top - abs(d))) for p, d in ctr.items()}
    return cold_search(source, cfg, start_sample, signal, centres=ctr, half_width_hz=width)


def _assisted(a, start_sample):
    """An acquisition-like record from an assistance dict (prn, doppler_hz, code_phase_chips,
    sample_index, optional cn0_dbhz)."""
    cn0 = float(a.get("cn0_dbhz", math.nan))
    r = AcqResult(prn=int(a["prn"]), doppler_hz=float(a["doppler_hz"]), code_phase_chips=float(a["code_phase_chips"]),
                  cn0_dbhz=cn0, metric=math.inf, detected=True, threshold=0.0,
                  sample_index=int(a.get("sample_index", start_sample)))
    r.peak_cn0_dbhz = math.inf        # assisted channels are not subject to the acquisition C/N0 floor
    r.coherent_ms = 0
    r.noncoherent = 0
    return r


def search_rate(source, a, cfg, stop_sample, signal=GPS_L1CA):
    """High dynamics: the Doppler and Doppler rate of the detected acquisition ``a`` by
    :func:`ultratight.receiver.dsp.acquisition.doppler_rate_search` over ``cfg.rate_span_s`` (shorter
    before ``stop_sample``); sets ``a.doppler_hz`` and ``a.rate_hz_s``. Normal dynamics, assisted
    records, or too few samples left: ``a.rate_hz_s`` = None (the loop starts without a rate)."""
    a.rate_hz_s = None
    if cfg.dynamics != "high" or not a.detected or not math.isfinite(a.metric):
        return a
    span = min(cfg.rate_span_s, (stop_sample - a.sample_index) / source.fs_hz)
    if span < 0.05:
        return a
    r = doppler_rate_search(source, a.prn, a.doppler_hz, a.code_phase_chips, a.sample_index, span_s=span,
                            signal=signal)
    a.doppler_acq_hz = a.doppler_hz
    a.doppler_hz = r.doppler_hz
    a.rate_hz_s = r.rate_hz_s
    return a


def acquire_signals(source, cfg, start_sample, assist=None, signal=GPS_L1CA):
    """Acquisition / assistance stage: one :class:`ultratight.receiver.dsp.acquisition.AcqResult` per
    PRN searched (``assist``: records replacing the search). Detections below the C/N0 floor are
    marked ``weak`` and not ``detected``; raises :class:`NoSignalError` when none is left."""
    if assist is not None:
        acq = [_assisted(a, start_sample) for a in assist]
    else:
        acq = cold_search(source, cfg, start_sample, signal)
    for a in acq:
        if a.detected and not (a.peak_cn0_dbhz >= cfg.acq_min_cn0_dbhz):
            a.weak = True                # passed the false-alarm test, below the C/N0 floor
            a.detected = False
    if not any(a.detected for a in acq):
        fs = source.fs_hz
        raise NoSignalError(
            f"no satellites acquired in {source.path} (format {source.fmt}, fs {fs:g} Hz, IF {source.if_hz:g} Hz, "
            f"{'complex' if source.is_complex else 'real'} samples, iq_conj={bool(getattr(source, '_conj', False))}, "
            f"Doppler +-{cfg.doppler_range_hz:g} Hz, {acq[0].coherent_ms} ms coherent x {acq[0].noncoherent}, "
            f"C/N0 floor {cfg.acq_min_cn0_dbhz:g} dB-Hz; below the floor: "
            f"{[a.prn for a in acq if getattr(a, 'weak', False)] or 'none'}). "
            f"Hint: check --fs/--if/--format; for complex files try --iq-conj (I - jQ spectrum inversion); "
            f"for real files check the IF sign/LO side")
    return acq


def allocate_channels(acq, cfg, signal=GPS_L1CA):
    """Channel allocation: ``(found, idle_prns)`` - the acquisitions that start a channel now
    (strongest first, at most ``n_channels``) and, all in view (``n_channels`` None), the searched
    PRNs that get a channel for a later search."""
    found = sorted([a for a in acq if a.detected], key=lambda a: -a.metric)
    if cfg.n_channels is not None:
        return found[:cfg.n_channels], []
    searched = [int(p) for p in (cfg.prns or signal.prns)]
    got = {a.prn for a in found}
    return found, [p for p in dict.fromkeys(searched) if p not in got]


def channel_info(prn, acq=None, start_sample=0, fs=1.0):
    """The summary dict of a channel of ``prn`` (counters, decoding and lock times; ``acq``: the
    acquisition that started it at once, None for a PRN kept for a later search)."""
    return {"prn": prn, "epochs": 0, "locked_epochs": 0, "losses": 0, "reacquisitions": 0,
            "tow_s": None, "ephemeris_s": None, "cn0_dbhz": None, "tracked": False,
            "next_retry": None, "bit_sync": False, "bit_sync_s": None, "started": acq is not None,
            "acquired_s": None if acq is None else (acq.sample_index - start_sample) / fs}
