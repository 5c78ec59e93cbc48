"""Which rule stops the opt-in ``MarquardtLM(lambda_trials=...)`` fit of a straggler seed, and
what the Gauss-Newton model and the trials said there (**simulated**: ``tofjax.simulate`` of the
default OptoSkin scene, 100 frames, the fixed start of ``straggler_fits.py``).

Per step of ``solve_marquardt(trace=True)``: damping, gain ratio, predicted and actual decrease
of the chosen trial, accepted, and the Gauss-Newton prediction of what is left; at the end the
stopping rule that fired (small gain of an accepted step, small step, or the model's "nothing
left" with the trials agreeing).

    TOFJAX_PROGRAM_STORE=0 python experiments/straggler_trials_stop.py --seed 2000 --out docs/results/straggler_trials_stop.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=2000)
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--out", default="docs/results/straggler_trials_stop.json")
    a = p.parse_args(argv)
    os.environ.setdefault("TOFJAX_PROGRAM_STORE", "0")
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.flatten_util
    import numpy as np

    from tofjax.fit._start import envelope_candidates, timing_start
    from tofjax.fit.calibrate import Calibrator, _anchor, _data
    from tofjax.fit.solve import solve_marquardt
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    cal = Calibrator(scene)
    pb, cfg = cal.problem, cal.config
    solver = dataclasses.replace(cfg.make_solver(), lambda_trials=(1e-3, 1e-2, 1e-1, 1.0, 10.0))
    base, dtype = cal.base_params(), pb.model.geometry.ray_length.dtype
    d0, s0 = _data(simulate(scene, a.frames, seed=1000), dtype)
    st, found = timing_start(pb, np.asarray(d0), a.frames, scene, base)
    start = envelope_candidates(pb, st, d0, s0, 1)[0]
    anchor = _anchor(st, found, cfg, dtype)
    d, g = _data(simulate(scene, a.frames, seed=a.seed), dtype)
    p0, _, _, _ = pb.profile(start, d, g)
    u0 = pb.pack_jax(p0, pb.nonlinear)
    prior = pb.pack_jax(base, pb.nonlinear)
    prior["n1_anchor"] = anchor
    f0, unravel = jax.flatten_util.ravel_pytree(u0)
    t = time.perf_counter()
    out = jax.device_get(jax.jit(lambda f: solve_marquardt(lambda z, args: pb.residuals(unravel(z), args), solver, f, (p0, d, g, prior),
                                                           max_steps=cfg.max_steps, loss_tol=cfg.loss_tol, trace=True))(f0))
    wall = time.perf_counter() - t
    steps = int(out.steps)
    tr = {k: np.asarray(v)[: steps + 1].tolist() for k, v in out.trace.items() if k != "y"}
    last = steps  # the pass that stopped: trace row `steps` when the stop did not count as a step
    rows = [{k: tr[k][i] for k in tr} for i in range(min(steps + 1, len(tr["lam"])))]
    stop = rows[-1] if np.isfinite(rows[-1]["lam"]) else rows[-2]
    rule = ("model says nothing left, and the best trial gained < loss_tol" if stop["gn_pred"] < cfg.loss_tol and stop["actual"] < cfg.loss_tol
            else "small gain of an accepted step" if stop["accept"] == 1 and stop["actual"] < cfg.loss_tol else "small step or other")
    res = {"what": "the stopping rule of the lambda_trials fit of a straggler seed", "simulated": True,
           "data": f"simulated: tofjax.simulate.simulate(load_scene('optoskin'), {a.frames}, seed={a.seed})",
           "command": "TOFJAX_PROGRAM_STORE=0 python experiments/straggler_trials_stop.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "solver": repr(solver), "loss_tol": cfg.loss_tol, "steps": steps, "result": int(np.asarray(jax.tree_util.tree_leaves(out.result)[0])),
           "first_call_s": wall, "stop_pass": last, "stop_row": stop, "stop_rule": rule,
           "loss_history": np.asarray(out.history)[: steps + 1].tolist(), "trace": rows}
    path = ROOT / a.out if not Path(a.out).is_absolute() else Path(a.out)
    path.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps({k: res[k] for k in ("steps", "result", "stop_row", "stop_rule")}, indent=1))
    print("last rows:", json.dumps(rows[-6:], indent=0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
