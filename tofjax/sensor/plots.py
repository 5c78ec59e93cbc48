"""Residual plots of a sensor fit (``tofjax sensor fit --plots DIR``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..outputs import save_figure


def plot_sensor_fit(model, details, out) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    h, mu, d = details["histograms"], details["model"], details["distances_m"]
    c = model.report["centre_zone"]
    F = len(d)
    picks = sorted({0, F // 3, 2 * F // 3, F - 1})
    fig, axes = plt.subplots(2, len(picks), figsize=(3.2 * len(picks), 5), sharex=True, squeeze=False)
    b = np.arange(h.shape[-1]) + 0.5
    for j, f in enumerate(picks):
        ax, axr = axes[0, j], axes[1, j]
        ax.semilogy(b, np.maximum(h[f, c], 0.5), ".", ms=3, label="data")
        ax.semilogy(b, np.maximum(mu[f, c], 0.5), "-", lw=1, label="model")
        ax.set_title(f"{d[f] * 1e3:.0f} mm, centre zone", fontsize=9)
        r = (h[f, c] - mu[f, c]) / np.sqrt(np.maximum(mu[f, c], 1.0))
        axr.plot(b, r, ".-", ms=2, lw=0.5)
        axr.axhline(0, color="k", lw=0.5)
        axr.set_xlabel("bin")
        if j == 0:
            ax.set_ylabel("counts")
            axr.set_ylabel("(data - model) / sqrt(model)")
            ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out / "residuals.png")
    save_figure(fig, paths[-1], dpi=110)

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ax[0].semilogy(d * 1e3, model.report["frame_reduced_chi2"], "o", ms=3)
    ax[0].axhline(2, color="r", lw=0.8, ls="--", label="target 2")
    ax[0].set_xlabel("target distance (mm)")
    ax[0].set_ylabel("reduced chi-square (all zones, 128 bins)")
    ax[0].legend(fontsize=8)
    s = details["shift"][:, c]
    line = model.zero_range_bins[c] + model.bins_per_m[c] * d
    ax[1].plot(d * 1e3, (s - line) / model.bins_per_m[c] * 1e3, "o", ms=3, label="pulse fit")
    pk = details["peaks"][:, c]
    ax[1].plot(d * 1e3, (pk - pk.mean() - (line - line.mean())) / model.bins_per_m[c] * 1e3, "x", ms=3, label="raw peak (own offset)")
    ax[1].set_xlabel("target distance (mm)")
    ax[1].set_ylabel("position - line (mm)")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    paths.append(out / "chi2_and_line.png")
    save_figure(fig, paths[-1], dpi=110)

    fig, ax = plt.subplots(figsize=(6, 3.5))
    knots = model.pulse_start_bins + model.pulse_step_bins * np.arange(model.pulse.shape[1])
    for z in range(model.n_zones):
        ax.semilogy(knots, np.maximum(model.pulse[z], 1e-5), lw=1 if z != c else 2, label=f"zone {z}" if z in (0, c) else None)
    if model.reference_pulse is not None:
        rk = model.pulse_start_bins + (model.reference_pulse_step_bins or model.pulse_step_bins) * np.arange(len(model.reference_pulse))
        ax.semilogy(rk, np.maximum(model.reference_pulse, 1e-5), "k--", lw=1, label="reference")
    ax.set_xlabel("bins after the pulse position")
    ax.set_ylabel("pulse (per bin)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out / "pulses.png")
    save_figure(fig, paths[-1], dpi=110)
    return paths
