"""Studies on several devices and several machines (JAX's multi-process runtime).

tofjax runs one program on every process (JAX's multi-controller model): each process
calls :func:`initialize` first, then the same study code. What this module gives that code:

- :class:`Cluster` and :func:`cluster_from_env`: who am I (process id, how many processes,
  where the coordinator listens), from command-line values, ``TOFJAX_*`` environment
  variables or SLURM's (``SLURM_PROCID``, ``SLURM_NTASKS``, the first host of
  ``SLURM_JOB_NODELIST``).
- :func:`initialize`: ``jax.distributed.initialize`` with the gloo collectives on CPU (one
  process: nothing to do). Must run before any JAX computation.
- :func:`local_mesh` / :func:`global_mesh`: 1-D device meshes (axis ``"batch"``).
- :func:`split_items`: which work items (fits) this process does; contiguous blocks, so the
  gathered order is the items' order for any number of processes.
- :func:`sharded_fit_batch`: a drop-in for :func:`tofjax.fit.calibrate.fit_problem_batch` that
  runs the vmapped fits in fixed-size chunks over the local devices, each chunk on one device,
  dispatched asynchronously so that all devices work at once (each stops when its own fits are
  done). The chunk is the same whatever the number of devices and processes, so the results do
  not depend on how the work was split; on CPU devices the fits run one after the other instead
  (faster there). Not SPMD: ``jax.shard_map`` fails inside lineax's
  linear solves (its traced shapes carry the manual mesh axis and lineax's structure check
  refuses them), and a batch axis sharded with ``NamedSharding`` had not finished compiling
  after 8 minutes here (loaded machine), against 1.5 minutes for the one-device program.
- :func:`fit_many`: :func:`~tofjax.fit.calibrate.calibrate_many` with that batch function.
- :func:`allgather_json`: every process's JSON-able results to every process, through the
  key-value store of JAX's distributed runtime (no shared file system needed; no 30 s limit
  on how long one process waits for another, unlike gloo's collectives).
- :func:`run_mc` / :func:`run_slab`: the Monte Carlo on every device of every process: its
  packets draw their random numbers from their global index, and the compiled transport is a
  ``shard_map`` over ``jax.devices()`` (all processes' devices after :func:`initialize`) whose
  tallies are summed with ``psum``; so 2 processes with N/2 packets each give the tallies of 1
  process with N packets (to float rounding of the sum).

On one CPU, more devices come from ``--cpu-devices N`` (``jax_num_cpu_devices``) or
``XLA_FLAGS=--xla_force_host_platform_device_count=N``. See ``docs/distributed.md``.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .errors import UserError

__all__ = [
    "Cluster",
    "DistributedError",
    "allgather_json",
    "barrier",
    "cluster_from_env",
    "first_slurm_host",
    "fit_many",
    "global_mesh",
    "initialize",
    "local_mesh",
    "run_mc",
    "run_slab",
    "sharded_fit_batch",
    "split_items",
]

#: Port of the coordinator when only its host is known (SLURM); ``TOFJAX_COORDINATOR_PORT`` overrides it.
DEFAULT_PORT = 61_357
#: Fits per device in one compiled call (the shape every fit runs in).
DEFAULT_CHUNK = 4
AXIS = "batch"


class DistributedError(UserError):
    """A launch that cannot work (bad process id, no coordinator, too many devices asked for)."""


# ---- who am I ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Cluster:
    """One process's place in a run: ``process_id`` of ``processes``, the coordinator's
    ``host:port`` (needed when ``processes > 1``) and ``cpu_devices`` (devices of a CPU process;
    None: JAX's default)."""

    processes: int = 1
    process_id: int = 0
    coordinator: str | None = None
    cpu_devices: int | None = None

    def __post_init__(self):
        if self.processes < 1:
            raise DistributedError(f"processes: must be >= 1, got {self.processes}")
        if not 0 <= self.process_id < self.processes:
            raise DistributedError(f"process id: must be in 0..{self.processes - 1}, got {self.process_id}")
        if self.processes > 1:
            if not self.coordinator:
                raise DistributedError(
                    "coordinator: a run of several processes needs --coordinator HOST:PORT (or TOFJAX_COORDINATOR)"
                )
            host, _, port = self.coordinator.rpartition(":")
            if not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise DistributedError(f"coordinator: expected HOST:PORT, got {self.coordinator!r}")
        if self.cpu_devices is not None and self.cpu_devices < 1:
            raise DistributedError(f"cpu devices: must be >= 1, got {self.cpu_devices}")

    @property
    def is_main(self) -> bool:
        return self.process_id == 0


def first_slurm_host(nodelist: str) -> str:
    """The first host of a SLURM node list: ``node[03-05,9],gpu1`` -> ``node03``."""
    nodelist = nodelist.strip()
    m = re.match(r"([^,\[]+)(?:\[([^\]]+)\])?", nodelist)
    if not m or not m.group(1):
        raise DistributedError(f"SLURM_JOB_NODELIST: cannot read a host from {nodelist!r}")
    prefix, ranges = m.group(1), m.group(2)
    if ranges is None:
        return prefix
    return prefix + ranges.split(",")[0].split("-")[0]


def _int(value: str, name: str) -> int:
    try:
        return int(value)
    except ValueError:
        raise DistributedError(f"{name}: expected an integer, got {value!r}") from None


def cluster_from_env(
    processes: int | None = None,
    process_id: int | None = None,
    coordinator: str | None = None,
    cpu_devices: int | None = None,
    environ: Mapping[str, str] | None = None,
) -> Cluster:
    """A :class:`Cluster` from explicit values, else the environment.

    Order for each value: the argument; ``TOFJAX_NUM_PROCESSES`` / ``TOFJAX_PROCESS_ID`` /
    ``TOFJAX_COORDINATOR``; SLURM's ``SLURM_NTASKS`` / ``SLURM_PROCID`` / the first host of
    ``SLURM_JOB_NODELIST`` with port ``TOFJAX_COORDINATOR_PORT`` (default 61357); else one process.
    """
    env = os.environ if environ is None else environ
    if processes is None:
        v = env.get("TOFJAX_NUM_PROCESSES") or env.get("SLURM_NTASKS")
        processes = _int(v, "number of processes") if v else 1
    if process_id is None:
        v = env.get("TOFJAX_PROCESS_ID") or env.get("SLURM_PROCID")
        process_id = _int(v, "process id") if v else 0
    if coordinator is None:
        coordinator = env.get("TOFJAX_COORDINATOR")
        if not coordinator and env.get("SLURM_JOB_NODELIST") and processes > 1:
            port = _int(env.get("TOFJAX_COORDINATOR_PORT", str(DEFAULT_PORT)), "TOFJAX_COORDINATOR_PORT")
            coordinator = f"{first_slurm_host(env['SLURM_JOB_NODELIST'])}:{port}"
    if cpu_devices is None and env.get("TOFJAX_CPU_DEVICES"):
        cpu_devices = _int(env["TOFJAX_CPU_DEVICES"], "TOFJAX_CPU_DEVICES")
    return Cluster(processes=processes, process_id=process_id, coordinator=coordinator, cpu_devices=cpu_devices)


def initialize(cluster: Cluster, *, timeout_s: int = 300) -> Cluster:
    """Join the run: set the CPU device count and the gloo collectives, then
    ``jax.distributed.initialize`` (one process: no runtime is started). Call before any JAX
    computation. Returns ``cluster``."""
    import jax

    if cluster.cpu_devices is not None:
        jax.config.update("jax_num_cpu_devices", cluster.cpu_devices)
    if cluster.processes > 1:
        # gloo is JAX 0.10's default on CPU; set it anyway (older defaults had no CPU collectives)
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        try:
            jax.distributed.initialize(
                coordinator_address=cluster.coordinator,
                num_processes=cluster.processes,
                process_id=cluster.process_id,
                initialization_timeout=timeout_s,
            )
        except RuntimeError as e:  # a JAX computation ran first, or the coordinator is unreachable
            raise DistributedError(f"jax.distributed.initialize failed: {str(e).splitlines()[0]}") from None
        # Open the collectives' context now, while the processes are in step: gloo waits only
        # 30 s for a peer, and later the processes may be minutes apart (compiling, fitting).
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices("tofjax initialize")
    return cluster


# ---- meshes and work ---------------------------------------------------------------------------


def local_mesh(devices: int | None = None):
    """A 1-D mesh (axis ``"batch"``) over this process's devices (default: all of them)."""
    import jax
    from jax.sharding import Mesh

    devs = jax.local_devices()
    if devices is not None:
        if not 1 <= devices <= len(devs):
            raise DistributedError(f"devices: {devices} requested but this process has {len(devs)}")
        devs = devs[:devices]
    return Mesh(np.array(devs), (AXIS,))


def global_mesh():
    """A 1-D mesh (axis ``"batch"``) over every device of every process."""
    import jax
    from jax.sharding import Mesh

    return Mesh(np.array(jax.devices()), (AXIS,))


def split_items(n: int, process_id: int, processes: int) -> range:
    """The contiguous block of ``range(n)`` that process ``process_id`` of ``processes`` does
    (sizes differ by at most one; concatenated in process order they are ``range(n)``)."""
    if n < 0:
        raise DistributedError(f"items: must be >= 0, got {n}")
    base, extra = divmod(n, processes)
    start = process_id * base + min(process_id, extra)
    return range(start, start + base + (process_id < extra))


# ---- sharded batched fits ------------------------------------------------------------------------


def sharded_fit_batch(mesh=None, chunk: int = DEFAULT_CHUNK) -> Callable:
    """A function with :func:`~tofjax.fit.calibrate.fit_problem_batch`'s signature that runs the
    batch over the devices of ``mesh`` (default: :func:`local_mesh`) in chunks of ``chunk``
    fits: chunk ``j`` goes to device ``j mod D`` and is dispatched asynchronously, so separate
    accelerators fit at once, each in the one-device program, each stopping when its own chunk is
    done (XLA's forced host devices in one CPU process run one after the other: the same results,
    no speed; on a CPU host use processes, ``experiments/host_devices_parallel.py``). A
    short last chunk is padded with copies of its first fit. Every fit thus runs in a program of
    the same shape: the results do not depend on the number of devices or processes. Where every
    device of the mesh is a CPU the fits run one after the other instead
    (:func:`~tofjax.fit.calibrate.fit_problem_loop`, ``chunk`` unused): on a CPU that is faster
    than the vmapped chunks (``experiments/bench_fit_many.py``) and forced host devices add
    nothing. Returns host (numpy) arrays."""
    if chunk < 1:
        raise DistributedError(f"chunk: must be >= 1, got {chunk}")

    def fit_batch(problem, objective, solver, starts, data, sigma, prior_params, anchors, **kw):
        import jax

        from .fit.calibrate import fit_problem_batch, fit_problem_loop

        m = local_mesh() if mesh is None else mesh
        devs = list(m.devices.flat)
        if all(d.platform == "cpu" for d in devs):
            return fit_problem_loop(problem, objective, solver, starts, data, sigma, prior_params, anchors, **kw)
        n = int(data.shape[0])
        host = jax.tree_util.tree_map(np.asarray, (starts, data, sigma, anchors))
        pending = []
        for j, c0 in enumerate(range(0, n, chunk)):
            k = min(chunk, n - c0)

            def take(x, c0=c0, k=k):
                x = x[c0 : c0 + k]
                return np.concatenate([x, np.repeat(x[:1], chunk - k, axis=0)]) if k < chunk else x

            st, d, g, a = jax.device_put(jax.tree_util.tree_map(take, host), devs[j % len(devs)])
            out = fit_problem_batch(problem, objective, solver, st, d, g, prior_params, a, **kw)
            pending.append((k, out))  # dispatched; the devices work while the next chunk is sent
        outs = [jax.tree_util.tree_map(lambda x, k=k: np.asarray(x)[:k], jax.device_get(out)) for k, out in pending]
        return jax.tree_util.tree_map(lambda *x: np.concatenate(x), *outs)

    return fit_batch


def fit_many(captures, config=None, *, scene=None, mesh=None, chunk: int = DEFAULT_CHUNK, restart_failures: bool = True):
    """:func:`~tofjax.fit.calibrate.calibrate_many` with the fits spread over ``mesh``'s
    devices (default: this process's) in chunks of ``chunk`` fits per device
    (:func:`sharded_fit_batch`)."""
    from .fit.calibrate import FitConfig, calibrate_many

    return calibrate_many(
        captures, FitConfig() if config is None else config, scene=scene, restart_failures=restart_failures,
        fit_batch=sharded_fit_batch(mesh, chunk),
    )
# ---- gathering ------------------------------------------------------------------------------------


_GATHERS = [0]
#: How long a process waits for the others at a gather (a fit block can take hours on a big study).
GATHER_TIMEOUT_S = float(os.environ.get("TOFJAX_GATHER_TIMEOUT_S", 7 * 24 * 3600))


def _client():
    from jax._src import distributed

    client = distributed.global_state.client
    if client is None:
        raise DistributedError("several processes but no jax.distributed client: call tofjax.parallel.initialize first")
    return client


def allgather_json(obj: Any, *, timeout_s: float | None = None) -> list[Any]:
    """Every process's JSON-able ``obj``, in process order (one process: ``[obj]``).

    Exchanged through the key-value store of JAX's distributed runtime (the coordinator), not
    through device collectives: gloo on CPU gives up when a peer is 30 s late, and one
    process's block of fits can take far longer than another's. Needs no shared file system.
    Every process must call it, in the same order; it waits up to ``timeout_s`` (default a week,
    ``$TOFJAX_GATHER_TIMEOUT_S``) for the others."""
    import jax

    if jax.process_count() == 1:
        return [json.loads(json.dumps(obj))]
    client = _client()
    tag = f"tofjax/gather/{_GATHERS[0]}"
    _GATHERS[0] += 1
    client.key_value_set(f"{tag}/{jax.process_index()}", json.dumps(obj))
    ms = int(1000 * (GATHER_TIMEOUT_S if timeout_s is None else timeout_s))
    return [json.loads(client.blocking_key_value_get(f"{tag}/{k}", ms)) for k in range(jax.process_count())]


def barrier(name: str, *, timeout_s: float | None = None) -> None:
    """Wait until every process got here (the distributed runtime's barrier; one process: no-op)."""
    import jax

    if jax.process_count() > 1:
        _GATHERS[0] += 1
        _client().wait_at_barrier(f"tofjax/{name}/{_GATHERS[0]}", int(1000 * (GATHER_TIMEOUT_S if timeout_s is None else timeout_s)))


def gather_items(local: Sequence[Any], items: range, n: int) -> list[Any]:
    """Per-item JSON-able results of :func:`split_items` blocks, gathered in item order."""
    parts = allgather_json({"start": items.start, "stop": items.stop, "items": list(local)})
    out: list[Any] = [None] * n
    for part in parts:
        out[part["start"] : part["stop"]] = part["items"]
    if any(x is None for x in out):
        raise DistributedError("gather: some items were done by no process (were all processes started alike?)")
    return out


# ---- the Monte Carlo on every process --------------------------------------------------------------


def _check_mc_devices(options) -> None:
    import jax

    if jax.process_count() > 1 and options.devices is not None:
        raise DistributedError(
            "devices: a Monte Carlo over several processes uses every device of every process; leave devices unset"
        )


def run_mc(scene, options, *, progress: bool = False):
    """:func:`tofjax.mc.run_mc` with the packets spread over every device of every process
    (call it on every process with the same arguments; every process gets the summed result).

    The tallies are summed by device collectives (gloo on CPU), which fail when one process
    reaches them more than 30 s after another: the processes start together (a barrier), but
    each compiles the transport on its own; with a warm compilation cache that takes seconds."""
    from .mc.transport import run_mc as _run_mc

    _check_mc_devices(options)
    barrier("run_mc")
    return _run_mc(scene, options, progress=progress)


def run_slab(options, *, progress: bool = False):
    """:func:`tofjax.mc.slab.run_slab` on every device of every process (as :func:`run_mc`)."""
    from .mc.slab import run_slab as _run_slab

    _check_mc_devices(options)
    barrier("run_slab")
    return _run_slab(options, progress=progress)
