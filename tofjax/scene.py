"""Scenes: what is physically there (waveguide, sensors, contacts), from TOML.

A scene file has the tables ``[waveguide]``, ``[sensor]`` (shared by every
sensor), ``[[sensors]]`` (one per sensor on the edge) and optionally
``[[touches]]``, ``[noise]`` and ``[model]``. Keys carry SI units in their
names. Every key beyond the minimal set has a default, so a scene written with
only the keys of ``docs/scene-format.md``'s first example is complete.

Loading validates everything and raises :class:`~tofjax.config.ConfigError`
with a one-line message naming the key and the reason.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from .config import ConfigError, from_dict, load_toml, to_dict, toml_value

__all__ = [
    "COMPONENTS",
    "FreeSpaceTarget",
    "ModelSpec",
    "Noise",
    "Scene",
    "SensorModel",
    "SensorPlacement",
    "Touch",
    "Waveguide",
    "default_scene",
    "load_scene",
    "scene_from_dict",
    "scene_from_json",
]

#: Every component the forward model knows, in the order they are summed.
COMPONENTS = (
    "crosstalk",  # light-entry peak: light going straight from emitter to detector
    "interface",  # backscatter from interface roughness, spread along the range
    "volume",  # single backscatter from the scattering medium, proportional to mu_s
    "end",  # reflection at the far edge of the waveguide along each zone's rays
    "multiple_scattering",  # late diffuse light that scattered more than once
    "touch",  # contacts frustrating total internal reflection
    "shadowing",  # light scattered out at a contact no longer reaches what lies behind
    "ambient",  # constant background counts per bin
)

_EDGE_TOL_M = 1e-6

# Size caps from the hardware family (a TMF8828 histogram has 128 bins; its largest mode has
# 64 zones; a rig is at most 8 muxes of 8 sensors). Beyond them a scene cannot describe a
# real setup, and the model's arrays would not fit in memory (issue 15).
MAX_BINS = 128
MAX_ZONES = 64
MAX_SENSORS = 64
MAX_TOUCHES = 256
#: Disks one stick or ring contact is modelled with.
MAX_ELEMENTS = 4096
#: Laser pulses per histogram (the TMF8828 takes up to about 4 million; 2**24 counts per bin).
MAX_ITERATIONS = 2**24


def _positive(value: float, key: str, *, strict: bool = True) -> None:
    if (value <= 0) if strict else (value < 0):
        raise ConfigError(f"{key}: must be {'> 0' if strict else '>= 0'}, got {value!r}")


@dataclass(frozen=True)
class Waveguide:
    """The slab: a ``size_m[0] x size_m[1]`` rectangle of thickness ``thickness_m``, origin at a corner.

    ``mu_s_per_m`` and ``mu_a_per_m`` are the *effective* scattering and
    absorption coefficients along guided paths (see ``docs/physics.md`` for why
    they can be far below bulk values).
    """

    size_m: tuple[float, float]
    thickness_m: float
    n1: float
    mu_s_per_m: float
    mu_a_per_m: float
    #: Backscatter per metre of range from interface roughness (beta_int).
    interface_backscatter_per_m: float = 0.1
    #: Fraction of the edge-reaching light reflected straight back (the end peak).
    end_reflectance: float = 0.5
    #: Fraction of volume-scattered light that returns inside the sensor's acceptance.
    volume_backscatter_fraction: float = 0.05
    #: Coupling of multiply-scattered light back to the sensor (dimensionless). The guided optics derive the
    #: coupling from the geometry and read this relative to its default (0.5: the derived value; 0: none).
    multiple_scattering: float = 0.5
    #: Fraction of a zone's light removed by a contact covering the whole zone.
    shadow_opacity: float = 0.5
    #: Range below which the 1/r^2 falloff saturates (the slab is not thin there); default: thickness.
    near_field_m: float | None = None

    def __post_init__(self):
        for i, s in enumerate(self.size_m):
            if s <= 0:
                raise ConfigError(f"size_m[{i}]: must be > 0, got {s!r}")
            if not 1e-3 <= s <= 1e3:
                raise ConfigError(f"size_m[{i}]: must be in [1 mm, 1 km] (a skin's side), got {s!r}")
        _positive(self.thickness_m, "thickness_m")
        if not 1e-6 <= self.thickness_m <= 1.0:
            # thinner than a few wavelengths of the 940 nm light is no ray-optics guide; the near field and the
            # Monte Carlo's steps are lengths of this order and fail on it (they named near_field_m before)
            raise ConfigError(f"thickness_m: must be in [1 um, 1 m], got {self.thickness_m!r}")
        if self.n1 <= 1.0:
            raise ConfigError(f"n1: must be > 1 for total internal reflection in air, got {self.n1!r}")
        if self.n1 > 4.0:  # no waveguide material; far beyond it the model's light never returns (all-zero captures)
            raise ConfigError(f"n1: must be <= 4 (no waveguide material refracts more), got {self.n1!r}")
        _positive(self.mu_s_per_m, "mu_s_per_m", strict=False)
        _positive(self.mu_a_per_m, "mu_a_per_m", strict=False)
        _positive(self.interface_backscatter_per_m, "interface_backscatter_per_m", strict=False)
        _positive(self.volume_backscatter_fraction, "volume_backscatter_fraction", strict=False)
        _positive(self.multiple_scattering, "multiple_scattering", strict=False)
        for key in ("end_reflectance", "shadow_opacity", "volume_backscatter_fraction"):
            v = getattr(self, key)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{key}: must be in [0, 1], got {v!r}")
        if self.near_field_m is not None:
            _positive(self.near_field_m, "near_field_m")
            if self.near_field_m > max(self.size_m):
                raise ConfigError(f"near_field_m: the 1/r^2 saturation range must be within the guide's size "
                                  f"({max(self.size_m):g} m), got {self.near_field_m!r}")

    @property
    def near_field(self) -> float:
        return self.thickness_m if self.near_field_m is None else self.near_field_m

    def contains(self, x: float, y: float, tol: float = 0.0) -> bool:
        return -tol <= x <= self.size_m[0] + tol and -tol <= y <= self.size_m[1] + tol


@dataclass(frozen=True)
class SensorModel:
    """What every sensor shares (a TMF8828 in a given mode).

    Timing: bin ``b`` covers ``[b, b + 1) * bin_width_s``; the laser fires at
    ``emission_time_s`` (the crosstalk peak; default 14.5 bins, as real parts
    show it near bin 14-15). The instrument response is an exponentially
    modified Gaussian: a sharp Gaussian rise of width ``pulse_sigma_s`` and an
    exponential tail of time constant ``pulse_tail_s``.
    """

    bin_width_s: float
    n_bins: int
    zones: int
    fov_deg: float
    pulse_sigma_s: float = 60e-12
    pulse_tail_s: float = 150e-12
    emission_time_s: float | None = None
    #: Counts·m^2 per unit backscatter (K of Eq. 3), the same for every sensor unless overridden.
    gain: float = 150.0
    #: Total counts in the light-entry (crosstalk) peak of each zone.
    crosstalk_counts: float = 3000.0
    #: Ambient counts per bin (N_a), after the sensor's optical filter.
    ambient_counts: float = 10.0
    #: Laser pulses summed into one histogram (sets SPAD pile-up).
    iterations: int = 250_000
    #: Largest count a bin can hold (24-bit on the TMF8828).
    saturation_counts: float = float(2**24 - 1)
    #: Two-dimensional zone grid (rows, cols) of a TMF882x in free space (3x3, 4x4, 8x8);
    #: ``rows * cols`` must equal ``zones``. None: the angular fan of zones along the waveguide.
    grid: tuple[int, int] | None = None
    #: A sensor model fitted by ``tofjax sensor fit`` (JSON path, relative to the working
    #: directory): its bin width, pulse, pile-up and zone offsets replace the nominal ones.
    model: str | None = None

    def __post_init__(self):
        _positive(self.bin_width_s, "bin_width_s")
        if not 1e-13 <= self.bin_width_s <= 1e-6:  # 0.1 ps to 1 us (a TMF8828's is ~250 ps)
            raise ConfigError(f"bin_width_s: must be in [1e-13, 1e-6] s, got {self.bin_width_s!r}")
        if not 2 <= self.n_bins <= MAX_BINS:
            raise ConfigError(f"n_bins: must be in [2, {MAX_BINS}] (a TMF8828 histogram), got {self.n_bins!r}")
        if not 1 <= self.zones <= MAX_ZONES:
            raise ConfigError(f"zones: must be in [1, {MAX_ZONES}] (a TMF8828's largest mode), got {self.zones!r}")
        if not 0.0 < self.fov_deg < 180.0:
            raise ConfigError(f"fov_deg: must be in (0, 180), got {self.fov_deg!r}")
        _positive(self.pulse_sigma_s, "pulse_sigma_s")
        _positive(self.pulse_tail_s, "pulse_tail_s")
        if self.emission_time_s is not None:
            if not 0.0 <= self.emission_time_s < self.n_bins * self.bin_width_s:
                raise ConfigError(
                    f"emission_time_s: must be inside the histogram [0, {self.n_bins * self.bin_width_s:g}) s, "
                    f"got {self.emission_time_s!r}"
                )
        _positive(self.gain, "gain", strict=False)
        _positive(self.crosstalk_counts, "crosstalk_counts", strict=False)
        _positive(self.ambient_counts, "ambient_counts", strict=False)
        if not 1 <= self.iterations <= MAX_ITERATIONS:
            raise ConfigError(f"iterations: must be in [1, {MAX_ITERATIONS}], got {self.iterations!r}")
        _positive(self.saturation_counts, "saturation_counts")
        if self.saturation_counts < 1:
            raise ConfigError(f"saturation_counts: must be >= 1 (a bin's largest count), got {self.saturation_counts!r}")
        if self.grid is not None:
            if min(self.grid) < 1 or self.grid[0] * self.grid[1] != self.zones:
                raise ConfigError(f"grid: {self.grid[0]} x {self.grid[1]} zones do not make zones = {self.zones}")

    @property
    def emission_time(self) -> float:
        return 14.5 * self.bin_width_s if self.emission_time_s is None else self.emission_time_s


@dataclass(frozen=True)
class SensorPlacement:
    """One sensor on the edge: where it sits and where its optical axis points (CCW from +x)."""

    position_m: tuple[float, float]
    direction_deg: float
    #: Per-sensor gain K, overriding ``[sensor].gain``.
    gain: float | None = None
    name: str | None = None

    def __post_init__(self):
        if self.gain is not None:
            _positive(self.gain, "gain", strict=False)


@dataclass(frozen=True)
class Touch:
    """A contact. ``shape`` is ``"disk"`` (default), ``"stick"`` or ``"ring"``.

    A stick is a line of length ``length_m`` through ``position_m`` at
    ``angle_deg``; a ring (a mug rim) is a circle of radius ``ring_radius_m``
    around ``position_m``. ``radius_m`` is the disk radius, or the half-width
    of a stick or rim. Sticks and rings are modelled as touching disks, each
    with backscatter ``strength``.
    """

    position_m: tuple[float, float]
    radius_m: float
    strength: float
    shape: str = "disk"
    length_m: float = 0.0
    angle_deg: float = 0.0
    ring_radius_m: float = 0.0

    def __post_init__(self):
        _positive(self.radius_m, "radius_m")
        _positive(self.strength, "strength", strict=False)
        if self.shape not in ("disk", "stick", "ring"):
            raise ConfigError(f"shape: must be one of disk, stick, ring, got {self.shape!r}")
        if self.shape == "stick":
            _positive(self.length_m, "length_m")
        if self.shape == "ring":
            _positive(self.ring_radius_m, "ring_radius_m")
        n = self._n_elements()
        if n > MAX_ELEMENTS:
            raise ConfigError(
                f"radius_m: a {self.shape} of radius {self.radius_m:g} m needs {n} disks (at most {MAX_ELEMENTS}); "
                "make radius_m larger"
            )

    def _n_elements(self) -> int:
        if self.shape == "stick":
            return max(2, int(math.ceil(self.length_m / (2 * self.radius_m))) + 1)
        if self.shape == "ring":
            return max(6, int(math.ceil(2 * math.pi * self.ring_radius_m / (2 * self.radius_m))))
        return 1

    def elements(self) -> np.ndarray:
        """The disks that make up this contact: (n, 4) = x_m, y_m, radius_m, strength."""
        x, y = self.position_m
        r = self.radius_m
        if self.shape == "disk":
            return np.array([[x, y, r, self.strength]])
        if self.shape == "stick":
            n = max(2, int(math.ceil(self.length_m / (2 * r))) + 1)
            s = np.linspace(-self.length_m / 2, self.length_m / 2, n)
            a = math.radians(self.angle_deg)
            pts = np.stack([x + s * math.cos(a), y + s * math.sin(a)], 1)
        else:
            n = max(6, int(math.ceil(2 * math.pi * self.ring_radius_m / (2 * r))))
            a = np.linspace(0, 2 * math.pi, n, endpoint=False)
            pts = np.stack([x + self.ring_radius_m * np.cos(a), y + self.ring_radius_m * np.sin(a)], 1)
        return np.concatenate([pts, np.full((len(pts), 1), r), np.full((len(pts), 1), self.strength)], 1)


@dataclass(frozen=True)
class FreeSpaceTarget:
    """A flat target in air, perpendicular to the sensor's axis (a free-space scene: no waveguide)."""

    distance_m: float
    #: Scales the return relative to the target the sensor model was fitted on.
    reflectance: float = 1.0

    def __post_init__(self):
        _positive(self.distance_m, "distance_m")
        _positive(self.reflectance, "reflectance", strict=False)


