"""The light the walls and the volume exchange around a zone's lit wall (guided.EDGE_SCATTER, issue 14).

Small scenes and few compiles. The evidence that the term is the Monte Carlo's is the study
(experiments/edge_scatter.py, docs/results/edge_scatter.json); here its properties.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tofjax.model.guided as guided
from tofjax.model import ModelOptions, Params, build_model
from tofjax.scene import scene_from_dict

BIN = 5e-11
T_E = 5e-10
GUIDED = ModelOptions(optics="guided")


def _scene(size=(0.2, 0.2), position=(0.0, 0.1), direction=0.0, mu_s=2.0, zones=3, fov=30.0):
    return scene_from_dict({
        "waveguide": {"size_m": list(size), "thickness_m": 0.004, "n1": 1.4, "mu_s_per_m": mu_s, "mu_a_per_m": 0.1},
        "sensor": {"bin_width_s": BIN, "n_bins": 128, "zones": zones, "fov_deg": fov, "emission_time_s": T_E},
        "sensors": [{"position_m": list(position), "direction_deg": direction}],
    })


def _term(monkeypatch, sc, **replace):
    """The far edge's light with the kernels minus without (the reverberant field and the second bounce off, so the
    difference is the kernels' alone), and the first return alone; (S, Z, B) each."""
    monkeypatch.setattr(guided, "EDGE_REVERB", False)
    monkeypatch.setattr(guided, "EDGE_SECOND", False)
    p = Params.from_scene(sc)
    if replace:
        p = p.replace(**{k: jnp.asarray(v, p.n1.dtype) for k, v in replace.items()})
    out = {}
    for on in (True, False):
        monkeypatch.setattr(guided, "EDGE_SCATTER", on)
        out[on] = np.asarray(build_model(sc, GUIDED, ("end",))(p))
    monkeypatch.setattr(guided, "EDGE_SCATTER", True)
    return out[True] - out[False], out[False]


def test_edge_scatter_needs_scattering_and_grows_with_it(monkeypatch):
    """Both kernels are light scattered by the volume: none in a clear guide (to rounding), proportional to mu_s
    while it is small, never negative, finite with finite gradients, the gradient in mu_s as central differences."""
    sc = _scene()
    none, first = _term(monkeypatch, sc, mu_s_per_m=0.0)
    assert np.abs(none).max() <= 1e-12 * first.max() and first.sum() > 0
    small, _ = _term(monkeypatch, sc, mu_s_per_m=0.05)
    double, _ = _term(monkeypatch, sc, mu_s_per_m=0.1)
    assert small.min() >= -1e-9 * small.max() and small.sum() > 1e-4 * first.sum()
    assert double.sum() / small.sum() == pytest.approx(2.0, rel=0.02)
    # the whole guided model (reverberant field included) with the kernels: gradients finite, mu_s's as differences
    model = build_model(sc, GUIDED)
    p = Params.from_scene(sc)
    f = jax.jit(lambda q: jnp.sum(model(q) ** 0.5))
    g = jax.jit(jax.grad(lambda q: jnp.sum(model(q) ** 0.5)))(p)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(g))
    h, v = 1e-4, float(p.mu_s_per_m)
    fd = (f(p.replace(mu_s_per_m=jnp.asarray(v + h))) - f(p.replace(mu_s_per_m=jnp.asarray(v - h)))) / (2 * h)
    assert float(g.mu_s_per_m) == pytest.approx(float(fd), rel=1e-5)


def test_edge_scatter_kernels_converge(monkeypatch):
    """The kernels' tables (bins of path difference, points along the rays, elements per footprint) are converged: a
    quarter of the bin width with four times the bins, and twice the points and elements, move the term by under 2%
    (relative L2), in a guide whose zones see two walls."""
    sc = _scene(position=(0.0, 0.03), direction=35.0)
    base, _ = _term(monkeypatch, sc)
    monkeypatch.setattr(guided, "SCATTER_BIN_M", guided.SCATTER_BIN_M / 4)
    monkeypatch.setattr(guided, "SCATTER_BINS", guided.SCATTER_BINS * 4)
    monkeypatch.setattr(guided, "SCATTER_SOURCES", guided.SCATTER_SOURCES * 2)
    monkeypatch.setattr(guided, "SCATTER_ELEMENTS", guided.SCATTER_ELEMENTS * 2)
    fine, _ = _term(monkeypatch, sc)
    assert np.linalg.norm(fine - base) < 0.02 * np.linalg.norm(fine)


