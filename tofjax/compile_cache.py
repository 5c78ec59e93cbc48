"""Persistent XLA compilation cache: compile once per machine, not once per process.

A calibration compiles for 10-20 s on a laptop-class CPU; without a persistent cache every new
``tofjax`` process pays that again. JAX can keep compiled executables on disk, keyed by the
program, the JAX/XLA versions and the device, so a second process with the same scene shape
loads them instead of compiling.

The CLI turns the cache on at its entry point (never on import). Where it lives, in order:

1. ``$TOFJAX_COMPILATION_CACHE`` if set: a folder, or ``0``/``off``/``false``/``no`` to turn the
   cache off;
2. ``$XDG_CACHE_HOME/tofjax/jax`` if ``XDG_CACHE_HOME`` is set;
3. ``~/.cache/tofjax/jax``.

Library users call :func:`enable_compilation_cache` themselves (a notebook, a study script).
Entries are safe to delete at any time. The folder is not size-bounded: JAX's bounded (LRU)
mode keeps access-time files that processes without the bound do not write, and two such
processes sharing a folder (pytest-xdist workers, a study beside a CLI call) then fail to read
each other's entries. A calibration's programs take a few MB; delete the folder to reclaim it.

The XLA cache skips compilation, not the Python tracing and lowering before it, which for a
calibration costs several seconds of every new process. :func:`call_stored` therefore also
keeps *exported* programs (:mod:`jax.export`: the traced and lowered StableHLO) in
``<folder>/programs``, keyed by the program's structure, its argument shapes, the JAX version
and a hash of tofjax's own source. A later process deserialises the program instead of tracing
it, and its compilation is then a hit in the XLA cache. ``$TOFJAX_PROGRAM_STORE=0`` turns only
this part off.

Lowering a stored program and looking it up in the XLA cache still costs a new process about a
second; the store therefore also keeps the *compiled executable* of each program
(``<key>-<machine>.xla``, :mod:`jax.experimental.serialize_executable`, keyed further by the
backend, the host CPU's features and ``$XLA_FLAGS``), which a later process loads and runs
directly. What remains of a warm start is then mostly loading that executable, whose cost
grows with its number of kernels (see ``experiments/first_fit_kernels.py``); the load releases
the GIL, so :func:`prefetch` starts it on a background thread as soon as the arguments' shapes
are known (the calibration does so before its start stages). The default calibration's fit
computes its Laplace pieces from its own Jacobians (one program); with another solver they are
a second program, read while the first runs.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Callable

ENV_VAR = "TOFJAX_COMPILATION_CACHE"
PROGRAM_ENV_VAR = "TOFJAX_PROGRAM_STORE"
_OFF = {"0", "off", "false", "no", "none", ""}
# where exported programs go; set by enable_compilation_cache (None: the store is off)
_program_dir: Path | None = None

__all__ = ["AHEAD_ENV_VAR", "CPU_EMITTER_ENV_VAR", "ENV_VAR", "FAST_CPU_FLAG", "PROGRAM_ENV_VAR", "call_stored", "compile_ahead",
           "default_cache_dir", "enable_compilation_cache", "fusion_jit", "prefetch", "program_store", "use_fast_cpu_compiler"]


def default_cache_dir(environ: dict[str, str] | None = None) -> Path | None:
    """The cache folder the CLI uses, or ``None`` when the user turned the cache off."""
    env = os.environ if environ is None else environ
    if ENV_VAR in env:
        value = env[ENV_VAR].strip()
        if value.lower() in _OFF:
            return None
        return Path(value).expanduser()
    base = env.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "tofjax" / "jax"


def enable_compilation_cache(
    path: str | os.PathLike | None = None,
    *,
    min_compile_time_s: float = 0.5,
    programs: bool = True,
) -> Path | None:
    """Keep compiled XLA programs on disk so later processes skip compilation.

    **Arguments:**

    - `path`: cache folder; default :func:`default_cache_dir` (``None`` there means the user
      turned the cache off with ``$TOFJAX_COMPILATION_CACHE=0``, and nothing is changed).
    - `min_compile_time_s`: only programs that took at least this long to compile are stored
      (small programs are faster to recompile than to read back).
    - `programs`: also keep exported programs (:func:`call_stored`) in ``<folder>/programs``
      unless ``$TOFJAX_PROGRAM_STORE`` turns them off.

    **Returns:** the folder in use, or ``None`` if the cache is off or the folder cannot be
    created (a read-only home directory must not stop a fit: the cache is only an optimisation).
    """
    import jax

    global _program_dir
    folder = Path(path).expanduser() if path is not None else default_cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK):
            return None
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    store = os.environ.get(PROGRAM_ENV_VAR, "1").strip().lower() not in _OFF
    _program_dir = folder / "programs" if programs and store else None
    return folder


#: ``$TOFJAX_COMPILE_AHEAD=0`` turns :func:`compile_ahead` off
AHEAD_ENV_VAR = "TOFJAX_COMPILE_AHEAD"
#: ``$TOFJAX_CPU_EMITTER=fusion`` keeps XLA's default CPU emitters (:func:`use_fast_cpu_compiler`)
CPU_EMITTER_ENV_VAR = "TOFJAX_CPU_EMITTER"
#: the XLA flag :func:`use_fast_cpu_compiler` adds
FAST_CPU_FLAG = "--xla_cpu_use_fusion_emitters=false"


def use_fast_cpu_compiler(environ: dict[str, str] | None = None) -> bool:
    """Compile CPU programs with XLA's elemental emitters instead of its newer fusion emitters
    (``--xla_cpu_use_fusion_emitters=false`` added to ``$XLA_FLAGS``).

    Measured on the 2-core VM (``experiments/cpu_emitters.py``): a cold calibration runs about
    1.4x faster and its warm fit 1.1x faster; the test suite took half the time. One loop ran
    slower with it, the Monte Carlo's transport, whose program asks for the fusion emitters itself. The
    flag concerns the CPU backend only (accelerators ignore it). XLA reads ``$XLA_FLAGS`` once,
    when JAX's backend starts, so call this at the entry point before any JAX computation (the
    CLI and the tests do), like :func:`tofjax.enable_x64`; never on import.

    Changes nothing (and returns ``False``) where ``$XLA_FLAGS`` already names the option (the
    user's choice stands), where ``$TOFJAX_CPU_EMITTER=fusion`` asks for XLA's default, or where
    JAX's backend has already started (too late to take effect).

    **Returns:** whether the flag was added.
    """
    env = os.environ if environ is None else environ
    if env.get(CPU_EMITTER_ENV_VAR, "").strip().lower() == "fusion":
        return False
    flags = env.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" in flags:
        return False
    try:
        from jax._src import xla_bridge

        started = bool(xla_bridge.backends_are_initialized())
    except Exception:  # a JAX without this query: assume not started (at worst the flag is inert)
        started = False
    if started:
        return False
    env["XLA_FLAGS"] = f"{flags} {FAST_CPU_FLAG}".strip()
    return True


_FUSION_ON = {"xla_cpu_use_fusion_emitters": True}
_UNOPTIMISED = re.compile(r"--xla_backend_optimization_level=0(\s|$)")


def _backend_unoptimised() -> bool:
    """Whether ``$XLA_FLAGS`` compiles without the backend's optimisation (``--xla_backend_optimization_level=0``)."""
    return bool(_UNOPTIMISED.search(os.environ.get("XLA_FLAGS", "")))


class _FusionEmitters(Mapping):
    """``{"xla_cpu_use_fusion_emitters": True}``, read when a program is compiled, or empty where ``$XLA_FLAGS``
    compiles without the backend's optimisation (``--xla_backend_optimization_level=0``, as the test suite's default
    selection does): there the Monte Carlo's transport compiled 1.8x slower with them and ran no faster
    (``experiments/emitters_unoptimised.py``). XLA reads ``$XLA_FLAGS`` once, when JAX's backend starts; this reads
    it at each compile, so set it before the backend starts (as :func:`use_fast_cpu_compiler` asks)."""

    def _options(self) -> dict:
        return {} if _backend_unoptimised() else _FUSION_ON

    def __getitem__(self, key):
        return self._options()[key]

    def __iter__(self):
        return iter(self._options())

    def __len__(self) -> int:
        return len(self._options())

    def __repr__(self) -> str:
        return repr(self._options())


#: XLA's compile option that :func:`fusion_jit` (and the Monte Carlo's transport) set for CPU programs; empty when
#: ``$XLA_FLAGS`` turns the backend's optimisation off (see :class:`_FusionEmitters`)
FUSION_EMITTERS: Mapping = _FusionEmitters()


def fusion_jit(fn: Callable) -> Callable:
    """``jax.jit(fn)`` whose CPU programs keep XLA's fusion emitters whatever ``$XLA_FLAGS`` says
    (:func:`use_fast_cpu_compiler` turns them off for the rest): for the loops that run far
    more often than they compile and run faster with them (the inversion's gather-heavy maps:
    2x the frames per second in a batch, ``experiments/bench_invert.py``). The compile option
    is passed on a CPU backend only, and not where ``$XLA_FLAGS`` turns the backend's optimisation off
    (:data:`FUSION_EMITTERS`); one jitted function per backend, made on first use."""
    import jax

    jitted: dict[str, Callable] = {}

    @functools.wraps(fn)
    def call(*args, **kwargs):
        backend = jax.default_backend()
        f = jitted.get(backend)
        if f is None:
            options = dict(FUSION_EMITTERS) if backend == "cpu" else None
            f = jitted[backend] = jax.jit(fn, compiler_options=options or None)
        return f(*args, **kwargs)

    return call


def program_store() -> Path | None:
    """The folder of exported programs, or ``None`` when the store is off (the default until
    :func:`enable_compilation_cache` turns it on)."""
    return _program_dir


@functools.lru_cache(maxsize=1)
def _code_version() -> str:
    """JAX, jaxlib and a hash of tofjax's source: a stored program is only reused by the same code."""
    import jax
    import jaxlib

    h = hashlib.sha256(f"{jax.__version__}|{jaxlib.__version__}".encode())
    root = Path(__file__).resolve().parent
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


class _Unkeyable(Exception):
    pass


_ADDRESS = re.compile(r"0x[0-9a-fA-F]{6,}")


def _leaf_key(x) -> str:
    if callable(x) and hasattr(x, "__qualname__"):
        return f"{getattr(x, '__module__', '?')}.{x.__qualname__}"
    r = repr(x)
    if _ADDRESS.search(r):  # an object known only by its address: no stable key
        raise _Unkeyable(r)
    return r


def _program_key(name: str, treedef, static, leaves) -> str:
    import jax

    s_leaves, s_def = jax.tree_util.tree_flatten(static)
    structure = f"{treedef}\n{s_def}"
    if _ADDRESS.search(structure):
        raise _Unkeyable(name)
    parts = [name, _code_version(), structure, *map(_leaf_key, s_leaves)]
    parts += [f"{tuple(x.shape)}:{x.dtype.str}" for x in leaves]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]


