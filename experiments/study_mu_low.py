"""Study: is the low-attenuation miss of the calibration noise or bias? (issue 13, mu_t = 0.05 /m)

``study_calib_independent.py`` meets n1 within 1% everywhere but misses mu_t = mu_s + mu_a
within 25% at mu_t = 0.05 /m (one fit per truth). Here every truth at mu_t = 0.05 /m is fitted
on ``replicates`` baselines of the same rig that differ only in the photon-noise seed, from
both simulators (``own``: ``tofjax.simulate``; ``independent``: ``tests/indep_sim.py``, the rig
of the calibration study at that grid point, fixed), at several frame counts. Per
(simulator, n1, frames):

* the bias: the mean relative error of mu_t and its standard error (sd / sqrt(replicates));
* the spread: the sd of the relative error against the mean Laplace standard error, and
  z = error / Laplace standard error (sd of z ~ 1 where the interval is honest);
* the share within 25%, converged fits, reduced chi-square;
* the misfit that replicates share: the residual maps ``(model - data) / sigma`` averaged over
  the replicates (times sqrt(replicates), so noise alone gives unit variance): its mean square
  (~1 without a shared misfit) and its mean over zones per bin (a shape the model lacks).

Then the frames needed: the sd of the relative error against frames, with the power law fitted
(-1/2 if the error is photon noise), and the frames at which 2 sd reach 25% (extrapolated), or
|bias| + 2 sd reach 25% (never where the bias alone exceeds 25%).

The scene is the calibration study's (3 sensors, 7 zones, 128 bins, optoskin, albedo 0.8).
Column ``independent_dense`` (opt-in): the same rigs sampled 4x denser (the independent
simulator's frozen sampling noise taken out). ``--diagnose`` fits the same seeds with the rig
or tofjax changed one thing at a time (``VARIANTS``) and writes ``mu_low_diagnose.json``.
Run it in parts (``--columns``, ``--n1``) on a loaded machine and ``--merge`` them.

    python experiments/study_mu_low.py --out out/mu_low [--replicates 16] [--frames 60 240 960]
        [--n1 1.3 1.45 1.6] [--columns own,independent] [--quick] [--overwrite]

More replicates later: ``--first-replicate 32`` fits new seeds (replicates 32..), any subset of
points and frame counts; ``--merge-replicates A/mu_low.json B/mu_low.json --out C`` joins the
fits per point and recomputes every figure, including ``planner`` (:func:`planner_check`: does the
precision plan of the 60-frame fits, ``CalibrationResult.precision``, predict the spread at more
frames?). Seeds must be unique per point across parts and frame counts (checked).

Writes ``mu_low.json`` (copy it to ``docs/results/``). **Simulated** data.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

import tofjax
from tofjax.fit import Calibrator, FitConfig
from tofjax.fit._precision import frames_needed
from tofjax.outputs import atomic_write_text, check_output
from tofjax.scene import load_scene
from tofjax.simulate import simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from indep_sim import CONVERGED, IndepOptions, IndepRig  # noqa: E402
from indep_sim import simulate as simulate_independent  # noqa: E402
from study_calib_independent import ALBEDO, FULL, _mu_t_stderr, _scene, truth_scene  # noqa: E402

MU_T = 0.05
# independent_dense: the same rigs (same per-zone draws) with the geometry sampled 4x denser
# (DENSE): the independent simulator's frozen sampling noise taken out
# independent_converged: the same rigs at indep_sim.CONVERGED (0.125 mm, 96 angles, 384 edge
# rays), where the expected counts stop changing (--convergence, mu_low_convergence.json)
COLUMNS = ("own", "independent", "independent_dense", "independent_converged")


@dataclasses.dataclass(frozen=True)
class MuLowConfig:
    n1: tuple[float, ...] = (1.3, 1.45, 1.6)
    mu_t: float = MU_T
    frames: tuple[int, ...] = (60, 240, 960)
    replicates: int = 16
    first_replicate: int = 0  # replicate r has seed ... + first_replicate + r: a later part adds new seeds
    columns: tuple[str, ...] = ("own", "independent")
    sensors: int = FULL["sensors"]
    zones: int = FULL["zones"]
    bins: int = FULL["bins"]

    def __post_init__(self):
        if self.replicates < 2:
            raise ValueError(f"replicates: at least 2 (a spread needs two), got {self.replicates}")
        if not 0 <= self.first_replicate or self.first_replicate + self.replicates > 100:
            raise ValueError(f"first_replicate: replicates {self.first_replicate}.. must stay below 100 (seeds of the next frame count)")
        bad = [c for c in self.columns if c not in COLUMNS]
        if bad:
            raise ValueError(f"columns: unknown column {bad[0]!r}; known: {', '.join(COLUMNS)}")
        if not self.frames or min(self.frames) < 1:
            raise ValueError(f"frames: positive frame counts, got {self.frames}")


QUICK = MuLowConfig(n1=(1.45,), frames=(20,), replicates=2, sensors=2, zones=3, bins=96)


def _grid_index(n1: float, mu_t: float) -> int:
    """The calibration study's grid index of (n1, mu_t) (its rig seed is 200 + index), or 0."""
    grid = [(a, b) for a in FULL["n1"] for b in FULL["mu_t"]]
    return grid.index((n1, mu_t)) if (n1, mu_t) in grid else 0


def _full_scene():
    """The nominal scene of the calibration study's grid (``FULL``'s sensors, zones and bins)."""
    return _scene(load_scene("optoskin"), FULL["sensors"], FULL["zones"], FULL["bins"])


def _truth(nominal, n1: float, mu_t: float):
    """``nominal`` at (n1, mu_t) with the study's albedo, and its grid index (:func:`_grid_index`)."""
    return truth_scene(nominal, n1, mu_t), _grid_index(n1, mu_t)


