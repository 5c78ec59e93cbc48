"""The greedy contact fit (``method="fit"``, tofjax/invert/greedy.py).

The fast tests give the detector a stand-in forward model (a contact that removes light from the
far-edge return and the volume light before it, by geometry; differentiable jnp, so no compilation of
the guided model); the slow one uses the guided model itself on a small scene.
"""

import dataclasses
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tofjax.config import ConfigError
from tofjax.invert import match
from tofjax.invert.correction import InversionError, OpticalParams
from tofjax.invert.greedy import FitDetectOptions, build_fit_detector

from small_scenes import BINS, EDGE_BIN
from small_scenes import three_sensor_square as _small_scene


def _stand_in_change(scene, K, smooth=False):
    """theta (3K,) -> change (S*Z*B,): each contact removes light in the zones that see it (triangular
    share between zone centres; ``smooth``: a Gaussian share, no kinks) from its range bin up to the far edge,
    and from the far-edge return."""
    pos = jnp.asarray([sp.position_m for sp in scene.sensors])
    dirs = jnp.asarray([sp.direction_deg for sp in scene.sensors])
    half = scene.sensor.fov_deg / 2
    width = scene.sensor.fov_deg / scene.sensor.zones
    zc = (jnp.arange(scene.sensor.zones) + 0.5) * width - half
    b = jnp.arange(BINS)
    to_bins = 2 * scene.waveguide.n1 / 2.998e8 / scene.sensor.bin_width_s

    def change(theta):
        x, y, s = theta[:K], theta[K : 2 * K], theta[2 * K :]
        dx, dy = x[None] - pos[:, 0, None], y[None] - pos[:, 1, None]  # (S, K)
        off = (jnp.degrees(jnp.arctan2(dy, dx)) - dirs[:, None] + 180.0) % 360.0 - 180.0
        if smooth:
            share = jnp.exp(-0.5 * ((off[:, None, :] - zc[None, :, None]) / (0.6 * width)) ** 2)  # (S, Z, K)
        else:
            share = jnp.clip(1.0 - jnp.abs(off[:, None, :] - zc[None, :, None]) / width, 0.0, 1.0)
        rb = jnp.sqrt(dx**2 + dy**2) * to_bins  # (S, K)
        behind = 1 / (1 + jnp.exp(-(b[None, :, None] - rb[:, None, :]) / 0.7)) * (b < EDGE_BIN)[None, :, None]
        lost = 150.0 * jnp.exp(-0.5 * ((b - EDGE_BIN) / 1.5) ** 2)[None, :, None] + 15.0 * behind  # (S, B, K)
        return -jnp.einsum("szk,sbk,k->szb", share, lost, s).ravel()

    return change


def _patch_stand_in(monkeypatch, smooth=False):
    import tofjax.invert.greedy as greedy
    import tofjax.invert.reconstruct as rec

    sc = _small_scene()

    def fake_change(scene, optical, K, radius_m):
        return _stand_in_change(scene, K, smooth), jnp.float64

    def fake_response(scene, optical, centres, radius_m, chunk=128, *, shadow=False, signed=False):
        one = jax.vmap(_stand_in_change(scene, 1, smooth))
        c = np.asarray(centres, float)
        return np.asarray(one(jnp.asarray(np.c_[c, np.ones(len(c))]))).reshape(len(c), *scene.shape)

    monkeypatch.setattr(greedy, "_contact_change", fake_change)
    monkeypatch.setattr(rec, "response_matrix", fake_response)
    base = np.broadcast_to(20.0 + 600.0 * np.exp(-0.5 * ((np.arange(BINS) - EDGE_BIN) / 1.5) ** 2), sc.shape).copy()
    optical = dataclasses.replace(OpticalParams.from_scene(sc), optics="guided")
    return sc, base, optical


@pytest.fixture()
def stand_in(monkeypatch):
    return _patch_stand_in(monkeypatch)


@pytest.fixture()
def smooth_stand_in(monkeypatch):
    return _patch_stand_in(monkeypatch, smooth=True)


