"""Hostile inputs (issue 15): every command, every input file, every number, every output.

A table of bad inputs, each run through ``tofjax.cli.main(argv)`` in-process (starting
``tofjax`` 250 times would cost minutes of imports). Each must end in a one-line error
(``tofjax CMD: error: ...``, exit code != 0) with no traceback, or -- where the input is
usable in part -- in exit 0 with a *named* warning and a result that says what was left out.
Outputs that already exist must come out byte for byte unchanged.

Cheap by construction: the captures are written with NumPy (no model is compiled), and every
bad input is refused before any model is built; only the two warning cases run an inversion.

``python tests/test_hostile.py [--json OUT]`` runs the table outside pytest and counts clear
errors, tracebacks and silent results (the counts in the README were made this way; run it with
another checkout first on PYTHONPATH to count the "before").
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pickle
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from tofjax.capture import BadFramesWarning, Capture, read_capture, write_capture
from tofjax.cli import main
from tofjax.errors import UserError

GOOD_SCENE = None  # filled by _build(): TOML text of a tiny scene (1 sensor x 2 zones x 16 bins)


# ---- the world the cases run in -----------------------------------------------------------------


def _tiny_scene():
    from tofjax.scene import Touch, load_scene

    s = load_scene("optoskin")
    s = s.replace(sensor=dataclasses.replace(s.sensor, n_bins=16, zones=2), sensors=s.sensors[:1], name="tiny")
    lx, ly = s.waveguide.size_m
    return s, s.replace(touches=(Touch(position_m=(0.5 * lx, 0.5 * ly), radius_m=0.01, strength=1.0),))


def _capture(scene, n=3, seed=0, **kw) -> Capture:
    rng = np.random.default_rng(seed)
    hist = rng.poisson(200.0, (n, *scene.shape)).astype(float) + 1.0
    return Capture(hist, np.arange(n) * 0.033, scene, **kw)


def _scene_variants(text: str) -> dict[str, bytes]:
    """Bad scene files: name -> bytes."""
    text = "\n".join(line for line in text.splitlines() if line.strip() != "touches = []") + "\n"

    def sub(old, new):
        assert old in text, old
        return text.replace(old, new, 1).encode()

    return {
        "non_utf8": b'name = "\xff\xfe\xfa"\n' + text.encode(),
        "binary_junk": bytes(range(256)) * 4,
        "empty": b"",
        "invalid_toml": b"[waveguide\nsize_m = [",
        "duplicate_key": ('name = "again"\n' + text).encode(),
        "no_waveguide": "\n".join(l for l in text.splitlines() if not l.startswith("[waveguide")).encode(),
        "unknown_top_key": ("colour = 3\n" + text).encode(),
        "n_bins_huge": sub("n_bins = 16", "n_bins = 10000000"),
        "n_bins_129": sub("n_bins = 16", "n_bins = 129"),
        "n_bins_1": sub("n_bins = 16", "n_bins = 1"),
        "n_bins_float": sub("n_bins = 16", "n_bins = 16.5"),
        "n_bins_string": sub("n_bins = 16", 'n_bins = "16"'),
        "n_bins_bool": sub("n_bins = 16", "n_bins = true"),
        "zones_huge": sub("zones = 2", "zones = 100000000"),
        "zones_65": sub("zones = 2", "zones = 65"),
        "zones_0": sub("zones = 2", "zones = 0"),
        "zones_negative": sub("zones = 2", "zones = -3"),
        "n1_one": _replace_value(text, "n1", "1.0"),
        "n1_nan": _replace_value(text, "n1", "nan"),
        "n1_inf": _replace_value(text, "n1", "inf"),
        "n1_below_one": _replace_value(text, "n1", "0.5"),
        "thickness_zero": _replace_value(text, "thickness_m", "0.0"),
        "thickness_negative": _replace_value(text, "thickness_m", "-0.005"),
        "mu_s_negative": _replace_value(text, "mu_s_per_m", "-1.0"),
        "mu_a_nan": _replace_value(text, "mu_a_per_m", "nan"),
        "size_zero": _replace_value(text, "size_m", "[0.0, 0.3]"),
        "size_three": _replace_value(text, "size_m", "[0.3, 0.3, 0.3]"),
        "size_string": _replace_value(text, "size_m", '"big"'),
        "fov_180": _replace_value(text, "fov_deg", "180.0"),
        "fov_negative": _replace_value(text, "fov_deg", "-5.0"),
        "bin_width_zero": _replace_value(text, "bin_width_s", "0.0"),
        "iterations_zero": _replace_value(text, "iterations", "0"),
        "iterations_huge": _replace_value(text, "iterations", "1000000000000"),
        "end_reflectance_2": _replace_value(text, "end_reflectance", "2.0"),
        "emission_outside": _replace_value(text, "gain", "150.0\nemission_time_s = 1.0"),
        "no_sensors": "\n".join(_drop_table(text, "[[sensors]]")).encode(),
        "sensor_off_edge": _replace_value(text, "position_m", "[0.1, 0.1]"),
        "sensor_points_out": _replace_value(text, "direction_deg", "270.0"),
        "sensors_65": (text + "".join(_sensor_block(text) for _ in range(64))).encode(),
        "touch_outside": (text + "\n[[touches]]\nposition_m = [5.0, 5.0]\nradius_m = 0.01\nstrength = 1.0\n").encode(),
        "touch_radius_zero": (text + "\n[[touches]]\nposition_m = [0.1, 0.1]\nradius_m = 0.0\nstrength = 1.0\n").encode(),
        "touch_strength_negative": (text + "\n[[touches]]\nposition_m = [0.1, 0.1]\nradius_m = 0.01\nstrength = -1.0\n").encode(),
        "touch_shape_blob": (text + '\n[[touches]]\nposition_m = [0.1, 0.1]\nradius_m = 0.01\nstrength = 1.0\nshape = "blob"\n').encode(),
        "touch_stick_billions": (text + '\n[[touches]]\nposition_m = [0.1, 0.1]\nradius_m = 1e-9\nstrength = 1.0\nshape = "stick"\nlength_m = 0.1\n').encode(),
        "touch_ring_billions": (text + '\n[[touches]]\nposition_m = [0.15, 0.15]\nradius_m = 1e-9\nstrength = 1.0\nshape = "ring"\nring_radius_m = 0.05\n').encode(),
        "touch_missing_radius": (text + "\n[[touches]]\nposition_m = [0.1, 0.1]\nstrength = 1.0\n").encode(),
        "components_unknown": _replace_value(text, "components", '["crosstalk", "magic"]'),
        "components_string": _replace_value(text, "components", '"all"'),
        "noise_not_bool": _replace_value(text, "poisson", "1"),
        # the audit of 2026-11-29: scenes that wrote all-zero captures (exit 0), a sensor model ignored
        "n1_huge": _replace_value(text, "n1", "1e300"),
        "bin_width_tiny": _replace_value(text, "bin_width_s", "1e-300"),
        "saturation_tiny": _replace_value(text, "saturation_counts", "1e-300"),
        "sensor_model_missing": sub("[sensor]", '[sensor]\nmodel = "no-such-sensor.json"'),
    }


def _replace_value(text: str, key: str, value: str) -> bytes:
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.split("=")[0].strip() == key:
            lines[i] = f"{key} = {value}"
            return "\n".join(lines).encode()
    raise AssertionError(key)


def _drop_table(text: str, header: str):
    skip = False
    for line in text.splitlines():
        if line.startswith("["):
            skip = line.strip() == header
        if not skip:
            yield line


def _sensor_block(text: str) -> str:
    lines = text.splitlines()
    i = lines.index("[[sensors]]")
    block = ["", "[[sensors]]"]
    for line in lines[i + 1:]:
        if line.startswith("[") or not line.strip():
            break
        if not line.startswith("name"):
            block.append(line)
    return "\n".join(block) + "\n"


def _capture_variants(world: Path, good: Path) -> dict[str, Path]:
    """Bad capture files, made from a copy of a good one."""
    out = {}

    def copy(name, edit=None):
        p = world / f"cap_{name}.h5"
        p.write_bytes(good.read_bytes())
        if edit is not None:
            with h5py.File(p, "a") as f:
                edit(f)
        out[name] = p
        return p

    def raw(name, data: bytes):
        p = world / f"cap_{name}.h5"
        p.write_bytes(data)
        out[name] = p

    def replace(f, name, data):
        del f[name]
        f[name] = data

    raw("text_file", b"hello, not a capture\n")
    raw("empty_file", b"")
    raw("truncated", good.read_bytes()[: len(good.read_bytes()) // 3])
    raw("hdf5_header_only", good.read_bytes()[:600])
    foreign = world / "cap_foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["data"] = np.zeros(3)
    out["foreign"] = foreign
    copy("format_wrong", lambda f: f.attrs.__setitem__("format", "someone.else"))
    copy("format_number", lambda f: f.attrs.__setitem__("format", 7))
    copy("version_2", lambda f: f.attrs.__setitem__("version", 2))
    copy("version_string", lambda f: f.attrs.__setitem__("version", "1"))
    copy("version_float", lambda f: f.attrs.__setitem__("version", 1.5))
    copy("version_array", lambda f: f.attrs.__setitem__("version", np.array([1, 1])))
    copy("no_version", lambda f: f.attrs.__delitem__("version"))
    copy("no_scene", lambda f: f.attrs.__delitem__("scene"))
    copy("scene_not_json", lambda f: f.attrs.__setitem__("scene", "{not json"))
    copy("scene_number", lambda f: f.attrs.__setitem__("scene", 3.0))
    copy("scene_list", lambda f: f.attrs.__setitem__("scene", "[1, 2]"))
    copy("scene_invalid", lambda f: f.attrs.__setitem__("scene", f.attrs["scene"].replace('"n1": 1.', '"n1": 0.')))
    copy("scene_huge_number", lambda f: f.attrs.__setitem__("scene", f.attrs["scene"].replace('"n1": 1.', '"n1": 1' + "0" * 400 + '.')))
    copy("no_histograms", lambda f: f.__delitem__("histograms"))
    copy("no_timestamps", lambda f: f.__delitem__("timestamps"))
    copy("histograms_group", lambda f: (f.__delitem__("histograms"), f.create_group("histograms")))
    copy("histograms_strings", lambda f: replace(f, "histograms", np.full((3, 1, 2, 16), "x", dtype="S3")))
    copy("timestamps_strings", lambda f: replace(f, "timestamps", np.array([b"a", b"b", b"c"])))
    copy("histograms_wrong_shape", lambda f: replace(f, "histograms", np.ones((3, 1, 2, 15), np.float32)))
    copy("histograms_1d", lambda f: replace(f, "histograms", np.ones(3, np.float32)))
    copy("timestamps_2d", lambda f: replace(f, "timestamps", np.zeros((3, 2))))
    copy("fewer_histograms", lambda f: replace(f, "histograms", np.ones((1, 1, 2, 16), np.float32)))
    copy("zero_frames", lambda f: (replace(f, "histograms", np.ones((0, 1, 2, 16), np.float32)),
                                   replace(f, "timestamps", np.zeros(0)), f.attrs.__setitem__("committed_frames", 0)))
    copy("committed_zero", lambda f: f.attrs.__setitem__("committed_frames", 0))
    copy("committed_negative", lambda f: f.attrs.__setitem__("committed_frames", -1))
    copy("committed_string", lambda f: f.attrs.__setitem__("committed_frames", "3"))
    hist = np.asarray(read_capture(good).histograms, np.float32)
    copy("all_nan", lambda f: f["histograms"].__setitem__(slice(None), np.nan))
    copy("all_zero", lambda f: f["histograms"].__setitem__(slice(None), 0.0))
    copy("all_negative", lambda f: f["histograms"].__setitem__(slice(None), -hist))
    copy("all_inf", lambda f: f["histograms"].__setitem__(slice(None), np.inf))

    def one_nan_bin_per_frame(f):
        h = hist.copy()
        h[:, 0, 0, 5] = np.nan
        f["histograms"][...] = h

    copy("one_nan_bin_per_frame", one_nan_bin_per_frame)
    copy("timestamps_nan", lambda f: f["timestamps"].__setitem__(slice(None), np.nan))
    copy("truth_not_json", lambda f: f.require_group("truth").attrs.__setitem__("parameters", "{oops"))
    copy("force_short", lambda f: f.create_dataset("force", data=np.zeros(1)))
    copy("force_strings", lambda f: f.create_dataset("force", data=np.array([b"a", b"b", b"c"])))
    folder = world / "cap_folder.h5"
    folder.mkdir()
    out["folder"] = folder
    out["missing"] = world / "cap_missing.h5"
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return _build(tmp_path_factory.mktemp("hostile"))


def _build(d: Path) -> dict:
    base, touched = _tiny_scene()
    scene = d / "tiny.toml"
    scene.write_text(base.to_toml())
    good = write_capture(d / "good.h5", _capture(base, 3))
    touch = write_capture(d / "touch.h5", _capture(touched, 2, seed=1))
    other = base.replace(sensor=dataclasses.replace(base.sensor, n_bins=8))
    other_cap = write_capture(d / "other_shape.h5", _capture(other, 2))
    scenes = {}
    for name, data in _scene_variants(base.to_toml()).items():
        p = d / f"scene_{name}.toml"
        p.write_bytes(data)
        scenes[name] = p
    scenes["folder"] = d
    scenes["missing"] = d / "nope.toml"
    caps = _capture_variants(d, good)
    notes = d / "notes.txt"
    notes.write_text("my notes: do not lose\n")
    existing_json = d / "existing.json"
    existing_json.write_text('{"keep": true}\n')
    return {"d": d, "scene": scene, "good": good, "touch": touch, "other": other_cap, "scenes": scenes,
            "caps": caps, "notes": notes, "json": existing_json, "base_scene": base}


# ---- the table ----------------------------------------------------------------------------------


@dataclasses.dataclass
class Case:
    id: str
    argv: object  # (world, out_dir) -> list[str]
    #: "error", or the name of the warning expected on stderr with exit 0.
    expect: str = "error"
    #: extra check (world, out_dir, stdout, stderr) -> None
    check: object = None
    #: files that must be byte for byte the same after the command
    keep: object = None


def _hash(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "missing"


SCENE_COMMANDS = {
    "scene": lambda s, o: ["scene", s],
    "simulate": lambda s, o: ["simulate", s, "--frames", "2", "--out", f"{o}/x.h5"],
    "mc": lambda s, o: ["mc", s, "--photons", "10", "--out", f"{o}/x.h5"],
    "prune": lambda s, o: ["prune", s],
    "acquire": lambda s, o: ["acquire", s, "--emulate", "--frames", "1", "--quiet", "--out", f"{o}/x.h5"],
}
# The scene variants each command is tried with (the scene loader is shared: all for `scene`,
# a spread for the rest).
SCENE_SPREAD = ("non_utf8", "binary_junk", "empty", "invalid_toml", "no_waveguide", "n_bins_huge", "zones_huge",
                "n_bins_float", "n1_nan", "thickness_zero", "no_sensors", "sensor_off_edge", "sensors_65",
                "touch_outside", "touch_radius_zero", "touch_stick_billions", "iterations_huge", "folder", "missing",
                "n1_huge", "bin_width_tiny", "sensor_model_missing")

CAPTURE_COMMANDS = {
    "plot": lambda w, c, o: ["plot", c, "--out", f"{o}/plots"],
    "calibrate": lambda w, c, o: ["calibrate", c, "--out", f"{o}/cal.json"],
    "process": lambda w, c, o: ["process", c, "--baseline", str(w["good"]), "--method", "baseline",
                                "--out", f"{o}/maps.h5"],
    "detect": lambda w, c, o: ["detect", str(w["touch"]), "--baseline", c, "--method", "baseline",
                               "--json", f"{o}/d.json"],
    "replay": lambda w, c, o: ["replay", c, "--quiet"],
    "predict": lambda w, c, o: ["predict", str(w["d"] / "run_mlp_missing"), c, "--out", f"{o}/p.csv"],
}
CAPTURE_SPREAD = ("text_file", "empty_file", "truncated", "foreign", "version_string", "version_float",
                  "no_scene", "histograms_strings", "zero_frames", "all_nan", "all_zero", "all_negative",
                  "one_nan_bin_per_frame", "committed_negative", "folder", "missing")


def _cases() -> list[Case]:
    cases: list[Case] = []
    names = list(_scene_variants(_tiny_scene()[0].to_toml())) + ["folder", "missing"]
    # Scenes: every variant through `scene`, a spread through the other commands that read one.
    for name in names:
        cases.append(Case(f"scene/{name}", lambda w, o, n=name: SCENE_COMMANDS["scene"](str(w["scenes"][n]), o)))
    for cmd, fn in SCENE_COMMANDS.items():
        if cmd == "scene":
            continue
        for name in SCENE_SPREAD:
            cases.append(Case(f"{cmd}/scene_{name}", lambda w, o, n=name, fn=fn: fn(str(w["scenes"][n]), o)))
    for name in SCENE_SPREAD[:8]:
        cases.append(Case(f"demo/scene_{name}", lambda w, o, n=name: ["demo", "--scene", str(w["scenes"][n]),
                                                                      "--out", f"{o}/demo"]))
    # Captures: every variant through `plot` (the reader is shared), a spread through the rest.
    capnames = [
        "text_file", "empty_file", "truncated", "hdf5_header_only", "foreign", "format_wrong", "format_number",
        "version_2", "version_string", "version_float", "version_array", "no_version", "no_scene",
        "scene_not_json", "scene_number", "scene_list", "scene_invalid", "scene_huge_number", "no_histograms",
        "no_timestamps", "histograms_group", "histograms_strings", "timestamps_strings", "histograms_wrong_shape",
        "histograms_1d", "timestamps_2d", "fewer_histograms", "zero_frames", "committed_zero", "committed_negative",
        "committed_string", "all_nan", "all_zero", "all_negative", "all_inf", "one_nan_bin_per_frame",
        "timestamps_nan", "truth_not_json", "force_short", "force_strings", "folder", "missing",
    ]
    for name in capnames:
        cases.append(Case(f"plot/capture_{name}", lambda w, o, n=name: CAPTURE_COMMANDS["plot"](w, str(w["caps"][n]), o)))
    for cmd, fn in CAPTURE_COMMANDS.items():
        if cmd in ("plot", "predict"):
            continue
        for name in CAPTURE_SPREAD:
            cases.append(Case(f"{cmd}/capture_{name}", lambda w, o, n=name, fn=fn: fn(w, str(w["caps"][n]), o)))
    cases.append(Case("plot/baseline_other_shape", lambda w, o: ["plot", str(w["good"]), "--baseline",
                                                                 str(w["other"]), "--out", f"{o}/p"]))
    cases.append(Case("detect/other_shape", lambda w, o: ["detect", str(w["other"]), "--baseline", str(w["good"]),
                                                          "--method", "baseline", "--json", f"{o}/d.json"]))
    cases.append(Case("calibrate/scene_other_shape", lambda w, o: ["calibrate", str(w["other"]), "--scene",
                                                                   str(w["scene"]), "--out", f"{o}/c.json"]))
    # Numbers: out of range, NaN, infinite, not a number.
    S = lambda w: str(w["scene"])  # noqa: E731
    G = lambda w: str(w["good"])  # noqa: E731
    T = lambda w: str(w["touch"])  # noqa: E731
    numeric = [
        ("simulate", "--frames", ["0", "-5", "x", "1e3", "1000000000"]),
        ("simulate", "--seed", ["-1", "99999999999", "1.5"]),
        ("simulate", "--quadrature", ["0", "-2", "100000"]),
        ("demo", "--frames", ["0", "-1"]),
        ("mc", "--photons", ["0", "-10", "1e20"]),
        ("mc", "--frames", ["0"]),
        ("mc", "--g", ["1.0", "-1", "nan", "inf"]),
        ("mc", "--batch", ["0"]),
        ("prune", "--frames", ["0"]),
        ("prune", "--noise-floor", ["-1", "nan"]),
        ("prune", "--quadrature", ["0"]),
        ("detect", "--resolution-mm", ["0", "-2.5", "nan", "inf", "1e-9"]),
        ("detect", "--relative", ["0", "-0.3", "1.5", "nan"]),
        ("detect", "--n-sigma", ["-1", "nan", "inf"]),
        ("process", "--resolution-mm", ["0", "nan"]),
        ("calibrate", "--walkers", ["0", "1"]),
        ("calibrate", "--max-steps", ["0", "-1"]),
        ("calibrate", "--mcmc", ["hmc", "1"]),
        ("calibrate", "--chains", ["0", "-1", "4"]),  # 4: only for --mcmc nuts
        ("calibrate", "--warmup", ["0", "5", "x"]),
        ("calibrate", "--draws", ["0", "-3"]),
        ("acquire", "--frames", ["0", "-1"]),
        ("acquire", "--duration", ["0", "-1", "nan", "inf"]),
        ("acquire", "--bus", ["-1", "300"]),
        ("acquire", "--bus-speed", ["0", "-400000"]),
        ("acquire", "--period-ms", ["0", "-33"]),
        ("acquire", "--faults", ["nack=2", "nack=x", "gremlins=0.1", "nack"]),
        ("replay", "--speed", ["0", "-1", "fast", "nan"]),
        ("predict", "--baseline-frames", ["-1"]),
        ("mc slab", "--n", ["0.5", "nan", "inf"]),
        ("mc slab", "--thickness-m", ["0", "-0.005", "inf"]),
        ("mc slab", "--mu-s-per-m", ["-1", "nan", "1e30"]),
        ("mc slab", "--mu-a-per-m", ["-2", "inf"]),
        ("mc slab", "--g", ["1", "-1", "nan"]),
        ("mc slab", "--photons", ["0"]),
    ]
    base_argv = {
        "simulate": lambda w, o: ["simulate", S(w), "--out", f"{o}/x.h5"],
        "demo": lambda w, o: ["demo", "--out", f"{o}/demo"],
        "mc": lambda w, o: ["mc", S(w), "--out", f"{o}/x.h5"],
        "prune": lambda w, o: ["prune", S(w)],
        "detect": lambda w, o: ["detect", T(w), "--baseline", G(w), "--json", f"{o}/d.json"],
        "process": lambda w, o: ["process", T(w), "--baseline", G(w), "--out", f"{o}/m.h5"],
        "calibrate": lambda w, o: ["calibrate", G(w), "--out", f"{o}/c.json"],
        "acquire": lambda w, o: ["acquire", S(w), "--emulate", "--quiet", "--out", f"{o}/x.h5"],
        "replay": lambda w, o: ["replay", G(w), "--quiet"],
        "predict": lambda w, o: ["predict", str(w["d"]), G(w), "--out", f"{o}/p.csv"],
        "mc slab": lambda w, o: ["mc", "slab", "--photons", "10", "--json", f"{o}/slab.json"],
    }
    for cmd, flag, values in numeric:
        for v in values:
            def argv(w, o, cmd=cmd, flag=flag, v=v):
                a = base_argv[cmd](w, o) + [f"{flag}={v}"]
                if cmd == "acquire" and flag not in ("--frames", "--duration"):
                    a += ["--frames", "1"]
                return a
            cases.append(Case(f"{cmd.replace(' ', '_')}/{flag}={v}", argv))
    # Outputs: existing files are refused without --overwrite (and kept), inputs never written over.
    notes = lambda w: str(w["notes"])  # noqa: E731
    keep_notes = lambda w: [w["notes"]]  # noqa: E731
    writers = {
        "simulate": lambda w, out: ["simulate", S(w), "--frames", "1", "--out", out],
        "mc": lambda w, out: ["mc", S(w), "--photons", "10", "--out", out],
        "acquire": lambda w, out: ["acquire", S(w), "--emulate", "--frames", "1", "--quiet", "--out", out],
        "baseline": lambda w, out: ["baseline", S(w), "--emulate", "--frames", "1", "--quiet", "--out", out],
        "replay": lambda w, out: ["replay", G(w), "--quiet", "--out", out],
        "process": lambda w, out: ["process", T(w), "--baseline", G(w), "--out", out],
        "detect": lambda w, out: ["detect", T(w), "--baseline", G(w), "--json", out],
        "calibrate": lambda w, out: ["calibrate", G(w), "--out", out],
        "prune": lambda w, out: ["prune", S(w), "--out", out],
        "predict": lambda w, out: ["predict", str(w["d"]), G(w), "--out", out],
    }
    for cmd, fn in writers.items():
        cases.append(Case(f"{cmd}/out_existing_notes", lambda w, o, fn=fn: fn(w, notes(w)), keep=keep_notes))
        cases.append(Case(f"{cmd}/out_existing_json", lambda w, o, fn=fn: fn(w, str(w["json"])),
                          keep=lambda w: [w["json"]]))
        cases.append(Case(f"{cmd}/out_is_folder", lambda w, o, fn=fn: fn(w, str(w["d"]))))
        cases.append(Case(f"{cmd}/out_under_a_file", lambda w, o, fn=fn: fn(w, f"{notes(w)}/x.out"), keep=keep_notes))
        cases.append(Case(f"{cmd}/out_empty", lambda w, o, fn=fn: fn(w, "")))
    unwritable = {  # /proc takes no new files, even from root: refused before any work
        "simulate": lambda w: ["simulate", S(w), "--frames", "1", "--out", "/proc/tofjax-x.h5"],
        "calibrate": lambda w: ["calibrate", G(w), "--out", "/proc/tofjax-cal.json"],
        "detect": lambda w: ["detect", T(w), "--baseline", G(w), "--json", "/proc/tofjax-d.json"],
        "process": lambda w: ["process", T(w), "--baseline", G(w), "--out", "/proc/tofjax-m.h5"],
        "plot": lambda w: ["plot", G(w), "--out", "/proc/tofjax-plots"],
        "acquire": lambda w: ["acquire", S(w), "--emulate", "--frames", "1", "--out", "/proc/tofjax-x.h5"],
    }
    if Path("/proc/self").exists():
        for name, fn in unwritable.items():
            cases.append(Case(f"{name}/out_unwritable", lambda w, o, fn=fn: fn(w)))
    own_input = {
        "simulate": lambda w: ["simulate", S(w), "--frames", "1", "--out", S(w), "--overwrite"],
        "mc": lambda w: ["mc", S(w), "--out", S(w), "--overwrite"],
        "acquire": lambda w: ["acquire", S(w), "--emulate", "--frames", "1", "--out", S(w), "--overwrite"],
        "replay": lambda w: ["replay", G(w), "--out", G(w), "--overwrite"],
        "process_touch": lambda w: ["process", T(w), "--baseline", G(w), "--out", T(w), "--overwrite"],
        "process_baseline": lambda w: ["process", T(w), "--baseline", G(w), "--out", G(w), "--overwrite"],
        "detect": lambda w: ["detect", T(w), "--baseline", G(w), "--json", G(w), "--overwrite"],
        "calibrate": lambda w: ["calibrate", G(w), "--out", G(w), "--overwrite"],
        "calibrate_via_dotdot": lambda w: ["calibrate", G(w), "--out", f"{w['d']}/../{w['d'].name}/good.h5",
                                           "--overwrite"],
        "prune": lambda w: ["prune", S(w), "--out", S(w), "--overwrite"],
        "predict": lambda w: ["predict", str(w["d"]), G(w), "--out", G(w), "--overwrite"],
    }
    for name, fn in own_input.items():
        cases.append(Case(f"own_input/{name}", lambda w, o, fn=fn: fn(w),
                          keep=lambda w: [w["scene"], w["good"], w["touch"]]))
    folder_outputs = {
        "plot": lambda w, out: ["plot", G(w), "--out", out],
        "demo": lambda w, out: ["demo", "--frames", "2", "--out", out],
        "force-data": lambda w, out: ["force-data", "--out", out],
        "calibrate_plots": lambda w, out: ["calibrate", G(w), "--out", f"{w['d']}/new.json", "--plots", out],
    }
    for name, fn in folder_outputs.items():
        cases.append(Case(f"{name}/folder_not_empty", lambda w, o, fn=fn: fn(w, str(w["d"])),
                          keep=lambda w: [w["good"], w["notes"]]))
        cases.append(Case(f"{name}/folder_is_a_file", lambda w, o, fn=fn: fn(w, notes(w)), keep=keep_notes))
    # Config, rig, protocol, run folders.
    d = lambda w: w["d"]  # noqa: E731

    def cfg(name, text):
        def argv(w, o):
            p = d(w) / f"{name}.toml"
            p.write_text(text)
            return ["train", str(p), "--runs", f"{o}/runs", "--quiet"]
        return argv

    for name, text in {
        "train_gb_typo": 'name = "x"\n[model]\nkind = "gb"\n[model.gb]\niteratons = 5\n',
        "train_svr_typo": 'name = "x"\n[model]\nkind = "svr"\n[model.svr]\nC = 5\n',
        "train_svr_table_for_gb": 'name = "x"\n[model]\nkind = "gb"\n[model.svr]\nc = 5.0\n',
        "train_kind_unknown": 'name = "x"\n[model]\nkind = "oracle"\n',
        "train_dropout_1": 'name = "x"\n[model]\ndropout = 1.0\n',
        "train_unknown_table": 'name = "x"\n[modle]\nkind = "mlp"\n',
        "train_not_toml": "name = \n",
        "train_feature_source_typo": 'name = "x"\n[features]\nsource = "maps"\n',
        "train_inversion_option_for_counts": 'name = "x"\n[features]\ncontacts = 2\n',
        "train_forest_too_deep": 'name = "x"\n[forest]\nmax_depth = 20\n',
        "train_position_not_a_pair": 'name = "x"\n[data.protocol]\npositions_m = [0.1, 0.0]\n',
        "train_position_off_the_skin": 'name = "x"\n[data.protocol]\nunseen_positions_m = [[0.5, 0.0]]\n',
        "train_two_contacts_one_position": 'name = "x"\n[data.protocol]\ntwo_contacts_m = [[[0.1, 0.0]]]\n',
    }.items():
        cases.append(Case(f"train/{name}", cfg(name, text)))
    cases.append(Case("train/missing_config", lambda w, o: ["train", f"{d(w)}/none.toml", "--runs", f"{o}/r"]))
    cases.append(Case("train/non_utf8", lambda w, o: ["train", str(w["scenes"]["non_utf8"]), "--runs", f"{o}/r"]))
    for name, text in {"protocol_unknown_key": "gremlins = 1\n", "protocol_not_toml": "[[[\n",
                       "protocol_wrong_type": 'velocities_mm_s = "fast"\n'}.items():
        def argv(w, o, name=name, text=text):
            p = d(w) / f"{name}.toml"
            p.write_text(text)
            return ["force-data", "--protocol", str(p), "--out", f"{o}/fd"]
        cases.append(Case(f"force-data/{name}", argv))
    for name, text in {
        "rig_unknown_key": 'name = "r"\nscene = "optoskin"\ncolour = 1\n[[sensors]]\nname = "S0"\n',
        "rig_scene_missing": 'name = "r"\nscene = "no-such-scene"\n[[sensors]]\nname = "S0"\n',
        "rig_not_toml": "name = [\n",
        "rig_bad_select": 'name = "r"\nscene = "optoskin"\nselect = "magic"\n[[sensors]]\nname = "S0"\n',
        "rig_no_sensors": 'name = "r"\nscene = "optoskin"\nbus = 1\n',
        "rig_sensor_count": 'name = "r"\nscene = "optoskin"\n[[sensors]]\nname = "S0"\n',
        # a multiplexer address no I2C bus can carry (accepted before)
        "rig_mux_address_out_of_range": 'name = "r"\nscene = "optoskin"\nselect = "mux"\nmux_address = 4096\n'
        + "".join(f'[[sensors]]\nname = "S{i}"\nmux_channel = {i}\n' for i in range(6)),
    }.items():
        def argv(w, o, name=name, text=text):
            p = d(w) / f"{name}.toml"
            p.write_text(text)
            return ["acquire", str(p), "--emulate", "--frames", "1", "--quiet", "--out", f"{o}/x.h5"]
        cases.append(Case(f"acquire/{name}", argv))
    cases.append(Case("acquire/no_i2c_device", lambda w, o: ["acquire", S(w), "--frames", "1", "--bus", "250",
                                                             "--quiet", "--out", f"{o}/x.h5"]))
    cases.append(Case("acquire/faults_without_emulate", lambda w, o: ["acquire", S(w), "--frames", "1", "--faults",
                                                                      "nack=0.1", "--out", f"{o}/x.h5"]))
    cases.append(Case("acquire/image_missing", lambda w, o: ["acquire", S(w), "--emulate", "--frames", "1",
                                                             "--image", f"{d(w)}/none.hex", "--out", f"{o}/x.h5"]))
    cases.append(Case("acquire/image_garbage", lambda w, o: ["acquire", S(w), "--emulate", "--frames", "1",
                                                             "--image", notes(w), "--out", f"{o}/x.h5"]))
    cases.append(Case("calibrate/config_missing", lambda w, o: ["calibrate", G(w), "--config", f"{d(w)}/none.toml",
                                                                "--out", f"{o}/c.json"]))
    cases.append(Case("calibrate/config_non_utf8", lambda w, o: ["calibrate", G(w), "--config",
                                                                 str(w["scenes"]["non_utf8"]), "--out", f"{o}/c.json"]))
    for name, text in {"precision_target_nan": "precision_target_mu_t = nan\n",
                       "precision_target_zero": "precision_target_n1 = 0\n"}.items():
        def fit_cfg(w, o, name=name, text=text):
            p = d(w) / f"{name}.toml"
            p.write_text(text)
            return ["calibrate", G(w), "--config", str(p), "--out", f"{o}/c.json"]
        cases.append(Case(f"calibrate/{name}", fit_cfg))
    cases.append(Case("calibrate/scene_bad", lambda w, o: ["calibrate", G(w), "--scene", str(w["scenes"]["n1_nan"]),
                                                           "--out", f"{o}/c.json"]))
    cases.append(Case("detect/calibration_missing", lambda w, o: ["detect", T(w), "--baseline", G(w), "--calibration",
                                                                  f"{d(w)}/none.json", "--json", f"{o}/d.json"]))
    cases.append(Case("detect/calibration_not_json", lambda w, o: ["detect", T(w), "--baseline", G(w),
                                                                   "--calibration", notes(w), "--json", f"{o}/d.json"]))
    # Sensor models (tofjax sensor fit) where a command takes one.
    for cmd in ("detect", "process", "calibrate"):
        def sensor_argv(w, o, cmd=cmd, which="missing"):
            path = {"missing": f"{d(w)}/none.json", "not_json": notes(w), "not_a_model": str(w["scenes"]["non_utf8"])}
            head = {"detect": ["detect", T(w), "--baseline", G(w), "--json", f"{o}/d.json"],
                    "process": ["process", T(w), "--baseline", G(w), "--out", f"{o}/m.h5"],
                    "calibrate": ["calibrate", G(w), "--out", f"{o}/c.json"]}[cmd]
            return head + ["--sensor", path[which]]
        for which in ("missing", "not_json", "not_a_model"):
            cases.append(Case(f"{cmd}/sensor_{which}", lambda w, o, f=sensor_argv, which=which: f(w, o, which=which)))
    cases.append(Case("detect/dynamic_with_model", lambda w, o: ["detect", T(w), "--baseline", G(w), "--method", "model",
                                                                 "--dynamic-baseline", "--json", f"{o}/d.json"]))

    def run(name, files: dict[str, bytes]):
        def argv(w, o):
            r = d(w) / f"run_{name}"
            r.mkdir(exist_ok=True)
            for k, v in files.items():
                (r / k).write_bytes(v)
            return ["predict", str(r), G(w), "--out", f"{o}/p.csv"]
        return argv

    header = {"format": "tofjax.force-model", "kind": "gb"}
    evil = pickle.dumps(_Evil())
    for name, files in {
        "mlp_missing": {},
        "model_json_not_json": {"model.json": b"{oops"},
        "model_json_list": {"model.json": b"[1, 2]"},
        "model_json_wrong_format": {"model.json": b'{"format": "other"}'},
        "model_json_missing_keys": {"model.json": json.dumps({"format": _model_format()}).encode()},
        "pickle_only": {"model.json": json.dumps({**header, "format": _model_format()}).encode(), "model.pkl": evil},
        "skops_garbage": {"model.json": json.dumps({**header, "format": _model_format()}).encode(),
                          "model.skops": b"PK\x03\x04garbage"},
    }.items():
        cases.append(Case(f"predict/run_{name}", run(name, files),
                          check=lambda w, o, *_: _no_evil(w)))
    cases.append(Case("predict/run_is_a_file", lambda w, o: ["predict", notes(w), G(w), "--out", f"{o}/p.csv"]))
    # Arguments argparse itself refuses (one line, not usage + error).
    for name, argv in {
        "no_command": [],
        "unknown_command": ["frobnicate"],
        "simulate_no_out": ["simulate", "optoskin"],
        "detect_no_baseline": ["detect", "x.h5", "--json", "y.json"],
        "method_unknown": ["detect", "x.h5", "--baseline", "y.h5", "--method", "magic", "--json", "j"],
        "dtype_unknown": ["simulate", "optoskin", "--dtype", "float16", "--out", "x.h5"],
        "acquire_frames_and_duration": ["acquire", "optoskin", "--frames", "1", "--duration", "1", "--out", "x.h5"],
        "unknown_flag": ["scene", "optoskin", "--colour"],
    }.items():
        cases.append(Case(f"argparse/{name}", lambda w, o, argv=argv: list(argv)))
    # Partly usable inputs: exit 0, a named warning, and the result says what was left out.
    cases.append(Case("detect/some_bad_frames", lambda w, o: ["detect", str(w["mixed"]), "--baseline", G(w),
                                                              "--method", "baseline", "--json", f"{o}/d.json"],
                      expect="BadFramesWarning", check=_check_mixed_json))
    cases.append(Case("replay/some_bad_frames", lambda w, o: ["replay", str(w["mixed"]), "--quiet"],
                      expect="BadFramesWarning"))
    # tofjax bench tradeoff (issue 14): every refusal comes before the Monte Carlo runs.
    bench = lambda w, o: ["bench", "tradeoff", "--photons", "10", "--repeats", "1", "--json", f"{o}/b.json"]  # noqa: E731
    for flag, values in {"--photons": ["0", "1", "-5", "1e20", "x"], "--repeats": ["0", "-1"], "--nee-points": ["0", "5000"],
                         "--elevations": ["0", "nan"], "--g": ["1", "-1", "nan"], "--seed": ["-1"], "--batch": ["0"],
                         "--frontier": ["4:4:1", "4:x:1:float32", "4:4:1:float16", "0:4:1:float64"]}.items():
        for v in values:
            cases.append(Case(f"bench_tradeoff/{flag}={v}", lambda w, o, flag=flag, v=v: bench(w, o) + [f"{flag}={v}"]))
    for name, extra in {"touch_scene_without_contacts": ["--touch-scene", "optoskin"],
                        "touch_scene_missing": ["--touch-scene", "no-such-scene"],
                        "scene_missing": ["--scene", "no-such-scene"],
                        "scene_broken": ["--scene", "BROKEN"]}.items():
        cases.append(Case(f"bench_tradeoff/{name}", lambda w, o, extra=extra: [
            x if x != "BROKEN" else str(w["scenes"]["invalid_toml"]) for x in bench(w, o) + extra]))
    cases.append(Case("bench_tradeoff/no_json", lambda w, o: ["bench", "tradeoff", "--photons", "10"]))
    cases.append(Case("bench_tradeoff/json_existing", lambda w, o: ["bench", "tradeoff", "--photons", "10", "--json", notes(w)],
                      keep=keep_notes))
    cases.append(Case("bench_tradeoff/json_is_scene", lambda w, o: ["bench", "tradeoff", "--scene", S(w), "--json", S(w),
                                                                    "--overwrite"], keep=lambda w: [w["scene"]]))
    cases.append(Case("argparse/bench_without_what", lambda w, o: ["bench"]))
    cases.append(Case("argparse/bench_unknown", lambda w, o: ["bench", "speed"]))
    cases += _audit_cases()
    return cases


#: A free-space scene (a TMF8820 facing a flat target; docs/sensor.md), no sensor model.
FREE_SPACE = """name = "air"
[sensor]
bin_width_s = 94e-12
n_bins = 128
zones = 9
grid = [3, 3]
fov_deg = 45.0

