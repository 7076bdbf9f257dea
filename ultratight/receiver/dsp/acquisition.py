"""Acquisition: FFT parallel code-phase search over Doppler bins.

The signal is a :class:`ultratight.signals.signal.SignalDescription` (default GPS L1 C/A): its PRNs,
code generator, chip rate ``f_chip``, code length ``L`` and carrier ``f_carrier`` (below for C/A:
``f_chip`` = 1.023 MHz, ``L`` = 1023, ``f_carrier`` = L1).

Search
------
The input (complex baseband, or real IF mixed down to complex baseband with
``exp(-j*2*pi*if_hz*t)``) is cut into ``K = noncoherent`` consecutive blocks of
``N = round(fs * coherent_ms * 1e-3)`` samples.  For a Doppler bin ``f`` the
block is wiped with ``exp(-j*2*pi*f*n/fs)`` and circularly correlated with the
sampled local code ``c_rep[n] = code(floor(n * f_chip / fs) mod L)`` (repeated
``coherent_ms`` times) by ``IFFT(FFT(x) * conj(FFT(c_rep)))``, all code phases
at once.  The Doppler grid is ``f_j = j * step`` (anchored at 0 Hz) with ``step = (p/q) *
fs/N`` (default ``p/q = 2/3``, i.e. ~2/(3T)); a shift by a whole FFT bin ``fs/N`` is a circular shift of
the spectrum, so only ``q`` mixed FFTs per block are computed and every Doppler bin reuses them (the
shift is applied to the code spectrum, which leaves the correlation magnitude unchanged). Code FFTs
are cached per ``(fs, N)``.

The detection statistic is the non-coherent sum ``S(f, m) = sum_k |Y_k(f, m)|^2``
where block ``k``'s correlation is circularly shifted by ``round(k*drift)``, the
predicted lag drift per block ``drift = (P - N) - N*f/f_carrier`` samples (the
non-integer code period ``P = fs*coherent_ms*1e-3`` samples versus the block
length ``N``, plus the code Doppler), so the peak stays in
one cell over long searches and for sample rates that are not multiples of
1.023 MHz.  The code Doppler *inside* one coherent block (<= 0.065 chip at
10 kHz over 10 ms) is not compensated (loss < 0.3 dB).

Detection statistics
--------------------
Under noise only, each ``Y_k`` is circular complex Gaussian, ``|Y_k|^2`` is
exponential and ``S`` is ``E[S]/(2K) * chi2(2K)`` (chi-square with 2K degrees of
freedom); a cell's ``S / E[S]`` is ``chi2(2K)/(2K)``, of variance ``1/K``.
Only one code period of lags is kept (for ``coherent_ms > 1`` the circular
correlation repeats every period).

Noise floor, per Doppler row (cell-averaging CFAR along the code dimension): the
mean of the row's cells outside ``+-exclude_chips`` (default 2 chips) of the
candidate's code phase.  Per row because real recordings are not white: CW and
1-ms-periodic interference (the pocketsdr front end has both) correlate with the
periodic code only in Doppler rows at particular offsets (e.g. whole kHz), and
the cross-correlation of strong satellites concentrates near their Dopplers.
In the candidate's own row its code autocorrelation sidelobes
``(peak - floor) * R(l - m)^2`` (deterministic, ``R`` from the sampled code) are
subtracted before the statistics: they are signal, not noise.

Structured interference repeats identically in every block (it does not average
down non-coherently), so the cells disperse more than ``1/K``.  Each row's
threshold uses an effective number of sums ``K_eff = min(K, 1/v)``, ``v`` = the
variance of ``S/floor`` over the row's noise cells (moment matching of a scaled
chi-square, Satterthwaite); for white noise ``K_eff ~= K``, the textbook test.

The search covers ``M = n_doppler * n_lags`` cells per PRN; with a false-alarm
probability ``pfa`` per PRN search the per-cell probability is
``1 - (1 - pfa)**(1/M)`` (Sidak: cells treated as independent, conservative
since neighbouring cells are correlated) and a row's threshold is
``chi2.isf(pfa_cell, 2*K_eff) / (2*K_eff)`` (:func:`cell_threshold`).  The
candidate is the raw peak of ``S``, unless the cell farthest above its row's
threshold lies at another code phase (the raw peak then sat in a row raised by
interference).  ``metric = S(candidate) / floor(row)`` is compared with that
row's threshold.

CW excision: before correlating, spectral bins of the blocks whose power exceeds the local median level
by the factor a noise-only bin exceeds with probability 1e-4 are zeroed with one neighbour each side
(unless more than 5 % of the bins are flagged: that is not narrowband interference).

Refinement and C/N0 (detected PRNs)
-----------------------------------
1. Parabolic interpolation over the Doppler bins and code lags around the peak.
2. The code is wiped off at the estimated code phase and the signal summed over
   1 ms sub-blocks ``z_i``; the residual frequency is
   ``angle(sum z_{i+1} conj(z_i)) / (2*pi*T_sub)`` (unambiguous +-500 Hz,
   insensitive to data-bit flips, which only flip single products).
3. At the fine frequency the normalised power ``|z_i|^2`` (corr_model scaling,
   unit noise per arm) is evaluated on a 0.05-chip grid of code offsets (+-0.5 chip,
   at the input rate when the search was decimated); the
   best offset refines the code phase and ``C/N0 = (mean|z|^2 - 2) / (2*T_sub)``.

Outputs
-------
``code_phase_chips`` is the signal's code phase at sample ``sample_index`` (the
first sample of the acquisition block), ready for
:meth:`ultratight.receiver.dsp.correlator.CorrelatorBank.init_channel`;
``doppler_hz`` is the carrier Doppler (for real IF: relative to ``if_hz``).
"""