def test_fast_two_contacts_found_within_1cm_none_without_touch(stand_in):
    sc, base, optical = stand_in
    truth = np.array([[0.06, 0.10, 0.9], [0.11, 0.05, 0.7]])
    K = 3
    theta = np.zeros(3 * K)
    theta[:2], theta[K : K + 2], theta[2 * K : 2 * K + 2] = truth.T
    touch = base + np.asarray(_stand_in_change(sc, K)(jnp.asarray(theta))).reshape(sc.shape)
    rng = np.random.default_rng(0)
    frames = rng.poisson(np.stack([touch, base])).astype(float)
    opts = FitDetectOptions(cell_m=0.01, max_contacts=K, iterations=4, relocate_candidates=2)
    det = build_fit_detector(sc, base, optical, opts, n_baseline=100)
    res = det.process(frames)
    pos = res.detections[0].positions()
    assert len(pos) == 2, res.detections[0].touches
    assert match(pos, truth[:, :2], 0.01)[0] == 2, (pos, truth)
    assert res.detections[1].touches == []
    # the fit reaches the optimum: its chi-square is no worse than the truth's refitted (the stand-in leaves
    # the two strengths nearly degenerate, so they are not compared)
    y = (frames[0].ravel() - det.base) / det.sigma
    assert res.chi2[0] <= det._refit(theta, np.arange(2), y)[1] + 1.0


def test_fast_threshold_is_in_noise_units(stand_in):
    """A contact of evidence 12 noise sd is found with n_sigma 9, not with 15, at any noise level (the
    stand-in's contact has a fixed amplitude: the baseline's counts, and so the noise, change)."""
    sc, base, optical = stand_in
    one = _stand_in_change(sc, 1)
    opts = FitDetectOptions(cell_m=0.02, max_contacts=1, iterations=3, overdispersion=False, relocate=False,
                            rebirth=False)
    for scale in (1.0, 0.25):
        b = base * scale
        resp = np.asarray(one(jnp.asarray([0.07, 0.08, 1.0]))).reshape(sc.shape)
        z = np.sqrt(np.sum(resp**2 / b))  # the strength-1 contact's evidence in noise sd
        frame = b + (12.0 / z) * resp  # noise-free: its chi-square drop is 144
        det = build_fit_detector(sc, b, optical, opts, n_baseline=10**9)
        found = [len(det.with_options(dataclasses.replace(opts, n_sigma=n, n_sigma_forward=n)).process(
            frame[None]).detections[0].touches) for n in (9.0, 15.0)]
        assert found == [1, 0], (scale, found)
        # the search once, pruned at both thresholds: the same answer
        levels = det.with_options(dataclasses.replace(opts, n_sigma_forward=9.0)).process_levels(frame[None], (9.0, 15.0))
        assert [len(r.detections[0].touches) for r in levels] == [1, 0], scale
    with pytest.raises(ConfigError, match="cell_m"):
        det.with_options(dataclasses.replace(opts, cell_m=0.01))


def test_fast_contact_beyond_the_strength_cap(stand_in):
    """A contact twice as strong as the strength cap allows is fitted as duplicates at the cap (ghosts) with
    ``max_strength`` 1, as one contact at about its strength with ``max_strength`` 2.5."""
    sc, base, optical = stand_in
    base = base + 40.0  # room for the strong contact's removed light
    one = _stand_in_change(sc, 1)
    truth = np.array([[0.06, 0.10, 2.0], [0.11, 0.05, 0.7]])
    signal = sum(np.asarray(one(jnp.asarray(c))).reshape(sc.shape) for c in truth)
    frame = np.random.default_rng(0).poisson(base + signal).astype(float)
    opts = FitDetectOptions(cell_m=0.01, max_contacts=3, iterations=4, relocate_candidates=2)
    det = build_fit_detector(sc, base, optical, opts, n_baseline=10**9)
    capped = det.process(frame[None]).detections[0]
    assert len(capped.touches) == 3 and max(t["strength"] for t in capped.touches) == 1.0, capped.touches
    free = det.with_options(dataclasses.replace(opts, max_strength=2.5)).process(frame[None]).detections[0]
    pos = free.positions()
    assert len(pos) == 2 and match(pos, truth[:, :2], 0.01)[0] == 2, free.touches
    strong = max(t["strength"] for t in free.touches)
    assert 1.7 < strong < 2.3, free.touches


