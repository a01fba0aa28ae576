"""Residual removal and BVH export (issue 8, part 1): the BVH file, read by an independent parser,
reproduces flockcal's reconstruction, and reconstructed joints never separate while raw ones do."""

from __future__ import annotations

import numpy as np
import pytest
from bvh import Bvh
from scipy.spatial.transform import Rotation

from flockcal.exports.bvh import bvh_world, write_bvh
from flockcal.solver.reconstruct import (
    Articulation,
    ArticulationError,
    articulation,
    joint_separation,
    reconstruct,
    tree_order,
)
from flockcal.takes import make_take


def chain_take(n=120, noise=0.004, seed=3, dropouts=True):
    """An exact articulated take (random tree, random joints) plus position noise on every sensor.

    Returns the take, the exact Articulation, and the calibration dict (design.md §5 shape) for it.
    """
    rng = np.random.default_rng(seed)
    names = ["pelvis", "spine", "head", "l arm", "l fore", "r thigh"]
    parent = np.array([-1, 0, 1, 1, 3, 0])
    m = len(names)
    c = rng.normal(0, 0.15, (m, 3))
    l = rng.normal(0, 0.15, (m, 3))
    c[0] = l[0] = 0
    # Smooth, large rotations: each body turns about its own random axis at its own speed.
    tt = np.linspace(0, 4, n)
    axes = rng.normal(size=(m, 3))
    R0 = Rotation.random(m, random_state=seed).as_matrix()
    rotvec = axes[None] * (1.5 * np.sin(tt[:, None, None] * rng.uniform(0.5, 2, (1, m, 1))))
    R = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(n, m, 3, 3) @ R0
    t = np.empty((n, m, 3))
    t[:, 0] = np.stack([np.sin(tt), np.cos(tt), 1 + 0.1 * tt], axis=1)
    for j in tree_order(parent)[1:]:
        p = parent[j]
        t[:, j] = R[:, p] @ l[j] + t[:, p] - R[:, j] @ c[j]
    t_noisy = t + rng.normal(0, noise, t.shape)
    valid = np.ones((n, m), dtype=bool)
    if dropouts:
        valid[40:45, 4] = False  # a dropout on a leaf
        valid[70:72, 1] = False  # and on a mid-chain body
    take = make_take(R, t_noisy, names, 120.0, valid=valid)
    cal = {
        "sensors": names,
        "root": names[0],
        "parent": {names[j]: names[parent[j]] for j in range(m) if parent[j] >= 0},
        "joints": [
            {"child": names[j], "parent": names[parent[j]], "c": c[j].tolist(), "l": l[j].tolist()}
            for j in range(m)
            if parent[j] >= 0
        ],
    }
    return take, Articulation(tuple(names), parent, c, l, tree_order(parent)), cal


def axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """(n, 3, 3) right-handed rotations by `angle` about the X, Y or Z axis, written out by hand."""
    co, si = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(angle), np.zeros_like(angle)
    rows = {
        "X": [[one, zero, zero], [zero, co, -si], [zero, si, co]],
        "Y": [[co, zero, si], [zero, one, zero], [-si, zero, co]],
        "Z": [[co, -si, zero], [si, co, zero], [zero, zero, one]],
    }[axis]
    return np.moveaxis(np.array(rows), -1, 0)


def bvh_forward_kinematics(mocap: Bvh) -> dict[str, np.ndarray]:
    """World positions (n, 3) of every JOINT/ROOT, from the parser's offsets and channel values only."""
    frames = np.array(mocap.frames, dtype=float)
    out: dict[str, np.ndarray] = {}
    world_R: dict[str, np.ndarray] = {}
    for name in mocap.get_joints_names():
        channels = mocap.joint_channels(name)
        first = mocap.get_joint_channels_index(name)
        values = {ch: frames[:, first + k] for k, ch in enumerate(channels)}
        # BVH: the local rotation is the product of the rotation channels in the order they are listed.
        local = np.broadcast_to(np.eye(3), (len(frames), 3, 3)).copy()
        for ch in channels:
            if ch.endswith("rotation"):
                local = local @ axis_rotation(ch[0], np.radians(values[ch]))
        offset = np.array(mocap.joint_offset(name))
        parent = mocap.joint_parent(name)
        if parent is None:
            pos = offset + np.stack([values[f"{a}position"] for a in "XYZ"], axis=1)
            world_R[name] = local
        else:
            pos = out[parent.name] + world_R[parent.name] @ offset
            world_R[name] = world_R[parent.name] @ local
        out[name] = pos
    return out


