"""The differentiable forward model of light in the waveguide (seed 000, Eq. 2-5)."""

from .components import SPEED_OF_LIGHT_M_PER_S as SPEED_OF_LIGHT_M_PER_S
from .forward import ForwardModel as ForwardModel
from .forward import OPTICS as OPTICS
from .forward import ModelOptions as ModelOptions
from .forward import build_model as build_model
from .forward import pile_up as pile_up
from .geometry import Geometry as Geometry
from .noise import sample_counts as sample_counts
from .noise import sample_frames as sample_frames
from .params import Params as Params
from .params import speed_in_guide as speed_in_guide
from .pulse import emg_cdf as emg_cdf
from .pulse import emg_pdf as emg_pdf