def test_fast_pruning_variants_share_one_search(stand_in):
    """process_variants gives what process gives for each variant of the pruning's options, and refuses
    variants that change the search (naming the options)."""
    sc, base, optical = stand_in
    one = _stand_in_change(sc, 1)
    frame = np.random.default_rng(1).poisson(
        base + np.asarray(one(jnp.asarray([0.07, 0.09, 0.8]))).reshape(sc.shape)).astype(float)
    opts = FitDetectOptions(cell_m=0.02, max_contacts=2, iterations=3, relocate_candidates=2)
    det = build_fit_detector(sc, base, optical, opts, n_baseline=100)
    variants = [opts, dataclasses.replace(opts, model_error=0.05), dataclasses.replace(opts, n_sigma=40.0)]
    together = det.process_variants(frame[None], variants)
    for v, r in zip(variants, together):
        alone = det.with_options(v).process(frame[None])
        assert r.detections[0].touches == alone.detections[0].touches
        np.testing.assert_allclose(r.chi2, alone.chi2, rtol=1e-12)
    assert len(together[0].detections[0].touches) == 1 and together[2].detections[0].touches == []
    with pytest.raises(ConfigError, match="iterations, max_strength change the search"):
        det.process_variants(frame[None], [dataclasses.replace(opts, iterations=4, max_strength=2.0)])
    for bad in ({"model_error": -0.1}, {"max_strength": 0.0}, {"model_error": float("nan")}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            FitDetectOptions(**bad)


def test_fast_contact_standard_errors_match_the_scatter(smooth_stand_in):
    """Each contact's standard errors (Laplace, at the fit) agree with the scatter of the fitted position and
    strength over noise draws (a stand-in without kinks), and are reported in the JSON."""
    sc, base, optical = smooth_stand_in
    truth = np.array([0.05, 0.08, 0.8])
    sig = np.asarray(_stand_in_change(sc, 1, smooth=True)(jnp.asarray(truth))).reshape(sc.shape)
    frames = np.random.default_rng(2).poisson(base + sig, size=(40, *sc.shape)).astype(float)
    # the stand-in is the data's model: no model error to count as noise
    opts = FitDetectOptions(cell_m=0.01, max_contacts=1, iterations=6, relocate=False, rebirth=False, split=False,
                            model_error=0.0)
    res = build_fit_detector(sc, base, optical, opts, n_baseline=10**6).process(frames)
    t = [d.touches[0] for d in res.detections if len(d.touches) == 1]
    assert len(t) >= 38
    for k, i in (("x_m", 0), ("y_m", 1), ("strength", 2)):
        vals = np.array([u[k] for u in t])
        err = np.median([u[k.replace("_m", "") + ("_stderr_m" if k.endswith("_m") else "_stderr")] for u in t])
        assert abs(np.mean(vals) - truth[i]) < 4 * err / np.sqrt(len(t)) + 1e-3, k
        assert 0.7 < np.std(vals) / err < 1.4, (k, np.std(vals), err)
    js = res.touches_json()["frames"][0]["touches"][0]
    assert {"x_stderr_m", "y_stderr_m", "strength_stderr"} <= set(js) and js["x_stderr_m"] > 0


def test_fast_position_bound_is_the_fits_scatter(smooth_stand_in):
    """``FitDetector.position_bound`` (the Cramer-Rao bound of contacts fitted together): two contacts 4 cm apart,
    refitted from the truth on 80 Poisson frames; each coordinate's scatter is the bound's standard deviation
    (within the sampling error of 80 draws), the share of fits within a radius is ``match_probability``'s, summed
    frames divide the covariance, a contact of strength 0 has no position (inf), and bad input is refused."""
    from tofjax.invert.sensitivity import match_probability

    sc, base, optical = smooth_stand_in
    K = 2
    truth = np.array([[0.05, 0.08, 0.8], [0.09, 0.08, 0.6]])
    opts = FitDetectOptions(cell_m=0.01, max_contacts=K, iterations=8, model_error=0.0)
    det = build_fit_detector(sc, base, optical, opts, n_baseline=10**6)
    cov = det.position_bound(truth)
    assert cov.shape == (2, 2, 2) and np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov) > 0)
    np.testing.assert_allclose(det.position_bound(truth, frames=4), cov / 4, rtol=1e-9)
    sig = np.asarray(_stand_in_change(sc, K, smooth=True)(jnp.asarray(truth.T.ravel()))).reshape(sc.shape)
    frames = np.random.default_rng(5).poisson(base + sig, size=(80, *sc.shape)).astype(float)
    t0 = truth.T.ravel().copy()
    fits = []
    for h in frames:
        t, _, _ = det._refit(t0, np.arange(K), (h.ravel() - det.base) / det.sigma)
        fits.append([t[:K], t[K : 2 * K]])
    fits = np.asarray(fits)  # (frames, 2: x y, K)
    for k in range(K):
        for i in range(2):
            ratio = np.std(fits[:, i, k]) / np.sqrt(cov[k, i, i])
            assert 0.75 < ratio < 1.3, (k, i, ratio)
    # the share within a radius of 1.5 x the larger standard deviation (about two thirds)
    r = 1.5 * float(np.sqrt(np.linalg.eigvalsh(cov[0])[1]))
    inside = np.mean(np.hypot(fits[:, 0, 0] - truth[0, 0], fits[:, 1, 0] - truth[0, 1]) < r)
    assert abs(inside - float(match_probability(cov[0], r))) < 0.15, (inside, match_probability(cov[0], r))
    none = det.position_bound(np.array([[0.05, 0.08, 0.0]]))
    assert np.all(np.isinf(none)) and float(match_probability(none[0], 0.02)) == 0.0
    assert det.position_bound(np.zeros((0, 3))).shape == (0, 2, 2)
    for bad, what in ((np.zeros((3, 3)), "at most max_contacts"), (np.zeros(3), "shape"),
                      (np.array([[np.nan, 0.1, 1.0]]), "finite")):
        with pytest.raises(ConfigError, match=what):
            det.position_bound(bad)
    with pytest.raises(ConfigError, match="frames"):
        det.position_bound(truth, frames=0)


