"""Promises of the FakeFlock protocol state machine, driven by a manual clock (no I/O, no sleeps)."""

import numpy as np
import pytest

from flockcal.drivers.commands import fbb_prefix, format_command
from flockcal.drivers.hemispheres import fold_to_hemisphere, hemisphere_command
from flockcal.drivers.parameters import PARAMETERS, change_command, examine_command, measurement_rate_word
from flockcal.drivers.records import FORMATS, decode_records
from quantisation import position_axis_m, rotation_rad, tolerance
from flockcal.drivers.status import decode_flock_status, decode_status_word
from flockcal.drivers.stream import StreamDecoder
from flockcal.clock import ManualClock
from flockcal.simulator.fake_tracker import FakeFlock, FakeTrackerError
from flockcal.simulator.smooth_source import SmoothSource


def _angle_between(a, b):
    rel = np.einsum("...ji,...jk->...ik", a, b)
    return np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1))


def _flock(n=4, **kw):
    clock = ManualClock()
    src = SmoothSource(n, seed=n)
    return FakeFlock(src, clock=clock, **kw), clock, src


def _ask(flock, clock, data, port=0, dt=0.05):
    flock.write(data, port)
    clock.advance(dt)
    return flock.read(port)


def _configure(flock, clock, formats, group=True):
    units = flock.units
    cmd = change_command(50, units)
    if group:
        cmd += change_command(35, 1)
    for a, f in formats.items():
        cmd += format_command(f, a, flock.addressing)
    assert _ask(flock, clock, cmd) == b""


def test_point_before_configuration_answers_the_masters_pos_angles_record():
    flock, clock, src = _flock()
    reply = _ask(flock, clock, b"B")
    assert len(reply) == 12  # POS/ANG power-up default, no group byte
    r, p, _ = decode_records("position_angles", reply, group=False)
    rot, pos, _ = src.poses(np.array([0.0]))
    assert np.max(np.abs(p[0] - pos[0, 0])) <= position_axis_m(36.0)
    assert _angle_between(r[0], rot[0, 0]) <= rotation_rad("angles")


@pytest.mark.parametrize("birds,addressing", [(4, "normal"), (16, "expanded")])
def test_examine_replies_have_the_tables_lengths(birds, addressing):
    flock, clock, _ = _flock(birds)
    assert flock.addressing == addressing
    for p, param in PARAMETERS.items():
        reply = _ask(flock, clock, examine_command(p))
        assert len(reply) == param.reply_length(addressing), param.name


def test_vrpn_flock_status_query_gets_14_bytes_with_every_unit_running():
    flock, clock, _ = _flock(4, ert=True)
    _configure(flock, clock, {a: "position_quaternion" for a in range(2, 6)})
    status = decode_flock_status(_ask(flock, clock, examine_command(36)))
    assert len(status.accessible) == 14
    assert np.all(status.accessible[:5] & status.running[:5])
    assert status.ert[0] and not status.sensor[0] and list(status.running_sensors()) == [2, 3, 4, 5]
    assert flock.scale_inches == 144.0


def test_unknown_command_sets_error_6_which_clears_when_read():
    flock, clock, _ = _flock()
    _ask(flock, clock, b"\x01")  # tried: 0x01 is no FOB command
    assert _ask(flock, clock, examine_command(10)) == bytes([6])
    assert _ask(flock, clock, examine_command(10)) == bytes([0])


def test_expanded_error_code_names_the_missing_unit_after_autoconfig_of_too_many():
    flock, clock, _ = _flock(3)
    _ask(flock, clock, change_command(50, 5))  # tried: 5 units on a flock of 3
    assert _ask(flock, clock, examine_command(16)) == bytes([13, 4])


