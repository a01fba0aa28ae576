"""The humanoid's segments through a fit (solver/humanoid_pose.py), what the VRPN and VMC streams send, on a
simulated performer's exact poses fitted with the solver: consecutive segments are the fitted bone apart
whatever body the fit's tree hangs from, and the VMC bones (server/vmc.py), chained from the hips in Unity's
left-handed frame as a receiver chains them, land on the same points mirrored.

The oracle is the fit's own report (its `bones`, and its joint centres for the hips' centre), not the rig's
code; the mapping of simulator bodies to humanoid bones is this file's own table.
"""

from __future__ import annotations

import numpy as np
import pytest

from flockcal.simulator.performer import Performer
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate
from flockcal.solver.humanoid import find_humanoid, proximal_points
from flockcal.solver.humanoid_pose import humanoid_rig, rooted_at
from flockcal.solver.reconstruct import articulation

# The simulator's bodies and the humanoid bone each is, in the VRPN sensor order of issue 47.
BODY_OF = ["pelvis", "abdomen", "chest", "head", "l_upper_arm", "l_forearm", "l_hand", "r_upper_arm",
           "r_forearm", "r_hand", "l_thigh", "l_shin", "l_foot", "r_thigh", "r_shin", "r_foot"]
TREE = {"abdomen": "pelvis", "chest": "abdomen", "head": "chest", "l_upper_arm": "chest", "l_forearm": "l_upper_arm",
        "l_hand": "l_forearm", "r_upper_arm": "chest", "r_forearm": "r_upper_arm", "r_hand": "r_forearm",
        "l_thigh": "pelvis", "l_shin": "l_thigh", "l_foot": "l_shin", "r_thigh": "pelvis", "r_shin": "r_thigh",
        "r_foot": "r_shin"}
# Sensor k's parent bone's sensor: the pairs a bone apart.
PARENT_BONE = {1: 0, 2: 1, 3: 2, 4: 2, 5: 4, 6: 5, 7: 2, 8: 7, 9: 8, 10: 0, 11: 10, 12: 11, 13: 0, 14: 13, 15: 14}
EXACT_M = 1e-9  # exact poses through the fit: only rounding separates the rig's points from the fit's


def hung_from(tree: dict, root: str) -> dict:
    """The same undirected tree as {child: parent} hanging from `root`."""
    edges = {(c, p) for c, p in tree.items()} | {(p, c) for c, p in tree.items()}
    out, todo = {}, [root]
    while todo:
        at = todo.pop()
        for a, b in edges:
            if a == at and b not in out and b != root:
                out[b] = at
                todo.append(b)
    return out


@pytest.fixture(scope="module")
def take():
    p = Performer("human", "exercise", seed=3, rate_hz=60)
    t = np.arange(0, 30, 1 / 60)
    R, x = p.exact_poses(t)
    acc = GramAccumulator(p.n_sensors)
    acc.add_poses(R, x)
    return p.names, R, x, acc


def fit(take, root: str):
    names, R, x, acc = take
    cal = calibrate(acc, hierarchy=hung_from(TREE, root), root=root, names=names)
    hum = find_humanoid(cal, R[::30], x[::30])
    assert [hum.bones[names.index(b)] for b in BODY_OF] == [
        "hips", "spine", "chest", "head", "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm",
        "rightLowerArm", "rightHand", "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg",
        "rightLowerLeg", "rightFoot"]
    return cal, hum


def fitted_bones(cal) -> dict[tuple[str, str], float]:
    """{(body, child): the distance between the body's two joint centres, its inboard one and the child's},
    in the body's frame (design.md §5's bone), for every joint of a pelvis-rooted fit, determined or not: the
    streams place them all. Where the fit reports the bone (determined joints), the two must agree."""
    pairs, c, l = cal.joint_arrays()
    at = {cal.names[ch]: (c[i], l[i]) for i, ch in enumerate(pairs[:, 0])}
    out = {(TREE[child], child): float(np.linalg.norm(at[child][1] - at[TREE[child]][0]))
           for child in TREE if TREE[child] in at}
    for body, frm, to, length in zip(cal.bones.body, cal.bones.from_joint, cal.bones.to_joint, cal.bones.length):
        if frm == body:
            assert out[(cal.names[body], cal.names[to])] == pytest.approx(length, abs=1e-12)
    return out


