"""Calibration: fit n1, mu_s, mu_a and the nuisance parameters to a baseline capture.

One pure entry, :func:`calibrate`, returns a :class:`CalibrationResult` with a result code
(``result``; ``converged`` is True only for ``successful``). The pieces, optimistix-style:

- :class:`~tofjax.fit._problem.CalibrationProblem` (an ``eqx.Module``): the profiled
  residuals; the data are arguments, never state.
- :mod:`~tofjax.fit._start`: timing, then envelope, then the joint fit.
- :func:`fit_problem`: one compiled solve from one start (:func:`fit_problem_batch`: many
  starts and data sets in one compiled, vmapped call; :func:`fit_problem_compact`: vmapped
  calls of a few steps that drop the fits that have stopped; :func:`fit_problem_loop`: the same
  arguments, one fit after the other, faster on a CPU).
- :mod:`~tofjax.fit._laplace` and :mod:`~tofjax.fit._result`: covariance and the result.

The solver is an optimistix solver object and the objective an :class:`AbstractObjective`
(:class:`ChiSquare` for least-squares solvers, :class:`PoissonDeviance` for minimisers);
:class:`FitConfig` builds both from a TOML file's strings.

Residuals are Poisson-weighted, ``(model - mean) / sqrt(max(mean, 1) / frames)``, so
``sum(r^2) / dof`` is a reduced chi-square.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..capture import Capture
from ..compile_cache import call_stored, compile_ahead, prefetch
from ..config import INFINITE_OK, ConfigError, from_dict, load_toml
from ..model import OPTICS, ModelOptions, Params, build_model
from ..scene import Scene
from ._batch import CompactBatch, solve_marquardt_compact
from ._discrepancy import discrepancy_report
from ._laplace import data_shares, laplace_covariance
from ._precision import check_target, precision_plan
from ._problem import LINEAR, CalibrationProblem
from ._result import (
    RESULTS,
    CalibrationError,
    CalibrationRefused,
    CalibrationResult,
    fit_report,
    load_calibration,
    scene_fingerprint,
)
from ._start import envelope_candidates, timing_start
from ._scores import fixed_score_record
from ._tails import one_tail_problem, tail_test, tail_tests, two_tail_problem
from .solve import MarquardtLM, SolveResult, dense_jvp, solve_marquardt, solve_with_history
from .transforms import FITTABLE, default_transforms

__all__ = [
    "AbstractObjective",
    "CalibrationError",
    "CalibrationProblem",
    "CalibrationRefused",
    "CalibrationResult",
    "Calibrator",
    "ChiSquare",
    "CompactBatch",
    "FitConfig",
    "FitSolution",
    "PoissonDeviance",
    "RESULTS",
    "base_params",
    "build_problem",
    "calibrate",
    "calibrate_many",
    "check_baseline",
    "fit_problem",
    "default_fit_batch",
    "fit_batch_tails",
    "fit_problem_batch",
    "fit_problem_compact",
    "fit_problem_loop",
    "fit_report",
    "load_calibration",
    "load_fit_config",
    "scene_fingerprint",
    "tail_configs",
]

SOLVERS = ("levenberg-marquardt", "gauss-newton", "dogleg", "poisson-deviance")
DEFAULT_FREE = (
    "n1",
    "mu_s_per_m",
    "mu_a_per_m",
    "gain",
    "ambient_counts",
    "crosstalk_counts",
    "pulse_sigma_s",
    "pulse_tail_s",
    "emission_time_s",
    "interface_backscatter_per_m",
    "end_reflectance",
    "end_incidence_power",
    "near_field_m",
    "near_field_shape",
    "pulse_slow_weight",
    "pulse_slow_tail_s",
    "crosstalk_width_s",
)
#: The second tail of the pulse: free only with ``pulse_tails = 2``.
SLOW_TAIL = ("pulse_slow_weight", "pulse_slow_tail_s")
#: Parameters the guided optics do not use (their near field has no shape parameter): dropped
#: from the default ``free`` with ``optics = "guided"``, refused where listed.
NOT_GUIDED = ("near_field_shape",)
#: ``FitConfig.pulse_tails``: one tail, two, or the data decide.
PULSE_TAILS = (1, 2, "auto")
#: Where a two-tail fit starts the slow tail when the scene states none (its share; its time
#: constant starts at 4x the scene's tail, ``Params.from_scene``). Also the prior's centre.
SLOW_WEIGHT_START = 0.1


# ---- objectives ----------------------------------------------------------------------------


class AbstractObjective(eqx.Module):
    """What the solver minimises, given a :class:`CalibrationProblem`."""

    minimise: eqx.AbstractClassVar[bool]

    def __call__(self, problem: CalibrationProblem, u, args):
        raise NotImplementedError


class ChiSquare(AbstractObjective):
    """Poisson-weighted residuals for a least-squares solver (Gauss-Newton family)."""

    minimise: ClassVar[bool] = False

    def __call__(self, problem, u, args):
        return problem.residuals(u, args)


class PoissonDeviance(AbstractObjective):
    """The Poisson deviance per bin, a scalar for a minimiser (BFGS)."""

    minimise: ClassVar[bool] = True

    def __call__(self, problem, u, args):
        return problem.deviance(u, args)


def _check_pair(solver, objective: AbstractObjective) -> None:
    """Refuse a solver the objective cannot drive (instead of silently doing something else)."""
    if objective.minimise and not isinstance(solver, optx.AbstractMinimiser) or isinstance(solver, MarquardtLM) and objective.minimise:
        raise ConfigError(f"solver: {type(solver).__name__} is not a minimiser; PoissonDeviance needs one (e.g. optx.BFGS)")
    if not objective.minimise and not isinstance(solver, (optx.AbstractLeastSquaresSolver, MarquardtLM)):
        raise ConfigError(
            f"solver: {type(solver).__name__} is not a least-squares solver; ChiSquare needs one (e.g. optx.LevenbergMarquardt)"
        )


# ---- configuration ----------------------------------------------------------------------------


#: The largest ``quadrature``, ``angles_per_zone`` and ``elevations`` a fit config takes (the model's arrays and its
#: Jacobian grow with each; the sampling converges by 16, docs/calibration.md).
MAX_SAMPLING = 64


@dataclass(frozen=True)
class FitConfig:
    """Options of a calibration fit (TOML: keys at the top level of the file).

    - ``solver``: ``levenberg-marquardt`` (default: Levenberg-Marquardt with Marquardt's
      scaling, :class:`~tofjax.fit.solve.MarquardtLM`), ``gauss-newton``, ``dogleg``, or
      ``poisson-deviance`` (BFGS on the Poisson deviance instead of least squares). To run
      optimistix's own (unscaled) ``optx.LevenbergMarquardt``, pass it as ``solver=`` to
      :func:`calibrate`.
    - ``rtol``, ``atol``: optimistix tolerances in the unconstrained space.
    - ``loss_tol``: also stop when an accepted step lowers chi-square / 2 by less than this
      (a few hundredths of a standard error from the optimum); 0 turns it off. (A
      ``MarquardtLM(lambda_trials=...)`` passed as ``solver=`` stops instead when the Gauss-Newton
      model says less than this is left, ``0.5 g^T (J^T J)^-1 g``, and its best trial agrees.)
    - ``gauss_newton_first``: up to this many undamped Gauss-Newton steps first, with
      ``solver = "dogleg"`` only (ignored by every other ``solver``, and by a solver object passed
      as ``solver=`` unless ``solver = "dogleg"`` too; the default solver's first steps already are
      nearly Gauss-Newton steps); where they fail or do not lower the loss the solver takes over.
      0 = off.
    - ``max_steps``: per start.
    - ``free``: which parameters to fit; the rest stay at the scene's values.
    - ``zone_gain``: the gain is free per (sensor, zone), profiled out like ambient and
      crosstalk (default: a real rig's zones differ by several per cent). False: one gain
      per sensor, as the scene states it.
    - ``zone_end``: the far-edge reflectance free per (sensor, zone), profiled out like the
      gain (needs ``zone_gain``; default off). A real edge reflects differently in each zone
      (angle of incidence, polish); one shared reflectance makes the fit explain those
      differences with attenuation, which biases mu_t (on the independent simulator, whose
      edge reflectance goes with the cosine of incidence, by about +0.3 /m). Per-zone
      reflectances remove that bias but also the edge returns' information on mu_t: a
      baseline then barely pins mu_t below about 1 /m (own-data fits at 0.5 /m ended near 0),
      so it is an option, not the default. The JSON then has one reflectance per zone;
      ``Params.end_reflectance`` is their mean.
    - ``envelope``: start from the best point of an (n1, mu_t) grid of profiled
      chi-squares around the timing estimate (default); False: the timing start alone.
    - ``restarts``: further starts (the envelope's other basins first, then its next best
      points) when the fit fails or ends on a bound.
    - ``pulse_tails``: 2 (default), 1 or ``"auto"``. 2: the pulse has a second, slower tail
      whose share and time constant are fitted (``pulse_slow_weight``, ``pulse_slow_tail_s``):
      a real SPAD's response is not one exponentially modified Gaussian, and on data tofjax did
      not make a one-tail pulse leaves a reduced chi-square of 20-46. 1: one tail (the slow-tail
      parameters drop out of the default ``free``). ``"auto"``: one tail first, then a score
      test of the slow tail's share at 0 (:mod:`tofjax.fit._tails`); two tails (from the
      envelope's best start, then from the one-tail end point) only where the data support them (above
      ``pulse_tail_threshold``). Where they are absent the two-tail optimum is singular (share
      0, or both tails equal) and fits crawl (docs/calibration.md, "Straggler fits"). The
      result says which model was chosen and why (``pulse_tails``, ``pulse_tail_test``).
      Not the default: where the data do have a slow tail (every real SPAD measured so far) the
      one-tail fit that comes first crawls to its step limit (200 steps, then 15-71 two-tail
      steps, against 6-53 for ``pulse_tails = 2`` alone; docs/calibration.md).
    - ``pulse_tail_threshold``: ``"auto"``'s threshold on the one-sided score statistic z of
      the slow tail's share (the largest over slow/fast time-constant ratios 2, 4 and 8);
      default 4 (false alarms on tail-less data below 3 x 3.2e-5 by Bonferroni; a slow tail of
      share 0.1 gives z in the tens to hundreds, docs/calibration.md).
    - ``restarts`` apply to refused fits too (reduced chi-square above ``max_reduced_chi2``):
      another basin may describe the capture; the best result is kept.
    - ``quadrature``: model fidelity (time nodes per bin).
    - ``angles_per_zone``, ``elevations``: model fidelity: rays per zone, and (guided optics) quadrature nodes
      over the guided elevation band (:class:`~tofjax.model.ModelOptions`; defaults 8 and 8). On the 64x Monte
      Carlo baseline the guided model's misfit falls with them (experiments/guided_fidelity_calibration.py,
      docs/calibration.md, "The guided model's sampling"); the fit's time grows with them.
    - ``dtype``: ``float64`` (default) or ``float32`` for the model.
    - ``optics``: the forward model's optics, ``"default"`` (seed 000's in-plane light at
      ``c / n1``) or ``"guided"`` (:mod:`tofjax.model.guided`: elevations in the slab, ``1/r``
      backscatter, a Lambertian edge; what describes Monte Carlo data, docs/tradeoff.md). The
      calibration JSON records it (``optics``), and its readers build the same optics or refuse it.
    - ``max_reduced_chi2``: above this the fit is refused (``converged = false``,
      ``result = refused_reduced_chi2``): the model does not describe the capture.
    - ``model_error``: a relative error of the model added in quadrature to the photon
      noise, ``sigma^2 = max(mean, 1) / frames + (model_error x mean)^2`` (0, the default:
      photon noise only). A rig's pulse shape or near field is never exactly the model's:
      with many frames the photon noise of the bright bins (the light-entry peak, the near
      field) is far below that mismatch, and those bins then pull n1 and mu_t away; a floor
      of a few per cent lets the timing and the decay decide. The reduced chi-square is
      then relative to that floor (the JSON reports it with and without).
    - ``timing_anchor``: the n1 read from the timing of the far-edge returns enters the fit as
      a measurement with this relative width (default 2%: several times the estimator's
      scatter, far below how far amplitude errors pull n1 on data the model does not fully
      describe); 0 turns it off. Without a visible edge there is no anchor.
    - ``prior_width``: width of a weak Gaussian prior on each nonlinear parameter in the
      unconstrained space, centred on the scene's values; 0 turns it off.
    - ``basin_check_chi2``: a successful fit whose reduced chi-square is above this is not
      taken at once: the envelope's other basins (interior local minima of its chi-square
      along mu_t, among the ``1 + restarts`` starts, with an extinction more than 2x from
      every fit's end point so far) are fitted too, and the lowest chi-square wins. A
      strongly attenuating guide (4 /m) has a second basin near 0.1 /m whose chi-square
      (2.7-3.2 on the independent simulator) is under ``max_reduced_chi2`` but above the
      true basin's (1.7-2.1). Default 1.5; ``inf`` turns the check off.
    - ``fixed_score_chi2``, ``fixed_score_threshold``: where the fit's reduced chi-square is above
      ``fixed_score_chi2`` (default 1.5; 0: always, ``inf``: never), every held scalar parameter is
      score-tested at its held value (:mod:`tofjax.fit._scores`): ``z`` says how strongly the data
      want it to move, the free parameters refitted to first order, and
      ``discrepancy["fixed_parameters"]`` lists them, most contradicted first, with the value one
      Gauss-Newton step would move each to. Those with ``|z| / sqrt(reduced chi-square)`` above
      ``fixed_score_threshold`` (default 5) are ``contradicted`` (the CLI warns). A held value the
      data contradict biases the free parameters beyond their standard errors: on the Monte Carlo
      baseline the guided optics' multiple-scattering coupling, held at 0.5, put mu_a at 0.30 +- 0.01
      against 0.14 (docs/calibration.md, "Fixed parameters the data contradict"). One more
      compiled program (the Laplace Jacobian and a column per held parameter), so not on a fit
      that describes its capture.
    - ``geodesic``: the default solver adds the geodesic acceleration to its steps
      (:class:`~tofjax.fit.solve.MarquardtLM`); off by default: on the calibration study's grid
      it took more steps (its acceptance test rejects steps near the optimum, where the
      profiled residuals' curvature changes with the active set) and ended no lower, and its
      nested forward mode makes the compiled fit larger (docs/results/fit_bench.json).
    - ``secant``: the default solver adds NL2SOL's structured secant estimate of the residuals'
      own curvature to its Gauss-Newton model where it predicts better (:class:`~tofjax.fit.solve.MarquardtLM`;
      on by default): on data the model did not make the residuals are partly the model's error,
      and without it the steps zigzag along the poorly determined directions. On the independent
      simulator's default-scene baselines it took 40-48 steps against 75-131 (0.45x the time), on
      tofjax's own and on the small-scene grid about as many (docs/calibration.md, "The structured secant term").
    - ``free`` includes ``end_incidence_power`` by default: the edge's angle law
      ``R(theta) = end_reflectance cos(theta)^p`` (docs/physics.md); a scene states ``p = 0``.
    - ``free`` includes ``near_field_shape`` by default (not with ``optics = "guided"``): the
      near field's shape ``p`` in ``G = (r^p + d^p)^(-2/p)`` with ``d = near_field_m``; a scene
      states ``p = 2`` (``1/(r^2 + d^2)``). At low attenuation the decay over the first
      centimetres is as large as the attenuation's, so a rig whose near field has another
      shape biased mu_t by up to -32% at 0.05 /m with ``p`` fixed (docs/physics.md, "Near field").
    - ``precision_target_n1``, ``precision_target_mu_t``: the relative errors the precision plan
      (``CalibrationResult.precision``, :mod:`tofjax.fit._precision`) plans the baseline's
      frames for: n1 and mu_s + mu_a within them with 95% probability (photon noise only;
      defaults 1% and 25%, the issue's targets). They do not change the fit.
    """

    solver: str = "levenberg-marquardt"
    rtol: float = 1e-7
    atol: float = 1e-7
    loss_tol: float = 1e-4
    max_steps: int = 200
    gauss_newton_first: int = 10
    free: tuple[str, ...] = DEFAULT_FREE
    zone_gain: bool = True
    zone_end: bool = False
    envelope: bool = True
    restarts: int = 3
    prior_width: float = 3.0
    model_error: float = 0.0
    timing_anchor: float = 0.02
    quadrature: int = 2
    angles_per_zone: int = 8
    elevations: int = 8
    dtype: str = "float64"
    max_reduced_chi2: float = 4.0
    pulse_tails: int | str = 2
    pulse_tail_threshold: float = 4.0
    basin_check_chi2: float = dataclasses.field(default=1.5, metadata={INFINITE_OK: True})  # inf: off
    fixed_score_chi2: float = dataclasses.field(default=1.5, metadata={INFINITE_OK: True})  # inf: never
    fixed_score_threshold: float = 5.0
    optics: str = "default"
    geodesic: bool = False
    secant: bool = True
    precision_target_n1: float = 0.01
    precision_target_mu_t: float = 0.25

    def __post_init__(self):
        check_target("precision_target_n1", self.precision_target_n1)
        check_target("precision_target_mu_t", self.precision_target_mu_t)
        if self.optics not in OPTICS:
            raise ConfigError(f"optics: must be one of {', '.join(OPTICS)}, got {self.optics!r}")
        if type(self.pulse_tails) not in (int, str) or self.pulse_tails not in PULSE_TAILS:
            raise ConfigError(f"pulse_tails: must be 1, 2 or \"auto\", got {self.pulse_tails!r}")
        if self.pulse_tail_threshold <= 0:
            raise ConfigError(f"pulse_tail_threshold: must be > 0, got {self.pulse_tail_threshold!r}")
        if not isinstance(self.free, tuple):
            object.__setattr__(self, "free", tuple(self.free))
        twice = sorted({k for k in self.free if self.free.count(k) > 1})
        if twice:
            raise ConfigError(f"free: {', '.join(repr(k) for k in twice)} listed more than once")
        if self.free == DEFAULT_FREE:
            drop = (SLOW_TAIL if self.pulse_tails == 1 else ()) + (NOT_GUIDED if self.optics == "guided" else ())
            object.__setattr__(self, "free", tuple(k for k in DEFAULT_FREE if k not in drop))
        elif self.pulse_tails == 1 and any(k in SLOW_TAIL for k in self.free):
            raise ConfigError("free: pulse_slow_weight and pulse_slow_tail_s need pulse_tails = 2")
        elif self.optics == "guided" and any(k in NOT_GUIDED for k in self.free):
            raise ConfigError("free: near_field_shape is a parameter of the default optics only (optics = 'guided' has no near-field shape)")
        if self.solver not in SOLVERS:
            raise ConfigError(f"solver: must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.loss_tol < 0:
            raise ConfigError(f"loss_tol: must be >= 0, got {self.loss_tol!r}")
        if not 0 <= self.model_error < 1:
            raise ConfigError(f"model_error: must be in [0, 1), got {self.model_error!r}")
        if self.timing_anchor < 0:
            raise ConfigError(f"timing_anchor: must be >= 0, got {self.timing_anchor!r}")
        if self.prior_width < 0:
            raise ConfigError(f"prior_width: must be >= 0, got {self.prior_width!r}")
        if not self.fixed_score_chi2 >= 0:
            raise ConfigError(f"fixed_score_chi2: must be >= 0 (0: always; inf: never), got {self.fixed_score_chi2!r}")
        for k in ("rtol", "atol", "max_reduced_chi2", "basin_check_chi2", "fixed_score_threshold"):
            if getattr(self, k) <= 0:
                raise ConfigError(f"{k}: must be > 0, got {getattr(self, k)!r}")
        if self.max_steps < 1:
            raise ConfigError(f"max_steps: must be >= 1, got {self.max_steps!r}")
        if self.gauss_newton_first < 0:
            raise ConfigError(f"gauss_newton_first: must be >= 0, got {self.gauss_newton_first!r}")
        if self.restarts < 0:
            raise ConfigError(f"restarts: must be >= 0, got {self.restarts!r}")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"dtype: must be float32 or float64, got {self.dtype!r}")
        for k in ("quadrature", "angles_per_zone", "elevations"):  # the model's size grows with each
            v = getattr(self, k)
            if type(v) is not int or not 1 <= v <= MAX_SAMPLING:
                raise ConfigError(f"{k}: must be an integer in 1..{MAX_SAMPLING}, got {v!r}")
        for name in self.free:
            if name not in FITTABLE:
                raise ConfigError(f"free: {name!r} cannot be fitted; fittable: {', '.join(FITTABLE)}")
        if not self.free:
            raise ConfigError("free: at least one parameter must be free")
        if all(name in LINEAR for name in self.free):
            raise ConfigError(
                "free: at least one of n1, mu_s_per_m, mu_a_per_m, the pulse, the emission time or the "
                "reflectances must be free (gain, ambient and crosstalk alone are a linear solve, not a fit)"
            )
        if self.pulse_tails == "auto" and not all(k in self.free for k in SLOW_TAIL):
            raise ConfigError('free: pulse_tails = "auto" chooses whether to fit pulse_slow_weight and pulse_slow_tail_s: '
                              "list both, or set pulse_tails = 1")

    def make_solver(self):
        """The optimistix solver object the ``solver`` string names."""
        if self.solver == "levenberg-marquardt":
            return MarquardtLM(rtol=self.rtol, atol=self.atol, geodesic=self.geodesic, secant=self.secant)
        if self.solver == "gauss-newton":
            return optx.GaussNewton(rtol=self.rtol, atol=self.atol)
        if self.solver == "dogleg":
            return optx.Dogleg(rtol=self.rtol, atol=self.atol)
        return optx.BFGS(rtol=self.rtol, atol=self.atol)

    def make_objective(self) -> AbstractObjective:
        return PoissonDeviance() if self.solver == "poisson-deviance" else ChiSquare()

    @property
    def gn_first(self) -> int:
        # Marquardt's scaled LM (the default) takes Gauss-Newton-like steps itself
        return min(self.gauss_newton_first, self.max_steps) if self.solver == "dogleg" else 0


def load_fit_config(path) -> FitConfig:
    """Read a fit config TOML; errors name the file and the key."""
    try:
        return from_dict(FitConfig, load_toml(path))
    except ConfigError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None


# ---- checks -------------------------------------------------------------------------------


def check_baseline(capture: Capture, scene: Scene) -> None:
    """Refuse data that cannot be a usable baseline, with the reason."""
    h = capture.histograms
    if scene.shape != capture.scene.shape:
        raise CalibrationError(
            f"the scene has (sensors, zones, bins) = {scene.shape} but the capture {capture.scene.shape}"
        )
    if capture.n_frames < 1:
        raise CalibrationError("the capture has no frames")
    if not np.isfinite(h).all():
        bad = np.argwhere(~np.isfinite(h))[0]
        raise CalibrationError(f"non-finite counts (NaN or inf), first at frame {bad[0]}, sensor {bad[1]}, zone {bad[2]}")
    if (h < 0).any():
        raise CalibrationError("negative counts: these are not raw histograms")
    per_zone = h.sum(axis=(0, 3))
    if (per_zone == 0).any():
        s, z = np.argwhere(per_zone == 0)[0]
        raise CalibrationError(f"all-zero histograms (sensor {s}, zone {z}): is the sensor connected?")
    sat = scene.sensor.saturation_counts
    n_sat = int((h >= sat).sum())
    if n_sat:
        raise CalibrationError(
            f"{n_sat} bins at the saturation limit ({sat:g} counts): lower the sensor's iterations or gain"
        )


# ---- the compiled fit ------------------------------------------------------------------------


class FitSolution(NamedTuple):
    """What one compiled fit returns (a pytree: batched along a leading axis by the vmapped form)."""

    params: Params  # profiled end point (gain: mean over zones with zone_gain)
    linear: dict  # the profiled linear parameters (gain (S, Z) with zone_gain)
    result: Any  # optx.RESULTS
    steps: jax.Array
    history: jax.Array  # loss per step, NaN after the last
    chi2: jax.Array
    residuals: jax.Array  # (S, Z, B) (model - data) / sigma
    hessian: Any  # J^T J over every free coordinate (None without covariance)
    dphys: Any


def build_problem(scene: Scene, config: FitConfig = FitConfig()) -> CalibrationProblem:
    """The calibration problem of ``scene`` (touches dropped) with ``config``'s free parameters."""
    # "auto" builds the two-tail problem (every parameter); its one-tail problem is derived from it
    tails = 2 if config.pulse_tails == "auto" else config.pulse_tails
    options = ModelOptions(quadrature=config.quadrature, angles_per_zone=config.angles_per_zone,
                           elevations=config.elevations, dtype=config.dtype, pulse_tails=tails, optics=config.optics)
    if scene.noise.pile_up:
        raise CalibrationError("calibration of scenes with pile-up is not supported yet: set [noise] pile_up = false")
    base = scene.without_touches()
    model = build_model(base, options)
    return CalibrationProblem.build(
        model, default_transforms(base), config.free, zone_gain=config.zone_gain, prior_width=config.prior_width,
        zone_end=config.zone_end,
    )


def base_params(scene: Scene, config: FitConfig, dtype) -> Params:
    """The scene's parameters as a fit sees them: the prior centre, the values of fixed
    parameters and (timing aside) the start. A two-tail fit starts its slow tail at
    :data:`SLOW_WEIGHT_START` when the scene states none (a zero share has no gradient)."""
    base = Params.from_scene(scene, dtype)
    if config.pulse_tails != 1 and float(base.pulse_slow_weight) == 0.0:
        base = base.replace(pulse_slow_weight=np.asarray(SLOW_WEIGHT_START, dtype))  # NumPy: no small program to compile
    return base


def _fit_inputs(problem, start, data, sigma, prior_params, anchor):
    """``(f0, unravel, args)`` of one fit: the start's nonlinear coordinates flattened, their unravel,
    and the objective's ``args = (start, data, sigma, prior)`` (the prior holds the timing anchor).
    The start is not profiled here: the residuals profile every linear value afresh, so a profile
    of the start (what it was) changed nothing but the compiled program's size."""
    u0 = problem.pack_jax(start, problem.nonlinear)
    prior = problem.pack_jax(prior_params, problem.nonlinear)
    prior["n1_anchor"] = anchor
    f0, unravel = jax.flatten_util.ravel_pytree(u0)
    return f0, unravel, (start, data, sigma, prior)


def _solver_loss_tol(objective, loss_tol, n_data):
    """``loss_tol`` in the objective's units: the deviance loss is chi-square per bin."""
    return 2.0 * loss_tol / n_data if objective.minimise else loss_tol


def _fit(problem, objective, solver, start, data, sigma, prior_params, anchor, max_steps, loss_tol, gn_first, with_cov):
    f0, unravel, args = _fit_inputs(problem, start, data, sigma, prior_params, anchor)
    p0 = args[0]
    tol = _solver_loss_tol(objective, loss_tol, data.size)

    def flat(f, a):
        return objective(problem, unravel(f), a)

    if isinstance(solver, MarquardtLM):
        # with the covariance, the solver also keeps the profiled linear values' Jacobian: the
        # Laplace pieces then come from the fit's own Jacobians (no second forward-mode pass to compile)
        keep = with_cov and _cov_in_fit(objective, solver)
        out = solve_marquardt((lambda f, a: problem.residuals_and_linear(unravel(f), a)) if keep else flat, solver, f0, args,
                              max_steps=max_steps, loss_tol=tol)
        return _finish(problem, out, unravel, p0, data, sigma, prior_params, anchor, with_cov)
    fn = flat if objective.minimise else dense_jvp(flat)

    def main(v_start):
        return solve_with_history(fn, solver, v_start, args, max_steps=max_steps, minimise=objective.minimise, loss_tol=tol)

    if gn_first:
        # undamped Gauss-Newton steps from the start (3-6 reach the optimum where damped
        # solvers crawl along curved valleys); the configured solver runs where they fail
        gn = solve_with_history(fn, optx.GaussNewton(rtol=solver.rtol, atol=solver.atol), f0, args, max_steps=gn_first, loss_tol=tol)
        hist = gn.history
        last = hist[jnp.clip(gn.steps, 0, gn_first)]
        finite = jnp.isfinite(last) & jnp.all(jnp.isfinite(gn.value))
        ok = (gn.result == optx.RESULTS.successful) & finite & (last <= hist[0])
        better = finite & (last < hist[0])
        pad = jnp.full((max_steps + 1,), jnp.nan, hist.dtype)

        def done(_):
            return gn.value, gn.result, gn.steps, jnp.concatenate([hist[: gn_first + 1], pad])

        def fallback(_):
            o = main(jnp.where(better, gn.value, f0))
            return o.value, o.result, gn.steps + o.steps, jnp.concatenate([hist[: gn_first + 1], o.history])

        out = SolveResult(*jax.lax.cond(ok, done, fallback, None))
    else:
        out = main(f0)
    return _finish(problem, out, unravel, p0, data, sigma, prior_params, anchor, with_cov)


def _finish(problem, out: SolveResult, unravel, p0, data, sigma, prior_params, anchor, with_cov) -> FitSolution:
    """The profiled end point, its residuals and (``with_cov``) the Laplace pieces."""
    u = unravel(out.value)
    if out.keep is not None:
        # the solver kept the profiled point (residuals_and_linear): no model to evaluate here
        params, lin, parts = out.keep
        r = out.residuals[: data.size].reshape(data.shape)
    else:
        params, m, lin = problem.profiled_model(u, p0, data, sigma)
        r, parts = (m - data) / sigma, None
    hessian = dphys = None
    if with_cov and out.aux_jac is not None:
        hessian, dphys = problem.laplace_from_fit(params, lin, out.jac, out.aux_jac, sigma, parts)
    elif with_cov:
        hessian, dphys, _ = problem.laplace(params, lin, prior_params, data, sigma, anchor)
    return FitSolution(params, lin, out.result, out.steps, out.history, jnp.sum(r**2), r, hessian, dphys)


@eqx.filter_jit
def fit_problem(
    problem: CalibrationProblem,
    objective: AbstractObjective,
    solver,
    start: Params,
    data,
    sigma,
    prior_params: Params,
    anchor,
    *,
    max_steps: int = 200,
    loss_tol: float = 1e-3,
    gn_first: int = 10,
    with_cov: bool = True,
) -> FitSolution:
    """One fit from ``start`` as one compiled call (compiled once per problem structure and
    data shape, reused for every capture).

    **Arguments:** the problem, objective and solver objects; ``start`` (its nonlinear
    parameters are the starting point, the rest stay fixed); ``data`` mean histograms
    (S, Z, B) and ``sigma`` their standard deviations; ``prior_params`` the prior centre;
    ``anchor`` = (n1 from timing, its width) (width inf: none).

    **Returns:** a :class:`FitSolution`; failures are result codes, never exceptions.
    """
    return _fit(problem, objective, solver, start, data, sigma, prior_params, anchor, max_steps, loss_tol, gn_first, with_cov)


@eqx.filter_jit
def fit_problem_batch(
    problem, objective, solver, starts: Params, data, sigma, prior_params, anchors, *, max_steps=200, loss_tol=1e-3, gn_first=10, with_cov=True
) -> FitSolution:
    """:func:`fit_problem` over a batch: ``starts`` (every leaf with a leading batch axis),
    ``data`` and ``sigma`` (N, S, Z, B), ``anchors`` (N, 2), all in one compiled, vmapped call."""

    def one(s, d, g, a):
        return _fit(problem, objective, solver, s, d, g, prior_params, a, max_steps, loss_tol, gn_first, with_cov)

    return jax.vmap(one)(starts, data, sigma, anchors)


def fit_problem_loop(
    problem, objective, solver, starts: Params, data, sigma, prior_params, anchors, *, max_steps=200, loss_tol=1e-3, gn_first=10, with_cov=True
) -> FitSolution:
    """:func:`fit_problem_batch`'s arguments and result, the fits run one after the other through
    :func:`run_fit` (the program :func:`calibrate` runs, compiled once per problem structure,
    read from the program store where it is on). Each fit stops at its own step count; a vmapped
    batch runs every fit for as many steps as its slowest, and on a CPU its batched Jacobian
    costs more per fit than a single one, so on a CPU this is faster
    (``experiments/bench_fit_many.py``). Returns host (numpy) arrays."""
    n = int(np.shape(data)[0])
    outs = []
    for i in range(n):
        start = jax.tree_util.tree_map(lambda x, i=i: x[i], starts)
        sol = run_fit(problem, objective, solver, start, data[i], sigma[i], prior_params, anchors[i],
                      max_steps=max_steps, loss_tol=loss_tol, gn_first=gn_first, with_cov=with_cov)
        outs.append(jax.device_get(sol))
    return jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v) for v in x]), *outs)


