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

Two data sources, scored the same way (the README reports both columns):

* ``own``: tofjax's forward model (:func:`tofjax.invert.synth.simulate_contacts`), baseline
  from :func:`tofjax.simulate.simulate`;
* ``independent``: the NumPy simulator ``tests/indep_sim.py`` (different discretisation,
  pulse, emission time, per-zone gains, crosstalk, shadowing, no multiple scattering), its
  own 100-frame baseline. The inversion uses the scene's stated optics (``n1``, ``mu_s``,
  ``mu_a``: the truth) or, with ``calibration``, a calibrated set.

Recall is also split by the contact's distance to the nearest edge (``border_m``: border
band vs interior). ``attenuations`` repeats the six-contact scenario on guides with other
``(mu_s, mu_a)``.

``frames_summed`` (``--frames-summed``; default 1) is a researcher holding a static touch and summing
frames: every touch frame is the sum of ``frames_summed`` frames, each drawn with its own photon noise
(and its own saturation) from the same expected counts, and the baseline is on the same exposure: each
of its ``baseline_frames`` frames is a sum of as many (``n_baseline`` stays ``baseline_frames``: it is
the number of summed frames averaged). The inversion is built on that baseline as from any other, so
the Poisson variance it assumes (``B (1 + 1/n_baseline)``, ``B`` the summed baseline) and the CFAR floor
measured on the baseline's (summed) frames are those of the summed data: every threshold in noise units
sees the summed noise, and a contact's SNR grows by ``sqrt(frames_summed)``. Signals are in counts per
summed frame, so the model method's strengths come out ``frames_summed`` times the forward model's (its
thresholds are in noise units and relative to the frame: unaffected). With 1 the draws are today's,
bit for bit. This is the convention of :mod:`tofjax.invert.sensitivity` (``frames``).

Writes ``eval_touch.json``, ``eval_touch.md`` (the table) and figures
``fig5_single.png``, ``fig6_multi.png``, ``fig7_shapes.png``, ``metrics.png``.

    python experiments/eval_touch.py --config configs/studies/eval_touch.toml --out out/eval_touch
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

import tofjax
from tofjax.config import ConfigError, from_dict, load_toml
from tofjax.invert.correction import OpticalParams
from tofjax.invert.detect import DetectOptions, match
from tofjax.invert.maps import MapOptions
from tofjax.invert.pipeline import InvertOptions, build_inverter
from tofjax.invert.reconstruct import ReconstructOptions
from tofjax.invert.synth import random_contacts, shadowed, simulate_contacts
from tofjax.model import sample_counts
from tofjax.scene import load_scene
from tofjax.simulate import simulate


@dataclass(frozen=True)
class EvalConfig:
    scene: str = "optoskin"
    methods: tuple[str, ...] = ("raw", "decay", "baseline", "full", "model")
    sources: tuple[str, ...] = ("own", "independent")
    baseline_frames: int = 100
    single_grid: int = 7  # single touches on an n x n grid (0: none)
    multi_counts: tuple[int, ...] = (3, 6)
    multi_configs: int = 100
    min_separation_m: float = 0.04
    match_radius_m: float = 0.02
    border_m: float = 0.05  # recall is split: contacts nearer the edge than this vs the interior
    resolution_m: float = 0.0025
    relative: float = 0.2
    n_sigma: float = 7.0
    cfar: bool = True
    no_touch_frames: int = 40  # no-touch frames: false touches per frame  # detection on the map divided by its noise (see DetectOptions)
    model_n_sigma: float | None = None  # model method's threshold in noise sigma (None: its default)
    model_relative: float | None = None  # model method's threshold relative to the frame's strongest (None: its default)
    # Six-contact runs on other guides: [mu_s_per_m, mu_a_per_m] pairs.
    attenuations: tuple[tuple[float, float], ...] = ()
    shapes: tuple[str, ...] = ("configs/touch-stick.toml", "configs/touch-ring.toml")
    calibration: str | None = None  # calibration JSON for the inversion (default: the scene's optics)
    rig_seed: int = 1  # the independent simulator's rig (per-zone gains, crosstalk, sampling)
    seed: int = 0
    # Frames summed per touch frame (a static touch), the baseline on the same exposure (each of its
    # baseline_frames frames a sum of as many); 1: single frames, today's draws bit for bit.
    frames_summed: int = 1

    def __post_init__(self):
        n = self.frames_summed
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"frames_summed: must be an integer >= 1, got {n!r}")


