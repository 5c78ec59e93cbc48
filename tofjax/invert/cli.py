"""``tofjax process`` and ``tofjax detect``: thin wrappers over :mod:`tofjax.invert.pipeline`.

Without ``--calibration`` the scene's stated optics are used and a warning says so
(simulated captures carry the truth in their scene; a real device needs a calibration).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
import warnings
from pathlib import Path

__all__ = ["register"]


@contextlib.contextmanager
def _printed_warnings(command: str):
    """Warnings raised inside (no calibration, scene notes) printed as one stderr line each, after the block."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        print(f"tofjax {command}: warning: {type(w.message).__name__}: {w.message}", file=sys.stderr)


def _options(a):
    from .correction import InversionError
    from .detect import DetectOptions
    from .maps import MapOptions
    from .pipeline import InvertOptions
    from .reconstruct import ReconstructOptions

    if a.method == "fit":
        return _fit_options(a)
    model = a.method == "model"
    # Reject what the chosen method would ignore instead of dropping it silently.
    for flag, given in (("--model-error", a.model_error), ("--max-strength", a.max_strength)):
        if given is not None:
            raise InversionError(f"{flag} applies to --method fit only")
    if a.dynamic_baseline and a.method not in ("baseline", "full"):
        raise InversionError(f"--dynamic-baseline works with --method baseline or full, not {a.method}")
    if model and a.no_cfar:
        raise InversionError("--no-cfar applies to back-projection, not --method model")
    if not model and a.min_strength is not None:
        raise InversionError("--min-strength applies to --method model only")
    if not model and a.contact_response is not None:
        raise InversionError("--contact-response applies to --method model only")
    detect, rec = DetectOptions(), ReconstructOptions()
    if model:
        changes = {"n_sigma": a.n_sigma, "relative": a.relative, "min_strength": a.min_strength,
                   "response": a.contact_response}
        rec = dataclasses.replace(rec, **{k: v for k, v in changes.items() if v is not None})
    else:
        changes = {"n_sigma": a.n_sigma, "relative": a.relative, "cfar": not a.no_cfar}
        detect = dataclasses.replace(detect, **{k: v for k, v in changes.items() if v is not None})
    return InvertOptions(
        method=a.method,
        maps=MapOptions(resolution_m=a.resolution_mm / 1000.0),
        detect=detect,
        reconstruct=rec,
    )


def _fit_options(a):
    """``--method fit``: the greedy contact fit's options (what it would ignore is refused)."""
    from .correction import InversionError
    from .greedy import FitDetectOptions

    for flag, given in (("--dynamic-baseline", a.dynamic_baseline), ("--no-cfar", a.no_cfar),
                        ("--relative", a.relative is not None), ("--contact-response", a.contact_response is not None)):
        if given:
            raise InversionError(f"{flag} does not apply to --method fit")
    changes = {"n_sigma": a.n_sigma, "min_strength": a.min_strength, "model_error": a.model_error,
               "max_strength": a.max_strength}
    return FitDetectOptions(**{k: v for k, v in changes.items() if v is not None})


def _run(a, *, want_detect: bool):
    from .pipeline import build_inverter, load_inputs

    options = _options(a)  # option errors first, before any reading
    with _printed_warnings(a.command):
        touch, base, optical = load_inputs(
            a.touch,
            a.baseline,
            a.calibration,
            allow_unconverged=a.allow_unconverged_calibration,
            allow_other_scene=a.allow_other_scene_calibration,
            sensor_path=a.sensor,
        )
    if a.method in ("model", "fit"):
        print(
            f"tofjax {a.command}: building the model-based {'reconstruction' if a.method == 'model' else 'contact fit'} "
            "(the forward model's response at every cell; tens of seconds) ...",
            file=sys.stderr,
            flush=True,
        )
    if a.method == "fit":
        from .greedy import build_fit_detector

        inv = build_fit_detector(base.scene, base.mean(), optical, options, n_baseline=base.n_frames)
        res = inv.process(touch.histograms, detect=True)
        return touch, base, optical, inv, _flag_bad(a, res)
    inv = build_inverter(
        base.scene, base.mean(), options, optical, n_baseline=base.n_frames, baseline_frames=base.histograms
    )
    if a.dynamic_baseline:
        from .baseline import run_dynamic
        from .pipeline import ProcessResult

        dyn = run_dynamic(inv, touch.histograms)
        res = ProcessResult(dyn.maps, dyn.ok, inv.grid, a.method, dyn.detections(inv), dyn.noise[-1])
        print(
            f"tofjax {a.command}: dynamic baseline: {int(dyn.no_touch.sum())} of {len(dyn.ok)} frames classified "
            "no-touch updated it",
            file=sys.stderr,
        )
    else:
        res = inv.process(touch.histograms, detect=want_detect or bool(getattr(a, "png", None)))
    return touch, base, optical, inv, _flag_bad(a, res)


