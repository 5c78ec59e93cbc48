"""Subcommands ``tofjax import``, ``tofjax sensor fit`` and ``tofjax range`` (issue 12). Thin."""

from __future__ import annotations

import json
import sys
import warnings

from ..errors import UserError


def _cmd_import(a) -> int:
    from .importer import DroppedFramesWarning, import_file

    with warnings.catch_warnings():  # every dropped frame is named, on stderr (``tofjax.cli.main`` shows it in one line)
        warnings.simplefilter("always", DroppedFramesWarning)
        frames, out = import_file(a.file, a.format, a.out, distance_m=a.distance_m, require_truth=not a.no_truth,
                                  overwrite=a.overwrite)
    d = frames.target_distance_m
    truth = (
        f", target {float(d.min()) * 1e3:.0f}-{float(d.max()) * 1e3:.0f} mm"
        if d is not None and bool((d == d).all())
        else ", no ground truth"
    )
    print(
        f"wrote {out}: {frames.n_frames} frames, {frames.histograms.shape[1]} zones ({frames.grid[0]}x{frames.grid[1]}) x "
        f"{frames.histograms.shape[2]} bins{', reference channel' if frames.reference is not None else ''}{truth}"
        f"{f'; {len(frames.dropped)} frames dropped' if frames.dropped else ''}"
    )
    return 0


def _capture_one_sensor(path):
    import numpy as np

    from ..capture import read_capture
    from .response import SensorModelError

    cap = read_capture(path)
    if cap.histograms.shape[1] != 1:
        raise SensorModelError(f"{path}: {cap.histograms.shape[1]} sensors; the sensor commands take captures of one sensor")
    ref = None if cap.reference is None else cap.reference[:, 0]
    if ref is not None and np.isnan(ref).all():
        ref = None
    return cap, cap.histograms[:, 0], ref


def _cmd_sensor_fit(a) -> int:
    import numpy as np

    from .fit import SensorFitOptions, fit_sensor
    from .importer import DroppedFramesWarning
    from .response import SensorModelError

    if a.no_shape_drift and a.drift_order is not None:
        raise UserError("--drift-order: the order of the shape drift, which --no-shape-drift leaves out")
    cap, hist, ref = _capture_one_sensor(a.capture)
    if cap.target_distance_m is None:
        raise SensorModelError(f"{a.capture}: no truth/target_distance_m: a sensor fit needs captures of a target at known distances")
    opts = SensorFitOptions(
        min_distance_m=a.min_distance_m, max_distance_m=a.max_distance_m, knots_per_bin=a.knots_per_bin,
        max_iterations=a.max_iterations, pile_up=not a.no_pile_up, shape_drift=not a.no_shape_drift, echo=not a.no_echo,
        drift_order=2 if a.drift_order is None else a.drift_order,
    )
    grid = cap.scene.sensor.grid
    with warnings.catch_warnings():  # saturated frames left out: named on stderr
        warnings.simplefilter("always", DroppedFramesWarning)
        model, details = fit_sensor(hist, cap.target_distance_m, opts, reference=None if a.no_reference else ref,
                                    grid=tuple(grid) if grid else None, progress=(lambda m: print("  " + m)) if a.verbose else None)
    model.save(a.out)
    r = model.report
    print(f"bin width        {r['bin_width_s'] * 1e12:.2f} +- {r['bin_width_se_s'] * 1e12:.2f} ps (pulse fit, centre zone)")
    print(
        f"  peak-time line {r['bin_width_from_peak_line_s'] * 1e12:.2f} +- {r['bin_width_from_peak_line_se_s'] * 1e12:.2f} ps "
        f"over {r['line_distances_m'][0] * 1e3:.0f}-{r['line_distances_m'][1] * 1e3:.0f} mm: "
        f"difference {100 * r['bin_width_relative_difference']:+.2f}%"
    )
    c = r["centre_zone"]
    print(f"zero range       {r['zero_range_s'][c] * 1e12:.1f} +- {r['zero_range_se_s'][c] * 1e12:.1f} ps after bin 0 (centre zone)")
    if r["pulses_per_histogram"][0] is not None:
        print(f"pile-up          {np.median(r['pulses_per_histogram']):.3g} effective laser pulses per histogram (median over zones)")
    print(f"reduced chi2     median {r['median_reduced_chi2']:.2f} over {len(r['frames'])} frames "
          f"({min(r['distances_m']) * 1e3:.0f}-{max(r['distances_m']) * 1e3:.0f} mm), per zone "
          + " ".join(f"{v:.1f}" for v in r["zone_median_reduced_chi2"]))
    n = r["parameters"]
    print(f"parameters       {n['shared_total']} shared by every capture ({n['shared_per_zone_total']} per zone), "
          f"{n['per_capture_total']} per capture ({n['per_capture_per_zone']} per zone)")
    if r["reference_median_reduced_chi2"] is not None:
        print(f"reference        its own pulse, median reduced chi2 {r['reference_median_reduced_chi2']:.2f}")
    if a.plots:
        from .plots import plot_sensor_fit

        paths = plot_sensor_fit(model, details, a.plots)
        print(f"wrote {len(paths)} figures to {a.plots}/")
    print(f"wrote {a.out}")
    if not r.get("converged", True):
        # written (the fit's state is worth keeping), but never silently: `range` and `simulate` would trust it
        print(f"tofjax sensor fit: warning: the fit did not converge in --max-iterations {a.max_iterations} "
              f"(report.converged = false in {a.out}); raise --max-iterations before ranging with it", file=sys.stderr)
    return 0


