"""The walls' later bounces against their time grid, with and without the field's delay spread (issue 14).

The guided model's reverberant field (``guided._reverb``) is solved per frequency on a coarse grid of at most
``guided.REVERB_NODES`` nodes, each leg's delay put on it like a deposit (a quadratic spline). Without
``guided.REVERB_SPREAD`` every wall-to-wall leg and every ray's view of its wall took its elevations' *mean* delay,
so the only spread in time was the grid's: the field's shape, and the 64x calibration of the Monte Carlo baseline
that leans on it, moved with ``REVERB_NODES``. With it each leg's delay spreads as the guided elevations do (the
variance of ``1 / cos`` over a Lambertian wall's guided emission times ``(r / c1)^2``) and each view's as its return
elevations do. The spread variant includes ``guided.REVERB_DECONVOLVE`` (the grid's own spread taken back out) when
that is on, as it is by default since the twenty-fifth session; this script's JSONs before it are without.

Two parts, both on **simulated** data:

* **the field's shape** (always; seconds): OptoSkin's baseline (the eval's scene), the far edge's term with the
  field minus without it, at 32, 64, 128 and 256 nodes: its relative L2 against the 256-node form and its total;
* **the 64x calibration** (``--calibrate``; about a minute per variant on the 2-core VM): the Monte Carlo baseline of
  ``experiments/eval_mc_data.py`` (its 64 cached runs of 25,000 packets per sensor, 10 frames at 64x exposure, seed
  0: the same capture its calibrations fit) calibrated with each ``SPREAD:NODES`` variant of ``--variants``.

    python experiments/reverb_spread_grid.py --calibrate --out docs/results/reverb_spread_grid.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

NODES = (32, 64, 128, 256)


def field_shape(scene, nodes=NODES) -> dict:
    """The field (far edge with minus without ``EDGE_REVERB``) at each of ``nodes`` (the last the reference), per
    spread setting: its relative L2 against the last node count's and its total."""
    from tofjax.mc.prune import model_breakdown
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.model import guided as G

    model = build_model(scene, ModelOptions(optics="guided", elevations=8), scene.components())
    p = Params.from_scene(scene)
    saved = (G.REVERB_NODES, G.REVERB_SPREAD, G.EDGE_REVERB)
    out = {}
    try:
        G.EDGE_REVERB = False
        without = np.asarray(model_breakdown(model, p)["end"])  # the far edge's first two bounces: no grid
        G.EDGE_REVERB = True
        for spread in (False, True):
            field = {}
            for n in nodes:
                G.REVERB_NODES, G.REVERB_SPREAD = n, spread
                field[n] = np.asarray(model_breakdown(model, p)["end"]) - without
            ref = field[nodes[-1]]
            out["spread" if spread else "no_spread"] = {
                str(n): {"relative_l2_vs_%d_nodes" % nodes[-1]: float(np.linalg.norm(f - ref) / np.linalg.norm(ref)),
                         "total_counts": float(f.sum())} for n, f in field.items()}
    finally:
        G.REVERB_NODES, G.REVERB_SPREAD, G.EDGE_REVERB = saved
    return out


def calibrate_one(spread: bool, nodes: int) -> dict:
    """The eval's 64x Monte Carlo calibration with the field's spread and grid set so (in this process: a fit
    compiled in a process keeps the switches it was traced with, so :func:`calibrations` runs each in its own)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    from tofjax.model import guided as G

    scene, expected, mc_var = ev.calibration_baseline()  # its runs cached by eval_mc_data.py
    G.REVERB_SPREAD, G.REVERB_NODES = spread, nodes
    fig, _ = ev.calibrate_column(scene, expected, mc_var, 10, 0, "guided", "simulated (monte_carlo)")
    return {k: fig.get(k) for k in ("result", "converged", "reduced_chi2_photon_noise", "reduced_chi2_with_mc_variance",
                                    "n1_rel_error", "mu_t_rel_error", "steps", "seconds")}


def calibrations(variants: list[tuple[bool, int]]) -> dict:
    """:func:`calibrate_one` per (spread, nodes) variant, each in a process of its own."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    out = {}
    for spread, nodes in variants:
        key = f"{'spread' if spread else 'no_spread'}_{nodes}_nodes"
        variant = f"{'on' if spread else 'off'}:{nodes}"
        out[key] = ev.run_in_own_process(__file__, ["--out", os.devnull, "--calibrate-one", variant])
        print(key, json.dumps(out[key]), flush=True)
    return out


def _variants(text: str) -> list[tuple[bool, int]]:
    out = []
    for item in text.split(","):
        spread, _, nodes = item.strip().partition(":")
        if spread not in ("on", "off") or not nodes.isdigit() or int(nodes) < 2:
            raise ValueError(f"--variants: expected SPREAD:NODES with SPREAD on or off and NODES >= 2, got {item!r}")
        out.append((spread == "on", int(nodes)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--calibrate", action="store_true", help="also the 64x Monte Carlo calibration per variant")
    ap.add_argument("--variants", default="on:64,on:128,off:32,off:64,off:128",
                    help="calibration variants, SPREAD:NODES comma-separated (default: %(default)s)")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--calibrate-one", metavar="SPREAD:NODES", help=argparse.SUPPRESS)  # one variant; JSON to stdout
    a = ap.parse_args(argv)
    import tofjax
    from tofjax.outputs import OutputError, atomic_write_text, check_output

    if a.calibrate_one:
        tofjax.enable_x64()
        (spread, nodes), = _variants(a.calibrate_one)
        print(json.dumps(calibrate_one(spread, nodes)))
        return 0

    try:
        variants = _variants(a.variants)
        path = check_output(Path(a.out), overwrite=a.overwrite)
    except (ValueError, OutputError) as e:
        ap.exit(2, f"error: {e}\n")
    tofjax.enable_x64()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    t0 = time.perf_counter()
    result = ev.study_header("the guided model's reverberant field against its time grid, with and without its delay "
                             "spread (guided.REVERB_SPREAD)",
                             "simulated (tofjax's guided model; the calibration: tofjax.mc Monte Carlo runs)")
    result["field_shape"] = field_shape(ev.guided_scene())
    if a.calibrate:
        result["calibration_64x_monte_carlo"] = calibrations(variants)
    result["seconds"] = time.perf_counter() - t0
    atomic_write_text(path, json.dumps(result, indent=1))
    print(json.dumps(result["field_shape"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
