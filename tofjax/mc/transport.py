"""Time-resolved Monte Carlo photon transport in the waveguide: the reference for the analytic model.

Photon packets (a weight each) start at a sensor on the edge of the slab and are
followed event by event, all packets of a batch at once (vectorised):

* **Faces.** The slab ``0 <= z <= d`` has air (n = 1) on both faces. Between events a
  packet's polar angle does not change, so its bounces are folded analytically: the
  slab is "unfolded" along z, the number ``k`` of face hits on the way is counted and
  the weight is multiplied by the Fresnel reflectance ``R^k`` (1 under total internal
  reflection), the rest is tallied as *escaped through the faces*. A guided packet
  therefore costs one event per scattering, edge or contact, not one per bounce.
* **Contacts** are disks on the top face (z = d) where the outer index is the
  finger's (``contact_n``): the first top-face hit inside a disk is an event. With
  the Fresnel reflectance for ``n1 -> contact_n`` the packet reflects; otherwise it
  enters the finger and is scattered back into the slab diffusely (Lambertian), its
  weight multiplied by the contact's albedo (its ``strength``, at most 1). Contacts
  thus frustrate total internal reflection, send light back, and shadow what lies
  behind them, with no further assumption.
* **Volume.** Free paths are exponential with ``mu_s``; scattering follows
  Henyey-Greenstein with anisotropy ``g``. Absorption multiplies the weight by
  ``exp(-mu_a s)`` along each path (weight, not survival, so there is no absorption
  noise).
* **Lateral edges** reflect diffusely (Lambertian, a cut edge), specularly, or absorb,
  with reflectance ``edge_reflectance`` (default: the scene's ``end_reflectance``).
* **Detection.** A packet reaching the edge within ``aperture_m / 2`` of its own sensor
  and arriving within the sensor's field of view is detected: its angle of return
  (the direction it came from, relative to the optical axis) picks the zone, its path
  length ``L`` the arrival time ``t_e + L n1 / c``. Detected weight is deposited on a
  grid of ``quadrature`` time nodes per bin and convolved with the scene's pulse
  (exact bin integration, :mod:`tofjax.model.pulse`), as in the analytic model.
* **Emission.** From the sensor's point on the edge, uniformly over the slab's
  thickness, the azimuth uniform over the field of view and ``u_z`` uniform up to the
  beam's elevation half-angle refracted at the edge (``sin(a) / n1``; by default the
  beam is round, ``a = fov / 2``), never beyond the guided band
  ``|u_z| < sqrt(1 - 1/n1^2)`` (light launched into total internal reflection).
* Packets end when detected, when their path exceeds the histogram's time window
  (*late*), or by Russian roulette at low weight (unbiased; off with
  ``roulette_weight = 0``, which makes the weight ledger exact).

Every packet draws its random numbers from a counter-based generator (Threefry-2x32, the one
behind ``jax.random``, written out so that it fuses): its key is ``threefry(seed, (global
index, 0))`` and the numbers of its event ``e`` are ``threefry(key, (e, j))``. The result
depends on the seed and the photon count only, not on the batch size or how many devices
share the work.

Speed (issue 14): lanes step in lock-step with masks and take new packets as theirs end; the
next-event scores of all aperture pieces and elevation nodes are computed at once with lanes
as the contiguous axis and the per-node work shared; every deposit is one windowed scatter;
the conditionals in :func:`_materialise` keep XLA from recomputing per-lane values in every
score; the queue's packets are emitted once per call and gathered by the lanes that free up;
the ledger is kept per lane (no reductions in the loop); in float32 ``cos``/``sin``, ``atan2``
and ``expm1`` are polynomials that XLA vectorises (on the CPU ``jnp.cos`` and ``jnp.sin`` cost
~4 ns per element each, ``exp`` 0.8) and float powers are ``exp(k log R)``. Photons are
sharded over a 1-D device mesh (axis ``"photons"``) with :func:`jax.shard_map`;
each device tallies its packets and the tallies are summed across devices.

Units: SI; weights are fractions of one emitted packet.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ..config import ConfigError
from ..errors import UserError
from ..model.guided import inward_normals
from ..model.params import speed_in_guide
from ..model.pulse import apply_kernels, bin_kernels
from ..scene import Scene
from .contact import SkinContact

__all__ = ["LEDGER", "MCOptions", "MCResult", "fresnel_reflectance", "photon_mesh", "run_mc"]

#: Where the emitted weight ends up (``MCResult.ledger``); they sum to the photons emitted.
LEDGER = ("detected", "escaped", "edge_loss", "absorbed", "contact_loss", "late", "remaining", "roulette")

_EDGES = ("diffuse", "specular", "absorb")

#: Tallies beside the ledger: the top face's share of ``escaped`` and per-packet second moments
#: (top, bottom, absorbed) for standard errors, all per emitted packet.
_EXTRA = ("escaped_top", "sq_top", "sq_bottom", "sq_absorbed")


@dataclass(frozen=True)
class MCOptions:
    """Settings of a Monte Carlo run (all frozen; ``photons`` is the accuracy knob).

    - ``photons``: packets emitted per sensor. Noise falls as ``1/sqrt(photons)``.
    - ``batch``: packets followed at once (memory is ``O(batch)``); rounded up to a
      multiple of the device count. Does not change the result.
    - ``seed``: the same seed and photon count give the same tallies.
    - ``g``: Henyey-Greenstein anisotropy of volume scattering (0 isotropic).
    - ``edges``: lateral edges ``"diffuse"`` (Lambertian), ``"specular"`` or ``"absorb"``.
    - ``edge_reflectance``: reflectance of the lateral edges (default: the scene's
      ``end_reflectance``).
    - ``contact_n``: refractive index of what touches (skin ~1.45).
    - ``contact``: a :class:`~tofjax.mc.contact.SkinContact` (index, absorption, reduced
      scattering, anisotropy and coupling of skin, from the literature): sets the contact's
      index and its diffuse albedo (diffusion theory), and the share of each contact in optical
      contact (``coupling`` x the contact's ``strength``, at most 1; the rest is an air gap). Without it
      (default) ``contact_n`` and ``contact_albedo`` apply, in full optical contact.
    - ``contact_albedo``: diffuse albedo of every contact (default: each contact's
      ``strength``, clipped to 1).
    - ``aperture_m``: width of the receiver window on the edge around each sensor.
    - ``quadrature``: time nodes per bin of the tally grid.
    - ``max_events``: events of one packet before it is stopped (its weight tallied as
      ``remaining``).
    - ``roulette_weight``, ``roulette_survival``: Russian roulette below this weight (0: off).
    - ``counts_per_gain_m2``: counts per unit gain per detected fraction (expected counts
      ``= gain x detected fraction x counts_per_gain_m2``); default ``1 / (aperture x
      thickness)``. The absolute efficiency is a convention: comparisons with the analytic
      model profile the gain, as calibration does.
    - ``launch_elevation_deg``: half-angle (in air) of the emitted beam out of the plane;
      default: the same as in the plane (half the field of view: a round beam). Refracted
      into the guide at the edge and capped at the guided band (90 fills the band).
    - ``nee``: next-event estimation (default on): after every diffuse event (volume
      scattering, a diffuse edge, a contact's diffuse return) the expected direct flight to
      the own sensor's aperture is scored, integrated over elevation with ``nee_points``
      nodes across the guided band (and a quarter as many outside it) and ``nee_aperture``
      pieces of the aperture (the field of view limits the angle of arrival); packets then reach
      the aperture unscored unless their last event was specular. Unbiased up to that
      elevation quadrature and the expected (not sampled) number of frustrating bounces
      under a contact on the direct flight; orders of magnitude less noise per photon.
    - ``dtype``: ``"float32"`` (default, fast) or ``"float64"``.
    - ``devices``: how many devices to shard the photons over (default: all).
    """

    photons: int = 100_000
    batch: int = 32_768
    seed: int = 0
    g: float = 0.0
    edges: str = "diffuse"
    edge_reflectance: float | None = None
    contact_n: float = 1.45
    contact_albedo: float | None = None
    contact: "SkinContact | None" = None
    aperture_m: float = 1e-3
    quadrature: int = 4
    max_events: int = 4000
    roulette_weight: float = 1e-3
    roulette_survival: float = 0.1
    counts_per_gain_m2: float | None = None
    launch_elevation_deg: float | None = None
    nee: bool = True
    nee_points: int = 6
    nee_aperture: int = 4
    dtype: str = "float32"
    devices: int | None = None

    def __post_init__(self):
        if self.photons < 1:
            raise ConfigError(f"photons: must be >= 1, got {self.photons!r}")
        if self.batch < 1:
            raise ConfigError(f"batch: must be >= 1, got {self.batch!r}")
        if not -1.0 < self.g < 1.0:
            raise ConfigError(f"g: the Henyey-Greenstein anisotropy must be in (-1, 1), got {self.g!r}")
        if self.edges not in _EDGES:
            raise ConfigError(f"edges: must be one of {', '.join(_EDGES)}, got {self.edges!r}")
        if self.edge_reflectance is not None and not 0.0 <= self.edge_reflectance <= 1.0:
            raise ConfigError(f"edge_reflectance: must be in [0, 1], got {self.edge_reflectance!r}")
        if not self.contact_n >= 1.0:
            raise ConfigError(f"contact_n: a refractive index must be >= 1, got {self.contact_n!r}")
        if self.contact_albedo is not None and not 0.0 <= self.contact_albedo <= 1.0:
            raise ConfigError(f"contact_albedo: must be in [0, 1], got {self.contact_albedo!r}")
        if self.contact is not None:
            if not isinstance(self.contact, SkinContact):
                raise ConfigError(f"contact: expected a SkinContact, got {type(self.contact).__name__}")
            if self.contact_albedo is not None or self.contact_n != 1.45:
                raise ConfigError("contact_n, contact_albedo: set by the contact model (contact=SkinContact(...)); leave them out")
        if not self.aperture_m > 0:
            raise ConfigError(f"aperture_m: must be > 0, got {self.aperture_m!r}")
        if self.quadrature < 1:
            raise ConfigError(f"quadrature: must be >= 1, got {self.quadrature!r}")
        if self.max_events < 1:
            raise ConfigError(f"max_events: must be >= 1, got {self.max_events!r}")
        if not 0.0 <= self.roulette_weight < 1.0:
            raise ConfigError(f"roulette_weight: must be in [0, 1), got {self.roulette_weight!r}")
        if not 0.0 < self.roulette_survival <= 1.0:
            raise ConfigError(f"roulette_survival: must be in (0, 1], got {self.roulette_survival!r}")
        if self.counts_per_gain_m2 is not None and not self.counts_per_gain_m2 > 0:
            raise ConfigError(f"counts_per_gain_m2: must be > 0, got {self.counts_per_gain_m2!r}")
        if self.launch_elevation_deg is not None and not 0.0 < self.launch_elevation_deg <= 90.0:
            raise ConfigError(f"launch_elevation_deg: must be in (0, 90], got {self.launch_elevation_deg!r}")
        if self.nee_points < 1:
            raise ConfigError(f"nee_points: must be >= 1, got {self.nee_points!r}")
        if self.nee_aperture < 1:
            raise ConfigError(f"nee_aperture: must be >= 1, got {self.nee_aperture!r}")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"dtype: must be float32 or float64, got {self.dtype!r}")
        if self.devices is not None and self.devices < 1:
            raise ConfigError(f"devices: must be >= 1, got {self.devices!r}")

    @property
    def jnp_dtype(self):
        if self.dtype == "float64" and not jax.config.jax_enable_x64:
            raise ConfigError("dtype: float64 requested but JAX runs in 32-bit mode; call tofjax.enable_x64() first")
        return jnp.float64 if self.dtype == "float64" else jnp.float32


@dataclass
class MCResult:
    """A finished Monte Carlo run.

    - ``counts``: (sensors, zones, bins) expected counts of the transported light
      (no light-entry peak, no ambient), scaled to each sensor's gain.
    - ``fraction``: the same per emitted packet (detected fraction per bin).
    - ``nodes``: detected fraction on the time nodes before the pulse, (S, Z, bins x quadrature).
    - ``ledger``: where the emitted weight went, as fractions of the emitted weight
      (keys :data:`LEDGER`; they sum to 1 up to rounding).
    - ``photons``: packets per sensor; ``events``: packet-events processed; ``seconds``: wall time
      (compilation included in ``compile_seconds`` and excluded from ``seconds``).
    """

    counts: np.ndarray
    fraction: np.ndarray
    nodes: np.ndarray
    ledger: dict[str, float]
    photons: int
    events: int
    seconds: float
    compile_seconds: float
    devices: int
    options: MCOptions = field(repr=False)
    moments: dict[str, float] = field(default_factory=dict, repr=False)

    @property
    def events_per_second(self) -> float:
        return self.events / max(self.seconds, 1e-12)


def fresnel_reflectance(n_in, n_out, cos_i):
    """Unpolarised Fresnel reflectance from index ``n_in`` into ``n_out`` at incidence cosine ``cos_i``.

    1 beyond the critical angle (total internal reflection) and at grazing incidence.
    """
    cos_i = jnp.clip(jnp.abs(cos_i), 0.0, 1.0)
    sin_i2 = 1.0 - cos_i**2
    sin_t2 = (n_in / n_out) ** 2 * sin_i2
    tir = sin_t2 >= 1.0
    cos_t = jnp.sqrt(jnp.clip(1.0 - sin_t2, 0.0, 1.0))
    a_s, b_s = n_in * cos_i - n_out * cos_t, n_in * cos_i + n_out * cos_t
    a_p, b_p = n_in * cos_t - n_out * cos_i, n_in * cos_t + n_out * cos_i
    safe = ~tir & (b_s > 0) & (b_p > 0)
    rs = jnp.where(safe, a_s / jnp.where(safe, b_s, 1.0), 1.0) ** 2
    rp = jnp.where(safe, a_p / jnp.where(safe, b_p, 1.0), 1.0) ** 2
    return jnp.where(tir, 1.0, jnp.clip(0.5 * (rs + rp), 0.0, 1.0))


def photon_mesh(devices: int | None = None) -> Mesh:
    """A 1-D mesh over ``devices`` (default: all) with the axis ``"photons"``."""
    devs = jax.devices()
    if devices is not None:
        if devices > len(devs):
            raise ConfigError(f"devices: {devices} requested but JAX sees {len(devs)}")
        devs = devs[:devices]
    return Mesh(np.array(devs), ("photons",))


# ---- the transport kernel ---------------------------------------------------------------


def _hg_cos(g, u):
    """Henyey-Greenstein: cosine of the scattering angle from a uniform ``u``."""
    small = jnp.abs(g) < 1e-4
    gs = jnp.where(small, 0.5, g)
    frac = (1.0 - gs**2) / (1.0 - gs + 2.0 * gs * u)
    c = (1.0 + gs**2 - frac**2) / (2.0 * gs)
    return jnp.clip(jnp.where(small, 2.0 * u - 1.0, c), -1.0, 1.0)


#: use the vectorised float32 ``sin``/``cos`` of a turn (:func:`_cos_sin_turn`; False: ``jnp.cos``/``jnp.sin``)
_FAST_TRIG = True


def _cos_sin_turn(u):
    """``cos(2 pi u), sin(2 pi u)``. In float32 Cephes' ``sinf``/``cosf`` polynomials on
    ``[-pi/4, pi/4]`` after reduction by quarter turns (exact in ``u``; error ~1e-7, float32
    rounding): ``jnp.cos`` and ``jnp.sin`` cost ~4 ns per element each on the CPU, this 1.7 ns for
    both (``docs/results/mc-ops.json``, loaded VM); float64 keeps ``jnp.cos``/``jnp.sin``."""
    if u.dtype != jnp.float32 or not _FAST_TRIG:
        phi = 2.0 * math.pi * u
        return jnp.cos(phi), jnp.sin(phi)
    q = jnp.floor(4.0 * u + 0.5)
    r = (2.0 * math.pi) * (u - 0.25 * q)  # in [-pi/4, pi/4]
    z = r * r
    s = ((-1.9515295891e-4 * z + 8.3321608736e-3) * z - 1.6666654611e-1) * z * r + r
    c = ((2.443315711809948e-5 * z - 1.388731625493765e-3) * z + 4.166664568298827e-2) * z * z - 0.5 * z + 1.0
    qi = q.astype(jnp.int32) & 3  # quarter turns mod 4 (also for negative q)
    cos = jnp.where(qi == 0, c, jnp.where(qi == 1, -s, jnp.where(qi == 2, -c, s)))
    sin = jnp.where(qi == 0, s, jnp.where(qi == 1, c, jnp.where(qi == 2, -s, -c)))
    return cos, sin


def _rotate(ux, uy, uz, cos_t, u_phi):
    """New direction at polar angle acos(cos_t), azimuth ``2 pi u_phi`` about (ux, uy, uz)."""
    sin_t = jnp.sqrt(jnp.clip(1.0 - cos_t**2, 0.0, 1.0))
    cp, sp = _cos_sin_turn(u_phi)
    near_pole = jnp.abs(uz) > 0.99999
    den = jnp.sqrt(jnp.clip(1.0 - uz**2, 1e-20, None))
    nx = sin_t * (ux * uz * cp - uy * sp) / den + ux * cos_t
    ny = sin_t * (uy * uz * cp + ux * sp) / den + uy * cos_t
    nz = -sin_t * cp * den + uz * cos_t
    sign = jnp.sign(uz) + (uz == 0)
    px, py, pz = sin_t * cp, sin_t * sp, sign * cos_t
    nx, ny, nz = jnp.where(near_pole, px, nx), jnp.where(near_pole, py, ny), jnp.where(near_pole, pz, nz)
    norm = jnp.sqrt(nx**2 + ny**2 + nz**2)
    return nx / norm, ny / norm, nz / norm


def _lambertian(nx, ny, nz, tx, ty, tz, u1, u2):
    """Cosine-weighted direction about the unit normal n (t a unit tangent, n x t the other)."""
    cos_t = jnp.sqrt(u1)
    sin_t = jnp.sqrt(1.0 - u1)
    cp, sp = _cos_sin_turn(u2)
    bx, by, bz = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx
    c, s = sin_t * cp, sin_t * sp
    return cos_t * nx + c * tx + s * bx, cos_t * ny + c * ty + s * by, cos_t * nz + c * tz + s * bz


def _launch_uz(opts: "MCOptions", fov_deg: float, n1: float) -> float:
    """Largest |u_z| of launched light: the beam's elevation half-angle in air refracted at the edge,
    never beyond the guided band."""
    guided = math.sqrt(max(1.0 - 1.0 / n1**2, 0.0))
    half = 0.5 * fov_deg if opts.launch_elevation_deg is None else opts.launch_elevation_deg
    return min(math.sin(math.radians(half)) / n1, guided)


class _Static:
    """A run's settings, split into what shapes the program (``key``: hashable, compiled once per
    value) and the physics (``dyn``: arrays passed at run time, so another scene with the same
    shapes reuses the compiled program)."""

    def __init__(self, scene: Scene, opts: MCOptions):
        wg, sm = scene.waveguide, scene.sensor
        self.S, self.Z, self.B = scene.shape
        self.q = opts.quadrature
        self.K = self.B * self.q
        n1 = float(wg.n1)
        c1 = speed_in_guide(n1)
        h = float(sm.bin_width_s) / self.q
        t_e = float(sm.emission_time)
        el = scene.contact_elements()
        strength = np.clip(el[:, 3], 0.0, None)
        if opts.contact is not None:
            # a skin model: its diffuse albedo seen from the guide; a contact's strength scales the
            # share of its area in optical contact (above 1: more than the skin's typical share, up to
            # full optical contact), as the analytic model's guided optics do
            albedo = np.full(len(el), opts.contact.diffuse_albedo(n1))
            coupling = np.minimum(opts.contact.coupling * strength, 1.0)
        else:
            albedo = np.minimum(strength, 1.0) if opts.contact_albedo is None else np.full(len(el), opts.contact_albedo)
            coupling = np.ones(len(el))
        self.n_contacts = len(el)
        self.edge_mode = opts.edges
        self.max_events = int(opts.max_events)
        self.nee = bool(opts.nee)
        self.nee_points = int(opts.nee_points)
        self.nee_aperture = int(opts.nee_aperture)
        self.slab = False
        self.key = (self.S, self.Z, self.K, self.n_contacts, self.edge_mode, self.max_events, self.nee, self.nee_points, self.nee_aperture, self.slab)
        self.dyn = {
            "lx": wg.size_m[0], "ly": wg.size_m[1], "d": wg.thickness_m, "n1": n1,
            "mu_s": wg.mu_s_per_m, "mu_a": wg.mu_a_per_m, "c1": c1, "h": h, "t_e": t_e,
            # packets later than the window (plus two nodes of B-spline support) are stopped
            "L_max": max((self.B * sm.bin_width_s + 2 * h - t_e) * c1, 0.0),
            "fov": math.radians(sm.fov_deg),
            "sensor_xy": np.array([s.position_m for s in scene.sensors], float),
            "sensor_dir": np.radians([s.direction_deg for s in scene.sensors]),
            "sensor_normal": inward_normals(scene),
            "contacts": el[:, :3].astype(float).reshape(-1, 3),
            "albedo": albedo.astype(float),
            "coupling": coupling.astype(float),
            "contact_n": opts.contact_n if opts.contact is None else opts.contact.n, "g": opts.g,
            "edge_R": float(wg.end_reflectance if opts.edge_reflectance is None else opts.edge_reflectance),
            "half_ap": 0.5 * opts.aperture_m,
            "cos_guided": math.sqrt(max(1.0 - 1.0 / n1**2, 0.0)),  # |u_z| below this is guided
            "launch_uz": _launch_uz(opts, sm.fov_deg, n1),
            "roulette_w": opts.roulette_weight, "roulette_p": opts.roulette_survival,
        }

    def arrays(self, dtype):
        return {k: jnp.asarray(v, dtype) for k, v in self.dyn.items()}


class _View:
    """Attribute access to the static shapes and the traced physics inside the kernel."""

    def __init__(self, st: _Static, ph: dict):
        self.__dict__.update({k: getattr(st, k) for k in ("S", "Z", "K", "n_contacts", "edge_mode", "max_events", "nee", "nee_points", "nee_aperture", "slab")})
        self.__dict__.update(ph)


def _emit(st: _View, idx, u, dtype):
    """Initial packets for global photon indices ``idx`` (sensor = idx mod S), from three uniform
    numbers per packet ``u`` (n, 3)."""
    s = idx % st.S
    if st.slab:
        # pencil beam at normal incidence on the top face; the specular reflection at entry is not
        # transported (tallied by the caller)
        zero = jnp.zeros(idx.shape, dtype)
        return dict(x=zero, y=zero, z=zero + st.d, ux=zero, uy=zero, uz=zero - 1.0, L=zero,
                    w=zero + (1.0 - st.R_entry), s=s, diffuse=jnp.zeros(idx.shape, bool))
    xy = jnp.asarray(st.sensor_xy, dtype)[s]
    az = jnp.asarray(st.sensor_dir, dtype)[s] + (u[:, 0] - 0.5) * st.fov
    uz = (2.0 * u[:, 1] - 1.0) * st.launch_uz
    v = jnp.sqrt(1.0 - uz**2)
    return dict(
        x=xy[:, 0], y=xy[:, 1], z=u[:, 2] * st.d,
        ux=v * jnp.cos(az), uy=v * jnp.sin(az), uz=uz,
        L=jnp.zeros_like(uz), w=jnp.ones_like(uz), s=s, diffuse=jnp.zeros(uz.shape, bool),
    )


def _deposit(tally, st, base, tau, w):
    """Add weights ``w`` at times ``tau`` (same shape) to rows ``base`` of the node grid (quadratic B-spline).

    The reference form (one scatter per B-spline node); the kernel uses :func:`_deposit_rows`."""
    base, tau, w = (jnp.ravel(jnp.broadcast_to(v, jnp.broadcast_shapes(base.shape, tau.shape, w.shape))) for v in (base, tau, w))
    uu = tau / st.h - 0.5
    uu = jnp.where((w != 0) & jnp.isfinite(uu), jnp.clip(uu, -10.0, st.K + 10.0), -10.0)
    centre = jnp.round(uu)
    dd = uu - centre
    ic = centre.astype(jnp.int32)
    for off, wt in ((-1, 0.5 * (0.5 - dd) ** 2), (0, 0.75 - dd**2), (1, 0.5 * (0.5 + dd) ** 2)):
        node = ic + off
        inside = (node >= 0) & (node < st.K)
        tally = tally.at[jnp.where(inside, base + node, 0)].add(jnp.where(inside, w * wt, 0.0))
    return tally


#: columns of padding on each side of a row of the kernel's tally (nodes -2, -1 and K, K + 1: dropped)
_PAD = 2

#: the B-spline weights 0.5 (0.5 - dd)^2, 0.75 - dd^2, 0.5 (0.5 + dd)^2 as polynomials in dd
_BSPLINE = np.array([[0.125, 0.75, 0.125], [-0.5, 0.0, 0.5], [0.5, -1.0, 0.5]])


def _deposit_rows(tally, st, row, tau, w):
    """:func:`_deposit` into the padded tally (flat, rows of K + 2 * _PAD): the same quadratic B-spline,
    its three weights added as one window per deposit (one scatter of ``w.size`` windows, not three
    scatters of ``w.size`` numbers); nodes outside ``[0, K)`` land in the padding. ``row``, ``tau``
    and ``w`` have one shape; no concatenation (it would stop XLA vectorising the fused producer)."""
    row, tau = (jnp.broadcast_to(v, w.shape) for v in (row, tau))
    r = w.ndim  # deposits keep their shape (flattening them costs XLA index arithmetic per element)
    uu = tau * (1.0 / st.h) - 0.5  # (a reciprocal once, not a division per element)
    uu = jnp.where((w != 0) & jnp.isfinite(uu), jnp.clip(uu, -10.0, st.K + 10.0), -10.0)
    centre = jnp.round(uu)
    dd = uu - centre
    ic = centre.astype(jnp.int32)
    in_range = (ic >= 1 - _PAD) & (ic <= st.K + _PAD - 2)
    col = jnp.where(in_range, ic - 1 + _PAD, 0)  # the window holds nodes ic - 1 .. ic + 1
    ww = jnp.where(in_range, w, 0.0)
    cf = jnp.asarray(_BSPLINE, tau.dtype)
    dd = dd[..., None]
    upd = (cf[0] + dd * cf[1] + dd**2 * cf[2]) * ww[..., None]
    idx = (row.astype(jnp.int32) * (st.K + 2 * _PAD) + col)[..., None]
    dn = jax.lax.ScatterDimensionNumbers(update_window_dims=(r,), inserted_window_dims=(), scatter_dims_to_operand_dims=(0,))
    return jax.lax.scatter_add(tally, idx, upd, dn, mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS)


def _nee_nodes(st, M: int, dtype):
    """Quadrature in mu = sin(elevation): M points over the guided band, M/2 over the rest."""
    cg = st.cos_guided
    g = (jnp.arange(M, dtype=dtype) + 0.5) / M * 2.0 - 1.0
    m2 = max(M // 4, 1)
    o = (jnp.arange(m2, dtype=dtype) + 0.5) / m2
    mu = jnp.concatenate([cg * g, cg + (1.0 - cg) * o, -(cg + (1.0 - cg) * o)])
    dmu = jnp.concatenate([jnp.full((M,), 2.0 * cg / M, dtype), jnp.full((2 * m2,), (1.0 - cg) / m2, dtype)])
    return mu, dmu


def _nee(st, x, y, z, sensor, mu, dmu, dtype, offset=0.0, half=None):
    """Direct flight from event points to the own sensor's aperture (next-event estimation).

    For each event (n,) and elevation node (M,): the solid-angle weight ``dphi dmu`` of the
    aperture, the transmission (Fresnel at the faces for non-guided elevations, attenuation
    by mu_s + mu_a, frustration under contacts) and the path length. Returns the outgoing
    directions (n, M, 3) for the phase function, weights (n, M), path (n, M), zone (n,) and
    a mask (n,) of events the sensor can see. ``offset`` and ``half`` select a piece of the
    aperture (its centre along the edge and half-width): the field of view is a condition on
    the angle of arrival, which differs across a wide aperture.
    """
    sn = st.sensor_normal[sensor]
    half = st.half_ap if half is None else half
    sp = st.sensor_xy[sensor] + offset * jnp.stack([-sn[:, 1], sn[:, 0]], -1)  # this piece of the aperture
    dx, dy = sp[:, 0] - x, sp[:, 1] - y
    rho = jnp.sqrt(dx**2 + dy**2)
    ok = rho > 1e-9
    rho_ = jnp.where(ok, rho, 1.0)
    ex, ey = dx / rho_, dy / rho_
    # exact in-plane angle subtended by the aperture (a segment along the edge), facing side only
    tx, ty = -sn[:, 1] * half, sn[:, 0] * half
    ax_, ay_, bx_, by_ = dx + tx, dy + ty, dx - tx, dy - ty
    facing = (ex * sn[:, 0] + ey * sn[:, 1]) < 0
    dphi = jnp.where(facing, jnp.abs(jnp.arctan2(ax_ * by_ - ay_ * bx_, ax_ * bx_ + ay_ * by_)), 0.0)
    rel = jnp.mod(jnp.arctan2(-ey, -ex) - st.sensor_dir[sensor] + math.pi, 2.0 * math.pi) - math.pi
    seen = ok & (jnp.abs(rel) < 0.5 * st.fov)
    zone = jnp.clip(jnp.floor((rel + 0.5 * st.fov) / (st.fov / st.Z)), 0, st.Z - 1).astype(jnp.int32)
    c = jnp.sqrt(jnp.clip(1.0 - mu**2, 1e-12, 1.0))  # (M,)
    path = rho_[:, None] / c[None, :]
    zu = z[:, None] + mu[None, :] * path
    k = jnp.abs(jnp.floor(zu / st.d))
    R = fresnel_reflectance(st.n1, jnp.asarray(1.0, dtype), mu)[None, :]
    T = jnp.where(R >= 1.0, 1.0, R**k) * jnp.exp(-(st.mu_s + st.mu_a) * path)
    if st.n_contacts:
        cxy, crad = st.contacts[:, :2], st.contacts[:, 2]
        px, py = x[:, None] - cxy[None, :, 0], y[:, None] - cxy[None, :, 1]
        b = px * ex[:, None] + py * ey[:, None]
        cc = px**2 + py**2 - crad[None, :] ** 2
        disc = jnp.maximum(b**2 - cc, 0.0)
        t0 = jnp.clip(-b - jnp.sqrt(disc), 0.0, rho_[:, None])
        t1 = jnp.clip(-b + jnp.sqrt(disc), 0.0, rho_[:, None])
        chord = jnp.where(b**2 - cc > 0, t1 - t0, 0.0)  # (n, N) in-plane length under each contact
        hits = chord[:, :, None] * (jnp.abs(mu) / (2.0 * st.d * c))[None, None, :]  # expected top hits
        # a top-face hit under a contact reflects fc Rs + (1 - fc) R_air instead of R_air (already in
        # R^k above): the factor is their ratio (Rs <= R_air: the skin's index is nearer the guide's)
        Rs = fresnel_reflectance(st.n1, st.contact_n, mu)[None, None, :]
        fc = st.coupling[None, :, None]
        Ra = R[:, None, :]
        Rc = jnp.where(Ra > 0, (fc * Rs + (1.0 - fc) * Ra) / jnp.where(Ra > 0, Ra, 1.0), 1.0)
        T = T * jnp.prod(jnp.where(Rc >= 1.0, 1.0, Rc**hits), axis=1)
    weight = (dphi[:, None] * dmu[None, :]) * T
    omega = jnp.stack([c[None, :] * ex[:, None], c[None, :] * ey[:, None], jnp.broadcast_to(mu[None, :], path.shape)], -1)
    return omega, jnp.where(seen[:, None], weight, 0.0), path, zone


#: use the vectorised float32 ``atan2`` below (False: ``jnp.arctan2`` everywhere)
_FAST_ATAN2 = True


def _atan2(y, x):
    """``atan2`` that XLA vectorises: in float32 Cephes' ``atanf`` (range reduction to
    ``|t| <= tan(pi/8)`` and a degree-9 odd polynomial; error ~1e-7, float32 rounding), since
    ``jnp.arctan2`` is a scalar library call per element on the CPU (~24 ns); float64 keeps
    ``jnp.arctan2``."""
    if y.dtype != jnp.float32 or not _FAST_ATAN2:
        return jnp.arctan2(y, x)
    ax, ay = jnp.abs(x), jnp.abs(y)
    swap = ay > ax
    num, den = jnp.where(swap, ax, ay), jnp.where(swap, ay, ax)
    t = num / jnp.where(den > 0, den, 1.0)  # in [0, 1]
    big = t > 0.41421356237309503
    u = jnp.where(big, (t - 1.0) / (t + 1.0), t)
    z = u * u
    r = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1) * z * u + u
    r = jnp.where(big, math.pi / 4 + r, r)
    r = jnp.where(swap, math.pi / 2 - r, r)
    r = jnp.where(x < 0, math.pi - r, r)
    return jnp.where(y < 0, -r, r)


def _wrap(x, period):
    """``x mod period`` in [0, period] as ``x - period floor(x / period)``: ``jnp.mod`` is a scalar
    ``fmod`` call per element on the CPU (~70 ns), this vectorises."""
    return x - period * jnp.floor(x / period)


def _materialise(gate, tree):
    """``tree`` unchanged, computed into buffers before its consumers. ``gate`` is a traced boolean
    that is always True: the conditional is a fusion boundary, so XLA neither recomputes per-lane
    values in every (lane, piece, node) element nor duplicates a long elementwise chain into each
    of its consumers (``optimization_barrier`` does not stop fusion on the CPU)."""
    return jax.lax.cond(gate, lambda t: t, lambda t: jax.tree.map(jnp.zeros_like, t), tree)


def _nee_setup(st, dtype):
    """What next-event estimation needs per elevation node and aperture piece, computed once per
    call (not per event): nodes, ``1 / cos``, log Fresnel reflectance at the faces, the log
    frustration per unit chord under each contact, the aperture pieces' offsets."""
    mu, dmu = _nee_nodes(st, st.nee_points, dtype)
    c = jnp.sqrt(jnp.clip(1.0 - mu**2, 1e-12, 1.0))
    R = fresnel_reflectance(st.n1, jnp.asarray(1.0, dtype), mu)
    q = dict(mu=mu, dmu=dmu, c=c, inv_c=1.0 / c, logR=jnp.where(R >= 1.0, 0.0, jnp.log(jnp.maximum(R, 1e-30))),
             phase_c=jnp.maximum(-mu, 0.0) / math.pi)
    if st.n_contacts:
        # a top-face hit under a contact reflects fc Rs + (1 - fc) R_air instead of R_air: the
        # factor Rc per hit, and hits = chord |mu| / (2 d cos) per unit in-plane chord
        Rs = fresnel_reflectance(st.n1, st.contact_n, mu)[None, :]
        fc = st.coupling[:, None]
        Rc = jnp.where(R > 0, (fc * Rs + (1.0 - fc) * R) / jnp.where(R > 0, R, 1.0), 1.0)
        logRc = jnp.where(Rc >= 1.0, 0.0, jnp.log(jnp.maximum(Rc, 1e-30)))
        q["G"] = logRc * (jnp.abs(mu) / (2.0 * st.d * c))[None, :]  # (contacts, M)
    half = st.half_ap / st.nee_aperture
    q["half"] = half
    q["offset"] = -st.half_ap + (2.0 * jnp.arange(st.nee_aperture, dtype=dtype) + 1.0) * half
    return q