def test_walls_light_reaches_an_oblique_zone_before_its_own_first_return(monkeypatch):
    """The geometry the kernels carry: a zone that sees its wall obliquely, next to zones whose wall is nearer, gets
    the volume's back-scatter of their lit walls before its own first return begins; a sensor facing a wall square on
    gets nothing before its first return (scattered paths are longer than the direct one)."""

    def onset(y, frac=0.02):
        return int(np.argmax(y > frac * y.max()))

    sq, first_sq = _term(monkeypatch, _scene(size=(0.2, 0.1), position=(0.0, 0.05), fov=6.0, zones=1))
    assert onset(sq[0, 0]) >= onset(first_sq[0, 0]) - 1
    ob, first_ob = _term(monkeypatch, _scene(position=(0.0, 0.02), direction=40.0, zones=4, fov=40.0))
    early = [onset(first_ob[0, z]) - onset(ob[0, z]) for z in range(4)]
    assert max(early) >= 3, early  # bins of 50 ps: the neighbours' walls are centimetres nearer


def _kernel(monkeypatch, switch, sc, **replace):
    """An optional kernel alone (``switch`` of guided, e.g. SCATTER_REDIRECT) and the first return;
    (S, Z, B) each, the field and the second bounce off."""
    out = {}
    for on in (True, False):
        monkeypatch.setattr(guided, switch, on)
        out[on] = _term(monkeypatch, sc, **replace)
    return out[True][0] - out[False][0], out[False][1]


def test_redirected_wall_light_is_one_scattering_and_one_more_bounce(monkeypatch):
    """The third kernel (SCATTER_REDIRECT: the lit walls' light scattered once on to the walls in view) is light that
    scattered once and met the walls twice: none in a clear guide, proportional to mu_s and (against the first return)
    to the walls' reflectance while both are small, never negative, later than the first return; its grid of
    scattering points is converged (half the spacing moves it by under 5%). Off by default (the Monte Carlo study:
    docs/results/scatter_redirect.json)."""
    switch, grid = "SCATTER_REDIRECT", "SCATTER_GRID_M"
    sc = _scene(position=(0.0, 0.03), direction=35.0)
    none, first = _kernel(monkeypatch, switch, sc, mu_s_per_m=0.0)
    assert np.abs(none).max() <= 1e-12 * first.max()
    a, first_a = _kernel(monkeypatch, switch, sc, mu_s_per_m=0.01, end_reflectance=0.3)
    b, _ = _kernel(monkeypatch, switch, sc, mu_s_per_m=0.02, end_reflectance=0.3)
    c, first_c = _kernel(monkeypatch, switch, sc, mu_s_per_m=0.01, end_reflectance=0.6)
    assert a.min() >= -1e-9 * a.max() and a.sum() > 1e-6 * first_a.sum()
    assert b.sum() / a.sum() == pytest.approx(2.0, rel=0.02)
    assert (c.sum() / first_c.sum()) / (a.sum() / first_a.sum()) == pytest.approx(2.0, rel=1e-6)
    t = np.arange(a.shape[-1])
    assert (a * t).sum() / a.sum() > (first_a * t).sum() / first_a.sum()
    monkeypatch.setattr(guided, grid, getattr(guided, grid) / 2)
    fine, _ = _kernel(monkeypatch, switch, sc, mu_s_per_m=0.01, end_reflectance=0.3)
    assert np.linalg.norm(fine - a) < 0.05 * np.linalg.norm(fine)


def test_kernels_are_timed_from_each_rays_own_return(monkeypatch):
    """One wide zone against the same field of view split into 16 narrow ones (whose footprints each span little
    distance, so their kernels need no timing from the zone's mean): a wide zone's kernels are applied to its whole
    first return, weighted to its near rays, while the scattered light is weighted to its far ones. Timed from each
    ray's own return (SCATTER_OWN_RETURN), the wide zone's kernel light agrees with the narrow zones' sum in amount
    (within 1.5%) and mean arrival (within 0.35 of a 50 ps bin); timed from the zone's first return it came almost a
    bin early and 3.5% too strong."""
    monkeypatch.setattr(guided, "EDGE_APERTURE", False)  # no spill between neighbouring zones

    def light(zones):
        sc = _scene(position=(0.0, 0.03), direction=35.0, zones=zones, fov=60.0)
        return _term(monkeypatch, sc)[0].sum(1)[0]  # the zones' sum

    t = np.arange(_scene().sensor.n_bins)
    errors = {}
    for own in (True, False):
        monkeypatch.setattr(guided, "SCATTER_OWN_RETURN", own)
        wide, narrow = light(1), light(16)
        errors[own] = (wide.sum() / narrow.sum() - 1.0, (wide * t).sum() / wide.sum() - (narrow * t).sum() / narrow.sum())
    assert abs(errors[True][0]) < 0.015 and abs(errors[True][1]) < 0.35, errors
    assert errors[False][1] < -0.6 and errors[False][0] > 0.025, errors  # what the switch mends