def test_fbb_prefix_applies_to_the_next_command_only():
    flock, clock, _ = _flock()
    _ask(flock, clock, change_command(50, 4) + bytes([0xF2, FORMATS["position_quaternion"].command,
                                                          FORMATS["position_matrix"].command]))
    status2 = decode_status_word(_ask(flock, clock, fbb_prefix(2) + examine_command(0)))
    status1 = decode_status_word(_ask(flock, clock, examine_command(0)))
    assert status2.format.name == "position_quaternion" and not status2.master
    assert status1.format.name == "position_matrix" and status1.master


def test_command_data_bytes_that_look_like_commands_are_not_executed():
    flock, clock, _ = _flock()
    # hemisphere LOWER is 4C 0C 00; a rate word 0x40xx carries '@' (STREAM) as data
    _ask(flock, clock, hemisphere_command("lower") + change_command(7, 0x4040))
    assert not flock.streaming()
    assert _ask(flock, clock, examine_command(7)) == bytes([0x40, 0x40])


def _stream(flock, clock, seconds, decoder, port=0, step=0.1):
    flock.write(b"@", port)
    parts = []
    for _ in range(int(round(seconds / step))):
        clock.advance(step)
        parts.append(decoder.feed(flock.read(port)))
    return parts


def _concat(parts, attr):
    return np.concatenate([getattr(p, attr) for p in parts])


@pytest.mark.parametrize("group", [True, False])
def test_every_format_decodes_to_the_source_poses_within_quantisation(group):
    names = sorted(FORMATS)
    flock, clock, src = _flock(len(names), rate_hz=100.0)
    formats = {a: names[a - 1] for a in range(1, len(names) + 1)}
    _configure(flock, clock, formats, group=group)
    for address, name in formats.items():
        if group:
            dec = StreamDecoder(formats, group=True)
            prefix = b""
        else:
            dec = StreamDecoder(name, group=False, address=address)
            prefix = fbb_prefix(address)
        flock.write(prefix)
        # records come from the measurement cycles after STREAM, one per cycle (the set fits the line)
        first = int(np.floor((flock.time() - flock.cycle_origin) * flock.rate_hz + 1e-9)) + 1
        parts = _stream(flock, clock, 1.0, dec)
        _ask(flock, clock, b"?")
        sel = _concat(parts, "addresses") == address
        k = np.count_nonzero(sel)
        assert k >= 95
        times = flock.cycle_origin + (first + np.arange(k)) / flock.rate_hz
        rot, pos, _ = src.poses(times)
        pos = fold_to_hemisphere(pos, "forward")  # what the bird reports in its hemisphere
        fmt = FORMATS[name]
        tol_r, tol_p = tolerance(name)[0], position_axis_m(36.0)  # tests/quantisation.py
        if fmt.position:
            assert np.max(np.abs(_concat(parts, "positions")[sel] - pos[:, address - 1])) <= tol_p
        if fmt.orientation:
            got_r = _concat(parts, "rotations")[sel]
            assert np.max(_angle_between(got_r, rot[:, address - 1])) <= tol_r + 1e-9
        if not group:
            break  # one bird at a time is enough off group mode


@pytest.mark.parametrize("rate", [103.0, 144.0])
def test_frame_count_matches_rate_times_duration(rate):
    flock, clock, _ = _flock(4, rate_hz=rate)
    _configure(flock, clock, {a: "position_quaternion" for a in range(1, 5)})
    dec = StreamDecoder("position_quaternion", group=True, n_birds=4)
    parts = _stream(flock, clock, 3.0, dec)
    sets = len(_concat(parts, "addresses")) / 4
    assert abs(sets - rate * 3.0) <= 1.5


def test_change_of_measurement_rate_and_report_rate_divisor_slow_the_stream():
    flock, clock, _ = _flock(2, rate_hz=103.0)
    _configure(flock, clock, {1: "position_matrix", 2: "position_matrix"})
    _ask(flock, clock, change_command(7, measurement_rate_word(120.0)) + b"R")  # every 2nd cycle
    dec = StreamDecoder("position_matrix", group=True, n_birds=2)
    sets = len(_concat(_stream(flock, clock, 2.0, dec), "addresses")) / 2
    assert abs(sets - 120.0) <= 1.5


