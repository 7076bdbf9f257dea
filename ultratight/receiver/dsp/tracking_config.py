"""Loop parameters of the scalar tracking bank: :class:`TrackingConfig` (bandwidths, loop orders,
coherent integration, lock and loss thresholds, bit-sync tests) and the profiles by receiver
dynamics (:data:`DYNAMICS_PROFILES`, ``process --dynamics``).

:meth:`TrackingConfig.params` packs them, with the tracked signal's code length, chip rate and
carrier, into the parameter vector the compiled kernel reads (columns ``P_*`` of
:mod:`ultratight.receiver.dsp.tracking_layout`).
"""

from dataclasses import asdict, dataclass

import numpy as np

from ultratight.errors import ConfigError
from ultratight.receiver.dsp.tracking_layout import (
    N_PRM, P_BS_ENERGY, P_BS_MARGIN, P_CARRIER, P_CHIP_RATE, P_CN0_ALPHA, P_CN0_LOST, P_CN0_WIN, P_CODE_LEN,
    P_COH_MS, P_DLL_ORDER, P_LOCK_S, P_LOST_S, P_MAX_BNT, P_PEL, P_PLI_LOCK, P_PLI_TAU, P_PLL_ORDER,
    P_PULL_COH_MS, P_PULL_DLL_BW, P_PULL_FLL_BW, P_PULL_PLL_BW, P_SPACING, P_TRK_DLL_BW, P_TRK_FLL_BW,
    P_TRK_PLL_BW, P_UNLOCK_S, P_WEAK_DBHZ, P_WEAK_LONG_COH_MS, P_WEAK_PLL_BW)
from ultratight.signals.signal import GPS_L1CA


@dataclass
class TrackingConfig:
    """Loop parameters (bandwidths are noise bandwidths Bn in Hz)."""
    pull_pll_bw_hz: float = 18.0
    pull_fll_bw_hz: float = 10.0
    pull_dll_bw_hz: float = 2.0
    track_pll_bw_hz: float = 15.0
    track_fll_bw_hz: float = 0.0
    track_dll_bw_hz: float = 0.5
    pll_order: int = 3
    dll_order: int = 1
    coh_ms: int = 1                 # coherent integration after bit sync (1, 2, 4, 5, 10 or 20)
    spacing_chips: float = 1.0
    cn0_win_ms: int = 100
    cn0_lost_dbhz: float = 22.0
    lost_s: float = 1.0
    pli_lock: float = 0.5
    lock_s: float = 0.1
    unlock_s: float = 0.5
    bs_margin: int = 25
    pli_tau_s: float = 0.25
    max_bnt: float = 0.15
    cn0_alpha: float = 0.3
    weak_dbhz: float = 32.0         # C/N0 below which a channel counts as weak: ...
    weak_coh_ms: int = 5            # ... coherent sums of this length before bit sync,
    weak_long_coh_ms: int = 20      # ... bit-synchronised sums of this length after bit sync,
    weak_pll_bw_hz: float = 5.0     # ... and at most this PLL bandwidth
    fast_el: bool = True            # 1-chip spacing: prompt + (E-L) kernel and dot-product DLL
    bs_energy: bool = False         # also the bit-energy bit sync (max sum of |bit sums|, 6-sigma test)

    @classmethod
    def for_dynamics(cls, dynamics="normal", **overrides):
        """The loop parameters of a dynamics profile (:data:`DYNAMICS_PROFILES`) with ``overrides``."""
        if dynamics not in DYNAMICS_PROFILES:
            raise ConfigError(f"--dynamics must be one of {', '.join(DYNAMICS_PROFILES)}, got {dynamics!r}")
        return cls(**{**DYNAMICS_PROFILES[dynamics], **overrides})

    def validate(self):
        if self.coh_ms not in (1, 2, 4, 5, 10, 20) or self.weak_long_coh_ms not in (1, 2, 4, 5, 10, 20):
            raise ConfigError(f"tracking coh_ms must be one of 1, 2, 4, 5, 10, 20 (divides a 20 ms bit), "
                              f"got {self.coh_ms}")
        if self.pll_order not in (2, 3) or self.dll_order not in (1, 2):
            raise ConfigError(f"tracking pll_order must be 2 or 3 and dll_order 1 or 2, "
                              f"got {self.pll_order}, {self.dll_order}")
        for k, v in asdict(self).items():
            if k.endswith("_bw_hz") and not (0.0 <= v <= 100.0):
                raise ConfigError(f"tracking {k} must be in [0, 100] Hz, got {v}")
        if not 0.0 < self.spacing_chips < 2.0:
            raise ConfigError(f"tracking spacing_chips must be in (0, 2), got {self.spacing_chips}")

    def params(self, signal=GPS_L1CA):
        """The kernel's parameter vector: these loop parameters and the ``signal``'s code length,
        chip rate and carrier (a :class:`ultratight.signals.signal.SignalDescription`)."""
        p = np.zeros(N_PRM)
        p[P_PULL_PLL_BW] = self.pull_pll_bw_hz
        p[P_PULL_FLL_BW] = self.pull_fll_bw_hz
        p[P_PULL_DLL_BW] = self.pull_dll_bw_hz
        p[P_TRK_PLL_BW] = self.track_pll_bw_hz
        p[P_TRK_FLL_BW] = self.track_fll_bw_hz
        p[P_TRK_DLL_BW] = self.track_dll_bw_hz
        p[P_PLL_ORDER] = self.pll_order
        p[P_DLL_ORDER] = self.dll_order
        p[P_COH_MS] = self.coh_ms
        p[P_SPACING] = self.spacing_chips
        p[P_CN0_WIN] = self.cn0_win_ms
        p[P_CN0_LOST] = self.cn0_lost_dbhz
        p[P_LOST_S] = self.lost_s
        p[P_PLI_LOCK] = self.pli_lock
        p[P_LOCK_S] = self.lock_s
        p[P_UNLOCK_S] = self.unlock_s
        p[P_BS_MARGIN] = self.bs_margin
        p[P_PLI_TAU] = self.pli_tau_s
        p[P_MAX_BNT] = self.max_bnt
        p[P_CN0_ALPHA] = self.cn0_alpha
        p[P_WEAK_DBHZ] = self.weak_dbhz
        p[P_PULL_COH_MS] = self.weak_coh_ms
        p[P_WEAK_LONG_COH_MS] = self.weak_long_coh_ms
        p[P_WEAK_PLL_BW] = self.weak_pll_bw_hz
        p[P_PEL] = 1.0 if (self.fast_el and self.spacing_chips == 1.0) else 0.0
        p[P_BS_ENERGY] = 1.0 if self.bs_energy else 0.0
        p[P_CODE_LEN] = signal.code_length
        p[P_CHIP_RATE] = signal.chip_rate_hz
        p[P_CARRIER] = signal.carrier_hz
        return p


