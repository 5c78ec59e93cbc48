"""Contact detection by fitting: greedy forward selection of contacts with a joint refit (``method="fit"``).

The grid reconstruction (:mod:`tofjax.invert.reconstruct`) explains a frame as a sparse sum of
fixed per-cell responses and thresholds a map; six skin contacts that each mostly *shadow* the
same far-edge return share their evidence and come out as blurred, merged or missing cells.
Here the contacts themselves are the unknowns, each a position and a strength, and the frame
is explained by the forward model with *all* of them at once (their shadows on each other
included, not a sum of single-contact responses):

1. The weighted residual of the frame against the current fit, ``r = (P - B - Delta(theta)) / sigma``,
   with ``B`` the baseline mean, ``sigma^2 = B (1 + 1/N)`` (photon noise of the frame and the
   N-frame baseline) and ``Delta(theta)`` the guided model's change of the histograms caused by
   the contacts ``theta`` (their added and removed light, with signs: each contact's signed
   response, strength in [0, ``max_strength``], in units of the skin model's coupling).
2. **Proposal**: for every cell of a fine grid (``cell_m``), the chi-square drop of adding one
   contact there with the best strength in [0, ``max_strength``], from the precomputed signed response of a
   unit contact there (a matched filter). The best cell at least ``min_separation_m`` from the
   contacts already found is added.
3. **Joint refit**: Levenberg-Marquardt on every contact's position and strength (the Jacobian
   by forward differentiation of the model), positions kept inside the guide, strengths in
   [0, ``max_strength``].
4. **Moves of several contacts** after the forward selection: relocation, splits, and a death-and-birth
   sweep (``rebirth``: a contact removed, the others refitted jointly without it, the forward selection
   resumed; kept when chi-square plus ``n_sigma_forward^2`` per contact falls), which frees a weak contact
   that a strong neighbour, pulled towards it, had absorbed. Optional pair moves (``pair_split``, off) replace a
   contact, or a contact and its neighbour, by the best pair of cells for the residual without them.
5. **Stop** when the refit's chi-square drop is below ``n_sigma^2`` (a likelihood-ratio test
   in noise units: the drop is ``z^2`` of the new contact's evidence); then **backward pruning**:
   a contact whose removal (with refit) raises the chi-square by less than ``n_sigma^2`` goes. The
   pruning's chi-square counts the model's own error as noise (``model_error``, default 0.2: each bin's
   variance plus ``(0.2 Delta)^2``), so what the model gets wrong of a strong contact is not evidence of
   another one; each contact kept gets standard errors of its position and strength (Laplace, at the fit).

Everything is in noise units, none in tofjax's amplitude scale: a rig whose contacts couple at a
tenth of the model's strength is thresholded the same way. ``overdispersion`` (default on) divides
the drops by the final fit's reduced chi-square when it exceeds 1: what the model cannot describe
of the frame (a different rig, the Monte Carlo) is then counted as noise instead of as contacts.

The number of contacts is inferred (at most ``max_contacts``: the model has that many slots, the
unused ones at strength 0, so one compiled model serves every count).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..config import ConfigError
from ..model import ModelOptions, build_model
from ..scene import Scene, Touch
from .correction import InversionError, OpticalParams
from .detect import Detection
from .maps import Grid

__all__ = ["PRUNE_OPTIONS", "FitDetectOptions", "FitDetector", "ProposalResponses", "build_fit_detector",
           "lone_position_bounds", "position_covariance", "proposal_responses"]

#: the options of the backward pruning only (:meth:`FitDetector.finish_frame`): variants that differ in these
#: share one search (:meth:`FitDetector.process_variants`)
PRUNE_OPTIONS = ("n_sigma", "overdispersion", "prune", "n_sigma_absorbed", "min_strength", "model_error")


@dataclass(frozen=True)
class FitDetectOptions:
    """- ``n_sigma``: a contact is kept when it lowers the chi-square by more than ``n_sigma^2``
      (its evidence in noise standard deviations, a likelihood-ratio test; default 6: the proposal
      searches thousands of positions, so pure noise reaches ~4-5).
    - ``n_sigma_forward``: the forward selection adds contacts down to this (lower) evidence; the
      pruning then keeps those above ``n_sigma`` (over-complete first: a spare contact lets the
      refit split a greedy pick that sat between two contacts).
    - ``cell_m``: the proposal grid (default 5 mm); positions are then refined continuously.
    - ``contact_radius_m``: the radius of the contacts the model fits.
    - ``max_contacts``: at most this many contacts per frame (the model's slots).
    - ``min_separation_m``: a new contact is proposed at least this far from those found.
    - ``edge_margin_m``: contact centres stay at least this far inside the guide.
    - ``iterations``: Levenberg-Marquardt steps of each joint refit.
    - ``overdispersion``: divide the chi-square drops by the final fit's reduced chi-square when > 1
      (model error counted as noise).
    - ``prune``: backward pruning after the forward selection.
    - ``relocate``: after the forward selection, move each contact to the best position the
      residual without it proposes (its ``relocate_candidates`` best local maxima), when that lowers
      the chi-square.
    - ``split``: after relocating, try replacing each contact (strongest first) by two, at the best
      ``split_candidates`` pairs of local maxima of the residual without it; kept when the chi-square
      falls by more than ``n_sigma_forward^2``.
    - ``rounds``: after a split (or relocation) changed the fit, resume the forward selection and the
      moves at most this many more times (0: one greedy pass, then relocation only).
    - ``starts``: multi-start: the whole search is also run from each of the ``starts - 1`` next best local
      maxima of the first evidence map as the first contact; the fit with the lowest chi-square plus
      ``n_sigma_forward^2`` per contact is kept (default 1: off; each start costs a whole search).
    - ``rebirth``: after the other moves, a death-and-birth sweep (weakest contact first): the contact is removed,
      *the others are refitted jointly without it*, and the forward selection resumes from there (it may add
      the contact back elsewhere, or two where there was one); kept when the chi-square plus
      ``n_sigma_forward^2`` per contact falls. Unlike ``relocate`` and ``split`` (which propose from the
      residual with the others fixed where they sat beside the removed contact), the proposal sees the
      evidence the others had absorbed: a strong contact pulled towards a weak neighbour, or one contact
      placed between two, moves back and frees the weak one (default on).
    - ``rebirth_candidates``: the birth after a death also tries the next best local maxima of the proposal
      (up to this many in all), alone and in pairs, each refitted briefly; the best of those is continued
      like the first (1: the forward selection's single best cell only).
    - ``rebirth_sweeps``: at most this many death-and-birth sweeps (a sweep that changes nothing ends them).
    - ``pair_split``: after the death-and-birth sweeps, each contact (strongest first) replaced by the best pairs of
      cells for the residual without it, scored by the linear model (the 2 x 2 normal equations of two cells'
      responses, over the ``pair_pool`` best single proposals; the responses' Gram matrix is computed once per
      detector); tried when the pair beats the best single contact by ``n_sigma_forward^2`` (linear), kept when the
      refit lowers the chi-square by more than that; ``pair_candidates`` pairs per contact. Aimed at a ghost at the
      strength bound standing in for two contacts (default off: on the twelve six-contact scenes at 16x it changed
      recall by +0 (own) / +1 contact (Monte Carlo) and added one duplicate in each, at a higher cost per frame).
    - ``pair_swap`` (with ``pair_split``): a contact and its nearest neighbour (within 3 ``min_separation_m``)
      replaced by the best pair for the residual without both, kept when the chi-square falls.
    - ``n_sigma_absorbed``: prune a contact at this threshold instead of ``n_sigma`` where its removal lets another
      contact move into its place (by more than half ``min_separation_m``) (default None: ``n_sigma``).
    - ``min_strength``: an extra floor on a contact's fitted strength (in units of the skin model's coupling;
      default 0: none).
    - ``model_error``: the forward model's relative error of a contact's signal, as a noise term of the
      backward pruning: each bin's variance becomes ``sigma^2 + (model_error * Delta)^2``, with ``Delta`` the
      fitted contacts' change of that bin (``Delta`` of the fit before pruning). What the model gets wrong of a
      strong contact's signal is then not evidence of another contact (a ghost explaining it), while a contact
      whose evidence lies in bins the others hardly change keeps its full weight. It matters only where a bin's
      change is several noise sd (long exposures); default 0.2, within the guided model's measured error of a
      contact's signal against the Monte Carlo (relative L2 0.055 mid-guide, 0.12 near a wall, 0.19-0.24 near a
      corner, where the false detections were), chosen over 0.1 on two sets of six-contact frames and confirmed on
      a third (docs/results/pruning_choice_protocol.md; 0 counts photon noise only).
    - ``max_strength``: the largest fitted strength, in units of the skin model's coupling (default 1; above 1 a
      contact couples more than the skin model's typical share, up to full optical contact at ``1 / coupling``:
      without it, such a contact is fitted as duplicates at the bound)."""

    n_sigma: float = 6.0
    n_sigma_forward: float = 4.0
    cell_m: float = 0.005
    contact_radius_m: float = 0.006
    max_contacts: int = 8
    min_separation_m: float = 0.02
    edge_margin_m: float = 0.006
    iterations: int = 6
    overdispersion: bool = True
    prune: bool = True
    relocate: bool = True
    relocate_candidates: int = 3
    split: bool = True
    split_candidates: int = 2
    rounds: int = 1
    starts: int = 1
    min_strength: float = 0.0
    rebirth: bool = True
    rebirth_sweeps: int = 2
    rebirth_candidates: int = 3
    pair_split: bool = False
    pair_swap: bool = True
    n_sigma_absorbed: float | None = None
    pair_candidates: int = 2
    pair_pool: int = 400
    model_error: float = 0.2
    max_strength: float = 1.0

    def __post_init__(self):
        for k in ("n_sigma", "n_sigma_forward", "min_strength", "min_separation_m", "edge_margin_m", "model_error"):
            v = getattr(self, k)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"{k}: must be a finite number >= 0, got {v!r}")
        for k in ("cell_m", "contact_radius_m", "max_strength"):
            v = getattr(self, k)
            if not (v > 0 and math.isfinite(v)):
                raise ConfigError(f"{k}: must be a finite number > 0, got {v!r}")
        if self.max_contacts < 1 or self.iterations < 1:
            raise ConfigError("max_contacts and iterations must be >= 1")
        na = self.n_sigma_absorbed
        if na is not None and not (na >= 0 and math.isfinite(na)):
            raise ConfigError(f"n_sigma_absorbed: must be a finite number >= 0 or None, got {self.n_sigma_absorbed!r}")
        if self.pair_candidates < 1 or self.pair_pool < 2:
            raise ConfigError("pair_candidates must be >= 1 and pair_pool >= 2")
        if self.rebirth_sweeps < 0 or self.rebirth_candidates < 1:
            raise ConfigError("rebirth_sweeps must be >= 0 and rebirth_candidates >= 1")
        if self.rounds < 0 or min(self.split_candidates, self.relocate_candidates, self.starts) < 1:
            raise ConfigError("rounds must be >= 0; split_candidates, relocate_candidates and starts >= 1")


@dataclass
class FitResult:
    """What :meth:`FitDetector.process` returns (the pipeline's ``ProcessResult`` shape): ``maps`` are
    each frame's evidence map before any contact is fitted (``sqrt`` of the chi-square drop of one
    contact at each cell, in noise standard deviations)."""

    maps: np.ndarray
    ok: np.ndarray
    grid: Grid
    method: str
    detections: list[Detection] | None = None
    noise: np.ndarray | None = None
    chi2: np.ndarray | None = None  # (F,) final chi-square of each frame (with model_error: its weighted one)
    dof: int = 0

    def touches_json(self) -> dict:
        """Each frame's contacts: position, strength and their standard errors (null where the data do not
        constrain a direction)."""
        keys = ("x_m", "y_m", "strength", "x_stderr_m", "y_stderr_m", "strength_stderr")
        return {"frames": [{"index": i, "touches": [{k: (t[k] if math.isfinite(t[k]) else None) for k in keys if k in t}
                                                    for t in d.touches]}
                           for i, d in enumerate(self.detections or [])]}


@dataclass(frozen=True)
class ProposalResponses:
    """The fit method's proposal grid and each cell's unit contact response in noise units (see
    :func:`proposal_responses`): ``bounds`` (2, 2) [m] where contact centres may lie, ``grid`` the scene's grid of
    ``cell_m``, ``cells`` the flat indices of its cells inside ``bounds``, ``centres`` (n, 2) [m] theirs,
    ``sigma`` (S*Z*B,) the noise of a frame minus the baseline, ``A`` (n, S*Z*B) the signed response of a
    strength-1 contact at each centre over ``sigma``, ``gdiag`` (n,) ``sum(A^2)``: the squared matched-filter
    SNR of a strength-1 contact alone at the cell in one frame (what a contact there lowers the chi-square by)."""

    bounds: np.ndarray
    grid: Grid
    cells: np.ndarray
    centres: np.ndarray
    sigma: np.ndarray
    A: np.ndarray
    gdiag: np.ndarray


def proposal_responses(scene: Scene, baseline: np.ndarray, optical: OpticalParams, options: FitDetectOptions,
                       n_baseline: int) -> ProposalResponses:
    """The fit method's proposal grid and responses (no compiled model: the part of :class:`FitDetector` that
    the sensitivity map, :func:`tofjax.invert.sensitivity.fit_sensitivity`, needs). ``baseline`` (S, Z, B) is the
    mean of ``n_baseline`` frames; a frame's noise is ``sqrt(max(B, 1) (1 + 1/n_baseline))``."""
    from .reconstruct import response_matrix

    o = options
    lx, ly = scene.waveguide.size_m
    bounds = np.array([[o.edge_margin_m, lx - o.edge_margin_m], [o.edge_margin_m, ly - o.edge_margin_m]])
    grid = Grid.for_scene(scene, o.cell_m)
    c = grid.centres().reshape(-1, 2)
    inside = ((c[:, 0] >= bounds[0, 0]) & (c[:, 0] <= bounds[0, 1]) & (c[:, 1] >= bounds[1, 0])
              & (c[:, 1] <= bounds[1, 1]))
    cells = np.flatnonzero(inside)
    centres = c[cells]
    base = np.asarray(baseline, float)
    sigma = np.sqrt(np.maximum(base, 1.0) * (1.0 + 1.0 / n_baseline)).ravel()
    R = response_matrix(scene, optical, centres, o.contact_radius_m, signed=True)  # (K, S, Z, B)
    A = R.reshape(len(centres), -1) / sigma[None]
    return ProposalResponses(bounds, grid, cells, centres, sigma, A, np.sum(A**2, 1))


