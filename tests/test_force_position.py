"""Force anywhere on the skin (issue 17): inversion features, the protocol over positions, the
packed forest and its format, the position run's metrics by split."""

import json
import shutil

import numpy as np
import pytest

from tofjax.config import ConfigError
from tofjax.errors import UserError
from tofjax.force.features import ContactInverter, FeatureConfig, FeatureError, capture_rows, find_window
from tofjax.force.forest import (
    ForestArrays,
    ForestFormatError,
    ForestOptions,
    fit_forest,
    forest_predict_numpy,
    forest_to_arrays,
)
from tofjax.force.generate import Protocol, simulate_session
from tofjax.force.train import load_predictor, run_config_from_dict, train

FAST = dict(velocities_mm_s=(5.0,), train_forces_n=(20.0, 50.0), hold_s=1.0, rest_s=0.5, baseline_s=1.0)
INV = FeatureConfig(variant="derivative", source="inversion", sensor=0)


@pytest.fixture(scope="module")
def scene():
    return Protocol().load_scene()


@pytest.fixture(scope="module")
def presses(scene):
    """One 50 N press at three distances from sensor 0."""
    return {d: simulate_session(scene, Protocol(distance_m=d, **FAST), [50.0], 5.0, 3) for d in (0.08, 0.15, 0.22)}


# ---- the contact inverter --------------------------------------------------------------------


def test_inverter_finds_the_contact_and_its_range(presses):
    for d, cap in presses.items():
        inv = ContactInverter(cap.scene)
        nb = cap.truth["baseline_frames"]
        c, ok = inv.correct(cap.histograms, cap.histograms[:nb].mean(0))
        assert ok.all() and c.shape == cap.histograms.shape
        (contact,) = inv.locate(c, 0, 1)
        # Within half a bin (5.4 mm of range at n1 = 1.4) of the true range.
        assert contact.range_m == pytest.approx(cap.truth["contacts"][0]["range_m"], abs=0.006)


def test_features_follow_the_contact_and_do_not_decay_with_range(presses):
    peak = {}
    for d, cap in presses.items():
        (x, valid, f), = capture_rows(cap, find_window([cap], INV), INV)
        assert x.shape[1] == 3 * 5 + 2 and valid.sum() > 0.9 * len(valid)
        assert x[0, -2] == pytest.approx(cap.truth["contacts"][0]["range_m"], abs=0.006)  # range is an input
        hold = np.abs(f - 50.0) < 0.3
        peak[d] = x[hold, :5].sum(1).mean()
    # Raw counts fall ~3x from 80 to 220 mm; the corrected window holds to 25 %.
    assert max(peak.values()) / min(peak.values()) < 1.25


def test_calibrated_optics_are_used(presses, scene):
    from tofjax.fit._result import scene_fingerprint

    cap = presses[0.15]
    base = ContactInverter(scene)
    cal = {"parameters": {"n1": {"value": 1.398 * 1.1}}, "converged": True, "scene_fingerprint": scene_fingerprint(scene),
           "fixed": {k: np.asarray(getattr(__import__("tofjax.model", fromlist=["Params"]).Params.from_scene(scene), k)).tolist()
                     for k in ("mu_s_per_m", "mu_a_per_m", "gain", "emission_time_s", "pulse_sigma_s", "pulse_tail_s")}}
    slow = ContactInverter.from_calibration(scene, cal)
    assert slow.optical.n1 == pytest.approx(1.398 * 1.1)
    nb = cap.truth["baseline_frames"]
    r = [inv.locate(inv.correct(cap.histograms, cap.histograms[:nb].mean(0))[0], 0)[0].range_m for inv in (base, slow)]
    assert r[1] == pytest.approx(r[0] / 1.1, rel=0.03)  # light is slower: the same bins are nearer
    with pytest.raises(FeatureError, match="did not converge"):
        ContactInverter.from_calibration(scene, {**cal, "converged": False})


def test_feature_options_are_checked():
    with pytest.raises(ConfigError, match="source"):
        FeatureConfig(source="maps")
    with pytest.raises(ConfigError, match="options of source"):
        FeatureConfig(contacts=2)


# ---- the protocol over positions -------------------------------------------------------------


def test_positions_outside_the_skin_are_refused():
    with pytest.raises(ConfigError, match="unseen_positions_m: a contact at \\[0.5, 0\\] m"):
        Protocol(unseen_positions_m=((0.5, 0.0),)).load_scene()


def test_two_contacts_each_with_its_own_force(scene):
    p = Protocol(**FAST)
    cap = simulate_session(scene, p, [[20.0], [50.0]], 5.0, 1, split="two_contacts", positions=[(0.09, 0.0), (0.21, 0.0)])
    assert cap.truth["n_contacts"] == 2 and cap.truth_touches.shape[1] == 2
    f1, f2 = (np.asarray(f) for f in cap.truth["contact_forces_n"])
    assert f1.max() == pytest.approx(20.0, abs=0.3) and f2.max() == pytest.approx(50.0, abs=0.3)
    np.testing.assert_allclose(cap.force, f1, atol=1e-3)
    rows = capture_rows(cap, find_window([cap], INV), INV)
    assert len(rows) == 2
    # Nearest first, each with its own force channel.
    assert rows[0][0][0, -2] < rows[1][0][0, -2]
    assert rows[0][2].max() == pytest.approx(20.0, abs=0.3) and rows[1][2].max() == pytest.approx(50.0, abs=0.3)


# ---- the packed forest -----------------------------------------------------------------------


