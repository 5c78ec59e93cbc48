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


# ---- exported programs (call_stored) ------------------------------------------------------------

_TOY = '''
import json, sys
import equinox as eqx, jax, jax.numpy as jnp
from tofjax import compile_cache

traces = []

class Toy(eqx.Module):
    w: jax.Array
    power: int = eqx.field(static=True)

def fn(m, x, scale):
    traces.append(1)
    return {"y": jnp.sum(m.w * x ** m.power) * scale, "z": [x[:2], None]}

compile_cache._program_dir = None if sys.argv[1] == "-" else __import__("pathlib").Path(sys.argv[1])
out = compile_cache.call_stored("toy", jax.jit(fn, static_argnums=2), (Toy(jnp.arange(3.0), 2), jnp.ones(3) * 2, 0.5),
                                to_plain=lambda o: o, from_plain=lambda p, a: p)
print(json.dumps({"y": float(out["y"]), "traces": len(traces)}))
'''


def _toy_run(folder) -> dict:
    import json
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _TOY, str(folder)], capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_second_process_reads_the_stored_program(tmp_path):
    """The first process traces and stores the program; the second reads it and traces nothing."""
    first, second = _toy_run(tmp_path / "programs"), _toy_run(tmp_path / "programs")
    assert first == {"y": 0.5 * (0 * 4 + 1 * 4 + 2 * 4), "traces": 1}
    assert second == {"y": first["y"], "traces": 0}
    assert len(list((tmp_path / "programs").glob("*.exported"))) == 1
    assert len(list((tmp_path / "programs").glob("*.xla"))) == 1


def test_call_stored_in_process(tmp_path, monkeypatch):
    import equinox as eqx
    import jax.numpy as jnp

    from tofjax import compile_cache

    class Holder(eqx.Module):
        w: jnp.ndarray
        tag: object = eqx.field(static=True)

    def fn(h, x):
        return (h.w * x, jnp.sum(x))

    args = (Holder(jnp.arange(4.0), "a"), jnp.full(4, 3.0))
    plain = dict(to_plain=lambda o: o, from_plain=lambda p, a: tuple(p))
    monkeypatch.setattr(compile_cache, "_program_dir", tmp_path)
    monkeypatch.setattr(compile_cache, "_loaded", {})
    want = fn(*args)
    got = compile_cache.call_stored("holder", jax.jit(fn), args, **plain)
    assert all(bool(jnp.all(a == b)) for a, b in zip(got, want))
    (entry,) = tmp_path.glob("*.exported")
    (compiled,) = tmp_path.glob("*.xla")  # the compiled executable beside the exported program
    # a truncated entry is dropped and traced (compiled) afresh, never an error
    for e in (entry, compiled):
        e.write_bytes(e.read_bytes()[:50])
    monkeypatch.setattr(compile_cache, "_loaded", {})
    got = compile_cache.call_stored("holder", jax.jit(fn), args, **plain)
    assert bool(jnp.all(got[0] == want[0]))
    assert entry.stat().st_size > 50 and compiled.stat().st_size > 50
    # another static value is another program
    compile_cache.call_stored("holder", jax.jit(fn), (Holder(jnp.arange(4.0), "b"), args[1]), **plain)
    assert len(list(tmp_path.glob("*.exported"))) == 2
    # an argument known only by its address has no stable key: it runs, nothing is stored
    got = compile_cache.call_stored("holder", jax.jit(fn), (Holder(jnp.arange(4.0), object()), args[1]), **plain)
    assert bool(jnp.all(got[0] == want[0]))
    assert len(list(tmp_path.glob("*.exported"))) == 2
    # the executable alone is enough: the exported program is not read
    entry.unlink()
    monkeypatch.setattr(compile_cache, "_loaded", {})
    got = compile_cache.call_stored("holder", jax.jit(fn), args, **plain)
    assert bool(jnp.all(got[0] == want[0])) and not entry.exists()