class FitDetector:
    """Precomputed fit detector of one scene, baseline and calibration (see :func:`build_fit_detector`)."""

    def __init__(self, scene: Scene, baseline: np.ndarray, optical: OpticalParams, options: FitDetectOptions,
                 n_baseline: int):
        if optical.optics != "guided":
            raise InversionError("--method fit needs a calibration with the guided optics (skin contacts); "
                                 f"this one has {optical.optics!r}")
        self.scene, self.options, self.optical = scene, options, optical
        o = options
        p = proposal_responses(scene, baseline, optical, options, n_baseline)
        self.bounds, self.grid, self.cells, self.centres, self.sigma = p.bounds, p.grid, p.cells, p.centres, p.sigma
        self.base = np.asarray(baseline, float).ravel()
        self._A = p.A.astype(np.float32)
        self._gdiag = p.gdiag
        K = o.max_contacts
        change, dtype = _contact_change(scene, optical, K, o.contact_radius_m)
        sig = jnp.asarray(self.sigma, dtype)
        self._dtype = dtype
        # theta (3K,): x, y, strength -> (model change) / sigma, (n,), and its Jacobian, split once per
        # model structure into what does not depend on theta (run here, once per detector) and what does
        # (compiled once per structure, taking those arrays as arguments): a second detector (another
        # baseline or calibration, same scene and slots) compiles nothing, and no evaluation recomputes
        # the contact-independent part (see _folded)
        # (a change that is not an eqx.Module, e.g. a test's stand-in closure made per detector, has no
        # structure to cache a split by: it takes the unsplit compiled functions, as before)
        if isinstance(change, eqx.Module):
            self._change = _folded(_change_over_sigma, change, sig, (3 * K,), dtype)
            self._jac = _folded(_jacobian_over_sigma, change, sig, (3 * K,), dtype)
        else:
            self._change = functools.partial(_weighted_change, change, sig)
            self._jac = functools.partial(_weighted_jacobian, change, sig)
        self.K = K
        self._cache = {}  # the responses' Gram matrix, computed on the first pair proposal (shared by with_options)
        self._sat = float(scene.sensor.saturation_counts)

    def with_options(self, options: FitDetectOptions) -> "FitDetector":
        """The same detector with other search and stopping options (thresholds, iterations, pruning),
        sharing the precomputed responses and compiled model; the grid, contact radius, slots and margin
        must be those it was built with."""
        fixed = ("cell_m", "contact_radius_m", "max_contacts", "edge_margin_m")
        changed = [k for k in fixed if getattr(options, k) != getattr(self.options, k)]
        if changed:
            raise ConfigError(f"with_options: {', '.join(changed)} need a new detector (build_fit_detector)")
        new = copy.copy(self)
        new.options = options
        return new

    # -- one frame -------------------------------------------------------------------------------
    def _chi2(self, theta, y, w=None):
        """Chi-square and weighted residual of ``theta`` for the frame ``y`` (noise units); ``w`` per-bin weights
        (``sigma / sigma_eff``, see ``model_error``), default 1."""
        r = y - np.asarray(self._change(jnp.asarray(theta, self._dtype)), float)
        if w is not None:
            r = r * w
        return float(r @ r), r

    def _clip(self, theta):
        K = self.K
        theta = theta.copy()
        theta[:K] = np.clip(theta[:K], *self.bounds[0])
        theta[K : 2 * K] = np.clip(theta[K : 2 * K], *self.bounds[1])
        theta[2 * K :] = np.clip(theta[2 * K :], 0.0, self.options.max_strength)
        return theta

    def _refit(self, theta, active, y, iterations=None, w=None):
        """Levenberg-Marquardt on the active contacts' x, y, strength (box-constrained by clipping); ``w`` per-bin
        weights of the residual (default 1)."""
        K = self.K
        cols = np.concatenate([active, active + K, active + 2 * K])
        chi, r = self._chi2(theta, y, w)
        lam = 1e-3
        for _ in range(self.options.iterations if iterations is None else iterations):
            J = np.asarray(self._jac(jnp.asarray(theta, self._dtype)), float)[:, cols]
            if w is not None:
                J = J * w[:, None]
            JtJ, g = J.T @ J, J.T @ r
            d = np.maximum(np.diag(JtJ), 1e-30)
            improved = False
            for _ in range(6):
                step = np.linalg.solve(JtJ + lam * np.diag(d), g)
                t2 = theta.copy()
                t2[cols] += step
                t2 = self._clip(t2)
                chi2, r2 = self._chi2(t2, y, w)
                if chi2 < chi:
                    theta, r, improved = t2, r2, True
                    drop = chi - chi2
                    chi = chi2
                    lam = max(lam / 3.0, 1e-6)
                    break
                lam *= 4.0
            if not improved or drop < 0.1:  # a tenth of one unit of chi-square: converged
                break
        return theta, chi, r

    def _propose(self, r, theta, active):
        """The best new contact on the grid for residual ``r`` (weighted): (cell, strength, drop)."""
        c = self._A @ r.astype(np.float32)
        s = np.clip(c / np.maximum(self._gdiag, 1e-30), 0.0, self.options.max_strength)
        gain = 2.0 * s * c - s * s * self._gdiag
        K = self.K
        for k in active:
            near = np.hypot(self.centres[:, 0] - theta[k], self.centres[:, 1] - theta[K + k]) < self.options.min_separation_m
            gain = np.where(near, -np.inf, gain)
        j = int(np.argmax(gain))
        return j, float(s[j]), float(gain[j]), gain

    def fit_frame(self, histogram) -> tuple[np.ndarray, float, np.ndarray]:
        """Contacts (n, 3: x_m, y_m, strength), the final chi-square, and the first evidence map (cells)."""
        state = self.search_frame(histogram)
        contacts, chi = self.finish_frame(state, self.options.n_sigma)
        return contacts, chi, state[4]

    def search_frame(self, histogram):
        """The search before the backward pruning: (theta, active, chi, y, first evidence map); the part of
        :meth:`fit_frame` that does not depend on ``n_sigma`` (see :meth:`finish_frame`)."""
        o, K = self.options, self.K
        y = (np.asarray(histogram, float).ravel() - self.base) / self.sigma
        theta = np.zeros(3 * K)
        theta[:K], theta[K : 2 * K] = self.centres[0]
        active = np.zeros(0, int)
        chi, r = float(y @ y), y
        thr_add = o.n_sigma_forward**2
        first = []
        theta, active, chi, r = self._search(theta, active, chi, r, y, thr_add, first)
        if o.starts > 1:
            # multi-start: the search again from each of the next best local maxima of the first evidence map as
            # the first contact; the fit with the lowest chi-square plus n_sigma_forward^2 per contact wins
            best = (chi + thr_add * len(active), theta, active, chi, r)
            c0 = np.maximum(first[0], 0.0) ** 2
            for j in self._local_maxima(c0, o.starts)[1:]:
                if not c0[j] > thr_add:
                    break
                t = np.zeros(3 * K)
                t[:K], t[K : 2 * K] = self.centres[0]
                self._place(t, 0, j, c0)
                t, c, rr = self._refit(t, np.array([0]), y)
                if float(y @ y) - c <= thr_add:
                    continue
                t, a, c, rr = self._search(t, np.array([0]), c, rr, y, thr_add, first)
                if c + thr_add * len(a) < best[0]:
                    best = (c + thr_add * len(a), t, a, c, rr)
            _, theta, active, chi, r = best
        return theta, active, chi, y, first[0]

    def finish_frame(self, state, n_sigma: float, options: FitDetectOptions | None = None, *, stderr: bool = False):
        """The backward pruning at ``n_sigma`` of a :meth:`search_frame` state: contacts (n, 3) and chi-square
        (weighted by ``model_error`` when that is set); with ``stderr`` also each contact's standard errors (n, 3:
        x, y in m, strength; see :meth:`_stderr`). ``options`` (default the detector's) may differ from the
        detector's in the pruning's options only (:data:`PRUNE_OPTIONS`): the search does not depend on them."""
        o, K = (self.options if options is None else options), self.K
        theta, active, chi, y, _ = state
        thr = n_sigma**2
        w = None
        if o.model_error > 0 and len(active):
            delta = np.asarray(self._change(jnp.asarray(theta, self._dtype)), float)
            w = 1.0 / np.sqrt(1.0 + (o.model_error * delta) ** 2)
            r = (y - delta) * w  # _chi2(theta, y, w) without evaluating the model again
            chi = float(r @ r)
        if len(active) and o.overdispersion:
            phi = max(1.0, chi / max(len(y) - 3 * len(active), 1))
            thr = thr * phi
        if o.prune and len(active):
            thr_abs = None if o.n_sigma_absorbed is None else thr * (o.n_sigma_absorbed / max(n_sigma, 1e-9)) ** 2
            theta, active, chi = self._prune(theta, active, chi, y, thr, thr_abs, w)
        out = np.stack([theta[active], theta[K + active], theta[2 * K + active]], -1) if len(active) else np.zeros((0, 3))
        err = self._stderr(theta, active, y, chi, w) if stderr else None
        if o.min_strength > 0:
            keep = out[:, 2] >= o.min_strength
            out, err = out[keep], (err[keep] if stderr else None)
        return (out, chi, err) if stderr else (out, chi)

    def _stderr(self, theta, active, y, chi, w=None) -> np.ndarray:
        """Standard errors (n, 3: x, y [m], strength) of the active contacts: the Laplace approximation at the fit,
        ``inv(J^T J)`` of the weighted Jacobian in every active contact's x, y and strength jointly, times the
        reduced chi-square when above 1 (as the overdispersion's). A contact at a strength bound, or one the data
        cannot place (seen by one sensor only: the guide's coverage holes), shows as a large error; a direction
        the data do not constrain at all as ``inf``."""
        K, n = self.K, len(active)
        if not n:
            return np.zeros((0, 3))
        cols = np.concatenate([active, active + K, active + 2 * K])
        J = np.asarray(self._jac(jnp.asarray(theta, self._dtype)), float)[:, cols]
        if w is not None:
            J = J * w[:, None]
        phi = max(1.0, chi / max(len(y) - 3 * n, 1))
        F = J.T @ J
        var = np.diag(_fisher_inverse(F)) * phi
        sd = np.where((np.diag(F) > 0) & (var > 0), np.sqrt(np.abs(var)), np.inf)
        return sd.reshape(3, n).T

    def position_bound(self, contacts, frames: int = 1) -> np.ndarray:
        """The Cramer-Rao bound on the positions of ``contacts`` (n, 3: x_m, y_m, strength; at most
        ``max_contacts``) fitted together, the number of contacts known: (n, 2, 2), each contact's position
        covariance [m^2] with ``frames`` frames summed (the baseline on the same exposure).

        It is the inverse of the Fisher information ``J^T J`` of the noise-weighted model change in every
        contact's x, y and strength jointly, at the true values: no unbiased estimate does better, and the fit
        method (a maximum-likelihood fit) reaches it where the evidence is strong. Each contact's neighbours
        are in it (their shadows on each other, and how far their signals overlap). A contact whose position the
        data do not see at all (strength 0, or outside every zone's view) is ``inf``. See
        :func:`tofjax.invert.sensitivity.match_probability` for the share of fits within a match radius."""
        c = np.asarray(contacts, float)
        if c.ndim != 2 or c.shape[1] != 3 or not np.all(np.isfinite(c)):
            raise ConfigError(f"contacts: must be finite (n, 3) x_m, y_m, strength, got shape {c.shape}")
        n, K = len(c), self.K
        if n > K:
            raise ConfigError(f"contacts: at most max_contacts = {K} fitted together, got {n}")
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
            raise ConfigError(f"frames: must be an integer >= 1, got {frames!r}")
        if n == 0:
            return np.zeros((0, 2, 2))
        theta = np.zeros(3 * K)
        theta[:K], theta[K : 2 * K] = self.centres[0]
        theta[:n], theta[K : K + n], theta[2 * K : 2 * K + n] = c[:, 0], c[:, 1], c[:, 2]
        idx = np.arange(n)
        J = np.asarray(self._jac(jnp.asarray(theta, self._dtype)), float)[:, np.concatenate([idx, idx + K, idx + 2 * K])]
        return position_covariance(J.T @ J * frames)

    def _search(self, theta, active, chi, r, y, thr_add, first):
        """Forward selection, relocation and splits from the current fit, in rounds (see ``rounds``)."""
        o = self.options
        for round_ in range(1 + o.rounds):
            theta, active, chi, r = self._forward(theta, active, chi, r, y, thr_add, first)
            if o.relocate and len(active) > 1:
                theta, chi, r = self._relocate(theta, active, chi, r, y)
            if not (o.split and round_ < o.rounds and len(active)):
                break
            n_before = len(active)
            theta, active, chi, r = self._split(theta, active, chi, r, y, thr_add)
            if len(active) == n_before:
                break  # no split kept: another round would repeat this one
        if o.rebirth and len(active):
            for _ in range(o.rebirth_sweeps):
                theta, active, chi, r, changed = self._rebirth(theta, active, chi, r, y, thr_add)
                if not changed:
                    break
        if o.pair_split and len(active):
            theta, active, chi, r = self._pair_split(theta, active, chi, r, y, thr_add)
        return theta, active, chi, r

    def _rebirth(self, theta, active, chi, r, y, thr_add):
        """One death-and-birth sweep (see ``FitDetectOptions.rebirth``): for each contact (weakest first) remove it,
        refit the others jointly, resume the forward selection; keep the result when the chi-square plus
        ``thr_add`` per contact falls (by more than a tenth: not a re-convergence of the same fit)."""
        K = self.K
        score = chi + thr_add * len(active)
        changed = False
        for k in active[np.argsort(theta[2 * K + active])]:
            if k not in active:
                continue  # a previous birth reused its slot
            t0 = theta.copy()
            t0[2 * K + k] = 0.0
            rest = active[active != k]
            if len(rest):
                t0, c0, r0 = self._refit(t0, rest, y, iterations=3)
            else:
                c0, r0 = self._chi2(t0, y)
            trials = [(t0, rest, c0, r0)]
            if self.options.rebirth_candidates > 1:
                # births at the next best local maxima too, alone and in pairs (one contact placed between two)
                _, _, _, gain = self._propose(r0, t0, rest)
                peaks = self._local_maxima(gain, self.options.rebirth_candidates)
                slots = np.setdiff1d(np.arange(K), rest)
                sets = [(j,) for j in peaks[1:]] + self._pairs(peaks)
                for js in sets:
                    if len(rest) + len(js) > K:
                        continue
                    t = t0.copy()
                    for slot, j in zip(slots, js):
                        self._place(t, slot, j, gain)
                    act = np.concatenate([rest, slots[: len(js)]])
                    t, c, rr = self._refit(t, act, y, iterations=2)  # a quick look; the best is continued
                    trials.append((t, act, c, rr))
                best = min(trials[1:], key=lambda q: q[2] + thr_add * len(q[1]), default=None)
                trials = [trials[0]] + ([best] if best is not None else [])
            for t, act, c, rr in trials:
                t1, a1, c1, r1 = self._forward(t, act, c, rr, y, thr_add, [None])
                if len(a1) > len(act) or len(trials) > 1:
                    t1, c1, r1 = self._refit(t1, a1, y)
                if c1 + thr_add * len(a1) < score - 0.1:
                    theta, active, chi, r, changed = t1, a1, c1, r1, True
                    score = chi + thr_add * len(active)
        return theta, active, chi, r, changed

    def _forward(self, theta, active, chi, r, y, thr_add, first):
        """Forward selection from the current fit: add the proposal's best cell and refit all, while the
        chi-square falls by more than ``thr_add``. ``first`` receives the first evidence map."""
        K = self.K
        while len(active) < K:
            j, s, gain, gmap = self._propose(r, theta, active)
            if not first:
                first.append(np.sqrt(np.maximum(gmap, 0.0)))
            if not gain > thr_add:
                break
            k = self._free_slot(active)
            t = theta.copy()
            t[k], t[K + k], t[2 * K + k] = self.centres[j, 0], self.centres[j, 1], s
            act = np.append(active, k)
            t, chi_new, r_new = self._refit(t, act, y)
            if chi - chi_new <= thr_add:
                break
            theta, active, chi, r = t, act, chi_new, r_new
        if not first:  # every slot taken before a proposal (cannot happen with K >= 1 from an empty fit)
            first.append(np.zeros(len(self.cells)))
        return theta, active, chi, r

    def _free_slot(self, active):
        return int(np.setdiff1d(np.arange(self.K), active)[0])

    def _split(self, theta, active, chi, r, y, thr_add):
        """Replace one contact by two (strongest first): remove it, put two contacts at the best pairs of local
        maxima (at least ``min_separation_m`` apart) of the proposal of the residual without it, refit all;
        kept when the chi-square falls by more than ``thr_add`` (the extra contact's price). Undoes a greedy
        pick that sat between two contacts and explains both well enough that neither is proposed again."""
        o, K = self.options, self.K
        for k in active[np.argsort(-theta[2 * K + active])]:
            if len(active) >= K:
                break
            t0 = theta.copy()
            t0[2 * K + k] = 0.0
            _, r0 = self._chi2(t0, y)
            others = active[active != k]
            _, _, _, gain = self._propose(r0, t0, others)
            peaks = self._local_maxima(gain, o.split_candidates + 1)
            pairs = self._pairs(peaks)[: o.split_candidates]
            best = None
            k2 = self._free_slot(active)
            act = np.append(active, k2)
            for a, b in pairs:
                t = t0.copy()
                for slot, j in ((k, a), (k2, b)):
                    self._place(t, slot, j, gain)
                t, cc, rr = self._refit(t, act, y, iterations=2)  # a quick look; the winner is refitted
                if cc < chi - thr_add and (best is None or cc < best[1]):
                    best = (t, cc, rr)
            if best is not None:
                theta, chi, r = self._refit(best[0], act, y)
                active = act
        return theta, active, chi, r

    def _gram(self):
        if "gram" not in self._cache:
            self._cache["gram"] = self._A @ self._A.T  # float32, (cells, cells); frame-independent
        return self._cache["gram"]

    def _best_pairs(self, r, theta, others, n):
        """The ``n`` best pairs of new contacts for the weighted residual ``r`` by the linear model: for every pair
        of cells among the ``pair_pool`` best single proposals (at least ``min_separation_m`` apart, and from
        ``others``), the chi-square drop of both contacts at their joint best strengths (the 2 x 2 normal
        equations, clipped to [0, max_strength]). Unlike pairs of local maxima of the single-contact map, this finds two
        contacts whose evidence one contact between them explains best (the merged pair). Returns
        ``[(a, b, s_a, s_b, drop)]`` (distinct pairs, best first) and the best single drop."""
        o = self.options
        c = self._A @ r.astype(np.float32)
        s1 = np.clip(c / np.maximum(self._gdiag, 1e-30), 0.0, o.max_strength)
        gain = 2.0 * s1 * c - s1 * s1 * self._gdiag
        K = self.K
        for k in others:
            near = np.hypot(self.centres[:, 0] - theta[k], self.centres[:, 1] - theta[K + k]) < o.min_separation_m
            gain = np.where(near, -np.inf, gain)
        pool = np.argsort(-gain)[: o.pair_pool]
        pool = pool[gain[pool] > 0]
        best1 = float(gain[pool[0]]) if len(pool) else 0.0
        if len(pool) < 2:
            return [], best1
        G = self._gram()[np.ix_(pool, pool)].astype(float)
        cp, g = c[pool].astype(float), self._gdiag[pool]
        det = g[:, None] * g[None, :] - G**2
        ok = det > 1e-9 * g[:, None] * g[None, :]
        det = np.where(ok, det, 1.0)
        sa = np.clip((cp[:, None] * g[None, :] - G * cp[None, :]) / det, 0.0, o.max_strength)
        sb = np.clip((cp[None, :] * g[:, None] - G * cp[:, None]) / det, 0.0, o.max_strength)
        drop = 2 * (sa * cp[:, None] + sb * cp[None, :]) - (sa**2 * g[:, None] + sb**2 * g[None, :] + 2 * sa * sb * G)
        xy = self.centres[pool]
        far = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1]) >= o.min_separation_m
        drop = np.where(ok & far & np.triu(np.ones_like(ok), 1).astype(bool), drop, -np.inf)
        out = []
        for flat in np.argsort(-drop, axis=None)[: 50 * n]:
            i, j = np.unravel_index(flat, drop.shape)
            if not np.isfinite(drop[i, j]):
                break
            a, b = xy[i], xy[j]
            seen = ((self.centres[u], self.centres[v]) for u, v, *_ in out)
            if any(min(np.hypot(*(a - p)) + np.hypot(*(b - q)), np.hypot(*(a - q)) + np.hypot(*(b - p)))
                   < o.min_separation_m for p, q in seen):
                continue  # the same pair moved by a cell or two
            out.append((int(pool[i]), int(pool[j]), float(sa[i, j]), float(sb[i, j]), float(drop[i, j])))
            if len(out) == n:
                break
        return out, best1

    def _pair_split(self, theta, active, chi, r, y, thr_add):
        """Replace a contact by two (strongest first) at the best pairs of cells for the residual without it
        (:meth:`_best_pairs`, by the linear model), tried only when the pair's linear drop exceeds the best single
        contact's by more than ``thr_add``; kept when the refit lowers the chi-square by more than ``thr_add``.
        A ghost at the strength bound standing in for two weaker contacts either side of it is the typical case."""
        K = self.K
        for k in active[np.argsort(-theta[2 * K + active])]:
            if len(active) >= K or k not in active:
                break
            t0 = theta.copy()
            t0[2 * K + k] = 0.0
            _, r0 = self._chi2(t0, y)
            others = active[active != k]
            pairs, best1 = self._best_pairs(r0, t0, others, self.options.pair_candidates)
            k2 = self._free_slot(active)
            act = np.append(active, k2)
            best = self._refit_best_pair(t0, pairs, (k, k2), act, y, lambda drop: drop - best1 <= thr_add, chi - thr_add)
            if best is not None:
                theta, chi, r = self._refit(best[0], act, y)
                active = act
        if self.options.pair_swap and len(active) > 1:
            theta, chi, r = self._pair_swap(theta, active, chi, r, y)
        return theta, active, chi, r

    def _pair_swap(self, theta, active, chi, r, y):
        """Two neighbouring contacts (each with its nearest, strongest first) replaced by the best pairs of cells for
        the residual without both (:meth:`_best_pairs`); tried when the pair's linear drop exceeds what the two
        explained, kept when the refit lowers the chi-square. A ghost between two contacts next to a contact
        placed 2-3 cm off the second one: one pair move cannot free them, a swap of both can."""
        K, o = self.K, self.options
        done = set()
        for k in active[np.argsort(-theta[2 * K + active])]:
            others = active[active != k]
            d = np.hypot(theta[others] - theta[k], theta[K + others] - theta[K + k])
            m = int(others[np.argmin(d)])
            if d.min() > 3 * o.min_separation_m or frozenset((k, m)) in done:
                continue
            done.add(frozenset((k, m)))
            t0 = theta.copy()
            t0[2 * K + k] = t0[2 * K + m] = 0.0
            c0, r0 = self._chi2(t0, y)
            rest = active[(active != k) & (active != m)]
            pairs, _ = self._best_pairs(r0, t0, rest, o.pair_candidates)
            # stop when a pair is no better than the two where they are, by the linear model
            best = self._refit_best_pair(t0, pairs, (k, m), active, y, lambda drop: drop <= c0 - chi, chi - 0.1)
            if best is not None:
                theta, chi, r = self._refit(best[0], active, y)
        return theta, chi, r

    def _refit_best_pair(self, t0, pairs, slots, active, y, stop, below):
        """The pair moves' trial: each of ``pairs`` (cells ``a``, ``b`` with strengths ``sa``, ``sb`` and their
        linear drop, best first, until ``stop(drop)``) put in contacts ``slots`` of ``t0`` and refitted briefly
        over ``active``; returns the lowest ``(theta, chi2, residual)`` with a chi-square under ``below``, or None."""
        K = self.K
        best = None
        for a, b, sa, sb, drop in pairs:
            if stop(drop):
                break
            t = t0.copy()
            for slot, j, s in zip(slots, (a, b), (sa, sb)):
                t[slot], t[K + slot] = self.centres[j]
                t[2 * K + slot] = s
            t, cc, rr = self._refit(t, active, y, iterations=2)
            if cc < below and (best is None or cc < best[1]):
                best = (t, cc, rr)
        return best

    def _relocate(self, theta, active, chi, r, y):
        """Move each contact (weakest first) to where the residual without it wants a contact (the
        ``relocate_candidates`` best local maxima of the proposal), refit all; kept when the chi-square
        falls (undoes a greedy pick that merged two contacts or sits on the wrong crossing of range rings)."""
        K = self.K
        moved = False
        for k in active[np.argsort(theta[2 * K + active])]:
            t0 = theta.copy()
            t0[2 * K + k] = 0.0
            _, r0 = self._chi2(t0, y)
            others = active[active != k]
            _, _, _, gain = self._propose(r0, t0, others)
            for j in self._local_maxima(gain, self.options.relocate_candidates):
                if np.hypot(self.centres[j, 0] - theta[k], self.centres[j, 1] - theta[K + k]) < self.options.min_separation_m:
                    continue  # it would come back where it is
                t = t0.copy()
                self._place(t, k, j, gain)
                t, cc, rr = self._refit(t, active, y, iterations=2)  # a quick look; the winner is refitted
                if cc < chi:
                    theta, chi, r = t, cc, rr
                    moved = True
        if moved:
            theta, chi, r = self._refit(theta, active, y)
        return theta, chi, r

    def _place(self, theta, slot, j, gain) -> None:
        """Put contact ``slot`` of ``theta`` (in place) at cell ``j`` with the strength the proposal's
        evidence ``gain[j]`` implies there (``sqrt(gain / G_jj)``, within [0, max_strength])."""
        K = self.K
        theta[slot], theta[K + slot] = self.centres[j]
        theta[2 * K + slot] = float(np.clip(np.sqrt(max(gain[j], 0.0) / max(self._gdiag[j], 1e-30)), 0.0,
                                           self.options.max_strength))

    def _pairs(self, peaks) -> list:
        """Pairs of the cells ``peaks`` (best first) at least ``min_separation_m`` apart, in the order of the peaks."""
        return [(a, b) for i, a in enumerate(peaks) for b in peaks[i + 1 :]
                if np.hypot(*(self.centres[a] - self.centres[b])) >= self.options.min_separation_m]

    def _local_maxima(self, gain, n):
        """Cells of the ``n`` largest local maxima (3 x 3) of the proposal map, best first."""
        full = np.full(self.grid.ny * self.grid.nx, -np.inf)
        full[self.cells] = gain
        m = full.reshape(self.grid.ny, self.grid.nx)
        from scipy import ndimage

        peak = (m == ndimage.maximum_filter(m, size=3, mode="constant", cval=-np.inf)) & np.isfinite(m) & (m > 0)
        idx = np.flatnonzero(peak.ravel())
        idx = idx[np.argsort(-full[idx])][:n]
        return [int(i) for i in np.searchsorted(self.cells, idx)]

    def _prune(self, theta, active, chi, y, thr, thr_absorbed=None, w=None):
        """Backward pruning: the contact whose removal (with refit) raises the chi-square least goes while that is
        at most ``thr``; at most ``thr_absorbed`` (when given) where the refit moved another contact by more than
        half ``min_separation_m`` (it absorbs the removed one: a pair fitted as one contact between them; the question
        is then one contact or two, not whether there is a contact at all)."""
        K = self.K
        thr_absorbed = thr if thr_absorbed is None else thr_absorbed
        while len(active):
            best = None
            for k in active:
                t = theta.copy()
                t[2 * K + k] = 0.0
                rest = active[active != k]
                c0, _ = self._chi2(t, y, w)
                if c0 - chi > max(thr, thr_absorbed):  # plainly needed even before refitting the others
                    continue
                t, c, _ = self._refit(t, rest, y, w=w) if len(rest) else (t, c0, None)
                moved = len(rest) and np.max(np.hypot(t[rest] - theta[rest], t[K + rest] - theta[K + rest])) > (
                    0.5 * self.options.min_separation_m)
                limit = thr_absorbed if moved else thr
                if c - chi <= limit and (best is None or c < best[1]):
                    best = (k, c, t)
            if best is None:
                break
            k, chi, theta = best
            active = active[active != k]
        return theta, active, chi

    # -- frames ----------------------------------------------------------------------------------
    def process(self, histograms, *, detect: bool = True) -> FitResult:
        return self.process_levels(histograms, (self.options.n_sigma,), detect=detect)[0]

    def process_levels(self, histograms, n_sigmas, *, detect: bool = True) -> list[FitResult]:
        """:meth:`process` at several thresholds ``n_sigmas`` at the cost of one: the search (forward selection,
        relocation, splits, starts) does not depend on ``n_sigma``, only the final pruning does."""
        return self.process_variants(histograms, [dataclasses.replace(self.options, n_sigma=float(n)) for n in n_sigmas],
                                     detect=detect)

    def process_variants(self, histograms, variants, *, detect: bool = True) -> list[FitResult]:
        """:meth:`process` with each of ``variants`` (:class:`FitDetectOptions` that differ from the detector's in
        the pruning's options only, :data:`PRUNE_OPTIONS`: thresholds, ``model_error``, ...) at the cost of one
        search per frame."""
        variants = list(variants)
        for v in variants:
            other = [f.name for f in dataclasses.fields(FitDetectOptions)
                     if f.name not in PRUNE_OPTIONS and getattr(v, f.name) != getattr(self.options, f.name)]
            if other:
                raise ConfigError(f"process_variants: {', '.join(other)} change the search; use with_options")
        h = np.asarray(histograms, float)
        if h.ndim != 4 or h.shape[1:] != self.scene.shape:
            raise InversionError(f"histograms have shape {h.shape[1:]} per frame, the scene {self.scene.shape}")
        F, L = len(h), len(variants)
        maps = np.zeros((F, self.grid.ny * self.grid.nx))
        ok = np.ones(F, bool)
        chi2 = np.full((L, F), np.nan)
        dets = [[] for _ in range(L)]
        for i in range(F):
            bad = ~np.isfinite(h[i]) | (h[i] >= self._sat)
            if bad.any():
                ok[i] = False
                for d in dets:
                    d.append(Detection())
                continue
            state = self.search_frame(h[i])
            maps[i, self.cells] = state[4]
            for lv, v in enumerate(variants):
                contacts, chi2[lv, i], err = self.finish_frame(state, v.n_sigma, v, stderr=True)
                dets[lv].append(Detection(touches=[{"x_m": float(x), "y_m": float(yy), "strength": float(s),
                                                    "x_stderr_m": float(ex), "y_stderr_m": float(ey),
                                                    "strength_stderr": float(es), "component": 0}
                                                   for (x, yy, s), (ex, ey, es) in zip(contacts, err)]))
        m = maps.reshape(F, self.grid.ny, self.grid.nx)
        return [FitResult(m, ok, self.grid, "fit", dets[lv] if detect else None, None, chi2[lv], int(self.sigma.size))
                for lv in range(L)]


