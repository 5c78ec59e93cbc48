"""Where in time the guided model's baseline departs from the Monte Carlo's (issue 14).

The Monte Carlo baseline of ``eval_mc_data.py`` (OptoSkin with isotropic scattering, 8 seeds x 25,000 packets per
sensor, its transported light: the analytic light entry and ambient taken off) against the guided model's
transported components at the scene's own optics, per sensor: the ratio of their counts summed over zones in eight
consecutive windows of the bins where the model has light (from the first light to the far edge's return and the
tail after it). A ratio that drifts with time is what a calibration reads as attenuation; one far from 1 in the
last window is light the model does not describe there. Writes JSON. **Simulated**.

    python experiments/mc_baseline_time_ratio.py --out docs/results/mc_baseline_time_ratio.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--windows", type=int, default=8)
    a = ap.parse_args(argv)
    if a.windows < 1:
        ap.error("--windows must be >= 1")
    sys.path.insert(0, str(ROOT / "experiments"))
    import numpy as np

    import tofjax

    tofjax.use_fast_cpu_compiler()
    tofjax.enable_x64()
    import eval_mc_data as E

    from tofjax.outputs import atomic_write_text

    sc = E.guided_scene()
    transported, parts = E.mc_baseline_against_guided(sc)
    g = sum(parts.values())
    sensors = []
    for s, sp in enumerate(sc.sensors):
        T, G = transported[s].sum(0), g[s].sum(0)
        lit = np.flatnonzero(G > 1e-3 * G.max())
        sensors.append({"sensor": sp.name,
                        "monte_carlo_share_after_the_models_light": float(T[lit[-1] + 1 :].sum() / T.sum()),
                        "windows": [
            {"bins": [int(w[0]), int(w[-1])], "monte_carlo_over_model": float(T[w].sum() / G[w].sum())}
            for w in np.array_split(lit, a.windows)]})
    out = {"study": "the Monte Carlo baseline's transported light over the guided model's, by time window (issue 14)",
           "data": "simulated: tofjax.mc (8 seeds x 25,000 packets per sensor) and the guided model at the scene's "
                   "own optics",
           "model_components": {k: float(v.sum() / g.sum()) for k, v in parts.items()},
           "sensors": sensors}
    atomic_write_text(Path(a.out), json.dumps(out, indent=1), overwrite=True)
    for r in sensors:
        print(r["sensor"], f"after: {r['monte_carlo_share_after_the_models_light']:.3f}", " ".join(f"{w['bins'][0]}-{w['bins'][1]}:{w['monte_carlo_over_model']:.2f}" for w in r["windows"]))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
