"""Import real TMF882x recordings into tofjax capture files (``tofjax import``).

Two formats:

- ``tmf882x-json``: a JSON list of captures, one frame each, with ``hists`` (zones x 128),
  ``reference_hist`` (128), ``dist_to_plane`` (m) and ``distances`` (the on-chip results),
  as in the shared TMF8820 plane sweep (github.com/cpsiff/SPAD-ICCP-Summer-School).
- ``tmf882x-log``: the serial log of ams-OSRAM's Arduino TMF882x driver: ``#Raw`` lines
  (one 128-byte plane of one channel each; packet ``n``: channel ``n % 10``, byte plane
  ``n // 10``) and ``#Obj`` lines (the result record), 3x3 mode.

Bad input never reaches a fit silently: a frame with a torn line, a missing byte plane, a
repeated packet number or saturated bins is dropped with a warning that names it; a file
with nothing usable is a one-line :class:`ImportError_` error.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..capture import BadFramesWarning
from ..errors import UserError

__all__ = ["DroppedFramesWarning", "ImportedFrames", "TmfImportError", "read_tmf882x_json", "read_tmf882x_log", "import_file", "FORMATS"]

FORMATS = ("tmf882x-json", "tmf882x-log")
#: Largest 24-bit count: a bin holding it has saturated.
SATURATED = 2**24 - 1
N_BINS = 128


class TmfImportError(UserError):
    """A recording cannot be imported; the message says why, in one line."""


class DroppedFramesWarning(BadFramesWarning):
    """Frames of a real recording were dropped (torn lines, missing byte planes, repeated
    packets, saturated bins, no ground truth) or left out of a sensor fit; the message names
    them by their index in the recording. The CLI shows it on stderr as
    ``tofjax <command>: warning: DroppedFramesWarning: ...``."""


@dataclass
class ImportedFrames:
    """Frames read from a recording of one sensor (zones in the recording's order)."""

    histograms: np.ndarray  # (F, Z, B)
    reference: np.ndarray | None  # (F, B)
    target_distance_m: np.ndarray | None  # (F,) ground truth, NaN where unknown
    onchip_distance_m: np.ndarray | None  # (F, Z) object-1 distance per zone, NaN where none
    onchip_confidence: np.ndarray | None  # (F, Z)
    source_index: np.ndarray  # (F,) index of each frame in the recording
    grid: tuple[int, int]
    dropped: list[tuple[int, str]] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return int(self.histograms.shape[0])


def _frames_text(idx: list[int]) -> str:
    if len(idx) > 12:
        return ", ".join(map(str, idx[:12])) + f", ... ({len(idx)} in all)"
    return ", ".join(map(str, idx))


def _warn_dropped(path, dropped: list[tuple[int, str]]) -> None:
    by_reason: dict[str, list[int]] = {}
    for i, why in dropped:
        by_reason.setdefault(why, []).append(i)
    for why, idx in by_reason.items():
        warnings.warn(f"{path}: dropped frame{'s' if len(idx) > 1 else ''} {_frames_text(idx)}: {why}", DroppedFramesWarning,
                      stacklevel=3)


def _grid_for(zones: int) -> tuple[int, int]:
    r = int(round(math.sqrt(zones)))
    return (r, r) if r * r == zones else (1, zones)


def _saturated(frames_hist: np.ndarray) -> np.ndarray:
    return np.any(frames_hist >= SATURATED, axis=tuple(range(1, frames_hist.ndim)))


# ---- JSON ----------------------------------------------------------------------------------
def read_tmf882x_json(path: str | Path, *, require_truth: bool = True) -> ImportedFrames:
    """Read the plane-sweep JSON format (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise TmfImportError(f"{path}: no such file")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise TmfImportError(f"{path}: not valid JSON ({e}); is it a tmf882x-log? pass --format tmf882x-log") from None
    if isinstance(data, dict):
        data = [data]
    if not isinstance(data, list) or not data:
        raise TmfImportError(f"{path}: expected a JSON list of captures (each with 'hists'), got {type(data).__name__}")
    hists, refs, dists, onc, conf, src, dropped = [], [], [], [], [], [], []
    zones = None
    no_truth, bad_ref = [], []
    for i, e in enumerate(data):
        if not isinstance(e, dict) or "hists" not in e:
            dropped.append((i, "no 'hists' field"))
            continue
        try:
            h = np.asarray(e["hists"], float)
        except (TypeError, ValueError):
            dropped.append((i, "'hists' is not a regular array of numbers"))
            continue
        if h.ndim != 2 or h.shape[1] != N_BINS or not np.all(np.isfinite(h)) or np.any(h < 0):
            dropped.append((i, f"'hists' is not zones x {N_BINS} non-negative counts (shape {h.shape})"))
            continue
        if zones is None:
            zones = h.shape[0]
        if h.shape[0] != zones:
            dropped.append((i, f"{h.shape[0]} zones where the first frame has {zones}"))
            continue
        dist = e.get("dist_to_plane")
        if dist is not None:
            try:
                dist = float(dist)
            except (TypeError, ValueError):
                dropped.append((i, f"'dist_to_plane' is not a number ({dist!r})"))
                continue
            if not np.isfinite(dist):
                dist = None  # NaN: no ground truth, as a missing field
        if dist is None:
            no_truth.append(i)
            if require_truth:
                continue
        if _saturated(h[None])[0]:
            dropped.append((i, f"saturated bins (count {SATURATED})"))
            continue
        r = e.get("reference_hist")
        try:
            r = None if r is None else np.asarray(r, float)
        except (TypeError, ValueError):
            r = np.zeros(0)
        if r is not None and r.shape != (N_BINS,):
            bad_ref.append(i)
            r = None
        refs.append(r if r is not None else np.full(N_BINS, np.nan))
        hists.append(h)
        dists.append(np.nan if dist is None else dist)
        dd, cc = _json_onchip(e.get("distances"), zones)
        onc.append(dd)
        conf.append(cc)
        src.append(i)
    if no_truth and require_truth:
        if len(no_truth) == len(data):
            raise TmfImportError(
                f"{path}: no frame has 'dist_to_plane' (the ground-truth distance in metres); "
                "pass --no-truth to import without ground truth"
            )
        dropped += [(i, "no 'dist_to_plane' (ground truth)") for i in no_truth]
    if dropped:
        _warn_dropped(path, sorted(dropped))
    if not hists:
        raise TmfImportError(f"{path}: no usable frame ({len(dropped)} dropped)")
    if bad_ref:
        warnings.warn(DroppedFramesWarning(
            f"{path}: {len(bad_ref)} frames' reference_hist is not {N_BINS} numbers (first: entry {bad_ref[0]}); "
            "their reference channel is left out (NaN)"), stacklevel=2)
    ref = np.stack(refs)
    return ImportedFrames(
        histograms=np.stack(hists),
        reference=None if np.all(np.isnan(ref)) else ref,
        target_distance_m=np.asarray(dists),
        onchip_distance_m=np.stack(onc),
        onchip_confidence=np.stack(conf),
        source_index=np.asarray(src),
        grid=_grid_for(zones),
        dropped=sorted(dropped),
    )


def _json_onchip(distances, zones):
    d = np.full(zones, np.nan)
    c = np.full(zones, np.nan)
    if isinstance(distances, list) and distances:
        rec = distances[0]
        if isinstance(rec, dict) and "depths_1" in rec:
            dep = np.asarray(rec["depths_1"], float)[:zones]
            cf = np.asarray(rec.get("confs_1", np.full(len(dep), 255)), float)[:zones]
            d[: len(dep)] = np.where(cf > 0, dep * 1e-3, np.nan)
            c[: len(cf)] = cf
    return d, c


# ---- Arduino serial log --------------------------------------------------------------------
def read_tmf882x_log(path: str | Path, *, distance_m: float | None = None) -> ImportedFrames:
    """Read a serial log of ams-OSRAM's Arduino TMF882x driver (3x3 mode).

    A frame ends at the packet with ``n = 29``; it is kept only if it holds each of the 30
    packets exactly once and none of its lines was torn. ``distance_m`` sets the ground
    truth of every frame (the log has none).
    """
    path = Path(path)
    if not path.is_file():
        raise TmfImportError(f"{path}: no such file")
    frames, dropped, src = [], [], []
    results = []
    packets: dict[int, np.ndarray] = {}
    problems: list[str] = []
    obj = None
    frame_no = 0
    seen_any = False
    with path.open("r", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if line.startswith("#Raw"):
                seen_any = True
                parts = line.split(",")
                n = _int(parts[2]) if len(parts) > 2 else None
                vals = [_int(p) for p in parts[3:]]
                if len(parts) != 131 or n is None or not 0 <= n <= 29 or any(v is None or not 0 <= v <= 255 for v in vals):
                    problems.append(f"torn #Raw line {lineno}")
                    if n == 29 and len(parts) > 2:
                        pass  # the end marker itself is torn: the frame still ends here
                    else:
                        continue
                elif n in packets:
                    problems.append(f"repeated packet number {n} (line {lineno})")
                else:
                    packets[n] = np.asarray(vals, float)
                if n == 29:
                    missing = sorted(set(range(30)) - set(packets))
                    if missing:
                        planes = sorted({m // 10 for m in missing})
                        problems.append(
                            f"missing packet{'s' if len(missing) > 1 else ''} {','.join(map(str, missing))} "
                            f"(byte plane{'s' if len(planes) > 1 else ''} {','.join(map(str, planes))})"
                        )
                    if problems:
                        dropped.append((frame_no, "; ".join(dict.fromkeys(problems))))
                    else:
                        counts = np.zeros((10, N_BINS))
                        for k, v in packets.items():
                            counts[k % 10] += v * 256 ** (k // 10)
                        if np.any(counts >= SATURATED):
                            dropped.append((frame_no, f"saturated bins (count {SATURATED})"))
                        else:
                            frames.append(counts)
                            results.append(obj)
                            src.append(frame_no)
                    packets, problems, obj = {}, [], None
                    frame_no += 1
            elif line.startswith("#Obj"):
                seen_any = True
                parts = line.split(",")
                vals = [_int(p) for p in parts[1:]]
                if len(parts) != 78 or any(v is None for v in vals):
                    problems.append(f"torn #Obj line {lineno}")
                    obj = None
                else:
                    obj = vals
            # any other line (start-up text, comments) is skipped
    if packets or problems:
        dropped.append((frame_no, "incomplete at the end of the log (no packet 29)"))
    if dropped:
        _warn_dropped(path, dropped)
    if not seen_any:
        raise TmfImportError(f"{path}: no '#Raw' or '#Obj' lines: not a TMF882x Arduino log (use --format tmf882x-json for JSON)")
    if not frames:
        raise TmfImportError(f"{path}: no complete frame ({len(dropped)} dropped)")
    counts = np.stack(frames)
    F = len(frames)
    onc = np.full((F, 9), np.nan)
    conf = np.full((F, 9), np.nan)
    for i, r in enumerate(results):
        if r is None:
            continue
        # fields 6-23 of the line (1-based after the tag: index 5..22 of r) are (distance mm, confidence) for channels 1-9
        pairs = np.asarray(r[5:23], float).reshape(9, 2)
        conf[i] = pairs[:, 1]
        onc[i] = np.where(pairs[:, 1] > 0, pairs[:, 0] * 1e-3, np.nan)
    return ImportedFrames(
        histograms=counts[:, 1:],
        reference=counts[:, 0],
        target_distance_m=np.full(F, np.nan if distance_m is None else float(distance_m)),
        onchip_distance_m=onc,
        onchip_confidence=conf,
        source_index=np.asarray(src),
        grid=(3, 3),
        dropped=dropped,
    )


def _int(s: str):
    try:
        return int(s.strip())
    except (ValueError, AttributeError):
        return None


# ---- to a capture --------------------------------------------------------------------------
def imported_scene(frames: ImportedFrames, bin_width_s: float = 100e-12):
    """A free-space scene for a recording: one sensor, its zone grid, no waveguide."""
    from ..scene import FreeSpaceTarget, scene_from_dict

    d = frames.target_distance_m
    dist = float(np.nanmedian(d)) if d is not None and np.any(np.isfinite(d)) else None
    scene = {
        "name": "tmf882x-import",
        "description": "imported TMF882x recording: a flat target in air (free space)",
        "sensor": {
            "bin_width_s": bin_width_s,
            "n_bins": int(frames.histograms.shape[-1]),
            "zones": int(frames.histograms.shape[1]),
            "grid": list(frames.grid),
            "fov_deg": 45.0,
            "emission_time_s": 14.5 * bin_width_s,
        },
        "sensors": [{"position_m": [0.0, 0.0], "direction_deg": 0.0, "name": "tmf882x"}],
    }
    if dist is not None:
        scene["target"] = {"distance_m": dist}
    _ = FreeSpaceTarget
    return scene_from_dict(scene, "imported scene")


def to_capture(frames: ImportedFrames, source: str):
    from ..capture import Capture

    F = frames.n_frames
    return Capture(
        histograms=frames.histograms[:, None].astype(np.float64),
        timestamps=np.arange(F, dtype=float),
        scene=imported_scene(frames),
        source=source,
        reference=None if frames.reference is None else frames.reference[:, None],
        target_distance_m=frames.target_distance_m,
        onchip_distance_m=None if frames.onchip_distance_m is None else frames.onchip_distance_m[:, None],
        onchip_confidence=None if frames.onchip_confidence is None else frames.onchip_confidence[:, None],
        truth={"source_frames": [int(i) for i in frames.source_index]},
    )


def import_file(path, fmt: str, out, *, distance_m: float | None = None, require_truth: bool = True,
                overwrite: bool = False):
    """Read ``path`` in format ``fmt`` and write a capture to ``out``; returns (ImportedFrames, out path)."""
    from ..capture import write_capture

    if fmt == "tmf882x-json":
        if distance_m is not None:
            raise TmfImportError("--distance-m is for logs without ground truth; the JSON format carries dist_to_plane")
        frames = read_tmf882x_json(path, require_truth=require_truth)
    elif fmt == "tmf882x-log":
        frames = read_tmf882x_log(path, distance_m=distance_m)
    else:
        raise TmfImportError(f"--format: unknown format {fmt!r}; known: {', '.join(FORMATS)}")
    return frames, write_capture(out, to_capture(frames, fmt), overwrite=overwrite)
