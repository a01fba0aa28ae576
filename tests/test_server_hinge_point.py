"""A hinge's centre on its axis, live in the service (issue #36, docs/design.md §3c): a real service reads a
simulated performer (the default soft tissue, the exercise routine in an 8 s loop) from a fake tracker on
a pty; once the routine has run once, the live fits served by GET /result keep each elbow and knee within
3 mm along its axis (1 mm of margin) while the same neighbours place it. Oracle: the simulator's body.
"""

from __future__ import annotations


import httpx
import numpy as np

from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected
from service_process import wait_for

LOOP_S = 8.0  # tests/conftest.py's performer
WATCH_UNTIL_S = 3 * LOOP_S
STEADY_M = 0.003 + 0.001


def test_live_fits_keep_each_hinge_put_along_its_axis_once_the_routine_has_run(tracker, performer, tmp_path):
    assert performer.sta_mm > 0  # skin-mounted sensors, what the rule is for
    truth = {frozenset((j["child"], j["parent"])): j for j in performer.truth()["joints"] if j["hinge"]}
    names = tuple(tracker.flock.source.names)
    settings = Settings(device=tracker.device, birds=16, names=names, http_port=free_port(), data_dir=tmp_path,
                        fast_init=True, scale_inches=72, baud=921600)
    seen: dict[tuple[str, str], list[tuple[float, float]]] = {}
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Ann"}).json()["id"]
        last_frames = [-1]

        def watched() -> bool:
            """One look at the live result (the watch runs on session time); True once past WATCH_UNTIL_S."""
            r = httpx.get(f"{srv.url}/api/sessions/{sid}/result", timeout=30)
            if r.status_code != 200:
                return False
            fit = r.json()
            t = fit["frames"] / 144.0
            if fit["frames"] == last_frames[0] or t < LOOP_S:
                return False
            last_frames[0] = fit["frames"]
            for j in fit["joints"]:
                key = frozenset((j["child"], j["parent"]))
                if key not in truth or not j["hinge"] or not j.get("hinge_point"):
                    continue
                true = truth[key]
                mine = j["c"] if j["child"] == true["child"] else j["l"]
                other = true["c"] if j["child"] == true["child"] else true["l"]
                axis = np.array(true["axis_child"] if j["child"] == true["child"] else true["axis_parent"])
                along = float((np.array(mine) - np.array(other)) @ axis)
                seen.setdefault((true["child"], j["hinge_point"]["rule"]), []).append((t, along))
            return t >= WATCH_UNTIL_S

        # 180 s only stops a hung test.
        wait_for(watched, 180.0, "the session reaches its third loop", every=0.25)
        httpx.post(f"{srv.url}/api/sessions/{sid}/stop", timeout=60)
    assert {child for child, _ in seen} >= {"l_forearm", "r_forearm"}, sorted(seen)
    for (child, rule), values in seen.items():
        along = [a for _, a in values]
        assert max(along) - min(along) <= STEADY_M, (child, rule, [(round(t, 1), round(1000 * a, 1)) for t, a in values])