_loaded: dict[str, tuple[Callable, Any]] = {}
# stored executables being read on the background thread (prefetch), by key
_pending: dict[str, Any] = {}
_pool: list = []


def _stored_key(name: str, args: tuple):
    """The program key of ``args`` (as :func:`call_stored` computes it), or ``None`` where the
    arguments have no stable key."""
    import equinox as eqx
    import jax

    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)
    try:
        return _program_key(name, treedef, static, leaves)
    except _Unkeyable:
        return None


def prefetch(name: str, args: tuple) -> bool:
    """Start reading the stored executable that ``call_stored(name, fn, args, ...)`` will run,
    on one background thread, so that reading it (most of a warm process: its kernels are
    linked on load) overlaps with the work before the call. Only the arguments' structure and
    shapes matter (as for the key), so ``args`` may hold placeholders of the right shapes (a
    start guessed before the start stages ran). Does nothing where the store is off, the key
    is unstable, the executable is already loaded or none is stored.

    **Returns:** whether a read was started. A read that turns out not to be needed (other
    shapes after all) is only wasted work: the process still waits for it before it exits.
    """
    folder = _program_dir
    if folder is None:
        return False
    key = _stored_key(name, args)
    if key is None or key in _loaded or key in _pending:
        return False
    try:
        if not _executable_path(folder, key).is_file():
            return False
    except Exception:  # no backend: nothing to read for
        return False
    _pending[key] = _background().submit(_read_executable, folder, key)
    return True


