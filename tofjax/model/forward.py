"""The forward model: scene -> expected histograms, composed from what the scene needs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from ..config import ConfigError
from ..jvp import dense_jvp
from ..scene import COMPONENTS, Scene
from . import components as C
from .geometry import Geometry, ray_samples
from .params import Params
from .pulse import apply_kernels, bin_kernels

__all__ = ["OPTICS", "ForwardModel", "ModelOptions", "build_model", "pile_up"]


#: The forward model's optics (``ModelOptions.optics``): seed 000's in-plane light, or the
#: guided optics of :mod:`tofjax.model.guided`. Calibrations record which (``FitConfig.optics``).
OPTICS = ("default", "guided")


@dataclass(frozen=True)
class ModelOptions:
    """Fidelity settings: accuracy against speed. Defaults are the benchmarked sweet spot.

    **Arguments:**

    - ``quadrature``: time nodes per bin (the bin-integration order). Errors fall
      as ``1/quadrature^2``.
    - ``angles_per_zone``: rays per zone for the far-edge distance and range truncation.
    - ``touch_samples``: range samples across each contact disk.
    - ``pulse_tails``: 1 (an exponentially modified Gaussian, the default) or 2 (a second,
      slower tail: ``Params.pulse_slow_weight``, ``Params.pulse_slow_tail_s``).
    - ``dtype``: ``"float64"`` (needs ``jax_enable_x64``, see :func:`tofjax.enable_x64`) or ``"float32"``.
    - ``optics``: ``"default"`` (seed 000's Eq. 4-5: in-plane light at ``c / n1``, ``1/r^2``) or
      ``"guided"`` (:mod:`tofjax.model.guided`: elevations inside the slab, ``1/r`` slab
      backscatter, the aperture, Lambertian edge, absolute amplitudes; about 1.5x the cost).
    - ``elevations``: guided optics only: quadrature nodes over the guided elevation band.
    - ``aperture_m``: guided optics only: the receiver window's width on the edge.
    - ``skin``: guided optics only: a :class:`~tofjax.model.contact.SkinContact`; touch and
      shadow amplitudes then follow from it (``touch_strength`` scales its coupling, as in the
      Monte Carlo) instead of the free strength and opacity.
    """

    quadrature: int = 2
    angles_per_zone: int = 8
    touch_samples: int = 5
    dtype: str = "float64"
    optics: str = "default"
    elevations: int = 8
    aperture_m: float = 1e-3
    skin: Any = None
    pulse_tails: int = 1

    def __post_init__(self):
        for k in ("quadrature", "angles_per_zone", "touch_samples", "elevations"):
            if int(getattr(self, k)) < 1:
                raise ConfigError(f"{k}: must be >= 1, got {getattr(self, k)!r}")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"dtype: must be float32 or float64, got {self.dtype!r}")
        if self.optics not in OPTICS:
            raise ConfigError(f"optics: must be {' or '.join(map(repr, OPTICS))}, got {self.optics!r}")
        if not isinstance(self.aperture_m, (int, float)) or not (0.0 < float(self.aperture_m) < float("inf")):
            raise ConfigError(f"aperture_m: must be a positive length in metres, got {self.aperture_m!r}")
        if self.skin is not None:
            from .contact import SkinContact

            if not isinstance(self.skin, SkinContact):
                raise ConfigError(f"skin: expected a SkinContact or None, got {type(self.skin).__name__}")
            if self.optics != "guided":
                raise ConfigError("skin: only with optics='guided' (the default optics keep the free touch strength)")
        if self.pulse_tails not in (1, 2):
            raise ConfigError(f"pulse_tails: must be 1 or 2, got {self.pulse_tails!r}")

    @property
    def jnp_dtype(self):
        if self.dtype == "float64" and not jax.config.jax_enable_x64:
            raise ConfigError(
                "dtype: float64 requested but JAX runs in 32-bit mode; call tofjax.enable_x64() "
                "at your entry point or use ModelOptions(dtype='float32')"
            )
        return jnp.float64 if self.dtype == "float64" else jnp.float32


#: The scalar parameters the distributed terms' node densities depend on (:meth:`ForwardModel._node_terms`).
NODE_SCALARS = ("n1", "emission_time_s", "near_field_m", "near_field_shape", "mu_s_per_m", "mu_a_per_m",
                "interface_backscatter_per_m", "volume_backscatter_fraction", "multiple_scattering")


class _Context(NamedTuple):
    params: Params
    geom: Geometry
    nodes: C.Nodes
    range: Any  # (K,) one-way range at the nodes, clipped at 0
    falloff: Any  # (K,) G integrated over each node's range
    transmittance: Any  # (K,) T(r)
    end_times: Any  # (S, Z, A) arrival time of each ray's far-edge reflection
    contacts: Any  # ContactGeometry or None
    shadowing: bool
    touch_samples: int
    edge_cos: Any = None  # (S, Z, A) |cos| of each ray's incidence on the edge it hits (None: not known)


def pile_up(expected, iterations):
    """SPAD pile-up (Coates): a detector that fired is blind for the rest of that laser pulse.

    With ``mu_b = expected_b / iterations`` photons per pulse in bin ``b``, the
    observed mean is ``iterations exp(-sum_{j<b} mu_j) (1 - exp(-mu_b))``:
    identical at low rates, compressed and skewed early at high rates.
    """
    mu = expected / iterations
    before = jnp.cumsum(mu, axis=-1) - mu
    return iterations * jnp.exp(-before) * -jnp.expm1(-mu)


class ForwardModel(eqx.Module):
    """``model(params) -> (sensors, zones, bins)`` expected counts for one scene.

    Only the components named in ``components`` are traced: a component the
    scene does not need costs nothing. Build it with :func:`build_model`.
    """

    geometry: Geometry
    components: tuple[str, ...] = eqx.field(static=True)
    options: ModelOptions = eqx.field(static=True)
    bin_width_s: float = eqx.field(static=True)
    n_bins: int = eqx.field(static=True)
    iterations: int = eqx.field(static=True)
    pile_up: bool = eqx.field(static=True)
    guided: Any = None  # GuidedGeometry with optics="guided" (tofjax.model.guided)
    # (S, Z, A) |cos| of each ray's incidence on the edge it hits, for the edge's angle law
    # (Params.end_incidence_power); None: the law is not applied (a model built without it)
    edge_cos: Any = None

    @property
    def shape(self) -> tuple[int, int, int]:
        S, Z, _ = self.geometry.ray_length.shape
        return (S, Z, self.n_bins)

    def _node_grid(self, params: Params):
        """The time nodes, their one-way range clipped at 0 and the round-trip transmittance there."""
        nodes = C.make_nodes(params, self.bin_width_s, self.n_bins, self.options.quadrature)
        r = jnp.maximum(nodes.r, 0.0)
        return nodes, r, C.transmittance(r, params.mu_s_per_m + params.mu_a_per_m)

    def _context(self, params: Params) -> _Context:
        nodes, r, trans = self._node_grid(params)
        wants_contacts = ("touch" in self.components or "shadowing" in self.components) and params.n_touches
        return _Context(
            params=params,
            geom=self.geometry,
            nodes=nodes,
            range=r,
            # the default optics' distributed terms replace this by node_falloff_after_emission
            # (with the near field's shape); the guided optics' interface term uses it, and the
            # guided optics have no near-field shape (p = 2, FitConfig refuses it free there)
            falloff=C.node_falloff(nodes, params.near_field_m),
            transmittance=trans,
            end_times=params.emission_time_s + 2.0 * self.geometry.ray_length / nodes.c1,
            contacts=C.contact_geometry(self.geometry, params) if wants_contacts else None,
            shadowing="shadowing" in self.components,
            touch_samples=self.options.touch_samples,
            edge_cos=self.edge_cos,
        )

    def _node_masses(self, params: Params, separate: bool = False, node_jvp: bool = False) -> dict[str, jax.Array]:
        """Counts at the time nodes, before the pulse: summed, or per component with ``separate``.
        ``node_jvp``: the distributed terms' node densities with their forward derivative as a matrix
        product (:meth:`_node_terms`; for forward-mode Jacobians, same values)."""
        ctx = self._context(params)
        if self.guided is not None:
            from .guided import guided_node_masses

            return guided_node_masses(ctx, self.guided, self.components, separate)
        # Shadowing acts on what lies behind a contact; without it contacts only add light.
        shadow_ctx = ctx if ctx.shadowing else ctx._replace(contacts=None)
        out = {}
        dist = tuple(n for n in self.components if n in C.DISTRIBUTED)
        if dist:
            nodes = ctx.nodes
            ended = C.step_on(ctx.end_times, nodes)  # rays past their far edge
            coverage = params.gain[:, None, None] * jnp.clip(1.0 - ended, 0.0, 1.0)
            if shadow_ctx.contacts is not None:
                coverage = coverage * C.shadow(jnp.broadcast_to(ctx.range, coverage.shape), ctx.contacts, params)
            densities, offset = (self._node_terms if node_jvp else self._node_terms_direct)(params, dist)
            if separate:
                out.update({n: C.smooth_like_deposit(coverage * d, offset) for n, d in densities.items()})
            else:
                out["distributed"] = C.smooth_like_deposit(coverage * sum(densities.values()), offset)
        for name in self.components:
            if name == "touch" and params.n_touches:
                out[name] = C.touch(ctx)
            elif name in ("crosstalk", "end"):
                out[name] = C.POINT[name](shadow_ctx)
        return out

    def _node_terms_direct(self, params: Params, names: tuple[str, ...]):
        """The distributed terms' densities at the nodes and where in its node each node's mass
        sits: ``({name: (K,)}, NodeSpread)``, functions of the scalar parameters alone (G over the
        part of each node after emission, exactly, and where in the node that mass sits: the near
        field is about one node deep, its timing is the emission time's)."""
        nodes, r, trans = self._node_grid(params)
        fall, offset = C.node_falloff_after_emission(nodes, params.near_field_m, params.near_field_shape)
        ctx = _Context(params=params, geom=None, nodes=nodes, range=r, falloff=fall, transmittance=trans, end_times=None,
                       contacts=None, shadowing=False, touch_samples=self.options.touch_samples)
        return {n: C.DISTRIBUTED[n](ctx) for n in names}, offset

    def _node_terms(self, params: Params, names: tuple[str, ...]):
        """:meth:`_node_terms_direct` with its forward-mode derivative as a matrix product.

        The terms are (K,) arrays of a few scalar parameters (:data:`NODE_SCALARS`); the masses
        multiply them by (S, Z, K) arrays. Differentiated directly, XLA fuses the (K,) tangents'
        long expressions (the near field's integrals and moments) into the loop over the (S, Z, K)
        product and computes them again for every sensor and zone: on the default scene the
        masses' Jacobian by the fit's 9 model coordinates took 10 ms, 20x their value. Here the
        derivative is ``J @ dx``, ``J`` the (K, scalars) Jacobian computed once: the product is a
        separate kernel, so the tangents are materialised before they meet the sensors and zones.
        The same computation (values equal to rounding: fused apart); derivatives equal to rounding
        (tested).

        Opt-in (``node_jvp=True``), taken by the calibration's structured Jacobian
        (:func:`tofjax.fit._problem._parts_jvp`), the one forward-mode Jacobian by these scalars.
        Reverse mode through it computes ``J`` (a forward pass per scalar) where the direct
        derivative needs one backward pass: the masses' value and gradient by four scalars took
        1.2x as long, their forward Jacobian by the same four 0.25x
        (``experiments/node_terms_jvp.py``, ``docs/results/node_terms_jvp_modes.json``); elsewhere
        the scalars' tangents are mostly zero and ``J`` would be computed for nothing."""
        x = jnp.stack([jnp.asarray(getattr(params, k), params.n1.dtype) for k in NODE_SCALARS])

        def direct(x, params):  # the terms depend on ``params`` only through the scalars in ``x``
            return self._node_terms_direct(params.replace(**{k: x[i] for i, k in enumerate(NODE_SCALARS)}), names)

        return dense_jvp(direct)(x, params)

    def _apply_pulse(self, masses, params: Params, extra_width=None):
        """The instrument response applied to node masses; ``extra_width``: a Gaussian spread
        of the events themselves (s), added in quadrature to the pulse's Gaussian rise (a
        Gaussian convolved with an ex-Gaussian is an ex-Gaussian)."""
        return apply_kernels(masses, self.pulse_kernels(params, extra_width), self.n_bins, self.options.quadrature)

    def pulse_kernels(self, params: Params, extra_width=None) -> jax.Array:
        """The bin-integrated pulse per node phase (:func:`~tofjax.model.pulse.bin_kernels`):
        a function of the pulse parameters (and ``extra_width``) only."""
        q = self.options.quadrature
        slow = (params.pulse_slow_weight, params.pulse_slow_tail_s) if self.options.pulse_tails == 2 else (None, None)
        sigma = params.pulse_sigma_s
        if extra_width is not None:
            sigma = jnp.sqrt(sigma**2 + extra_width**2)
        return bin_kernels(self.bin_width_s / q, self.n_bins, q, sigma, params.pulse_tail_s, params.n1.dtype, *slow)

    def light_entry_peak(self, params: Params) -> jax.Array:
        """The light-entry (crosstalk) peak of unit size in every zone, (bins,): a point at the
        emission time spread by ``Params.crosstalk_width_s`` (a Gaussian) and the pulse. With
        zero width it is the pulse alone, exactly what depositing the peak with the other
        components gives (the model is linear in the node masses)."""
        nodes = C.make_nodes(params, self.bin_width_s, self.n_bins, self.options.quadrature)
        dtype = params.n1.dtype
        unit = C.deposit(jnp.reshape(params.emission_time_s, (1, 1, 1)), jnp.ones((1, 1, 1), dtype), nodes)
        return self._apply_pulse(unit, params, extra_width=params.crosstalk_width_s)[0, 0]

    def _crosstalk(self, params: Params, counts=None) -> jax.Array:
        """The light-entry peaks (S, Z, B) at ``counts`` (default ``params.crosstalk_counts``)."""
        counts = params.crosstalk_counts if counts is None else counts
        return counts[..., None] * self.light_entry_peak(params)

    def _finish(self, binned, params: Params):
        if "ambient" in self.components:
            binned = binned + params.ambient_counts[..., None]
        if self.pile_up:
            binned = pile_up(binned, self.iterations)
        return binned

    def __call__(self, params: Params) -> jax.Array:
        # compiled: called eagerly (outside any jit) the model dispatches thousands of small
        # operations, 3-4x slower than compiling it once (inside a transformation it is
        # inlined). Python numbers in ``params`` become arrays first, so a new value is not a
        # new program. The guided optics' module switches are read when the model is traced:
        # they are part of the compiled program's key, so changing one retraces.
        return self._compiled(jax.tree_util.tree_map(jnp.asarray, params), _trace_switches())

    @eqx.filter_jit
    def _compiled(self, params: Params, switches: tuple) -> jax.Array:
        del switches  # only a key of the compiled program (see __call__)
        masses = self._node_masses(params)
        # the light-entry peak has a width of its own (Params.crosstalk_width_s): its pulse differs
        cross = masses.pop("crosstalk", None)
        S, Z, B = self.shape
        total = sum(masses.values()) if masses else jnp.zeros((S, Z, B * self.options.quadrature), params.n1.dtype)
        binned = self._apply_pulse(total, params)
        if cross is not None:
            binned = binned + self._crosstalk(params)
        return self._finish(binned, params)

    def linear_parts(self, params: Params, separate_end: bool = False) -> tuple[jax.Array, ...]:
        """The model as ``gain[s] * R + crosstalk[s, z] * P + ambient[s, z]`` (no pile-up):
        returns ``R`` (everything proportional to K, at unit gain) and ``P`` (the light-entry
        peak of unit size), both (sensors, zones, bins). Calibration profiles the linear
        parameters out with these. With ``separate_end``: ``(R - E, P, E)``, ``E`` the far-edge
        return at unit gain and unit reflectance (so it can be scaled per zone)."""
        S, Z, B = self.shape
        stack, has_cross = self.linear_masses(params, separate_end)
        binned = self._apply_pulse(stack, params)
        # the light-entry peak: its own width (Params.crosstalk_width_s), the same shape in every zone
        cross = self._crosstalk(self._unit(params)) if has_cross else jnp.zeros((S, Z, B), binned.dtype)
        return (binned[0], cross) + tuple(binned[i] for i in range(1, stack.shape[0]))

    def _unit(self, params: Params) -> Params:
        return params.replace(gain=jnp.ones_like(params.gain), crosstalk_counts=jnp.ones_like(params.crosstalk_counts))

    def linear_masses(self, params: Params, separate_end: bool = False, node_jvp: bool = False) -> tuple[jax.Array, bool]:
        """The node masses behind :meth:`linear_parts`, before the pulse: ``(stack, has_cross)``,
        ``stack`` (1 or 2, S, Z, K) (``R`` and, with ``separate_end``, ``E``) and whether the
        scene has the light-entry peak. Pieces of :meth:`linear_parts` so a calibration can
        differentiate each by only the parameters it depends on (the masses do not depend on
        the pulse, the pulse kernels on nothing else)."""
        if self.pile_up:
            raise ValueError("with pile-up the model is not linear in gain, crosstalk and ambient")
        S, Z, B = self.shape
        unit = self._unit(params)
        if separate_end:
            unit = unit.replace(end_reflectance=1.0)
        masses = self._node_masses(unit, node_jvp=node_jvp)
        zero = jnp.zeros((S, Z, B * self.options.quadrature), params.n1.dtype)
        has_cross = masses.pop("crosstalk", None) is not None
        parts = []
        if separate_end:
            parts.append(masses.pop("end", zero))
        rest = sum(masses.values()) if masses else zero
        return jnp.stack([rest] + parts), has_cross

    def breakdown(self, params: Params) -> dict[str, jax.Array]:
        """Each component's contribution in counts per bin (before pile-up), for plots and pruning.
        Compiled like :meth:`__call__` (eager, the demo's four breakdowns took 55 s on a loaded VM)."""
        return self._breakdown(jax.tree_util.tree_map(jnp.asarray, params), _trace_switches())

    @eqx.filter_jit
    def _breakdown(self, params: Params, switches: tuple) -> dict[str, jax.Array]:
        del switches  # only a key of the compiled program (see __call__)
        out = {k: self._crosstalk(params) if k == "crosstalk" else self._apply_pulse(v, params)
               for k, v in self._node_masses(params, separate=True).items()}
        if "ambient" in self.components:
            out["ambient"] = jnp.broadcast_to(params.ambient_counts[..., None], self.shape)
        return out


def _trace_switches() -> tuple:
    """The module-level switches of :mod:`tofjax.model.guided` that tracing reads (``guided.SWITCH_NAMES``)."""
    from . import guided

    return tuple(getattr(guided, k) for k in guided.SWITCH_NAMES)


def build_model(
    scene: Scene,
    options: ModelOptions = ModelOptions(),
    components: tuple[str, ...] | None = None,
) -> ForwardModel:
    """The forward model of ``scene`` at the fidelity ``options``.

    **Arguments:**

    - ``scene``: the scene (geometry, sensor, which components it requires).
    - ``options``: fidelity (see :class:`ModelOptions`).
    - ``components``: override the scene's component list (e.g. a pruned model).

    **Returns:** a :class:`ForwardModel`; call it on :class:`Params` (``Params.from_scene(scene)``).
    """
    comps = scene.components() if components is None else tuple(components)
    for c in comps:
        if c not in COMPONENTS:
            raise ConfigError(f"components: unknown component {c!r}; known: {', '.join(COMPONENTS)}")
    dtype = options.jnp_dtype
    geometry = Geometry.from_scene(scene, options.angles_per_zone, dtype)
    # NumPy from the scene, not from `geometry` (whose arrays are tracers where a model is built inside jit)
    xy, _, edges, ang = ray_samples(scene, options.angles_per_zone)
    guided = None
    if options.optics == "guided":
        from .guided import GuidedGeometry

        guided = GuidedGeometry.from_scene(scene, ang, edges[:, 0], edges[:, 1], options.elevations, options.aperture_m,
                                           options.skin, dtype,
                                           node_width_s=scene.sensor.bin_width_s / options.quadrature)
    edge_cos = C.edge_incidence_cos(scene.waveguide.size_m, xy[:, None, None, :], ang)
    return ForwardModel(
        geometry=geometry,
        guided=guided,
        edge_cos=jnp.asarray(edge_cos, dtype),
        components=tuple(c for c in COMPONENTS if c in comps),
        options=options,
        bin_width_s=float(scene.sensor.bin_width_s),
        n_bins=int(scene.sensor.n_bins),
        iterations=int(scene.sensor.iterations),
        pile_up=bool(scene.noise.pile_up),
    )
