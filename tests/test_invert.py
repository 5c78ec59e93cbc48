"""Touch inversion: correction (Algorithm 1), maps (Eq. 8), detection, commands."""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from tofjax import load_scene
from tofjax.capture import write_capture
from tofjax.cli import main
from tofjax.invert import (
    CorrectionOptions,
    InversionError,
    InvertOptions,
    MapOptions,
    OpticalParams,
    build_corrector,
    build_inverter,
    build_map_operator,
    match,
)
from tofjax.invert.maps import dense_map_matrix
from tofjax.invert.synth import random_contacts, simulate_contacts
from tofjax.simulate import expected_counts, simulate

NEAR_FAR = np.array(
    [
        [[0.14, 0.07, 1.0]],  # ~7 cm from S0/S1... near
        [[0.09, 0.20, 1.0]],  # mid
        [[0.27, 0.27, 1.0]],  # far corner: ~36 cm from S0
        [[0.20, 0.25, 1.0]],
    ]
)


@pytest.fixture(scope="module")
def scene():
    return load_scene("optoskin")


@pytest.fixture(scope="module")
def baseline(scene):
    return expected_counts(scene.without_touches())


@pytest.fixture(scope="module")
def single_clean(scene):
    return simulate_contacts(scene, NEAR_FAR, noise=False)


@pytest.fixture(scope="module")
def single_noisy(scene):
    return simulate_contacts(scene, NEAR_FAR, seed=1)


def test_masks_zero_impossible_bins(scene, baseline):
    c = build_corrector(scene, baseline, options=CorrectionOptions(method="full"), dtype=jnp.float64)
    mask = np.asarray(c.mask)
    r = np.asarray(c.range_m)
    dr = 0.5 * OpticalParams.from_scene(scene).c1 * scene.sensor.bin_width_s
    assert not mask[r + 0.5 * dr <= 0].any()  # before the light enters
    assert not mask[r > 0.43 + 3 * dr].any()  # beyond the farthest edge of a 30 x 30 cm slab
    assert mask[(r > 0.02) & (r < 0.2)].all()  # where contacts can be
    # Zone-specific far edge: some zone's edge is much nearer than the diagonal.
    assert mask.sum(-1).min() < mask.sum(-1).max() - 5
    rng = np.random.default_rng(0)
    h = rng.uniform(0, 1e6, (3, *scene.shape))
    for m in ("raw", "decay", "baseline", "full"):
        cm = build_corrector(scene, baseline, options=CorrectionOptions(method=m), dtype=jnp.float64)
        out, ok = cm(h)
        assert ok.all()
        assert np.all(np.asarray(out)[:, ~mask] == 0.0)


def test_no_nan_or_inf_at_extremes(scene, baseline):
    paper = load_scene("optoskin-paper")  # mu_t = 74 /m: a gain of e^60 at the far edge before the cap
    for sc in (scene, paper):
        base = expected_counts(sc.without_touches())
        inv = build_inverter(sc, base, InvertOptions(maps=MapOptions(resolution_m=0.01)))
        c = inv.corrector
        assert np.isfinite(np.asarray(c.gain)).all()
        r0 = sc.waveguide.near_field
        assert float(np.max(np.asarray(c.gain) * np.asarray(sc.gains())[:, None, None])) <= 1e5 * r0**2 * (1 + 1e-5)
        frames = np.stack(
            [
                np.zeros(sc.shape),
                np.full(sc.shape, 1e9),  # above saturation: flagged
                np.full(sc.shape, sc.sensor.saturation_counts - 1),
                np.where(np.arange(sc.shape[-1]) == 50, np.nan, base),  # a NaN bin: flagged
                base,
            ]
        )
        maps, ok = inv.maps(frames)
        assert np.isfinite(maps).all()
        assert ok.tolist() == [True, False, True, False, True]
        assert np.all(maps[~ok] == 0)
        res = inv.process(frames)
        assert res.detections[1].touches == []


def test_single_contact_recovered_within_1cm_near_and_far(scene, single_noisy):
    base = simulate(scene.without_touches(), 30, 0)
    inv = build_inverter(scene, base.mean(), InvertOptions(method="full"), n_baseline=30)
    res = inv.process(single_noisy)
    for det, truth in zip(res.detections, NEAR_FAR):
        assert len(det.touches) >= 1
        best = det.touches[0]  # the strongest
        err = math.hypot(best["x_m"] - truth[0, 0], best["y_m"] - truth[0, 1])
        assert err < 0.01, (truth, det.touches)
        assert len(det.touches) == 1, det.touches


