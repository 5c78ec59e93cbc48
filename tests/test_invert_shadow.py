"""Contacts that shadow (issue 14): the model method's signed contact response.

With the guided optics a skin contact mostly *removes* light (the far-edge return and the volume
light behind it); a detector that looks only for added light finds nothing. The fast tests give the
reconstruction a stand-in forward model (a contact's removed light, by geometry, no compilation); the
slow ones use the guided model itself on a small scene (15 cm guide, three sensors, coarse cells).
"""

import dataclasses

import jax
import numpy as np
import pytest

from tofjax.config import ConfigError
from tofjax.invert import InvertOptions, build_inverter, match
from tofjax.invert.correction import OpticalParams
from tofjax.invert.reconstruct import ReconstructOptions
from tofjax.model import ModelOptions, sample_counts
from tofjax.model.contact import SkinContact
from tofjax.scene import Touch
from tofjax.simulate import expected_counts

CONTACT = (0.085, 0.07)
from small_scenes import BINS, EDGE_BIN
from small_scenes import three_sensor_square as _small_scene


def _stand_in(scene, xy, strength=1.0):
    """What a contact that only shadows does to each (sensor, zone, bin), by geometry: the zones whose window
    holds it (shared linearly between neighbouring zone centres) lose part of their far-edge return (bin
    EDGE_BIN) and of the volume light behind it."""
    out = np.zeros(scene.shape)
    b = np.arange(BINS)
    for s, sp in enumerate(scene.sensors):
        dx, dy = xy[0] - sp.position_m[0], xy[1] - sp.position_m[1]
        off = (np.degrees(np.arctan2(dy, dx)) - sp.direction_deg + 180.0) % 360.0 - 180.0
        half = scene.sensor.fov_deg / 2
        if abs(off) >= half:
            continue
        width = scene.sensor.fov_deg / scene.sensor.zones
        share = np.clip(1.0 - np.abs(off + half - (np.arange(scene.sensor.zones) + 0.5) * width) / width, 0.0, 1.0)
        rb = 2 * np.hypot(dx, dy) * scene.waveguide.n1 / 2.998e8 / scene.sensor.bin_width_s  # its range, in bins
        lost = 150.0 * np.exp(-0.5 * ((b - EDGE_BIN) / 1.5) ** 2) + 15.0 * ((b > rb) & (b < EDGE_BIN))
        out[s] -= strength * share[:, None] * lost[None]
    return out


def _fake_response(scene, optical, centres, radius_m, chunk=128, *, shadow=False, signed=False):
    r = np.stack([_stand_in(scene, c) for c in np.asarray(centres)])
    return r if signed else (np.zeros_like(r) if not shadow else r)  # "added": a contact adds no light


@pytest.fixture()
def stand_in(monkeypatch):
    import tofjax.invert.reconstruct as rec

    monkeypatch.setattr(rec, "response_matrix", _fake_response)
    sc = _small_scene()
    base = np.broadcast_to(20.0 + 600.0 * np.exp(-0.5 * ((np.arange(BINS) - EDGE_BIN) / 1.5) ** 2), sc.shape).copy()
    optical = dataclasses.replace(OpticalParams.from_scene(sc), optics="guided")
    return sc, base, optical


def test_fast_shadow_only_contact_found_no_false_detection(stand_in):
    sc, base, optical = stand_in
    touch = base + _stand_in(sc, CONTACT)
    rng = np.random.default_rng(0)
    frames = rng.poisson(np.stack([touch] * 4 + [base] * 8)).astype(float)
    inv = _inverter(sc, base, optical, "auto")
    assert inv.reconstructor.response == "signed"  # from the guided calibration, no flag
    res = inv.process(frames)
    for det in res.detections[:4]:
        k, dist = match(det.positions(), np.array([CONTACT]), 0.02)
        assert k == 1 and len(det.touches) == 1 and dist[0] < 0.015
    assert all(not det.touches for det in res.detections[4:])  # no-touch frames: nothing
    assert np.isfinite(inv.noise).any() and not np.isnan(inv.noise).any()
    # the default optics keep the old column (a contact's added light): this contact adds none
    plain = dataclasses.replace(optical, optics="default")
    old = _inverter(sc, base, plain, "auto")
    assert old.reconstructor.response == "added"
    assert not old.process(frames[:1]).detections[0].touches


@pytest.fixture(scope="module")
def small():
    sc = _small_scene()
    guided = ModelOptions(optics="guided")
    base = expected_counts(sc, guided)
    # A contact that only shadows: skin that absorbs all it takes in (no light comes back).
    dark = ModelOptions(optics="guided", skin=SkinContact(mu_a_per_m=1e6))
    touch = expected_counts(sc.replace(touches=(Touch(CONTACT, 0.006, 1.0),)), dark)
    optical = dataclasses.replace(OpticalParams.from_scene(sc), optics="guided")
    return sc, base, touch, optical


def _inverter(sc, base, optical, response):
    ro = ReconstructOptions(cell_m=0.015, iterations=150, edge_exclusion_m=0.02, response=response)
    return build_inverter(sc, base, InvertOptions(method="model", reconstruct=ro), optical, n_baseline=100)


@pytest.mark.slow
def test_shadow_only_contact_is_found_and_no_touch_frames_stay_empty(small):
    sc, base, touch, optical = small
    d = touch - base
    assert d.clip(0).sum() < 1e-6 * -d.clip(None, 0).sum()  # the contact only removes light
    frames = np.asarray(
        jax.vmap(sample_counts, (0, None))(jax.random.split(jax.random.key(3), 6), np.stack([touch, base])),
        np.float64,
    )  # 3 touch frames, then 3 no-touch frames
    frames = frames.reshape(-1, *sc.shape)[[0, 2, 4, 1, 3, 5]]
    inv = _inverter(sc, base, optical, "auto")
    assert inv.reconstructor.response == "signed"  # from the guided calibration, no flag
    res = inv.process(frames)
    for det in res.detections[:3]:
        k, dist = match(det.positions(), np.array([CONTACT]), 0.02)
        assert k == 1 and len(det.touches) == 1 and dist[0] < 0.02  # 1.5 cm cells: within the studies' match radius
    assert all(not det.touches for det in res.detections[3:])


@pytest.mark.slow
def test_added_response_misses_the_shadow(small):
    sc, base, touch, optical = small
    # The old column (added light only) sees nothing of a contact that only shadows.
    res = _inverter(sc, base, optical, "added").process(touch[None])
    assert not any(
        abs(t["x_m"] - CONTACT[0]) < 0.02 and abs(t["y_m"] - CONTACT[1]) < 0.02 for t in res.detections[0].touches
    )


def test_response_option_checked():
    with pytest.raises(ConfigError, match="response"):
        ReconstructOptions(response="both")


def test_cli_contact_response_checked(tmp_path, capsys):
    from tofjax.cli import main

    # option errors come before any reading: the captures need not exist
    args = ["detect", str(tmp_path / "t.h5"), "--baseline", str(tmp_path / "b.h5"), "--json", str(tmp_path / "o.json")]
    rc = main([*args, "--method", "full", "--contact-response", "signed"])
    err = capsys.readouterr().err
    assert rc != 0 and "--contact-response applies to --method model only" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit) as e:
        main([*args, "--method", "model", "--contact-response", "both"])
    assert e.value.code != 0 and "invalid choice" in capsys.readouterr().err
