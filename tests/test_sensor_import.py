"""Importing real TMF882x recordings (issue 12): the JSON sweep format, the Arduino serial log,
and every bad input of the issue (one-line errors, or warnings that name the dropped frames)."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from tofjax.capture import read_capture, write_capture
from tofjax.cli import main
from tofjax.sensor.importer import TmfImportError, import_file, read_tmf882x_json, read_tmf882x_log

DATA = Path(__file__).parent / "data" / "tmf8820-plane-sweep" / "captures.json"


@pytest.fixture(scope="module")
def entries():
    return json.loads(DATA.read_text())


def test_json_import_round_trip(tmp_path, entries):
    frames, out = import_file(DATA, "tmf882x-json", tmp_path / "s.h5")
    cap = read_capture(out)
    n = len(entries)
    assert cap.histograms.shape == (n, 1, 9, 128)
    np.testing.assert_array_equal(cap.histograms[3, 0], np.asarray(entries[3]["hists"]))
    np.testing.assert_array_equal(cap.reference[5, 0], np.asarray(entries[5]["reference_hist"]))
    np.testing.assert_allclose(cap.target_distance_m, [e["dist_to_plane"] for e in entries])
    on = entries[2]["distances"][0]
    np.testing.assert_allclose(cap.onchip_distance_m[2, 0], np.asarray(on["depths_1"]) * 1e-3)
    np.testing.assert_allclose(cap.onchip_confidence[2, 0], on["confs_1"])
    assert cap.scene.free_space and cap.scene.sensor.grid == (3, 3) and cap.scene.shape == (1, 9, 128)


def test_old_captures_still_read(tmp_path, optoskin):
    from tofjax.capture import Capture

    cap = Capture(histograms=np.ones((2, *optoskin.shape)), timestamps=np.arange(2.0), scene=optoskin)
    write_capture(tmp_path / "old.h5", cap)
    back = read_capture(tmp_path / "old.h5")
    assert back.target_distance_m is None and back.onchip_distance_m is None
    assert not back.scene.free_space


def test_json_without_dist_to_plane(tmp_path, entries):
    bad = [dict(e) for e in entries]
    del bad[1]["dist_to_plane"], bad[4]["dist_to_plane"]
    p = tmp_path / "some.json"
    p.write_text(json.dumps(bad))
    with pytest.warns(UserWarning, match=r"dropped frames 1, 4: no 'dist_to_plane'"):
        frames = read_tmf882x_json(p)
    assert frames.n_frames == len(entries) - 2
    np.testing.assert_array_equal(frames.source_index, [0, 2, 3, 5, 6, 7])
    for e in bad:
        e.pop("dist_to_plane", None)
    p.write_text(json.dumps(bad))
    with pytest.raises(TmfImportError, match="no frame has 'dist_to_plane'"):
        read_tmf882x_json(p)
    assert np.isnan(read_tmf882x_json(p, require_truth=False).target_distance_m).all()


def test_json_malformed_values_are_dropped_by_name(tmp_path, entries):
    """Values that are not numbers (a ragged, short or textual 'hists', a textual 'dist_to_plane') drop
    their frame with a named reason (tracebacks before); NaN 'dist_to_plane' is no ground truth, as a
    missing one; a 'reference_hist' of the wrong length is left out with a warning (silently before)."""
    bad = [dict(e) for e in entries[:6]]
    bad[1]["hists"] = [list(r) for r in bad[1]["hists"]]
    bad[1]["hists"][2] = bad[1]["hists"][2][:50]
    bad[2]["hists"] = [["x"] * 128 for _ in bad[2]["hists"]]
    bad[3]["dist_to_plane"] = "far"
    bad[4]["dist_to_plane"] = float("nan")
    bad[5]["reference_hist"] = [1.0] * 10
    p = tmp_path / "malformed.json"
    p.write_text(json.dumps(bad))
    with pytest.warns(UserWarning) as rec:
        frames = read_tmf882x_json(p)
    text = " ".join(str(w.message) for w in rec)
    assert "'hists' is not a regular array of numbers" in text and "'dist_to_plane' is not a number" in text
    assert "no 'dist_to_plane'" in text and "reference_hist is not 128 numbers" in text
    np.testing.assert_array_equal(frames.source_index, [0, 5])
    assert np.isnan(frames.reference[1]).all() and not np.isnan(frames.reference[0]).any()


def test_json_saturated_bins_dropped(tmp_path, entries):
    bad = [dict(e) for e in entries[:3]]
    bad[2]["hists"] = [list(r) for r in bad[2]["hists"]]
    bad[2]["hists"][4][27] = 2**24 - 1
    p = tmp_path / "sat.json"
    p.write_text(json.dumps(bad))
    with pytest.warns(UserWarning, match=r"dropped frame 2: saturated bins"):
        assert read_tmf882x_json(p).n_frames == 2


def test_cli_names_dropped_frames_on_stderr(tmp_path, entries, capsys):
    """`tofjax import` exits 0, and the warning goes to stderr in one line, named by its class."""
    bad = [dict(e) for e in entries[:3]]
    bad[1]["hists"] = [list(r) for r in bad[1]["hists"]]
    bad[1]["hists"][0][30] = 2**24 - 1
    p = tmp_path / "sat.json"
    p.write_text(json.dumps(bad))
    assert main(["import", str(p), "--format", "tmf882x-json", "--out", str(tmp_path / "c.h5")]) == 0
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if "warning" in line]
    assert len(lines) == 1 and "warning: DroppedFramesWarning:" in lines[0] and "dropped frame 1: saturated bins" in lines[0]
    assert "warning" not in out and "1 frames dropped" in out


def _log_lines(counts, obj_distances_mm, result_number=0):
    """One frame of an Arduino log from (10, 128) counts: 30 #Raw packets and one #Obj line."""
    c = np.asarray(counts, np.int64)
    lines = []
    obj = ["#Obj", "65", str(result_number), "24", "9", "123456"]
    for ch in range(9):
        obj += [str(int(obj_distances_mm[ch])), "255"]
    obj += ["0"] * (78 - len(obj))
    lines.append(",".join(obj))
    for n in range(30):
        ch, plane = n % 10, n // 10
        b = (c[ch] >> (8 * plane)) & 0xFF
        lines.append(",".join(["#Raw", "0", str(n), *map(str, b)]))
    return lines


