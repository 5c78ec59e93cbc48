"""Where the walls' light of the guided model and of the Monte Carlo part (issue 14): by reflectance and scattering.

The Monte Carlo's wall light is its baseline with diffuse edges less the same runs with absorbing ones (the same
seeds: every path is the same until it meets an edge, so the difference is much less noisy than either). The guided
model's is its ``end`` component. Both at the scene's true optics (``eval_mc_data.guided_scene``, OptoSkin), for each
``mu_s`` of ``--mu-s`` and wall reflectance of ``--reflectance`` (``mu_a`` and everything else the scene's).

Wall light grows with the reflectance ``R`` as the number of diffuse bounces it took, and with ``mu_s`` as the number
of volume scatterings on its way, so the grid separates the orders: the light of one bounce and no scattering
(``R``), one bounce and one scattering (``R mu_s``: the beam's light scattered on to the lit walls, the lit walls'
light scattered back), two bounces and one scattering (``R^2 mu_s``). Per cell:

* ``windows``: the Monte Carlo over the model per sensor, in windows of bins relative to each zone's peak (the
  model's), summed over the zones;
* ``profile``: aligned on each zone's peak and summed over every zone, per bin from 8 before to 30 after, in
  thousandths of the model's total wall light: the Monte Carlo's excess over the model and the model's parts
  (``_edge_scatter``'s kernels, the second bounce, the reverberant field) by switching each off;
* ``corner_zones``: per sensor and zone, the excess in the 6 bins from the peak (where the zones whose footprint
  spans a corner stand out).

Then the orders, in the same thousandths: ``R mu_s`` (the lower reflectance's excess at each ``mu_s`` less at
``mu_s = 0``) and ``R^2 mu_s`` (the difference between the two reflectances' excesses, at ``mu_s`` less at 0,
scaled by ``R_hi / (R_hi - R_lo)`` to the higher reflectance's share of two-bounce light). **Simulated** data only.

    python experiments/wall_light_orders.py --out docs/results/wall_light_orders.json --plot docs/results/wall_light_orders.png

``--guided-switch NAME=VALUE`` sets a module switch of :mod:`tofjax.model.guided` for the run (repeatable), as
``calib_mc_seeds.py`` does.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: bins relative to each zone's peak: the aligned profile's span and the windows of the ratios
SPAN = (-8, 30)
WINDOWS = {"pre": (-6, -1), "peak": (-1, 2), "2..8": (2, 9), "9..15": (9, 16), "16..24": (16, 25), "25..34": (25, 35),
           "all": (-999, 999)}


def _floats(text: str, name: str) -> list[float]:
    try:
        out = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"{name}: expected comma-separated numbers, got {text!r}") from None
    if not out or any(not np.isfinite(v) or v < 0 for v in out):
        raise ValueError(f"{name}: expected non-negative numbers, got {text!r}")
    return sorted(set(out))


def cell(base, mu_s: float, reflectance: float, seeds: int, photons: int) -> dict:
    """One (mu_s, R) cell: the Monte Carlo's wall light against the guided model's ``end`` and its parts."""
    import equinox as eqx

    import eval_mc_data as ev
    import tofjax.model.guided as guided
    from tofjax.model import ModelOptions, Params, build_model

    scene = base.replace(waveguide=dataclasses.replace(base.waveguide, mu_s_per_m=mu_s, end_reflectance=reflectance))
    runs = np.stack([ev.mc_expected(scene, photons, s)[0] - ev.mc_expected(scene, photons, s, edges="absorb")[0]
                     for s in range(seeds)])
    mc, se = runs.mean(0), runs.std(0, ddof=1) / np.sqrt(seeds)
    p = Params.from_scene(scene)

    def end(model):
        return np.asarray(model.breakdown(p)["end"])

    model = build_model(scene, ModelOptions(optics="guided"), scene.components())
    full = end(model)
    parts = {}
    w = model.guided.sc_w
    if w is not None:
        for k in range(w.shape[2]):
            parts[f"scatter_kernel_{k}"] = full - end(eqx.tree_at(lambda m: m.guided.sc_w, model, w.at[:, :, k].set(0.0)))
    for name in ("EDGE_SECOND", "EDGE_REVERB"):
        old = getattr(guided, name)
        setattr(guided, name, False)
        try:
            parts[name.lower()] = full - end(build_model(scene, ModelOptions(optics="guided"), scene.components()))
        finally:
            setattr(guided, name, old)
    S, Z, K = full.shape
    rel = np.arange(K)[None, None] - full.argmax(-1)[..., None]
    total = full.sum()
    windows = {}
    for name, (lo, hi) in WINDOWS.items():
        m = (rel >= lo) & (rel < hi)
        a, b = (mc * m).sum((1, 2)), (full * m).sum((1, 2))
        e = np.sqrt(((se * m) ** 2).sum((1, 2)))
        windows[name] = {"mc_over_model": (a / b).round(4).tolist(), "standard_error": (e / b).round(4).tolist()}
    bins = list(range(SPAN[0], SPAN[1] + 1))

    def aligned(x):
        return [round(1e3 * float((x * (rel == r)).sum()) / total, 4) for r in bins]

    first = (rel >= 0) & (rel <= 5)
    return {"mu_s_per_m": mu_s, "end_reflectance": reflectance, "windows": windows,
            "profile": {"bins": bins, "excess": aligned(mc - full), "model": aligned(full),
                        "standard_error": [round(1e3 * float(np.sqrt(((se * (rel == r)) ** 2).sum())) / total, 4) for r in bins],
                        **{k: aligned(v) for k, v in parts.items()}},
            "corner_zones": {"excess_first_6_bins": (1e3 * ((mc - full) * first).sum(-1) / total).round(3).tolist(),
                             "edge_second_first_6_bins": (1e3 * (parts["edge_second"] * first).sum(-1) / total).round(3).tolist()}}


def orders(cells: dict, mus: list[float], rs: list[float]) -> dict:
    """The excess by order (thousandths of the model's wall light, per aligned bin), from the grid's corners."""
    if 0.0 not in mus or len(rs) < 2:
        return {"note": "needs mu_s = 0 and two reflectances"}
    lo, hi = rs[0], rs[-1]
    ex = {k: np.asarray(v["profile"]["excess"]) for k, v in cells.items()}
    out = {"reflectances": [lo, hi]}
    for m in mus:
        if m == 0.0:
            continue
        r1 = ex[(m, lo)] - ex[(0.0, lo)]
        r2 = hi / (hi - lo) * ((ex[(m, hi)] - ex[(m, lo)]) - (ex[(0.0, hi)] - ex[(0.0, lo)]))
        out[f"mu_s_{m:g}"] = {"R_mu_s": r1.round(4).tolist(), "R2_mu_s": r2.round(4).tolist(),
                              "R_mu_s_sum": round(float(r1.sum()), 3), "R2_mu_s_sum": round(float(r2.sum()), 3)}
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = result["cells"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharex=True)
    for c in cells:
        pr = c["profile"]
        axes[0].plot(pr["bins"], pr["excess"], label=f"mu_s {c['mu_s_per_m']:g}, R {c['end_reflectance']:g}")
    axes[0].axhline(0, color="k", lw=0.5)
    axes[0].set(title="Monte Carlo over the model: wall light", xlabel="bins from each zone's peak",
                ylabel="excess [1/1000 of the model's wall light]")
    axes[0].legend(fontsize=7)
    for k, v in result["orders"].items():
        if isinstance(v, dict) and "R_mu_s" in v:
            bins = cells[0]["profile"]["bins"]
            axes[1].plot(bins, v["R_mu_s"], label=f"R mu_s ({k})")
            axes[1].plot(bins, v["R2_mu_s"], "--", label=f"R^2 mu_s ({k})")
    axes[1].axhline(0, color="k", lw=0.5)
    axes[1].set(title="the excess by order", xlabel="bins from each zone's peak")
    axes[1].legend(fontsize=7)
    fig.text(0.5, 0.005, "simulated (tofjax.mc Monte Carlo, diffuse minus absorbing edges; guided model's end component)",
             ha="center", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--plot", help="PNG of the aligned profiles and the orders")
    ap.add_argument("--mu-s", default="0,0.6,1.2", help="scattering coefficients, /m, comma-separated")
    ap.add_argument("--reflectance", default="0.1,0.5", help="wall reflectances, comma-separated (two or more)")
    ap.add_argument("--seeds", type=int, default=8, help="Monte Carlo runs per cell and edge (cached)")
    ap.add_argument("--photons", type=int, default=25_000, help="photons per sensor per run")
    ap.add_argument("--guided-switch", action="append", default=[], metavar="NAME=VALUE",
                    help="set a module switch of tofjax.model.guided for this run (repeatable)")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    from tofjax.outputs import OutputError, check_output

    sys.path.insert(0, str(HERE))
    import eval_mc_data as ev

    try:
        mus, rs = _floats(a.mu_s, "--mu-s"), _floats(a.reflectance, "--reflectance")
        if any(r > 1 for r in rs):
            raise ValueError(f"--reflectance: must be at most 1, got {a.reflectance!r}")
        if a.seeds < 2 or a.photons < 1:
            raise ValueError("--seeds must be >= 2 (a standard error) and --photons >= 1")
        path = check_output(Path(a.out), overwrite=a.overwrite)
        png = check_output(Path(a.plot), overwrite=a.overwrite) if a.plot else None
        try:
            ev.set_guided_switches(a.guided_switch)
        except ValueError as e:
            raise ValueError(f"--guided-switch: {e}") from None
    except (ValueError, OutputError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    import tofjax

    tofjax.enable_x64()
    import tofjax.model.guided as guided

    t0 = time.perf_counter()
    result = ev.study_header("where the guided model's wall light and the Monte Carlo's part, by reflectance and mu_s",
                             "simulated (tofjax.mc Monte Carlo runs, diffuse minus absorbing edges, as "
                             "experiments/eval_mc_data.py)")
    base = ev.guided_scene()
    cells = {}
    for m in mus:
        for r in rs:
            cells[(m, r)] = c = cell(base, m, r, a.seeds, a.photons)
            print(f"mu_s {m:g} R {r:g}: MC over model, 2..8 bins after the peak "
                  f"{c['windows']['2..8']['mc_over_model']}, all {c['windows']['all']['mc_over_model']}", flush=True)
    result |= {"seeds": a.seeds, "photons_per_sensor": a.photons,
               "switches": {k: getattr(guided, k) for k in guided.SWITCH_NAMES},
               "units": "profiles and orders: thousandths of the model's total wall light per aligned bin",
               "cells": list(cells.values()), "orders": orders(cells, mus, rs)}
    for k, v in result["orders"].items():
        if isinstance(v, dict) and "R_mu_s_sum" in v:
            print(f"{k}: excess R mu_s {v['R_mu_s_sum']:+.2f}, R^2 mu_s {v['R2_mu_s_sum']:+.2f} (1/1000 of the wall light)")
    result["seconds"] = time.perf_counter() - t0
    ev.write_study(result, path)
    if png:
        plot(result, png)
        print(f"wrote {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