# Loop profiles by receiver dynamics (``process --dynamics``). ``high``: a start under a constant
# line-of-sight acceleration (paper-highdyn: 10 g, up to ~525 Hz/s Doppler rate) at 30 dB-Hz. The
# channels start from a Doppler-rate search (acquisition.doppler_rate_search: Doppler
# within ~1 Hz, rate within ~10 Hz/s), so the third-order PLL's rate integrator holds the rate from
# the first epoch and its zero steady-state error under constant acceleration does the rest
# (Kaplan & Hegarty ch. 5). What the profile changes against ``normal``:
# * FLL assist in pull-in 2 Hz instead of 10 Hz: the frequency is already within ~1 Hz; a 10 Hz
#   cross-product FLL on 30 dB-Hz sums adds Hz-level noise that walks the PLL out of lock;
# * a 1 Hz FLL assist kept in track mode: it pulls a slipping PLL back before the C/N0 test drops
#   the channel;
# * bit sync also by bit energy (tracking_block._bit_sync_energy): at 30 dB-Hz the sign-change histogram needs
#   5-7 s of phase lock for its 6-sigma test, the energy test ~1-2 s (the 1 ms amplitudes, not only
#   their signs), so the first subframe of the file is decoded;
# * weak signals (< weak_dbhz) use 10 ms coherent sums before bit sync (a bit edge spoils at most one
#   of two) and a PLL bandwidth cap of 12 Hz instead of 5 Hz: 5 Hz (w0 = 6.4 rad/s) leaves a rate
#   error of 10 Hz/s as a 0.25-cycle transient and no margin for the rate changes of the geometry,
#   12 Hz at 10 ms keeps B_n T = 0.12 (stable) and the thermal jitter at 30 dB-Hz near 7 deg.
DYNAMICS_PROFILES = {
    "normal": {},
    "high": {"pull_fll_bw_hz": 2.0, "track_fll_bw_hz": 1.0, "weak_coh_ms": 10, "weak_pll_bw_hz": 12.0,
             "bs_energy": True},
}