# programs being compiled ahead on the background thread (compile_ahead), by name
_ahead: dict[str, Any] = {}
_ahead_pool: list = []


def _executor(holder: list, workers: int, prefix: str):
    """The thread pool kept in ``holder``, made on first use."""
    if not holder:
        from concurrent.futures import ThreadPoolExecutor

        holder.append(ThreadPoolExecutor(max_workers=workers, thread_name_prefix=prefix))
    return holder[0]


def _background():
    # one worker: reads run in the order they were asked for (the order they are needed)
    return _executor(_pool, 1, "tofjax-prefetch")


def compile_ahead(name: str, compile_fn: Callable[[], Any]) -> bool:
    """Compile, on a background thread, a program that ``call_stored(name, ...)`` will run
    later, while this thread does other work (a calibration's start stages): ``compile_fn``
    lowers and compiles it (``jitted.lower(*args).compile()`` with arguments of the shapes the
    call will have), which fills JAX's in-process caches, so the call itself then neither traces
    nor compiles. XLA compiles release the GIL, so they overlap with this thread's work and with
    each other (two background threads: a calibration's fit and its Laplace pieces compile side
    by side; on the 2-core VM a cold calibration took 9.31 s instead of 11.47 s, medians of 5,
    ``experiments/compile_ahead.py``). :func:`call_stored` waits for a pending compilation of its
    name before it runs (two threads compiling the same program would each compile it).

    Only where the program store is off (a library call; with the store on, :func:`prefetch`
    reads the stored executable instead). ``$TOFJAX_COMPILE_AHEAD=0`` turns it off. A failed
    or mismatched compilation (other shapes after all) costs only the wasted work.

    **Returns:** whether a compilation was started.
    """
    if _program_dir is not None or name in _ahead:
        return False
    if os.environ.get(AHEAD_ENV_VAR, "1").strip().lower() in _OFF:
        return False
    _ahead[name] = _executor(_ahead_pool, 2, "tofjax-ahead").submit(compile_fn)
    return True


