"""Force estimation (seed 001): generator protocol, features, forest in JAX, training, runs, CLI."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tofjax.capture import read_capture, write_capture
from tofjax.config import ConfigError
from tofjax.force.features import (
    FeatureConfig,
    FeatureError,
    Scaling,
    backward_derivative,
    build_dataset,
    find_window,
    split_indices,
)
from tofjax.force.forest import ForestOptions, fit_forest, forest_predict, forest_to_arrays
from tofjax.force.generate import (
    Protocol,
    align_force,
    contact_radius,
    generate,
    indentation_force,
    lag,
    simulate_session,
    touch_strength,
)
from tofjax.force.models import TrainOptions, build_mlp, mlp_spec, operations, train_mlp
from tofjax.force.train import load_run_config, predict_capture, run_config_from_dict, table, train

# A short protocol: seconds to simulate, a few hundred frames.
SMALL = dict(
    velocities_mm_s=[1.0, 5.0],
    train_forces_n=[10.0, 30.0, 50.0],
    repetitions=2,
    test_forces_per_velocity=2,
    test_captures_per_velocity=1,
    hold_s=2.0,
    rest_s=1.0,
    baseline_s=1.0,
)


@pytest.fixture(scope="module")
def small_data(tmp_path_factory):
    d = tmp_path_factory.mktemp("force-data")
    p = Protocol(**{k: tuple(v) if isinstance(v, list) else v for k, v in SMALL.items()})
    paths = generate(p, d)
    return p, paths


# ---- generator -----------------------------------------------------------------------------


def test_indentation_force_follows_protocol():
    p = Protocol()
    rng = np.random.default_rng(0)
    for v in p.velocities_mm_s:
        t, f, seg = indentation_force([20.0, 50.0], v, p, rng)
        assert np.allclose(np.diff(t), 1 / p.force_rate_hz)
        assert f.max() == pytest.approx(50.0)
        for j, target in enumerate([20.0, 50.0]):
            fj = f[seg == j]
            # The hold: exactly hold_s at the target force.
            assert np.sum(fj == target) / p.force_rate_hz == pytest.approx(p.hold_s, abs=0.02)
            # Loading at the robot's velocity: depth (F/k)^(2/3) reached in depth / v seconds.
            ramp = np.sum((fj > 0) & (fj < target)) / 2 / p.force_rate_hz
            depth = (target / p.stiffness_n_per_mm1p5) ** (2 / 3)
            assert ramp == pytest.approx(depth / v, abs=0.02)
        assert np.all(f[seg == -1] == 0) and np.sum(seg == -1) / p.force_rate_hz == pytest.approx(p.baseline_s)


def test_lag_is_first_order():
    dt, tau = 0.01, 0.5
    y = lag(np.ones(200), dt, tau)
    t = np.arange(1, 201) * dt
    np.testing.assert_allclose(y, 1 - np.exp(-t / tau), rtol=1e-6)


def test_align_force_averages_the_exposure_window():
    t = np.arange(0, 2, 0.01)
    f = 3.0 * t  # a ramp: the mean of the ten samples in (t - 0.1, t] is 3 (t - 0.05) (frames between samples)
    frames = np.array([0.505, 1.005, 1.505])
    np.testing.assert_allclose(align_force(t, f, frames, 0.1), 3 * (frames - 0.005 - 0.045), atol=1e-9)


def test_force_to_signal_saturates_and_contact_grows():
    p = Protocol()
    s = touch_strength(np.array([0.0, 15, 30, 45, 60]), p)
    assert s[0] == 0 and np.all(np.diff(s) > 0) and np.all(np.diff(s, 2) < 0)  # increasing, concave
    r = contact_radius(np.array([1.0, 10, 60, 1e4]), p)
    assert np.all(np.diff(r) >= 0) and r[-1] == p.indenter_radius_m


def test_session_capture_is_aligned_and_lagged():
    p = Protocol(velocities_mm_s=(5.0,), hold_s=2.0, rest_s=2.0, baseline_s=1.0, ambient_counts_range=(20.0, 20.0))
    scene = p.load_scene()
    cap = simulate_session(scene, p, [40.0], 5.0, seed=3)
    assert cap.force is not None and cap.force.shape == (cap.n_frames,)
    assert np.allclose(np.diff(cap.timestamps), 1 / 9)
    assert cap.force.max() == pytest.approx(40, abs=0.3)
    assert cap.truth["velocity_mm_s"] == 5.0 and cap.truth["baseline_frames"] == 9
    # The optical signal (touch strength) trails the force: at the frame where loading ends
    # the strength is still well below its value at the end of the hold.
    s = cap.truth_touches[:, 0, 2]
    first_full = np.argmax(cap.force > 39.5)
    assert s[first_full] < 0.9 * s[first_full + 15]
    # The contact shows in the histograms of the sensor it is in front of.
    base = cap.histograms[:9].mean(0)
    delta = cap.histograms[first_full + 15] - base
    assert delta[p.sensor].sum() > 1000


def test_generated_protocol_files(small_data):
    p, paths = small_data
    assert len(paths["train"]) == 2 * 2 and len(paths["test"]) == 2
    cap = read_capture(paths["train"][0])
    peaks = sorted(cap.truth["target_forces_n"])
    assert peaks == [10.0, 30.0, 50.0]
    test = read_capture(paths["test"][0])
    assert not set(test.truth["target_forces_n"]) & set(p.train_forces_n)


# ---- features ------------------------------------------------------------------------------


def test_derivative_is_exact_on_a_quadratic():
    t = np.arange(10) * 0.1
    x = (2.0 * t**2 - 3.0 * t + 1.0)[:, None]
    d = backward_derivative(x, 0.1)
    np.testing.assert_allclose(d[2:, 0], 4.0 * t[2:] - 3.0, atol=1e-12)
    assert np.all(d[:2] == 0)


def test_window_is_found_where_the_contact_is(small_data):
    p, paths = small_data
    caps = [read_capture(x) for x in paths["train"]]
    w = find_window(caps, FeatureConfig(variant="single"))
    # Bins of the contact: the round trip to 150 mm (no emission delay in SoftSkin).
    c1 = 299_792_458.0 / 1.398
    expected = 2 * p.distance_m / c1 / 1e-10
    # every bin of the contact's return follows the force almost perfectly (|correlation| summed
    # over the zones 1.9-2.1 in bins 12-20), so the photon noise picks among neighbouring starts
    assert expected - 2 <= w.start_bin <= expected + 2
    # Sensors A and C are both 150 mm from the contact; B and D see it off-axis.
    assert w.sensor in (0, 2)
    # Moving the contact moves the window.
    far = simulate_session(p.load_scene(), Protocol(distance_m=0.25, hold_s=2.0, baseline_s=1.0), [30.0, 50.0], 5.0, 1)
    w_far = find_window([far], FeatureConfig(variant="single", sensor=p.sensor))
    assert w_far.start_bin > w.start_bin + 5


def test_scaling_is_fitted_on_training_rows_only(small_data):
    _, paths = small_data
    caps = [read_capture(x) for x in paths["train"]]
    cfg = FeatureConfig(variant="dual")
    w = find_window(caps, cfg)
    ds = build_dataset(caps, w, cfg)
    tr, va, ho = split_indices(len(ds), (0.8, 0.1, 0.1), seed=1)
    assert len(set(tr) | set(va) | set(ho)) == len(ds) and abs(len(tr) / len(ds) - 0.8) < 0.01
    raw = ds.raw.copy()
    raw[va[0], 0] = 1e9  # an outlier outside the training rows
    sc = Scaling.fit(raw[tr][:, : w.size], ds.force[tr], "global")
    assert sc.hi[0] < 1e9 and sc.hi[0] == raw[tr][:, : w.size].max()
    assert sc.force_hi == ds.force[tr].max()


def test_nan_frames_are_dropped_and_counted(small_data):
    _, paths = small_data
    cap = read_capture(paths["train"][0])
    cap.histograms[20] = np.nan
    cfg = FeatureConfig(variant="derivative")
    w = find_window([cap], cfg)
    ds = build_dataset([cap], w, cfg)
    assert ds.n_nan_frames == 1 and ds.n_dropped == 3  # the frame and the two whose Eq. 6 uses it
    assert np.isfinite(ds.raw).all() and len(ds) == cap.n_frames - 3


# ---- the forest in JAX ---------------------------------------------------------------------


def test_jax_forest_equals_sklearn():
    rng = np.random.default_rng(0)
    x = rng.uniform(size=(600, 7))
    y = np.sin(4 * x[:, 0]) + x[:, 1] * x[:, 2] + 0.05 * rng.standard_normal(600)
    rf = fit_forest(x, y, ForestOptions(trees=15, max_depth=12, min_samples_leaf=1, n_jobs=1), seed=0)
    arrays = forest_to_arrays(rf)
    # Unseen points, and the training points themselves (on thresholds' neighbours).
    xt = np.concatenate([rng.uniform(size=(300, 7)), x[:100]]).astype(np.float32)
    ours = np.asarray(jax.jit(jax.vmap(lambda v: forest_predict(arrays, v)))(xt))
    np.testing.assert_allclose(ours, rf.predict(xt), rtol=1e-5, atol=1e-6)


# ---- models and training -------------------------------------------------------------------


def test_architectures_match_seed_001():
    s = mlp_spec("mlp", "single", 20)
    m = build_mlp(s, jax.random.key(0))
    assert (m.d_layer.in_features, m.d_layer.out_features, m.layers[0].out_features) == (20, 64, 32)
    d = build_mlp(mlp_spec("mlp", "dual", 20), jax.random.key(0))
    assert (d.d_layer.out_features, d.b_layer.out_features, d.layers[0].in_features) == (32, 32, 64)
    e = build_mlp(mlp_spec("mlp", "derivative", 20), jax.random.key(0))
    assert (e.d_layer.in_features, e.d_layer.out_features, e.b_layer.in_features) == (40, 64, 20)
    assert eqx.filter_jit(m)(jnp.ones(20)).shape == () and eqx.filter_jit(e)(jnp.ones(60)).shape == ()
    # Operations per prediction: seed 001 counts ~6.7k for the MLP; ours counts multiplies and adds.
    assert 2 * (20 * 64 + 64 * 32 + 32) < operations(s) < 8000
    # Dropout is active with a key, off without one.
    x = jnp.ones(20)
    f = eqx.filter_jit(m)
    assert f(x) == f(x) and f(x, jax.random.key(1)) != f(x)


def test_training_lowers_validation_loss_and_keeps_the_best():
    rng = np.random.default_rng(0)
    x = rng.uniform(size=(512, 20)).astype(np.float32)
    y = (0.5 * x[:, :5].mean(1) + 0.3 * x[:, 5] ** 2).astype(np.float32)
    model = build_mlp(mlp_spec("mlp", "single", 20, dropout=0.0), jax.random.key(0))
    rows = []
    # A too-high constant learning rate makes validation loss bounce: the best epoch is kept.
    res = train_mlp(model, x[:400], y[:400], x[400:], y[400:], TrainOptions(epochs=30, batch_size=32,
                    learning_rate=3e-3, schedule="constant", patience=5), key=jax.random.key(1), on_epoch=rows.append)
    val = [r["val_loss"] for r in rows]
    assert val[-1] < val[0] / 3
    assert res.best_val_loss == min(val) and res.best_epoch == int(np.argmin(val)) + 1
    got = float(jnp.mean((jax.vmap(res.model)(jnp.asarray(x[400:])) - y[400:]) ** 2))
    assert got == pytest.approx(min(val), rel=1e-4)
    assert res.epochs_run == len(rows) and (res.epochs_run == 30 or res.epochs_run - res.best_epoch == 5)


# ---- configs and runs ----------------------------------------------------------------------


def _cfg(tmp, data_paths, **over):
    d = {
        "name": "t",
        "data": {"train": [str(x) for x in data_paths["train"]], "test": [str(x) for x in data_paths["test"]]},
        "features": {"variant": "derivative"},
        "training": {"epochs": 8, "patience": 0, "batch_size": 32},
        "forest": {"trees": 10, "max_depth": 8, "n_jobs": 1},
    }
    for k, v in over.items():
        d[k] = v
    return run_config_from_dict(d)


@pytest.fixture(scope="module")
def mlp_run(small_data, tmp_path_factory):
    _, paths = small_data
    tmp = tmp_path_factory.mktemp("runs")
    return train(_cfg(tmp, paths), tmp / "runs", log=None)


def test_run_folder_and_metrics_schema(small_data, mlp_run, tmp_path):
    _, paths = small_data
    run = mlp_run
    names = {p.name for p in run.iterdir()}
    assert {"config.toml", "config.json", "meta.json", "metrics.csv", "metrics.json", "model.eqx", "model.json",
            "forest.npz", "predictions.csv", "fig15_mlp_vs_mlp_rf.png", "fig16_by_velocity.png"} <= names
    m = json.loads((run / "metrics.json").read_text())
    assert set(m["mae_n"]) == {"mlp", "mlp_rf"}
    for k in ("mlp", "mlp_rf"):
        assert set(m["mae_n"][k]) == {"overall", "by_velocity_mm_s", "by_split"}
        assert set(m["mae_n"][k]["by_split"]) == {"seen"}
        assert set(m["mae_n"][k]["by_velocity_mm_s"]) == {"1.0", "5.0"}
        assert np.isfinite(m["mae_n"][k]["overall"])
    assert m["operations_per_prediction"]["mlp_rf"] > m["operations_per_prediction"]["mlp"]
    meta = json.loads((run / "meta.json").read_text())
    assert meta["seed"] == 0 and meta["precision"] == "float32" and "jax" in meta["versions"]
    assert len((run / "metrics.csv").read_text().splitlines()) == 1 + 8
    # The resolved config reads back as the same config.
    assert load_run_config(run / "config.toml") == _cfg(tmp_path, paths)
    # The model file starts with a JSON header line.
    with open(run / "model.eqx", "rb") as f:
        assert json.loads(f.readline())["format"] == "tofjax.force.model"
    assert "mlp_rf" in table([run])

    # Predict round trip: a saved run predicts a capture as the run's own test predictions did.
    pred = predict_capture(run, paths["test"][0])
    csv_rows = (run / "predictions.csv").read_text().splitlines()[1:]
    first = [r.split(",") for r in csv_rows if r.startswith(paths["test"][0].name)]
    got = pred["mlp_rf"][np.isfinite(pred["mlp_rf"])]
    np.testing.assert_allclose(got[: len(first)], [float(r[-1]) for r in first], atol=2e-3)

    # A recorded capture without the generator's truth needs its baseline length.
    rec = read_capture(paths["test"][0])
    rec.truth = {}
    with pytest.raises(FeatureError, match="baseline-frames"):
        predict_capture(run, rec)
    np.testing.assert_allclose(predict_capture(run, rec, baseline_frames=9)["mlp_rf"], pred["mlp_rf"])

    # A capture of another sensor layout: a clear error.
    cap = read_capture(paths["test"][0])
    bad = cap.scene.replace(sensor=cap.scene.sensor.__class__(**{**cap.scene.sensor.__dict__, "n_bins": 64}))
    cap.histograms = cap.histograms[..., :64]
    cap.scene = bad
    write_capture(tmp_path / "bad.h5", cap)
    with pytest.raises(FeatureError, match="model was trained on"):
        predict_capture(run, tmp_path / "bad.h5")


def test_alternative_run(small_data, tmp_path):
    _, paths = small_data
    kind = "nonlinear"
    run = train(_cfg(tmp_path, paths, model={"kind": kind}, features={"variant": "single"}, plots=False),
                tmp_path, log=None)
    m = json.loads((run / "metrics.json").read_text())
    assert list(m["mae_n"]) == [kind] and m["mae_n"][kind]["overall"] < 15
    assert np.isfinite(predict_capture(run, paths["test"][0])[kind]).any()


@pytest.mark.parametrize("kind", ["svr", "gb"])
def test_alternatives_fit_and_count_operations(kind):
    from tofjax.force.alternatives import GBOptions, SVROptions, fit_alternative

    rng = np.random.default_rng(0)
    x = rng.uniform(size=(300, 4))
    y = x[:, 0] ** 2 + 0.5 * x[:, 1]
    opts = GBOptions(iterations=20, max_leaf_nodes=4) if kind == "gb" else SVROptions(max_train_samples=200)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):  # OpenMP threads on a busy 2-core machine only wait for each other
        est, ops = fit_alternative(kind, opts, x[:250], y[:250], x[250:], y[250:])
    assert np.mean(np.abs(est.predict(x[250:]) - y[250:])) < 0.1
    if kind == "svr":
        assert len(est.support_) <= 200 and ops == len(est.support_) * (3 * 4 + 12)
    else:
        assert 20 <= ops <= 20 * 4


def test_bad_configs_name_the_keys(tmp_path):
    with pytest.raises(ConfigError, match="epochz: unknown key"):
        run_config_from_dict({"name": "x", "training": {"epochz": 3}})
    with pytest.raises(ConfigError, match="training.batch_size: expected an integer"):
        run_config_from_dict({"name": "x", "training": {"batch_size": "big"}})
    with pytest.raises(ConfigError, match="variant"):
        run_config_from_dict({"name": "x", "features": {"variant": "triple"}})
    with pytest.raises(ConfigError, match="svr: options for kind"):
        run_config_from_dict({"name": "x", "model": {"kind": "mlp", "svr": {"c": 1.0}}})
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[forest]\ntrees = 1.5\n')
    with pytest.raises(ConfigError, match="bad.toml: forest.trees"):
        load_run_config(bad)


def test_shipped_configs_load():
    from pathlib import Path

    root = Path(__file__).parents[1] / "configs" / "force"
    names = {p.stem for p in root.glob("*.toml")}
    assert {"mlp_single", "mlp_dual", "mlp_derivative", "nonlinear", "svr", "deep_mlp", "gradient_boosting"} <= names
    for p in root.glob("*.toml"):
        load_run_config(p)


def test_cli_train_predict_table(small_data, mlp_run, tmp_path, capsys):
    from tofjax.cli import main

    _, paths = small_data
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        'name = "cli"\nplots = false\n[data]\n'
        f"train = {json.dumps([str(x) for x in paths['train']])}\ntest = {json.dumps([str(x) for x in paths['test']])}\n"
        '[features]\nvariant = "single"\n[training]\nepochs = 2\n[forest]\ntrees = 3\nmax_depth = 4\n'
    )
    assert main(["train", str(cfg), "--runs", str(tmp_path / "runs"), "--quiet"]) == 0
    (run,) = list((tmp_path / "runs").iterdir())
    assert json.loads((run / "metrics.json").read_text())["variant"] == "single"
    assert main(["predict", str(mlp_run), str(paths["test"][0]), "--out", str(tmp_path / "p.csv")]) == 0
    assert (tmp_path / "p.csv").read_text().startswith("time_s,force_n,mlp_n,mlp_rf_n")
    assert main(["table", str(tmp_path / "runs"), str(mlp_run)]) == 0
    assert "overall" in capsys.readouterr().out
    assert main(["predict", str(tmp_path), str(paths["test"][0]), "--out", str(tmp_path / "q.csv")]) == 2
    assert "not a force run" in capsys.readouterr().err
    cfg.write_text('name = "x"\n[training]\nepochz = 3\n')
    assert main(["train", str(cfg)]) == 2
    assert "epochz: unknown key" in capsys.readouterr().err


def test_a_test_capture_that_is_also_a_training_capture_is_refused(tmp_path):
    """Training on the test set makes its MAE measure memory: a capture named in both lists (by another
    path to the same file, or through a glob) is refused before anything is read."""
    from tofjax.force.train import DataConfig, load_data

    for name in ("a.h5", "b.h5"):
        (tmp_path / name).write_bytes(b"not read")
    same = DataConfig(train=(str(tmp_path / "*.h5"),), test=(str(tmp_path / "sub" / ".." / "b.h5"),))
    (tmp_path / "sub").mkdir()
    with pytest.raises(ConfigError, match=r"data.test: .*b.h5 is also in data.train"):
        load_data(same)