class _FlatResiduals(eqx.Module):
    """The objective of :func:`_fit` on the flat coordinates, with ``args = (p0, data, sigma, prior)``:
    a module (hashed by its structure, its arrays traced), so the compacting batch's programs are
    compiled once per problem structure."""

    problem: CalibrationProblem
    objective: AbstractObjective
    keep_linear: bool = False

    def __call__(self, f, a):
        u = _unravel(self.problem, a[0])(f)
        if self.keep_linear:
            # (residuals, profiled linear values): the solver keeps both Jacobians (_cov_in_fit)
            return self.problem.residuals_and_linear(u, a)
        return self.objective(self.problem, u, a)


def _cov_in_fit(objective, solver) -> bool:
    """Whether a fit computes its Laplace pieces from its own Jacobians (:meth:`CalibrationProblem.laplace_from_fit`):
    with :class:`MarquardtLM` (it keeps the Jacobians) on the chi-square (the residuals the covariance is of).
    Otherwise a second program differentiates the residuals at the optimum (:func:`_covariance`)."""
    return isinstance(solver, MarquardtLM) and type(objective) is ChiSquare


def _unravel(problem, p0):
    return jax.flatten_util.ravel_pytree(problem.pack_jax(p0, problem.nonlinear))[1]


@eqx.filter_jit
def _prepare_batch(problem, starts, data, sigma, prior_params, anchors):
    """:func:`_fit`'s start (profiled) and arguments, for every fit of a batch."""

    def one(s, d, g, a):
        f0, _, args = _fit_inputs(problem, s, d, g, prior_params, a)
        return f0, args

    return jax.vmap(one)(starts, data, sigma, anchors)


