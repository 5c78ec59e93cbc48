"""Physical parameters of the forward model, as one pytree of named fields.

Everything the model is differentiable in lives here, in SI units. Fitting
code (calibration) transforms these to an unconstrained space and back;
the forward model only ever sees physical values.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..scene import Scene

__all__ = ["Params"]


class Params(eqx.Module):
    """Parameters of Eq. 2-5 for one scene.

    Shapes: ``S`` sensors, ``Z`` zones, ``N`` contact disks.
    """

    n1: Float[Array, ""]
    mu_s_per_m: Float[Array, ""]
    mu_a_per_m: Float[Array, ""]
    gain: Float[Array, " S"]  # K of Eq. 3, counts m^2
    pulse_sigma_s: Float[Array, ""]
    pulse_tail_s: Float[Array, ""]
    emission_time_s: Float[Array, ""]
    crosstalk_counts: Float[Array, "S Z"]
    ambient_counts: Float[Array, "S Z"]
    interface_backscatter_per_m: Float[Array, ""]
    end_reflectance: Float[Array, ""]
    volume_backscatter_fraction: Float[Array, ""]
    multiple_scattering: Float[Array, ""]
    shadow_opacity: Float[Array, ""]
    near_field_m: Float[Array, ""]
    touch_xy_m: Float[Array, "N 2"]
    touch_radius_m: Float[Array, " N"]
    touch_strength: Float[Array, " N"]

    @classmethod
    def from_scene(cls, scene: Scene, dtype=jnp.float64) -> "Params":
        """The parameters a scene file states (defaults filled in)."""
        wg, sm = scene.waveguide, scene.sensor
        S, Z, _ = scene.shape
        el = scene.contact_elements()

        def f(v):
            return jnp.asarray(v, dtype)

        return cls(
            n1=f(wg.n1),
            mu_s_per_m=f(wg.mu_s_per_m),
            mu_a_per_m=f(wg.mu_a_per_m),
            gain=f(scene.gains()),
            pulse_sigma_s=f(sm.pulse_sigma_s),
            pulse_tail_s=f(sm.pulse_tail_s),
            emission_time_s=f(sm.emission_time),
            crosstalk_counts=jnp.full((S, Z), sm.crosstalk_counts, dtype),
            ambient_counts=jnp.full((S, Z), sm.ambient_counts, dtype),
            interface_backscatter_per_m=f(wg.interface_backscatter_per_m),
            end_reflectance=f(wg.end_reflectance),
            volume_backscatter_fraction=f(wg.volume_backscatter_fraction),
            multiple_scattering=f(wg.multiple_scattering),
            shadow_opacity=f(wg.shadow_opacity),
            near_field_m=f(wg.near_field),
            touch_xy_m=f(el[:, :2].reshape(-1, 2)),
            touch_radius_m=f(el[:, 2]),
            touch_strength=f(el[:, 3]),
        )

    @property
    def n_touches(self) -> int:
        return self.touch_strength.shape[0]

    def replace(self, **changes) -> "Params":
        """A copy with some fields changed (values are cast to this pytree's dtype)."""
        dtype = self.n1.dtype
        names = list(changes)
        return eqx.tree_at(
            lambda p: [getattr(p, n) for n in names],
            self,
            [jnp.asarray(changes[n], dtype) for n in names],
        )
