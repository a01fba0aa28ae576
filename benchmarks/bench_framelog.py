"""What the session frame log's encoder (server/frameblocks.py) costs its thread (fc-framelog) and the disk, in
process: 16 birds at 144 Hz in position/matrix as the live reader hands them over (the simulated performer's
poses → the bytes a bird sends → the driver's own decoding, with the words it decoded them from), encoded in
quarter-second blocks as the log's flushes are. Three ways, in the same run: the words handed over with the
frames (the service today), the words worked out from the poses (frames that come without them), and the
handed-over words deflated at zlib level 6 instead of `frameblocks.LEVEL`.

    python benchmarks/bench_framelog.py [--seconds 30] [--rounds 3]

Prints bytes a frame, GB an hour and CPU as % of one core (median over the rounds), and each against the
first. Asserts nothing.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from flockcal.drivers.records import FORMATS, decode_block_words, encode_records, record_length
from flockcal.frames import TrackerWords
from flockcal.server import frameblocks
from flockcal.simulator.performer import Performer

RATE, BIRDS, FLUSH = 144.0, 16, 36  # a flush every quarter second


def reader_frames(seconds: float):
    fmt, scale = "position_matrix", 72
    perf = Performer("human", routine="exercise", rate_hz=RATE, birds=BIRDS, seed=1, noise="tracker")
    times = np.arange(int(seconds * RATE)) / RATE
    R0, x0, _ = perf.poses(times)
    n, m = R0.shape[:2]
    raw = np.frombuffer(encode_records(fmt, R0.reshape(-1, 3, 3), x0.reshape(-1, 3), scale_inches=scale), np.uint8)
    W, R, p, valid, _ = decode_block_words(fmt, raw.reshape(n * m, record_length(fmt, group=False)), scale_inches=scale)
    words = TrackerWords(W.reshape(n, m, -1), FORMATS[fmt].command, scale)
    return times, R.reshape(n, m, 3, 3), p.reshape(n, m, 3), valid.reshape(n, m), words


def encode(frames, carried: bool) -> tuple[int, float]:
    times, R, p, valid, words = frames
    enc = frameblocks.Encoder()
    size, t0 = 0, time.process_time()
    for a in range(0, len(times), FLUSH):
        s = slice(a, a + FLUSH)
        size += len(enc.block(times[s], R[s], p[s], valid[s], words[s] if carried else None))
    return size, time.process_time() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    frames = reader_frames(args.seconds)
    n = len(frames[0])
    level = frameblocks.LEVEL
    ways = {f"words handed over, zlib level {level}": (True, level), "words worked out from the poses": (False, level),
            "words handed over, zlib level 6": (True, 6)}
    got = {name: [] for name in ways}
    for _ in range(args.rounds):
        for name, (carried, lvl) in ways.items():  # in turn, so the machine's load falls on each alike
            frameblocks.LEVEL = lvl
            got[name].append(encode(frames, carried))
    frameblocks.LEVEL = level
    print(f"frame log encoding, {BIRDS} birds at {RATE:g} Hz position/matrix, {args.seconds:g} s in "
          f"{FLUSH}-frame blocks, median of {args.rounds} rounds:")
    base = None
    for name, runs in got.items():
        size = runs[0][0]
        cpu = 100.0 * float(np.median([c for _, c in runs])) / (n / RATE)
        base = base or (size, cpu)
        print(f"  {name:40s} {size / n:6.1f} B/frame  {size / n * RATE * 3600 / 1e9:.3f} GB/h  "
              f"{cpu:.2f} % of a core  (x{size / base[0]:.3f} bytes, x{cpu / base[1]:.2f} CPU)")


if __name__ == "__main__":
    main()