@pytest.mark.parametrize("root", ["pelvis", "chest", "l_hand"])
def test_consecutive_segments_are_the_fitted_bone_apart_whatever_the_root(take, root):
    names, R, x, _ = take
    cal, hum = fit(take, root)
    pos, rot = humanoid_rig(cal, hum).segments(R[::7], x[::7])
    assert pos.shape == (len(R[::7]), 16, 3)
    gap = {k: np.linalg.norm(pos[:, k] - pos[:, p], axis=1) for k, p in PARENT_BONE.items()}
    for k, g in gap.items():
        assert np.ptp(g) < EXACT_M, (BODY_OF[k], np.ptp(g))  # rigid: the same length at every frame
    # The parent body's fitted bone, from its inboard joint to the child's; from the hips' centre for the
    # bodies hanging from the hips.
    base, _ = fit(take, "pelvis")
    bones = fitted_bones(base)
    for k, p in PARENT_BONE.items():
        if p == 0:
            continue
        assert gap[k][0] == pytest.approx(bones[(BODY_OF[p], BODY_OF[k])], abs=1e-6), BODY_OF[k]
    pairs, c, l = base.joint_arrays()
    at = {base.names[ch]: (c[i], l[i]) for i, ch in enumerate(pairs[:, 0])}
    hips = (at["l_thigh"][1] + at["r_thigh"][1]) / 2
    for k in (1, 10, 13):  # the spine and both thighs start a fixed way from the hips' centre
        assert gap[k][0] == pytest.approx(np.linalg.norm(at[BODY_OF[k]][1] - hips), abs=1e-6), BODY_OF[k]


def test_segment_rotations_are_the_sensors_through_the_humanoid_frames(take):
    names, R, x, _ = take
    cal, hum = fit(take, "chest")
    _, rot = humanoid_rig(cal, hum).segments(R[:5], x[:5])
    s = [names.index(b) for b in BODY_OF]
    np.testing.assert_allclose(rot, hum.world @ R[:5][:, s] @ hum.frames[s], atol=1e-12)


def test_the_hips_segment_starts_at_the_midpoint_of_the_hip_joints(take):
    """proximal_points at a human root: the hips' centre, not the mean with the spine's joint."""
    cal, hum = fit(take, "pelvis")
    start = proximal_points(cal, hum)[cal.root]
    pairs, c, l = cal.joint_arrays()
    legs = [l[i] for i, ch in enumerate(pairs[:, 0]) if cal.names[ch] in ("l_thigh", "r_thigh")]
    np.testing.assert_allclose(start, np.mean(legs, axis=0), atol=1e-15)


def test_turning_the_tree_round_keeps_every_joint(take):
    """rooted_at: each joint is the same pair of points, only which body holds `c` changes."""
    cal, _ = fit(take, "pelvis")
    art = articulation(cal)
    turned = rooted_at(art, cal.names.index("l_hand"))
    assert turned.root == cal.names.index("l_hand")
    for j in range(art.n_bodies):
        p = art.parent[j]
        if p < 0:
            continue
        if turned.parent[j] == p:
            np.testing.assert_array_equal([turned.c[j], turned.l[j]], [art.c[j], art.l[j]])
        else:
            assert turned.parent[p] == j
            np.testing.assert_array_equal([turned.c[p], turned.l[p]], [art.l[j], art.c[j]])


def quat_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion x, y, z, w (the textbook formula; written here, not imported)."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_vmc_bones_chained_from_the_hips_in_unitys_frame_land_on_the_segments_mirrored(take):
    """A receiver sets each bone's local position and rotation and chains them from the hips (Unity's
    Transform: world = parent world · local); with Unity's x the humanoid's −x, every bone's start must come
    out where the segments put it, mirrored."""
    from flockcal.server.vmc import vmc_bones

    names, R, x, _ = take
    cal, hum = fit(take, "chest")
    rig = humanoid_rig(cal, hum)
    for f in (0, 400, 1300):
        pos, rot = rig.segments(R[f:f + 1], x[f:f + 1])
        numbers = vmc_bones(rig, pos[0], rot[0])
        world_R, world_p = {}, {}
        for k in range(16):  # parents come first in BONES order
            local_R, local_p = quat_matrix(numbers[k, 3:]), numbers[k, :3]
            if k in PARENT_BONE:
                p = PARENT_BONE[k]
                world_p[k] = world_p[p] + world_R[p] @ local_p
                world_R[k] = world_R[p] @ local_R
            else:
                world_p[k], world_R[k] = local_p, local_R
        mirror = np.diag([-1.0, 1.0, 1.0])
        for k in range(16):
            np.testing.assert_allclose(world_p[k], mirror @ pos[0, k], atol=1e-9, err_msg=BODY_OF[k])
            np.testing.assert_allclose(world_R[k], mirror @ rot[0, k] @ mirror, atol=1e-9, err_msg=BODY_OF[k])
        # A limb's local position is its parent's fitted bone.
        assert np.linalg.norm(numbers[5, :3]) == pytest.approx(np.linalg.norm(pos[0, 5] - pos[0, 4]), abs=1e-12)


def test_a_sensor_with_no_pose_yet_loses_only_its_own_subtree(take):
    """Held poses are NaN for a sensor that never sent a valid record: its bone and those below it have no
    segment; every other bone keeps its own."""
    names, R, x, _ = take
    cal, hum = fit(take, "pelvis")
    rig = humanoid_rig(cal, hum)
    R2, x2 = R[:3].copy(), x[:3].copy()
    R2[:, names.index("l_forearm")] = np.nan
    x2[:, names.index("l_forearm")] = np.nan
    pos, rot = rig.segments(R2, x2)
    whole, _ = rig.segments(R[:3], x[:3])
    lost = [BODY_OF.index(b) for b in ("l_forearm", "l_hand")]
    assert np.isnan(pos[:, lost]).all()
    kept = [k for k in range(16) if k not in lost]
    np.testing.assert_array_equal(pos[:, kept], whole[:, kept])


