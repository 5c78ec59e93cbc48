"""Capture files (HDF5, format ``tofjax.capture`` version 1): read, write, append.

One layout for simulated and recorded data; see ``docs/capture-format.md``.
Appending is frame by frame with a flush after each, so an interrupted
recording keeps every frame completed before the interruption.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .config import ConfigError
from .errors import UserError
from .scene import Scene, scene_from_json

__all__ = ["Capture", "CaptureError", "CaptureWriter", "read_capture", "write_capture", "FORMAT", "VERSION"]

FORMAT = "tofjax.capture"
VERSION = 1
#: Histograms are stored as float32: exact for every 24-bit TMF8828 count.
HIST_DTYPE = np.float32


class CaptureError(UserError):
    """A capture file is missing, truncated, foreign or inconsistent."""


@dataclass
class Capture:
    """A capture in memory.

    ``histograms`` is (frames, sensors, zones, bins) counts; ``timestamps``
    (frames,) seconds. ``force`` (frames,) newtons, ``reference`` (frames,
    sensors, bins) reference-channel histograms, ``truth_touches`` (frames,
    max_touches, 3) = x_m, y_m, strength (NaN-padded) and ``truth`` (the true
    parameters, JSON-able) are optional.
    """

    histograms: np.ndarray
    timestamps: np.ndarray
    scene: Scene
    source: str = "simulated"
    created: str = field(default_factory=lambda: _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    force: np.ndarray | None = None
    reference: np.ndarray | None = None
    truth_touches: np.ndarray | None = None
    truth: dict[str, Any] = field(default_factory=dict)
    #: Free-space ground truth and the sensor's own results (imported TMF882x recordings):
    #: target distance (frames,) m; on-chip distance and confidence (frames, sensors, zones).
    target_distance_m: np.ndarray | None = None
    onchip_distance_m: np.ndarray | None = None
    onchip_confidence: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.histograms.shape[0])

    def mean(self) -> np.ndarray:
        """Mean histogram over frames: (sensors, zones, bins)."""
        return self.histograms.mean(axis=0)


def _root_attrs(f: h5py.File, scene: Scene, source: str, created: str | None) -> None:
    f.attrs["format"] = FORMAT
    f.attrs["version"] = VERSION
    f.attrs["scene"] = scene.to_json()
    f.attrs["source"] = source
    f.attrs["created"] = created or _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _extendable(f: h5py.File, name: str, shape_tail: tuple[int, ...], dtype, fill=None) -> h5py.Dataset:
    return f.create_dataset(
        name,
        shape=(0, *shape_tail),
        maxshape=(None, *shape_tail),
        chunks=(1, *shape_tail) if shape_tail else (1024,),
        dtype=dtype,
        fillvalue=fill,
    )


class CaptureWriter:
    """Append frames to a new capture file; each frame is flushed when written.

    ::

        with CaptureWriter("rec.h5", scene, source="tmf8828") as w:
            w.append(histogram, timestamp=t)
    """

    def __init__(
        self,
        path: str | Path,
        scene: Scene,
        *,
        source: str = "simulated",
        with_force: bool = False,
        with_reference: bool = False,
        max_touches: int = 0,
        truth: dict[str, Any] | None = None,
        with_target: bool = False,
        with_onchip: bool = False,
    ):
        self.path = Path(path)
        self.scene = scene
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = h5py.File(self.path, "w")
        _root_attrs(self._f, scene, source, None)
        S, Z, B = scene.shape
        self._hist = _extendable(self._f, "histograms", (S, Z, B), HIST_DTYPE)
        self._hist.attrs["units"] = "counts"
        self._hist.attrs["axes"] = "frame, sensor, zone, bin"
        self._time = _extendable(self._f, "timestamps", (), np.float64)
        self._time.attrs["units"] = "s"
        self._force = _extendable(self._f, "force", (), np.float64) if with_force else None
        if self._force is not None:
            self._force.attrs["units"] = "N"
        self._ref = _extendable(self._f, "reference", (S, B), HIST_DTYPE) if with_reference else None
        self._touch = None
        if max_touches or truth:
            g = self._f.create_group("truth")
            g.attrs["parameters"] = json.dumps(truth or {})
            if max_touches:
                self._touch = _extendable(g, "touches", (max_touches, 3), np.float64, fill=np.nan)
        self._target = self._onchip = self._onchip_conf = None
        if with_target:
            g = self._f.require_group("truth")
            if "parameters" not in g.attrs:
                g.attrs["parameters"] = json.dumps(truth or {})
            self._target = _extendable(g, "target_distance_m", (), np.float64, fill=np.nan)
            self._target.attrs["units"] = "m"
        if with_onchip:
            g = self._f.create_group("onchip")
            self._onchip = _extendable(g, "distance_m", (S, Z), np.float64, fill=np.nan)
            self._onchip.attrs["units"] = "m"
            self._onchip_conf = _extendable(g, "confidence", (S, Z), np.float64, fill=np.nan)
        self.n_frames = 0
        self._f.flush()

    def append(self, histogram, timestamp: float, *, force=None, reference=None, touches=None) -> None:
        """Write one whole frame: histogram (sensors, zones, bins); optional force, reference, touches."""
        histogram = np.asarray(histogram, HIST_DTYPE)
        if histogram.shape != self._hist.shape[1:]:
            raise CaptureError(f"frame shape {histogram.shape} does not match the scene's {self._hist.shape[1:]}")
        if (force is None) != (self._force is None):
            raise CaptureError("force must be given for every frame of a capture with a force channel, and only then")
        i = self.n_frames
        # Extras first, histograms and timestamps last: a reader takes the frame count from
        # the timestamps, so a frame interrupted half-way is never seen as whole.
        if self._force is not None:
            self._force.resize(i + 1, 0)
            self._force[i] = float(force)
        if self._ref is not None:
            self._ref.resize(i + 1, 0)
            self._ref[i] = np.asarray(reference, HIST_DTYPE) if reference is not None else np.nan
        if self._touch is not None:
            self._touch.resize(i + 1, 0)
            if touches is not None and len(touches):
                t = np.asarray(touches, np.float64)[: self._touch.shape[1], :3]
                row = np.full(self._touch.shape[1:], np.nan)
                row[: len(t)] = t
                self._touch[i] = row
        for ds in (self._target, self._onchip, self._onchip_conf):  # free-space extras: NaN unless extended
            if ds is not None:
                ds.resize(i + 1, 0)
        self._hist.resize(i + 1, 0)
        self._hist[i] = histogram
        self._time.resize(i + 1, 0)
        self._time[i] = float(timestamp)
        self._f.flush()
        self.n_frames = i + 1

    def extend(self, histograms, timestamps, *, force=None, reference=None, touches=None,
               target_distance_m=None, onchip_distance_m=None, onchip_confidence=None) -> None:
        """Write many whole frames at once (one resize and one flush: fast for long simulated captures)."""
        histograms = np.asarray(histograms, HIST_DTYPE)
        n = histograms.shape[0]
        if histograms.shape[1:] != self._hist.shape[1:]:
            raise CaptureError(f"frame shape {histograms.shape[1:]} does not match the scene's {self._hist.shape[1:]}")
        if (force is None) != (self._force is None):
            raise CaptureError("force must be given for every frame of a capture with a force channel, and only then")
        i = self.n_frames
        # Same order as append: histograms and timestamps last.
        if self._force is not None:
            self._force.resize(i + n, 0)
            self._force[i:] = np.asarray(force, np.float64)
        if self._ref is not None:
            self._ref.resize(i + n, 0)
            self._ref[i:] = np.asarray(reference, HIST_DTYPE) if reference is not None else np.nan
        if self._touch is not None:
            self._touch.resize(i + n, 0)
            if touches is not None:
                t = np.asarray(touches, np.float64)[:, : self._touch.shape[1], :3]
                rows = np.full((n, *self._touch.shape[1:]), np.nan)
                rows[:, : t.shape[1]] = t
                self._touch[i:] = rows
        for ds, v in ((self._target, target_distance_m), (self._onchip, onchip_distance_m), (self._onchip_conf, onchip_confidence)):
            if ds is not None:
                ds.resize(i + n, 0)
                ds[i:] = np.asarray(v, np.float64) if v is not None else np.nan
        self._hist.resize(i + n, 0)
        self._hist[i:] = histograms
        self._time.resize(i + n, 0)
        self._time[i:] = np.asarray(timestamps, np.float64)
        self._f.flush()
        self.n_frames = i + n

    def close(self) -> None:
        if self._f.id.valid:
            self._f.close()

    def __enter__(self) -> "CaptureWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_capture(path: str | Path, cap: Capture) -> Path:
    """Write a whole :class:`Capture` at once."""
    path = Path(path)
    max_touches = 0 if cap.truth_touches is None else cap.truth_touches.shape[1]
    with CaptureWriter(
        path,
        cap.scene,
        source=cap.source,
        with_force=cap.force is not None,
        with_reference=cap.reference is not None,
        max_touches=max_touches,
        truth=cap.truth or None,
        with_target=cap.target_distance_m is not None,
        with_onchip=cap.onchip_distance_m is not None,
    ) as w:
        w._f.attrs["created"] = cap.created
        w.extend(cap.histograms, cap.timestamps, force=cap.force, reference=cap.reference, touches=cap.truth_touches,
                 target_distance_m=cap.target_distance_m, onchip_distance_m=cap.onchip_distance_m,
                 onchip_confidence=cap.onchip_confidence)
    return path


def read_capture(path: str | Path) -> Capture:
    """Read and check a capture; raises :class:`CaptureError` with the reason if it is not a good one."""
    path = Path(path)
    if not path.exists():
        raise CaptureError(f"{path}: no such file")
    if not h5py.is_hdf5(path):
        raise CaptureError(f"{path}: not an HDF5 file (truncated, or not a tofjax capture)")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise CaptureError(f"{path}: cannot be opened as HDF5 (truncated?): {e}") from None
    with f:
        fmt = f.attrs.get("format")
        if fmt != FORMAT:
            raise CaptureError(f"{path}: not a tofjax capture (format attribute is {fmt!r}, expected {FORMAT!r})")
        version = int(f.attrs.get("version", -1))
        if version != VERSION:
            raise CaptureError(f"{path}: capture version {version} is not supported (this tofjax reads {VERSION})")
        if "scene" not in f.attrs:
            raise CaptureError(f"{path}: the 'scene' attribute is missing")
        try:
            scene = scene_from_json(f.attrs["scene"], f"{path} (scene attribute)")
        except ConfigError as e:
            raise CaptureError(str(e)) from None
        for name in ("histograms", "timestamps"):
            if name not in f:
                raise CaptureError(f"{path}: dataset '{name}' is missing")
        try:
            n = f["timestamps"].shape[0]
            if f["histograms"].shape[0] < n:
                raise CaptureError(f"{path}: {f['histograms'].shape[0]} histograms for {n} timestamps")
            hist = np.asarray(f["histograms"][:n], np.float64)
            times = np.asarray(f["timestamps"][:n], np.float64)
            force = np.asarray(f["force"][:n], np.float64) if "force" in f else None
            ref = np.asarray(f["reference"][:n], np.float64) if "reference" in f else None
            touches = truth = None
            if "truth" in f:
                truth = json.loads(f["truth"].attrs.get("parameters", "{}"))
                if "touches" in f["truth"]:
                    touches = np.asarray(f["truth/touches"][:n], np.float64)
            extras = {
                k: np.asarray(f[name][:n], np.float64) if name in f else None
                for k, name in (("target_distance_m", "truth/target_distance_m"), ("onchip_distance_m", "onchip/distance_m"),
                                ("onchip_confidence", "onchip/confidence"))
            }
        except (OSError, KeyError) as e:
            raise CaptureError(f"{path}: unreadable data (truncated?): {e}") from None
        if hist.ndim != 4 or hist.shape[1:] != scene.shape:
            raise CaptureError(
                f"{path}: histograms have shape {hist.shape[1:]} per frame but the scene says "
                f"(sensors, zones, bins) = {scene.shape}"
            )
        for name, arr in (("force", force), ("reference", ref), ("truth/touches", touches), *extras.items()):
            if arr is not None and arr.shape[0] != n:
                raise CaptureError(f"{path}: '{name}' has {arr.shape[0]} frames, timestamps {n}")
        return Capture(
            histograms=hist,
            timestamps=times,
            scene=scene,
            source=str(f.attrs.get("source", "unknown")),
            created=str(f.attrs.get("created", "")),
            force=force,
            reference=ref,
            truth_touches=touches,
            truth=truth or {},
            **extras,
        )