[[sensors]]
position_m = [0.0, 0.0]
direction_deg = 0.0

[target]
distance_m = 0.2
reflectance = 0.8
"""


def _free_space(w) -> tuple[str, str]:
    """The free-space scene file and a capture of it (NumPy counts), made once per world."""
    if "free_space" not in w:
        from tofjax.scene import load_scene

        p = w["d"] / "air.toml"
        p.write_text(FREE_SPACE)
        w["free_space"] = (str(p), str(write_capture(w["d"] / "air.h5", _capture(load_scene(p), 3))))
    return w["free_space"]


def _fifo(w) -> str:
    p = w["d"] / "pipe.h5"
    if not p.exists():
        os.mkfifo(p)
    return str(p)


def _calibration(w, **edits) -> str:
    """A calibration JSON of the world's tiny scene that every reader accepts, then ``edits`` to its
    parameters' values (written without fitting anything)."""
    from tofjax.fit._result import scene_fingerprint
    from tofjax.scene import load_scene

    scene = load_scene(w["scene"])
    S, Z, _ = scene.shape
    values = {"n1": 1.4, "mu_s_per_m": 0.6, "mu_a_per_m": 0.14, "gain": [150.0] * S, "emission_time_s": 1.45e-9,
              "pulse_sigma_s": 6e-11, "pulse_tail_s": 1.5e-10, "crosstalk_counts": [[3000.0] * Z] * S}
    values.update(edits)
    data = {"converged": True, "result": "successful", "scene_fingerprint": scene_fingerprint(scene), "optics": "default",
            "parameters": {k: {"value": v, "stderr": 0.0} for k, v in values.items()}}
    p = w["d"] / f"cal_{abs(hash(json.dumps(edits, sort_keys=True)))}.json"
    p.write_text(json.dumps(data))
    return str(p)


