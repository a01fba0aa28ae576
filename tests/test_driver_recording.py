""".fobraw recordings: crash survival, truncated tails, corruption, and the pure frame assembly they replay through."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from flockcal.drivers.records import encode_records, quantisation_tolerance, record_length
from flockcal.rotations import from_euler
from flockcal.drivers.assembly import FrameAssembler
from flockcal.drivers.link import FlockSetup, choose_format
from flockcal.drivers.recording import RecordingError, RecordingWriter, intact_length, read_recording


def write_some(path, n=20):
    with RecordingWriter(path, {"config": {"birds": 2}}) as w:
        w.mark(0.0, {"stream": {"birds": 2}})
        for k in range(n):
            w.read(0.01 * k, 0, bytes([0x80 | k, 1, 2, 3]))
    return path


def test_a_killed_recorder_leaves_a_file_readable_up_to_the_last_flush(tmp_path):
    path = tmp_path / "killed.fobraw"
    script = textwrap.dedent(f"""
        import os, signal, time
        from flockcal.drivers.recording import RecordingWriter
        w = RecordingWriter({str(path)!r}, {{"config": {{}}}}, flush_interval=0.0)
        for k in range(50):
            w.read(float(k), 0, bytes([0x80, k]))
        w.flush()
        w._buf += b"CKR" # a chunk half-written when the process dies
        w._fh.write(w._buf); w._fh.flush()
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script])
    assert proc.returncode == -signal.SIGKILL
    rec = read_recording(path)
    assert len([c for c in rec.chunks if c.kind == b"R"]) == 50
    assert rec.truncated and "recovered" in rec.summary()


def test_a_cut_tail_is_dropped_and_the_summary_says_how_much_was_recovered(tmp_path):
    path = write_some(tmp_path / "a.fobraw")
    size = os.path.getsize(path)
    with open(path, "r+b") as fh:
        fh.truncate(size - 7)
    rec = read_recording(path)
    assert len(rec.chunks) == 20  # the marker and 19 of the 20 reads
    assert rec.good_bytes < size - 7 and f"of {size - 7} bytes" in rec.summary()


def test_a_copy_of_a_growing_recording_ends_on_its_last_whole_chunk(tmp_path):
    """intact_length: what GET /raw sends of a live session's recording. At every length the file may
    have when it is read (every byte boundary, a chunk header or payload cut anywhere), the length is
    the end of the last chunk wholly within it, as read_recording finds chunks in the whole file."""
    path = write_some(tmp_path / "c.fobraw", n=12)
    data = path.read_bytes()
    whole = read_recording(path)
    header = len(data) - sum(16 + len(c.payload) + 4 for c in whole.chunks)  # chunk: 16-byte head, CRC
    ends = np.cumsum([header] + [16 + len(c.payload) + 4 for c in whole.chunks])
    for size in range(len(data) + 1):
        want = 0 if size < header else int(ends[ends <= size].max())
        assert intact_length(path, size) == want, size
        if want:
            (tmp_path / "cut.fobraw").write_bytes(data[:want])
            assert not read_recording(tmp_path / "cut.fobraw").truncated


def test_a_corrupt_chunk_is_a_clear_error_unless_salvaged(tmp_path):
    path = write_some(tmp_path / "b.fobraw")
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="corrupt chunk at byte .* --salvage"):
        read_recording(path)
    rec = read_recording(path, salvage=True)
    assert 0 < len(rec.chunks) < 21 and rec.problem.startswith("corrupt chunk")


def test_a_file_that_is_not_a_recording_is_refused(tmp_path):
    # Tried: a text file passed as a recording.
    path = tmp_path / "notes.fobraw"
    path.write_text("hello\n")
    with pytest.raises(RecordingError, match="not a flockcal raw recording"):
        read_recording(path)


def group_setup(m, fmt, rate=100.0, group=True):
    return FlockSetup(urls=["x"] if group else [f"p{i}" for i in range(m)], birds=m,
                      addresses=list(range(1, m + 1)), group=group, mode="stream", record_format=fmt,
                      scale_inches=36.0, rate_hz=rate, hemisphere="forward", baud=115200)


