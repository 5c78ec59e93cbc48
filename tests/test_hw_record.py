"""Recording from emulated rigs: captures that read like any other, faults, Ctrl-C and kill -9."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from tofjax.capture import COMMITTED, read_capture
from tofjax.cli import main
from tofjax.hw.bus import BusFaults
from tofjax.hw.emulator import DeviceFaults
from tofjax.hw.recorder import AcquireOptions, acquire
from tofjax.scene import Touch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def small_scene(optoskin):
    """Two OptoSkin sensors and one touch: a multi-sensor rig that compiles quickly."""
    return optoskin.replace(sensors=optoskin.sensors[:2], name="optoskin-2",
                            touches=(Touch(position_m=(0.10, 0.20), radius_m=0.01, strength=1.0),))


@pytest.fixture(scope="module")
def scene_file(small_scene, tmp_path_factory):
    p = tmp_path_factory.mktemp("scene") / "two.toml"
    p.write_text(small_scene.to_toml())
    return p


def test_emulated_capture_reads_like_any_other(scene_file, small_scene, tmp_path, capsys):
    out = tmp_path / "cap.h5"
    res = acquire(str(scene_file), out, AcquireOptions(frames=4, emulate=True, progress=False, bus_speed_hz=1_000_000))
    assert res.frames == 4 and res.dropped == 0 and res.synthetic_image
    cap = read_capture(out)
    assert cap.histograms.shape == (4, *small_scene.shape) and cap.scene.shape == small_scene.shape
    assert cap.reference.shape == (4, 2, 128) and np.all(np.diff(cap.timestamps) > 0)
    assert cap.source == "tmf8828-emulated" and cap.truth["emulated"] and cap.truth_touches.shape == (4, 1, 3)
    assert np.all(cap.histograms == np.round(cap.histograms)) and cap.histograms.max() < 2**24
    # the simulated bus time per frame: 2 sensors x (measure 5 ms + period 33 ms + readout ~40 ms at 1 MHz)
    assert 0.12 < np.median(np.diff(cap.timestamps)) < 0.2
    assert main(["plot", str(out), "--out", str(tmp_path / "plots")]) == 0

    base = tmp_path / "base.h5"
    assert main(["baseline", str(scene_file), "--emulate", "--frames", "3", "--out", str(base), "--quiet"]) == 0
    b = read_capture(base)
    assert b.n_frames == 3 and not b.scene.touches and b.truth_touches is None
    assert "wrote" in capsys.readouterr().out


def test_faulty_emulated_rig_writes_only_whole_frames(scene_file, tmp_path):
    out = tmp_path / "faulty.h5"
    res = acquire(str(scene_file), out, AcquireOptions(
        frames=8, emulate=True, progress=False, noise=False, bus_speed_hz=1_000_000,
        bus_faults=BusFaults(nack=0.01, timeout=0.005, corrupt=0.02, seed=5),
        device_faults=DeviceFaults(repeat=0.01, skip=0.005, wrong_cid=0.01, reset=0.002, seed=5)))
    cap = read_capture(out)
    assert cap.n_frames == res.frames == 8
    assert sum(res.errors.values()) > 10
    # noise off: every whole frame is the same, so one broken frame would stand out
    assert np.all(cap.histograms == cap.histograms[0]) and np.all(cap.reference == cap.reference[0])


def test_cli_errors(tmp_path, capsys):
    assert main(["acquire", "optoskin", "--bus", "97", "--frames", "1", "--out", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/dev/i2c-97 does not exist" in err[0]
    assert main(["acquire", "optoskin", "--emulate", "--frames", "1", "--out", str(tmp_path / "x.h5"),
                 "--faults", "gremlins=0.1"]) == 2
    assert "unknown fault 'gremlins'" in capsys.readouterr().err
    assert main(["acquire", "optoskin", "--emulate", "--frames", "1", "--out", str(tmp_path / "x.h5"),
                 "--image", str(tmp_path / "none.hex")]) == 2
    assert "not shipped" in capsys.readouterr().err


def _frames_in(path: Path) -> int:
    try:
        # The committed count, not the datasets' length: a frame is resized into the datasets
        # before it is committed, so a length read mid-write can be one frame ahead.
        with h5py.File(path, "r", locking=False) as f:
            return int(f.attrs.get(COMMITTED, 0))
    except (OSError, KeyError):
        return 0


def test_interrupted_recordings_keep_every_whole_frame(scene_file, tmp_path):
    """SIGINT (Ctrl-C) and SIGKILL (a power cut, as far as the file is concerned) mid-recording."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    procs = {}
    for sig in (signal.SIGINT, signal.SIGKILL):
        out = tmp_path / f"{sig.name}.h5"
        # The CLI as users run it, with the forward model replaced by fixed signals so that the
        # subprocess starts in seconds (the model -> emulator path is tested in-process).
        args = ["acquire", str(scene_file), "--emulate", "--no-noise", "--duration", "1e6", "--quiet", "--out", str(out)]
        code = ("import numpy as np, tofjax.hw.rig as r\n"
                "r._signals_cached = lambda scene, rc, x64: (np.full(scene.shape, 3e4), np.full((scene.n_sensors, 128), 5e3))\n"
                f"from tofjax.cli import main\nraise SystemExit(main({args!r}))")
        cmd = [sys.executable, "-c", code]
        procs[sig] = (subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), out)
    try:
        _interrupt_and_check(procs)
    finally:
        # a recording that ignored its signal must not run on (it would record for 1e6 s and take
        # a core from the rest of the suite)
        for p, _ in procs.values():
            if p.poll() is None:
                p.kill()
                p.communicate()


