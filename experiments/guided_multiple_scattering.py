"""Does the Monte Carlo support the guided optics' multiple-scattering term? (issue 14: reduced chi-square <= 2 at 64x)

The guided optics keep the default optics' phenomenological multiple scattering (``guided._distributed``: density
``multiple_scattering / (4 pi) mu_s (1 - exp(-2 mu_s r)) exp(-mu_a r ...)``, coupling ``multiple_scattering`` from the
scene, 0.5 on OptoSkin, not fitted). Against the volume's single scattering that is about ``multiple_scattering x
mu_s r`` more light: 15% just before the far edge on OptoSkin. A geometric estimate says a guided beam's twice-scattered
light is far less: the once-scattered light spreads over the whole plane (``2 pi``) while the zone sees only its fan
(``dphi``), so the second scattering sees ``cg fov / (2 pi) mu_s r`` of the beam's irradiance, about 1.5% of single
scattering at 30 cm, and the light it sends to the walls is already the reverberant field's (``guided._reverb``).

Two parts, both on **simulated** data (the Monte Carlo baseline of ``experiments/eval_mc_data.py``: its 64 cached runs
of 25,000 packets per sensor):

* **at the scene's optics** (seconds): the Monte Carlo's transported light against the guided model's with the
  coupling at the scene's value and at 0: the relative L2 (one scale per sensor, as ``tofjax bench tradeoff``) and
  the Monte Carlo over the model by time bin before the far edge (each sensor's zones' mean), and, per zone, the
  least-squares amplitudes of the far edge, the volume and the multiple scattering (the last two over the first);
* **the calibrations** (``--calibrate``; 1-3 minutes each on the 2-core VM, each in a process of its own): 10 frames
  at 16x and 64x exposure (seed 0, as the eval's), with the coupling at the scene's value (the default), held at 0,
  and fitted (``free`` plus ``multiple_scattering``); each with the score tests of the parameters it holds
  (``discrepancy["fixed_parameters"]``, :mod:`tofjax.fit._scores`).

    python experiments/guided_multiple_scattering.py --calibrate --out docs/results/guided_multiple_scattering.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

import numpy as np

#: the bins (100 ps on OptoSkin) of the Monte Carlo over the model before the far edge
RATIO_BINS = tuple(range(17, 44, 3))
VARIANTS = ("scene", "zero", "free")


def at_scene_optics() -> dict:
    """The Monte Carlo's transported light against the guided model's, with the coupling at the scene's value and 0."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    from tofjax.mc.bench import profiled_relative_l2

    scene = ev.guided_scene()
    mc, parts = ev.mc_baseline_against_guided(scene)  # the mean of 8 runs, as the tradeoff bench's
    end, vol, ms = parts["end"], parts["volume"], parts.get("multiple_scattering", 0.0 * parts["end"])
    out = {"coupling_in_scene": float(scene.waveguide.multiple_scattering), "ratio_bins": list(RATIO_BINS)}
    for key, model in (("with_coupling", end + vol + ms), ("coupling_0", end + vol)):
        l2, _ = profiled_relative_l2(mc, model)
        ratio = (mc / np.where(model > 0, model, np.nan)).mean(axis=1)  # (S, B): the zones' mean
        out[key] = {"relative_l2": l2,
                    "mc_over_model_by_bin": [[round(float(ratio[s, b]), 4) for b in RATIO_BINS] for s in range(ratio.shape[0])]}
    out["multiple_scattering_share_of_model_by_bin_sensor0_zone3"] = [
        round(float(ms[0, 3, b] / (end + vol + ms)[0, 3, b]), 4) for b in RATIO_BINS]
    # per zone: least-squares amplitudes of (end, volume, multiple scattering), weighted by the 64x photon noise
    var = np.maximum(mc * 64.0, 1.0)
    coef = np.zeros(mc.shape[:2] + (3,))
    for s in range(mc.shape[0]):
        for z in range(mc.shape[1]):
            w = np.sqrt(64.0**2 / var[s, z])
            a = np.stack([end[s, z], vol[s, z], ms[s, z]], -1)
            c = np.linalg.lstsq(a * w[:, None], mc[s, z] * w, rcond=None)[0]
            coef[s, z] = c / c[0]
    out["per_zone_amplitudes_over_far_edge"] = {
        "volume": {"median": float(np.median(coef[..., 1])), "range": [float(coef[..., 1].min()), float(coef[..., 1].max())]},
        "multiple_scattering": {"median": float(np.median(coef[..., 2])),
                                "range": [float(coef[..., 2].min()), float(coef[..., 2].max())],
                                "negative_zones": int(np.sum(coef[..., 2] < 0)), "zones": int(coef[..., 2].size)}}
    return out


