"""NUTS posterior (tofjax/fit/nuts.py) and the log-density it shares with emcee: a short run on
a small scene, the ArviZ diagnostics as properties, and one-line errors for bad options."""

import os

import numpy as np
import pytest

from tofjax.cli import main
from tofjax.errors import UserError
from tofjax.fit.calibrate import Calibrator, FitConfig
from tofjax.fit.nuts import NutsOptions, diagnostics, plot_nuts, sample_nuts
from tofjax.fit.posterior import HELD, NUISANCE, log_density
from tofjax.scene import SensorModel
from tofjax.simulate import simulate


@pytest.fixture(scope="module")
def fitted(optoskin):
    """Three OptoSkin sensors, 3 zones, 96 bins (the shapes test_calibrate compiles too)."""
    small = optoskin.replace(sensor=SensorModel(bin_width_s=1e-10, n_bins=96, zones=3, fov_deg=29.0),
                             sensors=optoskin.sensors[:3])
    cap = simulate(small, 60, seed=3)
    cal = Calibrator(small, FitConfig(pulse_tails=2))  # the slow tail's coordinates are held (HELD)
    return small, cal, cal.fit(cap), cap


def test_log_density_is_shared_and_whitenable(fitted):
    """One log-density: the compiled value and gradient NUTS follows and the batched one
    (emcee's) agree; it is finite with a finite gradient at the fit; the Laplace covariance is
    symmetric positive definite; the nuisance prior and holding the slow tail at the fit (a
    conditional posterior) only narrow it; held coordinates are neither sampled nor reported."""
    import jax.numpy as jnp

    from tofjax.fit.posterior import _value_and_grad

    _, cal, res, cap = fitted
    ld = log_density(cal, cap, res)
    f0 = jnp.asarray(ld.flat0)
    # NUTS's own program (test_log_density_gain_prior_and_gradient and the coverage study's
    # NUTS compile the same one; jax.value_and_grad(ld.fn) eagerly compiled pieces of its own)
    v, g = _value_and_grad(ld.problem, ld.template, ld.args, f0, ld.idx)
    assert np.isfinite(float(v)) and np.isfinite(np.asarray(g)).all()
    # the same function, vmapped or not: they differ only by the summation order of per-bin terms far larger than the
    # total (a fresh clone saw 1.1e-12 relative after the near field's shape; a different density differs by far more)
    assert float(v) == pytest.approx(float(ld.batch(ld.flat0[None])[0]), rel=1e-10)
    np.testing.assert_allclose(ld.laplace_cov, ld.laplace_cov.T, rtol=1e-12, atol=0)
    assert np.linalg.eigvalsh(ld.laplace_cov).min() > 0
    held = [k for k in HELD if k in cal.problem.nonlinear]
    assert set(ld.coords) | set(held) == set(cal.problem.pack(res.params, cal.problem.nonlinear))
    assert len(ld.names) == ld.to_physical(ld.flat0[None]).shape[1]
    loose = log_density(cal, cap, res, nuisance_width=None, hold=())
    assert held and set(loose.coords) == set(ld.coords) | set(held) and not set(held) & set(ld.names)
    assert set(held) <= set(loose.names)
    # the light-entry width is held by default (its posterior is the weak prior below a steep wall)
    assert "crosstalk_width_s" in HELD and "crosstalk_width_s" in cal.problem.nonlinear
    assert "crosstalk_width_s" not in ld.coords and "crosstalk_width_s" in loose.coords
    for k in ld.coords:
        i, j = ld.coords.index(k), loose.coords.index(k)
        assert ld.laplace_cov[i, i] <= loose.laplace_cov[j, j] * (1 + 1e-9)
        if k in NUISANCE:
            assert ld.laplace_cov[i, i] < loose.laplace_cov[j, j]
    with pytest.raises(UserError, match="hold"):
        log_density(cal, cap, res, hold=("pulse_tails",))


