"""The live fit's §5 JSON (`fit_calibration`, what the fit worker runs) is JSON-safe as the solver builds it
(no NaN or infinity, no numpy scalars), so the live refit (~30×/s) returns it without a second walk; NaN in
the fit arrays is null at the same places."""

import json
import math

import numpy as np
import pytest

from flockcal.server.fitting import fit_calibration, json_safe

from flockcal.solver.segments import SegmentedAccumulator

from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate
from synthetic import articulated

DEAD = 4  # never valid: every pair with it has no data and fits to NaN


@pytest.fixture(scope="module")
def take():
    d = articulated(m=6, n=600, seed=5, joint_types=["root", "ball", "hinge", "rigid", "ball", "ball"], dropout=0.05)
    d.valid[:, DEAD] = False
    return d


def _fed(d, segmented: bool):
    acc = (SegmentedAccumulator(d.n_sensors) if segmented else GramAccumulator(d.n_sensors))
    times = np.arange(len(d.rotations)) / d.rate_hz
    for a in range(0, len(times), 7):  # micro-batches, as the live stream gives
        acc.ingest(times[a:a + 7], d.rotations[a:a + 7], d.positions[a:a + 7], d.valid[a:a + 7])
    return acc, times


def _assert_plain(x, path="fit"):
    """Containers are dicts (str keys) and lists; leaves are str, int, bool, None or a finite Python float."""
    if type(x) is dict:
        for k, v in x.items():
            assert type(k) is str, f"{path}: key {k!r}"
            _assert_plain(v, f"{path}.{k}")
    elif type(x) is list:
        for i, v in enumerate(x):
            _assert_plain(v, f"{path}[{i}]")
    else:
        assert type(x) in (str, int, bool, float, type(None)), f"{path}: {type(x).__name__} {x!r}"
        assert type(x) is not float or math.isfinite(x), f"{path}: {x!r}"


@pytest.mark.parametrize("segmented", [False, True])
@pytest.mark.parametrize("given", [False, True])
def test_live_fit_dict_is_json_safe_as_built_with_no_data_pairs(take, segmented, given):
    acc, times = _fed(take, segmented)
    if segmented:
        acc.start_segment(2, times[len(times) // 2])  # a slip: sensor 2's joints refit on the frames since
    fit = fit_calibration(acc.copy(), take.names, hierarchy=take.parent if given else None)[0]
    json.dumps(fit, allow_nan=False)
    _assert_plain(fit)
    assert json_safe(fit) == fit  # the walk the live path no longer makes would change nothing
    dead = [j for j in fit["joints"] if take.names[DEAD] in (j["child"], j["parent"])]
    assert dead and all(j["c"] == [None] * 3 and j["rms_m"] is None for j in dead)
    if segmented:
        assert any("segment_start_s" in j for j in fit["joints"])


def test_to_dict_turns_exactly_the_non_finite_values_into_null(take):
    acc, _ = _fed(take, False)
    cal = calibrate(acc, names=take.names)
    fit = cal.to_dict()

    def want(a):
        return [float(v) if np.isfinite(v) else None for v in np.ravel(a)]

    j = cal.joints
    for k, e in enumerate(fit["joints"]):
        assert (e["child"], e["parent"]) == (take.names[j.pairs[k, 0]], take.names[j.pairs[k, 1]])
        assert e["c"] == want(j.c[k]) and e["l"] == want(j.l[k]) and e["coverage"] == want(j.coverage[k])
        assert e["singular_values"] == want(j.singular_values[k])
        assert [e["rms_m"], e["epsilon"], e["c_stderr_m"], e["l_stderr_m"]] == want(
            [j.rms[k], j.epsilon[k], j.c_stderr[k], j.l_stderr[k]])
        assert e["hinge"] is bool(j.hinge[k])
        assert e["axis_child"] == (want(j.axis_i[k]) if j.hinge[k] else None)
    assert [[b["length_m"], b["stderr_m"]] for b in fit["bones"]] == [
        want([L, s]) for L, s in zip(cal.bones.length, cal.bones.stderr)]
    assert any(e["c"] == [None] * 3 for e in fit["joints"])
