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
  median of the per-pair ratios guided / default, and the ratio of the fastest evaluations (less
  sensitive to other jobs on a loaded machine);
* ``reference``: the Monte Carlo's settings, time, and its own noise: the photons are split over
  ``seeds`` independent seeds, the reference is their mean, and its noise is the norm of the
  standard error of that mean (the spread across seeds, bin by bin) over the reference's norm;
* ``analytic_vs_mc_relative_l2_noise_removed``: the model's own error, the reference's noise
  taken out two ways: ``quadrature`` (``sqrt(L2^2 - noise^2)``, the expected squared error of a
  noisy reference being the model's plus the noise's) and ``extrapolated`` (the L2 against half
  the seeds and against all, extrapolated as ``L2^2 = m^2 + c / photons`` to infinitely many);
  ``analytic_vs_mc_relative_l2`` stays the raw figure;
* ``frontier``: the guided optics at cheaper fidelities (:class:`GuidedFidelity`: elevations, rays
  per zone, time nodes per bin, float32 or float64), each with its relative L2 against the same
  references and its forward cost over the default optics' (at the default fidelity, float64),
  timed alternately with them; ``frontier_cheapest_meeting_targets`` names the cheapest fidelity
  within both targets (relative L2 <= 0.15 on both scenes, cost <= 2x), or None. The default
  fidelity is what calibration runs; the frontier is what a user who needs speed can choose;
* ``touch_signal``: per sensor, the counts the contacts add and remove (touch scene minus baseline,
  both Monte Carlo runs on the same seeds, so the difference is what the contacts do, not the
  noise of the whole histogram), Monte Carlo against the guided optics.

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

__all__ = ["BenchOptions", "GuidedFidelity", "profiled_relative_l2", "run_bench_tradeoff", "NOT_TRANSPORTED",
           "DEFAULT_FRONTIER"]

#: Terms no photon transport simulates (light entry, ambient) or the Monte Carlo leaves out (roughness).
NOT_TRANSPORTED = ("crosstalk", "ambient", "interface")

#: The guided fidelities ``tofjax bench tradeoff`` measures beside the default one (``ELEVATIONS:ANGLES:QUADRATURE:DTYPE``).
DEFAULT_FRONTIER = ("8:8:2:float32", "8:8:1:float64", "4:4:2:float64", "4:4:1:float64", "4:2:1:float64",
                    "4:2:1:float32", "2:2:1:float32")


