"""Receiver front-end model: sampling, spectral inversion, filter, AGC and quantiser.

The generator produces signal + noise in "noise units" (pre-quantisation noise
std ``sigma = 1`` per real component) and hands each block to a
:class:`FrontEnd`, which (optionally) filters it, scales it with an ideal AGC
and quantises it to integer levels that the IF file formats store.

Quantiser levels (the integers written to the file)
---------------------------------------------------
* ``bits = 1``: sign, levels ``{-1, +1}``.
* ``bits = 2``: levels ``{-3, -1, +1, +3}`` (the usual MAX2769/MAX2771 mapping),
  thresholds at ``0`` and ``+-1 sigma`` (close to the optimum 0.996 sigma);
  implemented as ``2*floor(x/2)+1`` clipped to +-3 with the noise scaled to
  ``sigma = 2`` LSB.
* ``bits = 4, 8, 16``: mid-tread rounding to integers clipped to
  ``+-(2**(bits-1) - 1)``, noise scaled so the clip level is 4 sigma
  (``sigma = (2**(bits-1)-1)/4`` LSB: 1.75, 31.75, 8191.75).
* ``bits = 0``: no quantisation (float output, ``sigma = 1``).

Quantisation loss against the configured C/N0 is about 1.96 dB (1 bit),
0.55 dB (2 bits), ~0.1 dB (4 bits) and negligible at 8 and 16 bits.

Gain (``gain_mode``): ``"agc"`` (default) -- the scale follows the *current* noise std
(including noise events that multiply it), like a fast hardware AGC, so the quantiser stays
loaded; the signal-to-noise ratio, not the absolute level, is what a noise event changes, and
a receiver that normalises by the IF power sees a fade.  ``"fixed"`` -- the gain is set once
from the nominal noise std (``sigma = 1``) and never follows noise events: the nominal noise
is scaled to ``noise_lsb(bits) / headroom`` LSB so a noise std up to ``headroom`` x nominal
still fits the 4-sigma clip level; a noise event then raises the sample power (the
receiver sees more noise, not a weaker signal).  Use ``ci16`` with fixed gain (8 bits with
headroom 20 leave only ~1.6 LSB per nominal sigma).

Filter: ``filter_bw_hz > 0`` adds a Butterworth filter (``filter_order``, SOS
form) designed with :mod:`scipy.signal`: a low-pass of cut-off ``bw/2`` for
complex baseband, a band-pass ``if_hz +- bw/2`` for real IF. It runs in
streaming fashion (state carried across blocks); the output is rescaled by the
filter's white-noise power gain so the post-filter noise std is still sigma.

Spectral inversion: ``inversion = True`` means the file's spectrum is mirrored
(high-side LO). For complex sampling the file then holds ``I - jQ`` of the
true baseband signal (readers undo it with ``iq_conj``); for real sampling the
carrier phase enters as ``cos(2 pi f_IF t - phi)``. The IF readers undo both
(see :mod:`ultratight.signals.recording.iffile`).
"""

from dataclasses import dataclass, field

import numpy as np

from ultratight.errors import ConfigError

SUPPORTED_BITS = (0, 1, 2, 4, 8, 16)
MAX_IMPULSE = 1 << 24      # samples of the impulse response that measures the filter's noise gain


def _signal():
    """:mod:`scipy.signal`, imported on first use: only a front end with a filter needs it, and its
    import (about a second, scipy.stats with it) would otherwise fall on every command that builds a
    scenario."""
    import scipy.signal
    return scipy.signal


def _number(fe, key, default):
    """``fe[key]`` (or ``default``) as a float; ConfigError naming the field when it is not a number."""
    v = fe.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"frontend.{key} must be a number, got {v!r}")
    return float(v)
GAIN_MODES = ("agc", "fixed")


def noise_lsb(bits):
    """Pre-quantisation noise std in LSB that loads a ``bits`` quantiser well (see module doc)."""
    if bits == 0:
        return 1.0
    if bits == 1:
        return 1.0
    if bits == 2:
        return 2.0
    return (2 ** (bits - 1) - 1) / 4.0


