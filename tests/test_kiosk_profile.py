"""The kiosk profile (issue #30, docs/service.md "Progress" and "Time to calibrate"): a guest's joint counts
once the data pin it to the kiosk's 10 mm and more data no longer changes it; a joint whose error is mostly
skin waits for its bones to hold still instead of for a statistic that skin makes shrink over minutes; on
white residuals the stage's target still holds; a stalled guest gets a patient prompt. Then the same on the
service's per-fit code: simulated guests with the default soft tissue are done in the documented time with
bones that a 120 s fit of the same guest no longer changes visibly, and rigid guests are no worse.
"""

from __future__ import annotations

import numpy as np
import pytest

from flockcal.server.fitting import fit_calibration

from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.progress import profile
from flockcal.solver.progress_tracker import ProgressTracker
from flockcal.simulator.performer import Performer

MM = 0.001


def kiosk() -> ProgressTracker:
    return ProgressTracker.for_profile(profile("kiosk", 5 * MM))


def skin_fit(frames: int, thigh_mm: float, err_mm: float = 8.0, noise_mm: float = 1.0, coverage: float = 0.5):
    """Pelvis → left thigh → left shin, each joint's error `err_mm` of which `noise_mm` is white noise; the
    thigh's bone (hip to knee) `thigh_mm` long."""
    def joint(child, parent):
        return {"child": child, "parent": parent, "determined": True, "hinge": False,
                "direction_error_m": [err_mm * MM] * 3, "noise_error_m": [noise_mm * MM] * 3,
                "coverage": [coverage] * 3}
    return {"sensors": ["pelvis", "l_thigh", "l_shin"], "root": "pelvis", "frames": frames,
            "parent": {"l_thigh": "pelvis", "l_shin": "l_thigh"},
            "joints": [joint("l_thigh", "pelvis"), joint("l_shin", "l_thigh")],
            "bones": [{"body": "l_thigh", "from_joint": "l_thigh", "to_joint": "l_shin", "length_m": thigh_mm * MM}],
            "rigid_groups": [], "ambiguous": []}


def run(tracker, lengths_mm, t0=0.0, rate=30.0, **kw):
    doc = None
    for k, length in enumerate(lengths_mm):
        t = t0 + k / rate
        doc = tracker.add_fit(skin_fit(int(100 * (t + 1)), length, **kw), t).to_dict()
    return doc


def test_a_skin_dominated_joint_counts_once_its_bones_hold_still_not_when_its_error_reaches_the_stage_target():
    # 8 mm of error, 1 mm of it white noise: the stage profile would wait minutes for 3.5 mm. The bone
    # holds still (within 0.5 mm): counted after the 2 s window and the growth of its information.
    tr = kiosk()
    doc = run(tr, [400.0 + 0.5 * np.sin(k) for k in range(30)])
    assert not doc["done"]
    states = {j["joint"]: j for j in doc["joint_progress"]}
    assert states["l_thigh"]["state"] == "settling" and "hold" in states["l_thigh"]["why"], states["l_thigh"]
    doc = run(tr, [400.0 + 0.5 * np.sin(k) for k in range(90)], t0=1.0)  # the window, then a second held
    assert doc["done"] and doc["percent"] == 100 and doc["profile"] == "kiosk" and "10 mm" in doc["rule"]


def test_a_joint_whose_bone_still_moves_keeps_settling_and_says_by_how_much():
    # The same joint, its bone swinging by 8 mm (more than the kiosk's 3 mm) every second: never counted.
    tr = kiosk()
    doc = run(tr, [400.0 + 4.0 * np.sin(2 * np.pi * k / 30) for k in range(150)])
    assert not doc["done"] and doc["percent"] < 100
    thigh = {j["joint"]: j for j in doc["joint_progress"]}["l_thigh"]
    assert thigh["state"] == "settling" and "moved" in thigh["why"], thigh
    # Every chip still ticked below 100 % is what the issue saw; here nothing is ticked that is not done.
    assert doc["joints_done"] == sum(j["done"] for j in doc["joint_progress"]) < 2


def test_on_white_residuals_a_kiosk_joint_waits_for_the_stage_target():
    # Rigid sensors: the error is all white noise (8 mm, of which 8 mm would shrink with more frames), so
    # a steady bone is not evidence enough: it pins towards the stage's 3.5 mm like the stage profile.
    tr = kiosk()
    doc = run(tr, [400.0] * 120, noise_mm=8.0)
    assert not doc["done"]
    assert {j["joint"]: j for j in doc["joint_progress"]}["l_thigh"]["state"] == "pinning"
    doc = run(tr, [400.0] * 60, t0=4.0, err_mm=3.0, noise_mm=3.0)
    assert doc["done"]


