"""Promises of PtyTracker: a FakeFlock on real pseudo-terminals, talked to through pyserial."""

import numpy as np
import pytest
import serial

from flockcal.drivers.commands import format_command
from flockcal.drivers.hemispheres import fold_to_hemisphere, hemisphere_command
from flockcal.drivers.parameters import change_command, examine_command, measurement_rate_from_count, software_revision
from flockcal.drivers.status import decode_flock_status, decode_status_word
from flockcal.drivers.stream import StreamDecoder
from flockcal.drivers.words import unpack_words
from flockcal.clock import ManualClock
from flockcal.simulator.fake_tracker import FakeFlock
from flockcal.simulator.smooth_source import SmoothSource
from flockcal.simulator.pty_tracker import PtyTracker
from service_process import wait_for


def _read_exactly(port, n, clock=None):
    """Read n bytes, moving the manual clock on in small steps so replies can arrive."""
    data = bytearray()

    def read() -> bool:
        if clock is not None:
            clock.advance(0.005)
        data.extend(port.read(min(port.in_waiting, n - len(data)) or 0))
        return len(data) >= n

    wait_for(read, 5.0, lambda: f"{n} bytes of reply (got {bytes(data)!r})", every=0.002)
    return bytes(data)


def _send(port, flock, data, k=0):
    """Write, and wait until the server has handed every byte to the flock, so that the commands take
    effect at the manual clock's present time."""
    target = flock.stats(k)["bytes_received"] + len(data)
    port.write(data)
    wait_for(lambda: flock.stats(k)["bytes_received"] >= target, 5.0, "the flock takes the command", every=0.002)
    assert flock.stats(k)["bytes_received"] == target


def _pass(trk, clock, seconds, steps=1):
    """Let flock time pass, step by step, each step's bytes handed on to the pty before the next."""
    for _ in range(steps):
        clock.advance(seconds / steps)
        # The flock has made this step's bytes (every thread on the clock caught up), then they are handed on.
        wait_for(clock.idle, 5.0, "the flock catches up with the clock", every=0.001)
        _handed_on(trk)


def _handed_on(trk):
    """Wait until the server thread has moved everything the flock sent by now to the pty."""
    wait_for(lambda: trk.pending() == 0, 5.0, "the pty server hands the flock's bytes on", every=0.002)


@pytest.fixture
def manual_pty():
    clock = ManualClock()
    src = SmoothSource(4, seed=4)
    flock = FakeFlock(src, clock=clock, rate_hz=100.0)
    with PtyTracker(flock=flock) as trk:
        port = serial.Serial(trk.device, 115200, timeout=0)
        yield trk, port, clock, src, flock
        port.close()


def test_vrpn_init_sequence_gets_replies_of_the_expected_lengths(manual_pty):
    trk, port, clock, src, flock = manual_pty
    port.write(b"B")
    assert len(_read_exactly(port, 12, clock)) == 12  # POS/ANG before group mode
    _send(port, flock, change_command(50, 4))
    _pass(trk, clock, 0.6)  # the manual's wait after AUTO-CONFIG
    cmd = change_command(35, 1)
    for a in range(1, 5):
        cmd += format_command("position_quaternion", a)
    for a in range(1, 5):
        cmd += hemisphere_command("lower", a)
    _send(port, flock, cmd)
    port.reset_input_buffer()
    port.write(examine_command(36))
    status = decode_flock_status(_read_exactly(port, 14, clock))
    assert np.all(status.accessible[:4] & status.running[:4])
    port.write(examine_command(2) + examine_command(6))
    reply = _read_exactly(port, 4, clock)
    assert reply[0] == 25 and measurement_rate_from_count(
        int(unpack_words(reply[2:], signed=False)[0])) == pytest.approx(100.0, rel=2e-3)
    port.write(examine_command(0) + examine_command(1))
    reply = _read_exactly(port, 4, clock)
    assert decode_status_word(reply[:2]).format.name == "position_quaternion"
    assert software_revision(reply[2:]) == pytest.approx(3.67)
    _pass(trk, clock, 0.1)
    assert port.in_waiting == 0  # nothing extra: every reply had exactly its length


def test_stream_over_the_pty_counts_rate_times_duration_and_matches_the_source(manual_pty):
    trk, port, clock, src, flock = manual_pty
    _send(port, flock, change_command(50, 4) + change_command(35, 1)
          + b"".join(format_command("position_matrix", a) for a in range(1, 5)))
    t_stream = flock.time()
    _send(port, flock, b"@")
    dec = StreamDecoder("position_matrix", group=True, n_birds=4)
    parts = []
    for _ in range(40):  # 2 s of flock time
        clock.advance(0.05)
        _handed_on(trk)
        parts.append(dec.feed(port.read(port.in_waiting)))
    _send(port, flock, b"?")
    _pass(trk, clock, 0.1)
    # Read until every record the flock sent has come through the pty.
    sent = flock.stats()["records_sent"]

    def all_read() -> bool:
        parts.append(dec.feed(port.read(port.in_waiting)))
        return sum(len(p.addresses) for p in parts) >= sent

    wait_for(all_read, 10.0, "every record the flock sent read", every=0.01)
    addresses = np.concatenate([p.addresses for p in parts])
    sets = len(addresses) / 4
    assert abs(sets - 2.0 * 100.0) <= 1
    assert dec.resyncs == 0 and dec.bad_records == 0
    sel = addresses == 3
    first = int(np.floor(t_stream * 100.0 + 1e-9)) + 1
    times = (first + np.arange(np.count_nonzero(sel))) / 100.0
    rot, pos, _ = src.poses(times)
    got = np.concatenate([p.positions for p in parts])[sel]
    assert np.max(np.abs(got - fold_to_hemisphere(pos[:, 2], "forward"))) <= 1e-4


