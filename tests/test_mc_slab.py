"""Slab mode of the Monte Carlo against references no one here wrote.

Adding-doubling (Prahl's iadpython), van de Hulst's MCML test slab, closed forms of a clear
slab, and time-resolved diffusion theory for a semi-infinite medium. The full grid of the
issue (n, g, albedo, optical thickness) is the slow test; a few cases run by default.
"""

import json
import math

import numpy as np
import pytest
from test_studies import load

from tofjax.cli import main
from tofjax.config import ConfigError
from tofjax.mc.slab import SlabOptions, run_slab

iad = pytest.importorskip("iadpython")

C = 299_792_458.0
study = load("validate_mc_slab")
CASES = {c["name"]: c for c in study.cases()}


def _assert_agrees(case, photons, seed=0):
    """Within 1% or 3 standard errors, as the issue asks, on both faces."""
    row = study.compare(case, photons, seed)
    for k in ("diffuse_reflectance", "total_transmittance"):
        r = row[k]
        assert r["pass"], f"{case['name']} {k}: MC {r['mc']:.5f} +- {r['se']:.5f}, reference {r['reference']:.5f}"
    return row


def test_clear_slab_closed_form():
    """No scattering: multiple reflections between the faces, each escape attenuated up to its face.

    Regression: the old tally attenuated escapes over the whole (path-length-limited) step, so
    almost nothing escaped from an absorbing clear slab.
    """
    n, d, mu_a = 1.4, 5e-3, 200.0
    r = run_slab(SlabOptions(n=n, thickness_m=d, mu_s_per_m=0.0, mu_a_per_m=mu_a, g=0.0, photons=64, dtype="float64"))
    R = ((n - 1) / (n + 1)) ** 2
    e = math.exp(-mu_a * d)
    den = 1 - R**2 * e**2
    assert r.total_transmittance == pytest.approx((1 - R) ** 2 * e / den, rel=1e-9)
    assert r.diffuse_reflectance == pytest.approx((1 - R) ** 2 * R * e**2 / den, rel=1e-9)
    assert r.absorbed == pytest.approx(1 - R - r.total_transmittance - r.diffuse_reflectance, rel=1e-9)
    assert r.specular_reflectance == pytest.approx(R)
    assert r.diffuse_reflectance_se < 1e-6  # every packet alike (rounding only)


def test_van_de_hulst_slab():
    """The MCML test slab (g = 0.75). Regression: the old direction flip gave R_d 0.666, T_t 0.138."""
    row = _assert_agrees(CASES["van de Hulst (MCML)"], photons=20_000)
    assert row["diffuse_reflectance"]["se"] < 0.003


FAST = ["n=1.4 g=0.9 a=0.9 tau=1", "n=1 g=0 a=0.99 tau=1", "n=1.4 g=0.75 a=0.9 tau=10"]


@pytest.mark.parametrize("name", FAST)
def test_adding_doubling_fast_subset(name):
    _assert_agrees(CASES[name], photons=20_000)


@pytest.mark.slow
@pytest.mark.parametrize("name", [k for k in CASES if k not in FAST])
def test_adding_doubling_full_grid(name):
    _assert_agrees(CASES[name], photons=100_000)


def test_standard_errors_are_honest():
    """Two seeds differ by about sqrt(2) standard errors, not by much more (nor zero)."""
    case = CASES["n=1 g=0 a=0.9 tau=1"]
    opts = dict(n=1.0, thickness_m=case["thickness_m"], mu_s_per_m=case["mu_s_per_m"], mu_a_per_m=case["mu_a_per_m"], g=0.0)
    a, b = (run_slab(SlabOptions(**opts, photons=20_000, seed=s)) for s in (1, 2))
    z = []
    for k in ("diffuse_reflectance", "total_transmittance", "absorbed"):
        z.append((getattr(a, k) - getattr(b, k)) / math.hypot(getattr(a, k + "_se"), getattr(b, k + "_se")))
    assert all(abs(v) < 4 for v in z) and any(v != 0 for v in z)


