"""A second, deliberately different simulator of ToF FTIR captures (NumPy only): a test fixture.

Written from seed 000's physics (Eq. 2-5: ``P_r = Q_int + Q_vol + Q_touch + N_ms + N_a``,
``Q_i = K G beta_i T``, ``G = 1/(c1 t)^2``, ``T = exp(-2 mu_t c1 t)``) without tofjax's
forward model. It reads the scene geometry from :class:`tofjax.scene.Scene` and returns a
:class:`tofjax.capture.Capture`; everything else is computed here. Use it to test tofjax on
data tofjax did not make: calibration and detection should hold on it with no change.

How it differs from :mod:`tofjax.model` (on purpose; each item is a convention a real rig
may break):

* **Discretisation.** tofjax integrates ``G`` over quadrature time nodes in closed form along
  a few rays per zone and deposits point events with B-spline weights. Here every
  distributed term is a *sum over sample points of the waveguide area*: each zone's wedge is
  sampled on jittered strata (1 mm in range x ``angles_per_zone`` in angle); a point counts
  only if it lies inside the waveguide, so the far edge truncates each angle exactly. Events
  go to a fine time grid (``fine`` sub-bins per bin, nearest cell), are convolved with the
  instrument response sampled on that grid, and summed into bins.
* **Near field.** ``G(r) = 1 / max(r, r0)^2`` with ``r0 = near_field_fraction x thickness``
  (tofjax: ``(r^p + d^p)^(-2/p)``, the scene's ``1 / (r^2 + thickness^2)`` at ``p = 2``).
  ``near_field_law`` picks another law with the same ``r0`` (a third one, neither tofjax's
  family nor this default, to test that a fit does not depend on one law):
  ``"gaussian"``: ``(1 - exp(-r^2 / r0^2)) / r^2``; ``"exponential"``:
  ``(1 - exp(-r / r0))^2 / r^2`` (both finite at 0, ``1/r^2`` far away).
* **Instrument response.** A Gaussian (``pulse_sigma_s``) convolved with *two* exponential
  tails (``tail_fast_s``, ``tail_slow_s``, weight ``slow_weight`` on the slow one); tofjax uses
  one tail (an EMG).
* **Emission time** is the scene's plus ``emission_offset_s`` (default +25 ps).
* **Gains per zone**: ``K_sz = K_s (1 + gain_spread x N(0, 1))`` (default 6%), fixed per rig;
  tofjax has one gain per sensor.
* **Crosstalk**: each zone's light-entry peak has its own size (``crosstalk_spread``, default
  25%) and is a Gaussian ``crosstalk_width_s`` wide at emission (then the response);
  ambient counts vary per zone (``ambient_spread``).
* **Far edge**: reflectance ``end_reflectance x |cos(incidence)|`` per ray (tofjax: constant),
  on ``end_rays`` rays per zone spread uniformly with jitter.
* **Contacts** are sampled as ``touch_points`` points over the disk (tofjax: a chord density
  in range and its area in each zone's wedge); a point belongs to the zone whose angle holds it.
  Their backscatter is ``touch_coupling x strength`` (default 0.6: the strength scale is not
  tofjax's).
* **Shadowing** is geometric: light to a point (background, far edge or another contact) is
  multiplied by ``(1 - shadow_opacity)^2`` for each contact disk its straight path from the
  sensor crosses (tofjax: a zone-wide fraction with a sigmoid in range).
* **Multiple scattering is omitted** (``N_ms = 0``); volume backscatter is
  ``volume_backscatter_fraction x mu_s`` per metre, interface backscatter ``beta_int`` per metre,
  as the scene states.
* **Noise**: Poisson (NumPy's generator); no pile-up, 24-bit saturation.

The capture's ``truth`` holds what was used (``n1``, ``mu_s_per_m``, ``mu_a_per_m``,
``emission_time_s``, per-zone gains, crosstalk, ambient, pulse) and ``truth_touches`` the
contacts; ``source`` says ``"simulated (tests/indep_sim.py)"``.

    from indep_sim import IndepRig, simulate
    rig = IndepRig.from_scene(load_scene("configs/touch-six.toml"), seed=1)
    cap = simulate(rig, frames=10, seed=2)              # the scene's own contacts
    base = simulate(rig, contacts=np.zeros((0, 3)), frames=100, seed=3)   # a baseline
    many = rig.histograms(contacts_cn3, seed=4)          # (C, S, Z, B), one frame each
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from tofjax.capture import Capture
from tofjax.scene import Scene

C_M_PER_S = 299_792_458.0


@dataclass(frozen=True)
class IndepOptions:
    """The independent simulator's own conventions (see the module docstring)."""

    emission_offset_s: float = 25e-12
    pulse_sigma_s: float = 55e-12
    tail_fast_s: float = 120e-12
    tail_slow_s: float = 550e-12
    slow_weight: float = 0.18
    gain_spread: float = 0.06
    crosstalk_spread: float = 0.25
    crosstalk_width_s: float = 30e-12
    ambient_spread: float = 0.3
    near_field_fraction: float = 0.6
    #: the near field's law (module docstring): "max" (the default), "gaussian" or "exponential"
    near_field_law: str = "max"
    touch_coupling: float = 0.6
    range_step_m: float = 1e-3
    angles_per_zone: int = 12
    end_rays: int = 48
    touch_points: int = 96
    fine: int = 16
    touch_radius_m: float = 0.006
    #: Resolution and jitter of the sampled geometry (defaults: the fast fixture; the study of
    #: experiments/study_mu_low.py --convergence shows where the data stop changing, see
    #: ``CONVERGED``). ``geometry_seed``: None draws the jitter from the rig's seed stream (after
    #: the per-zone draws, as always); an int draws it from its own stream, so the same rig
    #: (same per-zone draws) can be sampled again with other jitter.
    geometry_seed: int | None = None


