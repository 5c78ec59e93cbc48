"""A finished calibration: values, uncertainties, result code, what the model does not
describe, and the one way back from JSON to :class:`tofjax.model.Params`.

Every reader of a calibration JSON goes through :meth:`CalibrationResult.from_json` (or
:func:`load_calibration`), which refuses, with a one-line message, a calibration that did
not converge or was refused, one made for another scene, or one with missing parameters.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..errors import UserError
from ..model import OPTICS, Params
from ..scene import Scene
from ._precision import PrecisionPlan
from .transforms import FITTABLE

__all__ = [
    "CalibrationError",
    "CalibrationRefused",
    "CalibrationResult",
    "RESULTS",
    "calibration_optics",
    "fit_report",
    "load_calibration",
    "load_precision_plan",
    "scene_fingerprint",
]

#: Result codes, best first. Only ``successful`` is a usable calibration.
RESULTS = (
    "successful",  # converged, chi-square acceptable, nothing on a bound
    "refused_reduced_chi2",  # converged, but the model does not describe the data
    "on_bound",  # converged with a parameter at the edge of its range, after every restart
    "nonlinear_max_steps_reached",
    "nonlinear_divergence",
    "nonfinite",
    "singular",
    "failed",
)

#: A calibration's n1 and mu above these is refused as unphysical (no waveguide material has n1 > 4;
#: 1e5 /m is a 10 um attenuation length): a reader would otherwise see no light and report no touch.
MAX_N1 = 4.0
MAX_MU_PER_M = 1e5
#: The optics and timing a calibration must provide (fitted or fixed).
REQUIRED = ("n1", "mu_s_per_m", "mu_a_per_m", "gain", "emission_time_s", "pulse_sigma_s", "pulse_tail_s")


class CalibrationError(UserError):
    """The data cannot be calibrated as given (wrong scene, not a baseline, bad counts)."""


class CalibrationRefused(CalibrationError):
    """A calibration JSON that must not be used (unconverged, refused, another scene, incomplete)."""


def scene_fingerprint(scene: Scene) -> str:
    """A hash of what a calibration is valid for: the waveguide's size, where the sensors sit
    and look, and the sensor's binning and zones. Not the optics: those are what is fitted."""
    sm, wg = scene.sensor, scene.waveguide
    key = {
        "size_m": [round(float(x), 9) for x in wg.size_m],
        "thickness_m": round(float(wg.thickness_m), 9),
        "sensors": [[round(float(x), 9) for x in s.position_m] + [round(float(s.direction_deg), 6)] for s in scene.sensors],
        "n_bins": int(sm.n_bins),
        "bin_width_s": float(f"{sm.bin_width_s:.9g}"),
        "zones": int(sm.zones),
        "fov_deg": round(float(sm.fov_deg), 6),
    }
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]


