"""How many baseline frames a calibration needs: the precision plan.

After a fit, the Laplace covariance gives the standard error of n1 and of mu_s + mu_a (the sum
with its covariance term: the fit pins the sum, while mu_s and mu_a alone are strongly
anti-correlated). The residuals are weighted by ``frames / max(mean, 1)`` (photon noise), so
the covariance scales as ``1 / frames``: a relative standard error ``s`` from ``F`` frames
becomes ``s sqrt(F / F')`` from ``F'`` frames. An unbiased, normal estimate is within a relative
error ``r`` of the truth with probability 0.95 where ``1.96 s' <= r``, so

    F' = F (1.96 s / r)^2

frames are needed. What this cannot see: **more frames reduce the photon noise, not the
model's bias** (a rig the model does not describe is off by the same amount at any frame
count); a ``model_error`` floor (``FitConfig.model_error``) does not fall with frames either,
nor do the timing anchor and the weak prior (both far wider than the errors planned for).
The standard error is relative to the estimate (the truth is unknown), so a plan from a fit
that is far off is off by as much.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import ConfigError

__all__ = ["PrecisionPlan", "PrecisionTarget", "check_target", "precision_plan", "relative_sd"]

#: two-sided 95% quantile of the normal distribution
Z95 = 1.959963984540054
#: the quantities planned for, and the covariance labels whose sum each is
QUANTITIES = {"n1": ("n1",), "mu_s + mu_a": ("mu_s_per_m", "mu_a_per_m")}
NOTE = (
    "photon noise only (sd ~ 1/sqrt(frames)), normal and unbiased, relative to the estimate; "
    "more frames reduce noise, not model bias"
)


def check_target(name: str, value) -> float:
    """A relative error target in (0, 1), or a one-line :class:`ConfigError` naming ``name``."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < 1  # nan fails both
    if not ok:
        raise ConfigError(f"{name}: must be a relative error in (0, 1) (0.25 = 25%), got {value!r}")
    return float(value)


def frames_needed(frames: int, rel_sd: float, target: float, z: float = Z95) -> int | None:
    """``frames (z rel_sd / target)^2`` rounded up (at least 1); None where ``rel_sd`` is not finite."""
    if not (math.isfinite(rel_sd) and rel_sd >= 0):
        return None
    return max(1, math.ceil(frames * (z * rel_sd / target) ** 2 - 1e-9))


@dataclass(frozen=True)
class PrecisionTarget:
    """One quantity's plan: its estimate and standard error from ``frames`` frames, and the
    frames for ``|error| <= target x value`` with 95% probability (None: no finite error)."""

    quantity: str
    value: float
    stderr: float
    rel_stderr: float
    target: float
    frames_needed: int | None

    def enough(self, frames: int) -> bool:
        return self.frames_needed is not None and self.frames_needed <= frames