#: The resolution at which the expected counts have stopped changing what a calibration reads
#: from them (docs/results/mu_low_convergence.json: at mu_t = 0.05 /m the noise-free mu_t moves
#: by about 1 point between this, the next finer level and other jitters; at the default the
#: jitter alone moves it with a 9-26-point sd). 1.5-7 s per rig of 3 x 7 zones (loaded VM) instead
#: of 0.02-0.1 s: for studies and slow tests;
#: the default stays the fast fixture (its coarse sampling matters only where attenuation is low).
CONVERGED = IndepOptions(range_step_m=0.125e-3, angles_per_zone=96, end_rays=384)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _irf(opts: IndepOptions, dt: float) -> tuple[np.ndarray, int]:
    """Instrument response on the fine grid (sums to 1) and the index of time zero in it."""
    lo = int(math.ceil(5 * opts.pulse_sigma_s / dt))
    hi = int(math.ceil((5 * opts.pulse_sigma_s + 10 * opts.tail_slow_s) / dt))
    t = np.arange(-lo, hi + 1) * dt
    g = np.exp(-0.5 * (t / opts.pulse_sigma_s) ** 2)
    pos = np.clip(t, 0.0, None)
    tails = (1 - opts.slow_weight) * np.exp(-pos / opts.tail_fast_s) / opts.tail_fast_s
    tails += opts.slow_weight * np.exp(-pos / opts.tail_slow_s) / opts.tail_slow_s
    tails = np.where(t >= 0, tails, 0.0)
    k = np.convolve(g, tails)[lo : lo + len(t)]  # keep time zero at index lo
    return k / k.sum(), lo


