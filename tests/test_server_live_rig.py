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
from test_outputs_gltf import accessor, node_parents, quat_matrix, read_glb

CLAIM_M = 1e-4
RATE_HZ = 15


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    settings = Settings(device="sim://rig?birds=6&model=linkage&motion=exercise&rate=60", birds=6,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("rig"))
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Rig"}).json()["id"]
        deadline = time.monotonic() + 60  # only stops a hung test; enough is judged on the session's frames
        while time.monotonic() < deadline:
            if (httpx.get(srv.url + "/api/status", timeout=10).json()["session"] or {}).get("frames", 0) >= 240:
                break
            time.sleep(0.2)
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
