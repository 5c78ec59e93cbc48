"""The ``tofjax`` command. Thin: parse, call the library, print.

User errors (bad scene, bad capture, bad arguments) end in one line on
stderr and exit code 2, never in a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .capture import CaptureError
from .config import ConfigError
from .errors import UserError
from .model import OPTICS


def _cmd_simulate(a) -> int:
    from .capture import check_capture_target, write_capture
    from .model import ModelOptions
    from .scene import load_scene
    from .simulate import simulate

    scene = load_scene(a.scene)
    if a.frames < 1:
        raise ConfigError(f"--frames: must be >= 1, got {a.frames}")
    _check_size(scene, a.frames)
    check_capture_target(a.out, a.overwrite)
    if scene.free_space:  # a TMF882x in air: the fitted sensor model makes the histograms (issue 12)
        from .sensor.simulate import simulate_free_space

        cap = simulate_free_space(scene, a.frames, a.seed)
    else:
        cap = simulate(scene, a.frames, a.seed, options=ModelOptions(quadrature=a.quadrature, dtype=a.dtype))
    _check_some_light(cap, a.scene)
    write_capture(a.out, cap, overwrite=a.overwrite)
    print(f"wrote {a.out}: {cap.n_frames} frames of {scene.shape} (sensors, zones, bins), scene '{scene.name}'")
    return 0


def _cmd_plot(a) -> int:
    from .capture import read_capture
    from .plot import chosen_sensors, plot_capture, plot_scene

    cap = read_capture(a.capture)
    base = read_capture(a.baseline) if a.baseline else None
    if base is not None and base.scene.shape != cap.scene.shape:
        raise CaptureError(
            f"{a.baseline}: baseline shape {base.scene.shape} does not match the capture's {cap.scene.shape}"
        )
    sensors = None
    if a.sensors is not None:
        try:
            sensors = chosen_sensors(cap.scene.shape[0], [int(v) for v in a.sensors.split(",")])
        except ValueError as e:
            raise ConfigError(f"--sensors: expected comma-separated sensor indices of the capture, got {a.sensors!r} "
                              f"({e})") from None
    paths = plot_capture(cap, a.out, baseline=base, log=not a.linear, sensors=sensors)
    if not cap.scene.free_space:  # a free-space capture has no waveguide to draw
        paths.append(plot_scene(cap.scene, Path(a.out) / "scene.png"))
    print(f"wrote {len(paths)} figures to {a.out}/")
    return 0


def _cmd_demo(a) -> int:
    from .demo import run_demo
    from .scene import load_scene

    scene = load_scene(a.scene) if a.scene else None
    if scene is not None:
        scene.require_waveguide("tofjax demo", a.scene)
        _check_size(scene, a.frames)
    run_demo(a.out, scene, frames=a.frames, seed=a.seed, overwrite=a.overwrite)
    return 0


def _cmd_scene(a) -> int:
    from .scene import load_scene

    scene = load_scene(a.scene)
    if a.toml:
        print(scene.to_toml(), end="")
        return 0
    S, Z, B = scene.shape
    print(f"{a.scene}: ok: '{scene.name}', {S} sensors x {Z} zones x {B} bins, {len(scene.touches)} touches")
    print(f"components: {', '.join(scene.components())}")
    return 0


def _cmd_calibrate(a) -> int:
    import json

    import numpy as np

    from .capture import read_capture
    from .fit.calibrate import CalibrationError, Calibrator, FitConfig, fit_report, load_fit_config
    from .scene import load_scene

    nuts_only = [_flag(k) for k in ("chains", "warmup", "draws") if getattr(a, k) is not None]
    if nuts_only and a.mcmc != "nuts":
        raise UserError(f"{nuts_only[0]}: only for --mcmc nuts")
    emcee_only = [_flag(k) for k in ("walkers", "max_steps", "chain") if getattr(a, k) is not None]
    if emcee_only and a.mcmc != "emcee":
        # --max-steps is easily read as the fit's own step limit (that is max_steps in a --config)
        raise UserError(f"{emcee_only[0]}: only for --mcmc (emcee)" + ("; the fit's step limit is max_steps in a --config"
                                                                       if emcee_only[0] == "--max-steps" else ""))
    cap = read_capture(a.baseline)
    cap.scene.require_waveguide("tofjax calibrate", a.baseline)
    scene = load_scene(a.scene).require_waveguide("tofjax calibrate", a.scene) if a.scene else None
    if scene is not None and scene.shape != cap.scene.shape:
        raise CalibrationError(
            f"{a.scene}: the scene has (sensors, zones, bins) = {scene.shape} but {a.baseline} has {cap.scene.shape}"
        )
    config = load_fit_config(a.config) if a.config else FitConfig()
    if a.optics is not None or a.pulse_tails is not None:  # the command line wins over the config file
        import dataclasses

        if a.optics is not None:
            config = dataclasses.replace(config, optics=a.optics)
        if a.pulse_tails is not None:
            from .fit.calibrate import DEFAULT_FREE

            # a config on the default free parameters gets the new tails' default ones
            own = FitConfig(pulse_tails=config.pulse_tails, optics=config.optics).free
            free = {"free": DEFAULT_FREE} if config.free == own else {}
            tails = a.pulse_tails if a.pulse_tails == "auto" else int(a.pulse_tails)
            config = dataclasses.replace(config, pulse_tails=tails, **free)
    if a.sensor:  # a sensor model fitted on real histograms (issue 12): its bin width, not the nominal one
        scene = (scene or cap.scene).with_sensor_model(a.sensor)
        print(f"sensor model {a.sensor}: bin width {scene.sensor.bin_width_s * 1e12:.2f} ps")
    calibrator = Calibrator((scene or cap.scene), config)
    result = calibrator.fit(cap)
    from .outputs import atomic_write_text

    report = result.to_json()
    out = Path(a.out)
    atomic_write_text(out, json.dumps(report, indent=2))
    print(fit_report(result))
    if a.mcmc == "nuts" and result.converged:
        from .fit.nuts import NutsOptions, plot_nuts, sample_nuts

        given = {k: getattr(a, k) for k in ("chains", "warmup", "draws") if getattr(a, k) is not None}
        opts = NutsOptions(**given)  # the library's defaults for what is not given (one place)
        post = sample_nuts(calibrator, cap, result, opts)
        report["posterior"] = post.summary()
        atomic_write_text(out, json.dumps(report, indent=2))
        s = report["posterior"]
        print(
            f"posterior (NUTS): {opts.chains} chains x {opts.draws} draws in {post.wall_s:.1f} s, min ESS {s['ess_min']:.0f} "
            f"({s['ess_min_per_s']:.0f}/s), max R-hat {s['rhat_max']:.3f}, {post.divergences} divergences"
            + ("" if s["rhat_max"] <= 1.01 and not post.divergences else " -- NOT converged (raise --warmup/--draws)")
        )
        for k, v in s["parameters"].items():
            print(f"  {k:30s} median {v['median']:.6g}  95% [{v['interval95'][0]:.6g}, {v['interval95'][1]:.6g}]"
                  f"  ESS {min(s['ess_bulk'][k], s['ess_tail'][k]):.0f}  R-hat {s['rhat'][k]:.3f}")
        if a.plots:
            plot_nuts(post, a.plots)
            print(f"wrote corner.png and traces.png to {a.plots}/")
    elif a.mcmc and result.converged:
        from .fit.posterior import PosteriorOptions, sample_posterior

        post = sample_posterior(
            calibrator,
            cap,
            result,
            PosteriorOptions(walkers=a.walkers, max_steps=5000 if a.max_steps is None else a.max_steps, chain=a.chain,
                             progress=True),
        )
        report["posterior"] = post.summary()
        atomic_write_text(out, json.dumps(report, indent=2))
        print(
            f"posterior: {post.steps} steps, tau {np.nanmax(post.tau):.0f}, acceptance {post.acceptance:.2f}, "
            f"{post.n_effective:.0f} effective samples, {'converged' if post.converged else 'NOT converged (raise --max-steps)'}"
        )
        for k, v in report["posterior"]["parameters"].items():
            print(f"  {k:30s} median {v['median']:.6g}  95% [{v['interval95'][0]:.6g}, {v['interval95'][1]:.6g}]")
        if a.plots:
            from .plot import plot_posterior, plot_traces

            plot_posterior(post.samples, post.names, None, Path(a.plots) / "corner.png")
            plot_traces(post.chain_physical, post.names, Path(a.plots) / "traces.png")
            print(f"wrote corner.png and traces.png to {a.plots}/")
    if a.plots:
        from .fit._discrepancy import plot_residual_map
        from .plot import plot_data_share, plot_fit, plot_loss

        used = (scene or cap.scene).without_touches()
        data = cap.mean()
        sigma = np.sqrt(np.maximum(data, 1.0) / cap.n_frames)
        model = data + result.residuals * sigma  # the fitted model, per-zone gains included
        paths = plot_fit(data, model, sigma, used, a.plots)
        paths.append(plot_loss(result.loss_history, Path(a.plots) / "loss.png"))
        paths.append(plot_residual_map(result.residuals, Path(a.plots) / "residual_map.png", used.sensor.bin_width_s))
        if result.data_share:
            paths.append(plot_data_share(result.data_share, Path(a.plots) / "data_share.png"))
        print(f"wrote {len(paths)} figures to {a.plots}/ (residual_map.png: what the model does not describe)")
    print(f"wrote {out}")
    if result.result == "refused_reduced_chi2" and not a.allow_unconverged:
        raise CalibrationError(
            f"reduced chi-square {result.reduced_chi2:.1f} > {config.max_reduced_chi2:g}: the model does not describe "
            f"this capture (worst zones under discrepancy in {out}, written with converged = false); is it really a "
            "no-touch baseline of this scene?"
        )
    if not result.converged and not a.allow_unconverged:
        bound = f" on a bound: {', '.join(result.on_bound)};" if result.on_bound else ""
        poor = (f" reduced chi-square {result.reduced_chi2:.1f} > {config.max_reduced_chi2:g}: is it really a no-touch "
                "baseline of this scene?" if result.reduced_chi2 > config.max_reduced_chi2 else "")
        print(
            f"tofjax calibrate: error: the fit did not converge ({result.result});{bound} the parameters in {out} are "
            f"not a fit.{poor} Raise max_steps or loosen rtol/atol in a --config, or pass --allow-unconverged",
            file=sys.stderr,
        )
        return 3
    return 0


# ---- input and output checks of every command (issue 15) ---------------------------------

#: Outputs of each command: (argument, is a folder). Checked before any work is done.
_OUTPUTS = {
    "simulate": (("out", False),),
    "plot": (("out", True),),
    "demo": (("out", True),),
    "calibrate": (("out", False), ("plots", True)),
    "process": (("out", False), ("png", True)),
    "detect": (("json", False),),
    "sensitivity": (("out", True),),
    "acquire": (("out", False),),
    "baseline": (("out", False),),
    "replay": (("out", False),),
    "predict": (("out", False),),
    "force-data": (("out", True),),
    "mc": (("out", False), ("json", False)),
    "prune": (("out", False),),
    "bench": (("json", False),),
    "import": (("out", False),),
    "sensor": (("out", False), ("plots", True)),
    "range": (("json", False),),
}
#: Arguments naming files a command reads: no output may be one of them.
_INPUTS = ("scene", "capture", "baseline", "touch", "calibration", "config", "run", "rig", "protocol", "chain", "image",
           "sensor", "file")
#: Numeric arguments: (lowest, highest). argparse takes "nan" and "inf" for floats; these do not.
_RANGES = {
    "frames": (1, 10**8),
    "seed": (0, 2**32 - 1),
    "quadrature": (1, 64),
    "resolution_mm": (0.05, 1000.0),
    "relative": (1e-6, 1.0),
    "n_sigma": (0.0, 1e6),
    "strength": (1e-12, 1e12),
    "min_strength": (0.0, 1e12),
    "match_radius_m": (1e-6, 100.0),
    "walkers": (2, 100_000),
    "max_steps": (1, 10**8),
    "chains": (1, 1024),
    "warmup": (10, 10**6),
    "draws": (10, 10**7),
    "photons": (1, 10**10),
    "batch": (1, 10**8),
    "repeats": (1, 10**6),
    "nee_points": (1, 1024),
    "elevations": (1, 1024),
    "g": (-0.99, 0.99),
    "budget": (1e-9, 10.0),
    "baseline_frames": (0, 10**8),
    "bus": (0, 255),
    "bus_speed": (1_000, 10_000_000),
    "period_ms": (1, 100_000),
    "duration": (1e-6, 1e7),
    # tofjax mc slab
    "n": (1.0, 10.0),
    "thickness_m": (1e-9, 100.0),
    "mu_s_per_m": (0.0, 1e8),
    "mu_a_per_m": (0.0, 1e8),
    # tofjax import, sensor fit
    "distance_m": (0.0, 100.0),
    "min_distance_m": (0.0, 100.0),
    "max_distance_m": (0.0, 100.0),
    "knots_per_bin": (1, 64),
    "max_iterations": (1, 10**6),
}
#: Largest capture held in memory (frames x sensors x zones x bins values): 1.6 GB as float64.
_MAX_VALUES = 2 * 10**8


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def _check_some_light(cap, source: str) -> None:
    """Refuse to write a capture in which every bin is 0 (every reader refuses it as impossible counts)."""
    import numpy as np

    h = np.asarray(cap.histograms)
    if not np.any(h > 0):
        raise UserError(f"{source}: the scene gives no light at all (every bin of every frame is 0): check its gain, "
                        "crosstalk and ambient counts, n1 and bin width; nothing written")
    if not np.all(np.isfinite(h)):
        raise UserError(f"{source}: the scene's expected counts are not finite; nothing written")


def _check_size(scene, frames: int) -> None:
    S, Z, B = scene.shape
    if frames * S * Z * B > _MAX_VALUES:
        raise UserError(
            f"--frames: {frames} frames of {S} x {Z} x {B} bins are {frames * S * Z * B:.3g} values, more than "
            f"{_MAX_VALUES:.0e} fit in memory; record fewer frames"
        )


def _check_args(a) -> None:
    """One-line errors for numbers out of range and outputs that must not be written."""
    import math

    for dest, (lo, hi) in _RANGES.items():
        v = getattr(a, dest, None)
        if v is None or isinstance(v, (str, bool)):
            continue
        if isinstance(v, float) and not math.isfinite(v):
            raise UserError(f"{_flag(dest)}: must be a finite number, got {v}")
        if not lo <= v <= hi:
            raise UserError(f"{_flag(dest)}: must be in [{lo}, {hi}], got {v}")
    from .outputs import check_output

    inputs = []
    for name in _INPUTS:
        v = getattr(a, name, None)
        if isinstance(v, (list, tuple)):
            inputs += list(v)
        elif isinstance(v, str):
            inputs.append(v)
    for dest, folder in _OUTPUTS.get(a.command, ()):
        v = getattr(a, dest, None)
        if v is None:
            continue
        check_output(v, overwrite=getattr(a, "overwrite", False), inputs=inputs, folder=folder, flag=_flag(dest))


def _add_overwrite(parser: argparse.ArgumentParser) -> None:
    """``--overwrite`` on every (sub)command that writes something."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sp in action.choices.values():
                dests = {x.dest for x in sp._actions}
                if dests & {"out", "json", "plots", "png"} and "overwrite" not in dests:
                    sp.add_argument("--overwrite", action="store_true",
                                    help="replace existing outputs (never a file the command reads)")
                _add_overwrite(sp)


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (``tofjax CMD: error: ...``) instead of usage + error."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