class _Sent:
    """What the streams' thread hands its sockets, kept: VRPN's datagrams (one frame's reports each) and VMC's
    bundles; a VRPN client connected throughout."""

    streaming = True

    def __init__(self):
        self.sent = []

    def send_reports(self, frames):
        self.sent.append([bytes(f) for f in frames])

    def send(self, data):
        self.sent.append(bytes(data))

    def status(self):
        return {}

    def close(self):
        pass


def streamed(cal, names, R, x, valid, batches_per_wake: list[list[int]]):
    """Every datagram the streams send for these frames (times 1/144 s apart) handed over in `batches_per_wake`
    (per wake-up, the sizes of its batches), a VMC bundle due every second wake-up: what `Outputs._serve` does
    when it sends, on a clock that stands still just after the last frame (so that every wake-up reads the same
    offset of the wall clock from the frames' clock, whatever the batching)."""
    import tempfile
    from pathlib import Path

    from flockcal.clock import ManualClock
    from flockcal.frames import Frames
    from flockcal.server.outputs import Outputs
    from flockcal.server.settings import Settings

    class Stopped:  # a stopped session's final fit, no session live
        pose_fit, pose_fit_id, session = cal, ("s", None), None

    clock = ManualClock(wall=1.7e9, monotonic=1000.2)
    out = Outputs(Settings(data_dir=Path(tempfile.gettempdir())), tuple(names), Stopped, clock)
    out.vrpn, out.vmc, out._eager = _Sent(), _Sent(), True
    times = 1000.0 + np.arange(len(R)) / 144
    at = 0
    for wake, sizes in enumerate(batches_per_wake):
        batches = []
        for n in sizes:
            batches.append(Frames(times[at:at + n], R[at:at + n], x[at:at + n], valid[at:at + n]))
            at += n
        due = wake % 2 == 1
        followed = out._frames(batches, due)
        if due:
            out._send_vmc(clock.monotonic(), clock.monotonic(), followed)
    out.stop()
    return out.vrpn.sent, out.vmc.sent, times + (1.7e9 - 1000.2)


def test_the_streams_send_the_same_bytes_however_the_frames_are_batched_and_they_decode_to_the_segments(take):
    """The streams take frames with every sensor valid batch by batch and others joined and held
    (reconstruct.held_poses): the same frames handed over one, two or three at a time, or with a sensor's
    record marked invalid where it held the pose it had before, must send the same datagrams byte for byte;
    each VRPN report decodes (VRPN's Format_Of_Protocol.txt: big-endian header, sensor twice, 7 doubles) to the
    rig's segment for its frame and the frame's wall time."""
    import dataclasses
    import struct

    names, R, x, _ = take
    cal, hum = fit(take, "pelvis")
    cal = dataclasses.replace(cal, humanoid=hum)
    R, x = R[:24].copy(), x[:24].copy()
    valid = np.ones((24, len(names)), dtype=bool)
    ones = streamed(cal, names, R, x, valid, [[1, 1]] * 12)
    twos = streamed(cal, names, R, x, valid, [[2]] * 12)
    threes = streamed(cal, names, R, x, valid, [[1, 2]] * 8)
    # A sensor's record invalid at frames 5 and 6 whose pose stayed frame 4's: held, it is what was sent.
    s = names.index("l_forearm")
    R[5:7, s], x[5:7, s] = R[4, s], x[4, s]
    still = streamed(cal, names, R, x, valid, [[1, 1]] * 12)
    gaps = valid.copy()
    gaps[5:7, s] = False
    R2, x2 = R.copy(), x.copy()
    R2[5:7, s], x2[5:7, s] = 0.0, 0.0  # what an invalid slot holds
    held = streamed(cal, names, R2, x2, gaps, [[1, 1]] * 12)
    assert len(ones[0]) == 12 and len(ones[1]) == 6
    assert twos[:2] == ones[:2]
    assert still[:2] == held[:2]
    reports = [d for wake in threes[0] for d in wake]
    assert [d for wake in ones[0] for d in wake] == reports
    assert len(reports) == 24 and all(len(d) == 16 * 88 for d in reports)

    rig = humanoid_rig(cal, hum)
    pos, rot = rig.segments(take[1][:24], take[2][:24])  # the frames as first sent, before the edit above
    for f, d in enumerate(reports):
        for k in range(16):
            length, sec, usec, _sender, _type, _seq, sensor, again = struct.unpack_from(">IIIiiIii", d, 88 * k)
            numbers = struct.unpack_from(">7d", d, 88 * k + 32)
            assert (length, sensor, again) == (24 + 64, k, k)
            assert abs(sec + usec * 1e-6 - ones[2][f]) < 1.5e-6
            np.testing.assert_allclose(numbers[:3], pos[f, k], atol=1e-12)
            np.testing.assert_allclose(quat_matrix(np.array(numbers[3:])), rot[f, k], atol=1e-12)