def _audit_cases() -> list:
    """The bad inputs an audit of every command found (2026-11-29): tracebacks, hangs, a device replaced,
    and exit 0 with a wrong answer. Each now ends in one line."""
    G = lambda w: str(w["good"])  # noqa: E731
    T = lambda w: str(w["touch"])  # noqa: E731
    cases = []
    # free-space scenes and captures where a command needs a waveguide (AttributeError before)
    free = {
        "prune": lambda w, o: ["prune", _free_space(w)[0]],
        "mc": lambda w, o: ["mc", _free_space(w)[0], "--photons", "10", "--out", f"{o}/m.h5"],
        "demo": lambda w, o: ["demo", "--scene", _free_space(w)[0], "--frames", "1", "--out", f"{o}/demo"],
        "bench_tradeoff": lambda w, o: ["bench", "tradeoff", "--scene", _free_space(w)[0], "--photons", "10",
                                        "--json", f"{o}/b.json"],
        "calibrate": lambda w, o: ["calibrate", _free_space(w)[1], "--out", f"{o}/c.json"],
        "detect": lambda w, o: ["detect", _free_space(w)[1], "--baseline", _free_space(w)[1], "--json", f"{o}/d.json"],
        "process": lambda w, o: ["process", _free_space(w)[1], "--baseline", _free_space(w)[1], "--out", f"{o}/p.h5"],
        "sensitivity": lambda w, o: ["sensitivity", _free_space(w)[0], "--baseline", _free_space(w)[1], "--out", f"{o}/s"],
    }
    for name, argv in free.items():
        cases.append(Case(f"free_space/{name}", argv))
    # --overwrite never replaces a named pipe (it hung) or a device (/dev/full was replaced)
    cases.append(Case("output/fifo_capture", lambda w, o: ["simulate", str(w["scene"]), "--frames", "1", "--out", _fifo(w),
                                                           "--overwrite"]))
    cases.append(Case("output/fifo_json", lambda w, o: ["calibrate", G(w), "--out", _fifo(w), "--overwrite"]))
    cases.append(Case("output/dev_null_capture", lambda w, o: ["simulate", str(w["scene"]), "--frames", "1", "--out",
                                                               "/dev/null", "--overwrite"]))
    # calibrations whose values no reader can use (0 touches and exit 0, or tracebacks, before)
    for name, edits in {"n1_huge": {"n1": 1e300}, "mu_a_huge": {"mu_a_per_m": 1e300}, "gain_two_values_one_sensor": {"gain": [150.0, 150.0]},
                        "gain_nested": {"gain": [[150.0]]}, "n1_dict": {"n1": {"a": 1}},
                        "crosstalk_ragged": {"crosstalk_counts": [[3000.0, 3000.0], [3000.0]]}}.items():
        cases.append(Case(f"detect/calibration_{name}", lambda w, o, e=edits: [
            "detect", T(w), "--baseline", G(w), "--calibration", _calibration(w, **e), "--json", f"{o}/d.json"]))
    # options that did nothing without the sampler they belong to
    cases.append(Case("calibrate/max_steps_without_mcmc", lambda w, o: ["calibrate", G(w), "--max-steps", "5", "--out",
                                                                        f"{o}/c.json"]))
    cases.append(Case("calibrate/walkers_with_nuts", lambda w, o: ["calibrate", G(w), "--mcmc", "nuts", "--walkers", "8",
                                                                   "--out", f"{o}/c.json"]))

    def twice(w, o):
        p = w["d"] / "free_twice.toml"
        p.write_text('free = ["n1", "n1", "mu_s_per_m"]\n')
        return ["calibrate", G(w), "--config", str(p), "--out", f"{o}/c.json"]
    cases.append(Case("calibrate/free_listed_twice", twice))

    # replay: a recording's gap (or a tiny speed) read as a hang; backwards timestamps
    def replay(w, o, times, speed):
        from tofjax.scene import load_scene

        cap = _capture(load_scene(w["scene"]), len(times))
        cap = dataclasses.replace(cap, timestamps=np.asarray(times, float))
        p = write_capture(o / "rec.h5", cap, overwrite=True)
        return ["replay", str(p), "--speed", speed, "--quiet"]
    cases.append(Case("replay/gap_of_days", lambda w, o: replay(w, o, [0.0, 1e7], "recorded")))
    cases.append(Case("replay/speed_tiny", lambda w, o: replay(w, o, [0.0, 0.1], "1e-300")))
    cases.append(Case("replay/backwards", lambda w, o: replay(w, o, [0.0, 10.0, 0.0], "recorded")))
    # a baseline no sensor can record: counts above the limit, or every bin saturated (0 touches, exit 0)
    def baseline(w, o, value):
        from tofjax.scene import load_scene

        cap = _capture(load_scene(w["scene"]), 2)
        cap.histograms[:] = value
        return ["detect", T(w), "--baseline", str(write_capture(o / "b.h5", cap, overwrite=True)), "--json", f"{o}/d.json"]
    cases.append(Case("detect/baseline_above_the_limit", lambda w, o: baseline(w, o, 3e38)))
    cases.append(Case("detect/baseline_saturated", lambda w, o: baseline(w, o, 2.0**24 - 1)))
    # a map too fine for memory (killed for memory at 0.05 mm before)
    cases.append(Case("process/resolution_too_fine", lambda w, o: ["process", T(w), "--baseline", G(w), "--out",
                                                                   f"{o}/p.h5", "--resolution-mm", "0.05"]))

    # configs that asked for more memory than there is (SIGABRT / MemoryError before)
    def study(w, o):
        p = w["d"] / "study_huge.toml"
        p.write_text(f'scene = "{w["scene"]}"\nframes = 100000000\n')
        return ["study", str(p), "--out", f"{o}/st"]
    cases.append(Case("study/frames_huge", study))

    def protocol(w, o):
        p = w["d"] / "protocol_huge.toml"
        p.write_text("hold_s = 1e9\n")
        return ["force-data", "--protocol", str(p), "--out", f"{o}/f"]
    cases.append(Case("force_data/hold_huge", protocol))
    return cases