@dataclass(frozen=True)
class GuidedFidelity:
    """One fidelity of the guided optics (:class:`tofjax.model.ModelOptions` fields): ``elevations`` (nodes over the
    guided band), ``angles_per_zone`` (rays per zone), ``quadrature`` (time nodes per bin) and ``dtype``. Written
    ``ELEVATIONS:ANGLES:QUADRATURE:DTYPE``, e.g. ``4:4:1:float32`` (:meth:`parse`)."""

    elevations: int = 8
    angles_per_zone: int = 8
    quadrature: int = 2
    dtype: str = "float64"

    def __post_init__(self):
        for k in ("elevations", "angles_per_zone", "quadrature"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= 64:
                raise ConfigError(f"{k}: must be an integer in 1..64, got {v!r}")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"dtype: must be float32 or float64, got {self.dtype!r}")

    @classmethod
    def parse(cls, text: str) -> "GuidedFidelity":
        """``"E:A:Q:DTYPE"`` (e.g. ``"4:4:1:float32"``); a clear :class:`ConfigError` for anything else."""
        parts = str(text).strip().split(":")
        if len(parts) != 4:
            raise ConfigError(f"fidelity {text!r}: expected ELEVATIONS:ANGLES:QUADRATURE:DTYPE, e.g. 4:4:1:float32")
        try:
            e, a, q = (int(x) for x in parts[:3])
        except ValueError:
            raise ConfigError(f"fidelity {text!r}: ELEVATIONS, ANGLES and QUADRATURE must be integers") from None
        return cls(e, a, q, parts[3])

    @property
    def label(self) -> str:
        return f"{self.elevations}:{self.angles_per_zone}:{self.quadrature}:{self.dtype}"

    def model_options(self, skin=None):
        from ..model import ModelOptions

        return ModelOptions(optics="guided", elevations=self.elevations, angles_per_zone=self.angles_per_zone,
                            quadrature=self.quadrature, dtype=self.dtype, skin=skin)


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
    - ``seeds``: independent Monte Carlo runs the photons are split over (>= 2; their spread is the
      reference's noise).
    - ``repeats``: timed pairs of forward evaluations.
    - ``elevations``: the guided optics' elevation nodes.
    - ``frontier``: cheaper guided fidelities measured beside the default one (``ELEVATIONS:ANGLES:QUADRATURE:DTYPE``
      strings, :class:`GuidedFidelity`; empty for none). float32 fidelities need no ``jax_enable_x64``; the default
      optics they are timed against are float64.
    """

    scene: str = "optoskin"
    touch_scene: str = "touch-three-line"
    photons: int = 100_000
    seed: int = 0
    g: float = 0.0
    nee_points: int = 24
    seeds: int = 4
    repeats: int = 31
    elevations: int = 8
    batch: int = 32_768
    frontier: tuple[str, ...] = DEFAULT_FRONTIER

    def __post_init__(self):
        if isinstance(self.frontier, str) or not all(isinstance(f, str) for f in self.frontier):
            raise ConfigError(f"frontier: must be a sequence of ELEVATIONS:ANGLES:QUADRATURE:DTYPE strings, "
                              f"got {self.frontier!r}")
        object.__setattr__(self, "frontier", tuple(GuidedFidelity.parse(f).label for f in self.frontier))
        for k, lo in (("photons", 2), ("seeds", 2), ("repeats", 1), ("nee_points", 1), ("elevations", 1), ("batch", 1), ("seed", 0)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ConfigError(f"{k}: must be an integer >= {lo}, got {v!r}")
        if self.photons < 2 * self.seeds:
            raise ConfigError(f"photons: at least 2 per seed ({self.seeds} seeds), got {self.photons!r}")
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


def reference_noise(runs) -> tuple[np.ndarray, float]:
    """Mean of independent Monte Carlo runs (n, ...) and its relative noise: the norm of the standard
    error of the mean (the spread across runs, bin by bin) over the mean's norm."""
    runs = np.asarray(runs, np.float64)
    n = runs.shape[0]
    ref = runs.mean(0)
    var_mean = np.sum((runs - ref) ** 2, axis=0) / (n * (n - 1))
    return ref, float(np.sqrt(var_mean.sum()) / max(np.linalg.norm(ref), 1e-300))


def noise_removed(runs, y) -> dict:
    """The model's own relative L2 against noisy Monte Carlo runs (n, S, Z, B) of equal photon counts:
    ``raw`` (against their mean), ``reference_noise``, ``quadrature`` (``sqrt(raw^2 - noise^2)``) and
    ``extrapolated`` (``L2^2 = m^2 + c / photons`` through the L2 against each half of the runs, averaged
    in squares, and against all of them; n >= 2)."""
    runs = np.asarray(runs, np.float64)
    n = runs.shape[0]
    ref, noise = reference_noise(runs)
    raw = profiled_relative_l2(ref, y)[0]
    h = n // 2
    halves = [runs[:h].mean(0), runs[h:2 * h].mean(0)]
    e_half2 = float(np.mean([profiled_relative_l2(r, y)[0] ** 2 for r in halves]))
    # photons: h runs for the halves, n for all: m^2 = (n raw^2 - h e_half^2) / (n - h)
    m2 = (n * raw**2 - h * e_half2) / (n - h)
    return {"raw": raw, "reference_noise": noise, "quadrature": float(np.sqrt(max(raw**2 - noise**2, 0.0))),
            "extrapolated": float(np.sqrt(max(m2, 0.0))), "half_references_l2": float(np.sqrt(e_half2))}


def _signal(delta) -> list:
    """Counts added and removed per sensor of a (S, Z, B) difference, and the net."""
    d = np.asarray(delta, np.float64)
    return [{"sensor": s, "added": float(d[s].clip(0).sum()), "removed": float(d[s].clip(None, 0).sum()),
             "net": float(d[s].sum())} for s in range(d.shape[0])]


def _machine() -> dict:
    import jax

    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {"platform": platform.platform(), "machine": platform.machine(), "cpus": os.cpu_count(),
            "jax_backend": jax.default_backend(), "jax_devices": len(jax.devices()),
            "load_average_1_5_15": [round(x, 2) for x in load]}


def _compiled(scene, mo, comps):
    """A forward model compiled once per model structure (:func:`tofjax.mc.prune.evaluate`, not once per call) and
    its parameters."""
    import functools

    from ..model import Params, build_model
    from .prune import evaluate

    return functools.partial(evaluate, build_model(scene, mo, comps)), Params.from_scene(scene, mo.jnp_dtype)


def _guided(scene, opts: BenchOptions, comps, fidelity: GuidedFidelity | None = None):
    """The guided optics (compiled, with parameters) at ``fidelity`` (default: the default fidelity with
    ``opts.elevations``), with the Monte Carlo's volume backscatter and, on a touch scene, its skin model."""
    from ..model import ModelOptions
    from ..model.contact import SkinContact
    from ..model.guided import hg_backward_fraction

    d_opts = ModelOptions()
    fidelity = fidelity or GuidedFidelity(elevations=opts.elevations, angles_per_zone=d_opts.angles_per_zone,
                                          quadrature=d_opts.quadrature, dtype=d_opts.dtype)
    wg = dataclasses.replace(scene.waveguide, volume_backscatter_fraction=hg_backward_fraction(opts.g))
    return _compiled(scene.replace(waveguide=wg), fidelity.model_options(SkinContact() if scene.touches else None),
                     comps)


def _models(scene, opts: BenchOptions, comps):
    """(default, guided) compiled forward models and their parameters: the default optics at the default fidelity,
    the guided optics at the bench's (:func:`_guided`)."""
    from ..model import ModelOptions

    return [_compiled(scene, ModelOptions(), comps), _guided(scene, opts, comps)]


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
            "ratio_guided_over_default": float(np.median(tb / ta)), "pairs": repeats,
            "ratio_of_minima": float(tb.min() / ta.min())}


