"""Figures are written whole or not at all (tofjax.outputs.save_figure)."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

from tofjax.outputs import save_figure  # noqa: E402
from tofjax.plot import plot_scene  # noqa: E402
from tofjax.scene import default_scene  # noqa: E402


def test_save_figure_writes_the_format_of_the_suffix(tmp_path):
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    png = save_figure(fig, tmp_path / "a" / "f.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fig, _ = plt.subplots()
    pdf = save_figure(fig, tmp_path / "f.pdf")
    assert pdf.read_bytes()[:5] == b"%PDF-"
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "f.pdf", "f.png"]  # no temporaries left


def test_a_failed_save_keeps_the_old_file_and_leaves_no_partial(tmp_path):
    old = tmp_path / "f.png"
    old.write_bytes(b"old")
    fig, ax = plt.subplots()

    def boom(*a, **k):
        raise RuntimeError("renderer failed")

    fig.savefig = boom
    with pytest.raises(RuntimeError):
        save_figure(fig, old)
    assert old.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.png"]
    assert not plt.fignum_exists(fig.number)  # closed even on failure


def test_scene_plot_goes_through_it(tmp_path):
    path = plot_scene(default_scene(), tmp_path / "scene.png")
    assert path.stat().st_size > 1000 and [p.name for p in tmp_path.iterdir()] == ["scene.png"]


def test_never_writes_over_a_device_or_a_pipe(tmp_path):
    """--overwrite replaces files, never a device or a named pipe (an audit replaced /dev/full with a
    capture, and hung on a pipe, opening it to test its lock): one-line errors, nothing touched."""
    import os
    import stat

    from tofjax.capture import CaptureError, check_capture_target
    from tofjax.outputs import OutputError, check_output

    fifo = tmp_path / "fifo.h5"
    os.mkfifo(fifo)
    with pytest.raises(CaptureError, match="not a regular file"):
        check_capture_target(fifo, overwrite=True)
    with pytest.raises(OutputError, match="not a regular file"):
        check_output(fifo, overwrite=True)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    if os.path.exists("/dev/null"):
        with pytest.raises(CaptureError, match="not a regular file"):
            check_capture_target("/dev/null", overwrite=True)
        with pytest.raises(OutputError, match="not a regular file"):
            check_output("/dev/null", overwrite=True, flag="--json")
        assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