def test_prefetch_reads_the_executable_ahead(tmp_path, monkeypatch):
    """``prefetch`` starts reading a stored executable on a background thread (keyed by the
    arguments' shapes only: placeholders of the right shapes will do); ``call_stored`` then takes
    that read instead of reading again. Nothing stored, or the store off: nothing to start."""
    import jax.numpy as jnp
    import numpy as np

    from tofjax import compile_cache

    def fn(x, y):
        return (x * y + 1.0,)

    args = (jnp.arange(5.0), jnp.full(5, 2.0))
    plain = dict(to_plain=lambda o: o, from_plain=lambda p, a: tuple(p))
    monkeypatch.setattr(compile_cache, "_program_dir", tmp_path)
    monkeypatch.setattr(compile_cache, "_loaded", {})
    monkeypatch.setattr(compile_cache, "_pending", {})
    assert not compile_cache.prefetch("pf", args)  # nothing stored yet
    want = compile_cache.call_stored("pf", jax.jit(fn), args, **plain)
    monkeypatch.setattr(compile_cache, "_loaded", {})  # a new process, as far as the store knows
    assert compile_cache.prefetch("pf", (np.zeros(5), np.zeros(5)))  # placeholders: same key
    assert len(compile_cache._pending) == 1
    assert not compile_cache.prefetch("pf", args)  # already on its way
    calls = []
    monkeypatch.setattr(compile_cache, "_read_executable", lambda *a: calls.append(a))  # must not be needed
    got = compile_cache.call_stored("pf", jax.jit(fn), args, **plain)
    assert calls == [] and compile_cache._pending == {} and len(compile_cache._loaded) == 1
    assert bool(jnp.all(got[0] == want[0]))
    monkeypatch.setattr(compile_cache, "_program_dir", None)
    assert not compile_cache.prefetch("pf", args)


def test_cli_fast_exit_keeps_code_and_messages(tmp_path):
    """``tofjax calibrate`` from the command line ends without the interpreter's teardown: its
    exit code and its messages (flushed first) are those of a normal exit."""
    import os
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "tofjax.cli", "calibrate", str(tmp_path / "missing.h5"),
                           "--out", str(tmp_path / "c.json")], capture_output=True, text=True,
                          env=dict(os.environ, TOFJAX_COMPILATION_CACHE="0"))
    assert done.returncode == 2
    assert done.stderr.startswith("tofjax calibrate: error:") and "missing.h5" in done.stderr


def test_program_store_follows_the_environment(tmp_path, monkeypatch):
    from tofjax import compile_cache

    before = jax.config.jax_compilation_cache_dir
    try:
        monkeypatch.setattr(compile_cache, "_program_dir", None)
        monkeypatch.setenv("TOFJAX_PROGRAM_STORE", "1")
        assert enable_compilation_cache(tmp_path / "c") == tmp_path / "c"
        assert compile_cache.program_store() == tmp_path / "c" / "programs"
        monkeypatch.setenv("TOFJAX_PROGRAM_STORE", "0")
        enable_compilation_cache(tmp_path / "c")
        assert compile_cache.program_store() is None
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


@pytest.mark.slow
def test_cli_calibration_through_the_store(tmp_path):
    """A whole ``tofjax calibrate`` in two processes: the second reads the stored fit and gives the
    same calibration as a process without the store."""
    import json
    import os
    import subprocess
    import sys

    cli = [sys.executable, "-m", "tofjax.cli"]
    env = dict(os.environ, TOFJAX_COMPILATION_CACHE=str(tmp_path / "cache"), TOFJAX_PROGRAM_STORE="1")
    subprocess.run(cli + ["simulate", "optoskin", "--frames", "5", "--out", str(tmp_path / "b.h5")], env=env, check=True)
    outs = []
    for k, store in enumerate(["1", "1", "0"]):
        out = tmp_path / f"c{k}.json"
        subprocess.run(cli + ["calibrate", str(tmp_path / "b.h5"), "--out", str(out)],
                       env=dict(env, TOFJAX_PROGRAM_STORE=store), check=True, capture_output=True)
        outs.append(json.loads(out.read_text()))
    # the fit and the start's two stages (the timing reference model, the envelope grid)
    assert len(list((tmp_path / "cache" / "programs").glob("*.exported"))) >= 3
    for o in outs[1:]:
        assert o["parameters"] == outs[0]["parameters"]
        assert o["reduced_chi2"] == outs[0]["reduced_chi2"]


def test_core_command_parser_is_the_full_parsers():
    """A core command (calibrate, ...) parses without the extension packages' parsers, to the
    same arguments; ``--help`` and the other commands still see every command."""
    from tofjax.cli import _CORE, build_parser

    line = ["calibrate", "b.h5", "--out", "c.json", "--mcmc", "--max-steps", "7", "--overwrite"]
    core, full = build_parser(extensions=False), build_parser()
    a, b = vars(core.parse_args(line)), vars(full.parse_args(line))
    assert a == b
    sub = next(x for x in core._actions if hasattr(x, "choices") and isinstance(x.choices, dict))
    assert set(sub.choices) == set(_CORE)


