"""A .fobraw recording of a pose source made as fast as the bytes can be computed (no pty, no waiting for
the clock): what a group-mode flock streams, in reads of a few frames under the stream's setup marker, as
`flockcal record` writes it. For tests and benchmarks that need an hour-long recording in seconds.
"""

from __future__ import annotations

import os
import time

import numpy as np

from flockcal.drivers.link import FlockSetup
from flockcal.drivers.recording import RecordingWriter
from flockcal.drivers.records import encode_records, record_length
from flockcal.simulator.fake_tracker import PoseSource


def write_recording(path: str | os.PathLike, source: PoseSource, seconds: float, rate_hz: float = 100.0, *,
                    record_format: str = "position_quaternion", scale_inches: float = 72.0, baud: int = 921600,
                    frames_per_read: int = 2, block_s: float = 10.0) -> int:
    """Write `seconds` of `source` at `rate_hz` to `path`; the number of frames. Arrival times run from now
    on the monotonic clock (a frame arrives once its bytes crossed a `baud` line), as a recorder stamps them."""
    m = source.n_sensors
    addresses = np.arange(1, m + 1)
    setup = FlockSetup(urls=["fast://"], birds=m, addresses=addresses.tolist(), group=m > 1, mode="stream",
                       record_format=record_format, scale_inches=float(scale_inches), rate_hz=float(rate_hz),
                       hemisphere="forward", baud=baud, software_revision=3.67, model="6DFOB")
    per_frame = m * record_length(record_format, group=setup.group)
    transfer = per_frame * 10.0 / baud
    n = int(round(seconds * rate_hz))
    block = max(frames_per_read, int(block_s * rate_hz) // frames_per_read * frames_per_read)
    settings = {"names": list(source.names), "config": {"urls": setup.urls, "birds": m}}
    with RecordingWriter(path, settings) as rec:
        t0 = time.monotonic()
        rec.mark(t0, {"stream": setup.to_dict(), "assembler": {}})
        for a in range(0, n, block):
            k = min(block, n - a)
            times = (a + np.arange(k)) / rate_hz
            R, p, _valid = source.poses(times)
            data = encode_records(record_format, R.reshape(-1, 3, 3), p.reshape(-1, 3), scale_inches=scale_inches,
                                  addresses=np.tile(addresses, k) if setup.group else None)
            for j in range(0, k, frames_per_read):
                j2 = min(k, j + frames_per_read)
                rec.read(t0 + times[j2 - 1] + transfer, 0, data[j * per_frame:j2 * per_frame])
    return n
