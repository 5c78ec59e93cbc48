"""A contact model of skin: literature optical properties instead of an albedo knob.

Used by the Monte Carlo (``MCOptions(contact=...)``) and by the analytic model's guided optics
(``ModelOptions(optics="guided", skin=...)``); it lives here so the model never imports the Monte Carlo.

A fingertip on the guide is, optically, a turbid half-space (index ``n``, absorption
``mu_a``, reduced scattering ``mu_s'``) touching part of the contact disk: only a share
``coupling`` of the apparent contact area is in optical contact (skin ridges and an air
gap elsewhere). Light that crosses into the skin comes back diffusely with the skin's
diffuse albedo, computed here by diffusion theory for a semi-infinite medium; sources and
the values at 940 nm (the TMF8828's VCSEL) are in docs/monte-carlo.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..config import ConfigError

__all__ = ["SkinContact", "diffuse_reflectance_semi_infinite"]


def _internal_reflection_A(n_rel: float) -> float:
    """Boundary coefficient A = (1 + r_id) / (1 - r_id) for a relative index ``n_inside / n_outside``
    (Groenhuis et al. 1983 empirical r_id, as used by Farrell et al. 1992)."""
    r_id = -1.440 / n_rel**2 + 0.710 / n_rel + 0.668 + 0.0636 * n_rel
    return (1.0 + r_id) / (1.0 - r_id)


def diffuse_reflectance_semi_infinite(mu_a_per_m: float, mu_s_prime_per_m: float, n_rel: float = 1.0) -> float:
    """Total diffuse reflectance of a semi-infinite turbid medium (diffusion theory).

    Farrell, Patterson & Wilson (1992), Med. Phys. 19:879, integrated over the surface:
    ``R_d = a'/2 [1 + exp(-4/3 A sqrt(3 (1 - a')))] exp(-sqrt(3 (1 - a')))`` with the
    transport albedo ``a' = mu_s' / (mu_a + mu_s')`` and ``A`` for the index mismatch
    ``n_rel`` (medium over outside).
    """
    return _diffuse_reflectance(mu_s_prime_per_m / (mu_a_per_m + mu_s_prime_per_m), _internal_reflection_A(n_rel), math.exp)


def _diffuse_reflectance(a: float, A, exp):
    """Farrell's ``R_d`` for transport albedo ``a`` and boundary coefficient ``A`` (a float, or
    traced where the guide's index is fitted: ``exp`` is then ``jnp.exp``)."""
    k = math.sqrt(3.0 * (1.0 - a))
    return 0.5 * a * (1.0 + exp(-4.0 / 3.0 * A * k)) * math.exp(-k)


@dataclass(frozen=True)
class SkinContact:
    """Skin touching the guide (defaults: fingertip skin at 940 nm; see docs/monte-carlo.md).

    - ``n``: refractive index of the skin surface (epidermis ~1.42 in the NIR, Ding et al. 2006).
    - ``mu_a_per_m``: absorption (~0.3 /cm at 940 nm: water, blood, melanin; Bashkatov et al. 2011).
    - ``mu_s_prime_per_m``: reduced scattering, ``46 /cm x (lambda / 500 nm)^-1.421`` (Jacques 2013,
      skin) = 18.7 /cm at 940 nm.
    - ``g``: scattering anisotropy (0.9; Jacques 2013: 0.8-0.95 for soft tissues). Only ``mu_s'``
      enters the diffuse albedo; ``g`` gives ``mu_s = mu_s' / (1 - g)``.
    - ``coupling``: share of the apparent contact area in optical contact (0.3; the real contact
      area of a finger pad is a fraction of the apparent one and grows with force and moisture).
    """

    n: float = 1.42
    mu_a_per_m: float = 30.0
    mu_s_prime_per_m: float = 1870.0
    g: float = 0.9
    coupling: float = 0.3

    def __post_init__(self):
        checks = [("n", self.n >= 1.0, "a refractive index must be >= 1"), ("mu_a_per_m", self.mu_a_per_m >= 0, "must be >= 0"),
                  ("mu_s_prime_per_m", self.mu_s_prime_per_m > 0, "must be > 0"), ("g", -1.0 < self.g < 1.0, "must be in (-1, 1)"),
                  ("coupling", 0.0 <= self.coupling <= 1.0, "must be in [0, 1]")]
        for name, ok, why in checks:
            if not ok:
                raise ConfigError(f"{name}: {why}, got {getattr(self, name)!r}")

    @property
    def mu_s_per_m(self) -> float:
        return self.mu_s_prime_per_m / (1.0 - self.g)

    def diffuse_albedo(self, n_guide: float) -> float:
        """Share of the light entering the skin from the guide that comes back into the guide
        (diffuse reflectance of the skin half-space, its boundary with the guide's index)."""
        return diffuse_reflectance_semi_infinite(self.mu_a_per_m, self.mu_s_prime_per_m, self.n / n_guide)

    def diffuse_albedo_jax(self, n_guide):
        """:meth:`diffuse_albedo` for a traced guide index (the analytic model fits ``n1``)."""
        import jax.numpy as jnp

        a = self.mu_s_prime_per_m / (self.mu_a_per_m + self.mu_s_prime_per_m)
        return _diffuse_reflectance(a, _internal_reflection_A(self.n / n_guide), jnp.exp)