@pytest.mark.parametrize("up, rest", [("-z", "first"), ("+z", "sensor"), ("+y", 17)])
def test_bvh_round_trip_through_independent_parser_reproduces_reconstruction(tmp_path, up, rest):
    take, _, cal = chain_take()
    path = tmp_path / "take.bvh"
    write_bvh(path, cal, take, up=up, rest=rest)
    mocap = Bvh(path.read_text())
    assert mocap.nframes == take.n_frames
    assert mocap.frame_time == pytest.approx(1 / 120.0, rel=1e-6)
    fk = bvh_forward_kinematics(mocap)
    rec = reconstruct(take.rotations, take.positions, articulation(cal), take.valid)
    W = bvh_world(up)
    for i, name in enumerate(take.names):
        got = fk[name.replace(" ", "_")] / 100.0 @ W  # file is centimetres in the Y-up frame
        np.testing.assert_allclose(got, rec.joint_positions[:, i], atol=1e-6, rtol=0)


def test_bvh_rest_pose_is_the_chosen_frame(tmp_path):
    take, _, cal = chain_take()
    path = tmp_path / "take.bvh"
    write_bvh(path, cal, take, rest=17)
    mocap = Bvh(path.read_text())
    frames = np.array(mocap.frames, dtype=float)
    # Every joint's rotation channels are zero at the rest frame: the file's rest pose is that pose.
    np.testing.assert_allclose(frames[17, 3:], 0.0, atol=1e-6)
    assert np.abs(frames[0, 3:]).max() > 1.0


def test_reconstructed_joints_never_separate_while_raw_separation_equals_residual():
    take, art, _ = chain_take(noise=0.004)
    rec = reconstruct(take.rotations, take.positions, art, take.valid)
    assert np.nanmax(rec.separation()) < 1e-12
    raw = joint_separation(take.rotations, take.positions, art, take.valid)
    # Raw separation is the residual e_k = R_i c + t_i − R_j l − t_j, computed here independently.
    for j in range(1, art.n_bodies):
        p = art.parent[j]
        e = (
            take.rotations[:, j] @ art.c[j] + take.positions[:, j]
            - take.rotations[:, p] @ art.l[j] - take.positions[:, p]
        )
        ok = take.valid[:, j] & take.valid[:, p]
        np.testing.assert_allclose(raw[ok, j], np.linalg.norm(e[ok], axis=1), rtol=1e-12, atol=1e-15)
        assert np.isnan(raw[~ok, j]).all()
    assert np.nanmedian(raw) > 0.003  # the raw joints do come apart by the noise level


def test_reconstruction_holds_last_valid_rotation_over_dropouts():
    take, art, _ = chain_take()
    rec = reconstruct(take.rotations, take.positions, art, take.valid)
    np.testing.assert_array_equal(rec.rotations[40:45, 4], np.broadcast_to(take.rotations[39, 4], (5, 3, 3)))
    np.testing.assert_array_equal(rec.rotations[70:72, 1], np.broadcast_to(take.rotations[69, 1], (2, 3, 3)))


def test_reconstruction_matches_exact_data_sensor_positions():
    take, art, _ = chain_take(noise=0.0, dropouts=False)
    rec = reconstruct(take.rotations, take.positions, art, take.valid)
    np.testing.assert_allclose(rec.sensor_positions, take.positions, atol=1e-12)


def test_calibration_with_other_sensor_names_is_refused():
    take, _, cal = chain_take()
    # Tried: a calibration naming a sensor ("tail") that the take does not have.
    cal["sensors"] = [*cal["sensors"][:-1], "tail"]
    cal["parent"] = {("tail" if k == "r thigh" else k): v for k, v in cal["parent"].items()}
    for joint in cal["joints"]:
        if joint["child"] == "r thigh":
            joint["child"] = "tail"
    with pytest.raises(ArticulationError, match="tail"):
        articulation(cal).reordered(take.names)


def test_parent_map_with_a_cycle_is_refused():
    # Tried: a parent map where two bodies are each other's parent (no single tree).
    with pytest.raises(ArticulationError, match="not connected"):
        tree_order(np.array([-1, 2, 1]))


@pytest.fixture(scope="module")
def fitted_human():
    """A simulated 8-sensor performer with tracker noise and dropouts, calibrated by the solver."""
    from flockcal.simulator.take import simulate
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.calibration import calibrate

    take, _ = simulate("human", "exercise", seconds=6, rate_hz=50, seed=7, birds=8, faults={"dropout": 0.01})
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    return take, calibrate(acc, names=list(take.names))


