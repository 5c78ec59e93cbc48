"""Study: the TMF882x sensor model on the real TMF8820 plane sweep (issue 12).

Real data (80 captures of a flat plane at 5-400 mm, `../shared/data/tmf8820-plane-sweep/`):

1. **Held-out ranging.** Fit the sensor model on every other distance of 40-400 mm (even
   frames) and range the others (odd frames, never seen by the fit). Centre zone: the
   standard deviation of (range - truth) after removing one constant offset, against the
   sensor's own on-chip distance on the same frames, treated the same way. Also per zone.
2. **One model for every capture.** Fit on all frames of 40-400 mm: the median reduced
   chi-square (Pearson, Poisson weights, all 9 zones x 128 bins per frame), per zone, and
   per frame; the bin width from the pulse fit and from a straight line through the raw
   peak times (100-400 mm), with standard errors.

Writes the figures and both sensor models to ``--out`` (default ``out/study_sensor``) and the
figures' numbers to ``--json`` (default ``docs/results/sensor_study.json``; ``--overwrite`` to
replace it)::

    python experiments/study_sensor.py --data ../shared/data/tmf8820-plane-sweep/captures.json --overwrite
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="../shared/data/tmf8820-plane-sweep/captures.json")
    p.add_argument("--out", default="out/study_sensor")
    p.add_argument("--json", default="docs/results/sensor_study.json", help="the results (JSON)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json")
    p.add_argument("--knots-per-bin", type=int, default=4)
    p.add_argument("--drift-order", type=int, default=2, help="order of the pulse's shape drift (default 2)")
    p.add_argument("--max-iterations", type=int, default=40)
    p.add_argument("--skip-full", action="store_true", help="only the held-out part")
    p.add_argument("--no-drift", action="store_true", help="a fixed pulse shape (no first-order change with position)")
    p.add_argument("--no-echo", action="store_true", help="no double-bounce echo")
    a = p.parse_args(argv)

    import jax

    import tofjax
    from tofjax.sensor import SensorFitOptions, fit_sensor, range_histograms, read_tmf882x_json
    from tofjax.sensor.plots import plot_sensor_fit

    from tofjax.outputs import atomic_write_text, check_output

    tofjax.enable_x64()
    check_output(a.json, overwrite=a.overwrite, inputs=[a.data], flag="--json")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    fr = read_tmf882x_json(a.data)
    H, D = fr.histograms, fr.target_distance_m
    onchip = fr.onchip_distance_m
    opts = SensorFitOptions(knots_per_bin=a.knots_per_bin, max_iterations=a.max_iterations, shape_drift=not a.no_drift,
                            drift_order=a.drift_order, echo=not a.no_echo)
    sel = np.flatnonzero((D >= 0.04 - 1e-9) & (D <= 0.40 + 1e-9))
    train, test = sel[::2], sel[1::2]
    result = {
        "data": str(a.data),
        "data_kind": "real (TMF8820 plane sweep, MIT licence)",
        "machine": f"{platform.machine()} {platform.system()}, 2-core shared VM (loaded by other jobs), CPU only; jax {jax.__version__}",
        "options": {k: getattr(opts, k) for k in opts.__dataclass_fields__},
    }

    t = time.perf_counter()
    model, details = fit_sensor(H[train], D[train], opts, reference=fr.reference[train], grid=fr.grid, progress=print)
    fit_s = time.perf_counter() - t
    t = time.perf_counter()
    rng = range_histograms(model, H[test])
    range_s = time.perf_counter() - t
    c = model.report["centre_zone"]
    err = rng["distance_m"] - D[test][:, None]
    oerr = onchip[test] - D[test][:, None]
    per_zone = []
    for z in range(H.shape[1]):
        o = oerr[:, z]
        per_zone.append({
            "zone": z,
            "range_std_m": float(np.std(err[:, z])),
            "range_offset_m": float(np.mean(err[:, z])),
            "onchip_std_m": float(np.nanstd(o)),
            "onchip_valid_frames": int(np.isfinite(o).sum()),
            "median_stderr_m": float(np.median(rng["stderr_m"][:, z])),
            "median_reduced_chi2": float(np.median(rng["reduced_chi2"][:, z])),
        })
    result["held_out"] = {
        "train_distances_m": D[train].tolist(),
        "test_distances_m": D[test].tolist(),
        "fit_seconds": fit_s,
        "range_seconds": range_s,
        "centre_zone": c,
        "centre_range_std_m": per_zone[c]["range_std_m"],
        "centre_onchip_std_m": per_zone[c]["onchip_std_m"],
        "centre_range_errors_m": (err[:, c] - err[:, c].mean()).tolist(),
        "centre_onchip_errors_m": (oerr[:, c] - np.nanmean(oerr[:, c])).tolist(),
        "test_median_reduced_chi2_all_zones": float(np.median(rng["reduced_chi2"])),
        "train_median_reduced_chi2": model.report["median_reduced_chi2"],
        "per_zone": per_zone,
        "bin_width_s": model.bin_width_s,
        "bin_width_se_s": model.report["bin_width_se_s"],
    }
    print(f"held out: centre zone range std {per_zone[c]['range_std_m'] * 1e3:.3f} mm, on-chip {per_zone[c]['onchip_std_m'] * 1e3:.3f} mm")
    model.save(out / "sensor_heldout.json")
    _plot_heldout(result["held_out"], D[test], out / "sensor_range_heldout.png")

    if not a.skip_full:
        t = time.perf_counter()
        full, fdet = fit_sensor(H[sel], D[sel], opts, reference=fr.reference[sel], grid=fr.grid, progress=print)
        r = full.report
        result["full"] = {
            "fit_seconds": time.perf_counter() - t,
            "frames": len(sel),
            "median_reduced_chi2": r["median_reduced_chi2"],
            "zone_median_reduced_chi2": r["zone_median_reduced_chi2"],
            "frame_reduced_chi2": r["frame_reduced_chi2"],
            "distances_m": r["distances_m"],
            "fraction_frames_chi2_le_2": float(np.mean(np.asarray(r["frame_reduced_chi2"]) <= 2)),
            "bin_width_s": r["bin_width_s"],
            "bin_width_se_s": r["bin_width_se_s"],
            "bin_width_from_peak_line_s": r["bin_width_from_peak_line_s"],
            "bin_width_from_peak_line_se_s": r["bin_width_from_peak_line_se_s"],
            "bin_width_relative_difference": r["bin_width_relative_difference"],
            "bin_width_from_pulse_origin_s": r.get("bin_width_from_pulse_origin_s"),
            "zero_range_s": r["zero_range_s"],
            "pulses_per_histogram": r["pulses_per_histogram"],
            "path_scale": r["path_scale"],
            "reference_median_reduced_chi2": r["reference_median_reduced_chi2"],
            "median_reduced_chi2_40_95mm": float(np.median(np.asarray(r["frame_reduced_chi2"])[np.asarray(r["distances_m"]) < 0.0955])),
            "median_reduced_chi2_100_400mm": float(np.median(np.asarray(r["frame_reduced_chi2"])[np.asarray(r["distances_m"]) > 0.0955])),
            "parameters": r["parameters"],
        }
        full.save(out / "sensor.json")
        plot_sensor_fit(full, fdet, out)
        print(f"full: median reduced chi2 {r['median_reduced_chi2']:.2f}; bin width {r['bin_width_s'] * 1e12:.2f} +- "
              f"{r['bin_width_se_s'] * 1e12:.2f} ps, peak line {r['bin_width_from_peak_line_s'] * 1e12:.2f} ps")
    atomic_write_text(a.json, json.dumps(result, indent=1))
    print(f"wrote {a.json}")
    return result


def _plot_heldout(h, d_test, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(np.asarray(d_test) * 1e3, np.asarray(h["centre_onchip_errors_m"]) * 1e3, "s", ms=4, mfc="none",
            label=f"on-chip (std {h['centre_onchip_std_m'] * 1e3:.2f} mm)")
    ax.plot(np.asarray(d_test) * 1e3, np.asarray(h["centre_range_errors_m"]) * 1e3, "o", ms=4,
            label=f"tofjax range (std {h['centre_range_std_m'] * 1e3:.2f} mm)")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("target distance (mm), held-out frames")
    ax.set_ylabel("error - mean error (mm)")
    ax.set_title("centre zone, real TMF8820, model fitted on the other distances", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    from tofjax.outputs import save_figure

    save_figure(fig, path)


if __name__ == "__main__":
    main()
