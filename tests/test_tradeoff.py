"""The trade-off study (experiments/study_tradeoff.py): a fast run on a tiny scene (the full study
is configs/studies/tradeoff.toml)."""

import json

import numpy as np
import pytest
from test_studies import load

from tofjax.config import ConfigError
from tofjax.scene import scene_from_dict

study = load("study_tradeoff")
Fidelity, TradeoffConfig, fastest_within, run_tradeoff = study.Fidelity, study.TradeoffConfig, study.fastest_within, study.run_tradeoff
main = study.main


def tiny_scene_file(tmp_path):
    sc = scene_from_dict({
        "name": "tiny",
        "waveguide": {"size_m": [0.08, 0.06], "thickness_m": 0.004, "n1": 1.4, "mu_s_per_m": 3.0, "mu_a_per_m": 0.5},
        "sensor": {"bin_width_s": 1e-10, "n_bins": 32, "zones": 2, "fov_deg": 40.0, "emission_time_s": 4e-10},
        "sensors": [{"position_m": [0.0, 0.03], "direction_deg": 0.0}],
    })
    path = tmp_path / "tiny.toml"
    path.write_text(sc.to_toml())
    return path


def test_tradeoff_fast_run(tmp_path):
    cfg = TradeoffConfig(
        scene=str(tiny_scene_file(tmp_path)), quick=True, budget=10.0, photon_ladder=(500, 1000),
        fidelities=(Fidelity("default"), Fidelity("q=1", quadrature=1), Fidelity("no shadowing", exclude=("shadowing",)),
                    Fidelity("float32", dtype="float32")),
    )
    r = run_tradeoff(cfg, tmp_path / "out", progress=False)
    out = tmp_path / "out"
    data = json.loads((out / "tradeoff.json").read_text())
    assert data["data"].startswith("simulated") and data["scene"] == "tiny"
    labels = [row["label"] for row in data["analytic"]]
    assert labels == ["default", "q=1", "float32"]  # no contacts: the shadowing rung does not apply
    for row in data["analytic"]:
        assert row["finite"] and row["seconds"] > 0 and 0 <= row["error_vs_mc"] < 2 and row["error_numerical"] >= 0
    # the numerical error of q=1 is larger than the default's, and both are small next to leaving out a term
    num = {row["label"]: row["error_numerical"] for row in data["analytic"]}
    assert num["q=1"] > num["default"]
    # the photon ladder: more photons, less noise
    mc = data["monte_carlo"]
    # (quick mode runs 250, 500 and 1000 photons against a 4000-photon reference: neighbouring
    # rungs differ by less than their scatter, the ends by about 1.8x)
    assert mc[-1]["error_vs_mc"] < mc[0]["error_vs_mc"]
    assert [c["group"].split(" ")[0] for c in data["components"]] == ["far", "scattering"]
    # budget 10: every setting qualifies, the fastest is named
    fastest = min(data["analytic"], key=lambda row: row["seconds"])["label"]
    assert data["fastest_within_budget_error_vs_mc"] == fastest
    assert "skipped" in data["fit_bias"] and "skipped" in data["contact_bias"]
    md = (out / "tradeoff.md").read_text()
    assert "Error budget 10" in md and fastest in md and "Monte Carlo" in md
    assert (out / "tradeoff.png").stat().st_size > 10_000
    assert r["wall_s"] > 0
    # the headline number: the analytic model at the default fidelity against the Monte Carlo
    assert data["analytic_vs_mc_relative_l2"] == data["analytic"][0]["error_vs_mc"]  # "default" is the default fidelity


def test_fastest_within_budget():
    rows = [{"label": "a", "seconds": 1.0, "e": 0.01}, {"label": "b", "seconds": 0.1, "e": 0.2},
            {"label": "c", "seconds": 0.5, "e": 0.05}, {"label": "d", "seconds": 0.01, "e": float("nan")}]
    assert fastest_within(rows, "e", 0.1)["label"] == "c"
    assert fastest_within(rows, "e", 1.0)["label"] == "b"
    assert fastest_within(rows, "e", 1e-3) is None


def test_tradeoff_config_validated(tmp_path, capsys):
    with pytest.raises(ConfigError, match="budget"):
        TradeoffConfig(budget=0)
    with pytest.raises(ConfigError, match="exclude"):
        Fidelity("x", exclude=("wobble",))
    bad = tmp_path / "t.toml"
    bad.write_text("budgett = 0.1\n")
    assert main(["--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "budgett" in capsys.readouterr().err
    assert main(["--scene", "no-such-scene", "--out", str(tmp_path / "o")]) == 2
    assert np.isfinite(TradeoffConfig(quick=True).effective().reference_photons)


def test_contact_bias_row_detects_analytic_contacts(tmp_path):
    """The contact-position row: the same contact from the Monte Carlo and from the analytic
    model, detected by tofjax.invert's back-projection; the analytic one is found near the truth."""
    _contact_bias = study._contact_bias
    from tofjax.scene import Touch, load_scene

    scene = load_scene(str(tiny_scene_file(tmp_path)))
    scene = scene.replace(touches=(Touch(position_m=(0.045, 0.03), radius_m=0.005, strength=1.0),))
    r = _contact_bias(scene, TradeoffConfig(reference_photons=500, fit_frames=4), None)
    assert r["detector"] == "detect_backprojection" and r["contacts_m"] == [[0.045, 0.03]]
    a, m = r["analytic"], r["monte_carlo"]
    assert a["matched_within_2cm"] == 1
    # one sensor with two 20-degree zones places the contact coarsely across, but its range
    # (the arrival time) is sharp
    # (detections come strongest first)
    x, y = next(p for p in a["positions_m"] if np.hypot(p[0] - 0.045, p[1] - 0.03) < 0.02)
    bin_range_m = 0.5 * 299_792_458.0 / 1.4 * 1e-10  # one 100 ps bin of range
    assert abs(np.hypot(x, y - 0.03) - 0.045) < bin_range_m
    assert a["touch_gain_counts"] > a["touch_loss_counts"] > 0
    for c in (a, m):
        assert c["true"] == 1 and np.isfinite([c["touch_gain_counts"], c["touch_loss_counts"]]).all()
