"""Why the kiosk profile judges a soft-tissue guest's bones against more data of the same guest, not
against the simulated skeleton, and reads the batch-means error next to the white-noise one instead of
shrinking it (issues #21, #30; docs/service.md "Time to calibrate"): the artefact itself moves the centres
a sensor can see, and the batch-means error is about as large as the real spread between performances.
"""

from __future__ import annotations

import numpy as np

from flockcal.server.fitting import fit_calibration

from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.progress import FitFacts
from flockcal.simulator.motion import routine
from flockcal.simulator.performer import Performer

RATE = 144.0
LOOP_S = 30.0  # one whole kiosk loop: every joint's slot and the finale
TOLERANCE_M = 0.005
SEED, HEIGHT = 100, 1.8757  # the benchmark's first guest
HINGES = {"l_forearm", "r_forearm", "l_shin", "r_shin"}  # a bone ending there is measured to an axis instead


def _whole_loop(perf: Performer) -> dict:
    acc = GramAccumulator(perf.n_sensors)
    times = np.arange(int(LOOP_S * RATE)) / RATE
    for k in range(0, len(times), 2000):
        t = times[k:k + 2000]
        acc.ingest(t, *perf.poses(t))
    return fit_calibration(acc, perf.names, hierarchy=perf.truth()["parent"], tolerance=TOLERANCE_M)[0]


def _ball_bone_errors(fit: dict, truth: dict) -> list[float]:
    true = {(b["body"], b["from_joint"], b["to_joint"]): b["length_m"] for b in truth["bones"]}
    return [abs(b["length_m"] - true[(b["body"], b["from_joint"], b["to_joint"])]) for b in fit["bones"]
            if b["from_joint"] not in HINGES and b["to_joint"] not in HINGES]


def test_no_sensor_fit_reaches_the_rest_geometry_under_soft_tissue():
    # Exact poses, a whole loop, the true tree: the most any sensor-based fit of this performance can do.
    # Rigid, that is the rest geometry; with skin sliding as a function of the joint angles the fitted
    # (functional) centres move with it, so the 5 mm bone criterion fails however long the guest moves.
    rigid = Performer("human", "kiosk", seed=SEED, rate_hz=RATE, height=HEIGHT, noise=None, sta_mm=0)
    assert max(_ball_bone_errors(_whole_loop(rigid), rigid.truth())) < 1e-4
    skin = Performer("human", "kiosk", seed=SEED, rate_hz=RATE, height=HEIGHT, noise=None, sta_mm=12)
    errors = _ball_bone_errors(_whole_loop(skin), skin.truth())
    assert max(errors) > 0.005, [round(1000 * e, 1) for e in errors]  # 10.6 mm measured 2026-12-02


def test_batch_means_error_is_about_the_spread_between_performances_under_soft_tissue():
    # Holds `done` back under soft tissue, and must not be shrunk to make the kiosk figure: the same body
    # doing the routine with other phases and frequencies (motion seeds), noise-free, lands its centres
    # about one reported error apart (spread/error median 1.16–1.33 over 3 guests, 8 performances each).
    perf = Performer("human", "kiosk", seed=SEED, rate_hz=RATE, height=HEIGHT, sta_mm=12)
    error = {child: max(j.needed()) for child, j in FitFacts.of(_whole_loop(perf)).joints.items()}
    centres: dict[str, list] = {}
    for k in range(6):
        other = Performer("human", "kiosk", seed=SEED, rate_hz=RATE, height=HEIGHT, noise=None, sta_mm=12)
        other.motion = routine(other.model, "kiosk", 60.0, RATE, 1000 + k)
        for j in _whole_loop(other)["joints"]:
            centres.setdefault(j["child"], []).append(np.asarray(j["c"]))
    ratios = []
    for joint, cs in centres.items():
        if joint in HINGES:  # a hinge's centre along its axis is the min-norm rule's, not a measurement
            continue
        spread = np.sqrt(np.trace(np.cov(np.array(cs).T)))
        ratios.append(spread / error[joint])
    assert np.median(ratios) > 0.6, sorted(round(r, 2) for r in ratios)
