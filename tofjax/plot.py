"""Figures: scene layout, histograms per sensor and zone, model components.

Every function takes data already computed (a capture, arrays) and writes a
PNG, so figures can be regenerated from saved files.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Rectangle, Wedge  # noqa: E402

from .capture import Capture  # noqa: E402
from .model.geometry import zone_edges  # noqa: E402
from .outputs import save_figure  # noqa: E402
from .scene import Scene  # noqa: E402

__all__ = ["plot_capture", "plot_components", "plot_data_share", "plot_fit", "plot_loss", "plot_posterior", "plot_scene",
           "plot_traces"]


def _sensor_label(scene: Scene, i: int) -> str:
    return scene.sensors[i].name or f"S{i}"


def plot_scene(scene: Scene, path: str | Path, title: str | None = None) -> Path:
    """Top view: the waveguide, each sensor's field of view and zones, the contacts (seed 000 Fig. 3)."""
    wg = scene.waveguide
    lx, ly = wg.size_m
    fig, ax = plt.subplots(figsize=(5.5, 5.5 * ly / lx + 0.4))
    ax.add_patch(Rectangle((0, 0), lx, ly, fc="#e8f1fa", ec="k", lw=1.2))
    reach = math.hypot(lx, ly)
    colors = plt.cm.tab10(np.arange(scene.n_sensors) % 10)
    for i, s in enumerate(scene.sensors):
        x, y = s.position_m
        edges = np.degrees(zone_edges(scene.sensor.fov_deg, scene.sensor.zones)) + s.direction_deg
        for z, (a0, a1) in enumerate(edges):
            ax.add_patch(
                Wedge((x, y), reach, a0, a1, fc=colors[i], alpha=0.06 if z % 2 else 0.11, ec=colors[i], lw=0.3)
            )
        ax.plot([x], [y], "s", color=colors[i], ms=8, mec="k")
        ax.annotate(_sensor_label(scene, i), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=9)
    for x, y, r, _ in scene.contact_elements():
        ax.add_patch(Circle((x, y), r, fc="#d62728", ec="k", lw=0.5, alpha=0.9))
    ax.set_xlim(-0.02 * lx, 1.02 * lx)
    ax.set_ylim(-0.02 * ly, 1.02 * ly)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or f"{scene.name}: {scene.n_sensors} sensors, {scene.sensor.zones} zones each")
    return _save(fig, path)


def _bin_axis(scene: Scene) -> np.ndarray:
    return np.arange(scene.sensor.n_bins)


def chosen_sensors(n_sensors: int, sensors: Sequence[int] | None) -> list[int]:
    """The sensors' indices to draw, sorted, once each (``None``: all); ValueError for an empty list or an index out
    of ``0 .. n_sensors - 1``."""
    chosen = list(range(n_sensors)) if sensors is None else sorted(dict.fromkeys(int(s) for s in sensors))
    if not chosen or not all(0 <= s < n_sensors for s in chosen):
        raise ValueError(f"the capture has sensors 0-{n_sensors - 1}, got {list(sensors or [])!r}")
    return chosen


def plot_capture(
    capture: Capture,
    out_dir: str | Path,
    baseline: Capture | None = None,
    *,
    log: bool = True,
    sensors: Sequence[int] | None = None,
) -> list[Path]:
    """One PNG per sensor with a panel per zone: mean histogram over frames (with the
    frame-to-frame spread), and the baseline where one is given (seed 000 Fig. 2b).
    With a baseline, a second row shows touch minus baseline (Fig. 2c). ``sensors``: the
    sensors' indices to draw (default all; a skin of many sensors takes about 2 s a figure).
    """
    scene = capture.scene
    out_dir = Path(out_dir)
    S, Z, B = scene.shape
    bins = _bin_axis(scene)
    mean = capture.histograms.mean(0)
    lo, hi = np.percentile(capture.histograms, [16, 84], axis=0) if capture.n_frames > 1 else (mean, mean)
    base = baseline.histograms.mean(0) if baseline is not None else None
    chosen = chosen_sensors(S, sensors)
    paths = []
    rows = 2 if base is not None else 1
    for s in chosen:
        fig, axes = plt.subplots(rows, Z, figsize=(2.3 * Z, 2.4 * rows + 0.5), sharex=True, squeeze=False)
        for z in range(Z):
            ax = axes[0, z]
            if base is not None:
                ax.plot(bins, base[s, z], ":", color="tab:blue", lw=1.2, label="baseline")
            ax.fill_between(bins, lo[s, z], hi[s, z], color="tab:orange", alpha=0.3, lw=0)
            ax.plot(bins, mean[s, z], color="tab:orange", lw=1.0, label="capture")
            if log:
                ax.set_yscale("log")
                ax.set_ylim(bottom=max(0.5, float(mean[s].min()) * 0.5))
            ax.set_title(f"zone {z}", fontsize=9)
            if base is not None:
                d = axes[1, z]
                d.axhline(0, color="k", lw=0.5)
                d.plot(bins, mean[s, z] - base[s, z], color="tab:green", lw=1.0)
                d.set_xlabel("bin")
                if z == 0:
                    d.set_ylabel("capture - baseline")
            else:
                ax.set_xlabel("bin")
        axes[0, 0].set_ylabel("counts")
        axes[0, 0].legend(fontsize=7, loc="upper right")
        fig.suptitle(f"{scene.name}: sensor {_sensor_label(scene, s)} ({capture.source}, {capture.n_frames} frames)")
        paths.append(_save(fig, out_dir / f"histograms_sensor{s}.png"))
    return paths