def test_fitted_take_bvh_matches_reconstruction_and_raw_separation_is_the_solvers_residual(fitted_human, tmp_path):
    from residuals import joint_residuals

    take, cal = fitted_human
    d = cal.to_dict()
    path = tmp_path / "human.bvh"
    write_bvh(path, cal, take)
    fk = bvh_forward_kinematics(Bvh(path.read_text()))
    art = articulation(cal).reordered(take.names)
    rec = reconstruct(take.rotations, take.positions, art, take.valid)
    W = bvh_world("-z")
    for i, name in enumerate(take.names):
        np.testing.assert_allclose(fk[name] / 100.0 @ W, rec.joint_positions[:, i], atol=1e-6, rtol=0)
    assert np.nanmax(rec.separation()) < 1e-12
    idx = {n: i for i, n in enumerate(take.names)}
    pairs = np.array([[idx[j["child"]], idx[j["parent"]]] for j in d["joints"]])
    e = joint_residuals(take.rotations, take.positions, [j["c"] for j in d["joints"]], [j["l"] for j in d["joints"]],
                        pairs, valid=take.valid)  # fmt: skip
    raw = joint_separation(take.rotations, take.positions, art, take.valid)[:, pairs[:, 0]]
    np.testing.assert_allclose(raw, np.linalg.norm(e, axis=-1), rtol=1e-12, atol=1e-15, equal_nan=True)
    assert np.nanmean(raw) > 1e-3  # tracker noise: the raw joints come apart by millimetres


def test_rigidly_attached_sensor_rides_on_its_parent_in_the_bvh(tmp_path):
    from flockcal.simulator.take import simulate
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.calibration import calibrate

    # The rigid pair never turns one sensor against the other: the solver reports no joint for it.
    take, _ = simulate("pair", "walk", seconds=4, rate_hz=50, seed=2)
    acc = GramAccumulator(2)
    acc.add_poses(take.rotations, take.positions, take.valid)
    cal = calibrate(acc, names=list(take.names))
    assert cal.to_dict()["joints"] == []
    path = tmp_path / "pair.bvh"
    write_bvh(path, cal, take)
    fk = bvh_forward_kinematics(Bvh(path.read_text()))
    rec = reconstruct(take.rotations, take.positions, articulation(cal), take.valid)
    np.testing.assert_allclose(fk["sensor_b"] / 100.0 @ bvh_world("-z"), rec.joint_positions[:, 1], atol=1e-6)
    # Its pivot is its own sensor, placed from the pair's mean offset: within tracker noise of the data.
    assert np.median(np.linalg.norm(rec.sensor_positions[:, 1] - take.positions[:, 1], axis=1)) < 0.01


def test_sensor_never_valid_is_refused_for_export_and_nan_for_a_live_frame():
    take, art, _ = chain_take()
    valid = take.valid.copy()
    valid[:, 3] = False  # Tried: the "l arm" sensor never gave a record in the whole take.
    with pytest.raises(ArticulationError, match="never gave a valid record"):
        reconstruct(take.rotations, take.positions, art, valid)
    rec = reconstruct(take.rotations[:1], take.positions[:1], art, valid[:1], missing="nan")
    lost = np.isnan(rec.joint_positions[0]).any(axis=1)
    assert lost.tolist() == [False, False, False, True, True, False]  # "l arm" and its child "l fore"


def test_bvh_written_a_few_frames_at_a_time_is_the_file_of_the_whole_take():
    """bvh_chunks plays a take a chunk at a time, as the service plays a session's frame log: 7-frame chunks,
    a rest frame inside a later chunk where one sensor has dropped out since the chunk before (its pose held
    across the chunk edge), and a sensor whose first record comes after the first chunk."""
    from flockcal.exports.bvh import bvh_chunks, bvh_text

    take, _, cal = chain_take()
    valid = take.valid.copy()
    valid[:10, 2] = False  # "head" starts late: frames before its first record hold that record
    take = make_take(take.rotations, take.positions, take.names, take.rate_hz, valid=valid)
    assert not take.valid[42, 4] and take.valid[39, 4]  # the rest frame 42: "l fore" held from frame 39
    for rest in ("first", 42, "sensor"):
        whole = bvh_text(cal, take, rest=rest, units="mm")
        parts = list(bvh_chunks(cal, take, rest=rest, units="mm", chunk_frames=7))
        assert len(parts) == 1 + -(-take.n_frames // 7)  # the header, then one piece per chunk
        got, want = "".join(parts).splitlines(), whole.splitlines()
        head = want.index("MOTION") + 3
        assert got[:head] == want[:head], rest  # offsets and rest frames: the same numbers
        # Rows: the same to the file's 6 decimals, ± one last digit (a chunk's arrays are smaller).
        np.testing.assert_allclose(np.loadtxt(got[head:]), np.loadtxt(want[head:]), atol=2e-6, rtol=0)
    # Tried: a sensor that never gave a record; refused by the first piece, before any text.
    valid[:, 3] = False
    pieces = bvh_chunks(cal, make_take(take.rotations, take.positions, take.names, 120.0, valid=valid), chunk_frames=7)
    with pytest.raises(ArticulationError, match="never gave a valid record"):
        next(pieces)