@dataclass(frozen=True)
class PrecisionPlan:
    """The precision plan of a calibration (:func:`precision_plan`); ``targets`` holds n1 and
    mu_s + mu_a where the fit has them free."""

    frames: int
    targets: tuple[PrecisionTarget, ...]
    confidence: float = 0.95
    model_error: float = 0.0
    note: str = NOTE

    def __getitem__(self, quantity: str) -> PrecisionTarget:
        for t in self.targets:
            if t.quantity == quantity:
                return t
        raise KeyError(quantity)

    @property
    def enough(self) -> bool:
        """Every target met (with 95% probability) at the current frame count."""
        return all(t.enough(self.frames) for t in self.targets)

    def to_json(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "confidence": self.confidence,
            "model_error": self.model_error,
            "note": self.note,
            "targets": [dataclasses.asdict(t) for t in self.targets],
        }

    @staticmethod
    def from_json(data: dict[str, Any]) -> PrecisionPlan:
        try:
            targets = tuple(
                PrecisionTarget(
                    quantity=str(t["quantity"]), value=float(t["value"]), stderr=float(t["stderr"]),
                    rel_stderr=float(t["rel_stderr"]), target=float(t["target"]),
                    frames_needed=None if t["frames_needed"] is None else int(t["frames_needed"]),
                )
                for t in data["targets"]
            )
            return PrecisionPlan(frames=int(data["frames"]), targets=targets, confidence=float(data["confidence"]),
                                 model_error=float(data.get("model_error", 0.0)), note=str(data.get("note", NOTE)))
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(f"precision: not a precision plan ({type(e).__name__}: {e})") from None

    def lines(self) -> list[str]:
        """One line per quantity, e.g. ``mu_s + mu_a: +-27% (1 sd) from 60 frames; within 25% at
        95% needs about 270 frames``."""
        out = []
        for t in self.targets:
            head = f"{t.quantity}: +-{_pct(t.rel_stderr)} (1 sd) from {self.frames} frames; within {_pct(t.target)} at 95%"
            if t.frames_needed is None:
                out.append(f"{head}: no finite standard error, no plan")
            elif t.enough(self.frames):
                n = _about(t.frames_needed)
                out.append(f"{head}: enough (about {n} frame{'' if n == '1' else 's'} would do)")
            else:
                out.append(f"{head} needs about {_about(t.frames_needed)} frames")
        if not self.enough:
            out.append("(photon noise only: more frames reduce noise, not model bias"
                       + (f"; the model_error floor {self.model_error:g} does not fall with frames" if self.model_error else "")
                       + ")")
        return out


def relative_sd(values: dict, covariance: np.ndarray, labels: list[str], quantity: str) -> tuple[float, float, float] | None:
    """``(value, stderr, stderr / |value|)`` of ``quantity`` (a key of ``QUANTITIES``) from a fit's
    values and covariance, the sum's variance with its covariance terms; None where none of its
    parts is free."""
    parts = [k for k in QUANTITIES[quantity] if k in labels and k in values]
    if not parts:
        return None
    idx = [labels.index(k) for k in parts]
    c = np.asarray(covariance, np.float64)
    var = float(c[np.ix_(idx, idx)].sum())
    value = float(sum(float(np.ravel(values[k])[0]) for k in parts))
    sd = math.sqrt(var) if math.isfinite(var) and var >= 0 else float("nan")
    rel = sd / abs(value) if value != 0 and math.isfinite(sd) else float("nan")
    return value, sd, rel


def precision_plan(values: dict, covariance: np.ndarray, labels: list[str], frames: int, *, n1: float = 0.01,
                   mu_t: float = 0.25, model_error: float = 0.0) -> PrecisionPlan:
    """The frames a calibration needs for n1 within ``n1`` and mu_s + mu_a within ``mu_t``
    (relative errors) with 95% probability, from a fit's values, covariance and frame count
    (photon noise: module docstring). Bad targets raise a one-line :class:`ConfigError`."""
    goal = {"n1": check_target("precision_target_n1", n1), "mu_s + mu_a": check_target("precision_target_mu_t", mu_t)}
    if int(frames) < 1:
        raise ConfigError(f"frames: a plan needs the baseline's frame count (>= 1), got {frames!r}")
    targets = []
    for q, r in goal.items():
        got = relative_sd(values, covariance, labels, q)
        if got is None:
            continue
        value, sd, rel = got
        targets.append(PrecisionTarget(q, value, sd, rel, r, frames_needed(int(frames), rel, r)))
    return PrecisionPlan(frames=int(frames), targets=tuple(targets), model_error=float(model_error))


def _pct(x: float) -> str:
    if not math.isfinite(x):
        return "nan%"
    p = 100 * x
    return f"{p:.2g}%" if p < 10 else f"{p:.0f}%"


def _about(n: int) -> str:
    """``n`` to two significant figures (a plan, not a count)."""
    if n < 100:
        return str(n)
    k = 10 ** (len(str(n)) - 2)
    return str(round(n / k) * k)
