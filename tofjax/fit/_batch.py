"""A batch of :class:`~tofjax.fit.solve.MarquardtLM` fits that drops the fits that have stopped.

``jax.vmap`` of a ``lax.while_loop`` runs every fit of the batch until the slowest has stopped:
a batch whose fits need 20-60 steps and a few 200 pays for 200 steps of every fit. Here the
batch runs a few steps at a time (:attr:`CompactBatch.chunk_steps`) from the solver's whole
loop state (:class:`~tofjax.fit.solve.MarquardtState`), and the fits still running go on in a
smaller batch, its size one of a few buckets (the full batch, then powers of ``growth`` down to
``min_bucket``): one compiled program per bucket, at most ``1 + log_growth(n / min_bucket)``
of them, plus the start and the end. A fit run in pieces is the fit run at once (the same loop
body on the same state), so the results are the plain vmapped batch's up to the rounding of
batched kernels, which depends on the batch size (on 40 default-scene baselines: the same result
codes, n1 within 7e-7, but a crawling fit's small-gain stop can come a few steps apart).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import equinox as eqx
import jax
import numpy as np

from ..config import ConfigError
from .solve import MarquardtLM, SolveResult, marquardt_advance, marquardt_init, marquardt_solution

__all__ = ["BatchStats", "CompactBatch", "solve_marquardt_compact"]


@dataclass(frozen=True)
class CompactBatch:
    """Options of the compacting batch (:func:`tofjax.fit.calibrate.fit_problem_compact`).

    - ``chunk_steps``: solver steps per compiled call; after each call the fits that have stopped
      leave the batch (smaller: fewer wasted steps of finished fits, more calls and host syncs).
    - ``min_bucket``: the smallest batch size compiled (fewer fits are padded up to it).
    - ``growth``: the ratio between bucket sizes (2: n, 64, 32, 16, 8 for n = 100).
    """

    chunk_steps: int = 16
    min_bucket: int = 8
    growth: int = 2

    def __post_init__(self):
        for k in ("chunk_steps", "min_bucket"):
            v = getattr(self, k)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ConfigError(f"{k}: must be an integer >= 1, got {v!r}")
        if not isinstance(self.growth, int) or isinstance(self.growth, bool) or self.growth < 2:
            raise ConfigError(f"growth: must be an integer >= 2, got {self.growth!r}")

    def buckets(self, n: int) -> tuple[int, ...]:
        """The batch sizes a batch of ``n`` fits may run at, largest first."""
        sizes, b = {n}, 1
        while b < n:
            if b >= self.min_bucket:
                sizes.add(b)
            b *= self.growth
        return tuple(sorted(sizes, reverse=True))

    def bucket(self, n: int, active: int) -> int:
        """The smallest bucket that holds ``active`` fits of a batch of ``n``."""
        return min(b for b in self.buckets(n) if b >= active)


@dataclass
class BatchStats:
    """What a compacting batch ran: per compiled call its batch size and loop passes (the slowest
    fit's steps in that call). ``lane_steps`` = sum of size x passes, the work a vmapped machine
    does; ``ideal_lane_steps`` = each fit's own steps summed; ``vmap_lane_steps`` = what the plain
    vmapped batch runs (n x the slowest fit's steps). Steps count loop passes, the start's own
    first pass included (a ``lambda_trials`` fit's last pass that stops without a step is not)."""

    n: int
    calls: list = field(default_factory=list)  # [(batch size, passes)]
    fit_steps: list = field(default_factory=list)
    call_s: list = field(default_factory=list)  # wall seconds of each call, the host's sync included

    @property
    def lane_steps(self) -> int:
        return int(sum(b * p for b, p in self.calls))

    @property
    def ideal_lane_steps(self) -> int:
        return int(sum(self.fit_steps))

    @property
    def vmap_lane_steps(self) -> int:
        return int(self.n * max(self.fit_steps, default=0))

    @property
    def programs(self) -> int:
        """Distinct batch sizes run (each one compiled advance program)."""
        return len({b for b, _ in self.calls})

    def as_dict(self) -> dict:
        return {"n": self.n, "calls": [list(c) for c in self.calls], "lane_steps": self.lane_steps,
                "ideal_lane_steps": self.ideal_lane_steps, "vmap_lane_steps": self.vmap_lane_steps,
                "advance_programs": self.programs, "call_s": self.call_s}


@eqx.filter_jit
def _init(residuals, solver, y0s, args, max_steps):
    return jax.vmap(lambda y, a: marquardt_init(residuals, solver, y, a, max_steps=max_steps))(y0s, args)


@eqx.filter_jit
def _advance(residuals, solver, states, args, idx, max_steps, loss_tol, steps):
    """Advance the fits ``idx`` (a bucket's worth; padding repeats a stopped fit, which the loop
    leaves as it is) by up to ``steps`` loop passes, in place in the whole batch's state."""

    def take(x):
        return x[idx]

    sub = jax.vmap(lambda s, a: marquardt_advance(residuals, solver, s, a, max_steps=max_steps, loss_tol=loss_tol, steps=steps))(
        jax.tree_util.tree_map(take, states), jax.tree_util.tree_map(take, args))
    return jax.tree_util.tree_map(lambda x, v: x.at[idx].set(v), states, sub)


@eqx.filter_jit
def _solution(states):
    return jax.vmap(marquardt_solution)(states)


def solve_marquardt_compact(residuals, solver: MarquardtLM, y0s, args, *, max_steps: int, loss_tol: float = 0.0,
                            options: CompactBatch = CompactBatch()) -> tuple[SolveResult, BatchStats]:
    """:func:`~tofjax.fit.solve.solve_marquardt` over a batch (``y0s`` and every leaf of ``args``
    with a leading batch axis), the stopped fits dropped every ``options.chunk_steps`` steps.
    ``residuals`` must be hashable by what it computes (a module-level function or an
    ``eqx.Module``): it keys the compiled programs. Returns the batched :class:`SolveResult`
    (as the vmapped ``solve_marquardt``) and the :class:`BatchStats`."""
    n = int(np.shape(y0s)[0])
    states = _init(residuals, solver, y0s, args, max_steps)
    step0 = np.asarray(states.step)
    stats = BatchStats(n)
    while True:
        step, done = np.asarray(states.step), np.asarray(states.done)
        running = ~done & (step < max_steps)
        active = np.flatnonzero(running)
        if active.size == 0:
            break
        size = options.bucket(n, active.size)
        stopped = np.flatnonzero(~running)
        pad = stopped[0] if stopped.size else active[0]  # no padding without a stopped fit: size == n
        idx = np.concatenate([active, np.full(size - active.size, pad, active.dtype)]).astype(np.int32)
        t = time.perf_counter()
        states = _advance(residuals, solver, states, args, jax.device_put(idx), max_steps, loss_tol, options.chunk_steps)
        after = np.asarray(states.step)[active]
        stats.call_s.append(time.perf_counter() - t)
        stats.calls.append((size, int(np.max(after - step[active]))))
    stats.fit_steps = (np.asarray(states.step) - step0).tolist()
    return _solution(states), stats