def run_bench_tradeoff(opts: BenchOptions = BenchOptions(), *, progress: bool = False, transport=None) -> dict:
    """Run the benchmark; returns the JSON-ready result (see the module docstring).

    ``transport``: a module with ``MCOptions`` and ``run_mc`` (default :mod:`tofjax.mc.transport`;
    a study may pass a variant, whose name the result records as ``monte_carlo``)."""
    from ..model.contact import SkinContact
    from ..scene import load_scene

    from tqdm import tqdm

    if transport is None:
        from . import transport
    MCOptions, run_mc = transport.MCOptions, transport.run_mc

    t0 = time.perf_counter()
    base = load_scene(opts.scene).require_waveguide("tofjax bench tradeoff", opts.scene).without_touches()
    touch = load_scene(opts.touch_scene).require_waveguide("tofjax bench tradeoff", opts.touch_scene)
    if not touch.touches:
        raise ConfigError(f"--touch-scene: {opts.touch_scene!r} has no contacts ([[touches]])")
    result = {
        "what": "analytic model (default fidelity; default and guided optics) against the Monte Carlo",
        "data": "simulated (monte carlo reference and analytic model)",
        "machine": _machine(),
        "monte_carlo": transport.__name__,
        "options": dataclasses.asdict(opts),
        "analytic_vs_mc_relative_l2": {"default": {}, "guided": {}},
        "analytic_vs_mc_relative_l2_noise_removed": {"default": {}, "guided": {}},
        "gain_scale": {"default": {}, "guided": {}},
        "forward_cost": {},
        "reference": {},
    }
    per_seed = opts.photons // opts.seeds
    runs_of, guided_of, frontier = {}, {}, {}
    for case, scene in (("baseline", base), ("touch", touch)):
        comps = tuple(c for c in scene.components() if c not in NOT_TRANSPORTED)
        skin = SkinContact() if scene.touches else None
        runs, secs = [], 0.0
        for k in range(opts.seeds):
            mo = MCOptions(photons=per_seed, seed=opts.seed + k, g=opts.g, contact=skin, batch=opts.batch,
                           nee_points=opts.nee_points, nee_aperture=4)
            r = run_mc(scene, mo, progress=progress)
            runs.append(np.asarray(r.counts, np.float64))
            secs += r.seconds
        ref, noise = reference_noise(runs)
        runs_of[case] = np.asarray(runs)
        result["reference"][case] = {"scene": scene.name, "photons_per_sensor": opts.seeds * per_seed,
                                     "seeds": opts.seeds, "seconds": secs, "relative_noise": noise,
                                     "contact_model": None if skin is None else dataclasses.asdict(skin)}
        (fd, pd), (fg, pg) = _models(scene, opts, comps)
        for name, f, p in (("default", fd, pd), ("guided", fg, pg)):
            y = np.asarray(f(p), np.float64)
            err, scale = profiled_relative_l2(ref, y)
            result["analytic_vs_mc_relative_l2"][name][case] = err
            result["analytic_vs_mc_relative_l2_noise_removed"][name][case] = noise_removed(runs, y)
            result["gain_scale"][name][case] = [float(s) for s in scale]
            if name == "guided":
                guided_of[case] = y
        (fd, pd), (fg, pg) = _models(scene, opts, scene.components())  # the whole model, as calibration runs it
        result["forward_cost"][case] = _pair_timing(fd, pd, fg, pg, opts.repeats)
        for label in tqdm(opts.frontier, desc=f"frontier ({case})", unit="fidelity", disable=not progress,
                          leave=False):  # cheaper guided fidelities: their error and cost over the default optics'
            fid = GuidedFidelity.parse(label)
            fg, pg = _guided(scene, opts, comps, fid)
            err = profiled_relative_l2(ref, np.asarray(fg(pg), np.float64))[0]
            fg, pg = _guided(scene, opts, scene.components(), fid)
            cost = _pair_timing(fd, pd, fg, pg, opts.repeats)
            row = frontier.setdefault(label, {"fidelity": label, **dataclasses.asdict(fid), "relative_l2": {},
                                              "forward_cost": {}})
            row["relative_l2"][case] = err
            row["forward_cost"][case] = cost
    # what the contacts do: touch minus baseline (same seeds), transported light
    if base.sensors == touch.sensors:
        d_mc = runs_of["touch"] - runs_of["baseline"]  # (seeds, S, Z, B)
        result["touch_signal"] = {
            "monte_carlo": _signal(d_mc.mean(0)), "guided": _signal(guided_of["touch"] - guided_of["baseline"]),
            "monte_carlo_net_per_seed": [[float(x) for x in dk.sum((1, 2))] for dk in d_mc]}
    result["compared_components"] = {case: [c for c in sc.components() if c not in NOT_TRANSPORTED]
                                     for case, sc in (("baseline", base), ("touch", touch))}
    result["forward_cost_ratio"] = max(v["ratio_guided_over_default"] for v in result["forward_cost"].values())
    result["targets"] = {"relative_l2_max": 0.15, "cost_ratio_max": 2.0}
    g = result["analytic_vs_mc_relative_l2"]["guided"]
    result["targets_met"] = {"guided_relative_l2": max(g.values()) <= 0.15,
                             "cost_ratio": result["forward_cost_ratio"] <= 2.0}
    rows = []
    for row in frontier.values():
        row["cost_ratio"] = max(v["ratio_guided_over_default"] for v in row["forward_cost"].values())
        row["meets_targets"] = bool(max(row["relative_l2"].values()) <= 0.15 and row["cost_ratio"] <= 2.0)
        rows.append(row)
    result["frontier"] = rows
    meeting = [r for r in rows if r["meets_targets"]]
    result["frontier_cheapest_meeting_targets"] = min(meeting, key=lambda r: r["cost_ratio"])["fidelity"] if meeting else None
    result["wall_s"] = time.perf_counter() - t0
    return result