def test_fast_match_probability_closed_forms():
    """``match_probability``: a round error ``1 - exp(-r^2 / 2 s^2)``, an error along a line ``erf(r / s sqrt 2)``,
    an elongated tilted one as its Monte Carlo share, an unconstrained one 0; bad input refused."""
    from scipy.special import erf

    from tofjax.invert.sensitivity import match_probability

    r = 0.02
    for s in (0.004, 0.01, 0.02, 0.05):
        assert abs(float(match_probability(np.eye(2) * s * s, r)) - (1 - np.exp(-r * r / (2 * s * s)))) < 1e-10
        assert abs(float(match_probability(np.diag([0.0, s * s]), r)) - erf(r / (s * np.sqrt(2)))) < 1e-5
    rng = np.random.default_rng(0)
    covs = []
    for _ in range(3):
        L = rng.normal(size=(2, 2)) * 0.015
        covs.append(L @ L.T)
    p = match_probability(np.asarray(covs), r)
    for c, pk in zip(covs, p):
        z = rng.standard_normal((200_000, 2)) @ np.linalg.cholesky(c).T
        assert abs(pk - np.mean(np.hypot(*z.T) < r)) < 0.004, (pk, np.mean(np.hypot(*z.T) < r))
    assert float(match_probability(np.full((2, 2), np.inf), r)) == 0.0
    assert float(match_probability(np.zeros((2, 2)), r)) == 1.0
    with pytest.raises(ConfigError, match="radius_m"):
        match_probability(np.eye(2), 0.0)
    with pytest.raises(ConfigError, match="cov"):
        match_probability(np.eye(3), r)


def test_fast_options_and_inputs_rejected(stand_in):
    sc, base, optical = stand_in
    with pytest.raises(ConfigError, match="n_sigma"):
        FitDetectOptions(n_sigma=-1.0)
    with pytest.raises(ConfigError, match="max_contacts"):
        FitDetectOptions(max_contacts=0)
    with pytest.raises(InversionError, match="guided"):
        build_fit_detector(sc, base, dataclasses.replace(optical, optics="default"))
    det = build_fit_detector(sc, base, optical, FitDetectOptions(cell_m=0.02, max_contacts=1))
    with pytest.raises(InversionError, match="shape"):
        det.process(base[None, :2])
    bad = base.copy()
    bad[0, 0, 0] = np.nan
    res = det.process(bad[None])
    assert not res.ok[0] and res.detections[0].touches == []


