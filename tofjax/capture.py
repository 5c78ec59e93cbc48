"""Capture files (HDF5, format ``tofjax.capture`` version 1): read, write, append.

One layout for simulated and recorded data; see ``docs/capture-format.md``.
Appending is frame by frame with a flush after each, so an interrupted
recording keeps every frame completed before the interruption.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import json
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .config import ConfigError
from .errors import UserError
from .scene import Scene, scene_from_json

__all__ = [
    "BadFramesWarning",
    "Capture",
    "check_capture_target",
    "CaptureError",
    "CaptureWriter",
    "read_capture",
    "write_capture",
    "FORMAT",
    "VERSION",
]

FORMAT = "tofjax.capture"
VERSION = 1
#: Histograms are stored as float32: exact for every 24-bit TMF8828 count.
HIST_DTYPE = np.float32


#: Free space a writer keeps on its disk (bytes, beyond twice the frames about to be written):
#: HDF5 cannot close a file cleanly once a write has failed for lack of space (the process
#: crashes), so a writer stops, in one line and with every committed frame, before that.
DISK_MARGIN_BYTES = 512 * 1024

#: Root attribute: frames committed (whole, flushed). Written after each frame's data, so a
#: reader never sees a frame a crash or a full disk left half-written (or zero-filled).
COMMITTED = "committed_frames"


class CaptureError(UserError):
    """A capture file is missing, truncated, foreign or inconsistent."""


class BadFramesWarning(UserWarning):
    """Frames with impossible counts (NaN, infinite, negative, all zero) were dropped on reading."""


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
    #: Index in the file of each frame kept (frames with impossible counts are dropped on reading).
    frame_index: np.ndarray | None = None
    #: Frames dropped on reading: {index in the file: reason}.
    dropped: dict[int, str] = field(default_factory=dict)
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


def _being_written(path: Path) -> bool:
    """Whether another open file holds the HDF5 writer's lock on ``path`` (a live recording)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)  # closing releases the lock if we got it
    return False


def check_capture_target(path: str | Path, overwrite: bool = False) -> None:
    """Raise :class:`CaptureError` now if a capture could not be written to ``path`` later
    (it exists and ``overwrite`` is not set, or another process is still writing it): call it
    before a long simulation or before opening a rig."""
    _prepare_target(Path(path), overwrite)


def _prepare_target(path: Path, overwrite: bool) -> None:
    """Refuse an existing ``path`` unless ``overwrite``; never replace a capture being written."""
    if path.is_dir():
        raise CaptureError(f"{path}: is a folder, expected a capture file name")
    if path.exists() and not path.is_file():
        # a device, a pipe or a socket: replacing it would remove it (/dev/full), and opening a
        # pipe to test its lock would wait for a writer
        raise CaptureError(f"{path}: is not a regular file (a device, pipe or socket); refusing to write over it")
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise CaptureError(f"{path}: exists; pass --overwrite to replace it")
        if _being_written(path):
            raise CaptureError(f"{path}: is being written by another process; refusing to replace it")


