"""Study: force anywhere on the skin (issue 17), on the **simulated** position protocol.

Every model is trained on ``configs/force/position.toml``'s data (seed 001's indentation
protocol repeated at 10 positions in front of sensor 0) and tested on unseen forces at the
training positions (*seen*), at 4 held-out positions and distances (*unseen*), and on two
simultaneous contacts each pressed to its own forces (*two contacts*). One table:

- seed 001's three MLPs (single, dual, derivative-enhanced dual input), each alone and with
  the residual forest, on the inversion features (:class:`tofjax.force.features.ContactInverter`),
  and the derivative MLP with the 7-frame derivative (``features.derivative_frames``);
- the alternatives of seed 001's Table I (deep MLP, nonlinear regression, SVR, gradient
  boosting) on the derivative inputs;
- two ablations of the derivative MLP + forest: without the position inputs, and on seed
  001's fixed window of raw counts (which cannot follow the contact).

Where the forest helps: its MAE change against the MLP alone per split, velocity and force
band, from each run's ``predictions.csv``.

Independent column: the same pipeline (inversion features, dual-input MLP + forest, trained
and tested on seen and unseen positions) on static presses from ``tests/indep_sim.py``, a
second simulator with other conventions (per-zone gains, two-tail response, geometric
shadows, another strength scale): whether the unseen/seen ratio holds on data tofjax's forward
model did not make.

Writes ``force_position.json`` to ``--out`` and the table to ``--md``.

    python experiments/study_force_position.py --out docs/results --md docs/force_position.md \
        --work out/force_position_work --overwrite
    python experiments/study_force_position.py --seed001 --out docs/results --work out/force_position_work

``--seed001`` trains seed 001's derivative-enhanced MLP (with and without dropout, and with the
7-frame derivative) + forest on seed 001's own one-position protocol instead
(``force_seed001.json``: the issue's 1.0 N target).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

import tofjax
from tofjax.config import load_toml
from tofjax.force.train import run_config_from_dict, train
from tofjax.outputs import atomic_write_text, check_output

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "force" / "position.toml"

#: (row name, input, overrides of position.toml)
RUNS = (
    ("mlp_single", "single", {"features": {"variant": "single"}}),
    ("mlp_dual", "dual", {"features": {"variant": "dual"}}),
    ("mlp_derivative", "derivative", {}),
    ("mlp_derivative_smooth", "derivative, 7 frames", {"features": {"derivative_frames": 7}}),
    ("deep_mlp", "derivative", {"model": {"kind": "deep_mlp", "dropout": 0.0}, "forest": {"enabled": False}}),
    ("nonlinear", "derivative", {"model": {"kind": "nonlinear"}}),
    ("svr", "derivative", {"model": {"kind": "svr", "svr": {"max_train_samples": 4000}}}),
    ("gb", "derivative", {"model": {"kind": "gb"}}),
    ("no_position", "derivative (no position inputs)", {"features": {"position": False}}),
    ("counts", "derivative (seed 001 counts window)",
     {"features": {"source": "counts", "position": True, "sensor": 0}}),
)
SPLIT_OF_FILE = {"test": "seen", "unseen": "unseen", "two": "two_contacts"}
BANDS = ((0.0, 20.0), (20.0, 40.0), (40.0, 70.0))


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _forest_where(pred_csv: Path) -> dict:
    """MAE of the MLP alone and with the forest per split x velocity and per force band."""
    rows = list(csv.DictReader(open(pred_csv)))
    f = np.array([float(r["force_n"]) for r in rows])
    a = np.abs(np.array([float(r["mlp_n"]) for r in rows]) - f)
    b = np.abs(np.array([float(r["mlp_rf_n"]) for r in rows]) - f)
    split = np.array([SPLIT_OF_FILE[r["capture"].split("_")[0]] for r in rows])
    vel = np.array([float(r["velocity_mm_s"]) for r in rows])
    out = {}
    for s in sorted(set(split)):
        for v in sorted(set(vel)):
            m = (split == s) & (vel == v)
            out[f"{s}, v = {v:g} mm/s"] = {"mlp": float(a[m].mean()), "mlp_rf": float(b[m].mean()), "frames": int(m.sum())}
    for lo, hi in BANDS:
        m = (f >= lo) & (f < hi) & (split != "two_contacts")
        out[f"force {lo:g}-{hi:g} N"] = {"mlp": float(a[m].mean()), "mlp_rf": float(b[m].mean()), "frames": int(m.sum())}
    # Loading (force rising) vs the rest, where the lag makes the optics trail the force.
    return out


def _by_position(pred_csv: Path, protocol: dict) -> list[dict]:
    """MAE of each model per test position (seen and unseen), from a run's ``predictions.csv``."""
    from tofjax.force.generate import protocol_from_dict

    p = protocol_from_dict(protocol)
    rows = list(csv.DictReader(open(pred_csv)))
    models = [k[:-2] for k in rows[0] if k.endswith("_n") and k != "force_n"]
    groups: dict[tuple[str, int], list] = {}
    for r in rows:
        parts = r["capture"].split("_")
        if parts[0] in ("test", "unseen") and parts[1].startswith("p"):
            groups.setdefault((parts[0], int(parts[1][1:])), []).append(r)
    out = []
    for (split, i), rs in sorted(groups.items()):
        d, lat = (p.train_positions if split == "test" else p.unseen_positions_m)[i]
        f = np.array([float(r["force_n"]) for r in rs])
        out.append({"split": SPLIT_OF_FILE[split], "distance_m": d, "lateral_m": lat, "frames": len(rs)}
                   | {m: float(np.mean(np.abs(np.array([float(r[f"{m}_n"]) for r in rs]) - f))) for m in models})
    return out


