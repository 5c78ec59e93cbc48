"""The tofjax command: subcommands, help, one-line errors, and the demo job."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tofjax.capture import read_capture
from tofjax.cli import build_parser, main

ROOT = Path(__file__).parents[1]


def test_help_lists_subcommands_and_each_has_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for cmd in ("simulate", "plot", "demo", "scene"):
        assert cmd in out
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for cmd in sub.choices:
        with pytest.raises(SystemExit) as e:
            main([cmd, "--help"])
        assert e.value.code == 0


def test_simulate_then_plot(tmp_path, capsys):
    cap_path = tmp_path / "touch.h5"
    base_path = tmp_path / "base.h5"
    assert main(["simulate", "touch-single", "--frames", "3", "--seed", "4", "--out", str(cap_path)]) == 0
    assert main(["simulate", "optoskin", "--frames", "2", "--out", str(base_path)]) == 0
    cap = read_capture(cap_path)
    assert cap.n_frames == 3 and cap.source == "simulated"
    assert cap.scene.name == "touch-single"
    np.testing.assert_allclose(cap.truth_touches[0, 0], [0.10, 0.20, 1.0])
    assert cap.truth["n1"] == pytest.approx(1.4) and cap.truth["seed"] == 4
    assert (cap.histograms >= 0).all() and np.all(cap.histograms == np.round(cap.histograms))
    # same seed, same capture
    again = tmp_path / "again.h5"
    main(["simulate", "touch-single", "--frames", "3", "--seed", "4", "--out", str(again)])
    np.testing.assert_array_equal(read_capture(again).histograms, cap.histograms)
    out_dir = tmp_path / "plots"
    assert main(["plot", str(cap_path), "--baseline", str(base_path), "--out", str(out_dir), "--sensors", "5,0,5"]) == 0
    pngs = sorted(p.name for p in out_dir.glob("*.png"))
    assert pngs == ["histograms_sensor0.png", "histograms_sensor5.png", "scene.png"]
    assert all((out_dir / p).stat().st_size > 10_000 for p in pngs)
    for bad in ("6", "-1", "x", ""):
        assert main(["plot", str(cap_path), "--out", str(tmp_path / "bad"), f"--sensors={bad}"]) == 2
        err = capsys.readouterr().err.strip()
        assert "--sensors" in err and "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "bad").exists()



@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "no-such-scene.toml", "--out", "x.h5"], "no-such-scene.toml: no such file"),
        (["simulate", "optoskin", "--frames", "0", "--out", "x.h5"], "--frames: must be in [1, "),
        (["plot", "missing.h5", "--out", "d"], "missing.h5: no such file"),
        (["scene", "BADSCENE"], "waveguide.n1: must be > 1"),
    ],
)
def test_user_errors_are_one_line(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    bad = (ROOT / "configs" / "optoskin.toml").read_text().replace("n1 = 1.4", "n1 = 0.8")
    (tmp_path / "BADSCENE").write_text(bad)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and "Traceback" not in err


def test_scene_command_prints_components_and_toml(capsys):
    assert main(["scene", "touch-three-line"]) == 0
    out = capsys.readouterr().out
    assert "6 sensors x 7 zones x 128 bins, 3 touches" in out and "shadowing" in out
    assert main(["scene", "optoskin", "--toml"]) == 0
    assert "interface_backscatter_per_m" in capsys.readouterr().out


def test_console_script_runs_without_traceback(tmp_path):
    """The installed entry point, as a user runs it: a bad file is one line on stderr, exit 2."""
    exe = Path(sys.executable).parent / "tofjax"
    if not exe.exists():
        pytest.skip("console script not installed in this environment")
    bad = tmp_path / "bad.toml"
    bad.write_text("[waveguide]\nsize_m = [0.3, 0.3]\n")
    r = subprocess.run([str(exe), "scene", str(bad)], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "waveguide.thickness_m: missing key" in r.stderr


def test_demo_writes_plots_summary_and_captures(tmp_path, optoskin):
    from tofjax.demo import run_demo
    from tofjax.scene import SensorModel

    # the demo's job on a smaller OptoSkin (3 sensors, 3 zones) to keep the suite fast
    small = optoskin.replace(
        sensor=SensorModel(bin_width_s=1e-10, n_bins=96, zones=3, fov_deg=29.0), sensors=optoskin.sensors[:3]
    )
    summary = run_demo(tmp_path / "demo", small, frames=20)
    text = summary.read_text()
    assert "touch 0" in text and "touch 2" in text and "us per evaluation" in text
    assert "calibration: converged" in text and "95% interval" in text
    assert "force estimation (seed 001)" in text and "test MAE mlp_rf" in text
    for name in ("scene.png", "components.png", "histograms_sensor0.png", "histograms_sensor1.png",
                 "histograms_sensor2.png", "baseline.h5", "touch.h5", "calibration.json"):  # every sensor by default
        assert (tmp_path / "demo" / name).exists(), name
    touch = read_capture(tmp_path / "demo" / "touch.h5")
    assert touch.truth_touches.shape == (1, 3, 3)
