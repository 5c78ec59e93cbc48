"""Monte Carlo histograms as an ordinary capture (what ``tofjax mc`` writes)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..capture import Capture
from ..model import ModelOptions, Params, build_model, sample_frames
from ..scene import Scene
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
    lam = jnp.asarray(expected)
    keys = jax.random.split(jax.random.key(seed), n_frames)
    hist = np.array(sample_frames(keys, lam, poisson=bool(scene.noise.poisson), saturation=scene.sensor.saturation_counts),
                    np.float64)
    el = scene.contact_elements()
    touches = np.broadcast_to(el[:, [0, 1, 3]], (n_frames, len(el), 3)).copy() if len(el) else None
    params = Params.from_scene(scene, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    truth = {f.name: np.asarray(getattr(params, f.name)).tolist() for f in dataclasses.fields(params)}
    truth.update(seed=seed, monte_carlo=dataclasses.asdict(options), mc_ledger=result.ledger,
                 mc_events=result.events, mc_seconds=result.seconds)
    return Capture(histograms=hist, timestamps=np.arange(n_frames) * frame_period_s, scene=scene,
                   source="simulated (monte carlo)", truth_touches=touches, truth=truth)
