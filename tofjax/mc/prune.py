"""Model only what a scene requires: each component's largest effect against the photon noise.

For every component of the analytic model, the effect of leaving it out (the full
model minus the model without it, so multiplicative terms such as shadowing are
measured the same way as additive ones) is compared, bin by bin, with the photon
noise of the data it would be fitted to: ``sqrt(expected counts / frames)`` for an
average of ``frames`` frames (at least one count per bin). Additive components are read
off one breakdown of the model; shadowing, which multiplies, from one model without
it; the effect of several components is taken as the sum of theirs. The smallest model is
found greedily: components are dropped, least important first, while the effect
of everything dropped together stays within ``noise_floor`` standard deviations
in every bin.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import equinox as eqx
import numpy as np

from ..config import ConfigError
from ..errors import UserError
from ..model import ModelOptions, Params, build_model
from ..model.forward import _trace_switches
from ..scene import COMPONENTS, Scene
from ..timing import median_seconds

__all__ = ["PruneOptions", "PruneReport", "evaluate", "model_breakdown", "prune_model"]


# Module-level compiled calls that take the model as an argument: one program per model structure
# (scene shape, components, options), reused by every model of that structure. A ``jax.jit`` of a
# lambda made per call (what these replace) compiles again on every call. The guided optics'
# module switches are read when tracing: they are a static argument, so changing one retraces.
@eqx.filter_jit
def _evaluate(model, params, switches):
    del switches
    return model(params)


@eqx.filter_jit
def _breakdown(model, params, switches):
    del switches
    return model.breakdown(params)


def evaluate(model, params):
    """``model(params)``, compiled once per model structure (see above)."""
    return _evaluate(model, params, _trace_switches())


def model_breakdown(model, params) -> dict:
    """``model.breakdown(params)`` (each component's counts), compiled once per model structure."""
    return _breakdown(model, params, _trace_switches())


@dataclass(frozen=True)
class PruneOptions:
    """- ``noise_floor``: the largest effect (in photon-noise standard deviations, any bin)
      that the dropped components may have together.
    - ``frames``: frames averaged in the data the model will be fitted to (more frames,
      less noise, more components needed).
    - ``model``: fidelity of the model used for the comparison.
    - ``timing``: also time the full and the pruned model (warm, median)."""

    noise_floor: float = 1.0
    frames: int = 1
    model: ModelOptions = ModelOptions()
    timing: bool = False

    def __post_init__(self):
        if not self.noise_floor > 0:
            raise ConfigError(f"noise_floor: must be > 0, got {self.noise_floor!r}")
        if self.frames < 1:
            raise ConfigError(f"frames: must be >= 1, got {self.frames!r}")


@dataclass
class PruneReport:
    """``effects[c]``: largest effect of component ``c`` in noise standard deviations (0 when the
    scene does not have it), ``effect_counts[c]`` the same in counts, ``where[c]`` the (sensor,
    zone, bin) of the largest effect; ``kept``/``dropped``: the recommendation;
    ``dropped_effect``: everything dropped together, in standard deviations."""

    scene: str
    components: tuple[str, ...]
    effects: dict[str, float]
    effect_counts: dict[str, float]
    where: dict[str, tuple[int, int, int]]
    kept: tuple[str, ...]
    dropped: tuple[str, ...]
    dropped_effect: float
    options: PruneOptions
    full_seconds: float | None = None
    pruned_seconds: float | None = None

    def to_json(self) -> dict:
        d = {k: v for k, v in dataclasses.asdict(self).items() if k != "options"}
        d["options"] = {"noise_floor": self.options.noise_floor, "frames": self.options.frames,
                        "model": dataclasses.asdict(self.options.model)}
        return d

    def table(self) -> str:
        lines = [
            f"scene '{self.scene}': photon noise of {self.options.frames} frame(s), floor {self.options.noise_floor:g} sigma",
            f"{'component':22s} {'max effect [sigma]':>18s} {'[counts]':>12s}  where (sensor, zone, bin)  verdict",
        ]
        for c in COMPONENTS:
            if c not in self.components:
                lines.append(f"{c:22s} {'-':>18s} {'-':>12s}  {'':25s}  not in this scene")
                continue
            verdict = "keep" if c in self.kept else "drop"
            lines.append(
                f"{c:22s} {self.effects[c]:18.3g} {self.effect_counts[c]:12.3g}  {str(self.where[c]):25s}  {verdict}"
            )
        lines.append(f"recommended components: {', '.join(self.kept) or '(none)'}")
        lines.append(f"dropped together: largest effect {self.dropped_effect:.3g} sigma")
        if self.full_seconds is not None:
            lines.append(
                f"model time: full {self.full_seconds * 1e6:.0f} us, pruned {self.pruned_seconds * 1e6:.0f} us "
                f"(x{self.full_seconds / max(self.pruned_seconds, 1e-12):.2f})"
            )
        return "\n".join(lines)


def _effects(scene: Scene, opts: ModelOptions, comps, params):
    """The full model and, per component, full minus the model without it, (S, Z, B) each.

    Additive components come from one :meth:`~tofjax.model.ForwardModel.breakdown`;
    shadowing (it multiplies what lies behind a contact) from one model without it."""
    model = build_model(scene, opts, tuple(comps))
    full = np.asarray(evaluate(model, params), np.float64)
    parts = {k: np.asarray(v, np.float64) for k, v in model_breakdown(model, params).items()}
    diffs = {c: np.broadcast_to(parts[c], full.shape) for c in comps if c in parts}
    for c in comps:
        if c not in diffs:
            rest = build_model(scene, opts, tuple(k for k in comps if k != c))
            diffs[c] = full - np.asarray(evaluate(rest, params), np.float64)
    return full, diffs


def prune_model(scene: Scene, options: PruneOptions = PruneOptions(), params: Params | None = None) -> PruneReport:
    """Each component's largest effect against the photon noise, and the smallest model within it.

    **Arguments:**

    - ``scene``: the scene (its components are the starting point).
    - ``options``: :class:`PruneOptions`.
    - ``params``: parameters to evaluate at (default: the scene's).

    **Returns:** a :class:`PruneReport`; ``report.kept`` is the component list to pass to
    :func:`tofjax.model.build_model` (``components=``).
    """
    opts = options.model
    params = Params.from_scene(scene, opts.jnp_dtype) if params is None else params
    comps = tuple(scene.components())
    full, diffs = _effects(scene, opts, comps, params)
    bad = [c for c in ("model",) + tuple(diffs) if not np.all(np.isfinite(full if c == "model" else diffs[c]))]
    if bad:
        # effects of NaN would rank nothing and keep everything (printed as nan before the scene checks)
        raise UserError(f"scene '{scene.name}': the model is not finite at its parameters ({', '.join(bad)}): "
                        "no component's effect can be measured; check the scene's optics and sensor values")
    sigma = np.sqrt(np.maximum(full, 1.0) / options.frames)

    def effect(dropped):
        # effects of several components add (exactly for additive ones; to first order for shadowing)
        counts = np.abs(sum(diffs[c] for c in dropped))
        i = np.unravel_index(int(np.argmax(counts / sigma)), counts.shape)
        return float(counts[i] / sigma[i]), float(counts[i]), tuple(int(v) for v in i)

    effects, counts, where = {}, {}, {}
    for c in COMPONENTS:
        if c in comps:
            effects[c], counts[c], where[c] = effect({c})
        else:
            effects[c], counts[c], where[c] = 0.0, 0.0, (-1, -1, -1)
    dropped: list[str] = []
    total = 0.0
    for c in sorted(comps, key=lambda k: effects[k]):
        if effects[c] > options.noise_floor:
            break
        e = effect(set(dropped) | {c})[0]
        if e <= options.noise_floor:
            dropped.append(c)
            total = e
    kept = tuple(c for c in comps if c not in dropped)
    report = PruneReport(
        scene=scene.name, components=comps, effects=effects, effect_counts=counts, where=where,
        kept=kept, dropped=tuple(c for c in comps if c in dropped), dropped_effect=total, options=options,
    )
    if options.timing:
        for attr, cs in (("full_seconds", comps), ("pruned_seconds", kept)):
            m = build_model(scene, opts, cs)
            setattr(report, attr, median_seconds(lambda p, m=m: evaluate(m, p), params, 30))
    return report
