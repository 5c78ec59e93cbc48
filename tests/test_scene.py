"""Scene files: validation with one-line messages, defaults, round trips, the shipped configs."""

import math
from pathlib import Path

import numpy as np
import pytest

from tofjax import ConfigError, load_scene
from tofjax.model.geometry import zone_edges
from tofjax.scene import scene_from_dict, scene_from_json

CONFIGS = Path(__file__).parents[1] / "configs"

MINIMAL = """
[waveguide]
size_m = [0.30, 0.30]
thickness_m = 0.005
n1 = 1.4
mu_s_per_m = 0.6
mu_a_per_m = 0.14

[sensor]
bin_width_s = 1.0e-10
n_bins = 128
zones = 7
fov_deg = 29.0

[[sensors]]
position_m = [0.15, 0.0]
direction_deg = 90.0

[[touches]]
position_m = [0.10, 0.20]
radius_m = 0.01
strength = 1.0
"""


def write(tmp_path, text):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


def test_minimal_scene_is_complete(tmp_path):
    scene = load_scene(write(tmp_path, MINIMAL))
    assert scene.shape == (1, 7, 128)
    assert scene.sensor.emission_time == pytest.approx(14.5e-10)
    assert scene.waveguide.near_field == 0.005
    assert "touch" in scene.components() and "volume" in scene.components()


@pytest.mark.parametrize("name", sorted(p.stem for p in CONFIGS.glob("*.toml")))
def test_shipped_scenes_load(name):
    scene = load_scene(CONFIGS / f"{name}.toml")
    assert scene.name == name
    # built-in names resolve to the same scene
    assert load_scene(name) == scene


BAD = [
    ("[waveguide]\n", "n1 = 1.4", "n1 = 1.4\ncolour = 3", "waveguide.colour: unknown key"),
    ("", "thickness_m = 0.005\n", "", "waveguide.thickness_m: missing key"),
    ("", "n1 = 1.4", 'n1 = "high"', "waveguide.n1: expected a number"),
    ("", "n1 = 1.4", "n1 = 1.0", "waveguide.n1: must be > 1"),
    ("", "n1 = 1.4", "n1 = 0.9", "waveguide.n1: must be > 1"),
    ("", "size_m = [0.30, 0.30]", "size_m = [0.30, -0.30]", "waveguide.size_m[1]: must be > 0"),
    ("", "size_m = [0.30, 0.30]", "size_m = [0.30]", "waveguide.size_m: expected a list of 2"),
    ("", "thickness_m = 0.005", "thickness_m = -0.005", "waveguide.thickness_m: must be > 0"),
    ("", "thickness_m = 0.005", "thickness_m = 1e-300", "waveguide.thickness_m: must be in [1 um, 1 m]"),
    ("", "size_m = [0.30, 0.30]", "size_m = [0.30, 1e-300]", "waveguide.size_m[1]: must be in [1 mm, 1 km]"),
    ("", "mu_s_per_m = 0.6", "mu_s_per_m = -0.6", "waveguide.mu_s_per_m: must be >= 0"),
    ("", "fov_deg = 29.0", "fov_deg = 0.0", "sensor.fov_deg: must be in (0, 180)"),
    ("", "fov_deg = 29.0", "fov_deg = -5", "sensor.fov_deg: must be in (0, 180)"),
    ("", "n_bins = 128", "n_bins = 12.5", "sensor.n_bins: expected an integer"),
    ("", "position_m = [0.15, 0.0]", "position_m = [0.15, 0.1]", "sensors[0].position_m: sensor at (0.15, 0.1) m is not on the edge"),
    ("", "position_m = [0.15, 0.0]", "position_m = [0.45, 0.0]", "sensors[0].position_m"),
    ("", "direction_deg = 90.0", "direction_deg = 270.0", "sensors[0].direction_deg: the optical axis"),
    ("", "position_m = [0.10, 0.20]", "position_m = [0.10, 0.35]", "touches[0].position_m: touch at (0.1, 0.35) m is outside"),
    ("", "radius_m = 0.01", "radius_m = 0.0", "touches[0].radius_m: must be > 0"),
    ("", "strength = 1.0", "strength = true", "touches[0].strength: expected a number"),
]


@pytest.mark.parametrize("_, old, new, message", BAD, ids=[b[3][:40] for b in BAD])
def test_bad_scenes_name_key_and_reason(tmp_path, _, old, new, message):
    assert old in MINIMAL
    path = write(tmp_path, MINIMAL.replace(old, new, 1))
    with pytest.raises(ConfigError) as e:
        load_scene(path)
    text = str(e.value)
    assert message in text
    assert "\n" not in text and str(path) in text


