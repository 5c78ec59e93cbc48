"""Touch inversion (seed 000 sections 3-5 and beyond): signal correction (Algorithm 1),
tactile maps (Eq. 8), touch detection, model-based reconstruction, dynamic baseline and
uncertainty. See ``docs/inversion.md``."""

from .correction import METHODS as METHODS
from .correction import CorrectionOptions as CorrectionOptions
from .correction import InversionError as InversionError
from .correction import OpticalParams as OpticalParams
from .correction import build_corrector as build_corrector
from .detect import DetectOptions as DetectOptions
from .detect import detect as detect
from .detect import match as match
from .maps import Grid as Grid
from .maps import MapOptions as MapOptions
from .maps import build_map_operator as build_map_operator
from .pipeline import InvertOptions as InvertOptions
from .pipeline import build_inverter as build_inverter
from .pipeline import process_captures as process_captures
