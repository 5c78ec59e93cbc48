"""Fixed geometry of a scene: sensors, their zones and where each zone's rays leave the waveguide.

Sensor positions are hardware, not fit parameters, so this is computed once in
NumPy when a model is built. Contact geometry, which is differentiable, lives
in :mod:`tofjax.model.components`.

Conventions: angles are radians counter-clockwise from +x; zone ``z`` of ``Z``
covers relative angles ``[-fov/2 + z w, -fov/2 + (z + 1) w]`` about the
optical axis, ``w = fov / Z`` (zone 0 is the most clockwise).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..scene import Scene

__all__ = ["Geometry", "boundary_distance", "edge_hits", "ray_samples", "zone_edges"]


def zone_edges(fov_deg: float, zones: int) -> np.ndarray:
    """Relative angle limits of each zone, (zones, 2), radians."""
    fov = math.radians(fov_deg)
    e = -fov / 2 + fov * np.arange(zones + 1) / zones
    return np.stack([e[:-1], e[1:]], 1)


def boundary_distance(size_m, xy: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Distance from points ``xy`` (..., 2) along ``angle`` (...) to the waveguide's edge.

    Rays that start on the edge and point out of the waveguide get 0.
    """
    tx, ty, _, _ = edge_hits(size_m, xy, angle)
    return np.clip(np.minimum(tx, ty), 0.0, None)


def edge_hits(size_m, xy: np.ndarray, angle: np.ndarray):
    """Where rays from ``xy`` (..., 2) along ``angle`` (...) meet the rectangle's edges:
    distances ``tx`` to the vertical edge (``x = 0`` or ``lx``) and ``ty`` to the horizontal one
    (inf where the ray runs parallel to it), and the ray's ``cos``, ``sin``. The ray leaves
    through the vertical edge where ``tx <= ty``."""
    lx, ly = size_m
    c, s = np.cos(angle), np.sin(angle)
    x, y = xy[..., 0], xy[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(c > 1e-12, (lx - x) / c, np.where(c < -1e-12, -x / c, np.inf))
        ty = np.where(s > 1e-12, (ly - y) / s, np.where(s < -1e-12, -y / s, np.inf))
    return tx, ty, c, s


def ray_samples(scene: Scene, angles_per_zone: int):
    """The geometry's NumPy source (also where a model is built inside a trace, when the
    :class:`Geometry` arrays are tracers): sensor positions (S, 2), directions (S,), zone angle
    limits (Z, 2) and the absolute angle of every angular sample (S, Z, A), radians."""
    sm = scene.sensor
    xy = np.array([s.position_m for s in scene.sensors], float)
    direction = np.radians([s.direction_deg for s in scene.sensors])
    edges = zone_edges(sm.fov_deg, sm.zones)
    frac = (np.arange(angles_per_zone) + 0.5) / angles_per_zone
    rel = edges[:, :1] + (edges[:, 1:] - edges[:, :1]) * frac[None, :]  # (Z, A)
    ang = direction[:, None, None] + rel[None]  # (S, Z, A)
    return xy, direction, edges, ang


class Geometry(eqx.Module):
    """Per-sensor, per-zone geometry as arrays (no static arrays: all leaves are jnp)."""

    sensor_xy: Float[Array, "S 2"]
    sensor_dir: Float[Array, " S"]
    zone_lo: Float[Array, " Z"]  # relative angle limits of each zone
    zone_hi: Float[Array, " Z"]
    ray_angle: Float[Array, "S Z A"]  # absolute angle of each angular sample
    ray_length: Float[Array, "S Z A"]  # distance to the edge along it

    @classmethod
    def from_scene(cls, scene: Scene, angles_per_zone: int, dtype) -> "Geometry":
        xy, direction, edges, ang = ray_samples(scene, angles_per_zone)
        length = boundary_distance(scene.waveguide.size_m, xy[:, None, None, :], ang)
        return cls(
            sensor_xy=jnp.asarray(xy, dtype),
            sensor_dir=jnp.asarray(direction, dtype),
            zone_lo=jnp.asarray(edges[:, 0], dtype),
            zone_hi=jnp.asarray(edges[:, 1], dtype),
            ray_angle=jnp.asarray(ang, dtype),
            ray_length=jnp.asarray(length, dtype),
        )