def _model_format() -> str:
    from tofjax.force.train import MODEL_FORMAT

    return MODEL_FORMAT


class _Evil:
    """Unpickling this writes a file: a run folder must never be unpickled."""

    def __reduce__(self):
        return (open, (os.path.join(os.environ.get("TOFJAX_EVIL_DIR", "/tmp"), "pwned-by-pickle"), "w"))


def _no_evil(w):
    assert not (Path(os.environ["TOFJAX_EVIL_DIR"]) / "pwned-by-pickle").exists(), "a pickle was loaded"


def _check_mixed_json(w, o, out, err):
    data = json.loads(Path(o, "d.json").read_text())
    flags = {f["index"]: (f["ok"], f.get("reason", "")) for f in data["frames"]}
    assert sorted(flags) == [0, 1, 2, 3, 4]
    assert [i for i, (ok, _) in flags.items() if not ok] == [1, 2, 3]
    assert "non-finite" in flags[1][1] and "negative" in flags[2][1] and "zero" in flags[3][1]


CASES = _cases()


def _add_mixed(world):
    if "mixed" not in world:
        base = world["base_scene"]
        cap = _capture(base, 5, seed=3)
        cap.histograms[1, 0, 1, 3] = np.nan
        cap.histograms[2, 0, 0, 0] = -4.0
        cap.histograms[3] = 0.0
        world["mixed"] = write_capture(world["d"] / "mixed.h5", cap)
    return world