def _independent(base_cfg: dict, out: Path, runs_dir: Path, *, n_train: int, n_test: int, epochs: int, seed: int) -> dict:
    """Static presses from tests/indep_sim.py at the protocol's positions: train on the seen ones, test on both."""
    sys.path.insert(0, str(ROOT / "tests"))
    from indep_sim import IndepRig, simulate  # noqa: E402

    from tofjax.capture import Capture, write_capture
    from tofjax.force.generate import Protocol, contact_position, protocol_from_dict, touch_strength

    p = protocol_from_dict(base_cfg["data"]["protocol"])
    scene = Protocol().load_scene()
    rig = IndepRig.from_scene(scene, seed=seed + 1)
    rng = np.random.default_rng(seed)
    nb = 10
    data = out / "indep-data"
    data.mkdir(parents=True, exist_ok=True)
    files = {"train": [], "test": []}

    def capture(pos, forces, split, k):
        xy = contact_position(scene, p.sensor, *pos)
        base = simulate(rig, contacts=np.zeros((0, 3)), frames=nb, seed=int(rng.integers(1 << 30))).histograms
        contacts = np.array([[[xy[0], xy[1], touch_strength(f, p)]] for f in forces])
        hist = np.concatenate([base, rig.histograms(contacts, seed=int(rng.integers(1 << 30)))])
        force = np.concatenate([np.zeros(nb), forces])
        cap = Capture(histograms=hist, timestamps=np.arange(len(hist)) / 9.0, scene=scene,
                      source="simulated (tests/indep_sim.py)", force=force,
                      truth={"split": split, "baseline_frames": nb, "velocity_mm_s": 0.0, "n_contacts": 1})
        path = data / f"{split}_p{k}.h5"
        write_capture(path, cap, overwrite=True)
        return str(path)

    for k, pos in enumerate(p.train_positions):
        files["train"].append(capture(pos, rng.uniform(5, 60, n_train), "train", k))
        files["test"].append(capture(pos, rng.uniform(8, 60, n_test), "test", k))
    for k, pos in enumerate(p.unseen_positions_m):
        files["test"].append(capture(pos, rng.uniform(8, 60, n_test), "unseen", k))
    cfg = run_config_from_dict(_merge({k: v for k, v in base_cfg.items() if k != "data"}, {
        "name": "indep_dual", "plots": False,
        "data": {"train": files["train"], "test": files["test"]},
        "features": {"variant": "dual"}, "training": {"epochs": epochs}}))
    run = train(cfg, runs_dir, log=None)
    m = json.loads((run / "metrics.json").read_text())
    return {k: {"by_split": v["by_split"], "overall": v["overall"]} for k, v in m["mae_n"].items()} | {
        "frames": m["test_frames_by_split"], "run": str(run)}