def max_level(bits):
    """Largest absolute integer level of the quantiser (None for float)."""
    if bits == 0:
        return None
    if bits == 1:
        return 1
    if bits == 2:
        return 3
    return 2 ** (bits - 1) - 1


def quantize(x, bits, out=None):
    """Quantise real array ``x`` (already in LSB units) to the integer levels of ``bits``.

    Returns float32 values on the level grid (exactly representable integers).
    """
    x = np.asarray(x, dtype=np.float32)
    if out is None:
        out = np.empty_like(x)
    if bits == 0:
        out[...] = x
        return out
    if bits == 1:
        np.copysign(np.float32(1.0), x, out=out)
        return out
    if bits == 2:
        np.multiply(x, np.float32(0.5), out=out)
        np.floor(out, out=out)
        out *= np.float32(2.0)
        out += np.float32(1.0)
        np.clip(out, -3.0, 3.0, out=out)
        return out
    m = np.float32(2 ** (bits - 1) - 1)
    np.rint(x, out=out)
    np.clip(out, -m, m, out=out)
    return out


@dataclass
class FrontEnd:
    """Front-end parameters plus the streaming filter state.

    ``bits`` 0 means float output. ``if_hz = 0`` with ``is_complex`` means
    complex baseband. Use :meth:`process` on consecutive blocks.
    """

    fs_hz: float
    if_hz: float = 0.0
    is_complex: bool = True
    inversion: bool = False
    bits: int = 8
    filter_bw_hz: float = 0.0
    filter_order: int = 4
    gain_mode: str = "agc"      # "agc" (follows the current noise std) | "fixed" (nominal noise)
    headroom: float = 1.0       # fixed gain: noise std (x nominal) that still fits the clip level
    _sos: object = field(default=None, init=False, repr=False)
    _zi: object = field(default=None, init=False, repr=False)
    _gain: float = field(default=1.0, init=False, repr=False)

    def __post_init__(self):
        self.fs_hz = float(self.fs_hz)
        self.if_hz = float(self.if_hz)
        self.is_complex = bool(self.is_complex)
        self.inversion = bool(self.inversion)
        if not np.isfinite(self.fs_hz) or self.fs_hz <= 0:
            raise ConfigError(f"frontend.fs_hz must be > 0, got {self.fs_hz}")
        nyq = self.fs_hz / 2.0
        if self.is_complex:
            if abs(self.if_hz) >= nyq:
                raise ConfigError(
                    f"frontend.if_hz = {self.if_hz} Hz is beyond the complex Nyquist range +-{nyq} Hz")
        else:
            if not (0.0 < self.if_hz < nyq):
                raise ConfigError(
                    f"frontend.if_hz = {self.if_hz} Hz must lie in (0, fs/2 = {nyq}) Hz for real sampling")
        if self.bits not in SUPPORTED_BITS:
            raise ConfigError(f"frontend.bits must be one of {SUPPORTED_BITS}, got {self.bits!r}")
        if self.gain_mode not in GAIN_MODES:
            raise ConfigError(f"frontend.gain must be one of {GAIN_MODES}, got {self.gain_mode!r}")
        self.headroom = float(self.headroom)
        if not np.isfinite(self.headroom) or self.headroom < 1.0:
            raise ConfigError(f"frontend.headroom must be a number >= 1, got {self.headroom}")
        if self.filter_order < 1 or self.filter_order > 12:
            raise ConfigError(f"frontend.filter_order must be in 1..12, got {self.filter_order}")
        if self.filter_bw_hz < 0 or not np.isfinite(self.filter_bw_hz):
            raise ConfigError(f"frontend.filter_bw_hz must be >= 0, got {self.filter_bw_hz}")
        if self.filter_bw_hz > 0:
            self._design()

    @classmethod
    def from_config(cls, fe):
        """Build from a scenario ``[frontend]`` table."""
        sampling = fe.get("sampling", "complex")
        if sampling not in ("complex", "real"):
            raise ConfigError(f"frontend.sampling must be 'complex' or 'real', got {sampling!r}")
        return cls(fs_hz=_number(fe, "fs_hz", fe["fs_hz"]), if_hz=_number(fe, "if_hz", 0.0),
                   is_complex=(sampling == "complex"), inversion=fe.get("inversion", False),
                   bits=int(_number(fe, "bits", 8)), filter_bw_hz=_number(fe, "filter_bw_hz", 0.0),
                   filter_order=int(_number(fe, "filter_order", 4)),
                   gain_mode=fe.get("gain", "agc"), headroom=_number(fe, "headroom", 1.0))

    # -- filter -------------------------------------------------------------------------
    def _design(self):

        nyq = self.fs_hz / 2.0
        bw = self.filter_bw_hz
        if self.is_complex:
            fc = bw / 2.0
            if not (0 < fc < nyq):
                raise ConfigError(f"frontend.filter_bw_hz = {bw} must be in (0, fs) for complex sampling")
            if self.if_hz != 0.0:
                raise ConfigError("frontend.filter_bw_hz with complex sampling needs if_hz = 0")
            sos = _signal().butter(self.filter_order, fc, btype="low", fs=self.fs_hz, output="sos")
        else:
            lo, hi = self.if_hz - bw / 2.0, self.if_hz + bw / 2.0
            if lo <= 0 or hi >= nyq:
                raise ConfigError(
                    f"frontend band-pass {lo:.0f}..{hi:.0f} Hz must lie inside (0, fs/2 = {nyq:.0f}) Hz")
            sos = _signal().butter(self.filter_order, [lo, hi], btype="band", fs=self.fs_hz, output="sos")
        self._sos = sos
        # white-noise power gain = sum h^2 (impulse response long enough to converge)
        n = max(4096, 50 * self.fs_hz / bw)
        if n > MAX_IMPULSE:
            raise ConfigError(f"frontend.filter_bw_hz = {bw} Hz is too narrow for fs = {self.fs_hz} Hz (at least "
                              f"{50 * self.fs_hz / MAX_IMPULSE:.3g} Hz)")
        n = int(n)
        imp = np.zeros(n)
        imp[0] = 1.0
        h = _signal().sosfilt(sos, imp)
        self._gain = float(np.sqrt(np.sum(h * h)))
        self._zi = None

    @property
    def noise_gain(self):
        """RMS gain of the filter for white noise (1 without a filter)."""
        return self._gain

    def filter(self, x):
        """Filter one block (float32 / complex64), carrying state; output noise std unchanged."""
        if self._sos is None:
            return x

        if self._zi is None:
            self._zi = np.zeros((self._sos.shape[0], 2), dtype=np.complex128 if self.is_complex else np.float64)
        y, self._zi = _signal().sosfilt(self._sos, x, zi=self._zi)
        y /= self._gain
        return y.astype(x.dtype, copy=False)

    def reset(self):
        self._zi = None

    # -- quantiser ----------------------------------------------------------------------
    @property
    def lsb_per_sigma(self):
        """LSB per unit of *nominal* noise std (fixed gain: reduced by the headroom)."""
        if self.gain_mode == "fixed":
            return noise_lsb(self.bits) / self.headroom
        return noise_lsb(self.bits)

    def quantize_block(self, x, sigma_now=1.0):
        """Gain + quantise a filtered block whose current noise std is ``sigma_now``.

        ``x`` float32 (real) or complex64; ``sigma_now`` scalar or per-sample array (the AGC
        follows it; a fixed gain ignores it). Returns float32 array (real) or complex64 on the
        integer level grid.
        """
        if self.gain_mode == "fixed":
            sigma_now = 1.0
        scale = (self.lsb_per_sigma / np.asarray(sigma_now, dtype=np.float32)).astype(np.float32)
        if np.iscomplexobj(x):
            v = x.view(np.float32).reshape(-1, 2)
            v *= scale[..., None] if np.ndim(scale) else scale
            quantize(v, self.bits, out=v)
            return x
        x *= scale
        quantize(x, self.bits, out=x)
        return x

    def to_dict(self):
        return {"fs_hz": self.fs_hz, "if_hz": self.if_hz, "is_complex": self.is_complex,
                "inversion": self.inversion, "bits": self.bits, "filter_bw_hz": self.filter_bw_hz,
                "filter_order": self.filter_order, "noise_lsb": self.lsb_per_sigma,
                "gain": self.gain_mode, "headroom": self.headroom}