def _fisher_inverse(F) -> np.ndarray:
    """The pseudo-inverse of Fisher information matrices ``F`` (..., m, m) in their diagonal's units (each row
    and column scaled to a unit diagonal, so that coordinates in metres and in strength weigh alike; a zero
    diagonal stays unscaled), the contact fit's covariance (:meth:`FitDetector._stderr`,
    :func:`position_covariance`)."""
    d = np.diagonal(F, axis1=-2, axis2=-1)
    scale = np.sqrt(np.where(d > 0, d, 1.0))
    outer = scale[..., :, None] * scale[..., None, :]
    return np.linalg.pinv(F / outer, rcond=1e-12, hermitian=True) / outer


def position_covariance(F) -> np.ndarray:
    """Each contact's position covariance (..., n, 2, 2) from the Fisher information ``F`` (..., 3n, 3n) of n
    contacts in the fit's order (x_1..x_n, y_1..y_n, strength_1..strength_n): the x, y blocks of ``F^-1``
    (a pseudo-inverse in the diagonal's units). A contact whose position the data do not see (a zero diagonal, or a
    block that is not positive definite: a direction the inverse dropped) is ``inf``."""
    F = np.asarray(F, float)
    n = F.shape[-1] // 3
    d = np.diagonal(F, axis1=-2, axis2=-1)
    cov = _fisher_inverse(F)
    i = np.arange(n)
    out = np.stack([np.stack([cov[..., i, i], cov[..., i, n + i]], -1),
                    np.stack([cov[..., n + i, i], cov[..., n + i, n + i]], -1)], -2)
    bad = (d[..., i] <= 0) | (d[..., n + i] <= 0) | ~(np.linalg.eigvalsh(out)[..., 0] > 0)
    return np.where(bad[..., None, None], np.inf, out)


