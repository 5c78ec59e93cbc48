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

With ``source = "inversion"`` (issue 17: force anywhere on the skin) the window is
not fixed: :class:`ContactInverter` applies the touch inversion's full correction
(``tofjax.invert``, with a calibration's optics), locates each contact and its
range, and takes the window of corrected signal at the contact; the contact's range
and the ambient level follow as context inputs (columns after ``3 x window``), and a
capture with several contacts gives one row per contact and frame.
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
    "ContactInverter",
    "Contact",
    "capture_rows",
    "find_window",
    "inverter_for",
    "raw_features",
    "split_indices",
]

VARIANTS = ("single", "dual", "derivative")
SOURCES = ("counts", "inversion")
#: Context inputs of the inversion features: range (m), log10 ambient counts.
N_CONTEXT = 2


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
    #: ``counts``: seed 001's fixed window of raw counts; ``inversion``: the located contact's window
    #: of the touch inversion's fully corrected signal (see :class:`ContactInverter`).
    source: str = "counts"
    #: With ``inversion``: the contact's position (range, zone centroid) and the ambient level are inputs.
    position: bool = True
    #: With ``inversion``: a calibration JSON (``tofjax calibrate``) whose optics correct the signal;
    #: default the scene's stated optics.
    calibration: str | None = None
    #: With ``inversion``: contacts to locate per capture (default: the capture's ``truth.n_contacts``, else 1).
    contacts: int | None = None
    #: With ``inversion``: ``sum`` the zones (the contact's whole return, whichever zones see it) or keep ``each``.
    zones: str = "sum"
    #: Frames of the derivative: 3 is Eq. 6; more fit a quadratic by least squares (less noise).
    derivative_frames: int = 3

    def __post_init__(self):
        if self.source not in SOURCES:
            raise ConfigError(f"source: must be one of {', '.join(SOURCES)}, got {self.source!r}")
        if self.contacts is not None and not 1 <= self.contacts <= 4:
            raise ConfigError(f"contacts: must be 1-4, got {self.contacts!r}")
        if not 3 <= self.derivative_frames <= 15:
            raise ConfigError(f"derivative_frames: must be 3 (Eq. 6) to 15, got {self.derivative_frames!r}")
        if self.zones not in ("sum", "each"):
            raise ConfigError(f"zones: must be sum or each, got {self.zones!r}")
        if self.source == "counts" and (self.calibration is not None or self.contacts is not None or self.zones != "sum"):
            raise ConfigError("calibration, contacts, zones: options of source = \"inversion\"")
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

    With ``source = "inversion"`` the window follows each located contact instead:
    :func:`find_inversion_window`.

    Every bin of every zone is scored by the correlation of its baseline-subtracted
    counts with the force channel over all training frames; the window with the
    largest summed score (over its bins and the sensor's zones) wins. Bins before
    ``min_bin`` (the light-entry peak) are not considered.
    """
    if config.source == "inversion":
        return find_inversion_window(captures, config)
    shape = _training_shape(captures, config)
    S, Z, B = shape
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


def backward_derivative(x: np.ndarray, dt_s: float, frames: int = 3) -> np.ndarray:
    """The time derivative at each frame from the last ``frames`` frames, along axis 0.

    ``frames = 3`` is Eq. 6, ``(3 x(t) - 4 x(t - dT) + x(t - 2 dT)) / (2 dT)``; more frames
    fit a quadratic to them by least squares and take its slope at the latest frame (still
    exact for quadratics, less photon noise, no delay for a signal that is locally
    quadratic). The first ``frames - 1`` frames have no history: they get 0 (the signal is
    taken as static before the capture starts).
    """
    tau = np.arange(-(frames - 1), 1, dtype=np.float64)
    weights = np.linalg.pinv(np.stack([np.ones_like(tau), tau, tau**2], 1))[1]  # slope at tau = 0
    out = np.zeros_like(x, dtype=np.float64)
    n = x.shape[0]
    if n >= frames:
        for i, w in enumerate(weights):
            out[frames - 1 :] += w * x[i : n - frames + 1 + i]
        out[frames - 1 :] /= dt_s
    return out


def _derivative_valid(valid: np.ndarray, finite: np.ndarray, frames: int) -> np.ndarray:
    """A derivative needs its frame and the ``frames - 1`` before it finite."""
    valid = valid.copy()
    for k in range(1, frames):
        valid[k:] &= finite[:-k]
    return valid


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
    d = backward_derivative(wz, frame_period(cap), config.derivative_frames)
    valid = finite.copy()
    if config.variant == "derivative":
        valid = _derivative_valid(valid, finite, config.derivative_frames)
    x = np.concatenate([w, d, np.broadcast_to(base, w.shape)], 1)
    return x, valid


@dataclass
class Scaling:
    """Min-max normalisation of the window (and the derivative by the same scale), of the
    context inputs (per input) and of the force."""

    lo: np.ndarray  # (window.size,)
    hi: np.ndarray
    force_lo: float
    force_hi: float
    extra_lo: np.ndarray = None  # (context inputs,): empty for the counts features
    extra_hi: np.ndarray = None
    #: The baseline's own scale (inversion features: the window is corrected signal, the baseline
    #: counts); None: the window's (seed 001, both are counts).
    base_lo: np.ndarray | None = None
    base_hi: np.ndarray | None = None

    def __post_init__(self):
        if self.extra_lo is None:
            self.extra_lo, self.extra_hi = np.zeros(0), np.ones(0)

    @classmethod
    def fit(
        cls, x_window: np.ndarray, force: np.ndarray, normalisation: str, extra: np.ndarray | None = None,
        base: np.ndarray | None = None,
    ) -> "Scaling":
        if normalisation == "global":
            lo = np.full(x_window.shape[1], x_window.min())
            hi = np.full(x_window.shape[1], x_window.max())
        else:
            lo, hi = x_window.min(0), x_window.max(0)
        hi = np.where(hi > lo, hi, lo + 1.0)
        if extra is None or extra.shape[1] == 0:
            elo, ehi = np.zeros(0), np.ones(0)
        else:
            elo, ehi = extra.min(0), extra.max(0)
            ehi = np.where(ehi > elo, ehi, elo + 1.0)
        blo = bhi = None
        if base is not None:
            blo, bhi = np.full(base.shape[1], base.min()), np.full(base.shape[1], base.max())
            bhi = np.where(bhi > blo, bhi, blo + 1.0)
        return cls(lo, hi, float(force.min()), float(max(force.max(), force.min() + 1e-9)), elo, ehi, blo, bhi)

    @property
    def base(self) -> tuple[np.ndarray, np.ndarray]:
        return (self.lo, self.hi) if self.base_lo is None else (self.base_lo, self.base_hi)

    def to_json(self) -> dict:
        d = {"lo": self.lo.tolist(), "hi": self.hi.tolist(), "force_lo": self.force_lo, "force_hi": self.force_hi,
             "extra_lo": self.extra_lo.tolist(), "extra_hi": self.extra_hi.tolist()}
        if self.base_lo is not None:
            d |= {"base_lo": self.base_lo.tolist(), "base_hi": self.base_hi.tolist()}
        return d

    @classmethod
    def from_json(cls, d: dict) -> "Scaling":
        base = (np.asarray(d["base_lo"], float), np.asarray(d["base_hi"], float)) if "base_lo" in d else (None, None)
        return cls(np.asarray(d["lo"]), np.asarray(d["hi"]), d["force_lo"], d["force_hi"],
                   np.asarray(d.get("extra_lo", []), float), np.asarray(d.get("extra_hi", []), float), *base)

    def normalise(self, raw, xp=np):
        return normalise(raw, self.lo, self.hi, xp, self.extra_lo, self.extra_hi, *self.base)


def select(raw, variant: str, n: int, xp=np):
    """The model input of ``variant`` from raw features (already normalised or not): (..., n_inputs).

    Context inputs (the contact's position and the ambient level, columns after ``3 n``)
    follow the variant's inputs.
    """
    w, d, b, e = raw[..., :n], raw[..., n : 2 * n], raw[..., 2 * n : 3 * n], raw[..., 3 * n :]
    if variant == "single":
        return xp.concatenate([w, e], -1)
    if variant == "dual":
        return xp.concatenate([w, b, e], -1)
    return xp.concatenate([w, d, b, e], -1)


def normalise(raw, scaling_lo, scaling_hi, xp=np, extra_lo=None, extra_hi=None, base_lo=None, base_hi=None):
    """Min-max scale the window and baseline (by the window's scale unless ``base_lo``/``base_hi``
    are given); scale the derivative by the window's factor (Eq. 6 of the scaled data); min-max
    scale the context inputs each on its own."""
    n = scaling_lo.shape[-1]
    span = scaling_hi - scaling_lo
    w = (raw[..., :n] - scaling_lo) / span
    d = raw[..., n : 2 * n] / span
    if base_lo is None:
        base_lo, base_hi = scaling_lo, scaling_hi
    b = (raw[..., 2 * n : 3 * n] - base_lo) / (base_hi - base_lo)
    parts = [w, d, b]
    if extra_lo is not None and extra_lo.shape[-1]:
        parts.append((raw[..., 3 * n :] - extra_lo) / (extra_hi - extra_lo))
    return xp.concatenate(parts, -1)


@dataclass
class Dataset:
    """Rows (one per frame and contact) of many captures, with where each comes from."""

    raw: np.ndarray  # (n, 3 * window.size + context inputs)
    force: np.ndarray  # (n,)
    velocity: np.ndarray  # (n,) mm/s, NaN where unknown
    time: np.ndarray  # (n,) s within its capture
    capture: np.ndarray  # (n,) index of the capture
    n_nan_frames: int  # frames with a non-finite histogram window or force
    n_dropped: int  # frames dropped (NaN frames and, for the derivative, their next two)
    #: The capture's ``truth.split`` (``train``, ``test`` (seen positions), ``unseen``, ``two_contacts``).
    split: np.ndarray = None

    def __post_init__(self):
        if self.split is None:
            self.split = np.full(len(self.force), "test", dtype=object)

    def subset(self, idx) -> "Dataset":
        return Dataset(self.raw[idx], self.force[idx], self.velocity[idx], self.time[idx], self.capture[idx], 0, 0,
                       self.split[idx])

    def __len__(self) -> int:
        return int(self.force.shape[0])


def build_dataset(captures: list[Capture], window: Window, config: FeatureConfig, *, need_force: bool = True, names=None) -> Dataset:
    """Features, force and labels of every valid frame (and contact) of ``captures``."""
    parts = []
    n_nan = n_drop = 0
    for i, cap in enumerate(captures):
        src = names[i] if names else f"capture {i}"
        if need_force and cap.force is None:
            raise FeatureError(f"{src}: no force channel")
        for x, valid, f in capture_rows(cap, window, config, src):
            bad = ~np.isfinite(x[:, : window.size]).all(1) | (need_force & ~np.isfinite(f))
            n_nan += int(bad.sum())
            keep = valid & ~bad if need_force else valid
            n_drop += int((~keep).sum())
            v = float(cap.truth.get("velocity_mm_s", math.nan))
            split = str(cap.truth.get("split", "test"))
            parts.append((x[keep], f[keep], np.full(keep.sum(), v), cap.timestamps[keep], np.full(keep.sum(), i),
                          np.full(keep.sum(), split, dtype=object)))
    cat = [np.concatenate(p) for p in zip(*parts)]
    return Dataset(*cat[:5], n_nan_frames=n_nan, n_dropped=n_drop, split=cat[5])


def split_indices(n: int, fractions=(0.8, 0.1, 0.1), seed: int = 0):
    """Random train / validation / hold-out indices (seed 001: 80/10/10 of the samples)."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    a = int(round(fractions[0] * n))
    b = a + int(round(fractions[1] * n))
    return np.sort(perm[:a]), np.sort(perm[a:b]), np.sort(perm[b:])


# ---- features from the touch inversion -------------------------------------------------------


@dataclass(frozen=True)
class Contact:
    """One located contact: its range from the sensor, the zone centroid of its signal, the bin it peaks at."""

    range_m: float
    zone: float  # signal-weighted mean zone index (0 .. zones - 1)
    peak_bin: float  # fractional bin of the range profile's peak
    start_bin: int  # first bin of its feature window


class ContactInverter:
    """Force features from the touch inversion.

    The signal is ``tofjax.invert``'s *full* correction (Algorithm 1 of seed 000) with the
    given optics: baseline subtraction against the capture's no-touch frames, per-frame
    ambient tracking from the bins before the light enters, and the decay correction
    ``1 / (K G(r) T(r))`` at each bin's range. Build it from a calibration
    (:meth:`from_calibration`: the calibrated :class:`tofjax.model.Params`) or from the
    scene's stated optics.

    :meth:`locate` finds the contacts of a capture and their range; :meth:`rows` gives each
    contact's window of corrected signal (relative to the sensor's no-touch return, which
    cancels gain and the ambient flattening of the detector), its derivative, the raw
    baseline there, and its context inputs (range, log10 ambient counts).
    """

    def __init__(self, scene, params=None, *, source: str = "scene"):
        import jax.numpy as jnp

        from ..invert.correction import CorrectionOptions, OpticalParams, bin_ranges, build_corrector

        self.scene = scene.without_touches()
        self.optical = OpticalParams.from_scene(self.scene) if params is None else OpticalParams.from_params(params, source)
        # The mask and gain do not depend on the baseline: build once, swap the baseline per capture.
        self._corrector = build_corrector(self.scene, np.zeros(self.scene.shape), self.optical,
                                          CorrectionOptions(method="full"), jnp.float32)
        self.ranges = bin_ranges(self.scene, self.optical, True)
        self.mask = np.asarray(self._corrector.mask)
        self.early = np.asarray(self._corrector.early, float)
        self.gain = np.asarray(self._corrector.gain, float)
        self.saturation = self._corrector.saturation

    @classmethod
    def from_calibration(cls, scene, calibration) -> "ContactInverter":
        """Optics from a calibration JSON (``CalibrationResult.to_json``); refused with one line if unusable."""
        from ..fit._result import CalibrationRefused, load_calibration

        try:
            params = load_calibration(calibration, scene.without_touches())
        except CalibrationRefused as e:
            raise FeatureError(str(e)) from None
        return cls(scene, params, source=str(calibration))

    def correct(self, hist: np.ndarray, baseline: np.ndarray, sensor: int | None = None):
        """Corrected signals (F, S, Z, B) and ok flags (F,) of histograms against a no-touch baseline.

        :class:`tofjax.invert.correction.Corrector`'s full correction, evaluated in float64
        NumPy (one sensor only with ``sensor``: then (F, 1, Z, B) and ok for that sensor).
        """
        sl = slice(None) if sensor is None else slice(sensor, sensor + 1)
        h = np.asarray(hist, np.float64)[:, sl]
        bad = ~np.isfinite(h) | (h >= self.saturation)
        ok = ~bad.any((1, 2, 3))
        signal = np.where(bad, 0.0, h) - np.asarray(baseline, float)[sl]
        if self.early.any():
            signal = signal - (signal @ self.early)[..., None]
        out = signal * self.gain[sl]
        return np.where(ok[:, None, None, None], out, 0.0), ok

    def reference(self, baseline: np.ndarray, sensor: int) -> tuple[float, float]:
        """The sensor's no-touch return (counts above ambient, summed where a contact can be) and its
        ambient level (mean counts of the bins where no light of the sensor's own can be: before the
        light enters, or beyond the far edge)."""
        b = np.asarray(baseline[sensor], float)  # (Z, B)
        m = self.mask[sensor]
        dark = ~m
        amb = (b * dark).sum(1) / np.maximum(dark.sum(1), 1) if dark.any() else np.zeros(b.shape[0])
        ret = float(np.sum(np.maximum(b - amb[:, None], 0.0) * m))
        return max(ret, 1.0), float(np.mean(amb))

    def locate(self, corrected: np.ndarray, sensor: int, n: int = 1, bins: int = 5, mask_sensor: int | None = None) -> list[Contact]:
        """The ``n`` strongest contacts of a capture, nearest first.

        The contact frames are the quarter with the most positive corrected signal; their
        mean signal, summed over the zones, is the range profile. The highest peaks of its
        3-bin smoothing (at least ``bins`` bins apart) are the contacts; the range comes from
        a parabola through the unsmoothed peak and its neighbours.
        """
        c = corrected[:, sensor]  # (F, Z, B)
        m = self.mask[sensor if mask_sensor is None else mask_sensor]
        energy = (np.clip(c, 0, None) * m).sum((1, 2))
        strong = energy >= np.quantile(energy, 0.75)
        P = c[strong].mean(0) * m  # (Z, B)
        raw = P.sum(0)
        prof = np.convolve(raw, [0.25, 0.5, 0.25], mode="same")
        B = prof.size
        left = prof.copy()
        peaks = []
        for _ in range(n):
            b = int(np.argmax(left))
            peaks.append(b)
            left[max(0, b - bins) : b + bins + 1] = -np.inf
        out = []
        for b in sorted(peaks):
            frac = float(b)
            if 0 < b < B - 1:
                b = int(b - 1 + np.argmax(raw[b - 1 : b + 2]))  # the unsmoothed profile's own peak
                b = min(max(b, 1), B - 2)
                frac = float(b)
                y0, y1, y2 = raw[b - 1], raw[b], raw[b + 1]
                den = y0 - 2 * y1 + y2
                if den < 0:
                    frac = b + float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5))
            r = float(np.interp(frac, np.arange(B), self.ranges))
            lo, hi = max(0, b - 1), min(B, b + 2)
            wz = np.clip(P[:, lo:hi], 0, None).sum(1)
            zone = float((wz * np.arange(wz.size)).sum() / wz.sum()) if wz.sum() > 0 else 0.5 * (wz.size - 1)
            start = int(np.clip(b - 1, 0, B - bins))
            out.append(Contact(r, zone, frac, start))
        return out


