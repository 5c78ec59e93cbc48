"""Speed against accuracy: the analytic model's fidelity ladder, fits and the Monte Carlo itself,
measured against a Monte Carlo reference at a high photon count.

A study, not library code (it uses the demo and ``experiments/study_fit_speed.py``); it
replaces ``tofjax bench tradeoff``:

    python experiments/study_tradeoff.py --config configs/studies/tradeoff.toml --out out/tradeoff
    python experiments/study_tradeoff.py --quick --out out/tradeoff_quick      # a first look (minutes)

``tradeoff.json`` holds ``analytic_vs_mc_relative_l2``: the relative L2 error of the analytic
model at the default fidelity against the Monte Carlo reference (gain profiled per sensor,
transported light only).

What is measured (all on one scene, side by side in one run):

* **Fidelity ladder.** The analytic model at each setting (components on or off, pulse tail,
  bin quadrature, float32 / float64, the pruned model): time per evaluation (warm, median)
  and relative L2 error of the histograms (a) against the Monte Carlo reference, with one
  gain per sensor profiled out (the Monte Carlo's absolute efficiency is a convention,
  and calibration fits the gain anyway), over the transported light only (no light-entry
  peak or ambient, which no transport simulates, and no interface roughness, which the
  Monte Carlo does not model), and (b) against the analytic model at its highest fidelity
  (the numerical error alone).
* **Per component.** Groups of terms isolated in both models by switching physics off
  (the far edge: no scattering; scattering: with minus without; contacts: with minus
  without), gain fixed by the far edge: the ratio of total signal and the shape error.
* **Downstream.** Calibration of Monte Carlo data with the analytic model: the bias of the
  fitted n1, mu_s, mu_a against the truth, next to the same fit of analytic data (noise
  only); the pruned model's fit against the full one (in standard errors).
* **Fitting.** Solver and tolerance against time and parameter error: the study of
  ``experiments/study_fit_speed.py``, run on the same scene.
* **Monte Carlo.** Photon count against its own noise (relative L2 against the reference)
  and time.

* **Contact positions.** The same contacts simulated by the Monte Carlo and by the analytic
  model, detected by ``tofjax.invert``'s back-projection with the analytic optics: the
  detection and distance error on each (``detect=`` swaps in another detector).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from tofjax.config import ConfigError, from_dict, load_toml
from tofjax.model import ModelOptions, Params, build_model, sample_counts
from tofjax.scene import COMPONENTS, Scene, load_scene
from tofjax.timing import median_seconds
from tofjax.mc.prune import PruneOptions, prune_model
from tofjax.mc import MCOptions, run_mc

__all__ = ["Fidelity", "TradeoffConfig", "load_tradeoff_config", "run_tradeoff", "fastest_within"]

#: Terms no photon transport simulates (light entry, ambient) or the Monte Carlo leaves out (roughness).
NOT_TRANSPORTED = ("crosstalk", "ambient", "interface")
TARGETS = ("n1", "mu_s_per_m", "mu_a_per_m")


@dataclass(frozen=True)
class Fidelity:
    """One rung of the ladder: model options and components relative to the scene's."""

    label: str
    quadrature: int = 2
    dtype: str = "float64"
    exclude: tuple[str, ...] = ()
    pulse_tail: bool = True
    pruned: bool = False
    angles_per_zone: int = 8

    def __post_init__(self):
        for c in self.exclude:
            if c not in COMPONENTS:
                raise ConfigError(f"exclude: unknown component {c!r}; known: {', '.join(COMPONENTS)}")


DEFAULT_LADDER = (
    Fidelity("default (q=2, float64)"),
    Fidelity("q=1", quadrature=1),
    Fidelity("q=4", quadrature=4),
    Fidelity("q=8", quadrature=8),
    Fidelity("float32 (q=2)", dtype="float32"),
    Fidelity("float32, q=1", quadrature=1, dtype="float32"),
    Fidelity("no multiple scattering", exclude=("multiple_scattering",)),
    Fidelity("no volume backscatter", exclude=("volume",)),
    Fidelity("no scattering terms", exclude=("volume", "multiple_scattering")),
    Fidelity("no shadowing", exclude=("shadowing",)),
    Fidelity("no pulse tail", pulse_tail=False),
    Fidelity("4 rays per zone", angles_per_zone=4),
    Fidelity("pruned (tofjax prune)", pruned=True),
    Fidelity("pruned, float32, q=1", pruned=True, dtype="float32", quadrature=1),
)


