"""Study: spatial generalisation of force estimation (beyond seed 001, section V).

Contacts at a few distances from the sensor train a dual-input MLP; it is tested on
unseen forces at the training distances (seen) and at distances between them (unseen).
Two feature sets:

- ``raw``: the window's counts and the baseline, as seed 001;
- ``corrected``: the baseline-subtracted window multiplied by the decay gain
  ``1 / (G(r) T(r))`` of each bin (``tofjax.force.features.decay_gain``), and the baseline.

The window sits at the contact's bins, taken from the contact's known distance (the
localisation is the touch-inversion issue's job): the forward model's touch signal for
a unit contact there peaks at bin ``p``; the window is ``p - 2 .. p + 2``.

Writes ``spatial.json`` and ``spatial.md``.

    python experiments/study_force_spatial.py --out out/force_spatial
"""

from __future__ import annotations

import argparse
import functools
import json
import platform
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

import tofjax
from tofjax.config import from_dict, load_toml
from tofjax.force.features import FeatureConfig, Window, decay_gain, raw_features, split_indices
from tofjax.force.generate import Protocol, contact_position, generate
from tofjax.force.models import TrainOptions, build_mlp, mlp_spec, train_mlp
from tofjax.model import Params, build_model
from tofjax.scene import Touch


@dataclass(frozen=True)
class SpatialConfig:
    train_distances_m: tuple[float, ...] = (0.08, 0.14, 0.20)
    unseen_distances_m: tuple[float, ...] = (0.11, 0.17)
    velocities_mm_s: tuple[float, ...] = (1.0,)
    repetitions: int = 2
    test_forces_per_velocity: int = 6
    epochs: int = 200
    seed: int = 0


@functools.lru_cache(maxsize=64)
def window_at(scene, sensor: int, distance_m: float, bins: int = 5) -> Window:
    """The ``bins``-bin window centred on the touch peak of a contact ``distance_m`` in front of ``sensor``."""
    xy = contact_position(scene, sensor, distance_m)
    s1 = scene.replace(touches=(Touch(position_m=xy, radius_m=0.008, strength=1.0),))
    touch = np.asarray(build_model(s1).breakdown(Params.from_scene(s1))["touch"])[sensor].sum(0)
    start = int(np.argmax(touch)) - bins // 2
    return Window(sensor, start, bins, scene.sensor.zones, scene.shape)


def features(caps, scene, params, sensor, corrected: bool):
    cfg = FeatureConfig(variant="dual")
    xs, ys = [], []
    for cap in caps:
        w = window_at(scene, sensor, cap.truth["distance_m"])
        raw, valid = raw_features(cap, w, cfg)
        n = w.size
        win, base = raw[:, :n], raw[:, 2 * n :]
        if corrected:
            win = (win - base) * decay_gain(scene, params, w)
        xs.append(np.concatenate([win, base], 1)[valid])
        ys.append(cap.force[valid])
    return np.concatenate(xs), np.concatenate(ys)


def run(cfg: SpatialConfig, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    caps = {}
    for d in sorted(set(cfg.train_distances_m) | set(cfg.unseen_distances_m)):
        p = Protocol(distance_m=d, velocities_mm_s=cfg.velocities_mm_s, repetitions=cfg.repetitions,
                     test_forces_per_velocity=cfg.test_forces_per_velocity, test_captures_per_velocity=1,
                     seed=cfg.seed + int(d * 1000))
        caps[d] = generate(p)
    scene = Protocol().load_scene()
    params = Params.from_scene(scene)
    sensor = Protocol().sensor
    result = {"data": "simulated", "machine": f"{platform.machine()}, {__import__('os').cpu_count()} CPU cores (shared)",
              "config": {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.__dict__.items()}, "mae_n": {}}
    for corrected in (False, True):
        name = "corrected" if corrected else "raw"
        x, y = features([c for d in cfg.train_distances_m for c in caps[d]["train"]], scene, params, sensor, corrected)
        tr, va, _ = split_indices(len(y), (0.9, 0.1, 0.0), cfg.seed)
        lo, hi = x[tr].min(0), x[tr].max(0)
        hi = np.where(hi > lo, hi, lo + 1)
        f_lo, f_span = y[tr].min(), np.ptp(y[tr])

        def X(a):
            return (a - lo) / (hi - lo)

        model = build_mlp(mlp_spec("mlp", "dual", x.shape[1] // 2, dropout=0.0), jax.random.key(cfg.seed))
        res = train_mlp(model, X(x[tr]), (y[tr] - f_lo) / f_span, X(x[va]), (y[va] - f_lo) / f_span,
                        TrainOptions(epochs=cfg.epochs, patience=60), key=jax.random.key(cfg.seed + 1))
        per = {}
        for d in sorted(caps):
            xt, yt = features(caps[d]["test"], scene, params, sensor, corrected)
            pred = np.asarray(jax.vmap(res.model)(X(xt).astype(np.float32))) * f_span + f_lo
            per[f"{d:.3f}"] = float(np.mean(np.abs(pred - yt)))
        seen = [per[f"{d:.3f}"] for d in cfg.train_distances_m]
        unseen = [per[f"{d:.3f}"] for d in cfg.unseen_distances_m]
        result["mae_n"][name] = {"by_distance_m": per, "seen": float(np.mean(seen)), "unseen": float(np.mean(unseen))}
        print(f"{name}: seen {np.mean(seen):.2f} N, unseen {np.mean(unseen):.2f} N  {per}", flush=True)
    (out / "spatial.json").write_text(json.dumps(result, indent=2))
    lines = ["| features | " + " | ".join(f"{float(d) * 1000:.0f} mm{'' if float(d) in cfg.train_distances_m else ' (unseen)'}"
                                         for d in result["mae_n"]["raw"]["by_distance_m"]) + " | seen | unseen |",
             "|---|" + "---|" * (len(caps) + 2)]
    for name, v in result["mae_n"].items():
        lines.append(f"| {name} | " + " | ".join(f"{e:.2f}" for e in v["by_distance_m"].values())
                     + f" | {v['seen']:.2f} | {v['unseen']:.2f} |")
    (out / "spatial.md").write_text("\n".join(lines) + "\n\nMAE in N on unseen forces (simulated).\n")
    print("\n".join(lines))
    return result


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", help="TOML with SpatialConfig keys")
    ap.add_argument("--out", default="out/force_spatial")
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    cfg = from_dict(SpatialConfig, load_toml(a.config)) if a.config else SpatialConfig()
    return run(cfg, Path(a.out))


if __name__ == "__main__":
    main()
