"""Live joint rotations (issue 34, item 2): the websocket `pose` message's `rig` drives the glTF rig the
service serves, with no maths on the client's side.

A real uvicorn on loopback records a short session from the built-in simulator and stops it (the pose is
then drawn with that session's final fit, the one `/gltf` is built from). A websocket client takes pose
messages; the rig from `/gltf?rest=sensor` is read with the test's own GLB reader
(tests/test_outputs_gltf.py, written from the glTF spec), its nodes set from the message's quaternions
and root position, and its joint world positions must equal the message's `joints` within 0.1 mm, the
documented claim (docs/outputs.md), once turned from the rig's Y-up frame to the tracker's (+Z down).
"""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import numpy as np
import pytest
import websockets

from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected
from service_process import wait_for
from test_outputs_gltf import accessor, node_parents, quat_matrix, read_glb, validator_issues

CLAIM_M = 1e-4
RATE_HZ = 15


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    settings = Settings(device="sim://rig?birds=6&model=linkage&motion=exercise&rate=60", birds=6,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("rig"))
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Rig"}).json()["id"]
        # 60 s only stops a hung test; enough is judged on the session's frames.
        wait_for(lambda: (httpx.get(srv.url + "/api/status", timeout=10).json()["session"] or {}).get("frames", 0) >= 240,
                 60, "the session holds 240 frames", every=0.2)
        assert httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30).status_code == 200
        yield srv, sid


async def poses(url: str, count: int) -> list[dict]:
    """`count` pose messages that carry a rig, at the client's rate (a deadline only stops a hung test)."""
    got = []
    async with websockets.connect(url) as ws:
        await ws.send(json.dumps({"type": "subscribe", "rate_hz": RATE_HZ, "content": ["pose"]}))
        end = time.monotonic() + 60
        while len(got) < count and time.monotonic() < end:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 30))
            if msg["type"] == "pose" and "rig" in msg["pose"]:
                got.append(msg["pose"])
    return got


def rig_positions(doc: dict, binary: bytes, rig: dict) -> dict[str, np.ndarray]:
    """Node origins with the message's rotations and root translation (other nodes keep their TRS)."""
    nodes = doc["nodes"]
    parents = node_parents(doc)
    root = [k for k, n in enumerate(nodes) if k not in parents and "mesh" not in n][0]
    world: dict[int, np.ndarray] = {}

    def place(k: int) -> np.ndarray:
        if k not in world:
            node = nodes[k]
            T = np.eye(4)
            T[:3, 3] = rig["root"] if k == root else node["translation"]
            T[:3, :3] = quat_matrix(np.array(rig["rotations"].get(node["name"], [0.0, 0, 0, 1])))
            world[k] = place(parents[k]) @ T if k in parents else T
        return world[k]

    return {n["name"]: place(k)[:3, 3] for k, n in enumerate(nodes) if "mesh" not in n}


def test_live_rotations_drive_the_served_rig_to_the_pose_joints(stopped):
    srv, sid = stopped
    r = httpx.get(srv.url + f"/api/sessions/{sid}/gltf?rest=sensor", timeout=60)
    assert r.status_code == 200
    doc, binary = read_glb(r.content)
    assert doc["extras"]["flockcal"]["rest"] == "sensor"
    msgs = asyncio.run(poses(srv.url.replace("http://", "ws://") + "/ws/live", 3))
    assert len(msgs) == 3
    # Y-up rig → tracker frame (+X forward, +Z down): the rig's (x, y, z) is the tracker's (x, z, −y).
    to_tracker = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    for pose in msgs:
        rig = pose["rig"]
        assert rig["up"] == "-z" and rig["rest"] == "sensor"
        # Whose fit drew it: the stopped session's stored one (no live fit number), the one /gltf serves.
        assert rig["session"] == sid and rig["fit_seq"] is None
        assert set(rig["rotations"]) == {n["name"] for n in doc["nodes"][:len(rig["rotations"])]}
        got = rig_positions(doc, binary, rig)
        for joint in pose["joints"]:
            if joint["kind"] == "end":
                continue  # a leaf's sensor: the rig's end node, checked through its body below
            np.testing.assert_allclose(to_tracker @ got[joint["name"]], joint["p"], atol=CLAIM_M, rtol=0,
                                       err_msg=joint["name"])
        for joint in [j for j in pose["joints"] if j["kind"] == "end"]:
            end = joint["name"].removesuffix(" sensor") + "_end"
            np.testing.assert_allclose(to_tracker @ got[end], joint["p"], atol=CLAIM_M, rtol=0, err_msg=end)
    # The rig's rest pose is its animation's: keyframe 0 is what the message would say at frame 0, which
    # the reader checks through the times and rotations being there at all.
    assert accessor(doc, binary, doc["animations"][0]["samplers"][0]["input"]).shape[0] > 1


def test_the_pages_rig_is_the_download_without_its_animation(stopped, tmp_path):
    """`animation=false` (what the dashboard and the kiosk load, docs/dashboard.md): the same rig — nodes,
    skin, figure, their numbers — without the take's keyframes, and valid glTF on its own."""
    srv, sid = stopped
    full = httpx.get(srv.url + f"/api/sessions/{sid}/gltf?rest=sensor", timeout=60)
    bare = httpx.get(srv.url + f"/api/sessions/{sid}/gltf?rest=sensor&animation=false", timeout=60)
    assert full.status_code == bare.status_code == 200
    # The fit's number the pages match with the pose's rig.fit_seq: "final" for a stopped session's result.
    assert full.headers["x-flockcal-fit-seq"] == bare.headers["x-flockcal-fit-seq"] == "final"
    (doc, binary), (rig, rig_binary) = read_glb(full.content), read_glb(bare.content)
    assert "animations" not in rig and len(doc["animations"]) == 1
    for key in ("scene", "scenes", "nodes", "meshes", "materials", "skins", "extras"):
        assert rig[key] == doc[key], key
    prim = rig["meshes"][0]["primitives"][0]
    for k in [*prim["attributes"].values(), prim["indices"], rig["skins"][0]["inverseBindMatrices"]]:
        np.testing.assert_array_equal(accessor(rig, rig_binary, k), accessor(doc, binary, k))
    assert len(bare.content) < len(full.content) - 16 * len(rig["nodes"])  # no keyframes carried
    # Tried: a value that is not a boolean is refused like any bad query.
    assert httpx.get(srv.url + f"/api/sessions/{sid}/gltf?animation=maybe", timeout=60).status_code == 422
    (tmp_path / "rig.glb").write_bytes(bare.content)
    issues = validator_issues(tmp_path / "rig.glb")
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