def _nee_scores(st, q, x, y, z, sensor, ux, uy, uz, wnx, wny, w_sc, w_edge, w_c, gate):
    """Next-event scores of every lane (n,) for every aperture piece (P) and elevation node (M) at
    once: the same quantities as :func:`_nee` (the reference, per piece) times the phase function
    of the event, with the per-node work shared (one ``exp`` per element: Fresnel, attenuation and
    contact frustration are summed as logarithms) and no (n, M, 3) direction arrays. Lanes are
    the last axis (contiguous: XLA vectorises over them; broadcasts over pieces and nodes are free).

    ``w_sc``, ``w_edge``, ``w_c``: weight scattered in the volume, diffusely at an edge (or None),
    diffusely back from a contact (or None), per lane; ``gate``: a traced True (see
    :func:`_materialise`). Returns rows, path lengths and scores, each (P, M, n)."""
    snx, sny = st.sensor_normal[:, 0][sensor], st.sensor_normal[:, 1][sensor]  # (n,)
    off = q["offset"][:, None]  # (P, 1); along the edge: (-sny, snx)
    dx = st.sensor_xy[:, 0][sensor] - off * sny - x  # (P, n)
    dy = st.sensor_xy[:, 1][sensor] + off * snx - y
    rho = jnp.sqrt(dx**2 + dy**2)
    ok = rho > 1e-9
    rho_ = jnp.where(ok, rho, 1.0)
    ex, ey = dx / rho_, dy / rho_
    tx, ty = -sny * q["half"], snx * q["half"]
    ax_, ay_, bx_, by_ = dx + tx, dy + ty, dx - tx, dy - ty
    facing = (ex * snx + ey * sny) < 0
    dphi = jnp.where(facing, jnp.abs(_atan2(ax_ * by_ - ay_ * bx_, ax_ * bx_ + ay_ * by_)), 0.0)
    rel = _wrap(_atan2(-ey, -ex) - st.sensor_dir[sensor] + math.pi, 2.0 * math.pi) - math.pi
    seen = ok & (jnp.abs(rel) < 0.5 * st.fov)
    zone = jnp.clip(jnp.floor((rel + 0.5 * st.fov) / (st.fov / st.Z)), 0, st.Z - 1).astype(jnp.int32)
    # materialise the per-lane and per-piece factors: otherwise XLA fuses their computation into
    # every (piece, node, lane) element (P x M times the work)
    sx = ex * ux + ey * uy
    sw = ex * wnx + ey * wny
    dphi = jnp.where(seen, dphi, 0.0)
    row = sensor * st.Z + zone
    ws = [w for w in (w_sc, w_edge, w_c) if w is not None]
    rho_, ex, ey, sx, sw, dphi, row, uz, z, ws = _materialise(gate, (rho_, ex, ey, sx, sw, dphi, row, uz, z, ws))
    w_sc, w_edge, w_c = ws[0], (ws[1] if w_edge is not None else None), (ws[-1] if w_c is not None else None)
    col = lambda v: v[None, :, None]  # noqa: E731  per node: (1, M, 1)
    mu, c = col(q["mu"]), col(q["c"])
    path = rho_[:, None, :] * col(q["inv_c"])  # (P, M, n)
    k = jnp.abs(jnp.floor((z + mu * path) * (1.0 / st.d)))
    expo = k * col(q["logR"]) - (st.mu_s + st.mu_a) * path
    if st.n_contacts:
        cxy, crad = st.contacts[:, :2], st.contacts[:, 2]
        px, py = x - cxy[:, 0:1], y - cxy[:, 1:2]  # (N, n)
        b = px[None] * ex[:, None] + py[None] * ey[:, None]  # (P, N, n)
        cc = (px**2 + py**2 - crad[:, None] ** 2)[None]
        disc = jnp.maximum(b**2 - cc, 0.0)
        t0 = jnp.clip(-b - jnp.sqrt(disc), 0.0, rho_[:, None, :])
        t1 = jnp.clip(-b + jnp.sqrt(disc), 0.0, rho_[:, None, :])
        chord = jnp.where(b**2 - cc > 0, t1 - t0, 0.0)  # in-plane length under each contact
        # a sum of products per contact, fused into the elementwise chain (an einsum is a dot with
        # transposes on the CPU, 1.3x slower end to end with six contacts)
        expo = expo + sum(chord[:, j, None, :] * q["G"][j][None, :, None] for j in range(st.n_contacts))
    base = (dphi[:, None, :] * col(q["dmu"])) * jnp.exp(expo)
    # phase functions: Henyey-Greenstein about the incoming direction, Lambertian about the wall
    cos_in = c * sx[:, None, :] + mu * uz
    t = jnp.maximum(1.0 + st.g**2 - 2.0 * st.g * cos_in, 1e-12)
    w_ev = w_sc * ((1.0 - st.g**2) / (4.0 * math.pi)) / (t * jnp.sqrt(t))
    if w_edge is not None:
        w_ev = w_ev + w_edge * (jnp.maximum(c * sw[:, None, :], 0.0) / math.pi)
    if w_c is not None:
        w_ev = w_ev + w_c * col(q["phase_c"])
    return jnp.broadcast_to(row[:, None, :], path.shape), path, w_ev * base


