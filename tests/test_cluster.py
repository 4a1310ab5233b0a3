"""A sweep on a cluster of more machines than one, as a user starts it: ``dask scheduler`` and
``dask worker`` on the loopback address, in another directory, and an experiment run through
them with ``--scheduler tcp://HOST:PORT`` gives the same results.csv as on a LocalCluster."""

import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments"
sys.path.insert(0, str(EXPERIMENTS))
import run_all  # noqa: E402

DASK = Path(sys.executable).with_name("dask")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def loopback_cluster(tmp_path):
    """A scheduler and one single-threaded worker, started from a directory of their own."""
    from dask.distributed import Client

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    address = f"tcp://127.0.0.1:{free_port()}"
    quiet = dict(cwd=elsewhere, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                               "--no-dashboard"], **quiet)]
    try:
        procs.append(subprocess.Popen([str(DASK), "worker", address, "--nworkers", "1", "--nthreads", "1",
                                       "--no-dashboard"], **quiet))
        deadline = time.monotonic() + 60
        with Client(address, timeout=60) as client:
            client.wait_for_workers(1, timeout=max(deadline - time.monotonic(), 1))
        yield address
    finally:
        for p in reversed(procs):
            p.kill()  # throwaway processes: no graceful shutdown to wait for
        for p in procs:
            p.wait(timeout=30)


def test_experiment_through_a_loopback_scheduler_matches_the_local_cluster(tmp_path, loopback_cluster):
    experiment = run_all.load("paper_banana")
    assert experiment.main(["--quick", "--scheduler", loopback_cluster, "--out", str(tmp_path / "remote")]) == 0
    assert experiment.main(["--quick", "--workers", "1", "--out", str(tmp_path / "local")]) == 0
    remote = (tmp_path / "remote" / "paper_banana" / "results.csv").read_text()
    local = (tmp_path / "local" / "paper_banana" / "results.csv").read_text()
    assert remote.count("\n") > 1 and remote == local
    run = (tmp_path / "remote" / "paper_banana" / "run.json").read_text()
    assert loopback_cluster in run  # the run records where it ran