def run(out: Path, *, overwrite: bool = False, epochs: int | None = None, runs=RUNS, independent: bool = True,
        indep_frames: tuple[int, int] = (100, 30), protocol: dict | None = None, progress: bool = False,
        work: Path | None = None, md: Path | None = None) -> dict:
    """``out``: where the JSON goes; ``md``: the markdown table (default ``out/force_position.md``);
    ``work``: data, captures and run folders (default ``out``)."""
    out = Path(out)
    work = out if work is None else Path(work)
    md = out / "force_position.md" if md is None else Path(md)
    target = check_output(out / "force_position.json", overwrite=overwrite)
    check_output(md, overwrite=overwrite)
    t0 = time.perf_counter()
    base = load_toml(CONFIG)
    base = _merge(base, {"plots": False, "data": {"cache_dir": str(work / "force-data")}})
    if protocol:
        base = _merge(base, {"data": {"protocol": protocol}})
    if epochs is not None:
        base = _merge(base, {"training": {"epochs": epochs}})
    runs_dir = work / "runs"
    rows, where, by_position = [], {}, []
    for name, variant, over in runs:
        cfg = run_config_from_dict(_merge(base, _merge({"name": f"position_{name}"}, over)))
        t = time.perf_counter()
        d = train(cfg, runs_dir, log=None, progress=progress)
        m = json.loads((d / "metrics.json").read_text())
        for model, v in m["mae_n"].items():
            s = v["by_split"]
            rows.append({
                "run": name, "input": variant, "model": model,
                "seen": s.get("seen"), "unseen": s.get("unseen"), "two_contacts": s.get("two_contacts"),
                "unseen_over_seen": s["unseen"] / s["seen"] if s.get("seen") and s.get("unseen") else None,
                "by_velocity_mm_s": v["by_velocity_mm_s"], "overall": v["overall"],
                "operations": m["operations_per_prediction"].get(model),
            })
        if "mlp_rf" in m["mae_n"]:
            where[name] = _forest_where(d / "predictions.csv")
        if name == "mlp_derivative":
            by_position = _by_position(d / "predictions.csv", base["data"]["protocol"])
        print(f"{name}: " + ", ".join(f"{k} {v['overall']:.2f} N" for k, v in m["mae_n"].items())
              + f" ({time.perf_counter() - t:.0f} s)", flush=True)
    res = {
        "what": "MAE (N) of force estimation at seen and unseen contact positions and with two contacts",
        "data": "simulated (tofjax's forward model; independent column: tests/indep_sim.py)",
        "config": str(CONFIG.relative_to(ROOT)),
        "protocol": base["data"]["protocol"],
        "machine": f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPU cores (shared, loaded), "
                   f"JAX {jax.__version__} {jax.default_backend()} backend",
        "tofjax": tofjax.__version__,
        "rows": rows,
        "forest_where": where,
        "by_position_mlp_derivative": by_position,
        "targets": {"unseen_over_seen_max": 1.2},
    }
    if independent:
        res["independent"] = _independent(base, work, runs_dir, n_train=indep_frames[0], n_test=indep_frames[1],
                                          epochs=base["training"]["epochs"], seed=0)
    res["seconds"] = time.perf_counter() - t0
    atomic_write_text(target, json.dumps(res, indent=2) + "\n", overwrite=overwrite)
    atomic_write_text(md, markdown(res), overwrite=overwrite)
    return res


def _f(v, fmt="{:.2f}"):
    return "-" if v is None else fmt.format(v)


NAMES = {"mlp": "MLP", "mlp_rf": "MLP + RF", "deep_mlp": "deep MLP", "nonlinear": "nonlinear regression",
         "svr": "SVR", "gb": "gradient boosting"}


