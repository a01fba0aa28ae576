"""The one definition of calibration progress (solver/progress.py, solver/progress_tracker.py; docs/service.md
"Progress: one figure for the kiosk, the dashboard and the API"): every sensor but
the root counts, rigid or undetermined ones count 0 with a reason, "100 %" means done, a done joint stays
done through wobbles and is undone by a slip or a real loss of fit; and the same on the real solver.

Fits are written out by hand here, in the §5 shape, so each rule is tried on exactly the case it is about.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from flockcal.server.fitting import fit_calibration
from flockcal.solver.progress import Undone, default_target, progress_of
from flockcal.solver.progress_tracker import ProgressTracker
from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.slippage import SlipEvent
from flockcal.server.settings import Settings
from flockcal.simulator.performer import Performer

MM = 0.001
# The rules are tried at a 5 mm target; the service's own (`serve --target-mm`) is by default the 5 mm tolerance
# over √2 (docs/service.md "Options"), which test_the_default_target… below holds.
TARGET = 5 * MM


def joint(child, parent, err_mm=(1.0, 1.0, 1.0), determined=True, hinge=False):
    err = [None if e is None else e * MM for e in err_mm]
    return {"child": child, "parent": parent, "c": [0.0, 0.0, 0.1], "l": [0.0, 0.1, 0.0], "hinge": hinge,
            "determined": determined, "direction_error_m": err}


def slip(sensor, time_s, joints=None):
    """A slip of `sensor` at `time_s`, as the slip monitor reports it."""
    return SlipEvent(time_s, sensor, (sensor,), 1.0, tuple(joints or (sensor,)), 20.0)


def fit(joints, rigid_members=(), rigid_groups=(), root="pelvis", ambiguous=()):
    """A searched-topology fit: `joints` as (child, parent, …) dicts, rigid members as (child, parent)."""
    parent = {j["child"]: j["parent"] for j in joints}
    parent.update(dict(rigid_members))
    sensors = [root] + list(parent)
    return {"sensors": sensors, "root": root, "parent": parent, "joints": list(joints),
            "rigid_groups": [list(g) for g in rigid_groups], "ambiguous": list(ambiguous)}


def test_rigid_and_undetermined_sensors_count_zero_and_are_named_with_a_reason():
    # The case: every joint the fit has is determined, yet most sensors have not moved.
    f = fit([joint("l_thigh", "pelvis"), joint("r_thigh", "pelvis", err_mm=(None, 12.0, 3.0), determined=False),
             joint("l_shin", "l_thigh", err_mm=(30.0, 2.0, 2.0), determined=True, hinge=True)],
            rigid_members=[("chest", "pelvis"), ("head", "pelvis")], rigid_groups=[["pelvis", "chest", "head"]])
    doc = progress_of(f, TARGET).to_dict()
    assert doc["joints_needed"] == 5  # every sensor but the root
    assert doc["joints_done"] == 2  # the left hip, and the left knee (a hinge: its free axis is not needed)
    assert doc["progress"] == pytest.approx(2 / 5, abs=1e-4) and doc["percent"] == 40 and not doc["done"]
    missing = {m["joint"]: m for m in doc["missing"]}
    assert set(missing) == {"r_thigh", "chest", "head"}
    assert missing["chest"]["state"] == "rigid" and "has not moved relative to the pelvis" in missing["chest"]["why"]
    assert missing["r_thigh"]["state"] == "not_turned" and missing["r_thigh"]["label"] == "right hip"
    hints = {h["joint"]: h["hint"] for h in doc["hints"]}
    assert set(hints) == set(missing) and "the right hip" in hints["r_thigh"]
    # The one furthest from calibrated comes first: not moved at all before moved but not pinned.
    assert [m["state"] for m in doc["missing"]][:2] == ["rigid", "rigid"]


def test_a_joint_pinned_along_two_directions_is_undetermined_and_says_so():
    doc = progress_of(fit([joint("l_upper_arm", "pelvis", err_mm=(9.0, 2.0, 1.0), determined=False)]), TARGET).to_dict()
    (m,) = doc["missing"]
    assert m["state"] == "undetermined" and "2 of 3 directions" in m["why"]
    assert doc["progress"] == 0.0


def test_a_stricter_target_ramps_with_the_share_of_frames_still_needed():
    # Determined to the 5 mm tolerance at 4 mm, target 2 mm: the error falls as 1/sqrt(frames), so a
    # quarter of the frames it needs are in.
    doc = progress_of(fit([joint("l_thigh", "pelvis", err_mm=(4.0, 1.0, 1.0))]), 2 * MM, tolerance_m=TARGET).to_dict()
    assert doc["joint_progress"][0]["state"] == "pinning"
    assert doc["progress"] == pytest.approx(0.25, abs=1e-4)
    assert "4.0 mm" in doc["missing"][0]["why"]


def test_the_default_target_holds_a_bone_between_two_such_joints_to_the_tolerance():
    # A bone's two ends add in quadrature: each pinned to t, the bone to t·√2 = the tolerance.
    assert default_target(TARGET) * math.sqrt(2) == pytest.approx(TARGET)
    assert Settings(device="sim://x?birds=3", birds=3, tolerance_m=0.004).progress_target_m == pytest.approx(0.004 / math.sqrt(2))


def track(tracker, fits, t0=0.0, dt=0.1, epoch=0):
    doc = None
    for k, f in enumerate(fits):
        doc = tracker.add_fit(f, t0 + k * dt, epoch).to_dict()
    return doc


def test_done_needs_every_joint_held_for_a_second_and_the_ring_shows_100_only_then():
    tr = ProgressTracker(TARGET)
    both = fit([joint("l_thigh", "pelvis"), joint("r_thigh", "pelvis")])
    first = tr.add_fit(both, 0.0).to_dict()
    # Pinned, but a joint counts only once it has held for CONFIRM_S (1 s): nothing is counted yet.
    assert first["progress"] == 0.0 and {m["state"] for m in first["missing"]} == {"confirming"}
    doc = track(tr, [both] * 11, t0=0.1)  # up to 1.1 s
    assert doc["done"] and doc["progress"] == 1.0 and doc["percent"] == 100 and doc["missing"] == []
    assert doc["done_at_s"] == pytest.approx(1.0)


def test_a_wobble_about_the_target_leaves_done_joints_done_but_a_real_loss_undoes_them():
    tr = ProgressTracker(TARGET)
    good = fit([joint("l_thigh", "pelvis"), joint("r_thigh", "pelvis")])
    track(tr, [good] * 12)
    assert tr.latest.done
    # The right hip's newest fit reads 5.6 mm, undetermined: a wobble, nothing moves.
    wobble = fit([joint("l_thigh", "pelvis"), joint("r_thigh", "pelvis", err_mm=(5.6, 2.0, 1.0), determined=False)])
    doc = track(tr, [wobble] * 5, t0=1.2)
    assert doc["done"] and doc["progress"] == 1.0
    # Far beyond the target (over twice it): the fit is really lost; the page is told why.
    lost = fit([joint("l_thigh", "pelvis"), joint("r_thigh", "pelvis", err_mm=(14.0, 2.0, 1.0), determined=False)])
    doc = tr.add_fit(lost, 2.0).to_dict()
    assert not doc["done"] and doc["progress"] == 0.5
    (m,) = doc["missing"]
    assert m["joint"] == "r_thigh" and m["undone"]["reason"] == "loss" and "no longer fits" in m["why"]


def test_every_joint_done_again_while_one_wobbles_stays_below_100_until_one_clear_fit():
    tr = ProgressTracker(TARGET)
    both = fit([joint("l_thigh", "pelvis"), joint("r_thigh", "pelvis")])
    track(tr, [both] * 12)
    tr.slip(slip("r_thigh", 1.15), 1)
    # The right hip is re-pinned from fresh frames while the left one wobbles just above the target.
    wobble = fit([joint("l_thigh", "pelvis", err_mm=(5.6, 2.0, 1.0), determined=False), joint("r_thigh", "pelvis")])
    doc = track(tr, [wobble] * 12, t0=1.2, epoch=1)
    # Each joint was done once, but 100 % waits for one clear fit; meanwhile the one this fit leaves short
    # is shown as not done (issue #30: 15 chips ticked and "15 / 15" at 99 % told the guest nothing was left).
    assert not doc["done"] and doc["percent"] == 99 and doc["progress"] < 1
    assert doc["joints_done"] == 1 == sum(j["done"] for j in doc["joint_progress"])
    assert [m["joint"] for m in doc["missing"]] == ["l_thigh"]
    doc = tr.add_fit(both, 2.5, epoch=1).to_dict()
    assert doc["done"] and doc["percent"] == 100


def test_a_slip_undoes_its_sensors_joints_and_a_fit_begun_before_it_cannot_redo_them():
    tr = ProgressTracker(TARGET)
    arm = fit([joint("l_upper_arm", "pelvis"), joint("l_forearm", "l_upper_arm", err_mm=(30, 1, 1), hinge=True),
               joint("l_hand", "l_forearm")])
    track(tr, [arm] * 12)
    assert tr.latest.done
    undone = tr.slip(slip("l_forearm", 12.3, ("l_forearm", "l_hand")), 1)
    assert undone == ["l_forearm", "l_hand"]  # its inboard and outboard joints
    # The fit in flight was computed from the accumulator before the slip (epoch 0): it still reads pinned.
    doc = track(tr, [arm] * 15, t0=1.3, epoch=0)
    assert not doc["done"] and doc["joints_done"] == 1
    missing = {m["joint"]: m for m in doc["missing"]}
    assert set(missing) == {"l_forearm", "l_hand"}
    assert all(m["undone"]["reason"] == "slip" for m in missing.values())
    assert "left forearm sensor slipped at 12.3" in missing["l_hand"]["why"]
    # Fits from after the slip re-pin them (from fresh frames) and, held a second, they count again.
    doc = track(tr, [arm] * 12, t0=3.0, epoch=1)
    assert doc["done"] and doc["missing"] == []


def test_a_fit_lost_to_a_slip_before_the_monitor_confirmed_it_gives_the_slip_as_its_reason():
    # Seen in CI: the wrist's fit was lost 0.2 s after a forearm slip, the monitor confirmed the slip 0.3 s
    # later, and the wrist's entry went on saying "no longer fits" while the elbow's named the slip.
    tr = ProgressTracker(TARGET)
    arm = fit([joint("l_upper_arm", "pelvis"), joint("l_forearm", "l_upper_arm"), joint("l_hand", "l_forearm")])
    track(tr, [arm] * 12)
    lost = fit([joint("l_upper_arm", "pelvis"), joint("l_forearm", "l_upper_arm"),
                joint("l_hand", "l_forearm", err_mm=(14.0, 2.0, 1.0), determined=False)])
    doc = tr.add_fit(lost, 2.0).to_dict()
    assert doc["missing"][0]["undone"]["reason"] == "loss"
    # An earlier loss (before the slip's onset) is not the slip's: an unrelated shoulder lost at 1.5 s.
    tr.joint("l_upper_arm", "pelvis").undone = Undone("loss", 1.5, "l_upper_arm")
    assert tr.slip(slip("l_forearm", 1.8), 1) == ["l_forearm"]
    doc = tr.add_fit(lost, 2.1, epoch=0).to_dict()
    missing = {m["joint"]: m["undone"] for m in doc["missing"]}
    assert missing["l_hand"] == {"reason": "slip", "time_s": 1.8, "sensor": "l_forearm"}
    assert missing["l_forearm"]["reason"] == "slip"
    assert tr.joint("l_upper_arm", "pelvis").undone.reason == "loss"


def test_a_joint_pinning_towards_a_stricter_target_never_shows_less_than_it_reached():
    tr = ProgressTracker(2 * MM, tolerance_m=TARGET)

    def at(err):
        return fit([joint("l_thigh", "pelvis", err_mm=(err, 1.0, 1.0))])

    doc = track(tr, [at(4.0)] * 11)  # determined for a second: (2/4)² of the frames it needs
    assert doc["progress"] == pytest.approx(0.25, abs=1e-4)
    doc = tr.add_fit(at(4.5), 1.1).to_dict()  # the error wobbles up: the share shown stays
    assert doc["progress"] == pytest.approx(0.25, abs=1e-4)
    doc = tr.add_fit(at(3.0), 1.2).to_dict()
    assert doc["progress"] == pytest.approx((2 / 3) ** 2, abs=1e-4)
    # Undetermined far beyond the tolerance (over twice it): lost, shown as such.
    doc = tr.add_fit(fit([joint("l_thigh", "pelvis", err_mm=(11.0, 1.0, 1.0), determined=False)]), 1.3).to_dict()
    assert doc["progress"] == 0.0 and doc["missing"][0]["undone"]["reason"] == "loss"


def test_a_joint_done_against_a_rigid_group_stays_done_when_the_group_comes_apart():
    tr = ProgressTracker(TARGET)
    # The forearm and hand have not moved relative to each other yet: one body, joined to the upper arm
    # through the hand's sensor.
    before = fit([joint("l_upper_arm", "pelvis"), joint("l_hand", "l_upper_arm", err_mm=(30, 1, 1), hinge=True)],
                 rigid_members=[("l_forearm", "l_hand")], rigid_groups=[["l_forearm", "l_hand"]])
    doc = track(tr, [before] * 12)
    assert doc["joints_done"] == 2 and {m["joint"] for m in doc["missing"]} == {"l_forearm"}
    # The wrist moves: the tree re-links the elbow to the forearm; the wrist is a new joint.
    after = fit([joint("l_upper_arm", "pelvis"), joint("l_forearm", "l_upper_arm", err_mm=(30, 1, 1), hinge=True),
                 joint("l_hand", "l_forearm", err_mm=(None, 20, 9), determined=False)])
    doc = tr.add_fit(after, 1.2).to_dict()
    assert doc["joints_done"] == 2  # the elbow kept its done, now under the forearm's name
    by = {j["joint"]: j for j in doc["joint_progress"]}
    assert by["l_forearm"]["done"] and not by["l_hand"]["done"]
    assert by["l_hand"]["undone"]["reason"] == "tree" and "left forearm" in by["l_hand"]["why"]


def test_a_child_that_fits_two_parents_is_not_counted_until_the_tree_settles():
    # (The upper arm is a sensor of the fit too: a §5 object names every body its tree joins.)
    f = fit([joint("l_hand", "l_upper_arm"), joint("l_upper_arm", "pelvis"), joint("l_forearm", "l_upper_arm")],
            ambiguous=[{"child": "l_hand", "parents": ["l_upper_arm", "l_forearm"], "note": "fits equally well to each"}])
    (m,) = progress_of(f, TARGET).to_dict()["missing"]
    assert m["state"] == "unsettled" and "left upper arm and the left forearm" in m["why"]


@pytest.fixture(scope="module")
def kiosk_guest():
    """The service's per-fit steps on a simulated guest doing the kiosk routine, 30 fits a second."""
    # Rigid sensors: the guest must be done within the 28 s this fixture runs (docs/service.md measures the
    # kiosk's timing on rigid sensors; soft tissue slows it, see "Time to calibrate").
    perf = Performer("human", "kiosk", seed=7, rate_hz=100.0, height=1.68, sta_mm=0)
    acc = SegmentedAccumulator(perf.n_sensors)
    tracker = ProgressTracker(TARGET)
    out = []
    step = 1 / 30
    for k in range(int(28 / step)):
        times = np.arange(int(round(k * step * 100)), int(round((k + 1) * step * 100))) / 100.0
        R, t, valid = perf.poses(times)
        acc.ingest(times, R, t, valid)
        f, cal = fit_calibration(acc, perf.names)
        out.append((f, tracker.add_fit(cal, float(times[-1])).to_dict()))  # the typed fit, as the service
        if out[-1][1]["done"]:
            break
    return perf, out


