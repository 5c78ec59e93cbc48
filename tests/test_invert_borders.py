"""Detection that does not depend on tofjax's amplitude scale and holds at the borders:
inverse-variance combination of the sensors, a constant-false-alarm-rate floor, the model
method's noise-relative threshold; checked on the independent simulator (tests/indep_sim.py)."""

import dataclasses

import numpy as np
import pytest

from indep_sim import IndepOptions, IndepRig
from tofjax import load_scene
from tofjax.cli import main
from tofjax.invert import InvertOptions, MapOptions, build_inverter, match
from tofjax.invert.detect import DetectOptions
from tofjax.invert.reconstruct import ReconstructOptions
from tofjax.invert.synth import simulate_contacts
from tofjax.simulate import simulate

RES = MapOptions(resolution_m=0.005)


@pytest.fixture(scope="module")
def lossy():
    """The default scene on a guide with mu_s + mu_a = 3 /m, and a 40-frame baseline."""
    sc = load_scene("optoskin")
    sc = sc.replace(waveguide=dataclasses.replace(sc.waveguide, mu_s_per_m=2.0, mu_a_per_m=1.0))
    return sc, simulate(sc, 40, seed=1)


def _edge_distance(scene, xy):
    lx, ly = scene.waveguide.size_m
    return np.minimum.reduce([xy[..., 0], lx - xy[..., 0], xy[..., 1], ly - xy[..., 1]])


def test_inverse_variance_map_has_the_least_noise(lossy):
    """A weighted mean with weights 1/variance has no more noise than the plain mean, anywhere,
    and much less at the borders of an attenuating guide."""
    sc, base = lossy
    B = base.mean()
    noise = {}
    for c in ("mean", "inverse_variance"):
        inv = build_inverter(sc, B, InvertOptions(maps=dataclasses.replace(RES, combine=c)), n_baseline=40)
        noise[c] = inv.operator, inv.grid, np.asarray(_linear_noise(inv))
    a, b = noise["mean"][2], noise["inverse_variance"][2]
    seen = a > 0
    assert np.all(b[seen] <= a[seen] * (1 + 1e-4))
    shared = np.asarray(noise["mean"][0].coverage).reshape(a.shape) >= 2  # pixels two sensors or more see
    print("mean noise ratio where shared", np.mean(a[shared] / b[shared]))
    assert np.mean(a[shared] / b[shared]) > 1.2


def _linear_noise(inv):
    from tofjax.invert.pipeline import _noise_map

    return _noise_map(inv.corrector, inv.operator, inv.corrector.baseline, 40)


def test_cfar_floor_is_flat(lossy):
    """No-touch frames, normalised by the ensemble floor: the same spread at the borders as in the
    interior (the linear noise map itself varies by a large factor)."""
    sc, base = lossy
    inv = build_inverter(sc, base.mean(), InvertOptions(maps=RES), n_baseline=40, baseline_frames=base.histograms)
    assert inv.floor is not None
    H = simulate(sc, 24, seed=7).histograms
    maps, _ = inv.maps(H)
    z = (maps - inv.floor) / inv.noise
    border = _edge_distance(sc, inv.grid.centres()) < 0.03
    seen = inv.noise > 0
    sd_b, sd_i = z[:, border & seen].std(), z[:, ~border & seen].std()
    assert 0.7 < sd_b / sd_i < 1.4
    assert 0.7 < sd_i < 1.4
    assert inv.noise[border & seen].max() / np.median(inv.noise[~border & seen]) > 3  # what CFAR flattens
    # Few false alarms on no-touch frames at the default threshold (the tails are heavier than
    # Gaussian: Poisson bins of a few counts, amplified by the decay gain).
    false = sum(len(inv.detect(m).touches) for m in maps)
    print("false touches in 24 no-touch frames", false)
    assert false <= 3


def test_border_contacts_found_on_independent_data():
    """Independent simulator, mu_s + mu_a = 3 /m: contacts 1.5-3 cm from the edge are found (full)."""
    sc = load_scene("optoskin")
    sc = sc.replace(waveguide=dataclasses.replace(sc.waveguide, mu_s_per_m=2.0, mu_a_per_m=1.0))
    rig = IndepRig.from_scene(sc, seed=3, options=IndepOptions(angles_per_zone=6, end_rays=24))
    base = rig.histograms(np.zeros((100, 0, 3)), seed=1)
    C = np.array(
        [
            [[0.015, 0.10, 1.0], [0.15, 0.28, 1.0], [0.27, 0.20, 0.8]],
            [[0.285, 0.05, 1.0], [0.10, 0.02, 1.2], [0.16, 0.16, 1.0]],
        ]
    )
    H = rig.histograms(C, seed=2)
    inv = build_inverter(sc, base.mean(0), InvertOptions(maps=RES), n_baseline=100, baseline_frames=base)
    found = false = 0
    for m, c in zip(inv.maps(H)[0], C):
        det = inv.detect(m)
        k, d = match(det.positions(), c[:, :2])
        found, false = found + k, false + len(det.touches) - k
        assert np.all(d < 0.015)
    print("found", found, "false", false)
    assert found >= 5 and false <= 1


def test_model_threshold_is_relative_to_noise(optoskin):
    """Contacts at a fifth of the model's strength scale (another rig's gain or coupling) are
    still found by the noise-relative threshold; the old absolute one (0.2) loses them."""
    sc = optoskin
    base = simulate(sc, 30, seed=1).mean()
    C = np.array([[[0.08, 0.09, 0.2], [0.22, 0.07, 0.2], [0.14, 0.22, 0.2]]])
    H = simulate_contacts(sc, C, seed=5)
    ro = ReconstructOptions(cell_m=0.01, iterations=200, shadow=False)
    inv = build_inverter(sc, base, InvertOptions(method="model", reconstruct=ro), n_baseline=30)
    m = inv.maps(H)[0][0]
    det = inv.detect(m)
    k, d = match(det.positions(), C[0, :, :2])
    assert k == 3 == len(det.touches) and d.max() < 0.015
    assert inv.options.detect.threshold == 0.0 and inv.options.detect.n_sigma == 1.0
    old = dataclasses.replace(inv, options=dataclasses.replace(
        inv.options, detect=dataclasses.replace(inv.options.detect, threshold=0.2, n_sigma=0.0)))
    assert len(old.detect(m).touches) < 3


def test_options_a_method_ignores_are_rejected(optoskin):
    with pytest.raises(Exception, match="reconstruct"):
        build_inverter(optoskin, None, InvertOptions(method="decay", reconstruct=ReconstructOptions(n_sigma=2.0)))
    with pytest.raises(Exception, match="cfar_draws"):
        DetectOptions(cfar_draws=1)
    with pytest.raises(Exception, match="n_sigma"):
        ReconstructOptions(n_sigma=-1.0)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--method", "full", "--min-strength", "0.1"], "--min-strength applies to --method model only"),
        (["--method", "model", "--no-cfar"], "--no-cfar applies to back-projection"),
    ],
)
def test_cli_rejects_options_the_method_ignores(tmp_path, optoskin, capsys, args, message):
    from tofjax.capture import write_capture

    cap = simulate(optoskin, 2, seed=0)
    p = write_capture(tmp_path / "b.h5", cap)
    rc = main(["detect", str(p), "--baseline", str(p), "--json", str(tmp_path / "t.json"), *args])
    err = capsys.readouterr().err
    assert rc != 0 and message in err and len(err.strip().splitlines()) == 1