def test_data_bytes_like_xon_xoff_and_newlines_pass_the_raw_pty(manual_pty):
    trk, port, clock, src, flock = manual_pty
    # XON/XOFF, CR/LF, Ctrl-C, Ctrl-Z, Ctrl-D, DEL: a cooked tty would eat, map or signal on them
    table = bytes([0x11, 0x13, 0x0D, 0x0A, 0x03, 0x1A, 0x04, 0x7F, 0x1C, 0x00, 0x15, 0x12, 0x17, 0x16])
    port.write(change_command(5, table) + examine_command(5))
    assert _read_exactly(port, 14, clock) == table


def test_garbage_injection_is_visible_on_the_wire(manual_pty):
    trk, port, clock, src, flock = manual_pty
    _send(port, flock, change_command(50, 4) + change_command(35, 1) + b"@")
    _pass(trk, clock, 0.2)
    dec = StreamDecoder("position_angles", group=True, n_birds=4)
    dec.feed(port.read(port.in_waiting))
    trk.inject_garbage(30)
    _pass(trk, clock, 0.2)
    # Read until the records after the garbage are decoded (the kernel hands a pty's bytes to its reader a
    # moment after the server wrote them).
    out = []

    def resynced() -> bool:
        out.extend(dec.feed(port.read(port.in_waiting)).addresses)
        return dec.resyncs >= 1 and len(out) > 0

    wait_for(resynced, 5.0, lambda: f"records after the garbage (dropped {dec.dropped_bytes}, {len(out)} records)")
    assert dec.dropped_bytes == 30 and dec.resyncs == 1


def test_disconnect_fails_the_client_and_reconnect_serves_the_same_path(manual_pty):
    trk, port, clock, src, flock = manual_pty
    _send(port, flock, change_command(35, 1))
    trk.disconnect()
    with pytest.raises(serial.SerialException):
        for _ in range(50):  # the hang-up shows on the next read
            port.timeout = 0.02
            port.read(1)
    port.close()
    with pytest.raises(serial.SerialException):  # tried: reopening while unplugged
        serial.Serial(trk.device, 115200)
    trk.reconnect()
    port2 = serial.Serial(trk.device, 115200, timeout=0)
    try:
        port2.write(examine_command(35))
        assert _read_exactly(port2, 1, clock) == b"\x01"  # the bird kept its state
    finally:
        port2.close()


def test_one_pty_per_bird_streams_each_bird_without_address_bytes():
    clock = ManualClock()
    flock = FakeFlock(SmoothSource(3, seed=1), clock=clock, rate_hz=144.0, ports=3)
    with PtyTracker(flock=flock) as trk:
        ports = [serial.Serial(d, 115200, timeout=0) for d in trk.devices]
        try:
            assert len(set(trk.devices)) == 3
            for k, p in enumerate(ports):
                _send(p, flock, (change_command(50, 3) if k == 0 else b"")
                      + format_command("position_quaternion") + b"@", k)
            _pass(trk, clock, 1.0, steps=10)
            for k, p in enumerate(ports):
                # Every record this port's line sent, however late the server thread hands it on (the
                # newest may still be on the wire at the flock's present time).
                sent = flock.stats(k)["records_sent"]
                dec, got = StreamDecoder("position_quaternion", group=False, address=k + 1), [0]

                def read_all(p=p, dec=dec, got=got) -> bool:
                    got[0] += len(dec.feed(p.read(p.in_waiting)))
                    return got[0] >= sent - 1

                wait_for(read_all, 10.0, f"port {k}'s records read", every=0.01)
                assert abs(got[0] - 144) <= 1, (got[0], sent)
        finally:
            for p in ports:
                p.close()


def test_pty_follows_the_baud_the_client_sets_when_asked():
    clock = ManualClock()
    flock = FakeFlock(SmoothSource(4, seed=2), clock=clock, rate_hz=100.0)
    with PtyTracker(flock=flock, baud=None) as trk:
        port = serial.Serial(trk.device, 9600, timeout=0)
        try:
            # The server notices the line speed on its next poll.
            wait_for(lambda: flock.lines[0].baud == 9600, 5.0, "the flock follows 9600 baud", every=0.005)
            _send(port, flock, change_command(50, 4) + change_command(35, 1) + b"@")
            got = 0
            for _ in range(20):
                clock.advance(0.05)
                _handed_on(trk)
                got += len(port.read(port.in_waiting))
            assert got <= 960 * 1.0 + 60  # 9600 baud 8N1 carries 960 B/s
            assert flock.stats()["sets_skipped"] > 0
        finally:
            port.close()
