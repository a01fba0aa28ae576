"""The typed progress (solver/progress.py, issue 33): a session's tracker gives the same documents whether it
is handed the solver's `Calibration` (the live service, the report, a re-solve) or its §5 dict (a stored
result), and every document it publishes reads back as the same `Progress` (`from_dict(d).to_dict() == d`).
The session event's wording of becoming done and undone sits beside the rule (progress_words.done_change).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from flockcal.server.fitting import fit_calibration
from flockcal.simulator.performer import Performer
from flockcal.solver.calibration_json import event_from_json
from flockcal.solver.progress import JointProgress, JointState, Progress, profile, progress_of, waiting
from flockcal.solver.progress_tracker import ProgressTracker
from flockcal.solver.progress_words import done_change
from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.slippage import SlipEvent, SwapEvent

RATE, FIT_HZ = 144.0, 30.0


@pytest.fixture(scope="module")
def guest_fits():
    """A soft-tissue kiosk guest's fits, 30 a second for 14 s of session time: (time_s, §5 dict, Calibration)."""
    perf = Performer("human", "kiosk", seed=104, rate_hz=RATE, height=1.94, sta_mm=12)
    acc = SegmentedAccumulator(perf.n_sensors)
    step = int(round(RATE / FIT_HZ))
    out = []
    for k in range(int(14 * FIT_HZ)):
        times = np.arange(k * step, (k + 1) * step) / RATE
        acc.ingest(times, *perf.poses(times))
        d, cal = fit_calibration(acc, perf.names, tolerance=0.005)
        out.append((float(times[-1]), d, cal))
    return perf, out


@pytest.mark.parametrize("name", ["stage", "kiosk"])
def test_a_calibration_and_its_dict_give_the_same_documents_and_each_reads_back(guest_fits, name):
    perf, fits = guest_fits
    typed, stored = (ProgressTracker.for_profile(profile(name, 0.005)) for _ in range(2))
    # A slip of the left forearm at 6 s (as the monitor reports it: typed, and as the store keeps it), and
    # a swap of the two thighs at 9 s: their joints are undone, with the reason in their entries.
    slips = {180: SlipEvent(5.8, "l_forearm", ("l_forearm",), 0.9, ("l_forearm", "l_hand"), 30.0),
             270: SwapEvent(8.9, "l_thigh", "r_thigh", ("l_thigh", "r_thigh"), 25.0)}
    reasons = set()
    for k, (t, d, cal) in enumerate(fits):
        epoch = sum(1 for at in slips if at <= k)
        if k in slips:
            typed.slip(slips[k], epoch)
            stored.slip(event_from_json(json.loads(json.dumps(slips[k].to_dict())), perf.names), epoch)
        a, b = typed.add_fit(cal, t, epoch), stored.add_fit(d, t, epoch)
        doc = a.to_dict()
        assert json.loads(json.dumps(doc)) == doc == b.to_dict(), (name, t)
        assert Progress.from_dict(doc).to_dict() == doc
        assert isinstance(a.joints[0].state, JointState) and a.joints_done == doc["joints_done"]
        reasons |= {m["undone"]["reason"] for m in doc["missing"] if m["undone"]}
    assert "slip" in reasons  # the documents tried include undone entries


def test_the_reports_one_fit_reads_the_same_off_the_calibration_and_its_dict(guest_fits):
    _, fits = guest_fits
    for t, d, cal in fits[::30]:
        doc = progress_of(cal, 0.0035, 0.005).to_dict()
        assert doc == progress_of(d, 0.0035, 0.005).to_dict()
        assert Progress.from_dict(doc).to_dict() == doc


def test_a_share_on_a_rounding_boundary_reads_back_with_both_its_published_figures():
    # Published to 4 decimals in joint_progress and to 3 in its hint: 0.01249999 is 0.0125 and 0.012, while
    # 0.0125 alone would read back as 0.013 in the hint.
    joint = JointProgress("l_thigh", "pelvis", "left hip", JointState.PINNING, 0.01249999, False, 0.004,
                          "pinned to 4.0 mm", None, "Keep moving the left hip.")
    p = Progress("calibrating", 0.0125, 1, False, None, 0.0035, 1, (joint,), ("l_thigh",))
    doc = p.to_dict()
    assert doc["joint_progress"][0]["progress"] == 0.0125 and doc["hints"][0]["progress"] == 0.012
    assert Progress.from_dict(doc).to_dict() == doc
    before = waiting(["pelvis", "l_thigh"], 0.0035, "no fit yet: keep moving").to_dict()
    assert before["state"] == "no_fit" and before["note"] and Progress.from_dict(before).to_dict() == before


def test_becoming_done_and_undone_is_worded_beside_the_rule():
    joint = JointProgress("l_thigh", "pelvis", "left hip", JointState.DONE, 1.0, True, 0.001)
    done = Progress("done", 1.0, 100, True, 3.0, 0.0035, 1, (joint,))
    stage, kiosk = profile("stage", 0.005), profile("kiosk", 0.005)
    assert done_change(done, True, "Ada", stage, 3.0) is None
    assert done_change(done, False, "Ada", stage, 3.04) == (
        "calibrated", "Ada is calibrated: all 1 joints pinned to 3.5 mm after 3.0 s")
    assert done_change(done, False, "Ada", kiosk, 3.0)[1].endswith("pinned to 10 mm and steady after 3.0 s")
    # An arm done, then its forearm sensor slips: the event says which sensor and when.
    tr = ProgressTracker(0.0035, 0.005, confirm_s=0.0)
    arm = {"sensors": ["pelvis", "l_forearm", "l_hand"], "root": "pelvis",
           "parent": {"l_forearm": "pelvis", "l_hand": "l_forearm"},
           "joints": [{"child": c, "parent": p, "hinge": False, "determined": True, "direction_error_m": [0.001] * 3}
                      for c, p in (("l_forearm", "pelvis"), ("l_hand", "l_forearm"))]}
    assert tr.add_fit(arm, 1.0).done
    tr.slip(SlipEvent(1.04, "l_forearm", ("l_forearm",), 1.0, ("l_forearm",), 20.0), 1)
    after = tr.add_fit(arm, 1.1, epoch=0)  # begun before the slip: cannot redo the forearm's joints
    assert done_change(after, True, "Ada", stage, 1.1) == (
        "calibration_undone", "Ada is no longer calibrated: the left forearm sensor slipped at 1.0 s: measured afresh since")
