"""Tactile maps (seed 000, Eq. 8): corrected histograms projected onto an (x, y) grid.

Each sensor's zone ``z`` covers an angular window; a pixel at distance ``d`` from the
sensor, inside window ``z``, takes the sensor's corrected histogram of zone ``z`` at the
arrival time of range ``d`` (linear interpolation between the two nearest bins). The maps
of all sensors are combined: ``mean`` over the sensors that see the pixel, the paper's plain
``sum``, or ``inverse_variance`` (default): a weighted mean with each sensor's weight
proportional to the inverse of its photon-noise variance at that pixel. A corrected contact
has the same expected value in every sensor that sees it, so any weighted mean keeps it; the
inverse-variance one has the least noise. It matters at the borders: there one sensor reads the
pixel at the range of its far-edge reflection, with the largest decay gain and the most counts,
and a plain mean lets that sensor's noise swamp the others'.

The geometry is fixed per scene, so the projection is precomputed once as an index map
(:class:`MapOperator`): for each sensor that sees it, a pixel reads 2 zones x 2 bins (1 zone
with ``angular="zone"``) as (flat bin index, weight) pairs. Pixels are grouped by how many
non-zero pairs they read (4, 8, 12, 16 on the default scene), so a frame costs a few short
unrolled loops of gathers and multiply-adds that XLA fuses, and one final permutation.
``index``/``weight`` keep the padded (P, 4 x sensors) form for references and noise maps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..config import ConfigError
from ..model.geometry import zone_edges
from ..scene import Scene
from .correction import OpticalParams

__all__ = ["COMBINE", "Grid", "MapOperator", "MapOptions", "build_map_operator", "dense_map_matrix"]

#: How the sensors' readings of a pixel are combined.
COMBINE = ("inverse_variance", "mean", "sum")


@dataclass(frozen=True)
class MapOptions:
    """- ``resolution_m``: pixel size (default 2.5 mm; the benchmark uses 1 mm).
    - ``combine``: ``inverse_variance`` (a weighted mean, weights 1/variance of each sensor's
      reading; needs the corrected histograms' variance), ``mean`` over the sensors that see
      a pixel, or ``sum`` (seed 000).
    - ``clip_negative``: negative corrected signals (noise, shadowing) contribute 0.
    - ``response_delay``: place bins at their range after the response's peak delay.
    - ``angular``: ``linear`` interpolates between zone centres (default: a contact that
      straddles two zones lands between them), ``zone`` is Eq. 8's constant value per zone."""

    resolution_m: float = 0.0025
    combine: str = "mean"
    clip_negative: bool = True
    response_delay: bool = True
    angular: str = "linear"

    def __post_init__(self):
        if not (self.resolution_m > 0 and math.isfinite(self.resolution_m)):
            raise ConfigError(f"resolution_m: must be > 0, got {self.resolution_m!r}")
        if self.combine not in COMBINE:
            raise ConfigError(f"combine: must be one of {', '.join(COMBINE)}, got {self.combine!r}")
        if self.angular not in ("linear", "zone"):
            raise ConfigError(f"angular: must be linear or zone, got {self.angular!r}")


@dataclass(frozen=True)
class Grid:
    """Pixel centres: ``x[i] = (i + 0.5) * dx``, ``y[j] = (j + 0.5) * dy``; maps are (ny, nx)."""

    nx: int
    ny: int
    dx: float
    dy: float

    @classmethod
    def for_scene(cls, scene: Scene, resolution_m: float) -> "Grid":
        lx, ly = scene.waveguide.size_m
        nx, ny = max(1, round(lx / resolution_m)), max(1, round(ly / resolution_m))
        return cls(nx=nx, ny=ny, dx=lx / nx, dy=ly / ny)

    @property
    def x(self) -> np.ndarray:
        return (np.arange(self.nx) + 0.5) * self.dx

    @property
    def y(self) -> np.ndarray:
        return (np.arange(self.ny) + 0.5) * self.dy

    def centres(self) -> np.ndarray:
        """(ny, nx, 2) pixel centres."""
        X, Y = np.meshgrid(self.x, self.y)
        return np.stack([X, Y], -1)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        return (0.0, self.nx * self.dx, 0.0, self.ny * self.dy)


class MapOperator(eqx.Module):
    """The precomputed projection. ``op(corrected)`` maps (..., S, Z, B) -> (..., ny, nx)."""

    index: jax.Array  # (P, J) int32 into the flattened (S*Z*B) histogram
    weight: jax.Array  # (P, J)
    coverage: jax.Array  # (P,) number of sensors that see each pixel
    buckets: tuple  # ((idx (P_k, J_k), weight (P_k, J_k)), ...): pixels grouped by pairs read
    inverse: jax.Array  # (P,) position of each pixel in the concatenated buckets
    ny: int = eqx.field(static=True)
    nx: int = eqx.field(static=True)
    clip_negative: bool = eqx.field(static=True)

    def __call__(self, corrected):
        h = jnp.asarray(corrected, self.weight.dtype)
        lead = h.shape[:-3]
        flat = h.reshape(*lead, -1)
        if self.clip_negative:
            flat = jnp.maximum(flat, 0.0)
        rows = flat.reshape(-1, flat.shape[-1]) if lead else flat[None]  # (F, S*Z*B)
        # Pixels are bucketed by how many (bin, weight) pairs they read; each bucket is a short
        # unrolled loop of gathers (one per slot), which XLA fuses without an (P, J, F) temporary.
        parts = []
        for idx, w in self.buckets:
            acc = rows[:, idx[:, 0]] * w[None, :, 0]
            for j in range(1, idx.shape[1]):
                acc = acc + rows[:, idx[:, j]] * w[None, :, j]
            parts.append(acc)
        m = jnp.concatenate(parts, axis=-1)[:, self.inverse]
        return m.reshape(*lead, self.ny, self.nx) if lead else m.reshape(self.ny, self.nx)

    def std(self, variance):
        """Per-pixel standard deviation of the map of independent bins with ``variance`` (S, Z, B)
        (the projection is linear: var(map) = W^2 var(h); clipping ignored)."""
        v = jnp.asarray(variance, self.weight.dtype).reshape(-1)
        return jnp.sqrt(jnp.sum(v[self.index] * self.weight**2, axis=-1)).reshape(self.ny, self.nx)


def _projection(scene: Scene, grid: Grid, optical: OpticalParams, response_delay: bool):
    """Per pixel and sensor: fractional zone (centres at integers; NaN outside the field of
    view) and fractional bin (centres at integers)."""
    sm = scene.sensor
    xy = grid.centres().reshape(-1, 2)  # (P, 2)
    sxy = np.array([s.position_m for s in scene.sensors])  # (S, 2)
    sdir = np.radians([s.direction_deg for s in scene.sensors])
    d = xy[:, None, :] - sxy[None]  # (P, S, 2)
    dist = np.hypot(d[..., 0], d[..., 1])
    ang = np.arctan2(d[..., 1], d[..., 0]) - sdir[None]
    rel = (ang + np.pi) % (2 * np.pi) - np.pi  # relative angle in [-pi, pi)
    edges = zone_edges(sm.fov_deg, sm.zones)
    lo, w = edges[0, 0], edges[0, 1] - edges[0, 0]
    pos = (rel - lo) / w
    zone = np.where((pos >= 0) & (pos < sm.zones), pos - 0.5, np.nan)
    delay = optical.response_delay_s(sm.bin_width_s) if response_delay else 0.0
    t = optical.emission_time_s + delay + 2.0 * dist / optical.range_speed(scene)
    u = t / sm.bin_width_s - 0.5  # fractional bin (bin centres at integers)
    return zone, u


#: The most (pixel, sensor, neighbour) entries a map operator may hold (16 bytes each: 1.6 GB).
MAX_OPERATOR_ENTRIES = 10**8


def build_map_operator(
    scene: Scene,
    optical: OpticalParams | None = None,
    options: MapOptions = MapOptions(),
    dtype=jnp.float32,
    variance: np.ndarray | None = None,
) -> tuple[MapOperator, Grid]:
    """Precompute the projection of ``scene`` onto its grid; returns ``(operator, grid)``.

    ``variance`` (S, Z, B): variance of each corrected bin without touch, for
    ``combine = "inverse_variance"`` (without it that falls back to ``mean``)."""
    optical = OpticalParams.from_scene(scene) if optical is None else optical
    grid = Grid.for_scene(scene, options.resolution_m)
    S, Z, B = scene.shape
    entries = grid.nx * grid.ny * S * 4  # the operator's (pixel, sensor, 4 neighbours) indices and weights
    if entries > MAX_OPERATOR_ENTRIES:
        raise ConfigError(
            f"resolution_m: {options.resolution_m * 1e3:g} mm gives a {grid.nx} x {grid.ny} map; its projection of {S} "
            f"sensors needs about {entries * 16 / 1e9:.2g} GB; use a coarser resolution (>= "
            f"{math.sqrt(grid.nx * grid.ny * S * 4 / MAX_OPERATOR_ENTRIES) * options.resolution_m * 1e3:.2g} mm)"
        )
    zone, u = _projection(scene, grid, optical, options.response_delay)
    P = zone.shape[0]
    inside = np.isfinite(zone)
    zf = np.where(inside, zone, 0.0)
    if options.angular == "zone":
        zpairs = ((np.round(zf).astype(int), np.ones_like(zf)),)
    else:
        z0 = np.floor(zf).astype(int)
        fz = zf - z0
        zpairs = ((np.clip(z0, 0, Z - 1), 1.0 - fz), (np.clip(z0 + 1, 0, Z - 1), fz))
    b0 = np.floor(u).astype(int)
    f = u - b0
    bpairs = ((b0, 1.0 - f), (b0 + 1, f))
    J = len(zpairs) * 2
    idx = np.zeros((P, S, J), np.int64)
    wt = np.zeros((P, S, J))
    k = 0
    for z, wz in zpairs:
        for b, wb in bpairs:
            valid = inside & (b >= 0) & (b < B)
            flat = (np.arange(S)[None, :] * Z + z) * B + np.clip(b, 0, B - 1)
            idx[..., k] = np.where(valid, flat, 0)
            wt[..., k] = np.where(valid, wz * wb, 0.0)
            k += 1
    seen = (wt.sum(-1) > 0).astype(float)  # (P, S)
    coverage = seen.sum(-1)
    if options.combine == "inverse_variance" and variance is not None:
        v = np.asarray(variance, float).reshape(-1)
        var_ps = np.sum(wt**2 * v[idx], axis=-1)  # (P, S): variance of each sensor's reading
        pos = var_ps[var_ps > 0]
        floor = 1e-6 * float(np.median(pos)) if pos.size else 1.0
        # A sensor whose reading is all masked bins (variance 0) carries no information.
        inv = np.where((seen > 0) & (var_ps > 0), 1.0 / np.maximum(var_ps, floor), 0.0)
        tot = inv.sum(-1, keepdims=True)
        a = np.where(tot > 0, inv / np.where(tot > 0, tot, 1.0), seen / np.maximum(coverage, 1.0)[:, None])
        wt = wt * a[..., None]
    elif options.combine in ("mean", "inverse_variance"):
        wt = wt / np.maximum(coverage, 1.0)[:, None, None]
    idx, wt = idx.reshape(P, J * S), wt.reshape(P, J * S)
    buckets, inverse = _buckets(idx, wt, dtype)
    op = MapOperator(
        buckets=buckets,
        inverse=jnp.asarray(inverse, jnp.int32),
        index=jnp.asarray(idx, jnp.int32),
        weight=jnp.asarray(wt, dtype),
        coverage=jnp.asarray(coverage, dtype),
        ny=grid.ny,
        nx=grid.nx,
        clip_negative=options.clip_negative,
    )
    return op, grid


def _buckets(idx: np.ndarray, wt: np.ndarray, dtype, step: int = 4):
    """Group pixels by their number of non-zero pairs (rounded up to ``step``), non-zero first."""
    nz = wt != 0
    count = nz.sum(1)
    order = np.argsort(~nz, axis=1, kind="stable")
    idx, wt = np.take_along_axis(idx, order, 1), np.take_along_axis(wt, order, 1)
    width = np.maximum(step * np.ceil(count / step), step).astype(int)
    perm, buckets = [], []
    for J in np.unique(width):
        px = np.flatnonzero(width == J)
        perm.append(px)
        buckets.append((jnp.asarray(idx[px, :J], jnp.int32), jnp.asarray(wt[px, :J], dtype)))
    perm = np.concatenate(perm)
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(perm))
    return tuple(buckets), inverse


def dense_map_matrix(op: MapOperator, n_in: int) -> np.ndarray:
    """The projection as a dense (P, S*Z*B) matrix: a reference for tests and small grids."""
    P, J = op.index.shape
    M = np.zeros((P, n_in))
    np.add.at(M, (np.repeat(np.arange(P), J), np.asarray(op.index).ravel()), np.asarray(op.weight, float).ravel())
    return M
