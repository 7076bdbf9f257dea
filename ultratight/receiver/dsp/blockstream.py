"""IF block stream: the receiver's one reader of IF samples, with the per-arm noise estimate.

Every loop over IF data goes through :class:`BlockStream`:

* the ultra-tight engine (``receiver.deep.engine``) and the scenario's scalar reference
  (``receiver.cli.scenario_runner.run_scalar``) read *aligned* blocks ``[k L, (k+1) L)`` into a sliding
  buffer (:meth:`BlockStream.ensure`, :meth:`BlockStream.view`); each block gets its per-arm noise
  std once, when it is read (:meth:`BlockStream.sigma_at`), passed through an optional
  :class:`NoiseFloor`;
* ``receiver.scalar.receiver`` reads where its tracking channels need samples (they stop, re-acquire and
  restart anywhere): :meth:`BlockStream.read_at` returns the samples and the noise estimate of
  their first ``head`` samples.

The noise estimate (:func:`block_sigma_arm`) is the one used everywhere in the receiver
(correlator normalisation, acquisition C/N0, tracking). GPS signals lie far below the noise, so a
block's power is the noise power: complex input ``sigma = sqrt(mean(|x - mean x|^2) / 2)``, real
input ``sigma = std(x)``, then :func:`ultratight.signals.corr_model.noise_sigma_arm` (``/sqrt(2)``
for real input: the carrier wipe-off splits the noise over I and Q). The mean is removed first
(front-end DC offsets would otherwise count as noise).
"""

import math

import numpy as np
from numba import njit, prange

from ultratight.errors import ConfigError
from ultratight.io_guard import check_interrupted
from ultratight.signals.corr_model import noise_sigma_arm


@njit(cache=True, fastmath={"reassoc"})
def _complex_block_sigma(v):
    """``sqrt(mean(|x - mean x|^2) / 2)`` of a complex block given as its float32 (re, im) view,
    without temporaries (two-pass mean removal, float64 sums). The sums may be reassociated, so the
    compiler adds in vector lanes (3.3 times faster than one running sum: the estimate took 6 % of the
    ultra-tight engine's time); the order is fixed by the block's length, so a block always gives
    the same value, and samples on integer levels (every quantised recording) give exact sums of
    the mean."""
    n = v.shape[0] // 2
    mr = 0.0
    mi = 0.0
    for k in range(n):
        mr += v[2 * k]
        mi += v[2 * k + 1]
    mr /= n
    mi /= n
    s = 0.0
    for k in range(n):
        a = v[2 * k] - mr
        b = v[2 * k + 1] - mi
        s += a * a + b * b
    return math.sqrt(s / n / 2.0)


@njit(cache=True, parallel=True, nogil=True)
def _complex_block_sigmas(v, block_len, out):
    """:func:`_complex_block_sigma` of each of the ``out.shape[0]`` consecutive blocks of
    ``block_len`` complex samples in ``v`` (float32 (re, im) view), the blocks spread over numba's
    threads; each block's sums run in the same order as the one-block kernel (identical values)."""
    for b in prange(out.shape[0]):
        out[b] = _complex_block_sigma(v[2 * b * block_len:2 * (b + 1) * block_len])


def input_sigma(x, is_complex, fast=False):
    """Noise std of the input samples (complex: per arm of the complex samples; real: of the samples),
    mean removed, float64 sums; 0.0 for a block without power. ``fast`` uses the one-pass kernel
    for contiguous complex64 blocks (same value to rounding)."""
    x = np.asarray(x)
    if x.size == 0:
        return 0.0
    if is_complex:
        if fast and x.dtype == np.complex64 and x.flags.c_contiguous:
            return float(_complex_block_sigma(x.view(np.float32)))
        xc = x.astype(np.complex128, copy=False)
        return math.sqrt(float(np.mean(np.abs(xc - xc.mean()) ** 2)) / 2.0)
    return float(np.std(x.astype(np.float64, copy=False)))


def block_sigma_arm(x, is_complex, fast=False):
    """Per-arm noise std after carrier wipe-off of a block of IF samples (module docstring);
    0.0 when the block is empty or has no power (the caller decides what that means)."""
    s = input_sigma(x, is_complex, fast)
    return noise_sigma_arm(s, is_complex) if s > 0.0 else 0.0


class NoiseFloor:
    """Noise-floor estimator that normalises the correlator outputs (noise std per arm).

    Fed with the estimate of every IF block (``block_s`` long) in order, :meth:`update`
    returns the value to use for that block: ``tau_s = 0`` the block's own estimate (follows
    every noise change: with an AGC front end a noise burst then looks like a fade with a
    correct noise model); ``0 < tau_s < inf`` the square root of an exponential average of the
    block variances, ``v += min(1, block_s / tau_s) (s^2 - v)`` started on the first block (a
    slow tracker); ``tau_s = inf`` the first block's estimate held (start-up calibration: a
    noise burst on a fixed-gain front end reaches the prefilters as unknown extra noise).
    """

    def __init__(self, tau_s, block_s):
        tau = float(tau_s)
        if not tau >= 0.0:
            raise ConfigError(f"EngineOptions.noise_tau_s must be >= 0 s (0: per block, inf: start-up "
                              f"calibration), got {tau_s!r}")
        self.alpha = 1.0 if tau == 0.0 else min(1.0, float(block_s) / tau)
        self.var = None

    def update(self, sigma_block):
        s2 = float(sigma_block) ** 2
        if self.var is None or self.alpha >= 1.0:
            self.var = s2
        else:
            self.var += self.alpha * (s2 - self.var)
        return math.sqrt(self.var)


