"""Run ``tofjax calibrate`` (or any ``tofjax`` command) in this process with timestamps on its
stages; used by ``bench_first_fit.py --profile`` (not part of tofjax).

    python experiments/_first_fit_probe.py OUT.json calibrate BASELINE.h5 --out CAL.json --overwrite

Writes to OUT.json: ``t0_s`` (seconds since the interpreter started, from the process's own
start time), the import of each heavy package in the order the CLI imports them, and every
call of the wrapped stage functions as ``[name, start_s, end_s, depth]`` (seconds since the
probe started), plus JAX's own compile events summed (tracing, lowering to MLIR, XLA
compilation or reading the compiled program from the persistent cache).
Wrapping a function replaces it in every loaded module that holds it (``from x import f``
copies included), so stages are timed where they are called; functions missing in the code
under test (another branch) are skipped.
"""

import json
import os
import sys
import time

T0 = time.perf_counter()


def _since_process_start() -> float:
    """Seconds from the process's creation to now (Linux /proc; NaN elsewhere)."""
    try:
        ticks = os.sysconf("SC_CLK_TCK")
        start = int(open(f"/proc/{os.getpid()}/stat").read().rsplit(")", 1)[1].split()[19]) / ticks
        uptime = float(open("/proc/uptime").read().split()[0])
        return uptime - start
    except Exception:
        return float("nan")


STARTUP = _since_process_start()
events: list[list] = []
depth = [0]


def _timed(name, fn):
    import functools

    @functools.wraps(fn)
    def wrapper(*a, **k):
        t = time.perf_counter() - T0
        depth[0] += 1
        try:
            return fn(*a, **k)
        finally:
            depth[0] -= 1
            events.append([name, t, time.perf_counter() - T0, depth[0]])

    wrapper.__probe_original__ = fn
    return wrapper


def _wrap(module: str, attr: str, name: str) -> None:
    mod = sys.modules.get(module)
    fn = getattr(mod, attr, None) if mod is not None else None
    if fn is None:
        return
    w = _timed(name, fn)
    for m in list(sys.modules.values()):
        d = getattr(m, "__dict__", None)
        if not isinstance(d, dict):
            continue
        for k, v in list(d.items()):
            if v is fn:
                d[k] = w


def main() -> int:
    out, argv = sys.argv[1], sys.argv[2:]
    imports = []
    for mod in ("numpy", "jax", "jaxlib.xla_client", "equinox", "optimistix", "h5py", "tofjax", "tofjax.cli", "tofjax.fit.calibrate"):
        if mod == "tofjax.fit.calibrate":
            # as the CLI: float64 (and the cache) before the fit's modules are imported, since
            # what they build at import depends on it (and with it the stored programs' keys)
            import tofjax

            tofjax.enable_x64()
            tofjax.enable_compilation_cache()
        t = time.perf_counter()
        __import__(mod)
        imports.append([mod, time.perf_counter() - t])
    import jax.monitoring

    jax_events: dict[str, list[float]] = {}
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, secs, **kw: jax_events.setdefault(event, []).append(secs)
    )
    for module, attr, name in [
        ("tofjax.cli", "build_parser", "build the argument parser"),
        ("tofjax.compile_cache", "enable_compilation_cache", "enable the compilation cache"),
        ("tofjax.capture", "read_capture", "read the capture"),
        ("tofjax.fit.calibrate", "build_problem", "build the problem (model, geometry)"),
        ("tofjax.fit.calibrate", "calibrate", "calibrate (all stages)"),
        ("tofjax.fit._start", "timing_start", "timing start"),
        ("tofjax.fit._start", "envelope_candidates", "envelope start"),
        ("tofjax.fit.calibrate", "_prefetch_fit", "start reading the stored fit (background thread)"),
        ("tofjax.fit.calibrate", "run_fit", "joint fit (dispatch)"),
        ("jax", "device_get", "wait for the result (jax.device_get)"),
        ("tofjax.fit.calibrate", "_assemble", "assemble the result"),
        ("tofjax.fit._laplace", "laplace_covariance", "Laplace covariance"),
        ("tofjax.fit.calibrate", "discrepancy_report", "discrepancy report"),
        ("tofjax.fit._result", "fit_report", "fit report (text)"),
        ("tofjax.outputs", "atomic_write_text", "write the JSON"),
        ("tofjax.compile_cache", "_read_program", "read a stored program (export)"),
        # also on the prefetch thread: its time then overlaps the start stages
        ("tofjax.compile_cache", "_read_executable", "read a stored executable"),
        ("tofjax.compile_cache", "_export_program", "trace and export a program"),
        ("tofjax.compile_cache", "call_stored", "stored program: load and run"),
    ]:
        _wrap(module, attr, name)
    from tofjax.cli import main as cli_main

    t = time.perf_counter()
    rc = cli_main(argv)
    main_s = time.perf_counter() - t
    report = {
        "interpreter_start_s": STARTUP,
        "imports_s": imports,
        "cli_main_s": main_s,
        "probe_total_s": time.perf_counter() - T0,
        "events": events,
        "jax_events_s": {k: [len(v), sum(v)] for k, v in jax_events.items()},
        "rc": rc,
    }
    with open(out, "w") as f:
        json.dump(report, f)
    return rc


if __name__ == "__main__":
    sys.exit(main())
