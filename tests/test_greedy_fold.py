"""The greedy fit detector's model change with its contact-independent part computed once per detector
(``tofjax.invert.greedy._folded``): the same values as the unsplit compiled functions, the
contact-independent work out of what each evaluation runs, one split per model structure."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tofjax.invert.greedy as greedy

W = np.random.default_rng(0).normal(size=(6, 40))


class _Change(eqx.Module):
    """A stand-in change: a contact-independent factor (``cos(a)``, what the split must take out of the
    evaluation) times a contact-dependent one."""

    a: jax.Array

    def __call__(self, theta):
        return jnp.cos(self.a) * jnp.tanh(theta @ W)


def test_folded_equals_unsplit_and_leaves_the_known_part_out():
    theta = jnp.asarray([0.06, 0.11, 0.10, 0.05, 0.9, 0.3])
    n_before = len(greedy._SPLITS)
    for scale in (1.0, 0.7):  # two detectors: new data, same structure
        ch, sig = _Change(jnp.linspace(0.1, 2.0, 40) * scale), jnp.linspace(1.0, 3.0, 40) * scale
        fc = greedy._folded(greedy._change_over_sigma, ch, sig, (6,), jnp.float64)
        fj = greedy._folded(greedy._jacobian_over_sigma, ch, sig, (6,), jnp.float64)
        ref_c, ref_j = greedy._weighted_change(ch, sig, theta), greedy._weighted_jacobian(ch, sig, theta)
        np.testing.assert_allclose(fc(theta), ref_c, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(ref_c))))
        np.testing.assert_allclose(fj(theta), ref_j, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(ref_j))))
        # what an evaluation runs: the contact-dependent part only (cos(a) came in as an array)
        for f in (fc, fj):
            prog = str(jax.make_jaxpr(f)(theta))
            assert " cos " not in prog and "tanh" in prog, prog
    assert len(greedy._SPLITS) == n_before + 2  # one split of each per structure, not per detector


@pytest.mark.slow
def test_folded_guided_model_equals_unsplit():
    """On the guided model of the small scene (4 slots): change and Jacobian within 1e-12 of the unsplit ones."""
    from small_scenes import three_sensor_square

    from tofjax.invert.correction import OpticalParams

    sc = three_sensor_square()
    optical = dataclasses.replace(OpticalParams.from_scene(sc), optics="guided")
    change, dtype = greedy._contact_change(sc, optical, 4, 0.006)
    sig = jnp.asarray(np.linspace(3.0, 30.0, int(np.prod(sc.shape))))
    fc = greedy._folded(greedy._change_over_sigma, change, sig, (12,), dtype)
    fj = greedy._folded(greedy._jacobian_over_sigma, change, sig, (12,), dtype)
    rng = np.random.default_rng(1)
    for _ in range(3):
        t = jnp.asarray(np.r_[rng.uniform(0.02, 0.13, 8), rng.uniform(0, 1, 4)])
        for f, g in ((fc, greedy._weighted_change), (fj, greedy._weighted_jacobian)):
            ref = np.asarray(g(change, sig, t))
            assert np.max(np.abs(np.asarray(f(t)) - ref)) <= 1e-12 * np.max(np.abs(ref))


def test_folded_falls_back_to_the_unsplit_program_without_jax_partial_eval(monkeypatch):
    """The split uses JAX's private partial evaluation: where a JAX lacks it, the detector still works,
    through the unsplit compiled functions (the same values)."""
    from jax._src.interpreters import partial_eval as pe

    monkeypatch.delattr(pe, "partial_eval_jaxpr_nounits")
    theta = jnp.asarray([0.06, 0.11, 0.10, 0.05, 0.9, 0.3])
    ch, sig = _Change(jnp.linspace(0.1, 2.0, 40)), jnp.linspace(1.0, 3.0, 40)
    n_before = len(greedy._SPLITS)
    fc = greedy._folded(greedy._change_over_sigma, ch, sig, (6,), jnp.float64)
    assert fc.func is greedy._weighted_change and len(greedy._SPLITS) == n_before
    np.testing.assert_array_equal(fc(theta), greedy._weighted_change(ch, sig, theta))
