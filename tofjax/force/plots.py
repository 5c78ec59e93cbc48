"""Figures like seed 001 Fig. 15-18: actual and predicted force over time, with the error below."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..outputs import save_figure

__all__ = ["plot_by_velocity", "plot_mlp_vs_forest"]


def _timeline(ds, vel=None):
    """Test frames (optionally of one velocity) laid end to end on one time axis."""
    idx = np.arange(len(ds)) if vel is None else np.flatnonzero(ds.velocity == vel)
    t = np.zeros(idx.size)
    offset, last_cap, last_t = 0.0, None, 0.0
    for j, i in enumerate(idx):
        c = ds.capture[i]
        if c != last_cap:
            offset = last_t + (1.0 if last_cap is not None else 0.0) - ds.time[i]
            last_cap = c
        t[j] = ds.time[i] + offset
        last_t = t[j]
    return idx, t


def plot_mlp_vs_forest(ds, preds: dict, path) -> Path:
    """Fig. 15: the MLP alone (left) and MLP + forest (right) on the whole test set."""
    from ..plot import plt

    keys = [k for k in ("mlp", "mlp_rf") if k in preds] or list(preds)
    idx, t = _timeline(ds)
    fig, axes = plt.subplots(2, len(keys), figsize=(6 * len(keys), 5), sharex=True, squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1]})
    for j, k in enumerate(keys):
        err = preds[k][idx] - ds.force[idx]
        axes[0, j].plot(t, ds.force[idx], color="tab:blue", lw=1, label="actual")
        axes[0, j].plot(t, preds[k][idx], color="tab:orange", lw=0.8, label=k.replace("_", "+").upper())
        axes[0, j].set_title(f"{k.replace('_', ' + ').upper()}: MAE {np.mean(np.abs(err)):.2f} N")
        axes[0, j].set_ylabel("force (N)")
        axes[0, j].legend(loc="upper right", fontsize=8)
        axes[1, j].plot(t, err, color="m", lw=0.6)
        axes[1, j].set_ylabel("error (N)")
        axes[1, j].set_xlabel("time (s, test captures end to end)")
    fig.suptitle("Test set (unseen forces, simulated)")
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi=110)
    return path


def plot_by_velocity(ds, preds: dict, path, title: str = "") -> Path:
    """Fig. 16-18: actual and predicted force per indentation velocity, error below."""
    from ..plot import plt

    key = "mlp_rf" if "mlp_rf" in preds else next(iter(preds))
    vels = sorted(set(ds.velocity[np.isfinite(ds.velocity)].tolist())) or [None]
    fig, axes = plt.subplots(2, len(vels), figsize=(4.5 * len(vels), 5), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1]})
    for j, v in enumerate(vels):
        idx, t = _timeline(ds, v)
        err = preds[key][idx] - ds.force[idx]
        axes[0, j].plot(t, ds.force[idx], color="tab:blue", lw=1, label="actual")
        axes[0, j].plot(t, preds[key][idx], color="tab:red", lw=0.8, label="predicted")
        axes[0, j].set_title(f"v = {v:g} mm/s: MAE {np.mean(np.abs(err)):.2f} N" if v is not None else "")
        axes[1, j].plot(t, err, color="m", lw=0.6)
        axes[1, j].set_xlabel("time (s)")
    axes[0, 0].set_ylabel("force (N)")
    axes[1, 0].set_ylabel("error (N)")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{title} ({key.replace('_', ' + ')}), simulated")
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi=110)
    return path