_INVERTERS: dict = {}


def inverter_for(scene, config: FeatureConfig) -> ContactInverter:
    """One :class:`ContactInverter` per scene and calibration (the corrector's mask costs a ray trace)."""
    key = (scene.without_touches(), config.calibration)
    if key not in _INVERTERS:
        inv = (ContactInverter(scene) if config.calibration is None
               else ContactInverter.from_calibration(scene, config.calibration))
        _INVERTERS.clear() if len(_INVERTERS) > 8 else None
        _INVERTERS[key] = inv
    return _INVERTERS[key]


def _contact_forces(cap: Capture, contacts: list[Contact]) -> list[np.ndarray]:
    """The force channel of each located contact: from ``truth.contact_forces_n`` (several contacts,
    matched to the truth's ``contacts`` by range), else the capture's ``force``."""
    forces = cap.truth.get("contact_forces_n")
    truth = cap.truth.get("contacts")
    n_frames = cap.n_frames
    if not forces or not truth:
        f = cap.force if cap.force is not None else np.full(n_frames, np.nan)
        return [f] * len(contacts)
    if cap.frame_index is not None and len(cap.frame_index) == n_frames:
        idx = np.asarray(cap.frame_index)
    else:
        idx = np.arange(n_frames)
    ranges = np.array([t["range_m"] for t in truth])
    out = []
    for c in contacts:
        j = int(np.argmin(np.abs(ranges - c.range_m)))
        out.append(np.asarray(forces[j], float)[idx])
    return out


