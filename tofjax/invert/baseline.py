"""Dynamic baseline: follow slow ambient or temperature drift online (seed 000 section 6).

Frame by frame (``jax.lax.scan``): the frame is compared with the current baseline; if it
looks like no touch, the baseline moves towards it by an exponential moving average::

    z_b    = (P_b - B_b) / sqrt(max(B_b, 1))        over the bins a contact can reach
    score  = max_b z_b - median_b z_b               (a uniform drift shifts the median too)
    no touch  <=>  score < z_threshold
    B     <- B + rate (P - B)                       only for no-touch frames

A contact is a localised excess of many sigma in a few bins; slow drift is a small,
smooth change of all bins. Frames with touch, NaN or saturated bins never update the
baseline. Each frame is corrected and mapped against the baseline it found.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..config import ConfigError

__all__ = ["DynamicBaselineOptions", "DynamicResult", "run_dynamic"]


@dataclass(frozen=True)
class DynamicBaselineOptions:
    """- ``rate``: weight of a no-touch frame in the moving average (1/rate frames of memory).
    - ``z_threshold``: a frame whose largest localised excess exceeds this many sigma is a touch."""

    rate: float = 0.2
    z_threshold: float = 7.0

    def __post_init__(self):
        if not 0.0 < self.rate <= 1.0:
            raise ConfigError(f"rate: must be in (0, 1], got {self.rate!r}")
        if not self.z_threshold > 0:
            raise ConfigError(f"z_threshold: must be > 0, got {self.z_threshold!r}")


class DynamicResult(NamedTuple):
    maps: np.ndarray  # (F, ny, nx)
    ok: np.ndarray  # (F,) no NaN/saturation
    no_touch: np.ndarray  # (F,) frames used to update the baseline
    score: np.ndarray  # (F,) the classification statistic
    baseline: np.ndarray  # (S, Z, B) the baseline after the last frame
    noise: np.ndarray  # (F, ny, nx) per-pixel noise of each frame's map (from its baseline)

    def detections(self, inverter) -> list:
        """Touches in every frame, each against its own noise map."""
        from .detect import Detection, detect

        return [
            detect(m, inverter.grid, inverter.options.detect, noise=n, strength_scale=inverter.strength_scale)
            if good
            else Detection()
            for m, n, good in zip(self.maps, self.noise, self.ok)
        ]


def _scan(corrector, operator, baseline0, H, rate, z_thr):
    mask = corrector.mask

    def step(B, h):
        clean = jnp.where(jnp.isfinite(h), h, 0.0)
        ok = jnp.all(jnp.isfinite(h) & (h < corrector.saturation))
        z = (clean - B) / jnp.sqrt(jnp.maximum(B, 1.0))
        zm = jnp.where(mask, z, jnp.nan)
        score = jnp.nanmax(zm) - jnp.nanmedian(zm)
        quiet = ok & (score < z_thr)
        corrected, _ = corrector.replace_baseline(B)(h)
        m = operator(corrected)
        # Photon noise of the frame and of the moving average (its variance is rate / (2 - rate)).
        noise = operator.std(corrector.gain**2 * jnp.maximum(B, 1.0) * (1.0 + rate / (2.0 - rate)))
        B_new = jnp.where(quiet, B + rate * (clean - B), B)
        return B_new, (m, ok, quiet, score, noise)

    B, (maps, ok, quiet, score, noise) = jax.lax.scan(step, baseline0, H)
    return maps, ok, quiet, score, B, noise


_scan_jit = jax.jit(_scan)


def run_dynamic(
    inverter, histograms, options: DynamicBaselineOptions = DynamicBaselineOptions(), baseline0=None
) -> DynamicResult:
    """Process frames in order with a baseline that follows drift.

    ``inverter`` is a back-projection :class:`~tofjax.invert.pipeline.Inverter` (method
    ``baseline`` or ``full``); its baseline is the starting point unless ``baseline0``.
    """
    c = inverter.corrector
    if c.method not in ("baseline", "full"):
        raise ConfigError(f"a dynamic baseline needs method baseline or full, not {c.method!r}")
    dt = c.gain.dtype
    B0 = c.baseline if baseline0 is None else jnp.asarray(baseline0, dt)
    H = jnp.asarray(histograms, dt)
    maps, ok, quiet, score, B, noise = _scan_jit(c, inverter.operator, B0, H, options.rate, options.z_threshold)
    return DynamicResult(*(np.asarray(x) for x in (maps, ok, quiet, score, B, noise)))