def lone_position_bounds(scene: Scene, optical: OpticalParams, sigma, centres, strength: float, radius_m: float,
                         frames: int = 1, *, chunk: int = 64, progress: bool = False) -> np.ndarray:
    """The position bound of a contact of ``strength`` *alone* at each of ``centres`` (n, 2) [m]: (n, 2, 2)
    covariances [m^2] with ``frames`` summed, as :meth:`FitDetector.position_bound` of one contact (the guided
    model's exact Jacobian in x, y and strength, over the noise ``sigma`` (S*Z*B,) of a frame minus the
    baseline), vmapped over ``chunk`` centres at a time (``progress``: a progress bar). What the sensitivity map's
    position maps are made of (:func:`tofjax.invert.sensitivity.fit_sensitivity`, ``position``)."""
    from tqdm.auto import tqdm

    c = np.asarray(centres, float).reshape(-1, 2)
    change, dtype = _contact_change(scene, optical, 1, radius_m)
    sig = jnp.asarray(sigma, dtype)
    out = np.empty((len(c), 2, 2))
    for i in tqdm(range(0, len(c), chunk), desc="position bound", unit="chunk", disable=not progress, leave=False):
        part = c[i : i + chunk]
        t = np.c_[part, np.full(len(part), float(strength))]
        if len(t) < chunk:  # one compiled size: pad with the last centre
            t = np.concatenate([t, np.repeat(t[-1:], chunk - len(t), 0)])
        J = np.asarray(_lone_jacobians(change, sig, jnp.asarray(t, dtype)), float)[: len(part)]  # (m, bins, 3)
        out[i : i + len(part)] = position_covariance(np.einsum("mbi,mbj->mij", J, J) * frames)[:, 0]
    return out