def capture_rows(cap: Capture, window: Window, config: FeatureConfig, source: str = "capture"):
    """``[(raw (frames, 3 n + context), valid (frames,), force (frames,)), ...]``: one entry per contact.

    ``counts``: one entry, seed 001's fixed window (:func:`raw_features`). ``inversion``: one
    entry per located contact, its window of corrected signal (see :class:`ContactInverter`).
    """
    if config.source == "counts":
        x, valid = raw_features(cap, window, config, source)
        f = cap.force if cap.force is not None else np.full(cap.n_frames, np.nan)
        return [(x, valid, f)]
    window.check(cap.scene.shape, source)
    inv = inverter_for(cap.scene, config)
    nb = capture_baseline_frames(cap, config, source)
    hist = np.asarray(cap.histograms, np.float64)
    base = _baseline(hist, nb)
    corrected, ok = inv.correct(hist, base, window.sensor)
    finite = np.isfinite(hist).all((1, 2, 3)) & ok
    ret, ambient = inv.reference(base, window.sensor)
    n_contacts = config.contacts or int(cap.truth.get("n_contacts", 1))
    contacts = inv.locate(corrected[finite] if finite.any() else corrected, 0, n_contacts, window.bins, window.sensor)
    dt = frame_period(cap)
    rows = []
    for c, f in zip(contacts, _contact_forces(cap, contacts)):
        # The window starts one bin before the peak, at the peak's fractional position (shift-invariant).
        pos = np.clip(c.peak_bin - 1.0 + np.arange(window.bins), 0, hist.shape[-1] - 1.0001)
        i0 = np.floor(pos).astype(int)
        a = pos - i0

        def at(v):  # (..., Z, B) -> (..., Z, bins), linearly interpolated
            return (1 - a) * v[..., i0] + a * v[..., i0 + 1]

        cw, bw = at(corrected[:, 0]), at(base[window.sensor])
        if config.zones == "sum":
            cw, bw = cw.sum(-2, keepdims=True), bw.sum(-2, keepdims=True)
        w = cw.reshape(len(hist), -1) / ret * 1e3
        w = np.where(finite[:, None], w, np.nan)
        wz = np.where(finite[:, None], w, 0.0)
        d = backward_derivative(wz, dt, config.derivative_frames)
        valid = finite.copy()
        if config.variant == "derivative":
            valid = _derivative_valid(valid, finite, config.derivative_frames)
        b = np.broadcast_to(bw.reshape(-1), w.shape)
        parts = [w, d, b]
        if config.position:
            ctx = np.array([c.range_m, math.log10(max(ambient, 1e-3))])
            parts.append(np.broadcast_to(ctx, (len(hist), N_CONTEXT)))
        rows.append((np.concatenate(parts, 1), valid, f))
    return rows


