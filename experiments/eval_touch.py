"""Study: touch detection the way seed 000 section 5 measures it, on simulated data.

Scenarios (default OptoSkin scene, photon noise on, a 100-frame simulated baseline):

* single touches on a grid of positions (seed 000 Fig. 5),
* multi-touch: random configurations of 3 and 6 contacts at least ``min_separation_m``
  apart (seed 000 Fig. 6),
* shapes: a stick and a mug rim (seed 000 Fig. 7).

Every method (raw, decay, baseline, full back-projection, model-based) sees the same
frames with the same detection settings. A detection matches a true contact within
``match_radius_m`` (one-to-one); precision = matched / detections, recall = matched /
contacts, and the mean distance error of the matched pairs. Contacts *shadowed* (every
sensor that sees them has another contact in front, in the same zone) get their own recall.
Shapes are scored by coverage: the share of the shape's length within 1 cm of a detected
contact area, and the share of detected area within 1.5 cm of the shape.

Writes ``eval_touch.json``, ``eval_touch.md`` (the table) and figures
``fig5_single.png``, ``fig6_multi.png``, ``fig7_shapes.png``, ``metrics.png``.

    python experiments/eval_touch.py --config configs/studies/eval_touch.toml --out out/eval_touch
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

import tofjax
from tofjax.config import from_dict, load_toml
from tofjax.invert.detect import DetectOptions, match
from tofjax.invert.maps import MapOptions
from tofjax.invert.pipeline import InvertOptions, build_inverter
from tofjax.invert.synth import random_contacts, shadowed, simulate_contacts
from tofjax.scene import load_scene
from tofjax.simulate import simulate


@dataclass(frozen=True)
class EvalConfig:
    scene: str = "optoskin"
    methods: tuple[str, ...] = ("raw", "decay", "baseline", "full", "model")
    baseline_frames: int = 100
    single_grid: int = 7  # single touches on an n x n grid
    multi_counts: tuple[int, ...] = (3, 6)
    multi_configs: int = 100
    min_separation_m: float = 0.04
    match_radius_m: float = 0.02
    resolution_m: float = 0.0025
    relative: float = 0.3
    n_sigma: float = 6.0
    shapes: tuple[str, ...] = ("configs/touch-stick.toml", "configs/touch-ring.toml")
    seed: int = 0


def _score(detections, contacts, radius):
    tp = nd = nt = 0
    dists, found = [], []
    for det, c in zip(detections, contacts):
        pos = det.positions()
        k, d = match(pos, c[:, :2], radius)
        tp, nd, nt = tp + k, nd + len(pos), nt + len(c)
        dists += list(d)
        # Per contact: is it matched? (the same one-to-one matching)
        f = np.zeros(len(c), bool)
        if len(pos):
            from scipy.optimize import linear_sum_assignment

            dd = np.hypot(*(pos[:, None, :] - c[None, :, :2]).transpose(2, 0, 1))
            r, cc = linear_sum_assignment(np.where(dd <= radius, dd, 1e6))
            f[cc[dd[r, cc] <= radius]] = True
        found.append(f)
    return {
        "precision": tp / nd if nd else float("nan"),
        "recall": tp / nt if nt else float("nan"),
        "mean_error_cm": 100 * float(np.mean(dists)) if dists else float("nan"),
        "detections": nd,
        "contacts": nt,
        "matched": tp,
    }, found


def _shape_score(det, elements, grid):
    if det.labels is None or not det.labels.any():
        return {"shape_recall": 0.0, "shape_precision": float("nan")}
    X, Y = np.meshgrid(grid.x, grid.y)
    on = np.stack([X[det.labels > 0], Y[det.labels > 0]], 1)
    d = np.hypot(*(elements[:, None, :2] - on[None]).transpose(2, 0, 1))  # (E, pixels)
    return {
        "shape_recall": float(np.mean(d.min(1) <= 0.01)),
        "shape_precision": float(np.mean(d.min(0) <= 0.015)),
    }


def run(config: EvalConfig, out: Path, progress: bool = True) -> dict:
    t0 = time.perf_counter()
    scene = load_scene(config.scene).without_touches()
    rng_seed = config.seed
    baseline = simulate(scene, config.baseline_frames, rng_seed)
    B = baseline.mean()
    opts = {
        m: InvertOptions(
            method=m,
            maps=MapOptions(resolution_m=config.resolution_m),
            detect=DetectOptions(relative=config.relative, n_sigma=config.n_sigma),
        )
        for m in config.methods
    }
    bar = tqdm(total=len(config.methods), desc="building inverters", disable=not progress)
    inverters = {}
    for m in config.methods:
        inverters[m] = build_inverter(scene, B, opts[m], n_baseline=config.baseline_frames)
        bar.update()
    bar.close()
    lx, ly = scene.waveguide.size_m
    margin = 0.02
    g = np.linspace(margin, lx - margin, config.single_grid)
    gy = np.linspace(margin, ly - margin, config.single_grid)
    single = np.array([[[x, y, 1.0]] for y in gy for x in g])
    scenarios = {"single": single}
    for n in config.multi_counts:
        scenarios[f"multi{n}"] = random_contacts(
            scene, config.multi_configs, n, seed=config.seed + n, min_separation_m=config.min_separation_m
        )
    results: dict = {"scenarios": {}}
    examples: dict = {}
    for k, (name, contacts) in enumerate(scenarios.items()):
        H = simulate_contacts(scene, contacts, seed=config.seed + 100 + k)
        shadow = np.concatenate([shadowed(scene, c) for c in contacts])
        row = {
            "configs": len(contacts),
            "contacts_per_config": contacts.shape[1],
            "shadowed_contacts": int(shadow.sum()),
            "methods": {},
        }
        for m in tqdm(config.methods, desc=name, disable=not progress):
            res = inverters[m].process(H)
            score, found = _score(res.detections, contacts, config.match_radius_m)
            found = np.concatenate(found)
            score["recall_shadowed"] = float(found[shadow].mean()) if shadow.any() else float("nan")
            score["recall_unshadowed"] = float(found[~shadow].mean()) if (~shadow).any() else float("nan")
            row["methods"][m] = score
            idx = [0, len(contacts) // 2, len(contacts) - 1] if name == "single" else [0, 1]
            examples.setdefault(name, {})[m] = [
                (res.maps[i], res.detections[i], contacts[i, :, :2], res.grid) for i in idx
            ]
        results["scenarios"][name] = row
    # Shapes.
    shape_rows = {}
    for i, path in enumerate(config.shapes):
        sc = load_scene(path)
        cap = simulate(sc, 1, config.seed + 200 + i)
        el = sc.contact_elements()
        shape_rows[sc.name] = {}
        for m in config.methods:
            res = inverters[m].process(cap.histograms)
            shape_rows[sc.name][m] = _shape_score(res.detections[0], el, inverters[m].grid)
            examples.setdefault("shapes", {}).setdefault(m, []).append(
                (res.maps[0], res.detections[0], el[:, :2], res.grid)
            )
    results["shapes"] = shape_rows
    result = {
        "study": "touch detection (seed 000 section 5)",
        "data": "simulated",
        "config": dataclasses.asdict(config),
        "seconds": time.perf_counter() - t0,
        **results,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "eval_touch.json").write_text(json.dumps(result, indent=2))
    (out / "eval_touch.md").write_text(table(result))
    grid = inverters[config.methods[0]].grid
    _figures(examples, grid, scene, config.methods, out)
    _metrics_plot(result, out / "metrics.png")
    return result


def _metrics_plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["scenarios"])
    methods = list(result["scenarios"][names[0]]["methods"])
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    w = 0.8 / len(methods)
    for ax, key, label in zip(
        axes, ("precision", "recall", "mean_error_cm"), ("precision", "recall", "mean error [cm]")
    ):
        for k, m in enumerate(methods):
            v = [result["scenarios"][n]["methods"][m][key] for n in names]
            ax.bar(np.arange(len(names)) + (k - (len(methods) - 1) / 2) * w, v, w, label=m)
        ax.set_xticks(np.arange(len(names)), names)
        ax.set_title(label)
    axes[0].legend(fontsize=7)
    fig.suptitle("touch detection per method (simulated, default OptoSkin scene)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def table(result: dict) -> str:
    lines = [
        "| scenario | method | precision | recall | recall (shadowed) | mean error [cm] |",
        "|---|---|---|---|---|---|",
    ]
    for name, row in result["scenarios"].items():
        label = "single" if name == "single" else f"{row['contacts_per_config']} contacts"
        label += f" ({row['configs']} configs)"
        for m, s in row["methods"].items():
            sh = s["recall_shadowed"]
            shs = "-" if math.isnan(sh) else "%.0f%% of %d" % (100 * sh, row["shadowed_contacts"])
            lines.append(
                f"| {label} | {m} | {100 * s['precision']:.1f}% | {100 * s['recall']:.1f}% | {shs} | {s['mean_error_cm']:.2f} |"
            )
    if result.get("shapes"):
        lines += ["", "| shape | method | length covered | detected area on the shape |", "|---|---|---|---|"]
        for name, row in result["shapes"].items():
            for m, s in row.items():
                p = s["shape_precision"]
                ps = "-" if math.isnan(p) else "%.0f%%" % (100 * p)
                lines.append(f"| {name} | {m} | {100 * s['shape_recall']:.0f}% | {ps} |")
    return "\n".join(lines) + "\n"


def _cell(example, truth=True):
    m, det, pos, grid = example
    return {"map": m, "detection": det, "truth": pos if truth else None, "grid": grid}


def _figures(examples, grid, scene, methods, out: Path):
    from tofjax.invert.plots import plot_map_grid

    for key, fname, title in (("single", "fig5_single.png", "single"), ("shapes", "fig7_shapes.png", "shape")):
        if key not in examples:
            continue
        n = len(examples[key][methods[0]])
        rows = [[_cell(examples[key][m][i], truth=key != "shapes") for m in methods] for i in range(n)]
        plot_map_grid(
            rows, grid, scene, out / fname, col_titles=list(methods), row_titles=[f"{title} {i}" for i in range(n)]
        )
    multi = [k for k in examples if k.startswith("multi")]
    rows, titles = [], []
    for k in multi:
        for i in range(len(examples[k][methods[0]])):
            rows.append([_cell(examples[k][m][i]) for m in methods])
            titles.append(f"{k[5:]} contacts")
    if rows:
        plot_map_grid(rows, grid, scene, out / "fig6_multi.png", col_titles=list(methods), row_titles=titles)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="configs/studies/eval_touch.toml")
    ap.add_argument("--out", default="out/eval_touch")
    args = ap.parse_args(argv)
    tofjax.enable_x64()
    config = from_dict(EvalConfig, load_toml(args.config))
    result = run(config, Path(args.out))
    print(table(result))
    print(f"wrote {args.out}/eval_touch.json, eval_touch.md and figures ({result['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
