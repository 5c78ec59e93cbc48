"""Study: what one skin contact does to the histograms, Monte Carlo against the guided model (issue 14).

One contact (radius 6 mm, strength 1, the skin contact model) at the centre of the OptoSkin guide
(isotropic scattering, as ``experiments/eval_mc_data.py``). For each of two seeds the Monte Carlo's
touch run minus its no-touch run of the same seed (common random numbers: the difference is what the
contact does plus the Monte Carlo noise of the packets that met it), at two photon counts; the guided
model's touch minus no-touch. Reported per (sensor, zone): the summed change, Monte Carlo (each seed,
their mean) and guided, for the zones where either moves by more than 20 counts, and totals (added,
removed). Monte Carlo runs are cached under ``out/mc_cache/`` (as eval_mc_data). All data **simulated**.

    python experiments/mc_contact_sign.py --out out/mc_contact_sign
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def run(out: Path, photons=(25_000, 200_000), xy=(0.15, 0.15), overwrite: bool = False) -> dict:
    import eval_mc_data as E

    from tofjax.outputs import atomic_write_text, check_output
    from tofjax.simulate import expected_counts

    path = check_output(out / "mc_contact_sign.json", overwrite=overwrite)
    t0 = time.perf_counter()
    sc = E.guided_scene()
    ts = E.touch_scene(sc, np.array([[xy[0], xy[1], 1.0]]))
    dg = expected_counts(ts, E._own_model_options(True)) - expected_counts(sc, E._own_model_options())
    res = {
        "study": "one skin contact: Monte Carlo against the guided model (issue 14)",
        "data": "simulated (tofjax.mc and tofjax's guided optics with the skin contact model)",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, CPU only, shared with other sessions (loaded)",
        "contact": {"xy_m": list(xy), "radius_m": 0.006, "strength": 1.0},
        "guided": {"added": float(dg.clip(0).sum()), "removed": float(dg.clip(None, 0).sum())},
        "monte_carlo": [],
    }
    for n in photons:
        d = [E.mc_expected(ts, n, s)[0] - E.mc_expected(sc, n, s)[0] for s in (0, 1)]
        m = (d[0] + d[1]) / 2
        zs = [x.sum(-1) for x in (d[0], d[1], m, dg)]
        rows = [
            {
                "sensor": int(s),
                "zone": int(z),
                "mc_seed0": float(zs[0][s, z]),
                "mc_seed1": float(zs[1][s, z]),
                "mc_mean": float(zs[2][s, z]),
                "guided": float(zs[3][s, z]),
            }
            for s, z in zip(*np.nonzero((np.abs(zs[2]) > 20) | (np.abs(zs[3]) > 20)))
        ]
        res["monte_carlo"].append(
            {
                "photons_per_sensor_per_seed": n,
                "added_per_seed": [float(x.clip(0).sum()) for x in d],
                "removed_per_seed": [float(x.clip(None, 0).sum()) for x in d],
                "net_per_seed": [float(x.sum()) for x in d],
                "seed_correlation": float(np.corrcoef(d[0].ravel(), d[1].ravel())[0, 1]),
                "correlation_mean_vs_guided": float(np.corrcoef(m.ravel(), dg.ravel())[0, 1]),
                "zones": rows,
            }
        )
    res["seconds"] = time.perf_counter() - t0
    atomic_write_text(path, json.dumps(res, indent=1))
    return res


def main(argv=None):
    import tofjax

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/mc_contact_sign")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    r = run(Path(a.out), overwrite=a.overwrite)
    print(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
