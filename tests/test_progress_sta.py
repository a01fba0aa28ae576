"""Under soft-tissue artefact (the simulator's default, 12 mm) the published progress of a simulated kiosk
guest never goes down without a reason it states: each fall names, on the joint that fell, a slip, a loss of
fit or a tree that now joins it elsewhere (issue #21's "no flapping", issue #19's soft-tissue guest).

The guest runs through the service's own per-fit steps in session time (the segmented accumulator,
`fit_calibration`, `ProgressTracker`, one refit per 1/30 s as `serve --fit-hz 30`), without driver and
server: the same code the live pipeline calls, quick enough for CI.
"""

from __future__ import annotations

import numpy as np
import pytest

from flockcal.server.fitting import fit_calibration

from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.progress import default_target
from flockcal.solver.progress_tracker import ProgressTracker
from flockcal.simulator.performer import Performer

RATE = 144.0
FIT_HZ = 30.0
TOLERANCE_M = 0.005  # serve's default --tolerance-mm
STATED = {"slip", "loss", "tree"}


def published(seed: int, height: float, seconds: float) -> list[tuple[float, dict]]:
    perf = Performer("human", "kiosk", seed=seed, rate_hz=RATE, height=height, sta_mm=12)
    acc = SegmentedAccumulator(perf.n_sensors)
    tracker = ProgressTracker(default_target(TOLERANCE_M), TOLERANCE_M)
    step = int(round(RATE / FIT_HZ))
    docs = []
    for k in range(int(seconds * FIT_HZ)):
        times = np.arange(k * step, (k + 1) * step) / RATE
        R, t, valid = perf.poses(times)
        acc.ingest(times, R, t, valid)
        docs.append((float(times[-1]), tracker.add_fit(fit_calibration(acc, perf.names, tolerance=TOLERANCE_M)[1],
                                                       float(times[-1])).to_dict()))
    return docs


# Guests of benchmarks/bench_calibrate_time.py (seeds 100–107 with --performer-option sta_mm=12) whose ring
# went back with no reason before #19: seed 107 five times in its first 13 s (a thigh re-linked between
# pelvis and abdomen, back and forth), seed 103 twice by 11 s; seed 100 at 12.5 s (a share just under 1
# held through a re-link was shown capped at 0.99).
@pytest.mark.parametrize("seed, height, seconds", [(107, 1.9097, 14.0), (103, 1.5193, 11.5), (100, 1.8757, 12.6)])
def test_progress_of_a_soft_tissue_guest_falls_only_for_a_stated_reason(seed, height, seconds):
    docs = published(seed, height, seconds)
    prev_total, prev_joints = 0.0, {}
    falls = []
    for t, doc in docs:
        joints = {j["joint"]: j for j in doc["joint_progress"]}
        assert (doc["percent"] == 100) == doc["done"]
        if doc["progress"] < prev_total - 1e-9:
            fell = [j for name, j in joints.items()
                    if name in prev_joints and j["progress"] < prev_joints[name]["progress"] - 1e-9]
            assert fell, f"at {t:.2f} s the progress fell {prev_total} → {doc['progress']} with no joint falling"
            unexplained = [j["joint"] for j in fell if (j.get("undone") or {}).get("reason") not in STATED]
            assert not unexplained, (f"at {t:.2f} s the progress fell {prev_total} → {doc['progress']}: "
                                     f"{unexplained} fell with no stated reason")
            falls.append((t, [(j["joint"], j["undone"]["reason"]) for j in fell]))
            for j in fell:
                assert j["why"], j  # and it says so in words
        prev_total, prev_joints = doc["progress"], joints
    # The guest made progress at all (a ring stuck at 0 would pass the loop above).
    assert docs[-1][1]["progress"] > 0.2, docs[-1][1]["progress"]
