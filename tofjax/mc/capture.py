"""Monte Carlo histograms as an ordinary capture (what ``tofjax mc`` writes)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..capture import Capture
from ..model import ModelOptions, Params, build_model
from ..scene import Scene
from ..simulate import capture_from_expected
from .transport import MCOptions, MCResult, run_mc

__all__ = ["mc_capture", "mc_expected_counts"]

#: Terms the transport does not simulate, taken from the analytic model.
ANALYTIC_EXTRAS = ("crosstalk", "ambient")


def mc_expected_counts(scene: Scene, options: MCOptions = MCOptions(), *, progress: bool = False) -> tuple[np.ndarray, MCResult]:
    """Expected counts of one frame: the transported light (Monte Carlo) plus the light-entry peak
    and the ambient background of the analytic model (which no transport simulates), (S, Z, B)."""
    result = run_mc(scene, options, progress=progress)
    extras = [c for c in ANALYTIC_EXTRAS if c in scene.components()]
    expected = result.counts.copy()
    if extras:
        opts = ModelOptions(quadrature=options.quadrature, dtype=options.dtype)
        expected += np.asarray(build_model(scene, opts, tuple(extras))(Params.from_scene(scene, opts.jnp_dtype)))
    return expected, result


def mc_capture(scene: Scene, n_frames: int = 1, seed: int = 0, options: MCOptions = MCOptions(), *,
               progress: bool = False, frame_period_s: float = 1.0 / 9.0) -> Capture:
    """``n_frames`` frames drawn from the Monte Carlo expected counts (photon noise from the scene's
    ``[noise]`` table and ``seed``), with ground truth; ``source = "simulated (monte carlo)"``."""
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    expected, result = mc_expected_counts(scene, options, progress=progress)
    params = Params.from_scene(scene, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    return capture_from_expected(scene, expected, n_frames, seed, params, source="simulated (monte carlo)",
                                 frame_period_s=frame_period_s, monte_carlo=dataclasses.asdict(options),
                                 mc_ledger=result.ledger, mc_events=result.events, mc_seconds=result.seconds)
