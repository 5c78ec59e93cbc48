"""Physical parameters of the forward model, as one pytree of named fields.

Everything the model is differentiable in lives here, in SI units. Fitting
code (calibration) transforms these to an unconstrained space and back;
the forward model only ever sees physical values.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..errors import UserError
from ..scene import Scene

__all__ = ["Params", "ParamsError", "SPEED_OF_LIGHT_M_PER_S", "speed_in_guide"]

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0


def speed_in_guide(n1):
    """Speed of light in the waveguide, ``c / n1`` (m/s): the one place it is computed (the
    model's components, the inversion's time-to-range conversion and the fit's timing start
    all call this). Works on floats, NumPy and JAX values alike."""
    return SPEED_OF_LIGHT_M_PER_S / n1


class ParamsError(UserError):
    """Parameters the forward model cannot evaluate (NaN, out of range, inconsistent shapes)."""


# (field, lowest, highest, lowest allowed?) -- the physical ranges of Eq. 2-5; the same as
# the scene file's (tofjax.scene), so a Params a scene could not state is refused too.
_RANGES = (
    ("n1", 1.0, np.inf, False),
    ("mu_s_per_m", 0.0, np.inf, True),
    ("mu_a_per_m", 0.0, np.inf, True),
    ("gain", 0.0, np.inf, True),
    ("pulse_sigma_s", 0.0, np.inf, False),
    ("pulse_tail_s", 0.0, np.inf, False),
    ("pulse_slow_weight", 0.0, 1.0, True),
    ("pulse_slow_tail_s", 0.0, np.inf, False),
    ("emission_time_s", -np.inf, np.inf, True),
    ("crosstalk_counts", 0.0, np.inf, True),
    ("crosstalk_width_s", 0.0, np.inf, True),
    ("ambient_counts", 0.0, np.inf, True),
    ("interface_backscatter_per_m", 0.0, np.inf, True),
    ("end_reflectance", 0.0, 1.0, True),
    ("end_incidence_power", -1.0, 20.0, True),
    ("volume_backscatter_fraction", 0.0, 1.0, True),
    ("multiple_scattering", 0.0, np.inf, True),
    ("shadow_opacity", 0.0, 1.0, True),
    ("near_field_m", 0.0, np.inf, False),
    ("near_field_shape", 1.0, 1000.0, True),
    ("touch_xy_m", -np.inf, np.inf, True),
    ("touch_radius_m", 0.0, np.inf, False),
    ("touch_strength", 0.0, np.inf, True),
)


def _concrete(x):
    """``x`` as a NumPy array, or None while tracing (or for a placeholder that is not an array)."""
    if isinstance(x, jax.core.Tracer) or not isinstance(x, (jax.Array, np.ndarray, float, int, np.number)):
        return None
    return np.asarray(x)


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
    # the second, slower tail of a two-tail pulse (ModelOptions.pulse_tails = 2): a share
    # ``pulse_slow_weight`` of each return decays with ``pulse_slow_tail_s`` instead
    pulse_slow_weight: Float[Array, ""]
    pulse_slow_tail_s: Float[Array, ""]
    emission_time_s: Float[Array, ""]
    crosstalk_counts: Float[Array, "S Z"]
    # spread in time of the light-entry peak itself (s, a Gaussian's standard deviation) before
    # the sensor's response: light that reaches the detector without crossing the guide takes
    # paths of different lengths (cover window, package, the guide's entry face); 0: a point at
    # the emission time (the scene's model). The peak's pulse has sigma sqrt(sigma^2 + width^2).
    crosstalk_width_s: Float[Array, ""]
    ambient_counts: Float[Array, "S Z"]
    interface_backscatter_per_m: Float[Array, ""]
    end_reflectance: Float[Array, ""]
    # incidence-angle law of the edge's return: R(theta) = end_reflectance * cos(theta)^p
    # (theta the angle between the ray and the edge's normal; 0: one value for every angle,
    # 1: a diffuse (Lambertian) edge seen in the plane; see docs/physics.md)
    end_incidence_power: Float[Array, ""]
    volume_backscatter_fraction: Float[Array, ""]
    multiple_scattering: Float[Array, ""]
    shadow_opacity: Float[Array, ""]
    near_field_m: Float[Array, ""]
    # the near field's shape p: G(r) = (r^p + d^p)^(-2/p), d = near_field_m. 2: 1/(r^2 + d^2)
    # (seed 000's law, what a scene states); 1: 1/(r + d)^2; large p: 1/max(r, d)^2. A rig's
    # near field is not known a priori: calibration fits p (docs/physics.md, "Near field")
    near_field_shape: Float[Array, ""]
    touch_xy_m: Float[Array, "N 2"]
    touch_radius_m: Float[Array, " N"]
    touch_strength: Float[Array, " N"]

    def __check_init__(self):
        self.validate()

    def validate(self, names=None) -> "Params":
        """Raise :class:`ParamsError` (one line naming the field) if a concrete value is out of range.

        Skipped for traced values (inside ``jit``/``grad``): the check is for what a user passes in.
        ``names``: check only these fields (and the shape rules they take part in); :meth:`replace`
        checks what it changed, the rest having been checked when it was made (no need to read
        every field back to the host: on an accelerator, one transfer each).
        """
        vals: dict = {}

        def get(name):
            if name not in vals:
                vals[name] = _concrete(getattr(self, name))
            return vals[name]

        for name, lo, hi, lo_ok in _RANGES:
            if names is not None and name not in names:
                continue
            v = get(name)
            if v is None or v.size == 0:
                continue
            if not np.issubdtype(v.dtype, np.number):
                raise ParamsError(f"Params.{name}: expected numbers, got dtype {v.dtype}")
            if not np.isfinite(v).all():
                raise ParamsError(f"Params.{name}: must be finite, got {v.ravel()[~np.isfinite(v.ravel())][0].item()!r}")
            bad = (v < lo) | (v > hi) | ((v == lo) & (not lo_ok))
            if bad.any():
                rng = f"{'[' if lo_ok else '('}{lo:g}, {hi:g}]"
                raise ParamsError(f"Params.{name}: must be in {rng}, got {v.ravel()[bad.ravel()][0].item()!r}")
        touch = ("touch_xy_m", "touch_radius_m", "touch_strength")
        if names is None or any(n in names for n in touch):
            xy, r, st = (get(n) for n in touch)
        else:
            xy = r = st = None
        if xy is not None and r is not None and st is not None:
            if xy.ndim != 2 or xy.shape[1] != 2 or r.shape != (xy.shape[0],) or st.shape != (xy.shape[0],):
                raise ParamsError(
                    f"Params: touch_xy_m {xy.shape}, touch_radius_m {r.shape} and touch_strength {st.shape} "
                    "must be (N, 2), (N,) and (N,)"
                )
        if names is None or "crosstalk_counts" in names or "ambient_counts" in names:
            ct, amb = get("crosstalk_counts"), get("ambient_counts")
        else:
            ct = amb = None
        if ct is not None and amb is not None and ct.shape != amb.shape:
            raise ParamsError(f"Params: crosstalk_counts {ct.shape} and ambient_counts {amb.shape} differ in shape")
        return self

    @classmethod
    def from_scene(cls, scene: Scene, dtype=jnp.float64) -> "Params":
        """The parameters a scene file states (defaults filled in)."""
        wg, sm = scene.waveguide, scene.sensor
        S, Z, _ = scene.shape
        el = scene.contact_elements()

        def f(v):
            # a transfer, not jnp.asarray(python float, dtype): that compiles a small program in every new process
            return jax.device_put(np.asarray(v, dtype))

        return cls(
            n1=f(wg.n1),
            mu_s_per_m=f(wg.mu_s_per_m),
            mu_a_per_m=f(wg.mu_a_per_m),
            gain=f(scene.gains()),
            pulse_sigma_s=f(sm.pulse_sigma_s),
            pulse_tail_s=f(sm.pulse_tail_s),
            # a scene states one tail; the slow one starts switched off, 4x the fast one
            pulse_slow_weight=f(0.0),
            pulse_slow_tail_s=f(4.0 * sm.pulse_tail_s),
            emission_time_s=f(sm.emission_time),
            crosstalk_counts=jax.device_put(np.full((S, Z), sm.crosstalk_counts, dtype)),
            # a scene states a point-like light-entry peak
            crosstalk_width_s=f(0.0),
            ambient_counts=jax.device_put(np.full((S, Z), sm.ambient_counts, dtype)),
            interface_backscatter_per_m=f(wg.interface_backscatter_per_m),
            end_reflectance=f(wg.end_reflectance),
            # a scene states one reflectance for every angle of incidence
            end_incidence_power=f(0.0),
            volume_backscatter_fraction=f(wg.volume_backscatter_fraction),
            multiple_scattering=f(wg.multiple_scattering),
            shadow_opacity=f(wg.shadow_opacity),
            near_field_m=f(wg.near_field),
            # a scene states seed 000's law 1/(r^2 + d^2)
            near_field_shape=f(2.0),
            touch_xy_m=f(el[:, :2].reshape(-1, 2)),
            touch_radius_m=f(el[:, 2]),
            touch_strength=f(el[:, 3]),
        )

    @property
    def c1(self):
        """Speed of light in the waveguide, m/s (:func:`speed_in_guide`)."""
        return speed_in_guide(self.n1)

    @property
    def n_touches(self) -> int:
        return self.touch_strength.shape[0]

    def replace(self, **changes) -> "Params":
        """A copy with some fields changed (values are cast to this pytree's dtype)."""
        dtype = self.n1.dtype
        names = list(changes)
        unknown = [n for n in names if n not in self.__dataclass_fields__]
        if unknown:
            raise ParamsError(f"Params.replace: unknown field {unknown[0]!r}")
        out = eqx.tree_at(
            lambda p: [getattr(p, n) for n in names],
            self,
            [jnp.asarray(changes[n], dtype) for n in names],
        )
        return out.validate(names)
