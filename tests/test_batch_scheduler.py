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


PARTS = 9  # one more than the client folds at once, so the sums are folded in two rounds


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    src = tmp_path_factory.mktemp("takes")
    # Nine 6 s takes of one performer's 24 s routine, small enough that many of them cost little.
    perf = Performer("human", "exercise", seed=1, birds=6, rate_hz=100.0, period=24.0, sta_mm=0)
    for k in range(PARTS):
        times = np.arange(600) / 100.0 + 6.0 * k
        R, t, v = perf.poses(times)
        save_take(src / f"six{k}.npz", make_take(R, t, perf.names, 100.0, valid=v, times=times - times[0]))
    url = "sim://batch-scheduler?birds=4&rate=50&motion=walk"
    flockcal("record", "--port", url, "--birds", "4", "--rate", "50", "-o", src / "live.fobraw", "--seconds", "3")
    return src


@pytest.fixture(scope="module")
def batch(cluster, takes, tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("results")
    # Relative names, from the takes' folder: the workers run elsewhere and must get absolute paths.
    # Three seconds of a 4-bird walk may pin no joint: --allow-partial fits it anyway, as it does for `fit`.
    names = [f"six{k}.npz" for k in range(PARTS)] + ["live.fobraw"]
    run = flockcal("batch", *names, "-o", out_dir, "--scheduler", cluster, "--allow-partial", "--combine", cwd=takes)
    return out_dir, names, run.stderr.decode()


def test_batch_on_a_running_cluster_gives_what_fit_prints(cluster, takes, batch, tmp_path):
    out_dir, names, err = batch
    assert f"{PARTS + 1} takes on the cluster at {cluster}" in err and "Dask dashboard at http://127.0.0.1:" in err
    rows = list(csv.DictReader((out_dir / "summary.csv").open()))
    assert [r["take"] for r in rows] == names
    assert all(r["error"] == "" for r in rows), rows
    for name in ("six0", "six5"):
        assert (out_dir / f"{name}.json").read_bytes() == flockcal("fit", takes / f"{name}.npz", "--json").stdout
    flockcal("convert", takes / "live.fobraw", "-o", tmp_path / "live.npz")
    fitted = flockcal("fit", tmp_path / "live.npz", "--json", "--allow-partial")
    assert (out_dir / "live.json").read_bytes() == fitted.stdout
    # The same warning when fit gives one (a live recording moves as the clock fell; it may or may not).
    assert ("is too still to fit" in fitted.stderr.decode()) == ("warning: live.fobraw is too still to fit" in err)
    assert rows[-1]["sensors"] == "4" and int(rows[-1]["frames"]) > 100


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


def test_combine_folds_many_takes_into_plain_least_squares_on_all_their_frames(takes, batch):
    from flockcal.takes import load_take
    from plain_lsq import plain_fit

    out_dir, names, err = batch
    names = names[:-1]  # the six-sensor takes
    combined = json.loads((out_dir / "combined.json").read_text())
    assert combined["takes"] == names and combined["frames"] == 600 * PARTS, err
    assert [e["take"] for e in combined["left_out"]] == ["live.fobraw"]  # four birds, not the six
    parts = [load_take(takes / n) for n in names]
    checked = 0
    for j in combined["joints"]:
        if not j["determined"] or j["hinge"]:
            continue
        i, p = parts[0].names.index(j["child"]), parts[0].names.index(j["parent"])
        cat = [np.concatenate([getattr(tk, a)[:, x] for tk in parts]) for x, a in
               ((i, "rotations"), (i, "positions"), (p, "rotations"), (p, "positions"))]
        plain = plain_fit(*cat, np.concatenate([tk.valid[:, i] & tk.valid[:, p] for tk in parts]))
        # design.md §3a: a determined ball joint equals plain least squares within 1 mm.
        assert np.linalg.norm(np.subtract(j["c"], plain.c)) <= 1e-3, j["child"]
        checked += 1
    assert checked >= 2


# Start-up before the probe (the interpreter, flockcal's and Dask's imports) is about 1.5 s here; the margin
# covers it on a loaded 2-core machine. The claim (docs/batch.md): the probe itself ends by --timeout.
STARTUP_MARGIN_S = 8.0


def _batch_at(address, tmp_path, timeout=3.0):
    (tmp_path / "t.npz").write_bytes(b"")
    started = time.monotonic()
    run = flockcal("batch", tmp_path / "t.npz", "-o", tmp_path / "out", "--scheduler", address, "--timeout",
                   timeout, check=False)
    return run, run.stderr.decode(), time.monotonic() - started


def test_an_http_server_at_the_scheduler_address_is_named_in_one_line_within_the_timeout(tmp_path):
    # Tried: a real HTTP server on loopback that answers 400 to whatever it is sent (what the Dask dashboard
    # port does), given as the scheduler. Dask's client read "HTTP/1.1" as a frame length (3.07 EiB).
    import http.server
    import threading

    class Refuse(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_error(400, "Bad Request")

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Refuse)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        address = f"tcp://127.0.0.1:{server.server_address[1]}"
        run, err, took = _batch_at(address, tmp_path)
    finally:
        server.shutdown()
        server.server_close()
    assert run.returncode == 2 and err.count("\n") == 1, err
    assert f"{address} is not a Dask scheduler: an HTTP server answered ('HTTP/1.0 " in err, err
    assert "Traceback" not in err and took < 3.0 + STARTUP_MARGIN_S, took
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_a_silent_listener_at_the_scheduler_address_is_named_and_given_up_on_at_the_timeout(tmp_path):
    # Tried: a TCP listener that accepts connections (the kernel completes them) and never says a word.
    import socket

    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        address = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
        run, err, took = _batch_at(address, tmp_path, timeout=2.0)
    assert run.returncode == 2 and err.count("\n") == 1, err
    assert f"{address} is not a Dask scheduler: it accepted the connection but sent nothing in 2 s" in err, err
    assert 2.0 <= took < 2.0 + STARTUP_MARGIN_S, took


def test_the_dashboard_port_of_a_running_cluster_is_named_as_an_http_server(cluster, tmp_path):
    # Tried: the likeliest mistake, the running scheduler's own dashboard port given as the scheduler.
    from distributed import Client

    with Client(cluster, timeout=60) as c:
        port = c.scheduler_info()["services"]["dashboard"]
    address = f"tcp://127.0.0.1:{port}"
    run, err, took = _batch_at(address, tmp_path)
    assert run.returncode == 2 and err.count("\n") == 1, err
    assert f"{address} is not a Dask scheduler: an HTTP server answered ('HTTP/1.1 400 Bad Request'" in err, err
    assert took < 3.0 + STARTUP_MARGIN_S, took