def summary(result: dict) -> str:
    """A few lines for the terminal."""
    lines = []
    for optics, v in result["analytic_vs_mc_relative_l2"].items():
        lines.append(f"analytic_vs_mc_relative_l2 {optics:8s} " + "  ".join(f"{k} {e:.3f}" for k, e in v.items()))
    noise = "  ".join(f"{k} {v['relative_noise']:.3f}" for k, v in result["reference"].items())
    lines.append(f"Monte Carlo reference noise           {noise}")
    for optics, v in result.get("analytic_vs_mc_relative_l2_noise_removed", {}).items():
        lines.append(f"noise removed (quadrature/extrap.) {optics:8s} "
                     + "  ".join(f"{k} {e['quadrature']:.3f}/{e['extrapolated']:.3f}" for k, e in v.items()))
    cost = "  ".join(f"{k} {v['ratio_guided_over_default']:.2f}x "
                     f"({v['default_s'] * 1e6:.0f} -> {v['guided_s'] * 1e6:.0f} us)"
                     for k, v in result["forward_cost"].items())
    lines.append(f"forward cost guided / default        {cost}")
    for r in result.get("frontier", []):
        l2 = "  ".join(f"{k} {e:.3f}" for k, e in r["relative_l2"].items())
        c = "  ".join(f"{k} {v['ratio_guided_over_default']:.2f}x" for k, v in r["forward_cost"].items())
        lines.append(f"guided {r['fidelity']:<16s} relative L2 {l2}   cost {c}{'   meets both' if r['meets_targets'] else ''}")
    if result.get("frontier"):
        lines.append(f"cheapest guided fidelity meeting both targets: {result['frontier_cheapest_meeting_targets']}")
    return "\n".join(lines)