# ---- counter-based random numbers ---------------------------------------------------------

_THREEFRY_ROT = ((13, 15, 26, 6), (17, 29, 16, 24))


def _threefry2x32(k0, k1, x0, x1):
    """Threefry-2x32 with 20 rounds (Salmon et al. 2011, Random123; the generator behind
    ``jax.random``), written out so that XLA fuses it into one elementwise kernel (``jax.random``
    runs it as a rolled loop on the CPU, five launches per call). Key ``(k0, k1)``, counter
    ``(x0, x1)``: uint32 arrays that broadcast. Returns two uint32 words."""
    k0, k1, x0, x1 = (jnp.asarray(v, jnp.uint32) for v in (k0, k1, x0, x1))
    ks = (k0, k1, k0 ^ k1 ^ jnp.uint32(0x1BD11BDA))
    x0, x1 = x0 + ks[0], x1 + ks[1]
    for i in range(5):
        for r in _THREEFRY_ROT[i % 2]:
            x0 = x0 + x1
            x1 = (x1 << jnp.uint32(r)) | (x1 >> jnp.uint32(32 - r))
            x1 = x1 ^ x0
        x0 = x0 + ks[(i + 1) % 3]
        x1 = x1 + ks[(i + 2) % 3] + jnp.uint32(i + 1)
    return x0, x1