#: The commands this module defines; a command line for one of them needs no other package's parser.
_CORE = ("simulate", "plot", "demo", "calibrate", "scene")


def build_parser(extensions: bool = True) -> argparse.ArgumentParser:
    """The ``tofjax`` parser; ``extensions=False`` leaves out the commands of the packages built
    on the foundation (their modules import SciPy, the detector, ...: ~0.5 s of a ``calibrate``)."""
    p = _Parser(
        prog="tofjax",
        description="Time-of-flight FTIR tactile sensors: simulate, plot, calibrate and invert.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    s = sub.add_parser("simulate", help="simulate a capture (with ground truth) from a scene file")
    s.add_argument("scene", help="scene TOML file, or a built-in name (optoskin, softskin, ...)")
    s.add_argument("--frames", type=int, default=10, help="frames to simulate (default 10)")
    s.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    s.add_argument("--out", required=True, help="output capture (.h5)")
    s.add_argument("--quadrature", type=int, default=2, help="time nodes per bin (fidelity, default 2)")
    s.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    s.set_defaults(func=_cmd_simulate)

    s = sub.add_parser("plot", help="plot a capture's histograms per sensor and zone")
    s.add_argument("capture", help="capture file (.h5)")
    s.add_argument("--baseline", help="baseline capture to compare with (touch vs baseline)")
    s.add_argument("--out", required=True, help="output folder for PNGs")
    s.add_argument("--linear", action="store_true", help="linear count axis (default log)")
    s.add_argument("--sensors", help="the sensors to draw, comma-separated indices (default all; each figure takes a "
                   "second or two)")
    s.set_defaults(func=_cmd_plot)

    s = sub.add_parser("demo", help="the main job on the built-in default scene (what `make demo` runs)")
    s.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    s.add_argument("--scene", help="baseline scene instead of the built-in OptoSkin")
    s.add_argument("--frames", type=int, default=100, help="baseline frames (default 100)")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=_cmd_demo)

    s = sub.add_parser("calibrate", help="fit n1, mu_s, mu_a and nuisance parameters to a baseline capture")
    s.add_argument("baseline", help="baseline capture (.h5), no touch")
    s.add_argument("--scene", help="scene to start from (default: the capture's own)")
    s.add_argument("--config", help="fit config TOML (solver, tolerances, free parameters)")
    s.add_argument("--out", required=True, help="output JSON")
    s.add_argument("--plots", help="folder for fit and loss plots")
    s.add_argument("--allow-unconverged", action="store_true", help="exit 0 even if the fit did not converge")
    s.add_argument("--mcmc", nargs="?", const="emcee", choices=("emcee", "nuts"),
                   help="also sample the posterior: emcee (the default, derivative-free) or nuts (blackjax, gradients)")
    s.add_argument("--chains", type=int, default=None, help="NUTS chains (default: the library's, tofjax.fit.nuts.NutsOptions)")
    s.add_argument("--warmup", type=int, default=None, help="NUTS warm-up steps per chain (default: the library's, tofjax.fit.nuts.NutsOptions)")
    s.add_argument("--draws", type=int, default=None, help="NUTS draws per chain (default: the library's, tofjax.fit.nuts.NutsOptions)")
    s.add_argument("--walkers", type=int, default=None, help="emcee walkers (default max(32, 4 x parameters))")
    s.add_argument("--max-steps", type=int, default=None, help="most emcee steps (default 5000; --mcmc only)")
    s.add_argument("--chain", help="HDF5 file for the chain: an interrupted run resumes from it")
    s.add_argument("--sensor", help="sensor model from `tofjax sensor fit` (its bin width replaces the scene's)")
    s.add_argument("--optics", choices=OPTICS, default=None,
                   help="forward model optics (default: the config's, else 'default'); stored in the JSON, "
                        "and detect/process use the same")
    s.add_argument("--pulse-tails", choices=("1", "2", "auto"), default=None,
                   help="pulse tails to fit (default: the config's, else 2); auto: one tail, and a second, slow tail "
                        "only where a score test at the one-tail fit supports it")
    s.set_defaults(func=_cmd_calibrate)

    s = sub.add_parser("scene", help="validate a scene file and show what the model will include")
    s.add_argument("scene", help="scene TOML file, or a built-in name")
    s.add_argument("--toml", action="store_true", help="print the scene with every default filled in")
    s.set_defaults(func=_cmd_scene)
    if not extensions:
        _add_overwrite(p)
        return p

    # Subcommands of the packages built on the foundation, each registered by its own module.
    from .force.cli import register as register_force  # train, predict, table, force-data (issue 5)
    from .hw.cli import register as register_hw  # acquire, baseline, replay (issue 6)
    from .invert.cli import register as register_invert  # process, detect (issue 4)
    from .mc.cli import register as register_mc  # mc, mc slab, prune (issues 7, 14)
    from .sensor.cli import register as register_sensor  # import, sensor fit, range (issue 12)
    from .study_cli import register as register_study  # study on several devices and processes (issue 16)

    register_invert(sub)
    register_force(sub)
    register_hw(sub)
    register_mc(sub)
    register_sensor(sub)
    register_study(sub)
    _add_overwrite(p)
    return p


