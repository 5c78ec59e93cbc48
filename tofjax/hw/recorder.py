"""Recording: whole frames from a rig into a capture file, each appended and flushed.

:func:`acquire` is the one entry point (``tofjax acquire`` and ``tofjax baseline`` call
it). Frames come from :class:`~tofjax.hw.driver.TMF8828Array` only when whole; each is
written with :class:`~tofjax.capture.CaptureWriter`, which flushes after every frame, so
Ctrl-C or a power cut loses at most the frame in flight and the file stays readable.
"""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..capture import Capture, CaptureWriter, read_capture
from ..errors import UserError
from ..scene import Scene
from . import protocol as P
from .bus import BusFaults, SimClock
from .driver import DeviceError, ErrorCounts, Frame, FrameDropped
from .emulator import DeviceFaults
from .rig import Rig, emulated_bus, emulated_int_pins, load_rig_or_scene, open_array, real_bus

__all__ = ["AcquireOptions", "AcquireResult", "EndOfStream", "ReplaySource", "acquire", "iter_frames", "record", "replay"]


@dataclass(frozen=True)
class AcquireOptions:
    """What to record and how.

    - ``frames`` / ``duration_s``: stop after this many whole frames / seconds (of the rig's
      clock: simulated seconds when emulated). At least one must be given.
    - ``emulate``: an emulated rig (histograms from the scene's forward model) instead of ``/dev/i2c-N``.
    - ``image``: application image (Intel HEX or binary). Required on hardware; with ``emulate``
      and no image a synthetic one is used (it is not firmware; see ``docs/acquisition.md``).
    - ``bus``, ``bus_speed_hz``: override the rig's bus number / speed (the speed only matters
      for emulation: on a Pi it is set in config.txt).
    - ``baseline``: record a no-touch baseline (the scene without touches).
    - ``seed``, ``noise``: emulator photon noise (``None``: the scene's ``[noise]``).
    - ``bus_faults``, ``device_faults``: fault injection for emulated rigs.
    - ``period_ms``: override the rig's measurement period.
    - ``max_dropped_in_row``: consecutive dropped frames after which recording stops with an error.
    - ``progress``: a live status line (tqdm) with frame rate and error counts.
    - ``overwrite``: replace an existing ``out`` (never one another process is still writing).
    """

    frames: int | None = None
    duration_s: float | None = None
    emulate: bool = False
    image: str | None = None
    bus: int | None = None
    bus_speed_hz: int | None = None
    baseline: bool = False
    seed: int = 0
    noise: bool | None = None
    bus_faults: BusFaults = BusFaults()
    device_faults: DeviceFaults = DeviceFaults()
    period_ms: int | None = None
    max_dropped_in_row: int = 20
    progress: bool = True
    overwrite: bool = False

    def __post_init__(self):
        if self.frames is None and self.duration_s is None:
            raise UserError("give --frames N or --duration S")
        if self.frames is not None and self.frames < 1:
            raise UserError(f"--frames: must be >= 1, got {self.frames}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise UserError(f"--duration: must be > 0, got {self.duration_s}")


@dataclass
class AcquireResult:
    path: Path
    frames: int
    dropped: int
    errors: dict[str, int]
    elapsed_s: float  # on the rig's clock (simulated when emulated)
    wall_s: float
    interrupted: bool = False
    bus: dict[str, Any] = field(default_factory=dict)
    synthetic_image: bool = False

    @property
    def frame_rate_hz(self) -> float:
        return self.frames / self.elapsed_s if self.elapsed_s > 0 else float("nan")

    def summary(self) -> str:
        errs = ", ".join(f"{k} {v}" for k, v in self.errors.items() if v) or "none"
        return (f"{'interrupted: ' if self.interrupted else ''}wrote {self.path}: {self.frames} frames "
                f"({self.frame_rate_hz:.2f} frames/s), {self.dropped} dropped; handled errors: {errs}")


_HELD = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def _sigint_deferred():
    """Hold Ctrl-C and SIGTERM while one frame is being written, so a frame is in the file whole
    or not at all (a kill -9 or power cut cannot be held: the writer's commit count covers those)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got = []
    old = {s: signal.signal(s, lambda *a: got.append(a)) for s in _HELD}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if got:
            raise KeyboardInterrupt


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM ends a recording the way Ctrl-C does: cleanly, with every committed frame kept.
    SIGINT too, for the whole recording: a process started in the background by a
    non-interactive shell inherits SIGINT ignored, and it would then stop on Ctrl-C only when
    the signal happened to land while a frame was being written (where it is held)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(*_):
        raise KeyboardInterrupt

    old = {s: signal.signal(s, stop) for s in _HELD}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class EndOfStream(Exception):
    """A frame source (a replay) has no more frames."""


@dataclass
class StreamStats:
    frames: int = 0
    dropped: int = 0


def iter_frames(source, *, frames: int | None = None, duration_s: float | None = None,
                max_dropped_in_row: int = 20, stats: StreamStats | None = None) -> Iterator[Frame]:
    """Whole frames from a live rig (an opened :class:`TMF8828Array`) or a :class:`ReplaySource`, the same way.

    Frames the driver could not read whole are skipped and counted in ``stats.dropped``;
    after ``max_dropped_in_row`` in a row it stops with a :class:`DeviceError`. Stops after
    ``frames`` frames, ``duration_s`` seconds of the source's clock, or the end of a replay.
    """
    stats = stats if stats is not None else StreamStats()
    clock = source.clock
    t0 = clock.now()
    in_row = 0
    while (frames is None or stats.frames < frames) and (duration_s is None or clock.now() - t0 < duration_s):
        try:
            fr = source.read_frame()
        except EndOfStream:
            return
        except FrameDropped:
            stats.dropped += 1
            in_row += 1
            if in_row >= max_dropped_in_row:
                raise DeviceError(f"{in_row} frames in a row could not be read whole: {source.errors.short()}; "
                                  "check the wiring, or slow the bus") from None
            continue
        in_row = 0
        stats.frames += 1
        yield fr


def record(source, writer: CaptureWriter, *, frames: int | None = None, duration_s: float | None = None,
           touches=None, progress: bool = True, max_dropped_in_row: int = 20, label: str = "") -> tuple[int, int, bool]:
    """Append whole frames from ``source`` (an opened rig or a replay) to ``writer``, each flushed.

    Returns ``(frames written, frames dropped, interrupted)``. Ctrl-C ends it cleanly:
    every frame completed before it is in the file.
    """
    from tqdm import tqdm

    clock = source.clock
    t0 = clock.now()
    stats = StreamStats()
    written = 0
    interrupted = False
    bar = tqdm(total=frames, unit="frame", disable=not progress, desc=label or "acquire", dynamic_ncols=True)
    _term = _sigterm_as_interrupt()
    _term.__enter__()
    try:
        for fr in iter_frames(source, frames=frames, duration_s=duration_s, max_dropped_in_row=max_dropped_in_row,
                              stats=stats):
            with _sigint_deferred():
                writer.append(fr.histograms, fr.timestamp - t0, reference=fr.reference, touches=touches)
            written += 1
            bar.update(1)
            dt = clock.now() - t0
            bar.set_postfix_str(f"{written / dt if dt > 0 else 0:.2f} fps, dropped {stats.dropped}, errors: "
                                f"{source.errors.short()}", refresh=False)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        _term.__exit__(None, None, None)
        bar.close()
    return written, stats.dropped, interrupted


#: The longest a replay at a given speed may take (s): beyond, a recording's gaps (or a tiny speed) would
#: read as a hang.
MAX_REPLAY_S = 7 * 86400.0


class ReplaySource:
    """A recorded capture as a frame source: the same :meth:`read_frame` as a live rig.

    ``speed``: ``"max"`` (as fast as the consumer takes them), ``"recorded"`` (the recorded
    frame times, in wall time), or a number (a multiple of the recorded speed). ``clock``
    reads the recorded time of the frame last given, so timestamps pass through unchanged.
    """

    def __init__(self, capture: Capture | str | Path, speed: str | float = "max"):
        self.capture = capture if isinstance(capture, Capture) else read_capture(capture)
        if speed == "max":
            self.factor = None
        elif speed == "recorded":
            self.factor = 1.0
        else:
            try:
                self.factor = float(speed)
            except (TypeError, ValueError):
                raise UserError(f"--speed: max, recorded or a positive number, got {speed!r}") from None
            if not self.factor > 0:
                raise UserError(f"--speed: must be > 0, got {speed!r}")
        ts = np.asarray(self.capture.timestamps, float)
        where = capture if not isinstance(capture, Capture) else "the capture"
        if not np.isfinite(ts).all():
            raise UserError(f"{where}: its timestamps are not all finite")
        if self.factor is not None and len(ts) > 1:
            back = np.flatnonzero(np.diff(ts) < 0)
            if len(back):
                raise UserError(f"{where}: the timestamps go backwards at frame {back[0] + 1}; replay it with --speed max")
            total = (ts[-1] - ts[0]) / self.factor
            if not total <= MAX_REPLAY_S:
                raise UserError(f"--speed {speed}: replaying {ts[-1] - ts[0]:.3g} s of recording would take {total:.3g} s "
                                f"(more than {MAX_REPLAY_S / 86400:g} days); use a higher speed or max")
        self.errors = ErrorCounts()
        self.clock = SimClock(0.0)  # the recording's own time origin: timestamps pass through unchanged
        self._i = 0
        self._wall0: float | None = None

    def read_frame(self) -> Frame:
        cap = self.capture
        if self._i >= cap.n_frames:
            raise EndOfStream
        i = self._i
        t = float(cap.timestamps[i])
        if self.factor is not None:
            if self._wall0 is None:
                self._wall0 = time.perf_counter() - (t - float(cap.timestamps[0])) / self.factor
            wait = self._wall0 + (t - float(cap.timestamps[0])) / self.factor - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        self.clock.t = t
        self._i += 1
        ref = None if cap.reference is None else cap.reference[i]
        return Frame(cap.histograms[i], ref, t, [])


def replay(capture: str | Path, out: str | Path | None = None, *, speed: str | float = "max",
           progress: bool = True, overwrite: bool = False) -> AcquireResult:
    """Feed a recorded capture through the live pipeline (:func:`iter_frames`, :func:`record`),
    at recorded or maximum speed; with ``out``, the frames are written again as a live rig's are."""
    src = ReplaySource(capture, speed)
    cap = src.capture
    t_wall = time.perf_counter()
    if out is None:
        n = sum(1 for _ in iter_frames(src))
        written, dropped, interrupted, path = n, 0, False, Path(capture)
    else:
        with CaptureWriter(out, cap.scene, source=cap.source, with_reference=cap.reference is not None,
                           max_touches=0 if cap.truth_touches is None else cap.truth_touches.shape[1],
                           truth=cap.truth or None, overwrite=overwrite) as w:
            written, dropped, interrupted = record(src, w, progress=progress, label="replay")
        path = Path(out)
    elapsed = float(np.ptp(cap.timestamps[:written])) if written > 1 else 0.0  # timestamps may go backwards (at max speed)
    return AcquireResult(path, written, dropped, dict(src.errors.counts), elapsed, time.perf_counter() - t_wall,
                         interrupted)


def acquire(rig_or_scene: str | tuple[Rig, Scene], out: str | Path, options: AcquireOptions) -> AcquireResult:
    """Record a capture from a rig (real or emulated) into ``out``.

    **Arguments:**

    - ``rig_or_scene``: a rig file, a scene file or built-in scene name (one sensor: no
      selection; several: behind a mux on channels 0..), or a ``(Rig, Scene)`` pair.
    - ``out``: the capture file (HDF5, :mod:`tofjax.capture` format, with the reference channel).
    - ``options``: see :class:`AcquireOptions`.

    **Returns:** an :class:`AcquireResult` (frames written, dropped, error counts, rates).
    """
    from ..capture import check_capture_target
    from ..simulate import true_parameters

    check_capture_target(out, options.overwrite)  # before the rig is opened (firmware, seconds)
    if isinstance(rig_or_scene, tuple):
        rig, scene = rig_or_scene
        is_rig = True
    else:
        rig, scene, is_rig = load_rig_or_scene(rig_or_scene)
    if options.bus_speed_hz is not None:
        rig = dataclasses.replace(rig, bus_speed_hz=options.bus_speed_hz)
    if options.period_ms is not None:
        rig = dataclasses.replace(rig, period_ms=options.period_ms)
    if options.baseline:
        scene = scene.without_touches()
    if not options.emulate:
        n = rig.bus if options.bus is None else options.bus
        if not Path(f"/dev/i2c-{n}").exists():
            raise UserError(f"/dev/i2c-{n} does not exist: enable I2C (sudo raspi-config, Interface Options) "
                            "or pass --emulate")
    image_path = options.image or rig.image_path()
    synthetic = image_path is None
    if synthetic:
        if not options.emulate:
            raise UserError(
                "no application image: pass --image PATH (the ams-OSRAM TMF8828 image, Intel HEX or binary; "
                "tofjax does not ship it, see docs/acquisition.md)"
            )
        image = P.synthetic_image()
    else:
        image = P.load_image(image_path)
    truth = None
    touches = None
    if options.emulate:
        if not is_rig and scene.n_sensors > 8:
            raise UserError("an emulated rig for a bare scene puts its sensors behind one 8-channel mux")
        bus, pins, emus = emulated_bus(rig, scene, noise=options.noise, bus_faults=options.bus_faults,
                                       device_faults=options.device_faults, image=image, seed=options.seed)
        int_pins = emulated_int_pins(rig, emus)
        from ..model import Params

        truth = true_parameters(Params.from_scene(scene))
        truth.update(seed=options.seed, emulated=True, bus_speed_hz=rig.bus_speed_hz, synthetic_image=synthetic)
        el = scene.contact_elements()
        touches = el[:, [0, 1, 3]] if len(el) else None
        capture_scene = scene
    else:
        bus, pins, int_pins = real_bus(rig, options.bus)
        capture_scene = scene.without_touches()  # on hardware the contacts are what we want to find
    array = open_array(rig, scene, bus, pins, image, int_pins=int_pins)
    source = "tmf8828-emulated" if options.emulate else "tmf8828"
    t_wall = time.perf_counter()
    try:
        array.open()
        t0 = array.clock.now()
        with CaptureWriter(out, capture_scene, source=source, with_reference=True,
                           max_touches=0 if touches is None else len(touches), truth=truth,
                           overwrite=options.overwrite) as w:
            written, dropped, interrupted = record(
                array, w, frames=options.frames, duration_s=options.duration_s, touches=touches,
                progress=options.progress, max_dropped_in_row=options.max_dropped_in_row,
                label="baseline" if options.baseline else "acquire",
            )
        elapsed = array.clock.now() - t0
    finally:
        array.close()
        if not options.emulate:
            bus.close()
            for p in [*(pins or []), *(int_pins or [])]:
                if p is not None:
                    p.close()
    stats = getattr(bus, "stats", None)
    busd = {} if stats is None else {"transfers": stats.transfers, "bytes": stats.bytes, "busy_s": stats.busy_s,
                                     "frequency_hz": bus.frequency_hz}
    return AcquireResult(Path(out), written, dropped, dict(array.errors.counts), elapsed,
                         time.perf_counter() - t_wall, interrupted, busd, synthetic)
