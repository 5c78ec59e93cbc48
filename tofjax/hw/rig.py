"""Rig files: which sensors sit on which bus, how they are selected, how they are configured.

A rig file (TOML, ``configs/rigs/``) names the scene (the geometry the captures carry) and
describes the wiring::

    name = "optoskin-pi"
    scene = "optoskin"          # built-in name, or a path relative to this file
    bus = 1                     # /dev/i2c-1
    bus_speed_hz = 400000       # what config.txt sets (dtparam=i2c_arm_baudrate)
    select = "pins"             # "pins" (enable lines), "mux" (TCA9548A) or "none" (one sensor)

    [[sensors]]
    name = "S0"
    enable_pin = 17             # BCM GPIO number
    address = 0x42              # moved there after power-up (pins rigs)

:func:`open_array` turns a rig into a :class:`~tofjax.hw.driver.TMF8828Array` on the real
bus or on an emulated one (:func:`emulated_bus`).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import ConfigError, from_dict, load_toml
from ..errors import UserError
from ..scene import Scene, load_scene
from . import protocol as P
from .bus import BusFaults, SimBus, SimClock, SimIntPin, SimPin, TCA9548A
from .driver import DriverOptions, SensorSpec, TMF8828Array
from .emulator import DeviceFaults, EmulatorTiming, TMF8828Emulator, default_zone_map

__all__ = ["Rig", "RigSensor", "emulated_bus", "load_rig", "load_rig_or_scene", "open_array", "rig_for_scene"]


@dataclass(frozen=True)
class RigSensor:
    """One sensor of a rig. ``tmf_zones`` lists the TMF zone index of each scene zone (default: the
    layout's first zones, see ``docs/acquisition.md``)."""

    name: str | None = None
    enable_pin: int | None = None
    mux_channel: int | None = None
    address: int | None = None
    #: BCM GPIO of its INT line (optional): wait on the pin instead of polling INT_STATUS
    int_pin: int | None = None
    tmf_zones: tuple[int, ...] | None = None

    def __post_init__(self):
        if self.mux_channel is not None and not 0 <= self.mux_channel <= 7:
            raise ConfigError(f"mux_channel: must be in [0, 7], got {self.mux_channel}")
        if self.address is not None and not 0x08 <= self.address <= 0x77:
            raise ConfigError(f"address: must be a 7-bit address in [0x08, 0x77], got {self.address:#x}")
        for key in ("enable_pin", "int_pin"):
            v = getattr(self, key)
            if v is not None and not 0 <= v <= 53:
                raise ConfigError(f"{key}: must be a BCM GPIO number in [0, 53], got {v}")


@dataclass(frozen=True)
class Rig:
    """A rig: the scene, the bus, the selection scheme, the sensors and their configuration."""

    scene: str
    sensors: tuple[RigSensor, ...]
    name: str = "rig"
    description: str = ""
    bus: int = 1
    bus_speed_hz: int = 400_000
    select: str = "pins"
    mux_address: int = 0x70
    layout: str = "auto"
    period_ms: int = P.DEFAULT_PERIOD_MS
    #: ``None``: the scene's ``sensor.iterations`` / 1024
    kilo_iterations: int | None = None
    spad_map: int | None = None
    #: the application image (Intel HEX or binary); a relative path is relative to the rig file
    image: str | None = None

    def __post_init__(self):
        if not self.sensors:
            raise ConfigError("sensors: at least one [[sensors]] table is required")
        if self.select not in ("pins", "mux", "none"):
            raise ConfigError(f"select: must be pins, mux or none, got {self.select!r}")
        if self.select == "none" and len(self.sensors) > 1:
            raise ConfigError("select: \"none\" works for one sensor only; wire several with pins or a mux")
        if not 10_000 <= self.bus_speed_hz <= 1_000_000:
            raise ConfigError(f"bus_speed_hz: the TMF8828 accepts up to 1 MHz, got {self.bus_speed_hz}")
        for i, s in enumerate(self.sensors):
            if self.select == "pins" and s.enable_pin is None:
                raise ConfigError(f"sensors[{i}].enable_pin: required with select = \"pins\"")
            if self.select == "mux" and s.mux_channel is None:
                raise ConfigError(f"sensors[{i}].mux_channel: required with select = \"mux\"")
        gpios = [g for s in self.sensors for g in (s.enable_pin, s.int_pin) if g is not None]
        if len(gpios) != len(set(gpios)):
            raise ConfigError("sensors: a GPIO is used twice (enable_pin and int_pin must all differ)")
        for key in ("mux_channel",):
            vals = [getattr(s, key) for s in self.sensors if getattr(s, key) is not None]
            if len(vals) != len(set(vals)):
                raise ConfigError(f"sensors: two sensors share the same {key}")
        addrs = self.addresses()
        if len(set(addrs)) != len(addrs) and self.select == "pins":
            raise ConfigError("sensors: with enable pins every sensor needs its own address")
        if self.select == "pins" and len(addrs) > 1 and P.ADDRESS in addrs:
            raise ConfigError(f"sensors: with enable pins no sensor may keep {P.ADDRESS:#x} (sensors power up there)")
        if self.select == "mux" and not 0x08 <= self.mux_address <= 0x77:
            raise ConfigError(f"mux_address: must be a 7-bit address in [0x08, 0x77] (a TCA9548A answers at 0x70-0x77), "
                              f"got {self.mux_address:#x}")
        if self.select == "mux" and self.mux_address in addrs:
            raise ConfigError(f"mux_address {self.mux_address:#x} is also a sensor address")

    def addresses(self) -> list[int]:
        out = []
        for i, s in enumerate(self.sensors):
            if s.address is not None:
                out.append(s.address)
            elif self.select == "pins" and len(self.sensors) > 1:
                out.append(P.ADDRESS + 1 + i)
            else:
                out.append(P.ADDRESS)
        return out

    def load_scene(self) -> Scene:
        return load_scene(self.scene)

    def image_path(self) -> Path | None:
        return None if not self.image else Path(os.path.expanduser(self.image))


def load_rig(path: str | Path) -> Rig:
    """Load a rig file; its ``scene`` and ``image`` paths are taken relative to the file."""
    path = Path(path)
    data = load_toml(path)
    try:
        rig = from_dict(Rig, data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    changes = {}
    if (path.parent / rig.scene).exists():
        changes["scene"] = str(path.parent / rig.scene)
    if rig.image and not Path(os.path.expanduser(rig.image)).is_absolute():
        changes["image"] = str(path.parent / rig.image)
    return dataclasses.replace(rig, **changes)


def rig_for_scene(scene_ref: str, scene: Scene) -> Rig:
    """A rig for a bare scene: one sensor needs no selection; several sit behind a mux (channels 0..)."""
    n = scene.n_sensors
    if n == 1:
        sensors = (RigSensor(name=scene.sensors[0].name),)
        return Rig(scene=scene_ref, sensors=sensors, select="none", name=f"{scene.name} (one sensor)")
    if n > 8:
        raise UserError(f"{scene_ref}: {n} sensors do not fit one 8-channel mux; write a rig file")
    sensors = tuple(RigSensor(name=s.name, mux_channel=i) for i, s in enumerate(scene.sensors))
    return Rig(scene=scene_ref, sensors=sensors, select="mux", name=f"{scene.name} (mux)")


def load_rig_or_scene(ref: str) -> tuple[Rig, Scene, bool]:
    """``ref`` is a rig file or a scene (file or built-in name): (rig, scene, is_rig_file)."""
    p = Path(ref)
    if p.is_file():
        data = load_toml(p)
        rig_only = {f.name for f in dataclasses.fields(Rig)} - {"name", "description", "sensors"}
        if "sensors" not in data and "waveguide" not in data and "target" not in data and rig_only & set(data):
            keys = ", ".join(sorted(rig_only & set(data)))
            raise ConfigError(f"{p}: a rig file ({keys}) needs one [[sensors]] table per sensor "
                              f"(see configs/rigs/optoskin-mux.toml)")
        if "sensors" in data and "waveguide" not in data and "target" not in data:  # [target]: a free-space scene
            rig = load_rig(p)
            scene = rig.load_scene()
            _check(rig, scene, str(p))
            return rig, scene, True
    scene = load_scene(ref)
    return rig_for_scene(ref, scene), scene, False


def _check(rig: Rig, scene: Scene, where: str) -> None:
    if len(rig.sensors) != scene.n_sensors:
        raise ConfigError(f"{where}: the rig has {len(rig.sensors)} sensors but its scene {rig.scene!r} has {scene.n_sensors}")
    for i, (r, s) in enumerate(zip(rig.sensors, scene.sensors)):
        if r.name and s.name and r.name != s.name:
            raise ConfigError(f"{where}: sensors[{i}] is {r.name!r} in the rig but {s.name!r} in the scene")
    if scene.sensor.n_bins != P.N_BINS:
        raise ConfigError(f"{where}: the TMF8828 has {P.N_BINS} bins; the scene has {scene.sensor.n_bins}")
    lay = P.layout_for(scene.sensor.zones, rig.layout)
    for i, r in enumerate(rig.sensors):
        if r.tmf_zones is not None:
            valid = {lay.zone_index(*slot) for slot in lay.slots()}
            if len(r.tmf_zones) != scene.sensor.zones:
                raise ConfigError(f"{where}: sensors[{i}].tmf_zones has {len(r.tmf_zones)} entries for "
                                  f"{scene.sensor.zones} scene zones")
            bad = [z for z in r.tmf_zones if z not in valid]
            if bad:
                raise ConfigError(f"{where}: sensors[{i}].tmf_zones: {bad[0]} is not a zone of layout {lay.name}")


def driver_options(rig: Rig, scene: Scene, **overrides) -> DriverOptions:
    lay = P.layout_for(scene.sensor.zones, rig.layout)
    kilo = rig.kilo_iterations or max(1, round(scene.sensor.iterations / 1024))
    kw = dict(layout=lay.name, period_ms=rig.period_ms, kilo_iterations=kilo, spad_map=rig.spad_map)
    kw.update(overrides)
    return DriverOptions(**kw)


def sensor_specs(rig: Rig, scene: Scene, pins: list | None = None, int_pins: list | None = None) -> list[SensorSpec]:
    lay = P.layout_for(scene.sensor.zones, rig.layout)
    zmap = default_zone_map(lay, scene.sensor.zones)
    out = []
    for i, (r, addr) in enumerate(zip(rig.sensors, rig.addresses())):
        out.append(SensorSpec(
            name=r.name or scene.sensors[i].name or f"S{i}",
            zone_map=tuple(r.tmf_zones) if r.tmf_zones is not None else tuple(zmap),
            address=addr,
            pin=None if pins is None else pins[i],
            mux_channel=r.mux_channel if rig.select == "mux" else None,
            int_pin=None if int_pins is None else int_pins[i],
        ))
    return out


# ---- emulation -------------------------------------------------------------------------------
def expected_sensor_signals(scene: Scene, reference_counts: float = 2.0e4) -> tuple[np.ndarray, np.ndarray]:
    """The forward model's expected counts (sensors, zones, bins) and a reference-SPAD histogram
    (sensors, bins): the instrument response (the unit light-entry peak) times ``reference_counts``.

    Cached per scene (a rig is opened again and again in tests, the demo and notebooks)."""
    import jax

    lam, ref = _signals_cached(scene, float(reference_counts), bool(jax.config.jax_enable_x64))
    return lam.copy(), ref.copy()


@functools.lru_cache(maxsize=8)
def _signals_cached(scene: Scene, reference_counts: float, x64: bool) -> tuple[np.ndarray, np.ndarray]:
    import jax.numpy as jnp

    from ..model import ModelOptions, Params, build_model
    from ..simulate import expected_counts

    opts = ModelOptions(dtype="float64" if x64 else "float32")
    lam = expected_counts(scene, opts)
    base = scene.replace(noise=scene.noise.__class__(poisson=False, pile_up=False))
    model = build_model(base, opts, components=("crosstalk",))
    p = Params.from_scene(base, opts.jnp_dtype)
    p = p.replace(crosstalk_counts=jnp.ones_like(p.crosstalk_counts))
    unit = np.asarray(model(p))[:, 0, :]
    return np.asarray(lam, np.float64), reference_counts * unit


def emulated_bus(rig: Rig, scene: Scene, *, frequency_hz: float | None = None, noise: bool | None = None,
                 bus_faults: BusFaults = BusFaults(), device_faults: DeviceFaults = DeviceFaults(),
                 timing: EmulatorTiming = EmulatorTiming(), image: bytes | None = None, seed: int = 0,
                 overhead_s: float = 0.0, signals: tuple[np.ndarray, np.ndarray] | None = None):
    """An emulated rig: a :class:`SimBus` with one :class:`TMF8828Emulator` per sensor of ``scene``
    (histograms from its forward model), wired as the rig says (pins or a mux).

    Returns ``(bus, pins, emulators)``; ``pins`` are :class:`SimPin` (or ``None`` without pins).
    Sensors with an ``int_pin`` in the rig get a :class:`SimIntPin`: :func:`emulated_int_pins`.
    """
    _check(rig, scene, rig.name)
    lam, ref = signals if signals is not None else expected_sensor_signals(scene)
    clock = SimClock()
    bus = SimBus(frequency_hz or rig.bus_speed_hz, clock=clock, faults=bus_faults, overhead_s=overhead_s)
    mux = bus.attach(TCA9548A(rig.mux_address)) if rig.select == "mux" else None
    del mux
    lay = P.layout_for(scene.sensor.zones, rig.layout)
    specs = sensor_specs(rig, scene)
    emus, pins = [], []
    for i, spec in enumerate(specs):
        emu = TMF8828Emulator(
            lam[i], ref[i], clock,
            noise=scene.noise.poisson if noise is None else noise,
            zone_map={lay.name: list(spec.zone_map)},
            image=image, bin_width_s=scene.sensor.bin_width_s,
            faults=DeviceFaults(**{**device_faults.__dict__, "seed": device_faults.seed + i}),
            timing=timing, seed=seed * 1000 + i, name=spec.name,
        )
        bus.attach(emu, channel=spec.mux_channel)
        if rig.select == "pins":
            pins.append(SimPin(emu))
        else:
            emu.set_enable(True)  # no enable line: always powered
        emus.append(emu)
    return bus, (pins or None), emus


def emulated_int_pins(rig: Rig, emulators: list) -> list | None:
    """INT inputs wired to the emulators of the sensors whose rig entry has an ``int_pin``."""
    if not any(s.int_pin is not None for s in rig.sensors):
        return None
    return [None if s.int_pin is None else SimIntPin(e) for s, e in zip(rig.sensors, emulators)]


def real_bus(rig: Rig, bus_number: int | None = None):
    """Open ``/dev/i2c-N`` with smbus2 and the enable / INT pins with gpiozero; clear errors if either is
    missing. Returns ``(bus, enable pins or None, INT pins or None)``."""
    n = rig.bus if bus_number is None else bus_number
    dev = Path(f"/dev/i2c-{n}")
    if not dev.exists():
        raise UserError(f"{dev} does not exist: enable I2C (sudo raspi-config, Interface Options) or use --emulate")
    import smbus2

    try:
        bus = smbus2.SMBus(n)
    except OSError as e:
        raise UserError(f"{dev}: cannot open ({e.strerror}); is your user in the i2c group?") from None
    pins = None
    if rig.select == "pins":
        try:
            from gpiozero import DigitalOutputDevice
        except ImportError:
            raise UserError("enable pins need gpiozero (pip install gpiozero) on the Raspberry Pi") from None
        pins = [DigitalOutputDevice(s.enable_pin, initial_value=False) for s in rig.sensors]
    int_pins = None
    if any(s.int_pin is not None for s in rig.sensors):
        try:
            from gpiozero import DigitalInputDevice
        except ImportError:
            raise UserError("INT pins need gpiozero (pip install gpiozero) on the Raspberry Pi") from None
        int_pins = [None if s.int_pin is None else DigitalInputDevice(s.int_pin, pull_up=True) for s in rig.sensors]
    return bus, pins, int_pins


def open_array(rig: Rig, scene: Scene, bus: Any, pins: list | None, image: bytes, *, int_pins: list | None = None,
               **option_overrides) -> TMF8828Array:
    """A :class:`TMF8828Array` for ``rig`` on ``bus`` (not yet opened); ``int_pins``: one INT input
    per sensor (or ``None`` entries) for rigs that wire them."""
    return TMF8828Array(
        bus, sensor_specs(rig, scene, pins, int_pins), image,
        options=driver_options(rig, scene, **option_overrides),
        mux_address=rig.mux_address if rig.select == "mux" else None,
    )