def calibrate_one(variant: str, exposure: float) -> dict:
    """The eval's Monte Carlo calibration at ``exposure`` with the coupling per ``variant`` (in this process)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    from tofjax.fit.calibrate import DEFAULT_FREE, NOT_GUIDED

    scene, expected, mc_var = ev.calibration_baseline(exposure=exposure)
    frames = 10
    cap = ev._capture(scene, expected, frames, 0, "simulated (monte_carlo)")
    fit_scene, options = scene, {}
    if variant == "zero":
        fit_scene = dataclasses.replace(scene, waveguide=dataclasses.replace(scene.waveguide, multiple_scattering=0.0))
        cap = dataclasses.replace(cap, scene=fit_scene)
    elif variant == "free":
        options["free"] = tuple(k for k in DEFAULT_FREE if k not in NOT_GUIDED) + ("multiple_scattering",)
    # the eval's figures of a calibration (errors against fit_scene's optics: only the coupling differs from scene's)
    fig, res = ev.calibrate_capture(fit_scene, cap, mc_var, "guided", **options)
    p = res.params
    keep = ("result", "converged", "steps", "seconds", "reduced_chi2_photon_noise", "n1_rel_error", "mu_t_rel_error")
    out = {"variant": variant, "exposure": exposure, "frames": frames, **{k: fig[k] for k in keep},
           "mu_s_per_m": float(p.mu_s_per_m), "mu_a_per_m": float(p.mu_a_per_m),
           "multiple_scattering": float(p.multiple_scattering)}
    out.update({k: v for k, v in fig.items() if k.startswith(("reduced_chi2_with", "mc_variance"))})
    out["stderr"] = {k: float(np.ravel(res.stderr[k])[0]) for k in ("n1", "mu_s_per_m", "mu_a_per_m", "multiple_scattering")
                     if k in res.stderr}
    # the held parameters' score tests (FitConfig.fixed_score_chi2: on a fit above reduced chi-square 1.5)
    out["fixed_parameters"] = res.discrepancy.get("fixed_parameters")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--calibrate", action="store_true", help="also the 16x and 64x calibrations per variant")
    ap.add_argument("--exposures", default="16,64", help="exposures of --calibrate (comma-separated)")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--calibrate-one", metavar="VARIANT:EXPOSURE", help=argparse.SUPPRESS)  # JSON to stdout
    args = ap.parse_args(argv)
    out_path = Path(args.out)
    if not args.calibrate_one and out_path.exists() and not args.overwrite and str(out_path) != os.devnull:
        print(f"error: {out_path} exists (--overwrite to replace it)", file=sys.stderr)
        return 2
    try:
        exposures = [float(e) for e in args.exposures.split(",")]
    except ValueError:
        print(f"error: --exposures: expected numbers separated by commas, got {args.exposures!r}", file=sys.stderr)
        return 2
    if not exposures or any(not (e > 0 and e < float("inf")) for e in exposures):
        print(f"error: --exposures: every exposure must be positive and finite, got {args.exposures!r}", file=sys.stderr)
        return 2
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    import jax

    jax.config.update("jax_enable_x64", True)
    if args.calibrate_one:
        variant, _, exposure = args.calibrate_one.partition(":")
        if variant not in VARIANTS:
            print(f"error: --calibrate-one: variant must be one of {', '.join(VARIANTS)}, got {variant!r}", file=sys.stderr)
            return 2
        print(json.dumps(calibrate_one(variant, float(exposure))))
        return 0
    out = ev.study_header("the guided optics' multiple-scattering coupling against the Monte Carlo baseline",
                          "simulated (tofjax's Monte Carlo; 64 runs of 25,000 packets per sensor)")
    out["at_scene_optics"] = at_scene_optics()
    print(json.dumps({k: out["at_scene_optics"][k]["relative_l2"] for k in ("with_coupling", "coupling_0")}), flush=True)
    if args.calibrate:
        out["calibrations"] = {}
        for exposure in exposures:
            for variant in VARIANTS:
                key = f"{variant}_{exposure:g}x"
                out["calibrations"][key] = ev.run_in_own_process(__file__, ["--out", os.devnull, "--calibrate-one",
                                                                            f"{variant}:{exposure:g}"])
                print(key, json.dumps(out["calibrations"][key]), flush=True)
    ev.write_study(out, out_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