def test_on_the_solver_100_percent_means_every_sensors_joint_is_determined(kiosk_guest):
    perf, out = kiosk_guest
    assert out[-1][1]["done"], f"not done after {len(out) / 30:.1f} s: {out[-1][1]['missing']}"
    for f, doc in out:
        determined = {j["child"] for j in f["joints"] if j["determined"]}
        everyone = set(f["sensors"]) - {f["root"]}
        assert doc["percent"] == math.floor(round(doc["progress"] * 100, 6))
        if doc["percent"] == 100:
            assert everyone <= determined  # the issue: never 100 % while any joint is undetermined
        # Whatever is not done is named, and nothing done is.
        assert {m["joint"] for m in doc["missing"]} == {j["joint"] for j in doc["joint_progress"] if not j["done"]}
    # No flapping on a clean take: the figure only goes up.
    values = [doc["progress"] for _, doc in out]
    assert all(b >= a for a, b in zip(values, values[1:]))


def test_a_performer_standing_still_is_never_calibrated():
    perf = Performer("human", "idle", seed=2, rate_hz=100.0)
    acc = SegmentedAccumulator(perf.n_sensors)
    times = np.arange(0, 1500) / 100.0
    R, t, valid = perf.poses(times)
    acc.ingest(times, R, t, valid)
    doc = progress_of(fit_calibration(acc, perf.names)[0], TARGET).to_dict()
    # design.md §3a: standing still determines no joint, so nothing is calibrated and every joint is named.
    assert doc["progress"] == 0.0 and not doc["done"] and len(doc["missing"]) == perf.n_sensors - 1


def test_all_calibrated_but_waiting_for_one_fit_still_names_what_is_missing():
    # Every joint has been done once (latched), then the newest fit leaves one just short of the target:
    # not done yet, and `missing` must say which one, or a kiosk has no instruction to show.
    tracker = ProgressTracker(TARGET, confirm_s=0.0)
    both = [joint("l_thigh", "pelvis"), joint("r_thigh", "pelvis")]
    tracker.add_fit(fit([joint("l_thigh", "pelvis"), joint("r_thigh", "pelvis", err_mm=(6.0, 1.0, 1.0))]), 1.0)
    tracker.add_fit(fit([joint("l_thigh", "pelvis", err_mm=(6.0, 1.0, 1.0)), both[1]]), 2.0)
    doc = tracker.latest.to_dict()
    assert doc["joints_done"] == 1 and not doc["done"] and doc["percent"] < 100
    assert not all(j["done"] for j in doc["joint_progress"])
    assert [m["joint"] for m in doc["missing"]] == ["l_thigh"] and "waiting for a fit" in doc["missing"][0]["why"]
    assert tracker.add_fit(fit(both), 3.0).to_dict()["done"]
