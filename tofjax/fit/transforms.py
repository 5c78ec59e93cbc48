"""Unconstrained parametrisation of the fit parameters.

Every fitted parameter lives in an unconstrained space where one tolerance
fits all: positive ones through a log (relative to a natural scale), bounded
ones through a scaled sigmoid. Results are reported in physical units, with
standard errors carried through the transform's derivative.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from ..scene import Scene

__all__ = ["Transform", "default_transforms", "FITTABLE"]


@dataclass(frozen=True)
class Transform:
    """``kind = "log"``: x = scale exp(u); ``kind = "sigmoid"``: x = lo + (hi - lo) sigmoid(u).

    ``floor``: with ``kind = "log"``, 0 maps to the coordinate of ``floor x scale``: a parameter
    whose natural value is 0 (a width the scene does not state) then has a finite coordinate,
    and the prior centred there a finite pull. Positive values keep their own coordinate (a
    fit may end below the floor; its result must round-trip). With ``kind = "sigmoid"``, ``lo``
    (or below) maps to the coordinate of ``lo + floor x (hi - lo)`` (at least 1e-9 of the range,
    as every value is clipped): near ``lo`` such a sigmoid is a log with scale ``hi - lo``, and
    ``hi`` caps it (a width that must stay within a physical bound)."""

    kind: str
    lo: float = 0.0
    hi: float = 1.0
    scale: float = 1.0
    floor: float = 1e-12

    def to_physical(self, u):
        if self.kind == "log":
            return self.scale * jnp.exp(u)
        return self.lo + (self.hi - self.lo) * jnp.reciprocal(1.0 + jnp.exp(-u))

    def to_unconstrained(self, x):
        x = np.asarray(x, float)
        if self.kind == "log":
            return np.log(np.where(x > 0, np.maximum(x, 1e-12 * self.scale), self.floor * self.scale) / self.scale)
        f = np.clip((x - self.lo) / (self.hi - self.lo), 1e-9, 1 - 1e-9)
        f = np.where(x > self.lo, f, max(self.floor, 1e-9))
        return np.log(f) - np.log1p(-f)

    def to_physical_np(self, u):
        """:meth:`to_physical` in NumPy (no JAX dispatch: for reports after the fit)."""
        u = np.asarray(u, float)
        if self.kind == "log":
            return self.scale * np.exp(u)
        return self.lo + (self.hi - self.lo) / (1.0 + np.exp(-u))

    def derivative_np(self, u):
        """:meth:`derivative` in NumPy."""
        u = np.asarray(u, float)
        if self.kind == "log":
            return self.scale * np.exp(u)
        s = 1.0 / (1.0 + np.exp(-u))
        return (self.hi - self.lo) * s * (1.0 - s)

    def unconstrain(self, x):
        """:meth:`to_unconstrained` in JAX (jit- and grad-safe), for the compiled fit."""
        if self.kind == "log":
            return jnp.log(jnp.where(x > 0, jnp.maximum(x, 1e-12 * self.scale), self.floor * self.scale) / self.scale)
        f = jnp.clip((x - self.lo) / (self.hi - self.lo), 1e-9, 1 - 1e-9)
        f = jnp.where(x > self.lo, f, max(self.floor, 1e-9))
        return jnp.log(f) - jnp.log1p(-f)

    def derivative(self, u):
        """dx/du at ``u``: carries standard errors from u to physical units."""
        if self.kind == "log":
            return self.scale * jnp.exp(u)
        s = jnp.reciprocal(1.0 + jnp.exp(-u))
        return (self.hi - self.lo) * s * (1.0 - s)


#: Parameters calibration can fit, with their units for reports.
FITTABLE = {
    "n1": "",
    "mu_s_per_m": "1/m",
    "mu_a_per_m": "1/m",
    "gain": "counts m^2",
    "ambient_counts": "counts/bin",
    "crosstalk_counts": "counts",
    "crosstalk_width_s": "s",
    "pulse_sigma_s": "s",
    "pulse_tail_s": "s",
    "pulse_slow_weight": "",
    "pulse_slow_tail_s": "s",
    "emission_time_s": "s",
    "interface_backscatter_per_m": "1/m",
    "end_reflectance": "",
    "end_incidence_power": "",
    "multiple_scattering": "",
    "volume_backscatter_fraction": "",
    "near_field_m": "m",
    "near_field_shape": "",
}


def default_transforms(scene: Scene) -> dict[str, Transform]:
    """The transform of every fittable parameter, scaled to the scene."""
    sm = scene.sensor
    window = sm.n_bins * sm.bin_width_s
    return {
        "n1": Transform("sigmoid", lo=1.0, hi=4.0),
        "mu_s_per_m": Transform("log", scale=1.0),
        "mu_a_per_m": Transform("log", scale=1.0),
        "gain": Transform("log", scale=max(sm.gain, 1e-12)),
        "ambient_counts": Transform("log", scale=1.0),
        "crosstalk_counts": Transform("log", scale=1000.0),
        # the light-entry peak's own width: a scene states 0 (a point), which maps to 1/200 of
        # the range (1 ps for 100 ps bins, far below any pulse): the prior's centre. Capped at
        # two bins: paths that skip the guide differ by centimetres at most, and an uncapped
        # width ran off to a broad background (2.7 ns) on one independent baseline
        "crosstalk_width_s": Transform("sigmoid", lo=0.0, hi=2.0 * sm.bin_width_s, floor=0.005),
        "pulse_sigma_s": Transform("log", scale=sm.bin_width_s),
        "pulse_tail_s": Transform("log", scale=sm.bin_width_s),
        # the slow tail's share stays below one half: the fast tail is the main one
        "pulse_slow_weight": Transform("sigmoid", lo=0.0, hi=0.5),
        "pulse_slow_tail_s": Transform("log", scale=sm.bin_width_s),
        "emission_time_s": Transform("sigmoid", lo=0.0, hi=window),
        "interface_backscatter_per_m": Transform("log", scale=1.0),
        "end_reflectance": Transform("sigmoid", lo=0.0, hi=1.0),
        # the edge's angle law cos^p: from a return that grows toward grazing (-1) to a
        # narrow lobe about the normal (8); 0 (one reflectance for all angles) is inside
        "end_incidence_power": Transform("sigmoid", lo=-1.0, hi=8.0),
        "multiple_scattering": Transform("log", scale=1.0),
        "volume_backscatter_fraction": Transform("log", scale=0.01),
        "near_field_m": Transform("log", scale=max(scene.waveguide.near_field, 1e-6)),
        # the near field's shape p in G = (r^p + d^p)^(-2/p): from 1/(r + d)^2 (1) through the
        # scene's 1/(r^2 + d^2) (2) to 1/max(r, d)^2 (the cap, 65, is within 2% of it); near 1
        # the sigmoid is a log of p - 1 (scale 64)
        "near_field_shape": Transform("sigmoid", lo=1.0, hi=65.0),
    }
