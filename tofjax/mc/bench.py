"""``tofjax bench tradeoff``: the analytic model against the Monte Carlo, and what it costs (issue 14).

A small, fixed benchmark (the full trade-off study with fits and ladders is
``experiments/study_tradeoff.py``). For a baseline scene and a touch scene it runs the Monte
Carlo reference and the analytic model at the default fidelity, with the default optics and
with the guided optics (:mod:`tofjax.model.guided`), and reports

* ``analytic_vs_mc_relative_l2``: ``{optics: {"baseline": e, "touch": e}}``, the relative L2
  error of the histograms with one gain per sensor profiled out (the Monte Carlo's absolute
  efficiency is a convention), comparing the transported light only (no light-entry peak, no
  ambient, no roughness: no transport simulates them, and the Monte Carlo has no roughness);
* ``gain_scale``: the profiled gains (1 where the absolute amplitudes agree);
* ``forward_cost``: seconds per evaluation of the whole jitted forward model of each scene
  (every component the scene needs), default and guided optics timed alternately, and the
  median of the per-pair ratios guided / default;
* ``reference``: the Monte Carlo's settings, time, and its own noise (two halves of the photons
  with different seeds: their difference over sqrt 2 over the mean, halved for the average).

The guided optics get the physical volume backscatter of the Monte Carlo's phase function
(``volume_backscatter_fraction`` = the Henyey-Greenstein backward share, 0.5 for ``g = 0``) and,
on the touch scene, the skin model both sides use (:class:`~tofjax.model.contact.SkinContact`).
The default optics keep the scene's parameters, as calibrated. All data are simulated.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import time
from dataclasses import dataclass

import numpy as np

from ..config import ConfigError

__all__ = ["BenchOptions", "profiled_relative_l2", "run_bench_tradeoff", "NOT_TRANSPORTED"]

#: Terms no photon transport simulates (light entry, ambient) or the Monte Carlo leaves out (roughness).
NOT_TRANSPORTED = ("crosstalk", "ambient", "interface")


@dataclass(frozen=True)
class BenchOptions:
    """Settings of ``tofjax bench tradeoff``.

    - ``scene``, ``touch_scene``: built-in names or TOML files; the touch scene must have contacts.
    - ``photons``: Monte Carlo packets per sensor for each reference (split in two seeds; 1e5:
      relative noise ~0.05 on the baseline, ~0.1 on the touch scene).
    - ``seed``: the references use ``seed`` and ``seed + 1``.
    - ``g``: Henyey-Greenstein anisotropy of the Monte Carlo (and the guided optics' backscatter).
    - ``nee_points``: the Monte Carlo's elevation nodes for next-event estimation (24: its
      own quadrature error is then below its noise; the default 6 puts the far-edge return at
      three discrete delays).
    - ``repeats``: timed pairs of forward evaluations.
    - ``elevations``: the guided optics' elevation nodes.
    """

    scene: str = "optoskin"
    touch_scene: str = "touch-three-line"
    photons: int = 100_000
    seed: int = 0
    g: float = 0.0
    nee_points: int = 24
    repeats: int = 31
    elevations: int = 8
    batch: int = 32_768

    def __post_init__(self):
        for k, lo in (("photons", 2), ("repeats", 1), ("nee_points", 1), ("elevations", 1), ("batch", 1), ("seed", 0)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ConfigError(f"{k}: must be an integer >= {lo}, got {v!r}")
        if isinstance(self.g, bool) or not isinstance(self.g, (int, float)) or not -0.99 <= float(self.g) <= 0.99:
            raise ConfigError(f"g: must be a number in [-0.99, 0.99], got {self.g!r}")


def profiled_relative_l2(ref: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    """Relative L2 error of ``y`` (S, Z, B) against ``ref`` with one scale per sensor fitted (least squares)."""
    ref, y = np.asarray(ref, np.float64), np.asarray(y, np.float64)
    num = np.sum(ref * y, axis=(1, 2))
    den = np.sum(y * y, axis=(1, 2))
    scale = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    err = np.linalg.norm(ref - scale[:, None, None] * y) / max(np.linalg.norm(ref), 1e-300)
    return float(err), scale


def _machine() -> dict:
    import jax

    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {"platform": platform.platform(), "machine": platform.machine(), "cpus": os.cpu_count(),
            "jax_backend": jax.default_backend(), "jax_devices": len(jax.devices()),
            "load_average_1_5_15": [round(x, 2) for x in load]}


def _models(scene, opts: BenchOptions, comps):
    """(default, guided) jitted forward models and their parameters."""
    import jax

    from ..model import ModelOptions, Params, build_model
    from ..model.contact import SkinContact
    from ..model.guided import hg_backward_fraction

    out = []
    d_opts = ModelOptions()
    g_opts = ModelOptions(optics="guided", elevations=opts.elevations, skin=SkinContact() if scene.touches else None)
    wg = dataclasses.replace(scene.waveguide, volume_backscatter_fraction=hg_backward_fraction(opts.g))
    g_scene = scene.replace(waveguide=wg)
    for sc, mo in ((scene, d_opts), (g_scene, g_opts)):
        model = build_model(sc, mo, comps)
        out.append((jax.jit(lambda p, m=model: m(p)), Params.from_scene(sc, mo.jnp_dtype)))
    return out


def _pair_timing(fa, pa, fb, pb, repeats: int) -> dict:
    """Alternate ``fa(pa)`` and ``fb(pb)`` (warm): medians and the median of per-pair ratios b / a."""
    fa(pa).block_until_ready()
    fb(pb).block_until_ready()
    ta, tb = [], []
    for i in range(repeats):
        for f, p, acc in ((fa, pa, ta), (fb, pb, tb)) if i % 2 == 0 else ((fb, pb, tb), (fa, pa, ta)):
            t = time.perf_counter()
            f(p).block_until_ready()
            acc.append(time.perf_counter() - t)
    ta, tb = np.array(ta), np.array(tb)
    return {"default_s": float(np.median(ta)), "guided_s": float(np.median(tb)),
            "ratio_guided_over_default": float(np.median(tb / ta)), "pairs": repeats}


def run_bench_tradeoff(opts: BenchOptions = BenchOptions(), *, progress: bool = False) -> dict:
    """Run the benchmark; returns the JSON-ready result (see the module docstring)."""
    from ..model.contact import SkinContact
    from ..scene import load_scene
    from .transport import MCOptions, run_mc

    t0 = time.perf_counter()
    base = load_scene(opts.scene).without_touches()
    touch = load_scene(opts.touch_scene)
    if not touch.touches:
        raise ConfigError(f"--touch-scene: {opts.touch_scene!r} has no contacts ([[touches]])")
    result = {
        "what": "analytic model (default fidelity; default and guided optics) against the Monte Carlo",
        "data": "simulated (monte carlo reference and analytic model)",
        "machine": _machine(),
        "options": dataclasses.asdict(opts),
        "analytic_vs_mc_relative_l2": {"default": {}, "guided": {}},
        "gain_scale": {"default": {}, "guided": {}},
        "forward_cost": {},
        "reference": {},
    }
    for case, scene in (("baseline", base), ("touch", touch)):
        comps = tuple(c for c in scene.components() if c not in NOT_TRANSPORTED)
        skin = SkinContact() if scene.touches else None
        halves, secs = [], 0.0
        for k in range(2):
            mo = MCOptions(photons=opts.photons // 2, seed=opts.seed + k, g=opts.g, contact=skin, batch=opts.batch,
                           nee_points=opts.nee_points, nee_aperture=4)
            r = run_mc(scene, mo, progress=progress)
            halves.append(np.asarray(r.counts, np.float64))
            secs += r.seconds
        ref = 0.5 * (halves[0] + halves[1])
        noise = float(np.linalg.norm(halves[0] - halves[1]) / max(np.linalg.norm(ref), 1e-300) / 2.0)
        result["reference"][case] = {"scene": scene.name, "photons_per_sensor": 2 * (opts.photons // 2),
                                     "seconds": secs, "relative_noise": noise,
                                     "contact_model": None if skin is None else dataclasses.asdict(skin)}
        (fd, pd), (fg, pg) = _models(scene, opts, comps)
        for name, f, p in (("default", fd, pd), ("guided", fg, pg)):
            err, scale = profiled_relative_l2(ref, np.asarray(f(p), np.float64))
            result["analytic_vs_mc_relative_l2"][name][case] = err
            result["gain_scale"][name][case] = [float(s) for s in scale]
        (fd, pd), (fg, pg) = _models(scene, opts, scene.components())  # the whole model, as calibration runs it
        result["forward_cost"][case] = _pair_timing(fd, pd, fg, pg, opts.repeats)
    result["compared_components"] = {case: [c for c in sc.components() if c not in NOT_TRANSPORTED]
                                     for case, sc in (("baseline", base), ("touch", touch))}
    result["forward_cost_ratio"] = max(v["ratio_guided_over_default"] for v in result["forward_cost"].values())
    result["targets"] = {"relative_l2_max": 0.15, "cost_ratio_max": 2.0}
    g = result["analytic_vs_mc_relative_l2"]["guided"]
    result["targets_met"] = {"guided_relative_l2": max(g.values()) <= 0.15,
                             "cost_ratio": result["forward_cost_ratio"] <= 2.0}
    result["wall_s"] = time.perf_counter() - t0
    return result


def summary(result: dict) -> str:
    """A few lines for the terminal."""
    lines = []
    for optics, v in result["analytic_vs_mc_relative_l2"].items():
        lines.append(f"analytic_vs_mc_relative_l2 {optics:8s} " + "  ".join(f"{k} {e:.3f}" for k, e in v.items()))
    noise = "  ".join(f"{k} {v['relative_noise']:.3f}" for k, v in result["reference"].items())
    lines.append(f"Monte Carlo reference noise           {noise}")
    cost = "  ".join(f"{k} {v['ratio_guided_over_default']:.2f}x "
                     f"({v['default_s'] * 1e6:.0f} -> {v['guided_s'] * 1e6:.0f} us)"
                     for k, v in result["forward_cost"].items())
    lines.append(f"forward cost guided / default        {cost}")
    return "\n".join(lines)
