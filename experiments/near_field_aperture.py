"""Switches of the guided optics against the Monte Carlo (issue 14): the near field from the aperture's geometry
(default), the light exchanged around the lit walls (``--study edge_scatter``), the reverberant field's exchange
between wall segments (``--study reverb_strings``), multiple scattering's derived coupling (``--study ms_derived``),
the lit walls' light scattered on to the walls in view (``--study scatter_redirect``), or the beam's scattered light
on the walls by the geometry (``--study scatter_share``), the edge-scatter kernels timed from each ray's own return
(``--study own_return``), the second bounce from one source per zone and wall (``--study edge_groups``), or the
reverberant field on finer wall segments (``--study reverb_segments``).

A zone of the TMF8828 is a condition on the angle of arrival, and the Monte Carlo scores each event's light at the
aperture (1 mm along the edge) piece by piece, each piece in the zone its own arrival angle falls in. Near the
sensor the arrival angles of one point spread over ``a cos(psi) / r``: its light is shared among neighbouring zones,
and at the fan's two ends some falls outside it. ``tofjax.model.guided.NEAR_FIELD_APERTURE`` (the default) models
that from the geometry (``EDGE_APERTURE`` does the same for the far edge's first return); without it the guided
model's near field is ``1/sqrt(r^2 + r0^2)`` with ``r0 = 0.3`` thickness, fitted to the Monte Carlo once and the same
in every zone. This study holds both against the Monte Carlo baseline of ``experiments/eval_mc_data.py`` (its 64
cached runs of 25,000 packets per sensor):

1. **The light itself** at the scene's optics, transported light only (the analytic light-entry peak and ambient,
   which the Monte Carlo capture adds, taken off): per sensor the outer zones' light in the first four bins after the
   emission over the middle zone's; relative L2 (one scale per sensor, as ``tofjax bench tradeoff``) over the whole
   histogram and over the near window (the emission's bin to six after); the forward time with and without, timed
   alternately in one process (medians).
2. **The calibration** of the same capture at each of ``--exposures`` (64x by default; 10 frames, seed 0, as
   ``guided_fidelity_calibration.py``), with the
   switches off and on, and with the held multiple-scattering coupling at the scene's 0.5, at 0.1 and at 0: reduced
   chi-square (photon noise; with the Monte Carlo's own variance), the errors of n1 and mu_s + mu_a, the steps, and
   the excess chi-square by time window. Each calibration runs in a process of its own.

``--study edge_scatter`` compares ``tofjax.model.guided.EDGE_SCATTER`` off and on the same way instead: the light
the walls and the volume exchange around each zone's lit wall (the beam's light scattered on to the lit walls, and
the lit walls' light scattered back by the volume), which the reverberant field's even spread of the scattered light
left out. The relative L2 of part 1 is also given per time window (:data:`WINDOWS`).

``--study reverb_strings`` compares ``tofjax.model.guided.REVERB_STRINGS`` off and on: the reverberant field's
exchange between two wall segments from their centres (``cos cos len / (2 r)``, which sends out up to 5% more light
than a wall reflects) or by Hottel's crossed strings (exact for straight segments, each segment's light shared out
in full).

``--study ms_derived`` compares ``tofjax.model.guided.MS_DERIVED`` off (the coupling held at the scene's 0.5, and
at 0.1) and on (derived from the geometry: the scene's default is the derived value). Part 1 adds the volume's light
alone: the Monte Carlo with absorbing edges (32 cached runs) against the model's volume backscatter and multiple
scattering (:func:`absorbing_edges`).

``--study scatter_redirect`` compares ``tofjax.model.guided.SCATTER_REDIRECT`` off (the default) and on: a third
kernel of :func:`tofjax.model.guided._edge_scatter`, the lit walls' diffuse light scattered once by the volume on to
the walls in view (two bounces and one scattering), at the scene's held coupling only. ``--study scatter_share``
the same for ``REVERB_SCATTER_SHARE`` (the beam's scattered light on the walls where the geometry sends it, against
evenly), and ``--study share_and_redirect`` both switches off and on together. ``--study own_return`` the same for
``SCATTER_OWN_RETURN`` (each kernel entry timed from its own ray's return, against the zone's mean first return), and
``--study edge_groups`` for ``EDGE_SECOND_GROUPS`` (the far edge's second bounce from one source per zone and wall
the zone sees, against each zone's middle ray). ``--study reverb_segments`` compares the reverberant field on 4 and
on 6 segments per wall (``REVERB_SEGMENTS_PER_WALL``).

All data **simulated** (tofjax's Monte Carlo). About 3 minutes per exposure on the 2-core VM.

    python experiments/near_field_aperture.py --exposures 16,64 --out docs/results/near_field_aperture.json
    python experiments/near_field_aperture.py --study edge_scatter --exposures 16,64 --out docs/results/edge_scatter.json
    python experiments/near_field_aperture.py --study reverb_strings --exposures 16,64 --out docs/results/reverb_strings.json
    python experiments/near_field_aperture.py --study ms_derived --exposures 16,64 --out docs/results/ms_derived.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: time windows (bins, 100 ps each on OptoSkin) of the excess chi-square, as guided_fidelity_calibration.py
WINDOWS = {"before_light_entry": (0, 13), "light_entry": (13, 20), "volume": (20, 46), "far_edge": (46, 62),
           "after": (62, None)}
COUPLINGS = (0.5, 0.1, 0.0)
#: the studies this script runs (``--study``): the guided model's switches each turns on together, its two variants
#: (off, on) and the ratio's name in the JSON
STUDIES = {
    "aperture": {"switches": ("NEAR_FIELD_APERTURE", "EDGE_APERTURE"), "ratio": "forward_ratio_aperture_over_thickness",
                 "variants": {"thickness_near_field": False, "aperture_near_field": True},
                 "title": "the guided optics' near field from the aperture against the Monte Carlo baseline"},
    "edge_scatter": {"switches": ("EDGE_SCATTER",), "ratio": "forward_ratio_with_over_without",
                     "variants": {"without_edge_scatter": False, "with_edge_scatter": True},
                     "title": "the light the walls and the volume exchange around a zone's lit wall (guided "
                              "EDGE_SCATTER) against the Monte Carlo baseline"},
    "reverb_strings": {"switches": ("REVERB_STRINGS",), "ratio": "forward_ratio_with_over_without",
                       "variants": {"centre_point_exchange": False, "crossed_strings": True},
                       "title": "the reverberant field's exchange between wall segments by Hottel's crossed strings "
                                "(guided REVERB_STRINGS) against the Monte Carlo baseline"},
    "ms_derived": {"switches": ("MS_DERIVED",), "ratio": "forward_ratio_with_over_without",
                   "variants": {"coupling_held": False, "coupling_derived": True},
                   # held: the scene's 0.5 and the 0.1 earlier studies found better; derived: the scene's default
                   # (the derived coupling itself)
                   "couplings": {"coupling_held": (0.5, 0.1), "coupling_derived": (0.5,)},
                   "absorbing_edges": True,
                   "title": "multiple scattering's coupling derived from the geometry (guided MS_DERIVED) against "
                            "the Monte Carlo baseline, with its diffuse edges and with absorbing ones"},
    "scatter_redirect": {"switches": ("SCATTER_REDIRECT",), "ratio": "forward_ratio_with_over_without",
                         "variants": {"without_redirect": False, "with_redirect": True},
                         "couplings": {"without_redirect": (0.5,), "with_redirect": (0.5,)},
                         "title": "the lit walls' light scattered by the volume on to the walls in view (guided "
                                  "SCATTER_REDIRECT) against the Monte Carlo baseline"},
    "scatter_share": {"switches": ("REVERB_SCATTER_SHARE",), "ratio": "forward_ratio_with_over_without",
                      "variants": {"evenly": False, "by_geometry": True},
                      "couplings": {"evenly": (0.5,), "by_geometry": (0.5,)},
                      "title": "the beam's scattered light on the walls by the geometry, not evenly (guided "
                               "REVERB_SCATTER_SHARE) against the Monte Carlo baseline"},
    "share_and_redirect": {"switches": ("REVERB_SCATTER_SHARE", "SCATTER_REDIRECT"), "ratio": "forward_ratio_with_over_without",
                           "variants": {"neither": False, "both": True},
                           "couplings": {"neither": (0.5,), "both": (0.5,)},
                           "title": "REVERB_SCATTER_SHARE and SCATTER_REDIRECT together against the Monte Carlo baseline"},
    "edge_groups": {"switches": ("EDGE_SECOND_GROUPS",), "ratio": "forward_ratio_with_over_without",
                    "variants": {"middle_rays": False, "per_zone_and_wall": True},
                    "couplings": {"middle_rays": (0.5,), "per_zone_and_wall": (0.5,)},
                    "title": "the far edge's second bounce from one source per zone and wall, not each zone's middle "
                             "ray (guided EDGE_SECOND_GROUPS) against the Monte Carlo baseline"},
    "reverb_segments": {"switches": ("REVERB_SEGMENTS_PER_WALL",), "values": {False: 4, True: 6},
                        "ratio": "forward_ratio_with_over_without",
                        "variants": {"four_per_wall": False, "six_per_wall": True},
                        "couplings": {"four_per_wall": (0.5,), "six_per_wall": (0.5,)},
                        "title": "the reverberant field on 6 segments per wall, not 4 (guided REVERB_SEGMENTS_PER_WALL) "
                                 "against the Monte Carlo baseline"},
    "own_return": {"switches": ("SCATTER_OWN_RETURN",), "ratio": "forward_ratio_with_over_without",
                   "variants": {"zone_mean": False, "own_return": True},
                   "couplings": {"zone_mean": (0.5,), "own_return": (0.5,)},
                   "title": "the scattered light's kernels timed from each ray's own return, not the zone's (guided "
                            "SCATTER_OWN_RETURN) against the Monte Carlo baseline"},
}
#: the absorbing-edge comparison's volume window (bins): from just after the light entry to before the far edge
ABSORB_WINDOW = (16, 46)


def _switch(guided, on: bool, study: str = "aperture") -> None:
    """Set the ``study``'s switches off or on (a study with ``values`` maps off and on to a setting: a count)."""
    for name in STUDIES[study]["switches"]:
        setattr(guided, name, STUDIES[study].get("values", {}).get(on, on))