def test_fast_cpu_compiler_flag_respects_the_user_and_the_backend():
    """The emitter flag is added to $XLA_FLAGS beside the user's flags, never against an explicit
    choice of the same option or $TOFJAX_CPU_EMITTER=fusion, and never once JAX's backend runs
    (too late to matter: XLA read its flags when it started)."""
    import jax.numpy as jnp

    from tofjax.compile_cache import FAST_CPU_FLAG, use_fast_cpu_compiler

    jnp.zeros(1).block_until_ready()  # the backend runs in this test process
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert use_fast_cpu_compiler(env) is False and env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2"
    from jax._src import xla_bridge

    real = xla_bridge.backends_are_initialized
    xla_bridge.backends_are_initialized = lambda: False
    try:
        env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
        assert use_fast_cpu_compiler(env) is True
        assert env["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {FAST_CPU_FLAG}"
        assert use_fast_cpu_compiler(env) is False  # already there: added once
        mine = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}
        assert use_fast_cpu_compiler(mine) is False and mine["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"
        default = {"TOFJAX_CPU_EMITTER": "fusion"}
        assert use_fast_cpu_compiler(default) is False and "XLA_FLAGS" not in default
    finally:
        xla_bridge.backends_are_initialized = real


def test_fusion_jit_is_jit_with_the_fusion_emitters_on_a_cpu():
    """fusion_jit gives jax.jit's values; on a CPU its program is compiled with XLA's fusion emitters
    (the compile option reaches the executable), made once per backend."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tofjax.compile_cache import _FUSION_ON, fusion_jit

    def f(x, y):
        return jnp.sin(x) * y + jnp.exp(-x * x)

    g = fusion_jit(f)
    x = jnp.linspace(-2.0, 2.0, 33)
    np.testing.assert_allclose(np.asarray(g(x, 3.0)), np.asarray(jax.jit(f)(x, 3.0)), rtol=1e-12, atol=1e-15)
    assert g.__name__ == "f"
    if jax.default_backend() == "cpu":
        lowered = jax.jit(f, compiler_options=dict(_FUSION_ON)).lower(x, 3.0)
        assert lowered.compile().as_text()  # the option is one this XLA accepts on its CPU backend


def test_fusion_emitters_only_where_the_backend_optimises(monkeypatch):
    """FUSION_EMITTERS (what fusion_jit and the Monte Carlo's transport pass) is read when a program compiles: the
    fusion emitters' option, except where $XLA_FLAGS turns the backend's optimisation off (level 0, the test
    suite's default selection), where they only make the compile slower (experiments/emitters_unoptimised.py)."""
    from tofjax.compile_cache import _FUSION_ON, FUSION_EMITTERS

    on = {"xla_cpu_use_fusion_emitters": True}
    assert _FUSION_ON == on
    for flags, want in [("", on), ("--xla_cpu_use_fusion_emitters=false", on),
                        ("--xla_backend_optimization_level=2", on), ("--xla_backend_optimization_level=01", on),
                        ("--xla_backend_optimization_level=0", {}),
                        ("--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0 --xla_foo=1", {})]:
        monkeypatch.setenv("XLA_FLAGS", flags)
        assert dict(FUSION_EMITTERS) == want and FUSION_EMITTERS == want and len(FUSION_EMITTERS) == len(want), flags
    monkeypatch.delenv("XLA_FLAGS")
    assert dict(FUSION_EMITTERS) == on


def test_the_default_selection_alone_compiles_unoptimised():
    """tests/conftest.py: the default run (-m 'not slow') compiles without LLVM's optimisation; make test-all
    (-m ""), -m slow, TOFJAX_TEST_XLA_OPT=default and a user's own level compile as the CLI does."""
    from conftest import unoptimised

    assert unoptimised("not slow", {}) and unoptimised(" not  slow ", {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=false"})
    assert not unoptimised("", {}) and not unoptimised("slow", {})
    assert not unoptimised("not slow", {"TOFJAX_TEST_XLA_OPT": "default"})
    assert not unoptimised("not slow", {"XLA_FLAGS": "--xla_backend_optimization_level=2"})
