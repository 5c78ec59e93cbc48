"""Study: how calibration uncertainty in (n1, mu_s, mu_a) reaches tactile maps and touches.

Calibrates a simulated baseline of the default scene (``tofjax.fit.calibrate``), draws
samples of (n1, mu_s, mu_a) from its Laplace covariance, and maps one simulated frame with
contacts at increasing distance from the sensors that see them once per sample (full
method). Also repeats the propagation with the posterior widened ``widen`` times, the
spread a real device with model error might have. Writes ``invert_uncertainty.json``
(per contact: distance to the nearest sensor that sees it, strength relative std, position
std) and ``invert_uncertainty.png`` (median map and 95% interval width).

    python experiments/study_invert_uncertainty.py --out out/invert_uncertainty
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import tofjax
from tofjax.fit.calibrate import calibrate
from tofjax.invert.pipeline import InvertOptions
from tofjax.invert.synth import simulate_contacts
from tofjax.invert.uncertainty import propagate, samples_from_calibration
from tofjax.scene import load_scene
from tofjax.simulate import simulate

CONTACTS = np.array([[[0.10, 0.06, 1.0], [0.15, 0.15, 1.0], [0.24, 0.22, 1.0], [0.27, 0.27, 1.0]]])


def run(out: Path, frames: int = 100, samples: int = 100, widen: float = 10.0, progress: bool = True) -> dict:
    t0 = time.perf_counter()
    scene = load_scene("optoskin").without_touches()
    base = simulate(scene, frames, 0)
    fit = calibrate(base)
    cal = fit.to_json()
    frame = simulate_contacts(scene, CONTACTS, seed=1)[0]
    rows = {}
    for label, factor in (("calibration", 1.0), (f"calibration x{widen:g}", widen)):
        s = samples_from_calibration(cal, samples, seed=0)
        mean = s.mean(0)
        s = mean + factor * (s - mean)
        s[:, 0] = np.maximum(s[:, 0], 1.0 + 1e-6)
        s[:, 1:] = np.maximum(s[:, 1:], 0.0)
        r = propagate(scene, base.mean(), frame, s, options=InvertOptions(), n_baseline=frames, progress=progress)
        rows[label] = {
            "parameter_std": dict(zip(("n1", "mu_s_per_m", "mu_a_per_m"), s.std(0).tolist())),
            "contacts": sorted(r.contacts, key=lambda c: c["nearest_seeing_sensor_m"]),
            "interval95_width_max": float((r.quantiles[2] - r.quantiles[0]).max()),
        }
        if factor != 1.0:
            _plot(r, out / "invert_uncertainty.png")
    result = {
        "study": "calibration uncertainty -> tactile maps",
        "data": "simulated",
        "frames": frames,
        "samples": samples,
        "calibrated": {
            k: cal["parameters"][k]["value"] for k in ("n1", "mu_s_per_m", "mu_a_per_m") if k in cal["parameters"]
        },
        "stderr": {
            k: cal["parameters"][k]["stderr"] for k in ("n1", "mu_s_per_m", "mu_a_per_m") if k in cal["parameters"]
        },
        "propagation": rows,
        "seconds": time.perf_counter() - t0,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "invert_uncertainty.json").write_text(json.dumps(result, indent=2))
    return result


def _plot(r, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    for ax, img, title in (
        (axes[0], r.quantiles[1], "median map"),
        (axes[1], r.quantiles[2] - r.quantiles[0], "95% interval width"),
    ):
        h = ax.imshow(img, origin="lower", extent=(0, 0.3, 0, 0.3), cmap="magma")
        fig.colorbar(h, ax=ax, shrink=0.8)
        ax.set_title(title)
    fig.suptitle("map uncertainty from (n1, mu_s, mu_a) samples (simulated)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/invert_uncertainty")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--samples", type=int, default=100)
    ap.add_argument("--widen", type=float, default=10.0)
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    r = run(Path(a.out), a.frames, a.samples, a.widen)
    for label, row in r["propagation"].items():
        print(f"{label}: parameter std {row['parameter_std']}")
        for c in row["contacts"]:
            print(
                f"  contact at ({100 * c['x_m']:.1f}, {100 * c['y_m']:.1f}) cm, seen from {100 * c['nearest_seeing_sensor_m']:.0f} cm: "
                f"strength rel. std {100 * c['strength_rel_std']:.2f}%, position std {c['position_std_cm']:.3f} cm"
            )
    print(f"wrote {a.out}/invert_uncertainty.json ({r['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