def test_packed_forest_equals_sklearn_in_jax_and_numpy():
    import jax

    from tofjax.force.forest import forest_predict

    rng = np.random.default_rng(1)
    x = rng.uniform(size=(500, 6))
    y = np.cos(5 * x[:, 0]) + x[:, 1] + 0.05 * rng.standard_normal(500)
    rf = fit_forest(x, y, ForestOptions(trees=8, max_depth=6, min_samples_leaf=3, n_jobs=1), seed=0)
    fa = forest_to_arrays(rf)
    assert fa.depth <= 6 and fa.feature.shape == (8 * (2**fa.depth - 1),)
    xt = np.concatenate([rng.uniform(size=(200, 6)), x[:50]]).astype(np.float32)
    want = rf.predict(xt)
    np.testing.assert_allclose(np.asarray(jax.vmap(lambda v: forest_predict(fa, v))(xt)), want, rtol=1e-5, atol=1e-6)
    npf = fa.numpy()
    np.testing.assert_allclose([forest_predict_numpy(npf, v) for v in xt], want, rtol=1e-5, atol=1e-6)
    with pytest.raises(ConfigError, match="max_depth: at most 14"):
        ForestOptions(max_depth=20)


def test_old_forest_format_is_refused_in_one_line():
    old = {"feature": np.zeros((2, 3)), "threshold": np.zeros((2, 3)), "left": np.zeros((2, 3)),
           "right": np.zeros((2, 3)), "value": np.zeros((2, 3)), "depth": np.asarray(1)}
    with pytest.raises(ForestFormatError, match="forest format version 1 .*retrain") as e:
        ForestArrays.from_numpy(old, "run/forest.npz")
    assert "\n" not in str(e.value)


# ---- the position run ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def position_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pos")
    cfg = run_config_from_dict({
        "name": "pos",
        "plots": False,
        "data": {"cache_dir": str(tmp / "data"), "protocol": {
            **{k: list(v) if isinstance(v, tuple) else v for k, v in FAST.items()},
            "repetitions": 1, "test_forces_per_velocity": 2, "test_captures_per_velocity": 1,
            "positions_m": [[0.09, -0.01], [0.19, 0.01]], "unseen_positions_m": [[0.14, 0.0]],
            "two_contacts_m": [[[0.09, 0.0], [0.21, 0.0]]]}},
        "features": {"variant": "derivative", "source": "inversion", "sensor": 0},
        "training": {"epochs": 3, "patience": 0},
        "forest": {"trees": 4, "max_depth": 4, "n_jobs": 1},
    })
    return train(cfg, tmp / "runs", log=None)


def test_position_run_reports_every_split(position_run):
    m = json.loads((position_run / "metrics.json").read_text())
    for k in ("mlp", "mlp_rf"):
        assert set(m["mae_n"][k]["by_split"]) == {"seen", "unseen", "two_contacts"}
        assert all(np.isfinite(v) for v in m["mae_n"][k]["by_split"].values())
    assert set(m["test_frames_by_split"]) == {"seen", "unseen", "two_contacts"}
    header = json.loads((position_run / "model.json").read_text())
    assert header["version"] == 2 and header["features"]["source"] == "inversion"


def test_a_run_with_an_old_forest_is_refused(position_run, tmp_path, capsys):
    from tofjax.cli import main

    run = tmp_path / "old"
    shutil.copytree(position_run, run)
    with np.load(run / "forest.npz") as z:
        d = {k: z[k] for k in z.files if k != "format_version"}
    np.savez(run / "forest.npz", **d)
    with pytest.raises(UserError, match="forest format version 1"):
        load_predictor(run)
    cap = simulate_session(Protocol().load_scene(), Protocol(distance_m=0.12, **FAST), [30.0], 5.0, 2)
    from tofjax.capture import write_capture

    write_capture(tmp_path / "c.h5", cap)
    capsys.readouterr()
    assert main(["predict", str(run), str(tmp_path / "c.h5"), "--out", str(tmp_path / "p.csv")]) != 0
    err = capsys.readouterr().err.strip()
    assert "forest format version 1" in err and "retrain" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "p.csv").exists()


def test_predict_gives_each_contact_its_force(position_run, scene):
    from tofjax.force.train import predict_capture

    p = Protocol(**FAST)
    cap = simulate_session(scene, p, [[20.0], [50.0]], 5.0, 4, split="two_contacts", positions=[(0.09, 0.0), (0.21, 0.0)])
    pred = predict_capture(position_run, cap)
    assert {"mlp", "mlp_rf", "force_contact2", "mlp_contact2", "mlp_rf_contact2"} <= set(pred)
    assert pred["force"].max() == pytest.approx(20.0, abs=0.3) and pred["force_contact2"].max() == pytest.approx(50.0, abs=0.3)
    assert pred["mlp_rf_contact2"].shape == pred["time"].shape


def test_longer_derivative_is_exact_for_quadratics_and_quieter():
    from tofjax.force.features import backward_derivative

    t = np.arange(40) * 0.1
    x = (2.0 * t**2 - 3.0 * t + 1.0)[:, None]
    for k in (3, 5, 9):
        d = backward_derivative(x, 0.1, k)
        np.testing.assert_allclose(d[k - 1 :, 0], 4.0 * t[k - 1 :] - 3.0, atol=1e-9)
        assert np.all(d[: k - 1] == 0)
    noise = np.random.default_rng(0).standard_normal((4000, 1))
    assert backward_derivative(noise, 0.1, 7)[6:].std() < 0.3 * backward_derivative(noise, 0.1, 3)[2:].std()
    with pytest.raises(ConfigError, match="derivative_frames"):
        FeatureConfig(derivative_frames=2)
