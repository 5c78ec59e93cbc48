"""Calibration: fit the optics and nuisance parameters of a scene to a baseline capture.

The public API is what this module re-exports; the modules with a leading underscore are
its parts (problem, start, Laplace covariance, result, discrepancy report).
"""

from ._problem import CalibrationProblem as CalibrationProblem
from ._result import CalibrationError as CalibrationError
from ._result import CalibrationRefused as CalibrationRefused
from ._result import CalibrationResult as CalibrationResult
from ._batch import BatchStats as BatchStats
from ._batch import CompactBatch as CompactBatch
from ._precision import PrecisionPlan as PrecisionPlan
from ._precision import precision_plan as precision_plan
from ._result import load_calibration as load_calibration
from ._result import load_precision_plan as load_precision_plan
from ._result import scene_fingerprint as scene_fingerprint
from .calibrate import AbstractObjective as AbstractObjective
from .calibrate import Calibrator as Calibrator
from .calibrate import ChiSquare as ChiSquare
from .calibrate import FitConfig as FitConfig
from .calibrate import FitSolution as FitSolution
from .calibrate import PoissonDeviance as PoissonDeviance
from .calibrate import build_problem as build_problem
from .calibrate import calibrate as calibrate
from .calibrate import calibrate_many as calibrate_many
from .calibrate import fit_problem as fit_problem
from .calibrate import default_fit_batch as default_fit_batch
from .calibrate import fit_problem_batch as fit_problem_batch
from .calibrate import fit_problem_compact as fit_problem_compact
from .calibrate import fit_problem_loop as fit_problem_loop
