"""tofjax prune (model pruning against the photon noise) and the tofjax mc command."""

import dataclasses

import numpy as np
import pytest

from tofjax import load_scene
from tofjax.capture import read_capture
from tofjax.cli import main
from tofjax.config import ConfigError
from tofjax.mc.prune import PruneOptions, prune_model


def test_prune_keeps_what_matters_and_drops_what_does_not(optoskin):
    r = prune_model(optoskin)
    assert "touch" not in r.components and "shadowing" not in r.components  # no contacts: not needed
    assert r.effects["touch"] == 0.0
    for big in ("crosstalk", "end", "interface"):  # dominant terms stay
        assert big in r.kept and r.effects[big] > 10
    assert "multiple_scattering" in r.dropped  # below one sigma of one frame
    assert r.dropped_effect <= 1.0
    # with 100 frames the noise is ten times smaller: it is needed again
    r100 = prune_model(optoskin, PruneOptions(frames=100))
    assert "multiple_scattering" in r100.kept
    assert r100.effects["multiple_scattering"] == pytest.approx(10 * r.effects["multiple_scattering"], rel=1e-6)


def test_a_component_far_below_the_noise_is_dropped(optoskin):
    faint = optoskin.replace(waveguide=dataclasses.replace(optoskin.waveguide, interface_backscatter_per_m=1e-7))
    r = prune_model(faint, PruneOptions(noise_floor=0.5))
    assert "interface" in r.dropped and r.effects["interface"] < 1e-3
    # the dropped set together stays within the floor, and the pruned model is the kept list
    assert r.dropped_effect <= 0.5
    assert set(r.kept) | set(r.dropped) == set(r.components)


def test_prune_touch_scene_needs_touch_and_shadowing():
    r = prune_model(load_scene("touch-single"))
    assert "touch" in r.kept and "shadowing" in r.kept
    assert r.where["touch"][0] >= 0


def test_prune_refuses_a_model_that_is_not_finite(optoskin, monkeypatch):
    """A model that is NaN somewhere ranks nothing: a one-line error naming it, not a table of nan effects
    that keeps every component. (Params refuse non-finite values and the scene checks refuse the scenes
    that made NaN before, so the model is patched here to stand for one that still does.)"""
    import tofjax.mc.prune as prune_mod
    from tofjax.errors import UserError

    real = prune_mod.evaluate

    def nan_in_one_bin(model, params):
        out = np.array(real(model, params), np.float64)
        out[0, 0, 5] = np.nan
        return out

    monkeypatch.setattr(prune_mod, "evaluate", nan_in_one_bin)
    with pytest.raises(UserError, match=r"not finite at its parameters \(model"):
        prune_model(optoskin)


def test_prune_options_validated():
    with pytest.raises(ConfigError, match="noise_floor"):
        PruneOptions(noise_floor=0)
    with pytest.raises(ConfigError, match="frames"):
        PruneOptions(frames=0)


def test_prune_cli(tmp_path, capsys):
    out = tmp_path / "prune.json"
    assert main(["prune", "optoskin", "--noise-floor", "1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "recommended components" in text and "multiple_scattering" in text
    assert out.exists()
    assert main(["prune", "optoskin", "--noise-floor", "-1"]) == 2
    assert "noise_floor" in capsys.readouterr().err


def test_mc_cli_writes_a_capture(tmp_path, capsys):
    scene = load_scene("optoskin")
    small = scene.replace(sensors=scene.sensors[:1], name="one-sensor")
    path = tmp_path / "one.toml"
    path.write_text(small.to_toml())
    out = tmp_path / "mc.h5"
    assert main(["mc", str(path), "--photons", "2000", "--frames", "2", "--out", str(out)]) == 0
    cap = read_capture(out)
    assert cap.n_frames == 2 and cap.source == "simulated (monte carlo)"
    assert cap.histograms.shape == (2, 1, 7, 128) and np.all(np.isfinite(cap.histograms))
    assert cap.truth["monte_carlo"]["photons"] == 2000
    # the light-entry peak comes from the analytic model, the rest from transport
    assert cap.histograms[:, 0, :, 14:16].sum() > 0
    assert "where the light went" in capsys.readouterr().out
    assert main(["mc", str(path), "--photons", "0", "--out", str(out)]) == 2
