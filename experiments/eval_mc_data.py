"""Study: calibration and six-contact detection on Monte Carlo data, with the guided optics (issue 14).

The issue's targets on Monte Carlo data: calibration n1 within 1% and reduced chi-square <= 2;
six-contact detection precision >= 95%, recall >= 90%. Two columns: "own" (tofjax's simulator
with the guided optics and the skin contact model) and "monte carlo" (``tofjax.mc``, validated
against adding-doubling and van de Hulst), each calibrated and inverted the same way:

1. Baseline: the OptoSkin scene without contacts. Monte Carlo: ``seeds_baseline`` runs of
   ``photons`` packets per sensor (seeds 0, 1, ...; 24 next-event elevation nodes, g = 0), their
   mean is the expected transported light, plus the analytic light-entry peak and ambient (no
   transport simulates them: ``tofjax.mc.capture.mc_expected_counts``). The spread between the
   seeds is the Monte Carlo's own variance, reported next to the photon noise.
2. Calibration: ``FitConfig(optics="guided")`` from the nominal scene stating the guided optics'
   physical volume backscatter (``volume_backscatter_fraction`` = 0.5, isotropic scattering);
   ``calib_frames`` frames (10). The reduced chi-square is reported as the fit computes it (photon
   noise only) and with the Monte Carlo's own variance added (the data's other noise).
3. Detection: ``configs`` random six-contact configurations (4 cm apart, strengths 0.7-1.0 of the
   skin coupling), each one Monte Carlo run per seed of the first ``seeds_touch`` seeds (the same
   seeds as the detection baseline: common random numbers, so the touch frame differs from the
   baseline by what the contacts do, not by independent Monte Carlo noise of the whole histogram),
   ``frames_per_config`` photon-noise frames each; inverted with the calibrated optics by the
   ``full`` (back-projection), ``model`` (grid reconstruction) and ``fit`` (greedy contact fit,
   :mod:`tofjax.invert.greedy`) methods; scored as experiments/eval_touch.py scores
   (2 cm match radius). The model method's contact response follows from the calibration: with the
   guided optics it is the skin contact's signed response (added and removed light,
   ``ReconstructOptions.response`` "auto"). ``information_limit``: how much evidence of each contact
   one frame holds (matched-filter SNR at the known position, by the guided model; and the whole
   frame's change), the ceiling of any single-frame detector. Each method also processes 20 no-touch
   frames (``false_per_no_touch_frame``). ``false_detections`` says what the false ones are (a contact fitted
   twice, one placed more than the match radius off, or a ghost with no contact within 4 cm) and lists every
   frame's detections and missed contacts; ``--columns`` detects on one column only.

4. The touch relative L2 of the guided optics against the Monte Carlo on those scenes, split into the
   reference's noise and the model's error (noise removed in quadrature; extrapolated from two photon
   counts), with the touch signal (touch minus baseline) of both; and the first-order contact return
   alone (one contact, absorbing edges), Monte Carlo against the guided optics.

``--config-seed`` draws another set of configurations (a held-out set: 6 is the one the fit method's options were
developed on); ``--true-optics`` detects with the scene's n1, mu_s and mu_a instead of the calibrated ones (the
rest, gains and pulse, as calibrated: how much of the detectors' error is the calibrated optics');
``--fit-options`` sets the fit method's options and ``--fit-variants`` scores variants of them, those that change
only the pruning (``tofjax.invert.greedy.PRUNE_OPTIONS``) from the same search.

``--exposure K`` multiplies every count (the sensor's iterations per frame relative to the scene's): the
photon noise of a frame falls as 1/sqrt(K), as a longer exposure (or K frames of a held contact summed) gives.

Monte Carlo runs are cached under ``out/mc_cache/`` (keyed by scene, options and the Monte Carlo's source). Writes
``eval_mc_data.json`` (copy it to docs/results/). All data **simulated**.

    python experiments/eval_mc_data.py --out out/eval_mc_data [--photons 25000] [--configs 12]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "out" / "mc_cache"


def guided_scene(name: str = "optoskin"):
    """The baseline scene as the guided optics see it: isotropic volume backscatter (0.5)."""
    from tofjax.model.guided import hg_backward_fraction
    from tofjax.scene import load_scene

    scene = load_scene(name).without_touches()
    wg = dataclasses.replace(scene.waveguide, volume_backscatter_fraction=hg_backward_fraction(0.0))
    return scene.replace(waveguide=wg)


def mc_options(photons: int, seed: int):
    from tofjax.mc import MCOptions
    from tofjax.model.contact import SkinContact

    return MCOptions(photons=photons, seed=seed, g=0.0, contact=SkinContact(), nee_points=24, nee_aperture=4)


def mc_expected(scene, photons: int, seed: int, progress: bool = False, edges: str = "diffuse") -> tuple[np.ndarray, dict]:
    """Expected counts of one frame (Monte Carlo transport + analytic light entry and ambient), cached; ``edges``:
    the Monte Carlo's lateral edges (``MCOptions.edges``)."""
    from tofjax.mc.capture import mc_expected_counts

    opts = mc_options(photons, seed)
    if edges != opts.edges:
        opts = dataclasses.replace(opts, edges=edges)
    key = hashlib.sha256((repr(scene) + repr(opts) + mc_source_hash()).encode()).hexdigest()[:20]
    path = CACHE / f"{key}.npz"
    if path.exists():
        z = np.load(path, allow_pickle=False)
        return z["expected"], json.loads(str(z["info"]))
    expected, res = mc_expected_counts(scene, opts, progress=progress)
    info = {"seconds": res.seconds, "events": int(res.events), "photons": photons, "seed": seed,
            "touches": len(scene.touches)}
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, expected=expected, info=json.dumps(info))
    os.replace(tmp, path)
    return expected, info