@dataclass(frozen=True)
class Noise:
    """How expected counts become a measured histogram."""

    #: Poisson photon noise (off: the expected counts are returned).
    poisson: bool = True
    #: SPAD pile-up: a detector that fired stays blind for the rest of that laser pulse.
    pile_up: bool = False


@dataclass(frozen=True)
class ModelSpec:
    """Which forward-model components to include.

    ``components = "auto"`` (default) includes exactly what the scene requires:
    no volume term without scattering, no touch or shadowing term without
    contacts, no ambient term without ambient light. A list names them
    explicitly; ``exclude`` removes some from the automatic set.
    """

    components: tuple[str, ...] | str = "auto"
    exclude: tuple[str, ...] = ()

    def __post_init__(self):
        if isinstance(self.components, str):
            if self.components != "auto":
                raise ConfigError(f"components: must be \"auto\" or a list, got {self.components!r}")
        else:
            for c in self.components:
                if c not in COMPONENTS:
                    raise ConfigError(f"components: unknown component {c!r}; known: {', '.join(COMPONENTS)}")
        for c in self.exclude:
            if c not in COMPONENTS:
                raise ConfigError(f"exclude: unknown component {c!r}; known: {', '.join(COMPONENTS)}")


@dataclass(frozen=True, kw_only=True)
class Scene:
    """A whole scene. Build it with :func:`load_scene` or :func:`scene_from_dict`.

    A free-space scene (a TMF882x looking at a flat target in air) has no ``[waveguide]``;
    its sensor positions are not checked against an edge and ``[target]`` gives the target.
    """

    waveguide: Waveguide | None = None
    sensor: SensorModel
    sensors: tuple[SensorPlacement, ...]
    target: FreeSpaceTarget | None = None
    touches: tuple[Touch, ...] = ()
    noise: Noise = field(default_factory=Noise)
    model: ModelSpec = field(default_factory=ModelSpec)
    name: str = "scene"
    description: str = ""

    def __post_init__(self):
        wg = self.waveguide
        if not self.sensors:
            raise ConfigError("sensors: at least one [[sensors]] table is required")
        if len(self.sensors) > MAX_SENSORS:
            raise ConfigError(f"sensors: at most {MAX_SENSORS} sensors (8 muxes of 8), got {len(self.sensors)}")
        if len(self.touches) > MAX_TOUCHES:
            raise ConfigError(f"touches: at most {MAX_TOUCHES} contacts, got {len(self.touches)}")
        if wg is None:
            if self.touches:
                raise ConfigError("touches: a free-space scene (no [waveguide]) has no contacts")
            return
        if self.target is not None:
            raise ConfigError("target: a flat target in air belongs to a free-space scene; remove [waveguide] or [target]")
        for i, s in enumerate(self.sensors):
            key = f"sensors[{i}]"
            x, y = s.position_m
            on_edge = wg.contains(x, y, _EDGE_TOL_M) and (
                min(abs(x), abs(x - wg.size_m[0])) <= _EDGE_TOL_M or min(abs(y), abs(y - wg.size_m[1])) <= _EDGE_TOL_M
            )
            if not on_edge:
                raise ConfigError(
                    f"{key}.position_m: sensor at ({x:g}, {y:g}) m is not on the edge of the "
                    f"{wg.size_m[0]:g} x {wg.size_m[1]:g} m waveguide"
                )
            a = math.radians(s.direction_deg)
            step = 1e-3 * min(wg.size_m)
            if not wg.contains(x + step * math.cos(a), y + step * math.sin(a), 0.0):
                raise ConfigError(
                    f"{key}.direction_deg: the optical axis at {s.direction_deg:g} deg points out of the waveguide"
                )
        for i, t in enumerate(self.touches):
            for j, (x, y, r, _) in enumerate(t.elements()):
                if not wg.contains(x, y):
                    what = "touch" if t.shape == "disk" else f"{t.shape} (part {j})"
                    raise ConfigError(
                        f"touches[{i}].position_m: {what} at ({x:.4g}, {y:.4g}) m is outside the "
                        f"{wg.size_m[0]:g} x {wg.size_m[1]:g} m waveguide"
                    )

    # ---- derived quantities -------------------------------------------------------------
    @property
    def n_sensors(self) -> int:
        return len(self.sensors)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Histogram shape of one frame: (sensors, zones, bins)."""
        return (len(self.sensors), self.sensor.zones, self.sensor.n_bins)

    def gains(self) -> np.ndarray:
        return np.array([self.sensor.gain if s.gain is None else s.gain for s in self.sensors])

    def contact_elements(self) -> np.ndarray:
        """All contacts as disks: (n, 4) = x_m, y_m, radius_m, strength."""
        if not self.touches:
            return np.zeros((0, 4))
        return np.concatenate([t.elements() for t in self.touches], 0)

    @property
    def free_space(self) -> bool:
        """True for a sensor in air looking at a flat target (no waveguide)."""
        return self.waveguide is None

    def require_waveguide(self, what: str, source: str | None = None) -> "Scene":
        """``self``, or a one-line :class:`ConfigError` where this is a free-space scene: ``what``
        (a command, a job) needs a waveguide. ``source``: the file it came from, for the message."""
        if self.free_space:
            raise ConfigError(
                f"{source or self.name}: a free-space scene (a sensor facing a flat target, no [waveguide]); {what} "
                "needs a waveguide scene (free-space captures go to `tofjax sensor fit` and `tofjax range`)"
            )
        return self

    def with_sensor_model(self, path: str) -> "Scene":
        """This scene with ``[sensor] model`` set to a fitted sensor model (``tofjax sensor fit``);
        its bin width replaces the nominal one, so a waveguide fit no longer absorbs it into n1."""
        from .sensor.response import load_sensor_model

        fitted = load_sensor_model(path)
        sm = dataclasses.replace(self.sensor, model=str(path), bin_width_s=float(fitted.bin_width_s))
        if self.waveguide is None and fitted.n_zones == sm.zones and sm.grid is None:
            sm = dataclasses.replace(sm, grid=tuple(fitted.grid))
        return dataclasses.replace(self, sensor=sm)

    def components(self) -> tuple[str, ...]:
        """The model components this scene requires (see :class:`ModelSpec`)."""
        if self.waveguide is None:
            return ("target", "ambient")
        if not isinstance(self.model.components, str):
            return tuple(c for c in COMPONENTS if c in self.model.components and c not in self.model.exclude)
        wg, sm = self.waveguide, self.sensor
        need = {
            "crosstalk": sm.crosstalk_counts > 0,
            "interface": wg.interface_backscatter_per_m > 0,
            "volume": wg.mu_s_per_m > 0 and wg.volume_backscatter_fraction > 0,
            "end": wg.end_reflectance > 0,
            "multiple_scattering": wg.mu_s_per_m > 0 and wg.multiple_scattering > 0,
            "touch": bool(self.touches),
            "shadowing": bool(self.touches) and wg.shadow_opacity > 0,
            "ambient": sm.ambient_counts > 0,
        }
        return tuple(c for c in COMPONENTS if need[c] and c not in self.model.exclude)

    def replace(self, **changes) -> "Scene":
        """A copy with some fields changed, validated again."""
        return dataclasses.replace(self, **changes)

    def without_touches(self) -> "Scene":
        """The baseline scene: the same setup with nothing touching it."""
        return dataclasses.replace(self, touches=())

    # ---- serialisation ------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return to_dict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    def to_toml(self) -> str:
        """The scene as TOML text that :func:`load_scene` reads back."""
        return _dump_toml(self.to_dict())


def scene_from_dict(data: dict[str, Any], source: str = "scene") -> Scene:
    """Build and validate a scene from a parsed TOML/JSON table; errors name ``source`` and the key."""
    try:
        return from_dict(Scene, data)
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from None


def scene_from_json(text: str, source: str = "scene") -> Scene:
    """Parse a scene stored as JSON (the ``scene`` attribute of a capture)."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError(f"{source}: scene is not valid JSON: {e}") from None
    return scene_from_dict(_drop_nulls(data), source)