def _flag_bad(a, res):
    bad = int((~res.ok).sum())
    if bad:
        print(
            f"tofjax {a.command}: warning: {bad} of {len(res.ok)} frames have NaN or saturated bins; "
            "flagged (ok = false) and left out",
            file=sys.stderr,
        )
    return res


def _cmd_process(a) -> int:
    from .pipeline import write_maps

    from ..outputs import atomic_path

    touch, base, optical, inv, res = _run(a, want_detect=True)
    with atomic_path(a.out) as tmp:
        write_maps(tmp, res, base.scene, optical)
        import h5py

        with h5py.File(tmp, "a") as f:  # which capture frame each map is, and the frames left out
            if touch.frame_index is not None:
                f["frame_index"] = touch.frame_index
            f.attrs["dropped_frames"] = json.dumps({str(i): why for i, why in touch.dropped.items()})
    msg = f"wrote {a.out}: {len(res.maps)} maps of {inv.grid.ny} x {inv.grid.nx} px ({a.method})"
    if a.png:
        from .plots import plot_map

        for i, (m, det) in enumerate(zip(res.maps, res.detections)):
            plot_map(
                m,
                inv.grid,
                touch.scene,
                Path(a.png) / f"map_{i:04d}.png",
                detection=det,
                title=f"frame {i}, {a.method}",
            )
        msg += f"; PNGs in {a.png}/"
    print(msg)
    return 0


def _cmd_detect(a) -> int:
    touch, base, optical, inv, res = _run(a, want_detect=True)
    from ..outputs import atomic_write_text

    data = _with_frame_flags(res.touches_json(), touch, res)
    atomic_write_text(a.json, json.dumps(data, indent=1))
    n = sum(len(f["touches"]) for f in data["frames"])
    print(f"wrote {a.json}: {n} touches in {len(data['frames'])} frames ({a.method})")
    for f in data["frames"][:10]:
        pts = ", ".join(f"({t['x_m'] * 100:.1f}, {t['y_m'] * 100:.1f}) cm s={t['strength']:.2f}" for t in f["touches"])
        print(f"  frame {f['index']}: {pts or 'no touch'}")
    return 0


def _with_frame_flags(data: dict, touch, res) -> dict:
    """Per frame: its index in the capture file, ``ok`` and, if not ok, the reason; frames the
    reader dropped (impossible counts) are listed too, so no frame disappears silently."""
    idx = touch.frame_index if touch.frame_index is not None else range(len(data["frames"]))
    frames = []
    for f, i, ok in zip(data["frames"], idx, res.ok):
        f = {"index": int(i), "ok": bool(ok), **({} if ok else {"reason": "NaN or saturated bins"}),
             "touches": f["touches"]}
        frames.append(f)
    for i, why in touch.dropped.items():
        frames.append({"index": int(i), "ok": False, "reason": why, "touches": []})
    data["frames"] = sorted(frames, key=lambda f: f["index"])
    return data


def _optics_arguments(s):
    """The calibration and sensor-model options every reader of a calibration takes (process, detect, sensitivity)."""
    s.add_argument(
        "--calibration", help="calibration JSON from `tofjax calibrate` (default: the scene's optics, with a warning)"
    )
    s.add_argument(
        "--allow-unconverged-calibration",
        action="store_true",
        help="use a calibration that did not converge or was refused (at your own risk)",
    )
    s.add_argument(
        "--allow-other-scene-calibration",
        action="store_true",
        help="use a calibration whose scene fingerprint differs from the baseline's scene",
    )
    s.add_argument(
        "--sensor",
        help="sensor model from `tofjax sensor fit` (its bin width replaces the nominal one; pass the same "
        "model as to `tofjax calibrate --sensor`)",
    )


