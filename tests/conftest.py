"""Test set-up: float64 for gradients and fits, set here (never on import of tofjax)."""

import os
import tempfile

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402

jax.config.update("jax_enable_x64", True)
# Most of the suite's time is XLA compiling (87% of test_calibrate.py's and test_guided.py's, their
# backend's LLVM passes), and the default selection's programs run for milliseconds: it compiles
# without LLVM's optimisation (pytest_configure below). Measured side by side on the 2-core VM, fresh
# clones, empty caches: the suite 6:35 against 11:31 of pytest (2026-11-29). What a test computes does
# not change beyond rounding, except where a program sits on a knife edge (README "Tests").
TEST_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"


def unoptimised(markexpr: str, environ=os.environ) -> bool:
    """Whether this run compiles without LLVM's optimisation: the default selection (``-m 'not slow'``,
    pyproject's addopts) does; a run that selects the long studies (``make test-all``'s ``-m ""``, ``-m slow``),
    whose programs run long enough for optimisation to pay, compiles as the CLI does, and so does any run with
    ``TOFJAX_TEST_XLA_OPT=default`` or a ``$XLA_FLAGS`` that names the level itself."""
    if environ.get("TOFJAX_TEST_XLA_OPT", "").strip().lower() == "default":
        return False
    if "xla_backend_optimization_level" in environ.get("XLA_FLAGS", ""):
        return False
    return " ".join(markexpr.split()) == "not slow"


def pytest_configure(config):
    # after the options are read, before any test starts JAX's backend (XLA reads $XLA_FLAGS then)
    if unoptimised(config.getoption("markexpr", "") or ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {TEST_XLA_FLAGS}".strip()


# The CPU compiler the CLI uses (XLA's elemental emitters: most of the suite is compilation),
# set before any test starts JAX's backend.
use_fast_cpu_compiler()
# Many tests compile the same model or fit again (each CLI call builds afresh): a
# compilation cache shared by the session turns those into cache hits.
_cache = os.path.join(tempfile.gettempdir(), f"tofjax-test-jax-cache-{os.getuid()}")
jax.config.update("jax_compilation_cache_dir", _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
# The CLI's main() turns on the user's cache (~/.cache/tofjax/jax): point it at the test cache.
os.environ["TOFJAX_COMPILATION_CACHE"] = _cache
# The CLI also keeps exported (traced) programs; in one test process that would compile the same
# fit twice (exported and plain). Off here; tests/test_compile_cache.py turns it on where tested.
os.environ["TOFJAX_PROGRAM_STORE"] = "0"

# Every example compiles or runs a model: few examples, no deadline (CI machines are slow and shared).
settings.register_profile("tofjax", max_examples=15, deadline=None, derandomize=True)
settings.load_profile("tofjax")


@pytest.fixture(scope="session")
def optoskin():
    from tofjax import load_scene

    return load_scene("optoskin")
