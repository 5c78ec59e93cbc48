"""Photon noise: expected counts -> one measured histogram, reproducible from a key."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["sample_counts", "sample_frames"]

# Above this mean the Poisson sampler is replaced by its normal limit (relative error < 1e-3
# in every moment that matters here) so counts up to 1e9 and beyond neither overflow int32 nor slow down.
_NORMAL_LIMIT = 1e6


def sample_counts(key, expected, *, poisson: bool = True, saturation: float | None = None):
    """Draw counts with mean ``expected`` (any shape); float output.

    **Arguments:**

    - ``key``: a JAX PRNG key; the same key gives the same histogram.
    - ``expected``: non-negative expected counts.
    - ``poisson``: photon noise on (off returns ``expected``, rounded only by saturation).
    - ``saturation``: largest count a bin holds (the TMF8828 has 24-bit bins).
    """
    lam = jnp.maximum(jnp.nan_to_num(expected, nan=0.0, posinf=0.0), 0.0)
    if poisson:
        k1, k2 = jax.random.split(key)
        small = jnp.minimum(lam, _NORMAL_LIMIT)
        counts = jax.random.poisson(k1, small, dtype=jnp.int32).astype(lam.dtype)
        normal = jnp.round(lam + jnp.sqrt(lam) * jax.random.normal(k2, lam.shape, lam.dtype))
        counts = jnp.where(lam < _NORMAL_LIMIT, counts, jnp.maximum(normal, 0.0))
    else:
        counts = lam
    if saturation is not None:
        counts = jnp.minimum(counts, saturation)
    return counts


@functools.partial(jax.jit, static_argnames=("poisson", "saturation"))
def sample_frames(keys, expected, *, poisson: bool = True, saturation: float | None = None):
    """One frame per key (``(len(keys), *expected.shape)``), each as :func:`sample_counts` draws it.

    One compiled program per shape and noise setting, reused by every caller (a ``jax.jit`` of a
    lambda made per call compiles again each time: seconds per simulated capture).
    """
    return jax.vmap(lambda k: sample_counts(k, expected, poisson=poisson, saturation=saturation))(keys)