def run_case(case: Case, world: dict, out_dir: Path):
    """Run one case; returns (outcome, detail): outcome in clear, warning, traceback, silent, unclear."""
    import contextlib
    import io
    import traceback

    _add_mixed(world)
    os.environ.setdefault("TOFJAX_EVIL_DIR", str(world["d"]))
    out_dir.mkdir(parents=True, exist_ok=True)
    argv = case.argv(world, out_dir)
    kept = {p: _hash(p) for p in (case.keep(world) if case.keep else [])}
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as e:
            rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
        except BaseException:  # noqa: BLE001 -- a traceback is what we count
            return "traceback", traceback.format_exc()
    out, err = out.getvalue(), err.getvalue()
    changed = [str(p) for p, h in kept.items() if _hash(p) != h]
    if changed:
        return "silent", f"changed {changed}"
    if case.check is not None:
        try:
            case.check(world, out_dir, out, err)
        except AssertionError as e:
            return "silent", f"check failed: {e}"
    lines = [l for l in err.splitlines() if l.strip()]
    if "Traceback" in err:
        return "traceback", err
    if case.expect == "error":
        if rc == 0:
            return "silent", f"exit 0; stdout {out[-300:]!r}"
        errors = [l for l in lines if ": error: " in l]
        others = [l for l in lines if ": error: " not in l and not l.startswith("tofjax")]
        if len(errors) != 1 or others:
            return "unclear", err
        return "clear", errors[0]
    if rc != 0 or not any(case.expect in l for l in lines):
        return "unclear", f"exit {rc}: {err}"
    return "warning", err


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_hostile_input(case, world, tmp_path, monkeypatch):
    monkeypatch.setenv("TOFJAX_EVIL_DIR", str(world["d"]))
    outcome, detail = run_case(case, world, tmp_path)
    want = "clear" if case.expect == "error" else "warning"
    assert outcome == want, f"{case.id}: {outcome}: {detail}"


