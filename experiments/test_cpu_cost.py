"""CPU seconds of some default-run tests, before and after a change to them, side by side.

For each selection (pytest node ids, ``-m 'not slow'``), runs pytest in a tree before the change
(``--base``, e.g. ``git archive 7dc992e | tar -x -C /tmp/base``) and in this tree at the same
time (two processes: the same load for both), each cold: a fresh ``TMPDIR`` (the tests' JAX
persistent cache lives there), ``-p no:cacheprovider``. CPU seconds are the pytest process's
user + system time (``os.wait4``): a shared, loaded machine's wall time says little. Writes JSON.

    python experiments/test_cpu_cost.py --base /tmp/base --out docs/results/test_cpu_cost.json \\
        --select tests/test_nuts.py --select "tests/test_guided.py::test_guided_model_is_linear_and_differentiable"
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _start(tree: Path, ids: list[str], log: Path) -> tuple[subprocess.Popen, float, tempfile.TemporaryDirectory]:
    tmp = tempfile.TemporaryDirectory()
    env = dict(os.environ, TMPDIR=tmp.name, PYTHONPATH=str(tree))
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "not slow", *ids]
    p = subprocess.Popen(cmd, cwd=str(tree), env=env, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    return p, time.perf_counter(), tmp


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True)
    ap.add_argument("--select", action="append", required=True, help="space-separated node ids run in one pytest (repeatable)")
    ap.add_argument("--out", default="docs/results/test_cpu_cost.json")
    a = ap.parse_args(argv)
    trees = {"before": Path(a.base).resolve(), "after": Path(__file__).resolve().parents[1]}
    rows = []
    logs = Path(tempfile.mkdtemp(prefix="test_cpu_cost-"))
    for sel in a.select:
        ids = sel.split()
        load0 = os.getloadavg()[0]
        procs = {t: _start(tree, ids, logs / f"{t}-{len(rows)}.log") for t, tree in trees.items()}
        row = {"select": ids, "load_average_at_start": load0}
        left = {p.pid: t for t, (p, _, _) in procs.items()}
        while left:  # whichever ends first: each one's own wall time
            pid, status, ru = os.wait4(-1, 0)
            if pid not in left:
                continue
            t = left.pop(pid)
            p, t0, tmp = procs[t]
            p.returncode = os.waitstatus_to_exitcode(status)
            row[t] = {"cpu_s": ru.ru_utime + ru.ru_stime, "user_s": ru.ru_utime, "wall_s": time.perf_counter() - t0,
                      "passed": p.returncode == 0, "summary": (logs / f"{t}-{len(rows)}.log").read_text().strip().splitlines()[-1]}
            tmp.cleanup()
        row["saved_cpu_s"] = row["before"]["cpu_s"] - row["after"]["cpu_s"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    doc = {
        "what": "CPU seconds (user + system) of pytest on the selected default-run tests, cold (fresh TMPDIR: no JAX persistent cache), "
                "the tree before the change and this tree run at the same time",
        "data": "simulated scenes (the tests')",
        "machine": f"{platform.node()}: {os.cpu_count()} CPUs shared with other jobs (loaded; load average {min(r['load_average_at_start'] for r in rows):.1f}"
                   f" to {max(r['load_average_at_start'] for r in rows):.1f} at the starts)",
        "before": str(trees["before"]),
        "rows": rows,
        "saved_cpu_s_total": sum(r["saved_cpu_s"] for r in rows),
    }
    from tofjax.outputs import atomic_write_text, check_output

    atomic_write_text(check_output(a.out, overwrite=True), json.dumps(doc, indent=1) + "\n")
    print("saved", doc["saved_cpu_s_total"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