def test_sixteen_birds_at_144_hz_do_not_fit_one_115200_line():
    flock, clock, _ = _flock(16, rate_hz=144.0, baud=115200)
    _configure(flock, clock, {a: "position_quaternion" for a in range(1, 17)})
    dec = StreamDecoder("position_quaternion", group=True, n_birds=16)
    parts = _stream(flock, clock, 2.0, dec)
    records = len(_concat(parts, "addresses"))
    line_limit = 115200 / 10 / 15 * 2.0  # records the line can carry in 2 s
    assert records <= line_limit
    assert records < 16 * 144 * 2.0 / 2  # well below the measurement rate
    assert flock.stats()["sets_skipped"] > 0
    assert dec.bad_records == 0 and dec.resyncs == 0  # skipped whole sets, never broken records


def test_one_port_per_bird_carries_all_birds_at_full_rate():
    flock, clock, src = _flock(16, rate_hz=144.0, baud=115200, ports=16)
    assert flock.n_ports == 16
    decs = [StreamDecoder("position_quaternion", group=False, address=k + 1) for k in range(16)]
    for k in range(16):
        _ask(flock, clock, change_command(50, 16) if k == 0 else b"", port=k, dt=0)
        flock.write(format_command("position_quaternion"), k)
        flock.write(b"@", k)
    counts = np.zeros(16)
    for _ in range(10):
        clock.advance(0.1)
        for k in range(16):
            out = decs[k].feed(flock.read(k))
            counts[k] += len(out)
            assert np.all(out.addresses == k + 1)
    assert np.all(np.abs(counts - 144.0) <= 1.5)


def test_stream_stop_leaves_at_most_one_set_in_flight():
    flock, clock, _ = _flock(4)
    _configure(flock, clock, {a: "position_quaternion" for a in range(1, 5)})
    flock.write(b"@")
    clock.advance(0.5)
    flock.read()
    flock.write(b"?")
    clock.advance(0.5)
    assert len(flock.read()) <= 4 * 15


def test_sleep_freezes_the_data_and_run_resumes():
    flock, clock, _ = _flock(1)
    _ask(flock, clock, change_command(50, 1) + b"G")
    a = _ask(flock, clock, b"B", dt=0.3)
    b = _ask(flock, clock, b"B", dt=0.3)
    assert a == b
    assert decode_status_word(_ask(flock, clock, examine_command(0))).sleeping
    _ask(flock, clock, b"F")
    assert _ask(flock, clock, b"B", dt=0.3) != b


def test_invalid_sensor_sends_the_all_zero_record():
    flock, clock, src = _flock(2)
    src.invalidate(1)
    _configure(flock, clock, {1: "position_matrix", 2: "position_matrix"})
    out = StreamDecoder("position_matrix", group=True, n_birds=2).feed(_ask(flock, clock, b"B"))
    assert list(out.valid) == [True, False] and list(out.addresses) == [1, 2]


def test_positions_beyond_full_scale_saturate():
    class Far(SmoothSource):
        def poses(self, times):
            r, p, v = super().poses(times)
            return r, p * 0 + [1.5, -2.0, 0.3], v

    clock = ManualClock()
    flock = FakeFlock(Far(1), clock=clock)
    _, p, _ = decode_records("position_angles", _ask(flock, clock, b"B"), group=False)
    fs = 36 * 0.0254
    assert np.allclose(p[0], [fs, -fs, 0.3], atol=2e-4)
    _ask(flock, clock, change_command(3, bytes([1, 0])))  # 72-inch scale
    _, p, _ = decode_records("position_angles", _ask(flock, clock, b"B"), group=False,
                                   scale_inches=72.0)
    assert np.allclose(p[0], [1.5, -72 * 0.0254, 0.3], atol=3e-4)