@eqx.filter_jit
def _finish_batch(problem, out: SolveResult, args, prior_params, anchors, with_cov):
    def one(o, a, anchor):
        return _finish(problem, o, _unravel(problem, a[0]), a[0], a[1], a[2], prior_params, anchor, with_cov)

    return jax.vmap(one)(out, args, anchors)


def fit_problem_compact(
    problem, objective, solver, starts: Params, data, sigma, prior_params, anchors, *, max_steps=200, loss_tol=1e-3, gn_first=10,
    with_cov=True, options: CompactBatch = CompactBatch(), return_stats: bool = False,
):
    """:func:`fit_problem_batch`'s arguments and result, the fits that have stopped dropped from the
    batch every ``options.chunk_steps`` steps (:mod:`tofjax.fit._batch`): a vmapped batch then runs
    each fit for about its own steps, not the slowest fit's. The results are the vmapped batch's
    (the same loop body on the same state) up to the batch-size-dependent rounding of batched kernels. Compiles one program per bucket size
    (``options.buckets(n)``) besides the start and the end. Needs :class:`MarquardtLM` (its loop
    state can be resumed); any other solver runs as :func:`fit_problem_batch`.
    ``return_stats``: also return the :class:`~tofjax.fit._batch.BatchStats` (None for another solver)."""
    if not isinstance(solver, MarquardtLM):
        sol = fit_problem_batch(problem, objective, solver, starts, data, sigma, prior_params, anchors, max_steps=max_steps,
                                loss_tol=loss_tol, gn_first=gn_first, with_cov=with_cov)
        return (sol, None) if return_stats else sol
    tol = _solver_loss_tol(objective, loss_tol, data[0].size)
    f0, args = _prepare_batch(problem, starts, data, sigma, prior_params, anchors)
    residuals = _FlatResiduals(problem, objective, keep_linear=with_cov and _cov_in_fit(objective, solver))
    out, stats = solve_marquardt_compact(residuals, solver, f0, args, max_steps=max_steps, loss_tol=tol,
                                         options=options)
    sol = _finish_batch(problem, out, args, prior_params, anchors, with_cov)
    return (sol, stats) if return_stats else sol


