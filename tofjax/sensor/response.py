"""A TMF882x sensor model measured from real histograms (issue 12).

What a zone of the sensor records when it looks at a flat target in air::

    lambda_b = ambient + amplitude * P_z(b - shift),   shift = zero_range_bins[z] + bins_per_m[z] * d
    counts_b = pile_up(lambda, pulses_per_histogram[z])          (Coates; optional)

``P_z`` is the zone's instrument response learned from data: a piecewise linear pulse on
knots ``pulse_step_bins`` apart (:func:`tofjax.model.pulse.template_bin_masses` integrates
it exactly over each bin). A single exponentially modified Gaussian leaves a reduced
chi-square of ~300 on the real sweep; the learned pulse follows the second, slower tail.
Times are in bins; ``bin_width_s`` turns them into seconds (``bins_per_m = 2 / (c w)`` on
the centre zone, larger off axis where the path to the plane is longer).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..errors import UserError
from ..model.forward import pile_up
from ..model.params import SPEED_OF_LIGHT_M_PER_S
from ..model.pulse import template_bin_masses

__all__ = ["SensorResponse", "SensorModelError", "expected_counts", "load_sensor_model", "C_AIR"]

#: Speed of light in air (n = 1.000277 at 20 degC, 1 atm), m/s.
C_AIR = SPEED_OF_LIGHT_M_PER_S / 1.000277
FORMAT = "tofjax.sensor"
VERSION = 1


class SensorModelError(UserError):
    """A sensor model file is missing, foreign or inconsistent, or a fit cannot identify it."""


@dataclass(frozen=True)
class SensorResponse:
    """A fitted sensor model (all arrays numpy, one row per zone in the capture's order)."""

    bin_width_s: float
    n_bins: int
    grid: tuple[int, int]
    zero_range_bins: np.ndarray  # (Z,) pulse position at d = 0
    bins_per_m: np.ndarray  # (Z,) pulse position change per metre of target distance
    pulse: np.ndarray  # (Z, K) knot values, each zone's pulse integrates to 1
    pulse_start_bins: float
    pulse_step_bins: float
    pulses_per_histogram: np.ndarray | None = None  # (Z,) effective laser pulses (pile-up); None: no pile-up
    #: Range walk: position minus the straight line, a polynomial in distance (m) per zone (Z, degree + 1),
    #: highest power first (numpy.polyval); None: the line alone.
    walk_coeffs: np.ndarray | None = None
    #: Double-bounce echo: its amplitude relative to the first return, ``echo_ratio[z] * (d / 0.2 m)^echo_power[z]``.
    echo_ratio: np.ndarray | None = None
    echo_power: np.ndarray | None = None
    #: How the pulse's shape changes with its position (None: a fixed shape): (Z, K) first
    #: order only, or (Z, order, K), term ``k`` multiplying ``((shift - 28) / 10)^(k + 1)``.
    pulse_drift: np.ndarray | None = None
    #: Signal amplitude model for simulation: amplitude = gain_m2[z] / d^2 (counts at 1 m), ambient counts per bin.
    gain_m2: np.ndarray | None = None
    ambient_counts: np.ndarray | None = None
    #: The reference channel's own pulse (it is not the object pulse) and where it sits.
    reference_pulse: np.ndarray | None = None
    reference_shift_bins: float | None = None
    reference_counts: float | None = None
    reference_pulse_step_bins: float | None = None
    #: Standard errors and fit diagnostics, as written by ``tofjax sensor fit``.
    report: dict[str, Any] = field(default_factory=dict)

    @property
    def n_zones(self) -> int:
        return int(self.zero_range_bins.shape[0])

    @property
    def drift_order(self) -> int:
        """Order of the pulse's shape drift (0: a fixed shape)."""
        if self.pulse_drift is None:
            return 0
        return 1 if self.pulse_drift.ndim == 2 else int(self.pulse_drift.shape[1])

    def drift_terms(self, zone: int) -> np.ndarray | None:
        """The zone's shape-drift terms (order, K), or None for a fixed shape."""
        if self.pulse_drift is None:
            return None
        return np.asarray(self.pulse_drift[zone]).reshape(self.drift_order, -1)

    def walk_bins(self, distance_m, zone: int):
        """The range-walk correction of ``zone`` at ``distance_m`` (bins; 0 without one)."""
        if self.walk_coeffs is None:
            return np.zeros_like(np.asarray(distance_m, float))
        return np.polyval(self.walk_coeffs[zone], np.asarray(distance_m, float))

    def shift_bins(self, distance_m, zone: int):
        """Pulse position (bins) of ``zone`` for a target at ``distance_m``."""
        d = np.asarray(distance_m, float)
        return self.zero_range_bins[zone] + self.bins_per_m[zone] * d + self.walk_bins(d, zone)

    def distance_m(self, shift_bins, zone: int):
        """Inverse of :meth:`shift_bins` (a few fixed-point steps: the walk is a small correction)."""
        s = np.asarray(shift_bins, float)
        d = (s - self.zero_range_bins[zone]) / self.bins_per_m[zone]
        for _ in range(6):
            d = (s - self.zero_range_bins[zone] - self.walk_bins(d, zone)) / self.bins_per_m[zone]
        return d

    def pulse_peak_bins(self) -> np.ndarray:
        """Where each zone's pulse peaks relative to its position (bins; parabola through the top knots)."""
        out = []
        for p in self.pulse:
            k = int(np.clip(np.argmax(p), 1, len(p) - 2))
            a, b, c = p[k - 1], p[k], p[k + 1]
            den = a - 2 * b + c
            off = 0.5 * (a - c) / den if den < 0 else 0.0
            out.append(self.pulse_start_bins + self.pulse_step_bins * (k + float(np.clip(off, -1, 1))))
        return np.asarray(out)

    def zero_range_s(self) -> np.ndarray:
        """Time of the pulse's peak for a target at zero range, per zone, seconds after bin 0's start
        (the position itself is only defined up to the pulse's own origin)."""
        return (self.zero_range_bins + self.pulse_peak_bins()) * self.bin_width_s

    # ---- files ------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        def arr(a):
            return None if a is None else np.asarray(a, float).tolist()

        return {
            "format": FORMAT,
            "version": VERSION,
            "bin_width_s": float(self.bin_width_s),
            "n_bins": int(self.n_bins),
            "grid": list(self.grid),
            "zero_range_bins": arr(self.zero_range_bins),
            "bins_per_m": arr(self.bins_per_m),
            "pulse": arr(self.pulse),
            "pulse_start_bins": float(self.pulse_start_bins),
            "pulse_step_bins": float(self.pulse_step_bins),
            "pulses_per_histogram": arr(self.pulses_per_histogram),
            "walk_coeffs": arr(self.walk_coeffs),
            "pulse_drift": arr(self.pulse_drift),
            "echo_ratio": arr(self.echo_ratio),
            "echo_power": arr(self.echo_power),
            "gain_m2": arr(self.gain_m2),
            "ambient_counts": arr(self.ambient_counts),
            "reference_pulse": arr(self.reference_pulse),
            "reference_shift_bins": self.reference_shift_bins,
            "reference_counts": self.reference_counts,
            "reference_pulse_step_bins": self.reference_pulse_step_bins,
            "report": self.report,
        }

    def save(self, path: str | Path) -> Path:
        from ..outputs import atomic_write_text  # makes the folder, writes whole or not at all

        return atomic_write_text(path, json.dumps(self.to_json(), indent=1))

    @classmethod
    def from_json(cls, d: dict[str, Any], source: str = "sensor model") -> "SensorResponse":
        if d.get("format") != FORMAT:
            raise SensorModelError(f"{source}: not a tofjax sensor model (format {d.get('format')!r}, expected {FORMAT!r})")
        if d.get("version") != VERSION:
            raise SensorModelError(f"{source}: sensor model version {d.get('version')!r} is not supported")

        def arr(k):
            return None if d.get(k) is None else np.asarray(d[k], float)

        try:
            m = cls(
                bin_width_s=float(d["bin_width_s"]),
                n_bins=int(d["n_bins"]),
                grid=(int(d["grid"][0]), int(d["grid"][1])),
                zero_range_bins=arr("zero_range_bins"),
                bins_per_m=arr("bins_per_m"),
                pulse=arr("pulse"),
                pulse_start_bins=float(d["pulse_start_bins"]),
                pulse_step_bins=float(d["pulse_step_bins"]),
                pulses_per_histogram=arr("pulses_per_histogram"),
                walk_coeffs=arr("walk_coeffs"),
                pulse_drift=arr("pulse_drift"),
                echo_ratio=arr("echo_ratio"),
                echo_power=arr("echo_power"),
                gain_m2=arr("gain_m2"),
                ambient_counts=arr("ambient_counts"),
                reference_pulse=arr("reference_pulse"),
                reference_shift_bins=d.get("reference_shift_bins"),
                reference_counts=d.get("reference_counts"),
                reference_pulse_step_bins=d.get("reference_pulse_step_bins"),
                report=d.get("report", {}),
            )
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise SensorModelError(f"{source}: missing or malformed field: {e}") from None
        for k in ("zero_range_bins", "bins_per_m", "pulse"):
            if getattr(m, k) is None:
                raise SensorModelError(f"{source}: missing field: {k}")
        if not (np.isfinite(m.bin_width_s) and m.bin_width_s > 0) or m.n_bins < 1:
            raise SensorModelError(f"{source}: bin_width_s must be finite and > 0 and n_bins >= 1, got "
                                   f"{m.bin_width_s!r} and {m.n_bins!r}")
        for f in dataclasses.fields(m):
            v = getattr(m, f.name)
            if isinstance(v, np.ndarray) and not np.all(np.isfinite(v)):
                raise SensorModelError(f"{source}: {f.name} has non-finite values")
            if isinstance(v, float) and not np.isfinite(v):
                raise SensorModelError(f"{source}: {f.name} is not finite ({v!r})")
        Z = m.n_zones
        if m.pulse_drift is not None and (m.pulse_drift.ndim not in (2, 3) or m.pulse_drift.shape[0] != Z
                                          or m.pulse_drift.shape[-1] != m.pulse.shape[-1]):
            raise SensorModelError(f"{source}: pulse_drift {m.pulse_drift.shape} does not match the pulse {m.pulse.shape}")
        if m.pulse.ndim != 2 or m.pulse.shape[0] != Z or m.bins_per_m.shape != (Z,) or m.grid[0] * m.grid[1] != Z:
            raise SensorModelError(f"{source}: zone counts disagree (grid {m.grid}, {Z} zero-range offsets, pulse {m.pulse.shape})")
        return m


def load_sensor_model(path: str | Path) -> SensorResponse:
    """Read a sensor model written by ``tofjax sensor fit``."""
    path = Path(path)
    if not path.is_file():
        raise SensorModelError(f"{path}: no such sensor model file")
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise SensorModelError(f"{path}: not a text file (not UTF-8 at byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise SensorModelError(f"{path}: not valid JSON: {e}") from None
    except OSError as e:
        raise SensorModelError(f"{path}: cannot read: {e.strerror or e}") from None
    if not isinstance(d, dict):
        raise SensorModelError(f"{path}: not a tofjax sensor model (a JSON {type(d).__name__}, not an object)")
    return SensorResponse.from_json(d, str(path))


#: The pulse's shape drift is ``(shift - SHAPE_REF_BINS) / SHAPE_SCALE_BINS`` times ``pulse_drift``.
SHAPE_REF_BINS = 28.0
SHAPE_SCALE_BINS = 10.0


def zone_counts(pulse, start, step, n_bins, shift, amplitude, ambient, pulses=None, edges=None, drift=None,
                echo=None, zero_shift=0.0):
    """The model of one zone for many frames (jax): shift, amplitude, ambient (...,) -> (..., n_bins).

    ``edges`` (n_bins + 1,): the bin edges in nominal bins when the bins are unequal (the
    ambient floor then scales with each bin's width too). ``drift`` (K,) or (order, K): how
    the pulse's shape changes with its position, term ``k`` times ``a^(k + 1)`` with
    ``a = (shift - 28) / 10`` (the bin integrals are linear in the pulse: one more pass per
    order). ``echo`` (...,): the amplitude of the double bounce
    (target -> sensor cover -> target -> sensor), the same pulse at twice the distance:
    position ``2 shift - zero_shift``.
    """
    m = template_bin_masses(shift, pulse, start, step, n_bins, edges)
    if drift is not None:
        a = (jnp.asarray(shift) - SHAPE_REF_BINS) / SHAPE_SCALE_BINS
        terms = jnp.atleast_2d(jnp.asarray(drift))
        for k in range(terms.shape[0]):
            m = m + (a ** (k + 1))[..., None] * template_bin_masses(shift, terms[k], start, step, n_bins, edges)
    width = 1.0 if edges is None else jnp.diff(edges)
    lam = jnp.asarray(ambient)[..., None] * width + jnp.asarray(amplitude)[..., None] * m
    if echo is not None:
        s2 = 2.0 * jnp.asarray(shift) - zero_shift
        lam = lam + jnp.asarray(echo)[..., None] * template_bin_masses(s2, pulse, start, step, n_bins, edges)
    return lam if pulses is None else pile_up(lam, pulses)


def expected_counts(model: SensorResponse, distance_m, amplitude=None, ambient=None) -> np.ndarray:
    """Expected histograms of every zone for targets at ``distance_m`` (frames,) -> (frames, Z, bins).

    ``amplitude`` and ``ambient`` (frames, Z) default to the model's ``gain_m2 / d^2`` and
    ``ambient_counts``.
    """
    d = np.atleast_1d(np.asarray(distance_m, float))
    Z = model.n_zones
    if amplitude is None:
        if model.gain_m2 is None:
            raise SensorModelError("the sensor model has no gain_m2: pass amplitudes")
        amplitude = model.gain_m2[None, :] / d[:, None] ** 2
    if ambient is None:
        ambient = np.broadcast_to(model.ambient_counts if model.ambient_counts is not None else 0.0, (len(d), Z))
    amplitude = np.broadcast_to(amplitude, (len(d), Z))
    ambient = np.broadcast_to(ambient, (len(d), Z))
    out = []
    for z in range(Z):
        shift = model.shift_bins(d, z)
        N = None if model.pulses_per_histogram is None else float(model.pulses_per_histogram[z])
        out.append(
            zone_counts(
                jnp.asarray(model.pulse[z]), model.pulse_start_bins, model.pulse_step_bins, model.n_bins,
                jnp.asarray(shift), jnp.asarray(amplitude[:, z]), jnp.asarray(ambient[:, z]), N,
                drift=None if model.pulse_drift is None else jnp.asarray(model.drift_terms(z)),
                echo=None if model.echo_ratio is None else jnp.asarray(
                    amplitude[:, z] * model.echo_ratio[z] * (d / 0.2) ** model.echo_power[z]),
                zero_shift=float(model.zero_range_bins[z]),
            )
        )
    return np.stack([np.asarray(o) for o in out], axis=1)


def expected_reference(model: SensorResponse, n_frames: int = 1) -> np.ndarray | None:
    """The reference channel (frames, bins) from its own pulse, or None if the model has none."""
    if model.reference_pulse is None:
        return None
    r = template_bin_masses(
        jnp.asarray(model.reference_shift_bins), jnp.asarray(model.reference_pulse),
        model.pulse_start_bins, model.reference_pulse_step_bins or model.pulse_step_bins, model.n_bins,
    )
    return np.broadcast_to(np.asarray(r) * float(model.reference_counts), (n_frames, model.n_bins)).copy()
