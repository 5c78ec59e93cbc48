"""How well can any fit place a contact near the borders? The position Cramer-Rao bound against the fit method's
recall (issues 13 and 14: border recall).

The six-contact evaluation (``eval_mc_data.py``) matches a detection to a contact within 2 cm. Its border recall
(contacts within 5 cm of an edge) has stayed 8-13 points below the interior's on tofjax's own data, where the model
is exact, as on the Monte Carlo's. This study asks how much of that any detector could avoid. For each contact set
of the evaluation (``--config-seeds``; 12 configurations of six contacts each) and each ``--exposures`` (the
sensor's iterations per frame relative to the scene's, as ``eval_mc_data.py --exposure``), it computes every true
contact's position bound with the six fitted together (:meth:`tofjax.invert.greedy.FitDetector.position_bound`:
the inverse Fisher information in every contact's x, y and strength, at the true values, the number of contacts
known; the true optics; the Poisson noise of the baseline, averaged over 100 frames as in the evaluation) and the
probability that a fit reaching it lands within the match radius
(:func:`tofjax.invert.sensitivity.match_probability`). Their mean is the recall of a detector that finds every
contact and places it as well as the data allow, split border / interior as the evaluation splits it.

``--observed RESULT.json ...``: ``eval_mc_data.py`` results; the fit method's recall (border / interior) of each is
put beside the bound's for its contact set and exposure.

    python experiments/position_bound.py --out docs/results/position_bound.json \\
        [--config-seeds 6,7,8] [--exposures 16,64,256,1024] [--observed RESULT.json ...] [--quick] \\
        [--map docs/img/position_bound_64x.png --map-exposure 64 --map-strength 0.85]

``--map``: also the lone-contact position map of ``tofjax sensitivity --method fit --position`` (the bound of one
contact alone at every 5 mm cell; tens of seconds) as a PNG, its summary in the JSON.

``--quick``: one contact set of two configurations at one exposure, the detector's proposal grid 2 cm (the fast
test's size; the bound does not depend on the grid, only the reported SNR's nearest cell does). **Simulated** (the
bound is the model's: tofjax's guided optics and skin contact, the OptoSkin scene of ``eval_mc_data.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def detector_at(scene, exposure: float, n_baseline: int = 100, cell_m: float = 0.005):
    """The fit method's detector at the scene's true optics (guided), every count ``exposure`` times the scene's
    (``cell_m``: its proposal grid, which the bound does not use; ``--quick`` coarsens it)."""
    from tofjax.invert.correction import OpticalParams
    from tofjax.invert.greedy import FitDetectOptions, build_fit_detector
    from tofjax.simulate import expected_counts

    sys.path.insert(0, str(HERE))
    import eval_mc_data as E

    base = expected_counts(scene, E._own_model_options()) * exposure
    op = OpticalParams.from_scene(scene)
    optical = dataclasses.replace(op, optics="guided", gain=tuple(g * exposure for g in op.gain))
    return build_fit_detector(scene, base, optical, FitDetectOptions(cell_m=cell_m), n_baseline=n_baseline), base


def bound_of_set(det, scene, contacts: np.ndarray, match_radius_m: float = 0.02, border_m: float = 0.05) -> dict:
    """Per contact of ``contacts`` (configs, 6, 3) the bound's major standard deviation and match probability;
    their summary, border / interior."""
    sys.path.insert(0, str(HERE))
    import eval_touch

    from tofjax.invert.sensitivity import major_sd, match_probability

    p, sd, border, snr = [], [], [], []
    for c in contacts:
        cov = det.position_bound(c)
        p.append(match_probability(cov, match_radius_m))
        sd.append(major_sd(cov))
        border.append(eval_touch._edge_distance(scene, c[:, :2]) < border_m)
        j = [int(np.argmin(np.hypot(*(det.centres - xy).T))) for xy in c[:, :2]]
        snr.append(c[:, 2] * np.sqrt(det._gdiag[j]))
    p, sd, border, snr = (np.concatenate(v) for v in (p, sd, border, snr))

    def q(v):
        return np.quantile(v, [0.1, 0.5, 0.9]).tolist() if v.size else None

    return {
        "contacts": int(p.size), "border_contacts": int(border.sum()),
        "recall_bound": float(p.mean()), "recall_bound_border": float(p[border].mean()) if border.any() else None,
        "recall_bound_interior": float(p[~border].mean()) if (~border).any() else None,
        "position_sd_major_cm_border_quantiles_10_50_90": q(100 * sd[border]),
        "position_sd_major_cm_interior_quantiles_10_50_90": q(100 * sd[~border]),
        "lone_contact_snr_quantiles_10_50_90 (nearest proposal cell)": q(snr),
        "per_contact": {"match_probability": p.round(4).tolist(), "border": border.tolist(),
                        "position_sd_major_cm": [round(float(v), 3) if np.isfinite(v) else None for v in 100 * sd]},
    }


def observed(paths: list[str]) -> list[dict]:
    """The fit method's recall (all, border, interior) of each ``eval_mc_data.py`` result, with its set and exposure:
    one row per detection column and fit variant (``fit``, ``fit:NAME``)."""
    rows = []
    for path in paths:
        r = json.loads(Path(path).read_text())
        s = r["settings"]
        for col, d in r["detection"].items():
            for name, m in d["methods"].items():  # the fit method and its variants (fit:NAME), not its n_sigma levels
                if not (name == "fit" or name.startswith("fit:")) or "_n_sigma_" in name:
                    continue
                rows.append({"file": Path(path).name, "column": col, "method": name,
                             "config_seed": s.get("config_seed", 6), "exposure": s["exposure"], "configs": s["configs"],
                             "recall": m["recall"], "recall_border": m["recall_border"],
                             "recall_interior": m["recall_interior"], "precision": m["precision"]})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--config-seeds", default="6,7,8", help="contact sets (eval_mc_data.py --config-seed)")
    ap.add_argument("--configs", type=int, default=12, help="configurations of six contacts per set")
    ap.add_argument("--exposures", default="16,64,256,1024", help="exposures (eval_mc_data.py --exposure)")
    ap.add_argument("--observed", nargs="*", default=[], help="eval_mc_data.py results to set beside the bound")
    ap.add_argument("--map", help="also the lone-contact position map (tofjax sensitivity --method fit --position) at the "
                    "--map-exposure, strength --map-strength, written to this PNG; its summary goes in the JSON")
    ap.add_argument("--map-exposure", type=float, default=64.0)
    ap.add_argument("--map-strength", type=float, default=0.85, help="the study's contacts are 0.7-1.0")
    ap.add_argument("--quick", action="store_true", help="one set of two configurations at 64x")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    try:
        seeds = [int(v) for v in a.config_seeds.split(",")]
        exposures = [float(v) for v in a.exposures.split(",")]
    except ValueError:
        ap.error("--config-seeds and --exposures must be comma-separated numbers")
    if a.quick:
        seeds, exposures, a.configs = seeds[:1], [64.0], 2
    if a.configs < 1 or not all(e > 0 for e in exposures):
        ap.error("--configs must be >= 1 and every exposure > 0")
    if not (a.map_exposure > 0 and a.map_strength > 0):
        ap.error("--map-exposure and --map-strength must be > 0")
    sys.path.insert(0, str(HERE.parent))
    sys.path.insert(0, str(HERE))
    from tofjax import enable_x64
    from tofjax.compile_cache import use_fast_cpu_compiler
    from tofjax.outputs import OutputError, atomic_write_text, check_output

    try:
        path = check_output(Path(a.out), overwrite=a.overwrite)
        if a.map:
            check_output(Path(a.map), overwrite=a.overwrite, flag="--map")
    except OutputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    use_fast_cpu_compiler()
    enable_x64()
    import eval_mc_data as E

    t0 = time.perf_counter()
    scene = E.guided_scene()
    out = {**E.study_header("position Cramer-Rao bound of the six-contact sets against the fit method's recall "
                            "(issues 13, 14)", "simulated: the bound is tofjax's guided model's (true optics, skin contact)"),
           "settings": {"config_seeds": seeds, "configs": a.configs, "exposures": exposures, "match_radius_m": 0.02,
                        "border_m": 0.05, "baseline_frames": 100,
                        "what": "recall_bound: mean over the true contacts of the probability that a fit reaching the "
                                "joint position bound (six contacts fitted together, their number known) lands "
                                "within the match radius; border: contacts within border_m of an edge"},
           "bound": [], "observed": observed(a.observed)}
    for exposure in exposures:
        det, _ = detector_at(scene, exposure, cell_m=0.02 if a.quick else 0.005)
        for cs in seeds:
            res = bound_of_set(det, scene, E.contact_configs(scene, a.configs, cs))
            out["bound"].append({"config_seed": cs, "exposure": exposure, **res})
            print(f"exposure {exposure:g} set {cs}: recall bound {res['recall_bound']:.3f}, border "
                  f"{res['recall_bound_border']:.3f}, interior {res['recall_bound_interior']:.3f}", flush=True)
    if a.map:
        from tofjax.invert.plots import plot_position_bound
        from tofjax.invert.sensitivity import SensitivityOptions, fit_sensitivity_of

        det, _ = detector_at(scene, a.map_exposure)
        t = time.perf_counter()
        res = fit_sensitivity_of(det, SensitivityOptions(strength=a.map_strength, position=True), progress=True)
        summ = res.summary()
        out["map"] = {"exposure": a.map_exposure, "strength": a.map_strength, "png": a.map,
                      "seconds": time.perf_counter() - t, "cells": int(res.sensed.sum()),
                      "placed_within_match_radius": summ["placed_within_match_radius"],
                      "position_sd_cm_median_border_interior": summ["position_sd_cm_median_border_interior"],
                      "detectable_one_frame": summ["detectable_one_frame"]}
        plot_position_bound(res, a.map, title=f"OptoSkin (simulated), {a.map_exposure:g}x, strength {a.map_strength:g}: "
                            f"placed within 2 cm {100 * summ['placed_within_match_radius']['all']:.0f}% on average")
        pl = summ["placed_within_match_radius"]
        print(f"map ({a.map_exposure:g}x, strength {a.map_strength:g}): placed within 2 cm {pl['all']:.3f} (border "
              f"{pl['border']:.3f}, interior {pl['interior']:.3f}), {out['map']['seconds']:.0f} s; wrote {a.map}")
    for row in out["observed"]:
        b = [x for x in out["bound"] if x["config_seed"] == row["config_seed"] and x["exposure"] == row["exposure"]]
        if b:
            row["recall_bound_border"], row["recall_bound_interior"] = b[0]["recall_bound_border"], b[0]["recall_bound_interior"]
        print(f"observed {row['file']} ({row['column']}, {row['method']}, set {row['config_seed']}, {row['exposure']:g}x): border "
              f"{row['recall_border']:.3f}, interior {row['recall_interior']:.3f}"
              + (f" (bound {row['recall_bound_border']:.3f} / {row['recall_bound_interior']:.3f})" if b else ""))
    out["seconds"] = time.perf_counter() - t0
    import os

    out["load_average_end"] = list(os.getloadavg())
    atomic_write_text(path, json.dumps(out, indent=1) + "\n", overwrite=a.overwrite)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
