"""tofjax: a JAX framework for time-of-flight FTIR tactile sensors.

Precision is never changed on import: call :func:`enable_x64` at your entry
point (the CLI does) when fitting or differentiating in float64. Likewise the
persistent compilation cache: the CLI turns it on, library users call
:func:`enable_compilation_cache` (see :mod:`tofjax.compile_cache`); and the
CPU compiler: :func:`use_fast_cpu_compiler` before any JAX computation (the CLI
and the tests do; a cold calibration compiles about 1.4x faster).
"""

from .compile_cache import enable_compilation_cache as enable_compilation_cache
from .compile_cache import use_fast_cpu_compiler as use_fast_cpu_compiler
from .config import ConfigError as ConfigError
from .model import ForwardModel as ForwardModel
from .model import ModelOptions as ModelOptions
from .model import Params as Params
from .model import build_model as build_model
from .scene import Scene as Scene
from .scene import default_scene as default_scene
from .scene import load_scene as load_scene

__version__ = "0.1.0"


def enable_x64(enable: bool = True) -> None:
    """Switch JAX to 64-bit floats (call once, before building models)."""
    import jax

    jax.config.update("jax_enable_x64", enable)
