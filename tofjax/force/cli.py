"""``tofjax train``, ``tofjax predict``, ``tofjax table`` and ``tofjax force-data``: thin wrappers of the library."""

from __future__ import annotations

from pathlib import Path


def _cmd_train(a) -> int:
    from .train import load_run_config, train

    for path in a.config:
        train(load_run_config(path), a.runs, progress=not a.quiet)
    return 0


def _cmd_predict(a) -> int:
    import numpy as np

    from .train import predict_capture, write_prediction_csv

    from ..outputs import atomic_path

    pred = predict_capture(a.run, a.capture, baseline_frames=a.baseline_frames)
    with atomic_path(a.out) as tmp:
        write_prediction_csv(tmp, pred)
    keys = [k for k in pred if k not in ("time",) and not k.startswith("force")]
    msg = f"wrote {a.out}: {len(pred['time'])} frames, columns {', '.join(k + '_n' for k in keys)}"

    def reference(k):  # the reference force of k's contact: "force", or "force_contact<n>"
        return pred.get("force" + (k[k.index("_contact"):] if "_contact" in k else ""))

    parts = []
    for k in keys:
        ref = reference(k)
        if ref is not None and np.isfinite(ref).any():
            ok = np.isfinite(ref)
            parts.append(f"{k} {np.nanmean(np.abs(pred[k][ok] - ref[ok])):.3f} N")
    if parts:
        msg += "; MAE against the capture's force: " + ", ".join(parts)
    print(msg)
    return 0


def _cmd_table(a) -> int:
    from .train import table

    dirs = []
    for r in a.runs:
        p = Path(r)
        if (p / "metrics.json").exists():
            dirs.append(p)
        elif p.is_dir():
            dirs += sorted(d for d in p.iterdir() if (d / "metrics.json").exists())
    if not dirs:
        from ..errors import UserError

        raise UserError(f"no finished force runs (folders with metrics.json) in {', '.join(a.runs)}")
    print(table(dirs))
    return 0


def _cmd_data(a) -> int:
    from .generate import generate, protocol_from_dict
    from ..config import load_toml

    p = protocol_from_dict(load_toml(a.protocol) if a.protocol else {}, a.protocol or "protocol")
    paths = generate(p, a.out, progress=True, overwrite=a.overwrite)
    extra = "".join(f", {len(paths[k])} {k.replace('_', ' ')}" for k in ("unseen", "two_contacts") if k in paths)
    print(f"wrote {len(paths['train'])} training and {len(paths['test'])} test captures{extra} to {a.out}/")
    return 0


def register(sub) -> None:
    s = sub.add_parser("train", help="train a force model from a config (configs/force/*.toml) into runs/")
    s.add_argument("config", nargs="+", help="training config TOML file(s)")
    s.add_argument("--runs", default="runs", help="folder for run folders (default runs/)")
    s.add_argument("--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_train)

    s = sub.add_parser("predict", help="predict the force of every frame of a capture with a trained run")
    s.add_argument("run", help="run folder (runs/<time>_<name>)")
    s.add_argument("capture", help="capture file (.h5)")
    s.add_argument("--out", required=True, help="output CSV")
    s.add_argument("--baseline-frames", type=int, default=None,
                   help="no-touch frames at the start of the capture (default: the capture's truth.baseline_frames)")
    s.set_defaults(func=_cmd_predict)

    s = sub.add_parser("table", help="Table I-like comparison of force runs (MAE per velocity, operations)")
    s.add_argument("runs", nargs="+", help="run folders, or folders holding them")
    s.set_defaults(func=_cmd_table)

    s = sub.add_parser("force-data", help="simulate seed 001's indentation protocol as captures with a force channel")
    s.add_argument("--protocol", help="protocol TOML (keys of tofjax.force.generate.Protocol; default: seed 001's)")
    s.add_argument("--out", required=True, help="output folder")
    s.set_defaults(func=_cmd_data)