def _interrupt_and_check(procs):
    deadline = time.time() + 120
    while any(_frames_in(out) < 5 for _, out in procs.values()):
        assert time.time() < deadline, "the recordings did not start"
        assert all(p.poll() is None for p, _ in procs.values()), [p.communicate() for p, _ in procs.values()]
        time.sleep(0.2)
    seen = {}
    for sig, (p, out) in procs.items():
        seen[sig] = _frames_in(out)
        p.send_signal(sig)
    for sig, (p, out) in procs.items():
        stdout, stderr = p.communicate(timeout=60)
        if sig == signal.SIGINT:
            assert p.returncode == 130 and "interrupted: wrote" in stdout, stderr
        else:
            assert p.returncode == -signal.SIGKILL
        cap = read_capture(out)
        assert cap.n_frames >= seen[sig]
        assert np.all(cap.histograms == cap.histograms[0]) and np.all(cap.reference == cap.reference[0])
        assert np.all(np.diff(cap.timestamps) > 0)


def test_replay_feeds_a_capture_through_the_live_pipeline(scene_file, tmp_path, capsys):
    from tofjax.hw.recorder import ReplaySource, iter_frames, replay

    src = tmp_path / "rec.h5"
    acquire(str(scene_file), src, AcquireOptions(frames=3, emulate=True, progress=False, bus_speed_hz=1_000_000))
    a = read_capture(src)
    assert main(["replay", str(src), "--out", str(tmp_path / "copy.h5"), "--quiet"]) == 0
    assert "3 frames" in capsys.readouterr().out
    b = read_capture(tmp_path / "copy.h5")
    np.testing.assert_array_equal(a.histograms, b.histograms)
    np.testing.assert_array_equal(a.reference, b.reference)
    np.testing.assert_allclose(a.timestamps, b.timestamps)
    assert b.scene == a.scene and b.source == a.source
    frames = list(iter_frames(ReplaySource(src)))
    assert len(frames) == 3 and frames[2].histograms.shape == a.scene.shape
    # at the recorded speed x 4 the replay takes about a quarter of the recorded time
    t = time.perf_counter()
    res = replay(src, speed=4, progress=False)
    span = a.timestamps[-1] - a.timestamps[0]
    assert res.frames == 3 and span / 4 * 0.9 < time.perf_counter() - t < span / 4 + 0.5
    assert main(["replay", str(src), "--speed", "fast"]) == 2


def test_rig_file_with_an_intel_hex_image(scene_file, tmp_path):
    """A user-supplied Intel HEX image named in a rig file (relative path) is parsed and downloaded."""
    from tofjax.hw import protocol as P

    img = P.synthetic_image(size=3000, seed=11)
    (tmp_path / "app.hex").write_text(P.to_intel_hex(img))
    (tmp_path / "rig.toml").write_text(
        f'scene = "{scene_file}"\nselect = "pins"\nimage = "app.hex"\nbus_speed_hz = 1000000\n'
        '[[sensors]]\nenable_pin = 17\n[[sensors]]\nenable_pin = 27\naddress = 0x50\n')
    res = acquire(str(tmp_path / "rig.toml"), tmp_path / "c.h5", AcquireOptions(frames=2, emulate=True, progress=False))
    assert res.frames == 2 and not res.synthetic_image and sum(res.errors.values()) == 0
    assert read_capture(tmp_path / "c.h5").histograms.shape[1:] == (2, 7, 128)


def test_demo_acquisition_runs_twice_only_with_overwrite(small_scene, tmp_path):
    """`make demo` passes --overwrite: its recording must honour it (a second run failed at the
    acquisition step, after half a minute of work), and without it the first recording is kept."""
    from tofjax.capture import CaptureError
    from tofjax.hw.demo import run as hw_demo

    scene = small_scene.without_touches()
    hw_demo(tmp_path, scene, frames=1)
    before = (tmp_path / "acquired.h5").read_bytes()
    with pytest.raises(CaptureError, match="exists"):
        hw_demo(tmp_path, scene, frames=1)
    assert (tmp_path / "acquired.h5").read_bytes() == before
    lines = hw_demo(tmp_path, scene, frames=2, seed=1, overwrite=True)
    assert "2 whole frames" in "\n".join(lines)
    assert read_capture(tmp_path / "acquired.h5").n_frames == 2


def test_ctrl_c_stops_a_recording_even_when_inherited_ignored():
    """A background job of a non-interactive shell inherits SIGINT ignored; the recorder must still
    stop on it whenever it lands (it used to only while a frame was being written, held there)."""
    from tofjax.hw.recorder import _sigterm_as_interrupt

    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with pytest.raises(KeyboardInterrupt):
            with _sigterm_as_interrupt():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1.0)  # the handler runs at the next bytecode; never reached
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN  # restored afterwards
    finally:
        signal.signal(signal.SIGINT, old)