def _await_ahead(name: str) -> None:
    future = _ahead.pop(name, None)
    if future is not None:
        _result_or_none(future)


def call_stored(name: str, fn: Callable, args: tuple, *, to_plain: Callable, from_plain: Callable) -> Any:
    """``fn(*args)`` through the program store: traced and compiled once per machine, not once
    per process.

    **Arguments:**

    - `name`: what the program is (part of its key).
    - `fn`: the function (jitted: it also runs directly where nothing is stored); its array arguments (leaves of ``args`` that are arrays) are the
      program's inputs, everything else in ``args`` is fixed at trace time and keyed.
    - `to_plain`: turns ``fn``'s output into arrays in tuples, lists, dicts and ``None`` only
      (what can be stored); `from_plain(plain, args)` rebuilds the output from it.

    **Returns:** ``fn(*args)``. Where the store is off, the arguments have no stable key (an
    object known only by its address) or the program cannot be exported or read back, the
    function runs as a plain ``jax.jit`` program and nothing is stored.

    A later process first looks for the compiled executable (``<key>-<machine>.xla``,
    :mod:`jax.experimental.serialize_executable`), which it loads without tracing, lowering or
    hashing the program; then for the exported program (``<key>.exported``), which it lowers and
    compiles (a hit in the XLA cache where that holds it) and whose executable it then stores.
    """
    import equinox as eqx
    import jax

    folder = _program_dir
    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)

    def direct():
        _await_ahead(name)
        return fn(*args)

    if folder is None:
        return direct()
    try:
        key = _program_key(name, treedef, static, leaves)
    except _Unkeyable:
        return direct()
    if key not in _loaded:
        pending = _pending.pop(key, None)
        program = _read_executable(folder, key) if pending is None else _result_or_none(pending)
        if program is None:
            exported = _read_program(folder, key) or _export_program(folder, key, fn, to_plain, treedef, static, leaves)
            if exported is None:
                return direct()
            program = _compile_program(folder, key, *exported, leaves)
        _loaded[key] = program
    call, out_def = _loaded[key]
    try:
        out = call(*leaves)
    except TypeError:  # a compiled program takes only the argument types it was compiled for
        del _loaded[key]
        return direct()
    return from_plain(jax.tree_util.tree_unflatten(out_def, out), args)


def _result_or_none(future):
    try:
        return future.result()
    except Exception:
        return None


@functools.lru_cache(maxsize=1)
def _machine() -> str:
    """What a compiled executable is specific to: the backend and its devices, the host CPU's
    instruction set and the XLA flags (the program key already pins the code and versions)."""
    import platform

    import jax

    devices = jax.devices()
    client = devices[0].client
    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line for line in f if line.startswith(("flags", "Features"))), "")
    except OSError:
        pass
    parts = [client.platform, client.platform_version, str(len(devices)), devices[0].device_kind, platform.machine(),
             cpu, os.environ.get("XLA_FLAGS", "")]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