@eqx.filter_jit
def _lone_jacobians(change, sig, thetas):
    return jax.vmap(jax.jacfwd(lambda t: change(t) / sig))(thetas)


def _contact_change(scene: Scene, optical: OpticalParams, K: int, radius_m: float):
    """The guided model's change of the histograms (flattened) caused by ``K`` skin contacts
    ``theta = (x_1..x_K, y_1..y_K, strength_1..strength_K)``, at the calibrated optics, and its dtype.
    Every contact is in one model evaluation: their shadows on each other are in it. A slot at strength 0
    is exactly no contact (the skin model's coupling scales the contact's every effect)."""
    from ..model.contact import SkinContact
    from .reconstruct import _params_with_optics

    lx, ly = scene.waveguide.size_m
    dt = "float64" if jax.config.jax_enable_x64 else "float32"
    proto = scene.without_touches().replace(touches=tuple(Touch((0.5 * lx, 0.5 * ly), radius_m, 0.0) for _ in range(K)))
    mopts = ModelOptions(dtype=dt, pulse_tails=optical.pulse_tails, optics="guided", skin=SkinContact())
    model = build_model(proto, mopts, components=proto.components())
    p0 = _params_with_optics(proto, optical, mopts.jnp_dtype)
    f0 = model(p0.replace(touch_strength=jnp.zeros(K, mopts.jnp_dtype))).ravel()
    return _ContactChange(model, p0, f0, K), mopts.jnp_dtype


