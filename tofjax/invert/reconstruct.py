"""Model-based reconstruction: non-negative contact strengths on a coarse grid that best
explain every sensor's histograms through the forward model (beyond seed 000).

The touch component of the forward model is linear in the contacts' strengths (without
shadowing), so the response of a unit contact at each grid cell is computed once (one
vmapped model evaluation) into a matrix ``A`` (bins x cells). For a frame ``P`` with
baseline ``B`` the strengths solve the weighted non-negative lasso

    min_s  1/2 || (P - B - A s) / sigma ||^2 + sum_k lambda_k s_k ,   s >= 0

with Poisson ``sigma^2 = B (1 + 1/N)`` and ``lambda_k = tau sqrt((A^T A / sigma^2)_kk)``:
a cell switches on only when its evidence exceeds ``tau`` noise standard deviations.
FISTA (accelerated projected gradient) on the Gram matrix, batched over frames, so a frame
costs a few hundred (cells x cells) products, independent of the number of bins.

Unlike back-projection, every sensor's histogram is explained jointly: a contact dimmed in
one sensor by a contact in front of it is still supported by the others, and one contact's
response tail is not mistaken for another.

**Contacts that shadow.** With a physical contact model (the guided optics' skin contact,
:mod:`tofjax.model.contact`) a contact mostly *removes* light: what it frustrates into the
skin is missing from the far-edge return and the volume light behind it, and the skin sends
little back. Its whole effect on the histograms, added and removed light with their signs,
grows with its coupling (``touch_strength``), so the column of ``A`` is that signed response
of a strength-1 contact (``response="signed"``) and the non-negative unknown is the contact's
strength: the fit uses the removed light as evidence *for* a contact, where the ``added``
column (the touch return alone) sees only the little light the skin returns. ``response``
``auto`` (default) takes the signed response when the calibration's optics are ``guided``
(their contacts come from the skin model) and the added one otherwise (the default optics:
contacts add light, their shadow is a separate strength-free occupancy, see ``shadow``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..config import ConfigError
from ..model import ModelOptions, Params, build_model
from ..model.forward import _trace_switches
from ..scene import Scene, Touch
from .correction import OpticalParams
from .maps import Grid

__all__ = ["RESPONSES", "ReconstructOptions", "Reconstructor", "build_reconstructor", "response_matrix"]

#: Which contact response fills the model method's columns (see the module docstring).
RESPONSES = ("auto", "added", "signed")


@dataclass(frozen=True)
class ReconstructOptions:
    """- ``cell_m``: grid cell size (default 7.5 mm).
    - ``contact_radius_m``: radius of the unit contact whose response fills ``A``.
    - ``tau``: sparsity, in noise standard deviations of each cell's evidence.
    - ``iterations``: FISTA iterations.
    - ``shadow``: also fit, per cell, a non-negative occupancy whose response is the light a
      contact there removes from everything behind it (shadowing does not depend on
      strength, so it gets its own column). Without it, a contact's shadow is a negative
      residual exactly where the contacts behind it are, and hides them.
    - ``sum_cells``: detection sees the strength summed over each 3 x 3 block of cells
      (a contact between cells splits its strength among them).
    - ``edge_exclusion_m``: no cells whose centre is nearer the edge than this: there the
      contact response and the far-edge reflection (and its shadow) are confounded.
    - ``n_sigma``: detection threshold on that summed strength in units of its noise: each
      cell's strength noise is ``1/sqrt((A^T A / sigma^2)_kk)`` (the matched filter's), and a
      3 x 3 sum adds nine in quadrature. Relative to the noise, not to tofjax's amplitude
      scale: a rig whose contacts come out at a tenth of the model's strength (another gain,
      another coupling) is thresholded the same way.
    - ``relative``: also require this fraction of the frame's largest summed strength: the
      model never fits a rig exactly, and what it cannot explain of a contact lands in cells
      around it, in proportion to the contact (scale-free, like the noise threshold).
    - ``min_strength``: an extra absolute floor on the summed strength, in the forward
      model's units (default 0: none; it was the only threshold before, 0.2).
    - ``response``: the contact column: ``added`` (the touch return a contact adds, plus the
      ``shadow`` occupancy), ``signed`` (the contact's whole change of the histograms, added
      and removed light, per unit strength; ``shadow`` is then part of it), or ``auto``
      (default): ``signed`` when the optics are ``guided`` (skin contacts, which mostly
      shadow), ``added`` otherwise.
    - ``dtype``: float32 or float64 for the solve."""

    cell_m: float = 0.0075
    contact_radius_m: float = 0.006
    tau: float = 4.0
    iterations: int = 300
    shadow: bool = True
    sum_cells: bool = True
    min_strength: float = 0.0
    edge_exclusion_m: float = 0.012
    n_sigma: float = 1.0
    relative: float = 0.1
    dtype: str = "float32"
    response: str = "auto"

    def __post_init__(self):
        if self.response not in RESPONSES:
            raise ConfigError(f"response: must be one of {', '.join(RESPONSES)}, got {self.response!r}")
        if not self.cell_m > 0:
            raise ConfigError(f"cell_m: must be > 0, got {self.cell_m!r}")
        if not self.contact_radius_m > 0:
            raise ConfigError(f"contact_radius_m: must be > 0, got {self.contact_radius_m!r}")
        if self.tau < 0 or self.iterations < 1:
            raise ConfigError("tau must be >= 0 and iterations >= 1")
        if not 0.0 <= self.relative < 1.0:
            raise ConfigError(f"relative: must be in [0, 1), got {self.relative!r}")
        for k in ("n_sigma", "min_strength"):
            v = getattr(self, k)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"{k}: must be a finite number >= 0, got {v!r}")


def _params_with_optics(scene: Scene, optical: OpticalParams, dtype) -> Params:
    p = Params.from_scene(scene, dtype)
    return p.replace(
        n1=optical.n1,
        mu_s_per_m=optical.mu_s_per_m,
        mu_a_per_m=optical.mu_a_per_m,
        gain=np.asarray(optical.gain),
        emission_time_s=optical.emission_time_s,
        pulse_sigma_s=optical.pulse_sigma_s,
        pulse_tail_s=optical.pulse_tail_s,
        near_field_m=optical.near_field_m,
        near_field_shape=optical.near_field_shape,
        **({"pulse_slow_weight": optical.pulse_slow_weight, "pulse_slow_tail_s": optical.pulse_slow_tail_s}
           if optical.pulse_tails == 2 else {}),
    )


@eqx.filter_jit
def _unit_responses(model, p0: Params, centres, switches):
    """``model`` at ``p0`` with its one contact moved to each of ``centres`` (K, 2): (K, S, Z, B).
    Module level, the model an argument: one program per model structure and chunk size, reused by
    every reconstructor (a jitted lambda made per call compiled again each time). ``switches``: the
    guided optics' module switches (read when tracing, so a static key)."""
    del switches
    return jax.vmap(lambda xy: model(p0.replace(touch_xy_m=xy[None, :])))(centres)


