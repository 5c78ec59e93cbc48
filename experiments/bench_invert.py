"""Benchmark: correction (Algorithm 1) plus tactile map (Eq. 8) for 6-sensor frames on a 1 mm grid.

Times, in one run and on the same frames: the jitted JAX pipeline for one frame and for a
batch of frames, and the same work written plainly in NumPy (a gather with the same
precomputed index map). Also the float32 error against float64 and the Eq. 8 variant
(constant value per zone: half the gathers). Medians of repeated calls (shared machines
are noisy). Writes ``bench_invert.json``.

    python experiments/bench_invert.py --out out/bench_invert
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import tofjax
from tofjax.invert.maps import MapOptions
from tofjax.invert.pipeline import InvertOptions, build_inverter
from tofjax.invert.synth import random_contacts, simulate_contacts
from tofjax.scene import load_scene
from tofjax.simulate import simulate


def _median(f, repeats):
    f()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def numpy_pipeline(baseline, gain, early, index, weight):
    """The same correction and map in plain NumPy: (h - B) minus its pre-emission (ambient)
    mean, times the gain, clip, gather, weighted sum."""

    def correct(H):
        d = H - baseline
        return np.maximum((d - (d @ early)[..., None]) * gain, 0.0)

    def one(h):
        return (correct(h).ravel()[index] * weight).sum(-1)

    def batch(H):
        c = correct(H).reshape(len(H), -1)
        return np.einsum("fpj,pj->fp", c[:, index], weight)

    return one, batch


def run(out: Path, resolution_m: float = 0.001, batch: int = 64, repeats: int = 30) -> dict:
    scene = load_scene("optoskin")
    base = simulate(scene.without_touches(), 20, 0).mean()
    C = random_contacts(scene, batch, 6, seed=1)
    H = simulate_contacts(scene, C, seed=2)
    rows = {}
    for angular in ("linear", "zone"):
        for dtype in ("float32", "float64"):
            inv = build_inverter(
                scene,
                base,
                InvertOptions(method="full", maps=MapOptions(resolution_m=resolution_m, angular=angular), dtype=dtype),
            )
            dt = inv.corrector.gain.dtype
            h1 = jnp.asarray(H[0], dt)
            Hb = jnp.asarray(H, dt)
            one = _median(lambda: jax.block_until_ready(inv.map_frame(h1)), repeats)
            many = _median(
                lambda: jax.block_until_ready(inv._batch(inv.corrector, inv.operator, Hb)), max(3, repeats // 5)
            )
            rows[(angular, dtype)] = {"one_frame_ms": 1e3 * one, "batch_frames_per_s": batch / many, "inv": inv}
    # Plain NumPy, float32, the same index map.
    inv = rows[("linear", "float32")]["inv"]
    b, g, e = (np.asarray(x) for x in (inv.corrector.baseline, inv.corrector.gain, inv.corrector.early))
    idx, w = np.asarray(inv.operator.index), np.asarray(inv.operator.weight)
    np_one, np_batch = numpy_pipeline(b, g, e, idx, w)
    H32 = H.astype(np.float32)
    np_one_s = _median(lambda: np_one(H32[0]), max(3, repeats // 3))
    nb = min(batch, 32)
    np_batch_s = _median(lambda: np_batch(H32[:nb]), 3)
    mb_np = np_batch(H32[:2])
    mb_jax = np.asarray(inv._batch(inv.corrector, inv.operator, jnp.asarray(H32[:2]))[0]).reshape(2, -1)
    ref = np.asarray(rows[("linear", "float64")]["inv"].map_frame(jnp.asarray(H[0], jnp.float64)))
    m32 = np.asarray(inv.map_frame(jnp.asarray(H[0], jnp.float32)))
    mnp = np_one(H32[0]).reshape(ref.shape)
    grid = inv.grid
    result = {
        "benchmark": "correction + tactile map, one 6-sensor frame",
        "data": "simulated (default OptoSkin scene, 6 contacts, photon noise)",
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip()
        + f", {os.cpu_count()} CPUs, shared, JAX {jax.__version__} CPU backend",
        "grid": f"{grid.nx} x {grid.ny} px at {resolution_m * 1000:g} mm",
        "pixels": grid.nx * grid.ny,
        "gathers_per_frame": int(np.count_nonzero(w)),
        "batch": batch,
        "jax": {f"{a}/{d}": {k: v for k, v in r.items() if k != "inv"} for (a, d), r in rows.items()},
        "numpy_float32_linear": {"one_frame_ms": 1e3 * np_one_s, "batch_frames_per_s": nb / np_batch_s},
        "float32_max_rel_error": float(np.max(np.abs(m32 - ref)) / np.max(np.abs(ref))),
        "numpy_vs_jax_max_rel_diff": float(
            max(
                np.max(np.abs(mnp - m32)) / np.max(np.abs(m32)), np.max(np.abs(mb_np - mb_jax)) / np.max(np.abs(mb_jax))
            )
        ),
        "targets": {"one_frame_ms": 1.0, "batch_frames_per_s": 5000},
    }
    j = result["jax"]["linear/float32"]
    result["speedup_vs_numpy"] = {
        "one_frame": result["numpy_float32_linear"]["one_frame_ms"] / j["one_frame_ms"],
        "batch": j["batch_frames_per_s"] / result["numpy_float32_linear"]["batch_frames_per_s"],
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_invert.json").write_text(json.dumps(result, indent=2))
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/bench_invert")
    ap.add_argument("--resolution-mm", type=float, default=1.0)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=30)
    a = ap.parse_args(argv)
    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    tofjax.enable_x64()  # float64 reference; the timed pipeline is float32
    r = run(Path(a.out), a.resolution_mm / 1000.0, a.batch, a.repeats)
    print(json.dumps({k: v for k, v in r.items() if k not in ("targets",)}, indent=1))
    print(f"wrote {a.out}/bench_invert.json")


if __name__ == "__main__":
    main()
