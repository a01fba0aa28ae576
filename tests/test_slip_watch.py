"""The one slip loop (solver/slippage/watch.py): the live service hands frames over in whatever pieces the
reader delivers and still runs the micro-batches the slip figures were measured on; a changed tree
keeps watching (a slip just after it is found); a failing monitor stops watching but loses no frame, and the live service says so.
"""

from __future__ import annotations

import logging

import httpx
import numpy as np
import pytest

from flockcal.server.settings import Settings
from flockcal.simulator.performer import Performer
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.slippage.watch import SlipWatch
from flockcal.solver.slippage import SlipMonitor
from server_helpers import ServerThread, free_port, wait_connected
from service_process import wait_for
from slip_replay import tree

RATE = 100.0


def walk(seconds: float, slip: str | None = None, at: float = 9.0):
    perf = Performer("human", routine="walk", seed=3, noise="tracker", rate_hz=RATE, seconds=60)
    if slip:
        perf.inject_slip(slip, 0.02, at_time=at)
    times = np.arange(int(round(seconds * RATE))) / RATE
    return perf, (times, *perf.poses(times))


def pieces(frames, sizes):
    """The frames cut into consecutive pieces of the given sizes (cycled), as a reader hands them over."""
    n = len(frames[0])
    a, k = 0, 0
    while a < n:
        b = min(n, a + int(sizes[k % len(sizes)]))
        yield tuple(x[a:b] for x in frames)
        a, k = b, k + 1


@pytest.mark.parametrize("catch_up", [3, 10])
def test_a_pipeline_catching_up_still_finds_the_slip_in_time(catch_up):
    # A live service behind its tracker feeds 0.1 s or 1/3 s micro-batches (server/pipeline.py) until it
    # has caught up. The slip must still be found, on the right sensor, within docs/slippage.md's 0.5 s
    # of detection; the catch-up pieces are long ones, as a backlog comes.
    perf, frames = walk(14.0, slip="r_shin")
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names)
    for piece in pieces(frames, [37, 61, 150]):
        watch.feed(*piece, catch_up=catch_up)
    assert [e.sensor for e in watch.events] == ["r_shin"], watch.events
    assert 0 < watch.events[0].detected_s - 9.0 <= 0.5, watch.events
    assert abs(watch.events[0].time_s - 9.0) <= 0.1, watch.events
    assert watch.segments.frames == len(frames[0]) - len(watch._held[0] if watch._held else ())


def test_frames_handed_over_in_any_pieces_give_the_events_and_fits_of_one_replay():
    # The live service must do what docs/slippage.md measured: the same micro-batches, so the same
    # events at the same times and the same refits, whether a take is replayed at once or arrives live.
    perf, frames = walk(14.0, slip="r_shin")
    whole = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names)
    whole.feed(*frames)
    assert [e.sensor for e in whole.events] == ["r_shin"], whole.events  # the case is not empty
    live = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names)
    rng = np.random.default_rng(0)
    for piece in pieces(frames, rng.integers(1, 9, size=97)):
        live.feed(*piece)
    assert [(e.sensor, e.time_s, e.detected_s) for e in live.events] == \
        [(e.sensor, e.time_s, e.detected_s) for e in whole.events]
    np.testing.assert_array_equal(live.fits.c, whole.fits.c)
    assert live.segments.frames == whole.segments.frames


@pytest.mark.parametrize("rate_hz", [100.0, 120.0, 130.0, 144.0])
def test_the_accumulator_moves_on_at_least_30_times_a_second_at_any_tracker_rate(rate_hz):
    # The service refits 30 times a second (docs/service.md) on what the slip loop has put into the
    # accumulator; micro-batches longer than 1/30 s (5 frames at 144 Hz) left it 28.8 updates a second.
    perf = Performer("human", routine="walk", seed=3, noise="tracker", rate_hz=rate_hz, seconds=4)
    times = np.arange(int(2 * rate_hz)) / rate_hz
    frames = (times, *perf.poses(times))
    watch = SlipWatch(tree(perf.model), perf.n_sensors, rate_hz, perf.names)
    counts = []
    for piece in pieces(frames, [1]):  # frame by frame, as a fast reader hands them over
        watch.feed(*piece)
        counts.append(watch.segments.frames)
    updates = np.count_nonzero(np.diff(counts))
    assert watch.monitor is not None  # the micro-batch path, not the no-tree shortcut
    assert updates / (times[-1] - times[0]) >= 30, (updates, rate_hz)


def test_the_same_tree_in_another_order_changes_nothing_and_a_new_one_keeps_the_accumulator():
    perf, frames = walk(6.0)
    J = tree(perf.model)
    watch = SlipWatch(None, perf.n_sensors, RATE, perf.names)
    watch.feed(*(x[:200] for x in frames))  # no tree yet: the frames only go into the accumulator
    assert watch.monitor is None and watch.segments.frames == 200
    assert watch.watch(J) and not watch.watch(J[::-1].copy())  # the same tree, in any order, changes nothing
    watch.feed(*(x[200:] for x in frames))
    watch.flush()
    assert watch.watch(J[:-1])  # one joint fewer: the monitor watches the new list
    assert len(watch.monitor.joints) == len(J) - 1
    assert watch.segments.frames == len(frames[0])


def _index(perf, child: str) -> int:
    return list(perf.names).index(child)