class _ContactChange(eqx.Module):
    """``theta = (x_1..x_K, y_1..y_K, strength_1..strength_K)`` -> the model's change of the histograms
    (flattened) from ``f0``, its value with every slot at strength 0 (see :func:`_contact_change`). A pytree
    of the model and the optics, so the compiled functions below take it as an argument."""

    model: eqx.Module
    p0: eqx.Module
    f0: jax.Array
    K: int = eqx.field(static=True)

    def __call__(self, theta):
        K = self.K
        xy = jnp.stack([theta[:K], theta[K : 2 * K]], -1)
        return self.model(self.p0.replace(touch_xy_m=xy, touch_strength=theta[2 * K :])).ravel() - self.f0


def _change_over_sigma(change, sig, theta):
    """The contacts' change in noise units, ``change(theta) / sig``."""
    return change(theta) / sig


def _jacobian_over_sigma(change, sig, theta):
    """The Jacobian of :func:`_change_over_sigma` in ``theta`` (forward mode)."""
    return jax.jacfwd(lambda t: change(t) / sig)(theta)


# The same, compiled with the model and sigma as arguments (one program per model structure): every
# evaluation recomputes what does not depend on theta. Used for a change that is not an eqx.Module, and the
# reference for _folded (tests, experiments).
@eqx.filter_jit
def _weighted_change(change, sig, theta):
    """:func:`_change_over_sigma`, compiled."""
    return change(theta) / sig