def test_table_is_big_enough():
    assert len(CASES) >= 250
    assert len({c.id for c in CASES}) == len(CASES)


# ---- the library, not only the command line ---------------------------------------------------------


def test_params_refuse_what_the_model_cannot_evaluate():
    from tofjax.model import Params
    from tofjax.model.params import ParamsError
    from tofjax.scene import load_scene

    p = Params.from_scene(load_scene("touch-single"))
    for field, value in [("touch_radius_m", 0.0), ("touch_radius_m", -0.01), ("n1", 1.0), ("n1", np.nan),
                         ("mu_s_per_m", -1.0), ("gain", np.inf), ("end_reflectance", 1.5),
                         ("pulse_sigma_s", 0.0), ("touch_strength", -1.0), ("near_field_m", 0.0)]:
        with pytest.raises(ParamsError, match=field):
            p.replace(**{field: np.full(np.shape(getattr(p, field)), value)})
    with pytest.raises(ParamsError, match="touch_xy_m"):
        p.replace(touch_xy_m=np.zeros((3, 2)))
    with pytest.raises(ParamsError, match="ambient_counts"):  # replace checks the shape rules of what it changes
        p.replace(ambient_counts=np.zeros((1, 1)))
    with pytest.raises(ParamsError, match="unknown field"):
        p.replace(radius=1.0)
    assert isinstance(ParamsError("x"), UserError)