@dataclass
class IndepRig:
    """One simulated rig: a scene plus the hidden per-zone truth of this simulator."""

    scene: Scene
    options: IndepOptions
    gain_sz: np.ndarray  # (S, Z) counts m^2
    crosstalk_sz: np.ndarray  # (S, Z) counts in the light-entry peak
    ambient_sz: np.ndarray  # (S, Z) counts per bin
    emission_time_s: float
    seed: int
    _background: list = field(default_factory=list, repr=False)  # per (s, z): (xy, r, weight)
    _edge: list = field(default_factory=list, repr=False)  # per (s, z): (xy, length, weight)

    @classmethod
    def from_scene(cls, scene: Scene, seed: int = 0, options: IndepOptions = IndepOptions()) -> "IndepRig":
        rng = np.random.default_rng(seed)
        S, Z, _ = scene.shape
        sm = scene.sensor
        k = np.array([sm.gain if s.gain is None else s.gain for s in scene.sensors], float)
        gain = k[:, None] * np.clip(1 + options.gain_spread * rng.standard_normal((S, Z)), 0.5, 1.5)
        xt = sm.crosstalk_counts * np.clip(1 + options.crosstalk_spread * rng.standard_normal((S, Z)), 0.2, 2.0)
        amb = sm.ambient_counts * np.clip(1 + options.ambient_spread * rng.standard_normal((S, Z)), 0.1, 2.0)
        rig = cls(scene, options, gain, xt, amb, sm.emission_time + options.emission_offset_s, seed)
        rig._sample_geometry(rng if options.geometry_seed is None else np.random.default_rng(options.geometry_seed))
        return rig

    # ---- geometry ---------------------------------------------------------------------------
    @property
    def c1(self) -> float:
        return C_M_PER_S / self.scene.waveguide.n1

    def _zone_limits(self) -> np.ndarray:
        sm = self.scene.sensor
        fov = math.radians(sm.fov_deg)
        e = np.linspace(-fov / 2, fov / 2, sm.zones + 1)
        return np.stack([e[:-1], e[1:]], 1)

    def _inside(self, xy):
        lx, ly = self.scene.waveguide.size_m
        return (xy[..., 0] >= 0) & (xy[..., 0] <= lx) & (xy[..., 1] >= 0) & (xy[..., 1] <= ly)

    def _sample_geometry(self, rng) -> None:
        wg, o = self.scene.waveguide, self.options
        lx, ly = wg.size_m
        rmax = math.hypot(lx, ly)
        nr = int(math.ceil(rmax / o.range_step_m))
        lim = self._zone_limits()
        mu_t = wg.mu_s_per_m + wg.mu_a_per_m
        beta = wg.interface_backscatter_per_m + wg.volume_backscatter_fraction * wg.mu_s_per_m
        for s in self.scene.sensors:
            p0 = np.array(s.position_m, float)
            axis = math.radians(s.direction_deg)
            for lo, hi in lim:
                # Background: jittered strata in range x angle; weight = density per metre x dr / n_angles.
                r = (np.arange(nr)[:, None] + rng.random((nr, o.angles_per_zone))) * o.range_step_m
                a = axis + lo + (hi - lo) * (np.arange(o.angles_per_zone)[None, :] + rng.random((nr, o.angles_per_zone))) / o.angles_per_zone
                xy = p0 + np.stack([r * np.cos(a), r * np.sin(a)], -1)
                keep = self._inside(xy)
                r, xy = r[keep], xy[keep]
                w = beta * self._falloff(r) * np.exp(-2 * mu_t * r) * o.range_step_m / o.angles_per_zone
                self._background.append((xy, r, w))
                # Far edge along jittered rays.
                a = axis + lo + (hi - lo) * (np.arange(o.end_rays) + rng.random(o.end_rays)) / o.end_rays
                d = np.stack([np.cos(a), np.sin(a)], -1)
                with np.errstate(divide="ignore", invalid="ignore"):
                    tx = np.where(d[:, 0] > 1e-12, (lx - p0[0]) / d[:, 0], np.where(d[:, 0] < -1e-12, -p0[0] / d[:, 0], np.inf))
                    ty = np.where(d[:, 1] > 1e-12, (ly - p0[1]) / d[:, 1], np.where(d[:, 1] < -1e-12, -p0[1] / d[:, 1], np.inf))
                L = np.minimum(tx, ty)
                ok = np.isfinite(L) & (L > 1e-6)
                # Incidence: the edge normal is x for a hit on a vertical edge, else y.
                cos_inc = np.where(tx < ty, np.abs(d[:, 0]), np.abs(d[:, 1]))
                L, d, cos_inc = L[ok], d[ok], cos_inc[ok]
                w = wg.end_reflectance * cos_inc * self._falloff(L) * np.exp(-2 * mu_t * L) / o.end_rays
                self._edge.append((p0 + L[:, None] * d * (1 - 1e-9), L, w))

    def _falloff(self, r):
        r0 = self.options.near_field_fraction * self.scene.waveguide.thickness_m
        law = self.options.near_field_law
        if law == "max":
            return 1.0 / np.maximum(r, r0) ** 2
        r = np.asarray(r, float)
        x = r / r0
        safe = np.where(x > 0, x, 1.0)
        if law == "gaussian":  # (1 - exp(-x^2)) / x^2 -> 1 at 0
            f = np.where(x > 1e-4, -np.expm1(-safe**2) / safe**2, 1.0 - 0.5 * x**2)
        elif law == "exponential":  # ((1 - exp(-x)) / x)^2 -> 1 at 0
            f = np.where(x > 1e-6, (-np.expm1(-safe) / safe) ** 2, 1.0 - x)
        else:
            raise ValueError(f"near_field_law: 'max', 'gaussian' or 'exponential', got {law!r}")
        return f / r0**2

    # ---- contacts ---------------------------------------------------------------------------
    def _disk_points(self, contacts: np.ndarray):
        """Sample points of every contact disk: (N, P, 2) and the per-point backscatter (N, P)."""
        n = self.options.touch_points
        # A fixed sunflower pattern: uniform over the disk, the same for every contact.
        k = np.arange(n) + 0.5
        rho = self.options.touch_radius_m * np.sqrt(k / n)
        th = k * math.pi * (3 - math.sqrt(5))
        off = np.stack([rho * np.cos(th), rho * np.sin(th)], -1)
        pts = contacts[:, None, :2] + off[None]
        inside = self._inside(pts)
        w = self.options.touch_coupling * contacts[:, 2:3] / n * inside
        return pts, w

    def _shadow(self, p0, xy, contacts, skip=None):
        """Round-trip transmission past contact disks for straight paths p0 -> xy (..., 2)."""
        if len(contacts) == 0:
            return np.ones(xy.shape[:-1])
        op = self.scene.waveguide.shadow_opacity
        rad = self.options.touch_radius_m
        d = xy - p0
        L = np.linalg.norm(d, axis=-1)
        u = d / np.maximum(L, 1e-12)[..., None]
        out = np.ones(xy.shape[:-1])
        for j, c in enumerate(contacts[:, :2]):
            if skip is not None and j == skip:
                continue
            v = c - p0
            along = v @ u.reshape(-1, 2).T
            along = along.reshape(L.shape)
            perp2 = np.sum(v**2) - along**2
            crosses = (along > 0) & (along + rad < L) & (perp2 < rad**2)
            out = np.where(crosses, out * (1 - op) ** 2, out)
        return out

    # ---- the signal -------------------------------------------------------------------------
    def expected(self, contacts: np.ndarray | None = None) -> np.ndarray:
        """Expected counts (S, Z, B) with ``contacts`` (N, 3) = x_m, y_m, strength (default: the scene's)."""
        if contacts is None:
            el = self.scene.contact_elements()
            contacts = el[:, [0, 1, 3]] if len(el) else np.zeros((0, 3))
        contacts = np.asarray(contacts, float).reshape(-1, 3)
        sm, wg, o = self.scene.sensor, self.scene.waveguide, self.options
        S, Z, B = self.scene.shape
        dt = sm.bin_width_s / o.fine
        nf = B * o.fine
        irf, zero = _irf(o, dt)
        mu_t = wg.mu_s_per_m + wg.mu_a_per_m
        lim = self._zone_limits()
        pts, pw = self._disk_points(contacts) if len(contacts) else (np.zeros((0, 0, 2)), np.zeros((0, 0)))
        # Crosstalk shape: a narrow Gaussian at emission, on the fine grid.
        tf = (np.arange(nf) + 0.5) * dt
        xt_shape = np.exp(-0.5 * ((tf - self.emission_time_s) / o.crosstalk_width_s) ** 2)
        xt_shape /= xt_shape.sum()
        fine = np.zeros((S, Z, nf))
        for s, sen in enumerate(self.scene.sensors):
            p0 = np.array(sen.position_m, float)
            axis = math.radians(sen.direction_deg)
            if len(contacts):
                dp = pts - p0
                rp = np.linalg.norm(dp, axis=-1)
                ang = _wrap(np.arctan2(dp[..., 1], dp[..., 0]) - axis)
            for z, (lo, hi) in enumerate(lim):
                i = s * Z + z
                times, masses = [], []
                for xy, r, w in (self._background[i], self._edge[i]):
                    times.append(self.emission_time_s + 2 * r / self.c1)
                    masses.append(w * self._shadow(p0, xy, contacts))
                if len(contacts):
                    inz = (ang >= lo) & (ang < hi)
                    for j in range(len(contacts)):
                        m = inz[j] & (pw[j] > 0)
                        if not m.any():
                            continue
                        r = rp[j][m]
                        w = pw[j][m] * self._falloff(r) * np.exp(-2 * mu_t * r)
                        w = w * self._shadow(p0, pts[j][m], contacts, skip=j)
                        times.append(self.emission_time_s + 2 * r / self.c1)
                        masses.append(w)
                t = np.concatenate(times)
                m = np.concatenate(masses) * self.gain_sz[s, z]
                idx = np.floor(t / dt).astype(int)
                ok = (idx >= 0) & (idx < nf)
                fine[s, z] = np.bincount(idx[ok], m[ok], nf)
                fine[s, z] += self.crosstalk_sz[s, z] * xt_shape
        # Instrument response on the fine grid, then sum into bins.
        conv = np.stack([np.convolve(f, irf)[zero : zero + nf] for f in fine.reshape(-1, nf)]).reshape(S, Z, nf)
        binned = conv.reshape(S, Z, B, o.fine).sum(-1)
        return binned + self.ambient_sz[..., None]

    def histograms(self, contacts: np.ndarray, seed: int = 0) -> np.ndarray:
        """One noisy frame per configuration: ``contacts`` (C, N, 3) -> (C, S, Z, B)."""
        rng = np.random.default_rng(seed)
        sat = self.scene.sensor.saturation_counts
        out = [self._noisy(self.expected(c), rng) for c in np.asarray(contacts, float)]
        return np.minimum(np.stack(out), sat)

    def _noisy(self, lam, rng):
        if not self.scene.noise.poisson:
            return lam
        return rng.poisson(np.maximum(lam, 0.0)).astype(float)

    def truth(self) -> dict:
        wg = self.scene.waveguide
        return {
            "simulator": "tests/indep_sim.py",
            "rig_seed": self.seed,
            "n1": wg.n1,
            "mu_s_per_m": wg.mu_s_per_m,
            "mu_a_per_m": wg.mu_a_per_m,
            "emission_time_s": self.emission_time_s,
            "gain_per_zone": self.gain_sz.tolist(),
            "crosstalk_counts": self.crosstalk_sz.tolist(),
            "ambient_counts": self.ambient_sz.tolist(),
            "multiple_scattering": 0.0,
            "options": dataclasses.asdict(self.options),
        }


