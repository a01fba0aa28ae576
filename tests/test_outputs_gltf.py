"""glTF 2.0 rig (issue 34, item 1): `flockcal fit --gltf` read back by readers that are not ours.

A minimal GLB reader written here from the glTF 2.0 spec (not flockcal's writer) checks the node tree
against `fit --json`, the inverse bind matrices against the nodes' own bind transforms, the keyframe
times against the take, and the joint world positions the animation gives against the same fit played
by hand from the take and against the BVH of the same run (read by the `bvh` package): within 0.1 mm,
the documented claim (docs/outputs.md), where float32 storage costs about 1e-4 mm. The Khronos
validator (node + npm gltf-validator) and assimp (Debian assimp-utils) read the file too.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bvh import Bvh

from test_outputs_bvh import bvh_forward_kinematics

FRAMES_CHECKED = 4
CLAIM_M = 1e-4  # docs/outputs.md: joint positions within 0.1 mm of the fitted skeleton's
HERE = Path(__file__).parent


def flockcal(*argv, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flockcal", *map(str, argv)], cwd=cwd, capture_output=True,
                          text=True, timeout=240)


# --- a reader from the spec (glTF 2.0 §4.4 GLB, §3.6 accessors, §3.5 node transforms) ----------------
COMPONENTS = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def read_glb(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data)
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON"
    doc = json.loads(data[20:20 + json_len])
    at = 20 + json_len
    bin_len, bin_type = struct.unpack_from("<I4s", data, at)
    assert bin_type == b"BIN\0" and at + 8 + bin_len == len(data)
    return doc, data[at + 8:at + 8 + bin_len]


def accessor(doc: dict, binary: bytes, k: int) -> np.ndarray:
    acc = doc["accessors"][k]
    view = doc["bufferViews"][acc["bufferView"]]
    assert "byteStride" not in view
    dtype = np.dtype(COMPONENTS[acc["componentType"]])
    width = WIDTH[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    out = np.frombuffer(binary, dtype=dtype, count=acc["count"] * width, offset=start)
    assert start + out.nbytes <= view.get("byteOffset", 0) + view["byteLength"]
    return out.reshape(acc["count"], width).astype(float)


def quat_matrix(q: np.ndarray) -> np.ndarray:
    """(…, 3, 3) from unit quaternions (…, 4) stored x, y, z, w (glTF's order), by the textbook formula."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def node_parents(doc: dict) -> dict[int, int]:
    return {c: k for k, node in enumerate(doc["nodes"]) for c in node.get("children", [])}


def world_positions(doc: dict, binary: bytes, frames: list[int]) -> dict[str, np.ndarray]:
    """Node origins in the scene at keyframes `frames`: each node's T·R·S from its TRS or the animation."""
    nodes = doc["nodes"]
    anim = doc["animations"][0]
    animated: dict[tuple[int, str], np.ndarray] = {}
    for ch in anim["channels"]:
        sampler = anim["samplers"][ch["sampler"]]
        animated[(ch["target"]["node"], ch["target"]["path"])] = accessor(doc, binary, sampler["output"])[frames]
    parents = node_parents(doc)
    n = len(frames)
    world: dict[int, np.ndarray] = {}

    def place(k: int) -> np.ndarray:
        if k in world:
            return world[k]
        node = nodes[k]
        T = np.tile(np.eye(4), (n, 1, 1))
        T[:, :3, 3] = animated.get((k, "translation"), np.array(node.get("translation", [0.0, 0, 0])))
        q = animated.get((k, "rotation"), np.array(node.get("rotation", [0.0, 0, 0, 1])))
        T[:, :3, :3] = quat_matrix(np.broadcast_to(q, (n, 4)))
        assert "scale" not in node and "matrix" not in node
        world[k] = (place(parents[k]) @ T) if k in parents else T
        return world[k]

    return {node["name"]: place(k)[:, :3, 3] for k, node in enumerate(nodes) if "mesh" not in node}


def sensor_nodes(doc) -> dict[str, int]:
    """{sensor name: node index} of the body nodes, read from each node's extras (a node is named by its
    humanoid bone on a human tree, by its sensor otherwise)."""
    return {node["extras"]["flockcal"]["sensor"]: k for k, node in enumerate(doc["nodes"])
            if "mesh" not in node and not node["extras"]["flockcal"].get("end_site")}


# --- one take, fitted once by the CLI --------------------------------------------------------------
@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gltf")
    sim = flockcal("simulate", "--model", "human", "--motion", "exercise", "--seconds", "8", "--rate", "50",
                   "--seed", "7", "--dropout", "0.01", "-o", "take.npz", cwd=folder)
    assert sim.returncode == 0, sim.stderr
    fit = flockcal("fit", "take.npz", "--no-slips", "--json", "--bvh", "take.bvh", cwd=folder)
    assert fit.returncode == 0, fit.stderr
    # The plain rig, rest at the take's first frame as the BVH's (fit --gltf's VRM humanoid in its T-pose:
    # tests/test_outputs_vrm.py); the same fit, so the same skeleton as the BVH.
    out = flockcal("export-gltf", "take.npz", "--rest", "first", "-o", "take.glb", cwd=folder)
    assert out.returncode == 0, out.stderr
    doc, binary = read_glb((folder / "take.glb").read_bytes())
    with np.load(folder / "take.npz") as z:
        take = {k: z[k] for k in z.files}
    return folder, json.loads(fit.stdout), doc, binary, take


def test_nodes_are_the_fitted_tree_with_its_offsets(run):
    _, fit, doc, _, _ = run
    parents = node_parents(doc)
    by_name = sensor_nodes(doc)
    sensors = fit["sensors"]
    assert set(sensors) == set(by_name)
    # A human tree: every body node carries its humanoid bone in PascalCase, the root the hips (issue 47).
    assert fit["humanoid"] is not None and fit["humanoid"][fit["root"]] == "hips"
    for sensor, k in by_name.items():
        bone = fit["humanoid"][sensor]
        assert doc["nodes"][k]["name"] == bone[0].upper() + bone[1:]
    root = by_name[fit["root"]]
    assert root not in parents and doc["skins"][0]["skeleton"] == root
    c = {j["child"]: np.array(j["c"]) for j in fit["joints"]}
    for j in fit["joints"]:
        if fit["parent"].get(j["child"]) != j["parent"]:
            continue  # a loop candidate: not in the tree
        child = doc["nodes"][by_name[j["child"]]]
        assert parents[by_name[j["child"]]] == by_name[j["parent"]]
        # The node's offset is the child's joint seen from the parent's pivot (its own joint; the sensor at
        # the root), turned into the parent's axes: its length is frame-free.
        pivot = c.get(j["parent"], np.zeros(3))
        assert np.linalg.norm(child["translation"]) == pytest.approx(np.linalg.norm(np.array(j["l"]) - pivot), abs=1e-6)
        kind = child["extras"]["flockcal"]["joint"]
        assert kind == ("hinge" if j["hinge"] else "ball" if j["determined"] else "undetermined")
    # The skinned figure hangs at the scene root (its transform is the skeleton's, spec §3.7.3).
    figure = [k for k, node in enumerate(doc["nodes"]) if "mesh" in node]
    assert len(figure) == 1 and figure[0] not in parents and doc["nodes"][figure[0]]["skin"] == 0
    assert sorted(doc["scenes"][0]["nodes"]) == sorted([root, figure[0]])


def test_inverse_bind_matrices_invert_each_joints_bind_transform(run):
    _, _, doc, binary, _ = run
    skin = doc["skins"][0]
    ibm = accessor(doc, binary, skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    parents = node_parents(doc)

    def bind(k: int) -> np.ndarray:
        node = doc["nodes"][k]
        T = np.eye(4)
        T[:3, :3] = quat_matrix(np.array(node.get("rotation", [0.0, 0, 0, 1])))
        T[:3, 3] = node.get("translation", [0.0, 0, 0])
        return bind(parents[k]) @ T if k in parents else T

    assert len(ibm) == len(skin["joints"])
    for k, joint in enumerate(skin["joints"]):
        np.testing.assert_allclose(ibm[k] @ bind(joint), np.eye(4), atol=1e-5)
    # Every figure vertex is bound, fully, to one of them.
    prim = doc["meshes"][0]["primitives"][0]
    weights = accessor(doc, binary, prim["attributes"]["WEIGHTS_0"])
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-6)
    assert accessor(doc, binary, prim["attributes"]["JOINTS_0"]).max() < len(skin["joints"])


def test_keyframe_times_are_the_takes(run):
    _, _, doc, binary, take = run
    anim = doc["animations"][0]
    n = len(take["rotations"])
    times = take["times"] - take["times"][0] if "times" in take else np.arange(n) / float(take["rate_hz"])
    bodies = len(take["names"])
    assert sum(ch["target"]["path"] == "rotation" for ch in anim["channels"]) == bodies
    for sampler in anim["samplers"]:
        np.testing.assert_allclose(accessor(doc, binary, sampler["input"])[:, 0], times, atol=1e-5)


def test_joint_positions_equal_the_fit_played_by_hand_and_the_bvh(run):
    folder, fit, doc, binary, take = run
    n = len(take["rotations"])
    valid = take["valid"].all(axis=1)
    frames = [int(k) for k in np.flatnonzero(valid)[np.linspace(0, valid.sum() - 1, FRAMES_CHECKED).astype(int)]]
    node_of = {doc["nodes"][k]["name"]: s for s, k in sensor_nodes(doc).items()}
    got = {node_of.get(k, k): v for k, v in world_positions(doc, binary, frames).items()}
    # By hand from the fit JSON: the root joint rides on its sensor; each child's joint sits at its
    # parent's joint plus R_parent (l − c_parent). Tracker frame Z down, X forward → Y up: (x, y, z) → (x, −z, y).
    names = [str(x) for x in take["names"]]
    R, t = take["rotations"][frames], take["positions"][frames]
    up = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    c = {j["child"]: np.array(j["c"]) for j in fit["joints"]}
    l = {j["child"]: np.array(j["l"]) for j in fit["joints"]}
    joint = {fit["root"]: t[:, names.index(fit["root"])]}
    todo = [s for s in names if s != fit["root"]]
    while todo:
        for s in [s for s in todo if fit["parent"][s] in joint]:
            p = fit["parent"][s]
            joint[s] = joint[p] + R[:, names.index(p)] @ (l[s] - c.get(p, np.zeros(3)))
            todo.remove(s)
    bvh = {node_of.get(k, k): v for k, v in bvh_forward_kinematics(Bvh((folder / "take.bvh").read_text())).items()}
    for s in names:
        np.testing.assert_allclose(got[s], joint[s] @ up.T, atol=CLAIM_M, rtol=0, err_msg=s)
        np.testing.assert_allclose(got[s], bvh[s][frames] / 100.0, atol=CLAIM_M, rtol=0, err_msg=s)  # BVH is cm
    assert len(frames) == FRAMES_CHECKED and n > frames[-1]


def test_gltf_form_holds_the_same_document(run):
    folder, _, doc, binary, _ = run
    out = flockcal("export-gltf", "take.npz", "--rest", "first", "-o", "take.gltf", cwd=folder)
    assert out.returncode == 0, out.stderr
    other = json.loads((folder / "take.gltf").read_text())
    import base64

    uri = other["buffers"][0]["uri"]
    assert uri.startswith("data:application/octet-stream;base64,")
    assert base64.b64decode(uri.split(",", 1)[1]) == binary[:other["buffers"][0]["byteLength"]]
    assert [n["name"] for n in other["nodes"]] == [n["name"] for n in doc["nodes"]]


def test_wrong_extension_or_folder_is_one_line_before_the_fit(run):
    folder = run[0]
    # Tried: an .fbx name on fit --gltf and on export-gltf, and a folder that does not exist.
    for argv, says in [(["fit", "take.npz", "--gltf", "x.fbx"], "--gltf x.fbx: a glTF file ends in .glb"),
                       (["export-gltf", "take.npz", "-o", "x.fbx"], "-o x.fbx: a glTF file ends in .glb"),
                       (["fit", "take.npz", "--gltf", "nowhere/x.glb"], "the folder nowhere does not exist")]:
        out = flockcal(*argv, cwd=folder)
        assert out.returncode == 2 and says in out.stderr and "Traceback" not in out.stderr, out.stderr
        assert len(out.stderr.strip().splitlines()) == 1
    assert not (folder / "x.fbx").exists()


# --- readers that are not ours ---------------------------------------------------------------------
VALIDATOR = HERE / "gltf" / "node_modules" / "gltf-validator"


def validator_issues(path) -> dict:
    """The Khronos validator's `issues` for the file at `path` (skips the test where it is not installed)."""
    if shutil.which("node") is None or not VALIDATOR.is_dir():
        if os.environ.get("CI"):
            pytest.fail("CI installs node and the validator (.ci/run: npm install --prefix tests/gltf)")
        pytest.skip("needs node and the Khronos glTF validator: npm install --prefix tests/gltf")
    script = ("const v = require(process.argv[1]); const fs = require('fs');"
              "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2])))"
              ".then(r => console.log(JSON.stringify(r.issues)), e => { console.error(String(e)); process.exit(1); });")
    out = subprocess.run(["node", "-e", script, str(VALIDATOR), str(path)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_khronos_validator_reports_no_errors(run):
    issues = validator_issues(run[0] / "take.glb")
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]


def test_assimp_lists_the_joints_the_channels_and_the_duration(run):
    if shutil.which("assimp") is None:
        if os.environ.get("CI"):
            pytest.fail("CI installs assimp (.ci/run: apt-get install assimp-utils)")
        pytest.skip("needs assimp: apt-get install assimp-utils")
    folder, fit, _, _, take = run
    info = subprocess.run(["assimp", "info", "take.glb"], cwd=folder, capture_output=True, text=True, timeout=120)
    assert info.returncode == 0, info.stderr
    for s in fit["sensors"]:  # each body's node, named by its humanoid bone (a human tree)
        bone = fit["humanoid"][s]
        assert f"╴{bone[0].upper() + bone[1:]}\n" in info.stdout, s
    assert f"Animation Channels: {len(fit['sensors'])}" in info.stdout
    dump = subprocess.run(["assimp", "dump", "take.glb", "take.assxml", "-x"], cwd=folder, capture_output=True,
                          text=True, timeout=120)
    assert dump.returncode == 0, dump.stderr
    import re

    head = re.search(r'<Animation name="[^"]*" duration="([^"]+)" tick_cnt="([^"]+)"',
                     (folder / "take.assxml").read_text())
    seconds = float(head.group(1)) / float(head.group(2))
    span = take["times"][-1] - take["times"][0] if "times" in take else (len(take["rotations"]) - 1) / float(take["rate_hz"])
    assert seconds == pytest.approx(span, abs=1e-3)


def test_keyframe_quaternions_never_turn_the_long_way_also_across_chunks():
    """A forearm spinning three full turns: consecutive keyframes keep one hemisphere (dot ≥ 0), or
    glTF's linear interpolation would swing through the far side; the service writes the take in chunks
    (server/downloads.py) and must pick the same signs as the whole take."""
    from scipy.spatial.transform import Rotation

    from flockcal.exports.gltf import animation_rows, build_rig
    from flockcal.solver.reconstruct import Articulation, reconstruct

    n = 200
    spin = Rotation.from_rotvec(np.outer(np.linspace(0, 6 * np.pi, n), [0.3, 0.9, 0.1])).as_matrix()
    R = np.stack([np.broadcast_to(np.eye(3), (n, 3, 3)), spin], axis=1)
    t = np.zeros((n, 2, 3))
    art = Articulation(("arm", "fore"), np.array([-1, 0]), np.array([[0, 0, 0], [0.1, 0, 0.0]]),
                       np.array([[0, 0, 0], [0, 0.3, 0.0]]), np.array([0, 1]))
    rec = reconstruct(R, t, art)
    A = np.broadcast_to(np.eye(3), (2, 3, 3))
    rig = build_rig(rec.articulation, A, np.zeros(3), {})
    whole, _ = animation_rows(rec, np.eye(3), A, rig)
    assert (np.einsum("nk,nk->n", whole[1:, 1], whole[:-1, 1]) > 0).all()
    cut = 77
    first = reconstruct(R[:cut], t[:cut], art)
    rest = reconstruct(R[cut:], t[cut:], art)
    a, _ = animation_rows(first, np.eye(3), A, rig)
    b, _ = animation_rows(rest, np.eye(3), A, rig, previous=a[-1])
    np.testing.assert_array_equal(np.concatenate([a, b]), whole)
