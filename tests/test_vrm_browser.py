"""A VRM loader reads the service's rig as a humanoid (issue 47, item 3): pixiv's three-vrm (vendored beside
three.js, server/static/vendor/three-vrm) loads `/api/sessions/{id}/gltf` through three.js's GLTFLoader
in Debian's chromium, and its `vrm.humanoid` has every bone VRM 1.0 requires; the normalized bones sit,
in the rest, on the fitted joint centres laid out in the T-pose (computed here from the session's fit
and the humanoid's T-pose frames); and posing through the normalized humanoid moves the raw bones as
a normalized pose says (a raised-then-lowered arm, the hips moved).

A real uvicorn on loopback records a simulated 16-sensor performer; the download's VRM is also checked
against the exports of the whole take (the service streams it from its frame log) and the TRC download
likewise, and the Khronos validator reads the served file.
"""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from browser_helpers import NEEDS_CHROMIUM, launch
from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected
from service_process import wait_for
from test_outputs_vrm import REQUIRED, TRUTH, hung_from, joint_points
from test_server_downloads import same_glb, take_of

PERFORMER = "Vee"
FRAMES = 600  # 10 s at 60 Hz: every joint of the exercise routine fitted
CLAIM_M = 1e-5  # float32 node offsets summed down a limb: a few 1e-7 m; the claim, 0.01 mm
BONES = ["hips", "spine", "chest", "head", "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm",
         "rightLowerArm", "rightHand", "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg",
         "rightLowerLeg", "rightFoot"]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    data = tmp_path_factory.mktemp("vrm")
    settings = Settings(device="sim://vrm?birds=16&motion=exercise&rate=60&sta_mm=0", birds=16,
                        http_port=free_port(), data_dir=data)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": PERFORMER}).json()["id"]
        wait_for(lambda: (httpx.get(srv.url + "/api/status", timeout=10).json()["session"] or {}).get("frames", 0)
                 >= FRAMES, 120, f"{FRAMES} frames recorded")
        assert httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=60).status_code == 200
        result = httpx.get(srv.url + f"/api/sessions/{sid}/result", timeout=30).json()
        assert len(result["parent"]) == 15, result["parent"]  # one tree over the 16 sensors
        yield srv, sid, result


def test_the_download_is_the_vrm_of_the_whole_take(session):
    from flockcal.exports.gltf import gltf_bytes
    from flockcal.exports.trc import trc_text
    from flockcal.exports.vrm import vrm_meta, vrm_plan
    from test_outputs_gltf import read_glb, validator_issues

    srv, sid, result = session
    r = httpx.get(srv.url + f"/api/sessions/{sid}/gltf", timeout=60)
    assert r.status_code == 200 and r.headers["x-flockcal-vrm"] == "1.0"
    doc, _ = read_glb(r.content)
    vrm = doc["extensions"]["VRMC_vrm"]
    assert vrm["specVersion"] == "1.0" and vrm["meta"]["name"] == PERFORMER
    sensor = {k: n["extras"]["flockcal"]["sensor"] for k, n in enumerate(doc["nodes"]) if "extras" in n}
    assert {b: sensor[e["node"]] for b, e in vrm["humanoid"]["humanBones"].items()} == {b: s for s, b in TRUTH.items()}
    # The VRM of the session's whole take: its stored fit (as the service holds it, with each joint's rank:
    # the §5 JSON keeps no rank, and the finding places undetermined centres by it) and the humanoid found
    # on the whole take's sample, as `flockcal fit --gltf` does.
    cal = srv.service.sessions.result_seq(sid)[0].calibration
    take = take_of(srv.service.sessions.frames_path(sid))
    plan = vrm_plan(cal, take, meta=vrm_meta(PERFORMER), from_take=True)
    same_glb(r.content, gltf_bytes(cal, take, name=sid, vrm=plan))
    path = srv.service.sessions.frames_path(sid).parent / "served.glb"
    path.write_bytes(r.content)
    issues = validator_issues(path)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    # rest=first asks for the plain rig (the BVH's rest): no VRM, no header.
    plain = httpx.get(srv.url + f"/api/sessions/{sid}/gltf?rest=first", timeout=60)
    assert plain.status_code == 200 and "x-flockcal-vrm" not in plain.headers
    assert "extensions" not in read_glb(plain.content)[0]
    trc = httpx.get(srv.url + f"/api/sessions/{sid}/trc", timeout=60)
    assert trc.status_code == 200 and trc.text == trc_text(result, take, file_name=f"{sid}.trc")