RELEASE_BLOCKS = 64      # blocks passed between releases of the mapping's pages behind the kept samples


class BlockStream:
    """IF samples of ``src`` (an :class:`ultratight.signals.recording.iffile.IfSource`-like object with
    ``read``, ``is_complex``, ``n_samples``) in blocks of ``block_len`` samples.

    ``sigma_stop``: samples at or after it do not enter a block's noise estimate (default: the end
    of the file). ``floor``: a :class:`NoiseFloor` the block estimates pass through (default: none,
    each block's own estimate). ``on_zero``: the value used for a block without power; None
    raises ConfigError.
    """

    def __init__(self, src, block_len, sigma_stop=None, floor=None, on_zero=None):
        self.src = src
        self.block_len = int(block_len)
        if self.block_len <= 0:
            raise ValueError("block_len must be > 0")
        self.is_complex = bool(src.is_complex)
        self.sigma_stop = None if sigma_stop is None else int(sigma_stop)
        self.floor = floor
        self.on_zero = on_zero
        self.buf = np.zeros(0, dtype=np.complex64 if self.is_complex else np.float32)
        self.buf_start = 0
        self._sigma = np.zeros(64)  # per aligned block, in order of reading (first _n_sigma valid)
        self._n_sigma = 0
        self._released = 0          # the file mapping's pages before this sample are out of the resident set

    @property
    def buf_end(self):
        return self.buf_start + self.buf.shape[0]

    def _block_sigma(self, x, start, head=None):
        n = x.shape[0] if head is None else min(head, x.shape[0])
        if self.sigma_stop is not None:
            n = min(n, max(0, self.sigma_stop - start))
        sg = block_sigma_arm(x[:n], self.is_complex, fast=True) if n > 0 else 0.0
        if not sg > 0.0:
            if self.on_zero is None:
                raise ConfigError(f"{getattr(self.src, 'path', 'IF')}: the IF block at sample {start} has zero "
                                  f"noise power (all samples equal)")
            sg = float(self.on_zero)
        return sg

    def ensure(self, hi, keep_from):
        """Read aligned blocks until the buffer reaches sample ``hi`` (or the file ends), dropping the
        samples before ``keep_from``. True when the buffer reaches ``hi``."""
        buf_end = self.buf_end
        if hi <= buf_end:
            return True
        check_interrupted()
        lo = min(max(self.buf_start, int(keep_from)), buf_end)
        bl = self.block_len
        n_blocks = -(-(int(hi) - buf_end) // bl)
        # one read from the first kept sample over the whole new span (the kept samples are decoded
        # again rather than copied; new blocks stay aligned: buf_end is a block boundary until the end)
        y = self.src.read(lo, buf_end - lo + n_blocks * bl)
        x = y[buf_end - lo:]
        n_full = x.shape[0] // bl
        sig = self._full_block_sigmas(x, buf_end, n_full)
        for b in range(-(-x.shape[0] // bl)):
            start = buf_end + b * bl
            if start // bl == self._n_sigma:
                sg = sig[b] if b < n_full and sig is not None else self._block_sigma(x[b * bl:(b + 1) * bl], start)
                self._put_sigma(self.floor.update(sg) if self.floor is not None else sg)
        buf_end += x.shape[0]
        self.buf = y
        self.buf_start = lo
        if lo - self._released >= RELEASE_BLOCKS * bl:
            # a file read through its mapping would otherwise stay resident up to its size
            self.release(lo)
            self._released = lo
        return hi <= buf_end

    def _full_block_sigmas(self, x, start, n_full):
        """Per-arm noise std of the ``n_full`` whole blocks at the head of ``x`` (read at sample
        ``start``) in one threaded call, or None where :meth:`_block_sigma` must do them one by one
        (real input, fewer than two blocks, or a block reaching ``sigma_stop``)."""
        bl = self.block_len
        if (n_full < 2 or not self.is_complex or x.dtype != np.complex64 or not x.flags.c_contiguous
                or (self.sigma_stop is not None and start + n_full * bl > self.sigma_stop)):
            return None
        out = np.empty(n_full)
        _complex_block_sigmas(x.view(np.float32), bl, out)
        sig = [noise_sigma_arm(float(s), True) if s > 0.0 else 0.0 for s in out]
        for b, sg in enumerate(sig):
            if not sg > 0.0:
                sig[b] = self._block_sigma(x[b * bl:(b + 1) * bl], start + b * bl)   # raises or on_zero
        return sig

    def _put_sigma(self, sg):
        if self._n_sigma == self._sigma.shape[0]:
            self._sigma = np.concatenate([self._sigma, np.zeros_like(self._sigma)])
        self._sigma[self._n_sigma] = sg
        self._n_sigma += 1

    def view(self, lo):
        """``(samples from lo to the buffer end, lo)``; read back from the file when ``lo`` was dropped."""
        lo = int(lo)
        if lo < self.buf_start:
            return self.src.read(lo, self.buf_end - lo), lo
        return self.buf[lo - self.buf_start:], lo

    def sigma_at(self, sample):
        """Noise std per arm of the aligned block holding each ``sample`` (an int or an int array)."""
        return self._sigma[:self._n_sigma][np.asarray(sample) // self.block_len]

    def release(self, upto_sample):
        """Drop the file-mapping pages before ``upto_sample`` from the resident set when the source
        can (``IfSource.release``); the samples stay readable. Returns the bytes released."""
        release = getattr(self.src, "release", None)
        return release(upto_sample) if release is not None else 0

    def read_at(self, start, count, head):
        """``(samples [start, start + count), noise std per arm of their first head samples)``."""
        check_interrupted()
        x = self.src.read(start, count)
        return x, self._block_sigma(x, start, head)