def _uniforms(k0, k1, counter, n_words: int, dtype):
    """``n_words`` uniform numbers in [0, 1) per packet from its key ``(k0, k1)`` (n,) and a counter
    (n,): Threefry of ``(counter, j)``, j = 0, 1, ... Returns (n, n_words)."""
    j = jnp.arange((n_words + 1) // 2, dtype=jnp.uint32)[None, :]
    a, b = _threefry2x32(k0[:, None], k1[:, None], counter[:, None], j)
    bits = jnp.concatenate([a, b], axis=1)[:, :n_words]
    if jnp.dtype(dtype) == jnp.float64:
        return bits.astype(jnp.float64) * (2.0**-32)
    return (bits >> jnp.uint32(8)).astype(jnp.float32) * jnp.float32(2.0**-24)


#: counter of a packet's emission numbers (its events count from 1)
_EMIT_COUNTER = 0xFFFFFFFF


def _expm1(x):
    """``exp(x) - 1`` accurate near 0. In float32 a degree-8 Taylor polynomial for ``|x| < 0.5``
    (truncation < 1e-8 relative) and ``exp(x) - 1`` beyond (relative error < 3e-7 there), since
    ``jnp.expm1`` costs ~4 ns per element on the CPU, this ~1 ns (``docs/results/mc-ops.json``);
    float64 keeps ``jnp.expm1``."""
    if x.dtype != jnp.float32 or not _FAST_TRIG:
        return jnp.expm1(x)
    p = x * (1.0 / 40320.0) + 1.0 / 5040.0
    for c in (1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0):
        p = p * x + c
    return jnp.where(jnp.abs(x) < 0.5, p * x, jnp.exp(x) - 1.0)


def _geometric(n, log_r):
    """``sum_{j<n} r^j`` from ``log r <= 0`` (``n`` terms, 0 for ``n = 0``), stable as ``r -> 1``."""
    near_one = log_r > -1e-6
    lr = jnp.where(near_one, -1.0, log_r)
    ratio = _expm1(n * lr) / _expm1(lr)
    return jnp.where(n > 0, jnp.where(near_one, n, ratio), 0.0)


def _hg_pdf(g, cos_t):
    """Henyey-Greenstein phase function per steradian."""
    return (1.0 - g**2) / (4.0 * math.pi * jnp.maximum(1.0 + g**2 - 2.0 * g * cos_t, 1e-12) ** 1.5)


def _cumsum_lanes(flags):
    """Inclusive cumulative sum (int32) of a boolean lane mask, as two small float32 matrix products
    (exact: counts < 2**24): ``jnp.cumsum`` is a reduce-window on the CPU (4% of a step in XLA's trace)."""
    n = flags.shape[0]
    b = 64
    if n % b or n < 2 * b:
        return jnp.cumsum(flags, dtype=jnp.int32)
    v = flags.astype(jnp.float32).reshape(n // b, b)
    tri = jnp.triu(jnp.ones((b, b), jnp.float32))  # tri[i, j] = 1 for i <= j
    within = jnp.dot(v, tri, precision=jax.lax.Precision.HIGHEST)  # (blocks, b)
    m = n // b
    before = jnp.dot(jnp.triu(jnp.ones((m, m), jnp.float32), 1).T, within[:, -1], precision=jax.lax.Precision.HIGHEST)
    return (within + before[:, None]).reshape(n).astype(jnp.int32)


def _transport(st: _View, idx, valid, seed_key, dtype, lanes: int):
    """Follow a queue of packets to the end, ``lanes`` at a time.

    Lock-step over lanes with masks (one ``while_loop``); a lane whose packet ends takes the
    next packet of the queue in the same step, so no lane idles while packets are waiting
    (a batch's long tail of few live packets costs once per queue, not once per batch).
    Packet ``i`` has the key ``threefry(seed, (i, 0))`` and draws the numbers of its event ``e``
    from ``threefry(key, (e, j))``: the tallies do not depend on the lanes, the queue or the
    batch. ``max_events`` is per packet. ``seed_key``: the seed's two uint32 words.

    Returns (tally (S*Z*K,), ledger (LEDGER + _EXTRA,), events).
    """
    n_q = idx.shape[0]
    lanes = min(lanes, n_q)

    def emit(g):
        k0, k1 = _threefry2x32(seed_key[0], seed_key[1], g.astype(jnp.uint32), 0)
        q = _emit(st, g, _uniforms(k0, k1, jnp.full(g.shape, _EMIT_COUNTER, jnp.uint32), 3, dtype), dtype)
        q.update(key=jnp.stack([k0, k1], -1), ev=jnp.ones(g.shape, jnp.int32))
        return q

    # every packet of the queue emitted at once (once per packet, vectorised); a free lane then
    # gathers its next packet's state instead of emitting all lanes' in every step
    queue = emit(idx)
    p = {k: v[:lanes] for k, v in queue.items()}
    alive = valid[:lanes]
    f = lambda v: jnp.asarray(v, dtype)  # noqa: E731
    d = f(st.d)
    inf = f(jnp.inf)
    sxy = jnp.asarray(st.sensor_xy, dtype)
    sdir = jnp.asarray(st.sensor_dir, dtype)
    has_contacts = st.n_contacts > 0
    if has_contacts:
        cxy = st.contacts[:, :2]
        crad = st.contacts[:, 2]
        calb = st.albedo
    R_air_of = lambda cz: fresnel_reflectance(f(st.n1), f(1.0), cz)  # noqa: E731
    if st.nee:
        nee_q = _nee_setup(st, dtype)
    # the ledger per lane (summed once at the end: no reductions in the loop)
    ledger0 = tuple(jnp.zeros((lanes,), dtype) for _ in range(len(LEDGER) + len(_EXTRA)))
    tally0 = jnp.zeros((st.S * st.Z * (st.K + 2 * _PAD),), dtype)  # padded rows (see _deposit_rows)
    acc0 = tuple(jnp.zeros((lanes,), dtype) for _ in range(3))  # per packet: escaped top, escaped bottom, absorbed

    def body(carry):
        nxt, p, alive, tally, ledger, events, acc = carry
        # one random number per decision: 0 free path, 1-2 scattering, 3-4 diffuse direction,
        # 5 contact mirror or not, 6 roulette (never share one between two decisions)
        u = _uniforms(p["key"][:, 0], p["key"][:, 1], p["ev"].astype(jnp.uint32), 7, dtype)
        x, y, z, ux, uy, uz, L, w = (p[k] for k in ("x", "y", "z", "ux", "uy", "uz", "L", "w"))
        az_ = jnp.maximum(jnp.abs(uz), f(1e-12))
        # --- candidate distances ---
        scatters = st.mu_s > 0
        s_scat = jnp.where(scatters, -jnp.log(1.0 - u[:, 0]) / jnp.where(scatters, st.mu_s, 1.0), inf)
        tx = jnp.where(ux > 1e-12, (st.lx - x) / jnp.where(ux > 1e-12, ux, 1.0),
                       jnp.where(ux < -1e-12, -x / jnp.where(ux < -1e-12, ux, 1.0), inf))
        ty = jnp.where(uy > 1e-12, (st.ly - y) / jnp.where(uy > 1e-12, uy, 1.0),
                       jnp.where(uy < -1e-12, -y / jnp.where(uy < -1e-12, uy, 1.0), inf))
        s_edge = jnp.maximum(jnp.minimum(tx, ty), 0.0) if not st.slab else jnp.full_like(x, inf)  # a slab has no edges
        hit_x = tx <= ty
        s_late = jnp.maximum(st.L_max - L, 0.0)
        if has_contacts:
            # first top-face hit inside any contact disk
            s0 = jnp.where(uz > 0, (d - z) / az_, (z + d) / az_)
            delta = 2.0 * d / az_
            dx, dy = x[:, None] - cxy[None, :, 0], y[:, None] - cxy[None, :, 1]
            a = (ux**2 + uy**2)[:, None]
            b = 2.0 * (dx * ux[:, None] + dy * uy[:, None])
            cc = dx**2 + dy**2 - crad[None, :] ** 2
            disc = b**2 - 4.0 * a * cc
            vertical = a < 1e-14
            sq = jnp.sqrt(jnp.maximum(disc, 0.0))
            a_ = jnp.where(vertical, 1.0, a)
            sa = jnp.where(vertical, jnp.where(cc <= 0, -inf, inf), (-b - sq) / (2.0 * a_))
            sb = jnp.where(vertical, jnp.where(cc <= 0, inf, -inf), (-b + sq) / (2.0 * a_))
            kc = jnp.maximum(jnp.ceil((jnp.maximum(sa, 0.0) - s0[:, None]) / delta[:, None]), 0.0)
            kc = jnp.where(jnp.isfinite(kc), kc, 0.0)
            s_hit = s0[:, None] + kc * delta[:, None]
            ok = (disc >= 0) | vertical
            s_hit = jnp.where(ok & (s_hit <= sb) & (s_hit >= 0), s_hit, inf)
            j = jnp.argmin(s_hit, axis=1)
            s_cont = jnp.take_along_axis(s_hit, j[:, None], 1)[:, 0]
            k_cont = jnp.take_along_axis(kc, j[:, None], 1)[:, 0]
        else:
            s_cont = jnp.full_like(x, inf)
        cand = jnp.stack([s_late, s_scat, s_edge, s_cont], 1)
        kind = jnp.argmin(cand, axis=1)  # 0 late, 1 scatter, 2 edge, 3 contact
        s = jnp.min(cand, axis=1)
        s = jnp.where(jnp.isfinite(s), s, 0.0)
        # --- move, folding face bounces ---
        nx_, ny_ = x + ux * s, y + uy * s
        if not st.slab:
            nx_, ny_ = jnp.clip(nx_, 0.0, st.lx), jnp.clip(ny_, 0.0, st.ly)
        zu = z + uz * s
        k_faces = jnp.abs(jnp.floor(zu / d))
        m = _wrap(zu, 2.0 * d)
        flip = m > d
        nz_ = jnp.clip(jnp.where(flip, 2.0 * d - m, m), 0.0, d)
        nuz = jnp.where(flip, -uz, uz)  # an odd number of face hits reverses u_z
        is_cont = kind == 3
        if has_contacts:
            k_faces = jnp.where(is_cont, 2.0 * k_cont + (uz < 0), k_faces)
            nz_ = jnp.where(is_cont, d, nz_)
            nuz = jnp.where(is_cont, az_, nuz)
        R_air = R_air_of(uz)
        # R^k as exp(k log R): a float power costs ~8 ns per element on the CPU, this ~2.4
        keep = jnp.where((R_air >= 1.0) | (k_faces == 0), 1.0, jnp.exp(k_faces * jnp.log(R_air)))  # R = 0: log -inf, exp 0
        att = jnp.exp(-st.mu_a * s)
        w_new = w * att * keep
        # what escapes at the i-th face hit is attenuated up to that face, not over the whole step:
        # w (1 - R) exp(-mu_a s_i) R^i with s_i = s0 + i d / |u_z|; faces alternate, so the top and
        # bottom shares are two geometric series in q = R exp(-mu_a d / |u_z|)
        s0 = jnp.where(uz > 0, d - z, z) / az_
        e0 = jnp.exp(-st.mu_a * s0)
        lq = jnp.log(jnp.maximum(R_air, 1e-30)) - st.mu_a * d / az_
        n_first, n_second = jnp.ceil(0.5 * k_faces), jnp.floor(0.5 * k_faces)
        e_first = (1.0 - R_air) * e0 * _geometric(n_first, 2.0 * lq)
        e_second = (1.0 - R_air) * e0 * jnp.exp(lq) * _geometric(n_second, 2.0 * lq)
        esc_ok = (R_air < 1.0) & (k_faces > 0)
        e_top = jnp.where(esc_ok, w * jnp.where(uz > 0, e_first, e_second), 0.0)
        e_bot = jnp.where(esc_ok, w * jnp.where(uz > 0, e_second, e_first), 0.0)
        escaped = e_top + e_bot
        absorbed = jnp.where(st.mu_a > 0, jnp.maximum(w - w_new - escaped, 0.0), 0.0)  # exactly 0 in a clear guide
        L_new = L + s
        # --- events ---
        # late
        late = alive & (kind == 0)
        # scatter
        sc = alive & (kind == 1)
        ct = _hg_cos(st.g, u[:, 1])
        sx, sy, sz = _rotate(ux, uy, nuz, ct, u[:, 2])
        # edge: detection at the own sensor or reflection
        eg = alive & (kind == 2)
        sp = sxy[p["s"]]
        dist_sensor = jnp.sqrt((nx_ - sp[:, 0]) ** 2 + (ny_ - sp[:, 1]) ** 2)
        back = _atan2(-uy, -ux) - sdir[p["s"]]
        rel = _wrap(back + math.pi, 2.0 * math.pi) - math.pi
        in_fov = jnp.abs(rel) < 0.5 * st.fov
        det = eg & (dist_sensor <= st.half_ap) & in_fov
        refl = eg & ~det
        # inward normal of the wall hit and a tangent along it
        wnx = jnp.where(hit_x, jnp.where(ux > 0, -1.0, 1.0), 0.0)
        wny = jnp.where(hit_x, 0.0, jnp.where(uy > 0, -1.0, 1.0))
        if st.edge_mode == "specular":
            ex, ey, ez = jnp.where(hit_x, -ux, ux), jnp.where(hit_x, uy, -uy), nuz
            edge_R = st.edge_R
        elif st.edge_mode == "diffuse":
            ex, ey, ez = _lambertian(wnx, wny, 0.0 * wnx, -wny, wnx, 0.0 * wnx, u[:, 3], u[:, 4])
            edge_R = st.edge_R
        else:
            ex, ey, ez = ux, uy, nuz
            edge_R = 0.0
        # tally detections: zone by angle of return, time on the node grid (quadratic B-spline)
        # (with next-event estimation, a packet whose last event was diffuse was already scored)
        zone = jnp.clip(jnp.floor((rel + 0.5 * st.fov) / (st.fov / st.Z)), 0, st.Z - 1).astype(jnp.int32)
        wd = jnp.where(det, w_new, 0.0)
        score = wd if not st.nee else jnp.where(p["diffuse"], 0.0, wd)
        tally = _deposit_rows(tally, st, p["s"] * st.Z + zone, st.t_e + L_new / st.c1, score)
        # contact: Fresnel into the finger, diffuse return with its albedo
        if has_contacts:
            cn = alive & is_cont
            # a share `coupling` of the contact is in optical contact (Fresnel n1 -> skin); the
            # rest is an air gap (Fresnel n1 -> air: what it transmits escapes). Weights carry the
            # gap's escape; one number picks mirror or skin among the rest.
            fc = st.coupling[j]
            Rs = fresnel_reflectance(f(st.n1), f(st.contact_n), az_)
            Ra = R_air_of(az_)
            kept_c = fc + (1.0 - fc) * Ra
            Rc = (fc * Rs + (1.0 - fc) * Ra) / kept_c  # mirror probability among what is not lost to the gap
            gap_escape = jnp.where(alive & is_cont, w_new * (1.0 - kept_c), 0.0)
            w_new = jnp.where(is_cont, w_new * kept_c, w_new)
            mirror = u[:, 5] < Rc
            alb = calb[j]
            lx_, ly_, lz_ = _lambertian(0.0 * x, 0.0 * x, -jnp.ones_like(x), jnp.ones_like(x), 0.0 * x, 0.0 * x, u[:, 3], u[:, 4])
            into = cn & ~mirror
            c_ux, c_uy = jnp.where(into, lx_, ux), jnp.where(into, ly_, uy)
            c_uz = jnp.where(into, lz_, -az_)
            c_w = jnp.where(into, w_new * alb, w_new)
            contact_loss = jnp.where(into, w_new * (1.0 - alb), 0.0)
        else:
            cn = jnp.zeros_like(alive)
            c_ux, c_uy, c_uz, c_w, contact_loss = ux, uy, nuz, w_new, jnp.zeros_like(w)
        # --- next-event estimation: expected direct flight to the aperture after each diffuse event ---
        if st.nee:
            # every aperture piece x elevation node of every lane at once (see _nee_scores)
            w_sc = jnp.where(sc, w_new, 0.0)
            w_edge = jnp.where(refl, w_new * edge_R, 0.0) if st.edge_mode == "diffuse" else None
            w_c = jnp.where(cn, w_new * (1.0 - Rc) * alb, 0.0) if has_contacts else None
            row, npath, score_n = _nee_scores(st, nee_q, nx_, ny_, nz_, p["s"], ux, uy, nuz, wnx, wny, w_sc, w_edge, w_c, nxt >= 0)
            L_m = _materialise(nxt >= 0, L_new)  # else XLA recomputes the step in every score
            tau_n, score_n = _materialise(nxt >= 0, (st.t_e + (L_m + npath) * (1.0 / st.c1), score_n))
            tally = _deposit_rows(tally, st, row, tau_n, score_n)
        if st.nee:
            diffuse = jnp.where(sc | (refl & (st.edge_mode == "diffuse")), True, p["diffuse"])
            if has_contacts:
                # a packet that enters the skin comes back diffuse (its direct flight is scored above);
                # one mirrored under the contact keeps its mark: the next-event scores of its last
                # diffuse event already counted that mirror (fc Rs + (1 - fc) R_air per top-face hit)
                diffuse = jnp.where(cn & into, True, diffuse)
            diffuse = jnp.where(refl & (st.edge_mode == "specular"), False, diffuse)
        else:
            diffuse = p["diffuse"]
        # --- new state ---
        nux = jnp.where(sc, sx, jnp.where(refl, ex, jnp.where(cn, c_ux, ux)))
        nuy = jnp.where(sc, sy, jnp.where(refl, ey, jnp.where(cn, c_uy, uy)))
        nuz2 = jnp.where(sc, sz, jnp.where(refl, ez, jnp.where(cn, c_uz, nuz)))
        wn = jnp.where(refl, w_new * edge_R, jnp.where(cn, c_w, w_new))
        edge_loss = jnp.where(refl, w_new * (1.0 - edge_R), 0.0)
        still = alive & ~late & ~det & (wn > 0)
        # Russian roulette (never triggers with roulette_w = 0)
        low = still & (wn < st.roulette_w)
        survive = u[:, 6] < st.roulette_p
        rw = jnp.where(low, jnp.where(survive, wn / st.roulette_p, 0.0), wn)
        roulette = jnp.where(low, wn - rw, 0.0)  # weight removed (negative when survivors gain)
        wn = rw
        still = still & ~(low & ~survive)
        A = lambda v: jnp.where(alive, v, 0.0)  # noqa: E731
        if has_contacts:
            escaped, e_top = escaped + gap_escape, e_top + gap_escape
        # (separate arrays: a stacked (12, lanes) update made XLA recompute producers per row)
        stop = still & (p["ev"] >= st.max_events)
        ended = alive & ~(still & ~stop)
        acc = tuple(a + A(b) for a, b in zip(acc, (e_top, e_bot, absorbed)))
        sq = [jnp.where(ended, a**2, 0.0) for a in acc]
        ledger = tuple(a + b for a, b in zip(ledger, (
            wd, A(escaped), A(edge_loss), A(absorbed), A(jnp.where(cn, contact_loss, 0.0)),
            jnp.where(late, w_new, 0.0), jnp.where(stop, wn, 0.0), A(roulette), A(e_top), *sq,
        )))
        if st.slab:
            # time- and radius-resolved diffuse reflectance: the step's top-face escape at its first
            # top hit (exact for n = 1, where a packet leaves at its first hit)
            s_t = s0 + jnp.where(uz > 0, 0.0, d / az_)
            rho = jnp.sqrt((x + ux * s_t) ** 2 + (y + uy * s_t) ** 2)
            ir = jnp.floor(rho / st.rho_bin_m).astype(jnp.int32)
            it = jnp.floor((L + s_t) / st.c1 / st.time_bin_s).astype(jnp.int32)
            inside = alive & (e_top > 0) & (ir < st.Z) & (it < st.K) & (it >= 0)
            tally = tally.at[jnp.where(inside, ir * (st.K + 2 * _PAD) + it + _PAD, 0)].add(jnp.where(inside, e_top, 0.0))
        # a packet at its last allowed event stops; its weight is tallied as remaining
        # (tallied above: its weight as remaining; the second moments of packets that ended)
        still = still & ~stop
        acc = tuple(jnp.where(ended, 0.0, a) for a in acc)
        events = events + jnp.sum(alive, dtype=jnp.int32)
        p = dict(x=nx_, y=ny_, z=nz_, ux=nux, uy=nuy, uz=nuz2, L=L_new, w=wn, s=p["s"], diffuse=diffuse,
                 key=p["key"], ev=p["ev"] + 1)
        # free lanes take the next packets of the queue
        free = ~still
        pos = nxt + _cumsum_lanes(free) - 1
        take = free & (pos < n_q)
        pos = jnp.minimum(pos, n_q - 1)
        p = {k: jnp.where(take if v.ndim == 1 else take[:, None], queue[k][pos], v) for k, v in p.items()}
        alive = jnp.where(take, valid[pos], still)
        nxt = jnp.minimum(nxt + jnp.sum(free, dtype=jnp.int32), n_q)
        return nxt, p, alive, tally, ledger, events, acc

    def cond(carry):
        nxt, _, alive, *_ = carry
        return jnp.any(alive) | (nxt < n_q)

    nxt, p, alive, tally, ledger, events, acc = jax.lax.while_loop(
        cond, body, (jnp.int32(lanes), p, alive, tally0, ledger0, jnp.zeros((), jnp.int32), acc0)
    )
    return tally.reshape(-1, st.K + 2 * _PAD)[:, _PAD:_PAD + st.K].reshape(-1), jnp.stack([jnp.sum(v) for v in ledger]), events


_COMPILED: dict = {}

#: lanes per queue: (divisor, floor) -> max(queue // divisor, min(queue, floor)); (8, 512) was 1.25x faster
#: than (4, 2048) at 2000 photons per sensor of optoskin (fewer idle lanes in the tail of the walk); (32, 256)
#: (512 lanes for a queue of 16384) 1.1-1.2x faster than (8, 512) and as fast as 256 or 1024 lanes (the
#: step's (piece, node, lane) arrays likely stay in the 1 MiB of L2 cache per core)
_LANES = (32, 256)


def _lanes(q: int) -> int:
    """Lanes for a queue of ``q`` packets (the result does not depend on it, only the speed)."""
    div, floor = _LANES
    return max(q // div, min(q, floor))


def _compiler_options(mesh: Mesh) -> dict | None:
    """XLA's fusion emitters for the transport on a CPU, whatever ``$XLA_FLAGS`` chose for the
    rest (:func:`tofjax.compile_cache.use_fast_cpu_compiler` turns them off: the calibration
    compiles 1.4x faster without them, but this loop of transcendental-heavy kernels runs
    2.2x slower, ``experiments/cpu_emitters.py``)."""
    from ..compile_cache import FUSION_EMITTERS

    if mesh.devices.flat[0].platform != "cpu":
        return None
    return dict(FUSION_EMITTERS)


def _chunk_fn(st: _Static, mesh: Mesh, n_batch: int, per_call: int, dtype, args):
    """Compiled ``shard_map``: (per_call, n_batch) global indices + validity -> summed tallies.

    Cached by the program's shapes, so runs that differ only in physics reuse it.
    Returns (executable, compile seconds: 0 when cached)."""
    cache_key = (st.key, mesh, n_batch, per_call, jnp.dtype(dtype).name, _LANES, _FAST_ATAN2, _FAST_TRIG)
    if cache_key in _COMPILED:
        return _COMPILED[cache_key], 0.0

    def local(idx, valid, seed, ph):
        key = seed  # the seed key's two uint32 words
        view = _View(st, ph)

        # one queue per call: every batch of the call, followed `lanes` at a time
        q = idx.size
        t, l, e = _transport(view, idx.reshape(-1), valid.reshape(-1), key, dtype, _lanes(q))
        return jax.lax.psum(t, "photons"), jax.lax.psum(l, "photons"), jax.lax.psum(e, "photons")

    sm = jax.shard_map(
        local,
        mesh=mesh,
        in_specs=(P(None, "photons"), P(None, "photons"), P(), P()),
        out_specs=(P(), P(), P()),
        check_vma=False,
    )
    t0 = time.perf_counter()
    exe = jax.jit(sm).lower(*args).compile(compiler_options=_compiler_options(mesh))
    _COMPILED[cache_key] = exe
    return exe, time.perf_counter() - t0


def _run_kernel(st: "_Static", options, dtype, progress: bool):
    """Run the compiled transport over all packets (``options.photons`` per sensor) in batches.

    Returns (tally, ledger + extras, events, compile seconds, run seconds, devices)."""
    mesh = photon_mesh(options.devices)
    ndev = mesh.devices.size
    total = options.photons * st.S
    # batch sizes in a few power-of-two buckets (at least 4096), so that runs of different photon
    # counts share one compiled program; unused lanes start dead
    n_batch = min(options.batch, max(4096, 1 << (total - 1).bit_length()))
    n_batch = -(-n_batch // ndev) * ndev
    n_batches = -(-total // n_batch)
    # batches per compiled call (a progress tick each); two values only, so few programs are compiled
    per_call = 8 if n_batches >= 32 else 1
    ph = st.arrays(dtype)
    sharding = NamedSharding(mesh, P(None, "photons"))
    seed = jax.random.key_data(jax.random.key(options.seed))
    tally = np.zeros(st.S * st.Z * st.K)
    ledger = np.zeros(len(LEDGER) + len(_EXTRA))
    events = 0
    compile_s = 0.0
    t_run = 0.0
    from tqdm import tqdm

    calls = range(0, n_batches, per_call)
    for c0 in tqdm(calls, desc="monte carlo", unit="call", disable=not progress):
        idx = np.arange(c0 * n_batch, (c0 + per_call) * n_batch, dtype=np.int64).reshape(per_call, n_batch)
        valid = idx < total
        idx = np.where(valid, idx, 0).astype(np.int32)
        args = (jax.device_put(idx, sharding), jax.device_put(valid, sharding), seed, ph)
        if c0 == 0:
            fn, compile_s = _chunk_fn(st, mesh, n_batch, per_call, dtype, args)
        t0 = time.perf_counter()
        t, lg, ev = jax.block_until_ready(fn(*args))
        t_run += time.perf_counter() - t0
        tally += np.asarray(t, np.float64)
        ledger += np.asarray(lg, np.float64)
        events += int(ev)
    return tally, ledger, events, compile_s, t_run, ndev


def run_mc(scene: Scene, options: MCOptions = MCOptions(), *, progress: bool = False) -> MCResult:
    """Monte Carlo expected histograms of ``scene`` (transported light only).

    **Arguments:**

    - ``scene``: the scene (waveguide, sensors, contacts, pulse, gain).
    - ``options``: :class:`MCOptions` (photon count, seed, physics switches).
    - ``progress``: show a progress bar over batches.

    **Returns:** an :class:`MCResult`. The same seed and photon count give the same
    tallies on any number of devices and any batch size (to float rounding).
    """
    if not isinstance(scene, Scene):
        raise UserError(f"scene: expected a Scene, got {type(scene).__name__}")
    dtype = options.jnp_dtype
    st = _Static(scene, options)
    tally, ledger, events, compile_s, t_run, ndev = _run_kernel(st, options, dtype, progress)
    total = options.photons * st.S
    nodes = tally.reshape(st.S, st.Z, st.K) / options.photons
    kernels = bin_kernels(st.dyn["h"], st.B, st.q, jnp.asarray(scene.sensor.pulse_sigma_s, dtype),
                          jnp.asarray(scene.sensor.pulse_tail_s, dtype), dtype)
    fraction = np.asarray(apply_kernels(jnp.asarray(nodes, dtype), kernels, st.B, st.q), np.float64)
    scale = options.counts_per_gain_m2
    if scale is None:
        scale = 1.0 / (options.aperture_m * scene.waveguide.thickness_m)
    counts = scene.gains()[:, None, None] * fraction * scale
    return MCResult(
        counts=counts,
        fraction=fraction,
        nodes=nodes,
        ledger={k: float(v) / total for k, v in zip(LEDGER, ledger)},
        moments={k: float(v) / total for k, v in zip(_EXTRA, ledger[len(LEDGER):])},
        photons=options.photons,
        events=events,
        seconds=t_run,
        compile_seconds=compile_s,
        devices=ndev,
        options=options,
    )
