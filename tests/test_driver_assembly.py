"""Frame assembly promises: batching never changes the frames, and positions clipped at full scale are
never handed out as poses."""

from __future__ import annotations

import numpy as np
import pytest

from flockcal.drivers.hemispheres import fold_to_hemisphere
from flockcal.drivers.records import FORMATS, decode_block, encode_records, poses_from_words, record_length
from quantisation import position_axis_m
from flockcal.drivers.stream import StreamDecoder
from flockcal.rotations import from_euler
from flockcal.drivers.assembly import FrameAssembler
from flockcal.drivers.link import FlockSetup

INCH = 0.0254


def group_setup(m, fmt, rate=100.0, scale=36.0):
    return FlockSetup(urls=["x"], birds=m, addresses=list(range(1, m + 1)), group=True, mode="stream",
                      record_format=fmt, scale_inches=scale, rate_hz=rate, hemisphere="forward", baud=115200)


def moving_poses(n, m, rate=100.0, reach=0.3):
    t = np.arange(n)[:, None] / rate
    ang = 0.5 * np.sin(2 * np.pi * 0.7 * t + np.arange(m))
    R = from_euler(ang, 0.5 * ang, -ang)
    z = np.zeros((n, m))
    p = np.stack([0.4 + reach * np.sin(t + np.arange(m)), 0.1 * np.cos(t) + z, 0.05 * np.sin(2 * t) + z], -1)
    return R, p


def group_bytes(fmt, R, p, scale=36.0):
    n, m = p.shape[:2]
    addr = np.tile(np.arange(1, m + 1), n)
    return encode_records(fmt, R.reshape(-1, 3, 3), p.reshape(-1, 3), addresses=addr, scale_inches=scale)


def feed_all(asm, data, sizes, take_every=None, bytes_per_s=16000.0):
    out, i, k = [], 0, 0
    while i < len(data):
        s = int(sizes[k % len(sizes)])
        asm.feed(0, i / bytes_per_s, data[i:i + s])
        i, k = i + s, k + 1
        if take_every and k % take_every == 0:
            out.append(asm.take())
    asm.flush()
    out.append(asm.take())
    out = [f for f in out if len(f)]
    return {name: np.concatenate([getattr(f, name) for f in out]) for name in ("times", "rotations", "positions",
                                                                               "valid")}


@pytest.mark.parametrize("fmt", ["position_matrix", "position_quaternion"])
def test_frames_do_not_depend_on_how_reads_are_batched_or_when_frames_are_taken(fmt):
    # Damaged stream (garbage inside records, lost bytes, a hemisphere crossing), read in uneven chunks;
    # frames taken after every read, every 5th, or once at the end must be bit for bit the same.
    n, m = 240, 6
    R, p = moving_poses(n, m, reach=0.6)
    p[:, 2, 0] -= 0.6  # bird 2 crosses x = 0: the bird reports mirrored positions
    data = bytearray(group_bytes(fmt, R, fold_to_hemisphere(p, "forward")))
    L = record_length(fmt, group=True)
    rng = np.random.default_rng(3)
    for r in sorted(rng.choice(np.arange(30, n * m - 30), 10, replace=False))[::-1]:
        at = r * L + int(rng.integers(1, L))
        if r % 2:
            data[at:at] = rng.integers(0, 0x80, 3, dtype=np.uint8).tobytes()
        else:
            del data[at:at + 2]
    data = bytes(data)
    sizes = [3, 97, 1, 512, 40]
    results = [feed_all(FrameAssembler(group_setup(m, fmt)), data, sizes, take_every=k) for k in (1, 5, None)]
    assert len(results[0]["times"]) >= n - 2  # a damaged cycle boundary may merge or lose a cycle
    assert not results[0]["valid"].all()  # the damage did cost records
    for other in results[1:]:
        for name, a in results[0].items():
            assert np.array_equal(a, other[name], equal_nan=True), name


