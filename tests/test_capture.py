"""Capture files: round trip, optional parts, appending, and clear errors for bad files."""

import h5py
import numpy as np
import pytest

from tofjax.capture import Capture, CaptureError, CaptureWriter, read_capture, write_capture


@pytest.fixture
def small_scene(optoskin):
    return optoskin.replace(sensor=optoskin.sensor.__class__(bin_width_s=1e-10, n_bins=16, zones=3, fov_deg=29.0))


def make(scene, n=3, **extra):
    rng = np.random.default_rng(0)
    return Capture(
        histograms=rng.poisson(50, (n, *scene.shape)).astype(float),
        timestamps=np.arange(n) / 9.0,
        scene=scene,
        **extra,
    )


def test_round_trip_with_everything(tmp_path, small_scene):
    S, Z, B = small_scene.shape
    touches = np.full((3, 2, 3), np.nan)
    touches[:, 0] = [0.1, 0.2, 1.0]
    cap = make(
        small_scene,
        force=np.array([1.0, 2.0, 3.0]),
        reference=np.ones((3, S, B)),
        truth_touches=touches,
        truth={"n1": 1.4},
        source="tmf8828",
    )
    path = write_capture(tmp_path / "c.h5", cap)
    back = read_capture(path)
    np.testing.assert_array_equal(back.histograms, cap.histograms)
    np.testing.assert_array_equal(back.timestamps, cap.timestamps)
    np.testing.assert_array_equal(back.force, cap.force)
    np.testing.assert_array_equal(back.reference, cap.reference)
    np.testing.assert_array_equal(back.truth_touches, touches)
    assert back.truth == {"n1": 1.4}
    assert back.scene == small_scene and back.source == "tmf8828" and back.created == cap.created
    with h5py.File(path) as f:
        assert f.attrs["format"] == "tofjax.capture" and f.attrs["version"] == 1
        assert f["histograms"].chunks == (1, S, Z, B) and f["histograms"].maxshape[0] is None


def test_without_optional_parts(tmp_path, small_scene):
    back = read_capture(write_capture(tmp_path / "c.h5", make(small_scene)))
    assert back.force is None and back.reference is None and back.truth_touches is None and back.truth == {}


def test_writer_appends_and_flushes(tmp_path, small_scene):
    path = tmp_path / "rec.h5"
    w = CaptureWriter(path, small_scene, source="tmf8828", with_force=True)
    for i in range(4):
        w.append(np.full(small_scene.shape, i + 1), timestamp=i * 0.1, force=float(i))
        # Readable while still open for writing, with every completed frame.
        assert read_capture(path).n_frames == i + 1
    w.close()
    with pytest.raises(CaptureError, match="does not match"):
        with CaptureWriter(tmp_path / "x.h5", small_scene) as w2:
            w2.append(np.zeros((1, 2, 3)), 0.0)
    with pytest.raises(CaptureError, match="force must be given"):
        with CaptureWriter(tmp_path / "y.h5", small_scene, with_force=True) as w3:
            w3.append(np.zeros(small_scene.shape), 0.0)


def test_half_written_frame_is_not_read(tmp_path, small_scene):
    """A frame whose histogram was written but not its timestamp (interrupted) is left out."""
    path = write_capture(tmp_path / "c.h5", make(small_scene, n=2))
    with h5py.File(path, "a") as f:
        f["histograms"].resize(3, 0)
    assert read_capture(path).n_frames == 2


def test_truncated_file(tmp_path, small_scene):
    path = write_capture(tmp_path / "c.h5", make(small_scene))
    data = path.read_bytes()
    bad = tmp_path / "truncated.h5"
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(CaptureError, match="truncated"):
        read_capture(bad)


def test_foreign_and_wrong_files(tmp_path, small_scene):
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["data"] = np.zeros(3)
    with pytest.raises(CaptureError, match="not a tofjax capture"):
        read_capture(foreign)
    text = tmp_path / "notes.h5"
    text.write_text("hello")
    with pytest.raises(CaptureError, match="not an HDF5 file"):
        read_capture(text)
    with pytest.raises(CaptureError, match="no such file"):
        read_capture(tmp_path / "missing.h5")
    newer = write_capture(tmp_path / "v2.h5", make(small_scene))
    with h5py.File(newer, "a") as f:
        f.attrs["version"] = 2
    with pytest.raises(CaptureError, match="version 2 is not supported"):
        read_capture(newer)
    mismatch = write_capture(tmp_path / "m.h5", make(small_scene))
    with h5py.File(mismatch, "a") as f:
        f.attrs["scene"] = small_scene.replace(sensors=small_scene.sensors[:2]).to_json()
    with pytest.raises(CaptureError, match="scene says"):
        read_capture(mismatch)
    noscene = write_capture(tmp_path / "n.h5", make(small_scene))
    with h5py.File(noscene, "a") as f:
        del f.attrs["scene"]
    with pytest.raises(CaptureError, match="'scene' attribute is missing"):
        read_capture(noscene)


def test_minimal_foreign_scene_loads(tmp_path, small_scene):
    """A capture written elsewhere with only the required scene keys loads (defaults fill the rest)."""
    import json

    path = write_capture(tmp_path / "c.h5", make(small_scene))
    d = json.loads(small_scene.to_json())
    minimal = {
        "waveguide": {k: d["waveguide"][k] for k in ("size_m", "thickness_m", "n1", "mu_s_per_m", "mu_a_per_m")},
        "sensor": {k: d["sensor"][k] for k in ("bin_width_s", "n_bins", "zones", "fov_deg")},
        "sensors": [{k: s[k] for k in ("position_m", "direction_deg")} for s in d["sensors"]],
    }
    with h5py.File(path, "a") as f:
        f.attrs["scene"] = json.dumps(minimal)
    assert read_capture(path).scene.shape == small_scene.shape