def test_decay_correction_makes_strength_distance_independent(scene, baseline, single_clean):
    full = build_corrector(scene, baseline, options=CorrectionOptions(method="full"), dtype=jnp.float64)
    only = build_corrector(scene, baseline, options=CorrectionOptions(method="baseline"), dtype=jnp.float64)
    sf = np.asarray(full(single_clean)[0]).clip(0).sum((-1, -2))  # (C, S): per sensor, over zones and bins
    sb = np.asarray(only(single_clean)[0]).clip(0).sum((-1, -2))
    # The sensor that sees each contact best (largest share of its angular width).
    ratio_full = sf.max(1).max() / sf.max(1).min()
    ratio_base = sb.max(1).max() / sb.max(1).min()
    assert ratio_base > 5.0  # baseline removal alone: near contacts dominate
    assert ratio_full < 1.5  # decay corrected: strength ~1 everywhere
    assert np.allclose(sf.max(1), 1.0, atol=0.3)


def test_sparse_map_equals_dense_reference(scene):
    rng = np.random.default_rng(1)
    for opts in (MapOptions(resolution_m=0.02), MapOptions(resolution_m=0.015, combine="sum", angular="zone")):
        op, grid = build_map_operator(scene, options=opts, dtype=jnp.float64)
        M = dense_map_matrix(op, int(np.prod(scene.shape)))
        h = rng.normal(size=(4, *scene.shape))
        ref = (np.maximum(h.reshape(4, -1), 0) @ M.T).reshape(4, grid.ny, grid.nx)
        np.testing.assert_allclose(np.asarray(op(h)), ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(op(h[2])), ref[2], rtol=1e-10, atol=1e-12)  # one frame, no batch axis
    # A pixel outside every field of view reads nothing; inside, weights sum to 1 (mean).
    op, grid = build_map_operator(scene, options=MapOptions(resolution_m=0.02), dtype=jnp.float64)
    w = np.asarray(op.weight).sum(-1)
    cov = np.asarray(op.coverage)
    assert np.allclose(w[cov > 0], 1.0) and np.all(w[cov == 0] == 0)


def test_multi_touch_full_beats_baseline(scene):
    C = random_contacts(scene, 6, 6, seed=3)
    H = simulate_contacts(scene, C, seed=4)
    base = simulate(scene.without_touches(), 30, 0).mean()
    recall = {}
    for m in ("baseline", "full"):
        res = build_inverter(scene, base, InvertOptions(method=m), n_baseline=30).process(H)
        recall[m] = sum(match(d.positions(), c[:, :2])[0] for d, c in zip(res.detections, C)) / C[..., 0].size
    assert recall["full"] >= 0.85
    assert recall["full"] > recall["baseline"] + 0.2


def test_calibration_json(scene, tmp_path):
    from tofjax.fit import scene_fingerprint

    cal = {
        "parameters": {"n1": {"value": 1.45, "stderr": 0.01}, "gain": {"value": [120.0] * 6, "stderr": [1.0] * 6}},
        "fixed": {"mu_s_per_m": 0.5, "mu_a_per_m": 0.1, "emission_time_s": 1.45e-9, "pulse_sigma_s": 6e-11, "pulse_tail_s": 1.5e-10},
        "converged": True,
        "scene_fingerprint": scene_fingerprint(scene),
    }
    p = tmp_path / "cal.json"
    p.write_text(json.dumps(cal))
    o = OpticalParams.from_calibration(p, scene)
    assert o.n1 == 1.45 and o.mu_s_per_m == 0.5 and o.gain == (120.0,) * 6
    assert o.mu_a_per_m == 0.1
    assert o.near_field_shape == 2.0  # a calibration without a near-field shape: seed 000's law
    shaped = dict(cal, parameters={**cal["parameters"], "near_field_shape": {"value": 5.5, "stderr": 0.1}})
    assert OpticalParams.from_calibration(shaped, scene).near_field_shape == 5.5
    bad = dict(cal, parameters={"n1": {"value": 1.45}, "gain": {"value": [1.0, 2.0]}})
    with pytest.raises(InversionError, match="2 values for 6 sensors"):
        OpticalParams.from_calibration(bad, scene)
    with pytest.raises(InversionError, match="not a calibration"):
        OpticalParams.from_calibration({"x": 1}, scene)
    with pytest.raises(InversionError, match="did not converge or was refused"):
        OpticalParams.from_calibration(dict(cal, converged=False), scene)
    with pytest.raises(InversionError, match="another scene"):
        OpticalParams.from_calibration(dict(cal, scene_fingerprint="x"), scene)
    with pytest.raises(InversionError, match="missing parameters: pulse_tail_s"):
        OpticalParams.from_calibration(dict(cal, fixed={k: v for k, v in cal["fixed"].items() if k != "pulse_tail_s"}), scene)