def absorbing_edges(study: str, seeds: int = 32, photons: int = 25_000) -> dict:
    """The volume's light alone: the Monte Carlo baseline with absorbing edges (``seeds`` cached runs) against the
    guided model's volume backscatter and multiple scattering at the scene's optics, the ``study``'s switches off
    and on. Per sensor: the Monte Carlo over the model in :data:`ABSORB_WINDOW` (first and last five bins, summed
    over the zones), its least-squares slope per bin, and the multiple scattering the Monte Carlo asks for over
    the model's (the volume held; weights 1 / counts)."""
    import tofjax.model.guided as guided
    from tofjax.mc.bench import profiled_relative_l2
    from tofjax.model import ModelOptions, Params, build_model

    sys.path.insert(0, str(HERE))
    import eval_mc_data as ev

    scene = ev.guided_scene()
    runs = np.stack([ev.mc_expected(scene, photons, s, edges="absorb")[0] for s in range(seeds)])
    p = Params.from_scene(scene)
    mc = runs.mean(0) - np.asarray(build_model(scene, ModelOptions(optics="guided"), ("crosstalk", "ambient"))(p))
    lo, hi = ABSORB_WINDOW
    out = {"seeds": seeds, "photons_per_sensor": photons, "window_bins": [lo, hi],
           "note": "S2's window ends on its near walls' light (absorbed edges still cut its volume short)"}
    for name, on in STUDIES[study]["variants"].items():
        _switch(guided, on, study)
        parts = build_model(scene, ModelOptions(optics="guided"), ("volume", "multiple_scattering")).breakdown(p)
        vol, ms = (np.asarray(parts[k]) for k in ("volume", "multiple_scattering"))
        model = vol + ms
        ratio = mc[..., lo:hi].sum(1) / model[..., lo:hi].sum(1)  # (S, bins)
        bins = np.arange(lo, hi)
        k = []
        for s in range(mc.shape[0]):
            y, x = (mc[s] - vol[s])[:, lo:hi].ravel(), ms[s][:, lo:hi].ravel()
            w = 1.0 / np.maximum(mc[s][:, lo:hi].ravel(), 1.0)
            k.append(float(np.sum(w * x * y) / np.sum(w * x * x)))
        out[name] = {
            "mc_over_model_first_5_bins": ratio[:, :5].mean(1).round(4).tolist(),
            "mc_over_model_last_5_bins": ratio[:, -5:].mean(1).round(4).tolist(),
            "mc_over_model_slope_per_bin": [float(np.polyfit(bins, r, 1)[0]) for r in ratio],
            "mc_multiple_scattering_over_model": k,
            "multiple_scattering_share_last_5_bins": (ms[..., hi - 5:hi].sum((1, 2)) / model[..., hi - 5:hi].sum((1, 2))).round(4).tolist(),
            "relative_l2_window": profiled_relative_l2(mc[..., lo:hi], model[..., lo:hi])[0],
        }
    _switch(guided, True, study)
    return out


