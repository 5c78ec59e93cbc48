"""The forward model as physics: closed forms, limits, conservation, gradients, extremes."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from tofjax import ConfigError, ModelOptions, Params, build_model
from tofjax.model import SPEED_OF_LIGHT_M_PER_S as C
from tofjax.model import pile_up, sample_counts
from tofjax.scene import SensorModel, SensorPlacement, Touch


def strip_scene(base, *, size=(0.3, 0.3), n1=1.4, mu_s=0.6, mu_a=0.14, fov=1.0, zones=1, n_bins=128, **sensor):
    """One sensor at the middle of the bottom edge looking straight across (+y)."""
    wg = dataclasses.replace(base.waveguide, size_m=size, n1=n1, mu_s_per_m=mu_s, mu_a_per_m=mu_a)
    sm = SensorModel(bin_width_s=1e-10, n_bins=n_bins, zones=zones, fov_deg=fov, **sensor)
    return base.replace(
        waveguide=wg,
        sensor=sm,
        sensors=(SensorPlacement(position_m=(size[0] / 2, 0.0), direction_deg=90.0),),
        touches=(),
    )


def run(scene, opts=ModelOptions(), params=None, components=None):
    model = build_model(scene, opts, components)
    params = Params.from_scene(scene, opts.jnp_dtype) if params is None else params
    return model, params


def mean_bin_time(counts, width=1e-10):
    t = (np.arange(counts.shape[-1]) + 0.5) * width
    return float((counts * t).sum() / counts.sum())


# ---- closed forms --------------------------------------------------------------------------


@given(n1=st.floats(1.2, 2.5), length=st.floats(0.08, 0.4))
def test_end_peak_at_two_d_n1_over_c(optoskin, n1, length):
    """The far-edge reflection arrives at t_e + 2 d n1 / c (plus the pulse's mean delay, tau)."""
    scene = strip_scene(optoskin, size=(0.3, length), n1=n1)
    model, p = run(scene, components=("end",))
    counts = np.asarray(model.breakdown(p)["end"])[0, 0]
    expected = scene.sensor.emission_time + 2 * length * n1 / C + scene.sensor.pulse_tail_s
    assert mean_bin_time(counts) == pytest.approx(expected, abs=0.02e-10)
    # With a pulse much narrower than a bin, the peak bin is the one holding 2 d n1 / c.
    sharp = strip_scene(optoskin, size=(0.3, length), n1=n1, pulse_sigma_s=1e-13, pulse_tail_s=1e-13)
    m2, p2 = run(sharp, components=("end",))
    t = sharp.sensor.emission_time + 2 * length * n1 / C
    if abs(t / 1e-10 - round(t / 1e-10)) > 0.05:  # not on a bin edge
        assert int(np.argmax(np.asarray(m2(p2))[0, 0])) == int(t // 1e-10)


@given(mu_t=st.floats(0.0, 30.0), d=st.floats(0.03, 0.25))
def test_beer_lambert_touch(optoskin, mu_t, d):
    """A contact's signal falls as exp(-2 mu_t d) (Eq. 5), all else equal."""
    scene = strip_scene(optoskin, mu_s=0.0, mu_a=0.0, fov=20.0)
    scene = scene.replace(touches=(Touch(position_m=(0.15, d), radius_m=0.002, strength=1.0),))
    model, p0 = run(scene, components=("touch",))
    # model(p) is compiled with the model as an argument: one program for every example (a jitted
    # closure over each example's model compiled afresh per example)
    clear = float(model(p0).sum())
    lossy = float(model(p0.replace(mu_a_per_m=mu_t)).sum())
    # the disk spans d +- r, so compare with the chord-averaged transmittance
    r = 0.002
    u = np.cos(np.arange(1, 6) * np.pi / 6)
    w = np.sin(np.arange(1, 6) * np.pi / 6) ** 2
    g = 1 / ((d + r * u) ** 2 + 0.005**2)
    expected = (w * g * np.exp(-2 * mu_t * (d + r * u))).sum() / (w * g).sum()
    assert lossy / clear == pytest.approx(expected, rel=1e-6)
    assert lossy / clear == pytest.approx(math.exp(-2 * mu_t * d), rel=0.02)


def test_decay_corrected_touch_sums_to_strength(optoskin):
    """Over the zones that see all of it, a contact's counts / (K G T) equal its strength, at any distance."""
    for d in (0.05, 0.12, 0.25):
        scene = strip_scene(optoskin, fov=29.0, zones=7).replace(
            touches=(Touch(position_m=(0.153, d), radius_m=0.004, strength=0.7),)
        )
        model, p = run(scene, components=("touch",))
        total = float(model(p).sum())
        K = float(p.gain[0])
        dist = math.hypot(0.003, d)
        decay = K / (dist**2 + 0.005**2) * math.exp(-2 * (0.6 + 0.14) * dist)
        assert total / decay == pytest.approx(0.7, rel=0.01)


def test_touch_split_between_zones(optoskin):
    """A contact on a zone boundary appears in both zones, and only there."""
    scene = strip_scene(optoskin, fov=20.0, zones=2)  # boundary straight ahead
    scene = scene.replace(touches=(Touch(position_m=(0.15, 0.15), radius_m=0.01, strength=1.0),))
    model, p = run(scene, components=("touch",))
    per_zone = np.asarray(model(p)).sum(-1)[0]
    assert per_zone[0] == pytest.approx(per_zone[1], rel=1e-9) and per_zone[0] > 0
    off = scene.replace(touches=(Touch(position_m=(0.17, 0.15), radius_m=0.005, strength=1.0),))
    m2, p2 = run(off, components=("touch",))
    z = np.asarray(m2(p2)).sum(-1)[0]
    assert z[0] > 0 and z[1] == 0.0  # 7.6 deg clockwise of the axis: zone 0 only


def test_touch_shared_among_zones_by_area(optoskin):
    """A near contact spanning three zones is shared among them by its area in each zone's wedge (the chord
    law), not by its angular width: against points drawn uniformly over the disk (within 0.002 here; the
    angular-width law was 0.075 off: 36% in the zone holding 44% of the area). The Monte Carlo agrees
    (experiments/contact_zone_share_mc.py)."""
    scene = strip_scene(optoskin, fov=29.0, zones=7)
    x0, y0, rad = 0.153, 0.06, 0.006  # 6 cm ahead, 2.9 deg off the axis: over three zones
    scene = scene.replace(touches=(Touch(position_m=(x0, y0), radius_m=rad, strength=0.7),))
    model, p = run(scene, components=("touch",))
    per_zone = np.asarray(model(p)).sum(-1)[0]
    share = per_zone / per_zone.sum()
    rng = np.random.default_rng(0)
    r, a = rad * np.sqrt(rng.uniform(size=400_000)), rng.uniform(0, 2 * np.pi, 400_000)
    ang = np.degrees(np.arctan2(x0 + r * np.cos(a) - 0.15, y0 + r * np.sin(a)))  # clockwise of the axis (+y)
    edges = np.linspace(-14.5, 14.5, 8)
    area = np.histogram(-ang, edges)[0] / len(ang)  # zone 0 counter-clockwise, as Geometry orders them
    np.testing.assert_allclose(share, area, atol=0.01)


def test_volume_term_is_proportional_to_mu_s(optoskin):
    scene = strip_scene(optoskin, mu_s=0.5, mu_a=0.1)
    model, p = run(scene, components=("volume",))
    # hold mu_t fixed so only beta_vol changes
    a = np.asarray(model(p))
    b = np.asarray(model(p.replace(mu_s_per_m=0.25, mu_a_per_m=0.35)))
    np.testing.assert_allclose(b, 0.5 * a, rtol=1e-12, atol=1e-12)


def test_crosstalk_and_ambient_conserve_counts(optoskin):
    scene = strip_scene(optoskin)
    model, p = run(scene, components=("crosstalk", "ambient"))
    y = np.asarray(model(p))[0, 0]
    sm = scene.sensor
    assert y.sum() == pytest.approx(sm.crosstalk_counts + sm.ambient_counts * sm.n_bins, rel=1e-9)
    assert int(np.argmax(y)) in (14, 15, 16)  # the crosstalk peak near bin 14-15, as on real parts


def test_shadowing_dims_what_lies_behind(optoskin):
    near = Touch(position_m=(0.15, 0.08), radius_m=0.01, strength=1.0)
    far = Touch(position_m=(0.15, 0.2), radius_m=0.01, strength=1.0)
    scene = strip_scene(optoskin, fov=10.0).replace(touches=(near, far))
    with_shadow, p = run(scene, components=("touch", "shadowing", "end"))
    without, _ = run(scene, components=("touch", "end"))
    a, b = with_shadow.breakdown(p), without.breakdown(p)
    bins = np.arange(128)
    t_far = (scene.sensor.emission_time + 2 * 0.2 * 1.4 / C) / 1e-10
    late = bins > t_far - 3
    early = bins < (scene.sensor.emission_time + 2 * 0.08 * 1.4 / C) / 1e-10 + 3
    assert np.asarray(a["touch"])[0, 0, late].sum() < 0.9 * np.asarray(b["touch"])[0, 0, late].sum()
    np.testing.assert_allclose(np.asarray(a["touch"])[0, 0, early], np.asarray(b["touch"])[0, 0, early], rtol=0.02)
    assert np.asarray(a["end"]).sum() < np.asarray(b["end"]).sum()


def test_quadrature_converges(optoskin):
    """Bin-integration error falls with nodes per bin, and beyond the near field quadrature 2 is
    within a few 1e-4 of converged (a slow error there is read by a fit as attenuation)."""
    scene = load_touch_scene(optoskin)
    ref_m, ref_p = run(scene, ModelOptions(quadrature=16))
    ref = np.asarray(ref_m(ref_p))
    errs, ys = [], {}
    for q in (1, 2, 4):
        m, p = run(scene, ModelOptions(quadrature=q))
        ys[q] = np.asarray(m(p))
        errs.append(np.linalg.norm(ys[q] - ref) / np.linalg.norm(ref))
    assert errs[0] > errs[1] > errs[2]
    # measured: 2.3%, 0.33%, 0.17% (ratios 7.1, 1.9); before the distributed terms kept each node's
    # spread within its node: 2.0%, 0.55%, 0.20%; before the near field's mass was put where it sits
    # in its node: 6.2%, 1.9%, 0.62%. What is left at 4 is the near-field peak (bins at the emission)
    assert errs[1] < errs[0] / 2.5 and errs[2] < errs[1] / 1.5
    assert errs[1] < 0.005 and errs[2] < 0.0025
    # the tail over 5-13 cm of range, zone mean: measured +0.044% at most (multiple scattering's
    # build-up and T, sampled at node centres, are what is left); without the nodes' own spread -0.16%
    t = (np.arange(ref.shape[-1]) + 0.5) * scene.sensor.bin_width_s
    r = 0.5 * float(ref_p.c1) * (t - float(ref_p.emission_time_s))
    tail = (r > 0.05) & (r < 0.13)
    rel = (ys[2] - ref)[..., tail].mean((0, 1)) / ref[..., tail].mean((0, 1))
    assert np.abs(rel).max() < 8e-4


def load_touch_scene(optoskin):
    return optoskin.replace(
        touches=(
            Touch(position_m=(0.1, 0.2), radius_m=0.01, strength=1.0),
            Touch(position_m=(0.2, 0.12), radius_m=0.006, strength=0.5),
        )
    )


def test_left_out_components_are_not_traced(optoskin):
    base = build_model(optoskin)
    assert "touch" not in base.components and "shadowing" not in base.components
    p = Params.from_scene(optoskin)
    jaxpr_full = jax.make_jaxpr(lambda p: base(p))(p)
    only_end = build_model(optoskin, components=("end",))
    jaxpr_end = jax.make_jaxpr(lambda p: only_end(p))(p)
    # the model's call is one jitted equation: compare the printed programs, nested bodies included
    assert len(str(jaxpr_end).splitlines()) < 0.6 * len(str(jaxpr_full).splitlines())
    # expm1 appears only in the multiple-scattering term: absent when that term is left out
    assert "expm1" in str(jaxpr_full) and "expm1" not in str(jaxpr_end)
    with pytest.raises(ConfigError, match="unknown component"):
        build_model(optoskin, components=("nope",))


def test_float32_close_to_float64(optoskin):
    scene = load_touch_scene(optoskin)
    m64, p64 = run(scene)
    m32, p32 = run(scene, ModelOptions(dtype="float32"))
    y64, y32 = np.asarray(m64(p64)), np.asarray(m32(p32))
    assert y32.dtype == np.float32
    assert np.linalg.norm(y32 - y64) / np.linalg.norm(y64) < 1e-5


# ---- gradients ---------------------------------------------------------------------------


def test_gradients_match_central_differences(optoskin):
    """jax.grad (reverse mode, as fits use it) against central differences along a random
    direction in every parameter, float64; jax.jvp (forward mode) must agree too. The pulse
    has two tails with a non-zero slow weight, so its parameters are checked too."""
    scene = load_touch_scene(optoskin).replace(noise=optoskin.noise.__class__(pile_up=True))
    model, p = run(scene, ModelOptions(pulse_tails=2))
    # a light-entry width of 0 has no two-sided difference (widths are >= 0): checked at 20 ps
    p = p.replace(pulse_slow_weight=0.15, pulse_slow_tail_s=5.5e-10, crosstalk_width_s=2e-11)
    assert {"touch", "shadowing", "volume", "multiple_scattering"} <= set(model.components)
    weights = jax.random.uniform(jax.random.key(1), model.shape, jnp.float64)

    def loss(params):
        return jnp.sum(weights * model(params))

    # two compiled programs: value and gradient (reverse mode; its value serves the differences)
    # and forward mode (a separately jitted loss was a third, about 8 s of CPU)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    jvp_of = jax.jit(lambda q, t: jax.jvp(loss, (q,), (t,))[1])
    loss0, grad = value_and_grad(p)
    scale = abs(float(loss0))
    rng = np.random.default_rng(0)
    names = [f.name for f in dataclasses.fields(p)]
    checked = 0
    for name in names:
        value = np.asarray(getattr(p, name))
        # relative perturbations; zero-valued leaves get absolute ones of 1e-3
        direction = rng.normal(size=value.shape) * np.where(value != 0, np.abs(value), 1e-3)
        along_grad = float(np.sum(np.asarray(getattr(grad, name)) * direction))
        tangent = jax.tree_util.tree_map(jnp.zeros_like, p)
        tangent = eqx.tree_at(lambda t: getattr(t, name), tangent, jnp.asarray(direction))
        jvp = jvp_of(p, tangent)
        eps = 1e-6
        plus = float(value_and_grad(p.replace(**{name: value + eps * direction}))[0])
        minus = float(value_and_grad(p.replace(**{name: value - eps * direction}))[0])
        fd = (plus - minus) / (2 * eps)
        tol = dict(rel=2e-4, abs=1e-6 * scale)
        assert along_grad == pytest.approx(fd, **tol), name
        assert float(jvp) == pytest.approx(along_grad, rel=1e-9, abs=1e-9 * scale), name
        checked += 1
    assert checked == len(names) >= 20


# ---- extremes ----------------------------------------------------------------------------

GRID = [(mu_s, mu_a, n1) for mu_s in (0.0, 1e-3, 1e3) for mu_a in (0.0, 1e-3, 1e3) for n1 in (1.0001, 1.4, 3.5)]
# whole decades of mu_s and mu_a (n1 at its extremes where scattering is 0 or 1e3 /m), built from scenes
# (validation included): tests/test_extremes.py's sweep, here so one compiled value-and-gradient serves both
DECADES = (0.0, 1e-2, 1.0, 1e2, 1e3)
DECADE_GRID = [(mu_s, mu_a, n1) for mu_s in DECADES for mu_a in DECADES
               for n1 in ((1.0001, 3.5) if mu_s in (0.0, 1e3) else (1.4,))]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_no_nan_or_inf_at_the_extremes(optoskin, dtype):
    """Value and gradient stay finite over mu_s, mu_a in {0, 1e-3, 1e3} /m, n1 in {1.0001, 1.4, 3.5},
    whole decades of mu_s and mu_a from 0 to 1e3 /m (scenes the scene validation accepts), counts
    up to 1e9, emission at bin 0, tiny and huge pulses, contacts at a sensor and at the far edge.
    With pile-up: the model without it is the same program up to its last step, so a NaN there
    reaches this value and gradient too."""
    s0 = optoskin.sensors[0].position_m
    scene = optoskin.replace(
        touches=(
            Touch(position_m=s0, radius_m=0.005, strength=1.0),  # on top of sensor 0
            Touch(position_m=(0.3, 0.3), radius_m=0.01, strength=1.0),  # the far corner
            Touch(position_m=(0.15, 0.15), radius_m=0.01, strength=1.0),
        ),
        noise=optoskin.noise.__class__(pile_up=True),
    )
    opts = ModelOptions(dtype=dtype)
    model = build_model(scene, opts)
    base = Params.from_scene(scene, opts.jnp_dtype)

    @jax.jit
    def value_and_grad(p):
        return jax.value_and_grad(lambda q: jnp.sum(jnp.log1p(model(q))))(p)

    def finite(tree):
        return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(tree))

    variants = [base.replace(mu_s_per_m=a, mu_a_per_m=b, n1=c) for a, b, c in GRID]
    variants += [Params.from_scene(scene.replace(waveguide=dataclasses.replace(scene.waveguide, mu_s_per_m=a, mu_a_per_m=b, n1=c)),
                                   opts.jnp_dtype) for a, b, c in DECADE_GRID]
    labels = GRID + DECADE_GRID
    variants += [
        base.replace(gain=np.full(6, 1e9 * 0.01), crosstalk_counts=np.full((6, 7), 1e9)),  # ~1e9 counts
        base.replace(emission_time_s=0.0),  # light enters in bin 0
        base.replace(pulse_sigma_s=1e-16, pulse_tail_s=1e-16),
        base.replace(pulse_sigma_s=1e-8, pulse_tail_s=1e-8),
        base.replace(gain=np.zeros(6), crosstalk_counts=np.zeros((6, 7)), ambient_counts=np.zeros((6, 7))),
        base.replace(shadow_opacity=1.0, touch_radius_m=np.full(3, 0.3)),
    ]
    for i, v in enumerate(variants):
        val, grad = value_and_grad(v)
        assert finite(val) and finite(grad), f"variant {i}: {labels[i] if i < len(labels) else ''}"
        y = np.asarray(model(v))
        assert np.isfinite(y).all() and (y >= -1e-3 * max(1.0, np.abs(y).max())).all()


def test_printed_paper_attenuation_survives():
    from tofjax import load_scene

    scene = load_scene("optoskin-paper").replace(touches=(Touch(position_m=(0.15, 0.15), radius_m=0.01, strength=1),))
    model, p = run(scene)

    @jax.jit  # one compiled program for value and gradient (eager, this test took 35 s cold)
    def value_and_grad(q):
        y, vjp = jax.vjp(model, q)
        return y, vjp(jnp.ones_like(y))[0]

    y, g = value_and_grad(p)
    assert np.isfinite(np.asarray(y)).all()
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(g))