@pytest.fixture(scope="module")
def captures(tmp_path_factory, scene):
    d = tmp_path_factory.mktemp("inv")
    write_capture(d / "base.h5", simulate(scene.without_touches(), 10, 0))
    write_capture(d / "touch.h5", simulate(load_scene("configs/touch-three-line.toml"), 2, 1))
    write_capture(d / "soft.h5", simulate(load_scene("softskin"), 1, 0))
    return d


def test_detect_json_schema(captures, capsys):
    out = captures / "touches.json"
    rc = main(["detect", str(captures / "touch.h5"), "--baseline", str(captures / "base.h5"), "--json", str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    assert set(data) == {"frames"}
    assert [f["index"] for f in data["frames"]] == [0, 1]
    for f in data["frames"]:
        assert set(f) == {"index", "ok", "touches"} and f["ok"] is True  # "reason" only when not ok
        assert len(f["touches"]) >= 3
        for t in f["touches"]:
            assert set(t) == {"x_m", "y_m", "strength"}
            assert all(isinstance(v, float) and math.isfinite(v) for v in t.values())
        strongest = sorted(f["touches"], key=lambda t: -t["strength"])[:3]
        xs = sorted(t["x_m"] for t in strongest)
        assert np.allclose(xs, [0.08, 0.15, 0.22], atol=0.01) and all(abs(t["y_m"] - 0.15) < 0.01 for t in strongest)
    assert "no calibration given" in capsys.readouterr().err
    dyn = captures / "dyn.json"
    assert (
        main(
            [
                "detect",
                str(captures / "touch.h5"),
                "--baseline",
                str(captures / "base.h5"),
                "--json",
                str(dyn),
                "--dynamic-baseline",
            ]
        )
        == 0
    )
    assert [len(f["touches"]) >= 3 for f in json.loads(dyn.read_text())["frames"]] == [True, True]


def test_process_writes_maps(captures):
    import h5py

    out = captures / "maps.h5"
    rc = main(
        [
            "process",
            str(captures / "touch.h5"),
            "--baseline",
            str(captures / "base.h5"),
            "--out",
            str(out),
            "--png",
            str(captures / "png"),
            "--method",
            "baseline",
        ]
    )
    assert rc == 0
    with h5py.File(out) as f:
        assert f["maps"].shape == (2, 120, 120) and f.attrs["method"] == "baseline"
        assert f["ok"][:].all()
    assert (captures / "png" / "map_0001.png").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["detect", "{d}/soft.h5", "--baseline", "{d}/base.h5", "--json", "{d}/x.json"], "not the same setup"),
        (["detect", "{d}/touch.h5", "--baseline", "{d}/nope.h5", "--json", "{d}/x.json"], "no such file"),
        (
            [
                "process",
                "{d}/touch.h5",
                "--baseline",
                "{d}/base.h5",
                "--calibration",
                "{d}/touch.h5",
                "--out",
                "{d}/m.h5",
            ],
            "not valid JSON",
        ),
    ],
)
def test_cli_errors_are_one_line(captures, capsys, args, message):
    rc = main([a.format(d=captures) for a in args])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len([e for e in err if "warning" not in e]) == 1 and message in err[-1]


def test_different_scene_same_shape_is_an_error(scene):
    from tofjax.invert.correction import check_compatible

    other = scene.replace(waveguide=scene.waveguide.__class__(**{**scene.waveguide.__dict__, "n1": 1.5}))
    with pytest.raises(InversionError, match="different scenes"):
        check_compatible(other, scene)


