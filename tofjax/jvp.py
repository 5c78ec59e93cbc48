"""A forward-mode derivative computed once, as a dense Jacobian (used by the model and the fit)."""

from __future__ import annotations

import jax

__all__ = ["dense_jvp"]


def dense_jvp(fn):
    """``fn(y, args)`` (``y`` a flat vector, the output any pytree of arrays) whose forward-mode
    derivative is a dense Jacobian computed once: the rule builds ``J = jacfwd(fn)(y)`` and the
    tangent is ``J @ dy`` (leaf by leaf). Derivatives with respect to ``args`` are not propagated:
    use it where the output depends on ``args`` only through ``y`` or where only ``y`` is
    differentiated.

    Why: a derivative applied many times (optimistix's Gauss-Newton solvers ``jax.linearize`` the
    residuals and apply the linearisation several times per step, each application re-running the
    model's tangent: :mod:`tofjax.fit.solve`), or one whose tangents XLA would fuse into a larger
    loop and recompute for every element of it (the model's node terms, (K,) arrays multiplied by
    (S, Z, K) ones: :meth:`tofjax.model.forward.ForwardModel._node_terms`). ``J @ dy`` is a kernel
    of its own, so ``J`` is materialised once. Values are ``fn``'s; in reverse mode ``J`` costs a
    forward pass per entry of ``y``.
    """

    @jax.custom_jvp
    def wrapped(y, args):
        return fn(y, args)

    @wrapped.defjvp
    def _jvp(primals, tangents):
        y, args = primals
        dy, _ = tangents

        def both(z):
            out = fn(z, args)
            return out, out

        jac, out = jax.jacfwd(both, has_aux=True)(y)
        return out, jax.tree_util.tree_map(lambda j: j @ dy, jac)

    return wrapped