def plot_components(breakdown: dict[str, np.ndarray], scene: Scene, sensor: int, zone: int, path: str | Path) -> Path:
    """The forward model's terms (Eq. 2) for one sensor and zone, on a log scale."""
    bins = _bin_axis(scene)
    fig, ax = plt.subplots(figsize=(7, 4))
    total = sum(np.asarray(v)[sensor, zone] for v in breakdown.values())
    ax.plot(bins, total, "k", lw=2, label="P_r (sum)")
    for name, v in breakdown.items():
        ax.plot(bins, np.asarray(v)[sensor, zone], lw=1.2, label=name)
    ax.set_yscale("log")
    ax.set_ylim(max(1e-2, float(total.min()) * 1e-2), float(total.max()) * 2)
    ax.set_xlabel(f"bin ({scene.sensor.bin_width_s * 1e12:.0f} ps)")
    ax.set_ylabel("expected counts")
    ax.set_title(f"{scene.name}: forward model terms, sensor {_sensor_label(scene, sensor)}, zone {zone}")
    ax.legend(fontsize=8, ncol=2)
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def plot_fit(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, scene: Scene, out_dir: str | Path) -> list[Path]:
    """Data against fitted model per sensor and zone, with normalised residuals below."""
    out_dir = Path(out_dir)
    S, Z, _ = scene.shape
    bins = _bin_axis(scene)
    paths = []
    for s in range(S):
        fig, axes = plt.subplots(2, Z, figsize=(2.3 * Z, 4.6), sharex=True, squeeze=False,
                                 gridspec_kw={"height_ratios": [2, 1]})
        for z in range(Z):
            ax = axes[0, z]
            ax.plot(bins, data[s, z], ".", ms=2.5, color="k", label="data (mean)")
            ax.plot(bins, model[s, z], color="tab:red", lw=1.0, label="fit")
            ax.set_yscale("log")
            ax.set_ylim(bottom=max(0.5, float(data[s].min()) * 0.5))
            ax.set_title(f"zone {z}", fontsize=9)
            r = (model[s, z] - data[s, z]) / sigma[s, z]
            axes[1, z].axhline(0, color="k", lw=0.5)
            axes[1, z].plot(bins, r, color="tab:blue", lw=0.8)
            axes[1, z].set_ylim(-5, 5)
            axes[1, z].set_xlabel("bin")
        axes[0, 0].set_ylabel("counts")
        axes[1, 0].set_ylabel("(fit - data) / sigma")
        axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"{scene.name}: calibration fit, sensor {_sensor_label(scene, s)}")
        paths.append(_save(fig, out_dir / f"fit_sensor{s}.png"))
    return paths


def plot_loss(history, path: str | Path) -> Path:
    """The loss at every solver step (all stages, in order)."""
    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.semilogy(np.arange(len(history)), history, color="k", lw=1)
    ax.set_xlabel("solver step (all stages)")
    ax.set_ylabel("loss")
    ax.set_title("calibration: loss history")
    return _save(fig, path)


def plot_data_share(shares: dict[str, float], path: str | Path) -> Path:
    """The data's share of each fit coordinate's Laplace variance (``CalibrationResult.data_share``) as bars,
    least determined at the top; those the report calls "set mostly by the weak prior" (below
    ``PRIOR_SET_SHARE``) in red."""
    if not shares:
        raise ValueError("no data shares to plot (a calibration without a prior has none)")
    from .fit._result import PRIOR_SET_SHARE as threshold
    from .fit._result import SHARE_LABELS

    items = sorted(shares.items(), key=lambda kv: -kv[1])
    names = [SHARE_LABELS.get(k, k) for k, _ in items]
    vals = np.array([v for _, v in items])
    fig, ax = plt.subplots(figsize=(6, 0.28 * len(items) + 1.2))
    y = np.arange(len(items))
    ax.barh(y, vals, color=np.where(vals < threshold, "tab:red", "tab:blue"))
    for yi, v in zip(y, vals):  # the value beside each bar: a share near 0 has no visible bar
        ax.text(min(v, 0.85) + 0.01, yi, f"{v:.2g}", va="center", fontsize=7)
    ax.axvline(threshold, color="k", lw=0.8, ls="--")
    ax.set_yticks(y, names, fontsize=8)
    ax.set_xlim(0, 1)
    ax.set_xlabel("share of the Laplace variance from the data\n(1: the data alone; 0: the weak prior alone)", fontsize=9)
    ax.set_title("calibration: which values the data set", fontsize=10)
    return _save(fig, path)


def plot_posterior(samples: np.ndarray, names: list[str], truths, path: str | Path) -> Path:
    """Corner plot of posterior samples (physical units); ``truths`` may be None."""
    import corner

    fig = corner.corner(samples, labels=names, truths=truths, quantiles=[0.025, 0.5, 0.975], show_titles=True,
                        title_fmt=".3g", label_kwargs={"fontsize": 8}, title_kwargs={"fontsize": 7})
    return save_figure(fig, path, dpi=90)


def plot_traces(chain: np.ndarray, names: list[str], path: str | Path) -> Path:
    """Walker traces in physical units, (steps, walkers, parameters), one panel per parameter."""
    P = chain.shape[-1]
    fig, axes = plt.subplots(P, 1, figsize=(7, 1.3 * P + 0.5), sharex=True, squeeze=False)
    for i in range(P):
        axes[i, 0].plot(chain[:, :, i], color="k", alpha=0.15, lw=0.5)
        axes[i, 0].set_ylabel(names[i], fontsize=7)
    axes[-1, 0].set_xlabel("step")
    fig.suptitle("posterior: walker traces (physical units)")
    return _save(fig, path)