def _common(s):
    from .pipeline import ALL_METHODS
    from .reconstruct import RESPONSES

    s.add_argument("touch", help="touch capture (.h5)")
    s.add_argument("--baseline", required=True, help="no-touch baseline capture of the same setup (.h5)")
    _optics_arguments(s)
    s.add_argument(
        "--method",
        choices=(*ALL_METHODS, "fit"),
        default="full",
        help="correction (default full: Algorithm 1); 'model': grid reconstruction; 'fit': contacts fitted one by one "
        "(positions and strengths through the model; needs a guided-optics calibration)",
    )
    s.add_argument("--resolution-mm", type=float, default=2.5, help="map pixel size in mm (default 2.5)")
    s.add_argument(
        "--n-sigma",
        type=float,
        help="detection threshold in noise standard deviations: of the no-touch map at each pixel "
        "(back-projection, default 7), of each cell's strength (--method model, default 1) or of each fitted "
        "contact's chi-square drop, sqrt (--method fit, default 6)",
    )
    s.add_argument(
        "--relative",
        type=float,
        help="also require this fraction of the frame's maximum (default 0.2; --method model: 0.1)",
    )
    s.add_argument(
        "--no-cfar",
        action="store_true",
        help="back-projection: compare the map with n-sigma times the linear Poisson noise instead of "
        "normalising it by the measured no-touch floor (constant false-alarm rate, the default)",
    )
    s.add_argument(
        "--min-strength",
        type=float,
        help="--method model: also require this summed strength, in the forward model's units; --method fit: this "
        "fitted coupling strength, 0-1 (default: none)",
    )
    s.add_argument(
        "--contact-response",
        choices=RESPONSES,
        help="--method model: the contact's response the fit explains frames with: 'added' (the light a contact "
        "adds, its shadow a separate occupancy), 'signed' (added and removed light of a contact, one strength: "
        "contacts that mostly shadow, such as skin) or 'auto' (default: signed with a guided-optics calibration, "
        "added otherwise)",
    )
    s.add_argument(
        "--model-error",
        type=float,
        help="--method fit: the forward model's relative error of a contact's signal, counted as noise when pruning "
        "(each bin's variance plus (model-error x the fitted contacts' change)^2): fewer ghosts explaining what the "
        "model gets wrong of strong contacts, at long exposures where that exceeds photon noise (default 0.2; 0: photon "
        "noise only)",
    )
    s.add_argument(
        "--max-strength",
        type=float,
        help="--method fit: the largest fitted strength, in units of the skin model's coupling (default 1; above 1: "
        "contacts that couple more, up to full optical contact at 1 / coupling)",
    )
    s.add_argument(
        "--dynamic-baseline",
        action="store_true",
        help="update the baseline online from frames classified no-touch (slow drift; frames in order)",
    )


def _cmd_sensitivity(a) -> int:
    """``tofjax sensitivity``: where a contact of ``--strength`` is detectable (model or fit method), JSON and PNG."""
    from ..capture import read_capture
    from ..outputs import atomic_write_text
    from ..config import ConfigError
    from ..scene import load_scene
    from .correction import check_compatible
    from .pipeline import load_optics
    from .plots import plot_position_bound, plot_sensitivity
    from .sensitivity import SensitivityOptions, fit_sensitivity, sensitivity

    changes = {"n_sigma": a.n_sigma, "response": a.contact_response, "match_radius_m": a.match_radius_m}
    if a.position and a.method != "fit":
        raise ConfigError("--position: the position bound is the contact fit's map (add --method fit)")
    fit = None
    if a.cell_m is not None:
        import math

        from .greedy import FitDetectOptions

        if a.method != "fit":
            raise ConfigError("--cell-m: only the fit method's map has its own grid (add --method fit); the model "
                              "method's grid is its reconstruction's, as detect builds it")
        if not (math.isfinite(a.cell_m) and 0.0 < a.cell_m <= 0.05):
            raise ConfigError(f"--cell-m: must be a grid cell in (0, 0.05] m, got {a.cell_m!r}")
        fit = FitDetectOptions(cell_m=a.cell_m)
    options = SensitivityOptions(strength=a.strength, frames=a.frames, position=a.position,
                                 **{k: v for k, v in changes.items() if v is not None})
    scene = load_scene(a.scene).require_waveguide("tofjax sensitivity", a.scene).without_touches()
    base = read_capture(a.baseline)
    check_compatible(scene, base.scene, what="baseline", other="scene")
    if a.sensor is not None:
        scene = scene.with_sensor_model(a.sensor)
    with _printed_warnings(a.command):
        optical = load_optics(scene, a.calibration, allow_unconverged=a.allow_unconverged_calibration,
                              allow_other_scene=a.allow_other_scene_calibration)
    what = "model-based reconstruction's" if a.method == "model" else "contact fit's"
    print(f"tofjax {a.command}: building the {what} noise (the forward model's response at every cell; tens of "
          "seconds) ...", file=sys.stderr, flush=True)
    if a.method == "fit":
        res = fit_sensitivity(scene, base.mean(), optical, options, fit, n_baseline=base.n_frames,
                              progress=a.position)
    else:
        res = sensitivity(scene, base.mean(), optical, options, n_baseline=base.n_frames)
    out = Path(a.out)
    data = res.to_json()
    data["inputs"] = {"scene": str(a.scene), "baseline": str(a.baseline), "baseline_frames": base.n_frames,
                      "optics_source": optical.source}
    atomic_write_text(out / "sensitivity.json", json.dumps(data, indent=1))
    plot_sensitivity(res, out / "sensitivity.png")
    if res.position_sd is not None:
        plot_position_bound(res, out / "position.png")
    s = data["summary"]
    one, many, sure = s["detectable_one_frame"], s["detectable_with_frames"], s["detectable_one_frame_with_margin_2"]

    def pct(v):
        return "-" if v is None else f"{100 * v:.0f}%"

    print(f"wrote {out}/sensitivity.json and sensitivity.png: strength {a.strength:g} detectable on "
          f"{pct(one['all'])} of the sensed area in one frame (border {pct(one['border'])}, interior "
          f"{pct(one['interior'])}), with a 2x margin on {pct(sure['all'])}"
          + (f", {pct(many['all'])} with {a.frames} frames summed" if a.frames > 1 else "")
          + f"; frames needed, median {s['frames_needed_quantiles_10_50_90'][1]:.0f}, most "
            f"{s['frames_needed_max']:.0f}")
    if res.position_sd is not None:
        pl = s["placed_within_match_radius"]
        print(f"wrote {out}/position.png: a lone contact of strength {a.strength:g} is placed within "
              f"{100 * options.match_radius_m:g} cm with probability {pct(pl['all'])} on average (border "
              f"{pct(pl['border'])}, interior {pct(pl['interior'])}) at its position bound, {a.frames} frame(s)")
    return 0