import functools
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from ultratight.chi2 import gammainccinv
from ultratight.cores import allowed_cores
from ultratight.errors import ConfigError
from ultratight.receiver.dsp.blockstream import block_sigma_arm
from ultratight.receiver.dsp.medfilt import running_median_wrap
from ultratight.signals.geometry import light_time
from ultratight.signals.signal import GPS_L1CA

MAX_COHERENT_MS = 10
_T_SUB = 1e-3              # sub-block length for fine Doppler / C/N0 (s)
_FINE_CODE_STEP = 0.05     # chips
_FINE_CODE_SPAN = 0.5      # +- chips around the coarse code phase (coarse error < 0.25 chip)
_CHUNK_ELEMS = 1 << 22     # complex elements per IFFT batch


@dataclass
class AcqResult:
    """One PRN's acquisition result (see module docstring for the definitions)."""
    prn: int
    doppler_hz: float          # refined Doppler (coarse when not detected)
    code_phase_chips: float    # signal code phase at sample_index, [0, code length)
    cn0_dbhz: float            # NaN when not detected
    metric: float              # peak / noise floor
    detected: bool
    threshold: float           # metric threshold for the requested pfa
    sample_index: int          # absolute sample index the code phase refers to
    doppler_coarse_hz: float = math.nan
    n_doppler_bins: int = 0
    k_eff: float = math.nan    # effective non-coherent sums of the noise cells (<= noncoherent)
    n_excised_bins: int = 0    # spectral bins zeroed as CW interference


def _check_int(name, value, lo, hi):
    if isinstance(value, bool) or not float(value).is_integer():
        raise ConfigError(f"acquire: {name} must be a whole number in {lo}..{hi}, got {value!r}")
    value = int(value)
    if not lo <= value <= hi:
        raise ConfigError(f"acquire: {name} must be in {lo}..{hi}, got {value}")
    return value


def _code_spectra(fs_hz, n, coherent_ms, signal=GPS_L1CA):
    """conj(FFT(c_rep)) for every PRN of ``signal`` (in the order of ``signal.prns``), complex64."""
    return _code_spectra_of(signal.code, signal.prns, float(signal.chip_rate_hz), int(signal.code_length),
                            fs_hz, n, coherent_ms)


@functools.lru_cache(maxsize=16)
def _code_spectra_of(code, prns, chip_rate_hz, code_length, fs_hz, n, coherent_ms):
    idx = np.floor(np.arange(n) * (chip_rate_hz / fs_hz)).astype(np.int64) % code_length
    codes = np.stack([code(p) for p in prns]).astype(np.float32)[:, idx]
    spec = np.conj(np.fft.fft(codes, axis=1)).astype(np.complex64)
    spec.setflags(write=False)
    return spec


def _as_per_prn(value, prns, name):
    if isinstance(value, dict):
        missing = [p for p in prns if p not in value]
        if missing:
            raise ConfigError(f"acquire: {name} given per PRN but missing PRNs {missing}")
        return {p: float(value[p]) for p in prns}
    return {p: float(value) for p in prns}


def _read_input(source, fs_hz, if_hz, is_complex, start_sample, n_needed):
    """Return (samples, fs, if, is_complex) from an IfSource-like object or an array."""
    if hasattr(source, "read") and hasattr(source, "fs_hz"):
        fs_hz = source.fs_hz if fs_hz is None else fs_hz
        if_hz = getattr(source, "if_hz", 0.0) if if_hz is None else if_hz
        is_complex = source.is_complex if is_complex is None else is_complex
        total = getattr(source, "n_samples", None)
        if total is not None and start_sample + n_needed > total:
            raise ConfigError(f"acquire: block too short: need {n_needed} samples from sample {start_sample}, "
                              f"the source has {total}")
        x = np.asarray(source.read(start_sample, n_needed))
        offset = 0
    else:
        x = np.asarray(source)
        if x.ndim != 1:
            raise ConfigError(f"acquire: samples must be a 1-D array, got shape {x.shape}")
        if is_complex is None:
            is_complex = np.iscomplexobj(x)
        offset = start_sample
    if fs_hz is None:
        raise ConfigError("acquire: fs_hz is required when passing a sample array")
    if_hz = 0.0 if if_hz is None else float(if_hz)
    if x.shape[0] - offset < n_needed:
        raise ConfigError(f"acquire: block too short: need {n_needed} samples "
                          f"({n_needed / float(fs_hz) * 1e3:.3f} ms) from sample {start_sample}, "
                          f"got {max(x.shape[0] - offset, 0)}")
    return x[offset:offset + n_needed], float(fs_hz), if_hz, bool(is_complex)


