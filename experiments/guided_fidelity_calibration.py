"""The guided model's sampling against its misfit of the Monte Carlo baseline (issue 14: reduced chi-square <= 2 at 64x).

The guided optics sample each zone's fan by ``angles_per_zone`` rays and the guided elevation band by ``elevations``
quadrature nodes (:class:`tofjax.model.ModelOptions`, both 8 by default; :class:`tofjax.fit.FitConfig` sets them for a
calibration). How much of the 64x calibration's misfit of the Monte Carlo baseline is this sampling, and how much is
physics the model lacks? Each ``ELEVATIONS:ANGLES`` variant of ``--variants`` calibrates the same capture (the Monte
Carlo baseline of ``experiments/eval_mc_data.py``: its 64 cached runs of 25,000 packets per sensor, 10 frames at 64x
exposure, seed 0), each in a process of its own, and reports:

* the reduced chi-square against photon noise and with the Monte Carlo's own variance counted, the errors of n1 and
  mu_s + mu_a, the steps and the calibration's seconds (compile included);
* the excess chi-square (chi-square minus the bin count) by time window (light entry, volume, far edge, after);
* the guided model's forward time at that sampling over its time at 8:8, timed alternately in the same process
  (``--repeats`` calls each, median), on the baseline.

All data **simulated** (tofjax's Monte Carlo). About 1-3 minutes per variant on the 2-core VM.

    python experiments/guided_fidelity_calibration.py --out docs/results/guided_fidelity_calibration.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

#: time windows (bins, 100 ps each on OptoSkin) of the excess chi-square
WINDOWS = {"before_light_entry": (0, 13), "light_entry": (13, 20), "volume": (20, 46), "far_edge": (46, 62),
           "after": (62, None)}


def forward_ratio(scene, elevations: int, angles: int, repeats: int) -> dict:
    """The guided model's warm forward time at ``elevations:angles`` over its time at 8:8 (alternating calls, medians)."""
    import jax

    from tofjax.model import ModelOptions, Params, build_model

    p = Params.from_scene(scene)
    models = {key: jax.jit(build_model(scene, ModelOptions(optics="guided", elevations=e, angles_per_zone=a)).__call__)
              for key, (e, a) in (("this", (elevations, angles)), ("default", (8, 8)))}
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    med = ev.alternating_medians(models, repeats, p)
    return {"forward_s": med["this"], "forward_s_at_8_8": med["default"], "forward_ratio_to_8_8": med["this"] / med["default"]}


def calibrate_one(elevations: int, angles: int, repeats: int) -> dict:
    """The eval's 64x Monte Carlo calibration at this sampling (in this process), and the forward time ratio."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    scene, expected, mc_var = ev.calibration_baseline()  # its runs cached by eval_mc_data.py
    cap = ev._capture(scene, expected, 10, 0, "simulated (monte_carlo)")
    fig, res = ev.calibrate_capture(scene, cap, mc_var, "guided", elevations=elevations, angles_per_zone=angles)
    out = {k: fig[k] for k in ("result", "converged", "reduced_chi2_photon_noise", "n1_rel_error", "mu_t_rel_error",
                               "steps", "reduced_chi2_with_mc_variance", "mc_variance_over_photon_variance_median",
                               "mc_variance_share_of_photon_weighted_chi2")}
    out["calibration_seconds"] = fig["seconds"]
    r2 = np.asarray(res.residuals) ** 2  # (S, Z, B), photon-weighted
    out["excess_chi2_by_window"] = {k: float(r2[..., a:b].sum() - r2[..., a:b].size) for k, (a, b) in WINDOWS.items()}
    out["bins"] = int(r2.size)
    out.update(forward_ratio(scene, elevations, angles, repeats))
    return out


def calibrations(variants: list[tuple[int, int]], repeats: int, progress: bool) -> dict:
    """:func:`calibrate_one` per variant, each in a process of its own (a model's sampling is fixed when it is
    built; a process of its own also keeps the compiled programs apart)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    out = {}
    for e, a in variants:
        key = f"elevations_{e}_angles_{a}"
        out[key] = ev.run_in_own_process(__file__, ["--out", os.devnull, "--repeats", str(repeats),
                                                    "--calibrate-one", f"{e}:{a}"])
        if progress:
            r = out[key]
            print(f"{key}: chi2 {r['reduced_chi2_photon_noise']:.3f} ({r['reduced_chi2_with_mc_variance']:.3f} with the "
                  f"Monte Carlo's variance), n1 {r['n1_rel_error']:+.5f}, mu_t {r['mu_t_rel_error']:+.3f}, "
                  f"{r['steps']} steps, {r['calibration_seconds']:.0f} s, forward {r['forward_ratio_to_8_8']:.2f}x 8:8",
                  flush=True)
    return out


def _variants(text: str) -> list[tuple[int, int]]:
    out = []
    for item in text.split(","):
        e, _, a = item.strip().partition(":")
        if not (e.isdigit() and a.isdigit() and int(e) >= 1 and int(a) >= 1):
            raise ValueError(f"--variants: expected ELEVATIONS:ANGLES, both integers >= 1, got {item!r}")
        out.append((int(e), int(a)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--variants", default="8:8,16:8,8:16,16:16,32:16,16:32",
                    help="ELEVATIONS:ANGLES per zone, comma-separated (default: %(default)s)")
    ap.add_argument("--repeats", type=int, default=60, help="forward calls per sampling for the time ratio")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--calibrate-one", metavar="E:A", help=argparse.SUPPRESS)  # one variant; JSON to stdout
    a = ap.parse_args(argv)
    import tofjax
    from tofjax.outputs import OutputError, atomic_write_text, check_output

    if a.repeats < 1:
        ap.exit(2, "error: --repeats must be >= 1\n")
    if a.calibrate_one:
        tofjax.use_fast_cpu_compiler()
        tofjax.enable_x64()
        (e, n), = _variants(a.calibrate_one)
        print(json.dumps(calibrate_one(e, n, a.repeats)))
        return 0
    try:
        variants = _variants(a.variants)
        path = check_output(Path(a.out), overwrite=a.overwrite)
    except (ValueError, OutputError) as e:
        ap.exit(2, f"error: {e}\n")
    t0 = time.perf_counter()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    result = ev.study_header("the guided model's sampling (elevations, rays per zone) against its 64x calibration of "
                             "the Monte Carlo baseline",
                             "simulated (tofjax.mc Monte Carlo runs, as experiments/eval_mc_data.py)")
    result |= {"capture": "64 Monte Carlo runs x 25,000 packets per sensor, 64x exposure, 10 frames, seed 0",
               "windows_bins": {k: list(v) for k, v in WINDOWS.items()},
               "calibration_64x_monte_carlo": calibrations(variants, a.repeats, progress=True)}
    result["seconds"] = time.perf_counter() - t0
    result["load_average_end"] = list(os.getloadavg())
    atomic_write_text(path, json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