def _group(rows: list[dict], resid: np.ndarray | None) -> dict:
    e = np.array([r["mu_t_rel_error"] for r in rows])
    se = np.array([np.nan if r["mu_t_stderr_rel"] is None else r["mu_t_stderr_rel"] for r in rows])
    z = e / se
    n = len(e)
    out = {
        "replicates": n,
        "converged": int(sum(r["converged"] for r in rows)),
        "mu_t_bias": float(e.mean()),
        "mu_t_bias_stderr": float(e.std(ddof=1) / np.sqrt(n)),
        "mu_t_bias_in_its_stderr": float(e.mean() / (e.std(ddof=1) / np.sqrt(n))),
        "mu_t_rel_error_sd": float(e.std(ddof=1)),
        "mu_t_laplace_stderr_rel_mean": float(np.nanmean(se)),
        "sd_over_laplace": float(e.std(ddof=1) / np.nanmean(se)),
        "z_mean": float(np.nanmean(z)),
        "z_sd": float(np.nanstd(z, ddof=1)),
        "z_abs_over_2": int(np.sum(np.abs(z) > 2)),
        "within_25pct": int(np.sum(np.abs(e) <= 0.25)),
        "n1_rel_error_mean": float(np.mean([r["n1_rel_error"] for r in rows])),
        "n1_rel_error_abs_max": float(np.max(np.abs([r["n1_rel_error"] for r in rows]))),
        "reduced_chi2_median": float(np.median([r["reduced_chi2"] for r in rows])),
        "seconds_median": float(np.median([r["seconds"] for r in rows])),
    }
    if resid is not None:
        # mean residual map over replicates, scaled so that noise alone has unit variance per cell
        m = resid.mean(0) * np.sqrt(resid.shape[0])
        by_bin = m.mean(axis=(0, 1)) * np.sqrt(m.shape[0] * m.shape[1])
        zone = (m**2).mean(-1)
        S, Z = zone.shape
        worst = np.argsort(zone.ravel())[::-1][:3]
        out["shared_misfit"] = {
            "mean_square": float((m**2).mean()),
            "zone_mean_square_max": float(zone.max()),
            "worst_zones": [{"sensor": int(f // Z), "zone": int(f % Z), "mean_square": float(zone.ravel()[f])} for f in worst],
            "by_bin_mean_square": float((by_bin**2).mean()),
            "by_bin_abs_max": float(np.abs(by_bin).max()),
            "by_bin_worst": int(np.argmax(np.abs(by_bin))),
            "by_bin": by_bin.round(2).tolist(),
            "note": "replicate-mean residual x sqrt(replicates) (by_bin: also x sqrt(sensors x zones)); "
            "~N(0, 1) per cell where the model describes what the replicates share",
        }
    return out


def _scaling(groups: dict, cfg: MuLowConfig) -> dict:
    """sd of the relative error against frames: the power law and the frames for 2 sd <= 25%."""
    out = {}
    for col in cfg.columns:
        for n1 in cfg.n1:
            key = f"{col} n1={n1}"
            g = groups.get(col, {}).get(str(n1), {})
            frames = [fr for fr in cfg.frames if str(fr) in g]  # a merged column may lack some
            if not frames:
                continue
            f = np.array(frames, float)
            sd = np.array([g[str(fr)]["mu_t_rel_error_sd"] for fr in frames])
            rms = np.array([np.sqrt(g[str(fr)]["mu_t_bias"] ** 2 + g[str(fr)]["mu_t_rel_error_sd"] ** 2) for fr in frames])
            row = {"frames": list(frames), "sd": sd.tolist(), "rms_error": rms.tolist()}
            if len(f) >= 2:
                slope, icpt = np.polyfit(np.log(f), np.log(sd), 1)
                row["sd_power_law_exponent"] = float(slope)
                # frames at which 2 sd = 25% (95% of fits within 25% if unbiased), on the fitted law
                row["frames_for_2sd_within_25pct"] = float(np.exp((np.log(0.125) - icpt) / slope)) if slope < 0 else None
                # and on the 1/sqrt(frames) law from the largest frame count
                row["frames_for_2sd_within_25pct_sqrt_law"] = float(f[-1] * (sd[-1] / 0.125) ** 2)
                # with the bias measured at the largest frame count (it does not fall with frames):
                # |bias| + 2 sd <= 25%, never where the bias alone exceeds it
                bias = abs(g[str(frames[-1])]["mu_t_bias"])
                room = 0.25 - bias
                row["bias_at_most_frames"] = bias
                row["frames_for_bias_plus_2sd_within_25pct"] = float(f[-1] * (2 * sd[-1] / room) ** 2) if room > 0 else None
            out[key] = row
    return out


def _within(target: float, sd: float) -> float:
    """P(|error| <= target) for an unbiased normal error of this sd."""
    return math.erf(target / (sd * math.sqrt(2))) if sd > 0 else 1.0


def planner_check(fits: dict, mu_t: float = MU_T, target: float = 0.25, n1_target: float = 0.01) -> dict:
    """Does the precision plan (``tofjax.fit._precision``, what ``CalibrationResult.precision``
    holds) made on the fewest-frame fits predict the spread at more frames? Per (column, n1):
    the frames each such fit plans for mu_t within ``target`` at 95% (its own standard error
    relative to its own estimate, as the library computes it), and, for every larger frame
    count, the sd those fits predict (median Laplace sd x sqrt(F0 / F)) and the share within
    ``target`` they predict (unbiased normal) against what the replicates at F show."""
    out = {}
    for col, by_n1 in fits.items():
        for n1, by_fr in by_n1.items():
            frs = sorted(int(f) for f in by_fr)
            if not frs:
                continue
            f0 = frs[0]
            rows = [r for r in by_fr[str(f0)] if r["mu_t_stderr_rel"] is not None]
            if not rows:
                continue
            est = np.array([r["mu_s_per_m"] + r["mu_a_per_m"] for r in rows])
            se = np.array([r["mu_t_stderr_rel"] * mu_t for r in rows])  # absolute
            plan = [frames_needed(f0, float(s / e), target) if e > 0 else None for s, e in zip(se, est)]
            plan_f = np.array([np.nan if p is None else p for p in plan], float)
            sd0 = float(np.median(se / mu_t))  # relative to the truth, as the replicates' spread is
            row = {
                "from_frames": f0,
                "fits": len(rows),
                "planned_frames_median": float(np.nanmedian(plan_f)),
                "planned_frames_quartiles": [float(np.nanpercentile(plan_f, 25)), float(np.nanpercentile(plan_f, 75))],
                "planned_frames_from_median_sd": frames_needed(f0, sd0, target),
                "laplace_sd_rel_median": sd0,
                "observed_sd_rel": float(np.std([r["mu_t_rel_error"] for r in by_fr[str(f0)]], ddof=1)),
            }
            n1_se = [r.get("n1_stderr") for r in rows]
            if all(x is not None for x in n1_se):
                n1_plan = [frames_needed(f0, x / (float(n1) * (1 + r["n1_rel_error"])), n1_target) for x, r in zip(n1_se, rows)]
                row["n1_planned_frames_max"] = int(max(n1_plan))
            pred = {}
            for f in frs[1:]:
                e = np.array([r["mu_t_rel_error"] for r in by_fr[str(f)]])
                sd_pred = sd0 * math.sqrt(f0 / f)
                pred[str(f)] = {
                    "predicted_sd": sd_pred,
                    "observed_sd": float(e.std(ddof=1)),
                    "observed_over_predicted": float(e.std(ddof=1) / sd_pred),
                    "observed_bias": float(e.mean()),
                    "predicted_within": _within(target, sd_pred),
                    "observed_within": float(np.mean(np.abs(e) <= target)),
                    "replicates": int(e.size),
                }
            row["at_more_frames"] = pred
            out[f"{col} n1={n1}"] = row
    return {"target": target, "n1_target": n1_target, "confidence": 0.95,
            "note": "plan = frames x (1.96 sd / target)^2 with sd relative to the fit's own estimate (the library's "
                    "rule); predicted sd at F = median Laplace sd of the fewest-frame fits x sqrt(F0 / F); "
                    "predicted within = P(|N(0, sd)| <= target): photon noise only, no bias",
            "by_point": out}


def run(out: Path, cfg: MuLowConfig = MuLowConfig(), config: FitConfig = FitConfig(), progress: bool = True,
        overwrite: bool = False) -> dict:
    path = check_output(out / "mu_low.json", overwrite=overwrite)
    t0 = time.perf_counter()
    nominal = _scene(load_scene("optoskin"), cfg.sensors, cfg.zones, cfg.bins)
    cal = Calibrator(nominal, config)
    fits: dict = {c: {} for c in cfg.columns}
    groups: dict = {c: {} for c in cfg.columns}
    for n1 in cfg.n1:
        truth, k = _truth(nominal, n1, cfg.mu_t)
        rig = IndepRig.from_scene(truth, seed=200 + k)  # the calibration study's rig at this grid point
        rigs = {"independent": rig}
        if "independent_dense" in cfg.columns:
            rigs["independent_dense"] = IndepRig.from_scene(truth, seed=200 + k, options=DENSE)
        if "independent_converged" in cfg.columns:
            rigs["independent_converged"] = IndepRig.from_scene(truth, seed=200 + k, options=CONVERGED)
        for col in cfg.columns:
            fits[col][str(n1)], groups[col][str(n1)] = {}, {}
            for fr in cfg.frames:
                rows, resid = [], []
                for r in range(cfg.first_replicate, cfg.first_replicate + cfg.replicates):
                    seed = 10_000 + 1000 * k + 100 * cfg.frames.index(fr) + r
                    if col == "own":
                        cap = simulate(truth, fr, seed=seed)
                    else:
                        cap = simulate_independent(rigs[col], contacts=np.zeros((0, 3)), frames=fr, seed=seed)
                    t = time.perf_counter()
                    res = cal.fit(cap)
                    sec = time.perf_counter() - t
                    f_mu = float(res.params.mu_s_per_m + res.params.mu_a_per_m)
                    se = _mu_t_stderr(res)
                    rows.append({
                        "seed": seed,
                        "result": res.result,
                        "converged": bool(res.converged),
                        "n1_rel_error": float(res.params.n1) / n1 - 1,
                        "mu_t_rel_error": f_mu / cfg.mu_t - 1,
                        "mu_t_stderr_rel": None if se is None else se / cfg.mu_t,
                        "n1_stderr": float(np.ravel(res.stderr["n1"])[0]) if "n1" in res.stderr else None,
                        "mu_s_per_m": float(res.params.mu_s_per_m),
                        "mu_a_per_m": float(res.params.mu_a_per_m),
                        "reduced_chi2": float(res.reduced_chi2),
                        "seconds": sec,
                    })
                    if res.residuals is not None:
                        resid.append(np.asarray(res.residuals, np.float64))
                fits[col][str(n1)][str(fr)] = rows
                g = _group(rows, np.stack(resid) if len(resid) == len(rows) else None)
                groups[col][str(n1)][str(fr)] = g
                if progress:
                    print(f"{col:11s} n1 {n1:.2f} frames {fr:5d}: bias {100 * g['mu_t_bias']:+6.1f} +- {100 * g['mu_t_bias_stderr']:4.1f}%  "
                          f"sd {100 * g['mu_t_rel_error_sd']:5.1f}% laplace {100 * g['mu_t_laplace_stderr_rel_mean']:5.1f}%  "
                          f"z sd {g['z_sd']:.2f}  within 25% {g['within_25pct']}/{g['replicates']}  "
                          f"misfit {g.get('shared_misfit', {}).get('mean_square', float('nan')):.2f}  ({g['seconds_median']:.2f} s/fit)",
                          flush=True)
                atomic_write_text(path, json.dumps(_result(cfg, config, groups, fits, None, t0, finished=False), indent=2))
    result = _result(cfg, config, groups, fits, _scaling(groups, cfg), t0, finished=True)
    result["planner"] = planner_check(fits, cfg.mu_t)
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def _pooled(groups: dict, cfg: MuLowConfig) -> dict:
    """Per simulator and frame count, over the n1: the bias, its stderr, sd of z, misses."""
    out = {}
    for col in cfg.columns:
        for fr in cfg.frames:
            gs = [groups[col][str(n1)][str(fr)] for n1 in cfg.n1 if str(n1) in groups[col] and str(fr) in groups[col][str(n1)]]
            if not gs:
                continue
            n = sum(g["replicates"] for g in gs)
            out[f"{col} frames={fr}"] = {
                "replicates": n,
                "bias_mean": float(np.mean([g["mu_t_bias"] for g in gs])),
                "bias_stderr": float(np.sqrt(np.sum([g["mu_t_bias_stderr"] ** 2 for g in gs])) / len(gs)),
                "z_sd_rms": float(np.sqrt(np.mean([g["z_sd"] ** 2 for g in gs]))),
                "within_25pct": int(sum(g["within_25pct"] for g in gs)),
            }
    return out


def _result(cfg, config, groups, fits, scaling, t0, finished) -> dict:
    return {
        "study": "calibration at low attenuation (mu_s + mu_a = 0.05 /m): noise or bias, and frames needed",
        "data": "simulated (own: tofjax.simulate; independent: tests/indep_sim.py, the calibration study's rig per n1)",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
        "load_average": list(os.getloadavg()),
        "finished": finished,
        "seconds": time.perf_counter() - t0,
        "config": dataclasses.asdict(cfg) | {"base": "optoskin", "albedo": ALBEDO},
        "fit_config": dataclasses.asdict(config),
        "target": "mu_t within 25% of the truth",
        "pooled": _pooled(groups, cfg),
        "groups": groups,
        "scaling": scaling,
        "fits": fits,
    }


def _calibrator_with_rays(scene, config: FitConfig, angles_per_zone: int) -> Calibrator:
    """A calibrator whose model traces ``angles_per_zone`` rays per zone (the far edge and the
    range truncation; tofjax's default is 8). FitConfig does not expose it: the problem is
    rebuilt here as ``build_problem`` builds it, with that one option changed (a diagnosis, not
    a change of tofjax)."""
    from tofjax.fit._problem import CalibrationProblem
    from tofjax.fit.transforms import default_transforms
    from tofjax.model import ModelOptions, build_model

    cal = Calibrator(scene, config)
    options = ModelOptions(quadrature=config.quadrature, dtype=config.dtype, pulse_tails=config.pulse_tails,
                           optics=config.optics, angles_per_zone=angles_per_zone)
    base = scene.without_touches()
    cal.problem = CalibrationProblem.build(build_model(base, options), default_transforms(base), config.free,
                                           zone_gain=config.zone_gain, prior_width=config.prior_width, zone_end=config.zone_end)
    return cal


DENSE = IndepOptions(angles_per_zone=48, end_rays=192, range_step_m=0.25e-3)
NOSPREAD = IndepOptions(gain_spread=0.0, crosstalk_spread=0.0, ambient_spread=0.0)
NOSPREAD_DENSE = dataclasses.replace(DENSE, gain_spread=0.0, crosstalk_spread=0.0, ambient_spread=0.0)
VARIANTS = {
    # name: (data, tofjax rays per zone)
    "independent as is / tofjax 8 rays": ("indep", 8),
    "independent sampled 4x denser / tofjax 8 rays": ("indep dense", 8),
    "independent as is / tofjax 32 rays": ("indep", 32),
    "independent sampled 4x denser / tofjax 32 rays": ("indep dense", 32),
    "independent, another rig (seed 999) / tofjax 8 rays": ("indep rig999", 8),
    "own / tofjax 8 rays": ("own", 8),
    "own / tofjax 32 rays": ("own", 32),
    # which of the rig's per-zone draws moves the bias (the other draws unchanged: same seed)
    "independent rig 999 without gain spread / tofjax 8 rays": ("indep rig999 nogain", 8),
    "independent rig 999 without crosstalk spread / tofjax 8 rays": ("indep rig999 noxt", 8),
    "independent rig 999 without ambient spread / tofjax 8 rays": ("indep rig999 noamb", 8),
    # every per-zone draw off: the two rigs then differ only in their sampling jitter
    "independent rig of the study without per-zone spreads / tofjax 8 rays": ("indep nospread", 8),
    "independent rig 999 without per-zone spreads / tofjax 8 rays": ("indep rig999 nospread", 8),
    "independent rig of the study without per-zone spreads, sampled 4x denser / tofjax 8 rays": ("indep nospread dense", 8),
    "independent rig 999 without per-zone spreads, sampled 4x denser / tofjax 8 rays": ("indep rig999 nospread dense", 8),
    # and without the light-entry peak (the scene's crosstalk_counts = 0 in the rig only)
    "independent rig of the study without per-zone spreads or light-entry peak, sampled 4x denser / tofjax 8 rays":
        ("indep nospread dense noxt", 8),
    # FitConfig(zone_end=True): a far-edge reflectance per zone, profiled out
    "independent as is / tofjax 8 rays, zone_end": ("indep", "zone_end"),
    "independent, another rig (seed 999) / tofjax 8 rays, zone_end": ("indep rig999", "zone_end"),
    "own / tofjax 8 rays, zone_end": ("own", "zone_end"),
    # FitConfig(quadrature=4): 4 time nodes per bin instead of 2 (the light-entry peak is narrower than a bin)
    "independent as is / tofjax 8 rays, quadrature 4": ("indep", "quadrature4"),
    "independent, another rig (seed 999) / tofjax 8 rays, quadrature 4": ("indep rig999", "quadrature4"),
}


def diagnose(out: Path, n1: float = 1.3, frames: int = 960, replicates: int = 8, variants=tuple(VARIANTS),
             config: FitConfig = FitConfig(), progress: bool = True, overwrite: bool = False) -> dict:
    """Where the bias comes from: the same replicate seeds fitted with the independent rig
    sampled as it is or 4x denser (its own discretisation: 12 jittered angles per zone every
    1 mm, 48 far-edge rays), another rig, and tofjax tracing 8 (default) or 32 rays per zone."""
    path = check_output(out / "mu_low_diagnose.json", overwrite=overwrite)
    t0 = time.perf_counter()
    nominal = _full_scene()
    truth, k = _truth(nominal, n1, MU_T)
    rigs = {"indep": IndepRig.from_scene(truth, seed=200 + k), "indep dense": IndepRig.from_scene(truth, seed=200 + k, options=DENSE),
            "indep rig999": IndepRig.from_scene(truth, seed=999),
            "indep rig999 nogain": IndepRig.from_scene(truth, seed=999, options=IndepOptions(gain_spread=0.0)),
            "indep rig999 noxt": IndepRig.from_scene(truth, seed=999, options=IndepOptions(crosstalk_spread=0.0)),
            "indep rig999 noamb": IndepRig.from_scene(truth, seed=999, options=IndepOptions(ambient_spread=0.0)),
            "indep nospread": IndepRig.from_scene(truth, seed=200 + k, options=NOSPREAD),
            "indep rig999 nospread": IndepRig.from_scene(truth, seed=999, options=NOSPREAD),
            "indep nospread dense": IndepRig.from_scene(truth, seed=200 + k, options=NOSPREAD_DENSE),
            "indep rig999 nospread dense": IndepRig.from_scene(truth, seed=999, options=NOSPREAD_DENSE),
            "indep nospread dense noxt": IndepRig.from_scene(
                truth.replace(sensor=dataclasses.replace(truth.sensor, crosstalk_counts=0.0)), seed=200 + k, options=NOSPREAD_DENSE)}
    cals = {}
    rows = {}
    for name in variants:
        data, rays = VARIANTS[name]
        if rays not in cals:
            if rays == "zone_end":
                cals[rays] = Calibrator(nominal, dataclasses.replace(config, zone_end=True))
            elif rays == "quadrature4":
                cals[rays] = Calibrator(nominal, dataclasses.replace(config, quadrature=4))
            else:
                cals[rays] = Calibrator(nominal, config) if rays == 8 else _calibrator_with_rays(nominal, config, rays)
        fits, resid = [], []
        for r in range(replicates):
            seed = 50_000 + r
            cap = simulate(truth, frames, seed=seed) if data == "own" else simulate_independent(
                rigs[data], contacts=np.zeros((0, 3)), frames=frames, seed=seed)
            t = time.perf_counter()
            res = cals[rays].fit(cap)
            se = _mu_t_stderr(res)
            f_mu = float(res.params.mu_s_per_m + res.params.mu_a_per_m)
            fits.append({"seed": seed, "result": res.result, "converged": bool(res.converged),
                         "n1_rel_error": float(res.params.n1) / n1 - 1, "mu_t_rel_error": f_mu / MU_T - 1,
                         "mu_t_stderr_rel": None if se is None else se / MU_T, "mu_s_per_m": float(res.params.mu_s_per_m),
                         "mu_a_per_m": float(res.params.mu_a_per_m), "reduced_chi2": float(res.reduced_chi2),
                         "seconds": time.perf_counter() - t})
            resid.append(np.asarray(res.residuals, np.float64))
        g = _group(fits, np.stack(resid))
        g["shared_misfit"].pop("by_bin")
        rows[name] = {"summary": g, "fits": fits}
        if progress:
            print(f"{name:55s}: bias {100 * g['mu_t_bias']:+6.1f} +- {100 * g['mu_t_bias_stderr']:4.1f}%  sd {100 * g['mu_t_rel_error_sd']:5.1f}%  "
                  f"chi2 {g['reduced_chi2_median']:.3f}  misfit {g['shared_misfit']['mean_square']:.2f}", flush=True)
        result = {
            "study": "low attenuation: where the bias comes from (simulator sampling, tofjax rays per zone, rig)",
            "data": "simulated (own: tofjax.simulate; independent: tests/indep_sim.py)",
            "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
            "load_average": list(os.getloadavg()),
            "truth": {"n1": n1, "mu_t_per_m": MU_T, "albedo": ALBEDO, "frames": frames, "replicates": replicates},
            "dense_independent_options": dataclasses.asdict(DENSE),
            "variants": rows,
            "seconds": time.perf_counter() - t0,
        }
        atomic_write_text(path, json.dumps(result, indent=2))
    return result


# ---- is the independent reference converged? ---------------------------------------------------
# The independent simulator's geometry resolution, coarse to fine: (range step, jittered angles
# per zone, far-edge rays per zone, fine time cells per bin). Each level halves the range step
# and doubles the angles and rays (the first step is 4x); "fine64" is the finest geometry with
# a 4x finer time grid.
LEVELS = {
    "default (1 mm, 12 angles, 48 edge rays)": IndepOptions(),
    "dense (0.25 mm, 48, 192)": IndepOptions(range_step_m=0.25e-3, angles_per_zone=48, end_rays=192),
    "denser (0.125 mm, 96, 384)": IndepOptions(range_step_m=0.125e-3, angles_per_zone=96, end_rays=384),
    "densest (0.0625 mm, 192, 768)": IndepOptions(range_step_m=0.0625e-3, angles_per_zone=192, end_rays=768),
    "densest, time grid 64 cells per bin": IndepOptions(range_step_m=0.0625e-3, angles_per_zone=192, end_rays=768, fine=64),
}


def _noise_free(lam: np.ndarray, scene, frames: int, source: str):
    """The expected counts as a capture of ``frames`` identical frames: a fit to it weighs the
    bins as ``frames`` frames would and returns the estimator's limit without photon noise."""
    from tofjax.capture import Capture

    return Capture(histograms=np.broadcast_to(lam, (frames, *lam.shape)), timestamps=np.arange(frames) / 9.0,
                   scene=scene, source=source)


def _fit_row(cal, cap, n1: float, mu_t: float) -> dict:
    t = time.perf_counter()
    res = cal.fit(cap)
    se = _mu_t_stderr(res)
    return {"result": res.result, "converged": bool(res.converged), "n1_rel_error": float(res.params.n1) / n1 - 1,
            "mu_t_rel_error": float(res.params.mu_s_per_m + res.params.mu_a_per_m) / mu_t - 1,
            "mu_t_stderr_rel": None if se is None else se / mu_t, "reduced_chi2": float(res.reduced_chi2),
            "end_incidence_power": float(getattr(res.params, "end_incidence_power", np.nan)),
            "near_field_m": float(res.params.near_field_m),
            "near_field_shape": float(getattr(res.params, "near_field_shape", 2.0)),
            "seconds": time.perf_counter() - t}


def convergence(out: Path, n1s=(1.3, 1.45, 1.6), frames: int = 960, geometry_seeds=(None, 1, 2), levels=tuple(LEVELS),
                reference: str = "densest (0.0625 mm, 192, 768)",
                config: FitConfig = FitConfig(), progress: bool = True, overwrite: bool = False) -> dict:
    """The independent simulator's expected counts at mu_t = 0.05 /m on the study's rigs (same
    per-zone draws) at each resolution of ``LEVELS``, each with its own jitter (``geometry_seeds``;
    None = the rig's seed stream, what the studies used). Per (n1, level, jitter): the change of
    the expected counts against the ``reference`` level (mean of its jitters; the finest geometry
    on the default time grid) and against the previous level, in units of the photon noise of
    ``frames`` frames, and the noise-free fit (the expected counts as ``frames``
    identical frames: the estimator's limit, the bias that no frame count removes)."""
    path = check_output(out / "mu_low_convergence.json", overwrite=overwrite)
    t0 = time.perf_counter()
    nominal = _full_scene()
    cal = Calibrator(nominal, config)
    rows: dict = {}
    for n1 in n1s:
        truth, k = _truth(nominal, n1, MU_T)
        lams = {}
        for name in levels:
            for g in geometry_seeds:
                t = time.perf_counter()
                rig = IndepRig.from_scene(truth, seed=200 + k, options=dataclasses.replace(LEVELS[name], geometry_seed=g))
                lams[name, g] = (rig.expected(np.zeros((0, 3))), time.perf_counter() - t)
        means = {name: np.mean([lams[name, g][0] for g in geometry_seeds], 0) for name in levels}
        ref = means[reference]
        sig = np.sqrt(np.maximum(ref, 1.0) / frames)
        rows[str(n1)] = {}
        for i, name in enumerate(levels):
            per = []
            for g in geometry_seeds:
                lam, sec = lams[name, g]
                pull = (lam - ref) / sig
                prev = (lam - means[levels[i - 1]]) / sig if i else None
                zone_mean = pull.mean(axis=(0, 1)) * np.sqrt(pull.shape[0] * pull.shape[1])
                fit = _fit_row(cal, _noise_free(lam, truth, frames, "simulated (tests/indep_sim.py), noise-free"), n1, MU_T)
                per.append({"geometry_seed": g, "simulate_seconds": sec,
                            "pull_mean_square_vs_reference": float((pull**2).mean()),
                            "pull_abs_max_vs_reference": float(np.abs(pull).max()),
                            "zone_mean_pull_abs_max": float(np.abs(zone_mean).max()),
                            "zone_mean_pull_worst_bin": int(np.argmax(np.abs(zone_mean))),
                            "pull_mean_square_vs_previous_level": None if prev is None else float((prev**2).mean()),
                            "rel_change_abs_max_vs_reference": float(np.max(np.abs(lam - ref) / np.maximum(ref, 1.0))),
                            "noise_free_fit": fit})
                if progress:
                    print(f"n1 {n1:.2f} {name:38s} jitter {g}: pull ms {per[-1]['pull_mean_square_vs_reference']:8.3f} max {per[-1]['pull_abs_max_vs_reference']:6.2f}  "
                          f"fit mu_t {100 * fit['mu_t_rel_error']:+6.1f}% n1 {100 * fit['n1_rel_error']:+.3f}% chi2 {fit['reduced_chi2']:.2f}", flush=True)
            e = np.array([q["noise_free_fit"]["mu_t_rel_error"] for q in per])
            rows[str(n1)][name] = {"jitters": per, "mu_t_bias_mean": float(e.mean()), "mu_t_bias_jitter_sd": float(e.std(ddof=1)) if len(e) > 1 else None,
                                   "pull_mean_square_mean": float(np.mean([q["pull_mean_square_vs_reference"] for q in per]))}
        result = {
            "study": "is the independent simulator's reference converged at mu_t = 0.05 /m? (resolution of its sampled geometry)",
            "data": "simulated (tests/indep_sim.py, the calibration study's rig per n1; expected counts, noise-free fits)",
            "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
            "load_average": list(os.getloadavg()),
            "truth": {"mu_t_per_m": MU_T, "albedo": ALBEDO, "frames_weighting": frames},
            "levels": {k: {q: getattr(LEVELS[k], q) for q in ("range_step_m", "angles_per_zone", "end_rays", "fine")} for k in levels},
            "geometry_seeds": list(geometry_seeds),
            "reference_level": reference,
            "note": "pull = (expected counts - the reference level's, mean over its jitters) / photon noise of frames_weighting frames "
                    "(vs_previous_level: against the previous level's mean); "
                    "noise_free_fit: the expected counts fitted as frames_weighting identical frames (the bias no frame count removes)",
            "by_n1": rows,
            "seconds": time.perf_counter() - t0,
        }
        atomic_write_text(path, json.dumps(result, indent=2))
    return result


# ---- which part of the histogram drives the offset? ----------------------------------------------
MASKS = ("none", "near range to 3 cm", "near range to 6 cm", "far edge", "near range to 3 cm and far edge")


class _SoftNearRig(IndepRig):
    """The independent rig with tofjax's near-field law 1/(r^2 + h^2) instead of its own
    1/max(r, 0.6 h)^2 (a diagnosis of one convention; the fixture itself is unchanged)."""

    def _falloff(self, r):
        return 1.0 / (r**2 + self.scene.waveguide.thickness_m**2)


def _masks(rig: IndepRig, truth) -> dict:
    """Per (sensor, zone, bin) masks (True = left out) by the time of each bin's centre: the near
    range (the light-entry peak and the light from the first 3 or 6 cm, plus 300 ps of pulse) and
    the far edge (from 200 ps before the zone's nearest edge return to the end)."""
    S, Z, B = truth.shape
    bw = truth.sensor.bin_width_s
    t = (np.arange(B) + 0.5) * bw
    t0 = rig.emission_time_s
    near = {d: np.broadcast_to(t <= t0 + 2 * d / rig.c1 + 300e-12, (S, Z, B)) for d in (0.03, 0.06)}
    lmin = np.array([rig._edge[i][1].min() for i in range(S * Z)]).reshape(S, Z)
    far = t[None, None, :] >= t0 + 2 * lmin[..., None] / rig.c1 - 200e-12
    return {"none": np.zeros((S, Z, B), bool), "near range to 3 cm": near[0.03], "near range to 6 cm": near[0.06],
            "far edge": far, "near range to 3 cm and far edge": near[0.03] | far}


def _fit_masked(cal, cap, mask, n1, mu_t) -> dict:
    """A fit with the masked bins' standard deviations x 1e6 (they then weigh nothing)."""
    import jax.numpy as jnp

    import importlib

    C = importlib.import_module("tofjax.fit.calibrate")  # the module (tofjax.fit.calibrate is also the function)
    orig = C._data

    def masked(capture, dtype, model_error=0.0):
        mean, sig = orig(capture, dtype, model_error)
        return mean, jnp.where(jnp.asarray(mask), sig * 1e6, sig)

    C._data = masked
    try:
        row = _fit_row(cal, cap, n1, mu_t)
    finally:
        C._data = orig
    row["bins_masked"] = int(mask.sum())
    return row


def diagnose_masks(out: Path, level: str, n1s=(1.3, 1.45, 1.6), frames: int = 960, masks=MASKS,
                   config: FitConfig = FitConfig(), progress: bool = True, overwrite: bool = False) -> dict:
    """Noise-free fits (expected counts as ``frames`` frames) of own data, the independent rig at
    resolution ``level`` and the same with tofjax's near-field law, with parts of the histogram
    left out (``MASKS``): which part carries the offset of mu_t that no frame count removes."""
    from tofjax.simulate import expected_counts

    path = check_output(out / "mu_low_masks.json", overwrite=overwrite)
    t0 = time.perf_counter()
    nominal = _full_scene()
    cal = Calibrator(nominal, config)
    rows: dict = {}
    for n1 in n1s:
        truth, k = _truth(nominal, n1, MU_T)
        rig = IndepRig.from_scene(truth, seed=200 + k, options=LEVELS[level])
        soft = _SoftNearRig.from_scene(truth, seed=200 + k, options=LEVELS[level])
        mk = _masks(rig, truth)
        data = {"own": np.asarray(expected_counts(truth)), "independent": rig.expected(np.zeros((0, 3))),
                "independent with tofjax's near-field law": soft.expected(np.zeros((0, 3)))}
        rows[str(n1)] = {}
        for dname, lam in data.items():
            cap = _noise_free(lam, truth, frames, f"simulated ({dname}), noise-free")
            rows[str(n1)][dname] = {}
            for m in masks:
                r = _fit_masked(cal, cap, mk[m], n1, MU_T)
                rows[str(n1)][dname][m] = r
                if progress:
                    print(f"n1 {n1:.2f} {dname:42s} mask {m:32s}: mu_t {100 * r['mu_t_rel_error']:+6.1f}% "
                          f"(stderr {100 * (r['mu_t_stderr_rel'] or np.nan):.1f}%) n1 {100 * r['n1_rel_error']:+.3f}% chi2 {r['reduced_chi2']:.2f}", flush=True)
            result = {
                "study": "low attenuation: which part of the histogram carries the offset of mu_t (noise-free fits with bins left out)",
                "data": "simulated (own: tofjax expected counts; independent: tests/indep_sim.py at the converged resolution; noise-free)",
                "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
                "load_average": list(os.getloadavg()),
                "truth": {"mu_t_per_m": MU_T, "albedo": ALBEDO, "frames_weighting": frames},
                "independent_level": level,
                "independent_options": dataclasses.asdict(LEVELS[level]),
                "masks": {"near range to 3 cm": "bins whose centre is before emission + 2 (3 cm) / c1 + 300 ps",
                          "near range to 6 cm": "the same to 6 cm", "far edge": "bins from 200 ps before the zone's nearest edge return on"},
                "note": "mu_t_stderr_rel: the Laplace standard error at frames_weighting frames (the masked fit's)",
                "by_n1": rows,
                "seconds": time.perf_counter() - t0,
            }
            atomic_write_text(path, json.dumps(result, indent=2))
    return result


OFFSET_VARIANTS = (
    "independent",
    "independent, tofjax 32 rays per zone",
    "independent, FitConfig.model_error 0.01",
    "independent with tofjax's near-field law",
    "independent with tofjax's near-field law, tofjax 32 rays per zone",
    "independent with tofjax's near-field law, scene without multiple scattering",
    "independent with tofjax's near-field law, no per-zone spreads",
    "independent with tofjax's near-field law, tofjax quadrature 4",
    "independent, tofjax quadrature 4",
    # tofjax's own simulator with 8 time nodes per bin (its discretisation converged), fitted
    # with the default 2 and with 4: the offset of the default's time discretisation alone
    "own at quadrature 8",
    "own at quadrature 8, tofjax quadrature 4",
)


def diagnose_offset(out: Path, level: str, n1s=(1.3, 1.45, 1.6), frames: int = 960, variants=OFFSET_VARIANTS,
                    config: FitConfig = FitConfig(), progress: bool = True, overwrite: bool = False) -> dict:
    """Noise-free fits (the expected counts as ``frames`` frames) of the independent rig at
    resolution ``level`` with one thing changed at a time: the rig's near-field law set to
    tofjax's, tofjax tracing 32 rays per zone (default 8) or 4 time nodes per bin, the nominal
    scene stating no multiple scattering, the rig's per-zone spreads off, a model-error floor."""
    path = check_output(out / "mu_low_offset.json", overwrite=overwrite)
    t0 = time.perf_counter()
    nominal = _full_scene()
    no_ms = nominal.replace(waveguide=dataclasses.replace(nominal.waveguide, multiple_scattering=0.0))
    cals = {}

    def cal_for(v):
        key = ("rays32" if "32 rays" in v else "no_ms" if "multiple scattering" in v else "me01" if "model_error" in v
               else "q4" if "quadrature 4" in v else "base")
        if key not in cals:
            cals[key] = {"rays32": lambda: _calibrator_with_rays(nominal, config, 32),
                         "no_ms": lambda: Calibrator(no_ms, config),
                         "me01": lambda: Calibrator(nominal, dataclasses.replace(config, model_error=0.01)),
                         "q4": lambda: Calibrator(nominal, dataclasses.replace(config, quadrature=4)),
                         "base": lambda: Calibrator(nominal, config)}[key]()
        return cals[key]

    rows: dict = {}
    for n1 in n1s:
        truth, k = _truth(nominal, n1, MU_T)
        opts = LEVELS[level]
        nospread = dataclasses.replace(opts, gain_spread=0.0, crosstalk_spread=0.0, ambient_spread=0.0)
        from tofjax.model import ModelOptions
        from tofjax.simulate import expected_counts

        lam = {"own q8": np.asarray(expected_counts(truth, ModelOptions(quadrature=8))) if any(v.startswith("own") for v in variants) else None,
               "max": IndepRig.from_scene(truth, seed=200 + k, options=opts).expected(np.zeros((0, 3))),
               "soft": _SoftNearRig.from_scene(truth, seed=200 + k, options=opts).expected(np.zeros((0, 3))),
               "soft nospread": _SoftNearRig.from_scene(truth, seed=200 + k, options=nospread).expected(np.zeros((0, 3)))}
        rows[str(n1)] = {}
        for v in variants:
            which = "own q8" if v.startswith("own") else ("soft nospread" if "per-zone" in v else "soft") if "near-field law" in v else "max"
            cap = _noise_free(lam[which], truth, frames, "simulated (tests/indep_sim.py), noise-free")
            r = _fit_row(cal_for(v), cap, n1, MU_T)
            rows[str(n1)][v] = r
            if progress:
                print(f"n1 {n1:.2f} {v:75s}: mu_t {100 * r['mu_t_rel_error']:+6.1f}% n1 {100 * r['n1_rel_error']:+.3f}% chi2 {r['reduced_chi2']:.3f}", flush=True)
            result = {
                "study": "low attenuation: the offset of mu_t that no frame count removes, one convention changed at a time (noise-free fits)",
                "data": "simulated (tests/indep_sim.py at the converged resolution, expected counts; noise-free)",
                "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
                "load_average": list(os.getloadavg()),
                "truth": {"mu_t_per_m": MU_T, "albedo": ALBEDO, "frames_weighting": frames},
                "independent_level": level,
                "near_field_laws": {"independent": "1 / max(r, 0.6 h)^2", "tofjax": "1 / (r^2 + d^2), d fitted (near_field_m)"},
                "note": "reduced_chi2 of a noise-free fit: the misfit alone (at frames_weighting frames a noisy fit adds ~1)",
                "by_n1": rows,
                "seconds": time.perf_counter() - t0,
            }
            atomic_write_text(path, json.dumps(result, indent=2))
    return result


def quadrature_profile(out: Path, n1: float = 1.45, mu_ts=(0.05, 2.0), frames: int = 960, overwrite: bool = False) -> dict:
    """Where tofjax's default quadrature (2 time nodes per bin) differs from its converged self
    (8 nodes; 16 as the check of 8): the zone-mean relative difference and pull (photon noise of
    ``frames`` frames) per bin, on the study's scene at each true mu_t."""
    from tofjax.model import ModelOptions, speed_in_guide
    from tofjax.simulate import expected_counts

    path = check_output(out / "mu_low_quadrature_profile.json", overwrite=overwrite)
    nominal = _full_scene()
    rows = {}
    for mu_t in mu_ts:
        truth, _ = _truth(nominal, n1, mu_t)
        lam = {q: np.asarray(expected_counts(truth, ModelOptions(quadrature=q))) for q in (2, 8, 16)}
        ref = lam[8]
        rel = (lam[2] - ref) / np.maximum(ref, 1.0)
        pull = (lam[2] - ref) / np.sqrt(np.maximum(ref, 1.0) / frames)
        c1 = speed_in_guide(n1)
        rows[str(mu_t)] = {
            "range_per_bin_m": c1 * truth.sensor.bin_width_s / 2,
            "q2_vs_q8_zone_mean_rel_by_bin": rel.mean((0, 1)).round(5).tolist(),
            "q2_vs_q8_zone_mean_pull_by_bin": pull.mean((0, 1)).round(2).tolist(),
            "q8_vs_q16_rel_abs_max": float(np.max(np.abs(lam[8] - lam[16]) / np.maximum(lam[16], 1.0))),
            "round_trip_decay_per_bin": float(1 - np.exp(-2 * mu_t * c1 * truth.sensor.bin_width_s / 2)),
        }
        print(f"mu_t {mu_t}: q2 - q8 zone-mean rel by bin 10-30 (%): {np.round(100 * rel.mean((0, 1))[10:30], 2).tolist()}")
    result = {
        "study": "tofjax's default quadrature (2 nodes per bin) against 8 nodes, per bin",
        "data": "simulated (tofjax expected counts, noise-free)",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
        "load_average": list(os.getloadavg()),
        "truth": {"n1": n1, "albedo": ALBEDO, "frames_for_pull": frames},
        "by_mu_t": rows,
    }
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def merge_diagnose(parts: list[Path], out: Path, overwrite: bool = False) -> dict:
    """The variants of several ``--diagnose`` runs in one JSON (their load averages kept)."""
    path = check_output(out / "mu_low_diagnose.json", overwrite=overwrite)
    loaded = [json.loads(Path(q).read_text()) for q in parts]
    result = {k: loaded[0][k] for k in ("study", "data", "machine", "truth", "dense_independent_options")}
    result["load_average"] = [d["load_average"] for d in loaded]
    result["parts"] = [str(q) for q in parts]
    result["seconds"] = sum(d["seconds"] for d in loaded)
    result["variants"] = {}
    for d in loaded:
        result["variants"].update(d["variants"])
    result["bias_by_variant"] = {k: [v["summary"]["mu_t_bias"], v["summary"]["mu_t_bias_stderr"]] for k, v in result["variants"].items()}
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def merge_replicates(parts: list[Path], out: Path, overwrite: bool = False) -> dict:
    """One result from parts that fitted the same points with other seeds (``--first-replicate``):
    the fits of each (column, n1, frames) concatenated (a seed fitted twice is refused) and every
    figure recomputed from them. The shared-misfit maps need the residuals, which the JSON does not
    keep: each part's is kept as it was (``shared_misfit_by_part``)."""
    path = check_output(out / "mu_low.json", overwrite=overwrite)
    loaded = [json.loads(Path(q).read_text()) for q in parts]
    fits: dict = {}
    misfit: dict = {}
    for d in loaded:
        for col, by_n1 in d["fits"].items():
            for n1, by_fr in by_n1.items():
                for fr, rows in by_fr.items():
                    fits.setdefault(col, {}).setdefault(n1, {}).setdefault(fr, []).extend(rows)
                    m = d["groups"][col][n1][fr].get("shared_misfit")
                    misfit.setdefault(col, {}).setdefault(n1, {}).setdefault(fr, []).append(
                        None if m is None else {k: m[k] for k in ("mean_square", "by_bin_mean_square", "by_bin_abs_max")})
    groups: dict = {}
    for col, by_n1 in fits.items():
        for n1, by_fr in by_n1.items():
            # one seed per capture at a point, across frame counts too (a seed drawn at two frame
            # counts shares its first frames' noise)
            seeds = [r["seed"] for rows in by_fr.values() for r in rows]
            if len(set(seeds)) != len(seeds):
                raise ValueError(f"{col} n1={n1}: a seed fitted twice (parts with the same --first-replicate?)")
            for fr, rows in by_fr.items():
                g = _group(rows, None)
                g["shared_misfit_by_part"] = misfit[col][n1][fr]
                groups.setdefault(col, {}).setdefault(n1, {})[fr] = g
    c0 = loaded[0]["config"]
    n1s = tuple(sorted({float(n1) for by_n1 in groups.values() for n1 in by_n1}))
    frames = tuple(sorted({int(fr) for by_n1 in groups.values() for by_fr in by_n1.values() for fr in by_fr}))
    cols = tuple(c for c in COLUMNS if c in groups)
    n_rep = min(len(rows) for by_n1 in fits.values() for by_fr in by_n1.values() for rows in by_fr.values())
    cfg = MuLowConfig(n1=n1s, mu_t=c0["mu_t"], frames=frames, replicates=n_rep, columns=cols,
                      sensors=c0["sensors"], zones=c0["zones"], bins=c0["bins"])
    result = {k: loaded[0][k] for k in ("study", "data", "machine", "target")}
    result.update({
        "load_average": [d["load_average"] for d in loaded],
        # a part writes its JSON after each finished group: a part stopped early holds whole groups
        "finished": True,
        "parts_finished": [d["finished"] for d in loaded],
        "seconds": sum(d["seconds"] for d in loaded),
        "parts": [str(q) for q in parts],
        "config": dataclasses.asdict(cfg) | {"base": c0["base"], "albedo": c0["albedo"],
                                            "replicates_by_part": [d["config"]["replicates"] for d in loaded]},
        "fit_config": loaded[0]["fit_config"],
        "pooled": _pooled(groups, cfg),
        "groups": groups,
        "scaling": _scaling(groups, cfg),
        "planner": planner_check(fits, cfg.mu_t),
        "fits": fits,
    })
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def merge(parts: list[Path], out: Path, overwrite: bool = False) -> dict:
    """One result from the JSONs of parts run separately (``--columns``, ``--n1``): groups and
    fits joined (a later part wins), pooled figures and the frame scaling recomputed."""
    path = check_output(out / "mu_low.json", overwrite=overwrite)
    loaded = [json.loads(Path(q).read_text()) for q in parts]
    groups: dict = {}
    fits: dict = {}
    for d in loaded:
        for col, by_n1 in d["groups"].items():
            for n1, by_fr in by_n1.items():
                groups.setdefault(col, {}).setdefault(n1, {}).update(by_fr)
                fits.setdefault(col, {}).setdefault(n1, {}).update(d["fits"][col][n1])
    c0 = loaded[0]["config"]
    n1s = sorted({float(n1) for by_n1 in groups.values() for n1 in by_n1})
    frames = sorted({int(fr) for by_n1 in groups.values() for by_fr in by_n1.values() for fr in by_fr})
    cols = tuple(c for c in COLUMNS if c in groups)
    cfg = MuLowConfig(n1=tuple(n1s), mu_t=c0["mu_t"], frames=tuple(frames), replicates=c0["replicates"], columns=cols,
                      sensors=c0["sensors"], zones=c0["zones"], bins=c0["bins"])
    # every column at every n1 (a column may have run fewer frame counts)
    complete = all(groups[c].get(str(n1)) for c in cols for n1 in n1s)
    result = {k: loaded[0][k] for k in ("study", "data", "machine", "target")}
    result.update({
        "load_average": [d["load_average"] for d in loaded],
        "finished": all(d["finished"] for d in loaded) and complete,
        "seconds": sum(d["seconds"] for d in loaded),
        "parts": [str(q) for q in parts],
        "config": dataclasses.asdict(cfg) | {"base": c0["base"], "albedo": c0["albedo"]},
        "fit_config": loaded[0]["fit_config"],
        "pooled": _pooled(groups, cfg),
        "groups": groups,
        "scaling": _scaling(groups, cfg) if complete else None,
        "planner": planner_check(fits, cfg.mu_t),
        "fits": fits,
    })
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/mu_low")
    ap.add_argument("--replicates", type=int, default=MuLowConfig.replicates)
    ap.add_argument("--first-replicate", type=int, default=0,
                    help="replicate index of the first seed (a second part with new seeds; join with --merge-replicates)")
    ap.add_argument("--merge-replicates", nargs="+", type=Path,
                    help="join these parts' mu_low.json (same points, other seeds) into --out: fits concatenated, figures recomputed")
    ap.add_argument("--frames", type=int, nargs="+", default=list(MuLowConfig.frames))
    ap.add_argument("--n1", type=float, nargs="+", default=list(MuLowConfig.n1))
    ap.add_argument("--columns", default="own,independent", help=f"comma-separated subset of {', '.join(COLUMNS)}")
    ap.add_argument("--quick", action="store_true", help="a tiny scene, 2 replicates (what the test runs)")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--model-error", type=float, default=FitConfig().model_error, help="FitConfig.model_error (the study's fits)")
    ap.add_argument("--quadrature", type=int, default=FitConfig().quadrature, help="FitConfig.quadrature (the study's fits)")
    ap.add_argument("--merge", nargs="+", type=Path, help="merge these parts' mu_low.json into --out instead of fitting")
    ap.add_argument("--diagnose", action="store_true",
                    help="the bias's cause at the first --n1 and the last --frames (writes mu_low_diagnose.json)")
    ap.add_argument("--convergence", action="store_true",
                    help="the independent simulator's resolution levels, noise-free fits (writes mu_low_convergence.json)")
    ap.add_argument("--masks", metavar="LEVEL", help=f"noise-free fits with bins left out, the independent rig at LEVEL (one of {'; '.join(LEVELS)})")
    ap.add_argument("--offset", metavar="LEVEL", help="noise-free fits of the independent rig at LEVEL, one convention changed at a time")
    ap.add_argument("--quadrature-profile", action="store_true", help="tofjax's quadrature 2 against 8 per bin (mu_low_quadrature_profile.json)")
    ap.add_argument("--variants", help=f"with --diagnose: a ';'-separated subset of {'; '.join(VARIANTS)}")
    args = ap.parse_args(argv)
    from tofjax.compile_cache import enable_compilation_cache

    enable_compilation_cache()  # parts run as separate processes: compile once per machine
    if args.convergence:
        tofjax.enable_x64()
        convergence(Path(args.out), n1s=tuple(args.n1), frames=args.frames[-1], overwrite=args.overwrite)
        print(f"wrote {args.out}/mu_low_convergence.json")
        return
    if args.masks:
        if args.masks not in LEVELS:
            raise SystemExit(f"--masks: unknown level {args.masks!r}")
        tofjax.enable_x64()
        diagnose_masks(Path(args.out), args.masks, n1s=tuple(args.n1), frames=args.frames[-1], overwrite=args.overwrite)
        print(f"wrote {args.out}/mu_low_masks.json")
        return
    if args.quadrature_profile:
        tofjax.enable_x64()
        quadrature_profile(Path(args.out), overwrite=args.overwrite)
        print(f"wrote {args.out}/mu_low_quadrature_profile.json")
        return
    if args.offset:
        tofjax.enable_x64()
        v = tuple(x for x in args.variants.split(";") if x) if args.variants else OFFSET_VARIANTS
        bad = [x for x in v if x not in OFFSET_VARIANTS]
        if bad:
            raise SystemExit(f"--variants: unknown variant {bad[0]!r}")
        diagnose_offset(Path(args.out), args.offset, n1s=tuple(args.n1), frames=args.frames[-1], variants=v, overwrite=args.overwrite)
        print(f"wrote {args.out}/mu_low_offset.json")
        return
    if args.diagnose and not args.merge:
        tofjax.enable_x64()
        v = tuple(x for x in args.variants.split(";") if x) if args.variants else tuple(VARIANTS)
        bad = [x for x in v if x not in VARIANTS]
        if bad:
            raise SystemExit(f"--variants: unknown variant {bad[0]!r}")
        diagnose(Path(args.out), n1=args.n1[0], frames=args.frames[-1], replicates=min(args.replicates, 8), variants=v,
                 overwrite=args.overwrite)
        print(f"wrote {args.out}/mu_low_diagnose.json")
        return
    if args.merge_replicates:
        r = merge_replicates(args.merge_replicates, Path(args.out), overwrite=args.overwrite)
        print(json.dumps(r["pooled"], indent=1))
        print(f"wrote {args.out}/mu_low.json")
        return
    if args.merge and args.diagnose:
        r = merge_diagnose(args.merge, Path(args.out), overwrite=args.overwrite)
        print(json.dumps(r["bias_by_variant"], indent=1))
        return
    if args.merge:
        r = merge(args.merge, Path(args.out), overwrite=args.overwrite)
        print(json.dumps(r["pooled"], indent=1))
        print(f"wrote {args.out}/mu_low.json")
        return
    try:
        cfg = QUICK if args.quick else MuLowConfig(
            n1=tuple(args.n1), frames=tuple(args.frames), replicates=args.replicates, first_replicate=args.first_replicate,
            columns=tuple(c for c in args.columns.split(",") if c))
    except ValueError as e:
        raise SystemExit(str(e)) from None
    tofjax.enable_x64()
    r = run(Path(args.out), cfg, FitConfig(model_error=args.model_error, quadrature=args.quadrature), overwrite=args.overwrite)
    print(json.dumps(r["pooled"], indent=1))
    print(json.dumps({k: {q: v[q] for q in ("sd", "sd_power_law_exponent", "frames_for_2sd_within_25pct_sqrt_law") if q in v}
                      for k, v in (r["scaling"] or {}).items()}, indent=1))
    print(f"wrote {args.out}/mu_low.json")


if __name__ == "__main__":
    main()
