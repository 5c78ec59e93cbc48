"""One entry point per job: histograms -> corrected signals -> tactile maps -> touches.

:func:`build_inverter` precomputes everything that depends only on the scene, the
baseline and the calibration (gain, masks, projection, noise map); the returned
:class:`Inverter` is then applied to any number of frames::

    inv = build_inverter(scene, baseline.mean(), InvertOptions(method="full"))
    res = inv.process(capture.histograms)       # maps, flags, detections
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import jax
import jax.numpy as jnp
import numpy as np

from ..capture import Capture, read_capture
from ..compile_cache import fusion_jit
from ..config import ConfigError
from ..scene import Scene
from .correction import (
    METHODS,
    CorrectionOptions,
    Corrector,
    InversionError,
    OpticalParams,
    build_corrector,
    check_compatible,
    warn_no_calibration,
)
from .detect import Detection, DetectOptions, detect
from .maps import Grid, MapOperator, MapOptions, build_map_operator
from .reconstruct import ReconstructOptions

__all__ = [
    "ALL_METHODS",
    "InvertOptions",
    "Inverter",
    "ProcessResult",
    "build_inverter",
    "process_captures",
    "write_maps",
]

#: Back-projection variants plus the model-based reconstruction.
ALL_METHODS = (*METHODS, "model")


@dataclass(frozen=True)
class InvertOptions:
    """Everything the inversion can be told; each part has its own frozen options.

    ``method`` is one of ``raw``, ``decay``, ``baseline``, ``full`` (back-projection of
    Algorithm 1's variants) or ``model`` (model-based reconstruction, see
    :mod:`tofjax.invert.reconstruct`). ``dtype`` float32 (default, fast) or float64.
    """

    method: str = "full"
    correction: CorrectionOptions = field(default_factory=CorrectionOptions)
    maps: MapOptions = field(default_factory=MapOptions)
    detect: DetectOptions = field(default_factory=DetectOptions)
    reconstruct: ReconstructOptions = field(default_factory=ReconstructOptions)
    dtype: str = "float32"
    batch: int = 64

    def __post_init__(self):
        if self.method not in ALL_METHODS:
            raise ConfigError(f"method: must be one of {', '.join(ALL_METHODS)}, got {self.method!r}")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"dtype: must be float32 or float64, got {self.dtype!r}")
        if self.batch < 1:
            raise ConfigError(f"batch: must be >= 1, got {self.batch!r}")

    @property
    def jnp_dtype(self):
        if self.dtype == "float64" and not jax.config.jax_enable_x64:
            raise ConfigError("dtype: float64 requested but JAX runs in 32-bit mode (call tofjax.enable_x64())")
        return jnp.float64 if self.dtype == "float64" else jnp.float32


@dataclass
class ProcessResult:
    maps: np.ndarray  # (F, ny, nx)
    ok: np.ndarray  # (F,) False: frame had NaN/inf or saturated bins (its map is zeros)
    grid: Grid
    method: str
    detections: list[Detection] | None = None
    noise: np.ndarray | None = None  # (ny, nx) per-pixel noise of the map without touch

    def touches_json(self) -> dict:
        """``{"frames": [{"index": i, "touches": [{"x_m", "y_m", "strength"}]}]}``."""
        frames = []
        for i, det in enumerate(self.detections or []):
            frames.append(
                {
                    "index": i,
                    "touches": [{"x_m": t["x_m"], "y_m": t["y_m"], "strength": t["strength"]} for t in det.touches],
                }
            )
        return {"frames": frames}


def _unit_peak(optical: OpticalParams, bin_width_s: float, delay_s: float) -> float:
    """Map value at a unit-strength point contact, averaged over its phase within a bin:
    the binned response, linearly interpolated at the peak delay."""

    def binned(t):
        return optical.binned_response(t, bin_width_s)

    # Bin centres at (k - phase) * width after the event; interpolate at the delay.
    phase = np.linspace(0, 1, 16, endpoint=False)
    u = delay_s / bin_width_s + phase
    k0 = np.floor(u)
    f = u - k0
    a = binned((k0 - phase) * bin_width_s)
    b = binned((k0 + 1 - phase) * bin_width_s)
    vals = (1 - f) * a + f * b
    return float(np.mean(vals))


# The maps keep XLA's fusion emitters on a CPU (2x the frames per second of the elemental ones
# the CLI otherwise selects: compile_cache.fusion_jit).
@fusion_jit
def _map_one(corrector, operator, h):
    return operator(corrector(h)[0])


@fusion_jit
def _map_batch(corrector, operator, h):
    # Blocks of 16 frames in sequence: a (16, pixels) working set stays in cache, twice the
    # throughput of one gather over the whole batch (experiments/bench_invert.py).
    def block(x):
        corrected, ok = corrector(x)
        return operator(corrected), ok

    return jax.lax.map(block, h, batch_size=16)


@dataclass
class Inverter:
    """Precomputed inversion of one scene (see :func:`build_inverter`)."""

    scene: Scene
    options: InvertOptions
    optical: OpticalParams
    corrector: Corrector
    operator: MapOperator
    grid: Grid
    noise: np.ndarray  # (ny, nx)
    strength_scale: float
    reconstructor: object | None = None
    floor: np.ndarray | None = None  # (ny, nx) mean no-touch map (CFAR detection subtracts it)

    # Module-level jitted functions: inverters of the same shapes share one compilation.
    _frame = staticmethod(_map_one)
    _batch = staticmethod(_map_batch)

    def maps(self, histograms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Maps (F, ny, nx) and ok flags (F,) for histograms (F, S, Z, B)."""
        h = np.asarray(histograms)
        if h.ndim != 4 or h.shape[1:] != self.scene.shape:
            raise InversionError(f"histograms have shape {h.shape[1:]} per frame, the scene {self.scene.shape}")
        if self.reconstructor is not None:
            return self.reconstructor.maps(h)
        out, oks = [], []
        n = self.options.batch
        for i in range(0, len(h), n):
            chunk = h[i : i + n]
            pad = n - len(chunk) if len(h) > n else 0  # one compiled shape for every chunk
            if pad:
                chunk = np.concatenate([chunk, np.zeros((pad, *chunk.shape[1:]))])
            m, ok = self._batch(self.corrector, self.operator, jnp.asarray(chunk, self.corrector.gain.dtype))
            out.append(np.asarray(m)[: n - pad])
            oks.append(np.asarray(ok)[: n - pad])
        return np.concatenate(out), np.concatenate(oks)

    def map_frame(self, histogram) -> jax.Array:
        """One frame (S, Z, B) -> map (ny, nx), jitted (what the benchmark times)."""
        return self._frame(self.corrector, self.operator, histogram)

    def detect(self, tactile_map: np.ndarray) -> Detection:
        return detect(
            tactile_map,
            self.grid,
            self.options.detect,
            noise=self.noise,
            strength_scale=self.strength_scale,
            floor=self.floor,
        )

    def process(self, histograms: np.ndarray, *, detect: bool = True) -> ProcessResult:
        maps, ok = self.maps(histograms)
        dets = [self.detect(m) if good else Detection() for m, good in zip(maps, ok)] if detect else None
        return ProcessResult(
            maps=maps, ok=ok, grid=self.grid, method=self.options.method, detections=dets, noise=self.noise
        )