@dataclass(frozen=True)
class TradeoffConfig:
    """Options of the trade-off study (TOML: ``configs/studies/tradeoff.toml``).

    - ``scene``: scene file or built-in name.
    - ``reference_photons``: Monte Carlo reference, packets per sensor.
    - ``photon_ladder``: Monte Carlo runs measured against the reference.
    - ``budget``: error budget (relative L2 against the reference) for the summary.
    - ``fidelities``: the analytic ladder (default :data:`DEFAULT_LADDER`).
    - ``repeats``: timing repeats (medians).
    - ``fit_frames``: frames of the captures fitted downstream.
    - ``fit_bias``, ``fit_speed``, ``contact_bias``: run the downstream fits / the fit-speed
      study / the contact-position row.
    - ``fit_speed_settings``: labels of ``experiments/study_fit_speed.py`` settings to run
      (from ``configs/studies/fit_speed.toml``; empty: all).
    - ``quick``: a small run (few photons, no fits) for tests and a first look.
    - ``mc``: Monte Carlo physics options other than the photon count and seed.
    """

    scene: str = "optoskin"
    reference_photons: int = 200_000
    photon_ladder: tuple[int, ...] = (1_000, 3_000, 10_000, 30_000)
    seed: int = 0
    budget: float = 0.1
    fidelities: tuple[Fidelity, ...] = DEFAULT_LADDER
    repeats: int = 30
    fit_frames: int = 50
    fit_bias: bool = True
    fit_speed: bool = True
    contact_bias: bool = True
    fit_speed_settings: tuple[str, ...] = ("default (LM, loss_tol 1e-3)", "LM, rtol 1e-4", "float32", "quadrature 1")
    quick: bool = False
    mc_batch: int = 32_768
    mc_g: float = 0.0
    mc_edges: str = "diffuse"

    def __post_init__(self):
        if self.reference_photons < 1:
            raise ConfigError(f"reference_photons: must be >= 1, got {self.reference_photons!r}")
        if any(n < 1 for n in self.photon_ladder):
            raise ConfigError("photon_ladder: every photon count must be >= 1")
        if not self.budget > 0:
            raise ConfigError(f"budget: must be > 0, got {self.budget!r}")
        if self.repeats < 1:
            raise ConfigError(f"repeats: must be >= 1, got {self.repeats!r}")
        if self.fit_frames < 1:
            raise ConfigError(f"fit_frames: must be >= 1, got {self.fit_frames!r}")

    def effective(self) -> "TradeoffConfig":
        """With ``quick``: few photons, few repeats, no fits."""
        if not self.quick:
            return self
        return dataclasses.replace(
            self,
            reference_photons=min(self.reference_photons, 4_000),
            photon_ladder=tuple(n for n in (250, 500, 1_000) if n < min(self.reference_photons, 4_000)) or (100,),
            repeats=min(self.repeats, 5),
            fit_bias=False,
            fit_speed=False,
            contact_bias=False,
        )


def load_tradeoff_config(path) -> TradeoffConfig:
    return from_dict(TradeoffConfig, load_toml(path), where=str(path))


# ---- helpers ------------------------------------------------------------------------------