def default_fit_batch():
    """The batch function :func:`calibrate_many` uses unless given one: :func:`fit_problem_compact`
    (vmapped calls that drop the fits that have stopped) where the default backend is an
    accelerator, :func:`fit_problem_loop` (one fit after the other) on a CPU, where a vmapped call
    is the slower (measured: ``experiments/bench_fit_many.py``, README "Many fits in one call";
    ``experiments/bench_batch_compact.py``). The compacting batch runs fewer lane-steps than the
    plain vmapped call (:func:`fit_problem_batch`) whenever the fits' step counts differ
    (docs/calibration.md, "A batch that drops the finished fits")."""
    return fit_problem_loop if jax.default_backend() == "cpu" else fit_problem_compact


def _fit_positional(problem, objective, solver, start, data, sigma, prior_params, anchor, max_steps, loss_tol, gn_first, with_cov):
    return fit_problem(problem, objective, solver, start, data, sigma, prior_params, anchor,
                       max_steps=max_steps, loss_tol=loss_tol, gn_first=gn_first, with_cov=with_cov)


def _solution_to_plain(sol: FitSolution):
    result_leaves = jax.tree_util.tree_leaves(sol.result)
    if len(result_leaves) != 1:
        raise TypeError("unexpected result code structure")
    return (jax.tree_util.tree_leaves(sol.params), sol.linear, result_leaves[0], sol.steps, sol.history, sol.chi2,
            sol.residuals, sol.hessian, sol.dphys)


