"""Diagnostic: is the search or the data the fit method's limit? For each frame of a saved
``eval_mc_data.py`` run (``--column``, own or monte_carlo) where a contact was missed or a detection was false, the chi-square of the fit as found
(its saved detections, refitted jointly from there) against the true contacts refitted the same way.

A truth lower by more than ``n_sigma_forward^2`` (16) per contact difference says a better search exists;
a truth no better says the data (or the threshold) decide. Rebuilds the run's frames exactly (same seeds,
exposure, cached calibration in ``--out``). All data **simulated**.

    python experiments/fit_truth_chi2.py --out out/x64_own --result out/x64_own/eval_mc_data.json [--column own]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None):
    import tofjax

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="the run's --out (its cached calibration)")
    ap.add_argument("--result", required=True, help="the run's eval_mc_data.json (own column)")
    ap.add_argument("--method", default="fit")
    ap.add_argument("--column", default="own", choices=("own", "monte_carlo"))
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    import eval_mc_data as ev

    from tofjax.invert.correction import OpticalParams
    from tofjax.invert.greedy import FitDetectOptions, build_fit_detector
    from tofjax.outputs import atomic_write_text
    from tofjax.simulate import expected_counts

    t0 = time.perf_counter()
    r = json.loads(Path(a.result).read_text())
    st = r["settings"]
    E, seed, nb = st["exposure"], st["seed"], st["baseline_frames"]
    col = a.column
    if col not in r["detection"]:
        sys.exit(f"--result: has no {col} column")
    scene = ev.guided_scene()
    contacts = np.asarray(r["contacts"])
    fpc = r["detection"][col]["frames_per_config"]
    photons, nt = r["monte_carlo"]["photons_per_sensor_per_seed"], r["monte_carlo"]["seeds_touch"]
    cal = Path(a.out) / (f"calibration_{col}_guided_{st['calib_frames']}f_{photons}"
                         f"x{r['monte_carlo']['seeds_baseline']}_exposure{E:g}_"
                         f"{ev.mc_source_hash() if col == 'monte_carlo' else 'own'}.json")
    _, js = json.loads(cal.read_text())
    optical = OpticalParams.from_calibration(dict(js, converged=True), scene)
    if col == "own":
        b = expected_counts(scene, ev._own_model_options()) * E
        touch = [expected_counts(ev.touch_scene(scene, c), ev._own_model_options(True)) * E for c in contacts]
    else:  # as run() builds them: the touch seeds' baseline (common random numbers)
        b = E * np.mean([ev.mc_expected(scene, photons, k)[0] for k in range(nt)], 0)
        touch = [E * np.mean([ev.mc_expected(ev.touch_scene(scene, c), photons, k)[0] for k in range(nt)], 0)
                 for c in contacts]
    base = ev._capture(scene, b, nb, seed + 1000, "baseline")
    H = np.concatenate([ev._capture(scene, e, fpc, seed + 2000 + i, "touch").histograms for i, e in enumerate(touch)])
    truth = np.repeat(contacts, fpc, axis=0)
    det = build_fit_detector(scene, base.mean(), dataclasses.replace(optical), FitDetectOptions(), n_baseline=nb)
    frames = r["detection"][col]["methods"][a.method]["false_detections"]["frames"]
    K = det.K
    rows = []
    for i, fr in enumerate(frames):
        false = sum(not d[3] for d in fr["detections"])
        if not fr["missed"] and not false:
            continue
        y = (H[i].ravel() - det.base) / det.sigma

        def refit(c):
            c = np.asarray(c, float).reshape(-1, 3)[:K]
            th = np.zeros(3 * K)
            n = len(c)
            th[:n], th[K : K + n], th[2 * K : 2 * K + n] = c.T
            act = np.arange(n)
            th, chi, _ = det._refit(th, act, y, iterations=20)
            return chi, n

        chi_found, n_found = refit([d[:3] for d in fr["detections"]])
        chi_truth, n_truth = refit(truth[i])
        rows.append({"frame": i, "detections": n_found, "missed": len(fr["missed"]), "false": false,
                     "chi2_found_refitted": chi_found,
                     "chi2_truth_refitted": chi_truth, "truth_lower_by": chi_found - chi_truth,
                     "score_difference": (chi_found + 16 * n_found) - (chi_truth + 16 * n_truth)})
        print(rows[-1], flush=True)
    out = {"study": "chi-square of the fit as found against the true contacts, both refitted (20 LM steps) from "
                    "there, on the frames with a missed contact or a false detection; simulated", "result": a.result,
           "column": col, "score_what": "chi2 + 16 per contact (n_sigma_forward^2): the search's own comparison",
           "exposure": E, "dof": int(det.sigma.size), "frames": rows,
           "truth_lower_by_median": float(np.median([q["truth_lower_by"] for q in rows])) if rows else None,
           "seconds": time.perf_counter() - t0, "load_average_end": list(os.getloadavg())}
    atomic_write_text(Path(a.out) / f"fit_truth_chi2_{col}.json", json.dumps(out, indent=1), overwrite=True)
    print(f"wrote {a.out}/fit_truth_chi2_{col}.json")


if __name__ == "__main__":
    main()