@pytest.mark.slow  # 55 s cold; the default run samples with NUTS in test_calib_studies' coverage test
def test_nuts_short_run(fitted, tmp_path):
    """A short run (the targets are benchmarked in experiments/bench_posterior.py): draws near
    the truth, every diagnostic reported per parameter, plots written."""
    small, cal, res, cap = fitted
    r = sample_nuts(cal, cap, res, NutsOptions(chains=2, warmup=60, draws=60))
    assert r.samples.shape == (120, len(r.names)) and np.isfinite(r.samples).all()
    s = r.summary()
    for key in ("ess_bulk", "ess_tail", "rhat"):
        assert set(s[key]) == set(r.names)
    assert s["wall_s"] > 0 and s["ess_min_per_s"] == pytest.approx(s["ess_min"] / s["wall_s"])
    assert 0 < s["ess_min"] and 0.9 < s["rhat_max"]
    assert r.gradient_evaluations >= 2 * 120
    assert 2 * 60 <= r.warmup_gradient_evaluations < r.gradient_evaluations and s["warmup_gradient_evaluations"] > 0
    assert s["start"] == "mode" and s["start_info"]["used"] == "mode"
    import json

    json.dumps(s)  # the CLI writes it into the calibration JSON
    n1 = s["parameters"]["n1"]
    assert n1["interval95"][0] < n1["median"] < n1["interval95"][1]
    assert abs(n1["median"] - small.waveguide.n1) < 0.01
    mu_t = r.samples[:, r.names.index("mu_s_per_m")] + r.samples[:, r.names.index("mu_a_per_m")]
    truth = small.waveguide.mu_s_per_m + small.waveguide.mu_a_per_m
    assert np.median(mu_t) == pytest.approx(truth, rel=0.1)
    paths = plot_nuts(r, tmp_path)
    assert all(p.stat().st_size > 5000 for p in paths)
    # the chains in threads draw exactly what they drew one after the other (threads=1, the default)
    two = sample_nuts(cal, cap, res, NutsOptions(chains=2, warmup=60, draws=60, threads=2))
    np.testing.assert_array_equal(two.samples, r.samples)


def test_chains_in_threads_keep_their_order():
    """_run_chains: the chains' outputs in the chains' order, the same in threads as one
    after the other, and however many threads (more than chains, one)."""
    import jax
    import jax.numpy as jnp

    from tofjax.fit.nuts import _run_chains, _threads

    @jax.jit
    def chain(x, n):
        return jax.lax.fori_loop(0, 2000, lambda i, y: jnp.sin(y) + x, x), x * n

    args = [(jnp.asarray(float(c)),) for c in range(5)]
    seq = _run_chains(chain, args, (3.0,), 1)
    for threads in (2, 8):
        par = _run_chains(chain, args, (3.0,), threads)
        assert len(par) == 5
        for a, b in zip(seq, par):
            np.testing.assert_array_equal(a[0], b[0])
            np.testing.assert_array_equal(a[1], b[1])
    assert [float(o[1]) for o in par] == [3.0 * c for c in range(5)]
    assert _threads(NutsOptions(chains=4, threads=8)) == 4 and _threads(NutsOptions(chains=4, threads=1)) == 1
    assert 1 <= _threads(NutsOptions(chains=3)) == _threads(NutsOptions(chains=3, threads=None)) <= min(3, os.cpu_count() or 1)


def test_diagnostics_properties():
    """ArviZ's numbers behave: independent draws give ESS near their count and R-hat near 1;
    chains stuck apart give R-hat far above 1."""
    rng = np.random.default_rng(0)
    iid = rng.normal(size=(4, 500, 2))
    d = diagnostics(["a", "b"], iid)
    assert d["ess_min"] > 1000 and d["rhat_max"] < 1.02
    apart = iid + np.arange(4)[:, None, None]
    assert diagnostics(["a", "b"], apart)["rhat_max"] > 1.5


@pytest.mark.parametrize("kw", [{"chains": 0}, {"warmup": 5}, {"draws": -1}, {"draws": 1.5}, {"target_accept": 1.0},
                                {"max_tree_depth": 0}, {"chains": True}, {"gain_prior": "jeffreys"},
                                {"threads": 0}, {"threads": True}, {"threads": 1.5}, {"pilot_warmup": 5}, {"pilot_draws": 2.0}])
def test_bad_options_are_one_line_errors(kw):
    with pytest.raises(UserError, match=next(iter(kw))):
        NutsOptions(**kw)


def test_cli_nuts_options_need_nuts(tmp_path, capsys):
    """--chains/--warmup/--draws only with --mcmc nuts; refused before any file is read."""
    rc = main(["calibrate", str(tmp_path / "none.h5"), "--out", str(tmp_path / "c.json"), "--mcmc", "emcee", "--chains", "4"])
    err = capsys.readouterr().err
    assert rc != 0 and "--chains: only for --mcmc nuts" in err and "Traceback" not in err
    with pytest.raises(SystemExit):  # argparse: an unknown sampler
        main(["calibrate", str(tmp_path / "none.h5"), "--out", str(tmp_path / "c.json"), "--mcmc", "hmc"])