def _solution_from_plain(plain, args) -> FitSolution:
    params_leaves, linear, code, *rest = plain
    params = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(args[3]), params_leaves)
    result = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(optx.RESULTS.successful), [code])
    return FitSolution(params, linear, result, *rest)


@eqx.filter_jit
def _covariance(problem, params, linear, prior_params, data, sigma, anchor):
    """The Laplace pieces of :func:`_finish` (``J^T J`` and d(physical)/d(coordinates)) as a program of their own."""
    hessian, dphys, _ = problem.laplace(params, linear, prior_params, data, sigma, anchor)
    return hessian, dphys


def _fit_args(problem, objective, solver, start, data, sigma, prior_params, anchor, max_steps, loss_tol, gn_first, with_cov=True):
    # the stored fit holds the Laplace pieces only where it computes them from its own Jacobians
    # (_cov_in_fit); otherwise they are a second program (see run_fit)
    return (problem, objective, solver, start, data, sigma, prior_params, anchor, max_steps, loss_tol, gn_first,
            with_cov and _cov_in_fit(objective, solver))


def run_fit(problem, objective, solver, start, data, sigma, prior_params, anchor, *, max_steps=200, loss_tol=1e-3,
            gn_first=10, with_cov=True) -> FitSolution:
    """:func:`fit_problem` through the program store (:func:`tofjax.compile_cache.call_stored`):
    where the CLI (or :func:`tofjax.enable_compilation_cache`) turned the store on, a new process
    reads the compiled fit from disk instead of tracing and compiling it again; otherwise it is
    ``fit_problem``.

    With :class:`MarquardtLM` on the chi-square (the default) the fit computes its Laplace pieces
    (``with_cov``) from its own Jacobians at the optimum, in the same program
    (:meth:`CalibrationProblem.laplace_from_fit`). With another solver they are a second program
    that differentiates the residuals again: the fit is dispatched before that program is read
    from the store, so that reading overlaps the fit's run (and a fit without covariance never
    reads it)."""
    args = _fit_args(problem, objective, solver, start, data, sigma, prior_params, anchor, max_steps, loss_tol, gn_first, with_cov)
    sol = call_stored("calibration fit", _fit_positional, args, to_plain=_solution_to_plain, from_plain=_solution_from_plain)
    if not with_cov or args[-1]:
        return sol
    hessian, dphys = call_stored(
        "calibration covariance", _covariance, (problem, sol.params, sol.linear, prior_params, data, sigma, anchor),
        to_plain=lambda x: x, from_plain=lambda plain, _: tuple(plain),
    )
    return sol._replace(hessian=hessian, dphys=dphys)


def _prefetch_fit(problem, objective, solver, base: Params, data, sigma, config: FitConfig) -> bool:
    """Start reading the stored fit's executable (:func:`tofjax.compile_cache.prefetch`) while the
    start stages run: its key depends on the arguments' shapes only, so ``base`` stands in for the
    start and a placeholder for the timing anchor."""
    anchor = np.zeros(2, np.dtype(data.dtype))
    return prefetch("calibration fit", _fit_args(problem, objective, solver, base, data, sigma, base, anchor,
                                                 config.max_steps, config.loss_tol, config.gn_first, True))


def _compile_fit_ahead(problem, objective, solver, base: Params, data, sigma, config: FitConfig) -> bool:
    """Compile the fit and its Laplace pieces on background threads while the start stages
    run (:func:`tofjax.compile_cache.compile_ahead`; where the program store is off). The
    programs depend on the arguments' shapes only, so ``base`` stands in for the start and the
    prior, zeros for the timing anchor, and the fit's output shapes (``eqx.filter_eval_shape``)
    for the covariance's parameters."""
    dt = np.dtype(data.dtype)
    in_fit = _cov_in_fit(objective, solver)  # the fit computes its Laplace pieces itself: one program
    kw = dict(max_steps=config.max_steps, loss_tol=config.loss_tol, gn_first=config.gn_first, with_cov=in_fit)

    def fit_args():
        return (problem, objective, solver, base, data, sigma, base, jax.device_put(np.zeros(2, dt)))

    def compile_fit():
        return fit_problem.lower(*fit_args(), **kw).compile()

    def compile_cov():
        args = fit_args()
        out = eqx.filter_eval_shape(fit_problem, *args, **kw)

        def zeros(tree):
            return jax.tree_util.tree_map(lambda x: jax.device_put(np.zeros(x.shape, x.dtype)), tree)

        return _covariance.lower(problem, zeros(out.params), zeros(out.linear), base, data, sigma, args[7]).compile()

    started = compile_ahead("calibration fit", compile_fit)
    if in_fit:
        return started
    return compile_ahead("calibration covariance", compile_cov) or started


# ---- from a capture to a result -----------------------------------------------------------------


def _code(result) -> int:
    """An optimistix result code as an int, read on the host (comparing the enumeration items
    themselves dispatches, and in a new process compiles, a small JAX program)."""
    return int(np.asarray(jax.tree_util.tree_leaves(result)[0]))


