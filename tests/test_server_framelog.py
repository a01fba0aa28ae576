"""The session frame log (server/framelog.py, server/frameblocks.py): what it was given comes back bit for bit,
tracker frames take a fraction of the version-1 records, a log of version 1 (sessions recorded before the
upgrade) reads and downloads as it did, and a crash or damage on disk costs only the blocks it hits.

Tracker frames are made the way the live reader makes them: poses → the bytes a bird sends
(`encode_records`) → the driver's own decoding (`decode_block`), with dropouts and hemisphere flips.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from flockcal.drivers.records import FORMATS, decode_block_words, encode_records, record_length
from flockcal.frames import Frames, TrackerWords
from flockcal.server.downloads import FrameFile, npz_stream
from flockcal.server.framelog import FrameLog, FrameLogError, FrameLogReader, read_frames
from flockcal.simulator.performer import Performer

RATE = 144.0


def tracker_frames(fmt: str, scale: int, seconds: float = 6.0, birds: int = 16, seed: int = 0, words: bool = False):
    """(names, times, rotations, positions, valid) as the reader hands them over for `fmt` at `scale` inches;
    with `words`, the data words they were decoded from as well (Frames.words, flips negated in them)."""
    perf = Performer("human", routine="walk", rate_hz=RATE, birds=birds, seed=seed)
    times = 1234.5 + np.arange(int(seconds * RATE)) / RATE  # reader clock: monotonic seconds
    R0, x0, _ = perf.poses(times - times[0])
    n, m = R0.shape[:2]
    raw = np.frombuffer(encode_records(fmt, R0.reshape(-1, 3, 3), x0.reshape(-1, 3), scale_inches=scale), np.uint8)
    W, R, p, valid, _ = decode_block_words(fmt, raw.reshape(n * m, record_length(fmt, group=False)), scale_inches=scale)
    W, R, p, valid = W.reshape(n, m, -1), R.reshape(n, m, 3, 3), p.reshape(n, m, 3), valid.reshape(n, m)
    rng = np.random.default_rng(seed)
    valid &= rng.random((n, m)) > 0.02  # dropped records
    valid[100:160, 3] = False  # a sensor out for a while
    flip = np.where(rng.random(n) < 0.1, -1, 1)
    p[:, 5] *= flip[:, None]  # hemisphere flips, unfolded by negation
    W[:, 5, :3] *= flip[:, None]
    R[~valid], p[~valid] = 0.0, 0.0  # Frames: slots that are not valid hold zeros
    if words:
        return list(perf.names), times, R, p, valid, TrackerWords(W, FORMATS[fmt].command, scale)
    return list(perf.names), times, R, p, valid


def write_log(path, names, times, R, p, valid, per_flush: int = 36, batch: int = 3, words=None) -> None:
    """As the pipeline writes: small batches, a flush every `per_flush` frames (a quarter second at 144 Hz)."""
    log = FrameLog(path, names, RATE, flush_s=3600.0)
    for a in range(0, len(times), batch):
        log.write(times[a:a + batch], R[a:a + batch], p[a:a + batch], valid[a:a + batch],
                  None if words is None else words[a:a + batch])
        if (a + batch) % per_flush == 0:
            log.flush()
    log.close()


def write_version_1(path, names, times, R, p, valid) -> None:
    """A log as flockcal wrote it before version 2: a JSON line, then per frame a time (f8), the valid flags
    (u1 each), the rotations (9 f8 each) and the positions (3 f8 each), little-endian."""
    m = len(names)
    with open(path, "wb") as fh:
        fh.write((json.dumps({"format": "flockcal-frames", "version": 1, "names": names, "rate_hz": RATE}) + "\n").encode())
        for k in range(len(times)):
            fh.write(np.float64(times[k]).astype("<f8").tobytes() + valid[k].astype(np.uint8).tobytes()
                     + R[k].astype("<f8").tobytes() + p[k].astype("<f8").tobytes())
    assert path.stat().st_size > m * 96 * len(times)


def assert_bitwise(got: Frames, times, R, p, valid) -> None:
    assert got.times.tobytes() == np.asarray(times, dtype=float).tobytes()
    assert np.array_equal(got.valid, valid)
    assert got.rotations.tobytes() == R.tobytes()
    assert got.positions.tobytes() == p.tobytes()


@pytest.mark.parametrize("fmt,scale,limit", [("position_matrix", 72, 250), ("position_quaternion", 36, 200),
                                             ("position_angles", 72, 150)])
def test_tracker_frames_come_back_bit_for_bit_in_a_fraction_of_the_space(tmp_path, fmt, scale, limit):
    """What was tried: 6 s of 16 birds at 144 Hz in each pose format, with dropouts and hemisphere flips,
    written as the pipeline writes them. The claim: ~180 bytes a frame for position/matrix (docs/service.md);
    the limits allow a third more; version 1 took 1,560."""
    names, times, R, p, valid = tracker_frames(fmt, scale)
    path = tmp_path / "take.frames"
    write_log(path, names, times, R, p, valid)
    assert_bitwise(read_frames(path)[1], times, R, p, valid)
    per_frame = (path.stat().st_size - len(path.read_bytes().split(b"\n", 1)[0])) / len(times)
    assert per_frame < limit, f"{per_frame:.0f} bytes a frame"


@pytest.mark.parametrize("fmt,scale", [("position_matrix", 72), ("position_quaternion", 36)])
def test_the_words_the_reader_hands_over_are_stored_as_they_came(tmp_path, fmt, scale):
    """What was tried: the same frames written with the data words the reader decoded them from (hemisphere
    flips negated in them, as the reader negates the positions), and with words that belong to the next
    frame (a hand-over gone wrong). Both read back bit for bit; the words as they came take no more room
    than the words the log works out from the poses itself (which keeps whole what no pattern reproduces)."""
    names, times, R, p, valid, words = tracker_frames(fmt, scale, seconds=3.0, words=True)
    sizes = {}
    for how, w in (("searched", None), ("carried", words), ("wrong", words[np.r_[1:len(times), 0]])):
        path = tmp_path / f"{how}.frames"
        write_log(path, names, times, R, p, valid, words=w)
        assert_bitwise(read_frames(path)[1], times, R, p, valid)
        sizes[how] = path.stat().st_size
    assert sizes["carried"] <= sizes["searched"] and sizes["wrong"] == sizes["searched"], sizes


def test_frames_from_no_tracker_and_a_format_that_changes_are_kept_exactly(tmp_path):
    """What was tried: exact simulated poses (no tracker's words reproduce them), then tracker frames, then
    the tracker reconnected in another format and scale, with NaN in slots a record lacks."""
    names, t1, R1, p1, v1 = tracker_frames("position_matrix", 72, seconds=2.0)
    _, t2, R2, p2, v2 = tracker_frames("position_quaternion", 36, seconds=2.0, seed=1)
    perf = Performer("human", routine="walk", rate_hz=RATE, birds=16, seed=2)
    t0 = np.arange(200) / RATE
    R0, p0, v0 = perf.poses(t0)
    v0 = v0.copy()
    v0[50:60, 2] = False
    R0, p0 = R0.copy(), p0.copy()
    R0[50:60, 2], p0[50:60, 2] = np.nan, np.nan  # not valid: never read back as a pose
    times = np.concatenate([t0 + 1000.0, t1 + 2000.0, t2 + 3000.0])
    R, p, valid = np.concatenate([R0, R1, R2]), np.concatenate([p0, p1, p2]), np.concatenate([v0, v1, v2])
    path = tmp_path / "mixed.frames"
    write_log(path, names, times, R, p, valid)
    want_R = np.where(valid[..., None, None], R, 0.0)
    want_p = np.where(valid[..., None], p, 0.0)
    assert_bitwise(read_frames(path)[1], times, want_R, want_p, valid)


def test_a_version_1_log_reads_and_downloads_byte_for_byte_as_its_version_2_twin(tmp_path):
    """What was tried: the same frames written as version 1 (a session recorded before the upgrade, the last
    record cut by a crash) and as version 2: the frames, the .npz take a client downloads and its BVH are
    the same bytes."""
    from flockcal.exports.bvh import bvh_chunks
    from flockcal.solver.solve import solve_take
    from flockcal.takes import make_take

    names, times, R, p, valid = tracker_frames("position_matrix", 72, seconds=4.0, birds=6)
    old, new = tmp_path / "old.frames", tmp_path / "new.frames"
    write_version_1(old, names, times, R, p, valid)
    with open(old, "ab") as fh:
        fh.write(b"\x00" * 100)  # a partial record after a kill -9
    write_log(new, names, times, R, p, valid)
    (head_a, a), (head_b, b) = read_frames(old), read_frames(new)
    assert head_a.names == head_b.names and head_a.rate_hz == head_b.rate_hz == RATE
    for got in (a, b):
        assert_bitwise(got, times, R, p, valid)
    with FrameLogReader(old) as a, FrameLogReader(new) as b:
        assert a.version == 1 and b.version == 2
    result = solve_take(make_take(R, p, names, RATE, valid=valid, times=times - times[0])).to_dict()
    downloads = []
    for path in (old, new):
        frames = FrameFile(path)
        try:
            downloads.append((b"".join(npz_stream(frames)), "".join(bvh_chunks(result, frames, chunk_frames=97))))
        finally:
            frames.close()
    assert downloads[0] == downloads[1]


def test_a_crash_or_damage_on_disk_costs_only_the_blocks_it_hits(tmp_path):
    """What was tried: a log cut inside a block (kill -9 mid-write), one block's payload overwritten, one
    block's head overwritten. Every other frame reads exactly; the damaged payload's frames read as frames
    with no valid sensor; the block without a head is skipped; chunked reading gives what reading it whole does."""
    names, times, R, p, valid = tracker_frames("position_matrix", 72, seconds=3.0, birds=6)
    path = tmp_path / "take.frames"
    write_log(path, names, times, R, p, valid)
    data = path.read_bytes()
    body = data.index(b"\n") + 1
    heads = [body]  # block offsets, walked by the documented head: b"FB", codec, 0, frames, payload bytes, CRCs
    first = [0]  # each block's first frame
    while heads[-1] < len(data):
        first.append(first[-1] + int.from_bytes(data[heads[-1] + 4:heads[-1] + 8], "little"))
        size = int.from_bytes(data[heads[-1] + 8:heads[-1] + 12], "little")
        heads.append(heads[-1] + 20 + size)
    # The first batch (3 frames) is written at once, then a block a flush (36 frames).
    assert heads[-1] == len(data) and first[-1] == len(times) and first[1:4] == [3, 36, 72], first

    cut = tmp_path / "cut.frames"
    cut.write_bytes(data[:heads[5] + 30])  # five whole blocks and the start of the sixth
    f5 = first[5]
    assert_bitwise(read_frames(cut)[1], times[:f5], R[:f5], p[:f5], valid[:f5])
    with FrameLogReader(cut) as log:
        assert log.n == f5

    damaged = bytearray(data)
    damaged[heads[2] + 40:heads[2] + 60] = bytes(20)  # block 2's payload (frames 36-71)
    damaged[heads[4] + 3] ^= 0xFF  # block 4's head (frames 108-143)
    (tmp_path / "damaged.frames").write_bytes(bytes(damaged))
    _, got = read_frames(tmp_path / "damaged.frames")
    keep = np.r_[0:first[4], first[5]:len(times)]
    assert len(got) == len(keep)
    lost = np.arange(first[2], first[3])
    assert not got.valid[lost].any() and (got.times[lost] == times[first[2] - 1]).all()
    fine = np.r_[0:first[2], first[3]:first[4]]
    assert_bitwise(got[fine], times[fine], R[fine], p[fine], valid[fine])
    rest = np.arange(first[4], len(keep))
    assert_bitwise(got[rest], times[first[5]:], R[first[5]:], p[first[5]:], valid[first[5]:])
    frames = FrameFile(tmp_path / "damaged.frames")
    chunks = list(frames.chunks(50))
    frames.close()
    assert [len(c) for c in chunks] == [50] * (len(keep) // 50) + ([len(keep) % 50] if len(keep) % 50 else [])
    assert np.concatenate([c.rotations for c in chunks]).tobytes() == got.rotations.tobytes()


def test_a_log_of_a_newer_version_is_refused_in_one_line(tmp_path):
    path = tmp_path / "future.frames"
    path.write_bytes(json.dumps({"format": "flockcal-frames", "version": 3, "names": ["a"]}).encode() + b"\n" + bytes(64))
    with pytest.raises(FrameLogError, match=r"future\.frames: a frame log of version 3.*reads versions 1 and 2"):
        read_frames(path)


def test_a_fit_published_before_the_first_flush_interval_finds_its_frames_in_the_log(tmp_path):
    """What was tried: the service's pipeline with a session whose frame log flushes only every hour, fed a
    second of 6 sensors at 144 Hz, until its first fit is published (fits run at 30 Hz, the log's flush every
    0.25 s: the first fit came first, and a page loading that fit's rig (`/gltf?rest=sensor`, the kiosk's
    first request of a guest session) got 409 "holds no frames yet"). When the pose names the session's fit,
    the log opened as the downloads open it holds frames, and the rig is built from it."""
    import time

    from flockcal.exports.gltf import glb_chunks
    from flockcal.frames import Frames
    from server_helpers import live_pipeline
    from service_process import wait_for

    perf = Performer("human", routine="walk", rate_hz=RATE, birds=6)
    path = tmp_path / "s.frames"
    with live_pipeline(tmp_path, tuple(perf.names), RATE, flush_s=3600.0) as pipe:
        times = np.arange(int(RATE)) / RATE
        R, t, valid = perf.poses(times)
        start = time.monotonic()
        for a in range(0, len(times), 3):
            pipe.feed(Frames(start + times[a:a + 3], R[a:a + 3], t[a:a + 3], valid[a:a + 3]))
        # The pipeline has taken what it was fed (the call), then the pose names the session's fit.
        wait_for(lambda: pipe.call(lambda: None, timeout=60) or (pipe.snapshot.pose_fit_id or ("",))[0] == "s",
                 120, "a fit of the session")
        snap = pipe.snapshot
        assert snap.has_fit and snap.session.id == "s"
        frames = FrameFile(path)  # as the routes open it: n fixed at open
        try:
            assert frames.n > 0, "the session's first fit is published while its frame log reads no frames"
            glb = b"".join(glb_chunks(snap.fit, frames, up="-z",
                                      name="s", rest="sensor", animation=False, chunk_frames=frames.play_frames))
            assert glb[:4] == b"glTF"
        finally:
            frames.close()


def test_the_log_flushes_on_the_clock_it_is_given(tmp_path):
    from flockcal.clock import ManualClock

    names, times, R, p, valid = tracker_frames("position_matrix", 72, seconds=1.5, birds=6)
    clock = ManualClock(monotonic=10.0)
    path = tmp_path / "s.frames"
    log = FrameLog(path, names, RATE, flush_s=0.25, clock=clock)
    log.write(times[:2], R[:2], p[:2], valid[:2])  # the first frames go out at once
    flushed = path.stat().st_size
    # Tried: frames written with no time passing on the log's clock (however long the machine takes): held.
    for a in range(2, 40, 2):
        log.write(times[a:a + 2], R[a:a + 2], p[a:a + 2], valid[a:a + 2])
    log.wait_written()  # what was handed to the log's writer thread is in the file
    assert path.stat().st_size == flushed
    clock.advance(0.25)
    log.write(times[40:42], R[40:42], p[40:42], valid[40:42])  # a quarter second later on its clock: flushed
    log.wait_written()
    assert path.stat().st_size > flushed
    log.close()
    assert_bitwise(read_frames(path)[1], times[:42], R[:42], p[:42], valid[:42])


def test_flushes_handed_to_the_writer_thread_arrive_whole_and_in_order(tmp_path):
    """What was tried: 3 s of 16 birds handed over a quarter second at a time without waiting (as the pipeline
    does), then closed. Every frame comes back bit for bit, the blocks are those a waiting flush writes, and
    the log's writer thread is gone once it is closed."""
    import threading

    names, times, R, p, valid = tracker_frames("position_matrix", 72, seconds=3.0)
    waited, handed = tmp_path / "waited.frames", tmp_path / "handed.frames"
    write_log(waited, names, times, R, p, valid)
    before = set(threading.enumerate())  # other tests' live logs may still have theirs
    log = FrameLog(handed, names, RATE, flush_s=3600.0)
    for a in range(0, len(times), 3):
        log.write(times[a:a + 3], R[a:a + 3], p[a:a + 3], valid[a:a + 3])
        if (a + 3) % 36 == 0:
            log.flush(wait=False)
    assert [t for t in set(threading.enumerate()) - before if t.name == "flockcal-framelog"]
    log.close()
    assert not [t for t in set(threading.enumerate()) - before if t.name == "flockcal-framelog"]
    assert handed.read_bytes() == waited.read_bytes()
    assert_bitwise(read_frames(handed)[1], times, R, p, valid)


def test_a_failure_to_encode_ends_the_log_as_a_full_disk_does_and_nothing_waits_forever(tmp_path):
    names, times, R, p, valid = tracker_frames("position_matrix", 72, seconds=1.0, birds=6)
    path = tmp_path / "s.frames"
    log = FrameLog(path, names, RATE, flush_s=3600.0)
    log.write(times[:10], R[:10], p[:10], valid[:10])  # written at once: a whole block on disk

    def broken(*args):
        raise ValueError("a codec bug")

    # Tried: the writer thread's encoder raising (not a disk's error). flush() returns, the log says why.
    log._encoder.block = broken
    log.write(times[10:20], R[10:20], p[10:20], valid[10:20])
    log.flush()
    assert log.error is not None and "a codec bug" in str(log.error)
    log.write(times[20:30], R[20:30], p[20:30], valid[20:30])  # later frames: not logged, no error raised
    log.close()
    assert_bitwise(read_frames(path)[1], times[:10], R[:10], p[:10], valid[:10])
