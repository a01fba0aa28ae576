"""A session's live calibration (solver/live.py), driven as the service's pipeline drives it: reader-time
`Frames` chunks in, a refit of `fit_input` every 1/30 s of session time, typed updates out. What it holds:
slips come back as typed events on the right sensor and undo progress; every frame reaches the accumulator
exactly once (one feeder), with and without the slip watch; a fitted tree is watched only once it has
settled; the residual samples match the residuals worked out directly from the poses; a failing slip watch
is reported once and loses no frame. The service's own slip and kiosk tests hold the same object over HTTP.
"""

from __future__ import annotations

import numpy as np
import pytest

from flockcal.frames import Frames
from flockcal.simulator.performer import Performer
from flockcal.solver.live import TREE_SETTLE_S, JointResiduals, LiveCalibration, LiveUpdate
from flockcal.solver.progress import Progress, profile
from flockcal.solver.slippage import SlipEvent
from flockcal.solver.solve import solve
from residuals import joint_residuals

RATE = 100.0
T0 = 5000.0  # reader clock of the first frame: the session clock starts there


def performer(slip: str | None = None, at: float = 9.0) -> Performer:
    perf = Performer("human", routine="walk", seed=3, noise="tracker", rate_hz=RATE, seconds=60)
    if slip:
        perf.inject_slip(slip, 0.02, at_time=at)
    return perf


def given_tree(perf: Performer) -> dict:
    return {perf.names[i]: perf.names[int(p)] for i, p in enumerate(perf.model.parent) if p >= 0}


def drive(live: LiveCalibration, perf: Performer, seconds: float, chunk: int = 3, fit: bool = True):
    """Feed `seconds` of the performer in `chunk`-frame pieces, refitting every 1/30 s as the fit thread
    would (on the accumulator copy, its result folded in at the next chunk). Returns every update."""
    updates: list[LiveUpdate] = []
    next_fit = 0.0
    n = int(round(seconds * RATE))
    for a in range(0, n, chunk):
        times = np.arange(a, min(a + chunk, n)) / RATE
        R, t, valid = perf.poses(times)
        updates.append(live.add_frames(Frames(T0 + times, R, t, valid)))
        if fit and live.time_s >= next_fit and live.fit_due:
            job = live.fit_input()
            cal = solve(job.acc, perf.names, live.hierarchy, live.root, tolerance=live.profile.tolerance_m)
            updates.append(live.add_fit(cal, job.time_s, job.epoch))
            next_fit += 1 / 30
    updates.append(live.finish())
    return updates


def live_for(perf: Performer, hierarchy: dict | None = None, detect_slips: bool = True) -> LiveCalibration:
    return LiveCalibration(perf.names, RATE, profile("stage", 0.005), hierarchy=hierarchy,
                           root=None if hierarchy is None else "pelvis", detect_slips=detect_slips)


def test_a_slip_comes_back_typed_and_moves_the_epoch():
    # A 2 cm slip of the right shin at 9 s of a walk, a given tree (watched from the first fit): one typed
    # SlipEvent on the shin, its onset within 0.1 s and found within docs/slippage.md's 0.5 s, the slip
    # epoch moved on (fits begun before it cannot count the shin's joints) and the tracker told.
    perf = performer(slip="r_shin")
    live = live_for(perf, given_tree(perf))
    updates = drive(live, perf, 12.0)
    events = [e for u in updates for e in u.events]
    assert [type(e) for e in events] == [SlipEvent] and events[0].sensor == "r_shin", events
    assert abs(events[0].time_s - 9.0) <= 0.1 and 0 < events[0].detected_s - 9.0 <= 0.5, events
    assert live.slip_epoch == 1
    assert live.tracker.sensors["r_shin"].slipped == 1
    # The slip's update carries the progress worked out again on the newest fit, typed.
    slip_update = next(u for u in updates if u.events)
    assert isinstance(slip_update.progress, Progress)
    assert isinstance(live.progress, Progress)


@pytest.mark.parametrize("detect_slips", [True, False])
def test_every_frame_reaches_the_accumulator_once(detect_slips):
    # One feeder: the slip watch when slips are watched (it holds a micro-batch's remainder until the next
    # chunk or the end), else add_frames itself. After `finish`, the accumulator has counted each frame
    # exactly once, whatever the chunk sizes (7 frames: not a whole micro-batch of 3 at 100 Hz).
    perf = performer()
    live = live_for(perf, given_tree(perf), detect_slips=detect_slips)
    drive(live, perf, 6.0, chunk=7)
    assert live.received == 600
    assert live.frames == 600
    assert live.acc.whole_take.frames == 600


def test_a_fitted_tree_is_watched_once_it_has_settled():
    # Automatic topology: the fits' tree goes to the slip watch only once it has stayed the fits' tree for
    # TREE_SETTLE_S of session time; a given tree at once.
    perf = performer()
    live = live_for(perf)
    drive(live, perf, 4.0, fit=False)
    job = live.fit_input()
    cal = solve(job.acc, perf.names, tolerance=0.005)
    live.add_fit(cal, 4.0, 0)
    assert live.watch.joints is None
    live.add_fit(cal, 4.0 + TREE_SETTLE_S / 2, 0)
    assert live.watch.joints is None
    live.add_fit(cal, 4.0 + TREE_SETTLE_S, 0)
    pairs, _, _ = cal.joint_arrays()
    assert {tuple(r) for r in live.watch.joints.tolist()} == {tuple(r) for r in pairs.tolist()}

    given = live_for(perf, given_tree(perf))
    drive(given, perf, 1.0, fit=False)
    given.add_fit(solve(given.fit_input().acc, perf.names, given_tree(perf), "pelvis"), 1.0, 0)
    assert given.watch.joints is not None