def test_simulate_contacts_on_a_guide_smaller_than_15_cm():
    """The vmapped simulator's prototype contacts sit inside any guide (they were hard-coded at
    (0.15, 0.15) m, outside a 10 cm guide), and its frames equal the one-scene simulator's (the emission on
    a node edge: test_model.py::test_continuous_where_the_emission_sits_on_a_node_edge)."""
    from tofjax.scene import Touch, scene_from_dict

    sc = scene_from_dict({
        "waveguide": {"size_m": [0.1, 0.08], "thickness_m": 0.004, "n1": 1.4, "mu_s_per_m": 0.5, "mu_a_per_m": 0.1},
        "sensor": {"bin_width_s": 1e-10, "n_bins": 24, "zones": 3, "fov_deg": 30.0, "emission_time_s": 1e-10},
        "sensors": [{"position_m": [0.0, 0.04], "direction_deg": 0.0}],
    })
    c = np.array([[[0.06, 0.045, 1.0]]])
    got = simulate_contacts(sc, c, noise=False)[0]
    want = expected_counts(sc.replace(touches=(Touch((0.06, 0.045), 0.006, 1.0),)))
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * want.max())  # float32 model
    with pytest.raises(ValueError, match="configurations, contacts, 3"):
        simulate_contacts(sc, c[0])


def test_decay_gain_is_the_models_falloff_and_transmittance(scene, baseline):
    """The correction's gain is 1/(K G T) with the forward model's own G (its near-field shape p) and
    T, to 1e-12, for a calibrated p far from 2 (bins below the cap, inside the mask)."""
    import dataclasses

    from tofjax.invert.correction import bin_ranges
    from tofjax.model.components import falloff, transmittance

    for p in (1.0, 9.0):
        opt = dataclasses.replace(OpticalParams.from_scene(scene), near_field_shape=p, mu_a_per_m=3.0)
        c = build_corrector(scene, baseline, opt, CorrectionOptions(gain_cap=1e300), dtype=jnp.float64)
        r = np.maximum(bin_ranges(scene, opt), 0.0)
        K = np.asarray(opt.gain)[:, None, None]
        want = 1.0 / (K * np.asarray(falloff(r, opt.near_field_m, p) * transmittance(r, opt.mu_s_per_m + opt.mu_a_per_m)))
        m = np.asarray(c.mask)
        np.testing.assert_allclose(np.asarray(c.gain)[m], np.broadcast_to(want, m.shape)[m], rtol=1e-12)
    # the cap is still relative to zero range, 1/G(0) = d^2 for every shape
    capped = build_corrector(scene, baseline, dataclasses.replace(opt, mu_a_per_m=40.0), CorrectionOptions(gain_cap=10.0))
    top = np.exp(np.asarray(capped.log_gain, float).max() + np.log(np.asarray(opt.gain)).min())
    assert top == pytest.approx(10.0 * opt.near_field_m**2, rel=1e-5)


def test_decay_correction_uses_the_calibrated_near_field_shape(scene):
    """A rig whose near field has the shape p = 8 (G flatter out to d): the corrected signal of a
    contact near a sensor comes out as it does on a p = 2 rig only when the correction uses p = 8."""
    import dataclasses

    from tofjax.model import Params
    from tofjax.scene import Touch

    sc = scene.replace(waveguide=dataclasses.replace(scene.waveguide, near_field_m=0.02))
    base = sc.without_touches()
    a = math.radians(sc.sensors[0].direction_deg)
    x0, y0 = sc.sensors[0].position_m
    touch = base.replace(touches=(Touch((x0 + 0.05 * math.cos(a), y0 + 0.05 * math.sin(a)), 0.006, 1.0),))

    def corrected(p_rig, p_corr):
        b = expected_counts(base, params=Params.from_scene(base).replace(near_field_shape=p_rig))
        h = expected_counts(touch, params=Params.from_scene(touch).replace(near_field_shape=p_rig))
        opt = dataclasses.replace(OpticalParams.from_scene(sc), near_field_shape=p_corr)
        return float(np.asarray(build_corrector(sc, b, opt, dtype=jnp.float64)(h)[0])[0].clip(0).sum())

    ref = corrected(2.0, 2.0)
    with_shape, without = corrected(8.0, 8.0), corrected(8.0, 2.0)
    assert without > 1.1 * ref  # p = 2's G is too small near the sensor: too much gain
    assert abs(with_shape - ref) < 0.4 * abs(without - ref)