@pytest.mark.parametrize("fmt", ["position_matrix", "position_quaternion"])
def test_the_words_frames_carry_decode_to_their_poses_through_flips_and_damage(fmt):
    # What was tried: a stream with lost bytes and one bird crossing the hemisphere boundary (its positions
    # negated from there on, batch after batch), read in chunks with frames taken after every 5th read. The words the frames carry (words=True, what the service's
    # frame log stores) must decode, through the same decoding every reader uses, to the very floats of
    # every valid pose; asking for them changes no frame.
    n, m = 240, 6
    R, p = moving_poses(n, m, reach=0.6)
    p[:, 2, 0] -= 0.6  # crosses x = 0
    assert p[0, 2, 0] > 0 and (p[:, 2, 0] < 0).any() and p[-1, 2, 0] < 0
    data = bytearray(group_bytes(fmt, R, fold_to_hemisphere(p, "forward"), scale=72.0))
    L = record_length(fmt, group=True)
    for r in (700, 400, 90):
        del data[r * L + 3:r * L + 5]
    data = bytes(data)
    frames = []
    asm = FrameAssembler(group_setup(m, fmt, scale=72.0), words=True)
    for i in range(0, len(data), 97):
        asm.feed(0, i / 16000.0, data[i:i + 97])
        if (i // 97) % 5 == 0:
            frames.append(asm.take())
    asm.flush()
    frames.append(asm.take())
    from flockcal.frames import Frames
    f = Frames.concat([x for x in frames if len(x)], m)
    assert f.words is not None and f.words.words.shape == (len(f), m, FORMATS[fmt].n_words)
    v = f.valid
    assert v.sum() > 0.9 * n * m and not v.all()
    dR, dp = poses_from_words(fmt, f.words.words[v], f.words.scale_inches)
    assert dR.tobytes() == f.rotations[v].tobytes() and dp.tobytes() == f.positions[v].tobytes()
    assert (f.positions[-20:, 2, 0] < 0).all()  # unfolded: behind, as it is
    plain = feed_all(FrameAssembler(group_setup(m, fmt, scale=72.0)), data, [97], take_every=5)
    for name, a in plain.items():
        assert np.array_equal(a, getattr(f, name), equal_nan=True), name


def test_a_position_word_at_full_scale_is_invalid_and_one_step_inside_is_valid():
    rot = np.tile(np.eye(3), (5, 1, 1))
    fs = 36 * INCH
    step = fs * 4 / 32768
    pos = np.array([[fs - 2 * step, 0, 0],  # the last word below the limit: a real reading
                    [fs + 0.2, 0, 0],  # beyond: clipped to +32764
                    [0, -fs - 0.2, 0],  # beyond: clipped to −32768
                    [0, 0, -fs + step],  # word −32764, as far from zero as +32764
                    [0.1, 0.2, 0.3]])
    rec = np.frombuffer(encode_records("position_matrix", rot, pos), np.uint8).reshape(5, -1)
    _, decoded, valid, clipped = decode_block("position_matrix", rec)
    assert list(clipped) == [False, True, True, True, False]
    assert list(valid) == [True, False, False, False, True]
    assert np.allclose(decoded[[0, 4]], pos[[0, 4]], atol=position_axis_m(36.0))
    out = StreamDecoder("position_matrix", group=False).feed(rec.tobytes())
    assert list(out.valid) == list(valid) and list(out.clipped) == list(clipped)


def test_orientation_only_records_are_never_clipped():
    rot = np.tile(np.eye(3), (2, 1, 1))
    rec = np.frombuffer(encode_records("quaternion", rot, np.zeros((2, 3))), np.uint8).reshape(2, -1)
    _, _, valid, clipped = decode_block("quaternion", rec)
    assert valid.all() and not clipped.any()


def test_clipped_positions_are_invalid_counted_and_reported_once_per_burst():
    # Bird 1 reaches beyond 36 in twice (frames 100–149 and, after 2 s back in range, 350–379); the other
    # birds stay inside. Frames are taken every few reads, so a burst spans several batches.
    n, m, rate = 500, 4, 100.0
    R, p = moving_poses(n, m, rate)
    bursts = [(100, 150), (350, 380)]
    for a, b in bursts:
        p[a:b, 1, 0] = 36 * INCH + 0.05
    data = group_bytes("position_quaternion", R, p)
    asm = FrameAssembler(group_setup(m, "position_quaternion", rate))
    f = feed_all(asm, data, [128], take_every=3, bytes_per_s=n * m * 15 / (n / rate))
    expect = np.ones((n, m), bool)
    for a, b in bursts:
        expect[a:b, 1] = False
    assert np.array_equal(f["valid"], expect)
    assert asm.saturated_records == sum(b - a for a, b in bursts)
    assert asm.dropped_records == asm.saturated_records
    events = [e for e in asm.take_events() if e[0] == "position_saturated"]
    assert len(events) == len(bursts)
    kind, message, data = events[0]
    assert data["birds"] == [1] and "72-inch scale" in message and "transmitter" in message


def test_at_the_72_inch_scale_the_same_reach_is_a_valid_pose():
    n, m, rate = 200, 4, 100.0
    R, p = moving_poses(n, m, rate)
    p[50:80, 1, 0] = 36 * INCH + 0.05
    data = group_bytes("position_quaternion", R, p, scale=72.0)
    asm = FrameAssembler(group_setup(m, "position_quaternion", rate, scale=72.0))
    f = feed_all(asm, data, [512])
    assert f["valid"].all() and asm.saturated_records == 0
    assert np.max(np.abs(f["positions"] - p)) <= position_axis_m(72.0)


def test_garbage_framing_as_bird_1_after_lost_bytes_does_not_end_the_cycle():
    # Records of birds 5 and 6 in cycle 2 are destroyed: in their place, garbage around a fake record
    # whose address byte says bird 1. The read ends just after the fake record (on a stray phasing byte),
    # so nothing yet shows which cycle it is in; it must not close cycle 2 and push birds 7 and 8 into a
    # cycle of their own.
    n, m, fmt = 5, 8, "position_quaternion"
    R, p = moving_poses(n, m)
    data = group_bytes(fmt, R, p)
    L = record_length(fmt, group=True)
    fake = bytes([0x85]) + bytes(range(20, 33)) + bytes([1])
    cut = (2 * m + 4) * L
    broken = data[:cut] + bytes([3, 4, 5]) + fake + bytes([0x9A])
    rest = bytes([6, 7, 8]) + data[cut + 2 * L:]
    asm = FrameAssembler(group_setup(m, fmt))
    asm.feed(0, 0.0, broken)
    asm.feed(0, 0.001, rest)
    asm.flush()
    f = asm.take()
    expect = np.ones((n, m), bool)
    expect[2, [4, 5]] = False
    assert len(f) == n and np.array_equal(f.valid, expect)
    assert np.max(np.abs(f.positions[f.valid] - p[f.valid])) <= position_axis_m(36.0)


@pytest.mark.parametrize("mode", ["stream", "point"])
def test_a_cycle_is_out_within_10_ms_of_arrival_in_stream_mode_and_at_once_in_point_mode(mode):
    # Tiny stream reads are framed together (once 512 bytes or 10 ms of arrival time are queued); a POINT
    # answer is framed as soon as it is read.
    m, fmt = 4, "position_quaternion"
    R, p = moving_poses(3, m)
    data = group_bytes(fmt, R, p)
    L = record_length(fmt, group=True)
    setup = group_setup(m, fmt)
    setup.mode = mode
    asm = FrameAssembler(setup)
    asm.feed(0, 0.000, data[:m * L])  # cycle 0, complete (its last bird is the highest address)
    first = len(asm.take())
    asm.feed(0, 0.004, data[m * L:m * L + 5])
    still = len(asm.take())
    asm.feed(0, 0.011, data[m * L + 5:2 * m * L])
    later = len(asm.take())
    if mode == "point":
        assert first + still == 1  # cycle 0 is out before 10 ms have passed
    else:
        assert first + still == 0 and later >= 1
