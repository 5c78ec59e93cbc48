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
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "TOFJAX_COMPILATION_CACHE"
_OFF = {"0", "off", "false", "no", "none", ""}

__all__ = ["ENV_VAR", "default_cache_dir", "enable_compilation_cache"]


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
) -> Path | None:
    """Keep compiled XLA programs on disk so later processes skip compilation.

    **Arguments:**

    - `path`: cache folder; default :func:`default_cache_dir` (``None`` there means the user
      turned the cache off with ``$TOFJAX_COMPILATION_CACHE=0``, and nothing is changed).
    - `min_compile_time_s`: only programs that took at least this long to compile are stored
      (small programs are faster to recompile than to read back).

    **Returns:** the folder in use, or ``None`` if the cache is off or the folder cannot be
    created (a read-only home directory must not stop a fit: the cache is only an optimisation).
    """
    import jax

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
    return folder