def register(sub) -> None:
    s = sub.add_parser("process", help="correct touch histograms and write tactile maps (seed 000 Alg. 1, Eq. 8)")
    _common(s)
    s.add_argument("--out", required=True, help="output maps (.h5)")
    s.add_argument("--png", help="folder for one PNG per frame")
    s.set_defaults(func=_cmd_process)

    s = sub.add_parser("detect", help="detect touches (positions, strengths) and write them as JSON")
    _common(s)
    s.add_argument("--json", required=True, help="output JSON: {frames: [{index, touches: [{x_m, y_m, strength}]}]}; --method fit "
                   "adds each contact's standard errors (x_stderr_m, y_stderr_m, strength_stderr)")
    s.set_defaults(func=_cmd_detect)

    s = sub.add_parser(
        "sensitivity",
        help="where on the skin a contact is detectable (model or fit method): minimum strength per cell, SNR, "
        "frames needed",
        description="Sensitivity map of the model-based detection (`detect --method model`): per grid cell the "
        "smallest strength of a lone contact detected in one frame half the time (the lasso's shrinkage plus "
        "--n-sigma times the noise of the summed strength, from the baseline's photon noise), the matched-filter "
        "SNR of a contact of --strength, and the frames to sum for it to be detected. Among several contacts "
        "nearly all are found only with a 2x margin (simulated study). --method fit: the contact fit's map (guided "
        "optics, signed contact response; threshold --n-sigma 6 in matched-filter SNR). Writes OUT/sensitivity.json and "
        "OUT/sensitivity.png. See docs/inversion.md, 'Sensitivity map'.",
    )
    s.add_argument("scene", help="scene TOML file, or a built-in name (its contacts are ignored)")
    s.add_argument("--baseline", required=True, help="no-touch baseline capture of the same setup (.h5): the noise")
    _optics_arguments(s)
    s.add_argument("--strength", type=float, default=1.0,
                   help="contact strength of interest, in the units detect reports (default 1.0)")
    s.add_argument("--method", choices=("model", "fit"), default="model",
                   help="the detection method the map is for: 'model' (grid reconstruction, default) or 'fit' "
                   "(contacts fitted directly; needs a guided-optics calibration; threshold: a lone contact's "
                   "matched-filter SNR above --n-sigma)")
    s.add_argument("--n-sigma", type=float,
                   help="the threshold in noise units: the model method's on the summed strength (default: detect's, "
                   "1), the fit method's on a contact's chi-square drop, sqrt (default 6)")
    s.add_argument("--frames", type=int, default=1,
                   help="frames summed, the baseline on the same exposure (default 1); the JSON also gives the "
                   "frames needed per cell")
    from .reconstruct import RESPONSES

    s.add_argument("--contact-response", choices=RESPONSES,
                   help="the contact response, as for detect --method model (default auto)")
    s.add_argument("--position", action="store_true",
                   help="with --method fit: also where a contact can be placed, the Cramer-Rao bound of a lone contact's "
                   "position per cell and the probability that a fit lands within --match-radius-m (OUT/position.png; "
                   "the guided model's Jacobian at every cell: tens of seconds more)")
    s.add_argument("--match-radius-m", type=float,
                   help="with --position: the radius a placement must fall within (default 0.02, the evaluations' match "
                   "radius)")
    s.add_argument("--cell-m", type=float,
                   help="with --method fit: the map's grid cell [m] (default 0.005, the fit's proposal grid); the same "
                   "per-cell quantities sampled more coarsely, in about the cells' share of the time (1 cm: a quarter)")
    s.add_argument("--out", required=True, help="output folder: sensitivity.json, sensitivity.png (and position.png)")
    s.set_defaults(func=_cmd_sensitivity)
