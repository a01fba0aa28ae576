"""Promises of the wire-format modules (words, records, stream, commands, parameters, status): bytes ⇄ arrays."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flockcal.drivers.commands import fbb_prefix
from flockcal.drivers.hemispheres import HEMISPHERE_BY_BYTES, fold_to_hemisphere, hemisphere_command
from flockcal.drivers.parameters import (
    change_command, change_data_length, examine_reply_length, measurement_count_from_rate,
    measurement_rate_from_count, measurement_rate_from_word, measurement_rate_word, software_revision,
)
from flockcal.drivers.records import (
    FORMATS, decode_records, encode_records, record_length, saturated_records,
)
from flockcal.drivers.status import (
    ERROR_CODES, decode_flock_status, decode_status_word, encode_status_word, error_is_fatal, error_message,
    flock_status_byte,
)
from flockcal.drivers.stream import StreamDecoder
from flockcal.drivers.words import decode_words, encode_words, pack_words
from flockcal.rotations import from_euler
from quantisation import position_axis_m, rotation_rad, tolerance

RNG = np.random.default_rng(7)


def _poses(n, seed=0, reach=0.85):
    rot = Rotation.random(n, random_state=seed).as_matrix()
    pos = np.random.default_rng(seed).uniform(-reach, reach, (n, 3))
    return rot, pos


def _angle_between(a, b):
    rel = np.einsum("nji,njk->nik", a, b)
    return np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))


def test_manual_word_example_encodes_and_decodes_as_printed():
    data = encode_words([0x1122, 0x3344, 0x5566])
    assert bytes(data) == bytes.fromhex("C8 08 51 19 59 2A")
    assert list(decode_words(data)) == [0x1120, 0x3344, 0x5564]


def test_negative_words_decode_signed():
    words = np.array([-32768, -4, 0, 4, 32764])
    assert list(decode_words(encode_words(words))) == list(words)


@pytest.mark.parametrize("name", sorted(FORMATS))
@pytest.mark.parametrize("group", [False, True])
def test_every_format_round_trips_within_quantisation(name, group):
    fmt = FORMATS[name]
    rot, pos = _poses(2000, seed=len(name))
    addresses = np.arange(2000) % 14 + 1 if group else None
    data = encode_records(fmt, rot, pos, addresses=addresses)
    length = record_length(fmt, group=group)
    assert len(data) == 2000 * length
    records = np.frombuffer(data, np.uint8).reshape(2000, length)
    # phasing bit only on each record's first byte
    assert np.all(records[:, 0] & 0x80) and not np.any(records[:, 1:] & 0x80)
    r, p, a = decode_records(fmt, records, group=group)
    tol_rot, tol_pos = tolerance(name)[0], position_axis_m(36.0)  # tests/quantisation.py
    if fmt.position:
        assert np.max(np.abs(p - pos)) <= tol_pos
    else:
        assert np.all(np.isnan(p))
    if fmt.orientation:
        assert np.max(_angle_between(r, rot)) <= tol_rot
        assert np.allclose(np.einsum("nji,njk->nik", r, r), np.eye(3), atol=1e-12)
    else:
        assert np.all(np.isnan(r))
    if group:
        assert np.array_equal(a, addresses)
    else:
        assert a is None


def test_72_and_144_inch_scales_round_trip():
    rot, pos = _poses(100, reach=1.8)  # inside 72 in (1.83 m)
    for scale in (72.0, 144.0):
        data = encode_records("position_matrix", rot, pos, scale_inches=scale)
        _, p, _ = decode_records("position_matrix", data, group=False, scale_inches=scale)
        assert np.max(np.abs(p - pos)) <= position_axis_m(scale)


def test_positions_beyond_full_scale_saturate():
    rot, _ = _poses(2)
    pos = np.array([[2.0, -2.0, 0.1], [0.0, 0.0, -5.0]])  # 36 in = 0.914 m full scale
    _, p, _ = decode_records("position_angles", encode_records("position_angles", rot, pos),
                                   group=False)
    fs = 36 * 0.0254
    assert np.all(np.abs(p) <= fs) and np.allclose(np.abs(p[0, :2]), fs, atol=2e-4)
    assert np.sign(p[1, 2]) == -1


def test_matrix_words_are_m_column_by_column():
    # Pure azimuth A: M11 = cos A, M12 = sin A; column order puts M21 second, M12 fourth.
    a = np.deg2rad(30)
    rot = from_euler(np.array([a]), np.array([0.0]), np.array([0.0]))
    words = decode_words(np.frombuffer(encode_records("matrix", rot, np.zeros((1, 3))),
                                             np.uint8))
    m = rot[0].T
    expect = m.T.reshape(9)  # M11 M21 M31 M12 ...
    assert np.allclose(words / 32768, expect, atol=2e-4)
    assert words[3] / 32768 == pytest.approx(np.sin(a), abs=2e-4)


def test_fob_quaternion_of_pure_azimuth_has_negative_z():
    a = np.deg2rad(40)
    rot = from_euler(np.array([a]), np.array([0.0]), np.array([0.0]))
    words = decode_words(np.frombuffer(encode_records("quaternion", rot, np.zeros((1, 3))),
                                             np.uint8)) / 32768
    assert np.allclose(words, [np.cos(a / 2), 0, 0, -np.sin(a / 2)], atol=2e-4)
    conj = decode_words(np.frombuffer(encode_records(
        "quaternion", rot, np.zeros((1, 3)), quaternion_convention="conjugate"), np.uint8)) / 32768
    assert np.allclose(conj, [np.cos(a / 2), 0, 0, np.sin(a / 2)], atol=2e-4)


def test_quaternion_convention_mismatch_gives_the_inverse_rotation():
    rot, pos = _poses(50)
    data = encode_records("quaternion", rot, pos, quaternion_convention="conjugate")
    r, _, _ = decode_records("quaternion", data, group=False)
    assert np.allclose(r, np.transpose(rot, (0, 2, 1)), atol=1e-3)


def test_angles_near_gimbal_lock_decode_to_the_right_rotation():
    n = 200
    e = np.pi / 2 * np.where(np.arange(n) % 2, 1, -1) * (1 - RNG.uniform(0, 1e-9, n))
    rot = from_euler(RNG.uniform(-np.pi, np.pi, n), e, RNG.uniform(-np.pi, np.pi, n))
    r, _, _ = decode_records("angles", encode_records("angles", rot, np.zeros((n, 3))),
                                   group=False)
    assert np.max(_angle_between(r, rot)) <= rotation_rad("angles")


def test_all_zero_record_is_flagged_saturated_not_garbage():
    for name, fmt in FORMATS.items():
        rec = np.zeros((1, record_length(fmt, group=True)), np.uint8)
        rec[0, 0] = 0x80
        rec[0, -1] = 3
        r, p, a = decode_records(fmt, rec, group=True)
        assert saturated_records(fmt, rec)[0], name
        assert np.all(np.isfinite(r)) or not fmt.orientation
        assert a[0] == 3


def _stream(fmt="position_quaternion", n=300, group=True, birds=4, seed=1):
    rot, pos = _poses(n, seed=seed)
    addr = np.arange(n) % birds + 1 if group else None
    return encode_records(fmt, rot, pos, addresses=addr), rot, pos, addr


def test_stream_decoder_handles_arbitrary_chunking():
    data, rot, pos, addr = _stream()
    dec = StreamDecoder("position_quaternion", group=True, n_birds=4)
    cuts = np.sort(RNG.choice(len(data), 60, replace=False))
    parts = [dec.feed(c, arrival_time=i) for i, c in enumerate(np.split(np.frombuffer(data, np.uint8), cuts))]
    addresses = np.concatenate([p.addresses for p in parts])
    positions = np.concatenate([p.positions for p in parts])
    assert np.array_equal(addresses, addr)
    assert np.max(np.abs(positions - pos)) < 1e-4
    assert dec.dropped_bytes == 0 and dec.resyncs == 0 and dec.bad_records == 0
    offsets = np.concatenate([p.offsets for p in parts])
    assert np.array_equal(offsets, np.arange(300) * 15)


def test_garbage_between_records_costs_no_record():
    data, rot, pos, addr = _stream(n=20)
    buf = bytearray(data)
    garbage = bytes([0x11, 0x13, 0x00, 0x7F, 0x05])  # bit7 clear: cannot start a record
    buf[15 * 7:15 * 7] = garbage
    dec = StreamDecoder("position_quaternion", group=True, n_birds=4)
    out = dec.feed(bytes(buf))
    assert len(out) == 20
    assert dec.dropped_bytes == len(garbage) and dec.resyncs == 1


def test_dropped_byte_loses_only_the_broken_record():
    data, rot, pos, addr = _stream(n=20)
    buf = bytearray(data)
    del buf[15 * 5 + 6]  # a byte inside record 5
    del buf[15 * 12 - 1]  # the phasing byte of record 12 (shifted by the first deletion)
    dec = StreamDecoder("position_quaternion", group=True, n_birds=4)
    out = dec.feed(bytes(buf))
    expect = [i for i in range(20) if i not in (5, 12)]
    assert np.array_equal(out.addresses, addr[expect])
    assert np.max(np.abs(out.positions - pos[expect])) < 1e-4
    assert dec.resyncs == 2


def test_inserted_phasing_byte_rejects_the_record_it_lands_in():
    data, rot, pos, addr = _stream(n=10)
    buf = bytearray(data)
    buf.insert(15 * 3 + 4, 0xC5)  # a stray byte with bit7 set inside record 3
    dec = StreamDecoder("position_quaternion", group=True, n_birds=4)
    out = dec.feed(bytes(buf))
    assert np.array_equal(out.addresses, addr[[0, 1, 2, 4, 5, 6, 7, 8, 9]])
    assert dec.bad_records == 2  # the cut record and the stray start


def test_unknown_address_byte_is_rejected_in_group_mode():
    data, rot, pos, addr = _stream(n=8, birds=4)
    dec = StreamDecoder("position_quaternion", group=True, n_birds=3)  # bird 4 not configured
    out = dec.feed(data)
    assert set(out.addresses) == {1, 2, 3} and len(out) == 6


def test_per_address_formats_in_one_group_stream():
    rot, pos = _poses(6)
    fmts = {1: "position_matrix", 2: "position_quaternion", 3: "position_angles"}
    data = b"".join(encode_records(fmts[a], rot[i:i + 1], pos[i:i + 1], addresses=[a])
                    for i, a in enumerate([1, 2, 3, 1, 2, 3]))
    dec = StreamDecoder(fmts, group=True)
    out = dec.feed(data[:40])
    out2 = dec.feed(data[40:])
    assert dec.pending_bytes == 13  # the last record could be the start of a longer one
    out3 = dec.flush()
    addresses = np.concatenate([out.addresses, out2.addresses, out3.addresses])
    assert list(addresses) == [1, 2, 3, 1, 2, 3]
    positions = np.concatenate([out.positions, out2.positions, out3.positions])
    assert np.max(np.abs(positions - pos)) < 1e-4


def test_inner_byte_equal_to_a_shorter_formats_address_does_not_split_a_record():
    # bird 2's 19-byte matrix record whose 7th byte happens to be 1, bird 1's address (7-byte records)
    rot, pos = _poses(200, seed=3)
    fmts = {1: "angles", 2: "matrix"}
    recs = [np.frombuffer(encode_records(fmts[a], rot[i:i + 1], pos[i:i + 1], addresses=[a]), np.uint8)
            for i, a in enumerate(np.arange(200) % 2 + 1)]
    recs = [r.copy() for r in recs]
    for r in recs[1::2]:
        r[6] = 1
    dec = StreamDecoder(fmts, group=True)
    out = dec.feed(np.concatenate(recs).tobytes())
    out3 = dec.flush()
    assert len(out) + len(out3) == 200 and dec.bad_records == 0


def test_non_group_stream_uses_the_port_address():
    data, rot, pos, _ = _stream("position_angles", n=30, group=False)
    dec = StreamDecoder("position_angles", group=False, address=7)
    out = dec.feed(data)
    assert len(out) == 30 and set(out.addresses) == {7}


def test_vectorised_decode_of_100k_records():
    n = 100_000
    data, rot, pos, addr = _stream(n=n, birds=16)
    dec = StreamDecoder("position_quaternion", group=True, n_birds=16)
    out = dec.feed(data, arrival_time=1.5)
    assert len(out) == n and np.array_equal(out.addresses, addr)
    assert np.max(np.abs(out.positions - pos)) < 1e-4
    assert np.all(out.times == 1.5) and np.all(out.valid)


def test_examine_reply_lengths_follow_addressing_mode():
    assert examine_reply_length(36) == 14
    assert examine_reply_length(36, "expanded") == 30
    assert examine_reply_length(36, "super_expanded") == 126
    assert [examine_reply_length(50, m) for m in ("normal", "expanded", "super_expanded")] == [5, 7, 19]
    assert examine_reply_length(15) == 10 and change_data_length(50) == 1


def test_change_command_bytes():
    assert change_command(50, 3) == bytes([0x50, 0x32, 0x03])
    assert change_command(7, measurement_rate_word(103)) == bytes([0x50, 0x07, 0x00, 0x67])
    with pytest.raises(ValueError):  # tried: changing read-only parameter 0
        change_command(0, 1)
    with pytest.raises(ValueError):  # tried: two data bytes for one-byte group mode
        change_command(35, b"\x01\x00")


def test_fbb_prefixes_per_addressing_mode():
    assert fbb_prefix(1) == b"\xf1" and fbb_prefix(14) == b"\xfe"
    assert fbb_prefix(15, "expanded") == b"\xff"
    assert fbb_prefix(16, "expanded") == b"\xe0" and fbb_prefix(30, "expanded") == b"\xee"
    assert fbb_prefix(100, "super_expanded") == b"\xa0\x64"
    assert fbb_prefix(0) == b""
    with pytest.raises(ValueError):  # tried: address 20 in normal addressing
        fbb_prefix(20)


def test_error_codes_name_meaning_and_fatality():
    assert "invalid RS232 command" in ERROR_CODES[6]
    assert error_is_fatal(1) and error_is_fatal(22) and not error_is_fatal(6)
    assert "fatal" in error_message(16, address=3) and "bird 3" in error_message(16, 3)


def test_status_word_round_trip_and_format_code():
    w = encode_status_word(master=True, initialised=True, running=True,
                                 format="position_quaternion", stream=True)
    s = decode_status_word(pack_words([w]))
    assert s.master and s.running and s.stream and not s.sleeping
    assert s.format.name == "position_quaternion" and s.format.status_code + 0x55 == 0x5D


def test_flock_status_byte_decoding():
    raw = bytes([flock_status_byte(ert=True, sensor=False, transmitters=1)]
                + [flock_status_byte()] * 3 + [0] * 10)
    fs = decode_flock_status(raw)
    assert fs.ert[0] and not fs.sensor[0] and list(fs.running_sensors()) == [2, 3, 4]


def test_hemisphere_bytes_and_folding():
    assert hemisphere_command("lower", address=2) == bytes([0xF2, 0x4C, 0x0C, 0x00])
    assert HEMISPHERE_BY_BYTES[(0x06, 0x01)] == "left"
    p = np.array([[0.1, 0.2, -0.3], [0.1, 0.2, 0.3]])
    folded = fold_to_hemisphere(p, "lower")
    assert np.allclose(folded, [[-0.1, -0.2, 0.3], [0.1, 0.2, 0.3]])


def test_measurement_rate_helpers():
    assert measurement_rate_from_word(measurement_rate_word(144.0)) == 144.0
    count = measurement_count_from_rate(103.0)
    assert measurement_rate_from_count(count) == pytest.approx(103.0, rel=1e-3)
    assert software_revision(bytes([3, 67])) == pytest.approx(3.67)


def _framing_without_fast_path(dec):
    dec._single = 0  # every chunk through the general framing
    return dec


@pytest.mark.parametrize("group", [True, False])
def test_whole_record_fast_path_frames_exactly_like_the_general_framing(group):
    # Clean chunks take the fast path, damaged ones the general one; both must agree record for record.
    data, rot, pos, addr = _stream("position_matrix", n=400, group=group, birds=4)
    buf = bytearray(data)
    L = record_length("position_matrix", group=group)
    buf[L * 100 + 3:L * 100 + 3] = bytes([0x05, 0x91])  # garbage inside record 100
    del buf[L * 250 + 7]  # a byte lost inside record 250
    kw = dict(group=True, n_birds=4) if group else dict(group=False, address=3)
    fast = StreamDecoder("position_matrix", **kw)
    slow = _framing_without_fast_path(StreamDecoder("position_matrix", **kw))
    cuts = np.sort(RNG.choice(len(buf), 80, replace=False))
    chunks = [c.tobytes() for c in np.split(np.frombuffer(bytes(buf), np.uint8), cuts)]
    # whole-record chunks too, so that the fast path runs on aligned reads
    chunks += [bytes(data[i:i + 4 * L]) for i in range(0, 40 * L, 4 * L)]
    outs = [[d.feed(c, arrival_time=0.01 * i) for i, c in enumerate(chunks)] for d in (fast, slow)]
    for name in ("addresses", "offsets", "times", "rotations", "positions", "valid"):
        a, b = (np.concatenate([getattr(o, name) for o in out]) for out in outs)
        assert np.array_equal(a, b, equal_nan=True), name
    assert (fast.resyncs, fast.dropped_bytes, fast.bad_records, fast.records, fast.pending_bytes) == \
           (slow.resyncs, slow.dropped_bytes, slow.bad_records, slow.records, slow.pending_bytes)
    assert fast.resyncs >= 2


def test_framing_several_reads_at_once_gives_the_records_and_arrival_times_of_framing_them_one_by_one():
    data, rot, pos, addr = _stream("position_angles", n=200, birds=4)
    cuts = np.sort(RNG.choice(len(data), 50, replace=False))
    chunks = [c.tobytes() for c in np.split(np.frombuffer(data, np.uint8), cuts)]
    times = list(0.002 * np.arange(len(chunks)))
    one = StreamDecoder("position_angles", group=True, n_birds=4)
    singles = [one.frame(c, t) for c, t in zip(chunks, times)]
    many = StreamDecoder("position_angles", group=True, n_birds=4)
    batches = [many.frame_chunks(chunks[i:i + 7], times[i:i + 7]) for i in range(0, len(chunks), 7)]
    for name in ("addresses", "offsets", "times"):
        a, b = (np.concatenate([getattr(f, name) for f in fs]) for fs in (singles, batches))
        assert np.array_equal(a, b), name
    assert len(np.concatenate([f.offsets for f in batches])) == 200