def markdown(res: dict) -> str:
    vels = sorted({k for r in res["rows"] for k in r["by_velocity_mm_s"]}, key=float)
    head = ["model", "input", "seen", "unseen", "unseen / seen", "two contacts",
            *[f"v = {v} mm/s" for v in vels], "overall", "ops"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in res["rows"]:
        lines.append("| " + " | ".join([
            NAMES.get(r["model"], r["model"]), r["input"], _f(r["seen"]), _f(r["unseen"]),
            _f(r["unseen_over_seen"], "{:.2f}x"), _f(r["two_contacts"]),
            *[_f(r["by_velocity_mm_s"].get(v)) for v in vels], f"**{r['overall']:.2f}**",
            _f(r["operations"], "{:,}")]) + " |")
    lines.append("")
    lines.append("MAE in N, **simulated** data (tofjax's forward model), unseen forces; overall = seen and unseen "
                 "single-contact frames. " + res["machine"] + ".")
    if "independent" in res:
        ind = res["independent"]
        lines += ["", "Independent simulator (tests/indep_sim.py, static presses, dual-input MLP + forest on the inversion features):",
                  "", "| model | seen | unseen | unseen / seen |", "|---|---|---|---|"]
        for k in ("mlp", "mlp_rf"):
            if k in ind:
                s = ind[k]["by_split"]
                lines.append(f"| {NAMES[k]} | {s['seen']:.2f} | {s['unseen']:.2f} | {s['unseen'] / s['seen']:.2f}x |")
    if res["by_position_mlp_derivative"]:
        bp = res["by_position_mlp_derivative"]
        lines += ["", "Derivative MLP + RF per test position (distance, lateral in mm), MAE in N:", "",
                  "| " + " | ".join(f"{r['split']} {r['distance_m'] * 1e3:.0f}, {r['lateral_m'] * 1e3:+.0f}" for r in bp) + " |",
                  "|" + "---|" * len(bp),
                  "| " + " | ".join(f"{r.get('mlp_rf', r.get('mlp')):.2f}" for r in bp) + " |"]
    if res["forest_where"]:
        lines += ["", "Forest MAE change against the MLP alone (negative: the forest helps), N:", ""]
        keys = list(next(iter(res["forest_where"].values())))
        lines.append("| where | " + " | ".join(res["forest_where"]) + " |")
        lines.append("|" + "---|" * (1 + len(res["forest_where"])))
        for k in keys:
            lines.append(f"| {k} | " + " | ".join(
                f"{w[k]['mlp_rf'] - w[k]['mlp']:+.2f}" if k in w else "-" for w in res["forest_where"].values()) + " |")
    return "\n".join(lines) + "\n"


#: (config, overrides): seed 001's configs, and the no-dropout one on the inversion features.
SEED001 = (("configs/force/mlp_derivative.toml", {}), ("configs/force/mlp_derivative_nodrop.toml", {}),
           ("configs/force/mlp_derivative_smooth.toml", {}),
           ("configs/force/mlp_derivative_nodrop.toml", {"name": "mlp_derivative_nodrop_inversion",
                                                         "features": {"source": "inversion", "sensor": 0}}))


def run_seed001(out: Path, *, overwrite: bool = False, work: Path | None = None, configs=SEED001,
                override: dict | None = None) -> dict:
    """Seed 001's one-position protocol with the derivative-enhanced MLP + the packed forest
    (the issue's second target): ``force_seed001.json``."""
    out = Path(out)
    work = out if work is None else Path(work)
    target = check_output(out / "force_seed001.json", overwrite=overwrite)
    t0 = time.perf_counter()
    runs = []
    for c, over in configs:
        d = _merge(load_toml(ROOT / c), _merge({"plots": False, "data": {"cache_dir": str(work / "force-data")}},
                                               _merge(over, override or {})))
        r = train(run_config_from_dict(d, c), work / "runs", log=None)
        m = json.loads((r / "metrics.json").read_text())
        runs.append({"config": c, "name": d["name"], "features": d.get("features", {}), "mae_n": {k: {"overall": v["overall"], "by_velocity_mm_s": v["by_velocity_mm_s"]}
                                            for k, v in m["mae_n"].items()},
                     "forest_mae_reduction": m.get("forest_mae_reduction"), "forest_depth": d.get("forest", {}).get("max_depth", 8),
                     "train_seconds": m["train_seconds"]})
        print(f"{d['name']}: " + ", ".join(f"{k} {v['overall']:.3f} N" for k, v in m["mae_n"].items()), flush=True)
    res = {
        "what": "seed 001's protocol (one position, 0.1/1/5 mm/s), test MAE (N) on unseen forces",
        "data": "simulated (tofjax's forward model)",
        "features": "seed 001's counts window (the configs' own), and the inversion features (one run)",
        "machine": f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPU cores (shared, loaded), "
                   f"JAX {jax.__version__} {jax.default_backend()} backend",
        "tofjax": tofjax.__version__,
        "runs": runs,
        "targets": {"mlp_rf_overall_max_n": 1.0, "forest_never_worse": True},
        "seconds": time.perf_counter() - t0,
    }
    atomic_write_text(target, json.dumps(res, indent=2) + "\n", overwrite=overwrite)
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/force_position", help="folder for force_position.json and .md")
    ap.add_argument("--work", default="out/force_position_work", help="folder for the data and run folders")
    ap.add_argument("--md", default=None, help="the markdown table (default OUT/force_position.md)")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--epochs", type=int, default=None)
    ap.add_argument("--no-independent", action="store_true")
    ap.add_argument("--seed001", action="store_true",
                    help="instead: seed 001's one-position protocol, derivative MLP + forest -> OUT/force_seed001.json")
    a = ap.parse_args(argv)
    tofjax.enable_x64()  # as `tofjax train`: the generator's lag filter; the models run in float32
    if a.seed001:
        return run_seed001(Path(a.out), overwrite=a.overwrite, work=Path(a.work))
    res = run(Path(a.out), overwrite=a.overwrite, epochs=a.epochs, independent=not a.no_independent, work=Path(a.work),
              md=Path(a.md) if a.md else None)
    print(markdown(res))
    return res


if __name__ == "__main__":
    main()