def _drop_nulls(data: Any) -> Any:
    if isinstance(data, dict):
        return {k: _drop_nulls(v) for k, v in data.items() if v is not None}
    if isinstance(data, list):
        return [_drop_nulls(v) for v in data]
    return data


def load_scene(path: str | Path) -> Scene:
    """Load and validate a scene TOML file.

    ``path`` may also name a built-in scene (``"optoskin"``, ``"softskin"``, ...),
    looked up in the package data and in ``configs/``.
    """
    p = Path(path)
    if not p.exists() and p.suffix == "" and not p.parent.parts:
        builtin = resources.files("tofjax") / "data" / f"{p.name}.toml"
        if builtin.is_file():
            with resources.as_file(builtin) as bp:
                return scene_from_dict(load_toml(bp), str(p.name))
    scene = scene_from_dict(load_toml(p), str(p))
    if scene.sensor.model and not scene.free_space:
        # a waveguide scene's fitted sensor model: its bin width replaces the nominal one, as --sensor does
        # (it was silently ignored, even when the file did not exist)
        scene = scene.with_sensor_model(scene.sensor.model)
    return scene


def default_scene() -> Scene:
    """The built-in default scene: the OptoSkin baseline of seed 000 with effective attenuation."""
    return load_scene("optoskin")


def _dump_toml(d: dict[str, Any]) -> str:
    lines: list[str] = []
    scalars = {k: v for k, v in d.items() if not isinstance(v, (dict, list)) or (isinstance(v, list) and not (v and isinstance(v[0], dict)))}
    for k, v in scalars.items():
        if v is not None:
            lines.append(f"{k} = {toml_value(v)}")
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {toml_value(vv)}" for kk, vv in v.items() if vv is not None]
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                lines.append(f"\n[[{k}]]")
                lines += [f"{kk} = {toml_value(vv)}" for kk, vv in item.items() if vv is not None]
    return "\n".join(lines) + "\n"