@functools.lru_cache(maxsize=1)
def mc_source_hash() -> str:
    """A hash of the Monte Carlo's source: a cached run made by another version of the transport (e.g.
    before the contact flag fix) is not reused. Read once per process (every cached run asks for it)."""
    import tofjax.mc as mc

    h = hashlib.sha256()
    for f in sorted(Path(mc.__file__).parent.glob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def mc_baseline_mean(scene, photons: int = 25_000, seeds: int = 8) -> np.ndarray:
    """The Monte Carlo baseline this study calibrates: the mean expected counts of ``seeds`` runs (cached)."""
    return mc_mean_and_variance(np.stack([mc_expected(scene, photons, s)[0] for s in range(seeds)]))[0]


def mc_mean_and_variance(runs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean of Monte Carlo runs (runs first) and the Monte Carlo's own variance of that mean."""
    return runs.mean(0), runs.var(0, ddof=1) / runs.shape[0]


def calibration_baseline(exposure: float = 64.0, photons: int = 25_000, seeds: int = 64):
    """The baseline this study calibrates, as the studies of its calibration alone refit it: ``(scene, expected,
    mc_var)``, the guided scene, the mean of ``seeds`` cached Monte Carlo runs times ``exposure`` and the Monte Carlo's
    own variance of it (``experiments/reverb_spread_grid.py``, ``guided_fidelity_calibration.py``)."""
    scene = guided_scene()
    runs = np.stack([mc_expected(scene, photons, s)[0] for s in range(seeds)])
    mean, var = mc_mean_and_variance(runs)
    return scene, mean * exposure, var * exposure**2


def calibrate_baseline(baseline: tuple, coupling: float = 0.5):
    """The studies' calibration of a :func:`calibration_baseline` (its ``(scene, expected, mc_var)``): 10 frames of
    capture seed 0, guided optics, the multiple-scattering coupling held at ``coupling`` (``near_field_aperture.py``,
    ``calib_mc_seeds.py``). Returns :func:`calibrate_capture`'s figures and result."""
    scene, expected, mc_var = baseline
    cap = _capture(scene, expected, 10, 0, "simulated (monte_carlo)")
    fit_scene = scene.replace(waveguide=dataclasses.replace(scene.waveguide, multiple_scattering=coupling))
    return calibrate_capture(fit_scene, cap, mc_var, "guided")


def study_header(study: str, data: str) -> dict:
    """The head of a JSON of a study of this evaluation's baseline (``reverb_spread_grid.py``,
    ``guided_fidelity_calibration.py``): what, on which data, machine and load, and the scene."""
    return {"study": study, "data": data,
            "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only",
            "load_average_start": list(os.getloadavg()),
            "scene": "optoskin baseline (volume_backscatter_fraction 0.5), as experiments/eval_mc_data.py"}


def write_study(out: dict, path: Path) -> None:
    """Write a study's JSON (headed by :func:`study_header`) with the load average at its end, whole or not at all
    (:func:`tofjax.outputs.atomic_write_text`), and say so."""
    from tofjax.outputs import atomic_write_text

    out["load_average_end"] = list(os.getloadavg())
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


def alternating_medians(fns: dict, repeats: int, *args) -> dict:
    """Median seconds of each compiled function of ``fns`` called on ``args``, after one warm call each, timed in
    alternating order ``repeats`` times (the studies' side-by-side forward times: a shared machine's load moves them
    alike)."""
    import jax

    times = {k: [] for k in fns}
    for f in fns.values():
        jax.block_until_ready(f(*args))
    for _ in range(repeats):
        for k, f in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(f(*args))
            times[k].append(time.perf_counter() - t)
    return {k: statistics.median(v) for k, v in times.items()}


def run_in_own_process(script: str, args: list[str]) -> dict:
    """Run ``python script *args`` and read the JSON object its last line of output prints: a study's variant in a
    process of its own (a model's switches and sampling are fixed when its programs are traced). Raises
    ``RuntimeError`` with the process's last error line when it fails."""
    import subprocess

    run = subprocess.run([sys.executable, script, *args], capture_output=True, text=True)
    if run.returncode != 0:
        raise RuntimeError(f"{' '.join(args)}: the process failed: {run.stderr.strip().splitlines()[-1:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def chi2_with_mc_variance(res, data_mean: np.ndarray, frames: int, mc_var: np.ndarray) -> dict:
    """A calibration's reduced chi-square with the Monte Carlo's own variance (``mc_var``, of the expected counts the
    ``frames``-frame capture of mean ``data_mean`` was drawn around) added to the photon noise, and that variance's
    share of the photon-weighted chi-square (what it adds when left out). From ``res.residuals`` (photon-weighted,
    model - data) at ``model_error`` 0; approximate otherwise."""
    r = np.asarray(res.residuals, np.float64)
    dof = float(np.sum(r**2)) / res.reduced_chi2
    var_p = np.maximum(data_mean, 1.0) / frames
    diff = r * np.sqrt(var_p)  # model - data
    return {"reduced_chi2_with_mc_variance": float(np.sum(diff**2 / (var_p + mc_var)) / dof),
            "mc_variance_over_photon_variance_median": float(np.median(mc_var / var_p)),
            "mc_variance_share_of_photon_weighted_chi2": float(np.sum(mc_var / var_p) / dof)}


def mc_baseline_against_guided(scene) -> tuple[np.ndarray, dict]:
    """The Monte Carlo baseline's transported light (:func:`mc_baseline_mean` less the analytic light entry and
    ambient it adds) and the guided model's transported components at the scene's own optics (a dict by
    component), both (sensors, zones, bins): what the studies of where the guided model departs compare."""
    from tofjax.mc.bench import NOT_TRANSPORTED
    from tofjax.mc.capture import ANALYTIC_EXTRAS
    from tofjax.model import ModelOptions, Params, build_model

    o = ModelOptions(quadrature=4, dtype="float32")  # as mc_expected_counts adds them
    extras = np.asarray(build_model(scene, o, ANALYTIC_EXTRAS)(Params.from_scene(scene, o.jnp_dtype)), float)
    comps = tuple(c for c in scene.components() if c not in NOT_TRANSPORTED)
    model = build_model(scene, ModelOptions(optics="guided"), comps)
    parts = {k: np.asarray(v, float) for k, v in model.breakdown(Params.from_scene(scene)).items()}
    return mc_baseline_mean(scene) - extras, parts


def touch_scene(base, contacts: np.ndarray, radius_m: float = 0.006):
    from tofjax.scene import Touch

    return base.replace(touches=tuple(Touch((float(x), float(y)), radius_m, float(s)) for x, y, s in contacts))


def contact_configs(scene, configs: int, seed: int = 6) -> np.ndarray:
    from tofjax.invert.synth import random_contacts

    return random_contacts(scene, configs, 6, seed=seed, min_separation_m=0.04, strength=(0.7, 1.0))


def generate(photons: int, seeds_baseline: int, seeds_touch: int, configs: int, progress: bool = True,
             config_seed: int = 6) -> None:
    """Fill the cache (the slow part), baseline first."""
    base = guided_scene()
    for s in range(seeds_baseline):
        t = time.time()
        _, info = mc_expected(base, photons, s, progress)
        print(f"baseline seed {s}: {time.time() - t:.0f} s", info, flush=True)
    for c, contacts in enumerate(contact_configs(base, configs, config_seed)):
        for s in range(seeds_touch):
            t = time.time()
            _, info = mc_expected(touch_scene(base, contacts), photons, s, progress)
            print(f"config {c} seed {s}: {time.time() - t:.0f} s", info, flush=True)


def _capture(scene, expected: np.ndarray, frames: int, seed: int, source: str):
    import jax
    import jax.numpy as jnp

    from tofjax.capture import Capture
    from tofjax.model import sample_counts

    keys = jax.random.split(jax.random.key(seed), frames)
    lam = jnp.asarray(expected)
    draw = jax.jit(jax.vmap(lambda k: sample_counts(k, lam, poisson=scene.noise.poisson,
                                                     saturation=scene.sensor.saturation_counts)))
    return Capture(histograms=np.array(draw(keys), np.float64), timestamps=np.arange(frames) / 9.0, scene=scene,
                   source=source)


def mc_study_cli(doc: str, argv=None) -> tuple[argparse.Namespace, Path]:
    """The command line of the studies that hold the guided model against these Monte Carlo runs
    (``contact_zone_share_mc.py``, ``contact_behind_contact_mc.py``): ``--out`` (checked: an existing file
    needs ``--overwrite``; a bad one exits 2 with a one-line error), ``--seeds`` (runs per scene); turns
    float64 on. Returns the arguments and the output path."""
    import tofjax
    from tofjax.outputs import OutputError, check_output

    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--seeds", type=int, default=16, help="Monte Carlo runs per scene (25,000 packets per sensor each)")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    if a.seeds < 1:
        ap.error("--seeds must be >= 1")
    tofjax.enable_x64()
    try:
        return a, check_output(Path(a.out), overwrite=a.overwrite)
    except OutputError as e:
        ap.exit(2, f"error: {e}\n")


def _own_model_options(touch: bool = False):
    from tofjax.model import ModelOptions
    from tofjax.model.contact import SkinContact

    return ModelOptions(optics="guided", skin=SkinContact() if touch else None)


def calibrate_column(scene, expected: np.ndarray, mc_var: np.ndarray | None, frames: int, seed: int, optics: str,
                     source: str) -> tuple[dict, dict]:
    """Calibrate an ``frames``-frame capture of ``expected``; the figures and the calibration JSON."""
    out, res = calibrate_capture(scene, _capture(scene, expected, frames, seed, source), mc_var, optics)
    return out, res.to_json()


def calibrate_capture(scene, cap, mc_var: np.ndarray | None, optics: str, **fit_options):
    """Calibrate ``cap`` (``fit_options``: further :class:`~tofjax.fit.FitConfig` fields, e.g. the model's sampling);
    the figures of :func:`calibrate_column` and the :class:`~tofjax.fit.CalibrationResult`."""
    from tofjax.fit import Calibrator, FitConfig

    frames = cap.n_frames
    t = time.perf_counter()
    res = Calibrator(scene, FitConfig(optics=optics, **fit_options)).fit(cap)
    secs = time.perf_counter() - t
    wg = scene.waveguide
    p = res.params
    out = {
        "optics": optics, "frames": frames, "result": res.result, "converged": bool(res.converged),
        "reduced_chi2_photon_noise": res.reduced_chi2,
        "n1": float(p.n1), "n1_rel_error": float(p.n1) / wg.n1 - 1,
        "n1_stderr": float(np.ravel(res.stderr["n1"])[0]) if "n1" in res.stderr else None,
        "mu_t_per_m": float(p.mu_s_per_m + p.mu_a_per_m),
        "mu_t_rel_error": float(p.mu_s_per_m + p.mu_a_per_m) / (wg.mu_s_per_m + wg.mu_a_per_m) - 1,
        "steps": res.steps, "seconds": secs,
        "stages": [{k: v for k, v in st.items() if k != "starts"} for st in res.stages],
    }
    if mc_var is not None:
        out.update(chi2_with_mc_variance(res, cap.mean(), frames, mc_var))
    return out, res


def detect_column(scene, base_expected: np.ndarray, touch_expected: list[np.ndarray], contacts: np.ndarray,
                  cal_json: dict, frames_per_config: int, baseline_frames: int, seed: int, progress: bool,
                  no_touch_frames: int = 20, exposure: float = 1.0, methods=("full", "model", "fit"),
                  fit_variants: dict | None = None, fit_n_sigmas=(), fit_options: dict | None = None,
                  true_optics: bool = False) -> dict:
    """Six-contact detection with the calibrated optics (``true_optics``: the scene's n1, mu_s and mu_a, the
    calibration's gains, pulse and the rest): full, model and fit methods."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_touch

    from tofjax.invert.correction import OpticalParams
    from tofjax.invert.pipeline import build_inverter

    forced = not cal_json["converged"]
    optical = OpticalParams.from_calibration(dict(cal_json, converged=True), scene)
    if true_optics:  # the scene's n1 and attenuation; gains, pulse and the rest as calibrated (the data's scale)
        wg = scene.waveguide
        optical = dataclasses.replace(optical, n1=float(wg.n1), mu_s_per_m=float(wg.mu_s_per_m),
                                      mu_a_per_m=float(wg.mu_a_per_m))
    cfg = eval_touch.EvalConfig(methods=tuple(m for m in methods if m != "fit"))
    opts = eval_touch._options(cfg)
    base = _capture(scene, base_expected, baseline_frames, seed + 1000, "baseline")
    H = np.concatenate([_capture(scene, e, frames_per_config, seed + 2000 + i, "touch").histograms
                        for i, e in enumerate(touch_expected)])
    truth = np.repeat(contacts, frames_per_config, axis=0)
    border = np.concatenate([eval_touch._edge_distance(scene, c[:, :2]) < cfg.border_m for c in truth])
    out = {"configs": len(contacts), "frames_per_config": frames_per_config, "contacts": int(truth.shape[0] * 6),
           "calibration_forced": forced, "optics": optical.optics, "methods": {},
           "information_limit": information_limit(scene, base_expected, contacts, touch_expected, exposure)}
    fit_variants = dict(fit_variants or {})
    levels = [float(n) for n in (fit_n_sigmas or ())]
    from tofjax.invert.greedy import PRUNE_OPTIONS, FitDetectOptions

    base_opts = FitDetectOptions(**(fit_options or {}))
    # variants of the pruning only (thresholds, model_error, ...) share the plain fit's search
    prune_only = {v: o for v, o in fit_variants.items() if set(o) <= set(PRUNE_OPTIONS)}
    runs = [m for m in methods if m != "fit"] + (
        ["fit", *[f"fit:{v}" for v in fit_variants if v not in prune_only]] if "fit" in methods else [])
    fit_det = None
    snr = np.repeat(np.asarray(out["information_limit"]["per_contact_snr_guided_model"].pop("values")).reshape(
        len(contacts), -1), frames_per_config, axis=0).ravel()
    scores = {}
    for m in runs:
        t = time.perf_counter()
        if m.startswith("fit"):
            from tofjax.invert.greedy import FitDetectOptions, build_fit_detector

            from tofjax.invert.sensitivity import fit_sensitivity_of

            if fit_det is None:  # built once; the variants share its responses and compiled model
                fit_det = build_fit_detector(scene, base.mean(), dataclasses.replace(optical), base_opts,
                                             n_baseline=baseline_frames)
                out["sensitivity_fit"] = fit_map_summary(fit_sensitivity_of(fit_det), contacts, exposure)
                from position_bound import bound_of_set

                out["position_bound"] = {
                    "what": "the recall a detector that finds every contact and places it as well as the data allow "
                            "would score: per true contact, the probability that a fit reaching the joint position "
                            "Cramer-Rao bound (six contacts fitted together, the detector's calibrated model and noise) "
                            "lands within the match radius (experiments/position_bound.py); on the Monte Carlo column "
                            "it is the model's account of the information, not the Monte Carlo's",
                    **{k: v for k, v in bound_of_set(fit_det, scene, contacts, cfg.match_radius_m, cfg.border_m).items()
                       if k != "per_contact"}}
            inv = fit_det if m == "fit" else fit_det.with_options(
                dataclasses.replace(base_opts, **fit_variants[m[4:]]))
            bases = [(m, inv.options)] + ([(f"fit:{v}", dataclasses.replace(inv.options, **o))
                                            for v, o in prune_only.items()] if m == "fit" else [])
            variants, names = [], []
            for name0, o in bases:  # each at its own n_sigma, then at the --fit-n-sigmas levels
                variants += [o, *[dataclasses.replace(o, n_sigma=n) for n in levels]]
                names += [name0, *[f"{name0}_n_sigma_{n:g}" for n in levels]]
            results = inv.process_variants(H, variants)
            quiets = inv.process_variants(
                _capture(scene, base_expected, no_touch_frames, seed + 3000, "no touch").histograms, variants)
        else:
            inv = build_inverter(scene, base.mean(), opts[m], optical, n_baseline=baseline_frames,
                                 baseline_frames=base.histograms)
            names = [m]
            results = [inv.process(H)]
            quiets = [inv.process(_capture(scene, base_expected, no_touch_frames, seed + 3000, "no touch").histograms)]
        for name, res, quiet in zip(names, results, quiets):
            score, found = eval_touch._score(res.detections, truth, cfg.match_radius_m)
            score["no_touch_frames"] = no_touch_frames
            score["false_per_no_touch_frame"] = float(np.mean([len(d.touches) for d in quiet.detections]))
            score["false_on_no_touch_frames"] = int(sum(len(d.touches) for d in quiet.detections))
            found = np.concatenate(found)
            score["recall_border"] = float(found[border].mean()) if border.any() else float("nan")
            score["recall_interior"] = float(found[~border].mean()) if (~border).any() else float("nan")
            score["recall_by_contact_snr"] = _recall_by_snr(found, snr)
            if name.startswith("fit"):
                score["recall_by_map_snr"] = _recall_by_snr(found, map_snr(fit_sensitivity_of(fit_det), truth))
            score["false_detections"] = _false_kinds(res.detections, truth, cfg.match_radius_m)
            score["seconds"] = time.perf_counter() - t
            if getattr(inv, "reconstructor", None) is not None:
                score["contact_response"] = inv.reconstructor.response
            if name.startswith("fit"):
                score["options"] = repr(variants[names.index(name)])
                score["seconds_what"] = ("building (signed responses on the 5 mm grid, compiling) and every frame, "
                                         "all n_sigma levels" if m == "fit" else "every frame (the detector built for "
                                         "'fit' reused)")
                score["reduced_chi2_touch_frames_median"] = float(np.nanmedian(res.chi2 / res.dof))
                score["contacts_found_per_frame"] = np.bincount([len(d.touches) for d in res.detections]).tolist()
            scores[name] = score
    for m, score in scores.items():
        out["methods"][m] = score
        if progress:
            print(f"  {m}: P {score['precision']:.3f} R {score['recall']:.3f} err {score['mean_error_cm']:.2f} cm", flush=True)
    return out


SNR_BINS = (0.0, 3.0, 5.0, 8.0, 12.0, np.inf)


def _false_kinds(detections, truth: np.ndarray, radius: float) -> dict:
    """What the false detections (unmatched, one-to-one within ``radius``) are, by the true contact nearest each:
    ``duplicate`` (that contact is matched by another detection, and it is within 2 radii: a contact fitted twice),
    ``mislocated`` (that contact is unmatched, within 2 radii: found but placed more than ``radius`` off),
    ``ghost`` (no true contact within 2 radii: light explained where there is no contact, e.g. between two).
    With every frame's detections (x, y, strength, matched, and where the method gives them the standard errors
    of x and y) and truth, for inspection."""
    from scipy.optimize import linear_sum_assignment

    kinds = {"duplicate": 0, "mislocated": 0, "ghost": 0}
    nearest, frames = [], []
    for det, c in zip(detections, truth):
        pos = det.positions().reshape(-1, 2)
        ok = np.zeros(len(pos), bool)
        hit = np.zeros(len(c), bool)
        if len(pos):
            dd = np.hypot(*(pos[:, None, :] - c[None, :, :2]).transpose(2, 0, 1))
            r, cc = linear_sum_assignment(np.where(dd <= radius, dd, 1e6))
            good = dd[r, cc] <= radius
            ok[r[good]], hit[cc[good]] = True, True
            for i in np.flatnonzero(~ok):
                j = int(np.argmin(dd[i]))
                nearest.append(float(dd[i, j]))
                kinds["ghost" if dd[i, j] > 2 * radius else "duplicate" if hit[j] else "mislocated"] += 1
        frames.append({"detections": [[round(t["x_m"], 4), round(t["y_m"], 4), round(t["strength"], 3), bool(o),
                                       *([_round_finite(t["x_stderr_m"], 5), _round_finite(t["y_stderr_m"], 5)]
                                         if "x_stderr_m" in t else [])]
                                      for t, o in zip(det.touches, ok)],
                       "missed": [[round(float(x), 4), round(float(y), 4)] for x, y, _ in c[~hit]]})
    return {"what": "false detections by the nearest true contact: duplicate (it is matched by another detection, "
                    "within 2 match radii), mislocated (unmatched, within 2 match radii), ghost (none within 2 radii)",
            **kinds, "nearest_true_contact_cm": [round(100 * d, 2) for d in nearest], "frames": frames}


def _round_finite(v: float, digits: int):
    """``v`` rounded, or None where it is not finite (JSON has no infinity)."""
    return round(float(v), digits) if np.isfinite(v) else None


def _recall_by_snr(found: np.ndarray, snr: np.ndarray) -> dict:
    """Recall of the contacts in bins of their matched-filter SNR (``information_limit``), and the SNR of the
    contacts missed: how far a detector's misses are the noise's (SNR below ~5) or the search's."""
    rows = []
    for lo, hi in zip(SNR_BINS[:-1], SNR_BINS[1:]):
        sel = (snr >= lo) & (snr < hi)
        rows.append({"snr_from": lo, "snr_to": None if np.isinf(hi) else hi, "contacts": int(sel.sum()),
                     "recall": float(found[sel].mean()) if sel.any() else None})
    missed = snr[~found]
    return {"what": "recall of the contacts whose one-frame matched-filter SNR (guided model, known position) is in "
                    "[snr_from, snr_to); the missed contacts' SNR", "bins": rows,
            "missed": int(missed.size), "missed_below_5": int(np.sum(missed < 5)),
            "missed_snr_quantiles_10_50_90": np.quantile(missed, [0.1, 0.5, 0.9]).tolist() if missed.size else None,
            "recall_of_contacts_above_5": float(found[snr >= 5].mean()) if (snr >= 5).any() else None}


def map_snr(sens, contacts: np.ndarray) -> np.ndarray:
    """Each contact's matched-filter SNR by the fit method's sensitivity map (``sens``, strength 1, one frame of
    the map's baseline): the map's value at the contact's cell times its strength; contacts (..., 3) flattened."""
    c = np.asarray(contacts, float).reshape(-1, 3)
    return c[:, 2] / sens.at(c[:, :2])["cell_noise"]


def fit_map_summary(sens, contacts: np.ndarray, exposure: float, strengths=(0.7, 1.0)) -> dict:
    """The fit method's sensitivity map (:func:`tofjax.invert.sensitivity.fit_sensitivity`) of a column's detection
    baseline (at ``exposure``) in what a user asks: for the weakest and strongest contacts of the study, the
    exposure (frames of a held contact summed, relative to one frame at exposure 1) at which a share of the sensed
    area reaches SNR n_sigma (found half the time, alone) and 2 n_sigma (the reliable margin); and the study's own
    contacts' map SNR against the information limit's (true optics, exact position)."""
    from tofjax.invert.sensitivity import RELIABLE_MARGIN

    ok = sens.sensed
    snr1 = 1.0 / sens.cell_noise[ok] / np.sqrt(exposure)  # strength 1, one frame at exposure 1
    rows = {}
    for s in strengths:
        for label, need in (("alone_50%", sens.n_sigma), ("margin_2", RELIABLE_MARGIN * sens.n_sigma)):
            e = (need / (s * snr1)) ** 2  # exposure (frames summed) for this cell
            rows[f"strength_{s:g}_{label}"] = {
                "exposure_for_share_of_sensed_area_50_75_90_95_100": np.quantile(e, [0.5, 0.75, 0.9, 0.95, 1.0]).tolist(),
                "share_of_sensed_area_at_this_exposure": float(np.mean(e <= exposure)),
                **{f"share_at_exposure_{k}": float(np.mean(e <= k)) for k in (1, 4, 16, 32, 64, 128)}}
    c = map_snr(sens, contacts)
    border = sens.border[
        np.clip((np.asarray(contacts)[..., 1].ravel() / sens.grid.dy).astype(int), 0, sens.grid.ny - 1),
        np.clip((np.asarray(contacts)[..., 0].ravel() / sens.grid.dx).astype(int), 0, sens.grid.nx - 1)]
    return {
        "what": "the fit method's sensitivity map (tofjax.invert.sensitivity.fit_sensitivity_of: matched-filter SNR of "
                "a lone contact per 5 mm cell, calibrated optics, this column's detection baseline); threshold "
                f"n_sigma {sens.n_sigma:g}, reliable margin {RELIABLE_MARGIN:g} x (SNR {RELIABLE_MARGIN * sens.n_sigma:g}); "
                "exposures are relative to one frame at the scene's exposure (1)",
        "exposure_of_this_baseline": exposure, "sensed_cells": int(ok.sum()),
        "by_strength": rows,
        "study_contacts_map_snr_at_this_exposure_quantiles_10_25_50_75_90": np.quantile(c, [0.1, 0.25, 0.5, 0.75, 0.9]).tolist(),
        "study_contacts_share_above_margin_2": float(np.mean(c >= RELIABLE_MARGIN * sens.n_sigma)),
        "study_contacts_share_above_margin_2_border_interior": [
            float(np.mean(c[border] >= RELIABLE_MARGIN * sens.n_sigma)) if border.any() else None,
            float(np.mean(c[~border] >= RELIABLE_MARGIN * sens.n_sigma)) if (~border).any() else None],
        "study_contacts_map_snr": c.tolist(),
    }


def predicted_recall(by_snr: dict, snr: np.ndarray, exposure: float, exposures=(16, 32, 64, 128, 256)) -> dict:
    """Recall predicted at other exposures: each contact's map SNR scaled by ``sqrt(exposure' / exposure)``, and
    found with the recall this result measured in that SNR bin (:func:`_recall_by_snr`; an empty bin takes the
    next higher non-empty one's). Assumes recall depends on a contact's SNR only (not on its neighbours' SNR,
    which grows too, nor on the model's error, which photon noise no longer hides at long exposures)."""
    rows = by_snr["bins"]
    rec = [r["recall"] for r in rows]
    for i in range(len(rec) - 2, -1, -1):
        rec[i] = rec[i + 1] if rec[i] is None else rec[i]
    edges = np.asarray(SNR_BINS[1:-1])
    return {"what": "recall if each contact's recall were that of its SNR bin in this result, SNR x sqrt(exposure "
                    "ratio); a prediction, not a measurement",
            **{f"{e:g}": float(np.mean(np.asarray(rec, float)[np.searchsorted(edges, snr * np.sqrt(e / exposure),
                                                                            side="right")])) for e in exposures}}


def found_from_result(score: dict, contacts: np.ndarray, frames_per_config: int) -> np.ndarray:
    """Which true contacts (frames x 6, in order) a scored method found, from its ``false_detections`` frames
    (their ``missed`` lists, positions rounded to 0.1 mm): a saved result checked against a map afterwards."""
    truth = np.repeat(np.asarray(contacts), frames_per_config, axis=0)
    found = []
    for c, fr in zip(truth, score["false_detections"]["frames"]):
        missed = np.asarray(fr["missed"], float).reshape(-1, 2)
        found.append(~np.any(np.all(np.abs(np.round(c[:, None, :2], 4) - missed[None]) < 5e-5, -1), -1))
    return np.concatenate(found)


def information_limit(scene, baseline: np.ndarray, contacts: np.ndarray, touch_expected: list[np.ndarray],
                      exposure: float = 1.0) -> dict:
    """The most any detector can get from one frame.

    - ``per_contact_snr_guided_model``: each true contact's matched-filter signal-to-noise ratio at its
      known position and strength, ``sqrt(sum_bins r^2 / sigma^2)``, with ``r`` the guided model's signed
      response (skin contact, the scene's true optics) of that contact alone, added and removed light, and
      ``sigma^2`` the frame's Poisson variance (the baseline). A contact below ~5 cannot be found at a low
      false-alarm rate when its position is unknown, whatever the detector. It is the model's account: on
      the Monte Carlo column it holds only as far as the model's contact response agrees with the Monte
      Carlo's (it does not; see ``guided_vs_mc_relative_l2``).
    - ``frame_change_snr``: the same for the data's own expected change of a frame, all six contacts
      together (touch minus baseline; for the Monte Carlo, common random numbers, so its own noise is in it)."""
    from tofjax.invert.correction import OpticalParams
    from tofjax.invert.reconstruct import response_matrix

    optical = dataclasses.replace(OpticalParams.from_scene(scene), optics="guided")
    c = np.asarray(contacts).reshape(-1, 3)
    R = response_matrix(scene, optical, c[:, :2], 0.006, signed=True) * c[:, 2, None, None, None] * exposure
    var = np.maximum(baseline, 1.0)
    snr = np.sqrt(np.sum(R**2 / var[None], axis=(1, 2, 3)))
    frame = np.array([np.sqrt(np.sum((t - baseline) ** 2 / var)) for t in touch_expected])
    return {"per_contact_snr_guided_model": {
                "what": "matched-filter SNR of each contact alone in one frame (known position and strength; the "
                        "guided model's signed skin-contact response at the true optics; Poisson noise)",
                "quantiles_10_25_50_75_90": np.quantile(snr, [0.1, 0.25, 0.5, 0.75, 0.9]).tolist(),
                "share_above_4": float(np.mean(snr > 4)), "share_above_5": float(np.mean(snr > 5)),
                "values": snr.tolist()},
            "frame_change_snr": {
                "what": "sqrt(sum (touch - baseline)^2 / baseline) of each configuration's expected frame (six contacts)",
                "median": float(np.median(frame)), "min": float(frame.min()), "max": float(frame.max())}}


def first_order_touch(photons: int = 10_000, distances=(0.05, 0.2)) -> dict:
    """One skin contact on sensor S0's axis, absorbing edges, scattering 0.01 /m: the first-order touch
    return alone, Monte Carlo against the guided optics (the test of the skin's one-sided return)."""
    from tofjax.mc import MCOptions, run_mc
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.model.contact import SkinContact
    from tofjax.scene import Touch, load_scene

    sc = load_scene("optoskin").without_touches()
    sc = sc.replace(waveguide=dataclasses.replace(sc.waveguide, mu_s_per_m=0.01, end_reflectance=0.0))
    s0 = sc.sensors[0]
    ang = np.radians(s0.direction_deg)
    opts = MCOptions(photons=photons, seed=0, edges="absorb", contact=SkinContact(), nee_points=24, nee_aperture=4)
    bare = run_mc(sc, opts).counts
    out = {"what": "one contact on S0's axis, absorbing edges, mu_s 0.01 /m: touch counts of S0",
           "photons_per_sensor": photons, "rows": []}
    for D in distances:
        t = sc.replace(touches=(Touch((s0.position_m[0] + D * np.cos(ang), s0.position_m[1] + D * np.sin(ang)), 0.006, 1.0),))
        mc = float((run_mc(t, opts).counts - bare)[0].sum())
        g = float(np.asarray(build_model(t, ModelOptions(optics="guided", skin=SkinContact()), ("touch",))(
            Params.from_scene(t)))[0].sum())
        out["rows"].append({"distance_m": D, "monte_carlo": mc, "guided": g, "guided_over_mc": g / mc})
    return out


def touch_l2(scene, contacts, photons: int, seeds: int, base_seeds: np.ndarray) -> dict:
    """Guided optics against the Monte Carlo on the six-contact scenes, transported light only (relative L2,
    gain profiled per sensor), split into the Monte Carlo's noise and the model's error two ways:
    (a) subtracting the reference's estimated noise in quadrature, (b) from the L2 at two photon counts
    (each seed alone and their mean), extrapolating ``L2^2 = m^2 + c / photons`` to infinitely many."""
    from tofjax.mc.bench import NOT_TRANSPORTED, profiled_relative_l2
    from tofjax.mc.capture import ANALYTIC_EXTRAS
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.model.contact import SkinContact

    def extras(s):
        o = ModelOptions(quadrature=4, dtype="float32")  # as mc_expected_counts adds them
        return np.asarray(build_model(s, o, ANALYTIC_EXTRAS)(Params.from_scene(s, o.jnp_dtype)), np.float64)

    def guided(s):
        o = ModelOptions(optics="guided", skin=SkinContact() if s.touches else None)
        comps = tuple(c for c in s.components() if c not in NOT_TRANSPORTED)
        return np.asarray(build_model(s, o, comps)(Params.from_scene(s, o.jnp_dtype)), np.float64)

    rows = []
    xb = extras(scene)
    b = base_seeds - xb[None]
    gb = guided(scene)
    for c in contacts:
        ts = touch_scene(scene, c)
        x = extras(ts)
        t = [mc_expected(ts, photons, k)[0] - x for k in range(seeds)]
        ref = np.mean(t, 0)
        g = guided(ts)
        # the touch signal: touch minus baseline of the same seeds (common random numbers)
        d = [t[k] - b[k] for k in range(seeds)]
        dm, dg = np.mean(d, 0), g - gb
        signal = {"mc_added": float(dm.clip(0).sum()), "mc_removed": float(dm.clip(None, 0).sum()),
                  "guided_added": float(dg.clip(0).sum()), "guided_removed": float(dg.clip(None, 0).sum()),
                  "mc_added_per_sensor_per_seed": [np.round(dk.clip(0).sum((1, 2))).tolist() for dk in d],
                  "mc_largest_bin_per_seed": [float(dk.max()) for dk in d]}
        err, _ = profiled_relative_l2(ref, g)
        noise = float(np.linalg.norm(t[0] - t[1]) / np.linalg.norm(ref) / 2.0)
        single = float(np.mean([profiled_relative_l2(tk, g)[0] ** 2 for tk in t]))  # at photons / seeds
        m2 = (seeds * err**2 - single) / (seeds - 1)  # L2^2(N) = m^2 + c / N at N/seeds and N
        rows.append({"relative_l2": err, "reference_noise": noise,
                     "model_error_noise_subtracted": float(np.sqrt(max(err**2 - noise**2, 0.0))),
                     "relative_l2_single_seed_rms": float(np.sqrt(single)),
                     "model_error_extrapolated": float(np.sqrt(max(m2, 0.0))), "touch_signal": signal})
    eb, _ = profiled_relative_l2(b.mean(0), guided(scene))
    nb = float(np.sqrt(b.var(0, ddof=1).sum() / len(b)) / np.linalg.norm(b.mean(0)))
    keys = [k for k in rows[0] if k != "touch_signal"]
    return {"photons_per_sensor": photons * seeds, "touch_configs": rows,
            "touch_median": {k: float(np.median([r[k] for r in rows])) for k in keys},
            "baseline": {"relative_l2": eb, "reference_noise": nb, "photons_per_sensor": photons * len(b),
                         "model_error_noise_subtracted": float(np.sqrt(max(eb**2 - nb**2, 0.0)))}}


def set_guided_switches(items) -> dict:
    """Set ``NAME=VALUE`` module switches of :mod:`tofjax.model.guided` (upper-case names it defines; the value
    parsed as the switch's type: bool as true/false/1/0); returns them as set. Unknown names or bad values raise
    ValueError naming them."""
    import tofjax.model.guided as guided

    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        name, text = name.strip(), text.strip()
        if not sep or not name.isupper() or not hasattr(guided, name):
            known = sorted(k for k in vars(guided) if k.isupper() and not k.startswith("_"))
            raise ValueError(f"{item!r}: expected NAME=VALUE with NAME one of {', '.join(known)}")
        old = getattr(guided, name)
        if isinstance(old, bool):
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"{name}: expected true or false, got {text!r}")
            value = text.lower() in ("true", "1")
        else:
            try:
                value = type(old)(text)
            except ValueError:
                raise ValueError(f"{name}: expected a {type(old).__name__}, got {text!r}") from None
        setattr(guided, name, value)
        out[name] = value
    return out


def run(out: Path, photons: int = 25_000, seeds_baseline: int = 8, seeds_touch: int = 2, configs: int = 12,
        calib_frames: int = 10, frames_per_config: int = 2, baseline_frames: int = 100, seed: int = 0,
        progress: bool = True, overwrite: bool = False, with_default: bool = False, exposure: float = 1.0,
        methods=("full", "model", "fit"), skip_l2: bool = False, fit_variants: dict | None = None,
        fit_n_sigmas=(), columns=("own", "monte_carlo"), fit_options: dict | None = None, config_seed: int = 6,
        true_optics: bool = False, guided_switches: dict | None = None) -> dict:
    import tofjax.invert.greedy  # noqa: F401  (loaded now: the code a long run uses is the code it started with)
    from tofjax.outputs import atomic_write_text, check_output
    from tofjax.simulate import expected_counts

    path = check_output(out / "eval_mc_data.json", overwrite=overwrite)
    t0 = time.perf_counter()
    scene = guided_scene()
    generate(photons, seeds_baseline, 0, 0, progress=False)  # cached; the touch runs after the calibrations
    runs = [mc_expected(scene, photons, s) for s in range(seeds_baseline)]
    seeds = np.stack([e for e, _ in runs])
    mc_base, mc_var = mc_mean_and_variance(seeds)
    transported_noise = float(np.sqrt(mc_var.sum()) / np.linalg.norm(mc_base))
    own_base = expected_counts(scene, _own_model_options())
    contacts = contact_configs(scene, configs, config_seed)
    det_base = seeds[:seeds_touch].mean(0)  # the same seeds as the touch runs (common random numbers)
    own_touch = [expected_counts(touch_scene(scene, c), _own_model_options(True)) for c in contacts]
    # the sensor's exposure (iterations per frame) times the scene's: every count scales, ambient included
    own_base, mc_base, det_base = own_base * exposure, mc_base * exposure, det_base * exposure
    mc_var = mc_var * exposure**2
    own_touch = [e * exposure for e in own_touch]
    result = {
        "study": "calibration and six-contact detection on Monte Carlo data with the guided optics (issue 14)",
        "data": "simulated: 'monte_carlo' by tofjax.mc (validated against adding-doubling and van de Hulst), "
                "'own' by tofjax's analytic model with the guided optics and the skin contact model",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with "
                   "other sessions (loaded)",
        "load_average_start": list(os.getloadavg()),
        "scene": "optoskin (volume_backscatter_fraction 0.5: isotropic scattering, as the guided optics need)",
        "truth": {"n1": scene.waveguide.n1, "mu_s_per_m": scene.waveguide.mu_s_per_m,
                  "mu_a_per_m": scene.waveguide.mu_a_per_m},
        "monte_carlo": {"photons_per_sensor_per_seed": photons, "seeds_baseline": seeds_baseline,
                        "seeds_touch": seeds_touch, "options": repr(mc_options(photons, 0)),
                        "baseline_photons_per_sensor": photons * seeds_baseline,
                        "touch_photons_per_sensor": photons * seeds_touch,
                        "baseline_relative_noise": transported_noise,
                        "seconds_per_run": [i["seconds"] for _, i in runs]},
        "settings": {"calib_frames": calib_frames, "frames_per_config": frames_per_config, "methods": list(methods),
                     "fit_variants": fit_variants or {}, "fit_n_sigmas": list(fit_n_sigmas),
                     "fit_options": fit_options or {},
                     "guided_switches": guided_switches or {},
                     "skip_l2": skip_l2, "detection_columns": list(columns),
                     "baseline_frames": baseline_frames, "configs": configs, "seed": seed, "config_seed": config_seed,
                     "detection_optics": ("the scene's n1, mu_s, mu_a (true); gains, pulse and the rest calibrated"
                                          if true_optics else "calibrated, guided"),
                     "exposure": exposure, "exposure_what": "counts of every frame (baseline, calibration, touch; "
                     "transported light, light entry and ambient) times this: the sensor's iterations per frame "
                     "relative to the scene's",
                     "contacts": "6 per config, 4 cm apart, radius 6 mm, strength 0.7-1.0 (x skin coupling 0.3)"},
        "contacts": contacts.tolist(),
        "calibration": {}, "detection": {},
    }
    cal = {}
    for col, exp, var in (("own", own_base, None), ("monte_carlo", mc_base, mc_var)):
        for optics in ("guided", "default") if (col == "monte_carlo" and with_default) else ("guided",):
            if progress:
                print(f"calibrating {col} with {optics} optics ...", flush=True)
            cached = out / (f"calibration_{col}_{optics}_{calib_frames}f_{photons}x{seeds_baseline}"
                            f"_exposure{exposure:g}_{mc_source_hash() if col == 'monte_carlo' else 'own'}.json")
            if cached.exists():  # a calibration does not depend on the contact model: rerun detection alone
                fig, js = json.loads(cached.read_text())
            else:
                fig, js = calibrate_column(scene, exp, var, calib_frames, seed, optics, f"simulated ({col})")
                atomic_write_text(cached, json.dumps([fig, js]), overwrite=True)
            result["calibration"].setdefault(col, {})[optics] = fig
            cal[col, optics] = js
            if progress:
                print("  ", json.dumps({k: fig.get(k) for k in ("result", "reduced_chi2_photon_noise",
                                                               "reduced_chi2_with_mc_variance", "n1_rel_error")}), flush=True)
    generate(photons, seeds_baseline, seeds_touch, configs, progress=False, config_seed=config_seed)  # cached
    mc_touch = [exposure * np.mean([mc_expected(touch_scene(scene, c), photons, s)[0] for s in range(seeds_touch)], 0)
                for c in contacts]
    for col, b, tl in (("own", own_base, own_touch), ("monte_carlo", det_base, mc_touch)):
        if col not in columns:
            continue
        if progress:
            print(f"detecting six contacts ({col}, guided calibration) ...", flush=True)
        result["detection"][col] = detect_column(scene, b, tl, contacts, cal[col, "guided"], frames_per_config,
                                                 baseline_frames, seed, progress, exposure=exposure, methods=methods,
                                                 fit_variants=fit_variants, fit_n_sigmas=fit_n_sigmas,
                                                 fit_options=fit_options, true_optics=true_optics)
    if not skip_l2:
        if progress:
            print("touch L2: noise and model error ...", flush=True)
        result["guided_vs_mc_relative_l2"] = touch_l2(scene, contacts, photons, seeds_touch, seeds)
        if progress:
            print("  ", json.dumps(result["guided_vs_mc_relative_l2"]["touch_median"]), flush=True)
            print("first-order touch, one contact ...", flush=True)
        result["first_order_touch"] = first_order_touch()
    targets = {}
    for col in ("own", "monte_carlo"):
        c = result["calibration"][col]["guided"]
        d = result["detection"].get(col, {}).get("methods", {})
        targets[col] = {
            "calibration_n1_within_1%": abs(c["n1_rel_error"]) <= 0.01,
            "calibration_reduced_chi2<=2 (photon noise)": c["reduced_chi2_photon_noise"] <= 2.0,
            **({"calibration_reduced_chi2<=2 (with the Monte Carlo's variance)": c["reduced_chi2_with_mc_variance"] <= 2.0}
               if "reduced_chi2_with_mc_variance" in c else {}),
            **{f"{m}_precision>=95%": d[m]["precision"] >= 0.95 for m in d},
            **{f"{m}_recall>=90%": d[m]["recall"] >= 0.90 for m in d},
        }
    result["targets"] = targets
    result["load_average_end"] = list(os.getloadavg())
    result["seconds"] = time.perf_counter() - t0
    atomic_write_text(path, json.dumps(result, indent=1))
    return result


def check_map(out: Path, result_path: Path, overwrite: bool = False) -> dict:
    """The fit method's sensitivity map of each detection column of a saved result (``result_path``, written by
    :func:`run` into ``out``, whose cached calibrations it reuses), rebuilt from the same baseline frames (same
    Monte Carlo seeds, exposure and photon-noise seed) without compiling the fit's model, and the result's recall
    by the map's per-contact SNR (from its ``false_detections`` frames): does the map predict what was found?
    Writes ``out/sensitivity_check.json``."""
    from tofjax.invert.correction import OpticalParams
    from tofjax.invert.sensitivity import fit_sensitivity
    from tofjax.outputs import atomic_write_text, check_output
    from tofjax.simulate import expected_counts

    path = check_output(out / "sensitivity_check.json", overwrite=overwrite)
    r = json.loads(Path(result_path).read_text())
    st, mc = r["settings"], r["monte_carlo"]
    E, photons, nb, nt = st["exposure"], mc["photons_per_sensor_per_seed"], mc["seeds_baseline"], mc["seeds_touch"]
    scene = guided_scene()
    contacts = np.asarray(r["contacts"])
    result = {"study": "the fit method's sensitivity map against a saved six-contact result (issue 14); simulated",
              "result": str(result_path), "exposure": E, "load_average_start": list(os.getloadavg()), "columns": {}}
    for col, score in r["detection"].items():
        if col == "own":
            b = expected_counts(scene, _own_model_options()) * E
        else:
            b = E * np.mean([mc_expected(scene, photons, k)[0] for k in range(nt)], 0)
        cal = out / (f"calibration_{col}_guided_{st['calib_frames']}f_{photons}x{nb}"
                     f"_exposure{E:g}_{mc_source_hash() if col == 'monte_carlo' else 'own'}.json")
        if cal.exists():
            _, js = json.loads(cal.read_text())
        else:  # calibrated as run() does (and cached the same way)
            if col == "own":
                exp, var = b, None
            else:
                seeds = np.stack([mc_expected(scene, photons, k)[0] for k in range(nb)])
                exp, var = E * seeds.mean(0), E**2 * seeds.var(0, ddof=1) / nb
            fig, js = calibrate_column(scene, exp, var, st["calib_frames"], st["seed"], "guided", f"simulated ({col})")
            atomic_write_text(cal, json.dumps([fig, js]), overwrite=True)
        optical = OpticalParams.from_calibration(dict(js, converged=True), scene)
        base = _capture(scene, b, st["baseline_frames"], st["seed"] + 1000, "baseline")
        t = time.perf_counter()
        sens = fit_sensitivity(scene, base.mean(), optical, n_baseline=st["baseline_frames"])
        c = {"map_seconds": time.perf_counter() - t,
             "sensitivity_fit": fit_map_summary(sens, contacts, E), "methods": {}}
        snr = map_snr(sens, np.repeat(contacts, score["frames_per_config"], axis=0))
        for m, sc in score["methods"].items():
            if "false_detections" in sc:
                found = found_from_result(sc, contacts, score["frames_per_config"])
                by = _recall_by_snr(found, snr)
                c["methods"][m] = {"recall": float(found.mean()), "recall_in_result": sc["recall"],
                                   "recall_by_map_snr": by,
                                   "predicted_recall_at_exposure": predicted_recall(by, snr, E)}
        result["columns"][col] = c
    result["load_average_end"] = list(os.getloadavg())
    atomic_write_text(path, json.dumps(result, indent=1))
    return result


def main(argv=None):
    import tofjax

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/eval_mc_data")
    ap.add_argument("--generate", action="store_true", help="only fill the Monte Carlo cache")
    ap.add_argument("--photons", type=int, default=25_000, help="Monte Carlo packets per sensor and seed")
    ap.add_argument("--seeds-baseline", type=int, default=8)
    ap.add_argument("--seeds-touch", type=int, default=2)
    ap.add_argument("--configs", type=int, default=12)
    ap.add_argument("--config-seed", type=int, default=6,
                    help="seed of the random six-contact configurations (6: the study's; another: a held-out set)")
    ap.add_argument("--calib-frames", type=int, default=10)
    ap.add_argument("--frames-per-config", type=int, default=2)
    ap.add_argument("--with-default", action="store_true", help="also calibrate the Monte Carlo data with the default optics")
    ap.add_argument("--exposure", type=float, default=1.0,
                    help="the sensor's iterations per frame relative to the scene's: every count times this")
    ap.add_argument("--methods", default="full,model,fit", help="detection methods, comma-separated")
    ap.add_argument("--fit-options", default="{}",
                    help='JSON: FitDetectOptions fields of the fit method (its variants start from them), e.g. '
                         '\'{"max_strength": 2}\'')
    ap.add_argument("--fit-variants", default="{}",
                    help='JSON: name -> FitDetectOptions fields, each scored as method "fit:name" next to "fit" '
                         '(the defaults), e.g. \'{"n5": {"n_sigma": 5}}\'')
    ap.add_argument("--fit-n-sigmas", default="",
                    help='--method fit also at these thresholds (comma-separated), scored as "fit_n_sigma_N" from the '
                         'same search (only the final pruning depends on n_sigma)')
    ap.add_argument("--skip-l2", action="store_true",
                    help="leave out the guided-vs-Monte-Carlo L2 and the first-order touch (they do not depend on the "
                         "detectors; minutes of Monte Carlo on a loaded machine)")
    ap.add_argument("--columns", default="own,monte_carlo",
                    help="detection columns, comma-separated: own, monte_carlo (both calibrated either way)")
    ap.add_argument("--check-map", metavar="RESULT_JSON",
                    help="only the fit method's sensitivity map of each detection column of a saved result (run with "
                         "the same --out: its cached calibrations) and that result's recall by the map's SNR; writes "
                         "OUT/sensitivity_check.json")
    ap.add_argument("--true-optics", action="store_true",
                    help="detect with the scene's n1, mu_s and mu_a instead of the calibrated ones (gains, pulse and "
                         "the rest as calibrated: the data's scale)")
    ap.add_argument("--guided-switch", action="append", default=[], metavar="NAME=VALUE",
                    help="set a module switch of tofjax.model.guided for this run (e.g. REVERB_LEGS=true; repeatable)")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    try:
        switches = set_guided_switches(a.guided_switch)
    except ValueError as e:
        ap.error(f"--guided-switch: {e}")
    if not (a.exposure > 0 and np.isfinite(a.exposure)):
        ap.error(f"--exposure: must be a finite number > 0, got {a.exposure!r}")
    from tofjax.config import ConfigError
    from tofjax.invert.greedy import FitDetectOptions

    try:
        fit_options = json.loads(a.fit_options)
        base_opts = FitDetectOptions(**fit_options)
    except (ValueError, TypeError, AttributeError, ConfigError) as e:
        ap.error(f"--fit-options: {e}")
    try:
        variants = json.loads(a.fit_variants)

        for v in variants.values():
            dataclasses.replace(base_opts, **v)
    except (ValueError, TypeError, AttributeError, ConfigError) as e:
        ap.error(f"--fit-variants: {e}")
    try:
        levels = tuple(float(x) for x in a.fit_n_sigmas.split(",") if x.strip())
    except ValueError as e:
        ap.error(f"--fit-n-sigmas: {e}")
    if not all(n >= 0 and np.isfinite(n) for n in levels):
        ap.error(f"--fit-n-sigmas: each must be a finite number >= 0, got {a.fit_n_sigmas!r}")
    cols = tuple(c.strip() for c in a.columns.split(",") if c.strip())
    if not cols or set(cols) - {"own", "monte_carlo"}:
        ap.error(f"--columns: own and/or monte_carlo, got {a.columns!r}")
    tofjax.enable_x64()
    if a.check_map:
        r = check_map(Path(a.out), Path(a.check_map), overwrite=a.overwrite)
        for col, c in r["columns"].items():
            for m, v in c["methods"].items():
                print(col, m, json.dumps([(b["snr_from"], b["contacts"], b["recall"]) for b in v["recall_by_map_snr"]["bins"]]))
        print(f"wrote {a.out}/sensitivity_check.json")
        return
    if a.generate:
        generate(a.photons, a.seeds_baseline, a.seeds_touch, a.configs, progress=False, config_seed=a.config_seed)
        return
    r = run(Path(a.out), a.photons, a.seeds_baseline, a.seeds_touch, a.configs, a.calib_frames, a.frames_per_config,
            overwrite=a.overwrite, with_default=a.with_default, exposure=a.exposure,
            methods=tuple(m.strip() for m in a.methods.split(",") if m.strip()), skip_l2=a.skip_l2, fit_variants=variants,
            fit_n_sigmas=levels, columns=cols, fit_options=fit_options, config_seed=a.config_seed,
            true_optics=a.true_optics, guided_switches=switches)
    print(json.dumps(r["targets"], indent=1))
    print(f"wrote {a.out}/eval_mc_data.json")


if __name__ == "__main__":
    main()
