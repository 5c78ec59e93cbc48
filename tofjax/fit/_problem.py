"""The calibration problem: residuals of the forward model against a baseline, with the
linear parameters (gain, light-entry and ambient counts) profiled out.

:class:`CalibrationProblem` is an immutable ``eqx.Module``: it holds the forward model and
the choice of free parameters, never the data. The data (mean histograms and their
standard deviations) and the start are passed as arguments, so one problem serves every
capture of its shape, ``eqx.filter_jit`` does the caching and many fits ``vmap`` into one
compiled call.

The model of one zone is ``g R + x P + a``: ``R`` everything proportional to the gain,
``P`` the unit light-entry peak, ``a`` ambient (:meth:`ForwardModel.linear_parts`).
With ``zone_gain`` the gain ``g`` is free per (sensor, zone): a real rig's zones differ
by several per cent (lens, SPAD array, calibration of the part) in ways no optics explain.
The linear parameters of each zone are then the non-negative least-squares solution
(counts cannot be negative), found exactly by trying every active set of the (at most
three) unknowns in closed form and keeping the best feasible one.

With ``zone_end`` the far-edge return is a fourth linear unknown per zone: the model is
``g (R0 + e E) + x P + a`` with ``E`` the edge at unit reflectance, solved for ``h = g e``.
A real edge reflects differently in each zone (angle of incidence, polish, bevel); with one
reflectance for all zones the fit explains the zone-to-zone differences of the edge returns
with the attenuation along each zone's path, and mu_t comes out wrong (on the independent
simulator, whose edge reflectance goes with the cosine of incidence: +58% at 0.5 /m).
"""

from __future__ import annotations

import itertools
import math

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from ..model import ForwardModel, Params
from ..model.forward import _trace_switches
from ..model.pulse import apply_kernels
from .transforms import Transform

__all__ = ["CalibrationProblem", "LINEAR", "JOINT"]

#: Parameters that scale the histogram linearly: profiled out, never seen by the solver.
LINEAR = ("gain", "ambient_counts", "crosstalk_counts")
#: mu_s and mu_a are fitted as extinction mu_t = mu_s + mu_a (log) and albedo (logit): a
#: baseline pins mu_t far better than the split, and in (log mu_s, log mu_a) that makes a
#: curved valley in which Gauss-Newton overshoots; in (mu_t, albedo) it is straight.
JOINT = ("mu_s_per_m", "mu_a_per_m")