def _result_name(code) -> str:
    c = _code(code)
    for name in ("successful", "nonlinear_max_steps_reached", "nonlinear_divergence", "nonfinite", "singular"):
        if hasattr(optx.RESULTS, name) and c == _code(getattr(optx.RESULTS, name)):
            return name
    return "failed"


def _on_bound(problem: CalibrationProblem, scene: Scene, params: Params, linear: dict) -> list[str]:
    """Parameters at the edge of their range: a fit that should be restarted elsewhere."""
    out = []
    free = problem.free
    if "n1" in free and not (1.02 < float(params.n1) < 3.9):
        out.append("n1")
    window = scene.sensor.n_bins * scene.sensor.bin_width_s
    if "emission_time_s" in free and not (0.005 * window < float(params.emission_time_s) < 0.995 * window):
        out.append("emission_time_s")
    if "mu_s_per_m" in free and float(params.mu_s_per_m + params.mu_a_per_m) > 1e3:
        out.append("mu_s_per_m + mu_a_per_m")
    if "end_reflectance" in free and not problem.zone_end and float(params.end_reflectance) > 0.999:
        out.append("end_reflectance")
    g = np.asarray(linear.get("gain", params.gain))
    if "gain" in free and np.mean(g <= 0) > 0.25:
        out.append("gain")
    return out


def _assemble(problem, scene, config, sol: FitSolution, frames: int, stages, fingerprint) -> CalibrationResult:
    """A :class:`CalibrationResult` from one (host-side) :class:`FitSolution`."""
    params, lin = sol.params, dict(sol.linear)
    ok = _code(sol.result) == _code(optx.RESULTS.successful)
    bound = _on_bound(problem, scene, params, lin)
    n_free = int(sum(np.size(lin[k]) if k in lin else np.size(getattr(params, k)) for k in problem.free))
    residuals = np.asarray(sol.residuals, np.float64)
    dof = max(int(residuals.size) - n_free, 1)
    reduced = float(sol.chi2) / dof
    physical = {k: np.asarray(lin[k] if k in lin else getattr(params, k), np.float64) for k in problem.free}
    cov, labels, stderr, interval, u_stderr = laplace_covariance(problem, physical, sol.hessian, sol.dphys)
    if not ok:
        code = _result_name(sol.result)
    elif bound:
        code = "on_bound"
    elif reduced > config.max_reduced_chi2:
        code = "refused_reduced_chi2"
    else:
        code = "successful"
    h = np.asarray(sol.history)
    values = {k: physical[k] for k in problem.free}
    plan = precision_plan(values, cov, labels, frames, n1=config.precision_target_n1, mu_t=config.precision_target_mu_t,
                          model_error=config.model_error)
    return CalibrationResult(
        params=params,
        free=tuple(problem.free),
        values=values,
        stderr={k: stderr[k] for k in problem.free},
        interval95={k: interval[k] for k in problem.free},
        covariance=cov,
        labels=labels,
        converged=code == "successful",
        result=code,
        steps=int(sol.steps),
        reduced_chi2=reduced,
        loss_history=h[np.isfinite(h)].tolist(),
        solver=config.solver,
        frames=frames,
        stages=stages,
        unconstrained_stderr=u_stderr,
        solver_converged=ok,
        scene_fingerprint=fingerprint,
        discrepancy=discrepancy_report(residuals, scene.sensor.bin_width_s),
        on_bound=bound,
        residuals=residuals,
        optics=config.optics,
        precision=plan,
        data_share=data_shares(problem, physical, sol.hessian),
    )


def _data(capture: Capture, dtype, model_error: float = 0.0):
    """Mean histograms and their standard deviations (photon noise, and ``model_error``)."""
    mean = capture.mean()
    var = np.maximum(mean, 1.0) / capture.n_frames + (model_error * mean) ** 2
    return jnp.asarray(mean, dtype), jnp.asarray(np.sqrt(var), dtype)


def _anchor(start: Params, found: bool, config: FitConfig, dtype):
    """(n1 from timing, its width): the timing measurement the fit keeps (width inf: none)."""
    n1 = float(start.n1)
    width = config.timing_anchor * n1 if (found and config.timing_anchor > 0) else np.inf
    return jax.device_put(np.asarray([n1, width], dtype))  # a transfer: jnp.asarray would compile a small program


def _mu_t(p: Params) -> float:
    """mu_s + mu_a on the host (same dtype, same rounding as the JAX sum, without compiling it)."""
    return float(np.asarray(p.mu_s_per_m) + np.asarray(p.mu_a_per_m))


def _rank(res: CalibrationResult) -> tuple:
    """Order of preference among restarts: usable first, then solver-converged, then chi-square."""
    return (res.result != "successful", not res.solver_converged, res.result == "on_bound", res.reduced_chi2)


def calibrate(
    capture: Capture,
    config: FitConfig = FitConfig(),
    *,
    scene: Scene | None = None,
    solver=None,
    objective: AbstractObjective | None = None,
    problem: CalibrationProblem | None = None,
) -> CalibrationResult:
    """Fit the scene's optical and nuisance parameters to a baseline capture.

    **Arguments:**

    - ``capture``: a baseline (no touch), any number of frames; they are averaged.
    - ``config``: tolerances, free parameters, starts (:class:`FitConfig`).
    - ``scene``: the scene to start from (default: the capture's own).
    - ``solver``, ``objective``: optimistix solver and :class:`AbstractObjective` objects
      (default: from ``config``); a solver the objective cannot drive is refused.
    - ``problem``: a prebuilt :func:`build_problem` (saves rebuilding the model).

    **Returns:** a :class:`CalibrationResult`. ``converged`` is True only when ``result`` is
    ``successful``: a fit that ran out of steps, ends on a bound after every restart, or
    whose reduced chi-square exceeds ``max_reduced_chi2`` is never reported as converged.

    Raises :class:`CalibrationError` for data that cannot be a baseline.
    """
    scene = (scene or capture.scene).without_touches()
    check_baseline(capture, scene)
    problem = build_problem(scene, config) if problem is None else problem
    solver = config.make_solver() if solver is None else solver
    objective = config.make_objective() if objective is None else objective
    _check_pair(solver, objective)
    dtype = problem.model.geometry.ray_length.dtype
    data, sigma = _data(capture, dtype, config.model_error)
    fingerprint = scene_fingerprint(scene)
    if config.pulse_tails == "auto":
        return _calibrate_auto(capture, config, scene, problem, solver, objective, data, sigma, fingerprint)
    base = base_params(scene, config, dtype)
    if not _prefetch_fit(problem, objective, solver, base, data, sigma, config):
        _compile_fit_ahead(problem, objective, solver, base, data, sigma, config)
    start, found, anchor, candidates, n_basins, stages = _starts(problem, config, scene, capture, data, sigma, base)
    best = _fit_starts(problem, config, scene, objective, solver, candidates, n_basins, data, sigma, base, anchor,
                       capture.n_frames, stages, fingerprint)
    held = _hold_n1_at_timing(best, problem, scene, config, objective, solver, start, found, data, sigma, base, capture.n_frames, stages, fingerprint)
    if held is not None:
        best = held
    best.stages = stages
    best.pulse_tails = config.pulse_tails
    _score_fixed(best, problem, config, data, sigma, base, anchor)
    return best


def _score_fixed(res: CalibrationResult, problem, config: FitConfig, data, sigma, base, anchor) -> None:
    """Where ``res`` misfits (reduced chi-square above ``config.fixed_score_chi2``), score-test its held scalar
    parameters (:func:`~tofjax.fit._scores.fixed_score_record`) into ``res.discrepancy["fixed_parameters"]``."""
    if not res.reduced_chi2 > config.fixed_score_chi2 or not np.isfinite(res.reduced_chi2):
        return
    linear = {k: res.values[k] for k in problem.linear}
    res.discrepancy["fixed_parameters"] = fixed_score_record(problem, res.params, linear, base, data, sigma, anchor,
                                                             res.reduced_chi2, config.fixed_score_threshold)


def _starts(problem, config, scene, capture, data, sigma, base):
    """Timing, then the envelope: ``(start, found, anchor, candidates, n_basins, stages)``."""
    dtype = problem.model.geometry.ray_length.dtype
    start, found = timing_start(problem, np.asarray(data), capture.n_frames, scene, base)
    anchor = _anchor(start, found, config, dtype)
    stages: list[dict[str, Any]] = [{"stage": "timing", "n1": float(start.n1), "emission_time_s": float(start.emission_time_s)}]
    if config.envelope and any(k in problem.nonlinear for k in ("n1", "mu_s_per_m", "mu_a_per_m")):
        candidates, n_basins = envelope_candidates(problem, start, data, sigma, 1 + config.restarts, with_basins=True)
        stages.append(
            {"stage": "envelope", "starts": [{"n1": float(c.n1), "mu_t_per_m": _mu_t(c)} for c in candidates]}
        )
    else:
        candidates, n_basins = [start], 1
    return start, found, anchor, candidates, n_basins, stages