def _profiled_error(ref: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    """Relative L2 error of ``y`` against ``ref`` with one scale per sensor fitted (least squares)."""
    num = np.sum(ref * y, axis=(1, 2))
    den = np.maximum(np.sum(y * y, axis=(1, 2)), 1e-300)
    scale = num / den
    err = np.linalg.norm(ref - scale[:, None, None] * y) / max(np.linalg.norm(ref), 1e-300)
    return float(err), scale


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def _transport_components(scene: Scene, extra_exclude=()) -> tuple[str, ...]:
    return tuple(c for c in scene.components() if c not in NOT_TRANSPORTED and c not in extra_exclude)


def _model_fn(scene: Scene, fid: Fidelity, comps):
    opts = ModelOptions(quadrature=fid.quadrature, dtype=fid.dtype, angles_per_zone=fid.angles_per_zone)
    model = build_model(scene, opts, comps)
    params = Params.from_scene(scene, opts.jnp_dtype)
    if not fid.pulse_tail:
        # the tail's time constant far below a bin: the pulse is its Gaussian rise alone
        params = params.replace(pulse_tail_s=1e-6 * float(params.pulse_sigma_s))
    return jax.jit(lambda p: model(p)), params


def _with_waveguide(scene: Scene, **kw) -> Scene:
    return scene.replace(waveguide=dataclasses.replace(scene.waveguide, **kw))


def _mc(scene: Scene, cfg: TradeoffConfig, photons: int, seed: int):
    return run_mc(scene, MCOptions(photons=photons, seed=seed, batch=cfg.mc_batch, g=cfg.mc_g, edges=cfg.mc_edges))


def _capture_from(scene: Scene, expected: np.ndarray, frames: int, seed: int):
    from tofjax.capture import Capture

    keys = jax.random.split(jax.random.key(seed), frames)
    lam = jnp.asarray(expected)
    hist = np.array(jax.vmap(lambda k: sample_counts(k, lam, saturation=scene.sensor.saturation_counts))(keys), np.float64)
    return Capture(histograms=hist, timestamps=np.arange(frames) / 9.0, scene=scene, source="simulated (monte carlo)")


def _load_fit_speed_study():
    """``experiments/study_fit_speed.py`` of this checkout (the fit-speed logic is reused, not copied)."""
    path = Path(__file__).resolve().parent / "study_fit_speed.py"
    if not path.exists():
        return None
    spec = importlib.util.spec_from_file_location("study_fit_speed", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["study_fit_speed"] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def fastest_within(rows: list[dict], key: str, budget: float) -> dict | None:
    """The row with the smallest ``seconds`` among those with ``row[key] <= budget``."""
    ok = [r for r in rows if r.get(key) is not None and np.isfinite(r[key]) and r[key] <= budget]
    return min(ok, key=lambda r: r["seconds"]) if ok else None


# ---- the study -----------------------------------------------------------------------------


def run_tradeoff(
    config: TradeoffConfig,
    out: Path | str,
    *,
    progress: bool = True,
    detect: Callable | None = None,
) -> dict:
    """Run the trade-off study and write ``tradeoff.json``, ``tradeoff.md`` and ``tradeoff.png``.

    **Arguments:**

    - ``config``: :class:`TradeoffConfig`.
    - ``out``: output folder.
    - ``progress``: progress bars.
    - ``detect``: the detector of the contact-position row, ``detect(capture, baseline,
      scene) -> (n, 2)`` positions in metres (default :func:`detect_backprojection`). It gets
      Monte Carlo and analytic captures of the scene's contacts (the demo's line of three
      if the scene has none), with their no-touch baselines.

    **Returns:** the JSON-able result.
    """
    t_start = time.perf_counter()
    cfg = config.effective()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(cfg.scene) if isinstance(cfg.scene, str) else cfg.scene
    comps = _transport_components(scene)
    result: dict = {
        "study": "speed against accuracy (issue 7)",
        "data": "simulated (Monte Carlo reference and analytic model)",
        "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, {jax.device_count()} JAX device(s): "
        f"{jax.devices()[0].device_kind}",
        "scene": scene.name,
        "config": dataclasses.asdict(cfg),
        "compared_components": list(comps),
    }

    # -- the reference
    bar = tqdm(total=4 + len(cfg.photon_ladder) + len(cfg.fidelities), desc="tradeoff", disable=not progress)
    ref_run = _mc(scene, cfg, cfg.reference_photons, cfg.seed)
    ref = ref_run.counts
    bar.update()
    result["reference"] = {
        "photons_per_sensor": cfg.reference_photons,
        "seconds": ref_run.seconds,
        "compile_seconds": ref_run.compile_seconds,
        "events": ref_run.events,
        "events_per_second": ref_run.events_per_second,
        "photons_per_second": cfg.reference_photons * scene.n_sensors / max(ref_run.seconds, 1e-12),
        "ledger": ref_run.ledger,
    }

    # -- Monte Carlo photon ladder: its own noise and time
    mc_rows = []
    for i, n in enumerate(cfg.photon_ladder):
        r = _mc(scene, cfg, n, cfg.seed + 1 + i)
        mc_rows.append({"label": f"Monte Carlo {n:g} photons", "photons": n, "seconds": r.seconds,
                        "error_vs_mc": _rel(r.counts, ref), "kind": "monte carlo"})
        bar.update()
    # the reference's own noise, extrapolated as 1/sqrt(photons) from the ladder
    if mc_rows:
        c = np.median([row["error_vs_mc"] * np.sqrt(row["photons"]) for row in mc_rows])
        result["reference"]["noise_estimate"] = float(c / np.sqrt(cfg.reference_photons))
        for row in mc_rows:
            row["noise_estimate"] = float(c / np.sqrt(row["photons"]))
    result["monte_carlo"] = mc_rows

    # -- the fidelity ladder
    hi_fn, hi_p = _model_fn(scene, Fidelity("reference", quadrature=16, angles_per_zone=32), comps)
    hi = np.asarray(hi_fn(hi_p), np.float64)
    pruned = prune_model(scene, PruneOptions(frames=cfg.fit_frames))
    result["prune"] = pruned.to_json()
    rows = []
    for fid in cfg.fidelities:
        if fid.exclude and not any(c in comps for c in fid.exclude):
            bar.update()
            continue  # the scene has no such term (e.g. shadowing without contacts)
        use = tuple(c for c in comps if c not in fid.exclude and (not fid.pruned or c in pruned.kept))
        fn, p = _model_fn(scene, fid, use)
        y = np.asarray(fn(p), np.float64)
        secs = median_seconds(fn, p, cfg.repeats)
        err_mc, scale = _profiled_error(ref, y)
        rows.append({
            "label": fid.label, "kind": "analytic", "fidelity": dataclasses.asdict(fid), "components": list(use),
            "seconds": secs, "error_vs_mc": err_mc, "error_numerical": _rel(y, hi),
            "gain_scale": scale.tolist(), "finite": bool(np.isfinite(y).all()),
        })
        bar.update()
    result["analytic"] = rows

    # -- per component: isolate groups of terms in both models
    result["components"] = _per_component(scene, cfg, ref, comps)
    bar.update()

    # -- downstream: calibration of Monte Carlo data with the analytic model
    if cfg.fit_bias:
        result["fit_bias"] = _fit_bias(scene, cfg, ref, pruned.kept)
    else:
        result["fit_bias"] = {"skipped": "fit_bias = false in the config (or a quick run)"}
    bar.update()
    if cfg.fit_speed:
        result["fit_speed"] = _fit_speed(scene, cfg, out)
    else:
        result["fit_speed"] = {"skipped": "fit_speed = false in the config (or a quick run)"}
    if cfg.contact_bias:
        result["contact_bias"] = _contact_bias(scene, cfg, detect)
    else:
        result["contact_bias"] = {"skipped": "contact_bias = false in the config (or a quick run)"}
    bar.update()
    bar.close()

    # -- summary
    for key in ("error_vs_mc", "error_numerical"):
        best = fastest_within(rows, key, cfg.budget)
        result[f"fastest_within_budget_{key}"] = None if best is None else best["label"]
    default = next((r for r in rows if {**r["fidelity"], "label": ""} == dataclasses.asdict(Fidelity(""))), None)
    result["analytic_vs_mc_relative_l2"] = None if default is None else default["error_vs_mc"]
    best_mc = fastest_within(mc_rows, "error_vs_mc", cfg.budget)
    result["fastest_within_budget_monte_carlo"] = None if best_mc is None else best_mc["label"]
    result["wall_s"] = time.perf_counter() - t_start
    (out / "tradeoff.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "tradeoff.md").write_text(markdown(result))
    plot(result, out / "tradeoff.png")
    return result


def _per_component(scene: Scene, cfg: TradeoffConfig, ref: np.ndarray, comps) -> list[dict]:
    """Far edge (no scattering), scattering (with minus without), contacts (with minus without)."""
    out = []
    fid = Fidelity("default")
    clear = _with_waveguide(scene, mu_s_per_m=0.0)
    mc_clear = _mc(clear, cfg, cfg.reference_photons, cfg.seed).counts
    fn, p = _model_fn(clear, fid, tuple(c for c in _transport_components(clear)))
    an_clear = np.asarray(fn(p), np.float64)
    _, scale = _profiled_error(mc_clear, an_clear)  # the gain, fixed on the far edge
    S = scale[:, None, None]

    def row(name, mc, an, note):
        tot_mc, tot_an = float(mc.sum()), float((S * an).sum())
        shape_err, _ = _profiled_error(mc, an) if np.abs(an).sum() > 0 else (float("nan"), None)
        return {"group": name, "mc_total": tot_mc, "analytic_total": tot_an,
                "ratio_mc_over_analytic": tot_mc / tot_an if tot_an else float("nan"),
                "shape_error": shape_err, "note": note}

    out.append(row("far edge (mu_s = 0)", mc_clear, an_clear, "gain per sensor fitted here and used below"))
    if scene.waveguide.mu_s_per_m > 0:
        fn, p = _model_fn(scene, fid, comps)
        an_full = np.asarray(fn(p), np.float64)
        out.append(row("scattering (volume + multiple scattering, with minus without)", ref - mc_clear,
                       an_full - an_clear, "the analytic multiple-scattering term is phenomenological"))
    if scene.touches:
        bare = scene.without_touches()
        mc_bare = _mc(bare, cfg, cfg.reference_photons, cfg.seed).counts
        fn, p = _model_fn(scene, fid, comps)
        an_full = np.asarray(fn(p), np.float64)
        fn_b, p_b = _model_fn(bare, fid, _transport_components(bare))
        an_bare = np.asarray(fn_b(p_b), np.float64)
        out.append(row("contacts (touch + shadowing, with minus without)", ref - mc_bare, an_full - an_bare,
                       "Monte Carlo contacts: Fresnel into skin, Lambertian return with albedo = strength"))
    return out


def _fit_bias(scene: Scene, cfg: TradeoffConfig, ref: np.ndarray, kept) -> dict:
    from tofjax.fit.calibrate import Calibrator
    from tofjax.simulate import simulate

    base = scene.without_touches()
    truth = {k: float(getattr(base.waveguide, k)) for k in TARGETS}
    extras = [c for c in ("crosstalk", "ambient") if c in base.components()]
    opts = ModelOptions()
    expected = ref + np.asarray(build_model(base, opts, tuple(extras))(Params.from_scene(base, opts.jnp_dtype)))
    if scene.touches:
        mc_bare = _mc(base, cfg, cfg.reference_photons, cfg.seed).counts
        expected = mc_bare + (expected - ref)
    out: dict = {"truth": truth, "frames": cfg.fit_frames}
    cal = Calibrator(base)
    for name, cap in (("analytic data (noise only)", simulate(base, cfg.fit_frames, seed=cfg.seed + 100)),
                      ("Monte Carlo data", _capture_from(base, expected, cfg.fit_frames, cfg.seed + 100))):
        t = time.perf_counter()
        res = cal.fit(cap)
        secs = time.perf_counter() - t
        out[name] = {
            "seconds": secs, "converged": res.converged, "reduced_chi2": res.reduced_chi2,
            "values": {k: float(res.values[k]) for k in TARGETS},
            "stderr": {k: float(res.stderr[k]) for k in TARGETS},
            "bias": {k: float(res.values[k]) - truth[k] for k in TARGETS},
            "bias_in_stderr": {k: (float(res.values[k]) - truth[k]) / max(float(res.stderr[k]), 1e-300) for k in TARGETS},
        }
        if name.startswith("analytic"):
            full_fit = res
            full_cap = cap
    # the pruned model: same analytic data, fitted with the pruned component list
    dropped = tuple(c for c in base.components() if c not in kept)
    if dropped:
        pruned_scene = base.replace(model=dataclasses.replace(base.model, exclude=tuple(base.model.exclude) + dropped))
        cal_p = Calibrator(pruned_scene)
        t = time.perf_counter()
        res = cal_p.fit(full_cap)
        out["pruned model"] = {
            "dropped": list(dropped), "seconds": time.perf_counter() - t, "converged": res.converged,
            "reduced_chi2": res.reduced_chi2,
            "shift_in_stderr": {k: (float(res.values[k]) - float(full_fit.values[k])) / max(float(full_fit.stderr[k]), 1e-300)
                                for k in TARGETS},
        }
    else:
        out["pruned model"] = {"dropped": [], "note": "nothing to prune at this noise level"}
    return out


def _fit_speed(scene: Scene, cfg: TradeoffConfig, out: Path) -> dict:
    study = _load_fit_speed_study()
    if study is None:
        return {"skipped": "experiments/study_fit_speed.py not found (installed package without the repository)"}
    full = study.load_config(Path(__file__).resolve().parents[2] / "configs" / "studies" / "fit_speed.toml")
    settings = tuple(s for s in full.settings if not cfg.fit_speed_settings or s.label in cfg.fit_speed_settings)
    if not settings:
        raise ConfigError(f"fit_speed_settings: none of {list(cfg.fit_speed_settings)} is in configs/studies/fit_speed.toml")
    name = cfg.scene if isinstance(cfg.scene, str) else "optoskin"
    sc = study.FitSpeedConfig(scene=name, frames=cfg.fit_frames, captures=2, seed=cfg.seed + 200, settings=settings,
                              scipy_methods=(), scipy_jacobians=())
    r = study.run(sc, out / "fit_speed", progress=False)
    return {"source": "experiments/study_fit_speed.py", "settings": r["settings"], "output": str(out / "fit_speed")}


def detect_backprojection(capture, baseline, scene: Scene) -> np.ndarray:
    """Default detector of the contact-position row: ``tofjax.invert``'s back-projection
    (Algorithm 1 ``full``, Eq. 8 maps, detection) with the scene's own optics, on the mean
    frame. Returns the detected positions (n, 2) in metres."""
    from tofjax.invert import InvertOptions, build_inverter

    inv = build_inverter(scene.without_touches(), baseline.mean(), InvertOptions(), n_baseline=baseline.n_frames)
    return inv.process(capture.mean()[None]).detections[0].positions()


def _contact_bias(scene: Scene, cfg: TradeoffConfig, detect) -> dict:
    """Detected contact positions on Monte Carlo data and on analytic data of the same
    contacts (the scene's, or the demo's line of three if it has none): the difference is
    the bias the analytic model's mismatch puts into touch detection."""
    from tofjax.invert import match
    from tofjax.simulate import simulate
    from tofjax.mc.capture import mc_capture

    detect = detect_backprojection if detect is None else detect
    if not scene.touches:
        from tofjax.demo import three_touch_scene

        scene = three_touch_scene(scene)
    truth = scene.contact_elements()[:, :2]
    opts = MCOptions(photons=cfg.reference_photons, seed=cfg.seed, batch=cfg.mc_batch, g=cfg.mc_g, edges=cfg.mc_edges)
    frames = max(cfg.fit_frames, 2)
    sources = {
        "monte_carlo": lambda: (
            mc_capture(scene, frames, cfg.seed, opts),
            mc_capture(scene.without_touches(), frames, cfg.seed + 1, opts),
        ),
        "analytic": lambda: (simulate(scene, frames, cfg.seed), simulate(scene.without_touches(), frames, cfg.seed + 1)),
    }
    out: dict = {"contacts_m": truth.tolist(), "frames": frames, "detector": getattr(detect, "__name__", "custom")}
    for name, make in sources.items():
        cap, base = make()
        found = np.asarray(detect(cap, base, scene), float).reshape(-1, 2)
        matched, dist = match(found, truth, 0.02)
        diff = cap.mean() - base.mean()
        out[name] = {
            # what the contacts add (backscatter) and take away (shadowing), in mean counts
            "touch_gain_counts": float(np.clip(diff, 0, None).sum()),
            "touch_loss_counts": float(np.clip(-diff, 0, None).sum()),
            "detected": int(len(found)),
            "true": int(len(truth)),
            "matched_within_2cm": matched,
            "distance_m": [float(x) for x in dist],
            "mean_m": float(np.mean(dist)) if len(dist) else None,
            "positions_m": found.tolist(),
        }
    return out


# ---- report ----------------------------------------------------------------------------------


def markdown(r: dict) -> str:
    cfg = r["config"]
    ref = r["reference"]
    lines = [
        f"# Speed against accuracy: scene `{r['scene']}` ({r['data']})",
        "",
        f"Machine: {r['machine']}. Times are warm medians; errors are relative L2 of the histograms "
        f"(all sensors, zones, bins). Reference: Monte Carlo, {ref['photons_per_sensor']:g} photons per sensor, "
        f"{ref['seconds']:.1f} s ({ref['events_per_second']:.3g} packet-events/s, compile {ref['compile_seconds']:.1f} s), "
        f"own noise ~{ref.get('noise_estimate', float('nan')):.2g}. Compared: the transported light "
        f"({', '.join(r['compared_components'])}); gain profiled per sensor against the Monte Carlo.",
        "",
        f"**Error budget {cfg['budget']:g}:** fastest analytic setting within it against the Monte Carlo: "
        f"**{r['fastest_within_budget_error_vs_mc'] or 'none'}**; against the analytic model's own highest fidelity "
        f"(numerical error only): **{r['fastest_within_budget_error_numerical'] or 'none'}**; Monte Carlo: "
        f"**{r['fastest_within_budget_monte_carlo'] or 'none of the ladder'}**.",
        "",
        "## Analytic model: fidelity ladder",
        "",
        "| setting | time / eval | error vs Monte Carlo | numerical error (vs q=16) |",
        "|---|---|---|---|",
    ]
    for row in sorted(r["analytic"], key=lambda x: x["seconds"]):
        lines.append(f"| {row['label']} | {row['seconds'] * 1e6:.0f} us | {row['error_vs_mc']:.3f} | {row['error_numerical']:.2e} |")
    lines += ["", "## Per component (gain fixed on the far edge)", "",
              "| terms | Monte Carlo / analytic (total) | shape error | note |", "|---|---|---|---|"]
    for c in r["components"]:
        lines.append(f"| {c['group']} | {c['ratio_mc_over_analytic']:.3g} | {c['shape_error']:.3f} | {c['note']} |")
    lines += ["", "## Monte Carlo: photons against noise and time", "",
              "| photons per sensor | time | error vs reference | noise estimate |", "|---|---|---|---|"]
    for row in r["monte_carlo"]:
        lines.append(f"| {row['photons']:g} | {row['seconds']:.2f} s | {row['error_vs_mc']:.3f} | {row.get('noise_estimate', float('nan')):.3f} |")
    pr = r["prune"]
    lines += ["", f"## Pruning ({pr['options']['frames']} frames, floor {pr['options']['noise_floor']:g} sigma)", "",
              f"kept: {', '.join(pr['kept'])}; dropped: {', '.join(pr['dropped']) or 'nothing'}"]
    fb = r["fit_bias"]
    lines += ["", "## Downstream: calibration bias (analytic model fitted to the data)", ""]
    if "skipped" in fb:
        lines.append(f"not run: {fb['skipped']}")
    else:
        lines += ["| data | n1 | mu_s /m | mu_a /m | bias in stderr (n1, mu_s, mu_a) | reduced chi2 |", "|---|---|---|---|---|---|"]
        t = fb["truth"]
        lines.append(f"| truth | {t['n1']:.4g} | {t['mu_s_per_m']:.4g} | {t['mu_a_per_m']:.4g} | | |")
        for name in ("analytic data (noise only)", "Monte Carlo data"):
            v = fb[name]
            z = v["bias_in_stderr"]
            lines.append(
                f"| {name} | {v['values']['n1']:.4g} | {v['values']['mu_s_per_m']:.4g} | {v['values']['mu_a_per_m']:.4g} "
                f"| {z['n1']:.1f}, {z['mu_s_per_m']:.1f}, {z['mu_a_per_m']:.1f} | {v['reduced_chi2']:.2f} |"
            )
        pm = fb["pruned model"]
        if pm.get("dropped"):
            z = pm["shift_in_stderr"]
            lines.append("")
            lines.append(f"Pruned model (without {', '.join(pm['dropped'])}) on the analytic data: shift against the full "
                         f"model's fit {z['n1']:.2f}, {z['mu_s_per_m']:.2f}, {z['mu_a_per_m']:.2f} standard errors "
                         f"(n1, mu_s, mu_a), reduced chi2 {pm['reduced_chi2']:.2f}.")
    fs = r["fit_speed"]
    lines += ["", "## Fitting: solver and tolerance", ""]
    if "skipped" in fs:
        lines.append(f"not run: {fs['skipped']}")
    else:
        lines += ["| setting | warm fit s | steps | error (reference stderr) |", "|---|---|---|---|"]
        for row in fs["settings"]:
            lines.append(f"| {row['setting']['label']} | {row['warm_fit_s_median']:.2f} | {row['steps_median']:.0f} "
                         f"| {row['z_max_targets_median']:.3f} |")
    cb = r["contact_bias"]
    lines += ["", "## Contact positions (back-projection detection, matched within 2 cm)", ""]
    if "skipped" in cb:
        lines.append(f"not run: {cb['skipped']}")
    else:
        lines += ["| data | true | detected | matched | mean distance mm | counts added / removed by the contacts |",
                  "|---|---|---|---|---|---|"]
        for name in ("analytic", "monte_carlo"):
            c = cb[name]
            mean = "-" if c["mean_m"] is None else f"{c['mean_m'] * 1e3:.1f}"
            lines.append(f"| {name.replace('_', ' ')} | {c['true']} | {c['detected']} | {c['matched_within_2cm']} | {mean} "
                         f"| {c['touch_gain_counts']:.0f} / {c['touch_loss_counts']:.0f} |")
    return "\n".join(lines) + "\n"


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    ax = axes[0]
    pts = [(row["seconds"], row["error_vs_mc"], row["label"], "C0") for row in r["analytic"]]
    pts += [(row["seconds"], row["error_vs_mc"], row["label"], "C3") for row in r["monte_carlo"]]
    for t, e, lab, col in pts:
        ax.scatter(t, max(e, 1e-6), color=col, s=25)
        ax.annotate(lab, (t, max(e, 1e-6)), fontsize=6)
    # Pareto front
    front, best = [], np.inf
    for t, e, _, _ in sorted(pts):
        if e < best:
            front.append((t, e))
            best = e
    if front:
        ax.plot(*zip(*front), color="0.5", lw=0.8, ls="--")
    ax.axhline(r["config"]["budget"], color="C2", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per evaluation [s] (analytic: blue, Monte Carlo: red)")
    ax.set_ylabel("relative L2 error against the Monte Carlo reference")
    ax.set_title("Pareto: time against error (green: budget)", fontsize=9)
    ax = axes[1]
    for row in r["analytic"]:
        ax.scatter(row["seconds"], max(row["error_numerical"], 1e-9), color="C0", s=25)
        ax.annotate(row["label"], (row["seconds"], max(row["error_numerical"], 1e-9)), fontsize=6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per evaluation [s]")
    ax.set_ylabel("relative L2 error against the analytic model at q=16")
    ax.set_title("numerical error alone", fontsize=9)
    fig.suptitle(f"{r['scene']}: speed against accuracy ({r['data']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    """``python experiments/study_tradeoff.py --out DIR [--config TOML] [--scene S] [--budget B] [--photons N] [--quick]``."""
    import argparse

    from tofjax import enable_x64
    from tofjax.errors import UserError

    ap = argparse.ArgumentParser(description="fidelity ladder, fits and Monte Carlo against a Monte Carlo reference")
    ap.add_argument("--scene", help="scene TOML file or built-in name (default optoskin)")
    ap.add_argument("--config", help="trade-off config TOML (configs/studies/tradeoff.toml)")
    ap.add_argument("--budget", type=float, help="error budget: relative L2 error against the reference")
    ap.add_argument("--photons", type=int, help="reference photons per sensor")
    ap.add_argument("--quick", action="store_true", help="a small run (minutes): fewer photons, no fit study")
    ap.add_argument("--out", required=True, help="output folder")
    a = ap.parse_args(argv)
    enable_x64()
    try:
        cfg = load_tradeoff_config(a.config) if a.config else TradeoffConfig()
        changes = {k: v for k, v in (("scene", a.scene), ("budget", a.budget), ("reference_photons", a.photons)) if v is not None}
        if a.quick:
            changes["quick"] = True
        cfg = dataclasses.replace(cfg, **changes)
        load_scene(cfg.scene)  # fail early on a bad scene
    except UserError as e:
        print(f"study_tradeoff: error: {e}", file=sys.stderr)
        return 2
    result = run_tradeoff(cfg, Path(a.out), progress=True)
    print(Path(a.out, "tradeoff.md").read_text())
    print(f"analytic_vs_mc_relative_l2 (default fidelity): {result['analytic_vs_mc_relative_l2']}")
    print(f"wrote tradeoff.json, tradeoff.md and tradeoff.png to {a.out}/ ({result['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