# ---- noise -------------------------------------------------------------------------------


def test_poisson_noise_is_reproducible_and_unbiased():
    lam = jnp.array([0.0, 0.5, 10.0, 1e3, 1e5, 1e9])
    a = sample_counts(jax.random.key(3), jnp.broadcast_to(lam, (4000, 6)))
    b = sample_counts(jax.random.key(3), jnp.broadcast_to(lam, (4000, 6)))
    np.testing.assert_array_equal(a, b)
    mean = np.asarray(a).mean(0)
    stderr = np.sqrt(np.asarray(lam) / 4000)
    assert (np.abs(mean - np.asarray(lam)) <= 4 * stderr + 1e-12).all()
    assert mean[0] == 0 and np.isfinite(np.asarray(a)).all()
    var = np.asarray(a).var(0)
    np.testing.assert_allclose(var[2:5], np.asarray(lam)[2:5], rtol=0.1)
    assert float(sample_counts(jax.random.key(0), jnp.array([1e9]), saturation=2**24 - 1)[0]) == 2**24 - 1


def test_frames_reuse_one_compiled_program():
    """``sample_frames`` (what ``simulate`` and ``mc_capture`` draw with) compiles once per shape and
    noise setting: a second capture with another seed and frame count of that shape compiles nothing,
    and its frames are what ``sample_counts`` draws from the same keys."""
    from tofjax.model import sample_frames

    lam = jnp.linspace(0.0, 50.0, 24).reshape(2, 12)
    keys = jax.random.split(jax.random.key(7), 5)
    a = sample_frames(keys, lam, poisson=True, saturation=30.0)
    n = sample_frames._cache_size()
    b = sample_frames(jax.random.split(jax.random.key(8), 5), lam + 1.0, poisson=True, saturation=30.0)
    assert sample_frames._cache_size() == n
    assert a.shape == b.shape == (5, 2, 12) and float(a.max()) <= 30.0
    np.testing.assert_array_equal(a[3], sample_counts(keys[3], lam, poisson=True, saturation=30.0))