@pytest.mark.slow
def test_cli_fit_rejects_options_it_would_ignore(tmp_path):
    r = subprocess.run([sys.executable, "-m", "tofjax.cli", "detect", "t.h5", "--baseline", "b.h5", "--method", "fit",
                        "--relative", "0.3", "--json", str(tmp_path / "o.json")], capture_output=True, text=True)
    assert r.returncode != 0 and "--relative does not apply to --method fit" in r.stderr
    assert "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "tofjax.cli", "detect", "t.h5", "--baseline", "b.h5", "--method", "full",
                        "--model-error", "0.1", "--json", str(tmp_path / "o.json")], capture_output=True, text=True)
    assert r.returncode != 0 and "--model-error applies to --method fit only" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.slow
def test_slow_guided_model_two_contacts():
    """The real guided model (small scene): two skin contacts at a long exposure found within 1 cm, none
    on no-touch frames."""
    import tofjax
    from tofjax.model import ModelOptions
    from tofjax.model.contact import SkinContact
    from tofjax.scene import Touch
    from tofjax.simulate import expected_counts

    tofjax.enable_x64()
    sc = _small_scene()
    wg = dataclasses.replace(sc.waveguide, volume_backscatter_fraction=0.5)
    sc = sc.replace(waveguide=wg)
    opts = ModelOptions(optics="guided", skin=SkinContact())
    base = expected_counts(sc, ModelOptions(optics="guided")) * 16
    truth = np.array([[0.06, 0.09, 0.9], [0.10, 0.05, 0.8]])
    touch = expected_counts(sc.replace(touches=tuple(Touch((x, y), 0.006, s) for x, y, s in truth)), opts) * 16
    rng = np.random.default_rng(1)
    frames = rng.poisson(np.stack([touch, base, base])).astype(float)
    optical = dataclasses.replace(OpticalParams.from_scene(sc), optics="guided")
    optical = dataclasses.replace(optical, gain=tuple(g * 16 for g in optical.gain))
    det = build_fit_detector(sc, base, optical, FitDetectOptions(cell_m=0.01, max_contacts=4), n_baseline=100)
    res = det.process(frames)
    k, _ = match(res.detections[0].positions(), truth[:, :2], 0.01)
    assert k == 2 and len(res.detections[0].touches) == 2, res.detections[0].touches
    assert [len(d.touches) for d in res.detections[1:]] == [0, 0]


def _frame(sc, base, truth, K):
    theta = np.zeros(3 * K)
    n = len(truth)
    theta[:n], theta[K : K + n], theta[2 * K : 2 * K + n] = np.asarray(truth).T
    return base + np.asarray(_stand_in_change(sc, K)(jnp.asarray(theta))).reshape(sc.shape)


def test_fast_split_and_multi_start_leave_local_optima(stand_in):
    """Noise-free frames (stand-in model) where one greedy pass ends in a local optimum:
    (a) one contact fitted between two true ones: the split move replaces it by two, each within 1 cm of a
    true contact, and the chi-square falls more than fourfold; (b) two contacts the greedy search (with
    relocation and splits) places wrongly (none within 1 cm, chi-square ~30): a second start from the next
    local maximum of the first evidence map finds both (chi-square ~0)."""
    sc, base, optical = stand_in
    K = 3
    opts = FitDetectOptions(cell_m=0.01, max_contacts=K, iterations=4, relocate_candidates=2, n_sigma=5.0)
    det = build_fit_detector(sc, base, optical, opts, n_baseline=10**9)
    # (a) the split move
    truth = np.array([[0.06, 0.07, 0.8], [0.09, 0.08, 0.8]])
    y = (_frame(sc, base, truth, K).ravel() - det.base) / det.sigma
    t = np.zeros(3 * K)
    t[0], t[K], t[2 * K] = 0.075, 0.075, 1.0
    t, chi, r = det._refit(t, np.array([0]), y)
    t2, act, chi2, _ = det._split(t, np.array([0]), chi, r, y, 16.0)
    assert len(act) == 2 and chi2 < chi / 4, (chi, chi2)
    assert match(np.c_[t2[act], t2[K + act]], truth[:, :2], 0.01)[0] == 2, t2
    # (b) multi-start
    truth = np.array([[0.109, 0.076, 0.658], [0.061, 0.12, 0.591]])
    frame = _frame(sc, base, truth, K)[None]
    # (without the death-and-birth move, which finds them from one start too: tests/test_greedy_rebirth.py; and
    # without the pair moves, which cost time here and are tested below)
    one, two, reborn = (det.with_options(dataclasses.replace(opts, starts=s, rebirth=rb, pair_split=False))
                        .process(frame)
                        for s, rb in ((1, False), (2, False), (1, True)))
    assert match(one.detections[0].positions(), truth[:, :2], 0.01)[0] < 2 and one.chi2[0] > 16.0, one.chi2
    for res in (two, reborn):
        assert len(res.detections[0].touches) == 2 and match(res.detections[0].positions(), truth[:, :2], 0.01)[0] == 2
        assert res.chi2[0] < 1.0


