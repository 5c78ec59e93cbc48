"""What the fit method's false detections are (issue 14): read ``eval_mc_data.py`` results and report, per
detection column, precision and recall per result and pooled over them with their 95% intervals (Wilson's, for a
binomial share: how far a set of a few hundred contacts pins a precision), the matched and false detections' Laplace
position standard errors and share at the strength cap, how many false ones share their frame with a missed contact
(and how far it is), and precision / recall when detections above a standard error are dropped. Writes JSON.
**Simulated** (whatever the results were).

    python experiments/false_detections.py RESULT.json [RESULT.json ...] --out docs/results/false_detections.json
        [--method fit:model_error_0.2]   # a variant of the fit method the results hold (default: fit)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

#: position standard errors (cm) above which detections are dropped in the trade-off
THRESHOLDS_CM = (2.0, 1.0, 0.5, 0.3)


def _sd_cm(det) -> float:
    return 100.0 * float(np.hypot(det[4], det[5]))  # [x, y, strength, matched, x_stderr, y_stderr]


def share(k: int, n: int) -> dict:
    """``k`` of ``n`` as a share with its 95% Wilson interval (None for ``n = 0``)."""
    from scipy.stats import binomtest

    if n == 0:
        return {"value": None, "k": 0, "n": 0, "interval95": None}
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return {"value": k / n, "k": k, "n": n, "interval95": [float(ci.low), float(ci.high)]}


def _rates(matched: int, false: int, contacts: int) -> dict:
    """Precision (matched of all detections) and recall (matched of the contacts; a contact is matched at most once)."""
    return {"precision": share(matched, matched + false), "recall": share(matched, contacts)}


def summarize(results: list[dict], cap: float = 0.99, method: str = "fit") -> dict:
    out: dict = {}
    for res in results:
        for col, c in res["detection"].items():
            m = c["methods"][method]
            frames = m["false_detections"]["frames"]
            acc = out.setdefault(col, {"contacts": 0, "matched": [], "false": [], "false_with_missed": [],
                                       "false_missed_distance_cm": [], "per_result": []})
            acc["contacts"] += m["contacts"]
            before = len(acc["matched"]), len(acc["false"])
            for fr in frames:
                for d in fr["detections"]:
                    (acc["matched"] if d[3] else acc["false"]).append(d)
                    if not d[3] and fr["missed"]:
                        acc["false_with_missed"].append(d)
                        acc["false_missed_distance_cm"].append(
                            100.0 * min(float(np.hypot(d[0] - x, d[1] - y)) for x, y in fr["missed"]))
            acc["per_result"].append(_rates(len(acc["matched"]) - before[0], len(acc["false"]) - before[1], m["contacts"]))
    report = {}
    for col, a in out.items():
        dets = a["matched"] + a["false"]
        trade = {}
        for t in (None,) + THRESHOLDS_CM:
            keep = [d for d in dets if t is None or _sd_cm(d) <= t]
            tp = sum(bool(d[3]) for d in keep)
            trade["all" if t is None else f"<= {t:g} cm"] = {"precision": tp / max(len(keep), 1),
                                                               "recall": tp / max(a["contacts"], 1)}
        report[col] = {
            "contacts": a["contacts"], "matched": len(a["matched"]), "false": len(a["false"]),
            "pooled": _rates(len(a["matched"]), len(a["false"]), a["contacts"]), "per_result": a["per_result"],
            "stderr_cm_median_matched": float(np.median([_sd_cm(d) for d in a["matched"]])) if a["matched"] else None,
            "stderr_cm_median_false": float(np.median([_sd_cm(d) for d in a["false"]])) if a["false"] else None,
            "at_strength_cap_matched": float(np.mean([d[2] >= cap for d in a["matched"]])) if a["matched"] else None,
            "at_strength_cap_false": float(np.mean([d[2] >= cap for d in a["false"]])) if a["false"] else None,
            "false_sharing_a_frame_with_a_missed_contact": len(a["false_with_missed"]),
            "their_distance_to_it_cm_median": (float(np.median(a["false_missed_distance_cm"]))
                                               if a["false_missed_distance_cm"] else None),
            "dropping_by_stderr": trade,
        }
    return report


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", nargs="+", help="eval_mc_data.py result JSONs (pooled)")
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--method", default="fit", help="the detection method or fit variant to read (default: fit; e.g. "
                    "fit_n_sigma_6.5, fit:model_error_0.2, as eval_mc_data.py names them)")
    a = ap.parse_args(argv)
    try:
        results = [json.loads(Path(p).read_text()) for p in a.results]
        report = summarize(results, method=a.method)
    except (OSError, ValueError, KeyError, TypeError, IndexError) as e:
        ap.error(f"cannot read the results: {e}")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tofjax.outputs import atomic_write_text

    atomic_write_text(Path(a.out), json.dumps({"results": a.results, "method": a.method, "columns": report}, indent=1),
                      overwrite=True)
    for col, r in report.items():
        pr, rc = r["pooled"]["precision"], r["pooled"]["recall"]
        print(f"{col}: pooled precision {pr['value']:.3f} (95% {pr['interval95'][0]:.3f}-{pr['interval95'][1]:.3f}), "
              f"recall {rc['value']:.3f} (95% {rc['interval95'][0]:.3f}-{rc['interval95'][1]:.3f}) over "
              f"{len(r['per_result'])} results" if pr["value"] is not None and rc["value"] is not None else f"{col}: no detections")
        print(col, json.dumps({k: v for k, v in r.items() if k not in ("dropping_by_stderr", "per_result", "pooled")}),
              json.dumps(r["dropping_by_stderr"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