def _largest_eigenvalue(G: np.ndarray) -> float:
    """The largest eigenvalue of the (symmetric, positive semi-definite) Gram matrix: FISTA's step
    is its inverse. Lanczos (ARPACK) to machine precision from a fixed start (reproducible), not a
    whole eigendecomposition: on OptoSkin's 2592 columns 0.6 s instead of 36 s (loaded 2-core VM),
    the same value to 1e-15."""
    if G.shape[0] < 16:
        return float(np.linalg.eigvalsh(G)[-1])
    from scipy.sparse.linalg import eigsh

    v0 = np.random.default_rng(0).uniform(0.5, 1.5, G.shape[0])
    return float(eigsh(G, k=1, which="LA", return_eigenvectors=False, tol=0, v0=v0)[0])


class _Fista(eqx.Module):
    """The weighted non-negative lasso of one reconstructor (see the module docstring), as data:
    rows of the histograms kept, weighted response ``Aw`` (n, K), Gram matrix ``G``, penalties
    ``lam``, Poisson ``sigma`` and baseline of the kept rows, step ``1/L``, saturation."""

    rows: jax.Array
    Aw: jax.Array
    G: jax.Array
    lam: jax.Array
    sigma: jax.Array
    base: jax.Array
    step: jax.Array
    saturation: jax.Array
    iterations: int = eqx.field(static=True)


