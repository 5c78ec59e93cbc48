"""``tofjax study CONFIG --out DIR``: a study on every device of one or several processes.

Two kinds of study config (TOML, unknown keys refused):

- a recovery grid (``configs/studies/recovery.toml``: ``scene``, ``frames``, ``replicates``,
  ``seed`` and the ``n1`` / ``mu_s_per_m`` / ``mu_a_per_m`` lists): every (grid point,
  replicate) is one work item; each process simulates and fits its block of items as batched,
  vmapped fits sharded over its devices (:func:`tofjax.parallel.fit_many`); process 0 gathers
  the fits in item order and writes ``recovery.json``. The same items, seeds and per-device
  chunk give the same fits whatever the number of processes and devices.
- a Monte Carlo reference (``kind = "mc"``: ``scene``, ``photons``, ``seed``, ``g``, ``batch``,
  ``dtype``): the packets are spread over every device of every process and the tallies summed
  (:func:`tofjax.parallel.run_mc`); process 0 writes ``mc.json``.

Launch one process per host (or per SLURM task) with ``--processes N --process-id K
--coordinator HOST:PORT``, or the ``TOFJAX_*`` / SLURM environment variables
(``docs/distributed.md``).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import ConfigError, from_dict, load_toml

__all__ = ["MCStudy", "RecoveryStudy", "load_study", "register", "run_mc_study", "run_recovery"]


#: The most histogram values one process of a recovery study simulates (float32 or float64: 0.8-1.6 GB).
MAX_STUDY_VALUES = 2 * 10**8


@dataclass(frozen=True)
class RecoveryStudy:
    """The recovery grid (the keys of ``configs/studies/recovery.toml``)."""

    scene: str = "optoskin"
    frames: int = 100
    replicates: int = 3
    seed: int = 0
    n1: tuple[float, ...] = (1.4,)
    mu_s_per_m: tuple[float, ...] = (0.6,)
    mu_a_per_m: tuple[float, ...] = (0.14,)

    def __post_init__(self):
        if self.frames < 1:
            raise ConfigError(f"frames: must be >= 1, got {self.frames}")
        if self.replicates < 1:
            raise ConfigError(f"replicates: must be >= 1, got {self.replicates}")
        for k in ("n1", "mu_s_per_m", "mu_a_per_m"):
            if not getattr(self, k):
                raise ConfigError(f"{k}: at least one value")

    def items(self) -> list[tuple[int, int, tuple[float, float, float]]]:
        """(grid point, replicate, truth) of every fit, in the order of the output."""
        grid = list(itertools.product(self.n1, self.mu_s_per_m, self.mu_a_per_m))
        return [(k, r, g) for k, g in enumerate(grid) for r in range(self.replicates)]


@dataclass(frozen=True)
class MCStudy:
    """A Monte Carlo reference of a scene (``kind = "mc"``)."""

    scene: str = "optoskin"
    photons: int = 100_000
    seed: int = 0
    g: float = 0.0
    batch: int = 32_768
    dtype: str = "float32"


def load_study(path_or_name: str):
    """A study config from a TOML file or a built-in name (``recovery``, ...)."""
    p = Path(path_or_name)
    if not p.exists() and not p.suffix:
        from importlib import resources

        builtin = resources.files("tofjax") / "data" / "studies" / f"{path_or_name}.toml"
        if builtin.is_file():
            p = Path(str(builtin))
    if not p.exists():
        raise ConfigError(f"{path_or_name}: no such study config (a TOML file or a built-in name such as 'recovery')")
    raw = dict(load_toml(p))
    kind = raw.pop("kind", "recovery")
    cls = {"recovery": RecoveryStudy, "mc": MCStudy}.get(kind)
    if cls is None:
        raise ConfigError(f"{p}: kind: must be 'recovery' or 'mc', got {kind!r}")
    try:
        return from_dict(cls, raw)
    except ConfigError as e:
        raise ConfigError(f"{p}: {e}") from None


def simulate_item(study: RecoveryStudy, nominal, item):
    """The simulated baseline of one work item ``(grid point k, replicate r, truth)`` of
    :meth:`RecoveryStudy.items` (seed ``seed + 1000 k + r``)."""
    from .simulate import simulate

    k, r, (n1, mu_s, mu_a) = item
    wg = dataclasses.replace(nominal.waveguide, n1=n1, mu_s_per_m=mu_s, mu_a_per_m=mu_a)
    return simulate(nominal.replace(waveguide=wg), study.frames, seed=study.seed + 1000 * k + r)


def recovery_point(truth: tuple[float, float, float], fits: list[dict]) -> dict:
    """One grid point's row of a recovery study: its fits (dicts with ``n1``, ``mu_s_per_m``,
    ``mu_a_per_m``, ``converged``), their bias and spread against the truth (``mu_t`` too),
    the largest n1 error and how many converged."""
    n1, mu_s, mu_a = truth
    arr = {p: np.array([f[p] for f in fits]) for p in ("n1", "mu_s_per_m", "mu_a_per_m")}
    mu_t = arr["mu_s_per_m"] + arr["mu_a_per_m"]
    true = {"n1": n1, "mu_s_per_m": mu_s, "mu_a_per_m": mu_a}
    sd = (lambda x: float(x.std(ddof=1))) if len(fits) > 1 else (lambda x: 0.0)
    return {
        "truth": true,
        "fits": fits,
        "bias": {p: float(arr[p].mean() - true[p]) for p in arr} | {"mu_t": float(mu_t.mean() - mu_s - mu_a)},
        "spread": {p: sd(arr[p]) for p in arr} | {"mu_t": sd(mu_t)},
        "n1_rel_error_max": float(np.max(np.abs(arr["n1"] / n1 - 1))),
        "converged": int(sum(f["converged"] for f in fits)),
    }


def _fit_summary(res) -> dict:
    keys = ("n1", "mu_s_per_m", "mu_a_per_m")
    return {
        **{k: float(res.values[k]) for k in keys},
        **{f"{k}_stderr": float(res.stderr[k]) for k in keys},
        "converged": bool(res.converged),
        "result": res.result,
        "reduced_chi2": float(res.reduced_chi2),
        "steps": int(res.steps),
    }


def run_recovery(study: RecoveryStudy, *, chunk: int = 4, mesh=None) -> dict:
    """The recovery study on this process's block of items; every process returns the whole,
    gathered result (call it on every process)."""
    import jax

    from . import parallel
    from .scene import load_scene

    nominal = load_scene(study.scene).require_waveguide("a recovery study", study.scene)
    items = study.items()
    mine = parallel.split_items(len(items), jax.process_index(), jax.process_count())
    S, Z, B = nominal.shape
    values = len(mine) * study.frames * S * Z * B  # this process's simulated captures, all held at once
    if values > MAX_STUDY_VALUES:
        raise ConfigError(f"frames: {len(mine)} captures of {study.frames} frames x {S} x {Z} x {B} bins are {values:.3g} "
                          f"values, more than {MAX_STUDY_VALUES:.0e} fit in memory; use fewer frames or replicates, or more processes")
    t0 = time.perf_counter()
    caps = [simulate_item(study, nominal, items[i]) for i in mine]
    t_fit = time.perf_counter()
    results = parallel.fit_many(caps, scene=nominal, mesh=mesh, chunk=chunk) if caps else []
    fit_s = time.perf_counter() - t_fit
    fits = parallel.gather_items([_fit_summary(r) for r in results], mine, len(items))
    timing = parallel.allgather_json({"items": len(mine), "fit_seconds": fit_s, "seconds": time.perf_counter() - t0,
                                      "devices": len(jax.local_devices()) if mesh is None else int(mesh.devices.size)})
    reps = study.replicates
    rows = [recovery_point(items[k * reps][2], fits[k * reps : (k + 1) * reps]) for k in range(len(items) // reps)]
    return {
        "study": "parameter recovery",
        "data": "simulated",
        "config": dataclasses.asdict(study),
        "processes": jax.process_count(),
        "chunk_per_device": chunk,
        "per_process": timing,
        "points": rows,
    }


def run_mc_study(study: MCStudy) -> dict:
    """The Monte Carlo reference over every device of every process (call it on every process)."""
    import jax

    from . import parallel
    from .mc.transport import MCOptions
    from .scene import load_scene

    scene = load_scene(study.scene).require_waveguide("a Monte Carlo study", study.scene)
    opts = MCOptions(photons=study.photons, seed=study.seed, g=study.g, batch=study.batch, dtype=study.dtype)
    r = parallel.run_mc(scene, opts)
    return {
        "study": "monte carlo reference",
        "data": "simulated (Monte Carlo)",
        "config": dataclasses.asdict(study),
        "processes": jax.process_count(),
        "devices": r.devices,
        "photons_per_sensor": r.photons,
        "events": r.events,
        "seconds": r.seconds,
        "compile_seconds": r.compile_seconds,
        "ledger": r.ledger,
        "fraction": np.asarray(r.fraction).tolist(),
        "counts": np.asarray(r.counts).tolist(),
    }


def _cmd_study(a) -> int:
    from . import parallel
    from .outputs import atomic_write_text, check_output

    cluster = parallel.cluster_from_env(a.processes, a.process_id, a.coordinator, a.cpu_devices)
    study = load_study(a.config)
    if a.chunk < 1:
        raise ConfigError(f"--chunk: must be >= 1, got {a.chunk}")
    out = Path(a.out)
    if cluster.is_main:
        check_output(out, overwrite=a.overwrite, inputs=[a.config], folder=True)
    parallel.initialize(cluster)
    import jax

    if isinstance(study, MCStudy):
        result, name = run_mc_study(study), "mc.json"
    else:
        result, name = run_recovery(study, chunk=a.chunk), "recovery.json"
    if cluster.is_main:
        atomic_write_text(out / name, json.dumps(result, indent=1))
        print(f"wrote {out / name} ({jax.process_count()} process(es), {len(jax.devices())} device(s))")
    return 0


def add_cluster_arguments(s) -> None:
    """``--processes``, ``--process-id``, ``--coordinator``, ``--cpu-devices`` (also read from the environment)."""
    s.add_argument("--processes", type=int, help="processes in the run (default $TOFJAX_NUM_PROCESSES, $SLURM_NTASKS or 1)")
    s.add_argument("--process-id", type=int, help="this process's id, 0..N-1 (default $TOFJAX_PROCESS_ID or $SLURM_PROCID)")
    s.add_argument("--coordinator", help="HOST:PORT where process 0 listens (default $TOFJAX_COORDINATOR, or the "
                                         "first host of $SLURM_JOB_NODELIST and $TOFJAX_COORDINATOR_PORT)")
    s.add_argument("--cpu-devices", type=int, help="devices of a CPU process (default $TOFJAX_CPU_DEVICES or 1)")


def register(sub) -> None:
    """Add ``study`` to the ``tofjax`` command."""
    s = sub.add_parser("study", help="run a study config on every device of one or several processes (jax.distributed)")
    s.add_argument("config", help="study TOML (a recovery grid, or kind = \"mc\"), or a built-in name such as 'recovery'")
    s.add_argument("--out", required=True, help="output folder (process 0 writes recovery.json or mc.json)")
    s.add_argument("--chunk", type=int, default=4, help="fits per device in one compiled call on accelerators (default 4; unused where every device is a CPU: the fits then run one after the other)")
    add_cluster_arguments(s)
    s.set_defaults(func=_cmd_study)