def _fit_starts(problem, config, scene, objective, solver, candidates, n_basins, data, sigma, base, anchor, frames, stages,
                fingerprint, *, label: str = "", done=()):
    """Fit from each start in turn until one is usable (the restarts and the basin check); the
    best by :func:`_rank`. ``done``: results of the first starts, already fitted."""
    best = None
    ends: list[float] = []  # mu_t at the end of every fit so far
    for k, s in enumerate(candidates):
        if k < len(done):
            res = done[k]
        else:
            if best is not None and best.result == "successful":
                # the basin check: only the other basins' starts, away from every fit's end so far
                mt = _mu_t(s)
                if k >= n_basins or any(abs(np.log(mt / max(e, 1e-12))) < np.log(2.0) for e in ends):
                    continue
            sol = run_fit(
                problem, objective, solver, s, data, sigma, base, anchor,
                max_steps=config.max_steps, loss_tol=config.loss_tol, gn_first=config.gn_first, with_cov=True,
            )
            sol = jax.device_get(sol)
            res = _assemble(problem, scene, config, sol, frames, stages, fingerprint)
            stages.append(
                {"stage": f"fit from start {k}{label}", "steps": res.steps, "result": res.result, "reduced_chi2": res.reduced_chi2,
                 "n1": float(res.params.n1), "mu_t_per_m": float(res.params.mu_s_per_m + res.params.mu_a_per_m),
                 "on_bound": res.on_bound}
            )
        ends.append(float(res.params.mu_s_per_m + res.params.mu_a_per_m))
        if best is None or _rank(res) < _rank(best):
            best = res
        if best.result == "successful" and best.reduced_chi2 <= config.basin_check_chi2:
            break
        # a failure, a bound, a refused chi-square or a chi-square above the basin check:
        # the next start is another basin
    return best


def tail_configs(config: FitConfig) -> tuple[FitConfig, FitConfig]:
    """The one-tail and two-tail configs ``pulse_tails = "auto"`` chooses between."""
    one = dataclasses.replace(config, pulse_tails=1, free=tuple(k for k in config.free if k not in SLOW_TAIL))
    return one, dataclasses.replace(config, pulse_tails=2)


def _tail_test(one, params, linear, data, sigma, base1, anchor, config) -> dict:
    """:func:`~tofjax.fit._tails.tail_test` at a one-tail end point (``linear``: its profiled values)."""
    return tail_test(one, two_tail_problem(one, one.free), params, linear, base1, data, sigma, anchor,
                     config.pulse_tail_threshold)


def _two_tail_start(p: Params, test: dict) -> Params:
    return p.replace(pulse_slow_weight=np.asarray(test["slow_weight_start"]), pulse_slow_tail_s=np.asarray(test["slow_tail_start_s"]))


def _with_slow_tail_of(p: Params, base2: Params) -> Params:
    """A one-tail start ``p`` made a two-tail one with the slow tail of ``base2`` (the scene's)."""
    return p.replace(**{k: getattr(base2, k) for k in SLOW_TAIL})


def _calibrate_auto(capture, config, scene, two, solver, objective, data, sigma, fingerprint):
    """``pulse_tails = "auto"``: one tail from the first start; the score test there; then either
    the one-tail calibration's restarts, or the two-tail calibration from the envelope's best
    start, then the one-tail end point, then the envelope's other starts."""
    cfg1, cfg2 = tail_configs(config)
    one = one_tail_problem(two, cfg1.free)
    dtype = two.model.geometry.ray_length.dtype
    base1, base2 = base_params(scene, cfg1, dtype), base_params(scene, cfg2, dtype)
    frames = capture.n_frames
    if not _prefetch_fit(one, objective, solver, base1, data, sigma, cfg1):
        _compile_fit_ahead(one, objective, solver, base1, data, sigma, cfg1)
    start, found, anchor, candidates, n_basins, stages = _starts(one, cfg1, scene, capture, data, sigma, base1)
    first = _fit_starts(one, cfg1, scene, objective, solver, candidates[:1], 1, data, sigma, base1, anchor, frames, stages,
                        fingerprint, label=" (1 tail)")
    test = _tail_test(one, first.params, {k: first.values[k] for k in one.linear}, data, sigma, base1, anchor, config)
    stages.append({"stage": "pulse tails", **test})
    if not test["two_tails"]:
        problem, cfg, base = one, cfg1, base1
        best = _fit_starts(one, cfg1, scene, objective, solver, candidates, n_basins, data, sigma, base1, anchor, frames, stages,
                           fingerprint, label=" (1 tail)", done=(first,))
    else:
        problem, cfg, base = two, cfg2, base2
        # the envelope's best start first, as pulse_tails = 2 starts, then the one-tail end point: a
        # one-tail fit on data with a slow tail bends the near field and the optics to mimic it (on
        # the small test scene, once converged: near field 0.11 m, shape 9, n1 1.379), and two
        # tails fitted from there stayed in that basin (reduced chi-square 3.63 against 1.07)
        starts = [_with_slow_tail_of(c, base2) for c in candidates]
        starts = starts[:1] + [_two_tail_start(first.params, test)] + starts[1:]
        best = _fit_starts(two, cfg2, scene, objective, solver, starts, n_basins + 1, data, sigma, base2, anchor, frames, stages,
                           fingerprint, label=" (2 tails)")
    held = _hold_n1_at_timing(best, problem, scene, cfg, objective, solver, start, found, data, sigma, base, frames, stages, fingerprint)
    if held is not None:
        best = held
    best.stages = stages
    best.pulse_tails = 2 if test["two_tails"] else 1
    best.pulse_tail_test = test
    _score_fixed(best, problem, cfg, data, sigma, base, anchor)
    return best


def _hold_n1_at_timing(best, problem, scene, config, objective, solver, start, found, data, sigma, base, frames, stages, fingerprint):
    """Where the model does not describe the data (refused chi-square), amplitude errors pull n1;
    the timing of the edge returns does not depend on them. If the joint fit left the timing
    estimate by more than the anchor's width (``timing_anchor``: the fit is then inconsistent with
    the timing measurement it carries), refit with n1 held at the timing estimate (the result stays
    refused; n1 is then the timing's, as the stages say). Within that width the joint fit keeps its
    n1: the anchor is already in it. (The rule was a tenth of the width: on the 64x Monte Carlo
    baseline the timing estimate is 0.5% off and the joint fit 0.01%, and the held refit, where it
    converged, replaced a reduced chi-square of 5.50 by 9.88; docs/calibration.md.)"""
    if best.result != "refused_reduced_chi2" or not found or "n1" not in problem.nonlinear or not config.timing_anchor:
        return None
    n1_t = float(start.n1)
    if abs(float(best.params.n1) / n1_t - 1) <= config.timing_anchor:
        return None
    cfg = dataclasses.replace(config, free=tuple(k for k in config.free if k != "n1"))
    p2 = CalibrationProblem.build(
        problem.model, dict(problem.transforms), cfg.free, zone_gain=config.zone_gain, prior_width=config.prior_width,
        zone_end=config.zone_end,
    )
    s2 = best.params.replace(n1=n1_t)
    no_anchor = jnp.asarray([n1_t, np.inf], data.dtype)
    sol = jax.device_get(
        run_fit(p2, objective, solver, s2, data, sigma, base.replace(n1=n1_t), no_anchor,
                    max_steps=config.max_steps, loss_tol=config.loss_tol, gn_first=config.gn_first, with_cov=True)
    )
    res = _assemble(p2, scene, cfg, sol, frames, stages, fingerprint)
    stages.append({"stage": "n1 held at the timing estimate", "n1": n1_t, "result": res.result, "reduced_chi2": res.reduced_chi2})
    if res.result not in ("refused_reduced_chi2", "successful"):
        return None
    res.free, res.solver_converged = tuple(p2.free), res.solver_converged
    return res