def _executable_path(folder: Path, key: str) -> Path:
    return folder / f"{key}-{_machine()}.xla"


def _lapack_ready() -> bool:
    """Initialise JAX's CPU LAPACK kernels, which JAX itself does only while lowering a linear
    algebra operation: a loaded executable that calls them (a Cholesky solve) would otherwise
    jump to an unset function pointer. ``False`` where this JAX has no such hook (then no
    executable is loaded: the exported program is lowered instead, which initialises them)."""
    try:
        from jax._src.lax import linalg

        linalg.initialize_lapack()
        return True
    except Exception:
        return False


def _read_executable(folder: Path, key: str):
    """A stored compiled executable and its output structure, or ``None``."""
    from jax.experimental import serialize_executable

    if not _lapack_ready():
        return None
    path = _executable_path(folder, key)
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError:
        return None
    try:
        payload, in_tree, out_tree, out_def = pickle.loads(blob)
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # a truncated or foreign entry: drop it and compile afresh
        path.unlink(missing_ok=True)
        return None
    return compiled, out_def


def _compile_program(folder: Path, key: str, exported, out_def, leaves):
    """``exported`` compiled for ``leaves`` (from the XLA cache where it holds the program), its
    executable stored for the next process; ``jax.jit(exported.call)`` where that fails."""
    import jax
    from jax.experimental import serialize_executable

    from .outputs import atomic_path

    hits = _cache_hits()
    try:
        compiled = jax.jit(exported.call).lower(*leaves).compile()
    except Exception:
        return jax.jit(exported.call), out_def
    if _cache_hits() != hits:
        # read back from the XLA cache, not compiled here: such an executable serialises without
        # its kernels' code (a later load fails), so none is stored; the next process again
        # lowers the exported program and reads the XLA cache
        return compiled, out_def
    try:
        payload, in_tree, out_tree = serialize_executable.serialize(compiled)
        blob = pickle.dumps((payload, in_tree, out_tree, out_def))
        with atomic_path(_executable_path(folder, key), overwrite=True) as tmp:
            Path(tmp).write_bytes(blob)
    except Exception:  # not serialisable here, or a read-only cache: the work goes on
        pass
    return compiled, out_def


_hits = [0]


@functools.lru_cache(maxsize=1)
def _count_cache_hits() -> None:
    import jax.monitoring

    def count(event, *_, **__):
        if event == "/jax/compilation_cache/cache_retrieval_time_sec":
            _hits[0] += 1

    jax.monitoring.register_event_duration_secs_listener(count)


def _cache_hits() -> int:
    """How many programs this process has read from the XLA cache so far."""
    _count_cache_hits()
    return _hits[0]


def _read_program(folder: Path, key: str):
    from jax import export

    path = folder / f"{key}.exported"
    try:
        blob = path.read_bytes()
        out_def = pickle.loads((folder / f"{key}.tree").read_bytes())
        exported = export.deserialize(bytearray(blob))
    except FileNotFoundError:
        return None
    except Exception:  # a truncated or foreign entry: drop it and trace afresh
        for p in (path, folder / f"{key}.tree"):
            p.unlink(missing_ok=True)
        return None
    return exported, out_def


def _export_program(folder: Path, key: str, fn: Callable, to_plain: Callable, treedef, static, leaves):
    import equinox as eqx
    import jax
    from jax import export

    from .outputs import atomic_path

    out_def = []

    def flat(*xs):
        out = to_plain(fn(*eqx.combine(jax.tree_util.tree_unflatten(treedef, xs), static)))
        out_leaves, d = jax.tree_util.tree_flatten(out)
        out_def.append(d)
        return out_leaves

    try:
        # custom calls (LAPACK) have no cross-version guarantee; the key pins the versions
        exported = export.export(jax.jit(flat), disabled_checks=[export.DisabledSafetyCheck.custom_call("ALL")])(
            *[jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
        )
        blob = exported.serialize()
        tree = pickle.dumps(out_def[-1])
    except Exception:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for suffix, data in ((".tree", tree), (".exported", blob)):
            with atomic_path(folder / f"{key}{suffix}", overwrite=True) as tmp:
                Path(tmp).write_bytes(data)
    except Exception:  # a read-only cache must not stop the work
        pass
    return exported, out_def[-1]