def _to_baseband(x, fs_hz, if_hz, is_complex):
    if is_complex:
        if np.iscomplexobj(x):
            xb = x.astype(np.complex64, copy=True)
        else:
            raise ConfigError("acquire: is_complex=True but the samples are real")
    else:
        if np.iscomplexobj(x):
            raise ConfigError("acquire: is_complex=False but the samples are complex")
        xb = x.astype(np.float32, copy=False).astype(np.complex64)
    xb -= xb.mean()
    if if_hz != 0.0:
        n = np.arange(x.shape[0], dtype=np.float64)
        ph = (if_hz / fs_hz) * n
        ph -= np.floor(ph)
        xb *= np.exp(-2j * np.pi * ph).astype(np.complex64)
    return xb


def cell_threshold(pfa, n_cells, noncoherent):
    """Metric threshold (peak / noise floor) for a per-search false-alarm probability ``pfa``.

    Per-cell probability ``1 - (1 - pfa)**(1/n_cells)``; metric of a noise cell
    ``chi2(2K)/(2K)`` with ``K = noncoherent`` (scalar or array: one threshold per value).
    """
    pfa_cell = -math.expm1(math.log1p(-pfa) / n_cells)
    # chi2.isf(p, 2K) / (2K) = gammainccinv(K, p) / K  (ultratight.chi2)
    k = np.asarray(noncoherent, dtype=float)
    thr = gammainccinv(k, pfa_cell) / k
    return float(thr) if thr.ndim == 0 else thr


def acquire(source_or_samples, fs_hz=None, if_hz=None, is_complex=None, prns=None, doppler_range_hz=10e3,
            doppler_center_hz=0.0, coherent_ms=1, noncoherent=10, pfa=1e-3, bin_fraction=Fraction(2, 3),
            start_sample=0, exclude_chips=2.0, refine=True, decimate_to_hz=4.0e6, excise_cw=True, workers=-1,
            signal=GPS_L1CA):
    """Search PRNs of ``signal`` (a :class:`ultratight.signals.signal.SignalDescription`, default GPS
    L1 C/A); returns a list of :class:`AcqResult` (one per PRN, in order).

    Parameters
    ----------
    source_or_samples : IfSource-like (``read(start, count)``, ``fs_hz``, ``if_hz``, ``is_complex``)
        or 1-D ndarray (complex or real samples).
    fs_hz, if_hz, is_complex : front end (taken from the source when None; ``is_complex`` from the dtype).
    prns : iterable of PRNs (default all of the signal's).
    doppler_range_hz : half-width of the Doppler window (scalar or {prn: Hz}).
    doppler_center_hz : window centre (scalar or {prn: Hz}): the assisted mode passes the
        predicted Doppler per PRN (e.g. from :func:`predicted_doppler`) and a small window.
    coherent_ms : coherent integration, whole ms, 1..10.
    noncoherent : number K of non-coherent sums (>= 1).
    pfa : false-alarm probability per PRN search (0 < pfa < 1).
    bin_fraction : Doppler bin width as a fraction p/q of the FFT bin fs/N (default 2/3).
    start_sample : absolute index of the first sample used.
    exclude_chips : half-width (chips) of the code-phase region around the peak left out of the noise floor.
    refine : fine Doppler, code phase and C/N0 for detected PRNs.
    decimate_to_hz : when fs >= 2 * decimate_to_hz, the search and refinement run on the baseband
        signal low-passed and decimated by D = floor(fs / decimate_to_hz) (scipy.signal.resample_poly,
        Kaiser FIR); None or 0 disables.
    excise_cw : zero narrowband-interference bins of the block spectra before correlating
        (see :func:`_excise_cw`); the count is reported in ``AcqResult.n_excised_bins``.
    workers : threads (-1 or None: every allowed core, :func:`ultratight.cores.allowed_cores`): the PRNs are
        searched in that many threads (numpy's FFTs release the GIL; the results do not depend on it).
    signal : the signal searched: its PRNs, code generator, chip rate, code length and carrier.
    """
    coherent_ms, noncoherent, frac, prns, fs_hz = _check_arguments(
        source_or_samples, fs_hz, coherent_ms, noncoherent, pfa, bin_fraction, prns, signal)
    n_needed = int(round(fs_hz * coherent_ms * 1e-3)) * noncoherent
    x, fs_hz, if_hz, is_complex = _read_input(source_or_samples, fs_hz, if_hz, is_complex,
                                              int(start_sample), n_needed)
    if not is_complex and if_hz == 0.0:
        raise ConfigError("acquire: real samples need a non-zero if_hz (real baseband cannot carry the signal)")
    rng_hz = _as_per_prn(doppler_range_hz, prns, "doppler_range_hz")
    ctr_hz = _as_per_prn(doppler_center_hz, prns, "doppler_center_hz")
    for p, r in rng_hz.items():
        if not (math.isfinite(r) and r >= 0.0):
            raise ConfigError(f"acquire: doppler_range_hz must be >= 0, got {r!r} for PRN {p}")
        if abs(ctr_hz[p]) + r >= 0.5 * fs_hz:
            raise ConfigError(f"acquire: Doppler window {ctr_hz[p]} +- {r} Hz exceeds fs/2 = {fs_hz / 2} Hz")
    blk = _SearchBlocks(x, fs_hz, if_hz, is_complex, coherent_ms, noncoherent, frac, decimate_to_hz, excise_cw,
                        signal)
    exclude = int(math.ceil(exclude_chips * blk.fs_s / signal.chip_rate_hz))
    threads = min(len(prns), allowed_cores() if workers is None or workers < 1 else int(workers))
    if threads <= 1:
        return [_search_prn(blk, prn, ctr_hz[prn], rng_hz[prn], float(pfa), exclude, refine, int(start_sample))
                for prn in prns]
    # one PRN per thread (numpy and its FFTs release the GIL)
    with ThreadPoolExecutor(threads, thread_name_prefix="acquisition") as pool:
        return list(pool.map(lambda prn: _search_prn(blk, prn, ctr_hz[prn], rng_hz[prn], float(pfa), exclude,
                                                     refine, int(start_sample)), prns))