def test_fast_pair_split_replaces_a_bound_ghost_by_the_pair_it_stands_for(stand_in):
    """Noise-free (stand-in model): one contact fitted between two true ones, 10 cm apart, sits at the strength
    bound 1. The split move (pairs of local maxima of the residual without it) leaves one of them missed; the
    pair move (best pair of cells by the responses' 2 x 2 normal equations) finds both, chi-square ~0."""
    sc, base, optical = stand_in
    K = 3
    det = build_fit_detector(sc, base, optical, FitDetectOptions(cell_m=0.01, max_contacts=K, iterations=4,
                                                                 relocate_candidates=2), n_baseline=10**9)
    truth = np.array([[0.126, 0.107, 0.763], [0.022, 0.1, 0.508]])
    y = (_frame(sc, base, truth, K).ravel() - det.base) / det.sigma
    t = np.zeros(3 * K)
    t[0], t[K], t[2 * K] = *truth[:, :2].mean(0), 1.0
    t, chi, r = det._refit(t, np.array([0]), y)
    assert t[2 * K] > 0.99 and chi > 500, (t, chi)  # the ghost at the bound
    one = np.array([0])
    ts, act_s, chi_s, _ = det._split(t, one, chi, r, y, 16.0)
    tp, act_p, chi_p, _ = det._pair_split(t, one, chi, r, y, 16.0)
    assert match(np.c_[ts[act_s], ts[K + act_s]], truth[:, :2], 0.01)[0] < 2 and chi_s > 30, chi_s
    assert len(act_p) == 2 and match(np.c_[tp[act_p], tp[K + act_p]], truth[:, :2], 0.01)[0] == 2, tp
    assert chi_p < 5.0, chi_p
    with pytest.raises(ConfigError, match="pair_candidates"):
        FitDetectOptions(pair_candidates=0)


def test_fast_fit_sensitivity_map_is_the_fit_threshold(stand_in):
    """The fit method's sensitivity map (``fit_sensitivity``): its per-cell noise is the matched filter's of the
    detector's own responses (built without compiling the fit's model: the same values), it grows as the
    photon noise (the stand-in's response is fixed: 4x the baseline, 2x the noise in strength units), the SNR as
    sqrt(frames), and it is the fit's threshold: a noise-free lone contact at 1.15 x the map's minimum strength
    is found, at 0.85 x it is not (n_sigma 6, overdispersion off)."""
    from tofjax.invert.sensitivity import SensitivityOptions, fit_sensitivity, fit_sensitivity_of

    sc, base, optical = stand_in
    K = 2
    opts = FitDetectOptions(cell_m=0.01, max_contacts=K, iterations=4, overdispersion=False, relocate=False,
                            rebirth=False, split=False)
    det = build_fit_detector(sc, base, optical, opts, n_baseline=10**9)
    sens = fit_sensitivity_of(det)
    lib = fit_sensitivity(sc, base, optical, fit=opts, n_baseline=10**9)
    np.testing.assert_allclose(lib.cell_noise[lib.sensed], sens.cell_noise[sens.sensed], rtol=1e-9)
    assert sens.method == "fit" and (sens.threshold_snr[sens.sensed] == 6.0).all()
    x4 = fit_sensitivity(sc, 4 * base, optical, SensitivityOptions(frames=3), fit=opts, n_baseline=10**9)
    np.testing.assert_allclose(x4.cell_noise[x4.sensed], 2.0 * sens.cell_noise[sens.sensed], rtol=1e-9)
    np.testing.assert_allclose(x4.snr[x4.sensed], np.sqrt(3) / x4.cell_noise[x4.sensed], rtol=1e-12)
    # the cell of (0.08, 0.06) (inside, seen), its centre exactly: a contact there alone
    j = int(np.argmin(np.hypot(*(det.centres - [0.08, 0.06]).T)))
    xy = det.centres[j]
    s_min = float(sens.at(xy)["min_strength"])
    one = _stand_in_change(sc, 1)
    found = []
    for f in (1.15, 0.85):
        frame = base + np.asarray(one(jnp.asarray([*xy, f * s_min]))).reshape(sc.shape)
        found.append(len(det.process(frame[None]).detections[0].touches))
    assert 0 < s_min < 0.8 and found == [1, 0], (s_min, found)


