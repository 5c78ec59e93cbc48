"""Slab mode: the transport kernel on an infinite slab lit by a pencil beam, with per-face tallies.

The textbook Monte Carlo problem (MCML, Wang, Jacques & Zheng 1995): a slab of index ``n``,
thickness ``d``, scattering ``mu_s``, absorption ``mu_a`` and Henyey-Greenstein anisotropy
``g``, air (n = 1) on both sides, a pencil beam at normal incidence on the top face. Its
answers are known independently: adding-doubling (Prahl's ``iadpython``) gives the total
reflectance and transmittance for any ``n``, albedo, optical thickness and ``g``; van de
Hulst's tables give the classic MCML test case. It runs the *same* kernel as
:func:`tofjax.mc.run_mc` (face folding, Fresnel escape, Henyey-Greenstein scattering,
roulette); only the source and the tallies differ, so it checks the waveguide's physics.

Besides the totals it tallies the time- and radius-resolved diffuse reflectance
``R(rho, t)`` (weight per emitted packet in each ring and time bin), for checks against
diffusion theory (Patterson, Chance & Wilson 1989). It is exact for ``n = 1``; with
``n > 1`` the light leaving one free flight at several top-face hits is put at the first.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass

import numpy as np

from ..config import ConfigError
from ..model.params import speed_in_guide  # c / n, as the transport kernel (and the model) take it
from .transport import LEDGER, _EXTRA, _run_kernel, _Static

__all__ = ["SlabOptions", "SlabResult", "run_slab"]


@dataclass(frozen=True)
class SlabOptions:
    """A slab and the run settings (SI units; all frozen and validated).

    - ``n``, ``thickness_m``, ``mu_s_per_m``, ``mu_a_per_m``, ``g``: the slab (air outside).
    - ``photons``, ``seed``, ``batch``, ``dtype``, ``devices``: as in :class:`tofjax.mc.MCOptions`.
    - ``roulette_weight``, ``roulette_survival``: Russian roulette (MCML: 1e-4 and 0.1).
    - ``max_events``: events of one packet before it is stopped (tallied as ``remaining``).
    - ``rho_bins`` x ``rho_bin_m``, ``time_bins`` x ``time_bin_s``: the grid of ``R(rho, t)``.
    - ``max_path_m``: packets are stopped (``late``) after this path length (default: the
      time grid's window of flight when ``time_bins > 1``, else ``1e4`` thicknesses or mean
      free paths, whichever is longer).
    """

    n: float = 1.4
    thickness_m: float = 0.005
    mu_s_per_m: float = 200.0
    mu_a_per_m: float = 2.0
    g: float = 0.9
    photons: int = 100_000
    seed: int = 0
    batch: int = 32_768
    dtype: str = "float32"
    devices: int | None = None
    roulette_weight: float = 1e-4
    roulette_survival: float = 0.1
    max_events: int = 100_000
    rho_bins: int = 1
    rho_bin_m: float = 1.0
    time_bins: int = 1
    time_bin_s: float = 1e-9
    max_path_m: float | None = None

    def __post_init__(self):
        checks = [
            ("n", self.n >= 1.0, "a refractive index must be >= 1"),
            ("thickness_m", self.thickness_m > 0, "must be > 0"),
            ("mu_s_per_m", self.mu_s_per_m >= 0, "must be >= 0"),
            ("mu_a_per_m", self.mu_a_per_m >= 0, "must be >= 0"),
            ("g", -1.0 < self.g < 1.0, "the Henyey-Greenstein anisotropy must be in (-1, 1)"),
            ("photons", self.photons >= 1, "must be >= 1"),
            ("batch", self.batch >= 1, "must be >= 1"),
            ("dtype", self.dtype in ("float32", "float64"), "must be float32 or float64"),
            ("devices", self.devices is None or self.devices >= 1, "must be >= 1"),
            ("roulette_weight", 0.0 <= self.roulette_weight < 1.0, "must be in [0, 1)"),
            ("roulette_survival", 0.0 < self.roulette_survival <= 1.0, "must be in (0, 1]"),
            ("max_events", self.max_events >= 1, "must be >= 1"),
            ("rho_bins", self.rho_bins >= 1, "must be >= 1"),
            ("rho_bin_m", self.rho_bin_m > 0, "must be > 0"),
            ("time_bins", self.time_bins >= 1, "must be >= 1"),
            ("time_bin_s", self.time_bin_s > 0, "must be > 0"),
            ("max_path_m", self.max_path_m is None or self.max_path_m > 0, "must be > 0"),
        ]
        for name, ok, why in checks:
            if not ok:
                raise ConfigError(f"{name}: {why}, got {getattr(self, name)!r}")

    @property
    def albedo(self) -> float:
        mu_t = self.mu_s_per_m + self.mu_a_per_m
        return self.mu_s_per_m / mu_t if mu_t > 0 else 0.0

    @property
    def optical_thickness(self) -> float:
        return (self.mu_s_per_m + self.mu_a_per_m) * self.thickness_m

    @property
    def specular_reflectance(self) -> float:
        """Fresnel reflectance at normal incidence from air, (n - 1)^2 / (n + 1)^2."""
        return ((self.n - 1.0) / (self.n + 1.0)) ** 2


class _SlabStatic(_Static):
    """The kernel's settings for slab mode (one 'sensor', zones = rings, nodes = time bins)."""

    def __init__(self, o: SlabOptions):
        self.S, self.Z, self.B, self.q = 1, o.rho_bins, o.time_bins, 1
        self.K = o.time_bins
        self.n_contacts = 0
        self.edge_mode = "absorb"
        self.max_events = int(o.max_events)
        self.nee, self.nee_points, self.nee_aperture = False, 1, 1
        self.slab = True
        self.key = (self.S, self.Z, self.K, 0, "absorb", self.max_events, False, 1, 1, True)
        c1 = speed_in_guide(o.n)
        mu_t = o.mu_s_per_m + o.mu_a_per_m
        L_max = o.max_path_m
        if L_max is None and o.time_bins > 1:
            L_max = o.time_bins * o.time_bin_s * c1  # nothing later is tallied
        elif L_max is None:
            L_max = 1e4 * max(o.thickness_m, 1.0 / mu_t if mu_t > 0 else 0.0)
        self.dyn = {
            "lx": 1.0, "ly": 1.0, "d": o.thickness_m, "n1": o.n, "mu_s": o.mu_s_per_m, "mu_a": o.mu_a_per_m,
            "c1": c1, "h": o.time_bin_s, "t_e": 0.0, "L_max": L_max, "fov": 2 * math.pi,
            "sensor_xy": np.zeros((1, 2)), "sensor_dir": np.zeros(1), "sensor_normal": np.array([[0.0, 1.0]]),
            "contacts": np.zeros((0, 3)), "albedo": np.zeros(0), "contact_n": 1.0, "g": o.g,
            "edge_R": 0.0, "half_ap": 0.0, "cos_guided": math.sqrt(max(1.0 - 1.0 / o.n**2, 0.0)),
            "launch_uz": 1.0, "roulette_w": o.roulette_weight, "roulette_p": o.roulette_survival,
            "R_entry": o.specular_reflectance, "rho_bin_m": o.rho_bin_m, "time_bin_s": o.time_bin_s,
        }


