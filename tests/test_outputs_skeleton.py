"""Skeleton file and known-skeleton fit (issue 8, part 2): a saved skeleton fixes the topology and the
bones for the same performer's next take, only the sensor placements move; bad files are refused."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flockcal.cli import main
from flockcal.exports.skeleton import (FORMAT, VERSION, SkeletonError, load_skeleton, parse_skeleton, skeleton_dict,
                                      write_skeleton)
from flockcal.solver.known_skeleton import fit_saved
from flockcal.simulator.body import human
from flockcal.simulator.take import simulate
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate
from flockcal.takes import make_take, save_take


def accumulate(take) -> GramAccumulator:
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    return acc


def bone_map(d: dict) -> dict:
    return {frozenset((b["from_joint"], b["to_joint"])): b["length_m"] for b in d["bones"]}


@pytest.fixture(scope="module")
def performer(tmp_path_factory):
    """One performer, two takes: the second with every sensor taken off and put back ~2 cm, ~10° away."""
    first_model = human(seed=0)
    rng = np.random.default_rng(5)
    second_model = replace(
        first_model,
        sensor_offset=first_model.sensor_offset + rng.normal(0, 0.02, first_model.sensor_offset.shape),
        sensor_rotation=Rotation.from_rotvec(rng.normal(0, 0.2, (first_model.m, 3))).as_matrix()
        @ first_model.sensor_rotation,
    )
    # Rigid sensors: the test holds fitted placements to the truth's, which are where the sensors sit
    # at rest; soft tissue would carry them about that by centimetres.
    take1, truth1 = simulate(first_model, "exercise", seconds=30, seed=1, birds=None, sta_mm=0)
    take2, truth2 = simulate(second_model, "walk", seconds=20, seed=2, birds=None, sta_mm=0)
    cal1 = calibrate(accumulate(take1), names=list(take1.names))
    folder = tmp_path_factory.mktemp("skeleton")
    path = folder / "performer.json"
    write_skeleton(path, cal1, {"take": "first.npz", "frames": take1.n_frames, "rate_hz": take1.rate_hz})
    return {"take1": take1, "take2": take2, "truth2": truth2, "cal1": cal1.to_dict(), "path": path, "folder": folder}


def test_saved_skeleton_fixes_topology_and_gives_first_takes_bones_on_second_take(performer):
    skeleton = load_skeleton(performer["path"])
    take2 = performer["take2"]
    fit = fit_saved(skeleton, accumulate(take2), take2.names).to_dict()
    first = performer["cal1"]
    assert fit["parent"] == first["parent"] and fit["root"] == first["root"]
    saved, now = bone_map(first), bone_map(fit)
    assert saved.keys() == now.keys()
    assert max(abs(saved[k] - now[k]) for k in saved) < 1e-9
    # Placements follow the second take: away from hinge axes (along which no take locates a joint)
    # the fitted joint centres sit on take 2's truth, where the saved ones are centimetres off.
    # The fitted tree may hang from another root than the simulator's, so match joints by their two
    # bodies and compare each joint centre in the fitted child's frame.
    truth = {}
    for j in performer["truth2"]["joints"]:
        truth[(j["child"], j["parent"])] = (np.array(j["c"]), j["hinge"])
        truth[(j["parent"], j["child"])] = (np.array(j["l"]), j["hinge"])
    shared = [j for j in fit["joints"] if (j["child"], j["parent"]) in truth]
    assert len(shared) >= len(fit["joints"]) - 2
    balls = [j for j in shared if not truth[(j["child"], j["parent"])][1]]
    old = {j["child"]: np.array(j["c"]) for j in first["joints"]}
    err_new = np.median([np.linalg.norm(np.array(j["c"]) - truth[(j["child"], j["parent"])][0]) for j in balls])
    err_old = np.median([np.linalg.norm(old[j["child"]] - truth[(j["child"], j["parent"])][0]) for j in balls])
    assert err_new < 0.003 < 0.01 < err_old


def test_saved_skeleton_fits_a_take_whose_sensors_come_in_another_order(performer):
    take2 = performer["take2"]
    order = np.arange(take2.n_sensors)[::-1]
    shuffled = make_take(
        take2.rotations[:, order], take2.positions[:, order], [take2.names[i] for i in order], take2.rate_hz,
        valid=take2.valid[:, order],
    )  # fmt: skip
    skeleton = load_skeleton(performer["path"])
    a = fit_saved(skeleton, accumulate(take2), take2.names).to_dict()
    b = fit_saved(skeleton, accumulate(shuffled), shuffled.names).to_dict()
    assert a["parent"] == b["parent"]
    ca = {j["child"]: j["c"] for j in a["joints"]}
    # The same up to where the Gauss–Newton stops: a hinge's free fit leaves out its least-turned direction,
    # whose eigenvector carries the rounding of the two orders' sums over a small eigenvalue gap, and the
    # fit does not move a joint along its hinge axis after Procrustes (up to 1e-5 m seen). 0.1 mm: nothing
    # a bone or a placement shows.
    for j in b["joints"]:
        np.testing.assert_allclose(j["c"], ca[j["child"]], atol=1e-4)


def test_skeleton_file_carries_version_source_placements_and_round_trips(performer):
    data = json.loads(performer["path"].read_text())
    assert data["format"] == FORMAT and data["version"] == VERSION and data["units"] == "m"
    assert data["source"]["take"] == "first.npz" and data["source"]["frames"] == performer["take1"].n_frames
    first = performer["cal1"]
    assert {p["sensor"] for p in data["placements"]} == set(first["sensors"])
    assert all("hinge" in j and "c_stderr_m" in j for j in data["joints"])
    assert sum(len(b["joints"]) for b in data["bodies"]) == 2 * len(first["parent"])
    skeleton = parse_skeleton(json.dumps(data))
    assert skeleton.hierarchy == first["parent"] and skeleton.root == first["root"]
    for j in first["joints"]:
        i = skeleton.names.index(j["child"])
        np.testing.assert_allclose(skeleton.articulation.c[i], j["c"], rtol=0, atol=1e-15)
        np.testing.assert_allclose(skeleton.articulation.l[i], j["l"], rtol=0, atol=1e-15)


def test_a_result_whose_bones_disagree_with_its_centres_still_gives_a_whole_file(performer):
    """A session result stored before the slip refit measured bones between its own centres (solver/segments.py)
    holds a forearm bone 2 mm off the elbow and wrist it lists: its file gives the centres' length and loads
    back; the bones it leaves out (undetermined ends) stay out, and their standard errors stay."""
    stored = json.loads(json.dumps(performer["cal1"]))
    bone = next(b for b in stored["bones"] if b["body"] == "l_forearm")
    true_length, bone["length_m"] = bone["length_m"], bone["length_m"] + 0.002
    data = skeleton_dict(stored, take=performer["take1"])
    assert [(b["body"], b["from_joint"], b["to_joint"], b["stderr_m"]) for b in data["bones"]] == \
        [(b["body"], b["from_joint"], b["to_joint"], b["stderr_m"]) for b in performer["cal1"]["bones"]]
    (got,) = [b["length_m"] for b in data["bones"] if b["body"] == "l_forearm"]
    assert got == pytest.approx(true_length, abs=1e-12)
    parse_skeleton(json.dumps(data))


def test_skeleton_for_other_sensors_is_refused(performer):
    # Tried: the saved skeleton against a take whose sensor "head" was renamed "helmet".
    skeleton = load_skeleton(performer["path"])
    names = ["helmet" if n == "head" else n for n in performer["take2"].names]
    with pytest.raises(SkeletonError, match="helmet"):
        skeleton.check_names(names)


def _edit(data: dict, how: str) -> str:
    d = json.loads(json.dumps(data))
    if how == "not json":
        return "{ this is not json"
    if how == "other format":
        d["format"] = "something-else"
    elif how == "newer version":
        d["version"] = VERSION + 1
    elif how == "bone edited":
        d["bones"][0]["length_m"] += 0.05
    elif how == "cycle":
        a, b = list(d["parent"].items())[0]
        d["parent"][b] = a  # the parent of a's parent is a: no longer a tree
    elif how == "bad vector":
        d["joints"][0]["c"] = [0.1, "x", 0.2]
    elif how == "unknown sensor":
        d["parent"]["tail"] = d["root"]
    return json.dumps(d)


@pytest.mark.parametrize(
    "how, message",
    [
        ("not json", "not valid JSON"),
        ("other format", "not a flockcal skeleton"),
        ("newer version", "newer"),
        ("bone edited", "edited inconsistently"),
        ("cycle", "root|connected|parent"),
        ("bad vector", "3 numbers"),
        ("unknown sensor", "tail"),
    ],
)
def test_bad_skeleton_file_is_refused_with_a_clear_error(performer, how, message):
    # Tried: the saved file damaged in the way `how` names.
    data = json.loads(performer["path"].read_text())
    with pytest.raises(SkeletonError, match=message):
        parse_skeleton(_edit(data, how), origin="edited.json")


def test_commands_save_a_skeleton_and_export_the_next_take_with_it(performer, capsys):
    folder = performer["folder"]
    first, second = folder / "first.npz", folder / "second.npz"
    save_take(first, performer["take1"])
    save_take(second, performer["take2"])
    assert main(["skeleton", str(first), "-o", str(folder / "cli.json")]) == 0
    saved = load_skeleton(folder / "cli.json")
    assert main(["export-bvh", str(second), "--skeleton", str(folder / "cli.json"), "-o", str(folder / "next.bvh")]) == 0
    text = (folder / "next.bvh").read_text()
    # The saved tree hangs from the hips it was fitted with (issue 47), which the BVH names as a humanoid's.
    assert saved.root == "pelvis" and text.startswith("HIERARCHY") and "ROOT Hips" in text
    # Tried: a skeleton file that is not one; the command says so on one line and exits 2.
    (folder / "junk.json").write_text("[]")
    capsys.readouterr()
    assert main(["report", str(second), "--skeleton", str(folder / "junk.json"), "-o", str(folder / "r.html")]) == 2
    err = capsys.readouterr().err.strip()
    assert "junk.json" in err and len(err.splitlines()) == 1


def test_rigidly_attached_sensor_is_saved_at_its_sensor_and_refits():
    from flockcal.exports.skeleton import skeleton_bytes

    take, _ = simulate("pair", "walk", seconds=4, rate_hz=50, seed=2)
    acc = accumulate(take)
    cal = calibrate(acc, names=list(take.names))
    # Tried: saving a calibration whose rigid member has no joint without giving the frames to place it.
    with pytest.raises(SkeletonError, match="sensor_b"):
        skeleton_bytes(cal)
    skeleton = parse_skeleton(skeleton_bytes(cal, take=take))
    joint = next(j for j in skeleton.data["joints"] if j["child"] == "sensor_b")
    assert joint["rigid"] and joint["c"] == [0.0, 0.0, 0.0]
    # l is sensor_b's origin in sensor_a's frame: its length is the pair's distance (0.565 m).
    assert np.linalg.norm(joint["l"]) == pytest.approx(0.565, abs=0.01)
    refit = fit_saved(skeleton, acc, take.names).to_dict()
    assert refit["parent"] == {"sensor_b": "sensor_a"}


def test_live_refresh_from_the_previous_fit_lands_on_the_same_placements(performer):
    skeleton = load_skeleton(performer["path"])
    take2 = performer["take2"]
    half = take2.n_frames // 2
    acc = GramAccumulator(take2.n_sensors)
    acc.add_poses(take2.rotations[:half], take2.positions[:half], take2.valid[:half])
    earlier = fit_saved(skeleton, acc, take2.names)
    acc.add_poses(take2.rotations[half:], take2.positions[half:], take2.valid[half:])
    cold = fit_saved(skeleton, acc, take2.names)
    warm = fit_saved(skeleton, acc, take2.names, previous=earlier)
    # Same least-squares optimum; placements agree to well under a millimetre (a hinge joint's position
    # along its axis is free, so the two starts need not agree there exactly).
    assert np.nansum(warm.rms) == pytest.approx(np.nansum(cold.rms), rel=1e-6)
    np.testing.assert_allclose(warm.articulation.c, cold.articulation.c, atol=1e-3)
    np.testing.assert_allclose(warm.articulation.l, cold.articulation.l, atol=1e-3)


def test_rms_free_says_whether_the_saved_skeleton_still_fits(performer):
    # docs/outputs.md: compare each joint's rms_m with rms_free_m (the same joint fitted freely); a much
    # larger constrained rms says the skeleton no longer fits. Tried: the saved performer's second take
    # (sensors re-placed, same bones) and a take of another, shorter performer fitted with the same file.
    from plain_lsq import plain_take_fit

    skeleton = load_skeleton(performer["path"])
    same = performer["take2"]
    other, _ = simulate(human(height=1.55, seed=7), "walk", seconds=20, seed=2, birds=None, sta_mm=0)
    ratios = {}
    for name, take in (("same", same), ("other", other)):
        fit = fit_saved(skeleton, accumulate(take), take.names).to_dict()
        assert fit["known_skeleton"] is True
        for j in fit["joints"]:
            # rms_free_m is the free fit of that joint: textbook least squares on the take's frames agrees.
            assert j["rms_free_m"] == pytest.approx(plain_take_fit(take, j["child"], j["parent"]).rms, rel=0.02)
            # A constrained fit cannot fit better than free, except by the little the free fit gives up
            # where it leaves an unexercised direction out (measured: 1e-4 of the rms).
            assert j["rms_m"] >= j["rms_free_m"] * (1 - 1e-3)
        ratios[name] = np.array([j["rms_m"] / j["rms_free_m"] for j in fit["joints"]])
    # The same performer: the skeleton fits as well as a free fit (measured: every ratio 1.00).
    assert ratios["same"].max() < 1.05
    # 20 cm shorter: several joints fit clearly worse than free (measured: up to 2.2×, four above 1.4×).
    assert ratios["other"].max() > 1.8 and (ratios["other"] > 1.3).sum() >= 3