@dataclass
class CalibrationResult:
    """A finished fit, in physical units.

    ``converged`` is True only for a usable calibration (``result == "successful"``): a fit
    the solver finished but that is refused (chi-square too high, on a bound) is not
    converged. ``solver_converged`` says what the solver alone said.
    """

    params: Params  # every model parameter, fitted ones replaced (gain: mean over zones)
    free: tuple[str, ...]
    values: dict[str, np.ndarray]
    stderr: dict[str, np.ndarray]
    interval95: dict[str, tuple[np.ndarray, np.ndarray]]
    covariance: np.ndarray
    labels: list[str]
    converged: bool
    result: str
    steps: int
    reduced_chi2: float
    loss_history: list[float]
    solver: str
    frames: int
    stages: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    unconstrained_stderr: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    solver_converged: bool = False
    scene_fingerprint: str = ""
    discrepancy: dict[str, Any] = dataclasses.field(default_factory=dict)
    on_bound: list[str] = dataclasses.field(default_factory=list)
    residuals: np.ndarray | None = None  # (S, Z, B) Poisson-weighted, for plots
    optics: str = "default"  # the forward model's optics (FitConfig.optics); readers must use the same
    precision: PrecisionPlan | None = None  # the frames a baseline needs (FitConfig.precision_target_*)
    pulse_tails: int = 2  # the pulse model fitted (FitConfig.pulse_tails; "auto" chooses 1 or 2)
    pulse_tail_test: dict[str, Any] | None = None  # with pulse_tails = "auto": the score test that chose it
    # per fit coordinate, the share of its Laplace variance the data account for (not the weak prior):
    # tofjax.fit._laplace.data_shares; "extinction" is mu_s + mu_a, "albedo" mu_s / (mu_s + mu_a)
    data_share: dict[str, float] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        def pack(k):
            lo, hi = self.interval95[k]
            return {
                "value": np.asarray(self.values[k]).tolist(),
                "stderr": np.asarray(self.stderr[k]).tolist(),
                "interval95": [np.asarray(lo).tolist(), np.asarray(hi).tolist()],
            }

        return {
            "parameters": {k: pack(k) for k in self.free},
            "units": {k: FITTABLE[k] for k in self.free},
            "covariance": {"labels": self.labels, "matrix": np.asarray(self.covariance).tolist()},
            "converged": bool(self.converged),
            "result": self.result,
            "solver_converged": bool(self.solver_converged),
            "on_bound": list(self.on_bound),
            "steps": self.steps,
            "reduced_chi2": self.reduced_chi2,
            "discrepancy": self.discrepancy,
            "scene_fingerprint": self.scene_fingerprint,
            "loss_history": self.loss_history,
            "solver": self.solver,
            "optics": self.optics,
            "pulse_tails": int(self.pulse_tails),
            "pulse_tail_test": self.pulse_tail_test,
            "data_share": dict(self.data_share),
            "frames": self.frames,
            "stages": self.stages,
            "precision": None if self.precision is None else self.precision.to_json(),
            "fixed": {
                f.name: np.asarray(getattr(self.params, f.name)).tolist()
                for f in dataclasses.fields(self.params)
                if f.name not in self.free and not f.name.startswith("touch_")
            },
        }

    @staticmethod
    def from_json(
        data: dict[str, Any] | str | Path,
        scene: Scene,
        *,
        allow_unconverged: bool = False,
        allow_other_scene: bool = False,
        optics: tuple[str, ...] = ("default",),
    ) -> Params:
        """The calibrated :class:`Params` of ``scene`` from a calibration JSON (a dict or a
        path): fitted values where the JSON has them, the scene's for the rest.

        Raises :class:`CalibrationRefused` (one line) for an unconverged or refused fit
        (unless ``allow_unconverged``), a fit of another scene (unless
        ``allow_other_scene``), missing or unphysical parameters (always).
        """
        return load_calibration(data, scene, allow_unconverged=allow_unconverged, allow_other_scene=allow_other_scene,
                                optics=optics)