def smooth_poses(n, m, rate=100.0):
    t = np.arange(n)[:, None] / rate
    ang = 0.5 * np.sin(2 * np.pi * 0.7 * t + np.arange(m))
    R = from_euler(ang, 0.5 * ang, -ang)
    z = np.zeros((n, m))
    p = np.stack([0.4 + 0.1 * np.sin(t + np.arange(m)), 0.1 * np.cos(t) + z, 0.05 * np.sin(2 * t) + z], -1)
    return R, p


def test_garbage_inside_records_never_yields_a_corrupt_pose_and_costs_only_those_records():
    n, m, fmt = 300, 8, "position_quaternion"
    R, p = smooth_poses(n, m)
    addr = np.tile(np.arange(1, m + 1), n)
    data = bytearray(encode_records(fmt, R.reshape(-1, 3, 3), p.reshape(-1, 3), addresses=addr))
    L = record_length(fmt, group=True)
    rng = np.random.default_rng(0)
    hits = sorted(rng.choice(np.arange(50, n * m - 50), 12, replace=False))
    for r in hits[::-1]:  # insert inside record r (clean bytes: they cannot start a record)
        at = r * L + int(rng.integers(2, L - 1))
        data[at:at] = rng.integers(0, 0x80, int(rng.integers(1, 6)), dtype=np.uint8).tobytes()
    asm = FrameAssembler(group_setup(m, fmt))
    for k in range(0, len(data), 97):
        asm.feed(0, k * 1e-5, bytes(data[k:k + 97]))
    asm.flush()
    f = asm.take()
    assert len(f) == n
    lost = ~f.valid
    assert lost.sum() <= len(hits)
    _, pos_tol = quantisation_tolerance(fmt)
    err = np.linalg.norm(f.positions - p, axis=-1)[f.valid]
    assert err.max() <= pos_tol


def test_one_port_per_bird_aligns_cycles_when_reads_arrive_late_and_merged():
    # Each port is read with its own random host delay (up to 1.5 periods), so chunks merge records
    # and arrival times of one cycle differ by more than half a period between ports.
    n, m, rate = 200, 6, 100.0
    P = 1 / rate
    fmt = "position"
    setup = group_setup(m, fmt, rate, group=False)
    rng = np.random.default_rng(1)
    chunks = []
    for b in range(m):
        pos = np.zeros((n, 3))
        pos[:, 0] = 0.1 + 0.001 * np.arange(n)  # x encodes the cycle number
        pos[:, 1] = 0.01 * b
        data = encode_records(fmt, np.tile(np.eye(3), (n, 1, 1)), pos)
        L = record_length(fmt, group=False)
        read_at = np.arange(n) * P + rng.uniform(0, 1.5 * P, n)
        read_at = np.maximum.accumulate(read_at)
        # Each record becomes available at its cycle time; a read returns everything available.
        reads = np.unique(np.round(read_at / (P / 2)) * (P / 2))
        avail = np.searchsorted(np.arange(n) * P, reads, side="right")
        prev = 0
        for t, k in zip(reads, avail):
            if k > prev:
                chunks.append((t, b, data[prev * L:k * L]))
                prev = k
    chunks.sort(key=lambda c: (c[0], c[1]))
    asm = FrameAssembler(setup, hemisphere_tracking=False)
    for t, b, d in chunks:
        asm.feed(b, t, d)
    asm.flush()
    f = asm.take()
    cycle = np.round((f.positions[..., 0] - 0.1) / 0.001)
    assert f.valid.mean() > 0.97
    for k in range(len(f)):
        v = f.valid[k]
        assert len(set(cycle[k, v].tolist())) == 1, f"frame {k} mixes cycles {cycle[k, v]}"


def test_auto_format_keeps_position_matrix_when_the_line_carries_it():
    fmt, notes = choose_format("auto", birds_on_port=4, rate_hz=100, baud=115200, group=True)
    assert fmt == "position_matrix" and notes == []


def test_auto_format_falls_back_and_says_so_when_the_line_cannot_carry_the_matrix():
    fmt, notes = choose_format("auto", birds_on_port=8, rate_hz=60, baud=115200, group=True)
    assert fmt == "position_quaternion"
    assert notes[0].startswith("format_fallback") and "position/quaternion" in notes[0]