def _one_ray_tables(monkeypatch, n1=1.45, fov=0.4, h=0.004, L=0.2, width=0.2):
    """The tables of one ray square on to its wall, one scattering point half way (term 0's source and term 1's
    target) and one wall element."""
    monkeypatch.setattr(guided, "SCATTER_SOURCES", 1)
    monkeypatch.setattr(guided, "SCATTER_ELEMENTS", 1)
    monkeypatch.setattr(guided, "SCATTER_REDIRECT", False)
    one = np.ones((1, 1, 1))
    return guided._scatter_tables(width, 0.1, h, np.array([[0.0, 0.05]]), 0.0 * one, L * one, one, one,
                                  np.array([fov]), fov, n1)


def _band_means(cg, n=200_000):
    """The bands' mean ``1 / cos`` by quadrature over ``mu = sin(elevation)`` in the guided band ``|mu| < cg`` (at the
    midpoints of ``n`` equal cells): uniform in ``mu`` (isotropic light, and what a point receives), and weighted by
    ``cos`` (what an aperture in a wall receives from a Lambertian wall)."""
    cos = np.sqrt(1.0 - (cg * ((np.arange(n) + 0.5) / n * 2.0 - 1.0)) ** 2)
    return np.mean(1.0 / cos), 1.0 / np.mean(cos)


def test_each_kernels_delay_is_its_paths_legs_at_their_own_speeds(monkeypatch):
    """One ray square on to its wall, one scattering point half way and one wall element: the tables' mean lengths
    give each kernel's delay from the first return as the physical path difference, each leg at its own band's mean
    ``1 / cos``: the beam at ``1 / c_out``; light that a volume point scatters, or receives from a wall, at the
    isotropic band's ``g_iso`` (SCATTER_FLUENCE: a point takes a Lambertian wall's light uniformly in ``mu``, see
    test_a_points_light_from_a_wall_is_uniform_in_mu); light leaving a wall for a sensor's aperture at a Lambertian
    wall's ``g_wall``. Term 1's view leg leaves the volume (``g_iso``) where the direct return it is counted from
    leaves the wall (``g_wall``): before the twenty-sixth session's fix its light came ``(g_iso - g_wall) L`` early
    (3 mm at 20 cm). Each entry sits in the bin of its path difference at the scene's n1."""
    monkeypatch.setattr(guided, "SCATTER_SPREAD", 0)
    n1, fov, h, L = 1.45, 0.4, 0.004, 0.2
    tab = _one_ray_tables(monkeypatch, n1, fov, h, L)
    cg, _, c_out = guided.launch_band(n1, fov)
    g_iso, g_wall = _band_means(cg)
    x, rho = 0.5 * L, np.hypot(0.5 * L, h)  # the point, and its distance to the wall element
    g_back = g_iso if guided.SCATTER_FLUENCE else g_wall
    want = {  # scattered path less the first return (outbound L / c_out, back L g_wall)
        0: (x / c_out + g_iso * rho + L * g_wall) - (L / c_out + L * g_wall),  # beam -> point -> wall -> sensor
        1: (L / c_out + g_back * rho + g_iso * x) - (L / c_out + L * g_wall),  # beam -> wall -> point -> sensor
    }
    legs = {0: g_iso, 1: g_back}
    for term, path in want.items():
        w = tab["w"][0, 0, term]
        assert np.count_nonzero(w) == 1
        k = int(np.flatnonzero(w)[0])
        assert k == int(np.floor((path - guided.SCATTER_MIN_M) / guided.SCATTER_BIN_M)), (term, k, path)
        a, b, c = (tab[key][0, 0, term, k] for key in ("a", "b", "c"))
        got = a / c_out + legs[term] * b + g_iso * c  # what _edge_scatter computes from the tables
        assert got == pytest.approx(path, abs=1e-9), (term, got, path)