def _inv3(g):
    """Inverse of symmetric (..., 3, 3) matrices by the adjugate (elementwise: cheap to
    differentiate, unlike a batched LU)."""
    a, b, c = g[..., 0, 0], g[..., 0, 1], g[..., 0, 2]
    d, e, f = g[..., 1, 1], g[..., 1, 2], g[..., 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    D = a * f - c * c
    E = b * c - a * e
    F = a * d - b * b
    det = a * A + b * B + c * C
    adj = jnp.stack([jnp.stack([A, B, C], -1), jnp.stack([B, D, E], -1), jnp.stack([C, E, F], -1)], -2)
    return adj / det[..., None, None], det


def _mean_reflectance(e):
    """The scalar ``Params.end_reflectance`` of per-zone reflectances: their mean, kept in [0, 1]."""
    return jnp.clip(jnp.mean(e), 0.0, 1.0)


class CalibrationProblem(eqx.Module):
    """What is fitted and how; data and start come as arguments.

    **Fields:**

    - ``model``: the forward model of the scene without touches.
    - ``transforms``: ``(name, Transform)`` pairs, the unconstrained coordinates of each parameter.
    - ``free``: every free parameter; ``linear``/``nonlinear`` split it.
    - ``zone_gain``: gain free per (sensor, zone) instead of per sensor.
    - ``zone_end``: the far-edge reflectance free per (sensor, zone), profiled out (needs ``zone_gain``).
    - ``prior_width``: width of the weak Gaussian prior on the nonlinear coordinates (0: none).
    - ``switches``: the guided optics' module-level switches when the problem was built
      (:func:`tofjax.model.forward._trace_switches`): tracing reads them, so they key every program compiled on
      the problem (``eqx.filter_jit``, the program store) as they key the model's own calls; without them a fit
      compiled before a switch changed would run on.
    """

    model: ForwardModel
    transforms: tuple[tuple[str, Transform], ...] = eqx.field(static=True)
    free: tuple[str, ...] = eqx.field(static=True)
    linear: tuple[str, ...] = eqx.field(static=True)
    nonlinear: tuple[str, ...] = eqx.field(static=True)
    zone_gain: bool = eqx.field(static=True)
    prior_width: float = eqx.field(static=True)
    zone_end: bool = eqx.field(static=True, default=False)
    switches: tuple = eqx.field(static=True, default=())

    @classmethod
    def build(cls, model: ForwardModel, transforms: dict, free, *, zone_gain: bool, prior_width: float, zone_end: bool = False):
        comps = model.components
        present = {"gain": True, "crosstalk_counts": "crosstalk" in comps, "ambient_counts": "ambient" in comps}
        linear = tuple(p for p in LINEAR if p in free and present[p])
        zone_gain = bool(zone_gain and "gain" in linear)
        zone_end = bool(zone_end and zone_gain and "end_reflectance" in free and "end" in comps)
        if zone_end:
            linear = linear + ("end_reflectance",)
            # a reflectance per zone already takes any angle law: its power is not identified
            free = tuple(p for p in free if p != "end_incidence_power")
        if "end" not in comps:
            free = tuple(p for p in free if p != "end_incidence_power")
        nonlinear = tuple(p for p in free if p not in linear and p not in LINEAR)
        return cls(
            model=model,
            transforms=tuple(sorted(transforms.items())),
            free=tuple(free),
            linear=linear,
            nonlinear=nonlinear,
            zone_gain=zone_gain,
            prior_width=float(prior_width),
            zone_end=zone_end,
            switches=_trace_switches(),
        )

    def transform(self, name: str) -> Transform:
        return dict(self.transforms)[name]

    def prior_precision(self, name: str) -> float:
        """The weak prior's weight ``1 / prior_width^2`` on a coordinate (:meth:`prior_residuals`): 0 on a
        linear (profiled) one and without a prior."""
        return self.prior_width**-2.0 if self.prior_width > 0 and name not in self.linear else 0.0

    # ---- coordinates ------------------------------------------------------------------

    def pack(self, params: Params, names=None) -> dict[str, jax.Array]:
        """Unconstrained coordinates of ``names`` (default: the nonlinear parameters), in NumPy."""
        names = self.nonlinear if names is None else names
        joint = all(j in names for j in JOINT)
        u = {
            k: jnp.asarray(self.transform(k).to_unconstrained(np.asarray(getattr(params, k))))
            for k in names
            if not (joint and k in JOINT)
        }
        if joint:
            mu_s = max(float(params.mu_s_per_m), 1e-12)
            mu_a = max(float(params.mu_a_per_m), 1e-12)
            u["extinction"] = jnp.asarray(math.log(mu_s + mu_a))
            u["albedo"] = jnp.asarray(math.log(mu_s) - math.log(mu_a))
        return u

    def pack_jax(self, params: Params, names, values=None) -> dict[str, jax.Array]:
        """:meth:`pack` in JAX (jit-safe); ``values`` overrides ``getattr(params, k)``."""
        ft = jnp.result_type(float)
        values = values or {}

        def get(k):
            return jnp.asarray(values[k] if k in values else getattr(params, k), ft)

        joint = all(j in names for j in JOINT)
        u = {k: self.transform(k).unconstrain(get(k)) for k in names if not (joint and k in JOINT)}
        if joint:
            mu_s = jnp.maximum(get("mu_s_per_m"), 1e-12)
            mu_a = jnp.maximum(get("mu_a_per_m"), 1e-12)
            u["extinction"] = jnp.log(mu_s + mu_a)
            u["albedo"] = jnp.log(mu_s) - jnp.log(mu_a)
        return u

    def physical(self, u) -> dict[str, jax.Array]:
        """Physical values of the coordinates ``u`` (jit- and grad-safe)."""
        out = {k: self.transform(k).to_physical(v) for k, v in u.items() if k not in ("extinction", "albedo")}
        if "extinction" in u:
            mu_t = jnp.exp(u["extinction"])
            albedo = jax.nn.sigmoid(u["albedo"])
            out["mu_s_per_m"] = mu_t * albedo
            out["mu_a_per_m"] = mu_t * (1.0 - albedo)
        return out

    def unpack(self, u, base: Params) -> Params:
        phys = self.physical(u)
        if self.zone_gain and "gain" in phys and jnp.ndim(phys["gain"]) == 2:
            phys["gain"] = jnp.mean(phys["gain"], axis=-1)
        if "end_reflectance" in phys and jnp.ndim(phys["end_reflectance"]) == 2:
            phys["end_reflectance"] = _mean_reflectance(phys["end_reflectance"])
        return base.replace(**phys)

    # ---- the linear parameters, profiled out --------------------------------------------

    def _linear_parts(self, params: Params):
        """``(R, P, E)``: ``R`` everything proportional to the gain (without the edge with
        ``zone_end``), ``P`` the light-entry peak, ``E`` the edge at unit reflectance (or None)."""
        if self.zone_end:
            return self.model.linear_parts(params, separate_end=True)
        R, P = self.model.linear_parts(params)
        return R, P, None

    def _parts_of(self, u, base: Params):
        """:meth:`_linear_parts` at the coordinates ``u`` (a dict) with a structured derivative.

        The forward-mode derivative of ``linear_parts`` by plain ``jacfwd`` pushes every
        coordinate's tangent through every piece: the node masses, the pulse kernels and their
        Toeplitz products, the light-entry peak. Most of those tangents are zero (the masses do
        not depend on the pulse; the kernels depend on the pulse alone; the peak, one bin row,
        on the emission time, its width and the pulse), and the products of masses and kernels
        are the dominant cost. :func:`_structured_parts` differentiates each piece by only the
        coordinates it depends on and assembles the Jacobian once; the tangent is ``J @ du``.
        Values are exactly :meth:`_linear_parts`'s. Default optics only (the guided optics
        keep plain ``jacfwd``)."""
        if self.model.guided is not None:
            return self._linear_parts(self.unpack(u, base))
        flat, unravel = jax.flatten_util.ravel_pytree(u)
        return _structured_parts(self, unravel, flat, base)

    def _bases(self, params: Params, R, P, E=None):
        """The zone-local bases and the fixed part of the model (S, Z, B) each."""
        comps = self.model.components
        fixed = jnp.zeros_like(R)
        if "gain" not in self.linear:
            fixed = fixed + params.gain[:, None, None] * R
        if "crosstalk" in comps and "crosstalk_counts" not in self.linear:
            fixed = fixed + params.crosstalk_counts[..., None] * P
        if "ambient" in comps and "ambient_counts" not in self.linear:
            fixed = fixed + params.ambient_counts[..., None]
        names, basis = [], []
        if self.zone_gain:
            names.append("gain")
            basis.append(R)
        if E is not None:
            names.append("end_reflectance")
            basis.append(E)
        if "crosstalk_counts" in self.linear:
            names.append("crosstalk_counts")
            basis.append(P)
        if "ambient_counts" in self.linear:
            names.append("ambient_counts")
            basis.append(jnp.ones_like(R))
        return fixed, names, basis

    def profile(self, params: Params, data, sigma, parts=None):
        """The best linear parameters for the nonlinear ones in ``params``.

        **Returns:** ``(params, model, logdet, linear)``: ``params`` with the profiled values
        (with ``zone_gain`` its ``gain`` is the mean over zones), the model histograms at them,
        ``sum log det`` of the normal equations (for the posterior), and the profiled values
        themselves (``gain`` (S, Z) with ``zone_gain``).
        """
        R, P, E = self._linear_parts(params) if parts is None else parts
        if self.zone_gain:
            return self._profile_zone(params, R, P, data, sigma, E)
        return self._profile_sensor(params, R, P, data, sigma)

    def _profile_zone(self, params, R, P, data, sigma, E=None):
        w = 1.0 / sigma**2
        fixed, names, basis = self._bases(params, R, P, E)
        m = len(basis)
        n = 4 if E is not None else 3
        y = data - fixed
        # Gram matrix and projections, padded to n unknowns (identity rows for absent ones)
        Bs = jnp.stack(basis + [jnp.zeros_like(R)] * (n - m), axis=-2)  # (S, Z, n, B)
        # elementwise products and sums, not einsum: a (3 x B) @ (B x 3) product per zone is a
        # tiny batched matmul, which XLA's CPU backend runs as a loop of small calls, far worse
        # again under vmap; as broadcasts and reductions it fuses into a few passes
        Bw = Bs * w[..., None, :]
        G = jnp.sum(Bw[..., :, None, :] * Bs[..., None, :, :], axis=-1)
        b = jnp.sum(Bw * y[..., None, :], axis=-1)
        yy = jnp.sum(w * y * y, axis=-1)
        present = jnp.asarray([1.0] * m + [0.0] * (n - m), R.dtype)
        scale = jnp.where(present > 0, jnp.maximum(jnp.diagonal(G, axis1=-2, axis2=-1), jnp.finfo(R.dtype).tiny), 1.0)
        # every active set: the non-negative least-squares optimum is the best feasible one
        masks = jnp.asarray(list(itertools.product([1.0, 0.0], repeat=n)), R.dtype) * present  # (2^n, n)
        Gm = G[..., None, :, :] * masks[:, :, None] * masks[:, None, :]
        Gm = Gm + jnp.eye(n, dtype=R.dtype) * ((1.0 - masks)[:, :, None] + 1e-12 * masks[:, :, None]) * scale[..., None, :, None]
        if n == 3:
            inv, det = _inv3(Gm)  # (S, Z, 8, 3, 3)
        else:
            # scaled to unit diagonal first: the Gram matrix spans many decades
            d = 1.0 / jnp.sqrt(jnp.diagonal(Gm, axis1=-2, axis2=-1))
            inv_s = jnp.linalg.inv(Gm * d[..., :, None] * d[..., None, :])
            inv = inv_s * d[..., :, None] * d[..., None, :]
            det = jnp.linalg.det(Gm * d[..., :, None] * d[..., None, :]) / jnp.prod(d, axis=-1) ** 2
        c = jnp.sum(inv * (b[..., None, :] * masks)[..., None, :], axis=-1)
        ssr = yy[..., None] - 2.0 * jnp.sum(c * b[..., None, :], -1) + jnp.sum(c[..., :, None] * Gm * c[..., None, :], axis=(-2, -1))
        feasible = jnp.all(c >= 0.0, axis=-1)
        k = jnp.argmin(jnp.where(feasible, ssr, jnp.inf), axis=-1)  # (S, Z); the empty set is always feasible
        coef = jnp.take_along_axis(c, k[..., None, None], axis=-2)[..., 0, :]  # (S, Z, 3)
        fitted = fixed + sum(coef[..., i, None] * basis[i] for i in range(m))
        # the first active set is the full one (absent unknowns have unit rows)
        logdet = jnp.sum(jnp.log(jnp.maximum(det[..., 0], jnp.finfo(R.dtype).tiny)))
        out = {k: coef[..., i] for i, k in enumerate(names)}
        if "end_reflectance" in out:
            # the edge's coefficient is gain x reflectance
            g = out["gain"]
            out["end_reflectance"] = jnp.where(g > 0, out["end_reflectance"] / jnp.where(g > 0, g, 1.0), 0.0)
        rep = dict(out)
        if "gain" in rep:
            rep["gain"] = jnp.mean(rep["gain"], axis=-1)
        if "end_reflectance" in rep:
            rep["end_reflectance"] = _mean_reflectance(rep["end_reflectance"])
        return params.replace(**rep), fitted, logdet, out

    def _profile_sensor(self, params, R, P, data, sigma):
        """Gain shared by a sensor's zones: the zone unknowns are eliminated with an explicit
        2 x 2 solve per zone, then the gain from its Schur complement (unconstrained)."""
        w = 1.0 / sigma**2
        fixed, names, basis = self._bases(params, R, P)
        y = data - fixed

        def ip(a, b):
            return jnp.sum(w * a * b, axis=-1)

        logdet = jnp.zeros((), R.dtype)
        m = len(basis)
        if m == 1:
            g = ip(basis[0], basis[0])
            g = g + 1e-12 * g + jnp.finfo(R.dtype).tiny
            ginv = [[1.0 / g]]
            logdet = logdet + jnp.sum(jnp.log(g))
        elif m == 2:
            a, b, c = ip(basis[0], basis[0]), ip(basis[0], basis[1]), ip(basis[1], basis[1])
            ridge = 1e-12 * (a + c) + jnp.finfo(R.dtype).tiny
            a, c = a + ridge, c + ridge
            det = a * c - b * b
            ginv = [[c / det, -b / det], [-b / det, a / det]]
            logdet = logdet + jnp.sum(jnp.log(det))

        def zone_coefs(v):
            proj = [ip(bi, v) for bi in basis]
            return [sum(ginv[i][j] * proj[j] for j in range(m)) for i in range(m)]

        def q_ip(u, v):  # <u, (I - projection onto the zone basis) v>
            out = ip(u, v)
            if m:
                cv = zone_coefs(v)
                out = out - sum(ip(u, basis[i]) * cv[i] for i in range(m))
            return out

        out, fitted = {}, fixed
        if "gain" in self.linear:
            rr = jnp.sum(q_ip(R, R), axis=1) + jnp.finfo(R.dtype).tiny  # (S,)
            gain = jnp.sum(q_ip(R, y), axis=1) / rr
            out["gain"] = gain
            fitted = fitted + gain[:, None, None] * R
            logdet = logdet + jnp.sum(jnp.log(rr))
            y = y - gain[:, None, None] * R
        if m:
            for k, coef, bi in zip(names, zone_coefs(y), basis):
                out[k] = coef
                fitted = fitted + coef[..., None] * bi
        return params.replace(**out), fitted, logdet, out

    # ---- objectives -----------------------------------------------------------------------

    def prior_residuals(self, u, prior):
        """A weak Gaussian prior ``(u - prior) / width`` on the nonlinear coordinates: keeps a
        parameter the data cannot pin (mu_a -> 0 in log space) finite, barely moves the rest."""
        parts = [jnp.ravel((u[k] - prior[k]) / self.prior_width) for k in sorted(u) if self.prior_precision(k) > 0]
        if "n1" in u and "n1_anchor" in prior:
            # the timing estimate of n1 (edge returns, known geometry) as a measurement:
            # (centre, width); an infinite width (no edge seen) makes it zero
            centre, width = prior["n1_anchor"][0], prior["n1_anchor"][1]
            parts.append(jnp.ravel((self.transform("n1").to_physical(u["n1"]) - centre) / width))
        return jnp.concatenate(parts) if parts else jnp.zeros((0,), jnp.result_type(float))

    def _profiled(self, u, base: Params, data, sigma):
        """``(params, model, linear, parts)`` at the coordinates ``u``: the profiled parameters,
        the model at them, the linear values by name and the model's parts
        (:meth:`_linear_parts`; None without linear parameters)."""
        params = self.unpack(u, base)
        if not self.linear:
            return params, self.model(params), {}, None
        parts = self._parts_of(u, base)
        p, m, _, lin = self.profile(params, data, sigma, parts)
        return p, m, lin, parts

    def profiled_model(self, u, base: Params, data, sigma):
        return self._profiled(u, base, data, sigma)[:3]

    def _residual_vector(self, u, m, data, sigma, prior):
        """The Poisson-weighted data residuals of the model ``m``, then the prior's."""
        data_part = ((m - data) / sigma).ravel()
        return jnp.concatenate([data_part.astype(jnp.result_type(float)), self.prior_residuals(u, prior)])

    def residuals(self, u, args):
        """Profiled, Poisson-weighted residuals and the prior; ``args = (base, data, sigma, prior)``."""
        base, data, sigma, prior = args
        return self._residual_vector(u, self.profiled_model(u, base, data, sigma)[1], data, sigma, prior)

    def deviance(self, u, args):
        """Poisson deviance per bin of the profiled model, plus the prior."""
        base, d, sigma, prior = args
        _, m, _ = self.profiled_model(u, base, d, sigma)
        mu = jnp.maximum(m, 1e-9)
        term = mu - d + jnp.where(d > 0, d * jnp.log(jnp.where(d > 0, d, 1.0) / mu), 0.0)
        # the frame count from the arguments (sigma^2 = max(d, 1) / frames)
        frames = jnp.mean(jnp.maximum(d, 1.0) / sigma**2)
        return (2.0 * frames * jnp.sum(term) + jnp.sum(self.prior_residuals(u, prior) ** 2)) / d.size

    def full_residuals(self, u, base: Params, prior, data, sigma):
        """Residuals with every free parameter explicit (for the covariance), prior included."""
        phys = self.physical(u)
        params = self.unpack(u, base)
        if self.zone_gain:
            R, P, E = self._linear_parts(params)
            if E is not None:
                R = R + phys["end_reflectance"][..., None] * E
            m = phys["gain"][..., None] * R
            if "crosstalk" in self.model.components:
                m = m + params.crosstalk_counts[..., None] * P
            if "ambient" in self.model.components:
                m = m + params.ambient_counts[..., None]
        else:
            m = self.model(params)
        data_part = ((m - data) / sigma).ravel()
        return jnp.concatenate([data_part.astype(jnp.result_type(float)), self.prior_residuals(u, prior)])

    def _linear_columns(self, params: Params, linear: dict, sigma, ft, parts=None):
        """The data residuals' derivatives by each profiled linear parameter's *physical* values at
        ``params`` (one column per sensor or zone, written down from ``linear_parts``): ``{name:
        (S * Z * B, size)}``, for every name of ``self.linear`` among the free parameters.
        ``parts``: :meth:`_linear_parts` at ``params``, when the caller has them."""
        R, P, E = self._linear_parts(params) if parts is None else parts
        S, Z, B = R.shape
        R, P, sig = R.astype(ft), P.astype(ft), jnp.asarray(sigma, ft)
        if E is not None:
            E = E.astype(ft)
            e_z = jnp.asarray(linear["end_reflectance"], ft)
            g_z = jnp.asarray(linear["gain"], ft)
            R = R + e_z[..., None] * E  # d/d gain
            E = g_z[..., None] * E  # d/d reflectance
        eye_s, eye_z = jnp.eye(S, dtype=ft), jnp.eye(Z, dtype=ft)
        comps = self.model.components
        cols = {}
        for k in sorted(self.free):
            if k not in self.linear:
                continue
            if k == "gain" and not self.zone_gain:
                cols[k] = jnp.einsum("szb,st->szbt", R / sig, eye_s).reshape(S * Z * B, S)
            elif k in ("gain", "end_reflectance") or (k == "crosstalk_counts" and "crosstalk" in comps) or (k == "ambient_counts" and "ambient" in comps):
                part = {"gain": R, "crosstalk_counts": P, "end_reflectance": E}.get(k, jnp.ones_like(R))
                cols[k] = jnp.einsum("szb,st,zy->szbty", part / sig, eye_s, eye_z).reshape(S * Z * B, S * Z)
            else:
                cols[k] = jnp.zeros((S * Z * B, int(np.size(linear[k]))), ft)
        return cols

    def _assemble_jacobian(self, u: dict, j_nl, lin_cols: dict):
        """The covariance's Jacobian (columns in ``ravel_pytree`` order of ``u``) from the nonlinear
        columns ``j_nl`` (all rows) and the linear ones in physical units (data rows), carried to
        the linear parameters' coordinates."""
        n_rows = j_nl.shape[0]
        cols, pos = {}, 0
        for k in sorted(u):
            if k in self.linear:
                continue
            n = int(np.size(u[k]))
            cols[k] = j_nl[:, pos : pos + n]
            pos += n
        for k, block in lin_cols.items():
            block = block * jnp.ravel(self.transform(k).derivative(u[k]))[None, :]
            cols[k] = jnp.concatenate([block, jnp.zeros((n_rows - block.shape[0], block.shape[1]), block.dtype)])
        return jnp.concatenate([cols[k] for k in sorted(u)], axis=1)

    def covariance_jacobian(self, params: Params, linear: dict, prior_params: Params, data, sigma, anchor=None):
        """Jacobian of :meth:`full_residuals` over every free coordinate (columns in
        ``ravel_pytree`` order). Nonlinear columns by forward-mode AD; the linear ones (one per
        sensor or zone, most of the columns) written down from ``linear_parts``."""
        u = self.pack_jax(params, self.free, linear)
        prior = self.pack_jax(prior_params, self.free)
        if anchor is not None:
            prior["n1_anchor"] = anchor
        lin = {k: u[k] for k in u if k in self.linear}
        nl = {k: u[k] for k in u if k not in self.linear}
        f_nl, unravel_nl = jax.flatten_util.ravel_pytree(nl)
        j_nl = jax.jacfwd(lambda g: self.full_residuals({**unravel_nl(g), **lin}, params, prior, data, sigma))(f_nl)
        return self._assemble_jacobian(u, j_nl, self._linear_columns(params, linear, sigma, j_nl.dtype))

    def residuals_and_linear(self, u, args):
        """:meth:`residuals`, the profiled linear parameters' physical values, flat (sorted
        names, each raveled), and, not to be differentiated, ``(params, linear, parts)``: the
        profiled parameters (:meth:`profiled_model`'s), the linear values by name and the model's
        parts (:meth:`_linear_parts`; None without linear parameters). The objective of a fit that
        keeps both Jacobians and the profiled point (:meth:`laplace_from_fit`): its end evaluates
        no model of its own."""
        base, data, sigma, prior = args
        params, m, lin, parts = self._profiled(u, base, data, sigma)
        ft = jnp.result_type(float)
        flat = jnp.concatenate([jnp.ravel(lin[k]).astype(ft) for k in sorted(lin)] or [jnp.zeros((0,), ft)])
        return self._residual_vector(u, m, data, sigma, prior), flat, (params, lin, parts)

    def laplace_from_fit(self, params: Params, linear: dict, jac, jac_linear, sigma, parts=None):
        """:meth:`laplace`'s pieces from the fit's own Jacobians at the optimum, no new derivative:
        ``jac`` of the profiled residuals and ``jac_linear`` of the profiled linear values
        (:meth:`residuals_and_linear`), both by the fit's nonlinear coordinates. The residuals
        are affine in the linear parameters, so by the chain rule the derivative at fixed linear
        values is ``jac - (d r / d linear) jac_linear``: the same Jacobian as
        :meth:`covariance_jacobian` (equal to rounding; tested). ``parts``: the model's parts at
        ``params`` (:meth:`_linear_parts`), when the fit kept them."""
        u = self.pack_jax(params, self.free, linear)
        ft = jac.dtype
        lin_cols = self._linear_columns(params, linear, sigma, ft, parts)
        n_data = next(iter(lin_cols.values())).shape[0] if lin_cols else 0
        if lin_cols:
            names = sorted(linear)
            if names != list(lin_cols):
                raise ValueError(f"profiled linear parameters {names} are not the covariance's {list(lin_cols)}")
            pos, through = 0, jnp.zeros((n_data, jac.shape[1]), ft)
            for k, block in lin_cols.items():
                n = block.shape[1]
                through = through + block @ jac_linear[pos : pos + n]
                pos += n
            jac = jnp.concatenate([jac[:n_data] - through, jac[n_data:]])
        j = self._assemble_jacobian(u, jac, lin_cols)
        return j.T @ j, self._dphys(u)

    def _dphys(self, u):
        flat, unravel = jax.flatten_util.ravel_pytree(u)
        names = sorted(self.free)

        def phys_flat(f):
            x = self.physical(unravel(f))
            return jnp.concatenate([jnp.ravel(x[k]) for k in names])

        return jax.jacfwd(phys_flat)(flat)

    def laplace(self, params: Params, linear: dict, prior_params: Params, data, sigma, anchor=None):
        """``J^T J`` over every free coordinate, and d(physical)/d(coordinates) (physical values
        in ``sorted(free)`` order), at the optimum."""
        jac = self.covariance_jacobian(params, linear, prior_params, data, sigma, anchor)
        u = self.pack_jax(params, self.free, linear)
        return jac.T @ jac, self._dphys(u), jax.flatten_util.ravel_pytree(u)[0]


#: Coordinates the pulse kernels depend on (and nothing else in ``linear_parts`` but the peak).
_PULSE = ("pulse_sigma_s", "pulse_tail_s", "pulse_slow_weight", "pulse_slow_tail_s")
#: Coordinates the light-entry peak depends on.
_PEAK = _PULSE + ("emission_time_s", "crosstalk_width_s")


def _structured_parts(problem: CalibrationProblem, unravel, flat, base):
    """:meth:`CalibrationProblem._linear_parts` at ``unravel(flat)``, its forward-mode
    derivative by :func:`_parts_jvp` (a closure: the problem's arrays may be tracers)."""

    @jax.custom_jvp
    def parts(flat, base):
        return problem._linear_parts(problem.unpack(unravel(flat), base))

    @parts.defjvp
    def _jvp(primals, tangents):
        return _parts_jvp(problem, unravel, primals, tangents)

    return parts(flat, base)


def _parts_jvp(problem, unravel, primals, tangents):
    flat, base = primals
    dflat, _ = tangents  # no derivative by ``base`` (the fit differentiates the coordinates only)
    model = problem.model
    sep = problem.zone_end
    n = flat.shape[0]
    # which flat positions belong to which coordinate (ravel_pytree: sorted keys)
    template = unravel(flat)
    pos, names = 0, []
    for k in sorted(template):
        names += [k] * int(np.size(template[k]))
        pos += int(np.size(template[k]))
    i_pulse = [i for i, k in enumerate(names) if k in _PULSE]
    i_peak = [i for i, k in enumerate(names) if k in _PEAK]
    i_mass = [i for i, k in enumerate(names) if k not in _PULSE and k != "crosstalk_width_s"]

    def params_at(idx, sub):
        return problem.unpack(unravel(flat.at[jnp.asarray(idx, jnp.int32)].set(sub)), base)

    def sub_jac(fn, idx):
        """``(value, d value / d flat[idx])``, the derivative on a new last axis."""
        if not idx:
            return fn(problem.unpack(unravel(flat), base)), None

        def f(sub):
            out = fn(params_at(idx, sub))
            return out, out

        jac, val = jax.jacfwd(f, has_aux=True)(flat[jnp.asarray(idx, jnp.int32)])
        return val, jac

    def scatter(jac, idx, shape):
        full = jnp.zeros(shape + (n,), flat.dtype)
        return full if jac is None else full.at[..., jnp.asarray(idx, jnp.int32)].set(jac.astype(flat.dtype))

    q, B = model.options.quadrature, model.n_bins
    has_cross = "crosstalk" in model.components
    stack, j_mass = sub_jac(lambda p: model.linear_masses(p, sep, node_jvp=True)[0], i_mass)
    kernels, j_kern = sub_jac(model.pulse_kernels, i_pulse)
    binned = apply_kernels(stack, kernels, B, q)  # (parts, S, Z, B)
    # d binned = apply(d masses, K) + apply(masses, d K)
    jb = jnp.zeros(binned.shape + (n,), binned.dtype)
    if j_mass is not None:
        jm = apply_kernels(jnp.moveaxis(j_mass, -1, 0), kernels, B, q)  # (n_mass, parts, S, Z, B)
        jb = jb.at[..., jnp.asarray(i_mass, jnp.int32)].set(jnp.moveaxis(jm, 0, -1))
    if j_kern is not None:
        jk = jax.vmap(lambda dk: apply_kernels(stack, dk, B, q))(jnp.moveaxis(j_kern, -1, 0))
        jb = jb.at[..., jnp.asarray(i_pulse, jnp.int32)].add(jnp.moveaxis(jk, 0, -1))
    S, Z, _ = model.shape
    if has_cross:
        peak, j_peak = sub_jac(lambda p: model.light_entry_peak(model._unit(p)), i_peak)
        cross = jnp.broadcast_to(peak, (S, Z, B))
        j_cross = jnp.broadcast_to(scatter(j_peak, i_peak, (B,)), (S, Z, B, n))
    else:
        cross = jnp.zeros((S, Z, B), binned.dtype)
        j_cross = jnp.zeros((S, Z, B, n), binned.dtype)
    values = (binned[0], cross) + ((binned[1],) if sep else (None,))
    jacs = (jb[0], j_cross) + ((jb[1],) if sep else (None,))
    tangents_out = tuple(None if j is None else j @ dflat for j in jacs)
    return values, tangents_out
