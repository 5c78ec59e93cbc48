"""Features of seed 001 (section III-A/B): the contact window, its baseline and its derivative.

For every frame the *raw feature vector* is 3 x (beams x bins) values of one sensor:

- ``window``: counts of every beam (zone) in ``bins`` consecutive bins around
  the contact (Eq. 1-2; found from the training data by :func:`find_window`);
- ``derivative``: the same values differentiated in time by the second-order
  backward difference of Eq. 6;
- ``baseline``: the mean of the capture's first ``baseline_frames`` frames
  (nothing touching) in the same window.

The input variants use parts of it: ``single`` the window, ``dual`` window +
baseline, ``derivative`` window + derivative + baseline. :class:`Scaling` holds
the min-max normalisation (fitted on the training split only and stored with the
model).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..capture import Capture, CaptureError
from ..config import ConfigError
from ..errors import UserError

__all__ = [
    "VARIANTS",
    "Dataset",
    "FeatureConfig",
    "FeatureError",
    "Scaling",
    "Window",
    "backward_derivative",
    "build_dataset",
    "capture_baseline_frames",
    "decay_gain",
    "find_window",
    "raw_features",
    "split_indices",
]

VARIANTS = ("single", "dual", "derivative")


class FeatureError(UserError):
    """Captures that cannot give the features a model needs (shape, baseline, window)."""


@dataclass(frozen=True)
class FeatureConfig:
    """How features are made.

    **Arguments:**

    - ``variant``: ``single`` (20 values), ``dual`` (+ baseline) or ``derivative`` (+ Eq. 6).
    - ``bins``: bins in the contact window (seed 001: 5).
    - ``sensor``, ``start_bin``: fix the window instead of finding it from the data.
    - ``baseline_frames``: no-touch frames at the start of each capture; default: the
      capture's own ``truth.baseline_frames`` (set by the generator).
    - ``normalisation``: ``global`` (one min and max over all window values, as seed 001) or
      ``per_feature``.
    - ``min_bin``: the earliest bin the window may start at (skips the light-entry peak).
    """

    variant: str = "derivative"
    bins: int = 5
    sensor: int | None = None
    start_bin: int | None = None
    baseline_frames: int | None = None
    normalisation: str = "global"
    min_bin: int = 3

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ConfigError(f"variant: must be one of {', '.join(VARIANTS)}, got {self.variant!r}")
        if self.bins < 1:
            raise ConfigError(f"bins: must be >= 1, got {self.bins!r}")
        if self.normalisation not in ("global", "per_feature"):
            raise ConfigError(f"normalisation: must be global or per_feature, got {self.normalisation!r}")
        if self.baseline_frames is not None and self.baseline_frames < 1:
            raise ConfigError(f"baseline_frames: must be >= 1, got {self.baseline_frames!r}")


@dataclass(frozen=True)
class Window:
    """Where the contact shows: ``bins`` bins from ``start_bin`` of every zone of ``sensor``."""

    sensor: int
    start_bin: int
    bins: int
    zones: int
    #: The capture shape the window was found on: (sensors, zones, bins).
    shape: tuple[int, int, int]

    @property
    def size(self) -> int:
        return self.zones * self.bins

    def check(self, shape, source: str = "capture") -> None:
        if tuple(shape) != tuple(self.shape):
            raise FeatureError(
                f"{source}: histograms are (sensors, zones, bins) = {tuple(shape)} but the model was trained on "
                f"{tuple(self.shape)} (window: sensor {self.sensor}, bins {self.start_bin}-{self.start_bin + self.bins - 1})"
            )

    def take(self, hist: np.ndarray) -> np.ndarray:
        """(frames, S, Z, B) -> (frames, zones * bins), beam-major as Eq. 2."""
        w = hist[:, self.sensor, :, self.start_bin : self.start_bin + self.bins]
        return w.reshape(w.shape[0], -1)

    def to_json(self) -> dict:
        return {"sensor": self.sensor, "start_bin": self.start_bin, "bins": self.bins, "zones": self.zones, "shape": list(self.shape)}

    @classmethod
    def from_json(cls, d: dict) -> "Window":
        return cls(d["sensor"], d["start_bin"], d["bins"], d["zones"], tuple(d["shape"]))


def capture_baseline_frames(cap: Capture, config: FeatureConfig, source: str = "capture") -> int:
    n = config.baseline_frames if config.baseline_frames is not None else cap.truth.get("baseline_frames")
    if n is None:
        raise FeatureError(
            f"{source}: how many no-touch frames start the capture is unknown; set features.baseline_frames "
            "(training) or --baseline-frames (tofjax predict)"
        )
    n = int(n)
    if n < 1 or n > cap.n_frames:
        raise FeatureError(f"{source}: baseline_frames = {n} but the capture has {cap.n_frames} frames")
    return n


def _baseline(hist: np.ndarray, n: int) -> np.ndarray:
    base = hist[:n]
    ok = np.isfinite(base).all(axis=tuple(range(1, base.ndim)))
    if not ok.any():
        raise FeatureError("every baseline frame is NaN")
    return base[ok].mean(axis=0)


def find_window(captures: list[Capture], config: FeatureConfig) -> Window:
    """The sensor and ``bins``-bin window whose counts follow the force most closely.

    Every bin of every zone is scored by the correlation of its baseline-subtracted
    counts with the force channel over all training frames; the window with the
    largest summed score (over its bins and the sensor's zones) wins. Bins before
    ``min_bin`` (the light-entry peak) are not considered.
    """
    if not captures:
        raise FeatureError("no training captures")
    shape = captures[0].scene.shape
    S, Z, B = shape
    if config.bins > B:
        raise FeatureError(f"features.bins = {config.bins} is more than the {B} bins of the captures")
    deltas, forces = [], []
    for i, cap in enumerate(captures):
        if cap.scene.shape != shape:
            raise FeatureError(f"training capture {i}: shape {cap.scene.shape} differs from the first one's {shape}")
        if cap.force is None:
            raise FeatureError(f"training capture {i}: no force channel")
        nb = capture_baseline_frames(cap, config, f"training capture {i}")
        h = cap.histograms
        deltas.append(h - _baseline(h, nb)[None])
        forces.append(cap.force)
    d = np.concatenate(deltas)
    f = np.concatenate(forces)
    ok = np.isfinite(f) & np.isfinite(d).all(axis=(1, 2, 3))
    d, f = d[ok], f[ok]
    if f.size < 3 or np.std(f) == 0:
        raise FeatureError("the training force does not vary: cannot find where the contact shows")
    dc = d - d.mean(0)
    fc = f - f.mean()
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.einsum("n,nszb->szb", fc, dc) / (np.sqrt((dc**2).sum(0)) * np.sqrt((fc**2).sum()) + 1e-30)
    score = np.nan_to_num(np.abs(corr)).sum(axis=1)  # (S, B): summed over the beams
    lo = max(config.min_bin, 0)
    sensors = range(S) if config.sensor is None else [config.sensor]
    if config.sensor is not None and not 0 <= config.sensor < S:
        raise FeatureError(f"features.sensor = {config.sensor} but the captures have {S} sensors")
    best = None
    for s in sensors:
        if config.start_bin is not None:
            starts = [config.start_bin]
        else:
            starts = range(lo, B - config.bins + 1)
        for b in starts:
            if b < 0 or b + config.bins > B:
                raise FeatureError(f"features.start_bin = {b}: the window runs outside the {B} bins")
            v = score[s, b : b + config.bins].sum()
            if best is None or v > best[0]:
                best = (v, s, b)
    _, s, b = best
    return Window(int(s), int(b), config.bins, Z, shape)


def backward_derivative(x: np.ndarray, dt_s: float) -> np.ndarray:
    """Eq. 6: ``(3 x(t) - 4 x(t - dT) + x(t - 2 dT)) / (2 dT)`` along axis 0.

    Exact for quadratics. The first two frames have no history: they get 0 (the
    signal is taken as static before the capture starts).
    """
    out = np.zeros_like(x, dtype=np.float64)
    out[2:] = (3.0 * x[2:] - 4.0 * x[1:-1] + x[:-2]) / (2.0 * dt_s)
    return out


def frame_period(cap: Capture) -> float:
    t = cap.timestamps
    if t.size < 2:
        return 1.0 / 9.0
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        raise CaptureError("timestamps do not increase")
    return dt


def raw_features(cap: Capture, window: Window, config: FeatureConfig, source: str = "capture"):
    """Raw (unnormalised) features of every frame: ``(frames, 3 * window.size)`` and a validity mask.

    Columns: window, derivative (counts/s), baseline. A frame is invalid when it or
    (for the derivative) one of its two predecessors has a non-finite value.
    """
    window.check(cap.scene.shape, source)
    nb = capture_baseline_frames(cap, config, source)
    w = window.take(cap.histograms).astype(np.float64)
    base = window.take(_baseline(cap.histograms, nb)[None])[0]
    finite = np.isfinite(w).all(1)
    wz = np.where(finite[:, None], w, 0.0)
    d = backward_derivative(wz, frame_period(cap))
    valid = finite.copy()
    if config.variant == "derivative":
        bad = ~finite
        valid[1:] &= ~bad[:-1]
        valid[2:] &= ~bad[:-2]
    x = np.concatenate([w, d, np.broadcast_to(base, w.shape)], 1)
    return x, valid


@dataclass
class Scaling:
    """Min-max normalisation of the window (and the derivative by the same scale) and of the force."""

    lo: np.ndarray  # (window.size,)
    hi: np.ndarray
    force_lo: float
    force_hi: float

    @classmethod
    def fit(cls, x_window: np.ndarray, force: np.ndarray, normalisation: str) -> "Scaling":
        if normalisation == "global":
            lo = np.full(x_window.shape[1], x_window.min())
            hi = np.full(x_window.shape[1], x_window.max())
        else:
            lo, hi = x_window.min(0), x_window.max(0)
        hi = np.where(hi > lo, hi, lo + 1.0)
        return cls(lo, hi, float(force.min()), float(max(force.max(), force.min() + 1e-9)))

    def to_json(self) -> dict:
        return {"lo": self.lo.tolist(), "hi": self.hi.tolist(), "force_lo": self.force_lo, "force_hi": self.force_hi}

    @classmethod
    def from_json(cls, d: dict) -> "Scaling":
        return cls(np.asarray(d["lo"]), np.asarray(d["hi"]), d["force_lo"], d["force_hi"])


def select(raw, variant: str, n: int, xp=np):
    """The model input of ``variant`` from raw features (already normalised or not): (..., n_inputs)."""
    w, d, b = raw[..., :n], raw[..., n : 2 * n], raw[..., 2 * n : 3 * n]
    if variant == "single":
        return w
    if variant == "dual":
        return xp.concatenate([w, b], -1)
    return xp.concatenate([w, d, b], -1)


def normalise(raw, scaling_lo, scaling_hi, xp=np):
    """Min-max scale the window and baseline; scale the derivative by the same factor (Eq. 6 of the scaled data)."""
    n = scaling_lo.shape[-1]
    span = scaling_hi - scaling_lo
    w = (raw[..., :n] - scaling_lo) / span
    d = raw[..., n : 2 * n] / span
    b = (raw[..., 2 * n : 3 * n] - scaling_lo) / span
    return xp.concatenate([w, d, b], -1)


@dataclass
class Dataset:
    """Frames of many captures, with where each comes from."""

    raw: np.ndarray  # (n, 3 * window.size)
    force: np.ndarray  # (n,)
    velocity: np.ndarray  # (n,) mm/s, NaN where unknown
    time: np.ndarray  # (n,) s within its capture
    capture: np.ndarray  # (n,) index of the capture
    n_nan_frames: int  # frames with a non-finite histogram window or force
    n_dropped: int  # frames dropped (NaN frames and, for the derivative, their next two)

    def subset(self, idx) -> "Dataset":
        return Dataset(self.raw[idx], self.force[idx], self.velocity[idx], self.time[idx], self.capture[idx], 0, 0)

    def __len__(self) -> int:
        return int(self.force.shape[0])


def build_dataset(captures: list[Capture], window: Window, config: FeatureConfig, *, need_force: bool = True, names=None) -> Dataset:
    """Features, force and labels of every valid frame of ``captures``."""
    parts = []
    n_nan = n_drop = 0
    for i, cap in enumerate(captures):
        src = names[i] if names else f"capture {i}"
        if need_force and cap.force is None:
            raise FeatureError(f"{src}: no force channel")
        x, valid = raw_features(cap, window, config, src)
        f = cap.force if cap.force is not None else np.full(cap.n_frames, np.nan)
        bad = ~np.isfinite(x[:, : window.size]).all(1) | (need_force & ~np.isfinite(f))
        n_nan += int(bad.sum())
        keep = valid & ~bad if need_force else valid
        n_drop += int((~keep).sum())
        v = float(cap.truth.get("velocity_mm_s", math.nan))
        parts.append((x[keep], f[keep], np.full(keep.sum(), v), cap.timestamps[keep], np.full(keep.sum(), i)))
    cat = [np.concatenate(p) for p in zip(*parts)]
    return Dataset(*cat, n_nan_frames=n_nan, n_dropped=n_drop)


def split_indices(n: int, fractions=(0.8, 0.1, 0.1), seed: int = 0):
    """Random train / validation / hold-out indices (seed 001: 80/10/10 of the samples)."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    a = int(round(fractions[0] * n))
    b = a + int(round(fractions[1] * n))
    return np.sort(perm[:a]), np.sort(perm[a:b]), np.sort(perm[b:])


def decay_gain(scene, params, window: Window) -> np.ndarray:
    """Decay correction of the window: ``1 / (G(r) T(r))`` at each bin's range, (zones * bins,).

    A contact farther away returns fewer photons (seed 000 Eq. 4-5); multiplying
    the baseline-subtracted window by this gain makes the touch signal of one
    force roughly the same at any distance (seed 001, section V). Normalised to 1
    at the window's first bin. This is the one place the force package computes
    it: swap in ``tofjax.invert``'s correction here when it lands.
    """
    from ..model.components import SPEED_OF_LIGHT_M_PER_S, falloff, transmittance

    bw = scene.sensor.bin_width_s
    t = (window.start_bin + np.arange(window.bins) + 0.5) * bw
    c1 = SPEED_OF_LIGHT_M_PER_S / float(params.n1)
    r = np.maximum(0.5 * c1 * (t - float(params.emission_time_s)), 1e-3)
    mu_t = float(params.mu_s_per_m) + float(params.mu_a_per_m)
    g = np.asarray(falloff(r, float(params.near_field_m))) * np.asarray(transmittance(r, mu_t))
    gain = g[0] / g
    return np.tile(gain, window.zones)