@dataclass
class SlabResult:
    """Per emitted photon: where the light went, each with its standard error (``*_se``).

    - ``specular_reflectance``: Fresnel reflection at entry (exact, not transported).
    - ``diffuse_reflectance``: light leaving through the top face, without the specular part.
    - ``total_transmittance``: light leaving through the bottom face (unscattered included).
    - ``absorbed``: absorbed in the slab.
    - ``lost``: stopped late or by ``max_events`` (should be ~0).
    - ``reflectance_rho_t``: (rho_bins, time_bins) diffuse reflectance per ring and time bin.
    """

    diffuse_reflectance: float
    diffuse_reflectance_se: float
    total_transmittance: float
    total_transmittance_se: float
    absorbed: float
    absorbed_se: float
    specular_reflectance: float
    lost: float
    reflectance_rho_t: np.ndarray
    events: int
    seconds: float
    compile_seconds: float
    options: SlabOptions

    @property
    def events_per_second(self) -> float:
        return self.events / max(self.seconds, 1e-12)

    def to_json(self) -> dict:
        keys = ("diffuse_reflectance", "total_transmittance", "absorbed")
        out = {k: getattr(self, k) for k in keys}
        out.update({f"{k}_se": getattr(self, f"{k}_se") for k in keys})
        out.update(specular_reflectance=self.specular_reflectance, lost=self.lost, events=self.events,
                   seconds=self.seconds, compile_seconds=self.compile_seconds,
                   events_per_second=self.events_per_second, options=asdict(self.options),
                   albedo=self.options.albedo, optical_thickness=self.options.optical_thickness)
        return out

    def write_json(self, path) -> None:
        from ..outputs import atomic_write_text  # makes the folder, writes whole or not at all

        atomic_write_text(path, json.dumps(self.to_json(), indent=1))


def run_slab(options: SlabOptions = SlabOptions(), *, progress: bool = False) -> SlabResult:
    """Total reflectance, transmittance and absorption of a slab (pencil beam, normal incidence).

    **Arguments:**

    - ``options``: :class:`SlabOptions` (the slab, photon count, seed).
    - ``progress``: show a progress bar over batches.

    **Returns:** a :class:`SlabResult`; standard errors from the per-packet second moments.
    """
    from .transport import MCOptions

    mo = MCOptions(photons=options.photons, batch=options.batch, seed=options.seed, dtype=options.dtype,
                   devices=options.devices)
    dtype = mo.jnp_dtype
    st = _SlabStatic(options)
    tally, ledger, events, compile_s, t_run, _ = _run_kernel(st, mo, dtype, progress)
    N = options.photons
    lg = dict(zip(LEDGER, ledger[: len(LEDGER)] / N))
    ex = dict(zip(_EXTRA, ledger[len(LEDGER):] / N))
    top = ex["escaped_top"]
    bottom = lg["escaped"] - top

    def se(mean, second):
        return float(math.sqrt(max(second - mean**2, 0.0) / max(N - 1, 1)))

    return SlabResult(
        diffuse_reflectance=float(top), diffuse_reflectance_se=se(top, ex["sq_top"]),
        total_transmittance=float(bottom), total_transmittance_se=se(bottom, ex["sq_bottom"]),
        absorbed=float(lg["absorbed"]), absorbed_se=se(lg["absorbed"], ex["sq_absorbed"]),
        specular_reflectance=options.specular_reflectance, lost=float(lg["late"] + lg["remaining"]),
        reflectance_rho_t=tally.reshape(st.Z, st.K) / N, events=events, seconds=t_run,
        compile_seconds=compile_s, options=options,
    )