def test_pile_up_limits():
    low = jnp.full((64,), 1.0)
    np.testing.assert_allclose(pile_up(low, 250_000), low, rtol=1e-3)
    high = jnp.full((64,), 1e5)
    out = np.asarray(pile_up(high, 250_000))
    assert out.sum() < 250_000  # at most one detection per laser pulse
    assert out[0] > out[-1]  # early bins steal the detections of late ones


def test_light_entry_width(optoskin):
    """Params.crosstalk_width_s: zero gives the point-like peak of before exactly (the peak
    deposited and pulsed with the other components); a width keeps the peak's counts and its
    mean time, widens it by the width in quadrature, and its gradient is finite at 0 and above."""
    scene = strip_scene(optoskin, zones=2, n_bins=64)
    model, p = run(scene, components=("interface", "end", "crosstalk", "ambient"))

    @jax.jit
    def parts(p):
        masses = model._node_masses(p)
        before = model._finish(model._apply_pulse(sum(masses.values()), p), p)
        R, P = model.linear_parts(p)
        return before, model(p), p.gain[:, None, None] * R + p.crosstalk_counts[..., None] * P + p.ambient_counts[..., None]

    before, now, linear = (np.asarray(x) for x in parts(p))
    np.testing.assert_allclose(now, before, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(linear, before, rtol=1e-12, atol=1e-9)
    peak = jax.jit(lambda w: model.light_entry_peak(p.replace(crosstalk_width_s=w)))
    point, wide = np.asarray(peak(0.0)), np.asarray(peak(40e-12))
    assert wide.sum() == pytest.approx(point.sum(), rel=1e-9)
    assert mean_bin_time(wide) == pytest.approx(mean_bin_time(point), abs=1e-13)
    t = (np.arange(64) + 0.5) * 1e-10
    var = lambda c: float((c * (t - mean_bin_time(c)) ** 2).sum() / c.sum())  # noqa: E731
    assert var(wide) - var(point) == pytest.approx(40e-12**2, rel=0.02)
    f = jax.jit(jax.vmap(jax.grad(lambda w: jnp.sum(model(p.replace(crosstalk_width_s=w)) ** 2) * 1e-6)))
    g = np.asarray(f(jnp.asarray([0.0, 30e-12])))
    assert np.isfinite(g).all() and g[1] != 0.0


def test_continuous_where_the_emission_sits_on_a_node_edge():
    """A round emission time (1 bin, 2 nodes per bin) puts a node edge exactly on the emission. The model there
    equals its limit from both sides (1e-12 either way): XLA evaluated the near field's split of the edge's node
    (components.node_falloff_after_emission) with two roundings of the edge's range, and a placeholder in the
    branch not taken then gave the node's spread 11% too much (0.15% of the first bins; the vmapped simulator and
    the model's own program disagreed there)."""
    from tofjax.scene import scene_from_dict

    sc = scene_from_dict({
        "waveguide": {"size_m": [0.1, 0.08], "thickness_m": 0.004, "n1": 1.4, "mu_s_per_m": 0.5, "mu_a_per_m": 0.1},
        "sensor": {"bin_width_s": 1e-10, "n_bins": 24, "zones": 3, "fov_deg": 30.0, "emission_time_s": 1e-10},
        "sensors": [{"position_m": [0.0, 0.04], "direction_deg": 0.0}],
    })
    model, p = run(sc, components=("multiple_scattering",))
    at = np.asarray(model(p))
    for e in (-1e-12, 1e-12):
        near = np.asarray(model(p.replace(emission_time_s=p.emission_time_s * (1 + e))))
        np.testing.assert_allclose(at, near, rtol=1e-9, atol=1e-12 * at.max())