def _check_arguments(source, fs_hz, coherent_ms, noncoherent, pfa, bin_fraction, prns, signal):
    """Checked (coherent_ms, noncoherent, bin fraction, PRN list, fs_hz) of :func:`acquire`."""
    coherent_ms = _check_int("coherent_ms", coherent_ms, 1, MAX_COHERENT_MS)
    noncoherent = _check_int("noncoherent", noncoherent, 1, 100000)
    if fs_hz is not None and not (math.isfinite(float(fs_hz)) and float(fs_hz) > 0.0):
        raise ConfigError(f"acquire: fs_hz must be a positive sampling rate, got {fs_hz!r}")
    if not (0.0 < float(pfa) < 1.0):
        raise ConfigError(f"acquire: pfa must be in (0, 1), got {pfa!r}")
    frac = Fraction(bin_fraction).limit_denominator(16)
    if not (0 < frac <= 1):
        raise ConfigError(f"acquire: bin_fraction must be in (0, 1], got {bin_fraction!r}")
    prns = list(signal.prns) if prns is None else [int(p) for p in prns]
    for p in prns:
        if p not in signal.prns:
            raise ConfigError(f"acquire: PRN must be in {min(signal.prns)}..{max(signal.prns)}, got {p}")
    if hasattr(source, "fs_hz") and fs_hz is None:
        fs_hz = source.fs_hz
    if fs_hz is None:
        raise ConfigError("acquire: fs_hz is required when passing a sample array")
    fs_hz = float(fs_hz)
    if not (math.isfinite(fs_hz) and fs_hz > 0.0):
        raise ConfigError(f"acquire: fs_hz must be a positive sampling rate, got {fs_hz!r}")
    if fs_hz < signal.chip_rate_hz:
        raise ConfigError(f"acquire: fs_hz = {fs_hz} Hz is below the {signal.name} chip rate {signal.chip_rate_hz} Hz")
    return coherent_ms, noncoherent, frac, prns, fs_hz


