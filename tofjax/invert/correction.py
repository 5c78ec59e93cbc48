"""Time-resolved signal correction (seed 000, Algorithm 1), vectorised over frames, sensors, zones.

``beta_touch[b] = (P_r[b] - B[b]) / (K G(r_b) T(r_b))`` with ``r_b`` the one-way
range of bin ``b``. The variants seed 000 compares:

=========== ===========================
``raw``      ``P_r``
``decay``    ``P_r / (K G T)``
``baseline`` ``P_r - B``
``full``     ``(P_r - B) / (K G T)``
=========== ===========================

Beyond Algorithm 1:

* ``G`` and ``T`` are the forward model's own (:func:`tofjax.model.components.falloff` with the
  calibrated near-field shape ``p``, ``G = (r^p + d^p)^(-2/p)``, and
  :func:`~tofjax.model.components.transmittance`): the correction divides out exactly what the
  model puts in (:meth:`OpticalParams.log_decay`).
* The gain ``1 / (K G T)`` is computed in log space and capped
  (:attr:`CorrectionOptions.gain_cap`), so huge attenuation or far bins never overflow and
  noise is not amplified without bound.
* Bins that no contact can produce are masked to exactly zero in every variant: bins that
  end before the light enters the guide, and bins beyond the far edge of each zone (plus a
  margin for the instrument response).
* The range of a bin accounts for the delay of the instrument response's peak (its
  exponential tail shifts it); Eq. 8's ``d = t c1 / 2`` alone places every contact that
  much too far (about 1 cm on the default scene).
* ``K`` (per-sensor gain) is divided out, so corrected signals of different sensors share
  one unit: a contact's corrected signal summed over bins and zones equals its strength.

Frames with a NaN/inf or a saturated bin are flagged and give zeros; the rest are processed.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..config import ConfigError
from ..errors import UserError
from ..model.components import falloff, transmittance
from ..model.forward import OPTICS
from ..model.geometry import Geometry
from ..model.guided import launch_band
from ..model.params import speed_in_guide
from ..model.pulse import binned_response
from ..scene import Scene

__all__ = [
    "METHODS",
    "CorrectionOptions",
    "Corrector",
    "InversionError",
    "OpticalParams",
    "build_corrector",
    "check_compatible",
]

#: Correction variants (Algorithm 1 and the ablations seed 000 compares).
METHODS = ("raw", "decay", "baseline", "full")


class InversionError(UserError):
    """Inputs to the inversion do not fit together (scenes, shapes, calibration)."""


@dataclass(frozen=True)
class OpticalParams:
    """What the correction needs to know of the setup (SI units).

    Build it from a scene (:meth:`from_scene`) or from a calibration JSON
    (:meth:`from_calibration`, ``CalibrationResult.to_json`` format).
    """

    n1: float
    mu_s_per_m: float
    mu_a_per_m: float
    gain: tuple[float, ...]  # K per sensor, counts m^2
    emission_time_s: float
    pulse_sigma_s: float
    pulse_tail_s: float
    near_field_m: float
    source: str = "scene"
    # the second pulse tail of a two-tail calibration (share 0: one tail)
    pulse_slow_weight: float = 0.0
    pulse_slow_tail_s: float = 0.0
    # the forward model's optics the calibration was fitted with (FitConfig.optics): "default" or "guided"
    optics: str = "default"
    # the near field's shape p of the falloff G = (r^p + d^p)^(-2/p) (Params.near_field_shape):
    # 2 (seed 000's law, what a scene states) unless a calibration fitted another
    near_field_shape: float = 2.0

    def __post_init__(self):
        if self.optics not in OPTICS:
            raise InversionError(f"optics: must be {' or '.join(map(repr, OPTICS))}, got {self.optics!r}")
        if not 1.0 <= self.near_field_shape <= 1000.0:
            raise InversionError(f"near_field_shape: must be in [1, 1000], got {self.near_field_shape!r}")

    @classmethod
    def from_scene(cls, scene: Scene) -> "OpticalParams":
        wg, sm = scene.waveguide, scene.sensor
        return cls(
            n1=float(wg.n1),
            mu_s_per_m=float(wg.mu_s_per_m),
            mu_a_per_m=float(wg.mu_a_per_m),
            gain=tuple(float(g) for g in scene.gains()),
            emission_time_s=float(sm.emission_time),
            pulse_sigma_s=float(sm.pulse_sigma_s),
            pulse_tail_s=float(sm.pulse_tail_s),
            near_field_m=float(wg.near_field),
            source="scene",
        )

    @classmethod
    def from_params(cls, params, source: str = "params") -> "OpticalParams":
        """The optics in a :class:`tofjax.model.Params` (what a calibration gives)."""
        return cls(
            n1=float(params.n1),
            mu_s_per_m=float(params.mu_s_per_m),
            mu_a_per_m=float(params.mu_a_per_m),
            gain=tuple(float(g) for g in np.ravel(np.asarray(params.gain))),
            emission_time_s=float(params.emission_time_s),
            pulse_sigma_s=float(params.pulse_sigma_s),
            pulse_tail_s=float(params.pulse_tail_s),
            near_field_m=float(params.near_field_m),
            source=source,
            pulse_slow_weight=float(params.pulse_slow_weight),
            pulse_slow_tail_s=float(params.pulse_slow_tail_s),
            near_field_shape=float(params.near_field_shape),
        )

    @classmethod
    def from_calibration(
        cls,
        data: dict[str, Any] | str | Path,
        scene: Scene,
        *,
        allow_unconverged: bool = False,
        allow_other_scene: bool = False,
    ) -> "OpticalParams":
        """The optics of a calibration JSON (a dict, or a path), read by the one reader,
        :meth:`tofjax.fit.CalibrationResult.from_json`: an unconverged or refused calibration,
        one of another scene, or one with missing parameters is refused with one line."""
        from ..fit._result import CalibrationRefused, load_calibration

        from ..fit._result import calibration_optics

        source = "calibration" if isinstance(data, dict) else str(data)
        try:
            params = load_calibration(
                data, scene, allow_unconverged=allow_unconverged, allow_other_scene=allow_other_scene,
                optics=OPTICS,
            )
            optics = calibration_optics(data)
        except CalibrationRefused as e:
            raise InversionError(str(e)) from None
        return dataclasses.replace(cls.from_params(params, source), optics=optics)

    def replace(self, **changes) -> "OpticalParams":
        import dataclasses

        return dataclasses.replace(self, **changes)

    @property
    def c1(self) -> float:
        return float(speed_in_guide(self.n1))

    def range_speed(self, scene: Scene) -> float:
        """Twice the in-plane range over a return's delay: ``c1`` for the default optics. With the
        guided optics (:mod:`tofjax.model.guided`) light goes out at the launched beam's RMS cosine
        ``c_out`` and comes back, diffusely, at every guided elevation, ``c1 cos theta`` in the
        plane: ``2 c1 / (1/c_out + <1/cos theta>)``, with ``<1/cos theta> = 2 n1 / (n1 + 1)`` the
        mean over a Lambertian return across the guided band (on optoskin 8% slower than ``c1``;
        the guided model's contact peaks move 7% per metre more than ``2/c1``)."""
        if self.optics != "guided":
            return self.c1
        c_out = float(launch_band(float(self.n1), math.radians(scene.sensor.fov_deg))[2])  # the guided model's
        return 2.0 * self.c1 / (1.0 / c_out + 2.0 * self.n1 / (self.n1 + 1.0))

    def log_decay(self, r) -> np.ndarray:
        """``log(1 / (G(r) T(r)))`` at one-way ranges ``r`` (m; negative ranges count as 0): the
        forward model's own falloff (:func:`tofjax.model.components.falloff`, with this
        near-field shape) and round-trip transmittance
        (:func:`~tofjax.model.components.transmittance`), so the decay correction divides out
        exactly what the model puts in. ``+inf`` where ``T`` underflows (the caller caps it)."""
        rp = np.maximum(np.asarray(r, float), 0.0)
        g = falloff(rp, self.near_field_m, self.near_field_shape)
        t = transmittance(rp, self.mu_s_per_m + self.mu_a_per_m)
        return -np.asarray(jnp.log(g) + jnp.log(t), float)

    @property
    def pulse_tails(self) -> int:
        """2 where a calibration found a second, slow pulse tail."""
        return 2 if self.pulse_slow_weight > 0 and self.pulse_slow_tail_s > 0 else 1

    def binned_response(self, t, bin_width_s: float) -> np.ndarray:
        """The pulse (one or two tails) integrated over a bin centred ``t`` after a point event."""
        slow = (self.pulse_slow_weight, self.pulse_slow_tail_s) if self.pulse_tails == 2 else (0.0, None)
        return binned_response(np.asarray(t, float), bin_width_s, self.pulse_sigma_s, self.pulse_tail_s, *slow)

    def response_delay_s(self, bin_width_s: float) -> float:
        """Where a point event's binned response peaks, after the event: the mode of the
        pulse (one or two tails) integrated over one bin. A map's maximum sits at that
        mode, so this is the delay that puts it at the contact's range."""
        t = np.linspace(-3 * self.pulse_sigma_s, 6 * self.pulse_tail_s + 3 * self.pulse_sigma_s, 4001)
        return float(t[np.argmax(self.binned_response(t, bin_width_s))])


@dataclass(frozen=True)
class CorrectionOptions:
    """How to correct.

    - ``method``: ``raw``, ``decay``, ``baseline`` or ``full`` (Algorithm 1).
    - ``gain_cap``: the largest decay-correction gain ``1/(G T)``, relative to its value at
      zero range (``d^2``, ``d`` the near field, for every near-field shape). Default 1e5: never reached on the default scene (the far corner
      needs ~1.4e4), it bites only with extreme attenuation (seed 000's printed per-cm values).
    - ``mask``: zero the bins no contact can produce (before light entry, beyond the far edge).
    - ``edge_margin_bins``: bins kept beyond each zone's far edge (the response tail of a
      contact at the edge).
    - ``response_delay``: subtract the delay of the instrument response's peak (see
      :meth:`OpticalParams.response_delay_s`) when converting time to range.
    - ``ambient_tracking``: bins that end before the light enters (3 pulse widths early) see
      only ambient light; with baseline removal, their mean excess over the baseline is
      subtracted per frame, sensor and zone, so a change of ambient light since the baseline
      was taken does not masquerade as touch (decay correction would amplify it most at the
      far edge).
    """

    method: str = "full"
    gain_cap: float = 1e5
    mask: bool = True
    edge_margin_bins: float = 2.0
    response_delay: bool = True
    ambient_tracking: bool = True

    def __post_init__(self):
        if self.method not in METHODS:
            raise ConfigError(f"method: must be one of {', '.join(METHODS)}, got {self.method!r}")
        if not (self.gain_cap >= 1.0 and math.isfinite(self.gain_cap)):
            raise ConfigError(f"gain_cap: must be a finite number >= 1, got {self.gain_cap!r}")
        if self.edge_margin_bins < 0:
            raise ConfigError(f"edge_margin_bins: must be >= 0, got {self.edge_margin_bins!r}")


class Corrector(eqx.Module):
    """Precomputed correction for one scene: call it on histograms ``(..., S, Z, B)``.

    Returns ``(corrected, ok)``: corrected signals of the same shape (zeros for flagged
    frames and masked bins) and ``ok`` (...,) False where a frame had a NaN/inf or a
    saturated bin.
    """

    baseline: jax.Array  # (S, Z, B) mean baseline counts (zeros for raw/decay)
    gain: jax.Array  # (S, Z, B) exp(log gain) x mask (ones x mask for raw/baseline)
    log_gain: jax.Array  # (S, Z, B) uncapped-then-capped log of 1/(K G T), for inspection
    mask: jax.Array  # (S, Z, B) bool, True where a contact can be
    early: jax.Array  # (B,) weights of the ambient-only bins (sum 1), or zeros
    range_m: jax.Array  # (S, Z, B) one-way range of each bin centre
    method: str = eqx.field(static=True)
    saturation: float = eqx.field(static=True)

    def __call__(self, hist):
        hist = jnp.asarray(hist, self.gain.dtype)
        bad = ~jnp.isfinite(hist) | (hist >= self.saturation)
        ok = ~jnp.any(bad, axis=(-3, -2, -1))
        clean = jnp.where(bad, 0.0, hist)
        if self.method in ("baseline", "full"):
            signal = clean - self.baseline
            signal = signal - jnp.sum(signal * self.early, axis=-1, keepdims=True)
        else:
            signal = clean
        out = signal * self.gain
        return jnp.where(ok[..., None, None, None], out, 0.0), ok

    def replace_baseline(self, baseline) -> "Corrector":
        """The same correction against another baseline (the dynamic baseline uses it)."""
        return eqx.tree_at(lambda c: c.baseline, self, jnp.asarray(baseline, self.gain.dtype))


def bin_ranges(scene: Scene, optical: OpticalParams, response_delay: bool = True) -> np.ndarray:
    """One-way range (m) of each bin centre, (B,)."""
    sm = scene.sensor
    t = (np.arange(sm.n_bins) + 0.5) * sm.bin_width_s
    delay = optical.response_delay_s(sm.bin_width_s) if response_delay else 0.0
    return 0.5 * optical.range_speed(scene) * (t - optical.emission_time_s - delay)


def far_edges(scene: Scene, angles_per_zone: int = 16) -> np.ndarray:
    """Distance from each sensor to the far edge, per zone (largest over the zone's rays), (S, Z)."""
    g = Geometry.from_scene(scene, angles_per_zone, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    return np.asarray(g.ray_length).max(-1)


def build_corrector(
    scene: Scene,
    baseline: np.ndarray | None,
    optical: OpticalParams | None = None,
    options: CorrectionOptions = CorrectionOptions(),
    dtype=jnp.float32,
) -> Corrector:
    """The correction of ``scene``'s histograms.

    **Arguments:**

    - ``scene``: geometry and sensor timing.
    - ``baseline``: mean no-touch histogram (S, Z, B); required by ``baseline`` and ``full``.
    - ``optical``: n1, mu_s, mu_a, K, ... (default: the scene's values).
    - ``options``: see :class:`CorrectionOptions`.
    - ``dtype``: float32 (fast; the benchmark quantifies its error) or float64.
    """
    optical = OpticalParams.from_scene(scene) if optical is None else optical
    S, Z, B = scene.shape
    if len(optical.gain) != S:
        raise InversionError(f"calibration has {len(optical.gain)} sensor gains, the scene {S} sensors")
    needs_baseline = options.method in ("baseline", "full")
    if needs_baseline:
        if baseline is None:
            raise InversionError(f"method {options.method!r} needs a baseline")
        baseline = np.asarray(baseline, float)
        if baseline.shape != (S, Z, B):
            raise InversionError(f"baseline shape {baseline.shape} does not match the scene's {(S, Z, B)}")
        if not np.isfinite(baseline).all():
            raise InversionError("baseline has NaN or inf bins")
    r = bin_ranges(scene, optical, options.response_delay)  # (B,)
    dr = 0.5 * optical.range_speed(scene) * scene.sensor.bin_width_s
    log_k = np.log(np.asarray(optical.gain, float))
    # log(1/(K G T)) = -log K + log(1/(G T)) (the model's G and T); capped relative to zero range
    log_decay = np.minimum(optical.log_decay(r), math.log(options.gain_cap) + float(optical.log_decay(0.0)))
    log_gain = -log_k[:, None, None] + np.broadcast_to(log_decay, (S, Z, B))
    if options.mask:
        edge = far_edges(scene)  # (S, Z)
        mask = (r[None, None, :] + 0.5 * dr > 0.0) & (
            r[None, None, :] - 0.5 * dr <= edge[..., None] + options.edge_margin_bins * dr
        )
    else:
        mask = np.ones((S, Z, B), bool)
    if options.method in ("decay", "full"):
        gain = np.where(mask, np.exp(log_gain), 0.0)
    else:
        gain = mask.astype(float)
    base = baseline if needs_baseline else np.zeros((S, Z, B))
    sm = scene.sensor
    early = (np.arange(1, B + 1) * sm.bin_width_s < optical.emission_time_s - 3.0 * optical.pulse_sigma_s).astype(float)
    early = early / early.sum() if options.ambient_tracking and early.sum() >= 3 else np.zeros(B)
    return Corrector(
        baseline=jnp.asarray(base, dtype),
        gain=jnp.asarray(gain, dtype),
        log_gain=jnp.asarray(log_gain, dtype),
        mask=jnp.asarray(mask),
        early=jnp.asarray(early, dtype),
        range_m=jnp.asarray(np.broadcast_to(r, (S, Z, B)), dtype),
        method=options.method,
        saturation=float(scene.sensor.saturation_counts),
    )


def check_compatible(touch_scene: Scene, baseline_scene: Scene, what: str = "baseline", other: str = "touch capture") -> None:
    """Raise :class:`InversionError` (one line) unless both captures come from the same setup.

    Contacts may differ (that is the point); waveguide, sensor model and placement may not.
    """
    if touch_scene.shape != baseline_scene.shape:
        raise InversionError(
            f"{what} histograms have shape {baseline_scene.shape} (sensors, zones, bins), the {other} "
            f"{touch_scene.shape}: not the same setup"
        )
    a, b = touch_scene.without_touches(), baseline_scene.without_touches()
    for name in ("waveguide", "sensor", "sensors"):
        if getattr(a, name) != getattr(b, name):
            raise InversionError(
                f"{what} and {other} come from different scenes ('{baseline_scene.name}' vs "
                f"'{touch_scene.name}': their {name} differ)"
            )


def warn_no_calibration(scene: Scene) -> None:
    warnings.warn(
        f"no calibration given: using the scene's stated optics for '{scene.name}' (n1, mu_s, mu_a, gain); "
        "pass --calibration calib.json from `tofjax calibrate` for a real device",
        stacklevel=2,
    )
