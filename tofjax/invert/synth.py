"""Many simulated touch frames at once, for the evaluation, tests and the benchmark.

:func:`tofjax.simulate.simulate` builds and compiles a model per scene; the evaluation
needs hundreds of contact configurations with the same number of contacts, so this builds
the forward model once per contact count and maps it over the contact positions
(``jax.vmap``), then draws photon noise with :func:`tofjax.model.sample_counts`.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model import ModelOptions, Params, build_model, sample_counts
from ..model.forward import _trace_switches
from ..model.geometry import zone_edges
from ..scene import Scene, Touch

__all__ = ["random_contacts", "shadowed", "simulate_contacts"]


@eqx.filter_jit
def _contact_frames(model, p0, n_contacts, noise, poisson, saturation, switches, contacts, keys):
    """The frames of a batch of contact configurations: compiled once per model structure and guided switches
    (``switches``, only a key: tracing reads them; the model is an argument: a ``jax.jit`` of a closure made per
    call compiled on every call)."""
    del switches

    def one(c, key):
        p = p0.replace(touch_xy_m=c[:, :2], touch_strength=c[:, 2]) if n_contacts else p0
        lam = model(p)
        if not noise:
            return lam
        return sample_counts(key, lam, poisson=poisson, saturation=saturation)

    return jax.vmap(one)(contacts, keys)


def simulate_contacts(
    scene: Scene,
    contacts: np.ndarray,
    seed: int = 0,
    *,
    radius_m: float = 0.006,
    options: ModelOptions = ModelOptions(),
    noise: bool = True,
    chunk: int = 64,
) -> np.ndarray:
    """Histograms (C, S, Z, B) for C configurations of N disk contacts.

    ``contacts`` is (C, N, 3) = x_m, y_m, strength (all configurations share N).
    """
    contacts = np.asarray(contacts, float)
    if contacts.ndim != 3 or contacts.shape[2] != 3:
        raise ValueError(f"contacts must be (configurations, contacts, 3) = x_m, y_m, strength; got shape {contacts.shape}")
    C, N, _ = contacts.shape
    base = scene.without_touches()
    # The prototype only fixes the model's structure (N contacts of this radius); its positions
    # are replaced per configuration. The guide's centre lies inside any guide.
    centre = tuple(0.5 * s for s in scene.waveguide.size_m)
    proto = base.replace(touches=tuple(Touch(centre, radius_m, 1.0) for _ in range(N))) if N else base
    model = build_model(proto, options)
    p0 = Params.from_scene(proto, options.jnp_dtype)

    f = functools.partial(_contact_frames, model, p0, N, noise, scene.noise.poisson, scene.sensor.saturation_counts,
                          _trace_switches())
    keys = jax.random.split(jax.random.key(seed), C)
    out = []
    for i in range(0, C, chunk):
        out.append(np.asarray(f(jnp.asarray(contacts[i : i + chunk]), keys[i : i + chunk])))
    return np.concatenate(out)


def random_contacts(
    scene: Scene,
    n_configs: int,
    n_contacts: int,
    seed: int = 0,
    *,
    min_separation_m: float = 0.04,
    margin_m: float = 0.015,
    strength: tuple[float, float] = (0.7, 1.3),
) -> np.ndarray:
    """(n_configs, n_contacts, 3) random positions at least ``min_separation_m`` apart and
    ``margin_m`` from the edge, strengths uniform in ``strength``."""
    rng = np.random.default_rng(seed)
    lx, ly = scene.waveguide.size_m
    out = np.zeros((n_configs, n_contacts, 3))
    for c in range(n_configs):
        pts: list[np.ndarray] = []
        tries = 0
        while len(pts) < n_contacts:
            tries += 1
            if tries > 100_000:
                raise ValueError(f"cannot place {n_contacts} contacts {min_separation_m} m apart")
            p = rng.uniform([margin_m, margin_m], [lx - margin_m, ly - margin_m])
            if all(np.hypot(*(p - q)) >= min_separation_m for q in pts):
                pts.append(p)
        out[c, :, :2] = pts
        out[c, :, 2] = rng.uniform(*strength, n_contacts)
    return out


def shadowed(scene, contacts: np.ndarray) -> np.ndarray:
    """(N,) True where every sensor that sees contact i has another contact nearer to it in the same zone."""
    sm = scene.sensor
    edges = zone_edges(sm.fov_deg, sm.zones)
    out = np.ones(len(contacts), bool)
    seen_any = np.zeros(len(contacts), bool)
    for s in scene.sensors:
        d = contacts[:, :2] - np.array(s.position_m)
        dist = np.hypot(d[:, 0], d[:, 1])
        rel = (np.arctan2(d[:, 1], d[:, 0]) - math.radians(s.direction_deg) + np.pi) % (2 * np.pi) - np.pi
        zone = np.searchsorted(edges[:, 1], rel)
        inside = (rel >= edges[0, 0]) & (rel < edges[-1, 1])
        for i in np.flatnonzero(inside):
            seen_any[i] = True
            blocked = np.any(inside & (zone == zone[i]) & (dist < dist[i] - 0.01))
            out[i] &= blocked
    return out & seen_any
