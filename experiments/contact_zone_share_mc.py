"""How a near contact's light is shared among a sensor's zones: the guided model against the Monte Carlo (issue 14).

A contact 6 cm from a sensor spans three of its 4.1-degree zones. The model shares its returned light among them by
the disk's area in each zone's wedge (the chord law, ``tofjax.model.components.contact_geometry``); before, it shared
it by the angular width (uniform over angle), which puts ~20% too little in the zone the contact's centre lies in and
too much at the field of view's edge. Here contacts are swept across the field of view of OptoSkin's corner sensor S4
(6 and 10 cm away) and of the edge sensor S5 (6 cm), and each zone's added light (the positive part of touch minus
baseline, summed over bins) and removed light (negative part) are compared, for the chord law, the angular-width
law (the same model with the old share, patched in) and the Monte Carlo (``eval_mc_data.py``'s runs: 16 of 25,000
packets per sensor, cached). Writes JSON. **Simulated**.

    python experiments/contact_zone_share_mc.py --out docs/results/contact_zone_share_mc.json
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: (sensor index, distance m): the sweeps
SWEEPS = ((4, 0.06), (4, 0.10), (5, 0.06))
OFFSETS_DEG = (-22, -18, -15, -12, -8, -4, 0, 4, 8, 12, 15, 18, 22)


@contextmanager
def angular_width_law():
    """The model with the contact shared by angular width (the law before the chord law), in a program of its own."""
    import jax.numpy as jnp

    from tofjax.model import components, forward

    keys = forward._trace_switches
    with mock.patch.object(components, "_semicircle_cdf", lambda x: 0.5 + 0.5 * jnp.clip(x, -1.0, 1.0)), \
            mock.patch.object(forward, "_trace_switches", lambda: keys() + ("angular-width law",)):
        yield


def main(argv=None) -> int:
    sys.path.insert(0, str(ROOT / "experiments"))
    import eval_mc_data as E

    a, path = E.mc_study_cli(__doc__, argv)
    from tofjax.outputs import atomic_write_text
    from tofjax.simulate import expected_counts

    t0 = time.perf_counter()
    scene = E.guided_scene()
    lx, ly = scene.waveguide.size_m
    base_mc = np.mean([E.mc_expected(scene, 25_000, s)[0] for s in range(a.seeds)], 0)
    base_chord = expected_counts(scene, E._own_model_options())
    with angular_width_law():
        base_width = expected_counts(scene, E._own_model_options())
    rows = []
    for si, dist in SWEEPS:
        sp = scene.sensors[si]
        x0, y0 = sp.position_m
        for off in OFFSETS_DEG:
            ang = np.deg2rad(sp.direction_deg + off)
            x, y = x0 + dist * np.cos(ang), y0 + dist * np.sin(ang)
            if not (0.007 < x < lx - 0.007 and 0.007 < y < ly - 0.007):
                continue
            ts = E.touch_scene(scene, np.array([[x, y, 0.9]]))
            mc = np.mean([E.mc_expected(ts, 25_000, s)[0] for s in range(a.seeds)], 0)[si] - base_mc[si]
            chord = expected_counts(ts, E._own_model_options(True))[si] - base_chord[si]
            with angular_width_law():
                width = expected_counts(ts, E._own_model_options(True))[si] - base_width[si]
            row = {"sensor": sp.name, "distance_m": dist, "offset_deg": off, "xy_m": [round(x, 4), round(y, 4)]}
            for name, d in (("monte_carlo", mc), ("chord_law", chord), ("angular_width_law", width)):
                row[f"added_per_zone_{name}"] = np.clip(d, 0, None).sum(-1).round(2).tolist()
                row[f"removed_per_zone_{name}"] = np.clip(d, None, 0).sum(-1).round(2).tolist()
            for name, d in (("chord_law", chord), ("angular_width_law", width)):
                row[f"relative_l2_{name}"] = float(np.linalg.norm(d - mc) / np.linalg.norm(mc))
            rows.append(row)
            print(f"{sp.name} {dist:.2f} m {off:+3d} deg: relative L2 chord {row['relative_l2_chord_law']:.3f}, "
                  f"angular width {row['relative_l2_angular_width_law']:.3f}", flush=True)

    def added_l2(name):  # the zones' added light, all sweeps together
        m = np.concatenate([r["added_per_zone_monte_carlo"] for r in rows])
        return float(np.linalg.norm(np.concatenate([r[f"added_per_zone_{name}"] for r in rows]) - m) / np.linalg.norm(m))

    summary = {name: {"added_light_per_zone_relative_l2": added_l2(name),
                      "touch_change_relative_l2_median": float(np.median([r[f"relative_l2_{name}"] for r in rows]))}
               for name in ("chord_law", "angular_width_law")}
    result = {
        "study": "a near contact's light shared among a sensor's zones: guided model (chord law, angular-width law) "
                 "against the Monte Carlo (issue 14)",
        "data": "simulated: tofjax.mc (validated against adding-doubling and van de Hulst) and tofjax's guided model",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only",
        "scene": "optoskin (guided optics' isotropic scattering), one contact of radius 6 mm, strength 0.9, at 1x",
        "monte_carlo_seeds": a.seeds, "photons_per_sensor_per_seed": 25_000,
        "what": "per zone of the sensor the sweep is about: added = positive part of touch minus baseline summed over "
                "bins, removed = negative part; relative_l2_* over that sensor's whole touch change",
        "summary": summary, "rows": rows, "seconds": time.perf_counter() - t0,
    }
    atomic_write_text(path, json.dumps(result, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
