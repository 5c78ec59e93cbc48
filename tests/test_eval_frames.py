"""eval_touch.py's ``frames_summed`` (a static touch, frames summed; the baseline on the same exposure)
and the study that picks the frame count from the sensitivity map (experiments/eval_touch_frames.py)."""

import numpy as np
import pytest
from test_studies import load

from tofjax import load_scene
from tofjax.config import ConfigError, from_dict
from tofjax.invert.synth import simulate_contacts
from tofjax.simulate import expected_counts, simulate


@pytest.fixture(scope="module")
def et():
    return load("eval_touch")


@pytest.fixture(scope="module")
def scene():
    # three OptoSkin sensors, 3 zones, 96 bins (test_calibrate's small scene): the same draws, a fraction of the cost
    from tofjax.scene import SensorModel

    sc = load_scene("optoskin").without_touches()
    return sc.replace(sensor=SensorModel(bin_width_s=1e-10, n_bins=96, zones=3, fov_deg=29.0), sensors=sc.sensors[:3])


CONTACT = np.array([[[0.12, 0.2, 1.0]]])  # one contact, well inside


def test_one_frame_is_the_old_path(et, scene):
    """frames_summed = 1 draws exactly what eval_touch drew before the option (bit for bit)."""
    cfg = et.EvalConfig(baseline_frames=4)
    assert cfg.frames_summed == 1
    own = et._Source("own", scene, cfg)
    np.testing.assert_array_equal(own.baseline_frames, simulate(scene, 4, cfg.seed).histograms)
    np.testing.assert_array_equal(own.frames(CONTACT, seed=7), simulate_contacts(scene, CONTACT, seed=7))
    ind = et._Source("independent", scene, cfg)
    sim = et._indep()
    rig = sim.IndepRig.from_scene(scene, seed=cfg.rig_seed)
    np.testing.assert_array_equal(ind.baseline_frames, sim.simulate(rig, np.zeros((0, 3)), 4, cfg.seed).histograms)
    np.testing.assert_array_equal(ind.frames(CONTACT, seed=7), rig.histograms(CONTACT, seed=7))


def _matched_snr(H, signal, base):
    """Matched-filter statistic of each frame against the known contact signal: mean / std over frames."""
    w = (signal / np.maximum(base, 1.0)).ravel()
    t = (H - base).reshape(len(H), -1) @ w
    return t.mean() / t.std(ddof=1)


def test_summed_frames_raise_snr_by_sqrt_n(et, scene):
    """With N frames summed (touch and baseline), a known contact's matched-filter SNR grows by about
    sqrt(N), the baseline's counts by N, and the summed frames stay Poisson (variance = mean); the
    same on the independent simulator's noise."""
    reps = np.repeat(CONTACT, 64, axis=0)
    lam_t = simulate_contacts(scene, CONTACT, noise=False)[0]
    lam_b = expected_counts(scene)
    snr = {}
    for n in (1, 4):
        src = et._Source("own", scene, et.EvalConfig(baseline_frames=8, frames_summed=n))
        H = src.frames(reps, seed=11)
        assert H.shape == (64, *scene.shape)
        np.testing.assert_allclose(H.mean(0).sum(), n * lam_t.sum(), rtol=2e-3)
        np.testing.assert_allclose(src.baseline.sum(), n * lam_b.sum(), rtol=2e-3)
        snr[n] = _matched_snr(H, n * (lam_t - lam_b), n * lam_b)
    assert snr[1] > 3
    assert 1.6 < snr[4] / snr[1] < 2.5  # sqrt(4) = 2; 64 frames give each std to about 9%
    # the independent simulator: the summed frame's mean and variance both N x its expected counts
    ind = et._Source("independent", scene, et.EvalConfig(baseline_frames=2, frames_summed=5))
    lam = ind.rig.expected(CONTACT[0])
    H = ind._indep_summed([lam] * 48, seed=3)
    big = lam > 50
    np.testing.assert_allclose(H.mean(0)[big].sum(), 5 * lam[big].sum(), rtol=5e-3)
    ratio = H.var(0, ddof=1)[big].sum() / (5 * lam[big].sum())
    assert 0.8 < ratio < 1.2


def test_frames_summed_is_validated(et, tmp_path):
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ConfigError, match="frames_summed"):
            et.EvalConfig(frames_summed=bad)
    with pytest.raises(ConfigError, match="frames_summed"):
        from_dict(et.EvalConfig, {"frames_summed": 0})
    assert from_dict(et.EvalConfig, {"frames_summed": 3}).frames_summed == 3
    # the model method's relative threshold passes through (default: the method's own)
    assert et._options(et.EvalConfig(methods=("model",), model_relative=0.3))["model"].reconstruct.relative == 0.3
    assert et._options(et.EvalConfig(methods=("model",)))["model"].reconstruct.relative == 0.1
    cfg = tmp_path / "c.toml"
    cfg.write_text('scene = "optoskin"\n')
    with pytest.raises(SystemExit) as e:
        et.main(["--config", str(cfg), "--frames-summed", "0", "--out", str(tmp_path)])
    assert e.value.code == 2


def test_frames_study_choice_and_targets():
    study = load("eval_touch_frames")
    m = {"own": {"frames_needed_max": 5, "frames_margin2_max": 19, "frames_margin2_quantiles_50_90_99": [1, 4.2, 9]},
         "independent": {"frames_needed_max": 3, "frames_margin2_max": 12, "frames_margin2_quantiles_50_90_99": [1, 3, 7]}}
    assert study.choose("worst", m) == 5 and study.choose("margin2", m) == 19 and study.choose("margin2_q90", m) == 5

    def s(p, r, e, b, i):
        return {"precision": p, "recall": r, "mean_error_cm": e, "recall_border": b, "recall_interior": i}

    row = {"six": {"methods": {"full": s(0.99, 0.96, 0.5, 0.93, 0.97), "model": s(0.985, 0.97, 0.3, 0.96, 0.98)}}}
    t = study.targets(row)
    assert all(t["full"].values()) and all(t["model"].values())
    assert not t["model at least as good as full"]  # precision 98.5% < 99%
    row["six"]["methods"]["full"]["recall_border"] = 0.90
    assert not study.targets(row)["full"]["border within 5 points of interior"]