class _SearchBlocks:
    """The search input of :func:`acquire`: baseband blocks (decimated at high rates), their spectra
    at the q fractional Doppler offsets, the code spectra, and what the refinement needs."""

    def __init__(self, x, fs_hz, if_hz, is_complex, coherent_ms, noncoherent, frac, decimate_to_hz, excise_cw,
                 signal):
        self.signal, self.noncoherent, self.fs_hz = signal, noncoherent, fs_hz
        self.sigma_arm = _sigma_arm(x, is_complex)
        self.xb = _to_baseband(x, fs_hz, if_hz, is_complex)
        # high sampling rates: low-pass + decimation by D for the search and the refinement
        self.dec = int(fs_hz // decimate_to_hz) if (decimate_to_hz and fs_hz >= 2.0 * decimate_to_hz) else 1
        self.fs_s = fs_s = fs_hz / self.dec
        n_s = int(round(fs_s * coherent_ms * 1e-3))
        if self.dec > 1:
            # polyphase FIR low-pass (Kaiser) + decimation; output sample j is input sample j*D (delay
            # compensated).  A boxcar is not enough: for real IF the mixing image at -2*IF can alias
            # onto the signal band (e.g. IF = fs/4, D = 4 puts it at 0 Hz) and bias the code phase.
            # scipy.signal loads here, only for such rates: its import (~1 s, it loads scipy.stats)
            # would otherwise be a large part of a short run's start-up
            from scipy.signal import resample_poly
            xs = resample_poly(self.xb, 1, self.dec).astype(np.complex64)
            xs = xs[:n_s * noncoherent]
            if xs.shape[0] < n_s * noncoherent:
                raise ConfigError("acquire: block too short after decimation")
        else:
            xs = self.xb
        blocks = xs.reshape(noncoherent, n_s)
        sigma_dec = self.sigma_arm if self.dec == 1 else _sigma_arm(xs, True)
        self.n_coh = n_coh = n_s
        self.step = float(frac) * (fs_s / n_coh)
        self.p_num, self.q_den = frac.numerator, frac.denominator
        # mixed block spectra for the q fractional offsets r/q of an FFT bin
        n_idx = np.arange(n_coh)
        self.base = []
        for r in range(self.q_den):
            if r == 0:
                self.base.append(np.fft.fft(blocks, axis=1))
            else:
                mix = np.exp(-2j * np.pi * (r / self.q_den) * n_idx / n_coh).astype(np.complex64)
                self.base.append(np.fft.fft(blocks * mix, axis=1))
        self.n_excised = 0
        self.xs_ref, self.sigma_ref = xs, sigma_dec
        if excise_cw:
            for b in self.base:
                self.n_excised = max(self.n_excised, _excise_cw(b))
            if self.n_excised:
                # refinement and C/N0 on the cleaned signal (the unmixed blocks' excised spectra)
                self.xs_ref = np.fft.ifft(self.base[0], axis=1).ravel().astype(np.complex64)
                self.sigma_ref = _sigma_arm(self.xs_ref, True)
        self.code_spec = _code_spectra(fs_s, n_coh, coherent_ms, signal)
        self.period = fs_s * coherent_ms * 1e-3           # samples per coherent_ms (may be fractional)
        self.n_fold = min(n_coh, int(math.ceil(fs_s * signal.code_period_s)))   # lags in one code period


def _search_prn(blk, prn, ctr_hz, rng_hz, pfa, exclude, refine, start_sample):
    """Search one PRN over its Doppler window: CFAR decision, interpolated peak, refinement."""
    sig = blk.signal
    j_lo = math.ceil((ctr_hz - rng_hz) / blk.step - 1e-9)
    j_hi = math.floor((ctr_hz + rng_hz) / blk.step + 1e-9)
    js = np.arange(j_lo, j_hi + 1)
    cspec = blk.code_spec[sig.prns.index(prn)]
    n_fold, noncoherent = blk.n_fold, blk.noncoherent
    surf = _search_surface(blk.base, cspec, js, blk.p_num, blk.q_den, noncoherent, blk.n_coh, blk.period,
                           blk.step, sig.carrier_hz)
    # one code period of lags suffices (longer blocks repeat the same lags)
    surf = surf[:, :n_fold]
    self_r2 = _self_sidelobes(cspec, n_fold)
    n_cells = surf.size
    # candidate: the raw peak; statistics per Doppler row (CFAR along the code dimension)
    jrow, m = np.unravel_index(int(np.argmax(surf)), surf.shape)
    floors, k_rows, thr_rows = _row_statistics(surf, jrow, m, exclude, noncoherent, pfa, n_cells, self_r2)
    # the cell farthest above its row's threshold decides: at the raw peak's code phase it is
    # the same signal (kept at the raw peak); elsewhere the raw peak sat in a row raised by
    # interference and that cell becomes the candidate
    j2, m2 = np.unravel_index(int(np.argmax(surf / (floors * thr_rows)[:, None])), surf.shape)
    if abs((m2 - m + n_fold // 2) % n_fold - n_fold // 2) > exclude:
        jrow, m = j2, m2
        floors, k_rows, thr_rows = _row_statistics(surf, jrow, m, exclude, noncoherent, pfa, n_cells, self_r2)
    peak = float(surf[jrow, m])
    metric = peak / float(floors[jrow])
    thr = float(thr_rows[jrow])
    # parabolic interpolation (Doppler, lag)
    dj = _parabolic(surf[jrow - 1, m] if jrow > 0 else None, peak,
                    surf[jrow + 1, m] if jrow + 1 < surf.shape[0] else None)
    dm = _parabolic(surf[jrow, (m - 1) % n_fold], peak, surf[jrow, (m + 1) % n_fold])
    fd_coarse = float(js[jrow] * blk.step)
    fd = fd_coarse + dj * blk.step
    code_phase = (-(m + dm) * sig.chip_rate_hz / blk.fs_s) % sig.code_length
    detected = metric > thr
    cn0 = math.nan
    if detected and refine:
        if blk.dec > 1:
            # full rate: the low-passed decimated signal, correlated with a point-sampled replica
            # at a rate commensurate with the chip rate (e.g. 4.092 MHz), biases the code phase
            # by up to half a decimated sample; C/N0 then follows the correlator's sample-power
            # convention at the input rate
            fd, code_phase, cn0 = _refine(blk.xb, blk.fs_hz, prn, fd, code_phase, blk.sigma_arm, sig)
        else:
            fd, code_phase, cn0 = _refine(blk.xs_ref, blk.fs_s, prn, fd, code_phase, blk.sigma_ref, sig)
    code_phase = code_phase % sig.code_length
    return AcqResult(prn=prn, doppler_hz=float(fd), code_phase_chips=float(code_phase), cn0_dbhz=float(cn0),
                     metric=metric, detected=bool(detected), threshold=thr, sample_index=int(start_sample),
                     doppler_coarse_hz=fd_coarse, n_doppler_bins=int(js.size), k_eff=float(k_rows[jrow]),
                     n_excised_bins=blk.n_excised)


def _excise_cw(spec, p_false=1e-4, max_bin_fraction=0.05, halfwidth=1):
    """Zero narrowband (CW) interference bins in the block spectra ``spec`` (K, N) in place.

    A bin is interference when its power averaged over the K blocks exceeds the local median
    level (running median over ~N/40 bins, which follows the front-end filter's shape) by the
    factor for which a noise-only bin (``Gamma(K)`` distributed) exceeds it with probability
    ``p_false``; it is zeroed with ``halfwidth`` neighbours.  Nothing is excised when more than
    ``max_bin_fraction`` of the bins are flagged: that is not narrowband interference (zeroing
    it would remove the band).  Returns the number of bins zeroed.
    """
    k, n = spec.shape
    pw = (spec.real ** 2 + spec.imag ** 2).mean(axis=0)
    win = max(9, (n // 40) | 1)
    local = running_median_wrap(pw, win)
    ratio = gammainccinv(k, p_false) / gammainccinv(k, 0.5)
    hit = pw > ratio * np.maximum(local, np.finfo(np.float32).tiny)
    if not np.any(hit):
        return 0
    for d in range(1, halfwidth + 1):
        hit = hit | np.roll(hit, d) | np.roll(hit, -d)
    if hit.mean() > max_bin_fraction:
        return 0
    spec[:, hit] = 0.0
    return int(hit.sum())


def _self_sidelobes(cspec, n_fold):
    """Squared normalised circular autocorrelation R(l)^2 of the sampled local code (first n_fold lags)."""
    ac = np.fft.ifft((cspec.real.astype(np.float64) ** 2 + cspec.imag.astype(np.float64) ** 2)).real
    return (ac[:n_fold] / ac[0]) ** 2


def _row_statistics(surf, jrow, m, exclude, noncoherent, pfa, n_cells, self_r2):
    """Per-Doppler-row noise floor, effective sums K_eff and threshold.

    Cells within ``exclude`` lags of ``m`` are left out.  In the candidate's own row the
    candidate's code autocorrelation sidelobes (``(peak - floor) * R(l - m)^2``, deterministic,
    known from the code) are subtracted first: they are the signal, not noise.
    """
    n = surf.shape[1]
    lag = (np.arange(n) - m + n // 2) % n - n // 2
    keep = np.abs(lag) > exclude
    cells = surf[:, keep].astype(np.float64)
    row = cells[jrow]
    p_sig = max(float(surf[jrow, m]) - float(row.mean()), 0.0)
    cells[jrow] = row - p_sig * np.roll(self_r2, m)[keep]
    floors = cells.mean(axis=1)
    floors = np.maximum(floors, 1e-30 * max(float(surf.max()), 1e-300))
    disp = cells.var(axis=1) / floors ** 2
    k_rows = np.minimum(float(noncoherent), 1.0 / np.maximum(disp, 1e-12))
    return floors, k_rows, cell_threshold(pfa, n_cells, k_rows)


def _sigma_arm(x, is_complex):
    sigma_arm = block_sigma_arm(x, is_complex)
    if not sigma_arm > 0.0:
        raise ConfigError("acquire: the samples have zero power (all equal)")
    return sigma_arm


def _parabolic(ym, y0, yp):
    """Vertex offset in (-0.5, 0.5) of the parabola through (-1, ym), (0, y0), (1, yp)."""
    if ym is None or yp is None:
        return 0.0
    den = ym - 2.0 * y0 + yp
    if den >= 0.0:
        return 0.0
    return float(np.clip(0.5 * (ym - yp) / den, -0.5, 0.5))


def _search_surface(base, cspec, js, p_num, q_den, k_blocks, n, period, step, carrier_hz):
    """S(j, m) for Doppler bins j (float32 (len(js), n))."""
    surf = np.zeros((js.size, n), dtype=np.float32)
    tot = js * p_num
    shifts = np.floor_divide(tot, q_den)
    resid = tot - shifts * q_den
    rows_per_chunk = max(1, _CHUNK_ELEMS // (k_blocks * n))
    ar = np.arange(n)
    for r in range(q_den):
        rows = np.flatnonzero(resid == r)
        for c0 in range(0, rows.size, rows_per_chunk):
            rr = rows[c0:c0 + rows_per_chunk]
            # rolled code spectra: C*[m - s]
            cs = cspec[(ar[None, :] - shifts[rr][:, None]) % n]
            prod = base[r][None, :, :] * cs[:, None, :]
            y = np.fft.ifft(prod, axis=2, out=prod)
            pw = (y.real * y.real + y.imag * y.imag).astype(np.float32)
            # lag drift per block (samples): non-integer period and code Doppler
            drift = (period - n) - n * (js[rr] * step) / carrier_hz
            for k in range(k_blocks):
                sh = np.rint(k * drift).astype(np.int64)
                if not np.any(sh):
                    surf[rr] += pw[:, k, :]
                    continue
                for s in np.unique(sh):
                    sel = sh == s
                    surf[rr[sel]] += np.roll(pw[sel, k, :], -int(s), axis=1)
    return surf


def _refine(xb, fs_hz, prn, fd, code_phase, sigma_arm, signal=GPS_L1CA):
    """Fine Doppler (phase differences of 1 ms sums) and code phase / C/N0 on a fine code grid."""
    n_sub = int(round(fs_hz * _T_SUB))
    n_blocks = xb.shape[0] // n_sub
    n_tot = n_blocks * n_sub
    t = np.arange(n_tot) / fs_hz
    code = np.asarray(signal.code(prn)).astype(np.float32)
    n_code = signal.code_length

    def wipe(fd_):
        ph = fd_ * t
        return xb[:n_tot] * np.exp(-2j * np.pi * (ph - np.floor(ph))).astype(np.complex64)

    def sums(w, fd_, cp_):
        rep = code[np.floor(cp_ + t * (signal.chip_rate_hz * (1.0 + fd_ / signal.carrier_hz))).astype(np.int64) % n_code]
        return (w * rep).reshape(n_blocks, n_sub).sum(axis=1)

    if n_blocks >= 2:
        for _ in range(2):
            z = sums(wipe(fd), fd, code_phase)
            dphi = np.angle(np.sum(z[1:] * np.conj(z[:-1])))
            fd = fd + dphi / (2.0 * np.pi * n_sub / fs_hz)
    w = wipe(fd)
    offs = np.arange(-_FINE_CODE_SPAN, _FINE_CODE_SPAN + 1e-9, _FINE_CODE_STEP)
    pw = np.empty(offs.size)
    scale = 1.0 / (sigma_arm * math.sqrt(n_sub))
    for i, o in enumerate(offs):
        z = sums(w, fd, code_phase + o) * scale
        pw[i] = np.mean(z.real ** 2 + z.imag ** 2)
    i = int(np.argmax(pw))
    d = _parabolic(pw[i - 1] if i > 0 else None, pw[i], pw[i + 1] if i + 1 < pw.size else None)
    code_phase = (code_phase + offs[i] + d * _FINE_CODE_STEP) % n_code
    snr = (pw[i] - 2.0) / 2.0                       # A^2/2 = C/N0 * T_sub
    t_sub = n_sub / fs_hz
    cn0 = 10.0 * math.log10(snr / t_sub) if snr > 0 else math.nan
    return fd, code_phase, cn0


def predicted_doppler(ephemerides, rx_pos_e, week, tow_s, prns=None, rx_clk_drift_mps=0.0):
    """Assisted mode: predicted Doppler (Hz) per PRN from ephemerides and an approximate position/time.

    Uses :func:`ultratight.signals.geometry.light_time`; returns {prn: doppler_hz}.  Pass it as
    ``doppler_center_hz`` with a ``doppler_range_hz`` covering the position/clock-drift uncertainty.
    """
    prns = sorted(ephemerides) if prns is None else list(prns)
    pos = np.atleast_2d(np.asarray(rx_pos_e, dtype=float))
    out = {}
    for p in prns:
        lt = light_time(ephemerides[p], pos, np.zeros_like(pos), week, np.array([float(tow_s)]),
                        rx_clk_drift_mps=rx_clk_drift_mps)
        out[p] = float(np.asarray(lt["doppler_hz"]).ravel()[0])
    return out


@dataclass
class RateResult:
    """Doppler and Doppler rate of one signal from :func:`doppler_rate_search`."""
    doppler_hz: float          # at ``sample_index``
    rate_hz_s: float           # d(Doppler)/dt
    metric: float              # |sum of squared block sums| / its noise-only expectation
    sample_index: int
    span_s: float


def doppler_rate_search(source, prn, doppler_hz, code_phase_chips, sample_index, span_s=0.4, block_ms=5,
                        freq_span_hz=250.0, rate_max_hz_s=1000.0, signal=GPS_L1CA):
    """Fine Doppler and Doppler rate of a detected signal over ``span_s`` (high-dynamic start-up).

    Under a constant line-of-sight acceleration ``a`` the carrier is a chirp ``f(t) = f0 + r t`` with
    ``r = a / lambda`` (100 m/s^2 along the line of sight: 525 Hz/s at L1); a loop started from an
    acquisition Doppler alone must pull in both the frequency error (tens of Hz after a 5-10 ms
    search) and the rate r, which a weak-signal loop cannot. The search:

    1. the code is wiped at the acquisition code phase (Doppler-aided code rate; the rate moves the
       code by ``r span^2 / (2 f_carrier / f_chip)`` chips, 0.05 chip at 1000 Hz/s over 0.4 s), the
       carrier at the acquisition Doppler, and the product summed over blocks of ``block_ms``: ``z_k``;
    2. the squared sums ``z_k^2`` remove the data bits (a bit edge only weakens one block) and carry
       ``exp(j 2 pi (2 df t_k + r t_k^2))``; for every rate on a grid of step ``1/(4 span^2)``
       the chirp is removed and a zero-padded FFT over the blocks finds ``2 df`` (a coherent
       integration over the whole span: resolution ~``1/(2 span)`` Hz in df);
    3. the squaring leaves ``df`` ambiguous by ``1/(2 T_block)`` (100 Hz at 5 ms): the alias with the
       largest non-coherent block power (the block's sinc attenuation) within ``freq_span_hz`` wins.

    Returns a :class:`RateResult` (Doppler at ``sample_index``); the metric is the peak over the mean
    of the rate/frequency surface (a noise-only surface has its peak at ~ln(cells)).
    Cost: one 1 ms code wipe-off of the span, then per Doppler alias one FFT per rate (~0.2 s of CPU
    per satellite for 0.4 s at 2 MHz)."""
    z1, k_blocks, per, n1, fs = _wiped_millisecond_sums(source, prn, doppler_hz, code_phase_chips, sample_index,
                                                        span_s, block_ms, signal)
    t1 = (np.arange(k_blocks * per) + 0.5) * (n1 / fs)
    tb = per * n1 / fs
    tk = (np.arange(k_blocks) + 0.5) * tb
    span = k_blocks * tb
    r_step = 1.0 / (4.0 * span * span)
    rates = np.arange(-rate_max_hz_s, rate_max_hz_s + 0.5 * r_step, r_step)
    alias = 0.5 / tb
    surf, base, i_r, i_f = _rate_frequency_surface(z1, t1, tk, k_blocks, per, rates, alias, freq_span_hz)
    metric = float(surf[i_r, i_f] / np.mean(surf))
    rate, df0 = _surface_peak(surf, i_r, i_f, rates, r_step, tb, base)
    df = _strongest_alias(z1, t1, k_blocks, per, df0, rate, alias, freq_span_hz)
    return RateResult(doppler_hz=float(doppler_hz) + df, rate_hz_s=rate, metric=metric,
                      sample_index=int(sample_index), span_s=span)


def _wiped_millisecond_sums(source, prn, doppler_hz, code_phase_chips, sample_index, span_s, block_ms, signal):
    """Step 1 of :func:`doppler_rate_search`: the 1 ms sums of the span with the code wiped at the
    acquisition code phase (Doppler-aided code rate) and the carrier at the acquisition Doppler.
    Returns ``(z1, k_blocks, per, n1, fs)``: the sums, the number of blocks, 1 ms sums per block,
    samples per 1 ms sum and the sampling rate."""
    fs = float(source.fs_hz)
    n1 = int(round(1e-3 * fs))                        # 1 ms sub-blocks
    per = max(1, int(block_ms))                        # sub-blocks per block
    total = int(getattr(source, "n_samples", int(round(span_s * fs)) + sample_index))
    k_blocks = min(int(round(span_s * fs)), total - int(sample_index)) // (n1 * per)
    if k_blocks < 8:
        raise ConfigError(f"doppler_rate_search: {(total - int(sample_index)) / fs:.3f} s of samples from sample "
                          f"{sample_index}, need at least 8 blocks of {block_ms} ms")
    n = k_blocks * per * n1
    x, fs, if_hz, is_complex = _read_input(source, None, None, None, int(sample_index), n)
    xb = _to_baseband(x, fs, if_hz, is_complex)
    t = np.arange(n) / fs
    code = np.asarray(signal.code(int(prn))).astype(np.float32)
    fd0 = float(doppler_hz)
    ph = fd0 * t
    rep = code[np.floor(code_phase_chips + t * (signal.chip_rate_hz * (1.0 + fd0 / signal.carrier_hz)))
               .astype(np.int64) % signal.code_length]
    w = xb * (rep * np.exp(-2j * np.pi * (ph - np.floor(ph)))).astype(np.complex64)
    z1 = w.reshape(k_blocks * per, n1).sum(axis=1).astype(np.complex128)
    return z1, k_blocks, per, n1, fs


def _block_sums(z1, t1, k_blocks, per, df, rate):
    """Block sums of the 1 ms sums ``z1`` (at times ``t1``) counter-rotated by a Doppler offset ``df``
    and a rate."""
    rot = np.exp(-2j * np.pi * (df * t1 + 0.5 * rate * t1 * t1))
    return (z1 * rot).reshape(k_blocks, per).sum(axis=1)


def _rate_frequency_surface(z1, t1, tk, k_blocks, per, rates, alias, freq_span_hz):
    """Step 2 of :func:`doppler_rate_search`: the rate / frequency surface (squared block sums,
    chirp removed for every rate, zero-padded FFT over the blocks) of the Doppler alias with the
    highest peak. Returns ``(surf, base, i_r, i_f)``: the surface, the alias's Doppler offset and
    the peak's rate and frequency indices."""
    n_fft = 1 << int(math.ceil(math.log2(16 * k_blocks)))
    chirp = np.exp(-2j * np.pi * np.outer(rates, tk * tk))
    best = None
    # the squared sums of blocks wiped far off the signal's frequency are attenuated (sinc of the
    # block): search with the wipe at the acquisition Doppler and at its aliases within the span
    for m in range(-int(freq_span_hz // alias), int(freq_span_hz // alias) + 1):
        s = _block_sums(z1, t1, k_blocks, per, m * alias, 0.0) ** 2
        s /= np.mean(np.abs(s))
        surf = np.abs(np.fft.fft(s[None, :] * chirp, n=n_fft, axis=1)) ** 2
        i_r, i_f = np.unravel_index(int(np.argmax(surf)), surf.shape)
        if best is None or surf[i_r, i_f] > best[0]:
            best = (float(surf[i_r, i_f]), m * alias, surf, i_r, i_f)
    _, base, surf, i_r, i_f = best
    return surf, base, i_r, i_f


def _surface_peak(surf, i_r, i_f, rates, r_step, tb, base):
    """The rate (Hz/s) and Doppler offset ``df`` (Hz, one of the aliases step ``1/(2 tb)``) of the
    surface peak, interpolated in both directions."""
    n_fft = surf.shape[1]
    dr = _parabolic(surf[i_r - 1, i_f] if i_r > 0 else None, surf[i_r, i_f],
                    surf[i_r + 1, i_f] if i_r + 1 < rates.size else None)
    dfb = _parabolic(surf[i_r, (i_f - 1) % n_fft], surf[i_r, i_f], surf[i_r, (i_f + 1) % n_fft])
    rate = float(rates[i_r] + dr * r_step)
    f2 = ((i_f + dfb) / n_fft) / tb                    # 2 df, in [0, 1/tb)
    if f2 >= 0.5 / tb:
        f2 -= 1.0 / tb
    return rate, base + 0.5 * f2


def _strongest_alias(z1, t1, k_blocks, per, df0, rate, alias, freq_span_hz):
    """Step 3 of :func:`doppler_rate_search`: the alias of ``df0`` (step ``alias`` = 1/(2 tb)) with
    the largest block power once the chirp is removed."""
    cands = [df0 + m * alias for m in range(-int(freq_span_hz // alias) - 1, int(freq_span_hz // alias) + 2)
             if abs(df0 + m * alias) <= freq_span_hz + alias]
    pw = [float(np.sum(np.abs(_block_sums(z1, t1, k_blocks, per, df, rate)) ** 2)) for df in cands]
    return cands[int(np.argmax(pw))]
