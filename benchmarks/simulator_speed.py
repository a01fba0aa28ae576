"""How fast the simulator produces frames, as multiples of the tracker's real-time rate.

Prints ratios (frames produced per second of wall time ÷ frames the Flock makes per second), for a
recorded take and for the live performer asked for a few frames at a time as the fake tracker does.
Run: python benchmarks/simulator_speed.py
"""

import time

import numpy as np

from flockcal.simulator.performer import Performer
from flockcal.simulator.take import simulate

RATE = 144.0  # the Flock's fastest measurement rate


def best_of(fn, repeats=3):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    for noise in (None, "tracker"):
        seconds = 45.0
        dt = best_of(lambda: simulate(motion="walk", seconds=seconds, rate_hz=RATE, birds=16, seed=1, noise=noise))
        frames = seconds * RATE
        print(f"take.simulate, 16 birds, noise={noise}: {frames / dt:,.0f} frames/s = {frames / dt / RATE:,.0f}× real time")
    perf = Performer(routine="walk", seed=1)
    batch = 3  # the fake tracker asks for the few frames that came due since its last look
    calls = 2000
    t = np.arange(calls * batch) / RATE

    def live():
        for k in range(calls):
            perf.poses(t[k * batch : (k + 1) * batch])

    dt = best_of(live)
    print(f"Performer.poses, 16 birds, {batch} frames per call: {calls * batch / dt:,.0f} frames/s = "
          f"{calls * batch / dt / RATE:,.1f}× real time at {RATE:g} Hz")


if __name__ == "__main__":
    main()