def test_fast_fit_sensitivity_position_maps_are_the_lone_bound(smooth_stand_in, tmp_path):
    """``SensitivityOptions(position=True)``: the fit map's ``position_sd`` at a cell is the larger standard
    deviation of ``FitDetector.position_bound`` of a lone contact there (the vmapped map and the detector's own
    Jacobian agree), ``match_share`` is ``match_probability`` of it, four frames halve the deviation, the summary,
    JSON and plot carry both, and the model method's map refuses the option."""
    from tofjax.invert.sensitivity import SensitivityOptions, fit_sensitivity, match_probability, sensitivity

    sc, base, optical = smooth_stand_in
    opts = FitDetectOptions(cell_m=0.02, max_contacts=1)
    det = build_fit_detector(sc, base, optical, opts, n_baseline=10**6)
    so = SensitivityOptions(strength=0.7, position=True, match_radius_m=0.01)
    m1 = fit_sensitivity(sc, base, optical, so, fit=opts, n_baseline=10**6)
    m4 = fit_sensitivity(sc, base, optical, dataclasses.replace(so, frames=4), fit=opts, n_baseline=10**6)
    sensed = m1.sensed & np.isfinite(m1.position_sd)
    assert sensed.sum() > 10
    for xy in det.centres[[3, len(det.centres) // 2, -4]]:
        cov = det.position_bound(np.array([[*xy, 0.7]]))[0]
        j, i = int(xy[1] / m1.grid.dy), int(xy[0] / m1.grid.dx)
        assert abs(m1.position_sd[j, i] / np.sqrt(np.linalg.eigvalsh(cov)[1]) - 1) < 1e-6
        assert abs(m1.match_share[j, i] - float(match_probability(cov, 0.01))) < 1e-9
    np.testing.assert_allclose(m4.position_sd[sensed], m1.position_sd[sensed] / 2, rtol=1e-9)
    assert np.all(m4.match_share[sensed] >= m1.match_share[sensed])
    s = m1.summary()["placed_within_match_radius"]
    assert s["match_radius_m"] == 0.01 and 0 < s["all"] < 1
    js = m1.to_json()
    assert js["options"]["position"] is True and len(js["maps"]["position_sd_m"]) == m1.grid.ny
    plain = fit_sensitivity(sc, base, optical, fit=opts, n_baseline=10**6)
    assert "position_sd_m" not in plain.to_json()["maps"] and plain.position_sd is None
    from tofjax.invert.plots import plot_position_bound

    assert plot_position_bound(m1, tmp_path / "p.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="position"):
        plot_position_bound(plain, tmp_path / "q.png")
    with pytest.raises(ConfigError, match="position"):
        sensitivity(sc, base, optical, so)
    with pytest.raises(ConfigError, match="match_radius_m"):
        SensitivityOptions(match_radius_m=-1.0)


def test_fast_fit_sensitivity_rejects_what_it_would_ignore(stand_in):
    from tofjax.invert.reconstruct import ReconstructOptions
    from tofjax.invert.sensitivity import SensitivityOptions, fit_sensitivity

    sc, base, optical = stand_in
    fit = FitDetectOptions(cell_m=0.02)
    with pytest.raises(ConfigError, match="response: the fit method"):
        fit_sensitivity(sc, base, optical, SensitivityOptions(response="added"), fit)
    with pytest.raises(ConfigError, match="reconstruct"):
        fit_sensitivity(sc, base, optical, SensitivityOptions(reconstruct=ReconstructOptions(tau=2.0)), fit)
    with pytest.raises(InversionError, match="guided"):
        fit_sensitivity(sc, base, dataclasses.replace(optical, optics="default"), fit=fit)
    with pytest.raises(ConfigError, match="baseline"):
        fit_sensitivity(sc, base[:2], optical, fit=fit)