def test_hemisphere_mirrors_positions_on_the_wrong_side():
    flock, clock, src = _flock(1)
    _ask(flock, clock, hemisphere_command("aft"))  # sensors are at +X: all mirrored
    reply = _ask(flock, clock, b"B")
    _, p, _ = decode_records("position_angles", reply, group=False)
    asked = flock.time() - 0.05  # POINT answers with the latest completed measurement cycle
    cycle = flock.cycle_origin + np.floor((asked - flock.cycle_origin) * flock.rate_hz + 1e-9) / flock.rate_hz
    _, pos, _ = src.poses(np.array([cycle]))
    assert np.allclose(p[0], -pos[0, 0], atol=2e-4)


def test_status_word_reports_stream_format_and_master():
    flock, clock, _ = _flock(2)
    _configure(flock, clock, {1: "position_quaternion", 2: "angles"})
    flock.write(b"@")
    clock.advance(0.1)
    flock.write(b"?")
    st = decode_status_word(_ask(flock, clock, examine_command(0), dt=0.2)[-2:])
    assert st.master and st.initialised and not st.stream and st.format.name == "position_quaternion"


def test_injected_garbage_and_dropped_bytes_show_on_the_wire():
    flock, clock, _ = _flock(4)
    _configure(flock, clock, {a: "position_quaternion" for a in range(1, 5)})
    dec = StreamDecoder("position_quaternion", group=True, n_birds=4)
    _stream(flock, clock, 0.3, dec)
    flock.inject_garbage(20)
    clock.advance(0.1)
    dec.feed(flock.read())
    assert dec.dropped_bytes == 20 and dec.resyncs == 1 and dec.bad_records == 0
    flock.drop_bytes(3)
    clock.advance(0.1)
    dec.feed(flock.read())
    assert dec.bad_records == 1  # exactly the broken record is lost


def test_stall_leaves_a_gap_then_streaming_resumes():
    flock, clock, _ = _flock(2)
    _configure(flock, clock, {1: "position_quaternion", 2: "position_quaternion"})
    flock.write(b"@")
    clock.advance(0.2)
    flock.read()
    flock.stall(0.5)
    clock.advance(0.45)
    assert flock.read() == b""
    clock.advance(0.3)
    assert len(flock.read()) > 0


def test_disconnect_silences_the_line_and_reconnect_resumes_the_stream():
    flock, clock, _ = _flock(2)
    _configure(flock, clock, {1: "position_quaternion", 2: "position_quaternion"})
    flock.write(b"@")
    clock.advance(0.2)
    flock.disconnect()
    clock.advance(0.5)
    assert flock.read() == b""
    flock.write(b"?")  # lost: the cable is cut
    flock.reconnect()
    clock.advance(0.2)
    assert len(flock.read()) >= 15 * 2 * 15


def test_set_error_is_readable_through_p10():
    flock, clock, _ = _flock(1)
    flock.set_error(29)
    assert decode_status_word(_ask(flock, clock, examine_command(0))).error
    assert _ask(flock, clock, examine_command(10)) == bytes([29])


def test_host_that_never_reads_loses_the_oldest_bytes_not_memory():
    flock, clock, _ = _flock(4, buffer_limit=1000)
    _configure(flock, clock, {a: "position_quaternion" for a in range(1, 5)})
    flock.write(b"@")
    clock.advance(5.0)
    flock.advance()
    assert flock.stats()["queued"] <= 1000 + 60 and flock.stats()["bytes_lost"] > 0


def test_bad_setup_is_refused():
    with pytest.raises(FakeTrackerError):  # tried: more birds than the source has sensors
        FakeFlock(SmoothSource(2), birds=3, clock=ManualClock())
    with pytest.raises(FakeTrackerError):  # tried: 3 ports for 4 birds
        FakeFlock(SmoothSource(4), ports=3, clock=ManualClock())