def _edge_distance(scene, xy):
    lx, ly = scene.waveguide.size_m
    return np.minimum.reduce([xy[..., 0], lx - xy[..., 0], xy[..., 1], ly - xy[..., 1]])


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
        "false_per_frame": (nd - tp) / max(len(contacts), 1),
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


def _indep():
    """The independent simulator (a test fixture, imported from tests/)."""
    import sys

    root = Path(__file__).resolve().parents[1] / "tests"
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    import indep_sim

    return indep_sim


@functools.partial(jax.jit, static_argnames=("n", "poisson", "saturation"))
def _summed_draws(keys, expected, *, n: int, poisson: bool, saturation: float):
    """Per configuration (``keys`` (C,), ``expected`` (C, S, Z, B)): the sum of ``n`` frames, each drawn
    as :func:`tofjax.model.sample_counts` draws one (own photon noise, own saturation)."""

    def one(key, lam):
        return jax.vmap(lambda k: sample_counts(k, lam, poisson=poisson, saturation=saturation))(
            jax.random.split(key, n)
        ).sum(0)

    return jax.vmap(one)(keys, expected)


def _sum_groups(frames: np.ndarray, n: int) -> np.ndarray:
    """Consecutive groups of ``n`` frames summed: (F * n, ...) -> (F, ...)."""
    return frames.reshape(len(frames) // n, n, *frames.shape[1:]).sum(1)


class _Source:
    """Baseline and touch frames of one scene from one simulator; with ``config.frames_summed`` = N > 1
    every frame (baseline and touch) is the sum of N frames drawn independently."""

    def __init__(self, kind: str, scene, config: EvalConfig):
        self.kind, self.scene, self.config = kind, scene, config
        self.n = n = config.frames_summed
        if kind == "own":
            self.baseline_frames = _sum_groups(simulate(scene, config.baseline_frames * n, config.seed).histograms, n)
        elif kind == "independent":
            sim = _indep()
            self.rig = sim.IndepRig.from_scene(scene, seed=config.rig_seed)
            self.baseline_frames = _sum_groups(
                sim.simulate(self.rig, np.zeros((0, 3)), config.baseline_frames * n, config.seed).histograms, n
            )
        else:
            raise ValueError(f"sources: unknown source {kind!r} (own, independent)")
        self.baseline = self.baseline_frames.mean(0)

    def frames(self, contacts, seed):
        if self.n == 1:
            if self.kind == "own":
                return simulate_contacts(self.scene, contacts, seed=seed)
            return self.rig.histograms(contacts, seed=seed)
        if self.kind == "own":
            lam = simulate_contacts(self.scene, contacts, seed=seed, noise=False)
            keys = jax.random.split(jax.random.key(seed), len(lam))
            return np.asarray(
                _summed_draws(keys, lam, n=self.n, poisson=bool(self.scene.noise.poisson),
                              saturation=float(self.scene.sensor.saturation_counts)),
                np.float64,
            )
        return self._indep_summed([self.rig.expected(c) for c in np.asarray(contacts, float)], seed)

    def _indep_summed(self, expected, seed):
        """The independent simulator's noise (``IndepRig._noisy``, then its saturation) per frame, summed."""
        rng = np.random.default_rng(seed)
        sat = self.scene.sensor.saturation_counts
        return np.stack([sum(np.minimum(self.rig._noisy(lam, rng), sat) for _ in range(self.n)) for lam in expected])

    def shape_frame(self, shape_scene, seed):
        if self.kind == "own":
            return _sum_groups(simulate(shape_scene, self.n, seed).histograms, self.n)
        el = shape_scene.contact_elements()
        if self.n == 1:
            return self.rig.histograms(el[None, :, [0, 1, 3]], seed=seed)
        return self._indep_summed([self.rig.expected(el[:, [0, 1, 3]])], seed)


def _options(config: EvalConfig) -> dict:
    out = {}
    for m in config.methods:
        det = DetectOptions(relative=config.relative, n_sigma=config.n_sigma, cfar=config.cfar)
        rec = ReconstructOptions()
        if m == "model" and config.model_n_sigma is not None:
            rec = dataclasses.replace(rec, n_sigma=config.model_n_sigma)
        if m == "model" and config.model_relative is not None:
            rec = dataclasses.replace(rec, relative=config.model_relative)
        out[m] = InvertOptions(method=m, maps=MapOptions(resolution_m=config.resolution_m), detect=det, reconstruct=rec)
    return out


def _optics(config: EvalConfig, scene):
    if config.calibration is None:
        return None
    return OpticalParams.from_calibration(config.calibration, scene)


def _evaluate(source: _Source, scenarios: dict, config: EvalConfig, progress: bool, examples: dict | None):
    scene = source.scene
    opts = _options(config)
    optical = _optics(config, scene)
    inverters = {}
    for m in tqdm(config.methods, desc=f"building inverters ({source.kind})", disable=not progress):
        inverters[m] = build_inverter(
            scene,
            source.baseline,
            opts[m],
            optical,
            n_baseline=config.baseline_frames,
            baseline_frames=source.baseline_frames,
        )
    rows = {}
    for k, (name, contacts) in enumerate(scenarios.items()):
        H = source.frames(contacts, seed=config.seed + 100 + k)
        shadow = np.concatenate([shadowed(scene, c) for c in contacts])
        border = np.concatenate([_edge_distance(scene, c[:, :2]) < config.border_m for c in contacts])
        row = {
            "configs": len(contacts),
            "contacts_per_config": contacts.shape[1],
            "shadowed_contacts": int(shadow.sum()),
            "border_contacts": int(border.sum()),
            "methods": {},
        }
        for m in tqdm(config.methods, desc=f"{name} ({source.kind})", disable=not progress):
            res = inverters[m].process(H)
            score, found = _score(res.detections, contacts, config.match_radius_m)
            found = np.concatenate(found)
            score["recall_shadowed"] = float(found[shadow].mean()) if shadow.any() else float("nan")
            score["recall_unshadowed"] = float(found[~shadow].mean()) if (~shadow).any() else float("nan")
            score["recall_border"] = float(found[border].mean()) if border.any() else float("nan")
            score["recall_interior"] = float(found[~border].mean()) if (~border).any() else float("nan")
            row["methods"][m] = score
            if examples is not None:
                idx = [0, len(contacts) // 2, len(contacts) - 1] if name == "single" else [0, 1]
                examples.setdefault(name, {})[m] = [
                    (res.maps[i], res.detections[i], contacts[i, :, :2], res.grid) for i in idx
                ]
        rows[name] = row
    return rows, inverters


def run(config: EvalConfig, out: Path, progress: bool = True) -> dict:
    t0 = time.perf_counter()
    scene = load_scene(config.scene).without_touches()
    lx, ly = scene.waveguide.size_m
    margin = 0.02
    scenarios = {}
    if config.single_grid:
        g = np.linspace(margin, lx - margin, config.single_grid)
        gy = np.linspace(margin, ly - margin, config.single_grid)
        scenarios["single"] = np.array([[[x, y, 1.0]] for y in gy for x in g])
    for n in config.multi_counts:
        scenarios[f"multi{n}"] = random_contacts(
            scene, config.multi_configs, n, seed=config.seed + n, min_separation_m=config.min_separation_m
        )
    if config.no_touch_frames:
        scenarios["none"] = np.zeros((config.no_touch_frames, 0, 3))
    results: dict = {"scenarios": {}, "independent": {}, "attenuation": []}
    examples: dict = {}
    inverters = {}
    for kind in config.sources:
        src = _Source(kind, scene, config)
        rows, inv = _evaluate(src, scenarios, config, progress, examples if kind == config.sources[0] else None)
        if kind == "own":
            results["scenarios"] = rows
        else:
            results["independent"] = {"scenarios": rows}
        if kind == config.sources[0]:
            inverters = inv
        # Shapes.
        shape_rows = {}
        for i, path in enumerate(config.shapes):
            sc = load_scene(path)
            H = src.shape_frame(sc, config.seed + 200 + i)
            el = sc.contact_elements()
            shape_rows[sc.name] = {}
            for m in config.methods:
                res = inv[m].process(H)
                shape_rows[sc.name][m] = _shape_score(res.detections[0], el, inv[m].grid)
                if kind == config.sources[0]:
                    examples.setdefault("shapes", {}).setdefault(m, []).append(
                        (res.maps[0], res.detections[0], el[:, :2], res.grid)
                    )
        if kind == "own":
            results["shapes"] = shape_rows
        else:
            results["independent"]["shapes"] = shape_rows
    six = {k: v for k, v in scenarios.items() if k == "multi6"} or {
        "multi6": random_contacts(scene, config.multi_configs, 6, seed=config.seed + 6, min_separation_m=config.min_separation_m)
    }
    for mu_s, mu_a in config.attenuations:
        wg = dataclasses.replace(scene.waveguide, mu_s_per_m=float(mu_s), mu_a_per_m=float(mu_a))
        sc = scene.replace(waveguide=wg)
        entry = {"mu_s_per_m": mu_s, "mu_a_per_m": mu_a}
        for kind in config.sources:
            rows, _ = _evaluate(_Source(kind, sc, config), six, config, progress, None)
            entry[kind] = rows["multi6"]
        results["attenuation"].append(entry)
    result = {
        "study": "touch detection (seed 000 section 5)",
        "data": "simulated",
        "machine": platform.platform(),
        "config": dataclasses.asdict(config),
        "seconds": time.perf_counter() - t0,
        **results,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "eval_touch.json").write_text(json.dumps(result, indent=2))
    (out / "eval_touch.md").write_text(table(result))
    if inverters and scenarios:
        grid = inverters[config.methods[0]].grid
        _figures(examples, grid, scene, config.methods, out)
        _metrics_plot(result, out / "metrics.png")
    return result


def _metrics_plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in result["scenarios"] if n != "none"]
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


def _pct(v):
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else "%.1f%%" % (100 * v)


def table(result: dict) -> str:
    """Markdown tables: every scenario and method, one column group per data source."""
    srcs = [("own", result.get("scenarios") or {})]
    if result.get("independent", {}).get("scenarios"):
        srcs.append(("independent", result["independent"]["scenarios"]))
    head = " | ".join(f"{k}: precision | {k}: recall | {k}: recall border / interior | {k}: error [cm]" for k, _ in srcs)
    lines = [f"| scenario | method | {head} |", "|---|---|" + "---|" * (4 * len(srcs))]
    names = list(srcs[0][1]) or (list(srcs[1][1]) if len(srcs) > 1 else [])
    for name in names:
        row0 = next(r[name] for _, r in srcs if name in r)
        label = "single" if name == "single" else f"{row0['contacts_per_config']} contacts"
        label = "no touch" if name == "none" else label
        label += f" ({row0['configs']} configs)" if name != "none" else f" ({row0['configs']} frames)"
        for m in row0["methods"]:
            cells = []
            for _, rows in srcs:
                s = rows.get(name, {}).get("methods", {}).get(m)
                if s is None:
                    cells.append("- | - | - | -")
                    continue
                if name == "none":
                    cells.append(f"- | {s['false_per_frame']:.3f} false touches per frame | - | -")
                    continue
                cells.append(
                    f"{_pct(s['precision'])} | {_pct(s['recall'])} | "
                    f"{_pct(s.get('recall_border'))} / {_pct(s.get('recall_interior'))} | {s['mean_error_cm']:.2f}"
                )
            lines.append(f"| {label} | {m} | " + " | ".join(cells) + " |")
    if result.get("attenuation"):
        lines += ["", "Six contacts on attenuating guides:", ""]
        kinds = [k for k in ("own", "independent") if k in result["attenuation"][0]]
        head = " | ".join(f"{k}: precision | {k}: recall | {k}: recall border / interior | {k}: error [cm]" for k in kinds)
        lines += [f"| mu_s + mu_a [/m] | method | {head} |", "|---|---|" + "---|" * (4 * len(kinds))]
        for e in result["attenuation"]:
            for m in e[kinds[0]]["methods"]:
                cells = []
                for k in kinds:
                    s = e[k]["methods"][m]
                    cells.append(
                        f"{_pct(s['precision'])} | {_pct(s['recall'])} | "
                        f"{_pct(s['recall_border'])} / {_pct(s['recall_interior'])} | {s['mean_error_cm']:.2f}"
                    )
                lines.append(f"| {e['mu_s_per_m'] + e['mu_a_per_m']:g} | {m} | " + " | ".join(cells) + " |")
    for key, shapes in (("own", result.get("shapes")), ("independent", result.get("independent", {}).get("shapes"))):
        if shapes:
            lines += ["", f"| shape ({key}) | method | length covered | detected area on the shape |", "|---|---|---|---|"]
            for name, row in shapes.items():
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
    ap.add_argument("--frames-summed", type=int, default=None,
                    help="frames summed per touch frame, the baseline on the same exposure (overrides the config's)")
    args = ap.parse_args(argv)
    tofjax.enable_x64()
    data = load_toml(args.config)
    if args.frames_summed is not None:
        data["frames_summed"] = args.frames_summed
    try:
        config = from_dict(EvalConfig, data)
    except ConfigError as e:
        ap.error(str(e))
    result = run(config, Path(args.out))
    print(table(result))
    print(f"wrote {args.out}/eval_touch.json, eval_touch.md and figures ({result['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
