"""A contact behind another: how much of its return the nearer one takes, guided model against the Monte Carlo
(issue 14).

A skin contact frustrates light out of the guide wherever it lies, also the light going to and coming back from a
contact further along the same line of sight. The guided model shadowed the far edge and the volume light behind a
contact but let every contact return as if it were alone (``guided.CONTACT_SHADOW`` off); now a contact's return
crosses the others between it and the sensor (``guided._contacts_between``). Here pairs of contacts (radius 6 mm,
strength 0.9) are placed on lines of sight of OptoSkin's corner sensor S4 and edge sensor S5: a near one 5-7 cm
ahead, a far one 4-6 cm behind it, 0-8 mm off the near one's line. For each pair the far contact's return (the
bins where it alone adds light) is taken with and without the near one, ``(both - near) / (far - bare)``, in the
Monte Carlo (``eval_mc_data.py``'s runs: 16 of 25,000 packets per sensor, cached, common random numbers), in the
model, in the model without the crossing (patched off) and in the model with 16 elevation nodes instead of 8 (the
distributed terms then get two nodes instead of one: the far contact's shadow on the volume light falls in the same
bins). Writes JSON. **Simulated**.

    python experiments/contact_behind_contact_mc.py --out docs/results/contact_behind_contact_mc.json
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

#: (sensor index, near distance m, far distance m, lateral offset of the far one m)
PAIRS = ((4, 0.06, 0.10, 0.0), (4, 0.06, 0.10, 0.004), (4, 0.06, 0.10, 0.008), (4, 0.05, 0.11, 0.0),
         (4, 0.07, 0.11, 0.004), (5, 0.06, 0.10, 0.0), (5, 0.05, 0.09, 0.006), (5, 0.07, 0.12, 0.0))


@contextmanager
def without_crossing():
    """The model with every contact returning as if alone (before), in a program of its own."""
    from tofjax.model import guided

    with mock.patch.object(guided, "CONTACT_SHADOW", False):
        yield


def main(argv=None) -> int:
    sys.path.insert(0, str(ROOT / "experiments"))
    import eval_mc_data as E

    a, path = E.mc_study_cli(__doc__, argv)
    from tofjax.outputs import atomic_write_text
    from tofjax.simulate import expected_counts

    t0 = time.perf_counter()
    scene = E.guided_scene()
    base_mc = np.stack([E.mc_expected(scene, 25_000, s)[0] for s in range(a.seeds)])
    base_model = expected_counts(scene, E._own_model_options())  # no contact: the same with or without the crossing

    from tofjax.model import ModelOptions
    from tofjax.model.contact import SkinContact

    fine = ModelOptions(optics="guided", skin=SkinContact(), elevations=16)
    base_fine = expected_counts(scene, ModelOptions(optics="guided", elevations=16))

    def model(ts):
        with_ = expected_counts(ts, E._own_model_options(True))
        with without_crossing():
            before = expected_counts(ts, E._own_model_options(True))
        return with_, before, expected_counts(ts, fine)

    rows = []
    for si, d_near, d_far, lat in PAIRS:
        sp = scene.sensors[si]
        ang = np.deg2rad(sp.direction_deg)
        ux, uy = np.cos(ang), np.sin(ang)

        def at(d, off=0.0):
            return (sp.position_m[0] + d * ux - off * uy, sp.position_m[1] + d * uy + off * ux, 0.9)

        near, far = at(d_near), at(d_far, lat)
        scenes = {"near": [near], "far": [far], "both": [near, far]}
        mc = {k: np.stack([E.mc_expected(E.touch_scene(scene, np.array(v)), 25_000, s)[0][si] for s in range(a.seeds)])
              for k, v in scenes.items()}
        mod = {k: model(E.touch_scene(scene, np.array(v))) for k, v in scenes.items()}
        # the far contact's return: the bins where it alone adds at least a tenth of its peak (the model's)
        tot = (mod["far"][0][si] - base_model[si]).sum(0)
        win = tot > 0.1 * tot.max()
        # per Monte Carlo run (common random numbers), then the mean and its standard error
        runs = 1.0 - (mc["both"] - mc["near"])[..., win].sum((-2, -1)) / (mc["far"] - base_mc[:, si])[..., win].sum((-2, -1))
        lost = {"monte_carlo": float(runs.mean()),
                "monte_carlo_standard_error": float(runs.std(ddof=1) / np.sqrt(len(runs))) if len(runs) > 1 else None}
        for i, name, b in ((0, "model", base_model), (1, "model_without_crossing", base_model),
                           (2, "model_16_elevations", base_fine)):
            lost[name] = float(1.0 - (mod["both"][i][si] - mod["near"][i][si])[..., win].sum()
                               / (mod["far"][i][si] - b[si])[..., win].sum())
        row = {"sensor": sp.name, "near_distance_m": d_near, "far_distance_m": d_far, "far_lateral_offset_m": lat,
               "return_bins": np.flatnonzero(win).tolist(), "share_of_far_return_lost": lost}
        rows.append(row)
        print(f"{sp.name} near {d_near:.2f} far {d_far:.2f} off {lat * 1e3:.0f} mm: lost MC {lost['monte_carlo']:.3f} "
              f"+- {lost['monte_carlo_standard_error'] or 0:.3f}, model {lost['model']:.3f}, "
              f"without crossing {lost['model_without_crossing']:.3f}, 16 elevations {lost['model_16_elevations']:.3f}", flush=True)

    def err(name):
        return [abs(r["share_of_far_return_lost"][name] - r["share_of_far_return_lost"]["monte_carlo"]) for r in rows]

    summary = {name: {"mean_abs_error_of_share_lost": float(np.mean(err(name))), "max_abs_error": float(np.max(err(name)))}
               for name in ("model", "model_without_crossing", "model_16_elevations")}
    summary["monte_carlo_share_lost_range"] = [min(r["share_of_far_return_lost"]["monte_carlo"] for r in rows),
                                               max(r["share_of_far_return_lost"]["monte_carlo"] for r in rows)]
    result = {
        "study": "a contact behind another: the share of its return the nearer one takes, guided model (with and "
                 "without the crossing) against the Monte Carlo (issue 14)",
        "data": "simulated: tofjax.mc (validated against adding-doubling and van de Hulst) and tofjax's guided model",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only",
        "scene": "optoskin (guided optics' isotropic scattering), contacts of radius 6 mm, strength 0.9, at 1x",
        "monte_carlo_seeds": a.seeds, "photons_per_sensor_per_seed": 25_000,
        "what": "share lost = 1 - (both - near) / (far - bare), summed over the sensor's zones and the far contact's "
                "return bins (where it alone adds >= 10% of its peak, from the model)",
        "summary": summary, "rows": rows, "seconds": time.perf_counter() - t0,
    }
    atomic_write_text(path, json.dumps(result, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