LOAD_JS = """async ({sid, bones}) => {
  const THREE = await import('/static/vendor/three/three.module.js');
  const { GLTFLoader } = await import('/static/vendor/three/GLTFLoader.js');
  const { VRMLoaderPlugin } = await import('/static/vendor/three-vrm/three-vrm.module.min.js');
  const loader = new GLTFLoader();
  loader.register((parser) => new VRMLoaderPlugin(parser));
  const gltf = await loader.loadAsync(`/api/sessions/${sid}/gltf`);
  const vrm = gltf.userData.vrm;
  const h = vrm.humanoid;
  const at = (node) => node.getWorldPosition(new THREE.Vector3()).toArray();
  gltf.scene.updateMatrixWorld(true);
  const rest = {}, raw = {};
  for (const b of bones) {
    const n = h.getNormalizedBoneNode(b);
    if (n) { rest[b] = at(n); raw[b] = at(h.getRawBoneNode(b)); }
  }
  // A normalized pose: the left arm lowered (about +Z by -90°, the normalized frame's forward axis), the hips moved.
  h.getNormalizedBoneNode('leftUpperArm').quaternion.setFromAxisAngle(new THREE.Vector3(0, 0, 1), -Math.PI / 2);
  h.getNormalizedBoneNode('hips').position.set(0.1, 1.2, -0.3);
  vrm.update(0);
  gltf.scene.updateMatrixWorld(true);
  const posed = {};
  for (const b of Object.keys(rest)) posed[b] = at(h.getRawBoneNode(b));
  return {rest, raw, posed, humanBones: Object.keys(h.humanBones), metaVersion: vrm.meta.metaVersion,
          name: vrm.meta.name};
}"""


def tpose_layout(result: dict, frames: np.ndarray, names: list[str]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The fitted joint centres laid out in the T-pose, hips at the origin: every body turned by its T-pose
    frame (a vector v in body i's sensor frame lies along frames[i]ᵀ v in the T-pose), the hips' bone
    starting between the two hip joints. Returns ({body: its joint toward the hips (the hips: that
    middle)}, the lowest y of the skeleton, joints and leaf sensors)."""
    points = joint_points(result)
    F = {s: frames[names.index(s)] for s in names}
    hips = [s for s, b in TRUTH.items() if b == "hips"][0]
    start = np.mean([x for o, x in points[hips].items() if TRUTH[o].endswith("UpperLeg")], axis=0)
    joint = {(hips, o): F[hips].T @ (x - start) for o, x in points[hips].items()}
    where, low = {hips: np.zeros(3)}, 0.0
    for body, up in hung_from(points, hips)[1:]:
        where[body] = joint[(up, body)]
        for other, x in points[body].items():
            joint[(body, other)] = where[body] + F[body].T @ (x - points[body][up])
        if len(points[body]) == 1:  # a leaf: its sensor ends the skeleton
            low = min(low, float((where[body] + F[body].T @ -points[body][up])[1]))
        low = min(low, float(where[body][1]))
    return where, low


@pytest.mark.browser
@NEEDS_CHROMIUM
def test_three_vrm_reads_the_service_rig_as_a_humanoid(session):
    from playwright.sync_api import sync_playwright

    from flockcal.exports.vrm import take_humanoid
    from flockcal.server.downloads import FrameFile
    srv, sid, result = session
    with sync_playwright() as pw:
        browser = launch(pw)
        try:
            page = browser.new_page()
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(srv.url + "/api/status")
            got = page.evaluate(LOAD_JS, {"sid": sid, "bones": BONES})
            assert errors == []
        finally:
            browser.close()
    assert got["metaVersion"] == "1" and got["name"] == PERFORMER
    assert REQUIRED <= set(got["humanBones"]) and set(got["rest"]) == set(BONES)
    for b in BONES:  # three-vrm builds its normalized bones on the raw ones' rest positions
        np.testing.assert_allclose(got["rest"][b], got["raw"][b], atol=1e-7, err_msg=b)

    # The rest: the fitted joints in the T-pose of the humanoid's frames (the finding the service used:
    # the same calibration and the same frames, read from the session's recording).
    cal = srv.service.sessions.result_seq(sid)[0].calibration
    hum = take_humanoid(cal, FrameFile(srv.service.sessions.frames_path(sid)), from_take=True)
    where, low = tpose_layout(result, np.asarray(hum.frames), list(cal.names))
    hips = np.array(got["rest"]["hips"])
    np.testing.assert_allclose(hips, [0.0, -low, 0.0], atol=CLAIM_M)  # standing on y = 0 (VRM T-pose §1.3)
    bone_body = {b: s for s, b in TRUTH.items()}
    for b in BONES:
        np.testing.assert_allclose(np.array(got["rest"][b]) - hips, where[bone_body[b]], atol=CLAIM_M, rtol=0,
                                   err_msg=b)

    # Posing: the left arm turned as one piece about the shoulder by the normalized rotation, the rest of the
    # body carried along by the hips' move; normalized rotations are in the model's axes whatever the raw
    # nodes' own axes are.
    move = np.array([0.1, 1.2, -0.3]) - hips
    turn = Rotation.from_rotvec([0.0, 0.0, -np.pi / 2]).as_matrix()
    shoulder = np.array(got["rest"]["leftUpperArm"])
    for b in BONES:
        want = np.array(got["rest"][b]) + move
        if b in ("leftLowerArm", "leftHand"):
            want = shoulder + move + turn @ (np.array(got["rest"][b]) - shoulder)
        np.testing.assert_allclose(got["posed"][b], want, atol=CLAIM_M, rtol=0, err_msg=b)