def main(argv: list[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else list(argv)
    command = next((w for w in words if not w.startswith("-")), None)
    # ``--help`` lists every command; a core command parses the same without the others
    core = command in _CORE and not any(w in ("-h", "--help") for w in words[: words.index(command)])
    args = build_parser(extensions=not core).parse_args(argv)
    # Fitting and gradients need float64; set it here, at the entry point, never on import.
    from . import enable_compilation_cache, enable_x64
    from .compile_cache import use_fast_cpu_compiler

    # XLA's elemental CPU emitters: a cold calibration 1.4x faster (experiments/cpu_emitters.py); the
    # flag must be in $XLA_FLAGS before JAX's backend starts.
    use_fast_cpu_compiler()
    enable_x64()
    # Compile once per machine, not once per process ($TOFJAX_COMPILATION_CACHE=0 turns it off).
    enable_compilation_cache()

    def show(message, category, filename, lineno, file=None, line=None):
        # A warning is one line too, named by its category (BadFramesWarning, ...).
        print(f"tofjax {args.command}: warning: {category.__name__}: {message}", file=sys.stderr)

    rc = _run(args, show)
    if argv is None and args.command in _FAST_EXIT:
        _exit_now(rc)
    return rc


# Commands whose process ends without the interpreter's teardown when run from the command line
# (not when main() is called with arguments, as tests and scripts do): after the result was
# written, the teardown (modules, JAX's client and its loaded executables) took about a second of
# wall time and 0.4-0.5 s of CPU of a warm `tofjax calibrate` on the loaded 2-core VM. Its outputs
# are written atomically and closed before this; the standard streams and logging are flushed.
_FAST_EXIT = frozenset({"calibrate"})


def _exit_now(rc: int) -> None:
    import logging
    import os

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:
            pass
    os._exit(rc)


def _run(args, show) -> int:
    import warnings

    with warnings.catch_warnings():
        warnings.showwarning = show
        try:
            _check_args(args)
            return args.func(args)
        except UserError as e:
            print(f"tofjax {args.command}: error: {e}", file=sys.stderr)
            return 2
        except OSError as e:  # the disk, not the input: a full or read-only disk, a lost mount
            where = f"{e.filename}: " if getattr(e, "filename", None) else ""
            print(f"tofjax {args.command}: error: {where}{e.strerror or e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"tofjax {args.command}: interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
