"""Study: seed 001 Table I on the simulated indentation protocol, and the speed benchmark.

Trains every config of the study (the three MLPs with their residual forests, and
the four alternatives for each input variant) on the same simulated protocol,
then writes:

- ``force.json``: every run's MAE (overall and per velocity), the forest's MAE
  reduction per input variant, operations per prediction, training time per
  model, and the warm time of one MLP + forest prediction (median);
- ``force.md``: the Table I-like table for the README;
- ``force_velocity.png``: MAE against indentation velocity for every model.

    python experiments/study_force.py --config configs/studies/force.toml --out out/force_study
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from tofjax.config import from_dict, load_toml
from tofjax.force.train import RunConfig, load_predictor, load_run_config, run_config_from_dict, train
from tofjax.timing import median_seconds

ROOT = Path(__file__).parents[1]


@dataclass(frozen=True)
class ForceStudyConfig:
    """Which runs, and what to override in all of them (for a fast version)."""

    mlp_configs: tuple[str, ...] = ("configs/force/mlp_single.toml", "configs/force/mlp_dual.toml",
                                    "configs/force/mlp_derivative.toml", "configs/force/mlp_single_nodrop.toml",
                                    "configs/force/mlp_dual_nodrop.toml", "configs/force/mlp_derivative_nodrop.toml")
    alternative_configs: tuple[str, ...] = ("configs/force/nonlinear.toml", "configs/force/svr.toml",
                                            "configs/force/deep_mlp.toml", "configs/force/gradient_boosting.toml")
    #: Every alternative is trained on each of these input variants (Table I).
    variants: tuple[str, ...] = ("single", "dual", "derivative")
    #: Tables merged into every run config, e.g. a smaller protocol and fewer epochs.
    override: dict = field(default_factory=dict)
    prediction_repeats: int = 2000


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _configs(cfg: ForceStudyConfig) -> list[RunConfig]:
    out = []
    for p in cfg.mlp_configs:
        base = load_run_config(ROOT / p).to_dict()
        out.append(run_config_from_dict(_merge(base, cfg.override), p))
    for p in cfg.alternative_configs:
        base = load_run_config(ROOT / p).to_dict()
        for v in cfg.variants:
            d = _merge(_merge(base, cfg.override), {"features": {"variant": v}, "name": f"{base['name']}_{v}"})
            out.append(run_config_from_dict(d, p))
    return out


def time_one_prediction(run_dir: Path, repeats: int) -> dict:
    """Warm time of one frame through the jitted MLP + forest predictor (median)."""
    pred, header = load_predictor(run_dir)
    n = 3 * len(header["scaling"]["lo"])
    x = jnp.asarray(np.random.default_rng(0).uniform(0, 1000, n), jnp.float32)
    f = jax.jit(lambda r: pred(r))
    mlp_only = jax.jit(lambda r: pred.mlp(pred.inputs(r)))
    return {"mlp_rf_us": median_seconds(f, x, repeats) * 1e6, "mlp_us": median_seconds(mlp_only, x, repeats) * 1e6}


def run(cfg: ForceStudyConfig, out: Path, *, progress: bool = True) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    runs_dir = out / "runs"
    results = []
    t0 = time.perf_counter()
    for rc in _configs(cfg):
        print(f"--- {rc.name}", flush=True)
        d = train(rc, runs_dir, progress=False)
        m = json.loads((d / "metrics.json").read_text())
        m["run_dir"] = str(d)
        if rc.model.kind == "mlp":
            m["prediction_time"] = time_one_prediction(d, cfg.prediction_repeats)
        results.append(m)
    reductions = {m["name"]: m["forest_mae_reduction"] for m in results if "forest_mae_reduction" in m}
    mlps = [m for m in results if m["kind"] == "mlp"]
    best = min(mlps, key=lambda m: m["mae_n"]["mlp_rf"]["overall"]) if mlps else None
    summary = {
        "data": "simulated",
        "machine": f"{platform.machine()} {platform.system()}, {__import__('os').cpu_count()} CPU cores (shared), "
                   f"JAX {jax.__version__} {jax.default_backend()} backend",
        "study_seconds": time.perf_counter() - t0,
        "config": dataclasses.asdict(cfg),
        "runs": results,
        "forest_mae_reduction_by_run": reductions,
        "best_mlp_rf": None if best is None else {"name": best["name"], "overall_mae_n": best["mae_n"]["mlp_rf"]["overall"]},
        "mlp_rf_train_seconds": {m["name"]: m["train_seconds"].get("mlp_s", 0) + m["train_seconds"].get("forest_s", 0)
                                 for m in mlps},
        "prediction_time_us": {m["name"]: m["prediction_time"] for m in mlps},
    }
    (out / "force.json").write_text(json.dumps(summary, indent=2))
    (out / "force.md").write_text(markdown(summary))
    plot_velocity(summary, out / "force_velocity.png")
    print(markdown(summary))
    return summary


def markdown(s: dict) -> str:
    rows = []
    for m in s["runs"]:
        for model, v in m["mae_n"].items():
            if m["kind"] != "mlp":  # runs before deep MLPs reported under their own kind
                model, v = m["kind"], v
            label = {"mlp": "MLP only", "mlp_rf": "MLP + RF", "deep_mlp": "deep MLP", "gb": "gradient boosting",
                     "svr": "SVR", "nonlinear": "nonlinear regression"}.get(model, model)
            op = m["operations_per_prediction"].get(model, next(iter(m["operations_per_prediction"].values())))
            variant = m["variant"] + (" (no dropout)" if m["name"].endswith("nodrop") else "")
            rows.append((label, variant, v, op))
    vels = sorted({k for r in rows for k in r[2]["by_velocity_mm_s"]}, key=float)
    order = ["MLP only", "MLP + RF", "nonlinear regression", "SVR", "deep MLP", "gradient boosting"]
    rows.sort(key=lambda r: (order.index(r[0]) if r[0] in order else 99, r[1]))
    head = "| model | input | " + " | ".join(f"v = {v} mm/s" for v in vels) + " | overall | operations / prediction |"
    lines = [head, "|" + "---|" * (4 + len(vels))]
    for label, variant, v, op in rows:
        lines.append(f"| {label} | {variant} | " + " | ".join(f"{v['by_velocity_mm_s'][k]:.2f}" for k in vels)
                     + f" | **{v['overall']:.2f}** | {op:,} |")
    lines.append("")
    lines.append("MAE in N on the unseen test forces (simulated). Forest MAE reduction against the MLP alone: "
                 + ", ".join(f"{k} {100 * v:.0f}%" for k, v in s["forest_mae_reduction_by_run"].items()) + ".")
    if s["prediction_time_us"]:
        lines.append("One warm prediction (median): " + ", ".join(
            f"{k}: MLP {v['mlp_us']:.0f} us, MLP + RF {v['mlp_rf_us']:.0f} us" for k, v in s["prediction_time_us"].items()) + ".")
        lines.append("Training MLP + RF: " + ", ".join(f"{k} {v:.0f} s" for k, v in s["mlp_rf_train_seconds"].items())
                     + f". Machine: {s['machine']}.")
    return "\n".join(lines) + "\n"


def plot_velocity(s: dict, path: Path) -> Path:
    from tofjax.plot import plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for m in s["runs"]:
        for model, v in m["mae_n"].items():
            model = model if m["kind"] == "mlp" else m["kind"]
            ks = sorted(v["by_velocity_mm_s"], key=float)
            style = "-" if model == "mlp_rf" else ("--" if model == "mlp" else ":")
            ax.plot([float(k) for k in ks], [v["by_velocity_mm_s"][k] for k in ks], style, marker="o", ms=3,
                    label=f"{model} ({m['name'].replace('_nodrop', ', no dropout').split('_', 1)[-1] if m['kind'] == 'mlp' else m['variant']})")
    ax.set_xscale("log")
    ax.set_xlabel("indentation velocity (mm/s)")
    ax.set_ylabel("test MAE (N)")
    ax.set_title("Force MAE against indentation velocity (simulated)")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "studies" / "force.toml"))
    ap.add_argument("--out", default="out/force_study")
    ap.add_argument("--report", action="store_true", help="only rewrite force.md and the plot from force.json")
    ap.add_argument("--retime", action="store_true", help="re-time the saved predictors, then --report")
    a = ap.parse_args(argv)
    if a.report or a.retime:
        s = json.loads((Path(a.out) / "force.json").read_text())
        if a.retime:  # time the saved predictors again (e.g. on a quieter machine)
            for m in s["runs"]:
                if m["kind"] == "mlp":
                    m["prediction_time"] = time_one_prediction(Path(m["run_dir"]), s["config"]["prediction_repeats"])
            s["prediction_time_us"] = {m["name"]: m["prediction_time"] for m in s["runs"] if m["kind"] == "mlp"}
            (Path(a.out) / "force.json").write_text(json.dumps(s, indent=2))
        (Path(a.out) / "force.md").write_text(markdown(s))
        plot_velocity(s, Path(a.out) / "force_velocity.png")
        print(markdown(s))
        return s
    import tofjax

    tofjax.enable_x64()  # the generator's lag filter; the models themselves run in float32
    return run(load_study_config(a.config), Path(a.out))


def load_study_config(path) -> ForceStudyConfig:
    """The study TOML: the ForceStudyConfig keys, and an ``[override]`` table merged into every run config."""
    data = load_toml(path)
    override = data.pop("override", {})
    return dataclasses.replace(from_dict(ForceStudyConfig, data, str(path)), override=override)


if __name__ == "__main__":
    main()