def _corrected_variance(corrector: Corrector, baseline: np.ndarray, n_baseline: int) -> np.ndarray:
    """Variance (S, Z, B) of each corrected bin without touch under Poisson noise:
    ``gain^2 B (1 + 1/N)`` (photon noise of the frame and of the N-frame baseline mean), plus
    the ambient estimate's own noise."""
    g = np.asarray(corrector.gain, float)
    var_h = (
        g**2
        * np.maximum(baseline, 1.0)
        * ((1.0 + 1.0 / n_baseline) if corrector.method in ("baseline", "full") else 1.0)
    )
    e = np.asarray(corrector.early, float)
    if corrector.method in ("baseline", "full") and e.any():  # the ambient estimate's own noise
        var_h = var_h + g**2 * (np.maximum(baseline, 1.0) @ e**2)[..., None] * (1.0 + 1.0 / n_baseline)
    return var_h


def _noise_map(corrector: Corrector, operator: MapOperator, baseline: np.ndarray, n_baseline: int) -> np.ndarray:
    """Per-pixel std of the map under Poisson noise without touch: the projection is linear,
    so var(map) = W^2 var(h) (clipping of negative signals ignored)."""
    var_flat = _corrected_variance(corrector, baseline, n_baseline).ravel()
    w = np.asarray(operator.weight, float)
    var = np.sum(w**2 * var_flat[np.asarray(operator.index)], axis=-1)
    return np.sqrt(var).reshape(operator.ny, operator.nx)