def _diffusion_reflectance(t, mu_s_prime, mu_a):
    """Time-resolved diffuse reflectance of a semi-infinite medium (n = 1), integrated over the surface.

    Patterson, Chance & Wilson (1989) with the extrapolated boundary (a negative image at
    z0 + 2 z_e, z_e = 2 D; Haskell et al. 1994; Contini et al. 1997 for the flux form):
    R(t) = (4 pi D c)^-1/2 t^-3/2 exp(-mu_a c t) [z0 e^(-z0^2/4Dct) + z+ e^(-z+^2/4Dct)] / 2.
    """
    D = 1.0 / (3.0 * (mu_a + mu_s_prime))
    z0, zp = 1.0 / mu_s_prime, 1.0 / mu_s_prime + 4.0 * D
    a = (4 * math.pi * D * C) ** -0.5 * t**-1.5 * np.exp(-mu_a * C * t)
    return a * 0.5 * (z0 * np.exp(-(z0**2) / (4 * D * C * t)) + zp * np.exp(-(zp**2) / (4 * D * C * t)))


def test_time_resolved_reflectance_matches_diffusion_theory():
    """Semi-infinite medium: R(t) after the first ~20 transport mean free times follows diffusion
    theory, and its late decay gives back mu_a c."""
    mu_s, mu_a, dt, nt = 500.0, 10.0, 50e-12, 20
    r = run_slab(SlabOptions(n=1.0, thickness_m=1.0, mu_s_per_m=mu_s, mu_a_per_m=mu_a, g=0.0, photons=16_384,
                             time_bins=nt, time_bin_s=dt))
    R = r.reflectance_rho_t.sum(0)
    edges = np.arange(nt + 1) * dt
    fine = np.linspace(0, nt * dt, 20 * nt + 1)[1:]
    ref = np.array([np.trapezoid(_diffusion_reflectance(fine[(fine > a) & (fine <= b)], mu_s, mu_a), dx=dt / 20)
                    for a, b in zip(edges[:-1], edges[1:])])
    early, late = slice(3, 8), slice(8, 20)  # 150-400 ps and 400-1000 ps (1 / (mu_s' c) = 6.7 ps)
    # the Monte Carlo sits above diffusion theory by +4.3% early and +5.0-6.2% late (means of 16
    # seeds, the same for the kernel at 71e0f30 and the faster one: 0.0597 / 0.0596 early, 0.01277 /
    # 0.01264 late), and one run of 16384 photons scatters by 2.5% (early) and 2.2% (late): the
    # margins are that offset plus 3 standard deviations (5% and 8% passed at 71e0f30's seed 0 by luck)
    assert R[early].sum() == pytest.approx(ref[early].sum(), rel=0.12)
    assert R[late].sum() == pytest.approx(ref[late].sum(), rel=0.13)
    assert r.lost > 0  # the window ends the walk; packets are stopped, not lost from the ledger


def test_slab_options_validated():
    with pytest.raises(ConfigError, match="thickness_m"):
        SlabOptions(thickness_m=0.0)
    with pytest.raises(ConfigError, match="anisotropy"):
        SlabOptions(g=1.0)


def test_cli_slab_writes_json(tmp_path, capsys):
    out = tmp_path / "slab.json"
    rc = main(["mc", "slab", "--n", "1.4", "--thickness-m", "0.005", "--mu-s-per-m", "200", "--mu-a-per-m", "2",
               "--g", "0.9", "--photons", "20000", "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    for k in ("diffuse_reflectance", "total_transmittance", "absorbed"):
        assert 0 < res[k] < 1 and 0 < res[k + "_se"] < 0.05
    total = res["diffuse_reflectance"] + res["total_transmittance"] + res["absorbed"] + res["specular_reflectance"]
    assert total == pytest.approx(1.0, abs=0.02)  # roulette is unbiased, not exact
    assert main(["mc", "slab", "--photons", "10"]) == 2  # no --json
    assert "--json" in capsys.readouterr().err