def _cmd_range(a) -> int:
    import numpy as np

    from .ranging import range_histograms, ranges_to_json
    from .response import load_sensor_model

    cap, hist, _ = _capture_one_sensor(a.capture)
    model = load_sensor_model(a.sensor)
    res = range_histograms(model, hist)
    out = ranges_to_json(res)
    out["sensor_model"] = str(a.sensor)
    out["capture"] = str(a.capture)
    c = model.report.get("centre_zone", (model.n_zones) // 2)
    if cap.target_distance_m is not None and np.isfinite(cap.target_distance_m).all():
        err = res["distance_m"][:, c] - cap.target_distance_m
        summary = {"centre_zone": c, "mean_error_m": float(err.mean()), "std_error_m": float(err.std())}
        if cap.onchip_distance_m is not None:
            oe = cap.onchip_distance_m[:, 0, c] - cap.target_distance_m
            summary["onchip_std_error_m"] = float(np.nanstd(oe))
            summary["onchip_mean_error_m"] = float(np.nanmean(oe))
        out["against_truth"] = summary
        line = f"centre zone against truth: std {summary['std_error_m'] * 1e3:.2f} mm after removing {summary['mean_error_m'] * 1e3:+.2f} mm"
        if "onchip_std_error_m" in summary:
            line += f" (on-chip: std {summary['onchip_std_error_m'] * 1e3:.2f} mm)"
        print(line)
    if a.json:
        from ..outputs import atomic_write_text  # makes the folder, writes whole or not at all

        atomic_write_text(a.json, json.dumps(out, indent=1))
        print(f"wrote {a.json}: {hist.shape[0]} frames x {hist.shape[1]} zones")
    else:
        for f in out["frames"][:10]:
            print(f"frame {f['index']}: " + " ".join(f"{z['distance_m'] * 1e3:.1f}+-{z['stderr_m'] * 1e3:.2f}" for z in f["zones"]) + " mm")
    return 0


def register(sub) -> None:
    from .importer import FORMATS

    s = sub.add_parser("import", help="import a real TMF882x recording (JSON sweep or Arduino serial log) into a capture")
    s.add_argument("file", help="recording to read")
    s.add_argument("--format", required=True, choices=FORMATS, help="tmf882x-json (plane sweep JSON) or tmf882x-log (Arduino serial log)")
    s.add_argument("--out", required=True, help="output capture (.h5)")
    s.add_argument("--distance-m", type=float, default=None, help="ground-truth target distance of every frame of a log")
    s.add_argument("--no-truth", action="store_true", help="import JSON frames without dist_to_plane too (no ground truth)")
    s.set_defaults(func=_cmd_import)

    s = sub.add_parser("sensor", help="sensor model from real histograms: `tofjax sensor fit`")
    ss = s.add_subparsers(dest="sensor_command", metavar="SUBCOMMAND")
    ss.required = True
    f = ss.add_parser("fit", help="fit bin width, zero-range offset, pulse, pile-up and zone gains to a target at known distances")
    f.add_argument("capture", help="capture with truth/target_distance_m (from `tofjax import`)")
    f.add_argument("--out", required=True, help="output sensor model (.json)")
    f.add_argument("--plots", help="folder for residual plots")
    f.add_argument("--min-distance-m", type=float, default=0.04)
    f.add_argument("--max-distance-m", type=float, default=0.40)
    f.add_argument("--knots-per-bin", type=int, default=4, help="knots of the learned pulse per bin (default 4)")
    f.add_argument("--max-iterations", type=int, default=40)
    f.add_argument("--no-pile-up", action="store_true", help="leave pile-up out of the model")
    f.add_argument("--no-echo", action="store_true", help="leave the double-bounce echo out of the model")
    f.add_argument("--no-shape-drift", action="store_true",
                   help="a fixed pulse shape (median reduced chi2 ~5 on the TMF8820 sweep instead of below 2 with the "
                   "default second-order drift; fits faster)")
    f.add_argument("--drift-order", type=int, default=None, choices=(1, 2, 3),
                   help="order of the pulse's change of shape with distance (default 2; not with --no-shape-drift)")
    f.add_argument("--no-reference", action="store_true", help="do not fit the reference channel's pulse")
    f.add_argument("-v", "--verbose", action="store_true")
    f.set_defaults(func=_cmd_sensor_fit)

    s = sub.add_parser("range", help="distance per zone and frame from a fitted sensor model")
    s.add_argument("capture", help="capture of one TMF882x")
    s.add_argument("--sensor", required=True, help="sensor model from `tofjax sensor fit`")
    s.add_argument("--json", help="output JSON: {frames: [{index, zones: [{distance_m, stderr_m}]}]}")
    s.set_defaults(func=_cmd_range)