def test_bad_frames_are_dropped_and_named(world):
    _add_mixed(world)
    with pytest.warns(BadFramesWarning, match=r"dropped 3 of 5 frames.*frame 1: 1 non-finite"):
        cap = read_capture(world["mixed"])
    assert cap.n_frames == 2 and list(cap.frame_index) == [0, 4]
    assert set(cap.dropped) == {1, 2, 3} and "all bins zero" in cap.dropped[3]


def test_scene_fields_fuzzed():
    """Random values for every numeric scene key: a valid scene or a one-line ConfigError, nothing else."""
    from hypothesis import given
    from hypothesis import strategies as st

    from tofjax.config import ConfigError
    from tofjax.scene import scene_from_dict

    base = json.loads(_tiny_scene()[0].to_json())
    keys = [("waveguide", k) for k, v in base["waveguide"].items() if isinstance(v, (int, float))]
    keys += [("sensor", k) for k, v in base["sensor"].items() if isinstance(v, (int, float))]
    values = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2**70), 2**70),
                       st.text(max_size=3), st.booleans(), st.none(), st.lists(st.floats(), max_size=3))

    @given(st.sampled_from(keys), values)
    def check(where, value):
        d = json.loads(json.dumps(base))
        d[where[0]][where[1]] = value
        try:
            scene_from_dict({k: v for k, v in d.items()}, "fuzz")
        except ConfigError as e:
            assert "\n" not in str(e) and where[1] in str(e)

    check()