def test_gain_prior_marginal_against_numerical_integral():
    """The analytic marginal over a zone's linear parameters (gain g, light entry x, ambient a)
    that the log-density uses, ``-chi2_min/2 - log det(A^T W A)/2 - log g*`` (log-uniform gain)
    or without ``log g*`` (flat), against a numerical integral over (g, x, a) on a toy zone with
    a loosely pinned gain (sd(g)/g ~ 6%, so the 1/g factor is not trivially constant). And why
    the log-uniform prior: it does not depend on how the model per unit gain R is normalised
    (R -> s R), the flat one moves by -log s."""
    t = np.linspace(0, 1, 24)
    R, P, one = np.exp(-3 * t) * (1 + 2 * t), np.exp(-0.5 * ((t - 0.2) / 0.05) ** 2), np.ones_like(t)
    A = np.stack([R, P, one], 1)
    truth = np.array([2.0, 1.5, 0.4])
    sigma = (0.4 + 0.1 * t) / 3
    y = A @ truth + sigma * np.random.default_rng(1).normal(size=t.size)

    def analytic(A, log_gain):
        W = 1 / sigma**2
        G = A.T @ (A * W[:, None])
        c = np.linalg.solve(G, A.T @ (W * y))
        chi2 = np.sum(W * (y - A @ c) ** 2)
        return -0.5 * chi2 - 0.5 * np.linalg.slogdet(G)[1] - (np.log(c[0]) if log_gain else 0.0) + 1.5 * np.log(2 * np.pi), c

    def numerical(A, log_gain):
        """Brute force: the integrand on a regular grid over +-8 standard errors of each."""
        lp0, c = analytic(A, log_gain)
        W = 1 / sigma**2
        sd = np.sqrt(np.diag(np.linalg.inv(A.T @ (A * W[:, None]))))
        axes = [np.linspace(ci - 8 * s, ci + 8 * s, 61) for ci, s in zip(c, sd)]
        assert axes[0][0] > 0  # the gain's integral kept to g > 0 (the prior's support)
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        chi2 = np.sum(W * (y[None] - grid @ A.T) ** 2, axis=1)
        f = np.exp(-0.5 * chi2 - lp0) / (grid[:, 0] if log_gain else 1.0)
        return lp0 + np.log(f.sum() * np.prod([a[1] - a[0] for a in axes]))

    for log_gain in (True, False):
        lp, c = analytic(A, log_gain)
        sd_g = np.sqrt(np.linalg.inv(A.T @ (A / sigma[:, None] ** 2))[0, 0])
        assert 0.03 < sd_g / c[0] < 0.1
        # the 1/g factor taken at g*: off by ~(sd/g)^2, here < 1%; exact for the flat prior
        assert numerical(A, log_gain) == pytest.approx(lp, abs=0.01 if log_gain else 1e-4)
    s = 7.0
    As = A * np.array([s, 1, 1])
    assert analytic(As, True)[0] == pytest.approx(analytic(A, True)[0], abs=1e-9)
    assert analytic(As, False)[0] - analytic(A, False)[0] == pytest.approx(-np.log(s), abs=1e-9)


def test_log_density_gain_prior_and_gradient(fitted):
    """The log-uniform gain prior adds exactly -sum log g* (the profiled zone gains) to the flat
    one (at the fit: the fit's own profiled gains); the gradient (what NUTS follows) agrees
    with central finite differences along a random direction in Laplace-scaled units; an unknown gain prior is a one-line error."""
    import jax.numpy as jnp

    _, cal, res, cap = fitted
    ld = log_density(cal, cap, res)
    flat = log_density(cal, cap, res, gain_prior="flat")
    gains = np.asarray(res.values["gain"])  # the fit's profiled zone gains, at the same point
    assert gains.shape == (3, 3)
    assert float(ld.batch(ld.flat0[None])[0]) - float(flat.batch(flat.flat0[None])[0]) == pytest.approx(
        -float(np.sum(np.log(gains))), abs=1e-6)
    from tofjax.fit.posterior import _value_and_grad

    d = np.sqrt(np.diag(ld.laplace_cov)) * np.random.default_rng(0).normal(size=ld.flat0.size)
    _, g = _value_and_grad(ld.problem, ld.template, ld.args, jnp.asarray(ld.flat0), ld.idx)
    hs = np.array([0.005, 0.0025])  # Laplace sd units: along the ridge the density is far from Gaussian on 0.05 sd
    v = np.array([ld.batch((ld.flat0 + x)[None])[0] for x in (*(hs[:, None] * d), *(-hs[:, None] * d))])  # one shape: one program
    for fd in (v[:2] - v[2:]) / (2 * hs):
        assert fd == pytest.approx(float(np.asarray(g) @ d), rel=0.02, abs=0.05)
    with pytest.raises(UserError, match="gain_prior"):
        log_density(cal, cap, res, gain_prior="jeffreys")


