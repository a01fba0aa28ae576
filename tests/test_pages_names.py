"""The pages name joints as the service does: the joint-name table is kept once, in flockcal/names.py, and
the service serves it to the pages as /static/names.js, which static/common.js's `jointLabel` imports
(issue 33). Checked in a real chromium against a real service on loopback."""

from __future__ import annotations

import httpx
import pytest

from browser_helpers import NEEDS_CHROMIUM
from flockcal.names import joint_name
from flockcal.server.settings import Settings
from flockcal.simulator.body import human
from server_helpers import ServerThread, free_port

pytestmark = [pytest.mark.browser, NEEDS_CHROMIUM]

TOKEN = "names-secret-1"
# Pairs (child, parent) as fits name them: the simulator's human both ways round, mocap-style names,
# and bodies the table does not know.
MOCAP = [("LeftForeArm", "LeftArm"), ("RightUpLeg", "Hips"), ("RightLeg", "RightUpLeg"), ("Spine", "Hips"),
         ("Head", "Neck"), ("LeftToeBase", "LeftFoot"), ("r_shank", "r_thigh"), ("bird3", "bird2"), ("bird1", None)]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    settings = Settings(device="sim://names?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("names"), token=TOKEN)
    with ServerThread(settings) as srv:
        yield srv


def test_the_service_serves_the_table_as_a_script_and_the_page_names_joints_as_the_service(server, browser):
    r = httpx.get(server.url + "/static/names.js")
    assert r.status_code == 200 and "javascript" in r.headers["content-type"], r.text
    model = human()
    pairs = [(model.names[i], model.names[p]) for i, p in enumerate(model.parent) if p >= 0]
    pairs += [(b, a) for a, b in pairs] + MOCAP
    page = browser.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(f"{server.url}/?token={TOKEN}")
        labels = page.evaluate("async (pairs) => { const m = await import('/static/common.js');"
                               " return pairs.map(([c, p]) => m.jointLabel(c, p)); }", [list(p) for p in pairs])
    finally:
        page.close()
    assert labels == [joint_name(c, p) for c, p in pairs]
    # Written out, not read from the table: what a person calls these joints.
    by_pair = dict(zip(pairs, labels))
    assert by_pair[("l_forearm", "l_upper_arm")] == by_pair[("l_upper_arm", "l_forearm")] == "left elbow"
    assert by_pair[("RightUpLeg", "Hips")] == "right hip" and by_pair[("bird3", "bird2")] == "bird 2–bird 3"
    assert not errors, errors
