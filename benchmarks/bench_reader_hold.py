"""What holding a record read next to lost bytes costs in latency (drivers/checks.py: it waits for its bird's
next trusted record). Replays `.fobraw` recordings read by read at their recorded arrival times, taking frames
after every read as the live reader does, and prints each frame's hand-out delay (the read that released it
minus the cycle's first byte): the median, p99 and max, and the frames delayed most.

    python benchmarks/bench_reader_hold.py [FILE.fobraw …]   (default: ../shared/data/faults/{clean,spike}.fobraw)
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from flockcal.drivers.assembly import FrameAssembler
from flockcal.drivers.link import FlockSetup
from flockcal.drivers.recording import MARK, READ, read_recording

SHARED = Path(os.environ.get("FLOCKCAL_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def hand_out_delays(path: Path) -> tuple[np.ndarray, list[int]]:
    """(seconds from each frame's cycle time to the arrival of the read after which `take` returned it, the
    frames that were held back for a suspect record)."""
    asm, delays, held = None, [], []
    for chunk in read_recording(path).chunks:
        if chunk.kind == MARK:
            info = chunk.marker()
            if "stream" in info:
                asm = FrameAssembler(FlockSetup.from_dict(info["stream"]), **info.get("assembler", {}))
        elif chunk.kind == READ and asm is not None:
            waiting = len(asm.held[0]) if getattr(asm, "held", None) is not None else 0
            asm.feed(chunk.port, chunk.time, chunk.payload)
            out = asm.take()
            held.extend(range(len(delays), len(delays) + min(waiting, len(out))))
            delays.extend(chunk.time - out.times)
    return np.asarray(delays), held


def main(paths: list[str]) -> None:
    files = [Path(p) for p in paths] or [SHARED / "faults" / "clean.fobraw", SHARED / "faults" / "spike.fobraw"]
    for path in files:
        d, held = hand_out_delays(path)
        d = d * 1000
        print(f"{path.name}: {len(d)} frames; hand-out delay median {np.median(d):.1f} ms, p99 "
              f"{np.percentile(d, 99):.1f} ms, max {d.max():.1f} ms; held for a suspect record: "
              + (", ".join(f"frame {i} ({d[i]:.1f} ms)" for i in held) or "none"))


if __name__ == "__main__":
    main(sys.argv[1:])
