"""A live session's memory is bounded by design (docs/service.md "A long session's memory and disk"): the
live pipeline (server/pipeline.py, with its live calibration, slip watch, persistence and snapshots) holds
as many bytes after two minutes of a session as after one; and the accumulator's segment snapshots share
a few moments arrays however often refits copy it (the RSS of a real service over half an hour is
benchmarks/bench_live_memory.py's figure, not a unit test's).
"""

from __future__ import annotations

import collections
import sys
import time

import numpy as np

from flockcal.frames import Frames
from flockcal.simulator.performer import Performer
from flockcal.solver.segments import SegmentedAccumulator

RATE = 144.0
HALF_S = 50.0


def held_bytes(root) -> int:
    """Bytes reachable from `root` through attributes and containers: numpy arrays (each buffer once, a view
    counting as the array it looks into), byte strings, and the containers and numbers themselves."""
    seen: set[int] = set()
    buffers: dict[int, int] = {}
    objects = 0
    stack = [root]
    while stack:
        obj = stack.pop()
        if id(obj) in seen or isinstance(obj, (type, type(time), type(held_bytes))):
            continue
        seen.add(id(obj))
        if isinstance(obj, (str, int, float, bool, dict, list, tuple, set, frozenset, collections.deque)):
            objects += sys.getsizeof(obj)
        if isinstance(obj, np.ndarray):
            base = obj
            while isinstance(base.base, np.ndarray):
                base = base.base
            buffers[id(base)] = base.nbytes
            continue
        if isinstance(obj, (bytes, bytearray)):
            buffers[id(obj)] = len(obj)
            continue
        if isinstance(obj, dict):
            stack.extend(obj.keys())
            stack.extend(obj.values())
        elif isinstance(obj, (list, tuple, set, frozenset, collections.deque)):
            stack.extend(obj)
        elif hasattr(obj, "__dict__") or hasattr(type(obj), "__slots__"):
            if type(obj).__module__.split(".")[0] not in ("flockcal", "collections"):
                continue  # threads, locks, the database connection: not session data
            stack.extend(getattr(obj, "__dict__", {}).values())
            stack.extend(getattr(obj, name) for name in getattr(type(obj), "__slots__", ()) if hasattr(obj, name))
    return objects + sum(buffers.values())


def after_flushing(pipe) -> int:
    """`held_bytes` of the pipeline once the buffers it empties on the wall clock are written (the frame log
    every 0.25 s, residual rows every second): a replay faster than real time fills them with more."""
    pipe.live.framelog.flush()
    pipe.persistence.flush_db(pipe.live)
    return held_bytes(pipe)


def test_segment_snapshots_share_a_few_moments_arrays_however_often_refits_copy():
    """What was tried: a minute of 16 sensors at 144 Hz in batches of 3 frames, with a refit's copy of the
    accumulator after every batch (as often as a pipeline behind its frames hands them out). The 150
    snapshots of the last 15 s share at most 4 moments arrays (the whole take folds every 16 score blocks of
    64 frames: 7.1 s), and the sums are those of an accumulator fed the same frames without a copy."""
    perf = Performer("human", routine="walk", rate_hz=RATE, birds=16)
    times = np.arange(int(60 * RATE)) / RATE
    R, t, valid = perf.poses(times)
    acc, plain = SegmentedAccumulator(16), SegmentedAccumulator(16)
    copies = []
    for a in range(0, len(times), 3):
        acc.ingest(times[a:a + 3], R[a:a + 3], t[a:a + 3], valid[a:a + 3])
        copies = [acc.copy()]  # the fit thread holds one at a time
    plain.ingest(times, R, t, valid)
    moments = {id(snap._moments) for _, snap in acc._snaps}
    assert len(acc._snaps) == 150 and len(moments) <= 4, len(moments)
    pairs = np.array([[i, j] for i in range(16) for j in range(i + 1, 16)])
    got, want = acc.whole.block_moments(pairs), plain.whole.block_moments(pairs)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-9)
    assert copies[0].whole.frames == len(times)


def test_the_live_pipeline_holds_as_much_after_100_s_as_after_50_s(tmp_path):
    """What was tried: the service's pipeline (reader hand-over, live calibration with slip watch and refits,
    frame log, database, snapshots) fed 100 s of 6 sensors at 144 Hz in the reader's 3-frame batches, 20 times
    faster than real time. Its windows are full after 50 s (the slip monitor's pose history holds 40 s), but
    for the monitor's log of its frame scan's best steps (2,000 entries, full at ~70 s: +1 %); so the bytes
    its objects hold at 100 s are those at 50 s within 2 % (a series, event list or frame list kept per
    frame or per sample would add more: 50 s of the residual samples alone are 3 %)."""
    from server_helpers import live_pipeline

    perf = Performer("human", routine="walk", rate_hz=RATE, birds=6)
    with live_pipeline(tmp_path, tuple(perf.names), RATE) as pipe:
        held = []
        start = time.monotonic()
        for part in range(2):
            times = part * HALF_S + np.arange(int(HALF_S * RATE)) / RATE
            R, t, valid = perf.poses(times)
            for a in range(0, len(times), 3):
                pipe.feed(Frames(start + times[a:a + 3], R[a:a + 3], t[a:a + 3], valid[a:a + 3]))
                if (a + 3) % int(RATE) == 0:  # a second of frames: let refits land (20 seconds a second)
                    pipe.call(lambda: None, timeout=60)
                    time.sleep(0.05)
            held.append(pipe.call(lambda: after_flushing(pipe), timeout=120))
        assert pipe.call(lambda: pipe.live.cal.received) == 2 * int(HALF_S * RATE)
        assert pipe.fits_done > 10 and pipe.live.cal.watch.monitor is not None
        assert held[1] <= 1.02 * held[0], held
