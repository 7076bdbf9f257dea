"""The figure of ``ultratight integrate --plot``: error against the reference, outages shaded."""

import numpy as np

from ultratight.io_guard import savefig_atomic
from ultratight.signals.observations import week_tow


def plot_errors(path, series, windows, title):
    """Horizontal and vertical error (and the solution's 3σ) against the reference epochs, with the
    outage windows shaded; written atomically to ``path``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = series["t"]
    t0 = t[0]
    x = t - t0
    err, sig = series["err_enu"], series["sigma_enu"]
    h = np.hypot(err[:, 0], err[:, 1])
    sh = np.hypot(sig[:, 0], sig[:, 1])
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    axes[0].plot(x, h, ".", ms=2.5, label="horizontal error")
    axes[0].plot(x, 3.0 * sh, "-", lw=0.8, color="0.4", label="3σ (horizontal)")
    axes[0].set_ylabel("horizontal, m")
    axes[1].plot(x, err[:, 2], ".", ms=2.5, label="vertical error")
    axes[1].plot(x, 3.0 * sig[:, 2], "-", lw=0.8, color="0.4", label="±3σ (up)")
    axes[1].plot(x, -3.0 * sig[:, 2], "-", lw=0.8, color="0.4")
    axes[1].set_ylabel("up, m")
    _, tow0 = week_tow(t0)
    axes[1].set_xlabel(f"time since GPS second of week {tow0:.2f}, s")
    for ax in axes:
        for a, b in windows:
            ax.axvspan(a - t0, b - t0, color="tab:orange", alpha=0.2, lw=0)
        ax.grid(True, lw=0.3)
        ax.legend(loc="upper left", fontsize=8)
    axes[0].set_title(title + ("  (shaded: GNSS outages)" if windows else ""), fontsize=9)
    fig.tight_layout()
    savefig_atomic(fig, path)
    plt.close(fig)
