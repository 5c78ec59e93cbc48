"""One jitted optimistix solve that also records the loss at every step.

``optx.least_squares`` returns only the end point; users of a calibration want
to see how it got there. This drives an optimistix solver's own ``init``,
``step`` and ``terminate`` in a ``lax.while_loop`` (as ``optx`` does
internally) and writes ``0.5 * sum(residuals^2)`` (or the scalar loss of a
minimiser) into a preallocated history.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

__all__ = ["SolveResult", "dense_jvp", "solve_with_history"]


def dense_jvp(fn):
    """``fn(y, args)`` (y a flat vector) whose forward-mode derivative is a dense Jacobian
    computed once: the primal pass builds ``J = jacfwd(fn)`` and the tangent is ``J @ dy``.

    Gauss-Newton-type solvers in optimistix ``jax.linearize`` the residuals and then apply
    the linearisation many times per step (to materialise it for the QR solve, to predict
    the reduction); every application re-runs the model's tangent, and the loop carries all
    the linearisation's intermediates. With this wrapper a step costs one Jacobian (a
    batched forward pass over the few parameters) and carries only ``J``. Derivatives with
    respect to ``args`` are not propagated (the solvers differentiate ``y`` only).
    """

    @jax.custom_jvp
    def wrapped(y, args):
        return fn(y, args)

    @wrapped.defjvp
    def _jvp(primals, tangents):
        y, args = primals
        dy, _ = tangents
        jac, out = jax.jacfwd(lambda z: (fn(z, args), fn(z, args)), has_aux=True)(y)
        return out, jac @ dy

    return wrapped


class SolveResult(NamedTuple):
    value: object  # the solution pytree
    result: object  # optx.RESULTS
    steps: jax.Array
    history: jax.Array  # (max_steps + 1,) loss per step, NaN after the last


def _state_loss(state, fallback):
    """The loss at the solver's current iterate, read from its state when it keeps it
    (Gauss-Newton family: the residuals; quasi-Newton: the value), so the history
    costs no extra model evaluation."""
    info = getattr(state, "f_info", None)
    if info is not None and hasattr(info, "residual"):
        return 0.5 * jnp.sum(info.residual**2)
    if info is not None and hasattr(info, "f"):
        return info.f
    return fallback()


def solve_with_history(
    residuals, solver, y0, args, *, max_steps: int, minimise: bool = False, loss_tol: float = 0.0
) -> SolveResult:
    """Run ``solver`` on ``residuals(y, args)`` from ``y0``.

    For least-squares solvers ``residuals`` returns an array of residuals; with
    ``minimise=True`` it returns a scalar loss and ``solver`` is a minimiser.
    ``loss_tol > 0`` adds a stopping rule to the solver's own: stop when an
    accepted step lowers the loss by less than ``loss_tol`` (for a chi-square
    loss, ``0.5 chi^2``, this says the fit moved by a small fraction of its
    standard errors; the solver's tolerances on the parameters may take many
    more steps to be met in a flat valley).
    Returns the end point, optimistix's result code, the number of steps and the
    loss history. Jit-compatible; a failure is a result code, never an exception.
    """

    def fn(y, a):
        return residuals(y, a), None

    def loss(y):
        out = residuals(y, args)
        return out if minimise else 0.5 * jnp.sum(out**2)

    f_struct = jax.eval_shape(lambda y: fn(y, args)[0], y0)
    aux_struct = None
    tags = frozenset()
    options = {}
    state0 = solver.init(fn, y0, args, options, f_struct, aux_struct, tags)
    dyn0, static = eqx.partition(state0, eqx.is_array)
    history0 = jnp.full((max_steps + 1,), jnp.nan, dtype=jnp.result_type(float)).at[0].set(loss(y0))
    term0, res0 = solver.terminate(fn, y0, args, options, state0, tags)

    def cond(carry):
        _, step, _, term, res, _ = carry
        return (~term) & (res == optx.RESULTS.successful) & (step < max_steps)

    def body(carry):
        y, step, dyn, _, _, hist = carry
        state = eqx.combine(static, dyn)
        y_new, state_new, _ = solver.step(fn, y, args, options, state, tags)
        term, res = solver.terminate(fn, y_new, args, options, state_new, tags)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(y_new)]))
        res = optx.RESULTS.where(finite, res, optx.RESULTS.nonfinite)
        new_loss = _state_loss(state_new, lambda: loss(y_new))
        decrease = hist[step] - new_loss
        if loss_tol > 0:
            # step 0 only evaluates the start (its "decrease" is rounding); a rejected
            # step leaves the loss exactly as it was
            term = term | ((step >= 1) & (decrease > 0) & (decrease < loss_tol))
        hist = hist.at[step + 1].set(new_loss)
        dyn_new, _ = eqx.partition(state_new, eqx.is_array)
        return y_new, step + 1, dyn_new, term, res, hist

    carry = (y0, jnp.array(0), dyn0, term0, res0, history0)
    y, steps, dyn, term, res, hist = jax.lax.while_loop(cond, body, carry)
    res = optx.RESULTS.where((res == optx.RESULTS.successful) & ~term, optx.RESULTS.nonlinear_max_steps_reached, res)
    state = eqx.combine(static, dyn)
    y, _, _ = solver.postprocess(fn, y, None, args, options, state, tags, res)
    return SolveResult(y, res, steps, hist)