def test_a_guest_who_gains_little_for_eight_seconds_gets_a_patient_prompt_naming_a_joint():
    tr = kiosk()
    # The bone swings, so nothing counts and the ring sits at the settling share.
    doc = run(tr, [400.0 + 4.0 * np.sin(2 * np.pi * k / 30) for k in range(7 * 30)])
    assert doc["stalled_s"] is None and doc["prompt"] is None  # 7 s: not yet
    doc = run(tr, [400.0 + 4.0 * np.sin(2 * np.pi * k / 30) for k in range(2 * 30)], t0=7.0)
    assert doc["stalled_s"] >= 8.0 and doc["prompt"].startswith("Take your time")
    assert "hip" in doc["prompt"] or "knee" in doc["prompt"], doc["prompt"]


def test_the_stage_profile_is_as_strict_as_before():
    # Skin-dominated error of 8 mm with a bone that holds still: the stage never counts it.
    tr = ProgressTracker.for_profile(profile("stage", 5 * MM))
    doc = run(tr, [400.0] * 150)
    assert not doc["done"] and doc["profile"] == "stage"
    assert all(j["state"] == "pinning" for j in doc["joint_progress"])


# ------------------------------------------------------------------------------------ the real solver

RATE = 144.0
# docs/service.md "Time to calibrate": p90 ≤ 35 s with soft tissue, median ≤ 20 s rigid (the slowest
# guest there 22.4 s); bones at done within 5 mm of the same guest's after 120 s (soft tissue) or of the
# truth (rigid). Margins: 5 s on times, 1 mm on bones.
STA_DONE_S, RIGID_DONE_S, BONES_M = 35.0 + 5.0, 22.4 + 5.0, 0.005 + 0.001


def guest_run(perf: Performer, max_s: float):
    """The service's per-fit steps (server/fitting.py, solver/progress_tracker.py) at 30 fits a second, session
    clock, until done: (done_at_s, the fit at done)."""
    acc = SegmentedAccumulator(perf.n_sensors)
    tracker = ProgressTracker.for_profile(profile("kiosk", 5 * MM))
    step = int(round(RATE / 30))
    for k in range(int(max_s * 30)):
        times = np.arange(k * step, (k + 1) * step) / RATE
        acc.ingest(times, *perf.poses(times))
        fit, cal = fit_calibration(acc, perf.names, tolerance=tracker.tolerance_m)
        doc = tracker.add_fit(cal, float(times[-1])).to_dict()  # the typed fit, as the service passes it
        if doc["done"]:
            return doc["done_at_s"], fit
    return None, fit


def bone_lengths(fit: dict) -> dict:
    """{(body, {its two joints, each as its two bodies}): length}: the same bone whichever way the tree was
    rooted (a joint is named by its child, which depends on the root)."""
    par = fit["parent"]
    return {(b["body"], frozenset(frozenset((j, par[j])) for j in (b["from_joint"], b["to_joint"]))): b["length_m"]
            for b in fit.get("bones") or [] if b["from_joint"] in par and b["to_joint"] in par}


def later_fit(perf: Performer, seconds: float) -> dict:
    acc = SegmentedAccumulator(perf.n_sensors)
    for k in range(int(seconds)):
        times = np.arange(int(k * RATE), int((k + 1) * RATE)) / RATE
        acc.ingest(times, *perf.poses(times))
    return fit_calibration(acc, perf.names, tolerance=0.010)[0]


@pytest.mark.parametrize("seed, height", [(116, 1.948)])
def test_soft_tissue_guests_are_done_in_time_with_bones_more_data_does_not_change(seed, height):
    # The benchmark's hardest guest for bones: 116 had a bone move 5.4 mm after done under an earlier rule
    # (a joint counted as soon as its error read 3.5 mm, though that error was mostly skin).
    done_s, fit = guest_run(Performer("human", "kiosk", seed=seed, rate_hz=RATE, height=height), STA_DONE_S)
    assert done_s is not None and done_s <= STA_DONE_S, done_s
    later = later_fit(Performer("human", "kiosk", seed=seed, rate_hz=RATE, height=height), 120.0)
    assert later["parent"] == fit["parent"]
    now, then = bone_lengths(fit), bone_lengths(later)
    assert set(now) == set(then)
    moved = {k: abs(now[k] - then[k]) for k in then}
    assert max(moved.values()) <= BONES_M, max(moved.items(), key=lambda kv: kv[1])


def test_a_rigid_guest_is_done_as_fast_as_before_with_bones_true_to_5_mm():
    perf = Performer("human", "kiosk", seed=7, rate_hz=RATE, height=1.68, sta_mm=0)
    done_s, fit = guest_run(perf, RIGID_DONE_S)
    assert done_s is not None and done_s <= RIGID_DONE_S, done_s
    # Ball-to-ball bones against the body's own geometry (the simulator's truth, not the fit's code).
    truth = perf.truth()
    true = bone_lengths(truth)
    hinge = {frozenset((j["child"], j["parent"])) for j in truth["joints"] if j.get("hinge")}
    ball = [k for k in bone_lengths(fit) if k in true and not k[1] & hinge]
    assert len(ball) >= 5  # pelvis, abdomen, chest: the bones between two ball joints
    assert max(abs(bone_lengths(fit)[k] - true[k]) for k in ball) <= BONES_M