def _training_shape(captures: list[Capture], config: FeatureConfig) -> tuple[int, int, int]:
    """The captures' (sensors, zones, bins), after checking there are captures and enough bins."""
    if not captures:
        raise FeatureError("no training captures")
    shape = captures[0].scene.shape
    if config.bins > shape[2]:
        raise FeatureError(f"features.bins = {config.bins} is more than the {shape[2]} bins of the captures")
    return shape


def find_inversion_window(captures: list[Capture], config: FeatureConfig) -> Window:
    """The sensor whose corrected signal shows the training contacts most strongly (or ``config.sensor``);
    the window's bins follow each contact (``start_bin`` -1)."""
    shape = _training_shape(captures, config)
    S, Z, B = shape
    zw = 1 if config.zones == "sum" else Z
    if config.sensor is not None:
        if not 0 <= config.sensor < S:
            raise FeatureError(f"features.sensor = {config.sensor} but the captures have {S} sensors")
        return Window(config.sensor, -1, config.bins, zw, shape)
    score = np.zeros(S)
    for i, cap in enumerate(captures):
        if cap.scene.shape != shape:
            raise FeatureError(f"training capture {i}: shape {cap.scene.shape} differs from the first one's {shape}")
        inv = inverter_for(cap.scene, config)
        h = np.asarray(cap.histograms, np.float64)
        base = _baseline(h, capture_baseline_frames(cap, config, f"training capture {i}"))
        c, ok = inv.correct(h, base)
        for s in range(S):
            score[s] += np.clip(c[ok, s], 0, None).sum() / inv.reference(base, s)[0]
    return Window(int(np.argmax(score)), -1, config.bins, zw, shape)
