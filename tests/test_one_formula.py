"""Quantities computed in one place: the inversion's range speed takes the guided model's launched
beam (tofjax.model.guided.launch_band) and the light speed in the guide (speed_in_guide), and the
slab Monte Carlo the same c / n as the transport kernel."""

import dataclasses
import math
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np

from tofjax.invert.correction import OpticalParams
from tofjax.model import speed_in_guide
from tofjax.model.guided import _elevations, launch_band

from small_scenes import three_sensor_square


def test_range_speed_is_the_guided_models_launch_for_several_n1():
    """``OpticalParams.range_speed`` (floats) and the guided model's elevations (JAX, what the forward
    model evaluates) give identical numbers: ``2 c1 / (1/c_out + 2 n1/(n1 + 1))`` with the model's ``c_out``."""
    sc = three_sensor_square()
    for fov in (20.0, 63.0, 120.0):
        s = sc.replace(sensor=dataclasses.replace(sc.sensor, fov_deg=fov))
        gg = SimpleNamespace(fov=math.radians(fov), x=jnp.zeros(1), wx=jnp.zeros(1))
        for n1 in (1.05, 1.33, 1.41, 1.5, 2.4):
            el = _elevations(gg, jnp.asarray(n1))
            op = dataclasses.replace(OpticalParams.from_scene(s), optics="guided", n1=n1)
            c_out = float(el.c_out)
            assert op.range_speed(s) == 2.0 * speed_in_guide(n1) / (1.0 / c_out + 2.0 * n1 / (n1 + 1.0)), (fov, n1)
            assert float(el.mu_out) == 0.5 * float(launch_band(n1, math.radians(fov))[1])
            assert op.replace(optics="default").range_speed(s) == speed_in_guide(n1)
    # NumPy and JAX values alike, elementwise
    n1 = np.array([1.2, 1.5, 3.0])
    np.testing.assert_array_equal(np.stack(launch_band(n1, 1.0)), np.stack(launch_band(jnp.asarray(n1), 1.0)))


def test_slab_light_speed_is_the_models():
    from tofjax.mc.slab import SlabOptions, _SlabStatic

    for n in (1.0, 1.33, 1.4, 1.5):
        st = _SlabStatic(SlabOptions(n=n, thickness_m=0.002, mu_s_per_m=1000.0, mu_a_per_m=10.0, g=0.0, photons=1000))
        assert st.dyn["c1"] == speed_in_guide(n) == 299_792_458.0 / n