@eqx.filter_jit
def _fista(problem: _Fista, H):
    """H (F, S*Z*B) -> strengths (F, K), ok (F,): FISTA (accelerated projected gradient) on the Gram
    matrix. Module level, the problem an argument: one program per problem shape and iteration count,
    shared by every reconstructor (a jitted bound method compiled again for each)."""
    bad = ~jnp.isfinite(H) | (H >= problem.saturation)
    ok = ~jnp.any(bad, axis=-1)
    y = jnp.where(bad, 0.0, H)[:, problem.rows]
    yw = (y - problem.base) / problem.sigma
    b = yw @ problem.Aw  # (F, K)
    step = problem.step

    def body(_, state):
        s, z, t = state
        s_new = jnp.maximum(z - step * (z @ problem.G - b + problem.lam), 0.0)
        t_new = 0.5 * (1.0 + jnp.sqrt(1.0 + 4.0 * t * t))
        z_new = s_new + ((t - 1.0) / t_new) * (s_new - s)
        return s_new, z_new, t_new

    s0 = jnp.zeros_like(b)
    s, _, _ = jax.lax.fori_loop(0, problem.iterations, body, (s0, s0, jnp.asarray(1.0, b.dtype)))
    return jnp.where(ok[:, None], s, 0.0), ok