@pytest.mark.parametrize("chunk", [3, 60])
def test_residual_samples_match_the_poses(chunk):
    # Each sample is the rms of each joint's residual against the newest fit, over the frames since the
    # previous sample up to the first frame at or after a boundary of 50 ms of session time (docs/server.md:
    # 20 a second): worked out here from the poses with the tests' own residual function (tests/residuals.py),
    # sample by sample. Handed over in the reader's 3-frame pieces, and in 0.6 s pieces (a loaded machine's:
    # one sample per hand-over thinned the series to 2 a second there). A 0.3 s gap without frames gives one
    # sample, not six.
    perf = performer()
    live = live_for(perf, given_tree(perf), detect_slips=False)
    drive(live, perf, 6.0, fit=False)
    cal = solve(live.fit_input().acc, perf.names, given_tree(perf), "pelvis")
    live.add_fit(cal, live.time_s, 0)
    # 2 s more, off the 50 ms grid by a quarter of a frame (no frame time sits on a boundary), a gap inside
    steps = np.arange(200) / RATE
    every = live.time_s + 0.0125 + np.where(steps < 1.0, steps, steps + 0.3)
    samples: list[JointResiduals] = []
    for a in range(0, len(every), chunk):
        times = every[a:a + chunk]
        samples += live.add_frames(Frames(T0 + times, *perf.poses(times))).residuals
    samples += live.finish().residuals
    # The oracle: for each boundary k * 50 ms the frames cross, the first frame at or after it; the last frame
    # closes the final sample (the session's end).
    grid = np.arange(np.ceil(every[0] / 0.05), np.floor(every[-1] / 0.05) + 1) * 0.05
    closing = np.unique(np.append(np.searchsorted(every, grid), len(every) - 1))
    times = np.array([s.time_s for s in samples])
    np.testing.assert_allclose(times, every[closing], atol=1e-9)
    # 45 boundaries (6.05 … 8.25 s), one sample for the 7 in the gap, and the session's end (8.29 s)
    assert len(samples) == 45 - 6 + 1
    pairs, c, l = cal.joint_arrays()
    R, t, valid = perf.poses(every)
    e2 = np.sum(joint_residuals(R, t, c, l, pairs, valid) ** 2, axis=-1)  # (n, p) squared, NaN where invalid
    lo = every[0] - 0.005
    for s in samples:
        assert s.joints == samples[0].joints
        inside = (every > lo + 1e-6) & (every <= s.time_s + 1e-6)
        np.testing.assert_allclose(s.rms_m, np.sqrt(np.nanmean(e2[inside], axis=0)), rtol=1e-9, atol=1e-12)
        lo = s.time_s
    assert lo == pytest.approx(every[-1], abs=1e-6)  # the last sample ends on the last frame


def test_frames_at_the_last_samples_instant_give_no_second_sample_at_that_time():
    # A loaded reader clamps late, back-dated frames to the time of the frame before them (drivers/assembly.py):
    # frames after a sample's closing frame at its very time. The session's end (and a new tree) flushed them
    # as a sample of their own at that time; two samples at one time made a page of /residuals (since=,
    # exclusive) skip one. What was tried: a second of frames, then three at the last frame's time, finish.
    perf = performer()
    live = live_for(perf, given_tree(perf), detect_slips=False)
    drive(live, perf, 6.0, fit=False)
    live.add_fit(solve(live.fit_input().acc, perf.names, given_tree(perf), "pelvis"), live.time_s, 0)
    every = live.time_s + 0.0125 + np.arange(100) / RATE
    every[-1] = every[-2] + 0.0375  # the last frame just past a boundary: it closes a sample
    samples = live.add_frames(Frames(T0 + every, *perf.poses(every))).residuals
    again = np.full(3, every[-1])
    samples += live.add_frames(Frames(T0 + again, *perf.poses(again))).residuals
    samples += live.finish().residuals
    times = np.array([s.time_s for s in samples])
    assert times[-1] == pytest.approx(every[-1]) and np.all(np.diff(times) > 0), times


def test_a_failing_slip_watch_is_reported_once_and_loses_no_frame():
    # A monitor that raises (what was tried: its add_frames replaced by one that raises) stops the watch for
    # good: the update of that step carries the exception once, later ones none, and every frame still
    # reaches the accumulator.
    perf = performer()
    live = live_for(perf, given_tree(perf))
    drive(live, perf, 6.0, chunk=5)
    assert live.watch.monitor is not None

    def broken(*args, **kwargs):
        raise FloatingPointError("broken monitor")

    live.watch.monitor.add_frames = broken
    times = 6.0 + np.arange(50) / RATE
    first = live.add_frames(Frames(T0 + times, *perf.poses(times)))
    assert isinstance(first.failure, FloatingPointError)
    times = 6.5 + np.arange(50) / RATE
    second = live.add_frames(Frames(T0 + times, *perf.poses(times)))
    assert second.failure is None and not second.events
    live.finish()
    assert live.frames == live.received == 700
