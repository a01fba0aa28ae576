"""`flockcal batch --scheduler` against a cluster started the way one is on real machines: a `dask scheduler`
and two `dask worker` processes on 127.0.0.1 (free ports), run from another folder than the client. Results
are byte for byte what `fit --json` prints, for an .npz and for a .fobraw recording (as `convert` + `fit`)."""

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from flockcal.simulator.performer import Performer
from flockcal.takes import make_take, save_take

pytest.importorskip("distributed", reason="flockcal batch needs Dask: pip install '.[test]'")


def flockcal(*argv, cwd=None, check=True):
    out = subprocess.run([sys.executable, "-m", "flockcal", *map(str, argv)], capture_output=True, timeout=280, cwd=cwd)
    if check:
        assert out.returncode == 0, out.stderr.decode()
    return out


def _dask(*argv, cwd, log):
    # Its own process group, so stopping it also stops the worker processes its nanny started.
    return subprocess.Popen([sys.executable, "-m", "dask", *argv], cwd=cwd, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    home = tmp_path_factory.mktemp("cluster")
    info = home / "scheduler.json"
    log = (home / "dask.log").open("wb")
    procs = [_dask("scheduler", "--host", "127.0.0.1", "--port", "0", "--dashboard-address", "127.0.0.1:0",
                   "--scheduler-file", str(info), cwd=home, log=log)]
    try:
        deadline = time.monotonic() + 60
        while not info.exists() or not info.read_text().strip():
            assert time.monotonic() < deadline and procs[0].poll() is None, (home / "dask.log").read_text()
            time.sleep(0.2)
        address = json.loads(info.read_text())["address"]
        for _ in range(2):
            procs.append(_dask("worker", address, "--nthreads", "1", "--nworkers", "1", "--host", "127.0.0.1",
                               "--no-dashboard", cwd=home, log=log))
        from distributed import Client

        with Client(address, timeout=60) as c:
            c.wait_for_workers(2, timeout=90)
        yield address
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        log.close()


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    src = tmp_path_factory.mktemp("takes")
    for seed in (1, 2):
        perf = Performer("human", "exercise", seed=seed, birds=6, rate_hz=100.0, period=8.0)
        R, t, v = perf.poses(np.arange(800) / 100.0)
        save_take(src / f"six{seed}.npz", make_take(R, t, perf.names, 100.0, valid=v))
    url = "sim://batch-scheduler?birds=4&rate=50&motion=walk"
    flockcal("record", "--port", url, "--birds", "4", "--rate", "50", "-o", src / "live.fobraw", "--seconds", "3")
    return src


def test_batch_on_a_running_cluster_gives_what_fit_prints(cluster, takes, tmp_path):
    out_dir = tmp_path / "results"
    # Relative names, from the takes' folder: the workers run elsewhere and must get absolute paths.
    # Three seconds of a 4-bird walk may pin no joint: --allow-partial fits it anyway, as it does for `fit`.
    run = flockcal("batch", "six1.npz", "six2.npz", "live.fobraw", "-o", out_dir, "--scheduler", cluster,
                   "--allow-partial", cwd=takes)
    err = run.stderr.decode()
    assert f"3 takes on the cluster at {cluster}" in err and "Dask dashboard at http://127.0.0.1:" in err
    rows = list(csv.DictReader((out_dir / "summary.csv").open()))
    assert [r["take"] for r in rows] == ["six1.npz", "six2.npz", "live.fobraw"]
    assert all(r["error"] == "" for r in rows), rows
    for name in ("six1", "six2"):
        assert (out_dir / f"{name}.json").read_bytes() == flockcal("fit", takes / f"{name}.npz", "--json").stdout
    flockcal("convert", takes / "live.fobraw", "-o", tmp_path / "live.npz")
    fitted = flockcal("fit", tmp_path / "live.npz", "--json", "--allow-partial")
    assert (out_dir / "live.json").read_bytes() == fitted.stdout
    # The same warning when fit gives one (a live recording moves as the clock fell; it may or may not).
    assert ("is too still to fit" in fitted.stderr.decode()) == ("warning: live.fobraw is too still to fit" in err)
    assert rows[2]["sensors"] == "4" and int(rows[2]["frames"]) > 100


def test_a_scheduler_that_does_not_answer_is_one_line_and_exit_2(tmp_path):
    import socket

    with socket.socket() as s:  # a port nobody listens on any more
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "t.npz").write_bytes(b"")
    run = flockcal("batch", tmp_path / "t.npz", "-o", tmp_path / "out", "--scheduler", f"tcp://127.0.0.1:{port}",
                   "--timeout", "2", check=False)
    err = run.stderr.decode()
    assert run.returncode == 2 and err.count("\n") == 1, err
    assert f"cannot reach the Dask scheduler at tcp://127.0.0.1:{port}" in err and "dask scheduler" in err
