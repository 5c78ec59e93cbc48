"""Touch detection on a tactile map: threshold, local maxima, connected components.

A pixel is *on* when the map exceeds the threshold ``max(threshold, relative x max)`` and
its noise test: ``map > n_sigma x noise`` or, with ``cfar`` (constant false-alarm rate, the
default for back-projection), ``(map - floor) / noise > n_sigma`` where ``floor`` and ``noise``
are the mean and standard deviation of maps without touch (measured on the baseline's frames
or on Poisson draws around it, see :func:`tofjax.invert.pipeline.build_inverter`): the
normalised map has the same no-touch statistics everywhere, at the borders as in the middle,
so one ``n_sigma`` gives the same false-alarm rate at every pixel; each connected region of on pixels is a contact area (its pixels are
its shape: a stick or a mug's rim comes out as one elongated or ring-shaped component),
and each local maximum inside it (at least ``min_separation_m`` from a stronger one) is a
touch, placed at the weighted centroid of the map around it (sub-pixel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..config import ConfigError
from .maps import Grid

__all__ = ["Component", "DetectOptions", "Detection", "detect", "match"]


@dataclass(frozen=True)
class DetectOptions:
    """- ``threshold``: absolute floor, in map units.
    - ``relative``: fraction of the map's maximum below which nothing is a touch.
    - ``n_sigma``: multiple of the per-pixel noise (when a noise map is given).
    - ``cfar``: (methods with a baseline: ``baseline``, ``full``) test ``(map - floor) / noise`` against ``n_sigma``, with the floor and noise of
      no-touch maps measured by an ensemble (``cfar_draws`` Poisson draws around the
      baseline mean, seeded by ``cfar_seed``, or the baseline's own frames when given);
      otherwise ``map`` against ``n_sigma`` times the linear (unclipped) Poisson noise.
    - ``min_separation_m``: two touches closer than this are one.
    - ``refine_radius_m``: radius of the weighted centroid around each maximum.
    - ``min_area_m2``: components smaller than this are ignored (isolated noisy pixels).
    - ``saddle``: a weaker maximum joined to an accepted stronger one (within
      ``saddle_radius_m``) by a straight path that never dips below ``saddle`` times its own
      height is a shoulder of that contact (a pulse tail, a range smear), not another contact.
      1 turns the test off."""

    threshold: float = 0.0
    relative: float = 0.2
    n_sigma: float = 7.0
    min_separation_m: float = 0.02
    refine_radius_m: float = 0.008
    min_area_m2: float = 2e-5
    saddle: float = 0.4
    saddle_radius_m: float = 0.06
    cfar: bool = True
    cfar_draws: int = 64
    cfar_seed: int = 0

    def __post_init__(self):
        if self.cfar_draws < 2:
            raise ConfigError(f"cfar_draws: must be >= 2, got {self.cfar_draws!r}")
        if not 0.0 < self.saddle <= 1.0:
            raise ConfigError(f"saddle: must be in (0, 1], got {self.saddle!r}")
        if not 0.0 <= self.relative < 1.0:
            raise ConfigError(f"relative: must be in [0, 1), got {self.relative!r}")
        for k in ("threshold", "n_sigma", "min_separation_m", "refine_radius_m", "min_area_m2"):
            v = getattr(self, k)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"{k}: must be a finite number >= 0, got {v!r}")


@dataclass
class Component:
    """A connected contact area: its pixels are ``labels == label``."""

    label: int
    area_m2: float
    centroid_m: tuple[float, float]
    bbox_m: tuple[float, float, float, float]  # x0, x1, y0, y1
    peak: float
    elongation: float  # sqrt of the ratio of the principal second moments (1: round)


@dataclass
class Detection:
    touches: list[dict] = field(default_factory=list)  # {"x_m", "y_m", "strength", "component"}
    components: list[Component] = field(default_factory=list)
    labels: np.ndarray | None = None  # (ny, nx) int, 0 = background
    threshold: float = 0.0

    def positions(self) -> np.ndarray:
        return np.array([[t["x_m"], t["y_m"]] for t in self.touches]).reshape(-1, 2)


def detect(
    tactile_map: np.ndarray,
    grid: Grid,
    options: DetectOptions = DetectOptions(),
    noise: np.ndarray | None = None,
    strength_scale: float = 1.0,
    floor: np.ndarray | None = None,
) -> Detection:
    """Touches and contact areas in one map (ny, nx).

    ``noise`` (ny, nx) is the per-pixel standard deviation of the map without touch and
    ``floor`` (ny, nx) its mean (used with ``options.cfar``); ``strength_scale`` converts
    map values to contact strength.
    """
    m = np.nan_to_num(np.asarray(tactile_map, float), nan=0.0, posinf=0.0, neginf=0.0)
    peak = float(m.max()) if m.size else 0.0
    thr = max(options.threshold, options.relative * peak)
    if noise is not None and options.cfar and floor is not None:
        sd = np.asarray(noise, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(sd > 0, (m - np.asarray(floor, float)) / sd, 0.0)
        on_noise = z > options.n_sigma
    elif noise is not None and options.n_sigma > 0:  # n_sigma = 0: no noise gate (0 x an infinite sigma is NaN)
        on_noise = m > options.n_sigma * np.asarray(noise, float)
    else:
        on_noise = np.ones(m.shape, bool)
    on = (m > thr) & on_noise & (m > 0)
    labels, n = ndimage.label(on, structure=np.ones((3, 3)))
    px_area = grid.dx * grid.dy
    out = Detection(labels=labels, threshold=thr)
    if n == 0:
        return out
    sizes = ndimage.sum_labels(np.ones_like(m), labels, index=np.arange(1, n + 1))
    keep = np.zeros(n + 1, bool)
    keep[1:] = sizes * px_area >= options.min_area_m2
    labels = np.where(keep[labels], labels, 0)
    out.labels = labels
    X, Y = np.meshgrid(grid.x, grid.y)
    for lab in np.flatnonzero(keep):
        sel = labels == lab
        w = m[sel]
        cx, cy = float(np.average(X[sel], weights=w)), float(np.average(Y[sel], weights=w))
        dx, dy = X[sel] - cx, Y[sel] - cy
        cov = np.cov(np.stack([dx, dy]), aweights=w) if sel.sum() > 2 else np.eye(2)
        ev = np.sort(np.linalg.eigvalsh(np.atleast_2d(cov)))
        out.components.append(
            Component(
                label=int(lab),
                area_m2=float(sel.sum() * px_area),
                centroid_m=(cx, cy),
                bbox_m=(float(X[sel].min()), float(X[sel].max()), float(Y[sel].min()), float(Y[sel].max())),
                peak=float(w.max()),
                elongation=float(math.sqrt(ev[-1] / max(ev[0], 1e-30))) if ev[0] > 0 else float("inf"),
            )
        )
    # Local maxima inside the components, strongest first, at least min_separation apart.
    size = max(3, 2 * int(round(0.5 * options.min_separation_m / min(grid.dx, grid.dy))) + 1)
    is_max = (m == ndimage.maximum_filter(m, size=size, mode="constant")) & (labels > 0)
    cand = np.argwhere(is_max)
    cand = cand[np.argsort(-m[is_max])]
    rr = max(1, int(round(options.refine_radius_m / min(grid.dx, grid.dy))))
    taken: list[tuple[float, float]] = []
    peaks: list[tuple[int, int]] = []
    for j, i in cand:
        j0, j1, i0, i1 = max(0, j - rr), min(m.shape[0], j + rr + 1), max(0, i - rr), min(m.shape[1], i + rr + 1)
        win = m[j0:j1, i0:i1]
        ww = np.clip(win - 0.5 * m[j, i], 0.0, None)
        if ww.sum() <= 0:
            ww = np.ones_like(win)
        x = float(np.sum(ww * X[j0:j1, i0:i1]) / ww.sum())
        y = float(np.sum(ww * Y[j0:j1, i0:i1]) / ww.sum())
        if any(math.hypot(x - a, y - b) < options.min_separation_m for a, b in taken):
            continue
        if options.saddle < 1.0 and _is_shoulder(m, (j, i), peaks, options.saddle, options.saddle_radius_m, grid):
            continue
        taken.append((x, y))
        peaks.append((j, i))
        out.touches.append(
            {"x_m": x, "y_m": y, "strength": float(m[j, i] * strength_scale), "component": int(labels[j, i])}
        )
    return out


def _is_shoulder(m, p, peaks, saddle, radius_m, grid) -> bool:
    """True when ``m`` stays above ``saddle x m[p]`` all along the segment from pixel ``p`` to
    one of the (stronger) ``peaks`` within ``radius_m``."""
    j, i = p
    h = saddle * m[j, i]
    for pj, pi in peaks:
        dist = math.hypot((pj - j) * grid.dy, (pi - i) * grid.dx)
        if dist > radius_m:
            continue
        n = max(2, int(math.ceil(max(abs(pj - j), abs(pi - i)))) + 1)
        jj = np.round(np.linspace(j, pj, n)).astype(int)
        ii = np.round(np.linspace(i, pi, n)).astype(int)
        if m[jj, ii].min() >= h:
            return True
    return False


def match(detected: np.ndarray, truth: np.ndarray, radius_m: float = 0.02) -> tuple[int, np.ndarray]:
    """One-to-one matching of detections to true contacts within ``radius_m`` (Hungarian on
    distance). Returns (matches, distances of the matched pairs)."""
    from scipy.optimize import linear_sum_assignment

    detected, truth = np.asarray(detected).reshape(-1, 2), np.asarray(truth).reshape(-1, 2)
    if not len(detected) or not len(truth):
        return 0, np.zeros(0)
    d = np.hypot(*(detected[:, None, :] - truth[None, :, :]).transpose(2, 0, 1))
    cost = np.where(d <= radius_m, d, 1e6)
    r, c = linear_sum_assignment(cost)
    ok = d[r, c] <= radius_m
    return int(ok.sum()), d[r, c][ok]