def simulate(rig: IndepRig, contacts: np.ndarray | None = None, frames: int = 1, seed: int = 0,
             frame_period_s: float = 1.0 / 9.0) -> Capture:
    """A capture of ``frames`` frames of one static configuration (default: the scene's contacts).

    The capture's scene lists the contacts simulated, so ``scene.touches`` is the truth too.
    """
    from tofjax.scene import Touch

    if contacts is None:
        el = rig.scene.contact_elements()
        contacts = el[:, [0, 1, 3]] if len(el) else np.zeros((0, 3))
        scene = rig.scene
    else:
        contacts = np.asarray(contacts, float).reshape(-1, 3)
        r = rig.options.touch_radius_m
        scene = rig.scene.replace(touches=tuple(Touch((float(x), float(y)), r, float(k)) for x, y, k in contacts))
    lam = rig.expected(contacts)
    rng = np.random.default_rng(seed)
    hist = np.minimum(np.stack([rig._noisy(lam, rng) for _ in range(frames)]), rig.scene.sensor.saturation_counts)
    touches = np.broadcast_to(contacts, (frames, *contacts.shape)).copy() if len(contacts) else None
    truth = rig.truth()
    truth["seed"] = seed
    return Capture(
        histograms=hist,
        timestamps=np.arange(frames) * frame_period_s,
        scene=scene,
        source="simulated (tests/indep_sim.py)",
        truth_touches=touches,
        truth=truth,
    )
