"""Cost of the fit method's pair moves (``FitDetectOptions.pair_split``/``pair_swap``), side by side.

Frames of ``experiments/eval_mc_data.py``'s setup (Monte Carlo column by default, exposure 16; simulated), each
searched with the pair moves on and off in one process, alternating which goes first; the detector (and the
responses' Gram matrix) built before the timings. Writes ``--json`` (seconds per frame, contacts found, ratios).

    python experiments/bench_fit_pairs.py --json docs/results/eval_mc_data_greedy4_cost.json
"""

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", required=True)
    ap.add_argument("--column", choices=("own", "monte_carlo"), default="monte_carlo")
    ap.add_argument("--exposure", type=float, default=16.0)
    ap.add_argument("--frames", default="0,5,12,19", help="touch frames (of 12 configs x 2), comma-separated")
    ap.add_argument("--no-touch-frames", type=int, default=2)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--calibration", required=True, help="the column's calibration JSON cached by eval_mc_data.py")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as E

    import tofjax
    from tofjax.invert.correction import OpticalParams
    from tofjax.invert.greedy import FitDetectOptions, build_fit_detector
    from tofjax.outputs import atomic_write_text, check_output
    from tofjax.simulate import expected_counts

    tofjax.enable_x64()
    path = check_output(Path(a.json), overwrite=a.overwrite)
    scene = E.guided_scene()
    contacts = E.contact_configs(scene, 12)
    x = a.exposure
    if a.column == "own":
        base_e = expected_counts(scene, E._own_model_options()) * x
        touch_e = [expected_counts(E.touch_scene(scene, c), E._own_model_options(True)) * x for c in contacts]
    else:
        base_e = np.mean([E.mc_expected(scene, 25_000, s)[0] for s in range(2)], 0) * x
        touch_e = [x * np.mean([E.mc_expected(E.touch_scene(scene, c), 25_000, s)[0] for s in range(2)], 0)
                   for c in contacts]
    _, js = json.loads(Path(a.calibration).read_text())
    optical = OpticalParams.from_calibration(dict(js, converged=True), scene)
    base = E._capture(scene, base_e, 100, 1000, "baseline")
    H = np.concatenate([E._capture(scene, e, 2, 2000 + i, "touch").histograms for i, e in enumerate(touch_e)])
    quiet = E._capture(scene, base_e, a.no_touch_frames, 3000, "no touch").histograms
    det = build_fit_detector(scene, base.mean(), optical, FitDetectOptions(), n_baseline=100)
    on = det.with_options(FitDetectOptions())
    off = det.with_options(dataclasses.replace(FitDetectOptions(), pair_split=False))
    on._gram()  # once per detector, outside the timings
    frames = [("touch", int(i), H[int(i)]) for i in a.frames.split(",")] + [("no touch", j, q) for j, q in enumerate(quiet)]
    rows = []
    for rep in range(a.reps):
        for kind, i, h in frames:
            order = (("on", on), ("off", off)) if (rep + i) % 2 == 0 else (("off", off), ("on", on))
            row = {"kind": kind, "frame": i, "rep": rep}
            for name, d in order:
                t = time.perf_counter()
                out, _ = d.finish_frame(d.search_frame(h), d.options.n_sigma)
                row[name + "_s"] = time.perf_counter() - t
                row[name + "_contacts"] = len(out)
            rows.append(row)
            print(row, flush=True)
    ratio = [r["on_s"] / r["off_s"] for r in rows]
    res = {"what": "seconds per frame of --method fit (search and pruning at n_sigma 6) with the pair moves on and "
                   "off, side by side in one process, alternating order; simulated frames (eval_mc_data.py's setup)",
           "column": a.column, "exposure": x, "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, CPU only, "
           "shared with other sessions (loaded)", "load_average_end": list(os.getloadavg()), "rows": rows,
           "ratio_median": float(np.median(ratio)),
           "ratio_of_sums": sum(r["on_s"] for r in rows) / sum(r["off_s"] for r in rows)}
    atomic_write_text(path, json.dumps(res, indent=1))
    print("ratio median", res["ratio_median"], "of sums", res["ratio_of_sums"])


if __name__ == "__main__":
    main()
