"""Uncertainty of corrected signals and maps from the calibration's uncertainty.

The decay correction ``1/(K G T)`` and the time-to-range map depend on ``n1``, ``mu_s``
and ``mu_a``: ``d log(1/T) / d mu_t = 2 r`` and ``r = c t / (2 n1)``, so a far contact's
corrected strength and position move most when they are uncertain. Given samples of
(n1, mu_s, mu_a) (from the emcee posterior, or drawn from the Laplace covariance of a
calibration JSON), each frame is corrected and mapped once per sample: per-pixel quantiles
of the map and, per detected contact, the spread of its strength and position.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..scene import Scene
from .correction import InversionError, OpticalParams
from .maps import _projection
from .pipeline import InvertOptions, build_inverter

__all__ = ["PARAMETERS", "UncertaintyResult", "propagate", "samples_from_calibration"]

#: The parameters whose uncertainty is propagated.
PARAMETERS = ("n1", "mu_s_per_m", "mu_a_per_m")


def samples_from_calibration(calibration: dict | str | Path, n: int = 200, seed: int = 0) -> np.ndarray:
    """(n, 3) samples of (n1, mu_s, mu_a) from a calibration JSON's Laplace covariance
    (fixed parameters keep their value); clipped to n1 > 1, mu >= 0."""
    data = json.loads(Path(calibration).read_text()) if not isinstance(calibration, dict) else calibration
    try:
        params, labels = data["parameters"], list(data["covariance"]["labels"])
        cov = np.asarray(data["covariance"]["matrix"], float)
    except (KeyError, TypeError) as e:
        raise InversionError(
            f"calibration has no parameters/covariance ({e}): write it with `tofjax calibrate`"
        ) from None
    mean = np.array(
        [
            float(np.ravel(params[k]["value"])[0]) if k in params else float(np.ravel(data["fixed"][k])[0])
            for k in PARAMETERS
        ]
    )
    idx = [labels.index(k) if k in labels else -1 for k in PARAMETERS]
    sub = np.zeros((3, 3))
    for a, i in enumerate(idx):
        for b, j in enumerate(idx):
            if i >= 0 and j >= 0:
                sub[a, b] = cov[i, j]
    rng = np.random.default_rng(seed)
    x = rng.multivariate_normal(mean, sub, size=n, method="eigh")
    x[:, 0] = np.maximum(x[:, 0], 1.0 + 1e-6)
    x[:, 1:] = np.maximum(x[:, 1:], 0.0)
    return x


class _PointGrid:
    """A one-pixel 'grid' at a point, for the projection."""

    def __init__(self, p):
        self._p = np.asarray(p, float).reshape(1, 1, 2)

    def centres(self):
        return self._p


@dataclass
class UncertaintyResult:
    samples: np.ndarray  # (M, 3) n1, mu_s, mu_a
    maps: np.ndarray  # (M, ny, nx) one map per sample (one frame)
    quantiles: np.ndarray  # (3, ny, nx): 2.5%, 50%, 97.5%
    contacts: list[dict]  # per contact of the nominal detection: strength and position spread

    def summary(self) -> list[dict]:
        return self.contacts


def propagate(
    scene: Scene,
    baseline: np.ndarray,
    histogram: np.ndarray,
    samples: np.ndarray,
    optical: OpticalParams | None = None,
    options: InvertOptions = InvertOptions(),
    *,
    n_baseline: int = 1,
    progress: bool = True,
) -> UncertaintyResult:
    """Map one frame (S, Z, B) once per sample of (n1, mu_s, mu_a); returns quantiles and,
    for each contact the nominal parameters detect, the spread of its strength and position
    (the nearest detection in each sample's map)."""
    optical = OpticalParams.from_scene(scene) if optical is None else optical
    samples = np.asarray(samples, float).reshape(-1, 3)
    nominal = build_inverter(scene, baseline, options, optical, n_baseline=n_baseline)
    det0 = nominal.detect(np.asarray(nominal.map_frame(np.asarray(histogram))))
    maps, found = [], []
    for n1, mu_s, mu_a in tqdm(samples, desc="posterior samples", disable=not progress):
        o = optical.replace(n1=float(n1), mu_s_per_m=float(mu_s), mu_a_per_m=float(mu_a))
        inv = build_inverter(scene, baseline, options, o, n_baseline=n_baseline)
        m = np.asarray(inv.map_frame(np.asarray(histogram)))
        maps.append(m)
        found.append(inv.detect(m).touches)
    maps = np.stack(maps)
    contacts = []
    sxy = np.array([s.position_m for s in scene.sensors])
    for t in det0.touches:
        p = np.array([t["x_m"], t["y_m"]])
        zone, _ = _projection(scene, _PointGrid(p), optical, True)
        seen = np.isfinite(zone[0])
        dist = np.hypot(*(sxy - p).T)
        st, pos = [], []
        for touches in found:
            if not touches:
                continue
            q = np.array([[u["x_m"], u["y_m"]] for u in touches])
            k = int(np.argmin(np.hypot(*(q - p).T)))
            if np.hypot(*(q[k] - p)) < 0.03:
                st.append(touches[k]["strength"])
                pos.append(q[k])
        st, pos = np.array(st), np.array(pos).reshape(-1, 2)
        contacts.append(
            {
                "x_m": t["x_m"],
                "y_m": t["y_m"],
                "nearest_seeing_sensor_m": float(dist[seen].min()) if seen.any() else float("nan"),
                "strength": t["strength"],
                "strength_rel_std": float(st.std() / max(abs(st.mean()), 1e-30)) if len(st) > 1 else float("nan"),
                "strength_interval95": [float(x) for x in np.percentile(st, [2.5, 97.5])]
                if len(st)
                else [float("nan")] * 2,
                "position_std_cm": float(100 * np.sqrt(pos.var(0).sum())) if len(pos) > 1 else float("nan"),
                "found_fraction": len(st) / len(samples),
            }
        )
    return UncertaintyResult(samples, maps, np.percentile(maps, [2.5, 50, 97.5], axis=0), contacts)
