"""How fast the simulator produces frames, as multiples of the tracker's real-time rate, with the
soft-tissue artefact off and on (the human default, 12 mm) in the same run.

Prints ratios (frames produced per second of wall time ÷ frames the Flock makes per second), for a
recorded take and for the live performer asked for a few frames at a time as the fake tracker does.
Run: python benchmarks/simulator_speed.py
"""

import time

import numpy as np

from flockcal.simulator.performer import Performer
from flockcal.simulator.take import simulate

RATE = 144.0  # the Flock's fastest measurement rate


def best_of(fn, repeats=5):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    seconds = 45.0
    frames = seconds * RATE
    for noise in (None, "tracker"):
        rate = {}
        for sta in (0.0, 12.0):
            dt = best_of(lambda: simulate(motion="walk", seconds=seconds, rate_hz=RATE, birds=16, seed=1, noise=noise, sta_mm=sta))
            rate[sta] = frames / dt
            print(f"take.simulate, 16 birds, noise={noise}, STA {sta:g} mm: {frames / dt:,.0f} frames/s = "
                  f"{frames / dt / RATE:,.0f}× real time")
        print(f"  soft tissue costs {100 * (rate[0.0] / rate[12.0] - 1):.0f} % more time")
    batch = 3  # the fake tracker asks for the few frames that came due since its last look
    calls = 2000
    t = np.arange(calls * batch) / RATE
    rate = {}
    for sta in (0.0, 12.0):
        perf = Performer(routine="walk", seed=1, sta_mm=sta)

        def live():
            for k in range(calls):
                perf.poses(t[k * batch : (k + 1) * batch])

        dt = best_of(live, 3)
        rate[sta] = calls * batch / dt
        print(f"Performer.poses, 16 birds, {batch} frames per call, STA {sta:g} mm: {calls * batch / dt:,.0f} frames/s = "
              f"{calls * batch / dt / RATE:,.1f}× real time at {RATE:g} Hz")
    print(f"  soft tissue costs {100 * (rate[0.0] / rate[12.0] - 1):.0f} % more time")


if __name__ == "__main__":
    main()