def light_comparison(repeats: int, study: str = "aperture") -> dict:
    """Part 1: the transported light at the scene's optics, the Monte Carlo against the guided model with the
    ``study``'s switches off and on (relative L2 over the whole histogram, the near window and each of
    :data:`WINDOWS`)."""
    import jax

    import tofjax.model.guided as guided
    from tofjax.mc.bench import profiled_relative_l2
    from tofjax.model import ModelOptions, Params, build_model

    sys.path.insert(0, str(HERE))
    import eval_mc_data as ev

    scene, expected, _ = ev.calibration_baseline(exposure=1.0)
    p = Params.from_scene(scene)
    extras = np.asarray(build_model(scene, ModelOptions(optics="guided"), ("crosstalk", "ambient"))(p))
    mc = expected - extras
    comps = tuple(c for c in scene.components() if c not in ("crosstalk", "ambient", "interface"))
    t0 = int(scene.sensor.emission_time // scene.sensor.bin_width_s)
    near = slice(t0, t0 + 4)
    window = slice(t0, t0 + 7)

    def outer_over_middle(y):
        n = y[..., near].sum(-1)
        mid = n.shape[1] // 2
        return np.stack([n[:, 0] / n[:, mid], n[:, -1] / n[:, mid]], -1)  # (S, 2)

    out = {"components": list(comps), "emission_bin": t0, "near_bins": [t0, t0 + 4], "near_window_bins": [t0, t0 + 7],
           "monte_carlo": {"outer_over_middle_first_4_bins": outer_over_middle(mc).round(4).tolist()}}
    fns = {}
    variants = STUDIES[study]["variants"]
    for name, on in variants.items():
        _switch(guided, on, study)
        f = jax.jit(build_model(scene, ModelOptions(optics="guided"), comps).__call__)
        y = np.asarray(f(p))
        fns[name] = f
        oom = outer_over_middle(y)
        out[name] = {
            "outer_over_middle_first_4_bins": oom.round(4).tolist(),
            "outer_over_middle_error_vs_mc_rms": float(np.sqrt(np.mean((oom - outer_over_middle(mc)) ** 2))),
            "relative_l2": profiled_relative_l2(mc, y)[0],
            "relative_l2_near_window": profiled_relative_l2(mc[..., window], y[..., window])[0],
            "light_first_4_bins_mc_over_model": float(mc[..., near].sum() / y[..., near].sum()),
            "relative_l2_by_window": {k: profiled_relative_l2(mc[..., a:b], y[..., a:b])[0] for k, (a, b) in WINDOWS.items()},
        }
    _switch(guided, True, study)
    # forward time (traced programs keyed by the switches: each variant's program was compiled above)
    med = ev.alternating_medians(fns, repeats, p)
    out["forward_s"] = med
    off, on = variants
    out[STUDIES[study]["ratio"]] = med[on] / med[off]
    return out


def calibrate_one(aperture: bool, coupling: float, exposure: float = 64.0, study: str = "aperture") -> dict:
    """Part 2, in this process: the eval's calibration at ``exposure`` with the ``study``'s switches ``aperture`` (on
    or off) and the held coupling."""
    import tofjax.model.guided as guided

    sys.path.insert(0, str(HERE))
    import eval_mc_data as ev

    _switch(guided, aperture, study)
    fig, res = ev.calibrate_baseline(ev.calibration_baseline(exposure), coupling)  # its runs cached by eval_mc_data.py
    out = {k: fig[k] for k in ("result", "converged", "reduced_chi2_photon_noise", "reduced_chi2_with_mc_variance",
                               "n1_rel_error", "mu_t_rel_error", "steps")}
    p = res.params
    out |= {"mu_s_per_m": float(p.mu_s_per_m), "mu_a_per_m": float(p.mu_a_per_m), "seconds": fig["seconds"]}
    r2 = np.asarray(res.residuals) ** 2
    out["excess_chi2_by_window"] = {k: float(r2[..., a:b].sum() - r2[..., a:b].size) for k, (a, b) in WINDOWS.items()}
    # the calibration's score test of its held parameters (z against the residuals; scaled by sqrt(chi-square))
    fixed = (res.discrepancy or {}).get("fixed_parameters") or {}
    out["held_parameters_score"] = {r["name"]: {k: r.get(k) for k in ("value", "z", "z_scaled", "gauss_newton_value", "contradicted")}
                                    for r in fixed.get("parameters", []) if r.get("z") is not None}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--repeats", type=int, default=100, help="forward calls per variant for the time ratio")
    ap.add_argument("--no-calibration", action="store_true", help="part 1 only")
    ap.add_argument("--exposures", default="64", help="exposures of the calibrations, comma-separated (default: 64)")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--study", choices=sorted(STUDIES), default="aperture",
                    help="which switches to compare (default: aperture, NEAR_FIELD_APERTURE and EDGE_APERTURE)")
    ap.add_argument("--calibrate-one", metavar="APERTURE:COUPLING:EXPOSURE", help=argparse.SUPPRESS)  # JSON out
    a = ap.parse_args(argv)
    import tofjax
    from tofjax.outputs import OutputError, check_output

    if a.repeats < 1:
        ap.exit(2, "error: --repeats must be >= 1\n")
    tofjax.enable_x64()
    if a.calibrate_one:
        try:
            on, c, e = a.calibrate_one.split(":")
            if on not in ("0", "1") or not (0.0 <= float(c) < math.inf and 0.0 < float(e) < math.inf):
                raise ValueError
        except ValueError:
            ap.exit(2, f"error: --calibrate-one: expected 0|1:COUPLING:EXPOSURE, got {a.calibrate_one!r}\n")
        tofjax.use_fast_cpu_compiler()
        print(json.dumps(calibrate_one(on == "1", float(c), float(e), a.study)))
        return 0
    try:
        exposures = [float(x) for x in a.exposures.split(",")]
        if not all(0.0 < x < math.inf for x in exposures):
            raise ValueError(f"--exposures: every exposure must be a finite number > 0, got {a.exposures!r}")
        path = check_output(Path(a.out), overwrite=a.overwrite)
    except (OutputError, ValueError) as e:
        ap.exit(2, f"error: {e}\n")
    sys.path.insert(0, str(HERE))
    import eval_mc_data as ev

    t0 = time.perf_counter()
    study = STUDIES[a.study]
    result = ev.study_header(study["title"], "simulated (tofjax.mc Monte Carlo runs, as experiments/eval_mc_data.py)")
    result["study"] = {"name": a.study, "switches": list(study["switches"])}
    result["light_at_the_scene_optics"] = light = light_comparison(a.repeats, a.study)
    for k in study["variants"]:
        print(f"{k}: relative L2 {light[k]['relative_l2']:.4f}, near window {light[k]['relative_l2_near_window']:.4f}, "
              f"far edge {light[k]['relative_l2_by_window']['far_edge']:.4f}, "
              f"outer/middle error vs MC (rms) {light[k]['outer_over_middle_error_vs_mc_rms']:.3f}", flush=True)
    print(f"forward time, on over off: {light[study['ratio']]:.3f}", flush=True)
    if study.get("absorbing_edges"):
        result["absorbing_edges"] = ab = absorbing_edges(a.study)
        for k in study["variants"]:
            print(f"absorbing edges, {k}: MC over model first / last 5 bins {ab[k]['mc_over_model_first_5_bins']} / "
                  f"{ab[k]['mc_over_model_last_5_bins']}, the MC's multiple scattering over the model's "
                  f"{np.round(ab[k]['mc_multiple_scattering_over_model'], 2).tolist()}", flush=True)
    if not a.no_calibration:
        for x in exposures:
            cal = result[f"calibration_{x:g}x_monte_carlo"] = {}
            for name, on in study["variants"].items():
                for c in study.get("couplings", {}).get(name, COUPLINGS):
                    key = f"{name}_multiple_scattering_{c:g}"
                    cal[key] = r = ev.run_in_own_process(__file__, ["--out", os.devnull, "--study", a.study,
                                                                    "--calibrate-one", f"{int(on)}:{c}:{x}"])
                    print(f"{x:g}x {key}: {r['result']}, chi2 {r['reduced_chi2_photon_noise']:.3f} "
                          f"({r['reduced_chi2_with_mc_variance']:.3f} with the MC's variance), n1 "
                          f"{r['n1_rel_error']:+.5f}, mu_t {r['mu_t_rel_error']:+.3f}, {r['steps']} steps", flush=True)
    result["seconds"] = time.perf_counter() - t0
    ev.write_study(result, path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
