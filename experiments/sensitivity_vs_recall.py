"""Study: does the sensitivity map (``tofjax.invert.sensitivity``) predict which contacts the model
method finds? Simulated data.

The six-contact study of ``experiments/eval_touch.py`` on an attenuating guide (default
``mu_s, mu_a = 3, 1 /m``: mu_s + mu_a = 4 /m, ``configs/studies/eval_touch_six.toml``'s harder
scenario), built the same way: the same random configurations (``random_contacts``, seed + 6),
the same sources (``own``: tofjax's forward model; ``independent``: ``tests/indep_sim.py``), a
100-frame baseline from each, the true optics, the model method with its default detection.

For each source the map is computed from *that source's* baseline and the model method's own
reconstructor (:func:`sensitivity_of`, as ``tofjax sensitivity`` would on that baseline). Each
true contact is binned by the map's predicted one-frame SNR at its cell (matched filter, its true
strength) and by its margin, strength / the map's minimum detectable strength (> 1: predicted
detectable); recall is reported per bin.

A second check puts one contact per frame at random cells with strength = margin x the map's
minimum there (``--single`` positions x margins 0.5-3): the map's claim for a contact alone.

    python experiments/sensitivity_vs_recall.py --configs 60 --single 40 --json docs/results/sensitivity_vs_recall.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

SNR_BINS = (0.0, 3.0, 5.0, 7.0, 10.0, 15.0, np.inf)
MARGIN_BINS = (0.0, 0.5, 0.8, 1.0, 1.25, 1.5, 2.0, np.inf)
SINGLE_MARGINS = (0.5, 0.8, 1.0, 1.25, 1.5, 2.0, 3.0)


def _eval_touch():
    here = Path(__file__).resolve().parent
    if str(here) not in sys.path:
        sys.path.insert(0, str(here))
    import eval_touch

    return eval_touch


def _bins(found: np.ndarray, value: np.ndarray, edges, key: str) -> list[dict]:
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (value >= lo) & (value < hi)
        rows.append({f"{key}_from": lo, f"{key}_to": None if np.isinf(hi) else hi, "contacts": int(sel.sum()),
                     "recall": float(found[sel].mean()) if sel.any() else None})
    return rows


def _single(src, inv, sens, scene, config, n: int) -> dict:
    """One contact per frame, at ``n`` random cells (>= 1.5 cm from the edge), of strength ``margin``
    times the map's minimum there, for each of ``SINGLE_MARGINS``: the map's own claim (a contact
    alone, margin 1: found about half the time), apart from six-contact interactions."""
    rng = np.random.default_rng(config.seed + 7)
    lx, ly = scene.waveguide.size_m
    xy = np.stack([rng.uniform(0.015, lx - 0.015, n), rng.uniform(0.015, ly - 0.015, n)], 1)
    s_min = sens.at(xy)["min_strength"]
    keep = np.isfinite(s_min)
    xy, s_min = xy[keep], s_min[keep]
    C = np.array([[[x, y, m * s]] for m in SINGLE_MARGINS for (x, y), s in zip(xy, s_min)])
    H = src.frames(C, seed=config.seed + 300)
    res = inv.process(H)
    _, found = _eval_touch()._score(res.detections, C, config.match_radius_m)
    found = np.concatenate(found).reshape(len(SINGLE_MARGINS), len(xy))
    border = _eval_touch()._edge_distance(scene, xy) < config.border_m
    return {"what": "one contact per frame at random cells, strength = margin x the map's min_strength there; recall "
                    "per margin (all, border, interior) and false detections per frame",
            "positions": int(len(xy)),
            "rows": [{"margin": m, "recall": float(f.mean()), "recall_border": float(f[border].mean()),
                      "recall_interior": float(f[~border].mean())} for m, f in zip(SINGLE_MARGINS, found)],
            "false_per_frame": float(sum(max(len(d.positions()) - int(f), 0) for d, f in
                                         zip(res.detections, found.ravel())) / len(C))}


def run(configs: int, mu_s: float, mu_a: float, sources, seed: int = 0, baseline_frames: int = 100,
        single: int = 0) -> dict:
    et = _eval_touch()
    from tofjax.invert.pipeline import build_inverter
    from tofjax.invert.sensitivity import SensitivityOptions, sensitivity_of
    from tofjax.invert.synth import random_contacts
    from tofjax.scene import load_scene

    config = et.EvalConfig(methods=("model",), sources=tuple(sources), baseline_frames=baseline_frames, single_grid=0,
                           multi_counts=(6,), multi_configs=60, shapes=(), attenuations=((mu_s, mu_a),), seed=seed)
    scene = load_scene(config.scene).without_touches()
    scene = scene.replace(waveguide=dataclasses.replace(scene.waveguide, mu_s_per_m=float(mu_s), mu_a_per_m=float(mu_a)))
    # the configurations of eval_touch's six-contact scenario (all 60 drawn, the first `configs` used)
    contacts = random_contacts(scene, 60, 6, seed=config.seed + 6, min_separation_m=config.min_separation_m)[:configs]
    opts = et._options(config)["model"]
    out = {"sources": {}}
    for kind in sources:
        t0 = time.perf_counter()
        src = et._Source(kind, scene, config)
        inv = build_inverter(scene, src.baseline, opts, None, n_baseline=config.baseline_frames,
                             baseline_frames=src.baseline_frames)
        sens = sensitivity_of(inv.reconstructor, SensitivityOptions())
        t_build = time.perf_counter() - t0
        H = src.frames(contacts, seed=config.seed + 100)
        res = inv.process(H)
        score, found = et._score(res.detections, contacts, config.match_radius_m)
        found = np.concatenate(found)
        c = contacts.reshape(-1, 3)
        at = sens.at(c[:, :2])
        with np.errstate(divide="ignore"):
            snr = np.where(np.isfinite(at["cell_noise"]), c[:, 2] / at["cell_noise"], 0.0)
            margin = np.where(np.isfinite(at["min_strength"]), c[:, 2] / at["min_strength"], 0.0)
        border = et._edge_distance(scene, c[:, :2]) < config.border_m
        pred = margin >= 1.0
        missed = ~found
        out["sources"][kind] = {
            "precision": score["precision"], "recall": score["recall"], "contacts": int(found.size),
            "recall_border": float(found[border].mean()), "recall_interior": float(found[~border].mean()),
            "recall_by_predicted_snr": _bins(found, snr, SNR_BINS, "snr"),
            "recall_by_margin": _bins(found, margin, MARGIN_BINS, "margin"),
            "predicted_detectable": {
                "contacts": int(pred.sum()), "recall": float(found[pred].mean()) if pred.any() else None,
                "border_recall": float(found[pred & border].mean()) if (pred & border).any() else None},
            "predicted_undetectable": {
                "contacts": int((~pred).sum()), "recall": float(found[~pred].mean()) if (~pred).any() else None,
                "border_share": float(border[~pred].mean()) if (~pred).any() else None},
            "missed": int(missed.sum()),
            "missed_predicted_undetectable": int((missed & ~pred).sum()),
            "missed_margin_quantiles_10_50_90": np.quantile(margin[missed], [0.1, 0.5, 0.9]).tolist()
            if missed.any() else None,
            "found_margin_quantiles_10_50_90": np.quantile(margin[found], [0.1, 0.5, 0.9]).tolist(),
            "map_summary": sens.summary(),
            "threshold_snr_at_contacts_quantiles_10_50_90": np.quantile(at["threshold_snr"][np.isfinite(
                at["threshold_snr"])], [0.1, 0.5, 0.9]).tolist(),
            "seconds": time.perf_counter() - t0, "seconds_build": t_build,
        }
        if single:
            out["sources"][kind]["single_contact"] = _single(src, inv, sens, scene, config, single)
    return {
        "study": "sensitivity map against the model method's recall (six contacts, attenuating guide)",
        "data": "simulated",
        "how": "eval_touch's six-contact scenario (random_contacts seed + 6, >= 4 cm apart, strengths 0.7-1.3), true "
               "optics, model method with default detection (tau 4, n_sigma 1, relative 0.1); the map from each "
               "source's own 100-frame baseline (sensitivity_of on the model method's reconstructor); each true "
               "contact binned by the map at its cell: predicted one-frame matched-filter SNR (true strength / "
               "cell_noise) and margin = true strength / min_strength (>= 1: predicted detectable). Contacts in "
               "[from, to).",
        "scene": "optoskin", "mu_s_per_m": mu_s, "mu_a_per_m": mu_a, "configs": configs, "contacts_per_config": 6,
        "seed": seed, "baseline_frames": baseline_frames,
        "machine": platform.platform(), "cpus": os.cpu_count(), "load_at_end": list(os.getloadavg()),
        **out,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", type=int, default=60, help="six-contact configurations (of eval_touch's 60)")
    ap.add_argument("--mu-s", type=float, default=3.0)
    ap.add_argument("--mu-a", type=float, default=1.0)
    ap.add_argument("--sources", default="own,independent")
    ap.add_argument("--single", type=int, default=40, help="random positions of the single-contact check (0: none)")
    ap.add_argument("--json", default="docs/results/sensitivity_vs_recall.json")
    a = ap.parse_args(argv)
    import tofjax

    tofjax.enable_x64()
    t0 = time.perf_counter()
    load0 = list(os.getloadavg())
    result = run(a.configs, a.mu_s, a.mu_a, a.sources.split(","), single=a.single)
    result["load_at_start"] = load0
    result["seconds"] = time.perf_counter() - t0
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(result, indent=1))
    for k, s in result["sources"].items():
        print(f"{k}: P {100 * s['precision']:.1f}% R {100 * s['recall']:.1f}% (border {100 * s['recall_border']:.1f}%);"
              f" predicted detectable {s['predicted_detectable']['contacts']} contacts, recall "
              f"{s['predicted_detectable']['recall']}; predicted undetectable {s['predicted_undetectable']['contacts']}, "
              f"recall {s['predicted_undetectable']['recall']}; missed {s['missed']} of which "
              f"{s['missed_predicted_undetectable']} predicted undetectable")
        for r in s["recall_by_margin"]:
            print("  margin", r)
        for r in s["recall_by_predicted_snr"]:
            print("  snr", r)
        for r in s.get("single_contact", {}).get("rows", []):
            print("  single", r)
    print(f"wrote {a.json} ({result['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