def _read(data: dict[str, Any] | str | Path) -> tuple[dict, str]:
    source = "calibration"
    if not isinstance(data, dict):
        path = Path(data)
        source = str(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise CalibrationRefused(f"{path}: no such file") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CalibrationRefused(f"{path}: not valid JSON: {e}") from None
    if not isinstance(data, dict) or not isinstance(data.get("parameters"), dict):
        raise CalibrationRefused(f"{source}: not a calibration (no 'parameters' table; write it with `tofjax calibrate`)")
    return data, source


def calibration_optics(data: dict[str, Any] | str | Path) -> str:
    """The optics a calibration JSON was fitted with (``FitConfig.optics``; ``"default"`` where the
    JSON predates the field). An unknown value is refused in one line."""
    data, source = _read(data)
    optics = data.get("optics", "default")
    if optics not in OPTICS:
        raise CalibrationRefused(f"{source}: optics {optics!r} unknown (this tofjax knows {' and '.join(map(repr, OPTICS))})")
    return optics


def load_calibration(
    data: dict[str, Any] | str | Path,
    scene: Scene,
    *,
    allow_unconverged: bool = False,
    allow_other_scene: bool = False,
    optics: tuple[str, ...] = ("default",),
) -> Params:
    """See :meth:`CalibrationResult.from_json`. ``optics``: the optics the reader builds; a
    calibration fitted with other optics (``FitConfig.optics``) is refused in one line, since its
    parameters mean something else in another model."""
    data, source = _read(data)
    used = calibration_optics(data)
    if used not in optics:
        raise CalibrationRefused(
            f"{source}: fitted with optics = {used!r}, which this reader does not support (it uses "
            f"{' or '.join(repr(o) for o in optics)}); recalibrate with optics = {optics[0]!r}"
        )
    if not allow_unconverged and data.get("converged") is not True:
        why = data.get("result", "no 'converged' flag")
        chi = data.get("reduced_chi2")
        extra = f", reduced chi-square {chi:.3g}" if isinstance(chi, (int, float)) else ""
        raise CalibrationRefused(
            f"{source}: the calibration did not converge or was refused ({why}{extra}); recalibrate, "
            "or pass --allow-unconverged-calibration to use it anyway"
        )
    stored = data.get("scene_fingerprint")
    if not allow_other_scene:
        mine = scene_fingerprint(scene)
        if not stored:
            raise CalibrationRefused(
                f"{source}: no scene fingerprint (written by an older tofjax?); recalibrate, "
                "or pass --allow-other-scene-calibration"
            )
        if stored != mine:
            raise CalibrationRefused(
                f"{source}: calibrated for another scene (fingerprint {stored}, this scene {mine}); "
                "recalibrate, or pass --allow-other-scene-calibration"
            )
    values: dict[str, Any] = dict(data.get("fixed") or {})
    for k, v in data["parameters"].items():
        if not isinstance(v, dict) or "value" not in v:
            raise CalibrationRefused(f"{source}: parameters.{k} has no 'value'")
        values[k] = v["value"]
    missing = [k for k in REQUIRED if k not in values]
    if missing:
        raise CalibrationRefused(f"{source}: missing parameters: {', '.join(missing)}")
    base = Params.from_scene(scene.without_touches(), jnp.float64 if _x64() else jnp.float32)
    S, Z, _ = scene.shape
    changes = {}
    for f in dataclasses.fields(base):
        k = f.name
        if k not in values or k.startswith("touch_"):
            continue
        try:
            v = np.asarray(values[k], float)
        except (TypeError, ValueError):
            raise CalibrationRefused(f"{source}: {k} is not a number or a regular array of numbers") from None
        want = np.shape(getattr(base, k))
        if k == "gain" and v.shape not in ((S,), (S, Z)):
            raise CalibrationRefused(f"{source}: gain has {v.size} values for {S} sensors (shape {v.shape}; this scene needs "
                                     f"({S},) or ({S}, {Z})): a calibration of another scene?")
        if k == "gain" and v.shape == (S, Z):
            v = v.mean(-1)  # per-zone gains: the sensor's K is their mean
        if k == "end_reflectance" and v.shape == (S, Z):
            v = np.clip(v.mean(), 0.0, 1.0)  # per-zone reflectances: the model's one is their mean
        if v.size == 1 and want != v.shape and np.prod(want, dtype=int) != 1:
            v = np.full(want, float(v.ravel()[0]))
        if k == "gain" and v.size != S:
            raise CalibrationRefused(f"{source}: gain has {v.size} values for {S} sensors: a calibration of another scene?")
        if v.size != np.prod(want, dtype=int):
            raise CalibrationRefused(
                f"{source}: {k} has {v.size} values where this scene needs {int(np.prod(want, dtype=int))}: "
                "a calibration of another scene?"
            )
        if not np.isfinite(v).all():
            raise CalibrationRefused(f"{source}: {k} is not finite")
        changes[k] = v.reshape(want)
    params = base.replace(**changes)
    if (not 1.0 < float(params.n1) <= MAX_N1 or not 0 <= float(params.mu_s_per_m) <= MAX_MU_PER_M
            or not 0 <= float(params.mu_a_per_m) <= MAX_MU_PER_M or (np.asarray(params.gain) <= 0).any()):
        raise CalibrationRefused(
            f"{source}: unphysical n1={float(params.n1)} (1 < n1 <= {MAX_N1:g}), mu_s={float(params.mu_s_per_m)}, "
            f"mu_a={float(params.mu_a_per_m)} (each in [0, {MAX_MU_PER_M:g}] /m) or a non-positive gain"
        )
    return params


def load_precision_plan(data: dict[str, Any] | str | Path) -> PrecisionPlan | None:
    """The precision plan of a calibration JSON (a dict or a path; None where the JSON predates
    it): n1 and mu_s + mu_a, their relative standard errors and the frames needed for the targets."""
    data, _ = _read(data)
    plan = data.get("precision")
    return None if plan is None else PrecisionPlan.from_json(plan)


def _x64() -> bool:
    import jax

    return bool(jax.config.jax_enable_x64)


def fit_report(result: CalibrationResult) -> str:
    """A short text table: each parameter with its standard error and Laplace 95% interval,
    then the zones the model describes worst."""
    status = "converged" if result.converged else "NOT converged"
    lines = [
        f"calibration: {status} ({result.result}) after {result.steps} steps, {result.solver}, "
        f"{result.frames} frames, reduced chi-square {result.reduced_chi2:.3f}",
        f"{'parameter':30s} {'value':>12s} {'stderr':>10s}   95% interval (Laplace)",
    ]
    for k in result.free:
        v, e = np.ravel(result.values[k]), np.ravel(result.stderr[k])
        lo, hi = (np.ravel(x) for x in result.interval95[k])
        unit = FITTABLE[k]
        if v.size == 1:
            lines.append(f"{k:30s} {v[0]:12.6g} {e[0]:10.3g}   [{lo[0]:.6g}, {hi[0]:.6g}] {unit}")
        else:
            lines.append(
                f"{k + f' ({v.size})':30s} {np.mean(v):12.6g} {np.mean(e):10.3g}   values {v.min():.4g} .. {v.max():.4g} {unit}"
            )
    if "mu_s_per_m" in result.labels and "mu_a_per_m" in result.labels:
        i, j = result.labels.index("mu_s_per_m"), result.labels.index("mu_a_per_m")
        c = result.covariance
        corr = c[i, j] / np.sqrt(c[i, i] * c[j, j]) if c[i, i] > 0 and c[j, j] > 0 else float("nan")
        lines.append(
            f"correlation(mu_s, mu_a) = {corr:+.2f}"
            + ("  (strong: a baseline alone barely separates scattering from absorption)" if abs(corr) > 0.8 else "")
        )
    lines += prior_set_lines(result.data_share)
    if result.precision is not None and result.precision.targets:
        lines.append("precision (photon noise, 95%):")
        lines += ["  " + x for x in result.precision.lines()]
    test = result.pulse_tail_test
    if test is not None:
        lines.append(
            f"pulse tails: {result.pulse_tails} (auto: slow-tail score z = {test['z']:.3g} "
            f"{'>' if test['two_tails'] else '<='} {test['threshold']:g})"
        )
    else:
        lines.append(f"pulse tails: {result.pulse_tails}")
    if result.on_bound:
        lines.append(f"on a bound: {', '.join(result.on_bound)}")
    worst = result.discrepancy.get("worst_zones", [])[:3]
    if worst:
        lines.append(
            "worst zones (reduced chi-square): "
            + ", ".join(f"sensor {w['sensor']} zone {w['zone']}: {w['reduced_chi2']:.2f}" for w in worst)
        )
    lines += fixed_score_lines(result.discrepancy.get("fixed_parameters"))
    return "\n".join(lines)


#: below this share of its Laplace variance from the data, the report says a parameter is set by the prior
PRIOR_SET_SHARE = 0.5
#: how the report and plots name the data shares' coordinates (the rest by their parameter names)
SHARE_LABELS = {"extinction": "mu_s + mu_a", "albedo": "albedo mu_s / (mu_s + mu_a)", "gain": "gain (median of the zones)"}


def prior_set_lines(shares: dict[str, float] | None) -> list[str]:
    """The report's line on coordinates the weak prior, not the data, sets (:attr:`CalibrationResult.data_share`
    below :data:`PRIOR_SET_SHARE`), least determined first; none where there are none."""
    low = sorted((v, k) for k, v in (shares or {}).items() if v < PRIOR_SET_SHARE)
    if not low:
        return []
    return [f"set mostly by the weak prior, not the data (share of the Laplace variance from the data < {PRIOR_SET_SHARE:g}; "
            "their values depend on the prior, FitConfig.prior_width about the scene's values: not measurements):",
            "  " + ", ".join(f"{SHARE_LABELS.get(k, k)} {v:.2g}" for v, k in low)]


def fixed_score_lines(record: dict | None) -> list[str]:
    """The report's lines on held parameters the data contradict (``discrepancy["fixed_parameters"]``, from
    :func:`tofjax.fit._scores.fixed_score_record`): none where nothing was tested or nothing is contradicted."""
    if not record or not record.get("contradicted"):
        return []
    rows = [r for r in record["parameters"] if r["contradicted"]]
    return [f"held parameters the data contradict (score test, |z| / sqrt(reduced chi-square) > {record['threshold']:g}; "
            "the free parameters' values and errors are biased while they are held):"] + [
        f"  {r['name']} = {r['value']:.6g}: z = {r['z']:+.3g} (scaled {r['z_scaled']:+.3g}); one Gauss-Newton step "
        f"moves it to {r['gauss_newton_value']:.4g}" for r in rows] + [
        "  free them (FitConfig.free, or free = [...] in a --config TOML) or check the scene's values"]
