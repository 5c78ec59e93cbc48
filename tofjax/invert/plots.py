"""Figures of tactile maps: one map with its detections, and a grid of maps (seed 000 Fig. 5-7)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..scene import Scene  # noqa: E402
from .detect import Detection  # noqa: E402
from .maps import Grid  # noqa: E402
from ..outputs import save_figure  # noqa: E402

__all__ = ["draw_map", "plot_map", "plot_map_grid", "plot_position_bound", "plot_sensitivity"]


def draw_map(
    ax, tactile_map, grid: Grid, scene: Scene, detection: Detection | None = None, truth=None, title=None, equalize=True
):
    m = np.asarray(tactile_map, float)
    vmax = m.max() if equalize and m.max() > 0 else None
    ax.imshow(m, origin="lower", extent=grid.extent, cmap="magma", vmin=0, vmax=vmax, interpolation="nearest")
    for s in scene.sensors:
        ax.plot(*s.position_m, "s", color="#4fc3f7", ms=5, mec="k", clip_on=False)
    if truth is not None:
        for x, y in np.asarray(truth).reshape(-1, 2):
            ax.add_patch(plt.Circle((x, y), 0.02, fill=False, ec="#00e676", lw=1.0, ls="--"))
    if detection is not None:
        if detection.labels is not None and detection.labels.any():
            ax.contour(
                grid.x, grid.y, (detection.labels > 0).astype(float), levels=[0.5], colors="#29b6f6", linewidths=0.8
            )
        p = detection.positions()
        if len(p):
            ax.plot(p[:, 0], p[:, 1], "x", color="#00e5ff", ms=7, mew=1.6)
    ax.set_xlim(0, grid.nx * grid.dx)
    ax.set_ylim(0, grid.ny * grid.dy)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=9)


def plot_map(tactile_map, grid: Grid, scene: Scene, path, *, detection=None, truth=None, title=None) -> Path:
    """One map with its detections (crosses), contact areas (outlines) and the truth (dashed 2 cm circles)."""
    fig, ax = plt.subplots(figsize=(4.6, 4.6))
    draw_map(ax, tactile_map, grid, scene, detection, truth, title)
    return _save(fig, path)


def plot_map_grid(
    rows: list[list[dict]], grid: Grid, scene: Scene, path, *, col_titles=None, row_titles=None, size: float = 2.3
) -> Path:
    """A table of maps: ``rows[i][j]`` is a dict with ``map`` and optional ``detection``, ``truth``
    and ``grid`` (default ``grid``)."""
    nr, nc = len(rows), len(rows[0])
    fig, axs = plt.subplots(nr, nc, figsize=(size * nc, size * nr), squeeze=False)
    for i, row in enumerate(rows):
        for j, cell in enumerate(row):
            draw_map(axs[i, j], cell["map"], cell.get("grid", grid), scene, cell.get("detection"), cell.get("truth"))
            if i == 0 and col_titles:
                axs[i, j].set_title(col_titles[j], fontsize=9)
        if row_titles:
            axs[i, 0].set_ylabel(row_titles[i], fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_sensitivity(result, path, *, title=None) -> Path:
    """A sensitivity map (:class:`tofjax.invert.sensitivity.SensitivityResult`): the smallest strength
    detected in one frame per cell (log colour scale; grey: never detected), the sensors, and the
    contours where a contact of ``options.strength`` becomes detectable in one frame (solid: half the
    time, alone), with twice that margin (dotted: where the study found nearly all contacts) and with
    ``options.frames`` summed (dashed)."""
    from matplotlib.colors import LogNorm

    g, o = result.grid, result.options
    m = np.where(result.sensed, result.min_strength, np.nan)
    fin = m[np.isfinite(m)]
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    ax.set_facecolor("0.8")
    handles = []
    if fin.size:
        im = ax.imshow(m, origin="lower", extent=g.extent, cmap="viridis", interpolation="nearest",
                       norm=LogNorm(vmin=float(fin.min()), vmax=float(fin.max())))
        fig.colorbar(im, ax=ax, shrink=0.85, label="min detectable strength, one frame")
        filled = np.where(np.isfinite(m), m, float(fin.max()) * 10)
        from .sensitivity import RELIABLE_MARGIN

        levels = [(o.strength, "-", "1 frame"), (o.strength / RELIABLE_MARGIN, ":", f"1 frame, x{RELIABLE_MARGIN:g} margin")]
        if o.frames > 1:
            levels.append((o.strength * np.sqrt(o.frames), "--", f"{o.frames} frames"))
        for lev, ls, lab in levels:
            if fin.min() < lev < filled.max():
                ax.contour(g.x, g.y, filled, levels=[lev], colors="w", linestyles=ls, linewidths=1.2)
                handles.append(plt.Line2D([], [], color="k", ls=ls, lw=1.2, label=f"strength {o.strength:g}: {lab}"))
    _finish_guide_axes(ax, result, handles)
    share = result.summary()["detectable_one_frame"]["all"]
    ax.set_title(title or f"{result.scene.name}: strength {o.strength:g} detectable on "
                 f"{'-' if share is None else f'{100 * share:.0f}%'} (1 frame)", fontsize=9)
    fig.subplots_adjust(bottom=0.24)
    return _save(fig, path)


def plot_position_bound(result, path, *, title=None) -> Path:
    """Where a contact can be placed (:class:`tofjax.invert.sensitivity.SensitivityResult` with ``position``): the
    larger standard deviation of a lone contact's position per cell at its Cramer-Rao bound (log colour scale, cm;
    grey: not placed at all), the sensors, and the contours where a fit lands within ``match_radius_m`` with
    probability 0.5 (dashed) and 0.9 (solid)."""
    from matplotlib.colors import LogNorm

    if result.position_sd is None:
        raise ValueError("plot_position_bound: the result has no position maps (SensitivityOptions(position=True))")
    g, o = result.grid, result.options
    m = np.where(result.sensed & np.isfinite(result.position_sd), 100.0 * result.position_sd, np.nan)
    fin = m[np.isfinite(m)]
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    ax.set_facecolor("0.8")
    handles = []
    if fin.size:
        im = ax.imshow(m, origin="lower", extent=g.extent, cmap="magma_r", interpolation="nearest",
                       norm=LogNorm(vmin=max(float(fin.min()), 1e-3), vmax=max(float(fin.max()), 2e-3)))
        fig.colorbar(im, ax=ax, shrink=0.85, label="position standard deviation [cm] (larger axis)")
        share = np.where(result.sensed, result.match_share, 0.0)
        for lev, ls in ((0.5, "--"), (0.9, "-")):
            if share.min() < lev < share.max():
                ax.contour(g.x, g.y, share, levels=[lev], colors="c", linestyles=ls, linewidths=1.2)
                handles.append(plt.Line2D([], [], color="c", ls=ls, lw=1.2,
                                          label=f"placed within {100 * o.match_radius_m:g} cm with probability {lev:g}"))
    _finish_guide_axes(ax, result, handles)
    pl = result.summary()["placed_within_match_radius"]["all"]
    ax.set_title(title or f"{result.scene.name}: a lone contact of strength {o.strength:g}, {o.frames} frame(s), placed "
                 f"within {100 * o.match_radius_m:g} cm: {'-' if pl is None else f'{100 * pl:.0f}%'} on average", fontsize=9)
    fig.subplots_adjust(bottom=0.24)
    return _save(fig, path)


def _finish_guide_axes(ax, result, handles) -> None:
    """A sensitivity map's axes: the legend of ``handles`` below the guide, the sensors, the guide's extent, labels."""
    g = result.grid
    if handles:
        ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=1, frameon=False)
    for s in result.scene.sensors:
        ax.plot(*s.position_m, "s", color="#4fc3f7", ms=6, mec="k", clip_on=False)
    ax.set_xlim(0, g.nx * g.dx)
    ax.set_ylim(0, g.ny * g.dy)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=110)
    return path