@pytest.mark.parametrize("case", ["shared joints", "a joint new to the tree", "the first tree"])
def test_a_slip_just_after_the_tree_changed_is_found_in_time(case):
    # The live service's fitted tree changes now and then (server/pipeline.py hands a changed tree on once
    # it has held for 3 s). A slip 1 s after such a change must still be found within docs/slippage.md's
    # 0.5 s, naming the sensor: a monitor that started afresh on every change was blind for its 5 s
    # warm-up, and slips after a change were missed through the service (issue #20).
    slip_at, change_at = 9.0, 8.0
    perf, frames = walk(11.0, slip="r_shin", at=slip_at)
    J = tree(perf.model)
    if case == "shared joints":  # a joint far from the slip comes and goes
        before = J[J[:, 0] != _index(perf, "l_hand")]
    elif case == "a joint new to the tree":  # the slipped sensor's own joint to its parent was missing
        before = J[J[:, 0] != _index(perf, "r_shin")]
    else:  # no tree at all until the first fit
        before = None
    watch = SlipWatch(before, perf.n_sensors, RATE, perf.names)
    cut = int(round(change_at * RATE))
    watch.feed(*(x[:cut] for x in frames))
    kept = None if before is None else dict(zip(map(tuple, before.tolist()), watch.monitor.segment_start))
    assert watch.watch(J)
    if kept is not None:  # the joints both trees share kept their segments (nothing had slipped)
        assert all(kept.get(row, start) == start for row, start in
                   zip(map(tuple, J.tolist()), watch.monitor.segment_start))
    watch.feed(*(x[cut:] for x in frames))
    assert [e.sensor for e in watch.events] == ["r_shin"], watch.events
    assert 0 < watch.events[0].detected_s - slip_at <= 0.5, watch.events
    assert abs(watch.events[0].time_s - slip_at) <= 0.1, watch.events
    assert set(watch.events[0].joints) == {"r_shin", "r_foot"}  # both its joints stepped, the new one too
    assert watch.segments.frames == len(frames[0]) - len(watch._held[0] if watch._held else ())


class Failing(SlipMonitor):
    """A monitor that breaks after a while, as a bug in it would."""

    calls = 0

    def add_frames(self, *args, **kwargs):
        Failing.calls += 1
        if Failing.calls > 40:
            raise RuntimeError("monitor broke")
        return super().add_frames(*args, **kwargs)


def test_a_failing_monitor_stops_watching_but_every_frame_reaches_the_accumulator(monkeypatch):
    monkeypatch.setattr("flockcal.solver.slippage.watch.SlipMonitor", Failing)
    perf, frames = walk(4.0)
    Failing.calls = 0
    strict = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names)
    with pytest.raises(RuntimeError, match="monitor broke"):  # a replay: the failure is a bug, raised
        strict.feed(*frames)
    strict.flush()  # the remainder of an unfinished micro-batch
    Failing.calls = 0
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, strict=False)
    for piece in pieces(frames, [7]):
        watch.feed(*piece)
    watch.flush()
    assert isinstance(watch.failure, RuntimeError) and watch.monitor is None
    assert not watch.watch(tree(perf.model)[:-1])  # it stays stopped for the session
    reference = GramAccumulator(perf.n_sensors)
    reference.add_poses(frames[1], frames[2], frames[3])
    assert watch.segments.frames == strict.segments.frames == reference.frames == len(frames[0])


def test_live_service_reports_a_failing_slip_monitor_once_as_a_tracker_event(tmp_path, monkeypatch, caplog):
    # Tried: a slip monitor that raises on every batch during a live session.
    class Broken(SlipMonitor):
        def add_frames(self, *args, **kwargs):
            raise RuntimeError("monitor broke")

    monkeypatch.setattr("flockcal.solver.slippage.watch.SlipMonitor", Broken)
    settings = Settings(device="sim://walk?birds=16&motion=walk&rate=100&baud=921600&seed=2", birds=16,
                        http_port=free_port(), data_dir=tmp_path)
    with caplog.at_level(logging.ERROR, logger="flockcal.server"), ServerThread(settings) as srv:
        wait_connected(srv.url)
        r = httpx.post(srv.url + "/api/sessions", json={"performer": "Eve", "skeleton": "human"})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        def session_events() -> list[dict]:
            return httpx.get(srv.url + f"/api/sessions/{sid}/events").json()["events"]

        def frames() -> int:
            return httpx.get(srv.url + "/api/status").json()["session"]["frames"]

        wait_for(lambda: any(e["type"] == "tracker" and e.get("kind") == "slip_watch_failed"
                             for e in session_events()), 30, "the slip watch's failure reported", every=0.2)
        # A second of frames more (100 at 100 Hz): the failure must not be reported again.
        more = frames() + 100
        wait_for(lambda: frames() >= more, 30, "100 frames more")
        events = session_events()
        frames_before = httpx.get(srv.url + "/api/status").json()["session"]["frames"]
        r = httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30)
        assert r.status_code == 200, r.text
        result = httpx.get(srv.url + f"/api/sessions/{sid}/result")
    failed = [e for e in events if e["type"] == "tracker" and e.get("kind") == "slip_watch_failed"]
    assert len(failed) == 1, events
    assert "monitor broke" in failed[0]["message"] and "restart the session" in failed[0]["message"]
    logged = [r for r in caplog.records if "slip monitor failed" in r.getMessage()]
    assert len(logged) == 1 and logged[0].exc_info is not None  # with its traceback
    assert frames_before > 0 and result.status_code == 200  # recording and fitting went on