def _ensemble_floor(
    corrector: Corrector,
    operator: MapOperator,
    baseline: np.ndarray,
    n_baseline: int,
    frames: np.ndarray | None,
    n_draws: int,
    seed: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std (ny, nx) of no-touch maps: the floor a constant-false-alarm-rate detector
    divides by. From the recorded baseline frames when there are enough (whatever their noise
    is), else from Poisson draws around the baseline mean. Includes the clipping of negative
    signals, which the linear noise map ignores (it makes the no-touch map positive on
    average and narrower than the linear std). The std is scaled by sqrt(1 + 1/N): every touch
    frame is compared with the same N-frame mean, whose own noise adds once more."""
    if frames is not None and len(frames) >= 16:
        h = np.asarray(frames, float)
        inflate = math.sqrt((1.0 + 1.0 / n_baseline) / max(1.0 - 1.0 / len(h), 1e-9))
    else:
        rng = np.random.default_rng(seed)
        h = rng.poisson(np.maximum(np.asarray(baseline, float), 0.0), size=(n_draws, *np.shape(baseline))).astype(float)
        inflate = math.sqrt(1.0 + 1.0 / n_baseline)
    maps = []
    for i in range(0, len(h), 32):
        chunk = h[i : i + 32]
        n = len(chunk)
        if n < 32:  # one compiled shape
            chunk = np.concatenate([chunk, np.repeat(chunk[-1:], 32 - n, 0)])
        m, _ = _map_batch(corrector, operator, jnp.asarray(chunk, corrector.gain.dtype))
        maps.append(np.asarray(m, float)[:n])
    maps = np.concatenate(maps)
    mean = maps.mean(0)
    std = maps.std(0, ddof=1) * inflate
    return mean, std


def build_inverter(
    scene: Scene,
    baseline: np.ndarray | None,
    options: InvertOptions = InvertOptions(),
    optical: OpticalParams | None = None,
    *,
    n_baseline: int = 1,
    baseline_frames: np.ndarray | None = None,
) -> Inverter:
    """Precompute the inversion of ``scene``.

    **Arguments:**

    - ``scene``: the setup (its contacts are ignored).
    - ``baseline``: mean no-touch histogram (S, Z, B).
    - ``options``: :class:`InvertOptions`.
    - ``optical``: calibrated optics (default: the scene's stated values).
    - ``n_baseline``: frames averaged into ``baseline`` (for the noise map).
    - ``baseline_frames``: the baseline's frames (F, S, Z, B), if at hand: with
      ``options.detect.cfar`` the no-touch floor is measured on them (their real noise)
      instead of on Poisson draws around ``baseline``.
    """
    optical = OpticalParams.from_scene(scene) if optical is None else optical
    dtype = options.jnp_dtype
    if options.method != "model" and options.reconstruct != ReconstructOptions():
        raise ConfigError(f"reconstruct: options of the model-based method; method is {options.method!r}")
    corr_method = "full" if options.method == "model" else options.method
    corr_opts = CorrectionOptions(**{**options.correction.__dict__, "method": corr_method})
    corrector = build_corrector(scene, baseline, optical, corr_opts, dtype)
    base = np.zeros(scene.shape) if baseline is None else np.asarray(baseline, float)
    variance = _corrected_variance(corrector, base, n_baseline)
    operator, grid = build_map_operator(scene, optical, options.maps, dtype, variance=variance)
    noise = _noise_map(corrector, operator, base, n_baseline)
    delay = optical.response_delay_s(scene.sensor.bin_width_s) if options.maps.response_delay else 0.0
    scale = 1.0 / _unit_peak(optical, scene.sensor.bin_width_s, delay) if corr_method in ("full", "decay") else 1.0
    inv = Inverter(scene, options, optical, corrector, operator, grid, noise, scale)
    if options.method == "model":
        from .reconstruct import build_reconstructor

        rec = options.reconstruct
        inv.reconstructor = build_reconstructor(scene, base, optical, rec, n_baseline=n_baseline)
        inv.grid = inv.reconstructor.grid
        inv.noise = inv.reconstructor.noise_map()
        inv.strength_scale = 1.0
        # Strengths sit on the forward model's amplitude scale, which a rig need not share: the
        # threshold is in noise units (rec.n_sigma times each cell's strength noise) and relative
        # to the frame's strongest contact; min_strength adds an absolute floor (default none).
        inv.options = dataclasses.replace(
            options,
            detect=dataclasses.replace(
                options.detect,
                threshold=rec.min_strength,
                relative=rec.relative,
                n_sigma=rec.n_sigma,
                cfar=False,
            ),
        )
    elif options.detect.cfar and corr_method in ("baseline", "full"):
        # Only for the methods that use a baseline: subtracting the mean no-touch map would
        # be a baseline removal, which raw and decay (seed 000's ablations) must not have.
        inv.floor, inv.noise = _ensemble_floor(
            corrector,
            operator,
            base,
            n_baseline,
            baseline_frames,
            options.detect.cfar_draws,
            options.detect.cfar_seed,
        )
    return inv


def load_inputs(
    touch_path,
    baseline_path,
    calibration_path=None,
    *,
    allow_unconverged: bool = False,
    allow_other_scene: bool = False,
    sensor_path=None,
) -> tuple[Capture, Capture, OpticalParams]:
    """Read and check the captures and calibration the commands take (a calibration that did
    not converge, was refused, or is of another scene is refused unless allowed).

    ``sensor_path``: a fitted sensor model (``tofjax sensor fit``) whose bin width replaces the
    captures' nominal one, as ``tofjax calibrate --sensor`` does; a calibration made with it has
    that bin width in its scene fingerprint."""
    touch = read_capture(touch_path)
    base = read_capture(baseline_path)
    base.scene.require_waveguide("touch inversion", str(baseline_path))
    check_compatible(touch.scene, base.scene)
    _check_baseline_counts(base, baseline_path)
    if sensor_path is not None:
        touch = dataclasses.replace(touch, scene=touch.scene.with_sensor_model(sensor_path))
        base = dataclasses.replace(base, scene=base.scene.with_sensor_model(sensor_path))
    optical = load_optics(base.scene, calibration_path, allow_unconverged=allow_unconverged,
                          allow_other_scene=allow_other_scene)
    return touch, base, optical


def _check_baseline_counts(base: Capture, path) -> None:
    """Refuse a baseline whose counts no raw histogram of its sensor has: above the saturation limit
    (not this sensor's data), or at it (a saturated bin's mean is wrong, and a saturated baseline hides
    every touch: the inversion found 0 touches and said nothing)."""
    h = base.histograms
    sat = base.scene.sensor.saturation_counts
    if (h > sat).any():
        raise InversionError(f"{path}: counts up to {float(h.max()):.3g}, above the sensor's limit ({sat:g}): "
                             "not raw histograms of this sensor")
    n_sat = int((h >= sat).sum())
    if n_sat:
        raise InversionError(f"{path}: {n_sat} baseline bins at the saturation limit ({sat:g} counts): "
                             "lower the sensor's iterations or gain and record the baseline again")


def load_optics(
    scene: Scene, calibration_path=None, *, allow_unconverged: bool = False, allow_other_scene: bool = False
) -> OpticalParams:
    """The optics the commands use for ``scene``: a calibration JSON's (refused, one line, if it did not
    converge, was refused, or is of another scene, unless allowed), else the scene's stated optics with a
    warning. ``detect``, ``process`` and ``sensitivity`` read a calibration through this."""
    if calibration_path is None:
        warn_no_calibration(scene)
        return OpticalParams.from_scene(scene)
    return OpticalParams.from_calibration(
        calibration_path, scene, allow_unconverged=allow_unconverged, allow_other_scene=allow_other_scene
    )


def process_captures(
    touch: Capture,
    baseline: Capture,
    options: InvertOptions = InvertOptions(),
    optical: OpticalParams | None = None,
    *,
    detect: bool = True,
) -> ProcessResult:
    """The whole job on captures: check them, build the inversion, process every frame."""
    check_compatible(touch.scene, baseline.scene)
    inv = build_inverter(
        baseline.scene, baseline.mean(), options, optical, n_baseline=baseline.n_frames, baseline_frames=baseline.histograms
    )
    return inv.process(touch.histograms, detect=detect)


def write_maps(path: str | Path, result: ProcessResult, scene: Scene, optical: OpticalParams) -> Path:
    """Maps, flags, grid and detections as HDF5 (format ``tofjax.maps`` version 1)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "tofjax.maps"
        f.attrs["version"] = 1
        f.attrs["method"] = result.method
        f.attrs["scene"] = scene.to_json()
        f.attrs["optics_source"] = optical.source
        d = f.create_dataset("maps", data=np.asarray(result.maps, np.float32), compression="gzip")
        d.attrs["axes"] = "frame, y, x"
        f["ok"] = result.ok
        f["x_m"] = result.grid.x
        f["y_m"] = result.grid.y
        if result.noise is not None:
            f["noise"] = result.noise
        if result.detections is not None:
            f["labels"] = np.stack(
                [d.labels if d.labels is not None else np.zeros(result.maps.shape[1:], int) for d in result.detections]
            ).astype(np.int32)
            rows = [
                (i, t["x_m"], t["y_m"], t["strength"], t["component"])
                for i, d in enumerate(result.detections)
                for t in d.touches
            ]
            f["touches"] = np.array(rows, float).reshape(-1, 5)
            f["touches"].attrs["columns"] = "frame, x_m, y_m, strength, component"
    return path