class CaptureWriter:
    """Append frames to a new capture file; each frame is committed when whole.

    ::

        with CaptureWriter("rec.h5", scene, source="tmf8828") as w:
            w.append(histogram, timestamp=t)

    The file is created exclusively: an existing file is refused unless ``overwrite``, and
    a file another process is still writing is never replaced (HDF5 holds a lock on it).
    Each frame is written, flushed, and only then counted in the ``committed_frames``
    attribute (flushed again): readers take only committed frames, so a crash or a full
    disk in the middle of a frame never shows up as a frame.
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
        overwrite: bool = False,
        with_target: bool = False,
        with_onchip: bool = False,
    ):
        self.path = Path(path)
        self.scene = scene
        self.n_frames = 0
        self._f = None
        self._failed: str | None = None
        _prepare_target(self.path, overwrite)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if overwrite and (self.path.exists() or self.path.is_symlink()):
                self.path.unlink()
            # "w-": O_EXCL create, never a truncation (a failed "w" open of a file another writer
            # holds cut it to 0 bytes).
            self._f = h5py.File(self.path, "w-")
        except FileExistsError:
            raise CaptureError(f"{self.path}: exists (another writer created it just now); not touched") from None
        except BlockingIOError:
            raise CaptureError(f"{self.path}: is being written by another process; refusing to replace it") from None
        except OSError as e:
            raise CaptureError(f"{self.path}: cannot create the capture: {_oserror(e)}") from None
        try:
            self._setup(scene, source, with_force, with_reference, max_touches, truth, with_target, with_onchip)
        except (OSError, RuntimeError) as e:  # h5py reports a failed flush as RuntimeError
            self._fail(e)

    def _setup(self, scene, source, with_force, with_reference, max_touches, truth, with_target, with_onchip) -> None:
        _root_attrs(self._f, scene, source, None)
        self._f.attrs[COMMITTED] = np.int64(0)
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
        self._f.flush()

    def _fail(self, e: OSError):
        self._failed = _oserror(e)
        raise CaptureError(
            f"{self.path}: write failed after {self.n_frames} committed frames ({self._failed}); "
            "the committed frames are kept"
        ) from None

    def _commit(self, n: int) -> None:
        self._f.flush()  # the data first ...
        self._f.attrs[COMMITTED] = np.int64(n)
        self._f.flush()  # ... then the count that makes them visible
        self.n_frames = n

    def _check_open(self, n_bytes: int = 0) -> None:
        if self._failed is not None:
            raise CaptureError(f"{self.path}: an earlier write failed ({self._failed}); no more frames can be added")
        try:
            st = os.statvfs(self.path.parent)
        except OSError:
            return
        free = st.f_bavail * st.f_frsize
        if free < 2 * n_bytes + DISK_MARGIN_BYTES:
            self._failed = "disk full"
            raise CaptureError(
                f"{self.path}: write failed after {self.n_frames} committed frames (the disk is full: "
                f"{free / 1e6:.2f} MB left); the committed frames are kept"
            )

    def append(self, histogram, timestamp: float, *, force=None, reference=None, touches=None) -> None:
        """Write one whole frame: histogram (sensors, zones, bins); optional force, reference, touches.

        The same as ``extend`` with one frame (``touches``: up to ``max_touches`` rows of
        (x, y, strength); ``None`` or empty for none).
        """
        histogram = np.asarray(histogram, HIST_DTYPE)
        if histogram.shape != self._hist.shape[1:]:
            raise CaptureError(f"frame shape {histogram.shape} does not match the scene's {self._hist.shape[1:]}")
        rows = None
        if touches is not None and len(touches):
            rows = np.asarray(touches, np.float64).reshape(1, len(touches), -1)
        self.extend(
            histogram[None], [float(timestamp)],
            force=None if force is None else [float(force)],
            reference=None if reference is None else np.asarray(reference, HIST_DTYPE)[None],
            touches=rows,
        )

    def extend(self, histograms, timestamps, *, force=None, reference=None, touches=None,
               target_distance_m=None, onchip_distance_m=None, onchip_confidence=None) -> None:
        """Write many whole frames at once (one resize and one commit: fast for long simulated captures)."""
        histograms = np.asarray(histograms, HIST_DTYPE)
        n = histograms.shape[0]
        if histograms.shape[1:] != self._hist.shape[1:]:
            raise CaptureError(f"frame shape {histograms.shape[1:]} does not match the scene's {self._hist.shape[1:]}")
        if (force is None) != (self._force is None):
            raise CaptureError("force must be given for every frame of a capture with a force channel, and only then")
        if np.shape(timestamps) != (n,) or (force is not None and np.shape(force) != (n,)):
            raise CaptureError(f"{n} frames need {n} timestamps (and {n} forces with a force channel)")
        self._check_open(2 * histograms.nbytes)  # histograms, and room for the extras
        i = self.n_frames
        try:
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
            for ds, v in ((self._target, target_distance_m), (self._onchip, onchip_distance_m),
                          (self._onchip_conf, onchip_confidence)):
                if ds is not None:
                    ds.resize(i + n, 0)
                    ds[i:] = np.asarray(v, np.float64) if v is not None else np.nan
            self._hist.resize(i + n, 0)
            self._hist[i:] = histograms
            self._time.resize(i + n, 0)
            self._time[i:] = np.asarray(timestamps, np.float64)
            self._commit(i + n)
        except (OSError, RuntimeError) as e:  # h5py reports a failed flush as RuntimeError
            self._fail(e)

    def close(self) -> None:
        if self._f is not None and self._f.id.valid:
            try:
                self._f.close()
            except (OSError, RuntimeError) as e:
                if self._failed is None:
                    self._failed = _oserror(e)
                    raise CaptureError(f"{self.path}: closing failed ({self._failed})") from None

    def __enter__(self) -> "CaptureWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _oserror(e: Exception) -> str:
    text = getattr(e, "strerror", None) or str(e)
    if "No space left on device" in text:
        return "No space left on device"
    return " ".join(text.split())[:200]


def write_capture(path: str | Path, cap: Capture, *, overwrite: bool = False) -> Path:
    """Write a whole :class:`Capture` at once: under a temporary name, renamed when complete.

    An existing ``path`` is refused unless ``overwrite`` (and never replaced while another
    process is writing it).
    """
    path = Path(path)
    _prepare_target(path, overwrite)
    max_touches = 0 if cap.truth_touches is None else cap.truth_touches.shape[1]
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        with CaptureWriter(
            tmp,
            cap.scene,
            source=cap.source,
            with_force=cap.force is not None,
            with_reference=cap.reference is not None,
            max_touches=max_touches,
            truth=cap.truth or None,
            overwrite=True,
            with_target=cap.target_distance_m is not None,
            with_onchip=cap.onchip_distance_m is not None,
        ) as w:
            w._f.attrs["created"] = cap.created
            w.extend(cap.histograms, cap.timestamps, force=cap.force, reference=cap.reference, touches=cap.truth_touches,
                     target_distance_m=cap.target_distance_m, onchip_distance_m=cap.onchip_distance_m,
                     onchip_confidence=cap.onchip_confidence)
        _prepare_target(path, overwrite)
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)  # fails if the name was taken meanwhile: never clobbers
            except FileExistsError:
                raise CaptureError(f"{path}: exists (another writer created it just now); not touched") from None
            os.unlink(tmp)
    except OSError as e:
        raise CaptureError(f"{path}: cannot write the capture: {_oserror(e)}") from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
    return path


def _frame_problems(hist: np.ndarray, times: np.ndarray) -> dict[int, str]:
    """{frame index: reason} for frames no sensor can produce."""
    bad: dict[int, str] = {}
    flat = hist.reshape(hist.shape[0], -1)
    with np.errstate(invalid="ignore"):
        for i in np.flatnonzero(~np.isfinite(flat).all(axis=1)):
            n = int((~np.isfinite(flat[i])).sum())
            bad[int(i)] = f"{n} non-finite (NaN or infinite) bins"
        for i in np.flatnonzero((flat < 0).any(axis=1)):
            bad.setdefault(int(i), f"{int((flat[i] < 0).sum())} negative bins (min {np.nanmin(flat[i]):g})")
        if flat.shape[1]:
            for i in np.flatnonzero((flat == 0).all(axis=1)):
                bad.setdefault(int(i), "all bins zero (a frame never written, e.g. a full disk)")
        for i in np.flatnonzero(~np.isfinite(times)):
            bad.setdefault(int(i), f"timestamp {float(times[i])!r}")
    return dict(sorted(bad.items()))


def _describe(bad: dict[int, str], limit: int = 5) -> str:
    items = list(bad.items())
    text = "; ".join(f"frame {i}: {r}" for i, r in items[:limit])
    return text + (f"; and {len(items) - limit} more" if len(items) > limit else "")


def read_capture(path: str | Path) -> Capture:
    """Read and check a capture; raises :class:`CaptureError` with the reason if it is not a good one.

    Only committed frames are read. Frames with impossible counts (NaN, infinite, negative,
    all zero) are dropped with a :class:`BadFramesWarning` naming them; they are listed in
    :attr:`Capture.dropped` and :attr:`Capture.frame_index` maps the kept frames to the file.
    A capture with no good frame left is an error.
    """
    path = Path(path)
    if not path.exists():
        raise CaptureError(f"{path}: no such file")
    if path.is_dir():
        raise CaptureError(f"{path}: is a folder, expected a capture file")
    try:
        is_hdf5 = h5py.is_hdf5(path)
    except OSError as e:
        raise CaptureError(f"{path}: cannot be read: {_oserror(e)}") from None
    if not is_hdf5:
        raise CaptureError(f"{path}: not an HDF5 file (truncated, or not a tofjax capture)")
    # No lock: a recording in progress (which holds the writer's lock) can be read; the
    # committed-frame count says which frames are whole. A recording caught mid-flush can fail to
    # open for a moment: a few tries, 0.5 s in all, before the file is called bad.
    f = None
    for attempt in range(5):
        try:
            f = h5py.File(path, "r", locking=False)
            break
        except OSError:
            try:
                f = h5py.File(path, "r")  # already open in this process (with its lock): share that
                break
            except OSError as e:
                err = e
                if attempt < 4:
                    time.sleep(0.05 * (attempt + 1))
    if f is None:
        raise CaptureError(f"{path}: cannot be opened as HDF5 (truncated?): {err}") from None
    with f:
        try:
            fmt = f.attrs.get("format")
            if isinstance(fmt, bytes):
                fmt = fmt.decode("utf-8", "replace")
            if fmt != FORMAT:
                raise CaptureError(f"{path}: not a tofjax capture (format attribute is {fmt!r}, expected {FORMAT!r})")
            version = _int_attr(f.attrs, "version", path, default=-1)
            if version != VERSION:
                raise CaptureError(f"{path}: capture version {version} is not supported (this tofjax reads {VERSION})")
            if "scene" not in f.attrs:
                raise CaptureError(f"{path}: the 'scene' attribute is missing")
            scene_text = f.attrs["scene"]
            if isinstance(scene_text, bytes):
                scene_text = scene_text.decode("utf-8", "replace")
            if not isinstance(scene_text, str):
                raise CaptureError(f"{path}: the 'scene' attribute is not text (got {type(scene_text).__name__})")
            try:
                scene = scene_from_json(scene_text, f"{path} (scene attribute)")
            except ConfigError as e:
                raise CaptureError(str(e)) from None
            for name in ("histograms", "timestamps"):
                if name not in f:
                    raise CaptureError(f"{path}: dataset '{name}' is missing")
                if not isinstance(f[name], h5py.Dataset):
                    raise CaptureError(f"{path}: '{name}' is not a dataset")
            _check_numeric(f, ("histograms", "timestamps", "force", "reference", "truth/touches", "truth/target_distance_m",
                               "onchip/distance_m", "onchip/confidence"), path)
            if f["timestamps"].ndim != 1:
                raise CaptureError(f"{path}: 'timestamps' has shape {f['timestamps'].shape}, expected (frames,)")
            n = f["timestamps"].shape[0]
            if COMMITTED in f.attrs:
                committed = _int_attr(f.attrs, COMMITTED, path)
                if committed < 0:
                    raise CaptureError(f"{path}: attribute '{COMMITTED}' is {committed}, must be >= 0")
                n = min(n, committed)
            if f["histograms"].ndim < 1 or f["histograms"].shape[0] < n:
                raise CaptureError(f"{path}: {f['histograms'].shape[:1]} histograms for {n} timestamps")
            hist = np.asarray(f["histograms"][:n], np.float64)
            times = np.asarray(f["timestamps"][:n], np.float64)
            force = np.asarray(f["force"][:n], np.float64) if "force" in f else None
            ref = np.asarray(f["reference"][:n], np.float64) if "reference" in f else None
            touches = truth = None
            if "truth" in f:
                try:
                    truth = json.loads(f["truth"].attrs.get("parameters", "{}"))
                except (TypeError, ValueError) as e:
                    raise CaptureError(f"{path}: attribute truth/parameters is not JSON: {e}") from None
                if not isinstance(truth, dict):
                    raise CaptureError(f"{path}: attribute truth/parameters is not a JSON object")
                if "touches" in f["truth"]:
                    touches = np.asarray(f["truth/touches"][:n], np.float64)
            extras = {
                k: np.asarray(f[name][:n], np.float64) if name in f else None
                for k, name in (("target_distance_m", "truth/target_distance_m"), ("onchip_distance_m", "onchip/distance_m"),
                                ("onchip_confidence", "onchip/confidence"))
            }
            source = f.attrs.get("source", "unknown")
            created = f.attrs.get("created", "")
        except CaptureError:
            raise
        except (OSError, KeyError, TypeError, ValueError, AttributeError) as e:
            raise CaptureError(f"{path}: unreadable data (truncated?): {e}") from None
    if hist.ndim != 4 or hist.shape[1:] != scene.shape:
        raise CaptureError(
            f"{path}: histograms have shape {hist.shape[1:]} per frame but the scene says "
            f"(sensors, zones, bins) = {scene.shape}"
        )
    for name, arr in (("force", force), ("reference", ref), ("truth/touches", touches), *extras.items()):
        if arr is not None and arr.shape[0] != n:
            raise CaptureError(f"{path}: '{name}' has {arr.shape[0]} frames, timestamps {n}")
    if n == 0:
        raise CaptureError(f"{path}: the capture has no (committed) frames")
    bad = _frame_problems(hist, times)
    keep = np.array([i for i in range(n) if i not in bad], int)
    if bad:
        if not len(keep):
            raise CaptureError(f"{path}: all {n} frames have impossible counts: {_describe(bad)}")
        warnings.warn(
            BadFramesWarning(f"{path}: dropped {len(bad)} of {n} frames with impossible counts: {_describe(bad)}"),
            stacklevel=2,
        )
        hist, times = hist[keep], times[keep]
        force = None if force is None else force[keep]
        ref = None if ref is None else ref[keep]
        touches = None if touches is None else touches[keep]
        extras = {k: None if v is None else v[keep] for k, v in extras.items()}
    return Capture(
        histograms=hist,
        timestamps=times,
        scene=scene,
        source=str(source),
        created=str(created),
        force=force,
        reference=ref,
        truth_touches=touches,
        truth=truth or {},
        frame_index=keep,
        dropped=bad,
        **extras,
    )


def _int_attr(attrs, name: str, path: Path, default: int | None = None) -> int:
    v = attrs.get(name, default)
    if isinstance(v, np.ndarray) and v.shape == ():
        v = v[()]
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        shown = v.item() if isinstance(v, np.generic) else v
        raise CaptureError(f"{path}: attribute '{name}' must be an integer, got {shown!r}"[:300])
    return int(v)


def _check_numeric(f: h5py.File, names, path: Path) -> None:
    for name in names:
        if name in f:
            d = f[name]
            if not isinstance(d, h5py.Dataset):
                raise CaptureError(f"{path}: '{name}' is not a dataset")
            kind = d.dtype.kind
            if kind not in "iuf":
                raise CaptureError(f"{path}: dataset '{name}' has dtype {d.dtype}, expected numbers")