def test_log_fraction_coordinates_round_trip_and_jacobian():
    """The samplers' coordinates for albedo and end reflectance (w, with log p = -softplus(-k w)/k):
    the inverse maps back, ``log |d logit p / d w|`` is the derivative's log (finite differences),
    and w = log p away from p = 1 (so the ridge, straight in log p, stays straight)."""
    import jax.numpy as jnp

    from tofjax.fit.posterior import STEEP, _to_fit, _to_sampler_np

    u = np.array([-3.0, 0.0, 0.3, 2.5, 4.0])
    idx = (0, 1, 2, 3)
    w = _to_sampler_np(u, idx)
    back, _ = _to_fit(jnp.asarray(w), idx)
    np.testing.assert_allclose(np.asarray(back), u, atol=1e-9)
    assert w[4] == u[4]
    p = 1 / (1 + np.exp(-u[:4]))
    far = p < 0.8
    np.testing.assert_allclose(w[:4][far], np.log(p[far]), atol=1e-6 * STEEP)
    h = 1e-6
    du = (np.asarray(_to_fit(jnp.asarray(w + h), idx)[0]) - np.asarray(_to_fit(jnp.asarray(w - h), idx)[0]))[:4] / (2 * h)
    assert float(_to_fit(jnp.asarray(w), idx)[1]) == pytest.approx(np.sum(np.log(du)), rel=1e-5, abs=1e-5)


def test_ridge_coordinates_are_a_bijection_with_the_right_log_jacobian():
    """NUTS's ridge coordinates (tofjax/fit/nuts.py ``unshear``): the low end of the albedo's
    coordinate compressed (asinh), then the other coordinates measured from the ridge's line
    in log albedo (a shear). The map is a bijection (inverted by hand below, past the
    albedo's bound too), its log-Jacobian is ``log |det|`` of finite differences, JAX and
    NumPy agree, it is the identity at the centre, the shear decorrelates the albedo there,
    ``fit_tail`` finds the asinh scale that puts a known tail drop at 2 sd, and without a
    sampled log albedo it is the identity."""
    import jax.numpy as jnp

    from tofjax.fit.nuts import _unshear_np, fit_tail, ridge_shear, unshear
    from tofjax.fit.posterior import STEEP

    rng = np.random.default_rng(0)
    P = 4
    A = rng.normal(size=(P, P))
    cov = A @ A.T + 0.1 * np.eye(P)
    centre = np.array([-0.16, 1.0, 2.0, 3.0])
    coords = ("albedo", "b", "c", "d")
    sheared, cy = ridge_shear(coords, (0,), centre, cov)
    np.testing.assert_allclose(cy[0, 1:], 0.0, atol=1e-9 * cy[0, 0])  # albedo decorrelated from the rest
    s = sheared[4]
    # a toy log-density whose low end along the albedo falls as 8 at 2 sd (a unit normal: 2)
    ridge = fit_tail(sheared, centre, lambda x: -8.0 * float(((x[0] - centre[0]) / (2 * s)) ** 2))
    v = np.sqrt(16.0)
    assert ridge[5] > 0 and np.arcsinh(ridge[5] * v) / ridge[5] == pytest.approx(2.0, rel=1e-9)
    assert fit_tail(sheared, centre, lambda x: -0.5 * float(((x[0] - centre[0]) / s) ** 2))[5] == 0.0
    rj = tuple(jnp.asarray(x) for x in ridge)
    np.testing.assert_allclose(_unshear_np(centre, ridge)[0], centre, atol=1e-14)
    b, e, a_ref, m, _, al = ridge
    for y0 in (-0.9, -0.3, -0.01, 0.05, 0.4):  # the last two past the bound (log albedo saturates at 0)
        y = centre + 0.3 * rng.normal(size=P)
        y[0] = y0
        x, lj = unshear(jnp.asarray(y), rj)
        xn, ljn = _unshear_np(y, ridge)
        np.testing.assert_allclose(np.asarray(x), xn, atol=1e-12)
        assert float(lj) == pytest.approx(float(ljn), abs=1e-12)
        a = -np.logaddexp(0.0, -STEEP * xn[0]) / STEEP  # the inverse, by hand
        back = xn - b * (a - a_ref)
        vb = (back[0] - m) / s
        back[0] = m + s * (np.sinh(al * min(vb, 0.0)) / al + max(vb, 0.0))
        np.testing.assert_allclose(back, y, atol=1e-12)
        h = 1e-6
        J = np.stack([(_unshear_np(y + h * d, ridge)[0] - _unshear_np(y - h * d, ridge)[0]) / (2 * h) for d in np.eye(P)], 1)
        assert np.log(abs(np.linalg.det(J))) == pytest.approx(float(ljn), abs=1e-7)
    ident, c2 = ridge_shear(coords, (), centre, cov)
    assert not np.any(ident[0]) and not np.any(ident[1]) and c2 is cov
    np.testing.assert_allclose(_unshear_np(centre + 0.1, ident)[0], centre + 0.1, atol=1e-14)
