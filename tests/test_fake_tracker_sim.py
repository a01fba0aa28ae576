"""Promises of the sim:// pyserial URL handler: an in-process fake flock on the wall clock."""

import time
import uuid

import numpy as np
import pytest
import serial

import flockcal.simulator  # noqa: F401  (registers sim://)
from flockcal.drivers.commands import format_command
from flockcal.drivers.parameters import change_command, examine_command
from flockcal.drivers.stream import StreamDecoder
from flockcal.simulator import protocol_sim


def _name():
    return "t" + uuid.uuid4().hex[:8]


@pytest.fixture
def named():
    names = []

    def make():
        names.append(_name())
        return names[-1]

    yield make
    for n in names:
        protocol_sim.forget_simulation(n)


def _read(port, n, timeout=2.0):
    port.timeout = timeout
    return port.read(n)


def test_importing_flockcal_simulator_registers_the_sim_scheme():
    port = serial.serial_for_url("sim://?birds=3&motion=idle", timeout=1.0)
    try:
        assert isinstance(port, protocol_sim.Serial)
        port.write(b"B")
        assert len(port.read(12)) == 12
    finally:
        port.close()


def test_unnamed_simulation_goes_away_with_its_last_port():
    before = set(protocol_sim.SIMULATIONS)
    port = serial.serial_for_url("sim://?birds=2&motion=idle")
    assert len(set(protocol_sim.SIMULATIONS) - before) == 1
    port.close()
    assert set(protocol_sim.SIMULATIONS) == before


def test_named_simulation_exposes_the_live_flock_and_performer(named):
    name = named()
    port = serial.serial_for_url(f"sim://{name}?birds=16&motion=walk&seed=3&rate=144&baud=115200")
    try:
        sim = protocol_sim.get_simulation(name)
        assert sim.flock.n_birds == 16 and sim.flock.rate_hz == 144.0
        assert len(sim.source.names) == 16 and hasattr(sim.source, "inject_slip")
        assert sim.flock.addressing == "expanded"  # 16 units need expanded FBB addressing
        port.write(examine_command(3))
        assert _read(port, 2) == bytes([1, 0])  # the performer needs the 72-inch scale
    finally:
        port.close()
    assert protocol_sim.get_simulation(name) is sim  # a named flock outlives its ports


def test_read_timeout_semantics_match_pyserial():
    port = serial.serial_for_url("sim://?birds=2&motion=idle", timeout=0)
    try:
        assert port.read(10) == b""  # non-blocking
        port.timeout = 0.1
        t0 = time.monotonic()
        assert port.read(10) == b""
        assert time.monotonic() - t0 >= 0.09
        port.write(b"B")
        port.timeout = None  # blocks until all 12 bytes are in
        assert len(port.read(12)) == 12
        assert port.in_waiting == 0
    finally:
        port.close()


def test_modem_line_setters_do_not_raise_and_rts_falling_edge_resets():
    port = serial.serial_for_url("sim://?birds=2&motion=idle", timeout=1.0)
    try:
        port.dtr = True
        port.dtr = False
        port.write(change_command(35, 1) + examine_command(35))
        assert port.read(1) == b"\x01"
        port.rts = True
        port.rts = False  # the hardware reset pulse
        port.write(examine_command(35))
        assert port.read(1) == b"\x00"  # group mode is off again after power-up
        assert port.cts and port.dsr and port.cd and not port.ri
        port.send_break(0.001)
    finally:
        port.close()


def test_stream_rate_on_the_wall_clock_is_roughly_the_measurement_rate():
    port = serial.serial_for_url("sim://?birds=4&motion=idle&rate=144", baudrate=115200, timeout=0.05)
    try:
        port.write(change_command(50, 4) + change_command(35, 1)
                   + b"".join(format_command("position_quaternion", a) for a in range(1, 5)))
        dec = StreamDecoder("position_quaternion", group=True, n_birds=4)
        port.write(b"@")
        t0 = time.monotonic()
        n = 0
        while time.monotonic() - t0 < 0.5:
            n += len(dec.feed(port.read(4096)))
        elapsed = time.monotonic() - t0
        port.write(b"?")
        # generous: a loaded machine may read late, but cannot get more than the rate allows
        assert 0.3 * 144 * elapsed <= n / 4 <= 144 * elapsed + 2
        assert dec.bad_records == 0 and dec.resyncs == 0
    finally:
        port.close()


def test_sim_port_honours_the_clients_baud_rate():
    port = serial.serial_for_url("sim://?birds=4&motion=idle&rate=144", baudrate=9600, timeout=0.05)
    try:
        port.write(change_command(50, 4) + change_command(35, 1) + b"@")
        t0 = time.monotonic()
        got = 0
        while time.monotonic() - t0 < 0.5:
            got += len(port.read(4096))
        assert got <= 960 * (time.monotonic() - t0) + 60  # 9600 baud 8N1: 960 B/s at most
        assert port.simulation.flock.stats()["sets_skipped"] > 0
    finally:
        port.close()


def test_line_faults_injected_through_the_registry_reach_the_client(named):
    name = named()
    port = serial.serial_for_url(f"sim://{name}?birds=2&motion=idle", timeout=0.5)
    try:
        sim = protocol_sim.get_simulation(name)
        sim.inject_garbage(25)
        assert len(port.read(25)) == 25
        sim.set_error(31)
        port.write(examine_command(10))
        assert port.read(1) == bytes([31])
    finally:
        port.close()


def test_disconnect_fails_open_ports_and_reconnect_lets_the_client_reopen(named):
    name = named()
    url = f"sim://{name}?birds=2&motion=idle"
    port = serial.serial_for_url(url, timeout=0.1)
    port.write(change_command(35, 1))
    sim = protocol_sim.get_simulation(name)
    sim.disconnect()
    with pytest.raises(serial.SerialException):
        port.read(1)
    port.close()
    with pytest.raises(serial.SerialException):  # tried: reopening while unplugged
        serial.serial_for_url(url)
    sim.reconnect()
    port = serial.serial_for_url(url, timeout=1.0)
    try:
        port.write(examine_command(35))
        assert port.read(1) == b"\x01"  # same flock, state kept
    finally:
        port.close()


def test_ports_named_alike_share_one_flock_one_bird_each(named):
    name = named()
    ports = [serial.serial_for_url(f"sim://{name}?birds=3&motion=idle&rate=100&port={k}", timeout=0.05)
             for k in range(3)]
    try:
        sim = protocol_sim.get_simulation(name)
        assert sim.flock.n_ports == 3
        ports[0].write(change_command(50, 3))
        for p in ports:
            p.write(format_command("position_matrix") + b"@")
        decs = [StreamDecoder("position_matrix", group=False, address=k + 1) for k in range(3)]
        counts = np.zeros(3)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.4:
            for k, p in enumerate(ports):
                counts[k] += len(decs[k].feed(p.read(4096)))
        assert np.all(counts > 5) and all(d.bad_records == 0 for d in decs)
    finally:
        for p in ports:
            p.close()


def test_bad_url_options_are_refused_with_the_usage():
    with pytest.raises(serial.SerialException, match="sim://"):  # tried: a misspelt option
        serial.serial_for_url("sim://?brids=3")
    with pytest.raises(serial.SerialException):  # tried: a port beyond one-per-bird
        serial.serial_for_url(f"sim://{_name()}?birds=2&motion=idle&port=5")