@eqx.filter_jit
def _weighted_jacobian(change, sig, theta):
    """:func:`_jacobian_over_sigma`, compiled."""
    return jax.jacfwd(lambda t: change(t) / sig)(theta)


#: the unsplit compiled form of each function :func:`_folded` splits
_UNSPLIT = {_change_over_sigma: _weighted_change, _jacobian_over_sigma: _weighted_jacobian}


def _typeof(x):
    """``x``'s abstract value (shape, dtype, weak type): ``jax.typeof`` (jax >= 0.5), ``jax.core.get_aval`` before."""
    return jax.typeof(x) if hasattr(jax, "typeof") else jax.core.get_aval(x)


#: (function, structure of the model and sigma, their static values, avals, theta's aval, the model's trace
#: switches) -> (the theta-independent part, compiled; the theta-dependent part, compiled)
_SPLITS: dict = {}


def _folded(fn, change, sig, theta_shape, dtype):
    """``theta -> fn(change, sig, theta)`` with its theta-independent part computed once, here.

    ``fn``'s program is split by data dependence (JAX's partial evaluation of its jaxpr, as ``jax.linearize``
    does) into the operations whose inputs do not depend on ``theta`` (model geometry, optics, the
    baseline's model ``f0``, the no-contact terms, sigma) and the rest. The first part is run once per
    detector; its outputs (arrays) are the arguments of the second, which is all an evaluation computes:
    what a ``jax.jit`` of a closure over the model got from XLA's constant folding, without a compile per
    detector. Both parts are traced and compiled once per model structure (cached in ``_SPLITS``); the
    same operations as ``fn``, so the same values up to XLA's fusion (~1e-15 relative)."""
    try:  # JAX's own partial evaluation is not public API: where it moved, the unsplit program (same values)
        from jax._src import core
        from jax._src.interpreters import partial_eval as pe

        pe.partial_eval_jaxpr_nounits, core.jaxpr_as_fun  # noqa: B018
    except (ImportError, AttributeError):
        return functools.partial(_UNSPLIT[fn], change, sig)
    from ..model.forward import _trace_switches

    dyn, static = eqx.partition((change, sig), eqx.is_array)
    leaves, tdef = jax.tree_util.tree_flatten(dyn)
    sleaves, stdef = jax.tree_util.tree_flatten(static)
    theta = jax.ShapeDtypeStruct(theta_shape, dtype)
    key = (fn, tdef, stdef, tuple(sleaves), tuple(_typeof(x) for x in leaves), (theta.shape, str(theta.dtype)),
           _trace_switches(), bool(jax.config.jax_enable_x64))
    if key not in _SPLITS:

        def whole(leaves, theta):
            c, s = eqx.combine(jax.tree_util.tree_unflatten(tdef, leaves), static)
            return fn(c, s, theta)

        closed = jax.make_jaxpr(whole)(leaves, theta)
        known, unknown, _, _ = pe.partial_eval_jaxpr_nounits(closed, [False] * len(leaves) + [True], instantiate=True)
        run_unknown = core.jaxpr_as_fun(unknown)
        _SPLITS[key] = (jax.jit(core.jaxpr_as_fun(known)), jax.jit(lambda res, t: run_unknown(*res, t)[0]))
    first, rest = _SPLITS[key]
    return functools.partial(rest, tuple(first(*leaves)))


def build_fit_detector(scene: Scene, baseline: np.ndarray, optical: OpticalParams | None = None,
                       options: FitDetectOptions = FitDetectOptions(), *, n_baseline: int = 1) -> FitDetector:
    """Precompute the fit detector of ``scene``: the signed response of a unit contact at every cell of the
    proposal grid and the compiled forward model with ``options.max_contacts`` contact slots.

    **Arguments:** ``scene`` (its contacts ignored), ``baseline`` mean no-touch histogram (S, Z, B),
    ``optical`` the calibrated optics (guided; default the scene's stated values, as guided optics),
    ``options``, ``n_baseline`` frames averaged into ``baseline``.

    **Returns:** a :class:`FitDetector`; ``.process(histograms)`` gives detections per frame."""
    if optical is None:
        optical = dataclasses.replace(OpticalParams.from_scene(scene), optics="guided")
    return FitDetector(scene, baseline, optical, options, n_baseline)
