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
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
import re
from pathlib import Path
from typing import Any, Callable

ENV_VAR = "TOFJAX_COMPILATION_CACHE"
PROGRAM_ENV_VAR = "TOFJAX_PROGRAM_STORE"
_OFF = {"0", "off", "false", "no", "none", ""}
# where exported programs go; set by enable_compilation_cache (None: the store is off)
_program_dir: Path | None = None

__all__ = ["ENV_VAR", "PROGRAM_ENV_VAR", "call_stored", "default_cache_dir", "enable_compilation_cache", "program_store"]


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


def call_stored(name: str, fn: Callable, args: tuple, *, to_plain: Callable, from_plain: Callable) -> Any:
    """``fn(*args)`` through the program store: traced once per machine, not once per process.

    **Arguments:**

    - `name`: what the program is (part of its key).
    - `fn`: the function (jitted: it also runs directly where nothing is stored); its array arguments (leaves of ``args`` that are arrays) are the
      program's inputs, everything else in ``args`` is fixed at trace time and keyed.
    - `to_plain`: turns ``fn``'s output into arrays in tuples, lists, dicts and ``None`` only
      (what can be stored); `from_plain(plain, args)` rebuilds the output from it.

    **Returns:** ``fn(*args)``. Where the store is off, the arguments have no stable key (an
    object known only by its address) or the program cannot be exported or read back, the
    function runs as a plain ``jax.jit`` program and nothing is stored.
    """
    import equinox as eqx
    import jax

    folder = _program_dir
    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)

    def direct():
        return fn(*args)

    if folder is None:
        return direct()
    try:
        key = _program_key(name, treedef, static, leaves)
    except _Unkeyable:
        return direct()
    if key not in _loaded:
        program = _read_program(folder, key) or _export_program(folder, key, fn, to_plain, treedef, static, leaves)
        if program is None:
            return direct()
        _loaded[key] = program
    call, out_def = _loaded[key]
    out = call(*leaves)
    return from_plain(jax.tree_util.tree_unflatten(out_def, out), args)


def _read_program(folder: Path, key: str):
    import jax
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
    return jax.jit(exported.call), out_def


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
    return jax.jit(exported.call), out_def[-1]
