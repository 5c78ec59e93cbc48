"""tofjax.parallel and ``tofjax study``: launch settings, work split, gathers, and equality of
one process against two (jax.distributed on localhost, gloo) and one device against two
(forced host devices).

The default run keeps to pure Python plus one two-process gather (a few seconds); the fits and
the Monte Carlo on two processes or two devices compile for a minute or more here: slow-marked."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tofjax.config import ConfigError
from tofjax.parallel import (
    Cluster,
    DistributedError,
    allgather_json,
    cluster_from_env,
    first_slurm_host,
    gather_items,
    split_items,
)
from tofjax.study_cli import MCStudy, RecoveryStudy, load_study

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _env(**extra) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    for k in ("TOFJAX_NUM_PROCESSES", "TOFJAX_PROCESS_ID", "TOFJAX_COORDINATOR", "SLURM_NTASKS", "SLURM_PROCID",
              "SLURM_JOB_NODELIST", "XLA_FLAGS"):
        env.pop(k, None)
    env.update(extra)
    return env


def _two_processes(argv_for, timeout=600, **env) -> list[subprocess.CompletedProcess]:
    """Run ``argv_for(k)`` for k = 0, 1 at once; both must exit 0."""
    procs = [subprocess.Popen(argv_for(k), env=_env(**env), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k in (0, 1)]
    out = []
    for p in procs:
        try:
            o, e = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            raise
        out.append(subprocess.CompletedProcess(p.args, p.returncode, o, e))
    for r in out:
        assert r.returncode == 0, r.stderr[-3000:]
    return out


# ---- launch settings ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "nodelist, host",
    [("node07", "node07"), ("node[03-05,9]", "node03"), ("gpu-a[1-2],gpu-b3", "gpu-a1"), ("c[001,007]", "c001"),
     ("login1,login2", "login1")],
)
def test_first_slurm_host(nodelist, host):
    assert first_slurm_host(nodelist) == host


def test_cluster_from_arguments_environment_and_slurm():
    assert cluster_from_env(environ={}) == Cluster()
    c = cluster_from_env(2, 1, "h:1234", environ={"TOFJAX_NUM_PROCESSES": "8"})
    assert (c.processes, c.process_id, c.coordinator) == (2, 1, "h:1234")
    c = cluster_from_env(environ={"TOFJAX_NUM_PROCESSES": "3", "TOFJAX_PROCESS_ID": "2", "TOFJAX_COORDINATOR": "a:9",
                                  "TOFJAX_CPU_DEVICES": "2"})
    assert (c.processes, c.process_id, c.coordinator, c.cpu_devices, c.is_main) == (3, 2, "a:9", 2, False)
    slurm = {"SLURM_NTASKS": "4", "SLURM_PROCID": "3", "SLURM_JOB_NODELIST": "n[12-15]"}
    c = cluster_from_env(environ=slurm)
    assert (c.processes, c.process_id, c.coordinator) == (4, 3, "n12:61357")
    c = cluster_from_env(environ=slurm | {"TOFJAX_COORDINATOR_PORT": "5000", "TOFJAX_PROCESS_ID": "0"})
    assert (c.process_id, c.coordinator) == (0, "n12:5000")


@pytest.mark.parametrize(
    "kwargs, words",
    [({"processes": 2, "process_id": 2, "coordinator": "h:1"}, "process id"),
     ({"processes": 2, "process_id": 0}, "coordinator"),
     ({"processes": 2, "process_id": 0, "coordinator": "nohost"}, "HOST:PORT"),
     ({"processes": 0}, "processes"),
     ({"cpu_devices": 0}, "cpu devices")],
)
def test_bad_cluster_is_one_line(kwargs, words):
    with pytest.raises(DistributedError, match=words) as e:
        Cluster(**kwargs)
    assert "\n" not in str(e.value)


def test_bad_environment_is_one_line():
    with pytest.raises(DistributedError, match="SLURM_PROCID|process id"):
        cluster_from_env(environ={"SLURM_NTASKS": "2", "SLURM_PROCID": "x"})


@pytest.mark.parametrize("n", [0, 1, 5, 27, 100])
@pytest.mark.parametrize("p", [1, 2, 3, 7])
def test_split_items_covers_in_order(n, p):
    blocks = [split_items(n, k, p) for k in range(p)]
    assert [i for b in blocks for i in b] == list(range(n))
    assert max(map(len, blocks)) - min(map(len, blocks)) <= 1


def test_gather_one_process():
    assert allgather_json({"a": [1, 2.5]}) == [{"a": [1, 2.5]}]
    assert gather_items(["x", "y"], range(0, 2), 2) == ["x", "y"]
    with pytest.raises(DistributedError, match="no process"):
        gather_items(["x"], range(0, 1), 2)


def test_load_study(tmp_path):
    s = load_study("recovery")
    assert isinstance(s, RecoveryStudy) and len(s.items()) == 27 * 3
    p = tmp_path / "mc.toml"
    p.write_text('kind = "mc"\nphotons = 1000\n')
    assert load_study(str(p)) == MCStudy(photons=1000)
    p.write_text('kind = "mcmc"\n')
    with pytest.raises(ConfigError, match="kind"):
        load_study(str(p))
    p.write_text('scene = "optoskin"\nreplicas = 3\n')
    with pytest.raises(ConfigError, match="replicas"):
        load_study(str(p))
    with pytest.raises(ConfigError, match="no such study"):
        load_study(str(tmp_path / "none.toml"))


def test_study_cli_bad_launch_is_one_line(tmp_path):
    from tofjax.cli import main

    assert main(["study", "recovery", "--out", str(tmp_path / "o"), "--processes", "2", "--process-id", "0"]) == 2
    assert main(["study", "recovery", "--out", str(tmp_path / "o"), "--chunk", "0"]) == 2


# ---- two processes on this machine (jax.distributed, gloo) ---------------------------------------

_GATHER = textwrap.dedent(
    """
    import sys
    from tofjax import parallel
    k, port = int(sys.argv[1]), sys.argv[2]
    parallel.initialize(parallel.Cluster(2, k, f"localhost:{port}"), timeout_s=60)
    import jax
    assert jax.process_count() == 2 and len(jax.devices()) == 2
    mine = parallel.split_items(5, k, 2)
    got = parallel.gather_items([{"item": i, "by": k, "s": "x" * (i + 3 * k)} for i in mine], mine, 5)
    print([g["item"] for g in got], [g["by"] for g in got], len(got[4]["s"]))
    """
)


def test_two_processes_gather_in_item_order():
    port = _free_port()
    out = _two_processes(lambda k: [sys.executable, "-c", _GATHER, str(k), str(port)], timeout=120)
    for r in out:
        assert r.stdout.strip().splitlines()[-1] == "[0, 1, 2, 3, 4] [0, 0, 0, 1, 1] 7"


# ---- equality of one process and two, one device and two (slow: compiles fits and the MC) -------

_TINY_RECOVERY = 'scene = "optoskin"\nframes = 20\nreplicates = 3\nseed = 5\nn1 = [1.4]\nmu_s_per_m = [0.6]\nmu_a_per_m = [0.14]\n'
_TINY_MC = 'kind = "mc"\nscene = "optoskin"\nphotons = 3000\nbatch = 4096\nseed = 3\n'


def _study(config: Path, out: Path, *extra, **env) -> None:
    r = subprocess.run([sys.executable, "-m", "tofjax.cli", "study", str(config), "--out", str(out), *extra],
                       env=_env(**env), capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]


def _study_two_processes(config: Path, out: Path, *extra) -> None:
    port = _free_port()
    _two_processes(lambda k: [sys.executable, "-m", "tofjax.cli", "study", str(config), "--out", str(out), *extra,
                              "--processes", "2", "--process-id", str(k), "--coordinator", f"localhost:{port}"],
                   timeout=900)


def _fits(path: Path) -> list[dict]:
    return [f for p in json.loads(path.read_text())["points"] for f in p["fits"]]


@pytest.mark.slow
def test_recovery_study_two_processes_and_two_devices_equal_one(tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(_TINY_RECOVERY)
    _study(cfg, tmp_path / "one", "--chunk", "2")
    _study_two_processes(cfg, tmp_path / "two", "--chunk", "2")
    _study(cfg, tmp_path / "dev", "--chunk", "2", XLA_FLAGS="--xla_force_host_platform_device_count=2")
    one, two, dev = (_fits(tmp_path / d / "recovery.json") for d in ("one", "two", "dev"))
    assert len(one) == 3
    assert json.loads((tmp_path / "two" / "recovery.json").read_text())["processes"] == 2
    assert json.loads((tmp_path / "dev" / "recovery.json").read_text())["per_process"][0]["devices"] == 2
    for a, b, c in zip(one, two, dev):
        assert a["result"] == b["result"] == c["result"]
        for k in ("n1", "mu_s_per_m", "mu_a_per_m", "reduced_chi2"):
            assert b[k] == pytest.approx(a[k], rel=1e-9, abs=1e-12)
            assert c[k] == pytest.approx(a[k], rel=1e-9, abs=1e-12)


@pytest.mark.slow
def test_mc_study_two_processes_equal_one(tmp_path):
    cfg = tmp_path / "mc.toml"
    cfg.write_text(_TINY_MC)
    _study(cfg, tmp_path / "one")
    _study_two_processes(cfg, tmp_path / "two")
    a, b = (json.loads((tmp_path / d / "mc.json").read_text()) for d in ("one", "two"))
    assert (a["devices"], b["devices"], b["processes"]) == (1, 2, 2)
    assert a["events"] == b["events"]  # the same packets, followed event for event
    fa, fb = np.asarray(a["fraction"]), np.asarray(b["fraction"])
    assert np.abs(fb - fa).max() <= 1e-5 * np.abs(fa).max()  # float32 tallies summed in another order
    for k in a["ledger"]:
        assert b["ledger"][k] == pytest.approx(a["ledger"][k], rel=1e-5, abs=1e-8)