def test_a_points_light_from_a_wall_is_uniform_in_mu():
    """SCATTER_FLUENCE's premise, from the slab's mirror images: a wall element (a vertical strip the slab's faces
    mirror into an unbounded one) of constant radiance seen from a point ``rho`` away. The strip's patch at height
    ``z`` subtends ``l dz cos / r^2`` (``cos = rho / r``), so the fluence it gives, binned by ``mu = z / r``, is flat
    in ``mu``, and the guided part's mean ``1 / cos`` is the isotropic band's (``asin(cg) / cg``), not the
    flux-weighted one an aperture in a wall receives."""
    rho, cg = 0.07, float(guided.launch_band(1.4, 0.4)[0])
    z = np.linspace(-40.0, 40.0, 2_000_001) * rho  # heights on the images' strip
    r = np.hypot(rho, z)
    mu, fluence = z / r, rho / r**3  # per unit height (the solid angle per unit length and width)
    guided_ = np.abs(mu) < cg
    hist, _ = np.histogram(mu[guided_], bins=20, weights=fluence[guided_])
    assert hist.std() < 1e-3 * hist.mean()  # uniform in mu
    inv_cos = r / rho
    mean = np.sum(fluence * inv_cos * guided_) / np.sum(fluence * guided_)
    g_iso, g_wall = _band_means(cg)
    assert mean == pytest.approx(float(guided._band_inv_cos(cg)), rel=1e-4)
    assert mean == pytest.approx(g_iso, rel=1e-5) and abs(mean - g_wall) > 5e-3


def test_diffuse_leg_spread_keeps_each_entrys_light_and_mean_delay(monkeypatch):
    """SCATTER_SPREAD (built, off by default): each entry binned at n elevations of its diffuse leg keeps its light
    and its mean delay, and spreads it as ``1 / cos`` spreads over the isotropic band (the variance within 10%, the
    bins' width aside); the latest light is the steepest guided elevation's (``rho / cos`` up to ``n1 rho``)."""
    n1, fov, h, L = 1.45, 0.4, 0.004, 0.6
    cg, _, c_out = guided.launch_band(n1, fov)
    out = {}
    for n in (0, 8):
        monkeypatch.setattr(guided, "SCATTER_SPREAD", n)
        tab = _one_ray_tables(monkeypatch, n1, fov, h, L, width=0.6)
        w = tab["w"][0, 0, 0]
        delay = tab["a"][0, 0, 0] / c_out + float(guided._band_inv_cos(cg)) * tab["b"][0, 0, 0]
        m = np.sum(w * delay) / np.sum(w)
        out[n] = (np.sum(w), m, np.sum(w * (delay - m) ** 2) / np.sum(w), delay[w > 0].max())
    rho = np.hypot(0.5 * L, h)
    assert out[8][0] == pytest.approx(out[0][0], rel=1e-12) and out[0][2] == pytest.approx(0.0, abs=1e-18)
    assert out[8][1] == pytest.approx(out[0][1], abs=1e-9)
    mu = cg * ((np.arange(200_000) + 0.5) / 200_000)
    var = np.var(1.0 / np.sqrt(1.0 - mu**2)) * rho**2
    assert out[8][2] == pytest.approx(var, rel=0.1)
    assert out[8][3] - out[0][3] < (1.0 / np.sqrt(1.0 - cg**2) - float(guided._band_inv_cos(cg))) * rho


def test_second_bounces_light_scattered_back_is_two_bounces_and_one_scattering(monkeypatch):
    """SCATTER_SECOND: term 1's kernel on the second bounce's return too. What it adds is light that met the walls
    twice and scattered once: none in a clear guide, proportional to mu_s while it is small and to the reflectance
    squared (the first return carries one R, the second bounce two), never negative; it comes after the first
    return's own term 1 light (the second bounce arrives later)."""
    sc = _scene(position=(0.0, 0.03), direction=35.0)
    monkeypatch.setattr(guided, "EDGE_REVERB", False)
    p0 = Params.from_scene(sc)

    def added(**replace):
        p = p0.replace(**{k: jnp.asarray(v, p0.n1.dtype) for k, v in replace.items()})
        y = {}
        for on in (True, False):
            monkeypatch.setattr(guided, "SCATTER_SECOND", on)
            y[on] = np.asarray(build_model(sc, GUIDED, ("end",))(p))
        return y[True] - y[False], y[False]

    none, base = added(mu_s_per_m=0.0)
    assert np.abs(none).max() <= 1e-12 * base.max()
    a, _ = added(mu_s_per_m=0.01, end_reflectance=0.2)
    b, _ = added(mu_s_per_m=0.02, end_reflectance=0.2)
    c, _ = added(mu_s_per_m=0.01, end_reflectance=0.4)
    assert a.min() >= -1e-9 * a.max() and a.sum() > 0
    assert b.sum() / a.sum() == pytest.approx(2.0, rel=0.02)
    assert c.sum() / a.sum() == pytest.approx(4.0, rel=1e-6)
    # against term 1's light from the first return (the kernels' light with the second bounce off)
    monkeypatch.setattr(guided, "SCATTER_SECOND", False)
    first_kernels, _ = _term(monkeypatch, sc, mu_s_per_m=0.01, end_reflectance=0.2)
    t = np.arange(a.shape[-1])
    assert (a * t).sum() / a.sum() > (first_kernels * t).sum() / first_kernels.sum()
