"""Is the Monte Carlo baseline's late light what biases its calibration? An oracle (issue 14).

Before the guided model had the walls' later bounces (``tofjax.model.guided.EDGE_REVERB``), its calibration of the
Monte Carlo baseline at 64x (``eval_mc_data.py``'s: 8 seeds of 25,000 packets per sensor, 10 photon-noise frames)
was refused with mu_s + mu_a ~32% high. Here that model (``EDGE_REVERB = False``) calibrates the same baseline twice:
as it is, and with the light it lacks after each zone's far-edge peak taken out (the Monte Carlo's transported light
minus the model's at the scene's own optics, where positive, from ``--after`` bins past the peak on). If the second
calibration is right, the late light is the cause. An oracle: it uses the truth, so it is evidence, not a method.
Writes JSON. **Simulated**.

    python experiments/calib_mc_late_light_oracle.py --out docs/results/calib_mc_late_light_oracle.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--exposure", type=float, default=64.0)
    ap.add_argument("--after", type=int, default=2, help="bins past each zone's far-edge peak where the oracle starts")
    a = ap.parse_args(argv)
    if not a.exposure > 0 or a.after < 0:
        ap.error("--exposure > 0 and --after >= 0")
    sys.path.insert(0, str(ROOT / "experiments"))
    import numpy as np

    import tofjax

    tofjax.use_fast_cpu_compiler()
    tofjax.enable_x64()
    import eval_mc_data as E

    from tofjax.fit import Calibrator, FitConfig
    from tofjax.model import guided
    from tofjax.outputs import atomic_write_text

    saved = guided.EDGE_REVERB
    guided.EDGE_REVERB = False  # the model as it was (restored below)
    try:
        scene = E.guided_scene()
        wg = scene.waveguide
        mc = E.mc_baseline_mean(scene)
        transported, parts = E.mc_baseline_against_guided(scene)
        model = sum(parts.values())
        k = np.arange(mc.shape[-1])
        late = k >= parts["end"].argmax(-1)[..., None] + a.after
        lacking = np.where(late, np.maximum(transported - model, 0.0), 0.0)
        rows = []
        for name, base in (("as it is", mc), ("late light taken out", mc - lacking)):
            cap = E._capture(scene, a.exposure * base, 10, 0, "simulated (monte carlo)")
            res = Calibrator(scene, FitConfig(optics="guided")).fit(cap)
            p = res.params
            rows.append({"data": name, "result": res.result, "reduced_chi2": float(res.reduced_chi2),
                         "n1_rel_error": float(p.n1) / wg.n1 - 1,
                         "mu_t_rel_error": float(p.mu_s_per_m + p.mu_a_per_m) / (wg.mu_s_per_m + wg.mu_a_per_m) - 1})
            print(json.dumps(rows[-1]), flush=True)
    finally:
        guided.EDGE_REVERB = saved
    out = {"study": "the Monte Carlo baseline's calibration by the guided model without the walls' later bounces, "
                    "with and without the late light it lacks (an oracle; issue 14)",
           "data": "simulated: tofjax.mc, 8 seeds x 25,000 packets per sensor, 10 photon-noise frames",
           "exposure": a.exposure, "after_peak_bins": a.after, "late_light_share": float(lacking.sum() / transported.sum()),
           "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, CPU only, shared", "rows": rows}
    atomic_write_text(Path(a.out), json.dumps(out, indent=1), overwrite=True)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