def _frames_counts(entries, k):
    return [np.vstack([e["reference_hist"], e["hists"]]) for e in entries[:k]]


def test_log_import_matches_counts(tmp_path, entries):
    frames = _frames_counts(entries, 3)
    text = ["ams TMF882x Arduino driver v1.2", "# comment"]
    for i, c in enumerate(frames):
        text += _log_lines(c, entries[i]["distances"][0]["depths_1"], i)
    p = tmp_path / "ok.log"
    p.write_text("\n".join(text) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = read_tmf882x_log(p, distance_m=0.2)
    assert got.n_frames == 3
    for i in range(3):
        np.testing.assert_array_equal(got.histograms[i], np.asarray(entries[i]["hists"]))
        np.testing.assert_array_equal(got.reference[i], np.asarray(entries[i]["reference_hist"]))
        np.testing.assert_allclose(got.onchip_distance_m[i], np.asarray(entries[i]["distances"][0]["depths_1"]) * 1e-3)
    assert np.all(got.target_distance_m == 0.2)


@pytest.mark.parametrize(
    "damage, message",
    [
        ("torn", r"dropped frame 1: torn #Raw line"),
        ("missing", r"dropped frame 1: missing packet 13 \(byte plane 1\)"),
        ("repeated", r"dropped frame 1: repeated packet number 4"),
    ],
)
def test_log_bad_frames_are_named(tmp_path, entries, damage, message):
    frames = _frames_counts(entries, 3)
    blocks = [_log_lines(c, np.zeros(9), i) for i, c in enumerate(frames)]
    b = blocks[1]  # frame 1: its #Obj line, then packets 0..29
    if damage == "torn":
        b[8] = b[8][: len(b[8]) // 2]
    elif damage == "missing":
        del b[14]
    else:
        b.insert(6, b[5])
    p = tmp_path / f"{damage}.log"
    p.write_text("\n".join(sum(blocks, [])) + "\n")
    with pytest.warns(UserWarning, match=message):
        got = read_tmf882x_log(p)
    assert got.n_frames == 2
    np.testing.assert_array_equal(got.source_index, [0, 2])
    np.testing.assert_array_equal(got.histograms[1], np.asarray(entries[2]["hists"]))


def test_log_first_frame_partial_and_not_a_log(tmp_path, entries):
    frames = _frames_counts(entries, 2)
    lines = _log_lines(frames[0], np.zeros(9))[20:] + _log_lines(frames[1], np.zeros(9))  # logging started mid-frame
    p = tmp_path / "mid.log"
    p.write_text("\n".join(lines))
    with pytest.warns(UserWarning, match=r"dropped frame 0: missing packets 0,1,"):
        assert read_tmf882x_log(p).n_frames == 1
    q = tmp_path / "junk.log"
    q.write_text("hello\nworld\n")
    with pytest.raises(TmfImportError, match="not a TMF882x Arduino log"):
        read_tmf882x_log(q)


def test_cli_import_and_one_line_error(tmp_path, capsys):
    assert main(["import", str(DATA), "--format", "tmf882x-json", "--out", str(tmp_path / "c.h5")]) == 0
    assert "8 frames, 9 zones (3x3)" in capsys.readouterr().out
    assert main(["import", str(DATA), "--format", "tmf882x-log", "--out", str(tmp_path / "d.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not a TMF882x Arduino log" in err