def calibrate_many(
    captures: list[Capture],
    config: FitConfig = FitConfig(),
    *,
    scene: Scene | None = None,
    restart_failures: bool = True,
    fit_batch=None,
) -> list[CalibrationResult]:
    """:func:`calibrate` for many captures of one scene, from the same kind of start (timing, then
    the best envelope point), the failures and refusals then refitted one by one with restarts unless
    ``restart_failures`` is False. ``fit_batch`` runs the fits (:func:`fit_problem_batch`'s
    signature): by default :func:`default_fit_batch` (the compacting vmapped batch on an accelerator,
    one fit after the other on a CPU); :func:`fit_problem_batch` forces the one vmapped call,
    :func:`fit_problem_compact` the compacting batch (``functools.partial(fit_problem_compact,
    options=CompactBatch(...))`` for other options),
    :func:`tofjax.parallel.sharded_fit_batch` spreads it over devices. Each result's misfit is scored against
    its held parameters as :func:`calibrate` scores it (``config.fixed_score_chi2``)."""
    scene = (scene or captures[0].scene).without_touches()
    for c in captures:
        check_baseline(c, scene)
    problem = build_problem(scene, config)
    solver, objective = config.make_solver(), config.make_objective()
    _check_pair(solver, objective)
    auto = config.pulse_tails == "auto"
    cfg1 = tail_configs(config)[0] if auto else config
    first = one_tail_problem(problem, cfg1.free) if auto else problem
    dtype = problem.model.geometry.ray_length.dtype
    base = base_params(scene, cfg1, dtype)
    pairs = [_data(c, dtype, config.model_error) for c in captures]
    timed = [timing_start(first, np.asarray(d), c.n_frames, scene, base) for (d, _), c in zip(pairs, captures)]
    starts = [s for s, _ in timed]
    anchors = jnp.stack([_anchor(s, f, config, dtype) for s, f in timed])
    if config.envelope and any(k in first.nonlinear for k in ("n1", "mu_s_per_m", "mu_a_per_m")):
        starts = [envelope_candidates(first, s, d, g, 1)[0] for s, (d, g) in zip(starts, pairs)]
    stack = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *starts)
    data = jnp.stack([d for d, _ in pairs])
    sigma = jnp.stack([g for _, g in pairs])
    fits = fit_batch_tails(problem, config, objective, solver, stack, data, sigma, anchors,
                           default_fit_batch() if fit_batch is None else fit_batch, scene=scene)
    fingerprint = scene_fingerprint(scene)
    out = []
    for i, (c, f) in enumerate(zip(captures, fits)):
        res = _assemble(f.problem, scene, f.config, f.solution, c.n_frames, f.stages, fingerprint)
        res.pulse_tails, res.pulse_tail_test = f.config.pulse_tails, f.test
        # as calibrate does: a refused fit too is refitted with restarts (another basin may
        # describe the capture: a wrong held pulse width's first basin ends at a reduced
        # chi-square of 25.8, its restarts at 10.2), and a successful one above the basin check
        if restart_failures and (res.result != "successful" or res.reduced_chi2 > config.basin_check_chi2):
            res = calibrate(c, config, scene=scene, problem=problem)  # scores its held parameters itself
        else:
            _score_fixed(res, f.problem, f.config, data[i], sigma[i], base_params(scene, f.config, dtype), anchors[i])
        out.append(res)
    return out


class BatchFit(NamedTuple):
    """One fit of :func:`fit_batch_tails`: the problem and config of the model it ended with
    (with ``"auto"``: the chosen one), its host :class:`FitSolution`, the tail test (None
    without ``"auto"``) and its stages (steps of each)."""

    problem: CalibrationProblem
    config: FitConfig
    solution: FitSolution
    test: dict | None
    stages: list


def fit_batch_tails(problem, config: FitConfig, objective, solver, starts: Params, data, sigma, anchors, fit_batch, *,
                    scene: Scene, with_cov: bool = True) -> list[BatchFit]:
    """Many fits with ``config.pulse_tails``'s rule, through ``fit_batch``
    (:func:`fit_problem_batch`'s signature; :func:`fit_problem_loop` on a CPU).

    With ``"auto"``: one tail for every fit (``starts`` are one-tail starts; ``problem`` is
    :func:`build_problem`'s two-tail problem), the score test per fit at its end point (one call
    per fit after :func:`fit_problem_loop`, as :func:`calibrate` makes it; every fit's in one
    vmapped call after any other batch function), then one batch of two-tail fits for the fits
    that need them, each from its own start with the scene's slow tail (as :func:`calibrate`'s first
    two-tail start).
    Otherwise one batch of ``problem``. Returns one :class:`BatchFit` per fit (``with_cov``: with
    the Laplace pieces; the test computes its own)."""
    kw = dict(max_steps=config.max_steps, loss_tol=config.loss_tol, gn_first=config.gn_first, with_cov=with_cov)
    dtype = problem.model.geometry.ray_length.dtype
    if config.pulse_tails != "auto":
        base = base_params(scene, config, dtype)
        sols = jax.device_get(fit_batch(problem, objective, solver, starts, data, sigma, base, anchors, **kw))
        return [BatchFit(problem, config, _row(sols, i), None, [{"stage": "batch", "steps": int(np.asarray(sols.steps)[i])}])
                for i in range(int(np.shape(data)[0]))]
    cfg1, cfg2 = tail_configs(config)
    one = one_tail_problem(problem, cfg1.free)
    base1, base2 = base_params(scene, cfg1, dtype), base_params(scene, cfg2, dtype)
    sols1 = jax.device_get(fit_batch(one, objective, solver, starts, data, sigma, base1, anchors, **kw))
    n = int(np.shape(data)[0])
    scored = two_tail_problem(one, one.free)
    thr = config.pulse_tail_threshold
    if fit_batch is fit_problem_loop:  # one fit after the other: one test after the other
        tests = [tail_test(one, scored, r.params, r.linear, base1, data[i], sigma[i], anchors[i], thr)
                 for i, r in ((i, _row(sols1, i)) for i in range(n))]
    else:  # a batch on an accelerator: every fit's test in one vmapped call
        tests = tail_tests(one, scored, sols1.params, sols1.linear, base1, data, sigma, anchors, thr)
    out = []
    for i in range(n):
        sol = _row(sols1, i)
        test = tests[i]
        stages = [{"stage": "batch (1 tail)", "steps": int(sol.steps), "result": _result_name(sol.result)},
                  {"stage": "pulse tails", **test}]
        out.append(BatchFit(one, cfg1, sol, test, stages))
    two = [i for i in range(n) if out[i].test["two_tails"]]
    if two:
        # from the batch's own starts, as calibrate's first two-tail start (not the one-tail end
        # points: a converged one-tail fit can bend the near field to mimic the slow tail)
        starts2 = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[_with_slow_tail_of(_row(starts, i), base2) for i in two])
        idx = np.asarray(two)
        sols2 = jax.device_get(fit_batch(problem, objective, solver, starts2, data[idx], sigma[idx], base2, anchors[idx], **kw))
        for k, i in enumerate(two):
            sol = _row(sols2, k)
            stages = out[i].stages + [{"stage": "batch (2 tails)", "steps": int(sol.steps), "result": _result_name(sol.result)}]
            out[i] = BatchFit(problem, cfg2, sol, out[i].test, stages)
    return out


def _row(stacked, i: int):
    """Entry ``i`` of a pytree stacked along its leading axis (a batch's solutions or starts)."""
    return jax.tree_util.tree_map(lambda x: x[i], stacked)


class Calibrator:
    """A scene and a config with their problem built once: ``Calibrator(scene, config).fit(capture)``.

    Holds no data: :meth:`fit` is :func:`calibrate` with the prebuilt problem (the compiled
    fit is cached by ``eqx.filter_jit`` on the problem's structure, not on this object).
    With ``pulse_tails = "auto"`` ``problem`` and :meth:`base_params` are the two-tail ones (every
    parameter; the one-tail problem is derived from them); :meth:`for_result` gives the
    calibrator of the model a fit chose.
    """

    def __init__(self, scene: Scene, config: FitConfig = FitConfig()):
        self.scene = scene.without_touches()
        self.config = config
        self.problem = build_problem(self.scene, config)

    def base_params(self) -> Params:
        """The scene's own parameters: the prior centre and the values of fixed parameters."""
        return base_params(self.scene, self.config, self.problem.model.geometry.ray_length.dtype)

    def fit(self, capture: Capture) -> CalibrationResult:
        return calibrate(capture, self.config, scene=self.scene, problem=self.problem)

    def for_result(self, fit: CalibrationResult) -> "Calibrator":
        """The calibrator of the model ``fit`` ended with: itself, or with ``pulse_tails = "auto"``
        one whose config and problem have the tails the fit chose (what its posterior samples)."""
        if self.config.pulse_tails != "auto":
            return self
        cfg = tail_configs(self.config)[fit.pulse_tails - 1]
        out = object.__new__(Calibrator)
        out.scene, out.config = self.scene, cfg
        out.problem = self.problem if fit.pulse_tails == 2 else one_tail_problem(self.problem, cfg.free)
        return out

    def fit_many(self, captures: list[Capture], restart_failures: bool = True) -> list[CalibrationResult]:
        return calibrate_many(captures, self.config, scene=self.scene, restart_failures=restart_failures)
