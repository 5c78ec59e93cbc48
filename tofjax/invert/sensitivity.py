"""Where on the skin a touch is detectable: a sensitivity map of the model method.

The model-based reconstruction (:mod:`tofjax.invert.reconstruct`) already knows, per grid cell,
the noise of a contact's strength there: the matched filter's, ``1/sqrt(G_kk)`` with ``G`` the
Gram matrix of the noise-weighted unit responses (:meth:`Reconstructor.cell_noise_map`), and the
noise of the 3 x 3 sums that detection thresholds (:meth:`Reconstructor.noise_map`). This module
turns those two maps into what a user asks: how strong must a contact be here to be found, and how
many frames summed make a contact of a given strength detectable. Nothing is re-derived: the
noise comes from a :class:`Reconstructor` built exactly as ``tofjax detect --method model`` builds it.

**The threshold.** A contact of strength ``s`` alone at cell ``k`` is found by the model method when
what is left of it after the lasso's shrinkage, summed over the 3 x 3 block, exceeds ``n_sigma``
times that sum's noise ``N_k``. Without noise the lasso takes ``lambda_k / G_kk = tau * sigma_k`` off
a contact whose cell's strength column is the only one on (``sigma_k``: the cell's matched-filter
strength noise); with the default optics a contact also shadows what lies behind it, its cell's
occupancy column switches on too, and the two penalties come off jointly, which takes more (the
two columns are anti-correlated): :meth:`Reconstructor.shrinkage_map`. So the smallest strength
found half the time, at a known position, is

    s_min(k) = shrinkage_k + n_sigma * N_k

and in units of the matched-filter SNR of a contact at a known position (``s / sigma_k``, the
README's "information limit") the model method needs ``s_min / sigma_k`` (6.5-12 on OptoSkin at 4 /m with the
defaults ``tau = 4``, ``n_sigma = 1``). The frame-relative threshold (``relative``: 10% of the
frame's strongest contact) depends on the other contacts and is left out: the map is for one
contact alone. ``docs/inversion.md`` ("Sensitivity map") gives how well it predicts recall.

**Frames.** ``frames`` frames summed, the baseline on the same exposure (each of its frames a
sum of as many): signal and Poisson variance both grow ``frames`` times, so every noise in
strength units shrinks by ``sqrt(frames)``, the SNR grows by it, and a contact of strength ``s``
needs ``(s_min / s)^2`` frames (rounded up).

**The fit method** (:func:`fit_sensitivity`, :mod:`tofjax.invert.greedy`, guided optics, the skin contact's
signed response: the light it adds and the light it shadows). The fit keeps a contact that lowers the
chi-square by more than ``n_sigma^2``; a contact of strength ``s`` alone at a known cell lowers it by
``(s / sigma_k)^2`` (``sigma_k``: the matched filter's strength noise, on the fit's own proposal grid), with no
shrinkage, so ``s_min(k) = n_sigma * sigma_k`` and the threshold is ``n_sigma`` (6) in SNR units everywhere.
Among six contacts at unknown positions a contact needs about twice that (SNR 12: found at 99-100% in
the simulated six-contact study on Monte Carlo data at 16x exposure, SNR 8-12 at 61-68%): the same
``RELIABLE_MARGIN``. The fit's overdispersion correction (drops divided by the reduced chi-square when the model
misses the data) raises the threshold on data the model does not describe; the map assumes it does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..config import ConfigError
from ..scene import Scene
from .correction import OpticalParams
from .maps import Grid
from .reconstruct import RESPONSES, ReconstructOptions, Reconstructor, build_reconstructor

__all__ = ["RELIABLE_MARGIN", "SensitivityOptions", "SensitivityResult", "fit_sensitivity", "fit_sensitivity_of",
           "major_sd", "match_probability", "sensitivity", "sensitivity_of"]

#: strength / min_strength above which the simulated six-contact study at mu_s + mu_a = 4 /m found 96-97%
#: of the contacts (``docs/results/sensitivity_vs_recall.json``); ``min_strength`` itself is a 50% point
#: for a contact alone, lower still among several contacts. Summaries and the figure show both.
RELIABLE_MARGIN = 2.0
#: For the fit method (``min_strength`` = n_sigma matched-filter noise) the same margin is SNR 12 at n_sigma 6.

_MARGIN_WHAT = {
    "model": "strength >= 2 x min_strength: the margin above which the six-contact study at 4 /m found 96-97% of the "
             "contacts (docs/inversion.md, 'Sensitivity map')",
    "fit": "strength >= 2 x min_strength (matched-filter SNR >= 2 n_sigma, 12): where the fit method found 99-100% of "
           "the contacts in the simulated six-contact study on Monte Carlo data at 16x (docs/inversion.md, "
           "'Sensitivity map')",
}


@dataclass(frozen=True)
class SensitivityOptions:
    """- ``strength``: the contact strength of interest (forward model units, as ``detect`` reports).
    - ``n_sigma``: the model method's detection threshold on the 3 x 3 summed strength, in its noise
      (``None``: the model method's default, :class:`ReconstructOptions` ``n_sigma``).
    - ``frames``: frames summed (the baseline on the same exposure).
    - ``response``: the contact column, as ``detect --contact-response`` (``auto``, ``added``, ``signed``).
    - ``border_m``: cells whose centre is nearer an edge than this are "border" in the summaries.
    - ``reconstruct``: the rest of the model method's options (cell size, lasso ``tau``, ...);
      its ``n_sigma`` and ``response`` are replaced by the two fields above.
    - ``position`` (fit method only): also where a contact of ``strength`` can be *placed*: per cell the
      Cramer-Rao bound on a lone contact's position with ``frames`` summed, and the probability that a fit
      reaching it lands within ``match_radius_m`` of the contact (the guided model's Jacobian at every cell:
      tens of seconds more)."""

    strength: float = 1.0
    n_sigma: float | None = None
    frames: int = 1
    response: str = "auto"
    border_m: float = 0.05
    reconstruct: ReconstructOptions = field(default_factory=ReconstructOptions)
    position: bool = False
    match_radius_m: float = 0.02

    def __post_init__(self):
        if not (isinstance(self.strength, (int, float)) and math.isfinite(self.strength) and self.strength > 0):
            raise ConfigError(f"strength: must be a finite number > 0, got {self.strength!r}")
        if self.n_sigma is not None and not (math.isfinite(self.n_sigma) and self.n_sigma >= 0):
            raise ConfigError(f"n_sigma: must be a finite number >= 0, got {self.n_sigma!r}")
        if isinstance(self.frames, bool) or not isinstance(self.frames, int) or self.frames < 1:
            raise ConfigError(f"frames: must be an integer >= 1, got {self.frames!r}")
        if self.response not in RESPONSES:
            raise ConfigError(f"response: must be one of {', '.join(RESPONSES)}, got {self.response!r}")
        if not (math.isfinite(self.border_m) and self.border_m >= 0):
            raise ConfigError(f"border_m: must be a finite number >= 0, got {self.border_m!r}")
        if not isinstance(self.reconstruct, ReconstructOptions):
            raise ConfigError("reconstruct: must be a ReconstructOptions")
        if not isinstance(self.position, bool):
            raise ConfigError(f"position: must be true or false, got {self.position!r}")
        if not (isinstance(self.match_radius_m, (int, float)) and math.isfinite(self.match_radius_m) and self.match_radius_m > 0):
            raise ConfigError(f"match_radius_m: must be a finite number > 0, got {self.match_radius_m!r}")

    def reconstruct_options(self) -> ReconstructOptions:
        """The model method's options the map describes (what ``detect --method model`` would use)."""
        import dataclasses

        n = self.reconstruct.n_sigma if self.n_sigma is None else float(self.n_sigma)
        return dataclasses.replace(self.reconstruct, n_sigma=n, response=self.response)


@dataclass(frozen=True)
class SensitivityResult:
    """Per-cell maps (ny, nx) on the reconstruction's grid; cells the method never detects (the
    edge band it leaves out, cells no sensor sees) have infinite noise, ``min_strength`` and
    ``frames_needed``, and zero SNR.

    - ``cell_noise``: a cell's strength noise in one frame, ``1/sqrt(G_kk)`` (matched filter).
    - ``noise``: the noise of the 3 x 3 sums detection sees, one frame (the reconstructor's ``noise_map``).
    - ``shrinkage``: what the lasso takes off a contact's strength there (``tau * cell_noise``, more with
      the shadow occupancies; the reconstructor's ``shrinkage_map``).
    - ``min_strength``: smallest strength detected in one frame, ``shrinkage + n_sigma * noise``.
    - ``threshold_snr``: the same in matched-filter SNR units, ``min_strength / cell_noise``.
    - ``snr``: matched-filter SNR of a contact of ``options.strength`` alone at the cell, with ``frames`` summed.
    - ``frames_needed``: frames summed for that contact to reach ``min_strength`` (``(min_strength / strength)^2``, rounded up).
    - ``position_sd`` (fit method with ``options.position``; else None): the larger standard deviation [m] of a lone
      contact's position at the cell, ``options.strength`` and ``options.frames`` (the Cramer-Rao bound; inf where
      the data do not place it).
    - ``match_share`` (likewise): the probability that a fit reaching the bound lands within
      ``options.match_radius_m`` of the contact (:func:`match_probability`)."""

    grid: Grid
    scene: Scene
    options: SensitivityOptions
    tau: float
    n_sigma: float
    response: str
    cell_noise: np.ndarray
    noise: np.ndarray
    shrinkage: np.ndarray
    min_strength: np.ndarray
    threshold_snr: np.ndarray
    snr: np.ndarray
    frames_needed: np.ndarray
    method: str = "model"
    position_sd: np.ndarray | None = None
    match_share: np.ndarray | None = None

    @property
    def sensed(self) -> np.ndarray:
        """Cells where a contact can be detected at all (finite noise)."""
        return np.isfinite(self.noise) & np.isfinite(self.cell_noise)

    @property
    def border(self) -> np.ndarray:
        """Cells whose centre is within ``options.border_m`` of an edge."""
        c = self.grid.centres()
        lx, ly = self.scene.waveguide.size_m
        d = np.minimum.reduce([c[..., 0], lx - c[..., 0], c[..., 1], ly - c[..., 1]])
        return d < self.options.border_m

    def detectable(self, frames: int | None = None) -> np.ndarray:
        """Cells where a contact of ``options.strength`` is detectable with ``frames`` summed (default: ``options.frames``)."""
        f = self.options.frames if frames is None else frames
        return self.sensed & (self.frames_needed <= f)

    def at(self, xy) -> dict[str, np.ndarray]:
        """The maps at points ``xy`` (..., 2) [m]: the value of the cell each falls in."""
        xy = np.asarray(xy, float)
        i = np.clip((xy[..., 0] / self.grid.dx).astype(int), 0, self.grid.nx - 1)
        j = np.clip((xy[..., 1] / self.grid.dy).astype(int), 0, self.grid.ny - 1)
        keys = ("cell_noise", "noise", "shrinkage", "min_strength", "threshold_snr")
        keys += () if self.position_sd is None else ("position_sd", "match_share")
        return {k: getattr(self, k)[j, i] for k in keys}

    def summary(self) -> dict:
        """Shares of the sensed area where ``options.strength`` is detectable in one frame and with
        ``options.frames``, overall and split border / interior, and quantiles of the maps."""
        sensed, border = self.sensed, self.border

        def share(mask, region):
            n = int(region.sum())
            return float(mask[region].mean()) if n else None

        def mean_of(values, region):
            return float(values[region].mean()) if region.any() else None

        one, many = self.detectable(1), self.detectable()
        sure = sensed & (self.options.strength >= RELIABLE_MARGIN * self.min_strength)
        fin = self.min_strength[sensed]
        q = (lambda v: np.quantile(v, [0.1, 0.5, 0.9]).tolist() if v.size else None)
        return {
            "sensed_cells": int(sensed.sum()),
            "cells": int(sensed.size),
            "sensed_share_of_guide": float(sensed.mean()),
            "detectable_one_frame": {"all": share(one, sensed), "border": share(one, sensed & border),
                                     "interior": share(one, sensed & ~border)},
            "detectable_one_frame_with_margin_2": {
                "what": _MARGIN_WHAT[self.method],
                "all": share(sure, sensed), "border": share(sure, sensed & border),
                "interior": share(sure, sensed & ~border)},
            "detectable_with_frames": {"frames": self.options.frames, "all": share(many, sensed),
                                       "border": share(many, sensed & border), "interior": share(many, sensed & ~border)},
            "min_strength_one_frame_quantiles_10_50_90": q(fin),
            "min_strength_one_frame_median_border_interior": [
                float(np.median(self.min_strength[sensed & border])) if (sensed & border).any() else None,
                float(np.median(self.min_strength[sensed & ~border])) if (sensed & ~border).any() else None],
            "threshold_snr_quantiles_10_50_90": q(self.threshold_snr[sensed]),
            "frames_needed_quantiles_10_50_90": q(self.frames_needed[sensed]),
            "frames_needed_max": float(self.frames_needed[sensed].max()) if sensed.any() else None,
            **({} if self.match_share is None else {"placed_within_match_radius": {
                "what": "mean over the sensed cells of the probability that a lone contact of options.strength, "
                        "options.frames summed, fitted at its position bound, lands within match_radius_m",
                "match_radius_m": self.options.match_radius_m, "frames": self.options.frames,
                "all": mean_of(self.match_share, sensed), "border": mean_of(self.match_share, sensed & border),
                "interior": mean_of(self.match_share, sensed & ~border)},
                "position_sd_cm_median_border_interior": [
                    float(100 * np.median(self.position_sd[sensed & border])) if (sensed & border).any() else None,
                    float(100 * np.median(self.position_sd[sensed & ~border])) if (sensed & ~border).any() else None]}),
        }

    def to_json(self) -> dict:
        """Options, summary and every map (``null`` where infinite), rows bottom to top (y), columns x."""

        def arr(a):
            a = np.asarray(a, float)
            return [[(float(v) if math.isfinite(v) else None) for v in row] for row in a]

        o = self.options
        return {
            "format": "tofjax.sensitivity", "version": 1,
            "what": f"{self.method} method's detectability per cell (one contact alone, known position; Poisson noise "
                    "of the baseline); see docs/inversion.md, 'Sensitivity map'",
            "scene": self.scene.name,
            "options": {"method": self.method, "strength": o.strength, "frames": o.frames, "n_sigma": self.n_sigma, "tau": self.tau,
                        "response": self.response, "border_m": o.border_m, "cell_m": self.grid.dx,
                        "position": o.position, "match_radius_m": o.match_radius_m},
            "summary": self.summary(),
            "grid": {"nx": self.grid.nx, "ny": self.grid.ny, "dx_m": self.grid.dx, "dy_m": self.grid.dy,
                     "x_m": self.grid.x.tolist(), "y_m": self.grid.y.tolist()},
            "maps": {"cell_noise": arr(self.cell_noise), "noise": arr(self.noise), "shrinkage": arr(self.shrinkage),
                     "min_strength": arr(self.min_strength),
                     "threshold_snr": arr(self.threshold_snr), "snr": arr(self.snr),
                     "frames_needed": arr(self.frames_needed),
                     **({} if self.position_sd is None else {"position_sd_m": arr(self.position_sd),
                                                             "match_share": arr(self.match_share)})},
        }


def sensitivity_of(reconstructor: Reconstructor, options: SensitivityOptions = SensitivityOptions()) -> SensitivityResult:
    """The sensitivity map of a built reconstructor (its noise maps, its ``tau`` and ``n_sigma``):
    the one place the threshold formula lives (see the module docstring). ``options``' ``n_sigma``
    (if given) replaces the reconstructor's; the other reconstruct options are the reconstructor's."""
    ro = reconstructor.options
    if options.position:
        raise ConfigError("position: the position bound is the fit method's map (fit_sensitivity, --method fit)")
    if options.response not in ("auto", reconstructor.response):
        raise ConfigError(f"response: the reconstructor's contact response is {reconstructor.response!r}, the options "
                          f"ask for {options.response!r} (build it with that response, or use sensitivity())")
    n_sigma = ro.n_sigma if options.n_sigma is None else float(options.n_sigma)
    sig = reconstructor.cell_noise_map()
    N = reconstructor.noise_map()
    shrink = reconstructor.shrinkage_map()
    sensed = np.isfinite(sig) & np.isfinite(N) & np.isfinite(shrink)
    with np.errstate(invalid="ignore", divide="ignore"):
        s_min = np.where(sensed, shrink + n_sigma * N, np.inf)
        thr = np.where(sensed, s_min / sig, np.inf)
    snr, need = _snr_and_frames(sensed, sig, s_min, options)
    return SensitivityResult(
        grid=reconstructor.grid, scene=reconstructor.scene, options=options, tau=float(ro.tau), n_sigma=n_sigma,
        response=reconstructor.response, cell_noise=sig, noise=N, shrinkage=np.where(sensed, shrink, np.inf),
        min_strength=s_min, threshold_snr=thr, snr=snr,
        frames_needed=need,
    )


def major_sd(cov) -> np.ndarray:
    """The larger standard deviation of position covariances ``cov`` (..., 2, 2) [m^2] (the error ellipse's
    long axis); inf where an entry is not finite (a position the data do not see)."""
    c = np.asarray(cov, float)
    finite = np.all(np.isfinite(c), axis=(-2, -1))
    ev = np.linalg.eigvalsh(np.where(finite[..., None, None], c, np.eye(2)))[..., 1]
    return np.where(finite, np.sqrt(np.maximum(ev, 0.0)), np.inf)


def match_probability(cov, radius_m: float, *, nodes: int = 512) -> np.ndarray:
    """The probability that a position error ``e ~ N(0, cov)`` lies within ``radius_m`` of the truth: the share
    of fits an evaluation matches to their contact (``match_radius_m``) when the fit reaches its bound
    (:meth:`tofjax.invert.greedy.FitDetector.position_bound`). ``cov`` (..., 2, 2) [m^2]; a covariance with an
    infinite or non-finite entry gives 0.

    In the covariance's axes, ``e = (u, v)`` with standard deviations ``a <= b``; with ``v = r sin(phi)``,
    ``P = int_{-pi/2}^{pi/2} N(r sin(phi); 0, b^2) erf(r cos(phi) / (a sqrt 2)) r cos(phi) dphi`` (the ``u``
    integral over the chord in closed form). The integrand is smooth and its peak is ``b / r`` wide, so the
    midpoint rule on ``nodes`` points is accurate to 1e-6 or better for ``b >= r / 8`` (to rounding for a round
    error); below that ``P > 1 - 1e-14`` and is 1.
    ``a = b = s`` gives ``1 - exp(-r^2 / 2 s^2)``; ``a = 0`` gives ``erf(r / (b sqrt 2))``."""
    from scipy.special import erf

    if not (isinstance(radius_m, (int, float)) and math.isfinite(radius_m) and radius_m > 0):
        raise ConfigError(f"radius_m: must be a finite number > 0, got {radius_m!r}")
    c = np.asarray(cov, float)
    if c.ndim < 2 or c.shape[-2:] != (2, 2):
        raise ConfigError(f"cov: must have shape (..., 2, 2), got {c.shape}")
    ok = np.all(np.isfinite(c), axis=(-2, -1))
    ev = np.linalg.eigvalsh(np.where(ok[..., None, None], c, np.eye(2)))
    a = np.sqrt(np.maximum(ev[..., 0], 0.0))[..., None]
    b = np.sqrt(np.maximum(ev[..., 1], 0.0))[..., None]
    r = float(radius_m)
    phi = (np.arange(nodes) + 0.5) * (np.pi / nodes) - 0.5 * np.pi
    v, chord = r * np.sin(phi), r * np.cos(phi)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        bb = np.maximum(b, 1e-300)
        dens = np.exp(-0.5 * (v / bb) ** 2) / (bb * math.sqrt(2.0 * math.pi))
        inner = np.where(a > 0, erf(chord / (np.maximum(a, 1e-300) * math.sqrt(2.0))), 1.0)
        p = np.sum(dens * inner * chord, axis=-1) * (np.pi / nodes)
    p = np.where(b[..., 0] < r / 8.0, 1.0, p)
    return np.where(ok, np.clip(p, 0.0, 1.0), 0.0)


def _snr_and_frames(sensed, sig, s_min, options: SensitivityOptions):
    """Per cell the SNR of ``options.strength`` summed over ``options.frames`` (strength noise ``sig``
    shrinks by sqrt(frames)) and the frames a contact of that strength needs to reach ``s_min``:
    ``(s_min / strength)^2``, rounded up, at least 1 (unsensed cells: SNR 0, frames inf)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        snr = np.where(sensed, options.strength * math.sqrt(options.frames) / sig, 0.0)
        # rounded up; a ratio within 1e-12 of an integer (rounding error) counts as that integer
        need = np.where(sensed, np.ceil((s_min / options.strength) ** 2 * (1.0 - 1e-12)), np.inf)
    return snr, np.maximum(need, 1.0)


def sensitivity(
    scene: Scene,
    baseline: np.ndarray,
    optical: OpticalParams | None = None,
    options: SensitivityOptions = SensitivityOptions(),
    *,
    n_baseline: int = 1,
) -> SensitivityResult:
    """The model method's sensitivity map of ``scene`` (its contacts are ignored).

    **Arguments:**

    - ``scene``: the setup.
    - ``baseline``: mean no-touch histograms (S, Z, B), the noise's source.
    - ``optical``: calibrated optics (:meth:`OpticalParams.from_calibration`; default: the scene's).
    - ``options``: :class:`SensitivityOptions`.
    - ``n_baseline``: frames averaged into ``baseline`` (its own noise adds, as in detection).
    """
    b = np.asarray(baseline, float)
    if b.shape != scene.shape:
        raise ConfigError(f"baseline: histograms have shape {b.shape} (sensors, zones, bins), the scene {scene.shape}")
    if options.position:
        raise ConfigError("position: the position bound is the fit method's map (fit_sensitivity, --method fit)")
    optical = OpticalParams.from_scene(scene) if optical is None else optical
    rec = build_reconstructor(scene.without_touches(), b, optical, options.reconstruct_options(), n_baseline=n_baseline)
    return sensitivity_of(rec, options)


def _fit_map(grid: Grid, cells: np.ndarray, gdiag: np.ndarray, scene: Scene, options: SensitivityOptions,
             n_sigma: float, position_cov: np.ndarray | None = None) -> SensitivityResult:
    """The fit method's map from its proposal grid: ``gdiag`` (per cell in ``cells``) is the squared
    matched-filter SNR of a strength-1 contact alone in one frame; cells outside ``cells`` are never sensed.
    ``position_cov`` (per cell in ``cells``, (n, 2, 2)): a lone contact's position bound, for the position maps."""
    sig = np.full(grid.ny * grid.nx, np.inf)
    g = np.asarray(gdiag, float)
    sig[cells] = np.where(g > 0, 1.0 / np.sqrt(np.where(g > 0, g, 1.0)), np.inf)  # double where: no 1/0
    sig = sig.reshape(grid.ny, grid.nx)
    sensed = np.isfinite(sig)
    with np.errstate(invalid="ignore"):
        s_min = np.where(sensed, n_sigma * sig, np.inf)
    snr, need = _snr_and_frames(sensed, sig, s_min, options)
    sd = share = None
    if position_cov is not None:
        cov = np.asarray(position_cov, float)
        major = major_sd(cov)
        sd, share = np.full(grid.ny * grid.nx, np.inf), np.zeros(grid.ny * grid.nx)
        sd[cells], share[cells] = major, match_probability(cov, options.match_radius_m)
        sd = np.where(sensed, sd.reshape(grid.ny, grid.nx), np.inf)
        share = np.where(sensed, share.reshape(grid.ny, grid.nx), 0.0)
    return SensitivityResult(
        grid=grid, scene=scene, options=options, tau=0.0, n_sigma=n_sigma, response="signed", cell_noise=sig,
        noise=sig, shrinkage=np.where(sensed, 0.0, np.inf), min_strength=s_min,
        threshold_snr=np.where(sensed, n_sigma, np.inf), snr=snr, frames_needed=need, method="fit",
        position_sd=sd, match_share=share)


def _check_fit_options(options: SensitivityOptions) -> None:
    if options.response not in ("auto", "signed"):
        raise ConfigError(f"response: the fit method fits the signed contact response, got {options.response!r}")
    if options.reconstruct != ReconstructOptions():
        raise ConfigError("reconstruct: the fit method has no reconstruction options (leave them at their defaults)")


def fit_sensitivity_of(detector, options: SensitivityOptions = SensitivityOptions(), *,
                       progress: bool = False) -> SensitivityResult:
    """The fit method's sensitivity map of a built :class:`tofjax.invert.greedy.FitDetector` (its proposal grid,
    responses and noise; ``options.n_sigma``, when given, replaces its ``n_sigma``). See the module docstring."""
    _check_fit_options(options)
    n_sigma = detector.options.n_sigma if options.n_sigma is None else float(options.n_sigma)
    cov = _lone_bounds(detector.scene, detector.optical, detector.sigma, detector.centres, detector.options, options,
                       progress)
    return _fit_map(detector.grid, detector.cells, detector._gdiag, detector.scene, options, n_sigma, cov)


def _lone_bounds(scene, optical, sigma, centres, fit, options: SensitivityOptions, progress: bool):
    """A lone contact's position bound at every proposal centre, or None without ``options.position``."""
    if not options.position:
        return None
    from .greedy import lone_position_bounds

    return lone_position_bounds(scene, optical, sigma, centres, options.strength, fit.contact_radius_m, options.frames,
                                progress=progress)


def fit_sensitivity(
    scene: Scene,
    baseline: np.ndarray,
    optical: OpticalParams | None = None,
    options: SensitivityOptions = SensitivityOptions(),
    fit=None,
    *,
    n_baseline: int = 1,
    progress: bool = False,
) -> SensitivityResult:
    """The fit method's (``detect --method fit``) sensitivity map of ``scene`` (its contacts are ignored),
    without compiling the fit's model (the responses on its proposal grid only; with ``options.position`` the
    model's Jacobian at every cell, ``progress`` a progress bar).

    **Arguments:**

    - ``scene``, ``baseline`` (S, Z, B) mean no-touch histograms, ``n_baseline`` frames averaged into it.
    - ``optical``: calibrated optics; must be the guided optics (default: the scene's, as guided optics).
    - ``options``: :class:`SensitivityOptions` (``response`` auto or signed; ``reconstruct`` left at its defaults).
    - ``fit``: the fit method's :class:`tofjax.invert.greedy.FitDetectOptions` (grid, contact radius, edge
      margin, ``n_sigma``; default its defaults).

    **Returns:** a :class:`SensitivityResult` on the fit's proposal grid (``method`` "fit")."""
    import dataclasses

    from .correction import InversionError
    from .greedy import FitDetectOptions, proposal_responses

    _check_fit_options(options)
    fit = FitDetectOptions() if fit is None else fit
    b = np.asarray(baseline, float)
    if b.shape != scene.shape:
        raise ConfigError(f"baseline: histograms have shape {b.shape} (sensors, zones, bins), the scene {scene.shape}")
    if optical is None:
        optical = dataclasses.replace(OpticalParams.from_scene(scene), optics="guided")
    if optical.optics != "guided":
        raise InversionError("the fit method's map needs a calibration with the guided optics (skin contacts); "
                             f"this one has {optical.optics!r}")
    sc = scene.without_touches()
    p = proposal_responses(sc, b, optical, fit, n_baseline)
    n_sigma = fit.n_sigma if options.n_sigma is None else float(options.n_sigma)
    cov = _lone_bounds(sc, optical, p.sigma, p.centres, fit, options, progress)
    return _fit_map(p.grid, p.cells, p.gdiag, sc, options, n_sigma, cov)
