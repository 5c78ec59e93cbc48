"""What one switch of the guided model costs: its variants timed side by side in one process (issue 14).

``tofjax bench tradeoff`` compares the guided optics with the default optics, each in a process of its own run; its
ratio moves by several percent from run to run on a shared VM. Here the guided model (skin contacts, every component
of the scene, ``ModelOptions(optics="guided", elevations=8)``, float64) is compiled once per variant of a
module-level switch of :mod:`tofjax.model.guided` (each variant built with its switch set, for the switches that act
when the model is built, and compiled as its own program: the switches key it) and the
variants are timed in alternating order, ``--repeats`` calls each; medians. Writes JSON.

    python experiments/bench_guided_switch.py --switch CONTACT_SHADOW --values true,false \\
        --out docs/results/bench_guided_switch_contact_shadow.json
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np


def _parse(value: str, like):
    if isinstance(like, bool):
        if value.lower() not in ("true", "false"):
            raise ValueError(f"expected true or false, got {value!r}")
        return value.lower() == "true"
    return type(like)(value)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--switch", required=True, help="a module-level switch of tofjax.model.guided, e.g. CONTACT_SHADOW")
    ap.add_argument("--values", required=True, help="comma-separated values to compare, e.g. true,false")
    ap.add_argument("--scene", default="touch-three-line", help="built-in scene (default: the bench's touch scene)")
    ap.add_argument("--repeats", type=int, default=601, help="timed calls per variant")
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    if a.repeats < 1:
        ap.error("--repeats must be >= 1")
    import tofjax

    tofjax.enable_x64()
    from tofjax.mc.prune import evaluate
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.model import guided as G
    from tofjax.model.contact import SkinContact
    from tofjax.outputs import OutputError, atomic_write_text, check_output
    from tofjax.scene import load_scene

    if not a.switch.isupper() or not hasattr(G, a.switch):
        ap.error(f"--switch: tofjax.model.guided has no switch {a.switch!r}")
    like = getattr(G, a.switch)
    try:
        values = [_parse(v, like) for v in a.values.split(",")]
        path = check_output(Path(a.out), overwrite=a.overwrite)
        scene = load_scene(a.scene)
    except (ValueError, OutputError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    opts = ModelOptions(optics="guided", elevations=8, skin=SkinContact() if scene.touches else None)
    params = Params.from_scene(scene)
    times = {str(v): [] for v in values}
    fs = {}
    try:
        for v in values:  # build and compile each variant with its switch set (some switches act at build time:
            setattr(G, a.switch, v)  # the reverberant field's segments, the tables), each its own program
            fs[str(v)] = functools.partial(evaluate, build_model(scene, opts, scene.components()))
            fs[str(v)](params).block_until_ready()
        for i in range(a.repeats):
            for v in (values if i % 2 == 0 else values[::-1]):
                setattr(G, a.switch, v)
                t = time.perf_counter()
                fs[str(v)](params).block_until_ready()
                times[str(v)].append(time.perf_counter() - t)
    finally:
        setattr(G, a.switch, like)
    med = {k: float(np.median(t)) for k, t in times.items()}
    result = {"study": f"cost of tofjax.model.guided.{a.switch}: variants side by side in one process",
              "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only",
              "scene": a.scene, "repeats": a.repeats, "median_s": med,
              "ratio_to_first": {k: med[k] / med[str(values[0])] for k in med}}
    atomic_write_text(path, json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