if __name__ == "__main__":  # count outcomes (README): python tests/test_hostile.py [--json OUT]
    import tempfile
    from collections import Counter

    os.environ.setdefault("MPLBACKEND", "Agg")
    import jax

    jax.config.update("jax_enable_x64", True)
    root = Path(tempfile.mkdtemp(prefix="hostile-"))
    os.environ["TOFJAX_EVIL_DIR"] = str(root)
    (root / "world").mkdir()
    w = _build(root / "world")
    import time

    import signal

    # Restored before every case: an older tofjax may write over its inputs (counted as "silent").
    snapshot = {p: p.read_bytes() for p in (w["scene"], w["good"], w["touch"], w["notes"], w["json"])}
    limit = int(sys.argv[sys.argv.index("--timeout") + 1]) if "--timeout" in sys.argv else 0

    def alarm(*_):
        raise TimeoutError("took longer than --timeout")

    signal.signal(signal.SIGALRM, alarm)
    counts, bad, times, lines = Counter(), {}, {}, []
    # --log FILE: one line per case as it ends (a case that kills the process, e.g. by running
    # out of memory, leaves its id last in --log; run again with --start to go on).
    log = open(sys.argv[sys.argv.index("--log") + 1], "a") if "--log" in sys.argv else None
    start = int(sys.argv[sys.argv.index("--start") + 1]) if "--start" in sys.argv else 0
    for i, c in enumerate(CASES):
        if i < start:
            continue
        if log:
            log.write(f"{i}\t{c.id}\tstarted\n")
            log.flush()
        for p, data in snapshot.items():
            p.write_bytes(data)
        t0 = time.perf_counter()
        signal.alarm(limit)
        try:
            outcome, detail = run_case(c, w, root / f"case{i}")
        except TimeoutError as e:  # raised outside main()'s own handlers
            outcome, detail = "hang", str(e)
        signal.alarm(0)
        if "took longer than --timeout" in detail:
            outcome = "hang"
        if log:
            log.write(f"{i}\t{c.id}\t{outcome}\t{' '.join(detail.split())[-200:]}\n")
            log.flush()
        times[c.id] = time.perf_counter() - t0
        lines.append(f"{c.id}\t{outcome}\t{detail.strip().splitlines()[-1] if detail.strip() else ''}")
        counts[outcome] += 1
        if outcome not in ("clear", "warning"):
            bad[c.id] = f"{outcome}: {detail.strip().splitlines()[-1][:200] if detail.strip() else ''}"
    summary = {"inputs": len(CASES), **counts, "not_clear": bad,
               "slowest_s": dict(sorted(times.items(), key=lambda kv: -kv[1])[:15])}
    if "--lines" in sys.argv:
        Path(sys.argv[sys.argv.index("--lines") + 1]).write_text("\n".join(lines) + "\n")
    text = json.dumps(summary, indent=1)
    if "--json" in sys.argv:
        Path(sys.argv[sys.argv.index("--json") + 1]).write_text(text)
    print(text)
