"""A pipeline thread that fell behind its tracker catches up in steps and keeps publishing: clients see
the backlog go down instead of hearing nothing until it is gone, and no frame of the session is lost.
"""

from __future__ import annotations

import io
import threading

import httpx
import numpy as np

from flockcal.server.settings import Settings
from server_helpers import free_port, manual_service, run_clock
from service_process import wait_for

RATE = 144.0
STALL_S = 6.0


def test_a_backlog_is_worked_off_in_steps_with_snapshots_between(tmp_path):
    settings = Settings(device=f"sim://backlog?birds=8&motion=exercise&rate={RATE:g}&baud=921600", birds=8, baud=921600,
                        http_port=free_port(), data_dir=tmp_path)
    # On the service's clock, moved by the test (server_helpers.manual_service): the stall is 6 s of the
    # tracker's frames however fast the machine runs.
    with manual_service(settings) as (srv, clock):
        pipe = srv.service.pipeline
        # What the fake tracker sent, as the reader decoded it, batch by batch (on the reader's thread).
        reader = srv.service.source.reader
        sent: list = []
        lock = threading.Lock()
        deliver = reader.on_frames

        def tap(frames):
            with lock:
                sent.append((np.array(frames.times), np.array(frames.positions), np.array(frames.valid)))
            deliver(frames)

        def n_sent() -> int:
            with lock:
                return sum(len(b[0]) for b in sent)

        reader.on_frames = tap
        before_start = n_sent()
        r = httpx.post(srv.url + "/api/sessions", json={"performer": "Backlog"}, timeout=30)
        after_start = n_sent()
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        run_clock(clock, 2.0)
        seen: list[tuple[float, int]] = []
        publish = pipe.on_publish

        def spy(snap):
            seen.append((clock.monotonic(), snap.frames))
            publish(snap)

        pipe.on_publish = spy
        # Tried: the pipeline thread held up for 6 s (as a starved machine's is), 6 s of frames waiting.
        held: list[float] = []

        def hold() -> None:
            held.append(clock.monotonic())
            clock.sleep(STALL_S)

        caller = threading.Thread(target=pipe.call, args=(hold,), daemon=True)
        caller.start()
        wait_for(lambda: held, 30, "the pipeline thread held")
        run_clock(clock, STALL_S)
        caller.join(30)
        stalled = clock.monotonic()
        run_clock(clock, 3.0)
        pipe.on_publish = publish
        before_stop = n_sent()
        r = httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=60)
        after_stop = n_sent()
        assert r.status_code == 200, r.text
        reader.on_frames = deliver
        take = httpx.get(srv.url + f"/api/sessions/{sid}/take", timeout=60)
        assert take.status_code == 200, take.text
        stored = np.load(io.BytesIO(take.content))

    after = [(t, n) for t, n in seen if t >= stalled - 0.05]
    counts = [n for _, n in after]
    assert len(after) >= 4, after
    # The backlog (over 800 frames) went out in steps no bigger than 2 s of frames, each published.
    jumps = [b - a for a, b in zip(counts, counts[1:])]
    assert max(jumps) <= 2.0 * RATE, jumps
    assert sum(j for j in jumps if j > 0.5 * RATE) >= 0.5 * STALL_S * RATE, jumps  # the backlog was there
    # Every frame the tracker sent during the session is stored once, in order, unchanged: the stored take
    # is one unbroken run of the sent frames (a dropped, repeated or reordered frame breaks it), from the
    # first frame sent after the start request to the last sent before the stop took effect.
    times = np.concatenate([b[0] for b in sent])
    positions = np.concatenate([b[1] for b in sent])
    valid = np.concatenate([b[2] for b in sent])
    n = len(stored["times"])
    assert n > (STALL_S + 3.0) * 0.5 * RATE, n  # the stall and the 3 s after it are in the session
    # The take's times count from the session's first frame; that frame is the one sent while the start
    # request was on its way whose pose the take begins with.
    first = next((k for k in range(before_start, after_start + 1)
                  if k < len(times) and np.array_equal(positions[k], stored["positions"][0])), None)
    assert first is not None, (before_start, after_start)
    assert before_stop <= first + n <= after_stop, (before_stop, first + n, after_stop)
    assert np.array_equal(stored["times"], times[first:first + n] - times[first])
    assert np.array_equal(stored["positions"], positions[first:first + n])
    assert np.array_equal(stored["valid"], valid[first:first + n])


def test_a_pipeline_behind_for_good_still_refits(tmp_path):
    # A machine so starved that the pipeline never catches up: it must still hand out refits (progress,
    # the tree and the dashboard's fit move on), only fewer of them. Tried: the pipeline told it is
    # behind at every step for 4 s. Before, no refit went out at all while it was behind.
    settings = Settings(device=f"sim://behind?birds=8&motion=exercise&rate={RATE:g}&baud=921600", birds=8,
                        baud=921600, http_port=free_port(), data_dir=tmp_path)
    with manual_service(settings) as (srv, clock):
        pipe = srv.service.pipeline
        r = httpx.post(srv.url + "/api/sessions", json={"performer": "Behind"}, timeout=30)
        assert r.status_code == 201, r.text
        run_clock(clock, 2.0)
        pipe._behind = lambda now: True
        before = pipe.fits_done
        run_clock(clock, 4.0)
        during = pipe.fits_done - before
        del pipe._behind
        httpx.post(srv.url + f"/api/sessions/{r.json()['id']}/stop", timeout=60)
    assert during >= 4, during  # at least one a second (the service's 30/s when it keeps up)
