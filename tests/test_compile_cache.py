"""The persistent compilation cache: where it lives, the opt-out, and that it stores programs."""

import jax
import pytest

from tofjax.compile_cache import ENV_VAR, default_cache_dir, enable_compilation_cache


def test_default_location_and_opt_out(tmp_path):
    assert default_cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "tofjax" / "jax"
    assert default_cache_dir({ENV_VAR: str(tmp_path / "c")}) == tmp_path / "c"
    for off in ("0", "off", "False", "no", ""):
        assert default_cache_dir({ENV_VAR: off}) is None
    home = default_cache_dir({})
    assert home is not None and home.parts[-3:] == (".cache", "tofjax", "jax")


def test_opt_out_changes_nothing(monkeypatch):
    before = jax.config.jax_compilation_cache_dir
    monkeypatch.setenv(ENV_VAR, "0")
    assert enable_compilation_cache() is None
    assert jax.config.jax_compilation_cache_dir == before


def test_unwritable_folder_is_not_an_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    before = jax.config.jax_compilation_cache_dir
    assert enable_compilation_cache(blocker / "sub") is None
    assert jax.config.jax_compilation_cache_dir == before


def test_second_process_reads_the_cache(tmp_path):
    """JAX sets its cache up at the first compilation, so this runs in fresh processes."""
    import json
    import subprocess
    import sys

    script = (
        "import json, sys, time, jax, jax.numpy as jnp\n"
        "from tofjax.compile_cache import enable_compilation_cache\n"
        "folder = enable_compilation_cache(sys.argv[1], min_compile_time_s=0.0)\n"
        "f = jax.jit(lambda x: jnp.sin(x) * 3.25 + jnp.cos(x) ** 2)\n"
        "t = time.perf_counter(); f(jnp.arange(7.0)).block_until_ready()\n"
        "print(json.dumps({'folder': str(folder), 'entries': len(list(folder.iterdir()))}))\n"
    )
    folder = tmp_path / "jaxcache"
    runs = [
        json.loads(subprocess.run([sys.executable, "-c", script, str(folder)], capture_output=True, text=True,
                                  check=True).stdout.strip().splitlines()[-1])
        for _ in range(2)
    ]
    assert runs[0]["folder"] == str(folder)
    assert runs[0]["entries"] >= 1, "no compiled program reached the cache folder"
    # The second process found the program: it added no new entry.
    assert runs[1]["entries"] == runs[0]["entries"]


@pytest.mark.parametrize("cmd", [["scene", "optoskin"]])
def test_cli_uses_env_folder(tmp_path, monkeypatch, cmd, capsys):
    from tofjax.cli import main

    before = jax.config.jax_compilation_cache_dir
    try:
        monkeypatch.setenv(ENV_VAR, str(tmp_path / "cli-cache"))
        assert main(cmd) == 0
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "cli-cache")
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