def test_unknown_top_level_table_and_missing_sensor_table(tmp_path):
    with pytest.raises(ConfigError, match=r"sensros: unknown key.*known keys here"):
        load_scene(write(tmp_path, MINIMAL + "\n[[sensros]]\nposition_m = [0, 0]\n"))
    with pytest.raises(ConfigError, match="sensors: missing key"):
        load_scene(write(tmp_path, MINIMAL.split("[[sensors]]")[0]))


def test_not_toml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scene(write(tmp_path, "[waveguide\n"))
    with pytest.raises(ConfigError, match="no such file"):
        load_scene(tmp_path / "nope.toml")


def test_shapes_must_fit_inside(tmp_path):
    ring = MINIMAL + '\n[[touches]]\nshape = "ring"\nposition_m = [0.15, 0.15]\nring_radius_m = 0.2\nradius_m = 0.005\nstrength = 1.0\n'
    with pytest.raises(ConfigError, match=r"touches\[1\].position_m: ring \(part \d+\)"):
        load_scene(write(tmp_path, ring))
    bad_shape = MINIMAL.replace("strength = 1.0", 'strength = 1.0\nshape = "blob"')
    with pytest.raises(ConfigError, match="touches\\[0\\].shape: must be one of"):
        load_scene(write(tmp_path, bad_shape))


def test_components_auto_and_explicit(tmp_path):
    scene = load_scene(write(tmp_path, MINIMAL.replace("mu_s_per_m = 0.6", "mu_s_per_m = 0.0")))
    comps = scene.components()
    assert "volume" not in comps and "multiple_scattering" not in comps
    assert "touch" not in scene.without_touches().components()
    assert "shadowing" not in scene.without_touches().components()
    explicit = load_scene(write(tmp_path, MINIMAL + '\n[model]\ncomponents = ["end", "touch"]\n'))
    assert explicit.components() == ("end", "touch")
    with pytest.raises(ConfigError, match="model.components: unknown component 'bogus'"):
        load_scene(write(tmp_path, MINIMAL + '\n[model]\ncomponents = ["bogus"]\n'))


def test_round_trips(tmp_path, optoskin):
    ring = load_scene("touch-ring")
    for scene in (optoskin, ring):
        assert scene_from_json(scene.to_json()) == scene
        assert load_scene(write(tmp_path, scene.to_toml())) == scene


def test_stick_and_ring_elements():
    stick = load_scene("touch-stick").touches[0]
    el = stick.elements()
    ends = np.linalg.norm(el[-1, :2] - el[0, :2])
    assert ends == pytest.approx(stick.length_m)
    ring = load_scene("touch-ring").touches[0]
    r = np.linalg.norm(ring.elements()[:, :2] - np.array(ring.position_m), axis=1)
    np.testing.assert_allclose(r, ring.ring_radius_m)


def test_optoskin_coverage(optoskin):
    """Every point of the surface is inside at least one sensor's field of view (seed 000 section 4.1)."""
    lx, ly = optoskin.waveguide.size_m
    g = np.linspace(0.0025, lx - 0.0025, 160)
    X, Y = np.meshgrid(g, np.linspace(0.0025, ly - 0.0025, 160))
    seen = np.zeros(X.shape, bool)
    half = math.radians(optoskin.sensor.fov_deg) / 2
    for s in optoskin.sensors:
        a = np.arctan2(Y - s.position_m[1], X - s.position_m[0]) - math.radians(s.direction_deg)
        seen |= np.abs((a + np.pi) % (2 * np.pi) - np.pi) <= half
    assert seen.all(), f"{(~seen).sum()} grid points unseen"


def test_zone_edges_tile_the_fov():
    e = zone_edges(29.0, 7)
    assert e.shape == (7, 2)
    np.testing.assert_allclose(e[1:, 0], e[:-1, 1])
    assert e[0, 0] == pytest.approx(-math.radians(14.5)) and e[-1, 1] == pytest.approx(math.radians(14.5))


def test_scene_from_dict_rejects_wrong_table_type():
    with pytest.raises(ConfigError, match="waveguide: expected a table"):
        scene_from_dict({"waveguide": 3, "sensor": {}, "sensors": []})


def test_nested_list_type_is_named_in_plain_words():
    """A malformed nested list names its type in words ("lists of 2 numbers", not "a numberss")."""
    from tofjax.config import _type_name

    assert _type_name(tuple[tuple[float, float], ...]) == "a list of lists of 2 numbers"
    assert _type_name(tuple[float, float]) == "a list of 2 numbers"
    assert _type_name(tuple[bool, ...]) == "a list of booleans"
