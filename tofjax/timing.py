"""Wall-clock timing of jitted calls, for benchmarks and the demo's summary."""

from __future__ import annotations

import time

import jax
import numpy as np

__all__ = ["median_seconds"]


def median_seconds(f, arg, repeats: int = 50, *, warm: bool = True) -> float:
    """Median wall time of ``f(arg)`` over ``repeats`` calls, waiting for the result each time.

    With ``warm`` the first (compiling) call is made and not counted. Medians,
    not means: these machines are shared and noisy.
    """
    if warm:
        jax.block_until_ready(f(arg))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f(arg))
        times.append(time.perf_counter() - t)
    return float(np.median(times))
