"""Config-driven training runs: ``train(config) -> runs/<time>_<name>/``.

A run folder holds everything a researcher needs to trust and reuse it:

- ``config.toml`` / ``config.json``: the resolved config (every default filled in);
- ``meta.json``: versions, seed, precision, machine, data sizes, the window found,
  NaN frames dropped;
- ``metrics.csv``: one row per epoch, written as training goes;
- ``metrics.json``: MAE (N) overall and per indentation velocity on the unseen test
  captures, for the MLP alone and with the residual forest (``mae_n.mlp``,
  ``mae_n.mlp_rf``; an alternative reports under its kind), plus the hold-out split,
  operations per prediction and training times. Written last;
- ``model.eqx`` (a JSON header line + ``eqx.tree_serialise_leaves``), ``forest.npz``
  (the forest as arrays), or ``model.skops`` for scikit-learn alternatives (skops, a format
  that cannot run code on loading; pickles are refused);
- ``predictions.csv`` and figures like seed 001 Fig. 15-18.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime as _dt
import glob
import json
import math
import platform
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..capture import Capture, read_capture
from ..config import ConfigError, from_dict, load_toml, to_dict, toml_value
from ..errors import UserError
from .alternatives import GBOptions, NonlinearOptions, SVROptions, fit_alternative
from .features import (
    Dataset,
    FeatureConfig,
    FeatureError,
    Scaling,
    Window,
    build_dataset,
    find_window,
    normalise,
    select,
    split_indices,
)
from .forest import ForestArrays, ForestOptions, fit_forest, forest_operations, forest_predict, forest_to_arrays
from .generate import Protocol, generate, protocol_key
from .models import ForceMLP, MLPSpec, TrainOptions, build_mlp, mlp_spec, operations, train_mlp

__all__ = [
    "DataConfig",
    "ForcePredictor",
    "ModelConfig",
    "RunConfig",
    "load_predictor",
    "load_run_config",
    "predict_capture",
    "train",
]

KINDS = ("mlp", "deep_mlp", "nonlinear", "svr", "gb")
MODEL_FORMAT = "tofjax.force.model"


@dataclass(frozen=True)
class DataConfig:
    """Where the captures come from.

    With ``train`` empty, the protocol is simulated (and cached under ``cache_dir``
    by its hash, so runs on the same protocol share it). Otherwise ``train`` and
    ``test`` are capture files or glob patterns; each capture's velocity is read
    from its ``truth.velocity_mm_s`` (NaN if absent).
    """

    protocol: Protocol = field(default_factory=Protocol)
    train: tuple[str, ...] = ()
    test: tuple[str, ...] = ()
    cache_dir: str = "out/force-data"
    split: tuple[float, float, float] = (0.8, 0.1, 0.1)

    def __post_init__(self):
        if any(f < 0 for f in self.split) or abs(sum(self.split) - 1) > 1e-9 or self.split[0] == 0 or self.split[1] == 0:
            raise ConfigError(f"split: train/validation/hold-out fractions must be >= 0, sum to 1, with train and validation > 0; got {self.split!r}")
        if bool(self.train) != bool(self.test):
            raise ConfigError("train, test: give both (capture files) or neither (simulate the protocol)")


@dataclass(frozen=True)
class DeepOptions:
    hidden: tuple[int, ...] = (128, 128, 64, 32)


@dataclass(frozen=True)
class ModelConfig:
    """Which model: ``mlp`` (seed 001's, by input variant), ``deep_mlp``, ``nonlinear``, ``svr`` or ``gb``.

    Options of other kinds are refused (a table for a model that is not used is a mistake).
    """

    kind: str = "mlp"
    dropout: float = 0.3
    deep: DeepOptions | None = None
    nonlinear: NonlinearOptions | None = None
    svr: SVROptions | None = None
    gb: GBOptions | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ConfigError(f"kind: must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if not 0 <= self.dropout < 1:
            raise ConfigError(f"dropout: must be in [0, 1), got {self.dropout!r}")
        owner = {"deep": "deep_mlp", "nonlinear": "nonlinear", "svr": "svr", "gb": "gb"}
        for table, kind in owner.items():
            if getattr(self, table) is not None and self.kind != kind:
                raise ConfigError(f"{table}: options for kind = \"{kind}\" but kind = \"{self.kind}\"")

    def options(self):
        defaults = {"deep_mlp": ("deep", DeepOptions), "nonlinear": ("nonlinear", NonlinearOptions),
                    "svr": ("svr", SVROptions), "gb": ("gb", GBOptions)}
        if self.kind not in defaults:
            return None
        name, cls = defaults[self.kind]
        return getattr(self, name) or cls()

    @property
    def is_mlp(self) -> bool:
        return self.kind in ("mlp", "deep_mlp")


@dataclass(frozen=True)
class RunConfig:
    """A whole training run (``configs/force/*.toml``)."""

    name: str
    seed: int = 0
    precision: str = "float32"
    data: DataConfig = field(default_factory=DataConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    training: TrainOptions = field(default_factory=TrainOptions)
    forest: ForestOptions = field(default_factory=ForestOptions)
    plots: bool = True

    def __post_init__(self):
        if not self.name or any(c in self.name for c in "/\\ "):
            raise ConfigError(f"name: must be a non-empty name without slashes or spaces, got {self.name!r}")
        if self.precision != "float32":
            raise ConfigError(f"precision: only float32 is supported for force models, got {self.precision!r}")

    def to_dict(self) -> dict:
        return _drop_none(to_dict(self))


def _drop_none(d):
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, list):
        return [_drop_none(v) for v in d]
    return d


def run_config_from_dict(data: dict, source: str = "config") -> RunConfig:
    try:
        return from_dict(RunConfig, data)
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from None


def load_run_config(path: str | Path) -> RunConfig:
    """Load and validate a training config TOML; errors name the file and the key."""
    return run_config_from_dict(load_toml(path), str(path))


# ---- data --------------------------------------------------------------------------------


def _expand(patterns, what: str) -> list[Path]:
    paths: list[Path] = []
    for p in patterns:
        hits = sorted(glob.glob(p)) if any(c in p for c in "*?[") else [p]
        if not hits:
            raise ConfigError(f"data.{what}: {p!r} matches no file")
        paths += [Path(h) for h in hits]
    return paths


def load_data(cfg: DataConfig, *, progress: bool = False) -> tuple[list[Capture], list[Capture], list[str], list[str], dict]:
    """Training and test captures (simulated and cached, or read), their names, and where they came from."""
    if cfg.train:
        tr, te = _expand(cfg.train, "train"), _expand(cfg.test, "test")
        seen = {p.resolve(): p for p in tr}
        both = [str(p) for p in te if p.resolve() in seen]
        if both:
            raise ConfigError(f"data.test: {', '.join(both)} {'is' if len(both) == 1 else 'are'} also in data.train; "
                              "a test capture must be unseen in training (its MAE would measure memory)")
        info = {"source": "captures"}
    else:
        d = Path(cfg.cache_dir) / protocol_key(cfg.protocol)
        stamp = d / "complete.json"
        if not stamp.exists():
            # An incomplete cache (no stamp: an interrupted generation) is ours to replace.
            paths = generate(cfg.protocol, d, progress=progress, overwrite=True)
            stamp.write_text(json.dumps({k: [str(p) for p in v] for k, v in paths.items()}))
        paths = json.loads(stamp.read_text())
        tr = [Path(p) for p in paths["train"]]
        te = [Path(p) for k in ("test", "unseen", "two_contacts") for p in paths.get(k, [])]
        info = {"source": "simulated", "protocol": to_dict(cfg.protocol), "cache": str(d)}
    return [read_capture(p) for p in tr], [read_capture(p) for p in te], [str(p) for p in tr], [str(p) for p in te], info


# ---- the predictor -----------------------------------------------------------------------


class ForcePredictor(eqx.Module):
    """Raw features (window, derivative, baseline) -> (MLP force, MLP + forest force), in newtons.

    One jitted function: normalisation, the MLP and the forest's tree walk.
    """

    mlp: ForceMLP
    forest: ForestArrays | None
    lo: jax.Array
    hi: jax.Array
    force_lo: float
    force_span: float
    variant: str = eqx.field(static=True)
    extra_lo: jax.Array | None = None
    extra_hi: jax.Array | None = None
    base_lo: jax.Array | None = None
    base_hi: jax.Array | None = None

    def inputs(self, raw):
        x = normalise(raw, self.lo, self.hi, jnp, self.extra_lo, self.extra_hi, self.base_lo, self.base_hi)
        return select(x, self.variant, self.lo.shape[0], jnp).astype(jnp.float32)

    def __call__(self, raw):
        x = self.inputs(raw)
        f_mlp = self.mlp(x) * self.force_span + self.force_lo
        if self.forest is None:
            return f_mlp, f_mlp
        return f_mlp, f_mlp + forest_predict(self.forest, x)


@eqx.filter_jit
def predict_batch(predictor: ForcePredictor, raw):
    """Vectorised :class:`ForcePredictor` over frames: (n, features) -> ((n,), (n,))."""
    return jax.vmap(predictor)(jnp.asarray(raw, jnp.float32))


def _header(run_dir: Path) -> dict:
    path = run_dir / "model.json"
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: not a folder (a force run folder is expected)")
    if not path.exists():
        raise UserError(f"{run_dir}: not a force run (no model.json); train one with `tofjax train CONFIG`")
    try:
        header = json.loads(path.read_text())
    except (UnicodeDecodeError, ValueError) as e:
        raise UserError(f"{path}: not valid JSON: {e}") from None
    if not isinstance(header, dict):
        raise UserError(f"{path}: expected a JSON object")
    return header


def save_predictor(run_dir: Path, predictor: ForcePredictor, header: dict) -> None:
    (run_dir / "model.json").write_text(json.dumps(header, indent=2))
    with open(run_dir / "model.eqx", "wb") as f:
        f.write((json.dumps(header) + "\n").encode())
        eqx.tree_serialise_leaves(f, predictor.mlp)
    if predictor.forest is not None:
        np.savez_compressed(run_dir / "forest.npz", **predictor.forest.to_numpy())


def load_predictor(run_dir: str | Path):
    """The trained model of a run: a :class:`ForcePredictor` (MLPs) or a scikit-learn estimator, and its header."""
    run_dir = Path(run_dir)
    header = _header(run_dir)
    if header.get("format") != MODEL_FORMAT:
        raise UserError(f"{run_dir}: model.json is not a {MODEL_FORMAT} header")
    try:
        return _load_predictor(run_dir, header)
    except UserError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, OSError, RuntimeError, EOFError, zipfile.BadZipFile) as e:
        what = f"key {e}" if isinstance(e, KeyError) else f"{type(e).__name__}: {e}"
        raise UserError(f"{run_dir}: damaged run folder ({what})".splitlines()[0]) from None


def _extra_scaling(scaling: Scaling):
    """The predictor's ``extra_lo, extra_hi, base_lo, base_hi`` (None where the scaling has none)."""
    f = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    extra = (f(scaling.extra_lo), f(scaling.extra_hi)) if scaling.extra_lo.shape[0] else (None, None)
    base = (f(scaling.base_lo), f(scaling.base_hi)) if scaling.base_lo is not None else (None, None)
    return (*extra, *base)


def _load_predictor(run_dir: Path, header: dict):
    if header["kind"] not in ("mlp", "deep_mlp"):
        return _load_sklearn(run_dir), header
    scaling = Scaling.from_json(header["scaling"])
    if header["kind"] in ("mlp", "deep_mlp"):
        spec = MLPSpec.from_json(header["spec"])
        like = build_mlp(spec, jax.random.key(0))
        with open(run_dir / "model.eqx", "rb") as f:
            f.readline()
            mlp = eqx.tree_deserialise_leaves(f, like)
        forest = None
        if header.get("forest") and not (run_dir / "forest.npz").exists():
            raise UserError(f"{run_dir}: model.json names a residual forest but forest.npz is missing (a damaged run folder)")
        if header.get("forest"):
            with np.load(run_dir / "forest.npz") as npz:
                forest = ForestArrays.from_numpy(npz, str(run_dir / "forest.npz"))
        pred = ForcePredictor(
            mlp, forest, jnp.asarray(scaling.lo, jnp.float32), jnp.asarray(scaling.hi, jnp.float32),
            scaling.force_lo, scaling.force_hi - scaling.force_lo, header["features"]["variant"],
            *_extra_scaling(scaling),
        )
        return pred, header
    raise UserError(f"{run_dir}: model.json names kind {header['kind']!r}")


#: The only types a stored scikit-learn model may hold beyond what skops trusts by default:
#: the tree predictor of HistGradientBoostingRegressor (kind "gb").
_TRUSTED = ("sklearn.ensemble._hist_gradient_boosting.predictor.TreePredictor",)


def _save_sklearn(run_dir: Path, est) -> None:
    import skops.io as sio

    sio.dump(est, run_dir / "model.skops")


def _load_sklearn(run_dir: Path):
    """A scikit-learn model stored with skops, refusing any type outside the allowlist.

    ``model.pkl`` files (pickles, which run code when loaded) are never opened.
    """
    path = run_dir / "model.skops"
    if not path.exists():
        if (run_dir / "model.pkl").exists():
            raise UserError(
                f"{run_dir}: model.pkl is a pickle, which can run code when loaded; tofjax no longer loads "
                "them. Retrain the run (models are now stored as model.skops)"
            )
        raise UserError(f"{run_dir}: no model.skops (a scikit-learn model) in this run folder")
    import skops.io as sio

    try:
        untrusted = sio.get_untrusted_types(file=path)
    except Exception as e:  # a damaged or foreign file: skops raises many kinds
        raise UserError(f"{path}: not a skops model file: {type(e).__name__}: {e}") from None
    foreign = [t for t in untrusted if t not in _TRUSTED]
    if foreign:
        raise UserError(f"{path}: refusing to load types outside the allowlist: {', '.join(foreign[:3])}")
    try:
        return sio.load(path, trusted=list(untrusted))
    except Exception as e:
        raise UserError(f"{path}: cannot load the model: {type(e).__name__}: {e}") from None


def _predict(model, header: dict, raw: np.ndarray) -> dict[str, np.ndarray]:
    if isinstance(model, ForcePredictor):
        a, b = predict_batch(model, raw)
        out = {"mlp" if header["kind"] == "mlp" else header["kind"]: np.asarray(a, np.float64)}
        if model.forest is not None:
            out["mlp_rf"] = np.asarray(b, np.float64)
        return out
    sc = Scaling.from_json(header["scaling"])
    x = select(sc.normalise(raw), header["features"]["variant"], sc.lo.shape[0])
    y = model.predict(x) * (sc.force_hi - sc.force_lo) + sc.force_lo
    return {header["kind"]: np.asarray(y, np.float64)}


def predict_capture(
    run_dir: str | Path, capture: Capture | str | Path, *, baseline_frames: int | None = None
) -> dict[str, np.ndarray]:
    """Predict the force of every frame of a capture with a run's model.

    The capture's first ``baseline_frames`` frames (default: its ``truth.baseline_frames``,
    else the training config's) must show nothing touching: they are its baseline.
    Returns ``{"time": ..., "force": (reference, NaN if none), "<model>": ...}``; frames
    whose features are not finite get NaN. With several contacts (inversion features) the
    nearest is the first; contact ``k`` >= 2 adds ``force_contact<k>`` (its reference, from the
    capture's ``truth.contact_forces_n``, else the force channel) and ``<model>_contact<k>``. Raises :class:`FeatureError` when the
    capture's beams or bins do not match the trained model.
    """
    from .features import capture_rows

    if baseline_frames is not None and baseline_frames < 1:
        raise UserError(f"--baseline-frames: must be >= 1 (the features need a no-touch baseline), got {baseline_frames}")
    model, header = load_predictor(run_dir)
    src = str(capture) if not isinstance(capture, Capture) else "capture"
    cap = read_capture(capture) if not isinstance(capture, Capture) else capture
    window = Window.from_json(header["window"])
    fcfg = from_dict(FeatureConfig, header["features"])
    if baseline_frames is not None or "baseline_frames" in cap.truth:
        fcfg = dataclasses.replace(fcfg, baseline_frames=baseline_frames if baseline_frames is not None
                                   else int(cap.truth["baseline_frames"]))
    out = {"time": cap.timestamps, "force": cap.force if cap.force is not None else np.full(cap.n_frames, np.nan)}
    for j, (raw, valid, f) in enumerate(capture_rows(cap, window, fcfg, src)):
        preds = _predict(model, header, np.where(np.isfinite(raw), raw, 0.0))
        if j:  # a further contact: its own reference force (the capture's truth), then its predictions
            out[f"force_contact{j + 1}"] = np.asarray(f, float)
        for k, v in preds.items():
            out[k if j == 0 else f"{k}_contact{j + 1}"] = np.where(valid, v, np.nan)
    return out


# ---- metrics -----------------------------------------------------------------------------


#: Test splits (``truth.split`` of the test captures) and their names in ``metrics.json``.
SPLITS = {"test": "seen", "unseen": "unseen", "two_contacts": "two_contacts"}


def mae_by_velocity(pred: np.ndarray, ds: Dataset) -> dict:
    """MAE overall (single-contact test frames: seen and unseen positions), per velocity (the same
    frames) and per split (``seen``, ``unseen``, ``two_contacts``: each contact of each frame)."""
    err = np.abs(pred - ds.force)
    single = ds.split != "two_contacts"
    if not single.any():
        single = np.ones(len(err), bool)
    by = {}
    for v in sorted(set(ds.velocity[single & np.isfinite(ds.velocity)].tolist())):
        by[f"{v:.1f}" if v >= 0.1 else f"{v:g}"] = float(err[single & (ds.velocity == v)].mean())
    splits = {name: float(err[ds.split == key].mean()) for key, name in SPLITS.items() if (ds.split == key).any()}
    return {"overall": float(err[single].mean()), "by_velocity_mm_s": by, "by_split": splits}


def _versions() -> dict:
    import optax
    import sklearn

    import tofjax

    return {
        "tofjax": tofjax.__version__,
        "jax": jax.__version__,
        "equinox": eqx.__version__,
        "optax": optax.__version__,
        "scikit-learn": sklearn.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def dump_toml(d: dict, prefix: str = "") -> str:
    """Nested dicts as TOML tables (what :func:`load_run_config` reads back)."""
    lines = [f"{k} = {toml_value(v)}" for k, v in d.items() if not isinstance(v, dict)]
    for k, v in d.items():
        if isinstance(v, dict):
            name = f"{prefix}{k}"
            lines += ["", f"[{name}]", dump_toml(v, name + ".").rstrip("\n")]
    return "\n".join(line for line in lines) + "\n"


def _run_dir(runs_dir: Path, name: str) -> Path:
    """A new, unused run folder name; the folder itself is written as ``.<name>.partial``
    and renamed to it when the run is complete (issue 15: whole or not at all)."""
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    d = runs_dir / f"{stamp}_{name}"
    i = 1
    while d.exists() or _partial(d).exists():
        d = runs_dir / f"{stamp}-{i}_{name}"
        i += 1
    try:
        _partial(d).mkdir(parents=True)
    except OSError as e:
        raise UserError(f"{runs_dir}: cannot create a run folder: {e.strerror or e}") from None
    return d


def _partial(d: Path) -> Path:
    return d.with_name(f".{d.name}.partial")


def _finish_run_dir(partial: Path, final: Path) -> Path:
    import os

    try:
        os.rename(partial, final)  # fails rather than merge if the name was taken meanwhile
    except OSError as e:
        raise UserError(f"{final}: cannot finish the run folder ({e.strerror or e}); the run is in {partial}") from None
    return final


def train(config: RunConfig, runs_dir: str | Path = "runs", *, progress: bool = False, log=print) -> Path:
    """Train one config and write its run folder; returns the folder.

    **Arguments:**

    - ``config``: the run (data, features, model, training, forest).
    - ``runs_dir``: where run folders go (``runs/<time>_<name>/``).
    - ``progress``: tqdm bars for generation and epochs.
    - ``log``: where one-line progress messages go (``None``: silent).
    """
    say = log or (lambda *_: None)
    if not config.data.train:  # the protocol's positions lie on the skin: refused before a run folder exists
        try:
            config.data.protocol.load_scene()
        except ConfigError as e:
            raise ConfigError(f"{config.name}: data.protocol.{e}") from None
    final = _run_dir(Path(runs_dir), config.name)
    out = _partial(final)
    cfg_dict = config.to_dict()
    (out / "config.toml").write_text(dump_toml(cfg_dict))
    (out / "config.json").write_text(json.dumps(cfg_dict, indent=2))
    t_start = time.perf_counter()

    train_caps, test_caps, train_names, test_names, data_info = load_data(config.data, progress=progress)
    t_data = time.perf_counter() - t_start
    fc = config.features
    window = find_window(train_caps, fc)
    ds = build_dataset(train_caps, window, fc, names=train_names)
    dt = build_dataset(test_caps, window, fc, names=test_names)
    if len(ds) < 10:
        raise FeatureError(f"only {len(ds)} valid training frames")
    if ds.n_nan_frames or dt.n_nan_frames:
        say(f"dropped {ds.n_dropped} training and {dt.n_dropped} test frames "
            f"({ds.n_nan_frames} + {dt.n_nan_frames} with NaN values)")
    i_tr, i_va, i_ho = split_indices(len(ds), config.data.split, config.seed)
    n = window.size
    scaling = Scaling.fit(ds.raw[i_tr][:, :n], ds.force[i_tr], fc.normalisation, ds.raw[i_tr][:, 3 * n :],
                          ds.raw[i_tr][:, 2 * n : 3 * n] if fc.source == "inversion" else None)
    span = scaling.force_hi - scaling.force_lo
    n_extra = ds.raw.shape[1] - 3 * n

    def X(raw):
        return select(scaling.normalise(raw), fc.variant, n)

    def Y(f):
        return (f - scaling.force_lo) / span

    x_all = X(ds.raw)
    meta = {
        "name": config.name,
        "seed": config.seed,
        "precision": config.precision,
        "versions": _versions(),
        "machine": {"platform": platform.platform(), "processor": platform.machine(), "jax_backend": jax.default_backend(),
                    "cpu_count": __import__("os").cpu_count()},
        "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "data": data_info | {"train_captures": train_names, "test_captures": test_names},
        "window": window.to_json(),
        "frames": {"train": int(len(i_tr)), "validation": int(len(i_va)), "holdout": int(len(i_ho)), "test": len(dt),
                   "nan_frames_train": ds.n_nan_frames, "nan_frames_test": dt.n_nan_frames,
                   "dropped_train": ds.n_dropped, "dropped_test": dt.n_dropped},
    }
    (out / "meta.json").write_text(json.dumps(meta, indent=2))
    say(f"{config.name}: window sensor {window.sensor}, bins {window.start_bin}-{window.start_bin + window.bins - 1}; "
        f"{len(i_tr)} train / {len(i_va)} val / {len(i_ho)} hold-out / {len(dt)} test frames")

    header = {
        "format": MODEL_FORMAT,
        "version": 2,
        "kind": config.model.kind,
        "features": to_dict(fc),
        "window": window.to_json(),
        "scaling": scaling.to_json(),
    }
    metrics_csv = out / "metrics.csv"
    timings: dict[str, float] = {"data_s": t_data}
    ops: dict[str, int] = {}
    key = jax.random.key(config.seed)
    if config.model.is_mlp:
        kind = config.model.kind
        spec = mlp_spec(kind, fc.variant, n, dropout=config.model.dropout, extra=n_extra,
                        **({"deep_hidden": config.model.options().hidden} if kind == "deep_mlp" else {}))
        k_init, k_train = jax.random.split(key)
        model = build_mlp(spec, k_init)
        with open(metrics_csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, ["epoch", "train_loss", "val_loss", "val_mae_n", "learning_rate", "seconds"])
            w.writeheader()

            def on_epoch(row):
                w.writerow(row | {"val_mae_n": math.sqrt(row["val_loss"]) * span})  # RMSE proxy in N
                fh.flush()

            t0 = time.perf_counter()
            res = train_mlp(model, x_all[i_tr], Y(ds.force[i_tr]), x_all[i_va], Y(ds.force[i_va]), config.training,
                            key=k_train, on_epoch=on_epoch, progress=progress)
            timings["mlp_s"] = time.perf_counter() - t0
        mlp = res.model
        say(f"  MLP: {res.epochs_run} epochs in {res.seconds:.1f} s, best epoch {res.best_epoch}")
        pred0 = ForcePredictor(mlp, None, jnp.asarray(scaling.lo, jnp.float32), jnp.asarray(scaling.hi, jnp.float32),
                               scaling.force_lo, span, fc.variant, *_extra_scaling(scaling))
        f_mlp_train = np.asarray(predict_batch(pred0, ds.raw[i_tr])[0], np.float64)
        ops["mlp" if kind == "mlp" else kind] = operations(spec) + 2 * x_all.shape[1] + 2
        forest = None
        if config.forest.enabled and kind == "mlp":
            t0 = time.perf_counter()
            rf = fit_forest(x_all[i_tr], ds.force[i_tr] - f_mlp_train, config.forest, config.seed)
            forest = forest_to_arrays(rf)
            timings["forest_s"] = time.perf_counter() - t0
            ops["mlp_rf"] = ops["mlp"] + forest_operations(rf) + 1
            say(f"  forest: {config.forest.trees} trees, depth {forest.depth}, {timings['forest_s']:.1f} s")
        predictor = ForcePredictor(mlp, forest, pred0.lo, pred0.hi, pred0.force_lo, pred0.force_span, fc.variant,
                                   *_extra_scaling(scaling))
        header |= {"spec": spec.to_json(), "forest": forest is not None,
                   "best_epoch": res.best_epoch, "epochs_run": res.epochs_run}
        save_predictor(out, predictor, header)
        model_obj = predictor
    else:
        kind = config.model.kind
        t0 = time.perf_counter()
        est, n_ops = fit_alternative(kind, config.model.options(), x_all[i_tr], Y(ds.force[i_tr]),
                                     x_all[i_va], Y(ds.force[i_va]), config.seed)
        timings[f"{kind}_s"] = time.perf_counter() - t0
        ops[kind] = n_ops + 2 * x_all.shape[1] + 2
        with open(metrics_csv, "w") as fh:
            fh.write("epoch,train_loss,val_loss,val_mae_n,learning_rate,seconds\n")
            r = est.predict(x_all[i_va]) - Y(ds.force[i_va])
            fh.write(f"1,,{float(np.mean(r**2))},{float(np.mean(np.abs(r))) * span},,{timings[f'{kind}_s']}\n")
        (out / "model.json").write_text(json.dumps(header, indent=2))
        _save_sklearn(out, est)
        model_obj = est
        say(f"  {kind}: fitted in {timings[f'{kind}_s']:.1f} s")

    test_pred = _predict(model_obj, header, dt.raw)
    ho = ds.subset(i_ho)
    ho_pred = _predict(model_obj, header, ho.raw) if len(ho) else {}
    metrics = {
        "name": config.name,
        "kind": config.model.kind,
        "variant": fc.variant,
        "data": "simulated" if data_info["source"] == "simulated" else "captures",
        "mae_n": {k: mae_by_velocity(v, dt) for k, v in test_pred.items()},
        "holdout_mae_n": {k: float(np.mean(np.abs(v - ho.force))) for k, v in ho_pred.items()},
        "test_frames_by_split": {name: int((dt.split == key).sum()) for key, name in SPLITS.items() if (dt.split == key).any()},
        "operations_per_prediction": ops,
        "train_seconds": timings,
        "frames": meta["frames"],
        "window": window.to_json(),
    }
    if "mlp" in test_pred and "mlp_rf" in test_pred:
        a, b = metrics["mae_n"]["mlp"]["overall"], metrics["mae_n"]["mlp_rf"]["overall"]
        metrics["forest_mae_reduction"] = (a - b) / a
    _write_predictions(out / "predictions.csv", dt, test_pred, test_names)
    if config.plots:
        from .plots import plot_by_velocity, plot_mlp_vs_forest

        plot_mlp_vs_forest(dt, test_pred, out / "fig15_mlp_vs_mlp_rf.png")
        plot_by_velocity(dt, test_pred, out / "fig16_by_velocity.png", title=f"{config.name}")
    timings["total_s"] = time.perf_counter() - t_start
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    out = _finish_run_dir(out, final)
    best = min(metrics["mae_n"], key=lambda k: metrics["mae_n"][k]["overall"])
    say("  test MAE: " + ", ".join(f"{k} {v['overall']:.3f} N" for k, v in metrics["mae_n"].items())
        + f" (best {best}); wrote {out}")
    return out


def _write_predictions(path: Path, ds: Dataset, preds: dict, names: list[str]) -> None:
    keys = list(preds)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["capture", "velocity_mm_s", "time_s", "force_n", *[f"{k}_n" for k in keys]])
        for i in range(len(ds)):
            w.writerow([Path(names[int(ds.capture[i])]).name, ds.velocity[i], f"{ds.time[i]:.4f}", f"{ds.force[i]:.4f}",
                        *[f"{preds[k][i]:.4f}" for k in keys]])


def write_prediction_csv(path: str | Path, pred: dict) -> Path:
    """Write :func:`predict_capture`'s output as CSV (one row per frame)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = [k for k in pred if k not in ("time", "force")]  # further contacts' references, then the models
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", "force_n", *[f"{k}_n" for k in keys]])
        for i in range(len(pred["time"])):
            w.writerow([f"{pred['time'][i]:.4f}", f"{pred['force'][i]:.4f}", *[f"{pred[k][i]:.4f}" for k in keys]])
    return path


def table(run_dirs) -> str:
    """A Table I-like comparison (MAE in N per velocity, overall, operations) of run folders."""
    rows = []
    for d in run_dirs:
        d = Path(d)
        p = d / "metrics.json"
        if not p.exists():
            raise UserError(f"{d}: no metrics.json (not a finished force run)")
        try:
            m = json.loads(p.read_text())
            for model, v in m["mae_n"].items():
                rows.append((m["name"], m.get("variant", ""), model, v, m["operations_per_prediction"].get(model)))
                float(v["overall"]), dict(v["by_velocity_mm_s"])
        except (UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as e:
            what = f"key {e}" if isinstance(e, KeyError) else f"{type(e).__name__}: {e}"
            raise UserError(f"{p}: not a force run's metrics ({what})".splitlines()[0]) from None
    vels = sorted({k for r in rows for k in r[3]["by_velocity_mm_s"]}, key=float)
    head = ["run", "input", "model", *[f"v={v} mm/s" for v in vels], "overall", "ops/prediction"]
    lines = [head]
    for name, variant, model, v, op in rows:
        lines.append([name, variant, model, *[f"{v['by_velocity_mm_s'][k]:.3f}" if k in v["by_velocity_mm_s"] else "-" for k in vels],
                      f"{v['overall']:.3f}", f"{op:,}" if op is not None else "-"])
    widths = [max(len(str(r[i])) for r in lines) for i in range(len(head))]
    out = ["  ".join(str(c).ljust(w) for c, w in zip(r, widths)) for r in lines]
    out.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(out) + "\nMAE in N on the test set (unseen forces)."