def response_matrix(
    scene: Scene,
    optical: OpticalParams,
    centres: np.ndarray,
    radius_m: float,
    chunk: int = 128,
    *,
    shadow: bool = False,
    signed: bool = False,
) -> np.ndarray:
    """Expected touch counts (S, Z, B) of a unit contact at each of ``centres`` (K, 2): (K, S, Z, B).

    With ``shadow``: instead, the change of the no-touch histograms when a contact of zero
    strength sits there (the light it removes from everything behind it; <= 0).
    With ``signed``: the whole change a strength-1 contact makes (its touch return plus the
    light it removes, with their signs: every component with the contact minus without).
    """
    if shadow and signed:
        raise ValueError("response_matrix: shadow and signed are exclusive")
    base = scene.without_touches()
    lx, ly = scene.waveguide.size_m
    proto = base.replace(touches=(Touch((0.5 * lx, 0.5 * ly), radius_m, 1.0),))  # inside any guide
    guided = optical.optics == "guided"
    if guided:
        # the calibration's optics: guided light, and contacts from the skin model (the shadow then
        # follows from the contact's coupling, so the occupancy column is a contact of strength 1)
        from ..model.contact import SkinContact

        opts = ModelOptions(dtype="float64" if jax.config.jax_enable_x64 else "float32", pulse_tails=optical.pulse_tails,
                            optics="guided", skin=SkinContact())
    else:
        opts = ModelOptions(dtype="float64" if jax.config.jax_enable_x64 else "float32", pulse_tails=optical.pulse_tails)
    if signed:
        comps = proto.components()
    else:
        comps = tuple(c for c in proto.components() if c != "touch") if shadow else ("touch",)
    if shadow and "shadowing" not in comps:
        return np.zeros((len(centres), *scene.shape))
    model = build_model(proto, opts, components=comps)
    p0 = _params_with_optics(proto, optical, opts.jnp_dtype)
    if signed:
        ref = np.asarray(
            build_model(base, opts, components=tuple(c for c in comps if c not in ("touch", "shadowing")))(
                _params_with_optics(base, optical, opts.jnp_dtype)
            )
        )
    elif shadow:
        p0 = p0.replace(touch_strength=np.ones(1) if guided else np.zeros(1))
        ref = np.asarray(
            build_model(base, opts, components=tuple(c for c in comps if c != "shadowing"))(
                _params_with_optics(base, optical, opts.jnp_dtype)
            )
        )
    # chunks of one size (the last padded with copies of its last centre): one program for all of them, where
    # chunks of ``chunk`` and a shorter rest compiled the model twice
    K = len(centres)
    if K == 0:
        return np.zeros((0, *scene.shape))
    n = -(-K // chunk)
    size = -(-K // n)
    padded = np.concatenate([centres, np.repeat(centres[-1:], n * size - K, axis=0)])
    out = np.concatenate([np.asarray(_unit_responses(model, p0, jnp.asarray(padded[i : i + size]), _trace_switches()))
                          for i in range(0, n * size, size)])[:K]
    if signed:
        return out - ref[None]
    return np.minimum(out - ref[None], 0.0) if shadow else out


class Reconstructor:
    """Precomputed model-based reconstruction of one scene (see :func:`build_reconstructor`)."""

    def __init__(
        self, scene: Scene, baseline: np.ndarray, optical: OpticalParams, options: ReconstructOptions, n_baseline: int
    ):
        self.scene, self.options = scene, options
        self.grid = Grid.for_scene(scene, options.cell_m)
        all_centres = self.grid.centres().reshape(-1, 2)
        lx, ly = scene.waveguide.size_m
        e = options.edge_exclusion_m
        x, y = all_centres[:, 0], all_centres[:, 1]
        self.cells = np.flatnonzero((x >= e) & (x <= lx - e) & (y >= e) & (y <= ly - e))
        centres = all_centres[self.cells]
        resp = options.response
        self.response = ("signed" if optical.optics == "guided" else "added") if resp == "auto" else resp
        signed = self.response == "signed"
        R = response_matrix(scene, optical, centres, options.contact_radius_m, signed=signed)  # (K, S, Z, B)
        K = R.shape[0]
        self.n_cells = K
        A = R.reshape(K, -1).T  # (n, K)
        if options.shadow and not signed:
            D = response_matrix(scene, optical, centres, options.contact_radius_m, shadow=True).reshape(K, -1).T
            A = np.concatenate([A, D], 1)  # (n, 2K): strengths, then occupancies
        rows = np.flatnonzero(np.abs(A).max(1) > 1e-9 * np.abs(A).max())
        self.rows = rows
        sigma = np.sqrt(np.maximum(np.asarray(baseline, float).ravel()[rows], 1.0) * (1.0 + 1.0 / n_baseline))
        Aw = A[rows] / sigma[:, None]
        G = Aw.T @ Aw
        self._g_diag = np.diag(G).copy()
        # strength x occupancy of the same cell (shadow columns only): what the lasso's shrinkage of a
        # contact's strength depends on besides its own penalty (shrinkage_map)
        self._g_pair = np.diagonal(G, offset=K).copy() if G.shape[0] == 2 * K else None
        self.lam = options.tau * np.sqrt(np.maximum(self._g_diag, 1e-30))
        L = _largest_eigenvalue(G)
        dt = jnp.float64 if options.dtype == "float64" and jax.config.jax_enable_x64 else jnp.float32
        self._problem = _Fista(
            rows=jnp.asarray(rows), Aw=jnp.asarray(Aw, dt), G=jnp.asarray(G, dt), lam=jnp.asarray(self.lam, dt),
            sigma=jnp.asarray(sigma, dt), base=jnp.asarray(np.asarray(baseline, float).ravel()[rows], dt),
            step=jnp.asarray(1.0 / L, dt), saturation=jnp.asarray(float(scene.sensor.saturation_counts), dt),
            iterations=options.iterations,
        )

    def strengths(self, histograms) -> tuple[np.ndarray, np.ndarray]:
        """(F, ny, nx) strengths on the coarse grid and ok flags (F,)."""
        h = np.asarray(histograms, float)
        F = h.shape[0]
        s, ok = _fista(self._problem, jnp.asarray(h.reshape(F, -1), self._problem.G.dtype))
        out = np.zeros((F, self.grid.ny * self.grid.nx))
        out[:, self.cells] = np.asarray(s)[:, : self.n_cells]
        return out.reshape(F, self.grid.ny, self.grid.nx), np.asarray(ok)

    def maps(self, histograms) -> tuple[np.ndarray, np.ndarray]:
        """What detection sees: strengths, summed over 3 x 3 blocks with ``sum_cells``."""
        s, ok = self.strengths(histograms)
        if self.options.sum_cells:
            from scipy import ndimage

            s = 9.0 * ndimage.uniform_filter(s, size=(1, 3, 3), mode="constant")
        return s, ok

    def cell_noise_map(self) -> np.ndarray:
        """Noise (std) of one cell's strength, per cell: ``1/sqrt(G_kk)``, the matched filter's noise in
        strength units (a contact of strength ``s`` alone at a known cell has matched-filter SNR
        ``s sqrt(G_kk)``). Cells left out (near the edge) or that no sensor sees get +inf."""
        var = np.full(self.grid.ny * self.grid.nx, np.inf)
        g = self._g_diag[: self.n_cells]
        # a cell no sensor sees (no response: a million times weaker than the best seen) is never
        # detected: infinite noise, kept out of the sums
        var[self.cells] = np.where(g > 1e-12 * max(float(g.max()), 1e-300), 1.0 / np.maximum(g, 1e-300), np.inf)
        return np.sqrt(var.reshape(self.grid.ny, self.grid.nx))

    def shrinkage_map(self) -> np.ndarray:
        """Strength the lasso takes off a contact alone at each cell, without noise: ``lambda_k / G_kk``
        (``tau`` times :meth:`cell_noise_map`) when the cell's strength column is the only one on. With
        the shadow occupancies (``added`` response, ``shadow``), a contact's own shadow switches its cell's
        occupancy on too, and both penalties come off jointly: ``(G2^-1 lambda2)_0`` with ``G2`` the 2 x 2
        Gram block of the cell's strength and occupancy columns (their correlation is negative: the touch
        return's tail falls where the shadow begins, so the shrinkage is larger). +inf where not sensed."""
        sig = self.cell_noise_map().ravel()
        out = np.full(sig.shape, np.inf)
        K = self.n_cells
        g = self._g_diag[:K]
        la = self.lam[:K]
        shrink = la / np.maximum(g, 1e-300)
        if self._g_pair is not None:
            gd, gad, ld = self._g_diag[K:], self._g_pair, self.lam[K:]
            det = g * gd - gad**2
            both = (gd > 1e-12 * max(float(gd.max()), 1e-300)) & (det > 1e-9 * g * np.maximum(gd, 1e-300))
            with np.errstate(divide="ignore", invalid="ignore"):
                s_pair = (gd * la - gad * ld) / det
                o_pair = (g * ld - gad * la) / det  # what the occupancy (1 for a contact's shadow) loses
            both &= o_pair < 1.0  # the shadow survives its own penalty: both columns on
            shrink = np.where(both, s_pair, shrink)
        out[self.cells] = shrink
        out[~np.isfinite(sig)] = np.inf
        return out.reshape(self.grid.ny, self.grid.nx)

    def noise_map(self) -> np.ndarray:
        """Noise (std) of what :meth:`maps` returns, per cell: :meth:`cell_noise_map` for one cell's
        strength, nine added in quadrature for the 3 x 3 sums. Cells left out get +inf (never detected)."""
        var = self.cell_noise_map() ** 2
        if self.options.sum_cells:
            from scipy import ndimage

            finite = np.isfinite(var)
            v = np.where(finite, var, 0.0)
            # a direct 3 x 3 sum (uniform_filter's running sums cancel catastrophically across the
            # orders of magnitude between well-seen and barely-seen cells)
            var = np.where(finite, ndimage.correlate(v, np.ones((3, 3)), mode="constant"), np.inf)
        return np.sqrt(np.maximum(var, 0.0))


def build_reconstructor(
    scene: Scene,
    baseline: np.ndarray,
    optical: OpticalParams | None = None,
    options: ReconstructOptions = ReconstructOptions(),
    *,
    n_baseline: int = 1,
    grid: Grid | None = None,
) -> Reconstructor:
    """Build the response matrix and Gram matrix of ``scene`` once (``grid`` is ignored: the
    reconstruction has its own coarse grid, ``options.cell_m``)."""
    optical = OpticalParams.from_scene(scene) if optical is None else optical
    return Reconstructor(scene, baseline, optical, options, n_baseline)
