"""What the model does not describe: residual maps per zone and bin, worst zones first."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..outputs import save_figure

__all__ = ["discrepancy_report", "plot_residual_map"]


def discrepancy_report(residuals: np.ndarray, bin_width_s: float, worst: int = 5) -> dict[str, Any]:
    """Summary of Poisson-weighted residuals ``(model - data) / sigma`` (S, Z, B).

    Per zone: reduced chi-square, the bin with the largest residual, and the sign of the
    mismatch there; per bin: the mean residual over zones (a shape the model lacks shows as a
    run of bins with the same sign in every zone)."""
    r = np.asarray(residuals, np.float64)
    S, Z, B = r.shape
    chi = (r**2).mean(-1)
    order = np.argsort(chi.ravel())[::-1][:worst]
    zones = []
    for flat in order:
        s, z = divmod(int(flat), Z)
        b = int(np.argmax(np.abs(r[s, z])))
        zones.append(
            {
                "sensor": s,
                "zone": z,
                "reduced_chi2": float(chi[s, z]),
                "worst_bin": b,
                "worst_time_ns": float((b + 0.5) * bin_width_s * 1e9),
                "residual_at_worst_bin": float(r[s, z, b]),
                "model_is": "high" if r[s, z, b] > 0 else "low",
            }
        )
    by_bin = r.mean(axis=(0, 1))
    return {
        "worst_zones": zones,
        "zone_reduced_chi2": chi.round(4).tolist(),
        "mean_residual_by_bin": by_bin.round(4).tolist(),
        "note": "residual = (model - data) / sigma; reduced chi-square ~ 1 where the model describes the data",
    }


def plot_residual_map(residuals: np.ndarray, path: str | Path, bin_width_s: float) -> Path:
    """A heat map of the residuals, one row per (sensor, zone), one column per bin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = np.asarray(residuals, np.float64)
    S, Z, B = r.shape
    lim = max(3.0, float(np.percentile(np.abs(r), 99)))
    fig, ax = plt.subplots(figsize=(9, 0.25 * S * Z + 2), constrained_layout=True)
    im = ax.imshow(
        r.reshape(S * Z, B),
        aspect="auto",
        cmap="RdBu_r",
        vmin=-lim,
        vmax=lim,
        interpolation="nearest",
        extent=(0, B * bin_width_s * 1e9, S * Z - 0.5, -0.5),
    )
    ax.set_yticks(range(S * Z))
    ax.set_yticklabels([f"s{s} z{z}" for s in range(S) for z in range(Z)], fontsize=6)
    ax.set_xlabel("time (ns)")
    ax.set_title("calibration residuals (model - data) / sigma per sensor, zone and bin")
    fig.colorbar(im, ax=ax, label="residual (sigma)")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
    return path
