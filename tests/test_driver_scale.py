"""Position full scale against the fake flock on a real pty: the scale asked for is the scale the birds
use, and a sensor beyond it is reported invalid (never as a clipped pose) with a warning to the operator."""

from __future__ import annotations


import numpy as np
import pytest

from flockcal.rotations import from_euler
from flockcal.drivers.link import Timing, TrackerError
from flockcal.drivers.reader import TrackerConfig, TrackerReader
from flockcal.simulator.pty_tracker import PtyTracker
from service_process import wait_for

INCH = 0.0254


class ReachingSource:
    """Four sensors in front of the transmitter; sensor 1 reaches out to 1.1 m (beyond 36 in) and back."""

    n_sensors = 4
    names = ("s0", "s1", "s2", "s3")

    def __init__(self, power_up_scale: float):
        self.full_scale_in = power_up_scale  # what the fake flock powers up with

    def poses(self, times):
        t = np.asarray(times, float)
        p = np.zeros((len(t), 4, 3))
        p[:, :, 0] = 0.3 + 0.1 * np.arange(4)
        p[:, :, 1] = 0.05 * np.sin(2 * np.pi * 0.5 * t)[:, None]
        p[:, :, 2] = 0.1
        p[:, 1, 0] = 0.75 + 0.35 * np.sin(2 * np.pi * 0.8 * t)  # 0.4 … 1.1 m
        R = from_euler(0.3 * np.sin(t)[:, None] + np.zeros((1, 4)), np.zeros((len(t), 4)),
                                    np.zeros((len(t), 4)))
        return R, p, np.ones((len(t), 4), bool)


def read_reaching(scale: int, power_up: float, frames: int = 90):
    """What the reader makes of `frames` frames (1.5 s at 60 Hz, counted) of a reaching sensor."""
    parts, events = [], []
    with PtyTracker(ReachingSource(power_up), birds=4, baud=115200) as trk:
        cfg = TrackerConfig(urls=[trk.device], birds=4, rate_hz=60, record_format="position_quaternion",
                            scale_inches=scale, timing=Timing.fast())
        reader = TrackerReader(cfg, on_frames=lambda f: parts.append((f.positions.copy(), f.valid.copy())),
                               on_event=events.append)
        reader.start(wait=15)
        try:
            wait_for(lambda: sum(len(x[1]) for x in parts) >= frames, 60, f"{frames} frames read")
        finally:
            reader.stop()
        flock_scale = trk.flock.scale_inches
    p = np.concatenate([x[0] for x in parts])
    valid = np.concatenate([x[1] for x in parts])
    return p, valid, events, reader.status(), flock_scale


def test_a_sensor_beyond_36_inches_is_invalid_counted_and_reported_not_clipped():
    # The flock powers up at 72 in: the driver must switch it to the 36 in asked for.
    p, valid, events, status, flock_scale = read_reaching(36, power_up=72.0)
    fs = 36 * INCH
    assert flock_scale == 36.0
    assert status.scale_inches == 36 and status.saturated_records > 0
    assert np.abs(p[valid]).max() < fs  # no clipped position handed out as a pose
    assert valid[1:-1][:, [0, 2, 3]].all()  # only the reaching bird loses frames (ends: partial cycles)
    assert 0 < status.saturated_records <= np.count_nonzero(~valid[:, 1])
    saturated = [e for e in events if e.kind == "position_saturated"]
    assert 1 <= len(saturated) <= 2  # one per reach out of range (about 0.6 s each in 1.25 s)
    assert saturated[0].data["birds"] == [1] and "--scale 72" in saturated[0].message


def test_at_72_inches_the_same_reach_is_read_in_full():
    # The flock powers up at 36 in: the driver must switch it to the 72 in asked for.
    p, valid, events, status, flock_scale = read_reaching(72, power_up=36.0)
    assert flock_scale == 72.0
    assert valid[1:-1].all() and status.saturated_records == 0  # (ends: partial cycles)
    assert p[:, 1, 0].max() > 36 * INCH + 0.05  # beyond the 36-inch scale, read correctly
    assert not [e for e in events if e.kind == "position_saturated"]


def test_a_bird_that_keeps_its_old_scale_stops_the_setup_with_the_reason():
    # Tried: a flock whose firmware ignores CHANGE VALUE p3 (it stays at its power-up 36 in).
    with PtyTracker(ReachingSource(36.0), birds=4, baud=115200) as trk:
        change = trk.flock._change
        trk.flock._change = lambda bird, p, data: None if p == 3 else change(bird, p, data)
        reader = TrackerReader(TrackerConfig(urls=[trk.device], birds=4, scale_inches=72, timing=Timing.fast()))
        with pytest.raises(TrackerError) as err:
            reader.start(wait=10)
    text = str(err.value)
    assert "bird 0 (address 1)" in text and "36-inch position scale" in text and "72 in" in text
